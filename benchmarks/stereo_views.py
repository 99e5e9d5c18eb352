"""Novel views of a real photograph against the second view of a calibrated stereo pair (issue 27).

    python benchmarks/stereo_views.py LEFT RIGHT DISPARITY [--checkpoint DIR ...] [--device DEV] [--write]
    # scikit-image's Middlebury 2014 "Motorcycle" pair, whose calibration (MOTORCYCLE) the script uses: from the
    # files of the scikit-image wheel (pip download scikit-image --no-deps), skimage/data/motorcycle_left.png,
    # motorcycle_right.png and motorcycle_disp.npz

The held-out synthetic clips score novel views, but the photographs users give have no second view, so whether a
photo-layer depth that helps synthetic views also holds on real photographs was judged by eye. A rectified stereo
pair gives the missing number: ``generate`` runs from the left image along a camera path that starts at the left
camera (the pair's own intrinsics, centre-cropped and resized to the output resolution as ``generate`` reads the
photo) and translates to the right, with the right camera's principal point (Middlebury's ``doffs``), all at scene
time t = 0; each frame is compared with the right image.

A single photograph fixes depth only up to scale, so the path scans baselines s·B for s = k/6, k = 1…16 (B the
pair's baseline, metres): ``at B`` is the frame at the true baseline (metric scale counts), ``best`` the best
frame (the scale a perfect scale estimate would pick; the shape of the depth counts). PSNR (dB, kornia) over the
image without a 16-pixel border at 256². Rows beside the models: ``true depth`` (the first model given the pair's
own depth, z = f·B/(d + doffs), through ``generate --depth``: the renderer's oracle), ``repeat left`` (the left
image as the right view) and ``best shift of left`` (the left image shifted by the best whole number of pixels: a
flat card).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish, repo_relative  # noqa: E402

from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.generate import generate  # noqa: E402
from diff4splat.io import load_image  # noqa: E402
from diff4splat.request import load_pipeline  # noqa: E402
from diff4splat.utils.devices import AUTO, DEVICE_HELP  # noqa: E402
from training.eval_metrics import image_psnr  # noqa: E402

MOTORCYCLE = {"focal": 994.978, "cx": 311.193, "cy": 254.877, "doffs": 31.086, "baseline": 0.193001}
"""Calibration of scikit-image's motorcycle pair (its ``data.stereo_motorcycle`` docstring: Middlebury 2014,
down-sampled 4×): focal length and principal point in pixels, ``doffs`` the right camera's principal-point offset in
pixels, baseline in metres."""
SCALES = [k / 6 for k in range(1, 17)]
"""Baselines scanned, as multiples of the pair's (k = 6 is the true one)."""
SIZE, BORDER = 256, 16


def stereo_path(shape: tuple[int, int], calib: dict) -> CameraPath:
    """Left camera, then the right camera at each of :data:`SCALES` × the baseline, all at t = 0, for the left image
    of ``shape`` (H, W) pixels centre-cropped to a square and resized to :data:`SIZE` (as ``generate`` reads it).

    ``calib`` holds the keys of :data:`MOTORCYCLE` (pixels of the full image; baseline in metres). Returns
    1 + len(SCALES) cameras at SIZE², float64, world frame = the left camera's."""
    H, W = shape
    side = min(H, W)
    s = SIZE / side
    fx = calib["focal"] * s
    cx, cy = (calib["cx"] - (W - side) / 2) * s, (calib["cy"] - (H - side) / 2) * s
    K = torch.tensor([[fx, 0, cx], [0, fx, cy], [0, 0, 1]], dtype=torch.float64)
    K_right = K.clone()
    K_right[0, 2] += calib["doffs"] * s
    viewmats = torch.eye(4, dtype=torch.float64).repeat(len(SCALES) + 1, 1, 1)
    viewmats[1:, 0, 3] = -calib["baseline"] * torch.tensor(SCALES, dtype=torch.float64)  # camera centre at +x
    Ks = torch.stack([K] + [K_right] * len(SCALES))
    return CameraPath(viewmats, Ks, SIZE, SIZE, torch.zeros(len(SCALES) + 1, dtype=torch.float64))


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:  # (H, W, 3) in [0, 1], without the border
    crop = (slice(BORDER, -BORDER), slice(BORDER, -BORDER))
    return image_psnr(a[crop].permute(2, 0, 1)[None].cpu().float(), b[crop].permute(2, 0, 1)[None].float())


def scan(colors: torch.Tensor, right: torch.Tensor) -> tuple[float, float, float]:
    """(PSNR at the true baseline, best PSNR, its scale) of the frames 1… of ``colors`` (T, H, W, 3)."""
    p = [_psnr(c, right) for c in colors[1:]]
    best = int(np.argmax(p))
    return p[SCALES.index(1.0)], p[best], SCALES[best]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("left", type=Path)
    ap.add_argument("right", type=Path)
    ap.add_argument("disparity", type=Path, help="left image's disparity, pixels (.npz first array, or .npy)")
    ap.add_argument("--checkpoint", type=Path, action="append", default=None,
                    help="model folder (repeat for several; default: the shipped weights)")
    ap.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    calib = MOTORCYCLE
    raw = np.load(args.disparity)
    disparity = np.asarray(raw[raw.files[0]] if hasattr(raw, "files") else raw, dtype=np.float64)
    disparity = disparity[..., 0] if disparity.ndim == 3 else disparity
    depth = calib["focal"] * calib["baseline"] / (disparity + calib["doffs"])  # metres; NaN/inf holes stay holes
    path = stereo_path(disparity.shape, calib)
    left, right = load_image(args.left, size=(SIZE, SIZE)), load_image(args.right, size=(SIZE, SIZE))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        depth_file = Path(tmp) / "depth.npy"  # given as a user gives it: generate crops and resizes it
        np.save(depth_file, depth.astype(np.float32))
        for i, checkpoint in enumerate(args.checkpoint or [None]):
            pipe = load_pipeline(checkpoint, device=args.device)
            runs = [(repo_relative(pipe.source), None)] + ([("true depth", depth_file)] if i == 0 else [])
            for name, given in runs:
                at_b, best, scale = scan(generate(args.left, path, pipeline=pipe, depth=given).colors, right)
                rows.append([name, f"{at_b:.2f}", f"{best:.2f}", f"{scale:.2f}"])
                print(" | ".join(rows[-1]), flush=True)
    shifts = [_psnr(torch.roll(left, -s, dims=1), right) for s in range(SIZE // 4)]
    rows.append(["repeat left", f"{shifts[0]:.2f}", f"{shifts[0]:.2f}", "—"])
    rows.append([f"best shift of left ({int(np.argmax(shifts))} px)", "—", f"{max(shifts):.2f}", "—"])
    table = markdown_table(["depth of the photo layer", "right view at B, dB", "best over s·B, dB", "best s"], rows)
    publish("stereo_views", f"Novel views of a real photograph: the right view of a stereo pair ({args.left.name})",
            f"PSNR without a {BORDER}-px border at {SIZE}² (module docstring).", table, args.write)


if __name__ == "__main__":
    main()
