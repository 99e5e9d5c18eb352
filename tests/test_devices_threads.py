"""Issue 28: the CPU thread settings of diff4splat/utils/devices.py reach the OpenMP runtime that torch, MKL and numba
share (idle threads sleep: two runs at once share the cores), and the thread counts follow the CPU affinity; issue 61:
torch's large CPU tensors get transparent huge pages.

Each check runs in a fresh interpreter: the runtime reads its environment once, when torch loads it, and this
test process loaded it long ago.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from diff4splat.utils.devices import (
    ALLOCATOR_ENV,
    THREAD_ENV,
    USER_THREAD_VARIABLES,
    set_allocator_env,
    set_thread_env,
)

REPO = Path(__file__).resolve().parent.parent
CHILD = """
import json, os
import diff4splat.cli  # what the `diff4splat` command imports first
import cv2, numba, torch
print(json.dumps({"env": {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")},
                  "torch": torch.get_num_threads(), "numba": numba.config.NUMBA_NUM_THREADS,
                  "cv2": cv2.getNumThreads(), "cpus": len(os.sched_getaffinity(0))}))
"""


def _child(env_extra: dict[str, str], prefix: tuple[str, ...] = ()) -> tuple[dict, dict[str, str]]:
    """(what CHILD printed, libgomp's own display of its settings) in a fresh interpreter."""
    env = {k: v for k, v in os.environ.items() if k not in USER_THREAD_VARIABLES + ("OMP_NUM_THREADS",)}
    env.update(env_extra, OMP_DISPLAY_ENV="verbose")  # libgomp prints its settings on stderr as it loads
    run = subprocess.run([*prefix, sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, cwd=REPO,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    shown = {}
    for line in run.stderr.splitlines():
        key, sep, value = line.strip().partition(" = ")
        if sep and key.isupper():
            shown.setdefault(key, value.strip("'"))
    return json.loads(run.stdout.strip().splitlines()[-1]), shown


def test_set_thread_env_sets_passive_waiting_unless_the_user_chose():
    env = {"PATH": "/bin"}
    assert set_thread_env(env) == THREAD_ENV == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert env == {"PATH": "/bin", "OMP_WAIT_POLICY": "PASSIVE"}
    for name, value in (("OMP_WAIT_POLICY", "ACTIVE"), ("GOMP_SPINCOUNT", "300000")):
        env = {name: value}
        assert set_thread_env(env) == {} and env == {name: value}  # the user's choice stands


@pytest.mark.slow
def test_the_openmp_runtime_torch_loads_sleeps_when_idle():
    """libgomp's spin count is 0 under OMP_WAIT_POLICY=PASSIVE; its default (300000) means the package's setting
    came after torch had loaded the runtime."""
    out, shown = _child({})
    assert out["env"] == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": None}
    assert shown.get("GOMP_SPINCOUNT") == "0", shown
    out, shown = _child({"GOMP_SPINCOUNT": "300000"})  # libgomp's default, chosen by the user: left alone
    assert out["env"] == {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "300000"}
    assert shown.get("GOMP_SPINCOUNT") == "300000" and shown.get("OMP_WAIT_POLICY") == "PASSIVE", shown


@pytest.mark.slow
def test_thread_counts_follow_the_cpu_affinity():
    out, shown = _child({})
    assert out["torch"] == out["numba"] == out["cv2"] == out["cpus"] == int(shown["OMP_NUM_THREADS"])
    if shutil.which("taskset") is None or len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs taskset and 2 processors")
    first = min(os.sched_getaffinity(0))
    out, shown = _child({}, ("taskset", "-c", str(first)))
    assert out["torch"] == out["numba"] == out["cv2"] == out["cpus"] == 1 and shown["OMP_NUM_THREADS"] == "1"


def test_set_allocator_env_asks_for_huge_pages_unless_the_user_chose():
    env = {"PATH": "/bin"}
    assert set_allocator_env(env) == ALLOCATOR_ENV == {"THP_MEM_ALLOC_ENABLE": "1"}
    assert env == {"PATH": "/bin", "THP_MEM_ALLOC_ENABLE": "1"}
    env = {"THP_MEM_ALLOC_ENABLE": "0"}
    assert set_allocator_env(env) == {} and env == {"THP_MEM_ALLOC_ENABLE": "0"}


HUGE = """
import diff4splat.cli, torch
x = torch.ones(64 << 18)  # 64 MiB, touched
print([int(line.split()[1]) for line in open("/proc/self/smaps_rollup") if line.startswith("AnonHugePages")][0])
"""


@pytest.mark.slow
def test_torch_large_cpu_tensors_get_transparent_huge_pages():
    """In a fresh interpreter that imports what the command imports, a 64 MiB tensor is backed by huge pages (the
    kernel's count of the process's anonymous huge pages); with the user's THP_MEM_ALLOC_ENABLE=0, by none."""
    mode = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if not mode.exists() or "[never]" in mode.read_text() or not Path("/proc/self/smaps_rollup").exists():
        pytest.skip("the kernel offers no transparent huge pages")
    kb = {}
    for value in (None, "0"):
        env = {k: v for k, v in os.environ.items() if k != "THP_MEM_ALLOC_ENABLE"}
        env.update({} if value is None else {"THP_MEM_ALLOC_ENABLE": value})
        run = subprocess.run([sys.executable, "-c", HUGE], capture_output=True, text=True, env=env, cwd=REPO,
                             timeout=120)
        assert run.returncode == 0, run.stderr[-2000:]
        kb[value] = int(run.stdout.split()[-1])
    assert kb[None] >= 32 * 1024 and kb["0"] < 32 * 1024, kb
