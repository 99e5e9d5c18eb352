"""Training stages of a pretrained diffusers backbone (training/backbone_training.py; objectives through
models.backbones; issue 30, test d), on the tiny random Wan2.2-TI2V and CogVideoX-I2V backbones and a tiny synthetic
dataset, on the CPU: 20 steps through ``python -m training.train`` lower the loss and change only the LoRA adapters,
the camera weights and the LDRM (every other weight and buffer bit for bit as loaded); resuming from the run's
step-10 checkpoint repeats steps 11–20 bit for bit; the saved folder (LoRA merged, the transformer under its own key
names) reloads with ``BackboneModel.from_pretrained`` with the trained velocity, and ``generate --checkpoint`` runs
it; FSDP2 on two gloo ranks shards the backbone block by block and checkpoints only what trains. Fast tests: the flow
loss recomputed by hand, the shipped backbone stage configs, the stage fields' errors, the LoRA merge, the Plücker
packing for the backbone's grid."""
import csv
import dataclasses
import json
import math
import shutil
from pathlib import Path

import pytest

pytest.importorskip("diffusers", reason="training a diffusers backbone needs diff4splat[diffusers]")
pytestmark = pytest.mark.slow  # every test here: diffusers costs ~8 s to import (tests/conftest.py)
pytest.importorskip("peft", reason="training a diffusers backbone needs peft")

import torch  # noqa: E402
import yaml  # noqa: E402
from _trainer_toy import fsdp_stage_script, run_two_ranks  # noqa: E402
from helpers import EXAMPLE_IMAGE  # noqa: E402
from safetensors import safe_open  # noqa: E402
from simulated_cuda import simulated_cuda  # noqa: E402
from tiny_cogvideox import tiny_backbone as tiny_cogvideox  # noqa: E402
from tiny_wan import tiny_wan  # noqa: E402
from torch.utils.data import default_collate  # noqa: E402

import training.train as train  # noqa: E402
from data_prep.clips import ClipConfig, ClipDataset  # noqa: E402
from data_prep.synth import generate_scene  # noqa: E402
from diff4splat.cameras import pack_plucker, plucker_rays  # noqa: E402
from diff4splat.cli import main as cli_main  # noqa: E402
from diff4splat.utils.devices import cpu_bf16_warning  # noqa: E402
from models.backbone_model import BackboneModel, BackboneModelConfig  # noqa: E402
from models.ldrm import LDRM, LDRMConfig  # noqa: E402
from training.backbone_training import add_lora, load_backbone_model, lora_layers, merged_lora  # noqa: E402
from training.checkpoint import latest_checkpoint, load_checkpoint  # noqa: E402
from training.objectives import TrainingModule  # noqa: E402
from training.stage_config import LoraSettings, StageConfig, load_stage  # noqa: E402
from training.trainer import TrainerConfig  # noqa: E402

FRAMES, STEPS = 9, 20
BACKBONES = {  # name: (tiny backbone, clip height, width); the tiny fixtures' own sizes
    "wan": (tiny_wan, 64, 32),
    "cogvideox": (tiny_cogvideox, 16, 16),
}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two static scenes and a dynamic one, 64² and 9 frames (one clip each; cropped and resized per backbone)."""
    root = tmp_path_factory.mktemp("backbone_data")
    for i, ratio in enumerate((1.0, 1.0, 0.0)):
        generate_scene(root, i, seed=41, size=64, frames=FRAMES, cameras=1, static_ratio=ratio)
    return root


def _init_folder(name: str, folder: Path, camera_std: float = 0.0) -> Path:
    """A backbone model folder: the tiny backbone (camera weights zero, as from the Hub, or N(0, camera_std²)) and a
    tiny LDRM on its latents, saved with ``BackboneModel.save_pretrained``."""
    make, height, width = BACKBONES[name]
    backbone = make(0)
    with torch.no_grad():
        backbone.camera_conv.camera_weight.normal_(0, camera_std, generator=torch.Generator().manual_seed(2))
    fmt = backbone.latent
    ldrm = LDRMConfig(latent_channels=fmt.latent_channels, vae_temporal=fmt.temporal_factor,
                      vae_spatial=fmt.spatial_factor, depth=1, head_channels=16)
    config = BackboneModelConfig.for_backbone(backbone.kind, fmt, height=height, width=width, num_frames=FRAMES,
                                              ldrm=ldrm)
    torch.manual_seed(0)
    BackboneModel(backbone, LDRM(ldrm), config).save_pretrained(folder)
    return folder


def _stage(name: str, init: Path, data: Path, run_dir: Path, **trainer) -> StageConfig:
    """Stage 1 of backbone ``name`` (diffusion + rendering, LoRA rank 4) at the tiny size, batch 1."""
    _, height, width = BACKBONES[name]
    kind = {"wan": "wan2.2-ti2v", "cogvideox": "cogvideox-i2v"}[name]
    cfg = {**dict(run_dir=str(run_dir), total_steps=STEPS, batch_size=1, lr=3e-3, warmup_steps=2, checkpoint_every=10,
                  progress=False, seed=0, device="cpu"), **trainer}
    return StageConfig(name=f"{name}_stage1", backbone=kind, init_from=str(init), data=str(data), train=("dit", "ldrm"),
                       objectives=("diffusion", "reconstruction"), scenes="all", height=height, width=width,
                       num_frames=FRAMES, render_frames=2, caption_dropout=0.2, lora=LoraSettings(rank=4, alpha=8),
                       trainer=TrainerConfig(**cfg))


def _metrics(run_dir: Path) -> list[dict[str, str]]:
    """metrics.csv rows without the wall time."""
    return [{k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(open(run_dir / "metrics.csv"))]


@pytest.fixture(scope="module", params=list(BACKBONES))
def run(request, data, tmp_path_factory):
    """``python -m training.train`` for 20 steps of backbone stage 1 (checkpoints at steps 10 and 20), with the
    trainer and the trained model it built."""
    name = request.param
    root = tmp_path_factory.mktemp(f"{name}_run")
    init = _init_folder(name, root / "init")
    stage = _stage(name, init, data, root / "run")
    cfg = root / "stage.yaml"
    cfg.write_text(yaml.safe_dump(json.loads(json.dumps(dataclasses.asdict(stage)))))  # tuples as lists
    built = []
    real = train.build_training
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(train, "build_training", lambda st, seed=None: built.append(real(st, seed)) or built[-1])
        assert train.main(["--config", str(cfg), "--quiet"]) == 0
    trainer, model, counts = built[0]
    return {"name": name, "stage": stage, "init": init, "run_dir": root / "run", "trainer": trainer,
            "model": model, "counts": counts}


@pytest.mark.slow
def test_twenty_steps_lower_the_loss_and_train_only_lora_camera_and_ldrm(run):
    rows = _metrics(run["run_dir"])
    losses = [float(r["loss"]) for r in rows]
    assert [int(r["step"]) for r in rows] == list(range(1, STEPS + 1)) and all(r["skipped"] == "0" for r in rows)
    first, last = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert last < 0.95 * first, (first, last)  # seed 0: Wan 2.07 → 1.86, CogVideoX 1.81 → 1.35
    model, fresh = run["model"], load_backbone_model(run["stage"])  # as loaded: the init folder + LoRA (seeded)
    b = model.backbone  # the frozen pretrained encoders ran in eval mode (no dropout), the transformer trained
    assert not b.vae.training and not b.text_encoder.training and b.transformer.training and model.ldrm.training
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    assert all("lora_" in n or n.endswith("camera_weight") or n.startswith("ldrm.") for n in trainable)
    assert run["counts"] == {"dit": sum(p.numel() for n, p in model.named_parameters() if n in trainable
                                        and not n.startswith("ldrm.")),
                             "ldrm": sum(p.numel() for n, p in model.ldrm.named_parameters()
                                         if not n.startswith("deformation."))}  # deformation frozen in stage 1
    before = fresh.state_dict()
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed <= trainable  # every frozen weight and buffer bit for bit as loaded
    assert any("lora_B" in k for k in changed) and any(k.endswith("camera_weight") for k in changed)
    assert any(k.startswith("ldrm.") for k in changed)


@pytest.mark.slow
def test_resume_from_the_mid_run_checkpoint_repeats_the_run_bit_for_bit(run, tmp_path):
    """A new run folder holding the reference run's step-10 checkpoint (and its metrics): ``--resume`` redoes steps
    11–20 with the same losses, gradient norms and learning rates, and ends with the same trained weights."""
    ref = run["run_dir"]
    resumed = tmp_path / "resumed"
    (resumed / "checkpoints").mkdir(parents=True)
    shutil.copytree(ref / "checkpoints" / "step_00000010", resumed / "checkpoints" / "step_00000010")
    (resumed / "checkpoints" / "latest").write_text("step_00000010")
    shutil.copy(ref / "metrics.csv", resumed / "metrics.csv")
    trainer, model, _ = train.build_training(dataclasses.replace(
        run["stage"], trainer=dataclasses.replace(run["stage"].trainer, run_dir=str(resumed))))
    trainer.fit(resume=True)
    assert _metrics(resumed) == _metrics(ref)
    ref_state = run["model"].state_dict()
    diff = max(float((v - ref_state[k]).abs().max()) for k, v in model.state_dict().items())
    assert diff == 0.0
    saved = torch.load(latest_checkpoint(ref) / "state.pt", weights_only=False)["step"]
    assert saved == STEPS


@pytest.mark.slow
def test_the_saved_model_reloads_with_the_trained_velocity(run):
    """``<run_dir>/model`` (LoRA merged; the transformer under the checkpoint's own key names) loads with
    ``BackboneModel.from_pretrained``: its velocity is the trained model's, its LDRM and camera weights are equal."""
    folder, model = run["run_dir"] / "model", run["model"]  # train mode: no dropout anywhere (LoRA dropout 0)
    reloaded = BackboneModel.from_pretrained(folder).eval()
    keys = set()
    for f in (folder / "transformer").glob("*.safetensors"):
        with safe_open(str(f), "pt") as sf:
            keys |= set(sf.keys())
    with merged_lora(model.backbone.transformer):  # the plain transformer's names
        expected = {k for k in model.backbone.transformer.state_dict() if not k.endswith("camera_weight")}
    assert keys == expected and not any("lora" in k or "base_layer" in k for k in keys)
    assert lora_layers(model.backbone.transformer)  # merged for the save only
    for k, v in model.ldrm.state_dict().items():
        assert torch.equal(v, reloaded.ldrm.state_dict()[k]), k
    assert torch.equal(model.backbone.camera_conv.camera_weight, reloaded.backbone.camera_conv.camera_weight)
    fmt, (_, height, width) = model.backbone.latent, BACKBONES[run["name"]]
    n, h, w = fmt.num_latent_frames(FRAMES), height // fmt.spatial_factor, width // fmt.spatial_factor
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, fmt.latent_channels, n, h, w, generator=g)
    image = torch.randn(2, fmt.latent_channels, 1, h, w, generator=g)
    plucker = torch.randn(2, fmt.camera_channels, n, h, w, generator=g)
    sigma = torch.tensor([0.3, 0.8])
    with torch.no_grad():
        text, mask = model.backbone.text_model.encode_text(["a red car drives down the street", ""])
        trained = model.backbone(x, sigma, image, plucker, text, mask)
        loaded = reloaded.backbone(x, sigma, image, plucker, text, mask)
        initial = BackboneModel.from_pretrained(run["init"]).backbone(x, sigma, image, plucker, text, mask)
    torch.testing.assert_close(loaded, trained, rtol=1e-5, atol=1e-5)
    assert float((trained - initial).abs().max()) > 1e-3  # training changed the velocity


@pytest.mark.slow
def test_a_bfloat16_backbone_trains_float32_weights(data, tmp_path):
    """``backbone_dtype: bfloat16`` (with bf16 autocast): the transformer's own weights are bfloat16; the LoRA
    adapters, the camera weights and the LDRM are float32, the last two exactly the folder's; two steps train."""
    init = _init_folder("wan", tmp_path / "init", camera_std=0.02)
    stage = _stage("wan", init, data, tmp_path / "run", bf16=True, total_steps=2)
    trainer, model, _ = train.build_training(dataclasses.replace(stage, backbone_dtype="bfloat16"))
    saved = BackboneModel.from_pretrained(init)
    transformer = model.backbone.transformer
    assert transformer.blocks[0].attn1.to_q.base_layer.weight.dtype == torch.bfloat16
    assert all(p.dtype == torch.float32 for p in model.parameters() if p.requires_grad)
    assert all(torch.equal(v, saved.ldrm.state_dict()[k]) for k, v in model.ldrm.state_dict().items())
    assert torch.equal(model.backbone.camera_conv.camera_weight, saved.backbone.camera_conv.camera_weight)
    assert float(saved.backbone.camera_conv.camera_weight.detach().abs().max()) > 0
    # On a CPU whose oneDNN bfloat16 matmul leaks NaN across rows (oneDNN#5717, Intel AMX; the library warns of it,
    # tests/test_cpu_bf16.py) the steps run on torch's own kernels: this test is of the training, not of that bug.
    with torch.backends.mkldnn.flags(enabled=cpu_bf16_warning() is None):
        assert trainer.bf16 and trainer.fit()["step"] == 2
    rows = _metrics(tmp_path / "run")  # every loss term of every step, skipped ones included, in the message
    assert all(math.isfinite(float(r["loss"])) for r in rows), (rows, cpu_bf16_warning())


@pytest.mark.slow
def test_generate_runs_the_trained_folder(run, tmp_path):
    """`diff4splat generate photo --checkpoint <run_dir>/model` on the stage's output writes a scene."""
    out = tmp_path / "out"
    code = cli_main(["generate", str(EXAMPLE_IMAGE), "--checkpoint", str(run["run_dir"] / "model"), "--frames",
                     str(FRAMES), "--steps", "2", "--resolution", "64", "--prompt", "a dog runs", "--quiet",
                     "--out", str(out)])
    assert code == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["num_gaussians"] > 0 and (out / "scene.ply").is_file()


@pytest.mark.slow
def test_fsdp_on_two_gloo_ranks_shards_the_backbone_block_by_block(data, tmp_path):
    """``torchrun -m training.train --strategy fsdp`` on two CPU processes with the tiny Wan: the transformer's,
    LDRM's and umT5's blocks are FSDP units, the transformer checkpoints its blocks, the checkpoint holds exactly the
    trained weights (the EMA's keys: no frozen weight, not even the second name of umT5's tied embedding), and rank 0
    writes the model folder from the gathered EMA."""
    init = _init_folder("wan", tmp_path / "init")
    stage = _stage("wan", init, data, tmp_path / "run", ema_decay=0.9, gradient_checkpointing=True, total_steps=1,
                   checkpoint_every=1)
    cfg = tmp_path / "stage.yaml"
    cfg.write_text(yaml.safe_dump(json.loads(json.dumps(dataclasses.asdict(stage)))))
    script = fsdp_stage_script(cfg, """
        b = model.backbone
        units = [*b.transformer_blocks(), *model.ldrm.blocks, *b.text_encoder.encoder.block]
        assert trainer.sharded and all(isinstance(u, FSDPModule) for u in units)
        assert b.transformer.gradient_checkpointing and not isinstance(b.vae, FSDPModule)
    """)
    run_two_ranks(script, timeout=300, fresh=(tmp_path / "run",))
    weights, _, ema = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    trainable = {f"model.{n}" for n, p in load_backbone_model(stage).named_parameters() if "lora_" in n
                 or n.endswith("camera_weight") or (n.startswith("ldrm.") and not n.startswith("ldrm.deformation."))}
    assert set(weights) == set(ema) == trainable
    saved = BackboneModel.from_pretrained(tmp_path / "run" / "model")
    assert all(torch.equal(v, ema[f"model.ldrm.{k}"]) for k, v in saved.ldrm.named_parameters()
               if f"model.ldrm.{k}" in ema)
    assert torch.equal(saved.backbone.camera_conv.camera_weight,
                       ema["model.backbone.transformer.patch_embedding.camera_weight"])


# ------------------------------------------------------------------------------------------------ fast
def test_shipped_backbone_stages_follow_the_progressive_schedule():
    for name, kind, unit in (("wan", "wan2.2-ti2v", 32), ("cogvideox", "cogvideox-i2v", 16)):
        stages = [load_stage(f"train_{name}_stage{i}") for i in (1, 2, 3)]
        for i, st in enumerate(stages, 1):
            assert st.backbone == kind and st.name == f"{name}_stage{i}"
            assert st.lora is not None and "dit" in st.train and not {"vae", "text_encoder"} & set(st.train)
            assert st.backbone_dtype == "bfloat16" and st.trainer.bf16 is True
            assert st.trainer.gradient_checkpointing and st.trainer.strategy == "fsdp"
            assert st.height % unit == 0 and st.width % unit == 0 and (st.num_frames - 1) % 4 == 0
        one, two, three = stages
        assert not one.deformation and not two.deformation and three.deformation and three.motion
        assert one.scenes == two.scenes == "static" and three.scenes == "all"
        assert "ldrm.deformation" in three.train and "ldrm.deformation" not in two.train
        assert Path(two.init_from) == Path(one.trainer.run_dir) / "model"
        assert Path(three.init_from) == Path(two.trainer.run_dir) / "model"
        assert one.height * one.width <= two.height * two.width == three.height * three.width
    assert (load_stage("train_wan_stage2").height, load_stage("train_wan_stage2").width) == (704, 1280)
    assert (load_stage("train_cogvideox_stage1").height, load_stage("train_cogvideox_stage1").width) == (480, 720)


BASE = "name: s\nbackbone: wan2.2-ti2v\ntrain: [dit, ldrm]\nobjectives: [diffusion, reconstruction]\nlora: {rank: 4}\n"


@pytest.mark.parametrize("bad, field", [
    ("backbone: sora", "stage.backbone"),
    ("backbone_dtype: float16", "stage.backbone_dtype"),
    ("lora: {rank: 0}", "stage.lora.rank"),
    ("lora: {rank: 4, alpha: 0}", "stage.lora.alpha"),
    ("lora: {rank: 4, dropout: 1.0}", "stage.lora.dropout"),
    ("lora: {rank: 4, targets: [to_q]}", "'targets'"),
    ("lora: {rank: 2.5}", "'rank'"),
    ("lora: null", "stage.lora"),
    ("train: [vae, dit]", "stage.train"),
    ("objectives: [vae]", "stage.objectives"),
    ("backbone: ours", "stage.lora"),
])
def test_bad_backbone_stage_fields_raise_one_value_error_naming_the_field(tmp_path, bad, field):
    good = tmp_path / "good.yaml"
    good.write_text(BASE)
    assert load_stage(good).lora.rank == 4
    path = tmp_path / "bad.yaml"
    path.write_text(BASE + bad + "\n")
    with pytest.raises(ValueError) as err:
        load_stage(path)
    assert field in str(err.value)


def test_a_stage_refuses_a_folder_of_another_backbone(data, tmp_path):
    init = _init_folder("cogvideox", tmp_path / "init")
    wan = dataclasses.replace(_stage("wan", init, data, tmp_path / "run"))
    with pytest.raises(ValueError, match="holds a cogvideox-i2v backbone; stage.backbone is wan2.2-ti2v"):
        train.build_training(wan)
    with pytest.raises(ValueError, match="diffusers backbone folder"):  # our networks' stage
        train.build_training(StageConfig(init_from=str(init), data=str(data), trainer=TrainerConfig(device="cpu")))
    bf16 = dataclasses.replace(_stage("cogvideox", init, data, tmp_path / "run"), backbone_dtype="bfloat16")
    with pytest.raises(ValueError, match="backbone_dtype: bfloat16 weights need bf16 autocast"):
        train.build_training(bf16)


@pytest.mark.parametrize("name", list(BACKBONES))
def test_lora_starts_as_the_loaded_transformer_and_merges_under_its_own_names(name):
    """B = 0: adapters change nothing at first; with random B the merged plain Linear layers give the adapted
    transformer's outputs, under the original key names, and the adapters are back after the block."""
    backbone = BACKBONES[name][0](0)
    transformer = backbone.transformer
    plain_keys = set(transformer.state_dict())
    fmt, (_, height, width) = backbone.latent, BACKBONES[name]
    n, h, w = fmt.num_latent_frames(FRAMES), height // fmt.spatial_factor, width // fmt.spatial_factor
    g = torch.Generator().manual_seed(0)
    args = (torch.randn(1, fmt.latent_channels, n, h, w, generator=g), torch.tensor([0.6]),
            torch.randn(1, fmt.latent_channels, 1, h, w, generator=g),
            torch.randn(1, fmt.camera_channels, n, h, w, generator=g))
    with torch.no_grad():
        text, mask = backbone.text_model.encode_text(["a dog runs"])
        base = backbone(*args, text, mask)
        count = add_lora(transformer, LoraSettings(rank=2, alpha=4), seed=1)
        assert count == len(lora_layers(transformer)) > 0
        assert torch.equal(backbone(*args, text, mask), base)  # B = 0
        for _, layer in lora_layers(transformer):
            layer.lora_B["default"].weight.normal_(0, 0.1, generator=g)
        adapted = backbone(*args, text, mask)
        with merged_lora(transformer):
            assert not lora_layers(transformer) and set(transformer.state_dict()) == plain_keys
            merged = backbone(*args, text, mask)
    assert lora_layers(transformer) and float((adapted - base).abs().max()) > 1e-3
    torch.testing.assert_close(merged, adapted, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="already has LoRA"):
        add_lora(transformer, LoraSettings(rank=2))
    other = BACKBONES[name][0](0).transformer
    with pytest.raises(ValueError, match="stage.lora.target_modules"):
        add_lora(other, LoraSettings(rank=2, target_modules=("no_such_layer",)))


@pytest.mark.parametrize("name", list(BACKBONES))
def test_flow_loss_is_the_backbones_velocity_error_with_the_empty_prompt_for_dropped_captions(data, name):
    """The diffusion objective through the backbone, recomputed by hand from the step generator's draws (caption
    dropout, σ from ``training_sigmas``, ε): a dropped caption is the backbone's unconditional input (velocity with
    text=None, the embedding of ""), and Wan's loss leaves out latent frame 0, which its velocity replaces by the
    photograph's latent."""
    make, height, width = BACKBONES[name]
    backbone = make(0)
    fmt = backbone.latent
    ldrm = LDRMConfig(latent_channels=fmt.latent_channels, vae_temporal=fmt.temporal_factor,
                      vae_spatial=fmt.spatial_factor, depth=1)
    config = BackboneModelConfig.for_backbone(backbone.kind, fmt, height=height, width=width, num_frames=FRAMES,
                                              ldrm=ldrm)
    model = BackboneModel(backbone, LDRM(ldrm), config)
    with torch.no_grad():  # a camera branch that matters
        backbone.camera_conv.camera_weight.normal_(0, 0.02, generator=torch.Generator().manual_seed(1))
    stage = dataclasses.replace(_stage(name, Path("unused"), data, Path("unused")), objectives=("diffusion",),
                                caption_dropout=1.0)
    clips = ClipDataset(data, ClipConfig(num_frames=FRAMES, height=height, width=width, plucker="raw"))
    batch = default_collate([clips[0], clips[1]])
    with torch.no_grad():
        flow = TrainingModule(model, stage)(batch, torch.Generator().manual_seed(5))["flow"]
        gen = torch.Generator().manual_seed(5)
        torch.rand(2, generator=gen)  # caption dropout (all dropped)
        x0 = backbone.encode_latents(batch["video"] * 2 - 1)
        sigma = backbone.training_sigmas(2, gen)
        noise = torch.randn(x0.shape, generator=gen)
        s = sigma[:, None, None, None, None]
        plucker = pack_plucker(batch["plucker"], fmt.temporal_factor, fmt.spatial_factor)
        v = backbone((1 - s) * x0 + s * noise, sigma, x0[:, :, :1], plucker, None, None)
    first = 1 if name == "wan" else 0
    expected = ((v - (noise - x0))[:, :, first:] ** 2).mean()
    torch.testing.assert_close(flow, expected, rtol=1e-5, atol=1e-6)
    assert first == 0 or abs(float(flow) - float(((v - (noise - x0)) ** 2).mean())) > 1e-4


@pytest.mark.parametrize("name", list(BACKBONES))
def test_stage1_forward_on_simulated_cuda_gives_the_cpus_losses(data, name, tmp_path, cpu_tile_path):
    """Stage 1 of a backbone (LoRA, diffusion and rendering objectives) on "cuda" (tests/simulated_cuda.py, on a
    CPU-only machine): the forward of a static and a dynamic clip gives the CPU's losses, both rendering through
    the PyTorch tile path. The backward is not simulated."""
    stage = _stage(name, _init_folder(name, tmp_path / "init", camera_std=0.02), data, tmp_path / "run")
    clips = ClipDataset(data, ClipConfig(num_frames=FRAMES, height=stage.height, width=stage.width, plucker="raw"))
    batch = default_collate([clips[0], clips[2]])

    def losses(device):
        module = TrainingModule(load_backbone_model(stage), stage).train().to(device)
        with torch.no_grad():
            out = module({k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()},
                         torch.Generator().manual_seed(5))
            assert {v.device.type for v in out.values()} == {torch.device(device).type}
            return {k: float(v) for k, v in out.items()}

    ref = losses("cpu")
    with simulated_cuda():
        got = losses("cuda")
    assert set(ref) >= {"flow", "photo"} and got == pytest.approx(ref, rel=1e-5, abs=1e-7)


def test_rays_are_packed_for_the_backbones_latent_grid(data):
    """Wan's 4×16×16 grid: the dataset's 4×8×8 ``plucker_packed`` does not fit, so the rays are packed from the raw
    rays or, without them, from the cameras; CogVideoX's 4×8×8 grid takes the dataset's packing as it is."""
    clips = ClipDataset(data, ClipConfig(num_frames=FRAMES, height=64, width=32, plucker="both"))
    batch = default_collate([clips[0]])
    wan = tiny_wan(0).latent
    expected = pack_plucker(plucker_rays(batch["viewmats"][0], batch["Ks"][0], 32, 64)[None], 4, 16)
    grid = (3, 4, 2)
    cameras_only = {k: v for k, v in batch.items() if k != "plucker"}
    assert torch.equal(TrainingModule._plucker(cameras_only, wan, grid), expected)
    # the dataset's raw rays: the same function on its float64 cameras, then float32
    torch.testing.assert_close(TrainingModule._plucker(batch, wan, grid), expected, rtol=0, atol=1e-6)
    cog = tiny_cogvideox(0).latent
    assert TrainingModule._plucker(batch, cog, (3, 8, 4)) is batch["plucker_packed"]
