"""The motion generator in the pipeline (diff4splat/assembly/generated_motion.py, Diff4SplatPipeline with a model
whose config names a motion generator): key-time interpolation in closed form, the dead zone, and a prompted scene
whose photo layer moves exactly by the generated motion while no prompt stays static."""
import dataclasses

import pytest
import torch
from helpers import SQUARE_SIZE as SIZE
from helpers import square_scene, still_path, tiny_model, tiny_motion_generator_config

from diff4splat.assembly.generated_motion import (
    MIN_RELATIVE_MOTION,
    MOTION_GUIDANCE,
    MOTION_STEPS,
    generated_motion,
    key_time_weights,
)
from diff4splat.pipeline import Diff4SplatPipeline
from models.bundle import Diff4SplatModel
from models.motion_generator import MotionGenerator, motion_displacements, sample_motion


def test_key_time_weights_interpolate_linearly_between_key_times():
    w = key_time_weights(torch.tensor([0.0, 0.125, 0.25, 0.6, 1.0, 1.5], dtype=torch.float64), 4)
    values = torch.tensor([0.0, 1.0, 3.0, 4.0, 8.0], dtype=torch.float64)  # at times 0, 1/4, 1/2, 3/4, 1
    torch.testing.assert_close(w @ values, torch.tensor([0.0, 0.5, 1.0, 3.4, 8.0, 8.0], dtype=torch.float64))
    torch.testing.assert_close(w.sum(1), torch.ones(6, dtype=torch.float64))


def test_motion_below_the_dead_zone_is_none_and_above_it_is_the_decoded_sample():
    image, depth, _ = square_scene()
    times = torch.linspace(0, 1, 3)  # the tiny generator's key times (K = 2) and time 0
    torch.manual_seed(0)
    # untrained: the motion is the noise times motion_scale
    quiet = MotionGenerator(tiny_motion_generator_config(motion_scale=MIN_RELATIVE_MOTION / 100))
    motion, moving = generated_motion(quiet, image, depth, times, "a box slides to the left", seed=1)
    assert not moving.any() and motion.eq(0).all()
    loud = MotionGenerator(tiny_motion_generator_config(motion_scale=0.004))
    motion, moving = generated_motion(loud, image, depth, times, "a box slides to the left", seed=1)
    # by hand: the sample at 16², decoded at 64² with the depth; the key times are these times exactly
    small = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=(16, 16), mode="area") * 2 - 1
    z = torch.nn.functional.interpolate(depth[None, None], size=(16, 16), mode="nearest")[:, 0]
    raw = motion_displacements(sample_motion(loud, small, z, ["a box slides to the left"], steps=MOTION_STEPS,
                                             guidance=MOTION_GUIDANCE, generator=torch.Generator().manual_seed(1)),
                               depth[None], 0.004)[0]
    want = (raw.norm(dim=-1) > MIN_RELATIVE_MOTION * depth).any(0)
    assert torch.equal(moving, want) and 0 < moving.float().mean() < 1  # some pixels in the dead zone, some not
    assert motion[0].eq(0).all()  # time 0 never moves
    torch.testing.assert_close(motion[1:][:, moving], raw[:, moving])
    assert motion[:, ~moving].eq(0).all()


@pytest.mark.slow
def test_a_prompted_scene_moves_its_photo_layer_by_the_generated_motion_and_no_prompt_stays_static():
    image, depth, _ = square_scene()
    base = tiny_model(dynamic=True)
    config = dataclasses.replace(base.config, motion_generator=tiny_motion_generator_config(motion_scale=0.5))
    model = Diff4SplatModel(config)
    model.load_state_dict(base.state_dict(), strict=False)  # the tiny networks, a fresh motion generator
    pipe = Diff4SplatPipeline(model.eval())
    assert pipe.runtime.has_motion_generator
    path = still_path(pipe)
    assert pipe(image, path, steps=1, depth=depth).scene.is_static  # no prompt: no motion generator, no motion
    res = pipe(image, path, "a red box slides to the left", steps=1, depth=depth, seed=3)
    scene = res.scene
    assert not scene.is_static
    motion, moving = generated_motion(model.motion_generator, image, depth, scene.times, "a red box slides to the left",
                                      seed=3)
    front = res.gaussian_index < SIZE * SIZE  # the photo layer's front disks, pixel index = slot
    pixel = res.gaussian_index[front]
    torch.testing.assert_close(scene.d_means[:, front], motion.reshape(len(scene.times), -1, 3)[:, pixel])
    others = ~(res.gaussian_index < SIZE * SIZE + (SIZE // 2) ** 2)  # backdrop and generated frames: still
    assert float(scene.d_means[:, others].abs().max()) == 0.0
