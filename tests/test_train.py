"""Tests of training/train.py: the VAE stage and a stage-1 stage run end to end through ``main`` on a tiny
generated dataset and chain through ``--init-from``; the VAE's latent scaling is calibrated (closed form);
bad input is one ``train: error:`` line and exit code 2. The runs are on the CPU (``--device cpu``) on every machine:
the closed-form checks compare with CPU computations (tests/test_train_devices.py covers CUDA)."""
from pathlib import Path

import pytest
import torch
import yaml
from helpers import tiny_model

from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from models.bundle import Diff4SplatModel, load_config
from training.checkpoint import save_checkpoint
from training.stage_config import STAGE_CONFIG_DIR, load_stage
from training.train import build_training, calibrate_latent_scaling, main

CONFIGS = STAGE_CONFIG_DIR
SIZE, FRAMES = 32, 9


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two static scenes (stages 1–2 train on them) and one dynamic scene; one camera, 9 frames."""
    root = tmp_path_factory.mktemp("train_data")
    for i, ratio in enumerate((1.0, 1.0, 0.0)):
        generate_scene(root, i, seed=21, size=SIZE, frames=FRAMES, cameras=1, static_ratio=ratio)
    return root


def _clips(root, scenes="all"):
    """The clips build_training samples from ``root`` at the test size."""
    return ClipDataset(root, ClipConfig(num_frames=FRAMES, height=SIZE, width=SIZE, scenes=scenes, plucker="packed"))


def _stage_yaml(folder: Path, name: str, trainer: dict | None = None, **fields) -> Path:
    """The shipped ``configs/train_<name>.yaml`` with a few fields replaced (a smaller clip and batch)."""
    data = yaml.safe_load((CONFIGS / f"train_{name}.yaml").read_text())
    data.update(fields)
    data["trainer"] = {**data.get("trainer", {}), **(trainer or {})}
    path = folder / f"train_{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _latents(model, clips) -> torch.Tensor:
    with torch.no_grad():
        return torch.cat([model.vae.encode_latents(clips[i]["video"][None] * 2 - 1).flatten()
                          for i in range(len(clips))])


def _two_steps_from(init: Path, cfg: Path, data: Path, run: Path, capsys):
    """Two CPU steps of stage ``cfg`` from the model folder ``init`` through ``main``: (model before, model after,
    names of the parameters that changed)."""
    code = main(["--config", str(cfg), "--data", str(data), "--init-from", str(init),
                 "--run-dir", str(run), "--steps", "2", "--quiet", "--device", "cpu"])
    assert code == 0, capsys.readouterr().err
    before, after = Diff4SplatModel.from_pretrained(init), Diff4SplatModel.from_pretrained(run / "model")
    old = before.state_dict()
    return before, after, {k for k, v in after.state_dict().items() if not torch.equal(v, old[k])}


@pytest.fixture(scope="module")
def vae_run(data, tmp_path_factory):
    """The VAE stage (shipped config at 32², batch 2) for 2 steps through ``main``."""
    tmp = tmp_path_factory.mktemp("vae_stage")
    cfg = _stage_yaml(tmp, "vae", height=SIZE, width=SIZE, trainer={"batch_size": 2, "checkpoint_every": 100})
    run = tmp / "run"
    code = main(["--config", str(cfg), "--data", str(data), "--run-dir", str(run), "--steps", "2", "--quiet",
                 "--device", "cpu"])
    return code, run


@pytest.mark.slow
def test_vae_stage_trains_only_the_vae_and_calibrates_its_latents(vae_run, data):
    code, run = vae_run
    assert code == 0 and (run / "model" / "config.json").is_file()
    rows = (run / "metrics.csv").read_text().splitlines()
    assert len(rows) == 3 and "vae_l1" in rows[0]  # header + 2 steps
    trained = Diff4SplatModel.from_pretrained(run / "model")
    init = Diff4SplatModel.random(load_config("tiny"), seed=0)  # the stage's seeded start (trainer.seed 0)
    assert any(not torch.equal(v, init.vae.state_dict()[k]) for k, v in trained.vae.state_dict().items())
    for net in ("text_encoder", "dit", "ldrm"):
        init_state = getattr(init, net).state_dict()
        assert all(torch.equal(v, init_state[k]) for k, v in getattr(trained, net).state_dict().items()), net
    # the saved VAE maps the training clips to zero-mean, unit-variance DiT latents
    z = _latents(trained, _clips(data))
    assert float(z.mean()) == pytest.approx(0.0, abs=1e-4)
    assert float(z.std()) == pytest.approx(1.0, abs=1e-4)
    assert trained.config.vae == trained.vae.config


@pytest.mark.slow
def test_stage1_from_the_vae_run_keeps_the_vae_frozen_and_trains_dit_and_ldrm(vae_run, data, tmp_path, capsys):
    code, vae = vae_run
    assert code == 0
    cfg = _stage_yaml(tmp_path, "stage1", num_frames=FRAMES, render_frames=2,
                      trainer={"batch_size": 2, "checkpoint_every": 100})
    before, after, changed = _two_steps_from(vae / "model", cfg, data, tmp_path / "run", capsys)
    frozen = [k for k in before.state_dict() if k.startswith(("vae.", "text_encoder.", "ldrm.deformation."))]
    assert frozen and not changed & set(frozen)  # VAE, text encoder and deformation bit-identical
    assert any(k.startswith("dit.") for k in changed)
    assert any(k.startswith("ldrm.") for k in changed)
    assert after.config.vae == before.config.vae  # the latent scaling travels with the model, unchanged
    assert (before.config.vae.scaling_factor, before.config.vae.shift_factor) != (1.0, 0.0)


@pytest.mark.slow
def test_a_decoder_stage_trains_the_vae_decoder_alone_and_keeps_the_latents(vae_run, data, tmp_path, capsys):
    """``train: [vae.decoder]`` (the shipped base decoder stage at 32², from the VAE run's model): the decoder
    changes; the encoder, the other networks and the latent scaling stay bit-identical (no calibration after a
    decoder-only stage), so every latent the DiT and the LDRM were trained on is the same."""
    code, vae = vae_run
    assert code == 0
    cfg = _stage_yaml(tmp_path, "base_vae_decoder", height=SIZE, width=SIZE, num_frames=FRAMES,
                      trainer={"batch_size": 2, "checkpoint_every": 100})
    before, after, changed = _two_steps_from(vae / "model", cfg, data, tmp_path / "run", capsys)
    assert changed and all(k.startswith("vae.decoder.") for k in changed)
    assert after.config.vae == before.config.vae
    clips = _clips(data)
    assert torch.equal(_latents(after, clips), _latents(before, clips))


@pytest.mark.slow
def test_build_training_optimises_exactly_the_stage_modules_on_its_scenes(vae_run, data, tmp_path):
    stage = load_stage(_stage_yaml(tmp_path, "stage1", num_frames=FRAMES), data=str(data),
                       init_from=str(vae_run[1] / "model"),
                       trainer={"run_dir": str(tmp_path / "run"), "device": "cpu", "batch_size": 2})
    trainer, model, counts = build_training(stage)
    optimised = {id(p) for group in trainer.optimizer.param_groups for p in group["params"]}
    for name, p in model.named_parameters():
        expected = name.startswith(("dit.", "ldrm.")) and not name.startswith("ldrm.deformation.")
        assert (id(p) in optimised) == p.requires_grad == expected, name
    trainable = [(k, p.numel()) for k, p in model.named_parameters() if p.requires_grad]
    assert counts == {n: sum(c for k, c in trainable if k.startswith(n + ".")) for n in ("dit", "ldrm")}
    ds = trainer.dataset  # stage 1 samples the static scenes only, at the stage's clip size
    assert len(ds) == 2 and not any(ds.metas[item.scene].dynamic for item in ds.items)
    assert (ds.config.height, ds.config.width, ds.config.num_frames, ds.config.plucker) == (32, 32, FRAMES, "packed")
    assert model.config.vae == Diff4SplatModel.from_pretrained(vae_run[1] / "model").config.vae


@pytest.mark.slow
def test_calibrate_latent_scaling_standardises_the_calibration_latents(data):
    model = tiny_model(seed=3)
    model.vae.train()
    clips = _clips(data)
    a, b = calibrate_latent_scaling(model, clips, num_clips=2)
    assert (a, b) == (model.config.vae.scaling_factor, model.config.vae.shift_factor)
    assert (a, b) == (model.vae.config.scaling_factor, model.vae.config.shift_factor)
    assert model.vae.training  # the mode is restored
    first_two = [clips[0], clips[1]]
    z = _latents(model, first_two)
    assert float(z.mean()) == pytest.approx(0.0, abs=1e-4)
    assert float(z.std()) == pytest.approx(1.0, abs=1e-4)
    # it reads the raw posterior means, not the already scaled latents: calibrating again is a no-op
    assert calibrate_latent_scaling(model, clips, num_clips=2) == pytest.approx((a, b), rel=1e-6)
    # only the first num_clips clips count
    assert calibrate_latent_scaling(model, clips, num_clips=3) != pytest.approx((a, b), rel=1e-4)


def test_calibrate_latent_scaling_of_an_empty_dataset_raises():
    with pytest.raises(ValueError, match="dataset"):
        calibrate_latent_scaling(tiny_model(), [])


def _error(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("train: error:"), lines
    return lines[0]


def test_missing_config_file_is_exit_code_2(tmp_path, capsys):
    assert main(["--config", str(tmp_path / "missing.yaml"), "--quiet"]) == 2
    assert "missing.yaml" in _error(capsys)


def test_missing_data_folder_is_exit_code_2(tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["--config", str(CONFIGS / "train_vae.yaml"), "--data", str(tmp_path / "nodata"),
                 "--run-dir", str(run), "--steps", "2", "--quiet"])
    assert code == 2
    line = _error(capsys)
    assert "data" in line and "nodata" in line
    assert not run.exists()  # nothing was written


@pytest.mark.parametrize("fields, needle", [
    ({"train": ["dit", "unet"]}, "stage.train"),
    ({"height": 36, "width": 36}, "height"),  # the packed Plücker rays need multiples of 8
    ({"height": 40, "width": 40}, "multiple of 16"),  # the tiny DiT's 2×2 patches on 8×8 latents need 16
    ({"init_from": "no_such_model"}, "init_from"),
    # each passed the check and failed at step 1, or trained with a maximised loss
    ({"flow_shift": 0}, "stage.flow_shift must be > 0"),
    ({"kl_weight": -1e-3}, "stage.kl_weight must be ≥ 0"),
    ({"weights": {"smooth": -1e-3}}, "stage.weights.smooth must be a finite number ≥ 0"),
    ({"kl_weight": "tiny"}, "field 'kl_weight' of StageConfig must be a number, got 'tiny'"),
])
def test_bad_stage_values_are_exit_code_2(data, tmp_path, capsys, fields, needle):
    cfg = _stage_yaml(tmp_path, "vae", **fields)
    assert main(["--config", str(cfg), "--data", str(data), "--run-dir", str(tmp_path / "run"), "--quiet"]) == 2
    assert needle in _error(capsys)


def _listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_a_run_folder_is_never_the_data_a_user_folder_or_a_silent_fresh_start(data, tmp_path, capsys):
    """The run folder is written step by step, so it is checked before anything is built: never the dataset (a run
    written into it failed `data_prep validate`), inside it, or a folder of other files; an earlier run continues
    only with --resume (without it, its metrics and checkpoints would mix with a new run's), and --resume without a
    checkpoint is an error (it trained from step 0 without a word). One line, exit 2, nothing written."""
    cfg = _stage_yaml(tmp_path, "vae", height=SIZE, width=SIZE, trainer={"batch_size": 2})
    user = tmp_path / "notes"
    user.mkdir()
    (user / "notes.txt").write_text("mine\n")
    run = tmp_path / "earlier"  # what an earlier run leaves (its metrics.csv; checkpoints/ and model/ likewise)
    run.mkdir()
    (run / "metrics.csv").write_text("step,loss\n1,0.5\n")
    resumable = tmp_path / "stopped"  # an earlier run with a checkpoint
    save_checkpoint(resumable, 1, {"w": torch.zeros(1)}, {"step": 1}, {})
    cases = [(data, [], "input"), (data / "runs" / "a", [], "is inside input"), (user, [], "not a training run"),
             (resumable, [], "holds an earlier run; pass --resume to continue it"),
             (run, [], "holds an earlier run; it has no checkpoint to resume from: delete it, or choose a new"),
             (run, ["--resume"], "--resume: no checkpoint in"),
             (tmp_path / "new", ["--resume"], "--resume: no checkpoint in")]
    for folder, extra, needle in cases:
        before = {p: _listing(p) for p in (data, user, run, resumable)}
        code = main(["--config", str(cfg), "--data", str(data), "--run-dir", str(folder), "--steps", "1", "--quiet",
                     "--device", "cpu", *extra])
        assert code == 2 and needle in _error(capsys), folder
        assert {p: _listing(p) for p in (data, user, run, resumable)} == before and not (tmp_path / "new").exists()


def test_a_dataset_smaller_than_one_batch_writes_nothing(data, tmp_path, capsys):
    cfg = _stage_yaml(tmp_path, "vae", height=SIZE, width=SIZE, trainer={"batch_size": 4})
    run = tmp_path / "run"
    assert main(["--config", str(cfg), "--data", str(data), "--run-dir", str(run), "--quiet", "--device", "cpu"]) == 2
    assert "dataset of 3 items is smaller than one batch (4 × 1 processes)" in _error(capsys)
    assert not run.exists()
    # a stage that keeps only static scenes names its filter, the likely cause (two of three scenes are static)
    cfg = _stage_yaml(tmp_path, "vae", height=SIZE, width=SIZE, scenes="static", trainer={"batch_size": 4})
    assert main(["--config", str(cfg), "--data", str(data), "--run-dir", str(run), "--quiet", "--device", "cpu"]) == 2
    assert (f"data: 2 of the 3 scenes in {data} are static (stage.scenes: static), fewer than one batch of 4: make "
            "more static scenes (data_prep synth --static-ratio) or lower trainer.batch_size") in _error(capsys)
    assert not run.exists()
