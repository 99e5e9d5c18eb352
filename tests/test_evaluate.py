import math

import pytest
import torch
from helpers import tiny_model

from diff4splat.pipeline import Diff4SplatPipeline
from training.evaluate import (
    DIAGNOSTICS,
    METRICS,
    PSNR_CAP,
    _held_out_clips,
    _pearson,
    _psnr,
    evaluate_clip,
    sampling_tradeoffs,
)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    from data_prep.synth import generate_scene

    root = tmp_path_factory.mktemp("heldout")
    generate_scene(root, 0, seed=123, size=64, frames=9, cameras=1, static_ratio=0.0)
    return _held_out_clips(root, 64, 64, 9, None)


@pytest.fixture(scope="module")
def static_clip(tmp_path_factory):
    from data_prep.synth import generate_scene

    root = tmp_path_factory.mktemp("heldout_static")
    generate_scene(root, 0, seed=124, size=64, frames=9, cameras=1, static_ratio=1.0)
    (clip,) = _held_out_clips(root, 64, 64, 9, None)
    assert not bool(clip["dynamic"])
    return clip


def test_pearson_and_psnr_closed_forms():
    a = torch.arange(10.0)
    assert _pearson(a, 2 * a + 1) == pytest.approx(1.0)
    assert _pearson(a, -a) == pytest.approx(-1.0)
    assert _pearson(a, torch.ones(10)) == 0.0  # constant: no correlation, not NaN
    img = torch.rand(1, 3, 8, 8)
    assert _psnr(img, img) == PSNR_CAP
    assert _psnr(torch.zeros(1, 3, 8, 8), torch.full((1, 3, 8, 8), 0.1)) == pytest.approx(20.0, abs=1e-4)


@pytest.mark.slow
def test_metrics_of_a_generated_scene_match_independent_computations(clips):
    """Each metric recomputed from the same generation (seed 0, 2 steps): PSNR from its closed form
    −10·log10(MSE), SSIM of frame 0 vs frames 1…, depth correlation by numpy on the covered valid pixels."""
    import kornia
    import numpy as np

    from diff4splat.cameras import CameraPath
    from diff4splat.render.sequence import render_path

    clip = clips[0]
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    m = evaluate_clip(pipe, clip, steps=2)
    assert set(m) == set(METRICS + DIAGNOSTICS)
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double())
    res = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=2, seed=0)
    colors, depths, alphas = render_path(res.scene, res.cameras)
    pred, gt = colors.permute(0, 3, 1, 2).clamp(0, 1).double(), clip["video"].permute(1, 0, 2, 3).double()
    psnr = lambda a, b: -10 * math.log10(float(((a - b) ** 2).mean()))  # noqa: E731
    assert m["psnr_input"] == pytest.approx(psnr(pred[:1], gt[:1]), abs=1e-3)
    assert m["psnr_novel"] == pytest.approx(psnr(pred[1:], gt[1:]), abs=1e-3)
    assert m["psnr_input"] != pytest.approx(m["psnr_novel"], abs=1e-3)  # frame 0 is scored on its own
    assert m["ssim_input"] == pytest.approx(float(kornia.metrics.ssim(pred[:1], gt[:1], 11).mean()), abs=1e-4)
    assert m["ssim_novel"] == pytest.approx(float(kornia.metrics.ssim(pred[1:], gt[1:], 11).mean()), abs=1e-4)
    valid = clip["depth_valid"] & (alphas > 0.5)
    assert int(valid.sum()) > 100
    corr = np.corrcoef(depths[valid].double().numpy(), clip["depth"][valid].double().numpy())[0, 1]
    assert m["depth_corr"] == pytest.approx(corr, abs=1e-6)
    assert m["motion_epe"] != m["motion_epe_hold"]  # this deformation moves the points
    assert math.isnan(m["loop_psnr"])  # a dynamic clip has no ground truth at the loop-closing view
    # vae_psnr goes through the DiT latent scaling and back: it must equal the raw VAE round trip
    with torch.no_grad():
        recon, _, _ = pipe.model.vae(clip["video"][None] * 2 - 1, sample_posterior=False)
    expected = psnr(((recon[0] + 1) / 2).clamp(0, 1).permute(1, 0, 2, 3).double(), gt)
    assert m["vae_psnr"] == pytest.approx(expected, abs=1e-3)


def test_psnr_of_a_corrupted_prediction_drops_by_the_expected_amount():
    """Adding uniform error e to a perfect prediction gives MSE e², i.e. −20·log10(e) dB; doubling e costs
    20·log10(2) ≈ 6.02 dB. Predictions are clamped to [0, 1] before scoring."""
    gt = 0.25 + 0.5 * torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    assert _psnr(gt, gt) == PSNR_CAP
    a, b = _psnr(gt + 0.05, gt), _psnr(gt - 0.1, gt)
    assert a == pytest.approx(-20 * math.log10(0.05), abs=1e-3)
    assert a - b == pytest.approx(20 * math.log10(2), abs=1e-3)
    assert _psnr(gt.clamp(max=0.5) + 10.0, gt) == pytest.approx(_psnr(torch.ones_like(gt), gt), abs=1e-6)


@pytest.mark.slow
def test_loop_psnr_of_a_static_scene_is_its_orbit_input_view_psnr(static_clip):
    """With an identity deformation the loop-closing frame (first camera, t = 1) is the orbit's first
    frame, so loop_psnr must equal that frame's PSNR against the ground-truth first frame."""
    from diff4splat.cameras import make_trajectory
    from diff4splat.render.sequence import render_path

    pipe = Diff4SplatPipeline(tiny_model())  # zero-initialised deformation: a static scene
    loop = evaluate_clip(pipe, static_clip, steps=1)["loop_psnr"]
    depth0 = static_clip["depth"][0][static_clip["depth_valid"][0]]
    orbit = make_trajectory("orbit", 9, static_clip["Ks"][0].double(), 64, 64, scene_depth=float(depth0.median()))
    res = pipe(static_clip["video"][:, 0].permute(1, 2, 0), orbit, static_clip["caption"], steps=1)
    colors, _, _ = render_path(res.scene, res.cameras)
    expected = _psnr(colors[:1].permute(0, 3, 1, 2), static_clip["video"][:, :1].permute(1, 0, 2, 3))
    assert loop < PSNR_CAP and loop == pytest.approx(expected, abs=1e-4)
    # predicted motion moves the loop-closing frame away from the photograph: a different score
    moving = evaluate_clip(Diff4SplatPipeline(tiny_model(dynamic=True)), static_clip, steps=1)["loop_psnr"]
    assert math.isfinite(moving) and abs(moving - loop) > 1e-3


@pytest.mark.slow
def test_motion_diagnostics_of_an_identity_deformation(clips):
    """No deformation: every time equals frame 0, so the error equals holding the points still."""
    m = evaluate_clip(Diff4SplatPipeline(tiny_model()), clips[0], steps=1)
    assert math.isfinite(m["motion_epe"]) and m["motion_epe"] == pytest.approx(m["motion_epe_hold"], abs=1e-6)
    assert m["motion_epe_t0"] > 1e-3  # the random model's geometry misses the tracked points


@pytest.mark.slow
def test_sampling_sweep_reports_each_sampler_and_nfe(clips):
    model = tiny_model(active_dit=True)  # a non-trivial ODE
    rows = sampling_tradeoffs(Diff4SplatPipeline(model), clips[:1], nfes=(1, 4, 16), reference_steps=32)
    assert [(r["sampler"], r["nfe"]) for r in rows] == [("euler", 1), ("euler", 4), ("euler", 16),
                                                        ("heun", 1), ("heun", 5), ("heun", 17)]
    euler = [r["latent_rms"] for r in rows if r["sampler"] == "euler"]
    assert euler[0] > euler[1] > euler[2]  # more steps, closer to the reference solution


@pytest.mark.slow
def test_evaluate_cli_through_the_entry_point(clips, tmp_path, capsys):
    from diff4splat.cli import main

    root = tmp_path / "data"
    from data_prep.synth import generate_scene

    generate_scene(root, 0, seed=5, size=64, frames=9, cameras=1)
    code = main(["evaluate", "--random", "--data", str(root), "--frames", "9", "--steps", "1",
                 "--csv", str(tmp_path / "eval.csv")])
    assert code == 0
    out = capsys.readouterr().out
    assert "psnr_input" in out and (tmp_path / "eval.csv").is_file()
    assert "| random:tiny:seed=0 |" in out  # the untrained model, not the shipped weights


@pytest.mark.slow
def test_stiffness_profile_is_exact_for_a_zero_field_and_positive_otherwise(clips):
    from training.evaluate import stiffness_profile

    zero = stiffness_profile(Diff4SplatPipeline(tiny_model()), clips[0], steps=3, substeps=2)
    assert [r["step"] for r in zero] == [0, 1, 2] and zero[0]["sigma"] == 1.0 and zero[-1]["sigma_next"] == 0.0
    assert all(r["local_error"] == 0.0 and r["lipschitz"] == 0.0 for r in zero)  # v ≡ 0 at zero init
    pipe = Diff4SplatPipeline(tiny_model(active_dit=True))
    rows = stiffness_profile(pipe, clips[0], steps=3, substeps=4)
    assert all(r["local_error"] > 0 and r["lipschitz"] > 0 for r in rows)
    assert type(pipe.runtime).velocity is pipe.runtime.velocity.__func__  # the recorder was removed
