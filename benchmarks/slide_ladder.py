"""The slide ladder of :func:`diff4splat.assembly.prune.settle_generated`: novel views and the prune stage's time per
ladder.

    python benchmarks/slide_ladder.py --data DIR [DIR …] [--checkpoint DIR] [--limit N] [--write]

A generated Gaussian that would cover the photograph at the input view slides back along its source ray to the
first factor λ of a ladder at which it no longer does (:func:`diff4splat.assembly.prune.slide_behind`); the ladder is an
approximation of "the nearest free depth". Rows: ``drop`` (``factors=()``: every such Gaussian dropped, the rule
before the slide), and geometric ladders 1.05·r^k up to ~4 with ratios r = 1.25, 1.12 (the default,
:data:`diff4splat.assembly.prune.SLIDE_FACTORS`) and 1.06. For each held-out set (its clips' first frames, cameras and
captions, as ``diff4splat evaluate`` reads them) the novel frames 1…T−1 are scored against the truth with the
sampled latents and with the noise-latent ablation (:func:`training.eval_metrics.ablation_noise`): PSNR of the mean
MSE over all novel frames and beyond 45°, and the gap there. The time is the median ``prune`` stage of ``generate``
on ``examples/chelsea.png`` at 256² (5 runs after a warm-up).

``--write`` puts the table into docs/benchmarks.md (``slide_ladder``).
"""
from __future__ import annotations

import functools
import statistics
import sys
from pathlib import Path
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import held_out_run, markdown_table, publish, repo_relative  # noqa: E402

import diff4splat.pipeline as pipeline_module  # noqa: E402
from diff4splat.assembly.prune import SLIDE_FACTORS, settle_generated  # noqa: E402
from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.io import load_image  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from training.eval_metrics import ablation_noise, binned_psnr, frame_mse, psnr_from_mse, view_angles  # noqa: E402
from training.evaluate import held_out_clips  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def _ladder(ratio: float) -> tuple[float, ...]:
    """1.05·ratio^k for k = 0, 1, … while ≤ 4.2."""
    out, f = [], 1.05
    while f <= 4.2:
        out.append(f)
        f *= ratio
    return tuple(out)


LADDERS = {"drop": (), "1.05·1.25^k": _ladder(1.25), "1.05·1.12^k (default)": SLIDE_FACTORS,
           "1.05·1.06^k": _ladder(1.06)}


@torch.no_grad()
def _set_mse(pipe, clips) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Per-frame MSE of the novel frames of every clip, sampled and noise latents, and their view angles."""
    mse, angles = {"sampled": [], "noise": []}, []
    for clip in clips:
        T, H, W = clip["video"].shape[1:]
        cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), W, H, clip["times"].double())
        image, gt = clip["video"][:, 0].permute(1, 2, 0), clip["video"].permute(1, 0, 2, 3)[1:]
        res = pipe(image, cams, clip["caption"])
        noisy = pipe(image, cams, clip["caption"], video_latents=ablation_noise(res.latents.shape, 0))
        for name, r in (("sampled", res), ("noise", noisy)):
            rgb = render_path(r.scene, r.cameras, eps2d=r.eps2d, background=r.background)[0]
            mse[name].append(frame_mse(rgb[1:].permute(0, 3, 1, 2), gt))
        angles.append(view_angles(clip["viewmats"])[1:])
    return {k: torch.cat(v) for k, v in mse.items()}, torch.cat(angles)


def _prune_ms(pipe, runs: int = 5) -> float:
    width, height = pipe.output_size(256)
    image = load_image(EXAMPLE, size=(height, width))
    cams = pipe.default_cameras(resolution=256)  # generate's default path
    pipe(image, cams)  # warm-up
    return 1000 * statistics.median(pipe(image, cams).timings["prune"] for _ in range(runs))


def main() -> None:
    args, pipe, source = held_out_run(__doc__.splitlines()[0], "held-out dataset roots")
    cfg = pipe.config
    sets = {d: held_out_clips(d, cfg.height, cfg.width, cfg.num_frames, args.limit) for d in args.data}
    rows = []
    for name, factors in LADDERS.items():
        with mock.patch.object(pipeline_module, "settle_generated",
                               functools.partial(settle_generated, factors=factors)):
            cells = []
            for clips in sets.values():
                mse, angles = _set_mse(pipe, clips)
                far = {k: binned_psnr(v, angles)["45_90"][0] for k, v in mse.items()}
                cells.append(f"{psnr_from_mse(float(mse['sampled'].mean())):.2f} / {far['sampled']:.2f} / "
                             f"{far['sampled'] - far['noise']:.2f}")
            rows.append([name, len(factors), *cells, f"{_prune_ms(pipe):.0f}"])
    header = ["ladder", "factors", *(f"{d.name}: all / 45–90° / gap, dB" for d in sets), "prune ms (chelsea, 256²)"]
    publish("slide_ladder", f"The slide ladder of settle_generated ({repo_relative(source)})",
            "Novel views (sampled latents) over all frames and beyond 45°, and the noise-latent ablation's gap "
            "beyond 45°; the prune stage of generate.", markdown_table(header, rows), args.write)


if __name__ == "__main__":
    main()
