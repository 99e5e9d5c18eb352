"""``reconstruct`` between the frames it was given: in-between frames rendered from the 4D scene against holding
the previous frame and blending the two neighbours.

    python benchmarks/reconstruct_interp.py (--video FILE_OR_DIR [--start K] [--stride S] | --data DIR)
        [--frames T] [--resolution R] [--ablation] [--checkpoint DIR] [--device cpu] [--write]

The clip given to :func:`diff4splat.reconstruct.reconstruct` is every other frame (frames start, start + 2S, …,
T of them); the T − 1 frames between them are held out. Each is rendered from the scene at its time (halfway
between its neighbours' clip times) and camera, and scored (PSNR of the mean squared error over all held-out
frames, RGB in [0, 1]) against the true frame, beside baselines that need no scene: the previous given frame held,
the mean of the two given neighbours (a cross-fade is not motion), and a 2D frame interpolation from the same optical
flow (DIS between the two neighbours, :func:`~diff4splat.geometry.scene_flow.optical_flow` at ``reconstruct``'s
upsampling; Super SloMo's flows to the middle, Jiang et al. 2018 eq. 4 at t = ½, each neighbour warped by
``kornia.geometry.transform.remap`` and the two averaged, no occlusion reasoning), for each ``--layers`` choice. The
PSNR is also given over the moving pixels alone (where the two neighbours differ by more than 0.05 in a channel).
``--video``: a real video, still camera (the default of ``reconstruct``); ``--data``: each scene of a
``data_prep synth`` set (17 frames, so T = 9 at stride 2), its first camera's frames and true cameras.
``--write`` puts the table into docs/benchmarks.md (section ``reconstruct_interp_<label>``, ``--label`` default:
the video's or set's name). ``--strip PNG`` saves, for the first clip and ``--layers every``, four held-out frames
(columns) as the true frame, the 4D scene's render, the blend of the two neighbours and the previous frame held
(rows, labelled), to look at. ``--ablation`` scores, instead of the two layer choices, ``--layers every`` as
shipped beside variants of its layers (:data:`ABLATION`: the odd layers' push along their rays, 0 and 3 % against
1.5 %; every link of flow checked against the first links followed unchecked; ``Diff4SplatPipeline.reconstruct``'s
``order_offset`` and ``unchecked``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from kornia.geometry.transform import remap

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, parse_pipeline_run, publish, save_strip  # noqa: E402

from diff4splat.assembly.layers import FLOW_SIZE, LAYER_ORDER_OFFSET, LAYERS  # noqa: E402
from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.geometry.scene_flow import optical_flow  # noqa: E402
from diff4splat.io import load_cameras_json  # noqa: E402
from diff4splat.io.image import preprocess_image  # noqa: E402
from diff4splat.io.video_input import read_video_clip  # noqa: E402
from diff4splat.reconstruct import reconstruct, still_cameras  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from training.eval_metrics import psnr_from_mse  # noqa: E402

MOVING_DIFFERENCE = 0.05
"""A pixel is moving when its two given neighbours differ by more than this in some channel (RGB in [0, 1])."""
STRIP_LABELS = {"scene": "4D scene", "hold": "hold", "blend": "blend", "flow": "2D flow interp."}
BASELINES = {"hold": "previous given frame held", "blend": "mean of the two given neighbours",
             "flow": "2D flow interpolation (DIS, Super SloMo's t = ½ flows)"}


def held_out_scores(loaded, video: Path, frames: int, stride: int, start: int, resolution: int | None,
                    cameras: CameraPath | None, layers: str, strip: Path | None = None,
                    order_offset: float = LAYER_ORDER_OFFSET, unchecked: int | None = None) -> dict[str, float]:
    """Squared errors summed over the held-out frames of one clip ({"scene", "hold", "blend", "flow"}: sum of
    per-frame MSE; the same keys + " moving": the squared errors' sum over the moving pixels, and "moving", their
    count; "pixels": all pixels' count), the held-out frames' count, the seconds ``reconstruct`` took and its
    Gaussians. ``cameras``: the video's cameras at every frame (None: still); ``strip``: where to save the frame
    strip (module docstring); ``order_offset``, ``unchecked``: as :func:`~diff4splat.assembly.layers.layered_scene`."""
    pipe = loaded.pipeline
    given = [start + 2 * stride * i for i in range(frames)]
    between = [g + stride for g in given[:-1]]
    width, height = pipe.output_size(resolution if resolution is not None else max(256, pipe.config.height))
    path = None if cameras is None else _subset(cameras, given).fitted(width, height)
    t0 = time.perf_counter()
    gen = reconstruct(video, path, pipeline=loaded, frames=frames, stride=2 * stride, start=start,
                      resolution=resolution, layers=layers, order_offset=order_offset, unchecked=unchecked)
    seconds = time.perf_counter() - t0
    H, W = gen.colors.shape[1:3]
    clip = read_video_clip(video, 2 * frames - 1, stride, start)
    truth = torch.stack([preprocess_image(f, (H, W)) for f in clip.frames])  # (2T − 1, H, W, 3)
    times = (torch.arange(frames - 1, dtype=torch.float64) + 0.5) / (frames - 1)
    if cameras is None:
        mid = still_cameras(pipe, frames - 1, W, H)
        mid = CameraPath(mid.viewmats, mid.Ks, W, H, times.float())
    else:  # the in-between frames' own cameras, in the clip's frame (relative to its first camera)
        mid = _subset(cameras, between).fitted(W, H)
        first = cameras.viewmats[given[0]].double()
        mid = CameraPath((mid.viewmats.double() @ torch.linalg.inv(first)).float(), mid.Ks, W, H, times.float())
    scene = gen.result.scene
    rendered = render_path(scene, mid.to(scene.canonical.means.device), eps2d=gen.result.eps2d,
                           background=gen.result.background)[0].cpu()
    target, prev, nxt = truth[1::2], truth[0:-1:2], truth[2::2]
    moving = (nxt - prev).abs().amax(dim=-1) > MOVING_DIFFERENCE  # (T − 1, H, W)
    outputs = {"scene": rendered, "hold": prev, "blend": (prev + nxt) / 2,
               "flow": flow_interpolation(prev, nxt, max(1, round(FLOW_SIZE / H)))}
    if strip is not None:
        save_strip(strip, {"true": target, **{STRIP_LABELS[k]: v for k, v in outputs.items()}})
    scores = {"frames": len(between), "seconds": seconds, "gaussians": scene.num_gaussians,
              "moving": int(moving.sum()), "pixels": moving.numel()}
    for key, frames_out in outputs.items():
        error = ((frames_out - target) ** 2).mean(dim=-1)  # (T − 1, H, W)
        scores[key], scores[f"{key} moving"] = float(error.mean(dim=(1, 2)).sum()), float(error[moving].sum())
    return scores


def flow_interpolation(prev: torch.Tensor, nxt: torch.Tensor, upsample: int) -> torch.Tensor:
    """The frames (N, H, W, 3) in [0, 1] halfway between ``prev`` and ``nxt`` (N, H, W, 3) in [0, 1], from their DIS
    flows (:func:`optical_flow` on the frames upsampled ``upsample``×; module docstring): F_½→0 = (F_1→0 − F_0→1)/4,
    F_½→1 = −F_½→0 pixels (Jiang et al. 2018, eq. 4 at t = ½), each neighbour warped by ``remap``, on their device."""
    a, b = prev.permute(0, 3, 1, 2), nxt.permute(0, 3, 1, 2)
    half = (optical_flow(b, a, upsample=upsample) - optical_flow(a, b, upsample=upsample)) / 4  # (N, H, W, 2)
    H, W = a.shape[-2:]
    y, x = torch.meshgrid(torch.arange(H, dtype=a.dtype, device=a.device),
                          torch.arange(W, dtype=a.dtype, device=a.device), indexing="ij")
    warp = lambda img, f: remap(img, x + f[..., 0], y + f[..., 1], padding_mode="border", align_corners=True)  # noqa: E731
    return ((warp(a, half) + warp(b, -half)) / 2).permute(0, 2, 3, 1)


def _subset(cameras: CameraPath, index: list[int]) -> CameraPath:
    return CameraPath(cameras.viewmats[index], cameras.Ks[index], cameras.width, cameras.height)


ABLATION = (("shipped", LAYER_ORDER_OFFSET, None), ("odd layers not pushed back (offset 0)", 0.0, None),
            ("odd layers pushed back 3 %", 0.03, None),
            ("every link of flow checked (unchecked 0)", LAYER_ORDER_OFFSET, 0))
"""``--ablation``'s variants of the layers, ``--layers every``: (name, order_offset, unchecked)."""


def scored(loaded, jobs, frames: int, args, layers: str, order_offset: float, unchecked: int | None,
           strip: Path | None) -> tuple[dict[str, float], dict[str, float]]:
    """(PSNR of the 4D scene and each baseline, all pixels and moving ones; the summed counts) over ``jobs``."""
    keys = ("scene", *BASELINES)
    total = dict.fromkeys([*keys, *(f"{k} moving" for k in keys), "moving", "pixels", "frames", "seconds",
                           "gaussians"], 0)
    for j, (video, cameras) in enumerate(jobs):
        scores = held_out_scores(loaded, video, frames, args.stride, args.start, args.resolution, cameras, layers,
                                 strip if j == 0 else None, order_offset, unchecked)
        total = {k: total[k] + scores[k] for k in total}
        print(video, layers, order_offset, unchecked,
              {k: round(psnr_from_mse(scores[k] / scores["frames"]), 2) for k in keys}, flush=True)
    n = total["frames"]
    psnr = {k: psnr_from_mse(total[k] / n) for k in keys}
    psnr.update({f"{k} moving": psnr_from_mse(total[f"{k} moving"] / max(total["moving"], 1)) for k in keys})
    return psnr, total


def scene_row(name: str, psnr: dict[str, float], total: dict[str, float], clips: int) -> list:
    return [name, f"{psnr['scene']:.2f}", f"{psnr['scene moving']:.2f}", f"{psnr['scene'] - psnr['hold']:+.2f}",
            f"{psnr['scene'] - psnr['blend']:+.2f}", f"{total['seconds'] / clips:.1f}",
            f"{total['gaussians'] // clips:,}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--video", type=Path, help="a real video file or folder of frames (still camera)")
    source.add_argument("--data", type=Path, help="a data_prep synth set (first camera of every scene)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1, help="stride of the video's frames (the clip takes every 2nd)")
    ap.add_argument("--frames", type=int, default=None, help="T given frames (default: 17, or 9 for --data)")
    ap.add_argument("--resolution", type=int, default=None)
    ap.add_argument("--strip", type=Path, default=None, help="save a frame strip of the first clip (PNG)")
    ap.add_argument("--ablation", action="store_true",
                    help="the layers' variants (ABLATION) instead of the layer choices, in section "
                         "reconstruct_ablation_<label>")
    args, loaded = parse_pipeline_run(ap)
    if args.video is not None:
        jobs = [(args.video, None)]
        frames = args.frames or 17
    else:
        jobs = [(d / "cam00" / "rgb", load_cameras_json(d / "cam00" / "cameras.json"))
                for d in sorted(args.data.iterdir()) if (d / "cam00").is_dir()]
        frames = args.frames or 9
    rows = []
    if args.ablation:
        for name, offset, unchecked in ABLATION:
            psnr, total = scored(loaded, jobs, frames, args, "every", offset, unchecked, None)
            rows.append(scene_row(name, psnr, total, len(jobs)))
    else:
        for layers in LAYERS:
            strip = args.strip if layers == "every" else None
            psnr, total = scored(loaded, jobs, frames, args, layers, LAYER_ORDER_OFFSET, None, strip)
            rows.append(scene_row(f"4D scene, `--layers {layers}`", psnr, total, len(jobs)))
    rows += [[label, f"{psnr[k]:.2f}", f"{psnr[k + ' moving']:.2f}", "—", "—", "—", "—"]
             for k, label in BASELINES.items()]
    table = markdown_table(["in-between frames" if not args.ablation else "`--layers every`", "PSNR (dB)",
                            "moving pixels (dB)", "− hold", "− blend", "`reconstruct` s per clip", "Gaussians"], rows)
    what = str(args.video) if args.video is not None else f"{len(jobs)} scenes of {args.data}"
    label = args.label or (args.video.stem if args.video is not None else args.data.name)
    kind = "reconstruct_ablation" if args.ablation else "reconstruct_interp"
    title = "`reconstruct`'s layers, variants," if args.ablation else "`reconstruct`"
    publish(f"{kind}_{label}", f"{title} between its frames ({what}, start {args.start}, {frames} given frames)",
            f"{args.note} {total['frames']} held-out frames, rendered at their times "
            f"({100 * total['moving'] / total['pixels']:.1f} % of their pixels moving); `reconstruct`'s "
            "seconds: load excluded (encode, LDRM, motion, assembly, rendering the given frames).".strip(),
            table, args.write)


if __name__ == "__main__":
    main()
