"""``diff4splat reconstruct``'s cost against the clip's length: wall time, peak memory and the output folder.

    python benchmarks/reconstruct_cost.py --video FILE [--start K] [--stride S] [--frames 9 17 33]
        [--resolution 256] [--layers every] [--write]

Each clip length T runs the command as a user does, in a fresh process (``python -m diff4splat.cli reconstruct
VIDEO --frames T --stride S --start K --resolution R --layers L --no-frame-plys --device cpu --quiet``), into a
temporary folder on the disk of this checkout: its wall time, its peak resident set (the child's ``ru_maxrss``
from ``os.wait4``) beside :func:`diff4splat.reconstruct.memory_estimate`'s bound for the same request (the check
that refuses a run before it starts), the scene's Gaussians (``meta.json``) and the folder's bytes in all and per
part. ``--write`` puts the table into docs/benchmarks.md (section ``reconstruct_cost``).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_pipeline, markdown_table, publish  # noqa: E402

from diff4splat.assembly.layers import LAYERS, layer_frames  # noqa: E402
from diff4splat.reconstruct import memory_estimate  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PARTS = ("deformation.npz", "scene.ply", "viewer.html")


def run(args: argparse.Namespace, frames: int, out: Path) -> tuple[float, int]:
    """Wall seconds and peak resident bytes of one ``reconstruct`` command writing ``out``."""
    cmd = [sys.executable, "-m", "diff4splat.cli", "reconstruct", str(args.video), "--frames", str(frames),
           "--stride", str(args.stride), "--start", str(args.start), "--resolution", str(args.resolution),
           "--layers", args.layers, "--no-frame-plys", "--device", "cpu", "--quiet", "--out", str(out)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return seconds, usage.ru_maxrss * 1024  # Linux: kilobytes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--video", type=Path, required=True)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--frames", type=int, nargs="+", default=[9, 17, 33])
    ap.add_argument("--resolution", type=int, default=256)
    ap.add_argument("--layers", choices=LAYERS, default="every")
    ap.add_argument("--note", default="")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    pipe, _ = load_pipeline(None, "base")
    rows = []
    for frames in args.frames:
        with tempfile.TemporaryDirectory(dir=ROOT) as tmp:
            out = Path(tmp) / "out"
            seconds, peak = run(args, frames, out)
            meta = json.loads((out / "meta.json").read_text())
            files = [f for f in out.rglob("*") if f.is_file()]
            total = sum(f.stat().st_size for f in files)
            parts = [(out / name).stat().st_size if (out / name).is_file() else 0 for name in PARTS]
        layers = len(layer_frames(pipe.source_frames(frames), frames, args.layers))
        bound = memory_estimate(pipe, meta["width"], meta["height"], frames, layers)
        rows.append([frames, f"{meta['width']}×{meta['height']}", layers, f"{meta['num_gaussians']:,}",
                     f"{seconds:.1f}", f"{peak / 1e9:.2f}", f"{bound / 1e9:.2f}", f"{total / 1e9:.3f}",
                     *(f"{b / 1e9:.3f}" for b in parts)])
        print(" | ".join(str(c) for c in rows[-1]), flush=True)
    table = markdown_table(["frames", "output", "layers", "Gaussians", "wall s", "peak GB", "estimate GB",
                            "folder GB", *(f"{p} GB" for p in PARTS)], rows)
    publish("reconstruct_cost", "reconstruct against the clip's length", f"{args.note} GB = 10⁹ bytes; one run per "
            "length, each a fresh process; the folder without frames/ (`--no-frame-plys`).".strip(), table,
            args.write)


if __name__ == "__main__":
    main()
