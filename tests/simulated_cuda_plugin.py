"""pytest plugin: a whole test run on the simulated CUDA device of tests/simulated_cuda.py, autograd included.

    PYTHONPATH=tests python -m pytest -p simulated_cuda_plugin -m cuda

on a CPU-only machine with g++: the CUDA cases of the suite (the ``device`` fixture's and the ``cuda``-marked
tests) run on "cuda" tensors that compute on the CPU and raise PyTorch's own errors where a GPU would; those of
tests marked ``real_gpu`` skip (memory figures, pinned memory, torch.compile, CUDA generators, child processes).
tests/test_simulated_cuda.py runs this on CI.

Autograd records the device's stream for every tensor it tracks and synchronises through the accelerator, which
a CPU-only build of torch does not have. This plugin therefore builds tests/simulated_cuda_runtime.cpp (a CUDA
device guard and CUDA hooks, ~2 s with g++ and torch's headers, cached in the temp folder by source and torch
version) and loads it *before* torch is imported (torch reads its CUDA hooks once), then enters
:func:`simulated_cuda.simulated_cuda` for the session.
"""
from __future__ import annotations

import ctypes
import hashlib
import importlib.util
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "simulated_cuda_runtime.cpp"


def build_runtime() -> Path:
    """The shared library of :data:`SOURCE` for the installed torch (built once, then cached).

    Raises:
        RuntimeError: g++ is missing or the build fails (its last lines).
    """
    torch_dir = Path(importlib.util.find_spec("torch").submodule_search_locations[0])
    key = hashlib.sha256(SOURCE.read_bytes() + (torch_dir / "version.py").read_bytes()
                         + str(torch_dir).encode()).hexdigest()[:16]
    out = Path(tempfile.gettempdir()) / f"diff4splat_simulated_cuda_{key}.so"
    if not out.exists():
        tmp = out.with_name(f"{out.name}.{os.getpid()}.tmp")
        cmd = ["g++", "-O1", "-shared", "-fPIC", "-std=c++17", f"-I{torch_dir / 'include'}", str(SOURCE),
               f"-L{torch_dir / 'lib'}", "-lc10", "-ltorch_cpu", f"-Wl,-rpath,{torch_dir / 'lib'}", "-o", str(tmp)]
        try:
            subprocess.run(cmd, check=True, capture_output=True, text=True)
        except (OSError, subprocess.CalledProcessError) as e:
            why = getattr(e, "stderr", "") or str(e)
            raise RuntimeError(f"simulated CUDA runtime: building {SOURCE.name} failed: {why[-2000:]}") from None
        tmp.replace(out)
    return out


if "torch" in sys.modules:
    raise RuntimeError("simulated_cuda_plugin must be loaded before torch is imported (-p simulated_cuda_plugin)")
_RUNTIME = ctypes.CDLL(str(build_runtime()), mode=ctypes.RTLD_GLOBAL)

import torch  # noqa: E402  (after the runtime: torch reads the CUDA hooks it registers)

if torch.version.cuda is not None or _RUNTIME.register_simulated_cuda_guard() != 0:
    raise RuntimeError("simulated CUDA is for CPU-only builds of torch; this one has CUDA: run on the GPU")
sys.path.insert(0, str(HERE))
import simulated_cuda  # noqa: E402

assert simulated_cuda.RUNTIME, "the simulated CUDA runtime did not take: torch sees no CUDA accelerator"
_SESSION = simulated_cuda.simulated_cuda()
_SESSION.__enter__()


def pytest_collection_modifyitems(config, items):
    """The CUDA cases of tests marked ``real_gpu`` skip: they measure what the simulation does not have."""
    skip = pytest.mark.skip(reason="needs a real GPU (marked real_gpu): not on the simulated CUDA device")
    for item in items:
        if "real_gpu" in item.keywords and "cuda" in item.keywords:
            item.add_marker(skip)


def pytest_unconfigure(config):
    _SESSION.__exit__(None, None, None)
