"""Tests of training/compose.py: assembling a model from networks of several checkpoints."""
import json

import pytest
import torch
from helpers import tiny_model

from models.bundle import Diff4SplatModel
from training.compose import compose, main


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    a, b = tiny_model(seed=1), tiny_model(seed=2, image_branch=0)
    a.vae.config.scaling_factor = 0.37  # a calibrated VAE: its scaling must travel with it
    a.save_pretrained(root / "a")
    b.save_pretrained(root / "b")
    config = root / "target.yaml"
    config.write_text("name: target\nldrm: {image_branch: 8}\n")
    return root, a, b, config


def test_taken_networks_keep_their_weights_and_config(checkpoints):
    root, a, b, config = checkpoints
    model = compose(config, {"vae": root / "a", "ldrm": root / "b"}, seed=5)
    assert model.config.vae.scaling_factor == 0.37 and model.config.ldrm.image_branch == 8
    for name, src in (("vae", a), ("ldrm", b)):
        mine = getattr(model, name).state_dict()
        for key, value in getattr(src, name).state_dict().items():
            assert torch.equal(mine[key], value), f"{name}.{key}"
    # the image branch the checkpoint lacks is new and zero-initialised: the composed LDRM computes b's maps
    assert all(k.startswith("image_branch.") for k in set(model.ldrm.state_dict()) - set(b.ldrm.state_dict()))
    assert torch.equal(model.ldrm.image_branch.out.weight, torch.zeros_like(model.ldrm.image_branch.out.weight))
    # networks not taken are the seeded random ones
    fresh = Diff4SplatModel.random(model.config, seed=5)
    assert all(torch.equal(p, q) for p, q in zip(model.dit.parameters(), fresh.dit.parameters(), strict=True))


def test_mismatched_weights_and_bad_names_raise(checkpoints, tmp_path, capsys):
    root, _, _, config = checkpoints
    wide = tmp_path / "wide.yaml"
    wide.write_text("name: wide\nldrm: {embed_dim: 32, num_heads: 4, deformation: {in_channels: 32}}\n")
    with pytest.raises(ValueError, match="ldrm from .*do not fit"):  # 64-wide weights into a 32-wide LDRM
        compose(wide, {"ldrm": root / "b"})
    compose(wide, {}, seed=0).save_pretrained(tmp_path / "w")
    assert json.loads((tmp_path / "w" / "config.json").read_text())["ldrm"]["embed_dim"] == 32
    with pytest.raises(ValueError, match="network"):
        compose(config, {"unet": root / "a"})
    assert main(["--config", str(config), "--out", str(tmp_path / "o"), "dit"]) == 2
    assert "NETWORK=FOLDER" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_reinit_starts_a_replaced_head_from_its_initialisation(tmp_path, capsys):
    """A deconv-head LDRM taken into an upsampling-head config: refused without --reinit (the head's weights do not
    fit), and with ``--reinit ldrm.head`` every other LDRM weight is the checkpoint's and the head is the seeded
    initialisation."""
    src = tiny_model(seed=3)
    src.ldrm.config.head = "deconv"
    deconv = Diff4SplatModel.random(src.config, seed=3)
    deconv.save_pretrained(tmp_path / "deconv")
    target = tmp_path / "up.yaml"
    target.write_text("name: up\nldrm: {head: upsample}\n")
    with pytest.raises(ValueError, match="ldrm from .*do not fit"):
        compose(target, {"ldrm": tmp_path / "deconv"})
    model = compose(target, {"ldrm": tmp_path / "deconv"}, seed=7, reinit=("ldrm.head",))
    assert model.config.ldrm.head == "upsample"
    mine, theirs = model.ldrm.state_dict(), deconv.ldrm.state_dict()
    for key, value in theirs.items():
        if not key.startswith("head."):
            assert torch.equal(mine[key], value), key
    fresh = Diff4SplatModel.random(model.config, seed=7)
    for (n, p), q in zip(model.ldrm.head.named_parameters(), fresh.ldrm.head.parameters(), strict=True):
        assert torch.equal(p, q), n
    assert main(["--config", str(target), "--out", str(tmp_path / "o"), "--reinit", "dit.x", "ldrm=" +
                 str(tmp_path / "deconv")]) == 2
    assert "--reinit" in capsys.readouterr().err and not (tmp_path / "o").exists()
