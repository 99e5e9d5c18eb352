"""A toy regression problem for trainer tests (importable by spawned processes), and a launcher of two ranks
(env:// rendezvous, as under torchrun) for the distributed tests."""
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest
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
    """A small MLP with a frozen output layer. ``dropout`` draws from the device's own RNG (0 for runs that must
    match across devices); ``fsdp_units`` lists the layers FSDP shards one by one (as TrainingModule's blocks)."""

    def __init__(self, dropout=0.1):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(8, 16), nn.Dropout(dropout), nn.GELU(), nn.Linear(16, 3))
        self.frozen = nn.Linear(3, 3)
        self.frozen.requires_grad_(False)

    def forward(self, x):
        return self.frozen(self.net(x))

    def fsdp_units(self):
        return [self.net[0], self.net[3]]


def toy_step(model, batch, generator):
    x = batch["x"]
    # the step generator is on the CPU: draw there, then move (the same numbers on every device)
    noise = torch.randn(x.shape, generator=generator, device=generator.device).to(x) * 0.01
    pred = model(x + noise)
    return {"loss": ((pred - batch["y"]) ** 2).mean(), "mae": (pred - batch["y"]).abs().mean()}


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fsdp_stage_script(config: os.PathLike | str, checks: str) -> str:
    """A rank's script for :func:`run_two_ranks`: ``training.train`` on ``config`` with ``--strategy fsdp`` on the CPU,
    keeping what ``build_training`` built (``trainer``, ``model``), then ``checks`` (Python lines at the left margin
    that may use them and ``FSDPModule``), exiting with the run's code."""
    head = f"""import sys
import training.train as train
from torch.distributed.fsdp import FSDPModule
built = []
real = train.build_training
train.build_training = lambda stage, seed=None: built.append(real(stage, seed)) or built[-1]
code = train.main(["--config", {str(config)!r}, "--strategy", "fsdp", "--device", "cpu", "--quiet"])
trainer, model, _ = built[0]
"""
    return head + textwrap.dedent(checks) + "sys.exit(code)\n"


def run_two_ranks(script: str, attempts: int = 3, timeout: float = 120, fresh: tuple[Path, ...] = ()) -> None:
    """Start ranks 0 and 1 of ``script`` (env:// rendezvous, as under torchrun) and wait for both.

    The port is free when picked but another process may take it before rank 0's store binds it; on
    "address already in use" both ranks are stopped and the run is repeated with a fresh port. The same retry
    covers a rank that aborts in C++ with "terminate called without an active exception" and no Python traceback:
    Gloo's worker threads torn down with the interpreter (seen once in 2,000 CI tests on a loaded 2-core machine;
    pytorch/pytorch#179291 describes the race) — not an error of the code under test, which raises a traceback.

    ``fresh``: the folders the script writes (its run folder). They are removed before a repeated attempt, which
    must start where the first did: a run repeated into the first attempt's folder appended its metrics to the
    first attempt's (steps 1…4 twice, seen once in CI).
    """
    for attempt in range(attempts):
        for folder in fresh if attempt else ():
            shutil.rmtree(folder, ignore_errors=True)
        port, procs, logs = free_port(), [], []
        for rank in range(2):
            env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "WORLD_SIZE": "2",
                   "RANK": str(rank), "LOCAL_RANK": str(rank), "OMP_NUM_THREADS": "1"}
            logs.append(tempfile.TemporaryFile("w+"))  # a file, not a pipe: a chatty rank never blocks
            procs.append(subprocess.Popen([sys.executable, "-c", script], env=env, stderr=logs[-1], text=True))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(p.poll() is None for p in procs):
            if any(p.poll() not in (None, 0) for p in procs):  # one rank failed: the other would wait forever
                for p in procs:
                    if p.poll() is None:
                        p.kill()
            time.sleep(0.05)
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
        errs = []
        for log in logs:
            log.seek(0)
            errs.append(log.read())
            log.close()
        if all(p.returncode == 0 for p in procs):
            return
        port_taken = any("address already in use" in e.lower() or "eaddrinuse" in e.lower() for e in errs)
        teardown = any(p.returncode == -signal.SIGABRT and "terminate called without an active exception" in e
                       and "Traceback" not in e for p, e in zip(procs, errs, strict=True))
        if not (port_taken or teardown) or attempt == attempts - 1:
            pytest.fail(f"distributed run failed (attempt {attempt + 1}):\n" + "\n".join(errs))
