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


def nearest_frames(times: Tensor, frame_times: Tensor) -> Tensor:  # (..., K), (..., T) → (..., K) long
    """(..., K) long index into ``frame_times`` (..., T) of the frame nearest each of ``times`` (..., K) (earlier on a
    tie), batched over the leading dimensions."""
    return (times[..., :, None] - frame_times[..., None, :]).abs().argmin(dim=-1)


def frame_motion(
    net: MotionNetwork,
    out: LDRMOutput,
    frames: Tensor,  # (B, T, 3, H, W) in [0, 1], the model resolution
    frame_times: Tensor,  # (B, T)
    viewmats: Tensor,  # (B, T, 4, 4) world-to-camera of the frames
    Ks: Tensor,  # (B, T, 3, 3) pixels at (H, W)
    sources: Tensor,  # (S,) long: the source frames' indices into each scene's frames
    times: Tensor,  # (B, K) key times
) -> LDRMOutput:
    """``out`` (batch B: B scenes of the same sizes) with its deformation maps read from ``frames`` by ``net`` (module
    docstring). The B scenes' source pixels go through the network together, one call per step.

    Returns:
        An :class:`LDRMOutput` with d_means (B, K, S, H, W, 3) metres, world frame, and d_quats (B, K, S, H, W, 4) /
        d_scales (B, K, S, H, W, 3): ``out``'s where a pixel moves at that time, else (or without any) the identity.

    Raises:
        ValueError: frames / cameras / times whose shapes do not match ``out``'s (B, S, H, W).
    """
    distance = out.distance  # (B, S, H, W)
    B, S, H, W = distance.shape
    T, K = frames.shape[1], times.shape[-1]
    shapes = (frames.shape, frame_times.shape, viewmats.shape, Ks.shape, sources.shape, times.shape)
    if shapes != ((B, T, 3, H, W), (B, T), (B, T, 4, 4), (B, T, 3, 3), (S,), (B, K)):
        raise ValueError(f"frames ({B}, T, 3, {H}, {W}), frame_times ({B}, T), viewmats ({B}, T, 4, 4), Ks "
                         f"({B}, T, 3, 3), sources ({S},) and times ({B}, K) must agree with the maps, got "
                         + ", ".join(str(tuple(x)) for x in shapes))
    at = nearest_frames(times.to(frame_times.dtype), frame_times)  # (B, K) the frame seen at each key time
    home = nearest_frames(frame_times[:, sources], times.to(frame_times.dtype))  # (B, S) each source's key time
    # Rows r = b·S + s: scene b's source s. Frames, cameras and features are indexed flat, b·T + frame.
    scene = torch.arange(B, device=distance.device).repeat_interleave(S)  # (R,)
    home, base = home.reshape(-1), scene * T
    frames, viewmats, Ks = frames.flatten(0, 1), viewmats.flatten(0, 1).float(), Ks.flatten(0, 1).float()
    own = base + sources.repeat(B)  # (R,) each row's source frame
    with torch.no_grad():
        o, d = camera_rays(viewmats[own], Ks[own], W, H)
        points = o + d * distance.reshape(B * S, H, W).float()[..., None]  # (R, H, W, 3)
    frames = frames.to(next(net.parameters()).dtype)  # the network's dtype (bfloat16 in a bfloat16 runtime)
    feats = net.encode(frames * 2 - 1)
    d_means = torch.zeros(K, B * S, H, W, 3, dtype=torch.float32, device=distance.device)
    moving = torch.zeros(K, B * S, H, W, dtype=torch.bool, device=distance.device)
    # Step j reads key times home ± j, starting from the estimate at home ± (j − 1): a short look-up window suffices
    # however far a point travels over the clip, and every step compares against the source frame's own features.
    prior = {sign: (points, moving[0].clone()) for sign in (1, -1)}
    for j in range(1, K):
        for sign in (1, -1):
            k = home + sign * j
            live = ((k >= 0) & (k < K)).nonzero()[:, 0]
            if len(live) == 0:
                continue
            r, k = live, k[live]
            seen = base[r] + at[scene[r], k]  # (P,) the frame each live row reads at its key time
            position, was_moving = prior[sign]
            with torch.no_grad():
                cams, intr = viewmats[seen][:, None, None], Ks[seen][:, None, None]
                uv, z = project_points(position[r], cams, intr)  # (P, H, W, 2), (P, H, W)
            flow, log_depth = net([f[own[r]] for f in feats], [f[seen] for f in feats], uv.to(frames.dtype))
            now = was_moving[r] | ((flow != 0).any(-1) & (z > 0))  # still pixels stay exactly still
            target = unproject_pixels(uv + flow.float(), z * torch.exp(log_depth.float()), cams, intr)
            delta = target - points[r]  # still pixels: exactly 0, their gradient passes (models.motion)
            delta = delta - torch.where(now[..., None], torch.zeros_like(delta), delta.detach())
            d_means[k, r], moving[k, r] = delta, now
            new_position, new_moving = position.clone(), was_moving.clone()
            new_position[r], new_moving[r] = points[r] + delta.detach(), now
            prior[sign] = (new_position, new_moving)
    d_means = d_means.unflatten(1, (B, S)).transpose(0, 1)  # (B, K, S, H, W, 3)
    moving = moving.unflatten(1, (B, S)).transpose(0, 1)
    fields = {}
    for name, identity in (("d_quats", IDENTITY_QUAT), ("d_scales", (0.0, 0.0, 0.0))):
        ident = torch.tensor(identity, dtype=torch.float32, device=distance.device)
        token = getattr(out, name)
        fields[name] = (ident.expand(B, K, S, H, W, len(identity)) if token is None
                        else torch.where(moving[..., None], token.float(), ident))
    return dataclasses.replace(out, d_means=d_means.to(distance.dtype), **{
        k: v.to(distance.dtype) for k, v in fields.items()})
