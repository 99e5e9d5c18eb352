"""How every numba kernel of the package is compiled and launched: :data:`KERNEL` (``njit`` with the disk cache and
NumPy's error model), the threading layer shared with torch, and :func:`threads`.

Imported only by the kernel modules (:mod:`diff4splat.scene.kernels`, :mod:`diff4splat.render.fused_kernels`), which
are imported on first use, so ``import diff4splat`` does not pay numba's import time.
"""
from __future__ import annotations

import contextlib
import functools
import os

import numba
import torch
from numba import njit

__all__ = ["KERNEL", "threads"]

if "NUMBA_THREADING_LAYER" not in os.environ:
    # OpenMP first: torch's CPU wheel runs on libgomp, and numba's "omp" layer then shares torch's thread pool.
    # With numba's own "workqueue" pool, torch's OpenMP threads still spin-wait after each torch op and take
    # the cores from numba's threads.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


KERNEL = functools.partial(njit, cache=True, error_model="numpy")
"""numba's njit as every kernel uses it: cached on disk; NumPy's error model (a division by zero gives inf/NaN
instead of a Python exception check before every division and integer floor division, which would slow the inner
loops)."""


@contextlib.contextmanager
def threads(n: int):
    """Run the kernel launches inside on ``n`` threads (at most numba's pool size), then restore torch's count.

    numba's OpenMP layer sets the shared OpenMP thread count at each launch (``omp_set_num_threads``), which is
    also torch's: without the restore, ``torch.set_num_threads(1)`` would read back numba's count after a launch.
    """
    saved = torch.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch.get_num_threads() != saved:
            torch.set_num_threads(saved)
