"""Tests of training/stage_config.py: the shipped stage configs follow the paper's progressive schedule,
apply_freezing leaves exactly the listed networks trainable, and bad stage YAML fails with one ValueError."""
from pathlib import Path

import pytest

from models.bundle import Diff4SplatModel, load_config
from training.stage_config import MODULES, STAGE_CONFIG_DIR, StageConfig, apply_freezing, load_stage

CONFIGS = STAGE_CONFIG_DIR
STAGES = ("vae", "stage1", "stage2", "stage3")


@pytest.fixture(scope="module")
def shipped():
    return {name: load_stage(CONFIGS / f"train_{name}.yaml") for name in STAGES}


@pytest.fixture(scope="module")
def model():
    return Diff4SplatModel.random(load_config("tiny"), seed=0)


def _run_model(stage: StageConfig) -> Path:
    return Path(stage.trainer.run_dir) / "model"


def test_every_shipped_stage_loads_and_fits_its_model(shipped):
    for name, st in shipped.items():
        assert st.name == name
        assert (st.num_frames - 1) % 4 == 0, name  # T = 1 + 4k (causal VAE grouping)
        assert 1 <= st.render_frames <= st.num_frames
        cfg = load_config(st.model_config)
        unit = cfg.vae.spatial_factor * max(cfg.dit.patch_size[1], cfg.ldrm.patch_size)
        assert st.height % unit == 0 and st.width % unit == 0, name  # DiT/LDRM patches tile the latents
    assert len({st.trainer.run_dir for st in shipped.values()}) == len(STAGES)  # no stage overwrites another


def test_vae_stage_trains_only_the_vae_from_scratch(shipped):
    st = shipped["vae"]
    assert st.train == ("vae",) and st.objectives == ("vae",)
    assert st.init_from is None and st.scenes == "all"


def test_stage1_is_low_resolution_static_geometry_with_frozen_deformation(shipped):
    st, model_cfg = shipped["stage1"], load_config(shipped["stage1"].model_config)
    assert (st.height, st.width) == (32, 32) and st.height < model_cfg.height
    assert set(st.train) == {"dit", "ldrm"}  # ldrm without ldrm.deformation: deformation frozen
    assert set(st.objectives) == {"diffusion", "reconstruction"}
    assert st.scenes == "static" and not st.deformation and not st.motion
    assert Path(st.init_from) == _run_model(shipped["vae"])


def test_stage2_is_static_refinement_at_model_resolution(shipped):
    st, model_cfg = shipped["stage2"], load_config(shipped["stage2"].model_config)
    assert (st.height, st.width) == (model_cfg.height, model_cfg.width) == (64, 64)
    assert set(st.train) == {"dit", "ldrm"}
    assert st.scenes == "static" and not st.deformation and not st.motion
    assert Path(st.init_from) == _run_model(shipped["stage1"])


def test_stage3_is_dynamic_fine_tuning_with_motion(shipped):
    st, model_cfg = shipped["stage3"], load_config(shipped["stage3"].model_config)
    assert (st.height, st.width) == (model_cfg.height, model_cfg.width)
    assert set(st.train) == {"dit", "ldrm", "ldrm.deformation"}
    assert st.scenes == "all" and st.deformation and st.motion
    assert Path(st.init_from) == _run_model(shipped["stage2"])
    for name in ("stage1", "stage2", "stage3"):  # the VAE and the text encoder stay frozen after stage 0
        assert not {"vae", "text_encoder"} & set(shipped[name].train), name


def test_load_stage_overrides_merge_into_the_yaml():
    st = load_stage(CONFIGS / "train_vae.yaml", data="elsewhere", init_from=None,
                    trainer={"total_steps": 2, "run_dir": "tmp_run"})
    assert st.data == "elsewhere" and st.init_from is None  # None leaves the YAML value
    assert (st.trainer.total_steps, st.trainer.run_dir) == (2, "tmp_run")
    assert (st.trainer.batch_size, st.trainer.lr) == (4, 0.002)  # other trainer fields kept from the YAML
    assert st.kl_weight == 0.001 and isinstance(st.train, tuple)


def _owner(name: str) -> str:
    """The MODULES entry that controls parameter ``name`` of a Diff4SplatModel."""
    return "ldrm.deformation" if name.startswith("ldrm.deformation.") else name.split(".")[0]


@pytest.mark.parametrize("train", [("vae",), ("dit", "ldrm"), ("dit", "ldrm", "ldrm.deformation"),
                                   ("ldrm.deformation",), ("text_encoder", "dit")])
def test_apply_freezing_leaves_exactly_the_listed_modules_trainable(model, train):
    apply_freezing(model, MODULES)  # a previous stage left everything trainable: must be reset
    counts = apply_freezing(model, train)
    for name, p in model.named_parameters():
        assert p.requires_grad == (_owner(name) in train), name
    trainable = {n: p for n, p in model.named_parameters() if p.requires_grad}
    assert set(counts) == set(train)
    for module in train:
        expected = sum(p.numel() for n, p in trainable.items() if n.startswith(module + "."))
        assert counts[module] == expected > 0, module
    deformation = sum(p.numel() for p in model.ldrm.deformation.parameters())
    if train == ("dit", "ldrm"):  # the LDRM trains with its deformation network frozen
        assert counts["ldrm"] == model.parameter_counts()["ldrm"] - deformation
        assert counts["dit"] == model.parameter_counts()["dit"]
    if "ldrm.deformation" in train:
        assert counts["ldrm.deformation"] == deformation


def test_a_new_head_trains_alone_and_absent_parts_train_nothing(model):
    """``ldrm.head`` (and ``ldrm.image_branch``) alone: only the head's parameters train — the LDRM's blocks and
    its deformation network, which reads their features, stay as they are; a model without an image branch counts
    0 for it."""
    counts = apply_freezing(model, ("ldrm.head", "ldrm.image_branch"))
    head = {f"ldrm.head.{n}" for n, _ in model.ldrm.head.named_parameters()}
    assert {n for n, p in model.named_parameters() if p.requires_grad} == head
    assert counts["ldrm.head"] == sum(p.numel() for p in model.ldrm.head.parameters()) > 0
    assert counts["ldrm.image_branch"] == (0 if model.ldrm.image_branch is None else
                                           sum(p.numel() for p in model.ldrm.image_branch.parameters()))


BASE = "name: s\ntrain: [dit, ldrm]\nobjectives: [diffusion, reconstruction]\nnum_frames: 9\n"


@pytest.mark.parametrize("bad, field", [
    ("train: [dit, unet]", "stage.train"),
    ("objectives: [diffusion, gan]", "stage.objectives"),
    ("scenes: moving", "stage.scenes"),
    ("motion: true\ndeformation: false", "stage.motion"),
    ("render_frames: 0", "stage.render_frames"),
    ("render_frames: 10", "stage.render_frames"),
    ("caption_dropout: 1.5", "stage.caption_dropout"),
    ("learning_rate: 0.1", "'learning_rate'"),
    ("trainer: {total_steps: 0}", "trainer.total_steps"),
    ("trainer: {lr: 0}", "trainer.lr"),
    ("trainer: {optimiser: sgd}", "'optimiser'"),
    ("weights: {rgb: 1.0, colour: 2.0}", "'colour'"),
    ("scene: photo", "stage.scene"),
    ("objectives: [distill]", "stage.teacher"),  # distill without a teacher
    ("teacher: runs/previous/model", "stage.teacher"),  # a teacher without distill
    ("distill_sigma: -1", "stage.distill_sigma"),
])
def test_bad_stage_yaml_raises_value_error_naming_the_field(tmp_path, bad, field):
    good = tmp_path / "good.yaml"
    good.write_text(BASE)
    assert load_stage(good).num_frames == 9  # the base is valid: the error comes from the bad line
    path = tmp_path / "bad.yaml"
    path.write_text(BASE + bad + "\n")
    with pytest.raises(ValueError) as err:
        load_stage(path)
    assert field in str(err.value)


def test_missing_stage_file_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        load_stage(tmp_path / "nope.yaml")
