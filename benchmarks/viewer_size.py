"""Size and load time of ``viewer.html`` (the self-contained 4D viewer, diff4splat/io/viewer_page.py).

Rows: the shipped example (``diff4splat generate examples/chelsea.png``, default model), synthetic dynamic
scenes (random Gaussians, 17 keyframes) of 10,000 and 65,536 Gaussians at SH degree 0 and 3, and with ``--video``
the ``diff4splat reconstruct`` of a clip (``--start``, 17 frames, stride 2: short-lived layers, each holding only
the keys around its window). Columns: the key times, the held keyframes as a fraction of Gaussians × key times
(still Gaussians hold none, windowed ones a few), the keyframe bytes per Gaussian per held key (float16 or float32,
chosen by the measured float16 error), that error in pixels, the embedded PLY and keyframe sizes, the whole file,
whether the size budget reduced the scene, and — when Chromium and Playwright are installed — the time from
navigation until the page reports ready (headless Chromium, software WebGL, this machine), the milliseconds one
change of time takes in the page (interpolating every Gaussian between two keyframes and writing it into Spark's
PackedSplats) and the page's JavaScript heap once ready. A last row serves a paper-size scene (1,311,201 Gaussians,
49 keyframes: what the paper model keeps) with ``diff4splat view``, which never reduces the scene.

    python benchmarks/viewer_size.py --write [--video clip.mp4 --start 100]
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, write_section  # noqa: E402

from diff4splat.cameras.path import CameraPath  # noqa: E402
from diff4splat.commands.view import HOST, make_server  # noqa: E402
from diff4splat.generate import generate  # noqa: E402
from diff4splat.io.scene_folder import load_scene_folder, meta_background, meta_eps2d, write_scene_folder  # noqa: E402
from diff4splat.io.viewer_data import viewer_payload  # noqa: E402
from diff4splat.io.viewer_page import write_viewer  # noqa: E402
from diff4splat.reconstruct import reconstruct  # noqa: E402
from diff4splat.request import write  # noqa: E402
from diff4splat.scene.dynamic import DynamicGaussians  # noqa: E402
from diff4splat.scene.gaussians import Gaussians  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def synthetic(n: int, sh_degree: int, frames: int = 17, seed: int = 0) -> tuple[DynamicGaussians, CameraPath]:
    """n Gaussians in a 2 m box 2–4 m ahead, each drifting up to 0.2 m over the clip; 512×512, f = 500 px."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 2 - 1 + torch.tensor([0, 0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    sh = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    canon = Gaussians(means, quats / quats.norm(dim=1, keepdim=True), 0.01 + 0.02 * torch.rand(n, 3, generator=g),
                      torch.rand(n, generator=g), sh)
    times = torch.linspace(0, 1, frames)
    d_means = times[:, None, None] * (0.2 * torch.randn(1, n, 3, generator=g))
    d_quats = torch.tensor([1.0, 0, 0, 0]).repeat(frames, n, 1)
    scene = DynamicGaussians(canon, times, d_means, d_quats, torch.zeros(frames, n, 3))
    K = torch.tensor([[500.0, 0, 256], [0, 500.0, 256], [0, 0, 1]])
    return scene, CameraPath(torch.eye(4).repeat(frames, 1, 1), K.repeat(frames, 1, 1), 512, 512)


def load_seconds(url: str) -> tuple[float, float, float] | None:
    """(seconds until the page at ``url`` reports ready, ms of one time change: interpolating every Gaussian and
    writing it into Spark's PackedSplats, median of 5; the JavaScript heap once ready, MiB), or None without
    Chromium/Playwright."""
    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if chromium is None:
        return None
    with sync_playwright() as p:
        flags = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
        b = p.chromium.launch(executable_path=chromium, args=flags)
        page = b.new_page(viewport={"width": 640, "height": 560})
        t0 = time.perf_counter()
        page.goto(url)
        page.wait_for_function("window.d4s && (window.d4s.ready || window.d4s.error)", timeout=600_000)
        dt = time.perf_counter() - t0
        err = page.evaluate("d4s.error")
        heap = page.evaluate("performance.memory.usedJSHeapSize") / 2**20
        js = ("(() => { if (!d4s.config.dynamic) return null; const ms = []; for (let i = 0; i < 5; i++) {"
              " const t = performance.now(); d4s.setTime(0.1 + 0.2 * i); ms.push(performance.now() - t); }"
              " return ms.sort((a, b) => a - b)[2]; })()")
        step = None if err else page.evaluate(js)
        b.close()
    if err:
        raise RuntimeError(f"{url}: {err}")
    return dt, step, heap


def row(name: str, path: Path, payload, url: str | None = None) -> list:
    """The table's row of ``payload`` written at ``path`` (viewer.html), loaded from ``url`` (default: the file)."""
    c = payload.config
    mb = lambda x: f"{x / 2**20:.2f}"  # noqa: E731
    t = load_seconds(url or path.as_uri())
    ready, step, heap = (None, None, None) if t is None else t
    held = c["heldKeyframes"] / max(1, c["numGaussians"] * len(c["times"])) if c["times"] else 0.0
    return [name, f"{c['numGaussians']:,}", c["shDegree"], len(c["times"]), f"{held:.2f}", c["dtype"],
            "—" if c["float16ErrorPx"] is None else f"{c['float16ErrorPx']:.3f}",
            c["bytesPerHeldKey"], f"{c['bytesPerHeldKey'] * 4 / 3:.1f}",
            mb(len(payload.ply)), mb(len(payload.frames or b"")), mb(path.stat().st_size),
            "; ".join(payload.reductions) or "no", "—" if ready is None else f"{ready:.1f}",
            "—" if step is None else f"{step:.0f}", "—" if heap is None else f"{heap:.0f}"]


def served_row(tmp: Path, n: int, frames: int) -> list:
    """The row of a synthetic scene written as an output folder and served by ``diff4splat view`` (the full scene:
    its viewer.html columns are the folder's embedded, reduced copy)."""
    scene, cams = synthetic(n, 0, frames=frames)
    out = tmp / f"view_{n}"
    T, H, W = len(cams), cams.height, cams.width
    write_scene_folder(out, scene, cams, torch.zeros(T, H, W, 3), torch.ones(T, H, W), torch.ones(T, H, W), {},
                       frame_plys=False)
    del scene
    server = make_server(out, 0)
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01}, daemon=True).start()
    try:
        return row(f"synthetic, {frames} keyframes, `diff4splat view`", out / "viewer.html",
                   server.RequestHandlerClass.payload, f"http://{HOST}:{server.server_address[1]}/")
    finally:
        server.shutdown()
        server.server_close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    p.add_argument("--video", type=Path, help="also a reconstruct row: this clip, 17 frames, stride 2")
    p.add_argument("--start", type=int, default=0, help="the reconstruct clip's first frame")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        gen = Path(tmp) / "gen"
        write(generate(ROOT / "examples" / "chelsea.png"), gen)
        src = load_scene_folder(gen)  # the payload generate embedded (recomputed from the folder's files)
        rows.append(row("examples/chelsea.png (generate)", gen / "viewer.html",
                        viewer_payload(src.scene, src.cameras, fps=src.meta.get("fps", 8))))
        for n in (10_000, 65_536):
            for d in (0, 3):
                scene, cams = synthetic(n, d)
                path = Path(tmp) / f"s{n}_{d}.html"
                rows.append(row("synthetic, 17 keyframes", path, write_viewer(path, scene, cams)))
        if args.video is not None:
            rec = Path(tmp) / "rec"
            write(reconstruct(args.video, frames=17, stride=2, start=args.start, frame_plys=False), rec)
            src = load_scene_folder(rec)  # the payload reconstruct embedded (recomputed from the folder's files)
            rows.append(row(f"`reconstruct` {args.video.name}, start {args.start}", rec / "viewer.html",
                            viewer_payload(src.scene, src.cameras, fps=src.meta.get("fps", 8),
                                           background=meta_background(src.meta), eps2d=meta_eps2d(src.meta))))
        rows.append(served_row(Path(tmp), 1_311_201, 49))
    body = markdown_table(["scene", "Gaussians", "SH", "key times", "held keyframes", "dtype", "float16 error px",
                           "bytes / Gaussian / held key", "in the page (base64)", "PLY MiB", "keyframes MiB",
                           "viewer.html MiB", "reduced", "ready s", "time change ms", "page heap MiB"], rows)
    print(body)
    if args.write:
        write_section("viewer_size", f"Machine: {machine()}; headless Chromium with SwiftShader (software WebGL). "
                      f"Command: `python benchmarks/viewer_size.py --write`.\n\n{body}")


if __name__ == "__main__":
    main()
