"""ONNX export: manifest, checker, per-module parity with PyTorch, dynamic axes, external data, atomic writes.

The export of the perturbed tiny model is made once per test session (:func:`exported`, cached under
pytest's base temp folder) and shared with tests/test_onnx_runtime.py: exports are the slow part.
"""
import dataclasses
import hashlib
import json
import os

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from helpers import exported, tiny_model

from diff4splat.cli import main
from diff4splat.export import (
    LDRM_OUTPUTS,
    MANIFEST_NAME,
    MAX_OPSET,
    _export_graph,
    _graphs,
    checkpoint_sha256,
    export_checkpoint,
    export_onnx,
    state_dict_sha256,
)
from diff4splat.io import MARKER, OutputDirError
from models.bundle import Diff4SplatConfig, Diff4SplatModel
from models.pretrained import config_from_dict

pytestmark = pytest.mark.xdist_group("onnx_export")  # under `--dist loadgroup` one worker builds and uses the
# shared exports (helpers.exported) instead of another waiting on their file lock

TOL = 1e-4  # float32 max abs difference, ONNX vs eager


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():
        yield


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    ckpt, out = exported(tmp_path_factory)
    model = Diff4SplatModel.from_pretrained(ckpt).eval()
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    sessions = {name: ort.InferenceSession(str(out / e["file"]), providers=["CPUExecutionProvider"])
                for name, e in manifest["files"].items()}
    return ckpt, out, model, manifest, sessions


def test_this_module_runs_in_its_xdist_group(request):
    """Under pytest-xdist's ``--dist loadgroup`` (the suite's addopts) the module's tests carry their group: one
    worker builds the shared exports while the other runs other tests (pytest 9.2 with xdist 3.8 drops the group
    silently, and both workers then wait on the same export)."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None or not request.config.getvalue("loadgroup"):
        pytest.skip("not under pytest-xdist's --dist loadgroup")
    assert request.node.nodeid.endswith("@onnx_export"), request.node.nodeid


def _randn(*shape, seed=0):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed))


def _close(got: np.ndarray, ref: torch.Tensor, name: str) -> float:
    ref = ref.detach().numpy()
    assert got.shape == ref.shape, name
    diff = float(np.abs(got - ref).max())
    assert diff <= TOL, f"{name}: max abs diff {diff}"
    return diff


@pytest.mark.slow
def test_manifest_records_parts_files_names_shapes_config_and_weight_hashes(full):
    ckpt, out, model, manifest, _ = full
    assert manifest["format"] == "diff4splat-onnx/2" and manifest["opset"] == 18
    assert manifest["parts"] == {"vae_encoder": True, "vae_decoder": True, "text_encoder": True, "dit": True,
                                 "dit_text_inputs": True, "ldrm": True, "deformation": True,
                                 "ldrm_image_input": False}  # no image branch: no image input
    assert set(manifest["files"]) == {"vae_encoder", "vae_decoder", "text_encoder", "dit", "ldrm"}
    names = {k: ([i["name"] for i in e["inputs"]], [o["name"] for o in e["outputs"]])
             for k, e in manifest["files"].items()}
    assert names["vae_encoder"] == (["video"], ["latents"])
    assert names["vae_decoder"] == (["latents"], ["video"])
    assert names["text_encoder"] == (["ids", "mask"], ["tokens"])
    assert names["dit"] == (["x", "sigma", "image_latent", "plucker", "text", "text_mask"], ["velocity"])
    assert names["ldrm"] == (["latents", "plucker", "times"], list(LDRM_OUTPUTS))
    dit_in = {i["name"]: i for i in manifest["files"]["dit"]["inputs"]}
    assert dit_in["x"]["shape"] == ["batch", 4, "latent_frames", "2*dit_tokens_h", "2*dit_tokens_w"]
    assert dit_in["plucker"]["shape"][:2] == ["batch", 1536] and dit_in["text_mask"]["dtype"] == "bool"
    assert manifest["files"]["vae_encoder"]["inputs"][0]["shape"] == ["batch", 3, "4*k + 1", "8*h8", "8*w8"]
    assert manifest["files"]["text_encoder"]["inputs"][0]["dtype"] == "int64"
    assert manifest["files"]["vae_decoder"]["dims"]["latent_frames"][0] == 3
    ldrm_out = {o["name"]: o["shape"] for o in manifest["files"]["ldrm"]["outputs"]}
    pixels = ["8*ldrm_tokens_h", "8*ldrm_tokens_w"]  # S = n source frames ("latent"): a dynamic axis
    assert ldrm_out["distance"] == ["batch", "latent_frames", *pixels]
    assert ldrm_out["colors"] == ["batch", "latent_frames", *pixels, 3]
    assert ldrm_out["d_means"] == ["batch", "times", "latent_frames", *pixels, 3]
    assert config_from_dict(Diff4SplatConfig, manifest["config"]) == model.config
    files = {f"{n}/model.safetensors": hashlib.sha256((ckpt / n / "model.safetensors").read_bytes()).hexdigest()
             for n in ("vae", "text_encoder", "dit", "ldrm")}
    assert manifest["weights"] == {"kind": "checkpoint", "path": str(ckpt), "sha256": files}
    written = [MARKER, MANIFEST_NAME] + [e["file"] for e in manifest["files"].values()]
    assert sorted(p.name for p in out.iterdir()) == sorted(written)
    assert not any(p.name.startswith(".") for p in out.parent.iterdir())  # no temp folder left


@pytest.mark.slow
def test_every_graph_passes_the_checker_at_the_requested_opset(full):
    _, out, _, manifest, _ = full
    for entry in manifest["files"].values():
        onnx.checker.check_model(str(out / entry["file"]), full_check=True)
        model = onnx.load(str(out / entry["file"]))
        assert {o.domain: o.version for o in model.opset_import}[""] == 18
        assert not entry["external_data"]


@pytest.mark.slow
def test_vae_encoder_and_decoder_match_pytorch_for_several_frame_counts(full):
    *_, model, _, sessions = full
    for T in (1, 5, 9):  # exported with 9 frames; 1 is the pipeline's photograph
        video = _randn(1, 3, T, 64, 64, seed=T).tanh()
        (got,) = sessions["vae_encoder"].run(None, {"video": video.numpy()})
        ref = model.vae.encode_latents(video)
        _close(got, ref, f"vae_encoder T={T}")
        assert float(ref.abs().max()) > 1e-2
    for n in (3, 4):
        z = _randn(2, 4, n, 8, 8, seed=n)
        (got,) = sessions["vae_decoder"].run(None, {"latents": z.numpy()})
        _close(got, model.vae.decode_latents(z), f"vae_decoder n={n}")
        assert got.shape == (2, 3, 1 + 4 * (n - 1), 64, 64)


@pytest.mark.slow
def test_text_encoder_matches_pytorch_with_padding(full):
    *_, model, _, sessions = full
    ids, mask = model.text_encoder.tokenizer(["a cat turns its head", "hi"])
    (got,) = sessions["text_encoder"].run(None, {"ids": ids.numpy(), "mask": mask.numpy()})
    ref = model.text_encoder(ids, mask)
    _close(got, ref, "text_encoder")
    assert np.all(got[1, int(mask[1].sum()):] == 0)  # padded rows are zeroed


def _dit_inputs(B, n, h, w, seed=0):
    return (_randn(B, 4, n, h, w, seed=seed), torch.rand(B, generator=torch.Generator().manual_seed(seed)),
            _randn(B, 4, 1, h, w, seed=seed + 1), _randn(B, 1536, n, h, w, seed=seed + 2) * 0.5)


@pytest.mark.parametrize("B,n,h,w", [(1, 3, 8, 8), (2, 5, 8, 8), (1, 2, 12, 16)])
@pytest.mark.slow
def test_dit_velocity_matches_pytorch_over_batch_frames_and_resolution(full, B, n, h, w):
    *_, model, _, sessions = full
    x, sigma, image_latent, plucker = _dit_inputs(B, n, h, w)
    text = _randn(B, 6, 64, seed=3)
    mask = torch.tensor([[True] * 4 + [False] * 2] * B)
    feeds = dict(x=x, sigma=sigma, image_latent=image_latent, plucker=plucker, text=text, text_mask=mask)
    (got,) = sessions["dit"].run(None, {k: v.numpy() for k, v in feeds.items()})
    ref = model.dit(x, sigma, image_latent, plucker, text, mask)
    _close(got, ref, f"dit {B, n, h, w}")
    assert float(ref.abs().max()) > 1e-2


@pytest.mark.slow
def test_all_false_text_mask_is_exactly_the_no_text_dit(full):
    """The unconditional path of a text export: one zero token with mask False == text=None."""
    *_, model, _, sessions = full
    x, sigma, image_latent, plucker = _dit_inputs(1, 3, 8, 8, seed=5)
    text, mask = torch.zeros(1, 1, 64), torch.zeros(1, 1, dtype=torch.bool)
    no_text = model.dit(x, sigma, image_latent, plucker)
    assert torch.equal(model.dit(x, sigma, image_latent, plucker, text, mask), no_text)  # bit for bit
    assert not torch.allclose(model.dit(x, sigma, image_latent, plucker, _randn(1, 1, 64), ~mask), no_text)
    feeds = dict(x=x, sigma=sigma, image_latent=image_latent, plucker=plucker, text=text, text_mask=mask)
    (got,) = sessions["dit"].run(None, {k: v.numpy() for k, v in feeds.items()})
    _close(got, no_text, "dit all-False mask vs text=None")


def _ldrm_inputs(B, n, h, w, K, seed=1):
    """latents, plucker, times (K,), photo (B, 3, 8h, 8w) in [−1, 1]."""
    times = torch.linspace(0, 1, K) if K > 1 else torch.tensor([0.3])
    return (_randn(B, 4, n, h, w, seed=seed), _randn(B, 1536, n, h, w, seed=seed + 1) * 0.5, times,
            _randn(B, 3, 8 * h, 8 * w, seed=seed + 2).tanh())


@pytest.mark.parametrize("B,n,h,w,K", [(1, 3, 8, 8, 9), (2, 2, 6, 10, 1)])
@pytest.mark.slow
def test_ldrm_with_deformation_matches_pytorch(full, B, n, h, w, K):
    *_, model, _, sessions = full
    latents, plucker, times, image = _ldrm_inputs(B, n, h, w, K)
    assert [i.name for i in sessions["ldrm"].get_inputs()] == ["latents", "plucker", "times"]  # no image branch
    got = sessions["ldrm"].run(None, {"latents": latents.numpy(), "plucker": plucker.numpy(), "times": times.numpy()})
    ref = model.ldrm(latents, plucker, times, image)
    for name, value in zip(LDRM_OUTPUTS, got, strict=True):
        _close(value, getattr(ref, name), f"ldrm.{name}")
    assert got[0].shape == (B, n, 8 * h, 8 * w)  # one grid per latent frame (S = n)
    assert got[5].shape == (B, K, n, 8 * h, 8 * w, 3) and float(ref.d_means.abs().max()) > 1e-2


@pytest.fixture(scope="module")
def branch(tmp_path_factory):
    """Export (without text) of parity_model(image_branch=8): gaussian_frames "latent", the branch's
    zero-init last layer perturbed."""
    ckpt, out = exported(tmp_path_factory, text=False, image_branch=8)
    model = Diff4SplatModel.from_pretrained(ckpt).eval()
    manifest = json.loads((out / MANIFEST_NAME).read_text())
    session = ort.InferenceSession(str(out / "ldrm.onnx"), providers=["CPUExecutionProvider"])
    return model, manifest, session


@pytest.mark.parametrize("B,n,h,w,K", [(1, 1, 8, 8, 3), (1, 2, 8, 8, 5), (2, 3, 6, 10, 1)])
@pytest.mark.slow
def test_ldrm_with_image_branch_takes_the_photo_and_matches_pytorch(branch, B, n, h, w, K):
    """n = 1, 2, 3: the graph is traced size-oblivious and must hold where the slice of frames 1… has 0 or 1 frames."""
    model, manifest, session = branch
    assert model.config.ldrm.image_branch == 8 and model.config.ldrm.gaussian_frames == "latent"
    assert manifest["parts"]["ldrm_image_input"] is True
    inputs = {i["name"]: i["shape"] for i in manifest["files"]["ldrm"]["inputs"]}
    assert list(inputs) == ["latents", "plucker", "times", "image"]
    assert inputs["image"] == ["batch", 3, "8*ldrm_tokens_h", "8*ldrm_tokens_w"]
    latents, plucker, times, image = _ldrm_inputs(B, n, h, w, K, seed=n)
    feeds = {"latents": latents.numpy(), "plucker": plucker.numpy(), "times": times.numpy()}
    got = session.run(None, {**feeds, "image": image.numpy()})
    ref = model.ldrm(latents, plucker, times, image)
    for name, value in zip(LDRM_OUTPUTS, got, strict=True):
        _close(value, getattr(ref, name), f"ldrm.{name} {B, n, h, w, K}")
    assert got[0].shape == (B, n, 8 * h, 8 * w)
    # The branch is not a no-op: another photo moves frame 0's Gaussians, and only frame 0's.
    other = session.run(None, {**feeds, "image": (-image).numpy()})
    assert float(np.abs(other[0][:, 0] - got[0][:, 0]).max()) > 1e-3
    assert np.array_equal(other[0][:, 1:], got[0][:, 1:])
    _close(other[0], model.ldrm(latents, plucker, times, -image).distance, "ldrm.distance, other photo")


@pytest.mark.slow
def test_bilinear_vae_decoder_exports_and_matches_pytorch(branch, tmp_path_factory):
    """The base model's layout (the image-branch export: ``VideoVAEConfig.upsample = "bilinear"``): the decoder's
    trilinear resize exports (ONNX ``Resize``, half-pixel) and matches PyTorch at several frame counts and sizes."""
    model, manifest, _ = branch
    assert model.config.vae.upsample == "bilinear"
    out = exported(tmp_path_factory, text=False, image_branch=8)[1]
    session = ort.InferenceSession(str(out / manifest["files"]["vae_decoder"]["file"]),
                                   providers=["CPUExecutionProvider"])
    for n, h, w in ((1, 8, 8), (3, 6, 10)):
        z = _randn(2, 4, n, h, w, seed=n)
        (got,) = session.run(None, {"latents": z.numpy()})
        _close(got, model.vae.decode_latents(z), f"vae_decoder n={n} {h}×{w}")


@pytest.mark.slow
def test_external_data_graph_checks_and_runs(tmp_path):
    """Weights at or above the threshold go to ``<file>.onnx.data`` (threshold 0 here; 2 GB by default)."""
    model = tiny_model()
    graph = next(g for g in _graphs(model, text=True, deformation=True) if g.name == "text_encoder")
    entry = _export_graph(graph, tmp_path / "text_encoder.onnx", 18, external_data_bytes=0,
                          config=model.config.to_dict())
    assert entry["external_data"] and len(entry["files"]) == 2
    data = tmp_path / next(f for f in entry["files"] if f != "text_encoder.onnx")
    assert data.stat().st_size >= 0.9 * entry["weight_bytes"] > 0  # tiny tensors may stay inline
    assert (tmp_path / "text_encoder.onnx").stat().st_size < 0.5 * entry["weight_bytes"]  # inline would exceed it
    onnx.checker.check_model(str(tmp_path / "text_encoder.onnx"))
    ids, mask = model.text_encoder.tokenizer(["a cat", "a dog on a log"])
    session = ort.InferenceSession(str(tmp_path / "text_encoder.onnx"), providers=["CPUExecutionProvider"])
    _close(session.run(None, {"ids": ids.numpy(), "mask": mask.numpy()})[0], model.text_encoder(ids, mask), "external")
    meta = session.get_modelmeta().custom_metadata_map  # the graph carries its own part, config and dim ranges
    assert meta["diff4splat.part"] == "text_encoder" and json.loads(meta["diff4splat.config"]) == json.loads(
        json.dumps(model.config.to_dict())) and json.loads(meta["diff4splat.dims"]) == entry["dims"]


@pytest.mark.slow
def test_an_ldrm_whose_grid_is_below_the_pyramids_bound_exports_and_runs_at_its_own_grid(tmp_path):
    """deformation.levels 4 needs 9 LDRM tokens a side to trace, the tiny model has 8: export-onnx crashed with a
    ConstraintViolationError after its other graphs, though generate ran the model."""
    cfg = Diff4SplatConfig()
    deformation = dataclasses.replace(cfg.ldrm.deformation, levels=4)
    ldrm = dataclasses.replace(cfg.ldrm, deformation=deformation)
    model = Diff4SplatModel.random(dataclasses.replace(cfg, ldrm=ldrm))
    torch.nn.init.normal_(model.ldrm.deformation.out_conv.weight, std=0.5, generator=torch.Generator().manual_seed(0))
    graph = next(g for g in _graphs(model.eval(), text=False, deformation=True) if g.name == "ldrm")
    _export_graph(graph, tmp_path / "ldrm.onnx", 18, external_data_bytes=2**31, config=model.config.to_dict())
    session = ort.InferenceSession(str(tmp_path / "ldrm.onnx"), providers=["CPUExecutionProvider"])
    h = cfg.height // cfg.vae.spatial_factor  # the model's own grid, below the traced one
    latents, plucker, times, _ = _ldrm_inputs(1, 2, h, h, 3)
    got = session.run(None, {"latents": latents.numpy(), "plucker": plucker.numpy(), "times": times.numpy()})
    ref = model.ldrm(latents, plucker, times)
    for name, value in zip(LDRM_OUTPUTS, got, strict=True):
        _close(value, getattr(ref, name), f"ldrm.{name}")


def test_weight_hashes_follow_the_weights(tmp_path):
    a, b = tiny_model(seed=0), tiny_model(seed=0)
    assert state_dict_sha256(a) == state_dict_sha256(b)
    with torch.no_grad():
        b.ldrm.head.out.bias[0] += 1e-6
    assert state_dict_sha256(a) != state_dict_sha256(b)
    a.save_pretrained(tmp_path / "ck")
    hashes = checkpoint_sha256(tmp_path / "ck")
    dit_bytes = (tmp_path / "ck/dit/model.safetensors").read_bytes()
    assert hashes["dit/model.safetensors"] == hashlib.sha256(dit_bytes).hexdigest()
    (tmp_path / "ck/vae/model.safetensors").unlink()
    with pytest.raises(FileNotFoundError):
        checkpoint_sha256(tmp_path / "ck")


def test_failed_export_keeps_the_previous_folder_and_leaves_no_temp(tmp_path, monkeypatch):
    out = tmp_path / "onnx"
    out.mkdir()
    (out / "keep.txt").write_text("previous export")
    (out / MARKER).write_text(json.dumps({"tool": "diff4splat", "kind": "onnx", "format": 1}))

    def broken(graph, path, *args, **kwargs):
        path.write_bytes(b"half-written")
        raise RuntimeError("exporter crashed")

    monkeypatch.setattr("diff4splat.export._export_graph", broken)
    with pytest.raises(RuntimeError):
        export_onnx(tiny_model(), out)
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "keep.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["onnx"]


@pytest.mark.slow
def test_a_graph_at_the_newest_accepted_opset_passes_the_checker_and_loads(tmp_path):
    """Opsets 26–28 were accepted (onnx names them) and failed the checker after the whole export."""
    model = tiny_model()
    graph = next(g for g in _graphs(model, text=True, deformation=True) if g.name == "text_encoder")
    _export_graph(graph, tmp_path / "t.onnx", MAX_OPSET, external_data_bytes=2**31, config=model.config.to_dict())
    assert {o.domain: o.version for o in onnx.load(str(tmp_path / "t.onnx")).opset_import}[""] == MAX_OPSET
    ort.InferenceSession(str(tmp_path / "t.onnx"), providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("case", ["opset_17", "opset_above_max", "missing_checkpoint", "backbone", "out_is_file",
                                  "no_out"])
def test_export_cli_bad_input_one_line_exit_2_and_no_output(tmp_path, capsys, case):
    out = tmp_path / "out"
    args = ["export-onnx", "--out", str(out)]
    if case == "opset_17":
        args += ["--opset", "17"]
    elif case == "opset_above_max":
        args += ["--opset", str(MAX_OPSET + 1)]
    elif case == "missing_checkpoint":
        args += ["--checkpoint", str(tmp_path / "nope")]
    elif case == "backbone":  # refused before loading (a 5B backbone loaded for minutes, then a wrong message)
        (tmp_path / "wan").mkdir()
        (tmp_path / "wan" / "model_index.json").write_text('{"_class_name": "WanImageToVideoPipeline"}')
        args += ["--checkpoint", str(tmp_path / "wan")]
    elif case == "out_is_file":
        out.write_text("x")
    else:
        args = args[:1]
    code = main(args)
    lines = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("diff4splat: warning")]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("diff4splat: error:")
    assert out.is_file() if case == "out_is_file" else not out.exists()


def test_export_checkpoint_checks_out_opset_and_checkpoint_before_the_model_loads(tmp_path):
    """``export-onnx``'s library call refuses a bad ``--out``, ``--opset`` or backbone folder before ``load`` runs (the
    command checks none of them itself); a missing checkpoint is ``load_model``'s one refusal."""
    def never(*args, **kwargs):
        raise AssertionError("the model was loaded before the request was checked")

    (tmp_path / "wan").mkdir()
    (tmp_path / "wan" / "model_index.json").write_text("{}")
    (tmp_path / "file").write_text("x")
    for checkpoint, out, opset, error, message in [
        (None, tmp_path / "file", 18, OutputDirError, "is a file"),
        (None, tmp_path / "no" / "such", 18, OutputDirError, "does not exist"),
        (tmp_path / "wan", tmp_path, 18, OutputDirError, "holds input"),
        (None, tmp_path / "out", 17, ValueError, "opset must be an int"),
        (tmp_path / "wan", tmp_path / "out", 18, ValueError, "is a diffusers backbone"),
    ]:
        with pytest.raises(error, match=message):
            export_checkpoint(checkpoint, out, opset=opset, overwrite=True, load=never)
    with pytest.raises(FileNotFoundError, match="nope is not a folder"):
        export_checkpoint(tmp_path / "nope", tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "wan"]
