"""Model CPU offload: networks live in (pinned) CPU memory and visit the compute device only while they run.

A paper-size model does not fit one GPU's memory budget whole: in bfloat16 the DiT alone holds 23.8 GB and the
T5-XXL-shaped text encoder 9.5 GB (docs/benchmarks.md, "GPU"). With :class:`ModelOffload` at most one network is
on the device at a time — the one that runs now — so the peak is the largest network plus its activations
instead of the sum (diffusers' ``enable_model_cpu_offload`` does the same with hooks).

Inference only: the CPU copy of each weight is the master; moving a network off the device points its
parameters back at that copy (no device-to-host copy), so weights changed on the device are lost. On CUDA the CPU
copies are pinned once, and moving on is an asynchronous host-to-device copy on the current stream.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["ModelOffload"]


class ModelOffload:
    """Keep the networks of ``modules`` on the CPU and move one at a time to ``device`` (see the module docstring).

    Args:
        modules: name → network; each is moved to the CPU here (in place) and stays there between calls.
        device: the compute device. On the CPU nothing ever moves.
        pin: pin the CPU copies when ``device`` is CUDA (faster, asynchronous copies; needs that much
            page-locked host memory).

    Attributes:
        resident: the name of the network now on ``device``, or None.
    """

    def __init__(self, modules: dict[str, nn.Module], device: str | torch.device, *, pin: bool = True):
        self.device = torch.device(device)
        self.modules = dict(modules)
        self.resident: str | None = None
        self._home: dict[str, list[torch.Tensor]] = {}
        for name, module in self.modules.items():
            module.to("cpu")
            tensors = list(self._tensors(module))
            if pin and self.device.type == "cuda":
                for t in tensors:
                    t.data = t.data.pin_memory()
            self._home[name] = [t.data for t in tensors]

    @staticmethod
    def _tensors(module: nn.Module) -> Iterator[torch.Tensor]:
        yield from module.parameters()
        yield from (b for b in module.buffers() if b is not None)

    @contextmanager
    def use(self, name: str) -> Iterator[nn.Module]:
        """The network ``name``, on the device for the body of the ``with``; the network that was resident
        before goes back to the CPU first. It stays resident afterwards (a sampler's next step reuses it),
        until another network is used or :meth:`release` is called.

        Raises:
            KeyError: ``name`` is not one of the modules.
        """
        module = self.modules[name]
        if self.resident != name and self.device.type != "cpu":
            self.release()
            for t, home in zip(self._tensors(module), self._home[name], strict=True):
                t.data = home.to(self.device, non_blocking=True)
            self.resident = name
        yield module

    def release(self) -> None:
        """Move the resident network back to the CPU (its pinned master copy); frees its device memory."""
        if self.resident is None:
            return
        module = self.modules[self.resident]
        for t, home in zip(self._tensors(module), self._home[self.resident], strict=True):
            t.data = home
        self.resident = None
