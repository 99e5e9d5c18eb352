"""Tests for diff4splat.io.exr: float32 depth/alpha round trips through OpenEXR, errors."""
import re

import numpy as np
import OpenEXR
import pytest
import torch

from diff4splat.io import load_depth_exr, save_depth_exr


def test_depth_roundtrip_is_bit_exact_and_uses_z_channel(tmp_path):
    rng = np.random.default_rng(0)
    depth = (rng.random((13, 21)) * 50).astype(np.float32)
    depth[0, 0] = np.inf  # background at infinity is allowed
    depth[1, 1] = 0.0
    save_depth_exr(tmp_path / "d.exr", depth)
    out = load_depth_exr(tmp_path / "d.exr")
    assert out.dtype == np.float32 and out.shape == (13, 21)
    assert np.array_equal(out, depth)
    with OpenEXR.File(str(tmp_path / "d.exr"), separate_channels=True) as f:
        assert sorted(f.channels()) == ["Z"]
        assert f.channels()["Z"].pixels.dtype == np.float32
    d, a = load_depth_exr(tmp_path / "d.exr", return_alpha=True)
    assert a is None and np.array_equal(d, depth)


def test_depth_and_alpha_from_torch(tmp_path):
    depth = torch.linspace(0.5, 4.0, 6 * 8).reshape(6, 8)
    alpha = torch.linspace(0.0, 1.0, 6 * 8).reshape(6, 8)
    save_depth_exr(tmp_path / "sub" / "0000.exr", depth, alpha=alpha)  # creates the folder
    d, a = load_depth_exr(tmp_path / "sub" / "0000.exr", return_alpha=True)
    assert np.array_equal(d, depth.numpy()) and np.array_equal(a, alpha.numpy())
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["0000.exr"]  # no temp file left


def test_bfloat16_depth_is_written_as_its_float32_values(tmp_path):
    """numpy has no bfloat16: the writer widens it (it raised "unsupported ScalarType BFloat16")."""
    depth = torch.linspace(0.5, 4.0, 6 * 8).reshape(6, 8).bfloat16()
    save_depth_exr(tmp_path / "d.exr", depth, alpha=torch.ones(6, 8, dtype=torch.bfloat16))
    assert np.array_equal(load_depth_exr(tmp_path / "d.exr"), depth.float().numpy())


def test_reads_half_float_z_written_elsewhere(tmp_path):
    z = np.array([[1.5, 2.25], [1024.0, 0.125]], dtype=np.float16)
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"Z": z}).write(str(tmp_path / "h.exr"))
    d = load_depth_exr(tmp_path / "h.exr")
    assert d.dtype == np.float32 and np.array_equal(d, z.astype(np.float32))


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="depth must have shape"):
        save_depth_exr(tmp_path / "x.exr", np.zeros((2, 3, 1), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        save_depth_exr(tmp_path / "x.exr", np.full((2, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="≥ 0"):
        save_depth_exr(tmp_path / "x.exr", -np.ones((2, 3), np.float32))
    with pytest.raises(ValueError, match="alpha must have the shape"):
        save_depth_exr(tmp_path / "x.exr", np.ones((2, 3)), alpha=np.ones((3, 2)))
    with pytest.raises(ValueError, match="alpha must be finite"):
        save_depth_exr(tmp_path / "x.exr", np.ones((2, 3)), alpha=np.full((2, 3), 1.5))
    assert not (tmp_path / "x.exr").exists()
    with pytest.raises(FileNotFoundError):
        load_depth_exr(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="OpenEXR"):
        load_depth_exr(tmp_path / "junk.exr")
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"R": np.ones((2, 2), np.float32)}).write(str(tmp_path / "r.exr"))
    with pytest.raises(ValueError, match="'Z'"):
        load_depth_exr(tmp_path / "r.exr")


@pytest.mark.parametrize("head, said", [(b"\x89PNG\r\n\x1a\n" + bytes(24), "it holds a PNG image"),
                                        (b"\xff\xd8\xff\xe0" + bytes(24), "it holds a JPEG image"),
                                        (b"", "it does not start with the EXR signature 76 2f 31 01 (empty)"),
                                        (b"\x76\x2f\x31\x01" + bytes(4), "could not read")])
def test_a_file_named_exr_that_is_not_one_says_what_it_is(tmp_path, head, said):
    """``data_prep validate`` on a PNG named .exr printed OpenEXR's "Unable to open 'file' for read" (issue 61)."""
    path = tmp_path / "00000.exr"
    path.write_bytes(head)
    want = said if "could" in said else "^" + re.escape(f"{path} is not an OpenEXR file: {said}")
    with pytest.raises(ValueError, match=want):
        load_depth_exr(path)
