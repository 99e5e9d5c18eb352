"""Does this CPU's bfloat16 matmul let NaN from other rows into a clean row, and does the bfloat16 Wan backbone test
train to finite losses with Intel AMX and without it, and if not, which module first gave a non-finite output?

Why: ``tests/test_training_backbone.py::test_a_bfloat16_backbone_trains_float32_weights`` trains on the CPU
(``device: cpu``) and had a NaN flow loss at its second batch on the lent GPU machines' Intel Xeon hosts (an H200,
then an H100, 2026-11-26, torch 2.11.0+cu130). It never fails on the AMD EPYC machines here, torch 2.11 or 2.13.
A known oneDNN bug may fit: issue uxlfoundation/oneDNN#5717 (fixed by PR #5723, 2026-07-31). The AMX bf16 matmul
kernel (``brg_matmul:avx10_1_512_amx``) reads past a row's K columns into the next row when K > 32 and K % 32 != 0,
and a NaN there reaches a row that holds none. This script tells the causes apart on such a machine:

- ``matmul``: the issue's case (:func:`diff4splat.utils.devices.bf16_nan_leaks`, which warns trainers and runtimes that
  compute in bfloat16 on such a CPU). A (16, 32, 33) @ (16, 33, 64) bmm and a (64, 33) @ (33, 64) mm in bfloat16,
  row 0 of each matrix finite and every other row NaN. Row 0 of the product must be finite. Then the same with
  ``torch.backends.mkldnn`` switched off in the process (torch's own kernels), a remedy that needs no
  environment variable if it holds there.
- ``trace``: the test's two training steps, ``--repeats`` times, with a forward hook on every module: the first
  (deepest) module whose output is non-finite, and whether its inputs were finite.

Each runs in a child process under ``ONEDNN_MAX_CPU_ISA`` = ``DEFAULT`` and = ``AVX512_CORE_BF16`` (oneDNN without
AMX), since oneDNN reads the variable once per process.

    python benchmarks/amx_nan_check.py [--repeats N] [--no-test]

Prints the CPU's AMX flags, torch's CPU capability and oneDNN version, and one line per ISA and check.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from diff4splat.utils.devices import bf16_nan_leaks
from training.trainer import NonFiniteLossError

ROOT = Path(__file__).resolve().parent.parent
ISAS = ("DEFAULT", "AVX512_CORE_BF16")
"""oneDNN's instruction sets to compare: whatever this CPU has, and AVX-512 with bf16 but no AMX."""


def host() -> str:
    """The CPU's AMX flags, torch's CPU capability and the oneDNN version torch was built with."""
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    amx = sorted(set(re.findall(r"\bamx_\w+", flags))) or ["none"]
    onednn = re.search(r"(?:oneDNN|MKL-DNN) (v[\w.]+)", torch.__config__.show())
    return (f"torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}, "
            f"oneDNN {onednn.group(1) if onednn else '?'}, AMX flags: {' '.join(amx)}")


def traced_training() -> str:
    """The backbone test's two bf16 training steps (its data, folder and stage) with a forward hook on every module:
    "finite losses", or the first module whose output held NaN/inf (hooks fire inner modules first)."""
    sys.path.insert(0, str(ROOT / "tests"))  # the test's helpers; imported here, in the child that runs them
    import test_training_backbone as t  # lazy: pytest, diffusers and tests/ on the path, in the child that runs it

    first: list[str] = []

    def hook(name):
        def check(module, inputs, output):
            outs = output if isinstance(output, (tuple, list)) else (output,)
            bad = [o for o in outs if isinstance(o, torch.Tensor) and o.is_floating_point() and not o.isfinite().all()]
            if bad and not first:
                ins = [i for i in inputs if isinstance(i, torch.Tensor) and i.is_floating_point()]
                first.append(f"first non-finite output: {name or 'model'} ({type(module).__name__}), inputs "
                             f"{[(tuple(i.shape), str(i.dtype)[6:], bool(i.isfinite().all())) for i in ins]}")
        return check

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for i, ratio in enumerate((1.0, 1.0, 0.0)):
            t.generate_scene(root / "data", i, seed=41, size=64, frames=t.FRAMES, cameras=1, static_ratio=ratio)
        init = t._init_folder("wan", root / "init", camera_std=0.02)
        stage = t._stage("wan", init, root / "data", root / "run", bf16=True, total_steps=2)
        trainer, model, _ = t.train.build_training(dataclasses.replace(stage, backbone_dtype="bfloat16"))
        for name, module in model.named_modules():
            module.register_forward_hook(hook(name))
        try:
            trainer.fit()
            stopped = ""
        except NonFiniteLossError as e:  # every step non-finite: the trainer gives up, which is this check's answer
            stopped = f" (stopped: {e})"
        losses = [r["loss"] for r in t._metrics(root / "run")]
    return f"losses {losses}{stopped}; " + (first[0] if first else "every module's output finite")


def _child(check: str, isa: str) -> str:
    env = {**os.environ, "ONEDNN_MAX_CPU_ISA": isa}
    proc = subprocess.run([sys.executable, __file__, "--child", check], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)
    return proc.stdout.strip() if proc.returncode == 0 else f"error: {proc.stderr.strip()[-300:]}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=2, help="traced runs of the backbone test per ISA (default: 2)")
    ap.add_argument("--no-test", action="store_true", help="the matmul check only")
    ap.add_argument("--child", choices=("matmul", "trace"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child == "matmul":
        def says(leaks: dict[str, bool]) -> str:
            return " ".join(f"{k}: {'NaN leaked into a clean row' if v else 'clean'}" for k, v in leaks.items())

        with torch.backends.mkldnn.flags(enabled=False):  # torch's own bfloat16 kernels, oneDNN bypassed
            without = bf16_nan_leaks()
        print(f"{says(bf16_nan_leaks())}; without oneDNN (torch.backends.mkldnn off): {says(without)}")
        return 0
    if args.child == "trace":
        print(traced_training())
        return 0
    print(host(), flush=True)
    for isa in ISAS:
        print(f"ONEDNN_MAX_CPU_ISA={isa} matmul: {_child('matmul', isa)}", flush=True)
        for i in range(0 if args.no_test else args.repeats):
            print(f"ONEDNN_MAX_CPU_ISA={isa} test run {i + 1}: {_child('trace', isa)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
