"""The photograph's pixels' motion from the motion generator (docs/DESIGN.md, "The motion generator"): the prompt's
motion sampled at the generator's resolution, decoded at the photo layer's pixels with their depth, and linear in
time between its key times. What moves less than :data:`MIN_RELATIVE_MOTION` of its depth is still, so a prompt
that names no motion leaves a static scene.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from models.motion_generator import MotionGenerator, motion_displacements, sample_motion

__all__ = ["generated_motion", "key_time_weights", "MIN_RELATIVE_MOTION", "MOTION_STEPS", "MOTION_GUIDANCE"]

MIN_RELATIVE_MOTION = 0.01
"""A pixel whose generated displacement stays below this fraction of its z-depth at every key time does not move
(a dead zone: the sampler's residue where the prompt names no motion)."""
MOTION_STEPS = 16
"""Euler steps of the motion generator's flow (its NFE per branch)."""
MOTION_GUIDANCE = 3.0
"""Its classifier-free guidance scale."""


def key_time_weights(times: Tensor, key_frames: int) -> Tensor:
    """(Kt, K + 1) weights that interpolate values at the key times 0, 1/K, …, 1 linearly at ``times`` (Kt,) in
    [0, 1] (clamped): row i has 1 − f and f at the two keys around times[i]."""
    s = times.clamp(0, 1) * key_frames
    i = s.floor().clamp(max=key_frames - 1)
    f = (s - i)[:, None]
    cols = torch.arange(key_frames + 1, device=times.device)
    lo = (cols[None] == i.long()[:, None]).to(times.dtype)
    hi = (cols[None] == i.long()[:, None] + 1).to(times.dtype)
    return (1 - f) * lo + f * hi


def generated_motion(net: MotionGenerator, image: Tensor, depth: Tensor, times: Tensor, prompt: str, *, seed: int,
                     steps: int = MOTION_STEPS, guidance: float = MOTION_GUIDANCE) -> tuple[Tensor, Tensor]:
    """Dense motion of the photograph's pixels for ``prompt``.

    Args:
        net: the motion generator, on ``image``'s device.
        image: (H, W, 3) in [0, 1], the photograph; depth: (H, W) its z-depth, metres (+inf: no surface).
        times: (Kt,) normalised clip times in [0, 1] to give the motion at.
        prompt: non-empty; seed: the noise's (a CPU generator).

    Returns:
        (motion (Kt, H, W, 3) metres in the photograph's camera frame, 0 where still; moving (H, W) bool), float32
        on ``image``'s device.
    """
    cfg = net.config
    S = cfg.image_size
    dtype = next(net.parameters()).dtype
    small = F.interpolate(image.permute(2, 0, 1)[None].float(), size=(S, S), mode="area") * 2 - 1
    z_small = F.interpolate(depth[None, None].float(), size=(S, S), mode="nearest")[:, 0]  # keeps +inf
    motion = sample_motion(net, small.to(dtype), z_small.to(dtype), [prompt], steps=steps, guidance=guidance,
                           generator=torch.Generator(device="cpu").manual_seed(seed))
    keys = motion_displacements(motion.float(), depth[None].float(), cfg.motion_scale)[0]  # (K, H, W, 3)
    finite = torch.isfinite(depth) & (depth > 0)
    moving = finite & (keys.norm(dim=-1) > MIN_RELATIVE_MOTION * torch.where(finite, depth, 0).float()).any(0)
    keys = torch.where(moving[..., None], keys, 0.0)
    values = torch.cat([torch.zeros_like(keys[:1]), keys])  # time 0: no motion
    weights = key_time_weights(times.float(), cfg.key_frames)  # (Kt, K + 1)
    return torch.einsum("tk,khwc->thwc", weights, values), moving
