"""How every numba kernel is compiled and launched: :data:`KERNEL`, the threading layer shared with torch, and
:func:`threads`. Imported only by the kernel modules, on first use."""
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
"""numba's njit as every kernel uses it: cached on disk, NumPy's error model (no exception check per division)."""


@contextlib.contextmanager
def threads(n: int):
    """Run the kernel launches inside on ``n`` threads (at most numba's pool), then restore torch's count, which numba's
    OpenMP layer overwrites at each launch."""
    saved = torch.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch.get_num_threads() != saved:
            torch.set_num_threads(saved)
