"""Where one training process runs: its device (one GPU per torchrun process), whether its step autocasts to
bfloat16, and its rank in the process group. Used by :class:`training.trainer.Trainer` and ``training.train``."""
from __future__ import annotations

import os

import torch
import torch.distributed as dist

from diff4splat.utils.devices import AUTO, resolve_device

__all__ = ["resolve_bf16", "training_device", "dist_info"]


def resolve_bf16(bf16: bool | None, device: str | torch.device) -> bool:
    """Whether a trainer on ``device`` autocasts to bfloat16: ``bf16`` when it is set, else (None = auto)
    True for a CUDA device and False for any other (the CPU's bfloat16 matmuls are slower than float32)."""
    return torch.device(device).type == "cuda" if bf16 is None else bool(bf16)


def training_device(device: str | torch.device | None = AUTO, name: str = "trainer.device") -> torch.device:
    """The device one training process runs on.

    Args:
        device: as :func:`diff4splat.utils.devices.resolve_device` takes it (``auto``/None, ``cpu``, ``cuda``,
            ``cuda:N``, a ``torch.device``).
        name: what the user calls the setting, for the error message.

    Returns:
        The device, with a CUDA index: ``auto``/``cuda`` become ``cuda:$LOCAL_RANK`` under torchrun (one GPU
        per process), else the current CUDA device.

    Raises:
        ValueError: not a device, or one this machine lacks (no GPU, LOCAL_RANK ≥ the GPU count), naming ``name``.
    """
    dev = resolve_device(device, name)
    if dev.type == "cuda" and dev.index is None:
        local = os.environ.get("LOCAL_RANK")
        dev = resolve_device(f"cuda:{int(local) if local is not None else torch.cuda.current_device()}", name)
    return dev


def dist_info() -> tuple[int, int, bool]:
    """(rank, world size, whether torch.distributed is initialised): (0, 1, False) in a single process."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), True
    return 0, 1, False
