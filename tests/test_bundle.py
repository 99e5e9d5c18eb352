import dataclasses
import inspect
import json
from pathlib import Path

import pytest
import torch
import yaml
from helpers import EXAMPLE_IMAGE

from diff4splat.cli import main
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
from training.stage_config import StageConfig


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
    assert _readme_sizes("paper") == [counts[k] for k in ("vae", "text_encoder", "dit", "ldrm", "total")]


def _readme_sizes(name: str) -> list[int]:
    """The README's "Model sizes" row of config ``name``: VAE, text encoder, DiT, LDRM, total."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith(f"| `{name}`"))
    return [int(cell.split()[0].replace(",", "")) for cell in row.strip("|").split("|")[2:]]


@pytest.mark.parametrize("name", ["base", "tiny", "small"])
def test_readme_model_sizes_are_the_configs_counts(name):
    with torch.device("meta"):
        counts = Diff4SplatModel(load_config(name)).parameter_counts()
    assert _readme_sizes(name) == [counts[k] for k in ("vae", "text_encoder", "dit", "ldrm", "total")]


def test_default_config_is_shipped_with_weights_and_is_every_default():
    """DEFAULT_CONFIG names a shipped config whose trained weights ship too (a plain `generate` must not
    fall back to a random model), and it is the default of load_model, from_pretrained and the stages."""
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
    ({"generated_colors": "decoded"}, "generated_colors must be one of"),
    ({"generated_footprint": "disk"}, "generated_footprint must be one of"),
])
def test_inconsistent_configs_raise(tmp_path, override, match):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(override))
    with pytest.raises(ValueError, match=match):
        load_config(path)


def test_unknown_config_name_raises():
    with pytest.raises(FileNotFoundError, match="nonexistent"):
        load_config("nonexistent")
    assert (CONFIG_DIR / "tiny.yaml").is_file()


def test_missing_config_says_whether_a_name_or_a_file_was_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"'smal' not found \(known: .*tiny\) and no file of that name"):
        load_config("smal")
    with pytest.raises(FileNotFoundError, match="no file '.*gone.yaml'"):
        load_config(tmp_path / "gone.yaml")
    with pytest.raises(IsADirectoryError, match=f"{tmp_path} is a folder, not a model config file"):
        load_config(tmp_path)


@pytest.mark.parametrize("content, why", [
    ("root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1:daemon:/usr/sbin:/usr/sbin/nologin\n",
     "is not a model config: it holds a YAML string"),  # --config /etc/passwd
    ("- 1\n- 2\n", "is not a model config: it holds a YAML list"),
    ("height: [unclosed\n", "is not valid YAML"),
    (b"\x7fELF\x02\x01\x01\x00\xd0", "is not UTF-8 text"),
])
def test_an_existing_file_that_is_no_model_config_is_named_with_what_is_wrong(tmp_path, content, why):
    path = tmp_path / "passwd"  # no .yaml suffix: an existing file is read whatever its name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(ValueError, match=f"config: {path} {why}"):
        load_config(path)


def test_a_json_config_loads_like_its_yaml(tmp_path):
    """A checkpoint's config.json is a model config; read as JSON (YAML 1.1 would read 1e-06 as a string)."""
    config = load_config("small")
    path = tmp_path / "config.json"
    path.write_text(json.dumps(config.to_dict()))
    assert "e-" in path.read_text()  # a float such as 1e-06 that YAML 1.1 would read as text
    assert load_config(path) == config


def test_cli_config_that_is_no_model_config_is_one_line(tmp_path, capsys):
    path = tmp_path / "passwd"
    path.write_text("root:x:0:0:root:/root:/bin/bash\n")
    code = main(["generate", str(EXAMPLE_IMAGE), "--config", str(path), "--quiet", "--out", str(tmp_path / "o")])
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("diff4splat: warning")]
    assert code == 2 and len(err) == 1 and f"{path} is not a model config" in err[0], err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_save_and_load_round_trip_gives_identical_networks(tmp_path):
    model = Diff4SplatModel.random(Diff4SplatConfig(), seed=3)
    model.save_pretrained(tmp_path / "ckpt")
    loaded = Diff4SplatModel.from_pretrained(tmp_path / "ckpt")
    assert dataclasses.asdict(loaded.config) == dataclasses.asdict(model.config)
    a, b = model.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_a_checkpoint_loads_in_the_dtype_asked_for_without_building_a_cpu_model_first(tmp_path, monkeypatch):
    """`from_pretrained(dtype=)` builds the networks on the meta device and takes the file's tensors: no layer is
    ever initialised on the CPU (a paper-size checkpoint used to be built in float32 first, 67 GB), the result is
    the file's values, and in bfloat16 it equals the float32 load cast, parameter for parameter."""
    model = Diff4SplatModel.random(Diff4SplatConfig(), seed=3)
    model.save_pretrained(tmp_path / "ckpt")
    built_on = set()
    reset = torch.nn.Linear.reset_parameters
    monkeypatch.setattr(torch.nn.Linear, "reset_parameters",
                        lambda self: (built_on.add(self.weight.device.type), reset(self))[1])
    full = Diff4SplatModel.from_pretrained(tmp_path / "ckpt")
    half = Diff4SplatModel.from_pretrained(tmp_path / "ckpt", dtype=torch.bfloat16)
    assert built_on == {"meta"}
    ref, a, b = model.state_dict(), full.state_dict(), half.state_dict()
    assert a.keys() == b.keys() == ref.keys()
    assert all(torch.equal(a[k], ref[k]) and a[k].device.type == "cpu" for k in ref)
    assert all(b[k].dtype == torch.bfloat16 and torch.equal(b[k], ref[k].to(torch.bfloat16)) for k in ref
               if ref[k].is_floating_point())
    assert all(p.requires_grad for p in full.parameters())  # trainable as before (assign keeps requires_grad)
    loaded, _ = load_model(tmp_path / "ckpt", dtype=torch.bfloat16)
    assert {p.dtype for p in loaded.parameters()} == {torch.bfloat16}


def test_random_models_are_seeded():
    a = Diff4SplatModel.random(Diff4SplatConfig(), seed=0).state_dict()
    b = Diff4SplatModel.random(Diff4SplatConfig(), seed=0).state_dict()
    c = Diff4SplatModel.random(Diff4SplatConfig(), seed=1).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a if a[k].numel() > 1 and a[k].abs().sum() > 0)


def test_missing_checkpoint_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        Diff4SplatModel.from_pretrained(tmp_path)
