"""The viewer's payload: what one ``viewer.html`` embeds, as bytes (docs/DESIGN.md, "Viewer").

The canonical Gaussians as INRIA PLY bytes (:func:`diff4splat.io.ply_bytes`: colours, opacities, SH) and, for a scene
that changes with time, the frame data (:func:`encode_keyframes`): with temporal support each Gaussian's μ_t and σ_t
(and trapezoid ramp), from which the page evaluates the opacity at any t as :meth:`DynamicGaussians.at` does; for a
deforming scene each Gaussian's key window and held keyframes (:mod:`diff4splat.render.keyframes`), float16 when
their means move ≤ :data:`FLOAT16_MAX_PX` pixels and every value fits (``keyframe_dtype``), else float32. Size: per
Gaussian, 8 bytes with temporal support (12 with ramps), 4 for its key window in a deforming scene, and 10 values × 2
or 4 bytes per held keyframe (:func:`payload_bytes`), × 4/3 in base64. Above :data:`VIEWER_BUDGET_BYTES` of embedded
data the page gets a reduced scene (:func:`viewer_payload`: SH degree 0, then fewer keyframes, then the Gaussians
covering most) and says so on screen; ``diff4splat view`` serves the full one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.io.ply import ply_bytes
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.render import keyframes
from diff4splat.render.settings import BACKGROUND, EPS2D, NEAR_PLANE
from diff4splat.scene.dynamic import DynamicGaussians

__all__ = ["VIEWER_BUDGET_BYTES", "FLOAT16_MAX_PX", "ViewerPayload", "encode_keyframes", "decode_keyframes",
           "viewer_payload", "payload_bytes"]

VIEWER_BUDGET_BYTES = 50 * 2**20
"""Most bytes of data (PLY + keyframes, before base64) embedded in one viewer.html."""

FLOAT16_MAX_PX = 0.5
"""Keyframes are float16 only if float16 means reproject within this many pixels of the float32 ones."""


@dataclass
class ViewerPayload:
    """Everything the page needs.

    Attributes:
        config: JSON-ready dict read by the page (counts, cameras, key times, dtype, note …).
        ply: INRIA PLY bytes of the (possibly reduced) canonical Gaussians.
        frames: frame data bytes (layout in :func:`encode_keyframes`), or None for a scene that does not change
            with time.
        reductions: what the size budget took away (empty: the full scene), as stated on the page.
    """

    config: dict
    ply: bytes
    frames: bytes | None = None
    reductions: list[str] = field(default_factory=list)


def encode_keyframes(held: Tensor | None, windows: tuple[Tensor, Tensor] | None, dtype: str,
                     temporal: tuple[Tensor, ...] | None = None) -> bytes:
    """The frame data as little-endian bytes: with ``temporal`` = (t_means (N,), t_scales (N,)[, t_ramps (N,)]), each
    as float32 (4·N bytes each: σ_t keeps its precision whatever ``dtype``); then, for a scene with key times,
    ``windows`` = (first (N,), count (N,)) of :func:`keyframes.key_windows` as uint16 (2·N bytes each) and the
    ``held`` keyframes (Σ count, 10) of :func:`keyframes.held_keyframes` in ``dtype`` ("float16" or "float32"),
    Gaussian by Gaussian: per held key its means (3), quats (4, wxyz), scales (3). The page's splitFrames reads this.

    Raises:
        ValueError: another ``dtype``; ``held`` without ``windows`` or rows ≠ Σ count; a window past 65535 keys.
    """
    if dtype not in ("float16", "float32"):
        raise ValueError(f"dtype must be 'float16' or 'float32', got {dtype!r}")
    out = b""
    if temporal is not None:
        out = torch.cat([v.detach().reshape(-1) for v in temporal]).to(torch.float32).cpu().numpy().astype("<f4")
        out = out.tobytes()
    if held is None and windows is None:
        return out
    if held is None or windows is None or held.shape[0] != int(windows[1].sum()):
        raise ValueError("held keyframes need their windows, one row per held key")
    first, count = (w.cpu() for w in windows)
    if first.numel() and int((first + count).max()) > 65535:
        raise ValueError("key windows are uint16: at most 65535 key times")
    out += torch.cat([first, count]).cpu().numpy().astype("<u2").tobytes()  # device: the page's bytes, on the host
    values = held.reshape(-1).cpu().numpy()  # device: the page's bytes, on the host
    return out + values.astype("<f2" if dtype == "float16" else "<f4").tobytes()


def payload_bytes(num_gaussians: int, sh_degree: int, held_keyframes: int, temporal_arrays: int, itemsize: int,
                  keyed: bool) -> int:
    """Bytes of embedded data (before base64): PLY rows of (17 + 3·((d+1)² − 1)) float32, the temporal support's
    ``temporal_arrays`` (0; 2: μ_t, σ_t; 3: with ramps) float32 per Gaussian, for a ``keyed`` scene (one with key
    times) the key windows (2 uint16 per Gaussian), and ``held_keyframes`` (Σ count of
    :func:`keyframes.key_windows`; N·F when every Gaussian holds every key) of 10 values of ``itemsize`` bytes."""
    ply = num_gaussians * 4 * (17 + 3 * ((sh_degree + 1) ** 2 - 1))
    windows = 4 * num_gaussians if keyed else 0
    return ply + 4 * temporal_arrays * num_gaussians + windows + held_keyframes * 10 * itemsize


def viewer_payload(scene: DynamicGaussians, cameras: CameraPath, *, fps: float = DEFAULT_FPS,
                   budget: int | None = VIEWER_BUDGET_BYTES,
                   background: tuple[float, float, float] = BACKGROUND, eps2d: float = EPS2D) -> ViewerPayload:
    """The data of one viewer page (module docstring), reduced to at most ``budget`` bytes (None: never) by
    :func:`diff4splat.render.keyframes.page_scene`; each reduction taken is listed in ``config["note"]``.
    ``background``: RGB in [0, 1] behind the Gaussians (as the CPU renderer composites it); ``eps2d``: the scene's
    screen-space dilation, pixels² (Spark's ``preBlurAmount``; meta.json ``eps2d``).

    Raises:
        ValueError: an empty camera path or fps ≤ 0.
    """
    if len(cameras) == 0:
        raise ValueError("cameras: the viewer needs at least one camera")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    page = keyframes.page_scene(scene.to("cpu"), cameras, budget, payload_bytes, FLOAT16_MAX_PX)
    g, times, span, held, pose = page.gaussians, page.times, page.span, page.held, page.first_pose
    V, K = cameras.viewmats.detach().cpu().double(), cameras.Ks.detach().cpu().double()
    config = {
        "numGaussians": g.num_gaussians, "shDegree": g.sh_degree, "dynamic": span is not None,
        "temporal": scene.has_temporal, "temporalRamps": scene.t_ramps is not None,
        "times": [] if times is None else [float(t) for t in times], "timeRange": [] if span is None else list(span),
        "heldKeyframes": 0 if held is None else held.shape[0],
        "dtype": page.dtype, "float16ErrorPx": page.float16_error_px, "width": cameras.width, "height": cameras.height,
        "duration": (len(cameras) - 1) / fps if len(cameras) > 1 else 1.0 / fps,
        "cameras": [{"viewmat": V[i].reshape(-1).tolist(), "K": K[i].reshape(-1).tolist(),
                     "time": float(cameras.times[i])} for i in range(len(cameras))],
        "near": NEAR_PLANE, "background": [float(c) for c in background], "eps2d": float(eps2d),
        "far": max(100.0, 10 * float(pose.double().norm(dim=1).max()) if pose.numel() else 100.0),
        "targetDistance": page.target_distance,
        "note": ("reduced to fit the viewer's size budget: " + "; ".join(page.reductions) +
                 " — run `diff4splat view DIR` for the full scene") if page.reductions else "",
        "reductions": list(page.reductions),
        "bytesPerHeldKey": 10 * (2 if page.dtype == "float16" else 4) if held is not None else 0,
    }
    if not math.isfinite(config["far"]):
        config["far"] = 1e4
    data = None if span is None else encode_keyframes(held, page.windows, page.dtype, page.support)
    return ViewerPayload(config, ply_bytes(g), data, page.reductions)


def decode_keyframes(data: bytes, config: dict) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_keyframes` given the page config (tests and tools): "t_means", "t_scales" (and
    "t_ramps" when ``config["temporalRamps"]``) (N,) with temporal support; "key_first", "key_count" (N,) int64 and
    "means", "quats", "scales" (F, N, ·) float32 for F key times (F = 0 without deformation), NaN at the keys a
    Gaussian does not hold (outside its window; every key of a still one, whose pose is the PLY's)."""
    n, F = config["numGaussians"], len(config["times"])
    out, start = {}, 0
    if config["temporal"]:
        k = 3 if config.get("temporalRamps") else 2
        support = np.frombuffer(data, dtype="<f4", count=k * n).astype(np.float32)
        out["t_means"], out["t_scales"], start = support[:n], support[n:2 * n], 4 * k * n
        if k == 3:
            out["t_ramps"] = support[2 * n:]
    dense = np.full((F, n, 10), np.nan, dtype=np.float32)
    if F:
        windows = np.frombuffer(data, dtype="<u2", count=2 * n, offset=start).astype(np.int64)
        first, count = windows[:n], windows[n:]
        rows = np.frombuffer(data[start + 4 * n:], dtype="<f2" if config["dtype"] == "float16" else "<f4")
        rows = rows.astype(np.float32).reshape(-1, 10)
        gaussian = np.repeat(np.arange(n), count)
        key = first[gaussian] + np.arange(rows.shape[0]) - np.repeat(np.cumsum(count) - count, count)
        dense[key, gaussian] = rows
        out["key_first"], out["key_count"] = first, count
    out.update(means=dense[..., :3], quats=dense[..., 3:7], scales=dense[..., 7:])
    return out
