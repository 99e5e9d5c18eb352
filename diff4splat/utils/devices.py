"""Which device runs what, and the helpers that apply the rule (docs/DESIGN.md, "Devices"): tensors are created on
their inputs' device (a factory call without ``device=`` says why, ``# device: …``); numpy and numba see CPU tensors
only; random draws use a CPU generator; ``--device auto`` is CUDA when present, else the CPU (:func:`resolve_device`).

CPU threads: torch's libgomp, shared with MKL and numba, spins idle threads, starving concurrent runs;
:data:`THREAD_ENV` makes them sleep. CPU memory: :data:`ALLOCATOR_ENV` backs torch's large CPU tensors with
transparent huge pages (docs/DESIGN.md, "Devices"). libgomp and torch's allocator read their environment once, when
loaded, so this module sets both before importing torch, and ``diff4splat`` imports this module first.
"""
from __future__ import annotations

import contextlib
import functools
import os
import time
from collections.abc import Callable, Iterator, MutableMapping

THREAD_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
"""Environment :func:`set_thread_env` gives the OpenMP runtime: idle threads sleep rather than spin."""
USER_THREAD_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
"""Variables that mean the user chose the waiting policy: when any is set, :func:`set_thread_env` sets nothing."""


def set_thread_env(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """Put :data:`THREAD_ENV` into ``environ`` unless a :data:`USER_THREAD_VARIABLES` variable is set there; returns the
    variables it set. Affects only an OpenMP runtime loaded afterwards."""
    if any(name in environ for name in USER_THREAD_VARIABLES):
        return {}
    environ.update(THREAD_ENV)
    return dict(THREAD_ENV)


ALLOCATOR_ENV = {"THP_MEM_ALLOC_ENABLE": "1"}
"""Environment :func:`set_allocator_env` gives torch's CPU allocator: tensors of 2 MiB and more aligned to 2 MiB and
advised as transparent huge pages (``madvise(MADV_HUGEPAGE)``; no effect where the kernel's THP mode is "never")."""


def set_allocator_env(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """Put each :data:`ALLOCATOR_ENV` variable the user has not set into ``environ``; returns the variables it set.
    Affects only a torch loaded afterwards."""
    chosen = {name: value for name, value in ALLOCATOR_ENV.items() if name not in environ}
    environ.update(chosen)
    return chosen


set_thread_env()  # before torch loads libgomp (module docstring)
set_allocator_env()  # before torch's allocator reads it

import torch  # noqa: E402  (after set_thread_env)

__all__ = ["AUTO", "DEVICE_HELP", "THREAD_ENV", "USER_THREAD_VARIABLES", "set_thread_env", "ALLOCATOR_ENV",
           "set_allocator_env", "resolve_device",
           "synchronize", "Stopwatch", "autocast_off", "full_precision", "host_values"]

AUTO = "auto"
"""The device name that means "CUDA when present, else the CPU" (every command's ``--device`` default)."""
DEVICE_HELP = "torch device: auto (CUDA when present, else cpu), cpu, cuda, cuda:N (default: auto)"
"""The ``--device`` help text shared by every command."""


def resolve_device(device: str | torch.device | None = AUTO, name: str = "device") -> torch.device:
    """The usable ``torch.device`` that ``device`` names: ``"auto"`` or None (``cuda`` when available, else ``cpu``), a
    device string or a ``torch.device``; ``cuda`` without an index stays index-less. ``name`` is the flag or key the
    message names.

    Raises:
        ValueError: not a device name, or a device this machine does not have.
    """
    if device is None or (isinstance(device, str) and device.strip().lower() == AUTO):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"{name}: {device!r} is not a torch device (auto, cpu, cuda, cuda:1, …): {e}") from None
    if dev.type == "cpu":
        return dev
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "torch built without CUDA" if torch.version.cuda is None else "no GPU found"
            raise ValueError(f"{name}: {device} is not available ({why}); use cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{name}: {device} is not available (this machine has "
                             f"{torch.cuda.device_count()} GPU(s): cuda:0 … cuda:{torch.cuda.device_count() - 1})")
        return dev
    backend = torch.backends.mps if dev.type == "mps" else getattr(torch, dev.type, None)
    if backend is None or not getattr(backend, "is_available", lambda: False)():
        raise ValueError(f"{name}: {device} is not available on this machine; use cpu")
    return dev


def synchronize(device: str | torch.device) -> None:
    """Wait for the work queued on a CUDA ``device`` (so a wall-clock reading includes it); nothing elsewhere."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


class Stopwatch:
    """Wall-clock laps that include the device's queued work (:func:`synchronize` before each reading); ``high_water``:
    on CUDA, ``torch.cuda.max_memory_allocated`` (bytes) at each lap (never reset here), else empty."""

    def __init__(self, device: str | torch.device):
        self.device = torch.device(device)
        self.high_water: list[int] = []
        synchronize(self.device)
        self._last = time.perf_counter()

    def lap(self) -> float:
        """Seconds since the previous lap (or since construction)."""
        synchronize(self.device)
        now = time.perf_counter()
        elapsed, self._last = now - self._last, now
        if self.device.type == "cuda":
            self.high_water.append(torch.cuda.max_memory_allocated(self.device))
        return elapsed


@contextlib.contextmanager
def autocast_off() -> Iterator[None]:
    """A region where ``torch.autocast`` is disabled (CPU, and CUDA when available), so geometry computes in its inputs'
    dtypes rather than bfloat16."""
    with contextlib.ExitStack() as stack:
        stack.enter_context(torch.autocast("cpu", enabled=False))
        if torch.cuda.is_available():
            stack.enter_context(torch.autocast("cuda", enabled=False))
        yield


def full_precision(fn: Callable) -> Callable:
    """Decorator: run ``fn`` inside :func:`autocast_off`."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with autocast_off():
            return fn(*args, **kwargs)

    return wrapper


def host_values(x: torch.Tensor) -> torch.Tensor:
    """``x`` detached on the CPU in a dtype numpy has: bfloat16 widened to float32, every other dtype kept (no copy for
    a CPU tensor of such a dtype)."""
    x = x.detach().cpu()
    return x.float() if x.dtype == torch.bfloat16 else x


ONEDNN_NAN_LEAK = "uxlfoundation/oneDNN#5717"
"""The oneDNN bug :func:`bf16_nan_leaks` looks for."""


def bf16_nan_leaks(mm: Callable = torch.mm, bmm: Callable = torch.bmm) -> dict[str, bool]:
    """Whether this CPU's bfloat16 matmuls let NaN from other rows into a row that holds none (oneDNN's AMX kernel,
    :data:`ONEDNN_NAN_LEAK`, when K > 32 and K % 32 != 0): a (16, 32, 33) @ (16, 33, 64) ``bmm`` and a
    (64, 33) @ (33, 64) ``mm`` with only row 0 finite must give a finite row 0. ``mm``, ``bmm``: the products checked.

    Returns:
        ``{"bmm": leaked, "mm": leaked}``.
    """
    cpu, bf16, nan = torch.device("cpu"), torch.bfloat16, float("nan")  # the CPU's kernels are what is checked
    g = torch.Generator().manual_seed(0)
    a = torch.full((16, 32, 33), nan, dtype=bf16, device=cpu)
    a[:, 0] = torch.randn(16, 33, generator=g, device=cpu).to(bf16)
    b = torch.randn(16, 33, 64, generator=g, device=cpu).to(bf16)
    m = torch.full((64, 33), nan, dtype=bf16, device=cpu)
    m[0] = torch.randn(33, generator=g, device=cpu).to(bf16)
    w = torch.randn(33, 64, generator=g, device=cpu).to(bf16)
    return {"bmm": not bool(torch.isfinite(bmm(a, b)[:, 0]).all()),
            "mm": not bool(torch.isfinite(mm(m, w)[0]).all())}


@functools.cache
def cpu_bf16_warning() -> str | None:
    """A warning for bfloat16 compute on this CPU when :func:`bf16_nan_leaks` finds the leak (checked once per
    process), else None."""
    leaks = [k for k, v in bf16_nan_leaks().items() if v]
    if not leaks:
        return None
    return (f"this CPU's bfloat16 {'/'.join(leaks)} lets NaN from one row into others (Intel AMX, "
            f"{ONEDNN_NAN_LEAK}): bfloat16 losses or outputs may turn NaN here; set "
            f"ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16 before starting Python, or compute in float32")
