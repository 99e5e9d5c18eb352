"""The direction test of a prompt's motion (issue 58): does the scene move the captioned object the way its caption
names, and the other way when the caption's direction phrase is flipped?

A synthetic caption names each translating object's direction in the reference camera's frame
(:data:`data_prep.synth_world.DIRECTION_PHRASES`: "to the left", "towards the camera", …). A clip takes part when its
caption names exactly one direction. Its moving object is the set of frame-0 pixels whose true 3D track (the clip's
``pixel_tracks``, clip world = the reference camera at frame 0) has moved more than :data:`MOVING_M` by the last
frame; a scene moves it the named way when the mean displacement of those pixels' points along the phrase's axis,
by the last frame, has the phrase's sign and exceeds :data:`NAMED_WAY_M`. Holding still fails the test.
"""
from __future__ import annotations

from torch import Tensor

from data_prep.synth_world import DIRECTION_PHRASES

__all__ = ["MOVING_M", "NAMED_WAY_M", "caption_direction", "flip_direction", "moving_pixels", "directional_motion",
           "moves_named_way", "direction_query", "named_way_score"]

MOVING_M = 0.05
"""A frame-0 pixel whose true track moved more than this by the last frame (metres) belongs to the moving object."""
NAMED_WAY_M = 0.01
"""The mean displacement along the named axis (metres) above which the object moved the named way."""


def caption_direction(caption: str) -> tuple[str, int, int] | None:
    """The only direction phrase of ``caption`` as (phrase, camera axis 0/1/2 = x/y/z, sign ±1), or None when it names
    no direction or more than one."""
    found = [(phrase, axis, 1 if k == 0 else -1) for axis, pair in enumerate(DIRECTION_PHRASES)
             for k, phrase in enumerate(pair) for _ in range(caption.count(phrase))]
    return found[0] if len(found) == 1 else None


def flip_direction(caption: str) -> str:
    """``caption`` with its only direction phrase replaced by the opposite one. Raises ValueError when it names no
    direction or more than one."""
    found = caption_direction(caption)
    if found is None:
        raise ValueError(f"the caption must name exactly one direction ({DIRECTION_PHRASES}), got {caption!r}")
    phrase, axis, sign = found
    return caption.replace(phrase, DIRECTION_PHRASES[axis][1 if sign > 0 else 0])


def moving_pixels(pixel_tracks: Tensor, valid: Tensor) -> Tensor:
    """(..., H, W) bool: the ``valid`` (..., H, W) pixels whose true track ``pixel_tracks`` (..., T, H, W, 3) metres
    moved more than :data:`MOVING_M` from frame 0 to the last frame (leading dimensions: clips of a batch)."""
    return valid & ((pixel_tracks.select(-4, -1) - pixel_tracks.select(-4, 0)).norm(dim=-1) > MOVING_M)


def directional_motion(positions: Tensor, moving: Tensor, axis: int) -> float:
    """Mean displacement (metres) along clip-world ``axis`` from the first to the last time of the points
    ``positions`` (P, T, 3) selected by ``moving`` (P,) bool; NaN when none is selected."""
    if not bool(moving.any()):
        return float("nan")
    return float((positions[moving, -1, axis] - positions[moving, 0, axis]).double().mean())


def moves_named_way(displacement: float, sign: int) -> bool:
    """Whether a mean displacement (metres) along the named axis goes the named way (``sign`` ±1) by more than
    :data:`NAMED_WAY_M`; NaN is False."""
    return sign * displacement > NAMED_WAY_M


def direction_query(clip: dict) -> tuple[int, int, Tensor] | None:
    """What the test asks of a clip (``ClipDataset`` item: ``dynamic``, ``caption``, ``pixel_tracks`` (T, H, W, 3),
    ``pixel_track_valid`` (H, W)): (axis, sign, moving (H·W,) bool of :func:`moving_pixels`), or None when the clip
    does not take part (static, its caption names no direction or more than one, or nothing moves)."""
    named = caption_direction(clip["caption"]) if bool(clip["dynamic"]) else None
    if named is None:
        return None
    moving = moving_pixels(clip["pixel_tracks"], clip["pixel_track_valid"]).reshape(-1)
    return (named[1], named[2], moving) if bool(moving.any()) else None


def named_way_score(positions: Tensor, kept: Tensor, moving: Tensor, axis: int, sign: int) -> tuple[bool, float]:
    """A scene's answer for one caption: frame 0's pixels' points ``positions`` (H·W, T, 3) metres, ``kept`` (H·W,)
    bool (the pixel's point exists), the clip's ``moving`` (H·W,) bool, the named ``axis`` and ``sign`` (±1).
    Returns (moved the named way, :func:`moves_named_way`; the mean displacement along the named way, ``sign`` times
    :func:`directional_motion`, metres, 0 when no moving pixel was kept)."""
    d = directional_motion(positions, moving & kept, axis)
    return moves_named_way(d, sign), sign * d if d == d else 0.0  # NaN: no moving pixel kept
