"""`diff4splat generate --checkpoint DIR` end to end on tiny diffusers backbone folders (issue 30, test (e)): a Hub
layout written by the backbone, plus our ``ldrm/``, ``camera/`` and ``diff4splat.json``, loaded and run on the CPU."""
import contextlib
import importlib
import json
import subprocess
import sys

import pytest
import torch

pytest.importorskip("diffusers", reason="the diffusers backbones need diff4splat[diffusers]")
pytestmark = pytest.mark.slow  # every test here: diffusers costs ~8 s to import (tests/conftest.py)

from helpers import EXAMPLE_IMAGE  # noqa: E402
from simulated_cuda import SimulatedCudaTensor, simulated_cuda  # noqa: E402

from diff4splat.cli import main  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline, load_model  # noqa: E402
from models.backbone_model import BackboneModel, BackboneModelConfig  # noqa: E402
from models.deformation import DeformationConfig  # noqa: E402
from models.flow_matching import FlowMatchingConfig  # noqa: E402
from models.ldrm import LDRM, LDRMConfig  # noqa: E402

FIXTURES = {"cogvideox": "tiny_cogvideox", "wan": "tiny_wan"}


def _fixture(kind: str):
    try:
        return importlib.import_module(FIXTURES[kind])
    except ModuleNotFoundError as e:
        pytest.skip(f"{FIXTURES[kind]} not available: {e}")


def tiny_backbone_model(kind: str, seed: int = 0) -> BackboneModel:
    """The tiny backbone of ``kind`` with non-zero camera weights and a tiny random LDRM on its latents."""
    fixture = _fixture(kind)
    backbone = fixture.tiny_wan(seed) if kind == "wan" else fixture.tiny_backbone(seed)
    weight = backbone.camera_conv.camera_weight  # a trained camera branch: non-zero
    with torch.no_grad():
        weight.copy_(torch.randn(weight.shape, generator=torch.Generator().manual_seed(seed + 9)) * 0.02)
    lat = backbone.latent
    ldrm_cfg = LDRMConfig(latent_channels=lat.latent_channels, vae_temporal=lat.temporal_factor,
                          vae_spatial=lat.spatial_factor, patch_size=1, embed_dim=32, depth=1, num_heads=2,
                          head_channels=16, deformation=DeformationConfig(in_channels=32, hidden=32))
    torch.manual_seed(seed)
    config = BackboneModelConfig(name=f"tiny-{kind}", backbone=backbone.kind, height=fixture.HEIGHT,
                                 width=fixture.WIDTH, num_frames=fixture.FRAMES, vae=lat, ldrm=ldrm_cfg,
                                 sampling=FlowMatchingConfig(steps=2))
    return BackboneModel(backbone, LDRM(ldrm_cfg), config).eval()


@pytest.fixture(params=sorted(FIXTURES))
def folder(request, tmp_path):
    model = tiny_backbone_model(request.param)
    path = tmp_path / f"tiny-{request.param}"
    model.save_pretrained(path)
    return path, model


@pytest.mark.slow
def test_saved_folder_reloads_to_the_same_scene(folder):
    """save → load_model (detected by model_index.json) → the same latents and Gaussians as the model in memory."""
    path, model = folder
    loaded, source = load_model(path)
    assert isinstance(loaded, BackboneModel) and source == str(path) and loaded.config == model.config
    results = []
    for m in (model, loaded):
        pipe = Diff4SplatPipeline(m)
        cams = pipe.default_cameras("orbit", m.config.num_frames)
        image = torch.rand(m.config.height, m.config.width, 3, generator=torch.Generator().manual_seed(1))
        results.append(pipe(image, cams, "a cat walking", seed=3))
    a, b = results
    torch.testing.assert_close(a.latents, b.latents, rtol=0, atol=1e-6)
    torch.testing.assert_close(a.scene.canonical.means, b.scene.canonical.means, rtol=0, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("offload", ["none", "model-prefetch"])
def test_a_backbone_generates_on_simulated_cuda_as_on_the_cpu(folder, offload, cpu_tile_path):
    """The backbone pipeline (prompt, text encoder visiting the device) on "cuda" (tests/simulated_cuda.py, on a
    CPU-only machine) keeps its outputs there and gives the CPU's latents and Gaussians (both rendering through
    the PyTorch tile path); so does model offload with the diffusers transformer's blocks prefetched (a block
    that ran before its weights landed would read NaN there)."""
    path, _ = folder
    results = {}
    for dev in ("cpu", "cuda"):
        model, _ = load_model(path)
        with simulated_cuda() if dev == "cuda" else contextlib.nullcontext():
            pipe = Diff4SplatPipeline(model, dev, offload=offload if dev == "cuda" else "none")
            cams = pipe.default_cameras("orbit", model.config.num_frames)
            image = torch.rand(model.config.height, model.config.width, 3, generator=torch.Generator().manual_seed(1))
            results[dev] = pipe(image, cams, "a cat walking", seed=3)
    cpu, cuda = results["cpu"], results["cuda"]
    assert isinstance(cuda.latents, SimulatedCudaTensor) and isinstance(cuda.scene.canonical.means, SimulatedCudaTensor)
    torch.testing.assert_close(cuda.latents.elem, cpu.latents, rtol=0, atol=1e-5)
    torch.testing.assert_close(cuda.scene.canonical.means.elem, cpu.scene.canonical.means, rtol=0, atol=1e-4)


@pytest.mark.slow
def test_generate_cli_runs_a_backbone_folder(folder, tmp_path):
    """`diff4splat generate photo --checkpoint DIR` writes a whole output folder; meta.json names the model. In a fresh
    process with ``--quiet`` nothing but the summary line is printed: no loading bars, no transformers notes on
    backends the backbone does not use ("requires torchvision")."""
    path, model = folder
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "diff4splat.cli", "generate", str(EXAMPLE_IMAGE), "--checkpoint",
                          str(path), "--frames", str(model.config.num_frames), "--resolution", "64", "--prompt",
                          "waves on the beach", "--quiet", "--out", str(out)], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0 and run.stderr == "", run.stderr[-3000:]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["config"] == model.config.name and meta["frames"] == model.config.num_frames
    assert (meta["model_width"], meta["model_height"]) == (model.config.width, model.config.height)
    assert meta["num_gaussians"] > 0 and (out / "scene.ply").is_file() and (out / "video.mp4").is_file()


def test_a_folder_of_neither_format_is_one_clear_error(tmp_path, capsys):
    (tmp_path / "ckpt").mkdir()
    (tmp_path / "ckpt" / "weights.bin").write_bytes(b"x")
    code = main(["generate", str(EXAMPLE_IMAGE), "--checkpoint", str(tmp_path / "ckpt"), "--quiet",
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "config.json" in err[0] and "model_index.json" in err[0]
    assert not (tmp_path / "out").exists()


def test_a_folder_of_another_pipeline_is_refused(tmp_path):
    (tmp_path / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionPipeline"}))
    with pytest.raises(ValueError, match="StableDiffusionPipeline"):
        load_model(tmp_path)


def test_a_folder_fresh_from_the_hub_gets_the_released_config_zero_camera_and_a_random_ldrm(tmp_path):
    """A Hub folder has none of ours: camera weights zero (the pretrained transformer exactly), the backbone's
    released resolution and frames (models.backbone_model.DEFAULTS), the paper-size LDRM on its latents, random,
    with a warning naming the missing ldrm/."""
    fixture = _fixture("cogvideox")
    fixture.tiny_backbone(0).write_pretrained(tmp_path)
    with pytest.warns(UserWarning, match="ldrm/"):
        model = BackboneModel.from_pretrained(tmp_path)
    c = model.config
    assert (c.backbone, c.height, c.width, c.num_frames) == ("cogvideox-i2v", 480, 720, 49)
    assert (c.ldrm.latent_channels, c.ldrm.vae_spatial) == (4, 8) and c.ldrm.depth == LDRMConfig.paper().depth
    assert not model.backbone.camera_conv.camera_weight.any()


def test_guided_generation_reproduces_the_diffusers_pipeline_with_guidance(tmp_path):
    """Diff4SplatPipeline on a Wan backbone (camera weights zero: the pretrained model) with guidance 5 and a prompt:
    its sampled latents are WanImageToVideoPipeline's with ``guidance_scale=5`` (negative prompt "") for the same
    noise and photo — classifier-free guidance, conditioning and first-frame replacement as the pretrained model's."""
    fixture = _fixture("wan")
    backbone = fixture.tiny_wan(0)
    config = BackboneModelConfig.for_backbone("wan2.2-ti2v", backbone.latent, height=fixture.HEIGHT,
                                              width=fixture.WIDTH, num_frames=fixture.FRAMES,
                                              sampling=FlowMatchingConfig(steps=3, guidance=5.0))
    config.ldrm = LDRMConfig(latent_channels=48, vae_temporal=4, vae_spatial=16, embed_dim=32, depth=1, num_heads=2,
                             head_channels=16, deformation=DeformationConfig(in_channels=32, hidden=32))
    model = BackboneModel(backbone, LDRM(config.ldrm), config).eval()
    pipe = Diff4SplatPipeline(model)
    image = torch.rand(fixture.HEIGHT, fixture.WIDTH, 3, generator=torch.Generator().manual_seed(2))
    cams = pipe.default_cameras("orbit", fixture.FRAMES)
    prompt = "waves on the beach at sunset"
    ours = pipe(image, cams, prompt, seed=4)
    assert ours.guidance == 5.0
    noise = torch.randn(ours.latents.shape, generator=torch.Generator().manual_seed(4))  # the pipeline's draw
    with torch.no_grad(), backbone.hub_transformer():
        reference = backbone.pipeline(**backbone.pipeline_kwargs())(
            image=image.permute(2, 0, 1)[None], prompt=prompt, height=fixture.HEIGHT, width=fixture.WIDTH,
            num_frames=fixture.FRAMES, num_inference_steps=3, guidance_scale=5.0, latents=noise.clone(),
            output_type="latent", return_dict=False)[0]
    torch.testing.assert_close(ours.latents, reference, atol=1e-5, rtol=1e-5)
    unguided = pipe(image, cams, prompt, seed=4, guidance=1.0)
    assert (unguided.latents - ours.latents).abs().max() > 1e-3  # guidance changed the result
    assert pipe(image, cams, "", seed=4).guidance == 1.0  # no prompt: nothing to guide towards
