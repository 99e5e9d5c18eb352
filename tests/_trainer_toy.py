"""A toy regression problem for trainer tests (importable by spawned processes)."""
import math

import torch
from torch import nn
from torch.utils.data import Dataset


class ToyData(Dataset):
    """y = A x + noise; items depend only on (index, epoch) — per-epoch randomness like ClipDataset."""

    def __init__(self, n=32, nan_at=(), seed=0):
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 8, generator=g)
        self.A = torch.randn(8, 3, generator=g)
        self.nan_at = set(nan_at)
        self.epoch = 0

    def set_epoch(self, epoch):
        self.epoch = epoch

    def __len__(self):
        return self.x.shape[0]

    def __getitem__(self, i):
        g = torch.Generator().manual_seed(1000 * self.epoch + i)
        x = self.x[i] + 0.01 * torch.randn(8, generator=g)
        y = x @ self.A
        if i in self.nan_at:
            y = y * math.nan
        return {"x": x, "y": y}


class ToyModel(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(8, 16), nn.Dropout(0.1), nn.GELU(), nn.Linear(16, 3))
        self.frozen = nn.Linear(3, 3)
        self.frozen.requires_grad_(False)

    def forward(self, x):
        return self.frozen(self.net(x))


def toy_step(model, batch, generator):
    noise = torch.randn(batch["x"].shape, generator=generator) * 0.01  # uses the step generator
    pred = model(batch["x"] + noise)
    return {"loss": ((pred - batch["y"]) ** 2).mean(), "mae": (pred - batch["y"]).abs().mean()}
