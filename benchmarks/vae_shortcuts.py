"""Held-out reconstruction PSNR of the tiny VAE trained with and without the DC-AE shortcuts.

    python benchmarks/vae_shortcuts.py --data data/synth_train --heldout data/synth_heldout [--steps 600] [--write]

Both variants train from the same seed on the same batches (the VAE objective of ``training``:
L1 + 1e-3·KL per element, posterior samples, AdamW lr 2e-3, gradient clipping at 1, 9-frame 64² clips,
batch 4) and are scored every 200 steps on the first 16 held-out clips (posterior mean, decoded). Two
reference rows need no training: each image's mean colour, and an 8×8 area downsample with bilinear
upsampling (3 numbers per 8×8 block). ``--write`` puts the table into docs/benchmarks.md (section
``vae_shortcuts``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, write_section  # noqa: E402

from data_prep.clips import ClipConfig, ClipDataset  # noqa: E402
from models.vae import VideoVAE, VideoVAEConfig, kl_divergence  # noqa: E402


def _videos(root: str, limit: int | None) -> torch.Tensor:
    ds = ClipDataset(root, ClipConfig(num_frames=9, height=64, width=64, scenes="all", plucker="raw", seed=0))
    n = len(ds) if limit is None else min(limit, len(ds))
    return torch.stack([ds[i]["video"] for i in range(n)]) * 2 - 1  # (N, 3, 9, 64, 64) in [−1, 1]


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:  # pixels in [−1, 1]
    return float(-10 * torch.log10(((a.clamp(-1, 1) - b) / 2).pow(2).mean()))


def _train(shortcuts: bool, train: torch.Tensor, held: torch.Tensor, steps: int, every: int) -> tuple[list, float]:
    torch.manual_seed(0)
    vae = VideoVAE(VideoVAEConfig(shortcuts=shortcuts))
    opt = torch.optim.AdamW(vae.parameters(), lr=2e-3)
    gen = torch.Generator().manual_seed(0)
    scores, t0 = [], time.perf_counter()
    for step in range(1, steps + 1):
        x = train[torch.randint(0, len(train), (4,), generator=gen)]
        recon, mean, logvar = vae(x, sample_posterior=True, generator=gen)
        loss = (recon - x).abs().mean() + 1e-3 * kl_divergence(mean, logvar).mean() / mean[0].numel()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(vae.parameters(), 1.0)
        opt.step()
        opt.zero_grad()
        if step % every == 0 or step == steps:
            with torch.no_grad():
                scores.append((step, _psnr(vae.decode(vae.encode(held)[0]), held)))
    return scores, (time.perf_counter() - t0) / steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="training dataset root")
    ap.add_argument("--heldout", required=True, help="held-out dataset root")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    train, held = _videos(args.data, None), _videos(args.heldout, 16)
    first = held[:, :, :1, :, :]
    mean_colour = _psnr(first.mean((3, 4), keepdim=True).expand_as(first), first)
    area = F.interpolate(F.interpolate(first[:, :, 0], size=(8, 8), mode="area"), size=(64, 64), mode="bilinear",
                         align_corners=False)
    rows = [["per-image mean colour (first frames)", "—", f"{mean_colour:.2f}", "—"],
            ["8×8 area down, bilinear up (first frames)", "—", f"{_psnr(area, first[:, :, 0]):.2f}", "—"]]
    for shortcuts in (False, True):
        scores, sec = _train(shortcuts, train, held, args.steps, 200)
        for step, psnr in scores:
            rows.append([f"VAE, shortcuts={'on' if shortcuts else 'off'}", step, f"{psnr:.2f}", f"{1000 * sec:.0f}"])
    body = (f"### Tiny VAE with and without the DC-AE shortcuts ({len(train)} training clips, 16 held-out clips, "
            "9 frames, 64²)\n\n"
            f"`python benchmarks/vae_shortcuts.py --data data/synth_train --heldout data/synth_heldout --steps "
            f"{args.steps} --write`. Machine: {machine()}. Same seed and batches for both variants; PSNR of the "
            "posterior-mean round trip on all 9 frames (reference rows: first frames only).\n\n"
            + markdown_table(["model", "steps", "held-out PSNR dB", "ms / step"], rows))
    print(body)
    if args.write:
        write_section("vae_shortcuts", body)


if __name__ == "__main__":
    main()
