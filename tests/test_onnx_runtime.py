"""onnxruntime serving: the pipeline on ONNX sessions vs PyTorch (PSNR of the rendered video), the CLI
runtime, exports without text / deformation refusing what they cannot serve, manifest errors.

Exports come from tests/test_export.py's session cache (:func:`test_export.exported`).
"""
import json
import math
import os
import re
import shutil

import numpy as np
import onnxruntime as ort
import pytest
import torch
from helpers import EXAMPLE_IMAGE, exported

from diff4splat.cli import main
from diff4splat.io import load_depth_exr, load_image, load_ply
from diff4splat.io.scene_folder import load_deformation
from diff4splat.onnx_runtime import OnnxRuntime, default_providers, load_manifest, session_options  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.render.sequence import render_path
from models.bundle import Diff4SplatModel

pytestmark = pytest.mark.xdist_group("onnx_export")  # under `--dist loadgroup` one worker builds and uses the
# shared exports (helpers.exported) instead of another waiting on their file lock

FRAMES = 9
PROMPT = "a cat turns its head"


@pytest.fixture(scope="module")
def image():
    return load_image(EXAMPLE_IMAGE, size=(64, 64))


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    ckpt, out = exported(tmp_path_factory)
    return Diff4SplatModel.from_pretrained(ckpt).eval(), out


@pytest.fixture(scope="module")
def lean(tmp_path_factory):
    """``diff4splat export-onnx --no-text --static`` of the same checkpoint."""
    ckpt, out = exported(tmp_path_factory, text=False, deformation=False, cli=True)
    return Diff4SplatModel.from_pretrained(ckpt).eval(), out


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def _no_networks(monkeypatch):
    """Make any nn.Module call or model construction fail: the ONNX path must not need them."""
    def refuse(*a, **k):
        raise AssertionError("a PyTorch network was used by the onnxruntime runtime")

    monkeypatch.setattr(torch.nn.Module, "__call__", refuse)
    monkeypatch.setattr(Diff4SplatModel, "__init__", refuse)


@pytest.mark.parametrize("prompt", [PROMPT, ""])
@pytest.mark.slow
def test_onnxruntime_pipeline_matches_pytorch_end_to_end(full, image, prompt, monkeypatch):
    model, out = full
    torch_pipe = Diff4SplatPipeline(model)
    cams = torch_pipe.default_cameras("orbit", FRAMES)
    ref = torch_pipe(image, cams, prompt, steps=2, seed=3)
    ref_video = render_path(ref.scene, ref.cameras)[0]
    with monkeypatch.context() as m:
        _no_networks(m)
        onnx_pipe = Diff4SplatPipeline.from_onnx(out)
        got = onnx_pipe(image, cams, prompt, steps=2, seed=3)
        assert onnx_pipe.model is None and onnx_pipe.runtime.name == "onnxruntime"
    got_video = render_path(got.scene, got.cameras)[0]
    noise = torch.randn(ref.latents.shape, generator=torch.Generator().manual_seed(3))  # the pipeline's seed-3 start
    assert float((ref.latents - noise)[:, :, 1:].abs().max()) > 0.1  # v ≠ 0: the sampler moved the latents
    assert float((got.latents - ref.latents).abs().max()) <= 1e-4
    assert ref.scene.is_static == got.scene.is_static == (prompt == "")  # no prompt, no drag: a static scene
    if prompt:
        assert float((got.scene.d_means - ref.scene.d_means).abs().max()) <= 1e-4
    assert got.scene.num_gaussians == ref.scene.num_gaussians
    assert _psnr(got_video, ref_video) >= 45.0


@pytest.fixture(scope="module")
def branch(tmp_path_factory):
    """Export (without text) of parity_model(image_branch=8): an LDRM whose perturbed image branch
    takes the photograph; gaussian_frames "latent"."""
    ckpt, out = exported(tmp_path_factory, text=False, image_branch=8)
    return Diff4SplatModel.from_pretrained(ckpt).eval(), out


@pytest.mark.slow
def test_onnxruntime_pipeline_with_image_branch_matches_pytorch_end_to_end(branch, image, monkeypatch):
    model, out = branch
    torch_pipe = Diff4SplatPipeline(model)
    cams = torch_pipe.default_cameras("orbit", FRAMES)
    ref = torch_pipe(image, cams, "", steps=2, seed=3)
    with monkeypatch.context() as m:
        _no_networks(m)
        got = Diff4SplatPipeline.from_onnx(out)(image, cams, "", steps=2, seed=3)
    assert got.source_frames.tolist() == ref.source_frames.tolist() == [0, 4, 8]
    assert float((got.latents - ref.latents).abs().max()) <= 1e-4
    assert got.scene.num_gaussians == ref.scene.num_gaussians and torch.equal(got.gaussian_index, ref.gaussian_index)
    torch.testing.assert_close(got.scene.canonical.means, ref.scene.canonical.means, atol=1e-4, rtol=0)
    # No prompt (the export has no text encoder) and no drag: both static; the deformation graph's parity with the
    # image branch is test_export's (test_ldrm_with_image_branch_takes_the_photo_and_matches_pytorch).
    assert got.scene.is_static and ref.scene.is_static
    assert _psnr(render_path(got.scene, got.cameras)[0], render_path(ref.scene, ref.cameras)[0]) >= 45.0
    # The photograph reaches the graph: another photo changes the reference frame's Gaussians.
    runtime = Diff4SplatPipeline.from_onnx(out).runtime
    lat, plucker = got.latents, torch.zeros(1, 1536, *got.latents.shape[2:])
    a = runtime.reconstruct(lat, plucker, None, image.permute(2, 0, 1)[None] * 2 - 1)  # the photo in [−1, 1]
    b = runtime.reconstruct(lat, plucker, None, torch.zeros(1, 3, 64, 64))
    assert float((a.distance[:, 0] - b.distance[:, 0]).abs().max()) > 1e-3
    assert torch.equal(a.distance[:, 1:], b.distance[:, 1:])
    with pytest.raises(ValueError, match=r"^image must have shape \(1, 3, 64, 64\) .*image branch\), got None"):
        runtime.reconstruct(lat, plucker, None, None)
    # generated_colors "video": the exported VAE decoder colours the generated frames as the PyTorch one does.
    monkeypatch.setattr(model.config, "generated_colors", "video")
    ref_v = torch_pipe(image, cams, "", steps=2, seed=3)
    with monkeypatch.context() as m:
        _no_networks(m)
        onnx_pipe = Diff4SplatPipeline.from_onnx(out)
        m.setattr(onnx_pipe.config, "generated_colors", "video")
        got_v = onnx_pipe(image, cams, "", steps=2, seed=3)
    assert torch.equal(got_v.gaussian_index, ref_v.gaussian_index)
    generated = ref_v.gaussian_index >= ref_v.num_slots - 2 * 64 * 64  # source frames 4 and 8
    assert int(generated.sum()) > 100
    torch.testing.assert_close(got_v.scene.canonical.sh[generated], ref_v.scene.canonical.sh[generated], atol=1e-4,
                               rtol=0)
    video_rgb = render_path(ref_v.scene, ref_v.cameras)[0]
    assert _psnr(render_path(got_v.scene, got_v.cameras)[0], video_rgb) >= 45.0
    assert _psnr(video_rgb, render_path(ref.scene, ref.cameras)[0]) < 45.0  # the colours did change
    # Fewer latent frames than the decoder graph was traced for (3): padded, exact, as the causal decoder is.
    z = got.latents[:, :, :2]
    with torch.no_grad():
        want = model.vae.decode_latents(z)
    assert want.shape == (1, 3, 5, 64, 64)
    torch.testing.assert_close(runtime.decode_latents(z), want, atol=1e-4, rtol=0)


@pytest.mark.slow
def test_image_input_flag_is_checked_against_the_graph(branch, tmp_path):
    _, out = branch
    folder = tmp_path / "copy"
    shutil.copytree(out, folder)
    OnnxRuntime(folder)
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["parts"]["ldrm_image_input"] = False
    path.write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="ldrm.onnx: parts.ldrm_image_input is False but the graph's inputs"):
        OnnxRuntime(folder)
    del manifest["parts"]["ldrm_image_input"]
    path.write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="manifest.json: parts.ldrm_image_input must be a bool, got missing"):
        OnnxRuntime(folder)


@pytest.mark.slow
def test_the_onnx_runtime_checks_inputs_as_the_pytorch_networks_do(full):
    """A bad shape reached onnxruntime (a Reshape node's error and coloured log lines) and σ = 1.5 ran silently;
    the PyTorch networks refuse each with one ValueError, and so does the runtime now."""
    model, out = full
    rt = OnnxRuntime(out)
    cfg = model.config
    c, h = cfg.vae.latent_channels, cfg.height // cfg.vae.spatial_factor
    r = lambda *shape: torch.randn(shape, generator=torch.Generator().manual_seed(0))  # noqa: E731
    cases = [
        (lambda: rt.encode_image(r(1, 3, 6, cfg.height, cfg.width)), "T must be 1 + 4·k"),
        (lambda: rt.encode_image(r(1, 3, 1, cfg.height - 4, cfg.width)), "multiples of 8"),
        (lambda: rt.decode_latents(r(1, c + 1, 2, h, h)), "latents must have shape"),
        (lambda: rt.velocity(r(1, c, 2, h, h), torch.tensor([1.5]), r(1, c, 1, h, h), r(1, 1536, 2, h, h), None,
                             None), "sigma must lie in [0, 1]"),
        (lambda: rt.velocity(r(1, c, 2, h, h), torch.tensor([0.5]), r(1, c, 1, h, h), r(1, 1536, 3, h, h), None,
                             None), "plucker must have shape"),
        (lambda: rt.reconstruct(r(1, c, 2, h, h), r(1, 1536, 2, h, h), torch.tensor([0.0, 2.0]), None),
         "times must lie in [0, 1]"),
    ]
    for call, needle in cases:
        with pytest.raises(ValueError, match=re.escape(needle)):
            call()


@pytest.mark.slow
def test_prompt_changes_the_onnx_sample(full, image):
    _, out = full
    pipe = Diff4SplatPipeline.from_onnx(out)
    cams = pipe.default_cameras("orbit", 5)
    a, b = pipe(image, cams, PROMPT, steps=2), pipe(image, cams, "", steps=2)
    assert float((a.latents - b.latents).abs().max()) > 1e-3


@pytest.mark.slow
def test_generate_cli_onnxruntime_writes_the_same_folder(full, tmp_path, tmp_path_factory):
    model, out = full
    ckpt = exported(tmp_path_factory)[0]
    common = ["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "2", "--prompt", PROMPT, "--quiet"]
    assert main(common + ["--checkpoint", str(ckpt), "--device", "cpu", "--out", str(tmp_path / "torch")]) == 0
    assert main(common + ["--onnx", str(out), "--out", str(tmp_path / "ort")]) == 0  # --onnx: onnxruntime
    a, b = tmp_path / "torch", tmp_path / "ort"
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
    meta = json.loads((b / "meta.json").read_text())
    assert meta["runtime"] == "onnxruntime" and meta["model"].startswith("onnx:") and "onnxruntime" in meta["versions"]
    assert meta["attention"] is None and meta["compile"] is False
    assert json.loads((a / "meta.json").read_text())["runtime"] == "torch"
    assert (a / "cameras.json").read_text() == (b / "cameras.json").read_text()
    ga, gb = load_ply(a / "scene.ply"), load_ply(b / "scene.ply")
    torch.testing.assert_close(gb.means, ga.means, atol=1e-4, rtol=0)
    torch.testing.assert_close(gb.scales, ga.scales, atol=1e-5, rtol=1e-4)
    da, db = load_deformation(a / "deformation.npz"), load_deformation(b / "deformation.npz")
    np.testing.assert_allclose(db["d_means"], da["d_means"], atol=1e-4)
    depth_a, depth_b = load_depth_exr(a / "depth" / "0004.exr"), load_depth_exr(b / "depth" / "0004.exr")
    assert np.median(np.abs(depth_a - depth_b)) < 1e-4


@pytest.mark.slow
def test_no_text_static_export_has_only_what_it_serves(lean):
    _, out = lean
    manifest = load_manifest(out)
    assert manifest["parts"]["text_encoder"] is False and manifest["parts"]["deformation"] is False
    assert set(manifest["files"]) == {"vae_encoder", "vae_decoder", "dit", "ldrm"}
    assert not (out / "text_encoder.onnx").exists()
    assert [i["name"] for i in manifest["files"]["dit"]["inputs"]] == ["x", "sigma", "image_latent", "plucker"]
    ldrm = manifest["files"]["ldrm"]
    assert [i["name"] for i in ldrm["inputs"]] == ["latents", "plucker"]
    assert [o["name"] for o in ldrm["outputs"]] == ["distance", "scales", "quats", "opacities", "colors"]


@pytest.mark.slow
def test_no_text_static_export_refuses_prompt_and_times(lean, image):
    _, out = lean
    runtime = OnnxRuntime(out)
    pipe = Diff4SplatPipeline(runtime)
    cams = pipe.default_cameras("orbit", 5)
    with pytest.raises(ValueError, match="^prompt: .*without the text encoder") as info:
        pipe(image, cams, PROMPT, steps=1)
    assert "--" not in str(info.value)  # the library names parameters, not CLI flags
    with pytest.raises(ValueError, match="^text: .*without the text encoder"):
        runtime.velocity(torch.zeros(1, 4, 2, 8, 8), torch.ones(1), torch.zeros(1, 4, 1, 8, 8),
                         torch.zeros(1, 1536, 2, 8, 8), torch.zeros(1, 3, 64), None)
    with pytest.raises(ValueError, match="^times: .*without the deformation network"):
        runtime.reconstruct(torch.zeros(1, 4, 2, 8, 8), torch.zeros(1, 1536, 2, 8, 8), torch.tensor([0.0, 1.0]),
                            torch.zeros(1, 3, 64, 64))
    out = runtime.reconstruct(torch.zeros(1, 4, 2, 8, 8), torch.zeros(1, 1536, 2, 8, 8), None, None)
    assert out.distance.shape == (1, 2, 64, 64) and out.d_means is None  # no image branch: the photo is not needed


@pytest.mark.slow
def test_no_text_static_export_serves_the_empty_prompt_as_a_static_scene(lean, image):
    model, out = lean
    cams = Diff4SplatPipeline(model).default_cameras("orbit", FRAMES)
    ref = Diff4SplatPipeline(model)(image, cams, "", steps=2, seed=1)  # no prompt: static in PyTorch too
    got = Diff4SplatPipeline.from_onnx(out)(image, cams, "", steps=2, seed=1)
    assert ref.scene.is_static and got.scene.is_static
    assert float((got.latents - ref.latents).abs().max()) <= 1e-4  # the no-text DiT graph == text=None
    assert torch.equal(got.gaussian_index, ref.gaussian_index)
    torch.testing.assert_close(got.scene.canonical.means, ref.scene.canonical.means, atol=1e-4, rtol=0)


@pytest.mark.slow
def test_cli_prompt_on_a_no_text_export_is_one_line_exit_2(lean, tmp_path, capsys):
    _, out = lean
    code = main(["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "1", "--quiet", "--prompt", PROMPT,
                 "--runtime", "onnxruntime", "--onnx", str(out), "--out", str(tmp_path / "o")])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and "without the text encoder" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("case", ["no_onnx", "onnx_without_runtime", "with_checkpoint", "with_attention",
                                  "with_compile", "missing_folder"])
def test_cli_runtime_option_errors(tmp_path, capsys, case):
    args = ["generate", str(EXAMPLE_IMAGE), "--quiet", "--out", str(tmp_path / "o")]
    args += {"no_onnx": ["--runtime", "onnxruntime"],
             "onnx_without_runtime": ["--runtime", "torch", "--onnx", str(tmp_path)],
             "with_checkpoint": ["--runtime", "onnxruntime", "--onnx", str(tmp_path), "--checkpoint", str(tmp_path)],
             "with_attention": ["--runtime", "onnxruntime", "--onnx", str(tmp_path), "--attention", "cudnn"],
             "with_compile": ["--runtime", "onnxruntime", "--onnx", str(tmp_path), "--compile"],
             "missing_folder": ["--runtime", "onnxruntime", "--onnx", str(tmp_path / "none")]}[case]
    code = main(args)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error:")
    flag = {"no_onnx": "--onnx", "onnx_without_runtime": "--runtime", "with_checkpoint": "--checkpoint",
            "with_attention": "--attention", "with_compile": "--compile", "missing_folder": "--onnx"}[case]
    assert flag in err[0]  # the CLI names its own flags
    assert not (tmp_path / "o").exists()


def test_manifest_errors(tmp_path):
    """Library errors name the parameter (``directory``), not the CLI's ``--onnx`` flag."""
    with pytest.raises(FileNotFoundError, match="^directory: .* not a folder"):
        load_manifest(tmp_path / "none")
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        load_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match="^directory: .*not valid JSON") as info:
        load_manifest(tmp_path)
    assert "--" not in str(info.value)
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match="format") as info:
        load_manifest(tmp_path)
    assert "--" not in str(info.value)
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "diff4splat-onnx/2",
                                                        "files": {"dit": {"files": ["dit.onnx"]}}}))
    with pytest.raises(ValueError, match="manifest.json: config must be a dict, got missing"):
        load_manifest(tmp_path)  # the keys are checked (tests/test_reliability_errors.py: each key, missing files)


def test_session_settings():
    opts = session_options()
    assert opts.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert opts.intra_op_num_threads == os.cpu_count()
    providers = default_providers()
    assert providers[-1] == "CPUExecutionProvider" and set(providers) <= set(ort.get_available_providers())
    assert ("CUDAExecutionProvider" in providers) == ("CUDAExecutionProvider" in ort.get_available_providers())
