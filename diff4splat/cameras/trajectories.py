"""Preset camera trajectories in the frame of the first camera (OpenCV: x right, y down, z forward; first viewmat =
identity), around the scene centre c = (0, 0, d) with d = scene_depth; frame i of T at clip time t_i = i/(T−1)
(T = 1: one identity camera). a = amplitude, eye = camera centre; README ``--trajectory``/``--amplitude`` gives the
user's view, :data:`AMPLITUDE_LIMITS` the accepted range (beyond it the path leaves what one photograph can show).

- ``arc`` (default): eye_i = c + d·(sin θ_i, 0, −cos θ_i), θ_i = a·t_i, looking at c; a in radians, > 0 to the
  right, < 0 to the left; default 0.5 (inside the 20–70° sweeps of ``data_prep.synth_world``'s training clips).
- ``orbit``: as ``arc`` with θ_i = 2π·i/T, a seamless 360° loop; takes no amplitude.
- ``spiral``: eye(t) = a·d·t·(cos 4πt, sin 4πt, 0), two outward turns in the image plane, looking at c.
- ``forward``/``backward`` (dolly ±z), ``up``/``down`` (pedestal ∓y), ``pan-left``/``pan-right`` (truck ∓x):
  eye(t) = a·d·t·direction, orientation of the first camera kept (R = I).

``arc``, ``orbit`` and ``spiral`` use :func:`look_at` towards c with "up" = −y of the first camera.
"""
from __future__ import annotations

import math
from numbers import Real

import torch
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.utils.checks import check_positive_int

__all__ = ["TRAJECTORIES", "DEFAULT_TRAJECTORY", "DEFAULT_AMPLITUDES", "AMPLITUDE_LIMITS", "check_trajectory",
           "check_amplitude", "amplitude_help", "look_at", "make_trajectory"]

TRAJECTORIES: tuple[str, ...] = ("arc", "orbit", "spiral", "forward", "backward", "up", "down", "pan-left", "pan-right")
"""Names accepted by :func:`make_trajectory`."""

DEFAULT_TRAJECTORY = "arc"
"""The preset used when no camera path is named (``diff4splat generate``,
``Diff4SplatPipeline.default_cameras``): a short arc that one photograph supports."""

DEFAULT_AMPLITUDES: dict[str, float] = {"arc": 0.5, "spiral": 0.25, "forward": 0.5, "backward": 0.5, "up": 0.25,
                                         "down": 0.25, "pan-left": 0.25, "pan-right": 0.25}
"""Default ``amplitude`` per preset: radians for ``arc``, units of ``scene_depth`` for the others (not ``orbit``)."""

AMPLITUDE_LIMITS: dict[str, float] = {"arc": 2.0 * math.pi, "spiral": 1.0, "forward": 1.0, "backward": 4.0, "up": 1.0,
                                      "down": 1.0, "pan-left": 1.0, "pan-right": 1.0}
"""Largest ``amplitude`` per preset: ``arc`` 0 < |a| ≤ 2π radians (negative sweeps left), the others 0 < a ≤ limit
scene depths (:data:`_LIMIT_REASONS` says why)."""

_LIMIT_REASONS = {
    "arc": "a full turn; more would repeat it",
    "spiral": "at 1 the last camera sees the scene centre from 45° off the first camera's axis",
    "forward": "at 1 the camera reaches the scene centre; further it would pass through the scene",
    "backward": "at 4 the photograph spans about a fifth of the frame",
    **dict.fromkeys(("up", "down", "pan-left", "pan-right"),
                    "at 1 the photograph has (nearly) left the frame of a 50° camera"),
}

_DIRECTIONS = {"forward": (0.0, 0.0, 1.0), "backward": (0.0, 0.0, -1.0), "up": (0.0, -1.0, 0.0),
               "down": (0.0, 1.0, 0.0), "pan-left": (-1.0, 0.0, 0.0), "pan-right": (1.0, 0.0, 0.0)}

def check_trajectory(trajectory: object, name: str = "trajectory") -> None:
    """ValueError (naming ``name``) unless ``trajectory`` is one of :data:`TRAJECTORIES`."""
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"{name} must be one of {TRAJECTORIES}, got {trajectory!r}")


def check_amplitude(trajectory: str, amplitude: object, name: str = "amplitude") -> float | None:
    """The amplitude ``trajectory`` will use: ``amplitude`` (radians for ``arc``, scene depths otherwise) checked
    against :data:`AMPLITUDE_LIMITS`, or the preset's default for None; None for ``orbit``. ``name`` is the
    parameter's name in messages (the command line passes ``"--amplitude"``).

    Raises:
        ValueError: an unknown ``trajectory``; ``amplitude`` not a finite number in range, or given for ``orbit``
            (naming ``name``, the preset, the range and unit).
    """
    check_trajectory(trajectory)
    if trajectory == "orbit":
        if amplitude is not None:
            raise ValueError(f"{name} does not apply to orbit: it is the full 360° circle around the scene centre, "
                             f"whose radius is the scene depth; leave {name} out (for part of the circle use arc, "
                             f"whose amplitude is the sweep angle in radians)")
        return None
    if amplitude is None:
        return DEFAULT_AMPLITUDES[trajectory]
    limit = AMPLITUDE_LIMITS[trajectory]
    number = isinstance(amplitude, Real) and not isinstance(amplitude, bool)
    value = float(amplitude) if number else math.nan
    bad = not math.isfinite(value) or value == 0 or abs(value) > limit or (value < 0 and trajectory != "arc")
    if not bad:
        return value
    shown = f"{value:g}" if number else repr(amplitude)
    if trajectory == "arc":
        allowed, extra = f"[-2π, 0) or (0, 2π] radians, 2π ≈ {limit:.4g}", "; negative sweeps left"
        if 2 * math.pi < abs(value) <= 360:
            extra += f"; {shown}° would be {math.radians(value):.3g} rad"
    else:
        allowed, extra = f"(0, {limit:g}] scene depths", ""
    raise ValueError(f"{name} {shown} for {trajectory} must be in {allowed} ({_LIMIT_REASONS[trajectory]}); "
                     f"default {DEFAULT_AMPLITUDES[trajectory]:g}{extra}")


def amplitude_help() -> str:
    """One line describing every preset's amplitude range and default (the ``--amplitude`` help)."""
    arc = (f"arc: the sweep angle in radians, 0 < |A| ≤ 2π, negative sweeps left (default "
           f"{DEFAULT_AMPLITUDES['arc']:g})")
    others = ", ".join(f"{n} (0, {AMPLITUDE_LIMITS[n]:g}] (default {DEFAULT_AMPLITUDES[n]:g})"
                       for n in AMPLITUDE_LIMITS if n != "arc")
    return f"{arc}; in scene depths: {others}; orbit takes none"


def look_at(
    eyes: Tensor,  # (T, 3) camera centres, world frame
    targets: Tensor,  # (T, 3) or (3,) points to look at
    up: tuple[float, float, float] | Tensor = (0.0, -1.0, 0.0),
) -> Tensor:
    """World-to-camera viewmats (T, 4, 4), dtype of ``eyes``, of cameras at ``eyes`` (T, 3) looking at ``targets``
    (T, 3) or (3,), metres, with ``up`` the world direction shown up in the image. R has rows x = normalize(−up × z),
    y = z × x, z = normalize(target − eye); t = −R·eye (eye 0, target on +z, default up: exactly the identity).

    Raises:
        ValueError: an eye equal to its target, or ``up`` parallel to the viewing direction.
    """
    if eyes.dim() != 2 or eyes.shape[-1] != 3:
        raise ValueError(f"eyes must have shape (T, 3), got {tuple(eyes.shape)}")
    targets = torch.as_tensor(targets, dtype=eyes.dtype, device=eyes.device).expand_as(eyes)
    down = -torch.as_tensor(up, dtype=eyes.dtype, device=eyes.device).expand_as(eyes)
    fwd = targets - eyes
    n = fwd.norm(dim=-1, keepdim=True)
    if bool((n < 1e-12).any()):
        raise ValueError("eyes and targets must differ (the viewing direction is undefined)")
    fwd = fwd / n
    x = torch.linalg.cross(down, fwd, dim=-1)
    nx = x.norm(dim=-1, keepdim=True)
    if bool((nx < 1e-9 * down.norm(dim=-1, keepdim=True)).any()):
        raise ValueError("up must not be parallel to the viewing direction")
    x = x / nx
    y = torch.linalg.cross(fwd, x, dim=-1)
    R = torch.stack([x, y, fwd], dim=-2)  # rows = camera axes in world coordinates
    out = torch.zeros(eyes.shape[0], 4, 4, dtype=eyes.dtype, device=eyes.device)
    out[:, :3, :3] = R
    out[:, :3, 3] = -torch.einsum("tij,tj->ti", R, eyes)
    out[:, 3, 3] = 1.0
    return out


def make_trajectory(
    name: str,
    num_frames: int,
    K: Tensor,  # (3, 3) pixels
    width: int,
    height: int,
    scene_depth: float = 2.0,
    amplitude: float | None = None,
) -> CameraPath:
    """A preset camera path (module docstring) of ``num_frames`` ≥ 1 cameras sharing ``K`` (3, 3), pixels, for
    ``width`` × ``height`` images, around a scene centre ``scene_depth`` metres (> 0) ahead.

    Args:
        amplitude: motion size (:func:`check_amplitude`): radians for ``arc``, scene depths otherwise, None for the
            preset default; not accepted for ``orbit``.

    Returns:
        :class:`CameraPath` (viewmats[0] = I exactly, times i/(T−1)), dtype of ``K`` if floating, else float32.

    Raises:
        ValueError: naming ``name``, ``num_frames``, ``scene_depth``, ``amplitude``, ``K`` (not (3, 3)) or a field
            of :meth:`CameraPath.validate`.
    """
    check_trajectory(name, "name")
    num_frames = check_positive_int("num_frames", num_frames)
    if not isinstance(scene_depth, (int, float)) or not math.isfinite(scene_depth) or scene_depth <= 0:
        raise ValueError(f"scene_depth must be a finite number > 0 metres, got {scene_depth!r}")
    amplitude = check_amplitude(name, amplitude)
    K = K if isinstance(K, Tensor) else torch.as_tensor(K, device="cpu")  # a nested list is a CPU constant
    if tuple(K.shape) != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {tuple(K.shape)}")
    dtype = K.dtype if K.is_floating_point() else torch.float32

    T, d, a = num_frames, float(scene_depth), float(amplitude or 0.0)
    f64 = torch.float64
    dev = K.device
    t = torch.arange(T, dtype=f64, device=dev) / max(T - 1, 1)
    target = torch.tensor([0.0, 0.0, d], dtype=f64, device=dev)
    if name in ("arc", "orbit"):  # azimuth θ around c on the horizontal circle of radius d
        theta = a * t if name == "arc" else 2.0 * math.pi * torch.arange(T, dtype=f64, device=dev) / T
        eyes = target + d * torch.stack([torch.sin(theta), torch.zeros_like(theta), -torch.cos(theta)], -1)
        viewmats = look_at(eyes, target)
    elif name == "spiral":
        phi = 4.0 * math.pi * t
        eyes = a * d * t[:, None] * torch.stack([torch.cos(phi), torch.sin(phi), torch.zeros_like(phi)], -1)
        viewmats = look_at(eyes, target)
    else:
        eyes = a * d * t[:, None] * torch.tensor(_DIRECTIONS[name], dtype=f64, device=dev)
        viewmats = torch.eye(4, dtype=f64, device=dev).repeat(T, 1, 1)
        viewmats[:, :3, 3] = -eyes  # R = I → t = −eye
    viewmats[0] = torch.eye(4, dtype=f64, device=dev)  # exact identity (look_at gives it up to rounding)
    Ks = K.to(dtype).expand(T, 3, 3).clone()
    return CameraPath(viewmats.to(dtype), Ks, width, height, t.to(dtype))
