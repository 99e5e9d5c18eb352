"""Training and measuring the motion generator (:mod:`models.motion_generator`; docs/DESIGN.md, "The motion
generator"). Examples are frame 0 of :class:`data_prep.clips.ClipDataset` clips with their dense true tracks; the
loss is flow matching on the motion tensor, each cell weighted by its valid pixels, with the caption dropped (the
null embedding) at ``p_uncond``. A left-right mirror of the photograph (p = 0.5) negates x, mirrors the cells and
swaps "to the left" and "to the right" in the caption: every example also teaches the opposite word.

The motion stage's direction test (``motion_dir_stage``): for each clip whose caption names one direction
(:func:`training.direction_test.direction_query`), the motion sampled with the caption and with its direction
flipped moves the captioned object's frame-0 pixels (true depth) the named way; the magnitude ratio is the generated
mean displacement along the named way over the true one.

``python -m training.motion_generation --data ROOT [ROOT …] --steps N --into MODEL_DIR --out DIR`` trains one on the
CPU-friendly route (the examples held in memory: frame 0 and its tracks, not the clip) and writes ``MODEL_DIR``'s
model with it as ``DIR`` (``generate --checkpoint DIR``); ``python -m training.train --config
train_base_motion_generator`` trains it through the trainer (torchrun, bf16, checkpoints) with the same loss.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from data_prep.clips import ClipDataset
from data_prep.synth_world import DIRECTION_PHRASES
from diff4splat.io.output_folders import check_output_dir
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device
from diff4splat.utils.errors import run_cli
from models.bundle import Diff4SplatModel
from models.flow_matching import add_noise, sample_logit_normal, velocity_target
from models.motion_generator import (
    MotionGenerator,
    MotionGeneratorConfig,
    depth_features,
    motion_displacements,
    motion_targets,
    sample_motion,
)
from models.pretrained import MODEL_KIND

from .direction_test import direction_query, flip_direction, named_way_score

__all__ = ["MOVING_CELL", "MOVER_WEIGHT", "moving_cells", "MotionExamples", "motion_examples", "mirror",
           "mirrored_loss", "motion_generation_loss", "train_motion_generator", "MotionStageScores",
           "motion_stage_scores", "static_motion_mm", "main"]

MOVING_CELL = 0.1
"""A cell moves when its motion exceeds this at some key time (units of ``motion_scale``; at the default 0.1, 1 % of
its depth)."""
MOVER_WEIGHT = 10.0
"""Extra loss weight of a moving cell (:func:`motion_generation_loss`)."""


@dataclass
class MotionExamples:
    """Frame 0 of N clips: ``image`` (N, 3, S, S) in [−1, 1], ``depth`` (N, S, S) metres (+inf: none), ``motion``
    (N, 3K, g, g) and ``weight`` (N, 1, g, g) (:func:`models.motion_generator.motion_targets`), ``captions``, and for
    the direction test ``pixel_tracks`` (N, 2, S, S, 3) (frame 0 and the last frame, clip-world metres),
    ``valid`` (N, S, S) bool and ``dynamic`` (N,) bool."""

    image: Tensor
    depth: Tensor
    motion: Tensor
    weight: Tensor
    captions: list[str]
    pixel_tracks: Tensor
    valid: Tensor
    dynamic: Tensor

    def __len__(self) -> int:
        return len(self.captions)


def motion_examples(roots: Iterable[str], model: MotionGenerator, *, num_frames: int = 17,
                    progress: bool = False) -> MotionExamples:
    """Every clip of ``num_frames`` frames of the dataset ``roots`` at the model's image size, from each scene's
    first camera (the captions'); raises as :class:`data_prep.clips.ClipDataset`."""
    cfg = model.config
    parts: dict[str, list] = {k: [] for k in ("image", "depth", "motion", "weight", "captions", "pixel_tracks",
                                              "valid", "dynamic")}
    for root in roots:
        data = ClipDataset(root, num_frames=num_frames, height=cfg.image_size, width=cfg.image_size, num_tracks=1,
                           reference_camera="first")
        for i in tqdm(range(len(data)), disable=not progress, desc=str(root)):
            clip = data[i]
            motion, weight = motion_targets(clip["pixel_tracks"][None], clip["pixel_track_valid"][None],
                                            cfg.key_frames, cfg.grid, cfg.motion_scale)
            parts["image"].append(clip["video"][:, 0] * 2 - 1)
            parts["depth"].append(clip["depth"][0])
            parts["motion"].append(motion[0])
            parts["weight"].append(weight[0])
            parts["captions"].append(clip["caption"])
            parts["pixel_tracks"].append(clip["pixel_tracks"][[0, -1]])
            parts["valid"].append(clip["pixel_track_valid"])
            parts["dynamic"].append(clip["dynamic"])
    return MotionExamples(**{k: v if k == "captions" else torch.stack(v) for k, v in parts.items()})


def mirror(flip: Tensor, image: Tensor, depth: Tensor, motion: Tensor, weight: Tensor, captions: list[str]
           ) -> tuple[Tensor, Tensor, Tensor, Tensor, list[str]]:
    """The examples where ``flip`` (B,) bool mirrored left-right: ``image`` (B, 3, S, S), ``depth`` (B, S, S),
    ``motion`` (B, 3K, g, g) with its x components negated, ``weight`` (B, 1, g, g), and the captions with "to the
    right" and "to the left" swapped (a centred principal point is assumed, as the synthetic cameras have)."""
    right, left = DIRECTION_PHRASES[0]
    sign = torch.tensor([-1.0, 1.0, 1.0], dtype=motion.dtype, device=motion.device).repeat(motion.shape[1] // 3)
    f = flip.to(image.device)

    def where(x: Tensor, mirrored: Tensor) -> Tensor:
        return torch.where(f.reshape(-1, *[1] * (x.ndim - 1)), mirrored, x)

    swapped = [c.replace(right, "\0").replace(left, right).replace("\0", left) if bool(b) else c
               for b, c in zip(flip, captions, strict=True)]
    return (where(image, image.flip(-1)), where(depth, depth.flip(-1)),
            where(motion, motion.flip(-1) * sign[:, None, None]), where(weight, weight.flip(-1)), swapped)


def moving_cells(motion: Tensor) -> Tensor:
    """(B, 1, g, g) bool: the cells of ``motion`` (B, 3K, g, g) that move more than :data:`MOVING_CELL` at some key
    time."""
    B, C, g, _ = motion.shape
    return (motion.reshape(B, C // 3, 3, g, g).norm(dim=2).amax(1, keepdim=True) > MOVING_CELL)


def motion_generation_loss(model: MotionGenerator, image: Tensor, depth: Tensor, motion: Tensor, weight: Tensor,
                           captions: list[str], generator: torch.Generator, *, p_uncond: float = 0.1,
                           mover: float = MOVER_WEIGHT) -> Tensor:
    """The weighted flow-matching loss Σ w·|v − (ε − x0)|² / (Σ w · 3K) on a batch (shapes of
    :class:`MotionExamples`), w the cell's valid fraction times 1 + ``mover`` on :func:`moving_cells` (a moving
    object covers ~5 % of the cells: unweighted, predicting no motion is nearly optimal); σ logit-normal (SD3), ε and
    the caption drop drawn on the CPU ``generator``."""
    weight = weight * (1 + mover * moving_cells(motion).to(weight.dtype))
    B = image.shape[0]
    sigma = sample_logit_normal(B, generator=generator).to(image)
    noise = torch.randn(motion.shape, generator=generator, device="cpu").to(motion)
    drop = torch.rand(B, generator=generator, device="cpu") < p_uncond
    prompts = ["" if bool(d) else c for d, c in zip(drop, captions, strict=True)]
    v = model(add_noise(motion, noise, sigma), sigma, image, depth_features(depth), model.encode_prompts(prompts))
    err = (v - velocity_target(motion, noise)).square() * weight
    return err.sum() / (weight.sum() * motion.shape[1]).clamp_min(1e-12)


def mirrored_loss(model: MotionGenerator, image: Tensor, depth: Tensor, motion: Tensor, weight: Tensor,
                  captions: list[str], generator: torch.Generator, *, p_uncond: float = 0.1) -> Tensor:
    """:func:`motion_generation_loss` of the batch with each example mirrored (:func:`mirror`) with p = 0.5, the
    coins drawn first on the CPU ``generator``; shapes as :class:`MotionExamples`."""
    flip = torch.rand(image.shape[0], generator=generator, device="cpu") < 0.5
    return motion_generation_loss(model, *mirror(flip, image, depth, motion, weight, captions), generator,
                                  p_uncond=p_uncond)


def train_motion_generator(model: MotionGenerator, examples: MotionExamples, *, steps: int, batch_size: int = 32,
                           lr: float = 3e-4, p_uncond: float = 0.1, seed: int = 0, progress: bool = False
                           ) -> list[float]:
    """AdamW (cosine decay after 5 % warm-up) on random batches of ``examples``, each mirrored with p = 0.5; returns
    the loss of each step."""
    generator = torch.Generator(device="cpu").manual_seed(seed)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.0)
    warm = max(1, steps // 20)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda k: min(1.0, (k + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(k, steps) / steps)))
    model.train()
    losses = []
    for _ in tqdm(range(steps), disable=not progress, desc="motion generator"):
        idx = torch.randint(len(examples), (batch_size,), generator=generator, device="cpu")
        loss = mirrored_loss(model, examples.image[idx], examples.depth[idx], examples.motion[idx],
                             examples.weight[idx], [examples.captions[i] for i in idx.tolist()], generator,
                             p_uncond=p_uncond)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
    model.eval()
    return losses


@dataclass
class MotionStageScores:
    """The direction test of the motion stage: clips taking part, fractions moved the named way with the caption and
    with the flipped caption, the median ratio of the generated to the true displacement along the named way (with
    the caption), and the per-clip ratios."""

    clips: int
    caption: float
    flipped: float
    magnitude_ratio: float
    ratios: list[float]


def motion_stage_scores(model: MotionGenerator, examples: MotionExamples, *, steps: int = 16, guidance: float = 3.0,
                        seed: int = 0, batch_size: int = 32,
                        sampler: Callable[[list[int], list[str]], Tensor] | None = None) -> MotionStageScores:
    """:class:`MotionStageScores` of ``model`` on ``examples`` (module docstring); noise seeded by ``seed``.
    ``sampler(indices, prompts)`` → (b, 3K, g, g) replaces :func:`~models.motion_generator.sample_motion` (a
    baseline or the true motion)."""
    generator = torch.Generator(device="cpu").manual_seed(seed)
    if sampler is None:
        def sampler(idx: list[int], prompts: list[str]) -> Tensor:
            return sample_motion(model, examples.image[idx], examples.depth[idx], prompts, steps=steps,
                                 guidance=guidance, generator=generator)
    queries = []
    for i in range(len(examples)):
        q = direction_query({"dynamic": examples.dynamic[i], "caption": examples.captions[i],
                             "pixel_tracks": examples.pixel_tracks[i], "pixel_track_valid": examples.valid[i]})
        if q is not None:
            queries.append((i, *q))
    hits = {"caption": [], "flipped": []}
    ratios = []
    for start in range(0, len(queries), batch_size):
        chunk = queries[start:start + batch_size]
        idx = [q[0] for q in chunk]
        depth = examples.depth[idx]
        for which in hits:
            prompts = [examples.captions[i] if which == "caption" else flip_direction(examples.captions[i])
                       for i in idx]
            last = motion_displacements(sampler(idx, prompts), depth, model.config.motion_scale)[:, -1]  # metres
            for j, (i, axis, sign, moving) in enumerate(chunk):
                x0 = examples.pixel_tracks[i, 0].reshape(-1, 3)
                positions = torch.stack([x0, x0 + last[j].reshape(-1, 3)], dim=1)
                kept = torch.isfinite(depth[j]).reshape(-1)
                ok, along = named_way_score(positions, kept, moving, axis, sign if which == "caption" else -sign)
                hits[which].append(ok)
                if which == "caption":
                    truth = examples.pixel_tracks[i].permute(1, 2, 0, 3).reshape(-1, 2, 3)
                    _, true_along = named_way_score(truth, kept, moving, axis, sign)
                    ratios.append(along / true_along if true_along > 0 else float("nan"))
    n = len(queries)
    return MotionStageScores(n, float(np.mean(hits["caption"])) if n else float("nan"),
                             float(np.mean(hits["flipped"])) if n else float("nan"),
                             float(np.nanmedian(ratios)) if n else float("nan"), ratios)


def static_motion_mm(model: MotionGenerator, examples: MotionExamples, *, steps: int = 16, guidance: float = 3.0,
                     seed: int = 0, batch_size: int = 32) -> float:
    """The mean length (mm) of the displacement by the clip's end that ``model`` gives the valid pixels of the
    static clips of ``examples`` with their captions (which name no motion); NaN without a static clip."""
    idx = [i for i in range(len(examples)) if not bool(examples.dynamic[i])]
    generator = torch.Generator(device="cpu").manual_seed(seed)
    lengths = []
    for start in range(0, len(idx), batch_size):
        chunk = idx[start:start + batch_size]
        depth = examples.depth[chunk]
        motion = sample_motion(model, examples.image[chunk], depth, [examples.captions[i] for i in chunk],
                               steps=steps, guidance=guidance, generator=generator)
        last = motion_displacements(motion, depth, model.config.motion_scale)[:, -1].norm(dim=-1)  # (b, S, S)
        lengths += [float(d[v].mean()) for d, v in zip(last, examples.valid[chunk], strict=True) if bool(v.any())]
    return 1000 * float(np.mean(lengths)) if lengths else float("nan")


def main(argv: list[str] | None = None) -> int:
    """``python -m training.motion_generation`` (module docstring); one line and exit code 2 on bad input."""
    return run_cli("motion_generation", lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    ap = argparse.ArgumentParser(prog="python -m training.motion_generation",
                                 description="Train a motion generator and add it to a model folder.")
    ap.add_argument("--data", nargs="+", required=True, help="dataset roots (data_prep format)")
    ap.add_argument("--into", required=True, type=Path, help="the model folder it joins (e.g. models/weights/base)")
    ap.add_argument("--out", required=True, type=Path, help="output model folder (replaced only if a saved model)")
    ap.add_argument("--steps", type=int, default=2400)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--lr", type=float, default=4e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--text-attention", action="store_true", help="cross-attention to the prompt's tokens too")
    ap.add_argument("--device", default=AUTO, help=DEVICE_HELP)
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    check_output_dir(args.out, inputs=[args.into, *args.data], kind=MODEL_KIND, parents=True, overwrite_flag=None)
    model = Diff4SplatModel.from_pretrained(args.into)  # both checked before the examples are read
    size = model.config.height
    torch.manual_seed(args.seed)
    net = MotionGenerator(MotionGeneratorConfig(image_size=size, text_attention=args.text_attention)).to(device)
    examples = motion_examples(args.data, net, num_frames=model.config.num_frames, progress=not args.quiet)
    for name in ("image", "depth", "motion", "weight"):
        setattr(examples, name, getattr(examples, name).to(device))
    losses = train_motion_generator(net, examples, steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                                    seed=args.seed, progress=not args.quiet)
    model.config = dataclasses.replace(model.config, motion_generator=net.config)
    model.motion_generator = net.cpu()
    model.save_pretrained(args.out)
    print(f"wrote {args.out}: {len(examples)} examples, {args.steps} steps, loss {np.mean(losses[:50]):.3f} → "
          f"{np.mean(losses[-50:]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
