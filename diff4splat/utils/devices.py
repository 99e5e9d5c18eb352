"""Which device runs what: the one rule every module follows, and the helpers that apply it.

The rule (docs/DESIGN.md, "Devices"):

- Every tensor is created on the device of the inputs it belongs with (``device=x.device``, ``x.new_*``,
  ``torch.*_like``). A factory call without ``device=`` says why on its line (``# device: …``); the test suite
  checks this.
- numpy and the numba kernels see CPU tensors only: a ``.numpy()`` follows a ``.cpu()`` in the same
  expression, or the line says why it is already on the CPU (``# device: …``).
- Random draws use a CPU ``torch.Generator`` and are moved afterwards, so a seed gives the same numbers on
  every device (diffusers' ``randn_tensor`` does the same).
- Commands take ``--device`` (default ``auto``: the first CUDA GPU when torch sees one, else the CPU);
  :func:`resolve_device` turns it into a ``torch.device`` or one clear error naming the flag.

CPU thread pools: torch, its MKL and the numba kernels (threading layer ``omp``) share one OpenMP runtime, the
libgomp that torch loads. By default its idle threads spin for up to 300 000 iterations (milliseconds) after
every parallel region, which is free while one process has the machine; two runs at once each spin on the cores
the other one needs (two ``generate`` runs at once on 2 cores took 3.4× one alone; 1.75–1.9× with passive waiting,
docs/benchmarks.md, "Concurrent runs"). :data:`THREAD_ENV` makes them sleep instead (``OMP_WAIT_POLICY=PASSIVE``).
libgomp reads its environment once, when it is loaded, so this module sets it *before* importing torch, and
``diff4splat`` imports this module first; a program that imported torch before diff4splat keeps the runtime it had. The
thread counts stay torch's, numba's and OpenCV's defaults: the processors this process may run on
(``os.sched_getaffinity``: ``taskset -c 0`` gives one thread each).
"""
from __future__ import annotations

import contextlib
import functools
import os
import time
from collections.abc import Callable, Iterator, MutableMapping

THREAD_ENV = {"OMP_WAIT_POLICY": "PASSIVE"}
"""Environment :func:`set_thread_env` gives the OpenMP runtime (module docstring): idle threads sleep rather than
spin, so concurrent runs share the cores."""
USER_THREAD_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
"""Variables that mean the user chose the waiting policy: when any is set, :func:`set_thread_env` sets nothing
(``GOMP_SPINCOUNT=300000`` restores libgomp's default spinning)."""


def set_thread_env(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """Put :data:`THREAD_ENV` into ``environ`` unless a :data:`USER_THREAD_VARIABLES` variable is set there.

    Takes effect only for an OpenMP runtime loaded afterwards (this module calls it before importing torch).

    Returns:
        The variables it set (empty when the user chose).
    """
    if any(name in environ for name in USER_THREAD_VARIABLES):
        return {}
    environ.update(THREAD_ENV)
    return dict(THREAD_ENV)


set_thread_env()  # before torch loads libgomp (module docstring)

import torch  # noqa: E402  (after set_thread_env)

__all__ = ["AUTO", "DEVICE_HELP", "THREAD_ENV", "USER_THREAD_VARIABLES", "set_thread_env", "resolve_device",
           "synchronize", "Stopwatch", "autocast_off", "full_precision", "host_values"]

AUTO = "auto"
"""The device name that means "CUDA when present, else the CPU" (every command's ``--device`` default)."""
DEVICE_HELP = "torch device: auto (CUDA when present, else cpu), cpu, cuda, cuda:N (default: auto)"
"""The ``--device`` help text shared by every command."""


def resolve_device(device: str | torch.device | None = AUTO, name: str = "device") -> torch.device:
    """The ``torch.device`` that ``device`` names, checked to be usable on this machine.

    Args:
        device: ``"auto"`` or None (``cuda`` when ``torch.cuda.is_available()``, else ``cpu``), a device
            string (``cpu``, ``cuda``, ``cuda:1``, ``mps``, …) or a ``torch.device``.
        name: what the caller's user calls it (``--device``, ``trainer.device``), used in the message.

    Returns:
        The device; ``cuda`` without an index stays index-less (the current CUDA device).

    Raises:
        ValueError: not a device name, or a device this machine does not have (a CPU-only build of
            torch, no GPU, ``cuda:N`` beyond the GPU count, an unavailable backend), naming ``name``.
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
    """Wait for the work queued on ``device`` (CUDA kernels run asynchronously), so that a wall-clock
    reading after it includes that work; nothing on the CPU."""
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


class Stopwatch:
    """Wall-clock laps that include the device's queued work (:func:`synchronize` before each reading).

    Args:
        device: the device whose work the laps time.

    Attributes:
        high_water: on CUDA, ``torch.cuda.max_memory_allocated`` (bytes) read at each lap: the device's peak
            since the process started or the caller's last ``torch.cuda.reset_peak_memory_stats``, so the lap at
            which it last grew is the stage that set the peak. Read only, never reset here. Empty elsewhere.
    """

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
    """A region where ``torch.autocast`` is disabled (CPU, and CUDA when available): what runs inside computes in
    its inputs' dtypes. For geometry under a bfloat16 autocast region (8-bit mantissa): ray directions, depths
    and SSIM variances would otherwise be rounded to ~0.4 %."""
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
    """``x`` detached on the CPU in a dtype numpy has: bfloat16 widened to float32 (numpy has no bfloat16, and
    ``.numpy()`` raised "unsupported ScalarType BFloat16"); every other dtype kept. What writers call before
    ``.numpy()`` (numpy sees CPU tensors only: docs/DESIGN.md, "Devices").

    Args:
        x: a tensor of any shape, dtype and device.

    Returns:
        The same shape and values on the CPU, detached; float32 if ``x`` was bfloat16, else ``x``'s dtype (no data copy
        when ``x`` is already a CPU tensor of such a dtype).
    """
    x = x.detach().cpu()
    return x.float() if x.dtype == torch.bfloat16 else x


ONEDNN_NAN_LEAK = "uxlfoundation/oneDNN#5717"
"""The oneDNN bug :func:`bf16_nan_leaks` looks for (fixed by oneDNN PR #5723, 2026-07-31)."""


def bf16_nan_leaks(mm: Callable = torch.mm, bmm: Callable = torch.bmm) -> dict[str, bool]:
    """Whether this CPU's bfloat16 matmuls let NaN from other rows into a row that holds none: oneDNN's Intel AMX
    kernel (:data:`ONEDNN_NAN_LEAK`) reads past a row's K columns when K > 32 and K % 32 != 0. The bug's own case:
    a (16, 32, 33) @ (16, 33, 64) ``bmm`` and a (64, 33) @ (33, 64) ``mm``, row 0 of each left factor finite and
    every other row NaN; row 0 of each product must come out finite.

    Measured: both leak on an Intel Xeon host with AMX (torch 2.11.0, oneDNN v3.10.2) under oneDNN's default
    instructions, and neither with ``ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16`` (benchmarks/amx_nan_check.py); neither
    on the AMD EPYC machines here.

    Args:
        mm, bmm: the products to check (torch's by default; tests pass others).

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
    """What to tell someone who computes in bfloat16 on this CPU, or None: a message when :func:`bf16_nan_leaks`
    finds the leak here (checked once per process, two small matmuls). The bfloat16 Wan backbone test, which
    trains on the CPU, had a NaN loss in the test suite on two such Xeon hosts and passed on a third; whether the
    leak caused it is not established."""
    leaks = [k for k, v in bf16_nan_leaks().items() if v]
    if not leaks:
        return None
    return (f"this CPU's bfloat16 {'/'.join(leaks)} lets NaN from one row into others (Intel AMX, "
            f"{ONEDNN_NAN_LEAK}): bfloat16 losses or outputs may turn NaN here; set "
            f"ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16 before starting Python, or compute in float32")
