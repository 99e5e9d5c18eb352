"""End to end: `diff4splat generate` on the shipped photograph, every output file, every bad input."""
import inspect
import json
import math
import struct
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE
from plyfile import PlyData

import diff4splat.commands.generate as generate_module
import diff4splat.pipeline
from diff4splat.assembly.photo import PHOTO_EPS2D
from diff4splat.cameras import DEFAULT_AMPLITUDES, DEFAULT_TRAJECTORY, CameraPath, intrinsics_from_fov
from diff4splat.cli import build_parser, main
from diff4splat.io import load_depth_exr, load_image, load_ply, load_video, ply_property_names, save_cameras_json
from diff4splat.io.image import preprocess_image, read_image
from diff4splat.io.scene_folder import deformation_tensors, load_deformation
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.quaternions import quat_to_rotmat
from diff4splat.utils.devices import resolve_device
from models.bundle import DEFAULT_CONFIG, Diff4SplatModel, load_config

INRIA = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
         + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)])


def _generate(tmp_path, *extra, frames=9, resolution=64):
    """``generate`` on the example photo; ``resolution`` None: the default (256), else that output height (64 keeps
    the test fast)."""
    out = tmp_path / "out"
    size = [] if resolution is None else ["--resolution", str(resolution)]
    code = main(["generate", str(EXAMPLE_IMAGE), "--frames", str(frames), "--steps", "2", "--quiet",
                 "--out", str(out), *size, *extra])
    return code, out


def _check_folder(out, frames, size=64):
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frames"] == frames and meta["width"] == meta["height"] == size
    assert meta["model_width"] == meta["model_height"] == 64 and meta["eps2d"] == PHOTO_EPS2D
    assert set(meta["timings_s"]) >= {"load_model", "encode_image", "encode_text", "sample", "reconstruct", "render"}
    if meta["device"].startswith("cuda"):  # --device auto on a GPU machine: the pipeline's stages, in GB
        assert list(meta["peak_memory_gb"]) == ["encode_image", "encode_text", "sample", "reconstruct", "prune"]
    else:
        assert meta["peak_memory_gb"] is None  # the CPU has no allocator statistics
    ply = PlyData.read(str(out / "scene.ply"))
    names = [p.name for p in ply["vertex"].properties]
    assert names == ply_property_names(1) and set(INRIA) <= set(names)
    assert len(ply["vertex"]) == meta["num_gaussians"] > 0
    video = load_video(out / "video.mp4")
    assert video.shape == (frames, size, size, 3)
    rgb = [cv2.imread(str(out / "rgb" / f"{i:04d}.png"))[..., ::-1] for i in range(frames)]  # lossless frames
    assert all(f.shape == (size, size, 3) for f in rgb) and np.abs(video.astype(float) - np.stack(rgb)).mean() < 8
    for i in range(frames):
        depth, alpha = load_depth_exr(out / "depth" / f"{i:04d}.exr", return_alpha=True)
        assert depth.shape == (size, size) and np.isfinite(depth).all() and (depth > 0).all()
        assert alpha is not None and (alpha >= 0).all() and (alpha <= 1).all()
    cams = json.loads((out / "cameras.json").read_text())
    assert len(cams["viewmats"]) == frames and cams["width"] == size
    np.testing.assert_allclose(cams["viewmats"][0], np.eye(4), atol=1e-6)
    return meta


def _check_frames_follow_deformation(out, frames):
    """Every per-frame PLY equals the canonical scene deformed by deformation.npz at that frame's time."""
    canonical = load_ply(out / "scene.ply")
    d = deformation_tensors(load_deformation(out / "deformation.npz"))
    assert d["d_means"].shape == (frames, canonical.num_gaussians, 3)
    scene = DynamicGaussians(canonical, d["times"], d["d_means"], d["d_quats"], d["d_scales"])
    times = json.loads((out / "cameras.json").read_text())["times"]
    moved = 0.0
    for i, t in enumerate(times):
        frame = load_ply(out / "frames" / f"{i:04d}.ply")
        expect = scene.at(t)
        torch.testing.assert_close(frame.means, expect.means, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(frame.scales, expect.scales, atol=1e-6, rtol=1e-4)
        torch.testing.assert_close(quat_to_rotmat(frame.quats), quat_to_rotmat(expect.quats), atol=1e-5, rtol=0)
        torch.testing.assert_close(frame.opacities, canonical.opacities)
        torch.testing.assert_close(frame.sh, canonical.sh)
        moved = max(moved, float((frame.means - canonical.means).abs().max()))
    return moved


@pytest.mark.slow
def test_generate_writes_every_file_on_the_shipped_photograph(tmp_path, capsys):
    """The README's command (shorter clip, default resolution 256): the shipped trained model, no warning, a dynamic
    scene whose first frame is the photograph (≥ 30 dB after the video codec)."""
    code, out = _generate(tmp_path, "--trajectory", "arc", "--prompt", "a cat turns its head", resolution=None)
    assert code == 0
    assert "warning" not in capsys.readouterr().err
    meta = _check_folder(out, 9, size=256)
    assert meta["photo_psnr_db"] >= 40.0
    photo = load_image(EXAMPLE_IMAGE, size=(256, 256))
    first = torch.from_numpy(load_video(out / "video.mp4")[0]).float() / 255
    assert float(-10 * torch.log10(((first - photo) ** 2).mean())) >= 30.0
    lossless = torch.from_numpy(cv2.imread(str(out / "rgb" / "0000.png"))[..., ::-1].copy()).float() / 255
    assert float(-10 * torch.log10(((lossless - photo) ** 2).mean())) >= 40.0  # only 8-bit rounding left
    assert meta["model"].endswith(f"models/weights/{DEFAULT_CONFIG}") and not meta["static"]
    assert _check_frames_follow_deformation(out, 9) > 1e-4
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temp folder left


@pytest.mark.slow
def test_without_shipped_weights_a_seeded_random_model_is_used_with_a_warning(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(diff4splat.pipeline, "WEIGHTS_DIR", tmp_path / "no_weights")
    code, out = _generate(tmp_path, "--frames", "5")  # no --trajectory, no --config: the defaults
    assert code == 0
    assert "randomly initialised" in capsys.readouterr().err
    meta = _check_folder(out, 5)
    on = ":cuda" if resolve_device().type == "cuda" else ""  # --device auto: a GPU initialises it (test_random_init)
    assert meta["model"] == f"random:{DEFAULT_CONFIG}:seed=0{on}" and meta["config"] == DEFAULT_CONFIG
    assert meta["trajectory"] == "arc"
    # The default path is the arc: the first and last centres are 0.5 rad apart around the scene
    # centre c, at its distance, and the camera moved to its right.
    d = load_config(DEFAULT_CONFIG).scene_depth
    viewmats = torch.tensor(json.loads((out / "cameras.json").read_text())["viewmats"], dtype=torch.float64)
    centres = -torch.einsum("tji,tj->ti", viewmats[:, :3, :3], viewmats[:, :3, 3])
    u = centres - torch.tensor([0.0, 0.0, d], dtype=torch.float64)
    torch.testing.assert_close(u.norm(dim=-1), torch.full((5,), d, dtype=torch.float64), atol=1e-5, rtol=0)
    angle = math.acos(float(u[0] @ u[-1]) / d**2)
    assert angle == pytest.approx(0.5, abs=1e-4) and centres[-1, 0] > 0
    assert meta["static"] and not (out / "deformation.npz").exists()  # zero-initialised deformation
    # static: every frame would be scene.ply, five copies of it were written
    assert not (out / "frames").exists() and meta["frame_plys"] is False and (out / "scene.ply").is_file()


@pytest.mark.slow
def test_no_frame_plys_leaves_out_frames_and_nothing_else(tmp_path, dynamic_checkpoint):
    """`--no-frame-plys`: no frames/, meta.json says so, every other file the same bytes as with them."""
    args = ["--checkpoint", str(dynamic_checkpoint), "--trajectory", "spiral", "--frames", "5", "--prompt", "it moves"]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    code, with_plys = _generate(tmp_path / "a", *args)
    assert code == 0
    code, without = _generate(tmp_path / "b", *args, "--no-frame-plys")
    assert code == 0
    meta = _check_folder(without, 5)
    assert not (without / "frames").exists() and (with_plys / "frames" / "0004.ply").is_file()
    assert meta["frame_plys"] is False and json.loads((with_plys / "meta.json").read_text())["frame_plys"] is True
    assert not meta["static"]
    for name in ("scene.ply", "deformation.npz", "cameras.json", "rgb/0004.png", "depth/0004.exr", "video.mp4"):
        assert (without / name).read_bytes() == (with_plys / name).read_bytes(), name


@pytest.mark.slow
def test_dynamic_checkpoint_frames_differ_only_through_the_deformation(tmp_path, dynamic_checkpoint):
    code, out = _generate(tmp_path, "--checkpoint", str(dynamic_checkpoint), "--trajectory", "spiral", "--frames", "5",
                          "--prompt", "it moves")  # no prompt: a static scene
    assert code == 0
    meta = _check_folder(out, 5)
    assert not meta["static"]
    assert _check_frames_follow_deformation(out, 5) > 1e-3


@pytest.mark.slow
def test_cameras_file_round_trips_through_generate(tmp_path):
    code, out = _generate(tmp_path, "--trajectory", "pan-left", "--frames", "5")
    assert code == 0
    code2, out2 = main(["generate", str(EXAMPLE_IMAGE), "--cameras", str(out / "cameras.json"), "--steps", "2",
                        "--quiet", "--resolution", "64", "--out", str(tmp_path / "again")]), tmp_path / "again"
    assert code2 == 0
    assert json.loads((out2 / "meta.json").read_text())["trajectory"] is None  # not the --trajectory default
    a = json.loads((out / "cameras.json").read_text())
    b = json.loads((out2 / "cameras.json").read_text())
    np.testing.assert_allclose(a["viewmats"], b["viewmats"], atol=1e-6)
    np.testing.assert_allclose(a["Ks"], b["Ks"], atol=1e-4)


def _bad_camera_file(tmp_path, kind):
    Ks = intrinsics_from_fov(64, 64, fov_y_deg=50).expand(5, 3, 3).clone()
    cams = CameraPath(torch.eye(4).repeat(5, 1, 1), Ks, 64, 64)
    path = tmp_path / "cams.json"
    save_cameras_json(path, cams)
    data = json.loads(path.read_text())
    if kind == "nan":
        data["viewmats"][2][0][3] = float("nan")
    elif kind == "rotation":
        data["viewmats"][2][0][0] = 2.0
    else:
        data["viewmats"] = []
    path.write_text(json.dumps(data).replace("NaN", "NaN"))
    return path


@pytest.mark.parametrize("case", ["missing_image", "unreadable_image", "frames_not_1_plus_4k", "zero_frames",
                                  "unknown_trajectory", "both_camera_sources", "nan_cameras",
                                  "non_orthonormal_cameras", "zero_cameras", "missing_cameras",
                                  "missing_checkpoint", "zero_steps", "out_is_file", "bad_sampler", "no_out"])
def test_bad_input_one_line_exit_2_and_no_output(tmp_path, capsys, case):
    out = tmp_path / "out"
    args = ["generate", str(EXAMPLE_IMAGE), "--steps", "1", "--frames", "5", "--quiet", "--out", str(out)]
    if case == "missing_image":
        args[1] = str(tmp_path / "nope.png")
    elif case == "unreadable_image":
        (tmp_path / "junk.png").write_bytes(b"not an image")
        args[1] = str(tmp_path / "junk.png")
    elif case == "frames_not_1_plus_4k":
        args[5] = "8"
    elif case == "zero_frames":
        args[5] = "0"
    elif case == "unknown_trajectory":
        args += ["--trajectory", "loop-de-loop"]
    elif case == "both_camera_sources":
        args += ["--trajectory", "orbit", "--cameras", str(_bad_camera_file(tmp_path, "ok"))]
    elif case in ("nan_cameras", "non_orthonormal_cameras", "zero_cameras"):
        kind = {"nan_cameras": "nan", "non_orthonormal_cameras": "rotation", "zero_cameras": "empty"}[case]
        args = [a for a in args if a not in ("--frames", "5")] + ["--cameras", str(_bad_camera_file(tmp_path, kind))]
    elif case == "missing_cameras":
        args += ["--cameras", str(tmp_path / "none.json")]
    elif case == "missing_checkpoint":
        args += ["--checkpoint", str(tmp_path / "no_ckpt")]
    elif case == "zero_steps":
        args[3] = "0"
    elif case == "out_is_file":
        out.write_text("x")
    elif case == "bad_sampler":
        args += ["--sampler", "rk4"]
    else:
        args = args[:-2]
    code = main(args)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("diff4splat: warning")]
    assert code == 2
    assert len(lines) == 1 and lines[0].startswith("diff4splat: error:"), err
    assert out.is_file() if case == "out_is_file" else not out.exists()
    assert not any(p.name.startswith(".out") for p in tmp_path.iterdir())


@pytest.mark.slow
def test_console_script_runs_as_a_process(tmp_path):
    """The installed entry point (python -m form) exits 2 with one stderr line on a bad image."""
    proc = subprocess.run([sys.executable, "-m", "diff4splat.cli", "generate", str(tmp_path / "x.png"),
                           "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "x.png" in proc.stderr


@pytest.mark.slow
def test_rgba_grey_and_16bit_images_generate(tmp_path):
    img = cv2.imread(str(EXAMPLE_IMAGE), cv2.IMREAD_UNCHANGED)
    variants = {"rgba.png": np.dstack([img, np.full(img.shape[:2], 200, np.uint8)]),
                "grey.png": cv2.cvtColor(img, cv2.COLOR_BGR2GRAY),
                "deep.png": img.astype(np.uint16) * 257}
    for name, arr in variants.items():
        cv2.imwrite(str(tmp_path / name), arr)
        code = main(["generate", str(tmp_path / name), "--frames", "1", "--steps", "1", "--quiet",
                     "--resolution", "64", "--out", str(tmp_path / f"out_{name}")])
        assert code == 0, name
        assert load_video(tmp_path / f"out_{name}" / "video.mp4").shape == (1, 64, 64, 3)


def _spy_pipeline(monkeypatch) -> dict:
    """Record the image the CLI hands to the pipeline and the GenerationResult it gets back."""
    seen = {}
    real = Diff4SplatPipeline.__call__

    def spy(self, image, cameras, *args, **kwargs):
        seen["image"] = image
        seen["result"] = real(self, image, cameras, *args, **kwargs)
        return seen["result"]

    monkeypatch.setattr(Diff4SplatPipeline, "__call__", spy)
    return seen


@pytest.mark.slow
def test_exif_rotated_jpeg_crops_image_and_realestate10k_intrinsics_alike(tmp_path, monkeypatch):
    """A landscape-stored JPEG tagged Orientation 6 is a 40×80 portrait: the image is cropped from the
    upright photo and the RealEstate10K intrinsics are de-normalised by that same upright 40×80 size."""
    stored = np.zeros((40, 80, 3), np.uint8)  # H × W as stored (landscape)
    stored[:, :40] = (255, 40, 0)
    stored[:, 40:] = (0, 40, 255)
    stored[:10] = (0, 255, 0)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(stored, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 100])
    tiff = (b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, 6, 0)
            + struct.pack("<I", 0))
    app1 = b"\xff\xe1" + struct.pack(">H", 2 + 6 + len(tiff)) + b"Exif\x00\x00" + tiff
    data = jpg.tobytes()
    (tmp_path / "plain.jpg").write_bytes(data)
    photo = tmp_path / "rotated.jpg"
    photo.write_bytes(data[:2] + app1 + data[2:])
    # fx, fy, cx, cy normalised by the upright frame (W = 40, H = 80); identity pose
    (tmp_path / "cams.txt").write_text("https://example.invalid/v\n0 0.6 0.5 0.5 0.5 0 0 "
                                       "1 0 0 0 0 1 0 0 0 0 1 0\n")
    seen = _spy_pipeline(monkeypatch)
    out = tmp_path / "out"
    assert main(["generate", str(photo), "--cameras", str(tmp_path / "cams.txt"), "--steps", "1", "--quiet",
                 "--resolution", "64", "--out", str(out)]) == 0
    upright = np.rot90(read_image(tmp_path / "plain.jpg"), k=-1)  # Orientation 6: rotate 90° clockwise
    torch.testing.assert_close(seen["image"], preprocess_image(upright, (64, 64)))
    # intrinsics: fx = 0.6·40, fy = 0.5·80, c = (20, 40); centre crop 40×40 (y0 = 20), scale 64/40
    K = np.array(json.loads((out / "cameras.json").read_text())["Ks"][0])
    np.testing.assert_allclose(K, [[0.6 * 40 * 1.6, 0, 32], [0, 0.5 * 80 * 1.6, 32], [0, 0, 1]], atol=1e-4)


@pytest.mark.slow
def test_meta_steps_and_sampler_are_the_ones_the_pipeline_used(tmp_path, monkeypatch):
    seen = _spy_pipeline(monkeypatch)
    out = tmp_path / "defaults"
    assert main(["generate", str(EXAMPLE_IMAGE), "--frames", "1", "--quiet", "--out", str(out)]) == 0
    meta, result = json.loads((out / "meta.json").read_text()), seen["result"]
    assert (meta["steps"], meta["sampler"], meta["shift"]) == (result.steps, result.sampler, result.shift)
    assert meta["runtime"] == "torch" and "backend" not in meta and meta["attention"] == "auto"
    assert meta["compile"] is False
    out = tmp_path / "given"
    assert main(["generate", str(EXAMPLE_IMAGE), "--frames", "1", "--steps", "2", "--sampler", "heun", "--quiet",
                 "--attention", "math", "--out", str(out)]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert (meta["steps"], meta["sampler"]) == (seen["result"].steps, seen["result"].sampler) == (2, "heun")
    assert meta["attention"] == "math"


@pytest.mark.slow
def test_building_the_parser_imports_no_training_code():
    """`diff4splat --help` and `generate` list `evaluate` without importing the training package."""
    code = ("import sys; from diff4splat.cli import build_parser, main; build_parser(); "
            "main(['generate', 'missing.png', '--out', 'o']); "
            "bad = [m for m in sys.modules if m == 'training' or m.startswith('training.')]; assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    top = subprocess.run([sys.executable, "-m", "diff4splat.cli", "--help"], capture_output=True, text=True)
    assert top.returncode == 0 and "evaluate" in top.stdout


@pytest.mark.slow
def test_evaluate_subcommand_is_loaded_when_chosen(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "diff4splat.cli", "evaluate", "--help"], capture_output=True,
                          text=True)
    assert proc.returncode == 0 and "--data" in proc.stdout and "--sampling" in proc.stdout, proc.stderr
    proc = subprocess.run([sys.executable, "-m", "diff4splat.cli", "evaluate"], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "--data" in proc.stderr


def test_defaults_come_from_their_single_homes():
    """generate's --trajectory and the pipeline's default_cameras share DEFAULT_TRAJECTORY ('arc', a
    sweep a single photograph supports); export-onnx's --config is models.bundle.DEFAULT_CONFIG."""
    assert DEFAULT_TRAJECTORY == "arc" and DEFAULT_AMPLITUDES["arc"] == 0.5
    parser = build_parser()
    assert parser.parse_args(["generate", "a.png", "--out", "o"]).trajectory == DEFAULT_TRAJECTORY
    default = inspect.signature(Diff4SplatPipeline.default_cameras).parameters["trajectory"].default
    assert default == DEFAULT_TRAJECTORY
    assert parser.parse_args(["export-onnx", "--out", "o"]).config == DEFAULT_CONFIG


def test_unknown_arguments_are_one_line_exit_2(tmp_path, capsys):
    code = main(["generate", str(EXAMPLE_IMAGE), "--out", str(tmp_path / "o"), "--no-such-flag"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--no-such-flag" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("trajectory, amplitude, needles", [
    ("forward", "1e30", ["--amplitude 1e+30 for forward", "(0, 1] scene depths"]),
    ("spiral", "1e30", ["--amplitude 1e+30 for spiral", "(0, 1] scene depths"]),
    ("backward", "-1", ["--amplitude -1 for backward", "(0, 4] scene depths"]),
    ("arc", "30", ["--amplitude 30 for arc", "radians", "30° would be 0.524 rad"]),
    ("orbit", "1", ["--amplitude does not apply to orbit", "leave --amplitude out"]),
])
def test_amplitude_out_of_range_is_one_line_before_the_model_loads(tmp_path, capsys, monkeypatch, trajectory,
                                                                     amplitude, needles):
    def no_model(*a, **k):
        raise AssertionError("the model was loaded before --amplitude was checked")

    for how in ("from_pretrained", "random"):  # every way a model is built
        monkeypatch.setattr(Diff4SplatModel, how, no_model)
    out = tmp_path / "out"
    code = main(["generate", str(EXAMPLE_IMAGE), "--trajectory", trajectory, "--amplitude", amplitude, "--quiet",
                 "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error: "), err
    for needle in needles:
        assert needle in err[0], (needle, err[0])
    assert "pass None" not in err[0] and "non-finite" not in err[0] and "parallel" not in err[0]
    assert not out.exists()


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "1e9", "30.5"])  # 1e9: saturated noise (issue 61)
def test_a_bad_guidance_is_one_line_exit_2_before_the_model_loads(tmp_path, capsys, value, monkeypatch):
    monkeypatch.setattr(generate_module, "load_pipeline", lambda *a, **k: pytest.fail("the model loaded"))
    code = main(["generate", str(EXAMPLE_IMAGE), "--guidance", value, "--quiet", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--guidance must be a finite number in [0, 30]" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_guidance_is_recorded_in_meta(tmp_path):
    code, out = _generate(tmp_path, "--prompt", "a cat turns its head", "--guidance", "2.5", frames=5)
    assert code == 0 and json.loads((out / "meta.json").read_text())["guidance"] == 2.5


def test_model_prefetch_with_compile_is_one_line_exit_2_before_the_model_loads(tmp_path, capsys, monkeypatch):
    for how in ("from_pretrained", "random"):
        monkeypatch.setattr(Diff4SplatModel, how, lambda *a, **k: pytest.fail("the model loaded"))
    code = main(["generate", str(EXAMPLE_IMAGE), "--offload", "model-prefetch", "--compile", "--quiet",
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--offload model-prefetch does not combine with --compile" in err[0]
    assert not (tmp_path / "o").exists()
