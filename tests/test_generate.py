"""Tests of diff4splat/generate.py: the library `generate` + `write` behind the `diff4splat generate` command."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE, tiny_model

from diff4splat.cli import main
from diff4splat.generate import generate
from diff4splat.io import load_ply
from diff4splat.io.output_folders import OutputDirError
from diff4splat.pipeline import Diff4SplatPipeline, check_seed
from diff4splat.request import LoadedPipeline, write


def _never():
    raise AssertionError("the model was loaded before the request was checked")


@pytest.mark.parametrize("kwargs, message", [
    ({"steps": 0}, "--steps must be a positive int"),
    ({"frames": 10**6}, "--frames 1000000 exceeds the limit"),
    ({"resolution": -4}, "--resolution must be a positive int"),
    ({"seed": 2**70}, "--seed"),
    ({"seed": True}, "--seed must be an integer"),
    ({"depth_kind": "inverse"}, "--depth-kind inverse describes a --depth file"),
    ({"trajectory": "zigzag"}, "--trajectory must be one of"),
    ({"trajectory": "forward", "amplitude": 1e30}, "--amplitude"),
    ({"cameras": EXAMPLE_IMAGE, "amplitude": 0.1}, "--amplitude scales a --trajectory preset"),
    ({"depth_kind": "disparity"}, "--depth-kind must be one of"),
])
def test_the_request_is_checked_before_the_model_loads(kwargs, message):
    with pytest.raises(ValueError, match=message):
        generate(EXAMPLE_IMAGE, pipeline=_never, **kwargs)


def test_a_numpy_integer_seed_is_a_seed():
    """Counts take numpy integers everywhere; the seed refused np.int64(3)."""
    assert check_seed(np.int64(3)) == 3 and type(check_seed(np.uint64(2**64 - 1))) is int


def test_a_missing_photo_is_named_before_the_model_loads():
    with pytest.raises(FileNotFoundError, match="nonesuch.png"):
        generate(EXAMPLE_IMAGE.parent / "nonesuch.png", pipeline=_never)


def test_a_tensor_image_at_another_resolution_is_refused_before_the_model_loads():
    with pytest.raises(ValueError, match="resolution=128 but the image tensor is 64 pixels high"):
        generate(torch.rand(64, 64, 3), resolution=128, pipeline=_never)


@pytest.mark.slow
def test_generate_then_write_is_what_the_command_writes(tmp_path):
    """The library call and `diff4splat generate` give the same scene and meta.json settings (the command is a
    thin layer over these two functions), and the request's inputs are protected from `write`."""
    loaded = LoadedPipeline(Diff4SplatPipeline(tiny_model(dynamic=True)), "tiny")
    gen = generate(EXAMPLE_IMAGE, pipeline=loaded, frames=5, resolution=64, steps=1, seed=3, fps=6)
    T = len(gen.result.cameras)
    assert write(gen, tmp_path / "own")["fps"] == 6  # generate's frame rate unless write is given another
    assert gen.colors.shape == (T, 64, 64, 3) and gen.depths.shape == gen.alphas.shape == (T, 64, 64)
    meta = write(gen, tmp_path / "lib", fps=12)
    on_disk = json.loads((tmp_path / "lib" / "meta.json").read_text())
    assert on_disk["fps"] == meta["fps"] == 12 and on_disk["image"] == str(EXAMPLE_IMAGE) and on_disk["seed"] == 3
    assert on_disk["trajectory"] == "arc" and on_disk["num_gaussians"] == gen.result.scene.num_gaussians
    with pytest.raises(ValueError, match="input"):  # the photo's own folder is an input of the request
        write(gen, EXAMPLE_IMAGE.parent, overwrite=True)

    gen2 = generate(gen.colors[0], gen.result.cameras, pipeline=loaded.pipeline, steps=1, seed=3)  # tensors in
    assert gen2.meta["image"] is None and gen2.meta["trajectory"] is None and len(gen2.result.cameras) == T

    code = main(["generate", str(EXAMPLE_IMAGE), "--config", "tiny", "--frames", "5", "--resolution", "64",
                 "--steps", "1", "--seed", "3", "--quiet", "--out", str(tmp_path / "cli")])
    assert code == 0
    cli_meta = json.loads((tmp_path / "cli" / "meta.json").read_text())
    for key in ("frames", "width", "height", "seed", "steps", "sampler", "trajectory", "image", "prompt"):
        assert cli_meta[key] == on_disk[key], key
    assert load_ply(tmp_path / "cli" / "scene.ply").num_gaussians > 0
    assert torch.isfinite(gen.colors).all()


def test_a_frame_count_the_vae_cannot_take_is_named_by_its_flag():
    """``--frames 6`` said "video: T=6 frames; …": the user passed no video."""
    with pytest.raises(ValueError, match=r"^--frames 6: the frame count must be 1 \+ 4·k \(1, 5, 9, …\)$"):
        generate(EXAMPLE_IMAGE, pipeline=Diff4SplatPipeline(tiny_model()), frames=6)


def test_the_output_folder_and_frame_rate_are_checked_before_the_model_loads(tmp_path):
    """``generate`` checks the folder it is told of and the frame rate first, so its command does not check them
    again: a folder holding an input (the photo's, or a loader's checkpoint given in ``inputs``), a user's folder
    without ``overwrite``, a missing parent, a bad fps."""
    ckpt = tmp_path / "run" / "model"
    ckpt.mkdir(parents=True)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    for kwargs, error, message in [
        ({"out": EXAMPLE_IMAGE.parent, "overwrite": True}, OutputDirError, "holds input"),
        ({"out": tmp_path / "run", "inputs": [ckpt]}, OutputDirError, "holds input"),
        ({"out": tmp_path / "mine"}, OutputDirError, "not written by diff4splat"),
        ({"out": tmp_path / "no" / "such"}, OutputDirError, "does not exist"),
        ({"fps": 0}, ValueError, "--fps"),
        ({"out": tmp_path / "new", "fps": 1e6}, ValueError, "--fps must be at most"),
    ]:
        with pytest.raises(error, match=message):
            generate(EXAMPLE_IMAGE, pipeline=_never, **kwargs)
    assert not (tmp_path / "new").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["mine", "run"]
