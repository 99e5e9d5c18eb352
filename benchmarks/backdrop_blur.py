"""The backdrop's blur (:func:`diff4splat.assembly.photo.backdrop_colors`, 4 samples per cell) against its
full-resolution reference (:func:`diff4splat.assembly.photo.backdrop_colors_reference`): time and colour error per
photo size.

    python benchmarks/backdrop_blur.py [--write]

``examples/chelsea.png`` resized to each size; each function timed once after a warm-up call (min of 3 for the fast
one). Error: |fast − reference| over the backdrop's cells, RGB in [0, 1].

``--write`` puts the table into docs/benchmarks.md (section ``backdrop_blur``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.assembly.photo import BACKDROP_SAMPLES, _backdrop_grid, backdrop_colors, backdrop_colors_reference  # noqa: E402
from diff4splat.io import load_image  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
SIZES = [(256, 256), (512, 512), (704, 1280), (1024, 1024), (2048, 2048)]


def timed(fn, *args, repeats: int = 1) -> tuple[float, np.ndarray]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    rows = []
    for H, W in SIZES:
        image = load_image(EXAMPLE, size=(H, W)).numpy().astype(np.float32)
        grid = _backdrop_grid(W, H)
        backdrop_colors(image, *grid)
        fast_s, fast = timed(backdrop_colors, image, *grid, repeats=3)
        ref_s, ref = timed(backdrop_colors_reference, image, *grid)
        err = np.abs(fast - ref)
        rows.append([f"{W}×{H}", f"{grid[2]}×{grid[3]}", f"{fast_s * 1e3:.1f}", f"{ref_s * 1e3:.0f}",
                     f"{err.mean():.4f}", f"{err.max():.4f}"])
        print(rows[-1], flush=True)
    table = markdown_table(["photo", "cells", f"{BACKDROP_SAMPLES} samples/cell ms", "full resolution ms",
                            "mean abs error", "max abs error"], rows)
    publish("backdrop_blur", "The backdrop's blur: 4 samples per cell against full resolution",
            "The full-resolution blur's kernel (σ = one cell = H/16 pixels) grows with the photograph.", table,
            args.write)


if __name__ == "__main__":
    main()
