"""Training stages on devices (training/train.py, trainer.py, objectives.py on a tiny generated dataset): the
``--device`` flag and ``trainer.device`` (errors are one ``train: error:`` line, exit code 2), gradient
checkpointing of the DiT (the same losses as without), FSDP2 on two gloo ranks through ``python -m
training.train`` (per-block sharding, EMA, the final model gathered), ``torchrun`` with one process (DDP and FSDP
through gloo, and NCCL on a GPU), and, on a GPU, the CPU's losses on CUDA."""
import csv
import dataclasses
import functools
import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import yaml
from _trainer_toy import fsdp_stage_script, run_two_ranks
from helpers import tiny_model

import training.objectives as objectives
from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.render import rasterize
from models.bundle import Diff4SplatModel, load_config
from training.checkpoint import latest_checkpoint, load_checkpoint
from training.stage_config import StageConfig
from training.train import build_training, calibrate_latent_scaling, main
from training.trainer import TrainerConfig

ROOT = Path(__file__).resolve().parent.parent
SIZE, FRAMES = 32, 9
STAGES = {
    "vae": dict(train=("vae",), objectives=("vae",), scenes="all"),
    "stage1": dict(train=("dit", "ldrm"), objectives=("diffusion", "reconstruction"), scenes="static"),
    "stage3": dict(train=("dit", "ldrm", "ldrm.deformation"), objectives=("diffusion", "reconstruction"),
                   scenes="all", deformation=True, motion=True),
}
"""Objective sets of the shipped stages, for the tiny model at 32² and 9 frames."""


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two static and two dynamic scenes, one camera, 9 frames at 32² (one clip each)."""
    root = tmp_path_factory.mktemp("device_data")
    for i, ratio in enumerate((1.0, 1.0, 0.0, 0.0)):
        generate_scene(root, i, seed=31, size=SIZE, frames=FRAMES, cameras=1, static_ratio=ratio)
    return root


def _stage(name: str, data: Path, run_dir: Path, **trainer) -> StageConfig:
    """Stage ``name`` of the tiny model (random, seed 0) on ``data``: batch 1, 3 steps, no progress bar."""
    cfg = dict(run_dir=str(run_dir), total_steps=3, batch_size=1, lr=1e-3, warmup_steps=1, checkpoint_every=100,
               progress=False, seed=0)
    return StageConfig(name=name, model_config="tiny", init_from=None, data=str(data), height=SIZE, width=SIZE,
                       num_frames=FRAMES, render_frames=2, trainer=TrainerConfig(**{**cfg, **trainer}),
                       **STAGES[name])


def _yaml(stage: StageConfig, path: Path) -> Path:
    path.write_text(yaml.safe_dump(json.loads(json.dumps(dataclasses.asdict(stage)))))  # tuples as lists
    return path


def _metrics(run_dir: Path) -> dict[int, dict[str, float]]:
    """Loss columns of metrics.csv by step (the timing column left out)."""
    rows = csv.DictReader(open(Path(run_dir) / "metrics.csv"))
    return {int(r["step"]): {k: float(v) for k, v in r.items() if k not in ("step", "epoch", "seconds", "skipped")}
            for r in rows if r["skipped"] == "0"}


def _error(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("train: error:"), lines
    return lines[0]


# ------------------------------------------------------------------------------------------------ devices
def test_a_device_this_machine_lacks_is_one_error_line(data, tmp_path, capsys):
    """--device and trainer.device are checked before any model is built or file written."""
    cfg = _yaml(_stage("vae", data, tmp_path / "run"), tmp_path / "stage.yaml")
    assert main(["--config", str(cfg), "--device", "cuda:99", "--quiet"]) == 2
    assert "--device: cuda:99 is not available" in _error(capsys)
    assert main(["--config", str(cfg), "--device", "gpu", "--quiet"]) == 2
    assert "--device: 'gpu' is not a torch device" in _error(capsys)
    cfg = _yaml(_stage("vae", data, tmp_path / "run", device="cuda:99"), tmp_path / "stage.yaml")
    assert main(["--config", str(cfg), "--quiet"]) == 2
    assert "trainer.device: cuda:99 is not available" in _error(capsys)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_the_device_flag_overrides_the_yaml(data, tmp_path, capsys):
    cfg = _yaml(_stage("vae", data, tmp_path / "run", device="cuda:99", total_steps=1), tmp_path / "stage.yaml")
    assert main(["--config", str(cfg), "--device", "cpu", "--quiet"]) == 0, capsys.readouterr().err
    assert "steps on cpu →" in capsys.readouterr().err
    assert (tmp_path / "run" / "model" / "config.json").is_file()
    meta = json.loads((latest_checkpoint(tmp_path / "run") / "meta.json").read_text())
    assert meta["trainer"]["device"] == "cpu" and meta["trainer"]["bf16"] is None


# ------------------------------------------------------------------------------------------------ memory
@pytest.mark.slow
def test_gradient_checkpointing_trains_a_stage_exactly_as_without(data, tmp_path):
    """trainer.gradient_checkpointing recomputes the DiT's blocks in the backward pass: the same losses and
    gradient norms, step for step, and the same weights."""
    runs = {}
    for on in (False, True):
        trainer, model, _ = build_training(_stage("stage1", data, tmp_path / str(on), total_steps=2,
                                                  gradient_checkpointing=on, device="cpu"))
        assert model.dit.gradient_checkpointing is on
        trainer.fit()
        runs[on] = _metrics(tmp_path / str(on)), model.dit.state_dict()
    assert runs[True][0] == runs[False][0] and len(runs[True][0]) == 2
    assert all(torch.equal(v, runs[False][1][k]) for k, v in runs[True][1].items())


@pytest.mark.slow
def test_fsdp_on_two_gloo_ranks_trains_a_stage_block_by_block(data, tmp_path):
    """``torchrun -m training.train --strategy fsdp`` on two CPU processes: the DiT, LDRM and text-encoder blocks
    are FSDP units of their own, the stage (diffusion, rendering and motion losses; gradient checkpointing; EMA)
    trains, and rank 0 writes the full model, whose weights are the checkpoint's EMA."""
    stage = _stage("stage3", data, tmp_path / "run", total_steps=2, ema_decay=0.9, gradient_checkpointing=True)
    cfg = _yaml(stage, tmp_path / "stage.yaml")
    script = fsdp_stage_script(cfg, """
        units = [*model.dit.blocks, *model.ldrm.blocks, *model.text_encoder.blocks]
        assert trainer.sharded and all(isinstance(b, FSDPModule) for b in units)
        assert not isinstance(model.vae, FSDPModule) and model.dit.gradient_checkpointing
    """)
    run_two_ranks(script, timeout=300, fresh=(tmp_path / "run",))
    rows = _metrics(tmp_path / "run")
    assert sorted(rows) == [1, 2] and all(torch.isfinite(torch.tensor(list(r.values()))).all() for r in rows.values())
    assert {"flow", "photo", "motion", "displacement"} <= set(rows[1])
    trained = Diff4SplatModel.from_pretrained(tmp_path / "run" / "model")
    init = Diff4SplatModel.random(load_config("tiny"), seed=0).state_dict()
    _, _, ema = load_checkpoint(latest_checkpoint(tmp_path / "run"))
    for k, v in trained.state_dict().items():
        if f"model.{k}" in ema:  # trainable: the gathered EMA, whole tensors
            assert torch.equal(v, ema[f"model.{k}"]), k
        else:  # frozen: as initialised
            assert torch.equal(v, init[k]), k
    assert any(not torch.equal(v, init[k]) for k, v in trained.state_dict().items() if k.startswith("dit.blocks."))


def _torchrun_one_process(cfg: Path, device: torch.device, strategy: str, tmp_path: Path) -> None:
    """``torchrun --standalone --nproc_per_node 1`` of ``training.train`` on ``cfg``; asserts the run joined a group
    of one on the device's backend (NCCL on CUDA, gloo on the CPU), trained through the strategy's wrapper and
    exited 0."""
    script = tmp_path / "rank.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        import torch.distributed as dist
        from torch.distributed.fsdp import FSDPModule
        from torch.nn.parallel import DistributedDataParallel
        import training.train as train
        built = []
        real = train.build_training
        train.build_training = lambda stage, seed=None: built.append((real(stage, seed), dist.get_backend())) \\
            or built[-1][0]
        code = train.main(["--config", {str(cfg)!r}, "--strategy", {strategy!r}, "--device", {str(device)!r},
                           "--quiet"])
        (trainer, _, _), backend = built[0]
        assert trainer.distributed and trainer.world == 1, (trainer.distributed, trainer.world)
        assert backend == {"nccl" if device.type == "cuda" else "gloo"!r}, backend
        assert isinstance(trainer.model, {"FSDPModule" if strategy == "fsdp" else "DistributedDataParallel"})
        sys.exit(code)
    """))
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "1",
                           str(script)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]


@pytest.mark.slow
@pytest.mark.real_gpu  # a child process: not on the simulated CUDA device
@pytest.mark.parametrize("strategy", ["ddp", "fsdp"])
def test_torchrun_with_one_process_trains_through_the_strategy(data, tmp_path, device, strategy):
    """``torchrun --nproc_per_node 1`` joins a process group of one (NCCL on CUDA, gloo on the CPU: the path
    several GPUs take, on a machine with one) and trains through DDP or FSDP2, with the plain run's losses in float32
    (one rank: the gradient all-reduce averages one gradient)."""
    kw = dict(device=str(device), bf16=False, tf32=False)
    plain, _, _ = build_training(_stage("stage1", data, tmp_path / "plain", **kw))
    plain.fit()
    _torchrun_one_process(_yaml(_stage("stage1", data, tmp_path / "run", **kw), tmp_path / "stage.yaml"), device,
                          strategy, tmp_path)
    got, expected = _metrics(tmp_path / "run"), _metrics(tmp_path / "plain")
    assert sorted(got) == sorted(expected) == [1, 2, 3]
    for step, losses in expected.items():
        assert got[step] == pytest.approx(losses, rel=1e-4, abs=1e-6), step
    assert (tmp_path / "run" / "model").is_dir()


@pytest.mark.slow
@pytest.mark.cuda
@pytest.mark.real_gpu  # a child process: not on the simulated CUDA device
def test_torchrun_fsdp_on_cuda_trains_with_the_gpu_defaults(data, tmp_path):
    """The GPU defaults under FSDP2 (bf16 parameters in the blocks, float32 reductions; TF32): three finite steps
    through NCCL, the model gathered and written."""
    _torchrun_one_process(_yaml(_stage("stage3", data, tmp_path / "run", device="cuda"), tmp_path / "stage.yaml"),
                          torch.device("cuda"), "fsdp", tmp_path)
    rows = _metrics(tmp_path / "run")
    assert sorted(rows) == [1, 2, 3] and all(math.isfinite(v) for r in rows.values() for v in r.values())
    assert Diff4SplatModel.from_pretrained(tmp_path / "run" / "model") is not None


# ------------------------------------------------------------------------------------------------ CUDA
@pytest.mark.cuda
@pytest.mark.parametrize("name", list(STAGES))
def test_a_stage_on_cuda_gives_the_cpu_losses_in_float32(data, tmp_path, name, monkeypatch):
    """bf16 and TF32 off: the first steps' losses on CUDA are the CPU's to float32 rounding (the step generator's
    draws are the same numbers on both devices). Both devices render with the PyTorch tile path: gsplat, used for
    CUDA tensors when installed, differs from it by design (diff4splat/render/rasterize.py, rasterize_gsplat)."""
    monkeypatch.setattr(objectives, "rasterize", functools.partial(rasterize, compositor="torch"))
    flags = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    losses = {}
    try:
        for device in ("cpu", "cuda"):
            trainer, _, _ = build_training(_stage(name, data, tmp_path / device, device=device, bf16=False,
                                                  tf32=False))
            assert trainer.device.type == device and trainer.bf16 is False
            trainer.fit()
            losses[device] = _metrics(tmp_path / device)
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags
    assert sorted(losses["cuda"]) == sorted(losses["cpu"]) == [1, 2, 3]
    for step, cpu in losses["cpu"].items():
        assert losses["cuda"][step].keys() == cpu.keys()
        assert losses["cuda"][step] == pytest.approx(cpu, rel=1e-4, abs=1e-6), step


@pytest.mark.cuda
def test_latent_scaling_is_calibrated_on_the_vaes_device(data):
    """After a VAE stage on CUDA the model is on the GPU and the clips on the CPU: the clips go to the VAE."""
    clips = ClipDataset(data, ClipConfig(num_frames=FRAMES, height=SIZE, width=SIZE, scenes="all", plucker="packed"))
    expected = calibrate_latent_scaling(tiny_model(seed=3), clips, num_clips=2)
    got = calibrate_latent_scaling(tiny_model(seed=3).to("cuda"), clips, num_clips=2)
    assert got == pytest.approx(expected, rel=1e-2, abs=1e-3)  # cuDNN may convolve in TF32
