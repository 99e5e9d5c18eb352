"""Novel views with the true depth given (`generate --depth`), against the renderer's own oracle.

    python benchmarks/true_depth.py --data DIR [DIR …] [--checkpoint DIR] [--limit N] [--write]

For each held-out set (one group of rows per ``--data`` directory) and each of its clips (its first frame,
cameras and caption, as ``diff4splat evaluate`` reads them), frames 1…T−1 are rendered and compared with the
ground truth (PSNR of the mean MSE over all novel frames, and by view angle from the input camera,
:data:`training.eval_metrics.ANGLE_BINS`):

- ``oracle``: the photo layer alone (:func:`diff4splat.assembly.photo.photo_layer`) built from the true first frame and
  its true depth (invalid pixels at the largest valid depth), static, rendered with the scene's dilation over the
  photograph's mean colour: pixel-aligned Gaussians of what was observed, moved by the true geometry;
- ``generate, true depth``: the pipeline given the true depth map (``depth=``, metric; invalid pixels are holes
  the network's depth fills), sampled latents, rendered as ``generate`` renders it;
- ``generate``: the same without the depth map (the network's depth);
- ``repeat frame 0``: the input frame for every later frame.

``--write`` puts the table into docs/benchmarks.md (``true_depth``).
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import held_out_run, markdown_table, publish, repo_relative  # noqa: E402

from diff4splat.assembly.photo import PHOTO_EPS2D, photo_layer  # noqa: E402
from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from diff4splat.scene.dynamic import DynamicGaussians  # noqa: E402
from training.eval_metrics import ANGLE_BINS, binned_psnr, frame_mse, psnr_from_mse, repeat_baselines, view_angles  # noqa: E402
from training.evaluate import held_out_clips  # noqa: E402

VARIANTS = ("oracle", "generate, true depth", "generate", "repeat frame 0")


@torch.no_grad()
def clip_mse(pipe: Diff4SplatPipeline, clip: dict) -> dict[str, torch.Tensor]:
    """(T − 1,) per-frame MSE of the novel frames of one clip for each of :data:`VARIANTS`."""
    T, H, W = clip["video"].shape[1:]
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), W, H, clip["times"].double())
    image = clip["video"][:, 0].permute(1, 2, 0)
    gt = clip["video"].permute(1, 0, 2, 3)[1:]
    ok = clip["depth_valid"][0]
    depth = clip["depth"][0]
    background = tuple(float(c) for c in image.reshape(-1, 3).mean(0))
    filled = torch.where(ok, depth, depth[ok].max() if ok.any() else torch.tensor(10.0))
    rel = cams.relative_to_first().to(dtype=torch.float32)
    layer, _ = photo_layer(image, filled.float(), rel.viewmats[0], rel.Ks[0])
    out = {"oracle": render_path(DynamicGaussians(layer), rel, eps2d=PHOTO_EPS2D, background=background)[0]}
    for name, given in (("generate, true depth", torch.where(ok, depth, float("nan")).float()), ("generate", None)):
        res = pipe(image, cams, clip["caption"], depth=given)
        out[name] = render_path(res.scene, res.cameras, eps2d=res.eps2d, background=res.background)[0]
    mse = {k: frame_mse(v[1:].permute(0, 3, 1, 2), gt) for k, v in out.items()}
    mse["repeat frame 0"] = repeat_baselines(clip["video"])["repeat"]
    return mse


def main() -> None:
    args, pipe, source = held_out_run(__doc__.splitlines()[0], "held-out dataset roots, one row group each")
    cfg = pipe.config
    rows = []
    for data in args.data:
        clips = held_out_clips(data, cfg.height, cfg.width, cfg.num_frames, args.limit)
        acc: dict[str, list[torch.Tensor]] = {k: [] for k in VARIANTS}
        angles = []
        for clip in clips:
            for k, v in clip_mse(pipe, clip).items():
                acc[k].append(v)
            angles.append(view_angles(clip["viewmats"])[1:])
        A = torch.cat(angles)
        for k in VARIANTS:
            m = torch.cat(acc[k])
            bins = binned_psnr(m, A)
            rows.append([f"{data.name} ({len(clips)} clips)", k, f"{psnr_from_mse(float(m.mean())):.2f} ({len(A)})",
                         *(f"{bins[n][0]:.2f} ({bins[n][1]})" if bins[n][1] else "–" for n, _, _ in ANGLE_BINS)])
    used = [i for i in range(len(ANGLE_BINS)) if any(r[3 + i] != "–" for r in rows)]  # bins some set has frames in
    names = [f"{ANGLE_BINS[i][1]:g}–{ANGLE_BINS[i][2]:g}°" for i in used]
    rows = [r[:3] + [r[3 + i] for i in used] for r in rows]
    table = markdown_table(["held-out set", "novel views, PSNR dB (frames)", "all frames", *names], rows)
    sets = ", ".join(d.name for d in args.data)
    publish("true_depth", f"Novel views with the true depth given ({repo_relative(source)}; {sets})",
            "PSNR of the mean MSE over the novel frames, by view angle from the input camera (frame count; – : no "
            "frame in that bin).", table, args.write)


if __name__ == "__main__":
    main()
