"""Blockiness of the LDRM's decoded maps: gradient energy on the latent grid's block borders against inside.

    python benchmarks/blockiness.py --data DIR [--checkpoint LABEL=DIR ...] [--clips N] [--write]

Each checkpoint's LDRM decodes the held-out clips' true-video latents (its VAE; no sampling, so every checkpoint
reads the same kind of input) into per-pixel maps of every source frame: log ray distance, colour and opacity.
For a map x (S, H, W[, C]) and the decoder's block size f (``vae_spatial``·``patch_size`` = 8 pixels: one token),
the squared finite differences between horizontally and vertically adjacent pixels are split into those that
cross a block border (columns/rows j with (j + 1) mod f = 0) and all others:

    blockiness = mean(Δ² across borders) / mean(Δ² inside blocks)

1 means the borders are no different from anywhere else; a decoder that paints every token into its own f×f block
(the paper's kernel = stride transposed convolution) puts the steps between tokens on the borders and is ≫ 1.
The maps of source frame 0 are included (the photo layer uses frame 0's distance). "scene colour" is the colour the
scene's later source frames carry: the LDRM's, or for ``generated_colors: video`` the VAE-decoded video's
(:func:`diff4splat.assembly.assemble.video_colors`). ``--write`` puts the table into docs/benchmarks.md
(``blockiness``).
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

from data_prep.clips import ClipConfig, ClipDataset  # noqa: E402
from diff4splat.assembly.assemble import video_colors  # noqa: E402
from diff4splat.pipeline import load_model  # noqa: E402
from diff4splat.utils.devices import resolve_device  # noqa: E402
from models.ldrm import source_frame_indices  # noqa: E402
from training.eval_metrics import blockiness  # noqa: E402


@torch.no_grad()
def measure(checkpoint: Path, data: Path, clips: int, device: torch.device) -> dict[str, float]:
    """Blockiness of the log distance, colour and opacity maps, pooled over ``clips`` held-out clips, and of the
    colours the scene's later source frames carry (the LDRM's, or the decoded video's for ``generated_colors:
    video``)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, _ = load_model(checkpoint, None)
    model = model.to(device).eval()
    cfg = model.config
    ds = ClipDataset(data, ClipConfig(num_frames=cfg.num_frames, height=cfg.height, width=cfg.width,
                                      reference_camera="first", plucker="packed"))
    maps: dict[str, list[torch.Tensor]] = {"log distance": [], "colour": [], "opacity": [], "scene colour": [],
                                           "true frames": []}
    sources = torch.tensor(source_frame_indices(model.ldrm.config.gaussian_frames, cfg.vae.num_latent_frames(
        cfg.num_frames), cfg.vae.temporal_factor), device=device)
    for i in range(min(clips, len(ds))):
        item = ds[i]
        video = item["video"][None].to(device)
        latents = model.vae.encode_latents(video * 2 - 1)
        out = model.ldrm(latents, item["plucker_packed"][None].to(device), None, video[:, :, 0] * 2 - 1)
        maps["log distance"].append(out.distance[0].log())  # (S, H, W)
        maps["colour"].append(out.colors[0].permute(0, 3, 1, 2))  # (S, 3, H, W)
        maps["opacity"].append(out.opacities[0])
        if cfg.generated_colors == "video":  # what generate's later source frames carry (assemble.video_colors)
            out = video_colors(out, model.vae.decode_latents(latents), sources)
        maps["scene colour"].append(out.colors[0, 1:].permute(0, 3, 1, 2))  # (S − 1, 3, H, W)
        maps["true frames"].append(video[0][:, sources[1:]].transpose(0, 1))  # (S − 1, 3, H, W): the baseline
    block = model.ldrm.config.vae_spatial * model.ldrm.config.patch_size
    return {k: blockiness(torch.stack(v), block) for k, v in maps.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="held-out scenes (data_prep synth)")
    ap.add_argument("--checkpoint", action="append", default=[], metavar="LABEL=DIR",
                    help="checkpoint to measure (repeatable; default: shipped=models/weights/base)")
    ap.add_argument("--clips", type=int, default=24)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    device = resolve_device(args.device)
    checkpoints = args.checkpoint or ["shipped=models/weights/base"]
    rows, truth = [], None
    for item in checkpoints:
        label, _, folder = item.partition("=")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, _ = load_model(Path(folder), None)
        head = model.ldrm.config.head
        result = measure(Path(folder), args.data, args.clips, device)
        truth = result.pop("true frames")
        rows.append([label, head, *(f"{v:.2f}" for v in result.values())])
        print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(["checkpoint", "LDRM head", "log distance", "colour", "opacity",
                            "scene colour (frames 1…)"], rows)
    publish("blockiness", f"Blockiness of the LDRM's decoded maps ({args.clips} held-out clips, true-video "
            "latents)", "Mean squared neighbour difference across the 8-pixel token borders ÷ inside the blocks, "
            "over every source frame; 1 = no blocks; the true frames of the same source frames (1…) score "
            f"{truth:.2f}. \"scene colour\" is what the generated frames' Gaussians carry: the LDRM's colours, or "
            "with `generated_colors: video` the VAE decoder's frames.", table, args.write)

if __name__ == "__main__":
    main()
