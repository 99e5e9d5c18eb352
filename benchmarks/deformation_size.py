"""``deformation.npz`` of real output folders: bytes, write and read time, stored against deflated.

    python benchmarks/deformation_size.py --folders DIR [DIR ...] [--repeats 3] [--write]

Each folder's deformation (a ``generate`` or ``reconstruct`` output, read with ``load_output_scene``) is written to
a temporary file on the disk of this checkout, ``--repeats`` times per way, the fastest kept, and read back with
``load_deformation`` (both :mod:`diff4splat.io.scene_folder`): numpy's ``np.savez`` (every member stored),
``np.savez_compressed`` (every member deflated at zlib's default level 6), and ``save_deformation`` as shipped (the
members ``deflated`` picks, at ``DEFLATE_LEVEL``) and at level 6. Every way is checked to read back the same
arrays. ``--write`` puts the table into docs/benchmarks.md (section ``deformation_size``).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.io.scene_folder import (  # noqa: E402
    DEFLATE_LEVEL,
    DEFORMATION_ARRAYS,
    load_deformation,
    load_output_scene,
    save_deformation,
)

ROOT = Path(__file__).resolve().parent.parent


def ways(scene) -> dict:
    """Name → function writing ``scene``'s deformation to a path."""
    arrays = {k: getattr(scene, k).detach().cpu().float().numpy()  # device: np.savez writes host arrays
              for k in DEFORMATION_ARRAYS if getattr(scene, k) is not None}
    return {"`np.savez` (stored)": lambda p: np.savez(p, **arrays),
            "`np.savez_compressed` (all, level 6)": lambda p: np.savez_compressed(p, **arrays),
            f"`save_deformation` (level {DEFLATE_LEVEL}, shipped)": lambda p: save_deformation(p, scene),
            "`save_deformation` (level 6)": lambda p: save_deformation(p, scene, level=6)}


def fastest(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def folder_rows(folder: Path, repeats: int) -> list[list]:
    scene, meta = load_output_scene(folder)
    reference = None
    rows = []
    with tempfile.TemporaryDirectory(dir=ROOT) as tmp:
        path = Path(tmp) / "deformation.npz"
        for name, write in ways(scene).items():
            seconds = fastest(lambda w=write: w(path), repeats)
            size = path.stat().st_size
            read = fastest(lambda: load_deformation(path, scene.num_gaussians), repeats)
            got = load_deformation(path, scene.num_gaussians)
            reference = got if reference is None else reference
            assert got.keys() == reference.keys() and all(np.array_equal(got[k], reference[k]) for k in got), name
            rows.append([f"{folder.name} ({meta.get('kind', 'generate')})", f"{scene.num_gaussians:,}",
                         len(scene.times) if scene.times is not None else 0, name, f"{size / 1e6:.1f}",
                         f"{seconds:.2f}", f"{read:.2f}"])
            print(" | ".join(str(c) for c in rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folders", type=Path, nargs="+", required=True, help="generate / reconstruct output folders")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--note", default="")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    rows = [row for folder in args.folders for row in folder_rows(folder, args.repeats)]
    table = markdown_table(["folder", "Gaussians", "key times", "written by", "MB", "write s", "read s"], rows)
    publish("deformation_size", "deformation.npz: stored against deflated", f"{args.note} MB = 10⁶ bytes; the "
            f"fastest of {args.repeats} writes and reads each; every way reads back the same arrays.".strip(),
            table, args.write)


if __name__ == "__main__":
    main()
