"""training/direction_test.py: the caption's direction phrase and its flip, the moving pixels, the displacement
along the named axis; against synthetic captions and pixel tracks."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from data_prep.synth_world import DIRECTION_PHRASES, caption_for, direction_word, sample_scene_spec
from training.direction_test import (
    MOVING_M,
    caption_direction,
    direction_query,
    directional_motion,
    flip_direction,
    moves_named_way,
    moving_pixels,
    named_way_score,
)


def test_the_phrase_names_the_axis_and_sign_direction_word_chose():
    for axis in range(3):
        for sign in (1, -1):
            v = np.zeros(3)
            v[axis] = 0.7 * sign
            phrase = direction_word(v)
            caption = f"a red ball rolls {phrase} on a wooden floor, while the camera trucks left"
            assert caption_direction(caption) == (phrase, axis, sign)
            flipped = flip_direction(caption)
            assert caption_direction(flipped) == (DIRECTION_PHRASES[axis][0 if sign < 0 else 1], axis, -sign)
            assert flip_direction(flipped) == caption


def test_captions_naming_no_direction_or_two_take_no_part():
    assert caption_direction("a blue box spins clockwise on a sandy floor, while the camera pans left") is None
    two = "a ball rolls to the left and a box slides towards the camera on a tiled floor, while the camera orbits right"
    assert caption_direction(two) is None
    with pytest.raises(ValueError, match="exactly one direction"):
        flip_direction(two)


def test_synthetic_captions_of_single_translations_take_part():
    """Among sampled dynamic scenes, every caption with one direction phrase flips to the opposite phrase; the
    camera's own words ("orbits right", "pans left") are never taken for an object's direction."""
    taking_part = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=32, num_frames=5, texture_ratio=0.0)
        caption = caption_for(spec, np.eye(3))
        named = caption_direction(caption)
        phrases = sum(caption.count(p) for pair in DIRECTION_PHRASES for p in pair)
        assert (named is not None) == (phrases == 1)
        if named is not None:
            taking_part += 1
            assert caption_direction(flip_direction(caption))[1:] == (named[1], -named[2])
    assert taking_part >= 8


def test_moving_pixels_and_the_displacement_along_the_named_axis():
    T, H, W = 3, 2, 2
    tracks = torch.zeros(T, H, W, 3)
    tracks[:, 0, 0, 0] = torch.tensor([0.0, 0.1, 0.2])  # moves 0.2 m to the right
    tracks[:, 1, 1, 2] = torch.tensor([0.0, 0.0, MOVING_M / 2])  # below the moving threshold
    valid = torch.ones(H, W, dtype=torch.bool)
    moving = moving_pixels(tracks, valid)
    assert moving.tolist() == [[True, False], [False, False]]
    assert not moving_pixels(tracks, ~valid).any()
    positions = tracks.reshape(T, H * W, 3).transpose(0, 1)  # (P, T, 3): a scene that moves as the truth
    d = directional_motion(positions, moving.reshape(-1), axis=0)
    assert d == pytest.approx(0.2)
    assert moves_named_way(d, 1) and not moves_named_way(d, -1)
    assert not moves_named_way(directional_motion(positions.flip(1), moving.reshape(-1), 0), 1)  # the other way
    still = directional_motion(positions[:, :1].expand(-1, T, -1), moving.reshape(-1), 0)
    assert still == 0.0 and not moves_named_way(still, 1) and not moves_named_way(still, -1)  # holding still fails
    assert math.isnan(directional_motion(positions, torch.zeros(H * W, dtype=torch.bool), 0))
    assert not moves_named_way(float("nan"), 1)


def test_a_clip_takes_part_and_a_scene_is_scored_for_each_caption():
    """A clip takes part when it is dynamic, names one direction and its tracks move; a scene that moves as the
    truth answers the caption and fails the flipped one; one that dropped the moving pixel's point scores 0."""
    T, H, W = 3, 2, 2
    tracks = torch.zeros(T, H, W, 3)
    tracks[:, 0, 1, 0] = torch.tensor([0.0, -0.1, -0.3])  # 0.3 m to the left (−x)
    valid = torch.ones(H, W, dtype=torch.bool)
    clip = {"dynamic": torch.tensor(True), "caption": "a red ball rolls to the left on a wooden floor, while the "
            "camera stays still", "pixel_tracks": tracks, "pixel_track_valid": valid}
    axis, sign, moving = direction_query(clip)
    assert (axis, sign) == (0, -1) and moving.tolist() == [False, True, False, False]
    positions, kept = tracks.reshape(T, H * W, 3).transpose(0, 1), torch.ones(H * W, dtype=torch.bool)
    assert named_way_score(positions, kept, moving, axis, sign) == (True, pytest.approx(0.3))
    assert named_way_score(positions, kept, moving, axis, -sign) == (False, pytest.approx(-0.3))  # flipped caption
    assert named_way_score(positions, torch.tensor([True, False, True, True]), moving, axis, sign) == (False, 0.0)
    assert direction_query({**clip, "dynamic": torch.tensor(False)}) is None
    assert direction_query({**clip, "caption": "a ball rolls to the left and a box slides to the right"}) is None
    assert direction_query({**clip, "pixel_tracks": torch.zeros_like(tracks)}) is None  # nothing moves
