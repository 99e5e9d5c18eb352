"""Shared fixtures: small random models (no downloads) and the shipped example photograph."""
from pathlib import Path

import pytest
import torch

EXAMPLE_IMAGE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def tiny_model(seed: int = 0, dynamic: bool = False, active_dit: bool = False):
    """A random tiny Diff4SplatModel.

    ``dynamic`` perturbs the zero-initialised deformation head; ``active_dit`` perturbs the DiT's
    zero-initialised layers (final layer, adaLN gates, camera and cross-attention projections), so its
    velocity is non-zero and depends on every input.
    """
    from models.bundle import Diff4SplatConfig, Diff4SplatModel

    model = Diff4SplatModel.random(Diff4SplatConfig(), seed=seed).eval()
    if active_dit:
        g = torch.Generator().manual_seed(seed + 2)
        with torch.no_grad():
            for p in model.dit.parameters():
                if p.abs().sum() == 0:
                    p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    if dynamic:
        g = torch.Generator().manual_seed(seed + 1)
        conv = model.ldrm.deformation.out_conv
        with torch.no_grad():
            conv.weight.copy_(torch.randn(conv.weight.shape, generator=g) * 0.5)
            conv.bias.copy_(torch.randn(conv.bias.shape, generator=g) * 0.1)
    return model


@pytest.fixture(scope="session")
def dynamic_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "dynamic"
    tiny_model(seed=0, dynamic=True).save_pretrained(path)
    return path
