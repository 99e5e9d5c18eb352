import dataclasses
import inspect

import pytest
import torch

from diff4splat.pipeline import Diff4SplatPipeline, load_model
from models.bundle import (
    CONFIG_DIR,
    DEFAULT_CONFIG,
    WEIGHTS_DIR,
    Diff4SplatConfig,
    Diff4SplatModel,
    config_names,
    load_config,
)
from models.pretrained import count_parameters


@pytest.mark.parametrize("name", ["tiny", "small", "paper"])
def test_every_shipped_config_loads_and_fits_together(name):
    cfg = load_config(name)
    assert cfg.name == name
    cfg.validate()


@pytest.mark.slow
def test_paper_config_on_meta_device_reports_parameter_counts():
    with torch.device("meta"):
        model = Diff4SplatModel(load_config("paper"))
    counts = model.parameter_counts()
    print("paper parameter counts:", counts)
    assert counts["total"] == sum(v for k, v in counts.items() if k != "total") == count_parameters(model)
    # T5-v1.1-XXL encoder size is published: 4,762,310,656 parameters (embeddings included)
    assert counts["text_encoder"] == 4_762_310_656
    assert counts["dit"] > 10_000_000_000  # 32 blocks × 4096 wide
    assert all(p.device.type == "meta" for p in model.parameters())


def test_default_config_is_shipped_with_weights_and_is_every_default():
    """DEFAULT_CONFIG names a shipped config whose trained weights ship too (a plain `generate` must not
    fall back to a random model), and it is the default of load_model, from_pretrained and the stages."""
    from training.stages import StageConfig

    assert DEFAULT_CONFIG in config_names()
    assert load_config(DEFAULT_CONFIG).name == DEFAULT_CONFIG
    assert (WEIGHTS_DIR / DEFAULT_CONFIG / "config.json").is_file()
    assert inspect.signature(load_model).parameters["config"].default == DEFAULT_CONFIG
    assert inspect.signature(Diff4SplatPipeline.from_pretrained).parameters["config"].default == DEFAULT_CONFIG
    assert StageConfig().model_config == DEFAULT_CONFIG


def test_tiny_yaml_equals_dataclass_defaults():
    """configs/tiny.yaml only restates the defaults: the dataclasses are the single source."""
    assert load_config("tiny") == Diff4SplatConfig()


@pytest.mark.parametrize("override,match", [
    ({"dit": {"latent_channels": 8}}, "latent_channels"),
    ({"dit": {"text_dim": 32}}, "text_dim"),
    ({"height": 60}, "height"),
    ({"num_frames": 16}, "1 \\+ 4"),
    ({"bogus": 1}, "unknown field 'bogus'"),
])
def test_inconsistent_configs_raise(tmp_path, override, match):
    import yaml

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(override))
    with pytest.raises(ValueError, match=match):
        load_config(path)


def test_unknown_config_name_raises():
    with pytest.raises(FileNotFoundError, match="nonexistent"):
        load_config("nonexistent")
    assert (CONFIG_DIR / "tiny.yaml").is_file()


@pytest.mark.slow
def test_save_and_load_round_trip_gives_identical_networks(tmp_path):
    model = Diff4SplatModel.random(Diff4SplatConfig(), seed=3)
    model.save_pretrained(tmp_path / "ckpt")
    loaded = Diff4SplatModel.from_pretrained(tmp_path / "ckpt")
    assert dataclasses.asdict(loaded.config) == dataclasses.asdict(model.config)
    a, b = model.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_random_models_are_seeded():
    a = Diff4SplatModel.random(Diff4SplatConfig(), seed=0).state_dict()
    b = Diff4SplatModel.random(Diff4SplatConfig(), seed=0).state_dict()
    c = Diff4SplatModel.random(Diff4SplatConfig(), seed=1).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a if a[k].numel() > 1 and a[k].abs().sum() > 0)


def test_missing_checkpoint_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        Diff4SplatModel.from_pretrained(tmp_path)
