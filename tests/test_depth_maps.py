"""A user's depth map for the photo layer: reading (diff4splat/io/depth_maps.py), alignment by kind
(diff4splat.assembly.assemble.photo_depth) and ``generate --depth`` end to end."""
import json
import re

import cv2
import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE

import diff4splat.assembly.assemble as assemble
import diff4splat.commands.generate as generate_module
from diff4splat.assembly.assemble import photo_depth
from diff4splat.cameras import camera_rays, intrinsics_from_fov
from diff4splat.cli import main
from diff4splat.io import load_depth_exr, save_depth_exr
from diff4splat.io.depth_maps import MILLIMETRES, fit_depth_map, read_depth_map, valid_depth


def _depth(h=24, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    return (2.0 + 0.5 * xx + 0.2 * torch.rand(h, w, generator=g)).numpy()


def test_every_format_reads_back_in_metres(tmp_path):
    d = _depth()
    save_depth_exr(tmp_path / "d.exr", torch.from_numpy(d), torch.ones(d.shape))
    np.save(tmp_path / "d.npy", d)
    np.save(tmp_path / "d3.npy", d[..., None])
    mm = np.round(d / MILLIMETRES).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), mm)
    np.testing.assert_allclose(read_depth_map(tmp_path / "d.exr"), d, rtol=1e-6)
    np.testing.assert_array_equal(read_depth_map(tmp_path / "d.npy"), d)
    np.testing.assert_array_equal(read_depth_map(tmp_path / "d3.npy"), d)
    np.testing.assert_allclose(read_depth_map(tmp_path / "d.png"), mm * MILLIMETRES)  # millimetres
    np.testing.assert_array_equal(read_depth_map(tmp_path / "d.png", "relative"), mm)  # relative: as stored


@pytest.mark.parametrize("case,needle", [
    ("missing", "does not exist"), ("suffix", "is not a depth map"), ("eight_bit_metric", "is 8-bit"),
    ("three_channels", "one-channel"), ("no_depth", "holds no usable metric depth"), ("pickle", "readable .npy"),
    ("not_exr", "OpenEXR"), ("strings", "2-D numeric"),
])
def test_bad_depth_files_are_one_clear_error_naming_the_file(tmp_path, case, needle):
    path = tmp_path / {"suffix": "d.jpg", "eight_bit_metric": "d.png", "three_channels": "d.png",
                       "pickle": "d.npy", "not_exr": "d.exr", "strings": "d.npy"}.get(case, "d.npy")
    if case == "suffix":
        path.write_bytes(b"x")
    elif case == "eight_bit_metric":
        cv2.imwrite(str(path), np.full((8, 8), 9, np.uint8))
    elif case == "three_channels":
        cv2.imwrite(str(path), np.full((8, 8, 3), 900, np.uint16))
    elif case == "no_depth":
        np.save(path, np.full((4, 4), np.nan))
    elif case == "pickle":
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif case == "not_exr":
        path.write_bytes(b"not an exr")
    elif case == "strings":
        np.save(path, np.array([["a", "b"]]))
    with pytest.raises((ValueError, FileNotFoundError), match=needle) as info:
        read_depth_map(path)
    assert str(path.name) in str(info.value)


def test_maps_are_cropped_like_the_photo_and_resized_without_blending():
    d = np.arange(40 * 60, dtype=np.float64).reshape(40, 60)  # landscape map for a square output
    out, note = fit_depth_map(d, (40, 60), (20, 20))
    assert out.shape == (20, 20) and "60×40 resized to 20×20" in note and "check" not in note
    assert set(out.flatten().tolist()) <= set(d[:, 10:50].flatten().tolist())  # centre crop, nearest values only
    same, none = fit_depth_map(d[:20, :20], (20, 20), (20, 20))
    assert none is None and np.array_equal(same.numpy(), d[:20, :20].astype(np.float32))
    _, other = fit_depth_map(d, (80, 120), (20, 20))
    assert "check that the map is of this photograph" in other


def test_relative_and_inverse_maps_are_aligned_to_the_network_depth_and_holes_filled():
    """The network's depth z: a relative map a·z + b and an inverse map a/z + b are mapped back to z exactly
    (least squares), a metric map is kept as given, and NaN holes take the network's depth."""
    H = W = 16
    K = intrinsics_from_fov(W, H, fov_y_deg=50.0)
    eye = torch.eye(4)
    z = torch.from_numpy(_depth(H, W)).float()
    _, dirs = camera_rays(eye[None], K[None], W, H)
    distance = z / dirs[0, ..., 2]
    image = torch.full((H, W, 3), 0.5)
    net = photo_depth(distance, eye, K, image)
    torch.testing.assert_close(net, z, rtol=1e-5, atol=0)  # same resolution: the network's own z-depth
    for kind, user in (("relative", 3.0 * z - 1.0), ("inverse", 5.0 / z + 0.2)):
        holed = user.clone()
        holed[3, 4] = float("nan")
        torch.testing.assert_close(photo_depth(distance, eye, K, image, holed, kind), z, rtol=1e-4, atol=0)
    metric = z * 1.3
    torch.testing.assert_close(photo_depth(distance, eye, K, image, metric, "metric"), metric)
    far = metric.clone()
    far[:2] = 1e10  # Blender's "no surface": holes, filled from the network
    torch.testing.assert_close(photo_depth(distance, eye, K, image, far, "metric")[:2], z[:2])
    with pytest.raises(ValueError, match="depth_kind"):
        photo_depth(distance, eye, K, image, metric, "disparity")


@pytest.mark.slow
def test_generate_takes_its_own_depth_exr_back(tmp_path):
    """``--depth`` with the frame-0 depth EXR that ``generate`` wrote: the photo layer sits on that depth, so the
    new frame-0 depth equals it up to the expected-depth blending of neighbouring disks (≤ 1 % median, 5 % at
    the 95th percentile); the meta names the file, and a map of another size is resized with a note."""
    common = ["generate", str(EXAMPLE_IMAGE), "--resolution", "64", "--frames", "5", "--steps", "1", "--quiet"]
    assert main(common + ["--out", str(tmp_path / "a")]) == 0
    exr = tmp_path / "a" / "depth" / "0000.exr"
    assert main(common + ["--depth", str(exr), "--out", str(tmp_path / "b")]) == 0
    a, b = load_depth_exr(exr), load_depth_exr(tmp_path / "b" / "depth" / "0000.exr")
    rel = np.abs(b / a - 1)
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05
    meta = json.loads((tmp_path / "b" / "meta.json").read_text())
    assert meta["depth_file"] == str(exr) and meta["depth_kind"] == "metric" and meta["photo_psnr_db"] >= 40.0
    np.save(tmp_path / "small.npy", cv2.resize(a, (16, 16), interpolation=cv2.INTER_NEAREST))
    code = main(["generate", str(EXAMPLE_IMAGE), "--resolution", "64", "--frames", "5", "--steps", "1",
                 "--depth", str(tmp_path / "small.npy"), "--out", str(tmp_path / "c")])
    assert code == 0


def test_a_bad_depth_file_stops_generate_with_one_line(tmp_path, capsys):
    bad = tmp_path / "d.png"
    cv2.imwrite(str(bad), np.full((8, 8), 7, np.uint8))
    code = main(["generate", str(EXAMPLE_IMAGE), "--depth", str(bad), "--quiet", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0 and "d.png" in err and "8-bit" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind, values, needle", [
    ("metric", np.full((8, 8), 1e30), r"holds no usable metric depth: its values \(1e\+30 … 1e\+30\) are not metres "
                                      r"in \[0.001, 10000\]"),
    ("metric", np.full((8, 8), 1e-5), "holds no usable metric depth"),
    ("relative", np.full((8, 8), 5.0), "a relative depth map must vary, but every valid value is 5"),
    ("inverse", np.full((8, 8), -1.0), "holds no usable inverse depth"),
])
def test_depths_that_cannot_be_the_photos_are_refused_by_generate_before_any_work(tmp_path, capsys, monkeypatch,
                                                                                  kind, values, needle):
    """A metric map of 1e30 gave a flat brown frame 0 at 6.5 dB and exit 0 (issue 61); a constant relative map's
    message named neither --depth nor the file. Each is one line naming both, exit 2, before the model loads."""
    monkeypatch.setattr(generate_module, "load_pipeline", lambda *a, **k: pytest.fail("the model loaded"))
    path = tmp_path / "d.npy"
    np.save(path, values)
    code = main(["generate", str(EXAMPLE_IMAGE), "--depth", str(path), "--depth-kind", kind, "--quiet", "--out",
                 str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0 and f"--depth {path}" in err, err
    assert re.search(needle, err), err
    assert not (tmp_path / "o").exists()


def test_far_and_near_metric_values_are_holes_the_network_fills():
    depth = torch.tensor([[1e10, 2.0], [0.0, 1e-4]])
    assert valid_depth(depth, "metric").tolist() == [[False, True], [False, False]]
    assert valid_depth(depth, "relative").all() and valid_depth(-depth, "relative").all()
    assert valid_depth(torch.tensor([0.5, 0.0, -1.0]), "inverse").tolist() == [True, False, False]


@pytest.mark.slow
def test_a_photo_layer_that_misses_the_photograph_is_refused_and_nothing_is_written(tmp_path, capsys, monkeypatch):
    """The last guard of "frame 0 is the photograph": whatever put the photo layer's disks off their pixels, a
    render of the layer below 30 dB is an error, never an output."""
    real = assemble.photo_layer

    def missing(*args, **kwargs):
        layer, history = real(*args, **kwargs)
        return layer, [*history[:-1], 6.5]

    monkeypatch.setattr(assemble, "photo_layer", missing)
    code = main(["generate", str(EXAMPLE_IMAGE), "--resolution", "64", "--frames", "5", "--steps", "1", "--quiet",
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0, err
    assert "frame 0 would not be the photograph: its photo layer renders it at 6.5 dB PSNR, below 30 dB" in err, err
    assert not (tmp_path / "o").exists()
