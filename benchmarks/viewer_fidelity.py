"""The photo in the browser: viewer.html's canvas at the input camera against the photograph.

For each photo: ``generate`` (the library call of the command, shipped model, default settings) and ``write``; the
folder's viewer.html opened from disk in headless Chromium (Playwright, software WebGL as the browser tests use it)
at viewports whose canvas is the output's size magnified s = 1 and 3 times (``--scales``, odd); the canvas at t = 0
from the input camera read at the centres of the output's pixels (canvas pixel s·i + (s − 1)/2: where the CPU
renderer samples) and, for s > 1, also area-averaged to the output resolution (what the eye sees of the magnified
splats), against the photograph as the output shows it (centre-cropped, resized) — and, as baselines, the 8×8
thumbnail of the photograph and the CPU render of frame 0 (``rgb/0000.png``) against the same photograph.

    python benchmarks/viewer_fidelity.py [PHOTO ...] [--scales 1 3] [--write]   # default: examples/chelsea.png
    python benchmarks/viewer_fidelity.py --video CLIP [--start K] [--write]

``--video``: ``reconstruct`` of every other frame of a clip (17 given frames, stride 2, from ``--start``) and the
folder's embedded viewer.html (reduced to its size budget as written) at every frame time of the clip, given and
in between, from the still camera at 1×, against the video's frames; beside it the CPU render of the given frames
(``rgb/``), and for the in-between frames holding the previous given frame and blending the two neighbours.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch
from playwright.sync_api import sync_playwright

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from diff4splat.generate import generate  # noqa: E402
from diff4splat.io.image import preprocess_image, read_image  # noqa: E402
from diff4splat.io.video_input import read_video_clip  # noqa: E402
from diff4splat.reconstruct import reconstruct  # noqa: E402
from diff4splat.request import write  # noqa: E402
from training.eval_metrics import image_psnr, thumbnail  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
"""Software WebGL in headless Chromium, as tests/conftest.py launches it: no GPU needed."""


def _chw(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float()


def canvas_at_input_camera(browser, viewer: Path, width: int, height: int, scale: int = 1) -> np.ndarray:
    """viewer.html's canvas (t = 0, input camera) in a viewport that fits ``scale`` × (width × height):
    (scale·height, scale·width, 3) RGB float in [0, 1]."""
    page = browser.new_page(viewport={"width": scale * width, "height": scale * height + 120})
    page.goto(viewer.as_uri())
    page.wait_for_function("window.d4s && (window.d4s.ready || window.d4s.error)", timeout=120_000)
    if page.evaluate("d4s.error") is not None:
        raise RuntimeError(f"{viewer}: {page.evaluate('d4s.error')}")
    page.wait_for_timeout(500)  # the worker's sort after the first frame
    png = page.locator("#view").screenshot()
    page.close()
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
    if img.shape[:2] != (scale * height, scale * width):
        raise RuntimeError(f"{viewer}: canvas {img.shape[1]}×{img.shape[0]}, expected {scale * width}×{scale * height}")
    return img


def canvas_at_time(page, t: float, width: int, height: int) -> np.ndarray:
    """The open page's canvas (1×, the first path camera) once it has drawn time ``t``: (height, width, 3) in [0, 1]."""
    page.evaluate("t => d4s.setTime(t)", t)
    drawn = page.evaluate("d4s.renders")
    page.wait_for_function(f"d4s.renders > {drawn + 4}", timeout=120_000)
    page.wait_for_timeout(300)  # the worker's sort
    png = page.screenshot(clip=page.locator("#view").bounding_box(), timeout=300_000)  # large scenes draw slowly
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
    if img.shape[:2] != (height, width):
        raise RuntimeError(f"canvas {img.shape[1]}×{img.shape[0]}, expected {width}×{height}")
    return img


def reconstruct_row(browser, video: Path, start: int, tmp: Path) -> list:
    """The ``--video`` row (module docstring)."""
    frames = 17
    out = tmp / "rec"
    write(reconstruct(video, frames=frames, stride=2, start=start, frame_plys=False), out)
    H, W = (int(x) for x in cv2.imread(str(out / "rgb" / "0000.png")).shape[:2])
    clip = read_video_clip(video, 2 * frames - 1, 1, start)
    truth = [preprocess_image(f, (H, W)).numpy() for f in clip.frames]
    page = browser.new_page(viewport={"width": W, "height": H + 400})  # room for the controls and the note
    page.goto((out / "viewer.html").as_uri())
    page.wait_for_function("window.d4s && (window.d4s.ready || window.d4s.error)", timeout=600_000)
    if page.evaluate("d4s.error") is not None:
        raise RuntimeError(f"{out}/viewer.html: {page.evaluate('d4s.error')}")
    reductions = page.evaluate("JSON.parse(document.getElementById('d4s-config').textContent).reductions")
    mse = {"given": [], "between": []}
    for j in range(2 * frames - 1):
        canvas = canvas_at_time(page, j / (2 * frames - 2), W, H)
        mse["given" if j % 2 == 0 else "between"].append(float(((canvas - truth[j]) ** 2).mean()))
    page.close()
    cpu = [cv2.imread(str(out / "rgb" / f"{k:04d}.png"))[..., ::-1].astype(np.float32) / 255 for k in range(frames)]
    err = lambda a, b: float(((a - b) ** 2).mean())  # noqa: E731
    db = lambda m: f"{-10 * np.log10(np.mean(m)):.2f}"  # noqa: E731
    hold = [err(truth[2 * k], truth[2 * k + 1]) for k in range(frames - 1)]
    blend = [err((truth[2 * k] + truth[2 * k + 2]) / 2, truth[2 * k + 1]) for k in range(frames - 1)]
    return [f"{video.name}, start {start}", f"{W}×{H}", "; ".join(reductions) or "no",
            db(mse["given"]), db([err(cpu[k], truth[2 * k]) for k in range(frames)]), db(mse["between"]),
            db(hold), db(blend)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="*", type=Path, default=[EXAMPLE])
    ap.add_argument("--scales", type=int, nargs="+", default=[1, 3],
                    help="canvas pixels per output pixel, odd (default: 1 3)")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    ap.add_argument("--video", type=Path, help="a reconstruct row instead of photos (module docstring)")
    ap.add_argument("--start", type=int, default=0, help="--video's first frame")
    args = ap.parse_args()
    if any(s < 1 or s % 2 == 0 for s in args.scales):
        ap.error(f"--scales must be odd positive integers (an output pixel's centre is a canvas pixel's), "
                 f"got {args.scales}")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("viewer_fidelity: needs Chromium (apt-get install chromium)")
    if args.video is not None:
        with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS)
            row = reconstruct_row(browser, args.video, args.start, Path(tmp))
            browser.close()
        table = markdown_table(["clip", "output", "page reduced", "page, given frames dB",
                                "CPU render (rgb/), given dB", "page, in-between frames dB", "hold dB", "blend dB"],
                               [row])
        publish(f"viewer_fidelity_reconstruct_{args.video.stem}_{args.start}",
                "A `reconstruct` folder's viewer.html against its video",
                "Shipped base model; `reconstruct` of every other frame (17 given, `--no-frame-plys`), its "
                "embedded viewer.html (as written: reduced to the size budget) opened from disk in headless Chromium "
                "(SwiftShader WebGL, Spark) at 1× from the still camera at each frame time of the clip, against the "
                "video's frames; the in-between frames were not given to `reconstruct`.", table, args.write)
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS)
        for photo in args.photos:
            gen = generate(photo)
            out = Path(tmp) / photo.stem
            write(gen, out)
            H, W = gen.colors.shape[1:3]
            target = preprocess_image(read_image(photo), (H, W)).permute(2, 0, 1)[None].float()  # as generate frames it
            cells = []
            for s in args.scales:
                canvas = canvas_at_input_camera(browser, out / "viewer.html", W, H, s)
                cells.append(f"{image_psnr(_chw(canvas[s // 2::s, s // 2::s]), target):.2f}")
                if s > 1:
                    area = cv2.resize(canvas, (W, H), interpolation=cv2.INTER_AREA)
                    cells.append(f"{image_psnr(_chw(area), target):.2f}")
            frame0 = _chw(cv2.imread(str(out / "rgb" / "0000.png"))[..., ::-1].astype(np.float32) / 255)
            rows.append([photo.name, f"{W}×{H}", *cells,
                         f"{image_psnr(frame0, target):.2f}", f"{image_psnr(thumbnail(target), target):.2f}"])
        browser.close()
    heads = []
    for s in args.scales:
        heads += [f"viewer {s}×, pixel centres dB"] + ([f"viewer {s}×, area-averaged dB"] if s > 1 else [])
    table = markdown_table(["photo", "output", *heads, "frame 0 (rgb/0000.png) dB", "8×8 thumbnail dB"], rows)
    publish("viewer_fidelity", "The photo in the browser: viewer.html at the input camera",
            "Shipped base model, `generate` defaults (arc, 17 frames, 256²). The canvas of viewer.html opened from "
            "disk (headless Chromium, SwiftShader WebGL, Spark renderer) at t = 0 from the input camera, in a window "
            "that shows the output magnified s times, read at the output pixels' centres (where the CPU renderer "
            "samples) and, magnified, also area-averaged to the output size (the magnified splats as the eye "
            "averages them), against the photograph as the output frames it (centre crop, area resize); frame 0 "
            "of the CPU renderer and the photo's 8×8 thumbnail against the same photograph. Photos other than the "
            "demo are scikit-image and matplotlib samples that are not among the training textures.", table, args.write)


if __name__ == "__main__":
    main()
