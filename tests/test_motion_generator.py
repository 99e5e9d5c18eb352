"""The motion generator (models/motion_generator.py) and its training (training/motion_generation.py): the motion
tensor against a brute-force per-cell mean, its decoding in closed form, zero-init, guidance against a hand-written
Euler loop, save/load, and a tiny model that learns a direction word."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
from helpers import tiny_motion_generator_config
from torch.utils.data import default_collate

from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.export import checkpoint_sha256
from models.bundle import Diff4SplatConfig, Diff4SplatModel
from models.flow_matching import sample_logit_normal, sigma_schedule
from models.motion_generator import (
    MotionGenerator,
    MotionGeneratorConfig,
    depth_features,
    key_frame_indices,
    motion_displacements,
    motion_targets,
    sample_motion,
)
from training import train as train_module
from training.losses import LossWeights
from training.motion_generation import (
    MOVING_CELL,
    MotionExamples,
    mirror,
    motion_generation_loss,
    motion_stage_scores,
    moving_cells,
    train_motion_generator,
)
from training.motion_generation import main as motion_generation_main
from training.objectives import TrainingModule
from training.stage_config import StageConfig, apply_freezing


def random_tracks(B=2, T=5, H=8, W=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(B, 1, H, W, 3, generator=g, dtype=torch.float64)
    x0[..., 2] = 1 + torch.rand(B, 1, H, W, generator=g, dtype=torch.float64) * 4  # in front of the camera
    tracks = x0 + torch.cumsum(torch.randn(B, T, H, W, 3, generator=g, dtype=torch.float64) * 0.1, 1)
    tracks[:, 0] = x0[:, 0]
    valid = torch.rand(B, H, W, generator=g) > 0.3
    return tracks, valid


def test_key_frames_are_the_rounded_fractions_of_the_clip():
    assert key_frame_indices(17, 4) == [4, 8, 12, 16]
    assert key_frame_indices(9, 3) == [3, 5, 8]
    with pytest.raises(ValueError, match="fewer than 4 frames"):
        key_frame_indices(4, 4)


def test_motion_targets_are_each_cells_mean_relative_displacement():
    tracks, valid = random_tracks()
    motion, weight = motion_targets(tracks, valid, key_frames=2, grid=4, motion_scale=0.1)
    assert motion.shape == (2, 6, 4, 4) and weight.shape == (2, 1, 4, 4)
    keys = key_frame_indices(5, 2)
    t, v = tracks.numpy(), valid.numpy()
    for b in range(2):
        for cy in range(4):
            for cx in range(4):
                rows = [(y, x) for y in range(2 * cy, 2 * cy + 2) for x in range(2 * cx, 2 * cx + 2) if v[b, y, x]]
                assert weight[b, 0, cy, cx] == pytest.approx(len(rows) / 4)
                for k, f in enumerate(keys):
                    want = (np.mean([(t[b, f, y, x] - t[b, 0, y, x]) / t[b, 0, y, x, 2] for y, x in rows], 0) / 0.1
                            if rows else np.zeros(3))
                    np.testing.assert_allclose(motion[b, 3 * k:3 * k + 3, cy, cx].numpy(), want, atol=1e-9)
    with pytest.raises(ValueError, match="multiple of the grid"):
        motion_targets(tracks, valid, key_frames=2, grid=3, motion_scale=0.1)


def test_a_constant_motion_decodes_to_itself_times_depth():
    """Uniform cells: the bilinear upsampling is exact, so each pixel's displacement is m·scale·z; motion_targets of
    those displacements gives m back."""
    m = torch.tensor([0.5, -1.0, 2.0, 1.5, 0.0, -0.25], dtype=torch.float64).reshape(1, 6, 1, 1).expand(1, 6, 4, 4)
    depth = torch.linspace(1, 3, 64, dtype=torch.float64).reshape(1, 8, 8)
    depth[0, 0, 0] = float("inf")
    d = motion_displacements(m, depth, 0.1)  # (1, 2, 8, 8, 3)
    want = m[0, :, 0, 0].reshape(2, 3)[:, None, None, :] * 0.1 * depth[0, None, ..., None]
    want[:, 0, 0] = 0  # no surface: no displacement
    torch.testing.assert_close(d[0], want)
    x0 = torch.stack([torch.zeros_like(depth), torch.zeros_like(depth), depth], -1)  # points on the optical axis
    tracks = torch.stack([x0, x0 + 0.5 * d[:, 0], x0 + d[:, 0], x0 + 1.5 * d[:, 1], x0 + d[:, 1]], 1)
    back, _ = motion_targets(tracks, torch.isfinite(depth), key_frames=2, grid=4, motion_scale=0.1)
    torch.testing.assert_close(back, m.contiguous())


def test_depth_features_are_scale_free_and_flag_missing_depth():
    depth = torch.rand(2, 8, 8, dtype=torch.float64) * 5 + 0.5
    depth[1, :2] = float("inf")
    f = depth_features(depth)
    torch.testing.assert_close(depth_features(depth * 3.7), f)
    assert f[1, 1, :2].eq(0).all() and f[1, 0, :2].eq(0).all() and f[:, 1, 2:].eq(1).all()
    assert f[0, 0][f[0, 1] > 0].median().abs() < 1e-12


def test_untrained_generator_predicts_zero_and_learns_from_the_first_step():
    torch.manual_seed(0)
    model = MotionGenerator(tiny_motion_generator_config())
    B = 2
    x, image = torch.randn(B, 6, 4, 4), torch.rand(B, 3, 16, 16) * 2 - 1
    depth = torch.rand(B, 16, 16) + 1
    v = model(x, torch.rand(B), image, depth_features(depth), model.encode_prompts(["a ball rolls", ""]))
    assert v.eq(0).all()
    motion = torch.randn(B, 6, 4, 4)
    loss = motion_generation_loss(model, image, depth, motion, torch.ones(B, 1, 4, 4), ["a", "b"],
                                  torch.Generator().manual_seed(0))
    loss.backward()
    assert model.final_layer.linear.weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="image must have shape"):
        model(x, torch.rand(B), image[..., :8], depth_features(depth), model.encode_prompts(["", ""]))


@pytest.mark.parametrize("text_attention", [False, True])
def test_guidance_matches_a_hand_written_euler_loop_and_weights_round_trip(tmp_path, text_attention):
    torch.manual_seed(1)
    model = MotionGenerator(tiny_motion_generator_config(text_attention=text_attention)).eval()
    for p in model.parameters():  # every branch live
        p.data.add_(torch.randn_like(p) * 0.05)
    image, depth = torch.rand(2, 3, 16, 16) * 2 - 1, torch.rand(2, 16, 16) + 1
    prompts = ["the red ball rolls to the left", "a box slides upwards"]
    for w in (1.0, 2.5):
        got = sample_motion(model, image, depth, prompts, steps=3, guidance=w,
                            generator=torch.Generator().manual_seed(7))
        x = torch.randn(2, 6, 4, 4, generator=torch.Generator().manual_seed(7))
        sig = sigma_schedule(3, dtype=torch.float64)
        with torch.no_grad():
            cond, null = model.encode_prompts(prompts), model.encode_prompts(["", ""])
            feats = depth_features(depth)
            for i in range(3):
                s = torch.full((2,), float(sig[i]))
                v_c = model(x, s, image, feats, cond)
                v = v_c if w == 1 else model(x, s, image, feats, null) + w * (v_c - model(x, s, image, feats, null))
                x = x + float(sig[i + 1] - sig[i]) * v
        torch.testing.assert_close(got, x, atol=1e-5, rtol=1e-5)
    model.save_pretrained(tmp_path / "mg")
    loaded = MotionGenerator.from_pretrained(tmp_path / "mg")
    torch.testing.assert_close(sample_motion(loaded, image, depth, prompts, steps=2, guidance=2.0,
                                             generator=torch.Generator().manual_seed(3)),
                               sample_motion(model, image, depth, prompts, steps=2, guidance=2.0,
                                             generator=torch.Generator().manual_seed(3)))
    with pytest.raises(ValueError, match="1 prompts for 2 photographs"):
        sample_motion(model, image, depth, prompts[:1])


def test_mirror_swaps_left_and_right_and_is_its_own_inverse():
    image, depth = torch.rand(2, 3, 8, 8), torch.rand(2, 8, 8)
    motion, weight = torch.randn(2, 6, 4, 4), torch.rand(2, 1, 4, 4)
    caption = "a red ball rolls to the left and a box slides to the right, while the camera orbits left"
    flip = torch.tensor([True, False])
    out = mirror(flip, image, depth, motion, weight, [caption, caption])
    assert out[4] == ["a red ball rolls to the right and a box slides to the left, while the camera orbits left",
                      caption]
    torch.testing.assert_close(out[2][0, 0], -motion[0, 0].flip(-1))
    torch.testing.assert_close(out[2][0, 4], motion[0, 4].flip(-1))
    torch.testing.assert_close(out[0][0], image[0].flip(-1))
    for a, b in zip(out[:4], (image, depth, motion, weight), strict=True):
        torch.testing.assert_close(a[1], b[1])  # not flipped: unchanged
    back = mirror(flip, *out)
    for a, b in zip(back[:4], (image, depth, motion, weight), strict=True):
        torch.testing.assert_close(a, b)
    assert back[4] == [caption, caption]


def square_clip(direction: str, size: int = 16, frames: int = 5) -> dict:
    """A centred bright square (2×2 cells of a 4² grid: no cell mixes it with the floor) on a grey floor 2 m away
    that slides 0.4 m the way ``direction`` says."""
    image = torch.full((3, size, size), -0.2)
    image[0, 4:12, 4:12] = 1.0
    depth = torch.full((size, size), 2.0)
    v = (size - 1) / 2
    ys, xs = torch.meshgrid(torch.arange(size) - v, torch.arange(size) - v, indexing="ij")
    x0 = torch.stack([xs / 8.0 * 2.0, ys / 8.0 * 2.0, depth], -1)  # focal 8 px
    step = torch.tensor({"to the right": [0.4, 0, 0], "to the left": [-0.4, 0, 0]}[direction])
    inside = torch.zeros(size, size, dtype=torch.bool)
    inside[4:12, 4:12] = True
    tracks = torch.stack([x0 + inside[..., None] * step * (f / (frames - 1)) for f in range(frames)])
    return {"image": image, "depth": depth, "tracks": tracks, "caption": f"a red box slides {direction}"}


@pytest.mark.slow
def test_a_tiny_generator_learns_the_direction_word_and_passes_the_direction_test():
    """The same symmetric photograph moves its square right or left as the caption says: only the words tell them
    apart (and the mirror augmentation turns every caption into its opposite too). Untrained, its motion is the
    noise whatever the caption, so no clip can pass with both the caption and its flip."""
    clips = [square_clip("to the right"), square_clip("to the left")]
    cfg = tiny_motion_generator_config()
    tracks = torch.stack([c["tracks"] for c in clips])
    valid = torch.ones(2, 16, 16, dtype=torch.bool)
    motion, weight = motion_targets(tracks, valid, cfg.key_frames, cfg.grid, cfg.motion_scale)
    examples = MotionExamples(torch.stack([c["image"] for c in clips]), torch.stack([c["depth"] for c in clips]),
                              motion, weight, [c["caption"] for c in clips], tracks[:, [0, -1]], valid,
                              torch.ones(2, dtype=torch.bool))
    torch.manual_seed(0)
    model = MotionGenerator(cfg)
    before = motion_stage_scores(model, examples, steps=8, guidance=2.0)
    assert before.clips == 2 and before.caption + before.flipped <= 1
    losses = train_motion_generator(model, examples, steps=120, batch_size=8, lr=3e-3, p_uncond=0.2)
    assert np.mean(losses[-30:]) < 0.5 * np.mean(losses[:30])
    after = motion_stage_scores(model, examples, steps=8, guidance=2.0)
    assert after.caption == 1 and after.flipped == 1, after
    assert 0.7 < after.magnitude_ratio < 1.3, after


@pytest.fixture(scope="module")
def bundle_with_generator():
    config = dataclasses.replace(Diff4SplatConfig(),
                                 motion_generator=tiny_motion_generator_config(image_size=32, grid=8))
    return Diff4SplatModel.random(config, seed=0)


def test_the_bundle_saves_and_loads_its_motion_generator_and_leaves_it_out_when_unnamed(tmp_path,
                                                                                        bundle_with_generator):
    model = bundle_with_generator
    assert "motion_generator" in model.networks() and model.parameter_counts()["motion_generator"] > 0
    model.save_pretrained(tmp_path / "m")
    back = Diff4SplatModel.from_pretrained(tmp_path / "m")
    assert back.config == model.config
    for a, b in zip(back.motion_generator.state_dict().values(), model.motion_generator.state_dict().values(),
                    strict=True):
        torch.testing.assert_close(a, b)
    assert "motion_generator/model.safetensors" in checkpoint_sha256(tmp_path / "m")
    plain = Diff4SplatModel.random(Diff4SplatConfig(), seed=0)
    assert plain.motion_generator is None and "motion_generator" not in plain.networks()
    plain.save_pretrained(tmp_path / "p")
    assert not (tmp_path / "p" / "motion_generator").exists()
    assert Diff4SplatModel.from_pretrained(tmp_path / "p").motion_generator is None
    assert "motion_generator/model.safetensors" not in checkpoint_sha256(tmp_path / "p")


def test_the_motion_generation_objective_is_the_mirrored_flow_loss_and_trains_only_the_generator(
        tmp_path_factory, bundle_with_generator):
    root = tmp_path_factory.mktemp("mg_data")
    generate_scene(root, 0, seed=11, size=32, frames=9, cameras=1, static_ratio=0.0)
    generate_scene(root, 1, seed=12, size=32, frames=9, cameras=1, static_ratio=0.0)
    ds = ClipDataset(root, ClipConfig(num_frames=9, height=32, width=32, plucker="packed", num_tracks=8))
    batch = default_collate([ds[0], ds[1]])
    model = copy.deepcopy(bundle_with_generator)
    stage = StageConfig(height=32, width=32, num_frames=9, train=("motion_generator",),
                        objectives=("motion_generation",), scenes="all", caption_dropout=0.3,
                        weights=LossWeights(motion_flow=0.75))
    apply_freezing(model, stage.train)
    losses = TrainingModule(model, stage).train()(batch, torch.Generator().manual_seed(5))
    assert set(losses) == {"motion_flow", "loss"}
    torch.testing.assert_close(losses["loss"], 0.75 * losses["motion_flow"])
    g = torch.Generator().manual_seed(5)  # by hand: the flips, then the loss's own draws
    cfg = model.motion_generator.config
    motion, weight = motion_targets(batch["pixel_tracks"], batch["pixel_track_valid"], cfg.key_frames, cfg.grid,
                                    cfg.motion_scale)
    assert weight.sum() > 0 and motion.abs().max() > 0  # the clips move
    flip = torch.rand(2, generator=g) < 0.5
    want = motion_generation_loss(model.motion_generator, *mirror(flip, batch["video"][:, :, 0] * 2 - 1,
                                                                  batch["depth"][:, 0], motion, weight,
                                                                  list(batch["caption"])), g, p_uncond=0.3)
    torch.testing.assert_close(losses["motion_flow"], want)
    losses["loss"].backward()
    grads = {n.split(".")[0] for n, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert grads == {"motion_generator"}
    with pytest.raises(ValueError, match="this model has none"):
        TrainingModule(Diff4SplatModel.random(Diff4SplatConfig(), seed=0), stage)(batch, torch.Generator())
    small = dataclasses.replace(stage, height=16, width=16)
    with pytest.raises(ValueError, match="reads 32×32"):
        TrainingModule(model, small)(default_collate([ClipDataset(root, num_frames=9, height=16, width=16,
                                                                  plucker="packed")[0]]), torch.Generator())


def test_the_loss_weighs_moving_cells_by_one_plus_mover():
    """An untrained generator predicts v = 0, so the loss is the weighted mean of (ε − x0)² by hand, moving cells
    (above MOVING_CELL at some key time) weighing 1 + mover times their valid fraction."""
    torch.manual_seed(0)
    model = MotionGenerator(tiny_motion_generator_config())
    B = 3
    image, depth = torch.rand(B, 3, 16, 16) * 2 - 1, torch.rand(B, 16, 16) + 1
    motion = torch.zeros(B, 6, 4, 4)
    motion[0, 3:, 1, 2] = torch.tensor([0.5, 0.0, 0.0])  # moves at the second key time only
    motion[1, 0, 0, 0] = MOVING_CELL / 2  # below the threshold: still
    weight = torch.rand(B, 1, 4, 4)
    assert moving_cells(motion).sum() == 1 and bool(moving_cells(motion)[0, 0, 1, 2])
    loss = motion_generation_loss(model, image, depth, motion, weight, ["a", "b", "c"],
                                  torch.Generator().manual_seed(4), mover=7.0)
    g = torch.Generator().manual_seed(4)
    sample_logit_normal(B, generator=g)
    noise = torch.randn(motion.shape, generator=g)
    w = weight.clone()
    w[0, 0, 1, 2] *= 8.0
    want = ((noise - motion).square() * w).sum() / (w.sum() * 6)
    torch.testing.assert_close(loss, want)


@pytest.mark.slow
def test_the_command_trains_a_generator_into_a_model_folder_and_refuses_bad_input_first(tmp_path, capsys):
    root = tmp_path / "data"
    generate_scene(root, 0, seed=13, size=64, frames=9, cameras=1, static_ratio=0.0)
    base = Diff4SplatModel.random(Diff4SplatConfig(num_frames=9), seed=0)
    base.save_pretrained(tmp_path / "base")
    out = tmp_path / "with_generator"
    args = ["--data", str(root), "--into", str(tmp_path / "base"), "--steps", "2", "--batch-size", "2", "--quiet",
            "--device", "cpu"]
    assert motion_generation_main([*args, "--out", str(out)]) == 0, capsys.readouterr().err
    model = Diff4SplatModel.from_pretrained(out)
    assert model.motion_generator is not None and model.config.motion_generator.image_size == 64
    for name in ("vae", "dit", "ldrm"):  # the other networks are the folder's
        for a, b in zip(getattr(model, name).state_dict().values(), getattr(base, name).state_dict().values(),
                        strict=True):
            torch.testing.assert_close(a, b)
    capsys.readouterr()
    for bad in ([*args[:2], "--into", str(tmp_path / "none"), *args[4:], "--out", str(tmp_path / "o2")],
                [*args, "--out", str(root)]):  # no model folder; the output is the data
        assert motion_generation_main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("motion_generation: error:"), err
    assert not (tmp_path / "o2").exists()


def test_a_stage_that_trains_the_motion_generator_starts_a_fresh_one_at_its_clip_size():
    stage = StageConfig(height=32, width=32, num_frames=9, train=("motion_generator",),
                        objectives=("motion_generation",), scenes="all")
    model = train_module._with_motion_generator(Diff4SplatModel.random(Diff4SplatConfig(), seed=0), stage)
    assert model.config.motion_generator == MotionGeneratorConfig(image_size=32)
    assert model.motion_generator.config is model.config.motion_generator
    again = train_module._with_motion_generator(Diff4SplatModel.random(Diff4SplatConfig(), seed=0), stage)
    for a, b in zip(model.motion_generator.parameters(), again.motion_generator.parameters(), strict=True):
        torch.testing.assert_close(a, b)  # seeded by trainer.seed
    assert train_module._with_motion_generator(model, stage) is model  # one it has stays
    plain = Diff4SplatModel.random(Diff4SplatConfig(), seed=0)
    unchanged = train_module._with_motion_generator(plain, dataclasses.replace(stage, train=("dit",)))
    assert unchanged.motion_generator is None
    with pytest.raises(ValueError, match="must be equal for a motion generator"):
        train_module._with_motion_generator(plain, dataclasses.replace(stage, width=64))
