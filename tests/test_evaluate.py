"""Tests of training/evaluate.py and its command (training/evaluate_cli.py): every metric against an independent
computation, baselines and ablations, the sampler sweep, the CLI, and devices (``--device``, nothing made on torch's
default device)."""
import contextlib
import csv
import dataclasses
import math
import os
from pathlib import Path

import kornia
import numpy as np
import pytest
import torch
from helpers import tiny_model

import training.evaluate_cli
from data_prep.synth import generate_scene
from diff4splat.cameras import CameraPath, make_trajectory
from diff4splat.cli import main
from diff4splat.io import atomic_output_path
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.render.sequence import render_path
from diff4splat.runtime import TorchRuntime
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.errors import one_line
from training import eval_csv
from training.direction_test import caption_direction, flip_direction
from training.drag_eval import true_drags
from training.eval_csv import append_csv, check_csv_outputs, csv_outputs
from training.eval_metrics import ablation_noise, image_psnr, kept_index_map
from training.evaluate import (
    BASELINES,
    DEPTH_DIAGNOSTICS,
    DIAGNOSTICS,
    DIRECTION,
    METRICS,
    VARIANTS,
    ClipEvaluation,
    aggregate,
    binned_keys,
    clip_inputs,
    evaluate_clip,
    held_out_clips,
    sampling_tradeoffs,
    scene_motion,
    stiffness_profile,
)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    root = tmp_path_factory.mktemp("heldout")
    generate_scene(root, 0, seed=123, size=64, frames=9, cameras=1, static_ratio=0.0)
    return held_out_clips(root, 64, 64, 9, None)


@pytest.fixture(scope="module")
def static_clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("heldout_static")
    generate_scene(root, 0, seed=124, size=64, frames=9, cameras=1, static_ratio=1.0)
    (clip,) = held_out_clips(root, 64, 64, 9, None)
    assert not bool(clip["dynamic"])
    return clip


@pytest.mark.slow
def test_metrics_of_a_generated_scene_match_independent_computations(clips):
    """Each metric recomputed from the same generation (seed 0, 2 steps): PSNR from its closed form
    −10·log10(MSE), SSIM of frame 0 vs frames 1…, depth correlation by numpy on the covered valid pixels."""
    clip = clips[0]
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    e = evaluate_clip(pipe, clip, steps=2)
    m = e.metrics
    assert set(m) == set(METRICS + DIAGNOSTICS + DEPTH_DIAGNOSTICS + BASELINES + DIRECTION)
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double())
    res = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=2, seed=0)
    colors, depths, alphas = render_path(res.scene, res.cameras, eps2d=res.eps2d, background=res.background)
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
    assert m["psnr_novel_repeat"] == pytest.approx(psnr(gt[:1].expand_as(gt[1:]), gt[1:]), abs=1e-6)
    # the generated video itself: the sampled latents through the VAE decoder, no 3D
    with torch.no_grad():
        video = ((pipe.model.vae.decode_latents(res.latents)[0] + 1) / 2).clamp(0, 1).permute(1, 0, 2, 3)
    assert m["psnr_novel_video"] == pytest.approx(psnr(video[1:].double(), gt[1:]), abs=1e-4)
    assert m["psnr_novel_video"] != pytest.approx(m["psnr_novel"], abs=1e-2)
    # the oracle: the scene generated from the encoded true video
    with torch.no_grad():
        latents = pipe.model.vae.encode_latents(clip["video"][None] * 2 - 1)
    oracle = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=2, seed=0, video_latents=latents)
    colors, _, _ = render_path(oracle.scene, oracle.cameras, eps2d=oracle.eps2d, background=oracle.background)
    assert m["psnr_novel_gt"] == pytest.approx(psnr(colors[1:].permute(0, 3, 1, 2).clamp(0, 1).double(), gt[1:]),
                                               abs=1e-6)
    assert e.dynamic and e.max_angle == pytest.approx(float(e.angles.max())) and e.max_angle > 1.0
    agg = aggregate([e])
    assert set(agg) == set(METRICS + DIAGNOSTICS + DEPTH_DIAGNOSTICS + BASELINES + DIRECTION + binned_keys()
                           + ("direction_clips",))
    assert agg["psnr_novel"] == m["psnr_novel"] and sum(agg[k] for k in agg if k.startswith("frames_")) == 8
    with pytest.raises(ValueError, match="evals"):
        aggregate([])


@pytest.mark.slow
def test_loop_psnr_of_a_static_scene_is_its_orbit_input_view_psnr(static_clip):
    """With an identity deformation the loop-closing frame (first camera, t = 1) is the orbit's first
    frame, so loop_psnr must equal that frame's PSNR against the ground-truth first frame: the photograph, kept by
    the photo layer with nothing generated over it (≥ 40 dB)."""
    pipe = Diff4SplatPipeline(tiny_model())  # zero-initialised deformation: a static scene
    loop = evaluate_clip(pipe, static_clip, steps=1).metrics["loop_psnr"]
    depth0 = static_clip["depth"][0][static_clip["depth_valid"][0]]
    orbit = make_trajectory("orbit", 9, static_clip["Ks"][0].double(), 64, 64, scene_depth=float(depth0.median()))
    res = pipe(static_clip["video"][:, 0].permute(1, 2, 0), orbit, static_clip["caption"], steps=1)
    colors, _, _ = render_path(res.scene, res.cameras, eps2d=res.eps2d, background=res.background)
    expected = image_psnr(colors[:1].permute(0, 3, 1, 2), static_clip["video"][:, :1].permute(1, 0, 2, 3))
    assert loop == pytest.approx(expected, abs=1e-4) and loop >= 40.0
    # predicted motion moves the loop-closing frame away from the photograph: a different score
    moving = evaluate_clip(Diff4SplatPipeline(tiny_model(dynamic=True)), static_clip, steps=1).metrics["loop_psnr"]
    assert math.isfinite(moving) and abs(moving - loop) > 1e-3


@pytest.mark.slow
def test_direction_test_generates_the_flipped_caption_once_and_scores_both(tmp_path, static_clip, monkeypatch):
    """A clip whose caption names one direction (one translating object) is generated once more with the phrase
    flipped; a scene without deformation holds the object still, so it moves the named way with neither caption
    (0 / 0, 0 m along it). A static clip takes no part: no extra generation, NaN. The aggregate counts the clips."""
    generate_scene(tmp_path, 0, seed=5, size=64, frames=9, cameras=1, static_ratio=0.0, motions=("translate",),
                   max_movers=1)
    (clip,) = held_out_clips(tmp_path, 64, 64, 9, None)
    named = caption_direction(clip["caption"])
    assert named is not None
    pipe = Diff4SplatPipeline(tiny_model())
    prompts = []
    original = Diff4SplatPipeline.__call__
    monkeypatch.setattr(Diff4SplatPipeline, "__call__",
                        lambda self, image, cams, prompt, **kw: prompts.append(prompt) or original(self, image, cams,
                                                                                                  prompt, **kw))
    e = evaluate_clip(pipe, clip, steps=1)
    assert prompts.count(flip_direction(clip["caption"])) == 1
    assert {k: e.metrics[k] for k in DIRECTION} == {"direction_caption": 0.0, "direction_flipped": 0.0,
                                                    "direction_along_caption": 0.0, "direction_along_flipped": 0.0}
    prompts.clear()
    s = evaluate_clip(pipe, static_clip, steps=1)
    assert all(math.isnan(s.metrics[k]) for k in DIRECTION)
    assert prompts == [static_clip["caption"]] * 4  # the scene, loop orbit, noise ablation, true latents: no flip
    agg = aggregate([e, s])
    assert agg["direction_clips"] == 1 and agg["direction_caption"] == 0.0


@pytest.mark.slow
def test_motion_diagnostics_of_an_identity_deformation(clips):
    """No deformation: every time equals frame 0, so the error equals holding the points still, and the
    displacement error equals the true displacement (the prediction does not move)."""
    m = evaluate_clip(Diff4SplatPipeline(tiny_model()), clips[0], steps=1).metrics
    assert math.isfinite(m["motion_epe"]) and m["motion_epe"] == pytest.approx(m["motion_epe_hold"], abs=1e-6)
    assert m["motion_epe_t0"] > 1e-3  # the random model's geometry misses the tracked points
    assert m["motion_disp_hold"] > 1e-3  # a dynamic clip: the tracks move
    assert m["motion_disp_epe"] == pytest.approx(m["motion_disp_hold"], abs=1e-6)
    assert m["motion_disp_epe_gt"] == pytest.approx(m["motion_disp_hold"], abs=1e-6)  # the oracle scene too
    assert m["flow_disp_hold"] > 1e-3 and m["flow_disp_epe"] == pytest.approx(m["flow_disp_hold"], abs=1e-6)
    assert m["flow_disp_epe_gt"] == pytest.approx(m["flow_disp_hold"], abs=1e-6)


@pytest.mark.slow
def test_drags_from_the_true_tracks_score_the_dragged_scene(clips):
    """``evaluate --drags K``: the ``*_drag`` terms are ``scene_motion`` of the scene generated with K drags per moving
    object from the clip's true tracks (recomputed here), that scene moves (its error is not holding still's), and
    without drags they are NaN."""
    pipe, clip = Diff4SplatPipeline(tiny_model()), clips[0]
    m = evaluate_clip(pipe, clip, steps=1, drags=2).metrics
    cams, image = clip_inputs(pipe, clip)
    drags = true_drags(clip, per_object=2)
    assert drags is not None and len(drags) >= 2
    want = scene_motion(pipe, pipe(image, cams, clip["caption"], steps=1, drags=drags), clip)
    assert m["motion_disp_epe_drag"] == pytest.approx(want["motion_disp_epe"], rel=1e-6)
    assert (m["motion_disp_drag_d5"], m["motion_disp_drag_d10"]) == (want["motion_disp_d5"], want["motion_disp_d10"])
    assert abs(m["motion_disp_epe_drag"] - m["motion_disp_hold"]) > 1e-3
    plain = evaluate_clip(pipe, clip, steps=1).metrics
    assert all(math.isnan(plain[k]) for k in ("motion_disp_epe_drag", "motion_disp_drag_d5", "motion_disp_drag_d10"))


@pytest.mark.slow
def test_dense_scene_flow_terms_score_each_pixels_gaussian_against_the_pixel_tracks(clips):
    """A scene whose frame-0 pixel Gaussians move exactly as the clip's pixel tracks, plus 3 cm along x from frame 1
    on, has a dense displacement error of 3 cm, every pixel within 5 cm (δ5 = δ10 = 1); 6 cm puts every pixel outside δ5
    and inside δ10."""
    clip = clips[0]
    res = Diff4SplatPipeline(tiny_model())(clip["video"][:, 0].permute(1, 2, 0), CameraPath(
        clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double()), clip["caption"], steps=1)
    T, HW = clip["times"].shape[0], 64 * 64
    kept = kept_index_map(res.gaussian_index.cpu(), res.num_slots)[:HW]
    flow = clip["pixel_tracks"].reshape(T, HW, 3).double()
    valid = clip["pixel_track_valid"].reshape(HW) & (kept >= 0)
    assert valid.sum() > 1000
    for shift, d5 in ((0.03, 1.0), (0.06, 0.0)):
        d_means = torch.zeros(T, res.scene.num_gaussians, 3, dtype=torch.float64)
        d_means[:, kept[valid]] = flow[:, valid] - flow[:1, valid]
        d_means[1:, kept[valid], 0] += shift
        quats = torch.zeros(T, res.scene.num_gaussians, 4, dtype=torch.float64)
        quats[..., 0] = 1
        scene = DynamicGaussians(res.scene.canonical.to(torch.float64), clip["times"].double(), d_means, quats,
                                 torch.zeros_like(d_means))
        m = scene_motion(None, dataclasses.replace(res, scene=scene), clip)
        assert m["flow_disp_epe"] == pytest.approx(shift, abs=1e-5)
        assert m["flow_disp_d5"] == d5 and m["flow_disp_d10"] == 1.0
        still = ((flow[1:, valid] - flow[:1, valid]).norm(dim=-1) < 0.05).double().mean()
        assert m["flow_disp_hold_d5"] == pytest.approx(float(still))  # holding still's δ5 from the truth alone
        moves = (flow[1:, valid] - flow[:1, valid]).norm(dim=-1)
        assert moves.max() > 0.1 and m["flow_disp_hold"] == pytest.approx(float(moves.mean()), rel=1e-6)


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
    """The CLI prints the per-clip table, the metrics and the model beside its baselines per view-angle bin,
    appends the aggregate row to the CSV, and refuses a CSV with other columns before evaluating."""
    root = tmp_path / "data"
    generate_scene(root, 0, seed=5, size=64, frames=9, cameras=1)
    table = tmp_path / "eval.csv"
    code = main(["evaluate", "--random", "--config", "tiny", "--data", str(root), "--frames", "9", "--steps", "1",
                 "--csv", str(table), "--per-clip"])
    assert code == 0
    captured = capsys.readouterr()
    out = captured.out
    assert "evaluate: 100%" in captured.err and "1/1" in captured.err  # the progress bar over clips, on stderr
    assert "psnr_input" in out and "| random:tiny:seed=0 |" in out  # the untrained model, not the shipped weights
    assert "| scene_00000 |" in out  # the per-clip table
    for label in ("model (sampled latents)", "noise latents (ablation)", "true-video latents (oracle)",
                  "repeat frame 0 |", "repeat frame 0, blurred"):
        assert label in out
    gap_rows = out.split("bootstrap resamplings of the clips:")[1]  # the gap table, after the views table
    assert "| noise latents (ablation) | " in gap_rows and "(1 clip)" in gap_rows and " [" in gap_rows
    with open(table, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["model"] == "random:tiny:seed=0"
    assert {"psnr_45_90_noise", "psnr_45_90_repeat", "psnr_novel_gt", "motion_disp_epe"} <= set(rows[0])
    assert sum(int(float(rows[0][f"frames_{b}"])) for b in ("0_15", "15_45", "45_90", "90_180")) == 8
    empty = [b for b in ("0_15", "15_45", "45_90", "90_180") if float(rows[0][f"frames_{b}"]) == 0]
    assert empty and rows[0][f"psnr_{empty[0]}"] == "nan"  # the CSV keeps NaN for a bin with no frames …
    assert "nan" not in out and "| — |" in out  # … the printed tables show "—"
    assert (tmp_path / "eval_clips.csv").is_file()
    other = tmp_path / "other.csv"
    other.write_text("model,psnr_input\nx,1\n")
    code = main(["evaluate", "--random", "--config", "tiny", "--data", str(root), "--frames", "9", "--steps", "1",
                 "--csv", str(other)])
    err = capsys.readouterr()
    assert code != 0 and "--csv:" in err.err and "other columns" in err.err
    assert "| model (sampled latents)" not in err.out  # refused before evaluating
    assert other.read_text() == "model,psnr_input\nx,1\n"


class _RecordingRuntime(TorchRuntime):
    """A PyTorch runtime that records the latents every reconstruction starts from."""

    def __init__(self, model):
        super().__init__(model)
        self.latents: list[torch.Tensor] = []

    def reconstruct(self, latents, *args):
        self.latents.append(latents.clone())
        return super().reconstruct(latents, *args)


@pytest.mark.slow
def test_noise_ablation_reconstructs_from_the_noise(clips):
    """The ablation's reconstruction gets the seeded noise with frame 0 replaced by the photograph's latent
    (not the sampled latents), and psnr_novel_noise is the PSNR of that scene; a runtime without the
    PyTorch VAE has no oracle (NaN)."""
    clip = clips[0]  # dynamic: no loop-closure generation
    runtime = _RecordingRuntime(tiny_model(dynamic=True, active_dit=True))
    m = evaluate_clip(Diff4SplatPipeline(runtime), clip, steps=1, seed=3).metrics
    sampled, ablated = runtime.latents  # the sampled scene, then the ablation (no oracle without pipe.model)
    noise = ablation_noise(sampled.shape, 3)
    assert torch.equal(ablated[:, :, :1], sampled[:, :, :1])  # the photograph's latent
    assert torch.allclose(ablated[:, :, 1:], noise[:, :, 1:])
    assert not torch.allclose(sampled[:, :, 1:], noise[:, :, 1:], atol=1e-3)
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double())
    res = Diff4SplatPipeline(tiny_model(dynamic=True, active_dit=True))(
        clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=1, seed=3, video_latents=noise)
    colors, _, _ = render_path(res.scene, res.cameras, eps2d=res.eps2d, background=res.background)
    expected = image_psnr(colors[1:].permute(0, 3, 1, 2), clip["video"][:, 1:].permute(1, 0, 2, 3))
    assert m["psnr_novel_noise"] == pytest.approx(expected, abs=1e-6)
    assert m["psnr_novel_noise"] != pytest.approx(m["psnr_novel"], abs=1e-4)
    assert math.isnan(m["psnr_novel_gt"]) and math.isnan(m["motion_epe_gt"])


@pytest.mark.slow
def test_gaussian_index_maps_frame0_pixels_to_their_gaussians(clips):
    """Through kept_index_map(gaussian_index), each kept frame-0 pixel's Gaussian lies on that pixel's ray
    of the input camera: its canonical mean projects to the pixel's centre."""
    clip = clips[0]
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double())
    res = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=1)
    kept = kept_index_map(res.gaussian_index, res.num_slots)[: 64 * 64]  # the photo layer's front disks
    pixels = torch.nonzero(kept >= 0)[:, 0]
    assert 0 < len(pixels) and int(res.source_frames[0]) == 0
    means = res.scene.canonical.means[kept[pixels]].double()
    uv = means @ res.cameras.Ks[0].double().T
    uv = uv[:, :2] / uv[:, 2:]
    expected = torch.stack([pixels % 64 + 0.5, pixels // 64 + 0.5], -1).double()
    assert torch.allclose(uv, expected, atol=1e-3)


@pytest.mark.slow
def test_stiffness_profile_is_exact_for_a_zero_field_and_positive_otherwise(clips):
    zero = stiffness_profile(Diff4SplatPipeline(tiny_model()), clips[0], steps=3, substeps=2)
    assert [r["step"] for r in zero] == [0, 1, 2] and zero[0]["sigma"] == 1.0 and zero[-1]["sigma_next"] == 0.0
    assert all(r["local_error"] == 0.0 and r["lipschitz"] == 0.0 for r in zero)  # v ≡ 0 at zero init
    pipe = Diff4SplatPipeline(tiny_model(active_dit=True))
    rows = stiffness_profile(pipe, clips[0], steps=3, substeps=4)
    assert all(r["local_error"] > 0 and r["lipschitz"] > 0 for r in rows)
    assert type(pipe.runtime).velocity is pipe.runtime.velocity.__func__  # the recorder was removed


def test_pooled_psnr_is_that_of_the_mean_mse_over_every_bin():
    """psnr_pooled: the PSNR of the mean MSE over all novel frames of all clips (frame-count weighted bins)."""
    def clip(mses, angles):
        mse = torch.tensor(mses, dtype=torch.float64)
        metrics = {k: 1.0 for k in METRICS + DIAGNOSTICS + DEPTH_DIAGNOSTICS + BASELINES + DIRECTION}
        return ClipEvaluation(name="c", dynamic=True, max_angle=max(angles), metrics=metrics,
                              angles=torch.tensor(angles, dtype=torch.float64),
                              frame_mse={v: mse for v in ("model", *VARIANTS)})

    agg = aggregate([clip([1e-2, 1e-3], [5.0, 50.0]), clip([0.0], [20.0])])
    expect = -10 * math.log10((1e-2 + 1e-3 + 0.0) / 3)
    assert agg["psnr_pooled"] == pytest.approx(expect) and agg["psnr_pooled_repeat"] == pytest.approx(expect)


@pytest.mark.slow
def test_evaluate_clip_makes_nothing_on_the_default_device(clips, no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) a CPU pipeline evaluates a dynamic clip on the CPU:
    generation, the three scenes' renders, motion, baselines and the oracle."""
    with torch.device("cpu"):
        pipe = Diff4SplatPipeline(tiny_model(dynamic=True), device="cpu")
    e = evaluate_clip(pipe, clips[0], steps=1)
    assert math.isfinite(e.metrics["psnr_novel"]) and math.isfinite(e.metrics["motion_epe"])
    assert all(v.device.type == "cpu" for v in e.frame_mse.values())


@pytest.mark.slow
def test_loop_psnr_makes_nothing_on_the_default_device(static_clip, no_implicit_device):
    """The loop-closure orbit of a static clip under torch's default device "meta" stays on the CPU."""
    with torch.device("cpu"):
        pipe = Diff4SplatPipeline(tiny_model(), device="cpu")
    assert math.isfinite(evaluate_clip(pipe, static_clip, steps=1).metrics["loop_psnr"])


@pytest.mark.slow
def test_evaluate_cli_on_each_device(tmp_path, device, capsys):
    """``diff4splat evaluate --device``: the pipeline generates and renders there, the metrics come out on the CPU
    (on CUDA close to the CPU's: the same noise, slightly different arithmetic)."""
    root = tmp_path / "data"
    generate_scene(root, 0, seed=5, size=64, frames=9, cameras=1, static_ratio=0.0)
    rows = {}
    for dev in dict.fromkeys(["cpu", str(device)]):
        table = tmp_path / f"{dev}.csv"
        assert main(["evaluate", "--random", "--config", "tiny", "--data", str(root), "--frames", "9", "--steps", "1",
                     "--limit", "1", "--device", dev, "--csv", str(table), "--quiet"]) == 0
        with open(table, newline="") as f:
            (rows[dev],) = list(csv.DictReader(f))
    assert "evaluate:" not in capsys.readouterr().err  # --quiet: no progress bar
    got, ref = rows[str(device)], rows["cpu"]
    assert math.isfinite(float(got["psnr_novel"])) and math.isfinite(float(got["motion_epe"]))
    for k in ("psnr_input", "psnr_novel", "psnr_novel_noise", "psnr_novel_gt", "vae_psnr"):
        assert float(got[k]) == pytest.approx(float(ref[k]), abs=1.0 if device.type == "cuda" else 0.0), k
    assert [k for k in got if got[k] == "nan"] == [k for k in ref if ref[k] == "nan"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_evaluate_on_a_missing_device_is_one_line_exit_2(tmp_path, capsys):
    """The device is checked first: before the model and the data (which does not exist here) are read."""
    code = main(["evaluate", "--random", "--config", "tiny", "--data", str(tmp_path / "none"), "--device", "cuda"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error: --device: cuda is not available")


# --------------------------------------------------------------------------- issue 28: refused before evaluating

def _refusals(tmp_path):
    """(extra arguments, expected message) of runs ``evaluate`` must refuse before any model loads."""
    text = tmp_path / "text.png"
    text.write_text("not an image")
    taken = tmp_path / "taken.csv"
    taken.write_text("model,psnr_input\nx,1\n")
    (tmp_path / "ok_clips.csv").write_text("model,clip\nx,y\n")
    (tmp_path / "ok_sampling.csv").write_text("model,nfe\nx,1\n")
    return [
        (["--csv", tmp_path / "nodir" / "x.csv"],
         f"--csv: {tmp_path / 'nodir' / 'x.csv'}: folder {tmp_path / 'nodir'} does not exist"),
        (["--csv", tmp_path], f"--csv: {tmp_path} is a folder, not a file"),
        (["--csv", taken], f"--csv: {taken} has other columns (2) than this evaluation writes"),
        (["--csv", tmp_path / "ok.csv", "--per-clip"], f"--csv: {tmp_path / 'ok_clips.csv'} has other columns"),
        (["--csv", tmp_path / "ok.csv", "--sampling"], f"--csv: {tmp_path / 'ok_sampling.csv'} has other columns"),
        (["--photo", text], f"--photo: could not decode {text} as an image"),
        (["--photo", tmp_path / "missing.png"], f"--photo: {tmp_path / 'missing.png'} does not exist"),
        (["--limit", "0"], "--limit must be a positive int, got 0"),
        (["--checkpoint", tmp_path], "--random evaluates the untrained model; --checkpoint"),  # it was ignored
        (["--prompt", "a cat"], "--prompt is used with --photo"),  # it was ignored
        (["--sampling", "--sampling-clips", "0"], "--sampling-clips must be a positive int, got 0"),
        (["--steps", "1000000"], "--steps 1000000 exceeds the limit of 1000 sampler steps"),
        (["--frames", "0"], "--frames must be a positive int, got 0"),
        (["--photo", text, "--resolution", "100000"], "--resolution 100000 exceeds the limit of 2048"),
    ]


def test_bad_arguments_and_outputs_are_refused_before_the_model_loads(tmp_path, capsys, monkeypatch):
    """Before issue 28 ``--csv nodir/x.csv`` and ``--photo text.png`` failed after the whole evaluation, ``--limit 0``
    blamed ``--data`` and ``--sampling-clips 0`` said "no median for empty data"."""
    monkeypatch.setattr(training.evaluate_cli, "load_model", None)  # loading a model would fail: refusals come first
    for extra, message in _refusals(tmp_path):
        before = sorted(tmp_path.rglob("*"))
        code = main(["evaluate", "--random", "--config", "tiny", "--data", str(tmp_path), *map(str, extra)])
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert code == 2 and len(err) == 1 and err[0].startswith(f"diff4splat: error: {message}"), (extra, err)
        assert sorted(tmp_path.rglob("*")) == before  # nothing written


def test_csv_outputs_are_appended_with_one_header(tmp_path):
    outputs = csv_outputs(tmp_path / "e.csv", ["model", "a"], ["model", "clip"], None)
    assert outputs == {"aggregate": (tmp_path / "e.csv", ["model", "a"]),
                       "clips": (tmp_path / "e_clips.csv", ["model", "clip"])}
    check_csv_outputs(outputs)  # new files in a writable folder
    (tmp_path / "e.csv").touch()  # an empty file gets the header too
    for _ in range(2):
        append_csv(tmp_path / "e.csv", {"model": "m", "a": 1.5})
    assert (tmp_path / "e.csv").read_text().splitlines() == ["model,a", "m,1.5", "m,1.5"]
    check_csv_outputs(outputs)  # same columns: appendable
    with pytest.raises(ValueError, match="other columns"):
        check_csv_outputs(csv_outputs(tmp_path / "e.csv", ["model", "b"], None, None))


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_csv_append_on_a_full_disk_names_the_file_and_keeps_it_whole(tmp_path, monkeypatch):
    """The row is written with the file's old rows beside it and renamed over: on a full disk (every write fails
    with ENOSPC: the temporary file is /dev/full) the error names the CSV, an existing file keeps its rows and a new
    one is not left empty."""
    kept = tmp_path / "kept.csv"
    append_csv(kept, {"model": "m", "a": 1.5})
    before = kept.read_bytes()

    @contextlib.contextmanager
    def full(path):
        with atomic_output_path(path) as tmp:
            os.symlink("/dev/full", tmp)
            yield tmp

    monkeypatch.setattr(eval_csv, "atomic_output_path", full)
    for path in (kept, tmp_path / "new.csv"):
        with pytest.raises(OSError) as info:
            append_csv(path, {"model": "m", "a": 2.5})
        assert one_line(info.value) == f"{path}: No space left on device"
    assert kept.read_bytes() == before and not (tmp_path / "new.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.csv"]


@pytest.mark.slow
def test_the_sampled_video_is_decoded_once_per_generation(clips, monkeypatch):
    """With ``generated_colors: video`` the pipeline decodes the sampled latents for the scene's colours and
    returns them (``GenerationResult.video``, equal to a fresh decode); ``evaluate_clip`` scores
    ``psnr_novel_video`` on that decode instead of decoding again: one decode per generation, and one of the true
    video's latents (``vae_psnr``)."""
    model = tiny_model(dynamic=True)
    model.config = dataclasses.replace(model.config, generated_colors="video")
    pipe = Diff4SplatPipeline(model)
    clip = clips[0]
    cams = CameraPath(clip["viewmats"].double(), clip["Ks"].double(), 64, 64, clip["times"].double())
    res = pipe(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"], steps=2, seed=0)
    assert res.video is not None and torch.equal(res.video, pipe.runtime.decode_latents(res.latents))
    decodes, generations = [], []
    decode, call = pipe.runtime.decode_latents, Diff4SplatPipeline.__call__
    monkeypatch.setattr(pipe.runtime, "decode_latents", lambda latents: decodes.append(1) or decode(latents))
    monkeypatch.setattr(Diff4SplatPipeline, "__call__", lambda self, *a, **k: generations.append(1) or call(self, *a,
                                                                                                            **k))
    m = evaluate_clip(pipe, clip, steps=2).metrics
    assert len(generations) >= 3 and len(decodes) == len(generations) + 1  # + the true video's (vae_psnr)
    video = ((res.video[0] + 1) / 2).clamp(0, 1).permute(1, 0, 2, 3).double()
    gt = clip["video"].permute(1, 0, 2, 3).double()
    assert m["psnr_novel_video"] == pytest.approx(-10 * math.log10(float(((video[1:] - gt[1:]) ** 2).mean())),
                                                  abs=1e-6)
    ldrm = Diff4SplatPipeline(tiny_model(dynamic=True))(clip["video"][:, 0].permute(1, 2, 0), cams, clip["caption"],
                                                         steps=2, seed=0)
    assert ldrm.video is None  # generated_colors: ldrm decodes nothing


@pytest.mark.slow
def test_evaluate_clip_encodes_the_true_video_in_the_pipelines_dtype(clips):
    """The true video's latents (``vae_psnr`` and the oracle row) go through the runtime as generation does: a
    bfloat16 pipeline scores the clip (the VAE called directly was handed float32 input against bfloat16 weights;
    with model offload on a GPU, CUDA input against weights left on the CPU), within 1 dB of float32's."""
    m32 = evaluate_clip(Diff4SplatPipeline(tiny_model(dynamic=True)), clips[0], steps=2).metrics
    m16 = evaluate_clip(Diff4SplatPipeline(tiny_model(dynamic=True), dtype=torch.bfloat16), clips[0],
                        steps=2).metrics
    for k in ("vae_psnr", "psnr_novel_gt"):
        assert math.isfinite(m16[k]) and abs(m16[k] - m32[k]) < 1.0, (k, m16[k], m32[k])
