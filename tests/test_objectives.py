"""Tests of training/objectives.py: the track query pixel (closed form), the frame renders of static and
moving scenes, and TrainingModule's losses and gradient flow for every stage's objective set."""
import copy
import dataclasses
import math

import pytest
import torch
from helpers import OBJECTIVE_CASES, tiny_model
from torch.utils.data import default_collate

from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.assembly.assemble import assemble_scene, to_gaussians
from diff4splat.assembly.photo import PHOTO_EPS2D
from diff4splat.assembly.prune import settle_generated
from diff4splat.cameras import camera_rays
from diff4splat.cameras.path import CameraPath
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from models.flow_matching import shift_sigmas
from training.losses import (
    LossWeights,
    depth_correlation_loss,
    depth_smoothness_loss,
    head_distillation_loss,
    log_depth_loss,
    photometric_loss,
)
from training.objectives import TrainingModule, render_frames, track_query_index
from training.stage_config import StageConfig, apply_freezing

SIZE, FRAMES = 32, 9


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """One static and one dynamic 32² clip of 9 frames, as build_training's ClipDataset yields them."""
    root = tmp_path_factory.mktemp("objectives_data")
    generate_scene(root, 0, seed=11, size=SIZE, frames=FRAMES, cameras=1, static_ratio=1.0)
    generate_scene(root, 1, seed=11, size=SIZE, frames=FRAMES, cameras=1, static_ratio=0.0)
    ds = ClipDataset(root, ClipConfig(num_frames=FRAMES, height=SIZE, width=SIZE, scenes="all", plucker="packed",
                                      num_tracks=64, seed=0))
    items = [ds[0], ds[1]]
    assert not bool(items[0]["dynamic"]) and bool(items[1]["dynamic"])
    return items


# ----------------------------------------------------------------------------------- track_query_index
def test_track_query_index_closed_form():
    W, H = 40, 24  # not square: a row/column swap changes the index
    K = torch.tensor([[30.0, 0.0, 21.0], [0.0, 20.0, 11.0], [0.0, 0.0, 1.0]])
    pts = torch.tensor([
        [0.0, 0.0, 2.0],      # u = 21, v = 11 → pixel (11, 21)
        [0.5, -0.25, 1.0],    # u = 36, v = 6 → pixel (6, 36)
        [-1.4, -1.1, 2.0],    # u = 0, v = 0 exactly → pixel (0, 0)
        [1.25, 0.6, 2.0],     # u = 39.75, v = 17 → pixel (17, 39), the last column
        [0.0, 0.0, -2.0],     # behind the camera
        [0.0, 0.0, 0.0],      # at the camera centre (a padded track)
        [0.7, 0.0, 1.0],      # u = 42 ≥ W: right of the image
        [0.0, -0.6, 1.0],     # v = −1 < 0: above the image
        [-0.71, 0.0, 1.0],    # u = −0.3: floor would give column −1
        [0.0, 0.66, 1.0],     # v = 24.2 ≥ H
        [0.1, 0.1, 3.0],      # in the image, but not a valid track
    ])
    valid = torch.ones(len(pts), dtype=torch.bool)
    valid[-1] = False
    idx, ok = track_query_index(pts, K, W, H, valid)
    expected_ok = [True, True, True, True, False, False, False, False, False, False, False]
    assert ok.tolist() == expected_ok
    assert idx[:4].tolist() == [11 * W + 21, 6 * W + 36, 0, 17 * W + 39]
    assert idx.dtype == torch.long and idx[4:].tolist() == [0] * 7  # invalid → 0, a safe gather index


def test_track_query_index_recovers_the_pixel_of_every_pixel_aligned_gaussian():
    """Points on the pixel-centre rays (the LDRM's Gaussians, row-major) map back to their own index."""
    W, H = 12, 7
    K = torch.tensor([[[9.0, 0.0, 6.3], [0.0, 11.0, 3.2], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    origins, dirs = camera_rays(torch.eye(4, dtype=torch.float64)[None], K, W, H)
    dist = 0.5 + 3 * torch.rand(H, W, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    points = (origins[0] + dist * dirs[0]).reshape(-1, 3)
    idx, ok = track_query_index(points, K[0], W, H, torch.ones(H * W, dtype=torch.bool))
    assert ok.all() and torch.equal(idx, torch.arange(H * W))


# ----------------------------------------------------------------------------------- render_frames
def test_render_frames_uses_each_frames_time_and_camera():
    """A rigid deformation Δμ(t) = t·s equals moving the camera by −t·s, so the moving scene's renders
    equal the static scene's renders through shifted cameras, frame by frame."""
    D, W, H, T = torch.float64, 20, 16, 4
    g = torch.Generator().manual_seed(3)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    m = 80
    means = torch.stack([r(m) - 0.5, r(m) - 0.5, 2 + r(m)], -1)
    canon = Gaussians(means, torch.randn(m, 4, generator=g, dtype=D), 0.03 + 0.05 * r(m, 3), 0.3 + 0.6 * r(m),
                      rgb_to_sh0(r(m, 1, 3)))
    times = torch.linspace(0, 1, T, dtype=D)
    shift = torch.tensor([0.3, -0.2, 0.1], dtype=D)
    dq = torch.zeros(T, m, 4, dtype=D)
    dq[..., 0] = 1
    d_means = times[:, None, None] * shift.expand(T, m, 3)
    moving = DynamicGaussians(canon, times, d_means, dq, torch.zeros(T, m, 3, dtype=D))
    viewmats = torch.eye(4, dtype=D).repeat(T, 1, 1)
    viewmats[:, 0, 3] = torch.linspace(0, 0.2, T, dtype=D)  # a camera truck: every frame sees a different view
    Ks = torch.tensor([[18.0, 0, 10.0], [0, 18.0, 8.0], [0, 0, 1]], dtype=D).expand(T, 3, 3)
    frames = [0, 2, 3]
    rgb, depth, alpha = render_frames(moving, viewmats, Ks, times, frames, W, H)
    assert rgb.shape == (3, 3, H, W) and depth.shape == alpha.shape == (3, H, W)
    shifted = viewmats.clone()
    shifted[:, :3, 3] += times[:, None] * shift  # viewmat · translate(t·s)
    rgb_s, depth_s, alpha_s = render_frames(DynamicGaussians(canon), shifted, Ks, times, frames, W, H)
    torch.testing.assert_close(rgb, rgb_s)
    torch.testing.assert_close(alpha, alpha_s)
    torch.testing.assert_close(depth, depth_s)
    assert alpha.amax() > 0.5 and not torch.allclose(rgb[1], rgb[2])  # non-trivial renders


# ----------------------------------------------------------------------------------- TrainingModule
NETWORKS = ("vae", "text_encoder", "dit", "ldrm", "ldrm.deformation")
# not the defaults: the sum is checked
WEIGHTS = LossWeights(ssim=0.2, rgb=2.0, depth=0.5, metric_depth=0.75, smooth=0.25, motion=3.0, displacement=1.5,
                      warp=0.5, scene_flow=2.5, mover=1.25)


def _network(name: str) -> str:
    for part in ("ldrm.deformation", "ldrm.motion"):
        if name.startswith(part + "."):
            return part
    return name.split(".")[0]


CASES = {
    # stage: (StageConfig kwargs, loss keys, networks that must receive gradients)
    "vae": (dict(name="vae", train=("vae",), objectives=("vae",), scenes="all", kl_weight=0.01),
            {"vae_l1", "vae_kl"}, {"vae"}),
    "stage1": (dict(train=("dit", "ldrm"), objectives=("diffusion", "reconstruction")),
               {"flow", "flow_mover", "photo", "depth", "metric_depth", "smooth"}, {"dit", "ldrm"}),
    # the deformation network runs (deformation on) but is frozen: it must get no gradient
    "frozen_deformation": (dict(train=("ldrm",), objectives=("reconstruction",), deformation=True, motion=True),
                           {"photo", "depth", "metric_depth", "smooth", "motion", "displacement", "scene_flow"},
                           {"ldrm"}),
    "stage3": (dict(train=("dit", "ldrm", "ldrm.deformation"), objectives=("diffusion", "reconstruction"),
                    scenes="all", deformation=True, motion=True),
               {"flow", "flow_mover", "photo", "depth", "metric_depth", "smooth", "motion", "displacement",
                "scene_flow"}, {"dit", "ldrm", "ldrm.deformation"}),
    # the motion path (diff4splat.assembly.frame_motion) alone: the tracks and the renders reach it through the decoded
    # frames
    "motion_path": (dict(train=("ldrm.motion",), objectives=("reconstruction",), scenes="all", deformation=True,
                         motion=True),
                    {"photo", "depth", "metric_depth", "smooth", "motion", "displacement", "scene_flow"},
                    {"ldrm.motion"}),
    # the text encoder trains through the flow-matching loss when listed (frozen and without a graph otherwise)
    # (on the dynamic clip: the moving object's cells weigh in, weights.mover)
    "text": (dict(train=("text_encoder", "dit"), objectives=("diffusion",), scenes="all"), {"flow", "flow_mover"},
             {"text_encoder", "dit"}),
    # the tracking objective: the motion network alone, no renders
    "tracking": (dict(train=("ldrm.motion",), objectives=("tracking",), scenes="all"),
                 {"displacement", "warp", "scene_flow"}, {"ldrm.motion"}),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.slow
def test_forward_losses_and_gradients_reach_only_the_trainable_networks(clips, case):
    kwargs, keys, trained = CASES[case]
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, render_frames=2, weights=WEIGHTS, **kwargs)
    # a non-zero deformation head (and motion network): they shape the renders
    # the text case needs the DiT's zero-initialised cross-attention open for a gradient to reach the text encoder
    model = tiny_model(seed=1, dynamic=True, motion=case in ("motion_path", "tracking"), active_dit=case == "text")
    apply_freezing(model, stage.train)
    module = TrainingModule(model, stage).train()
    batch = default_collate(clips[1:] if stage.deformation or case in ("tracking", "text") else clips[:1])
    losses = module(batch, torch.Generator().manual_seed(0))
    assert set(losses) == keys | {"loss"}
    assert all(v.ndim == 0 and math.isfinite(float(v.detach())) for v in losses.values()), losses
    rendering = lambda t: (2.0 * t["photo"] + 0.5 * t["depth"] + 0.75 * t["metric_depth"]  # noqa: E731
                           + 0.25 * t["smooth"])
    tracks = lambda t: 3.0 * t["motion"] + 1.5 * t["displacement"] + 2.5 * t["scene_flow"]  # noqa: E731
    expected = {
        "vae": lambda terms: terms["vae_l1"] + stage.kl_weight * terms["vae_kl"],
        "stage1": lambda terms: terms["flow"] + 1.25 * terms["flow_mover"] + rendering(terms),
        "text": lambda terms: terms["flow"] + 1.25 * terms["flow_mover"],
        "frozen_deformation": lambda terms: rendering(terms) + tracks(terms),
        "motion_path": lambda terms: rendering(terms) + tracks(terms),
        "tracking": lambda terms: (1.5 * terms["displacement"] + WEIGHTS.warp * terms["warp"]
                                   + 2.5 * terms["scene_flow"]),
        "stage3": lambda terms: terms["flow"] + 1.25 * terms["flow_mover"] + rendering(terms) + tracks(terms),
    }[case](losses)
    torch.testing.assert_close(losses["loss"], expected)
    if "flow_mover" in keys:  # zero exactly where no object moves
        assert (float(losses["flow_mover"].detach()) > 1e-4) == bool(batch["dynamic"].any())
    if "motion" in keys or "displacement" in keys:
        assert float(losses["displacement"].detach()) > 1e-3  # visible tracks were queried and compared
        assert float(losses["scene_flow"].detach()) > 1e-3  # so were the dense tracks
    losses["loss"].backward()
    got = {}
    for name, p in model.named_parameters():
        if p.grad is None:
            continue
        assert _network(name) in trained, f"{case}: frozen {name} received a gradient"
        got[_network(name)] = got.get(_network(name), 0.0) + float(p.grad.abs().sum())
    assert set(got) == trained and all(v > 0 for v in got.values()), got


def test_training_sigmas_follow_the_model_configs_logit_normal_and_the_stage_shift():
    """The stage drew σ from logit-normal(0, 1) whatever the model config's logit_normal_mean/std said."""
    model = tiny_model()
    model.config = dataclasses.replace(model.config, sampling=dataclasses.replace(
        model.config.sampling, logit_normal_mean=1.5, logit_normal_std=0.5))
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, flow_shift=1.0)
    sigmas = TrainingModule(model, stage).backbone().training_sigmas(20_000, torch.Generator().manual_seed(0))
    u = torch.logit(sigmas.double())
    assert abs(float(u.mean()) - 1.5) < 0.02 and abs(float(u.std()) - 0.5) < 0.02
    plain = TrainingModule(model, stage).backbone().training_sigmas(8, torch.Generator().manual_seed(1))
    shifted = TrainingModule(model, dataclasses.replace(stage, flow_shift=3.0)).backbone()
    torch.testing.assert_close(shifted.training_sigmas(8, torch.Generator().manual_seed(1)), shift_sigmas(plain, 3.0))


@pytest.mark.slow
def test_forward_is_a_function_of_the_generator(clips):
    """Same generator state → the same losses (exact resume relies on it); another seed → new σ, ε."""
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, objectives=("diffusion",), caption_dropout=0.0)
    module = TrainingModule(tiny_model(active_dit=True), stage)
    batch = default_collate(clips[:1])
    with torch.no_grad():
        a = module(batch, torch.Generator().manual_seed(5))["flow"]
        b = module(batch, torch.Generator().manual_seed(5))["flow"]
        c = module(batch, torch.Generator().manual_seed(6))["flow"]
    assert float(a) == float(b) and float(a) != float(c)


@pytest.mark.slow
def test_caption_dropout_trains_the_empty_prompt_path(clips):
    """caption_dropout = 1 gives exactly the loss of an empty caption; with 0 the caption changes it."""
    model = tiny_model(active_dit=True)  # the DiT reads the text through its cross-attention
    batch = default_collate(clips[:1])
    assert batch["caption"][0].strip()
    empty = {**batch, "caption": [""]}

    def flow(b, dropout):
        stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, objectives=("diffusion",),
                            caption_dropout=dropout)
        with torch.no_grad():
            return float(TrainingModule(model, stage)(b, torch.Generator().manual_seed(9))["flow"])

    assert flow(batch, 1.0) == pytest.approx(flow(empty, 0.0), abs=1e-7)
    assert abs(flow(batch, 0.0) - flow(empty, 0.0)) > 1e-6


def _hand_motion(batch, g, dm) -> tuple[list[float], list[float]]:
    """Track end-point errors and displacement errors of clip 0, each visible track's frame-0 Gaussian found by
    projecting its frame-0 point by hand (u = fx·x/z + cx, v = fy·y/z + cy; the first H·W Gaussians are frame 0's
    pixel grid)."""
    tracks, K = batch["tracks"][0].double(), batch["Ks"][0, 0].double()
    vis = batch["track_visibility"][0] & batch["track_mask"][0][:, None]
    errors, moves = [], []
    for n in range(tracks.shape[0]):
        x, y, z = tracks[n, 0].tolist()
        if not bool(vis[n, 0]) or z <= 1e-6:
            continue
        u, v = K[0, 0].item() * x / z + K[0, 2].item(), K[1, 1].item() * y / z + K[1, 2].item()
        if not (0 <= u < SIZE and 0 <= v < SIZE):
            continue
        i = math.floor(v) * SIZE + math.floor(u)
        for t in range(FRAMES):
            if bool(vis[n, t]):
                errors.append(float((g.means[i] + dm[t, i] - tracks[n, t]).norm()))
                if t > 0:  # displacement from frame 0 (visible at 0 by the test above)
                    moves.append(float((dm[t, i] - dm[0, i] - (tracks[n, t] - tracks[n, 0])).norm()))
    assert len(errors) > 20 and len(moves) > 20
    return errors, moves


def _check_losses(losses, batch, frames, rgb, depth, alpha, g, dm) -> None:
    """losses equal training.losses on the hand renders (frames of clip 0) and the hand motion terms, weighted."""
    target = batch["video"][0][:, frames].permute(1, 0, 2, 3)
    valid = batch["depth_valid"][0][frames] & (alpha > 0.5)
    torch.testing.assert_close(losses["photo"], photometric_loss(rgb, target, WEIGHTS.ssim))
    torch.testing.assert_close(losses["depth"], depth_correlation_loss(depth, batch["depth"][0][frames], valid))
    torch.testing.assert_close(losses["smooth"], depth_smoothness_loss(depth, target, alpha > 0.5))
    torch.testing.assert_close(losses["metric_depth"], log_depth_loss(depth, batch["depth"][0][frames], valid))
    errors, moves = _hand_motion(batch, g, dm)
    assert float(losses["motion"]) == pytest.approx(sum(errors) / len(errors), rel=1e-5)
    assert float(losses["displacement"]) == pytest.approx(sum(moves) / len(moves), rel=1e-4)
    # the dense term: every valid pixel's frame-0 Gaussian (index v·W + u) against the clip's pixel tracks
    pix, ok = batch["pixel_tracks"][0].double().reshape(FRAMES, -1, 3), batch["pixel_track_valid"][0].reshape(-1)
    own = dm[:, : SIZE * SIZE].double()
    flow = ((own[1:] - own[:1]) - (pix[1:] - pix[:1])).norm(dim=-1)[:, ok]
    assert ok.sum() > 100 and float(losses["scene_flow"]) == pytest.approx(float(flow.mean()), rel=1e-4)
    weighted = (2.0 * losses["photo"] + 0.5 * losses["depth"] + 0.75 * losses["metric_depth"]
                + 0.25 * losses["smooth"] + 3.0 * losses["motion"] + 1.5 * losses["displacement"]
                + 2.5 * losses["scene_flow"])
    torch.testing.assert_close(losses["loss"], weighted)


def _reconstruction_case(clips, scene: str):
    """The dynamic clip's losses under ``stage.scene`` = scene, and what a hand computation needs."""
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, render_frames=3, weights=WEIGHTS, scene=scene,
                        train=("ldrm",), objectives=("reconstruction",), deformation=True, motion=True)
    model = tiny_model(seed=1, dynamic=True)
    batch = default_collate(clips[1:])
    with torch.no_grad():
        losses = TrainingModule(model, stage).eval()(batch, torch.Generator().manual_seed(0))
        latents = model.vae.encode_latents(batch["video"] * 2 - 1)
        times = batch["times"][0]
        out = model.ldrm(latents, batch["plucker_packed"], times)
    sources = torch.tensor([4 * i for i in range(latents.shape[2])])  # gaussian_frames "latent"
    draw = torch.randperm(FRAMES - 1, generator=torch.Generator().manual_seed(0))[:2] + 1
    return losses, batch, times, out, sources, [0] + sorted(draw.tolist())


@pytest.mark.slow
def test_assembled_reconstruction_losses_equal_a_hand_computation(clips):
    """``scene: assembled``: the scene is generate's (photo layer of frame 0 on the predicted depth, backdrop, later
    source frames without the redundant ones), the frames are frame 0 plus the generator's randperm draw,
    photo/depth/smooth come from training.losses on those renders over the photograph's mean colour, and the motion
    loss is the end-point error of each visible track's photo-layer disk."""
    losses, batch, times, out, sources, frames = _reconstruction_case(clips, "assembled")
    with torch.no_grad():
        cams = CameraPath(batch["viewmats"][0], batch["Ks"][0], SIZE, SIZE, times)
        photo = batch["video"][0, :, 0].permute(1, 2, 0)
        full, grid, info = assemble_scene(out, sources, cams, cams, photo, times)
        full, drop, counts = settle_generated(full, grid, cams, sources, info["photo_depth"])
        assert 0 < int(drop.sum()) == counts["duplicates"] + counts["occluders"] < int((grid > 0).sum())
        scene = full.select(~drop)
        rgb, depth, alpha = render_frames(scene, batch["viewmats"][0], batch["Ks"][0], times, frames, SIZE, SIZE,
                                          eps2d=PHOTO_EPS2D, background=torch.tensor(info["background"]))
    mse0 = float(((rgb[0] - photo.permute(2, 0, 1)) ** 2).mean())
    assert -10 * math.log10(mse0) >= 35.0, "frame 0 must be the photograph whatever the network predicts"
    _check_losses(losses, batch, frames, rgb, depth, alpha, scene.canonical, scene.d_means)  # rebased: dm[0] = 0


@pytest.mark.slow
def test_decoded_reconstruction_losses_equal_a_hand_computation(clips):
    """``scene: decoded`` (the default, the paper's LDRM objective): every source frame's pixel-aligned Gaussians,
    built by hand here (μ = camera centre + distance · unit ray through the pixel centre, colour and opacity as
    decoded), rendered alone over black with the default eps2d; frame 0 is then the network's, not the photograph."""
    losses, batch, times, out, sources, frames = _reconstruction_case(clips, "decoded")
    assert StageConfig().scene == "decoded"
    with torch.no_grad():
        S = len(sources)
        origins, dirs = camera_rays(batch["viewmats"][0][sources], batch["Ks"][0][sources], SIZE, SIZE)
        means = (origins + out.distance[0][..., None] * dirs).reshape(S * SIZE * SIZE, 3)
        g, dm, dq, ds = to_gaussians(out, batch["viewmats"][0][sources], batch["Ks"][0][sources])
        torch.testing.assert_close(g.means, means)
        scene = DynamicGaussians(g, times, dm, dq, ds)
        rgb, depth, alpha = render_frames(scene, batch["viewmats"][0], batch["Ks"][0], times, frames, SIZE, SIZE)
    mse0 = float(((rgb[0] - batch["video"][0][:, 0]) ** 2).mean())
    assert -10 * math.log10(mse0) < 35.0, "an untrained LDRM's frame 0 is not the photograph"
    _check_losses(losses, batch, frames, rgb, depth, alpha, g, dm)


@pytest.mark.slow
def test_distill_objective_follows_the_teacher_and_trains_only_the_head(clips):
    """``distill``: 0 when the teacher is the student itself (no blur); against another LDRM it equals
    head_distillation_loss of the two heads' raw maps on the same noised latents (σ then ε drawn from the step
    generator, frame 0 clean), and only the trained head gets gradients (the teacher none)."""
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, train=("ldrm.head",), objectives=("distill",),
                        teacher="unused", distill_sigma=1.0, latent_noise=0.3)
    model = tiny_model(seed=1)
    apply_freezing(model, stage.train)
    batch = default_collate(clips)
    with torch.no_grad():
        same = TrainingModule(model, dataclasses.replace(stage, distill_sigma=0.0), copy.deepcopy(model.ldrm))
        assert float(same(batch, torch.Generator())["loss"]) == 0
    teacher = tiny_model(seed=2).ldrm
    losses = TrainingModule(model, stage, teacher)(batch, torch.Generator().manual_seed(3))
    assert set(losses) == {"distill", "loss"}
    with torch.no_grad():
        latents = model.vae.encode_latents(batch["video"] * 2 - 1)
        gen = torch.Generator().manual_seed(3)
        sigma = (torch.rand(2, generator=gen) * 0.3)[:, None, None, None, None]
        noisy = (1 - sigma) * latents + sigma * torch.randn(latents.shape, generator=gen)
        noisy[:, :, 0] = latents[:, :, 0]
        plucker = batch["plucker_packed"]
        want = head_distillation_loss(model.ldrm.head_maps(model.ldrm.features(noisy, plucker)),
                                      teacher.head_maps(teacher.features(noisy, plucker)), 1.0)
    torch.testing.assert_close(losses["distill"], want)
    losses["loss"].backward()
    trained = {n for n, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained == {f"ldrm.head.{n}" for n, _ in model.ldrm.head.named_parameters()}
    assert all(p.grad is None for p in teacher.parameters())
    with pytest.raises(ValueError, match="teacher"):
        TrainingModule(model, stage)


@pytest.mark.slow
def test_latent_noise_reaches_frames_after_the_first_only(clips, monkeypatch):
    """latent_noise > 0: the LDRM sees frame 0's clean latent and noised later frames, (1 − σ)z + σε with
    σ ≤ latent_noise; latent_noise = 0 passes the encoded video unchanged."""
    model = tiny_model(seed=1)
    batch = default_collate(clips[:1])
    seen = []
    real = model.ldrm.forward
    monkeypatch.setattr(model.ldrm, "forward", lambda lat, *a, **k: seen.append(lat) or real(lat, *a, **k))
    with torch.no_grad():
        clean = model.vae.encode_latents(batch["video"] * 2 - 1)
        for noise in (0.0, 0.5):
            stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, render_frames=2, train=("ldrm",),
                                objectives=("reconstruction",), latent_noise=noise)
            TrainingModule(model, stage)(batch, torch.Generator().manual_seed(0))
    assert torch.equal(seen[0], clean)
    assert torch.equal(seen[1][:, :, 0], clean[:, :, 0]) and not torch.allclose(seen[1][:, :, 1:], clean[:, :, 1:])
    # x = (1 − σ)z + σε with one σ ≤ 0.5 per clip: the residual is a scaled standard normal, far below |z| + |ε|
    resid = seen[1][:, :, 1:] - clean[:, :, 1:]
    assert 0 < float(resid.std()) < 0.5 * float((clean[:, :, 1:].std() ** 2 + 1) ** 0.5) * 1.2


# ----------------------------------------------------------------------------------- devices
@pytest.mark.parametrize("case", list(OBJECTIVE_CASES))
@pytest.mark.slow
def test_forward_creates_every_tensor_on_the_inputs_device(clips, case, no_implicit_device):
    """The device rule in TrainingModule: with torch's default device "meta" (the fixture), a tensor made
    without device= (a draw on the CPU step generator left unmoved, a mask built on the default device) lands on
    meta beside the CPU batch and fails — as it failed beside CUDA batches on a GPU ("cuda:0 and cpu"). The
    forward and backward run, with the losses of the same forward made with the CPU as the default device."""
    kwargs, clip = OBJECTIVE_CASES[case]
    with torch.device("cpu"):  # the model, the batch and the reference losses: explicitly on the CPU
        stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, render_frames=2, **kwargs)
        model = tiny_model(seed=1, dynamic=True, active_dit=True)
        apply_freezing(model, stage.train)
        module = TrainingModule(model, stage).train()
        batch = default_collate(clips[clip:clip + 1])
        expected = {k: float(v.detach()) for k, v in module(batch, torch.Generator().manual_seed(4)).items()}
        gen = torch.Generator().manual_seed(4)
    losses = module(batch, gen)
    losses["loss"].backward()
    assert all(v.device.type == "cpu" for v in losses.values())
    assert {k: float(v.detach()) for k, v in losses.items()} == pytest.approx(expected, rel=1e-6, abs=1e-7)
    assert any(p.grad is not None and p.grad.device.type == "cpu" for p in model.parameters())
