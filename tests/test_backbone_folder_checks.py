"""A diffusers backbone folder given to ``--checkpoint`` is checked before diffusers is imported or anything loads
(:func:`models.backbone_model.check_backbone_folder`): a missing component folder or config, an absurd
``diff4splat.json`` and a missing ``[diffusers]`` extra are each one line, exit 2 (issue 61: tracebacks before)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import EXAMPLE_IMAGE

from diff4splat.cli import main
from models.backbone import LatentFormat
from models.backbone_model import BackboneModelConfig, check_backbone_folder

COMPONENTS = {"transformer": ("diffusers", "WanTransformer3DModel", "config.json"),
              "vae": ("diffusers", "AutoencoderKLWan", "config.json"),
              "text_encoder": ("transformers", "UMT5EncoderModel", "config.json"),
              "tokenizer": ("transformers", "T5TokenizerFast", "tokenizer_config.json"),
              "scheduler": ("diffusers", "UniPCMultistepScheduler", "scheduler_config.json")}


def hub_folder(root: Path, drop_folder: str | None = None, drop_config: str | None = None,
               drop_weights: str | None = None, empty_config: str | None = None) -> Path:
    """A Wan2.2 Hub layout of configs and empty weight files: enough for the checks, which run before any load."""
    index = {"_class_name": "WanPipeline", "_diffusers_version": "0.42.0", "transformer_2": [None, None],
             "boundary_ratio": None, "expand_timesteps": True}
    for name, (library, cls, config) in COMPONENTS.items():
        index[name] = [library, cls]
        if name != drop_folder:
            (root / name).mkdir(parents=True)
            if name != drop_config:
                (root / name / config).write_text("" if name == empty_config else "{}")
            if config == "config.json" and name != drop_weights:  # a model: its weights (empty: the checks only look)
                (root / name / "model.safetensors").write_bytes(b"")
    (root / "model_index.json").write_text(json.dumps(index))
    return root


def _one_line_exit_2(capsys, tmp_path, folder: Path) -> str:
    code = main(["generate", str(EXAMPLE_IMAGE), "--checkpoint", str(folder), "--quiet", "--out",
                 str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("diff4splat: error: "), err
    assert not (tmp_path / "o").exists()
    return err


def test_a_complete_folder_passes_the_checks(tmp_path):
    assert check_backbone_folder(hub_folder(tmp_path / "wan")) == ("wan2.2-ti2v", None)


@pytest.mark.parametrize("drop, needle", [
    (dict(drop_folder="scheduler"), "has no scheduler/ folder, which model_index.json names "
                                    "(diffusers.UniPCMultistepScheduler)"),
    (dict(drop_config="scheduler"), "scheduler holds no config file"),
    (dict(drop_config="tokenizer"), "tokenizer holds no config file"),
    (dict(drop_weights="text_encoder"), "text_encoder holds no weights (*.safetensors, *.bin) for its "
                                        "UMT5EncoderModel"),
    (dict(empty_config="vae"), "vae/config.json is not valid JSON (Expecting value at line 1 column 1)"),
])
def test_a_missing_component_is_one_line_naming_it(tmp_path, capsys, drop, needle):
    err = _one_line_exit_2(capsys, tmp_path, hub_folder(tmp_path / "wan", **drop))
    assert needle in err, err


def test_an_absurd_diff4splat_json_is_refused_before_loading(tmp_path, capsys):
    folder = hub_folder(tmp_path / "wan")
    config = BackboneModelConfig.for_backbone("wan2.2-ti2v", LatentFormat(48, 4, 16)).to_dict()
    config["ldrm"]["embed_dim"] = 10**6
    config["ldrm"]["num_heads"] = 1
    config["ldrm"]["head_channels"] = 10**6
    config["ldrm"]["deformation"]["in_channels"] = 10**6
    (folder / "diff4splat.json").write_text(json.dumps(config))
    err = _one_line_exit_2(capsys, tmp_path, folder)
    assert "diff4splat.json (ldrm): a model of" in err and "exceeds the limit" in err, err
    config = BackboneModelConfig.for_backbone("cogvideox-i2v", LatentFormat(16, 4, 8)).to_dict()
    (folder / "diff4splat.json").write_text(json.dumps(config))
    assert "describes a cogvideox-i2v backbone; the folder holds a wan2.2-ti2v" in _one_line_exit_2(capsys, tmp_path,
                                                                                                     folder)


@pytest.mark.slow
def test_a_backbone_folder_without_the_diffusers_extra_is_one_line_naming_it(tmp_path):
    """In a fresh interpreter where ``import diffusers`` fails (the extra not installed)."""
    folder = hub_folder(tmp_path / "wan")
    code = (f"import sys; sys.modules['diffusers'] = None; from diff4splat.cli import main; "
            f"sys.exit(main(['generate', {str(EXAMPLE_IMAGE)!r}, '--checkpoint', {str(folder)!r}, '--quiet', "
            f"'--out', {str(tmp_path / 'o')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr[-3000:]
    assert "needs diffusers: pip install 'diff4splat[diffusers]'" in r.stderr
    assert not (tmp_path / "o").exists()
