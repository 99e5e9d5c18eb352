"""What ``generate``'s deformation is worth to its renders: novel-view PSNR of the same generation with its
deformation and with it dropped, on held-out synthetic clips.

    python benchmarks/deformation_ablation.py --data DIR [DIR ...] [--checkpoint DIR] [--device cpu] [--write]

Each clip of a ``data_prep synth`` set (first camera, the model's size) is generated once from its first frame along
its own camera path with its caption as the prompt (sampled latents, as ``diff4splat evaluate``'s ``psnr_novel``).
Its scene is rendered along that path twice, as generated and with every Δμ, Δq and Δs dropped
(``DynamicGaussians.without_deformation`` with an infinite tolerance), and scored against the clip's true frames
1…T−1 (pooled MSE over the clips' frames, RGB in [0, 1]), for the dynamic and the static clips of each set.
``--write`` puts the table into docs/benchmarks.md (section ``deformation_ablation``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, parse_pipeline_run, publish  # noqa: E402

from diff4splat.cameras import CameraPath  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from training.eval_metrics import psnr_from_mse  # noqa: E402
from training.evaluate import held_out_clips  # noqa: E402


@torch.no_grad()
def clip_errors(pipe, clip: dict) -> tuple[float, float]:
    """Mean squared error of frames 1…T−1 rendered from ``clip``'s generation (as generated, deformation dropped)."""
    cfg = pipe.config
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), cfg.width, cfg.height, clip["times"].double())
    res = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"])
    truth = clip["video"].permute(1, 2, 3, 0)[1:]  # (T − 1, H, W, 3)
    errors = []
    for scene in (res.scene, res.scene.without_deformation(float("inf"))):
        colors = render_path(scene, res.cameras.to(scene.canonical.means.device), eps2d=res.eps2d,
                             background=res.background)[0].cpu()
        errors.append(float(((colors[1:] - truth) ** 2).mean()))
    return errors[0], errors[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="held-out sets (data_prep synth)")
    args, loaded = parse_pipeline_run(ap)
    pipe, cfg = loaded.pipeline, loaded.pipeline.config
    rows = []
    for root in args.data:
        found = {}
        for clip in held_out_clips(root, cfg.height, cfg.width, cfg.num_frames, None):
            found.setdefault("dynamic" if bool(clip["dynamic"]) else "static", []).append(clip_errors(pipe, clip))
        for kind, errors in sorted(found.items()):
            deformed, still = (psnr_from_mse(sum(e[i] for e in errors) / len(errors)) for i in (0, 1))
            rows.append([root.name, kind, len(errors), f"{deformed:.2f}", f"{still:.2f}", f"{deformed - still:+.2f}"])
            print(" | ".join(str(c) for c in rows[-1]), flush=True)
    table = markdown_table(["set", "kind", "clips", "with its deformation (dB)", "deformation dropped (dB)",
                            "gain (dB)"], rows)
    publish("deformation_ablation", "generate's deformation: novel views with it and without it",
            f"{args.note} Frames 1…T−1 along each clip's own path, the same generation rendered twice; pooled PSNR."
            .strip(), table, args.write)


if __name__ == "__main__":
    main()
