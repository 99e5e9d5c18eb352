"""Peak memory of ``render`` and ``fit`` against the estimate each checks before its heavy work
(:func:`diff4splat.commands.render.render_memory_estimate`, :func:`training.fit_cli.fit_memory_estimate`; constants in
:mod:`diff4splat.utils.costs` and ``training.fit_cli``).

    python benchmarks/command_memory.py [--quick] [--write]

Each row runs the real command twice in a child process: once with ``DIFF4SPLAT_MAX_MEMORY_BYTES=1``, refused at its
memory check, to read the estimate from the one-line refusal (GiB to 0.1), once without, for its own peak resident
set (``_common.run_with_peak_memory``). ``render`` renders scenes that ``generate`` wrote (17 frames, the shipped base
model) at their own size; ``fit`` fits synthetic scenes (``data_prep.synth.generate_scene``) for a few steps at the
densification caps named. An estimate is an upper bound when ratio ≥ 1; it refuses what would run when it is far
above 1.

``--write`` puts the table into docs/benchmarks.md (section ``command_memory``).
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish, run_with_peak_memory  # noqa: E402

from data_prep.synth import generate_scene  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
ESTIMATE = re.compile(r"estimated peak memory ([0-9.]+) (GiB|MiB)")


def _estimate_and_peak(argv: list[str]) -> tuple[float, float]:
    """(estimate GB read from the refusal, measured peak GB) of one command."""
    refused, _ = run_with_peak_memory(argv, capture_output=True, text=True,
                                      env={**os.environ, "DIFF4SPLAT_MAX_MEMORY_BYTES": "1"})
    found = ESTIMATE.search(refused.stderr)
    if refused.returncode != 2 or found is None:
        raise RuntimeError(f"{argv[:2]} was not refused at its memory check: {refused.stderr[-1000:]}")
    estimate = float(found.group(1)) * 2 ** (30 if found.group(2) == "GiB" else 20) / 1e9
    done, peak = run_with_peak_memory(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{argv[:2]}: {done.stderr[-2000:]}")
    return estimate, peak / 1e9


def _gaussians(folder: Path) -> int:
    """The scene's Gaussian count, from its PLY header."""
    with open(folder / "scene.ply", "rb") as f:
        header = f.read(4096).split(b"end_header")[0].decode("ascii")
    return int(re.search(r"element vertex (\d+)", header).group(1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the smallest row of each command only")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for res in (256,) if args.quick else (256, 512, 1024):
            scene = tmp / f"g{res}"
            done, _ = run_with_peak_memory(["diff4splat", "generate", str(EXAMPLE), "--resolution", str(res), "--quiet",
                                            "--device", "cpu", "--out", str(scene)], capture_output=True, text=True)
            if done.returncode != 0:
                raise RuntimeError(done.stderr[-2000:])
            est, peak = _estimate_and_peak(["diff4splat", "render", str(scene), "--trajectory", "orbit", "--device",
            "cpu", "--quiet",
                                            "--out", str(tmp / f"r{res}.mp4")])
            rows.append(["render", f"generated {res}², 17 frames", f"{_gaussians(scene):,}", f"{peak:.2f}",
                         f"{est:.2f}", f"{est / peak:.2f}"])
            print(rows[-1], flush=True)
        data = tmp / "data"
        scene_dir = generate_scene(data, 0, seed=0, size=64, frames=9, cameras=2)
        for cap in (20_000,) if args.quick else (20_000, 200_000):
            est, peak = _estimate_and_peak(["diff4splat", "fit", str(scene_dir), "--iterations", "30",
                                            "--coarse-iterations", "10", "--max-gaussians", str(cap), "--device",
                                            "cpu", "--quiet", "--out", str(tmp / f"fit{cap}")])
            rows.append(["fit", "synthetic 64², 9 frames, 2 cameras, 30 steps", f"≤ {cap:,}", f"{peak:.2f}",
                         f"{est:.2f}", f"{est / peak:.2f}"])
            print(rows[-1], flush=True)
    table = markdown_table(["command", "input", "Gaussians", "peak GB", "estimate GB", "estimate / peak"], rows)
    note = ("Each command's own peak resident set against the estimate it checks before its heavy work (read from "
            "its refusal under `DIFF4SPLAT_MAX_MEMORY_BYTES=1`, 0.1 GiB steps).")
    publish("command_memory", "Memory of render and fit against their estimates", note, table, args.write)


if __name__ == "__main__":
    main()
