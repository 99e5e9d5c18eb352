"""Tests of training/fit_cli.py: ``run_fit`` and ``diff4splat fit`` — the output folder, held-out metrics that
``diff4splat render`` reproduces, static fits, scenes that cannot be fitted, checkpoints and exact resume,
extreme scene scales, the command's errors, and devices (``--device``, checkpoints that resume on another
device, nothing made on torch's default device)."""
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest
import torch
from helpers import adam_steps_on_the_default_device

import diff4splat.utils.limits as limits
from data_prep.format import SceneWriter, load_scene, read_rgb
from data_prep.synth import generate_scene
from data_prep.validate import validate_scene
from diff4splat.cameras import CameraPath
from diff4splat.cli import main
from diff4splat.io import load_ply, save_ply
from diff4splat.io.output_folders import read_marker
from diff4splat.io.scene_folder import load_deformation, save_deformation
from diff4splat.render import spherical_harmonics
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.scene.quaternions import quat_multiply, quat_normalize, quat_to_rotmat, rotmat_to_quat
from diff4splat.utils.limits import LimitError
from models.hexplane import HexPlaneConfig, load_field
from training import fit_cli
from training.densify import DensifyConfig
from training.fit import FitConfig
from training.fit_cli import FitInterrupted, run_fit
from training.fit_data import depth_points, load_views

CONFIG = FitConfig(iterations=10, coarse_iterations=4, init_points=150, random_points=150, sh_degree=1,
                   sh_interval=5, densify=DensifyConfig(start=2, until=8, interval=3, opacity_reset_interval=6,
                                                        grad_threshold=1e-5),
                   field=HexPlaneConfig(feature_dim=4, resolution=(4, 4, 4, 3), multires=(1,), net_width=8))
SEED = 3


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def dynamic_scene(tmp_path_factory):
    return generate_scene(tmp_path_factory.mktemp("scenes"), 0, 0, size=16, frames=3, cameras=2, static_ratio=0.0)


@pytest.fixture(scope="module")
def dynamic_fit(dynamic_scene, tmp_path_factory):
    """(output folder, metrics) of an uninterrupted fit of ``dynamic_scene`` holding camera 1 out."""
    out = tmp_path_factory.mktemp("fits") / "dyn"
    return out, run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=0)


def _rewrite(src, dst, *, scale=1.0, cameras=None, depth=True, frames=None, static_camera=False):
    """A copy of scene ``src`` with its world scaled by ``scale`` (camera positions and depth), only
    ``cameras`` / the first ``frames`` frames, optionally without depth, or with every frame seen from the
    first frame's pose."""
    s = load_scene(src)
    names = cameras or s.camera_names
    T = frames or s.num_frames
    with SceneWriter(dst, source="test", dynamic=bool(s.meta.dynamic), depth_source="ground_truth" if depth
                     else "none", num_frames=T, fps=s.meta.fps) as w:
        for name in names:
            path = s.cameras(name)
            V = path.viewmats[:T].clone()
            if static_camera:
                V[:] = V[0]
            V[:, :3, 3] *= scale
            w.add_camera(name, CameraPath(V, path.Ks[:T], path.width, path.height,
                                          None if T == 1 else path.times[:T] / path.times[T - 1]))
            for i in range(T):
                w.write_frame(name, i, s.rgb(name, i), s.depth(name, i) * scale if depth else None)
    return dst


def meta_config_depth_weight(out):
    return json.loads((out / "meta.json").read_text())["config"]["depth_weight"]


def _param_tensors(out):
    g = load_ply(out / "scene.ply")
    return [g.means, g.quats, g.scales, g.opacities, g.sh]


def _assert_same_fit(out_a, metrics_a, out_b, metrics_b):
    for a, b in zip(_param_tensors(out_a), _param_tensors(out_b), strict=True):
        assert torch.equal(a, b)
    for k in ("train_psnr", "holdout_psnr", "holdout_ssim", "num_gaussians", "iterations", "densify"):
        assert metrics_a[k] == metrics_b[k], k
    strip = lambda h: [{k: v for k, v in r.items() if k != "train_time_s"} for r in h]  # noqa: E731
    assert strip(metrics_a["history"]) == strip(metrics_b["history"])
    if (out_a / "field.safetensors").exists():
        fa, fb = load_field(out_a / "field.safetensors"), load_field(out_b / "field.safetensors")
        for (k, a), (_, b) in zip(fa.state_dict().items(), fb.state_dict().items(), strict=True):
            assert torch.equal(a, b), k


def _sigterm_at(monkeypatch, step, signum=signal.SIGTERM):
    """Make run_fit's optimisation send SIGTERM (or ``signum``) to this process right after ``step`` (its handler
    then stops the loop and checkpoints)."""
    real = fit_cli.fit_steps

    def patched(state, views, config, until, *, on_step=None, **kw):
        def hook(s):
            on_step(s)
            if s.step == step:
                os.kill(os.getpid(), signum)
        return real(state, views, config, until, on_step=hook, **kw)

    monkeypatch.setattr(fit_cli, "fit_steps", patched)


class _Killed(Exception):
    pass


def _die_at(monkeypatch, step):
    """Make run_fit's optimisation stop dead after ``step`` as a SIGKILL would: no checkpoint of its own."""
    real = fit_cli.fit_steps

    def patched(state, views, config, until, *, on_step=None, **kw):
        def hook(s):
            on_step(s)
            if s.step == step:
                raise _Killed
        return real(state, views, config, until, on_step=hook, **kw)

    monkeypatch.setattr(fit_cli, "fit_steps", patched)


def test_output_folder_of_a_dynamic_fit(dynamic_scene, dynamic_fit):
    out, metrics = dynamic_fit
    scene = load_scene(dynamic_scene)
    T = scene.num_frames
    assert read_marker(out) == "fit"
    assert {p.name for p in out.iterdir()} >= {"scene.ply", "deformation.npz", "frames", "video.mp4", "depth",
                                               "cameras.json", "meta.json", "field.safetensors", "metrics.json"}
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{i:04d}.ply" for i in range(T)]
    assert sorted(p.name for p in (out / "depth").iterdir()) == [f"{i:04d}.exr" for i in range(T)]
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json.dumps(metrics))
    for k in ("train_psnr", "holdout_psnr", "holdout_ssim", "wall_time_s"):
        assert math.isfinite(metrics[k]), k
    assert metrics["iterations"] == CONFIG.iterations and metrics["holdout_camera"] == "cam01"
    assert 0 < metrics["holdout_ssim"] <= 1 and metrics["static"] is False
    assert 0 < metrics["holdout_covisible"] <= 1 and math.isfinite(metrics["holdout_masked_psnr"])  # it has depth
    assert CONFIG.depth_weight is None and meta_config_depth_weight(out) == 1.0  # ground-truth depth: trusted
    assert all(math.isfinite(h["holdout_masked_psnr"]) for h in metrics["history"])
    canonical = load_ply(out / "scene.ply")
    assert metrics["num_gaussians"] == canonical.means.shape[0]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["command"] == "fit" and meta["train_cameras"] == ["cam00"] and meta["seed"] == SEED
    # the learned background moved from its grey start; the frames were composited over it
    assert len(meta["background"]) == 3 and all(0 <= c <= 1 for c in meta["background"])
    assert max(abs(c - 0.5) for c in meta["background"]) > 1e-3 and meta["config"]["background"] == "learned"
    # the deformation at the reference camera's frame times is the saved field's
    arrays = load_deformation(out / "deformation.npz")
    times = scene.cameras("cam00").times
    np.testing.assert_allclose(arrays["times"], times.numpy(), rtol=0, atol=1e-7)
    field = load_field(out / "field.safetensors")
    with torch.no_grad():
        for k, t in enumerate(times.tolist()):
            d_means, _, d_scales = field(canonical.means, t)
            np.testing.assert_allclose(arrays["d_means"][k], d_means.numpy(), atol=1e-5)
            np.testing.assert_allclose(arrays["d_scales"][k], d_scales.numpy(), atol=1e-5)
    assert not (out.parent / (out.name + ".checkpoints")).exists()


def test_render_reproduces_the_held_out_psnr(dynamic_scene, dynamic_fit, tmp_path, capsys):
    out, metrics = dynamic_fit
    scene = load_scene(dynamic_scene)
    R = tmp_path / "R"
    assert main(["render", str(out), "--cameras", str(dynamic_scene / "cam01" / "cameras.json"), "--out", str(R),
                 "--quiet", "--device", "cpu"]) == 0  # the CPU, as the fit that measured holdout_psnr
    se, n = 0.0, 0
    for i in range(scene.num_frames):
        rendered = read_rgb(R / "rgb" / f"{i:04d}.png").astype(np.float64)
        truth = scene.rgb("cam01", i).astype(np.float64)
        se += float(((rendered - truth) ** 2).sum())
        n += truth.size
    assert 10 * math.log10(n / se) == pytest.approx(metrics["holdout_psnr"], abs=0.1)


def test_generate_init_is_placed_in_the_scene_world_at_the_depth_scale(dynamic_scene, tmp_path):
    # a generate output made from cam00's frame 0: its world is that camera's frame, at half the true scale
    scene = load_scene(dynamic_scene)
    view = load_views(scene, ["cam00"], frames=[0])[0]
    world, colors = depth_points([view], 10**6, torch.Generator())
    n = world.shape[0]
    R, t = view.viewmat[:3, :3].double(), view.viewmat[:3, 3].double()
    q_world = quat_normalize(torch.randn(n, 4, generator=torch.Generator().manual_seed(0)))
    cam = Gaussians(((world.double() @ R.T + t) / 2).float(), quat_multiply(rotmat_to_quat(R.float())[None], q_world),
                    torch.full((n, 3), 0.01), torch.full((n,), 0.7), torch.rand(n, 4, 3))
    init = tmp_path / "generated"
    init.mkdir()
    save_ply(init / "scene.ply", cam)
    means, quats, scales, opac, sh = fit_cli._generate_init(init, scene, "cam00")
    torch.testing.assert_close(means, world, atol=1e-4, rtol=0)  # the median depth ratio (2) undoes the scale
    torch.testing.assert_close(scales, torch.full((n, 3), 0.02), atol=1e-6, rtol=0)
    same = (quats * q_world).sum(-1).abs()  # q and −q are one rotation
    torch.testing.assert_close(same, torch.ones(n), atol=1e-5, rtol=0)
    torch.testing.assert_close(opac, torch.full((n,), 0.7), atol=1e-6, rtol=0)
    # degree 1: the colour the camera-frame Gaussian showed towards d is the world one's towards c2w·d = Rᵀd
    # (the coefficients themselves change: they were copied unrotated before)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    torch.testing.assert_close(spherical_harmonics(1, dirs @ R.float(), sh), spherical_harmonics(1, dirs, cam.sh),
                               atol=1e-5, rtol=0)
    metrics = run_fit(dynamic_scene, tmp_path / "out",
        dataclasses.replace(CONFIG, iterations=2, coarse_iterations=1), init=init,
                      checkpoint_every=0)
    assert metrics["iterations"] == 2 and json.loads((tmp_path / "out" / "meta.json").read_text())["init"] == str(init)
    with pytest.raises(FileNotFoundError, match="--init"):
        run_fit(dynamic_scene, tmp_path / "out3", CONFIG, init=tmp_path / "nothing")


def test_one_frame_gives_a_static_fit(dynamic_scene, tmp_path):
    one = _rewrite(dynamic_scene, tmp_path / "one", frames=1)
    assert load_scene(one).meta.dynamic  # the scene says dynamic, but one frame has no motion to fit
    out = tmp_path / "out"
    config = dataclasses.replace(CONFIG, iterations=3)
    metrics = run_fit(one, out, config, holdout_camera=0, seed=0, checkpoint_every=0)
    assert metrics["static"] is True and math.isfinite(metrics["holdout_psnr"])
    assert not (out / "field.safetensors").exists() and not (out / "deformation.npz").exists()
    assert (out / "scene.ply").is_file() and (out / "metrics.json").is_file() and read_marker(out) == "fit"


def test_one_static_camera_without_depth_cannot_be_fitted(dynamic_scene, tmp_path):
    blind = _rewrite(dynamic_scene, tmp_path / "blind", cameras=["cam00"], depth=False, static_camera=True)
    with pytest.raises(ValueError, match="one camera that does not move and no depth"):
        run_fit(blind, tmp_path / "out", CONFIG)
    assert not (tmp_path / "out").exists()
    # a moving camera without depth is fitted from the random box
    moving = _rewrite(dynamic_scene, tmp_path / "moving", cameras=["cam00"], depth=False)
    metrics = run_fit(moving, tmp_path / "out2",
        dataclasses.replace(CONFIG, iterations=2, coarse_iterations=1), checkpoint_every=0)
    assert metrics["iterations"] == 2 and math.isfinite(metrics["train_psnr"]) and metrics["holdout_psnr"] is None


@pytest.mark.parametrize("stop", [3, 7])  # in the coarse stage, in the fine stage
def test_resume_after_sigterm_is_exact(dynamic_scene, dynamic_fit, tmp_path, monkeypatch, stop):
    out = tmp_path / "fit"
    handler = signal.getsignal(signal.SIGTERM)
    _sigterm_at(monkeypatch, stop)
    with pytest.raises(FitInterrupted, match=f"stopped at step {stop}"):
        run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=5)
    ckpt = tmp_path / "fit.checkpoints"
    assert (ckpt / "checkpoints" / f"step_{stop:08d}").is_dir() and not out.exists()
    assert signal.getsignal(signal.SIGTERM) is handler  # run_fit put the previous handler back
    monkeypatch.undo()
    metrics = run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=5,
                      resume=True)
    _assert_same_fit(*dynamic_fit, out, metrics)
    assert not ckpt.exists()  # removed once the output is written


def test_resume_after_a_hard_kill_continues_from_the_last_periodic_checkpoint(dynamic_scene, dynamic_fit, tmp_path,
                                                                               monkeypatch):
    out = tmp_path / "fit"
    _die_at(monkeypatch, 7)
    with pytest.raises(_Killed):
        run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=3)
    assert [p.name for p in (tmp_path / "fit.checkpoints" / "checkpoints").glob("step_*")] == ["step_00000006"]
    monkeypatch.undo()
    metrics = run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=3,
                      resume=True)
    _assert_same_fit(*dynamic_fit, out, metrics)


def test_resume_errors(dynamic_scene, tmp_path, monkeypatch, capsys):
    with pytest.raises(ValueError, match="--resume: no checkpoint"):
        run_fit(dynamic_scene, tmp_path / "fit", CONFIG, resume=True)
    _sigterm_at(monkeypatch, 2, signal.SIGINT)  # Ctrl-C: the command exits 128 + 2 = 130 (it was 143 for both)
    with pytest.raises(FitInterrupted) as stopped:
        run_fit(dynamic_scene, tmp_path / "fit", CONFIG, holdout_camera=1, seed=SEED, checkpoint_every=0)
    assert stopped.value.signum == signal.SIGINT
    monkeypatch.undo()
    for other in (dict(holdout_camera=1, seed=SEED + 1), dict(holdout_camera=None, seed=SEED)):
        with pytest.raises(ValueError, match="checkpoint .* is of another fit"):
            run_fit(dynamic_scene, tmp_path / "fit", CONFIG, resume=True, **other)
    with pytest.raises(ValueError, match="of another fit") as e:
        run_fit(dynamic_scene, tmp_path / "fit", dataclasses.replace(CONFIG, iterations=12, sh_degree=2),
                holdout_camera=1, seed=SEED, resume=True)
    # issue 28: only the settings that differ, not both configs (a 2,305-character line before)
    assert e.value.args[0].endswith("of another fit: iterations 10 in the checkpoint vs 12 now; sh_degree 1 in the "
                                    "checkpoint vs 2 now (resume with the checkpoint's settings, or fit into a new "
                                    "--out)")
    with pytest.raises(ValueError, match=r"of another fit: seed 3 in the checkpoint vs 4 now \(resume"):
        run_fit(dynamic_scene, tmp_path / "fit", CONFIG, holdout_camera=1, seed=SEED + 1, resume=True)
    capsys.readouterr()
    assert main(["fit", str(dynamic_scene), "--out", str(tmp_path / "other"), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--resume: no checkpoint" in err[0]


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_extreme_scene_scales_stay_finite(dynamic_scene, tmp_path, scale):
    scaled = _rewrite(dynamic_scene, tmp_path / "scaled", scale=scale)
    out = tmp_path / "out"
    config = dataclasses.replace(CONFIG, iterations=6, coarse_iterations=2,
                                 densify=DensifyConfig(start=1, until=5, interval=2, grad_threshold=0.0))
    metrics = run_fit(scaled, out, config, holdout_camera=1, seed=0, checkpoint_every=0)
    assert all(math.isfinite(metrics[k]) for k in ("train_psnr", "holdout_psnr", "holdout_ssim"))
    for t in _param_tensors(out):
        assert torch.isfinite(t).all()
    for k, v in load_deformation(out / "deformation.npz").items():
        assert np.isfinite(v).all(), k


def test_run_differences_names_each_differing_setting_once():
    run = {"scene": "/s", "seed": 3, "config": {"iterations": 300, "densify": {"max_gaussians": 5, "start": 2},
                                               "field": {"resolution": (4, 4, 4, 3)}}}
    assert fit_cli.run_differences(run, json.loads(json.dumps(run))) == []  # tuples stored as lists are equal
    other = {"scene": "/t", "seed": 3, "config": {"iterations": 500, "densify": {"max_gaussians": 6, "start": 2},
                                                 "field": {"resolution": [4, 4, 4, 3]}, "new": 1}}
    assert fit_cli.run_differences(run, other) == [
        "scene /s in the checkpoint vs /t now", "iterations 300 in the checkpoint vs 500 now",
        "densify.max_gaussians 5 in the checkpoint vs 6 now", "new (absent) in the checkpoint vs 1 now"]
    assert fit_cli.run_differences(None, {"seed": 1}) == ["seed (absent) in the checkpoint vs 1 now"]


@pytest.mark.parametrize("argv, needle", [
    (["--iterations", "0"], "--iterations must be a positive int, got 0"),
    (["--checkpoint-every", "-1"], "--checkpoint-every must be a positive int, got -1"),  # issue 28: accepted before
    (["--checkpoint-every", "0"], "--checkpoint-every must be a positive int, got 0"),
    (["--eval-every", "0"], "--eval-every must be a positive int, got 0"),
    (["--iterations", "1000000000000"], "--iterations 1000000000000 exceeds the limit of 100000 optimisation steps "
                                        "(set DIFF4SPLAT_MAX_ITERATIONS to raise it)"),  # ran until killed before
    (["--max-gaussians", "1000000000"], "--max-gaussians 1000000000 exceeds the limit of 10000000 Gaussians "
                                        "(set DIFF4SPLAT_MAX_GAUSSIANS"),
    (["--init-points", "1000000000"], "--init-points 1000000000 exceeds the limit of 10000000 Gaussians"),
    (["--seed", str(10**30)], "--seed must be an integer in"),
    (["--fps", "100000"], "--fps must be at most 1000 frames per second"),
])
def test_bad_arguments_are_refused_before_the_scene_is_read(dynamic_scene, tmp_path, capsys, monkeypatch, argv,
                                                            needle):
    monkeypatch.setattr(fit_cli, "load_scene", None)  # reading the scene would fail: the refusal comes first
    assert main(["fit", str(dynamic_scene), "--out", str(tmp_path / "out"), "--quiet", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"diff4splat: error: {needle}"] or (len(err) == 1 and needle in err[0]), err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.checkpoints").exists()


def test_fit_config_holds_iterations_and_gaussians_to_their_limits(monkeypatch):
    with pytest.raises(LimitError, match="iterations 1000000000000 exceeds the limit of 100000"):
        FitConfig(iterations=10**12)
    with pytest.raises(LimitError, match="densify.max_gaussians 100000000 exceeds the limit of 10000000 Gaussians"):
        FitConfig(densify=DensifyConfig(max_gaussians=10**8))
    with pytest.raises(ValueError, match="checkpoint_every must be a positive int .*got -1"):
        run_fit("no-scene", "no-out", FitConfig(iterations=10), checkpoint_every=-1)  # before the scene is read
    monkeypatch.setenv("DIFF4SPLAT_MAX_GAUSSIANS", "1000")
    with pytest.raises(LimitError, match="init_points 15000 exceeds the limit of 1000 Gaussians"):
        FitConfig()


def test_out_inside_an_input_folder_is_refused(dynamic_scene, tmp_path, capsys):
    """issue 28: ``fit SCENE --out SCENE/fitout`` wrote into the scene (then ``data_prep validate SCENE`` failed)."""
    link = tmp_path / "link"
    link.symlink_to(dynamic_scene, target_is_directory=True)
    before = sorted(p.relative_to(dynamic_scene) for p in dynamic_scene.rglob("*"))
    for out in (dynamic_scene / "fitout", link / "cam00" / "fitout"):
        assert main(["fit", str(dynamic_scene), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"diff4splat: error: --out {out} is inside the scene folder {dynamic_scene}: the fit would "
                       "write into its own input; choose a folder outside it"], err
        with pytest.raises(ValueError, match="is inside the scene folder"):
            run_fit(dynamic_scene, out, CONFIG, checkpoint_every=0)
    init = tmp_path / "gen"
    init.mkdir()
    with pytest.raises(ValueError, match=f"--out {init / 'fit'} is inside the --init folder {init}"):
        run_fit(dynamic_scene, init / "fit", CONFIG, init=init, checkpoint_every=0)
    assert sorted(p.relative_to(dynamic_scene) for p in dynamic_scene.rglob("*")) == before
    assert validate_scene(dynamic_scene) == []


def test_cli_errors_are_one_line(dynamic_scene, tmp_path, capsys):
    for argv, needle in (([str(dynamic_scene), "--iterations", "0"], "--iterations must be a positive int"),
                         ([str(dynamic_scene), "--holdout-camera", "5"], "--holdout-camera: 5"),
                         ([str(tmp_path / "missing")], "missing")):
        capsys.readouterr()
        assert main(["fit", *argv, "--out", str(tmp_path / "out"), "--quiet"]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("diff4splat: error:") and needle in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_cli_sigterm_then_resume(dynamic_scene, tmp_path):
    """The real command in a subprocess: SIGTERM once a checkpoint exists → exit 143; --resume → 0."""
    out = tmp_path / "fit"
    argv = [sys.executable, "-m", "diff4splat.cli", "fit", str(dynamic_scene), "--out", str(out), "--iterations",
            "30", "--coarse-iterations", "2", "--init-points", "100", "--checkpoint-every", "1", "--quiet",
            "--holdout-camera", "1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True)
    latest = tmp_path / "fit.checkpoints" / "checkpoints" / "latest"
    deadline = time.monotonic() + 120
    while not latest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert "rerun with --resume" in err and not out.exists()
    done = subprocess.run([*argv, "--resume"], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 30 and math.isfinite(metrics["holdout_psnr"])


def test_a_dynamic_scene_needs_a_fine_stage(dynamic_scene, tmp_path):
    with pytest.raises(ValueError, match="coarse-iterations 4 leaves no fine stage"):
        run_fit(dynamic_scene, tmp_path / "out", dataclasses.replace(CONFIG, iterations=4), checkpoint_every=0)
    assert not (tmp_path / "out").exists()


def test_placed_generate_output_moves_like_the_original(dynamic_scene, tmp_path):
    # a generate scene with a deformation and SH degree 2, in cam00's frame: placed in the world, every time's
    # Gaussians are the similarity transform (scale s, c2w) of the original's at that time, and show towards R·d
    # the colour the original showed towards d

    scene = load_scene(dynamic_scene)
    g = torch.Generator().manual_seed(3)
    n, T = 50, 3
    means = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    cam = DynamicGaussians(
        Gaussians(means, quat_normalize(torch.randn(n, 4, generator=g)), torch.full((n, 3), 0.05),
                  torch.full((n,), 0.5), torch.rand(n, 9, 3, generator=g) - 0.5),
        torch.linspace(0, 1, T), torch.randn(T, n, 3, generator=g) * 0.1,
        quat_normalize(torch.randn(T, n, 4, generator=g) * 0.2 + torch.tensor([1.0, 0, 0, 0])),
        torch.randn(T, n, 3, generator=g) * 0.1)
    init = tmp_path / "gen"
    init.mkdir()
    save_ply(init / "scene.ply", cam.canonical)
    save_deformation(init / "deformation.npz", cam)
    placed = fit_cli.place_generate_output(init, scene, "cam00")
    c2w = torch.linalg.inv(scene.cameras("cam00").viewmats[0].double()).float()
    depth = torch.from_numpy(scene.depth("cam00", 0))
    s = float(depth[torch.isfinite(depth)].median() / means[:, 2].median())
    for t in (0.0, 0.3, 1.0):
        a, b = cam.at(t), placed.at(t)
        torch.testing.assert_close(b.means, a.means * s @ c2w[:3, :3].T + c2w[:3, 3], atol=1e-4, rtol=0)
        torch.testing.assert_close(quat_to_rotmat(b.quats), c2w[:3, :3] @ quat_to_rotmat(a.quats), atol=1e-5, rtol=0)
        torch.testing.assert_close(b.scales, a.scales * s, atol=1e-6, rtol=1e-5)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    torch.testing.assert_close(spherical_harmonics(2, dirs @ c2w[:3, :3].T, placed.canonical.sh),
                               spherical_harmonics(2, dirs, cam.canonical.sh), atol=1e-5, rtol=0)


def _tensors(obj):
    """Every tensor in ``obj`` (dicts, lists, tuples)."""
    if isinstance(obj, torch.Tensor):
        return [obj]
    if isinstance(obj, dict):
        return [t for v in obj.values() for t in _tensors(v)]
    if isinstance(obj, (list, tuple)):
        return [t for v in obj for t in _tensors(v)]
    return []


def test_fit_cli_on_each_device(dynamic_scene, tmp_path, device, capsys):
    """``diff4splat fit --device``: the metrics and meta record the device; on CUDA the fit matches the CPU's
    (the same draws; the renderers differ slightly, so a loose PSNR tolerance)."""
    out = tmp_path / "fit"
    argv = ["fit", str(dynamic_scene), "--out", str(out), "--iterations", "6", "--coarse-iterations", "2",
            "--init-points", "120", "--holdout-camera", "1", "--checkpoint-every", "100", "--seed", str(SEED),
            "--quiet"]
    assert main([*argv, "--device", str(device)]) == 0
    assert capsys.readouterr().out.strip().endswith(f"on {device}")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["device"] == str(device) and json.loads((out / "meta.json").read_text())["device"] == str(device)
    assert metrics["iterations"] == 6 and all(math.isfinite(metrics[k]) for k in ("train_psnr", "holdout_psnr"))
    if device.type == "cuda":
        assert main([*argv[:3], str(tmp_path / "cpu"), *argv[4:], "--device", "cpu"]) == 0
        cpu = json.loads((tmp_path / "cpu" / "metrics.json").read_text())
        assert metrics["num_gaussians"] == cpu["num_gaussians"]
        for k in ("train_psnr", "holdout_psnr"):
            assert metrics[k] == pytest.approx(cpu[k], abs=0.25), k


@pytest.mark.parametrize("written, resumed", [
    ("cpu", "cpu"),
    pytest.param("cuda", "cpu", marks=pytest.mark.cuda, id="cuda-cpu"),
    pytest.param("cpu", "cuda", marks=pytest.mark.cuda, id="cpu-cuda"),
])
def test_a_checkpoint_resumes_on_another_device(dynamic_scene, tmp_path, monkeypatch, written, resumed):
    """A checkpoint holds CPU tensors only (and the device that wrote it), so a fit stopped on one device
    continues on another; the same device gives the uninterrupted fit exactly (test_resume_after_sigterm_is_exact)."""
    out = tmp_path / "fit"
    _sigterm_at(monkeypatch, 7)  # in the fine stage: field, field optimizer
    with pytest.raises(FitInterrupted):
        run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=0,
                device=written)
    folder = tmp_path / "fit.checkpoints" / "checkpoints" / "step_00000007"
    saved = torch.load(folder / "state.pt", weights_only=False)  # no map_location: tensors as they were saved
    assert {t.device.type for t in _tensors(saved)} == {"cpu"}
    assert json.loads((folder / "meta.json").read_text())["device"].startswith(written)
    monkeypatch.undo()
    metrics = run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=0,
                      resume=True, device=resumed)
    assert metrics["iterations"] == CONFIG.iterations and metrics["device"].startswith(resumed)
    assert all(math.isfinite(metrics[k]) for k in ("train_psnr", "holdout_psnr", "holdout_ssim"))


@pytest.mark.skipif(adam_steps_on_the_default_device(), reason="this torch's Adam makes its step counter on "
                    "the default device (tests/helpers.py)")
def test_run_fit_makes_nothing_on_the_default_device(dynamic_scene, tmp_path, monkeypatch, no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) a whole fit runs on the CPU: views, initial points,
    both stages, densification, held-out evaluation, a checkpoint after SIGTERM, the resume and the output."""
    out = tmp_path / "fit"
    _sigterm_at(monkeypatch, 5)
    with pytest.raises(FitInterrupted):
        run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=0)
    monkeypatch.undo()
    metrics = run_fit(dynamic_scene, out, CONFIG, holdout_camera=1, seed=SEED, eval_every=4, checkpoint_every=0,
                      resume=True)
    assert metrics["device"] == "cpu" and metrics["iterations"] == CONFIG.iterations
    assert math.isfinite(metrics["holdout_masked_psnr"]) and (out / "field.safetensors").is_file()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_fit_on_a_missing_device_is_one_line_exit_2(dynamic_scene, tmp_path, capsys):
    code = main(["fit", str(dynamic_scene), "--out", str(tmp_path / "out"), "--quiet", "--device", "cuda"])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error: --device: cuda is not available")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="device: cuda is not available"):
        run_fit(dynamic_scene, tmp_path / "out", CONFIG, device="cuda")


def test_fit_checks_its_memory_before_loading_the_views(tmp_path, capsys, monkeypatch):
    """With less room than :func:`training.fit_cli.fit_memory_estimate` (the machine's, a cgroup's or a ulimit's:
    limits.available_memory), ``fit`` is one line naming the Gaussians and the knobs, exit 2, before any view is
    loaded and with nothing written; the estimate grows by FIT_BYTES_PER_GAUSSIAN per allowed Gaussian."""
    generate_scene(tmp_path, 0, seed=3, size=16, frames=3, cameras=1, static_ratio=0.0)
    scene_dir = tmp_path / "scene_00000"
    monkeypatch.setattr(fit_cli, "load_views", lambda *a, **k: pytest.fail("the views were loaded"))
    monkeypatch.setattr(limits, "available_memory", lambda: psutil.Process().memory_info().rss + (256 << 20))
    code = main(["fit", str(scene_dir), "--out", str(tmp_path / "o"), "--max-gaussians", "200000", "--quiet",
                 "--device", "cpu"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "a fit of up to 200,000 Gaussians" in err, err
    assert "--max-gaussians or --init-points" in err and not (tmp_path / "o").exists()
    scene, d = load_scene(scene_dir), FitConfig()
    small, large = (fit_cli.fit_memory_estimate(scene, dataclasses.replace(
        d, densify=dataclasses.replace(d.densify, max_gaussians=n))) for n in (100_000, 200_000))
    assert abs(large - small - 100_000 * fit_cli.FIT_BYTES_PER_GAUSSIAN) < 64 << 20  # the process may move a little
