"""Writing `generate`'s output folder at the sizes users run: wall time and bytes per part (CPU).

    python benchmarks/write_speed.py [--cases 93359x17x256 1311201x49x512] [--write]

Each case is GAUSSIANSxFRAMESxPIXELS, written with and without frames/ (``--no-frame-plys``): a seeded synthetic
dynamic scene of that many Gaussians with a deformation at one key time per frame (as ``generate`` makes),
rendered-image stand-ins at PIXELS², and the ``arc`` path; :func:`diff4splat.io.scene_folder.write_scene_folder`
writes it once into a temporary folder on the disk of this checkout (the first case's counts are the shipped base
model's on examples/chelsea.png at 256², the second the paper model's at 512², 49 frames, from docs/benchmarks.md
"generate on the GPU"). The folder's size is given per part; nothing here is the pipeline, so the figures hold
for any device the scene came from.

``--write`` puts the table into docs/benchmarks.md (section ``write_speed``).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.cameras import intrinsics_from_fov, make_trajectory  # noqa: E402
from diff4splat.io.scene_folder import write_scene_folder  # noqa: E402
from diff4splat.scene.dynamic import DynamicGaussians  # noqa: E402
from diff4splat.scene.gaussians import Gaussians  # noqa: E402

CASES = ["93359x17x256", "1311201x49x512"]
PARTS = {"frames/*.ply": lambda p: p.parent.name == "frames", "deformation.npz": lambda p: p.name == "deformation.npz",
         "viewer.html": lambda p: p.name == "viewer.html", "scene.ply": lambda p: p.name == "scene.ply"}


def synthetic_scene(m: int, frames: int, seed: int = 0) -> DynamicGaussians:
    """``m`` Gaussians 1-3 m in front of the origin, SH degree 0, small random motion at ``frames`` key times."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(m, 3, generator=g) * 0.5 + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.nn.functional.normalize(torch.randn(m, 4, generator=g), dim=-1)
    canonical = Gaussians(means, quats, torch.full((m, 3), 0.005), torch.full((m,), 0.8),
                          torch.rand(m, 1, 3, generator=g))
    d_quats = torch.zeros(frames, m, 4)
    d_quats[..., 0] = 1
    return DynamicGaussians(canonical, torch.linspace(0, 1, frames), torch.randn(frames, m, 3, generator=g) * 0.01,
                            d_quats, torch.zeros(frames, m, 3))


def write_case(m: int, frames: int, size: int, frame_plys: bool) -> list:
    scene = synthetic_scene(m, frames)
    path = make_trajectory("arc", frames, intrinsics_from_fov(size, size, fov_y_deg=50.0), size, size)
    g = torch.Generator().manual_seed(1)
    colors = torch.rand(frames, size, size, 3, generator=g)
    depths, alphas = torch.rand(frames, size, size, generator=g) + 1, torch.ones(frames, size, size)
    with tempfile.TemporaryDirectory(dir=Path(__file__).resolve().parent.parent) as tmp:
        t0 = time.perf_counter()
        write_scene_folder(Path(tmp) / "out", scene, path, colors, depths, alphas, {"static": False}, fps=8,
                           frame_plys=frame_plys)
        seconds = time.perf_counter() - t0
        files = [f for f in (Path(tmp) / "out").rglob("*") if f.is_file()]
        sizes = {name: sum(f.stat().st_size for f in files if test(f)) for name, test in PARTS.items()}
        total = sum(f.stat().st_size for f in files)
    row = [f"{m:,}", frames, f"{size}²", "yes" if frame_plys else "no (`--no-frame-plys`)", f"{seconds:.1f}",
           f"{total / 1e9:.2f}"]
    row += [f"{sizes[name] / 1e9:.2f}" for name in PARTS] + [f"{(total - sum(sizes.values())) / 1e9:.2f}"]
    print(row, flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=CASES, help="GAUSSIANSxFRAMESxPIXELS")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    rows = [write_case(*(int(v) for v in c.split("x")), plys) for c in args.cases for plys in (True, False)]
    table = markdown_table(["Gaussians", "frames", "images", "frames/", "write s", "folder GB", *PARTS,
                            "images, video, EXR GB"], rows)
    publish("write_speed", "Writing the output folder", "One write per case; GB = 10⁹ bytes. The per-frame PLYs "
            "are the scene at each frame's time for viewers that know no deformation: frames × Gaussians × 68 "
            "bytes, most of a long path's folder.", table, args.write)


if __name__ == "__main__":
    main()
