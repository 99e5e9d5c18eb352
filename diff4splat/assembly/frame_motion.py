"""The LDRM's motion path: each source pixel's 3D position at every key time, read from the frames (docs/DESIGN.md,
"The motion path"). :func:`frame_motion` projects each source pixel X_s = o + distance·d into the frame nearest
each key time and lets the motion network (:mod:`models.motion`) return a residual flow f (pixels) and log z-depth
ratio r: Δμ(t) = unproject(u + f, z·eʳ) − X_s, so zero flow is zero motion. Key times are visited outwards from
each source's own, from the previous estimate (RAFT's warm start, Teed & Deng 2020, §3.3); Δq and Δs are the token
network's where a pixel moves, else the identity. The geometry carries no gradient."""
from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from diff4splat.cameras import camera_rays, project_points, unproject_pixels
from models.deformation import IDENTITY_QUAT
from models.ldrm import LDRMOutput
from models.motion import MotionNetwork

__all__ = ["frame_motion", "nearest_frames"]


def nearest_frames(times: Tensor, frame_times: Tensor) -> Tensor:  # (K,), (T,) → (K,) long
    """(K,) long index into ``frame_times`` (T,) of the frame nearest each of ``times`` (K,) (earlier on a tie)."""
    return (times[:, None] - frame_times[None, :]).abs().argmin(dim=1)


def frame_motion(
    net: MotionNetwork,
    out: LDRMOutput,
    frames: Tensor,  # (T, 3, H, W) in [0, 1], the model resolution
    frame_times: Tensor,  # (T,)
    viewmats: Tensor,  # (T, 4, 4) world-to-camera of the frames
    Ks: Tensor,  # (T, 3, 3) pixels at (H, W)
    sources: Tensor,  # (S,) long: the source frames' indices into the frames
    times: Tensor,  # (K,) key times
) -> LDRMOutput:
    """``out`` (batch 1) with its deformation maps read from ``frames`` by ``net`` (module docstring).

    Returns:
        An :class:`LDRMOutput` with d_means (1, K, S, H, W, 3) metres, world frame, and d_quats (1, K, S, H, W, 4) /
        d_scales (1, K, S, H, W, 3): ``out``'s where a pixel moves at that time, else (or without any) the identity.

    Raises:
        ValueError: ``out`` not of batch 1, or frames / cameras / times whose shapes do not match.
    """
    distance = out.distance  # (1, S, H, W)
    if distance.shape[0] != 1:
        raise ValueError(f"frame_motion takes one scene, got a batch of {distance.shape[0]}")
    S, H, W = distance.shape[1:]
    T = frames.shape[0]
    shapes = (frames.shape, viewmats.shape, Ks.shape, frame_times.shape)
    if shapes != ((T, 3, H, W), (T, 4, 4), (T, 3, 3), (T,)):
        raise ValueError(f"frames (T, 3, {H}, {W}), viewmats (T, 4, 4), Ks (T, 3, 3) and frame_times (T,) must "
                         f"agree, got {tuple(frames.shape)}, {tuple(viewmats.shape)}, {tuple(Ks.shape)}, "
                         f"{tuple(frame_times.shape)}")
    if sources.shape != (S,):
        raise ValueError(f"sources must have shape ({S},), got {tuple(sources.shape)}")
    K = times.shape[0]
    at = nearest_frames(times.to(frame_times.dtype), frame_times)  # (K,) the frame seen at each key time
    home = nearest_frames(frame_times[sources], times.to(frame_times.dtype))  # (S,) each source's own key time
    with torch.no_grad():
        o, d = camera_rays(viewmats[sources].float(), Ks[sources].float(), W, H)
        points = o + d * distance[0].float()[..., None]  # (S, H, W, 3)
    frames = frames.to(next(net.parameters()).dtype)  # the network's dtype (bfloat16 in a bfloat16 runtime)
    feats = net.encode(frames * 2 - 1)
    d_means = torch.zeros(K, S, H, W, 3, dtype=torch.float32, device=distance.device)
    moving = torch.zeros(K, S, H, W, dtype=torch.bool, device=distance.device)
    # Step j reads key times home ± j, starting from the estimate at home ± (j − 1): a short look-up window suffices
    # however far a point travels over the clip, and every step compares against the source frame's own features.
    prior = {sign: (points, moving[0].clone()) for sign in (1, -1)}
    for j in range(1, K):
        for sign in (1, -1):
            k = home + sign * j
            live = ((k >= 0) & (k < K)).nonzero()[:, 0]
            if len(live) == 0:
                continue
            s, k = live, k[live]
            position, was_moving = prior[sign]
            with torch.no_grad():
                cams, intr = viewmats[at[k]].float()[:, None, None], Ks[at[k]].float()[:, None, None]
                uv, z = project_points(position[s], cams, intr)  # (P, H, W, 2), (P, H, W)
            flow, log_depth = net([f[sources[s]] for f in feats], [f[at[k]] for f in feats], uv.to(frames.dtype))
            now = was_moving[s] | ((flow != 0).any(-1) & (z > 0))  # still pixels stay exactly still
            target = unproject_pixels(uv + flow.float(), z * torch.exp(log_depth.float()), cams, intr)
            delta = target - points[s]  # still pixels: exactly 0, their gradient passes (models.motion)
            delta = delta - torch.where(now[..., None], torch.zeros_like(delta), delta.detach())
            d_means[k, s], moving[k, s] = delta, now
            new_position, new_moving = position.clone(), was_moving.clone()
            new_position[s], new_moving[s] = points[s] + delta.detach(), now
            prior[sign] = (new_position, new_moving)
    fields = {}
    for name, identity in (("d_quats", IDENTITY_QUAT), ("d_scales", (0.0, 0.0, 0.0))):
        ident = torch.tensor(identity, dtype=torch.float32, device=distance.device)
        token = getattr(out, name)
        fields[name] = (ident.expand(1, K, S, H, W, len(identity)) if token is None
                        else torch.where(moving[None, ..., None], token.float(), ident))
    return dataclasses.replace(out, d_means=d_means[None].to(distance.dtype), **{
        k: v.to(distance.dtype) for k, v in fields.items()})
