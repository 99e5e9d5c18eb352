"""Does this CPU's bfloat16 matmul let NaN from other rows into a clean row, and does the bfloat16 Wan backbone test
pass with Intel AMX and without it?

Why: ``tests/test_training_backbone.py::test_a_bfloat16_backbone_trains_float32_weights`` trains on the CPU
(``device: cpu``) and had a NaN flow loss at its second batch on the lent GPU machines' Intel Xeon hosts (an H200,
then an H100, 2026-11-26, torch 2.11.0+cu130). It never fails on the AMD EPYC machines here, torch 2.11 or 2.13.
A known oneDNN bug fits: issue uxlfoundation/oneDNN#5717 (fixed by PR #5723, 2026-07-31). The AMX bf16 matmul
kernel (``brg_matmul:avx10_1_512_amx``) reads past a row's K columns into the next row when K > 32 and K % 32 != 0,
and a NaN there reaches a row that holds none. This script tells the two apart on such a machine:

- ``matmul``: the issue's case. A (16, 32, 33) @ (16, 33, 64) bmm and a (64, 33) @ (33, 64) mm in bfloat16, row 0
  of each matrix finite and every other row NaN. Row 0 of the product must be finite.
- ``test``: the backbone test itself, ``--repeats`` times.

Each runs in a child process under ``ONEDNN_MAX_CPU_ISA`` = ``DEFAULT`` and = ``AVX512_CORE_BF16`` (oneDNN without
AMX), since oneDNN reads the variable once per process.

    python benchmarks/amx_nan_check.py [--repeats N] [--no-test]

Prints the CPU's AMX flags, torch's CPU capability and oneDNN version, and one line per ISA and check.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
TEST = "tests/test_training_backbone.py::test_a_bfloat16_backbone_trains_float32_weights"
ISAS = ("DEFAULT", "AVX512_CORE_BF16")
"""oneDNN's instruction sets to compare: whatever this CPU has, and AVX-512 with bf16 but no AMX."""


def leaked_rows() -> dict[str, bool]:
    """Whether row 0 of a bfloat16 product came out non-finite although row 0 of its left factor is finite
    (oneDNN#5717's case: K = 33, every other row NaN), for ``bmm`` and ``mm``; True means a leak."""
    g = torch.Generator().manual_seed(0)
    a = torch.full((16, 32, 33), float("nan"), dtype=torch.bfloat16)
    a[:, 0] = torch.randn(16, 33, generator=g).to(torch.bfloat16)
    b = torch.randn(16, 33, 64, generator=g).to(torch.bfloat16)
    m = torch.full((64, 33), float("nan"), dtype=torch.bfloat16)
    m[0] = torch.randn(33, generator=g).to(torch.bfloat16)
    w = torch.randn(33, 64, generator=g).to(torch.bfloat16)
    return {"bmm": not bool(torch.isfinite(torch.bmm(a, b)[:, 0]).all()),
            "mm": not bool(torch.isfinite(m @ w)[0].all())}


def host() -> str:
    """The CPU's AMX flags, torch's CPU capability and the oneDNN version torch was built with."""
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    amx = sorted(set(re.findall(r"\bamx_\w+", flags))) or ["none"]
    onednn = re.search(r"(?:oneDNN|MKL-DNN) (v[\w.]+)", torch.__config__.show())
    return (f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}, "
            f"oneDNN {onednn.group(1) if onednn else '?'}, AMX flags: {' '.join(amx)}")


def _child(check: str, isa: str) -> str:
    env = {**os.environ, "ONEDNN_MAX_CPU_ISA": isa}
    if check == "matmul":
        proc = subprocess.run([sys.executable, __file__, "--child"], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=120)
        return proc.stdout.strip() if proc.returncode == 0 else f"error: {proc.stderr.strip()[-300:]}"
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", TEST], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)
    if proc.returncode == 0:
        return "passed"
    nan = re.search(r"non-finite loss \([^)]*\) at step \d+", proc.stdout + proc.stderr)
    return f"failed ({nan.group(0) if nan else 'exit ' + str(proc.returncode)})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2, help="runs of the backbone test per ISA (default: 2)")
    ap.add_argument("--no-test", action="store_true", help="the matmul check only")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(" ".join(f"{k}: {'NaN leaked into a clean row' if v else 'clean'}" for k, v in leaked_rows().items()))
        return 0
    print(host(), flush=True)
    for isa in ISAS:
        print(f"ONEDNN_MAX_CPU_ISA={isa} matmul: {_child('matmul', isa)}", flush=True)
        for i in range(0 if args.no_test else args.repeats):
            print(f"ONEDNN_MAX_CPU_ISA={isa} test run {i + 1}: {_child('test', isa)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
