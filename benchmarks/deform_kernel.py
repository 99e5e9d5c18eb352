"""``DynamicGaussians.at`` on the CPU: the numba kernel (:mod:`diff4splat.scene.kernels`) against the PyTorch
reference it replaces without gradients (``deformation_at`` then ``compose_deformation`` of the same Gaussians), per
scene size; the largest difference of the deformed means, quats and scales.

    python benchmarks/deform_kernel.py [--sizes 100000 1000000 5000000] [--write]

Random dynamic float32 scenes with 17 key times and temporal support (as ``generate`` writes them), gate 0 (every
Gaussian); each path timed as the fastest of 3 calls after a warm-up (the kernel's first call loads it from numba's
disk cache). ``--write`` puts the table into docs/benchmarks.md (section ``deform_kernel``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.scene.dynamic import DynamicGaussians, compose_deformation  # noqa: E402
from diff4splat.scene.gaussians import Gaussians  # noqa: E402

KEYS = 17


def scene(m: int) -> DynamicGaussians:
    g = torch.Generator().manual_seed(0)
    canon = Gaussians(torch.randn(m, 3, generator=g), torch.randn(m, 4, generator=g),
                      torch.rand(m, 3, generator=g) + 0.01, torch.rand(m, generator=g),
                      torch.rand(m, 1, 3, generator=g))
    return DynamicGaussians(canon, torch.linspace(0, 1, KEYS), 0.01 * torch.randn(KEYS, m, 3, generator=g),
                            torch.randn(KEYS, m, 4, generator=g), 0.01 * torch.randn(KEYS, m, 3, generator=g),
                            torch.rand(m, generator=g), torch.rand(m, generator=g) + 0.5)


def fastest(fn, repeats: int = 3) -> tuple[float, object]:
    fn()
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000, 5_000_000])
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    rows, t = [], 0.37  # between two key times
    for m in args.sizes:
        s = scene(m)
        with torch.no_grad():
            fused_s, fused = fastest(lambda s=s: s.at(t, gate=0.0))
            ref_s, ref = fastest(lambda s=s: compose_deformation(s.canonical.means, s.canonical.quats,
                                                                 s.canonical.scales, *s.deformation_at(t)))
        err = max(float((a - b).abs().max()) for a, b in zip((fused.means, fused.quats, fused.scales), ref,
                                                             strict=True))
        rows.append([f"{m:,}", f"{1e3 * fused_s:.0f}", f"{1e3 * ref_s:.0f}", f"{ref_s / fused_s:.1f}×", f"{err:.1e}"])
        print(rows[-1], flush=True)
    table = markdown_table(["Gaussians", "kernel ms", "reference ms", "speed-up", "max abs difference"], rows)
    note = (f"float32, {KEYS} key times, t = {t}, gate 0, torch's thread count; fastest of 3 calls after a warm-up. "
            "The kernel's time includes the opacity and SH gathers that `at` does around it.")
    publish("deform_kernel", "The scene at a time: numba kernel against the PyTorch reference", note, table,
            args.write)


if __name__ == "__main__":
    main()
