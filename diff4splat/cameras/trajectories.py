"""Preset camera trajectories relative to the first camera (first viewmat = identity).

All presets are expressed in the frame of the first camera (OpenCV: x right, y down, z forward),
which is the world frame of the returned path. The scene is assumed to sit around the point
c = (0, 0, scene_depth) straight ahead of the first camera. Frame i of T has the clip time
t_i = i/(T−1) (T = 1 → t = 0, a single identity camera).

Presets (eye = camera centre in world coordinates, d = scene_depth, a = amplitude). The amplitude of
``arc`` is an ANGLE in radians; that of every translation preset and ``spiral`` is a LENGTH in units
of ``scene_depth``; ``orbit`` takes none. Each preset accepts the amplitudes of :data:`AMPLITUDE_LIMITS`
(:func:`check_amplitude`): beyond them the path leaves what one photograph can show.

- ``arc`` (the default path of ``diff4splat generate``): part of the orbit circle, the camera sweeps
  ``a`` radians in total around c, looking at c: eye_i = c + d·(sin θ_i, 0, −cos θ_i) with
  θ_i = a·t_i. a > 0 moves the eye to the camera's right (+x), a < 0 to its left; 0 < |a| ≤ 2π
  (a full turn: more would repeat it).
  Default a = 0.5 rad (≈ 29°), inside the 20–70° orbit sweeps of the synthetic training clips
  (``data_prep.synth_world``): a path a single photograph supports. With a = 2π·(T−1)/T it is
  exactly ``orbit`` of T frames.
- ``orbit``: a full 360° horizontal circle of radius d around c, looking at c:
  eye_i = c + d·(sin θ_i, 0, −cos θ_i) with θ_i = 2π·i/T, i.e. a seamless loop that starts by
  moving to the camera's right; the last frame is one step (2π/T) before returning to the first.
  ``amplitude`` does not apply (the radius is fixed by the first camera and c). Most of a full turn
  shows what one photograph cannot know (the back of the scene); ``arc`` is the conservative path.
- ``spiral``: an outward planar spiral of two turns in the first camera's image plane, looking at
  c: eye(t) = a·d·t·(cos 4πt, sin 4πt, 0). Default a = 0.25 (final radius d/4); 0 < a ≤ 1 (at 1 the
  last camera sees c from 45° off the first camera's axis).
- ``forward`` / ``backward``: dolly along ±z, eye(t) = ±a·d·t·(0, 0, 1). Default a = 0.5. Forward
  0 < a ≤ 1: at 1 the camera reaches c, further it would pass through the scene. Backward 0 < a ≤ 4: at 4
  the photograph (about d away) spans a fifth of the frame, the rest is the blurred backdrop.
- ``up`` / ``down``: pedestal along ∓y (y points down), eye(t) = ∓a·d·t·(0, 1, 0). Default a = 0.25.
- ``pan-left`` / ``pan-right``: truck along ∓x, eye(t) = ∓a·d·t·(1, 0, 0). Default a = 0.25.
  ``up``/``down``/``pan-*``: 0 < a ≤ 1; a shift of one scene depth takes the photograph (nearly) out of
  a 50° view (the shipped models' field of view), leaving only the blurred backdrop.

The translation presets keep the orientation of the first camera (R = I, looking along +z);
``arc``, ``orbit`` and ``spiral`` use :func:`look_at` towards c with "up" = −y of the first camera.
"""
from __future__ import annotations

import math
from numbers import Real

import torch
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.utils.checks import check_positive_int

__all__ = ["TRAJECTORIES", "DEFAULT_TRAJECTORY", "DEFAULT_AMPLITUDES", "AMPLITUDE_LIMITS", "check_amplitude",
           "amplitude_help", "look_at", "make_trajectory"]

TRAJECTORIES: tuple[str, ...] = ("arc", "orbit", "spiral", "forward", "backward", "up", "down", "pan-left", "pan-right")
"""Names accepted by :func:`make_trajectory`."""

DEFAULT_TRAJECTORY = "arc"
"""The preset used when no camera path is named (``diff4splat generate``,
``Diff4SplatPipeline.default_cameras``): a short arc that one photograph supports."""

DEFAULT_AMPLITUDES: dict[str, float] = {
    "arc": 0.5,
    "spiral": 0.25,
    "forward": 0.5,
    "backward": 0.5,
    "up": 0.25,
    "down": 0.25,
    "pan-left": 0.25,
    "pan-right": 0.25,
}
"""Default ``amplitude`` per preset: radians for ``arc``, units of ``scene_depth`` for the others
(``orbit`` takes none)."""

AMPLITUDE_LIMITS: dict[str, float] = {
    "arc": 2.0 * math.pi,
    "spiral": 1.0,
    "forward": 1.0,
    "backward": 4.0,
    "up": 1.0,
    "down": 1.0,
    "pan-left": 1.0,
    "pan-right": 1.0,
}
"""Largest ``amplitude`` per preset (``orbit`` takes none): ``arc`` accepts 0 < |a| ≤ 2π radians (negative
sweeps left), every other preset 0 < a ≤ limit, in units of ``scene_depth``. The module docstring says why."""

_LIMIT_REASONS = {
    "arc": "a full turn; more would repeat it",
    "spiral": "at 1 the last camera sees the scene centre from 45° off the first camera's axis",
    "forward": "at 1 the camera reaches the scene centre; further it would pass through the scene",
    "backward": "at 4 the photograph spans about a fifth of the frame",
    **dict.fromkeys(("up", "down", "pan-left", "pan-right"),
                    "at 1 the photograph has (nearly) left the frame of a 50° camera"),
}

_DIRECTIONS = {
    "forward": (0.0, 0.0, 1.0),
    "backward": (0.0, 0.0, -1.0),
    "up": (0.0, -1.0, 0.0),
    "down": (0.0, 1.0, 0.0),
    "pan-left": (-1.0, 0.0, 0.0),
    "pan-right": (1.0, 0.0, 0.0),
}


def check_amplitude(trajectory: str, amplitude: object, name: str = "amplitude") -> float | None:
    """The amplitude ``trajectory`` will use: ``amplitude`` checked against the preset's range, or its default.

    Called by :func:`make_trajectory` and, before any work, by the command line (``name="--amplitude"``).

    Args:
        trajectory: one of :data:`TRAJECTORIES`.
        amplitude: the requested amplitude (radians for ``arc``, scene depths otherwise), or None for the
            preset's default (:data:`DEFAULT_AMPLITUDES`).
        name: the parameter's name in messages, as the caller's user knows it.

    Returns:
        The amplitude as a float; None for ``orbit`` (which takes none).

    Raises:
        ValueError: naming ``trajectory`` (unknown preset), or ``name``, the preset, the accepted range and unit
            (:data:`AMPLITUDE_LIMITS`) when ``amplitude`` is not a finite number in that range, or is given for
            ``orbit``.
    """
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"trajectory must be one of {TRAJECTORIES}, got {trajectory!r}")
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
    """World-to-camera viewmats of cameras at ``eyes`` looking at ``targets`` (OpenCV frame).

    The camera's +z axis points from eye to target, +x = normalize(down × z) with down = −up, and
    +y = z × x points down in the image. With eye = 0, target on +z and the default up = (0, −1, 0)
    (world y down, as in the OpenCV first-camera frame) the result is exactly the identity.
    R has rows (x, y, z) and t = −R·eye.

    Args:
        eyes: (T, 3) camera centres, metres.
        targets: (T, 3) or (3,) look-at points, metres.
        up: (3,) world direction that appears up in the image.

    Returns:
        (T, 4, 4) world-to-camera rigid transforms in the dtype of ``eyes``.

    Raises:
        ValueError: naming ``eyes``/``targets`` when an eye coincides with its target, or ``up``
            when the viewing direction is parallel to it.
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
    """A preset camera path of ``num_frames`` cameras sharing the intrinsics ``K``.

    See the module docstring for each preset's exact motion and default amplitude.

    Args:
        name: one of :data:`TRAJECTORIES`.
        num_frames: T ≥ 1.
        K: (3, 3) intrinsics in pixels, used for every frame.
        width: image width, pixels.
        height: image height, pixels.
        scene_depth: distance d (metres, > 0) from the first camera to the scene centre c.
        amplitude: motion size; ``None`` → the preset default (:data:`DEFAULT_AMPLITUDES`). For
            ``arc`` an angle in RADIANS, the total sweep around c: 0 < |amplitude| ≤ 2π, positive to
            the camera's right, negative to its left. For every other preset a length in units of
            ``scene_depth`` in (0, :data:`AMPLITUDE_LIMITS`]. Not accepted for ``orbit``
            (:func:`check_amplitude`).

    Returns:
        :class:`CameraPath` with viewmats (T, 4, 4) (viewmats[0] = I exactly), Ks (T, 3, 3),
        times t_i = i/(T−1); validated. Dtype: that of ``K`` if floating, else float32.

    Raises:
        ValueError: naming ``name`` (unknown preset), ``num_frames`` (< 1 or not an int),
            ``scene_depth`` (≤ 0 or not finite), ``amplitude`` (outside the preset's range or given for
            ``orbit``, :func:`check_amplitude`), ``K`` (not (3, 3)), or a field of :meth:`CameraPath.validate`.
    """
    if name not in TRAJECTORIES:
        raise ValueError(f"name must be one of {TRAJECTORIES}, got {name!r}")
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
