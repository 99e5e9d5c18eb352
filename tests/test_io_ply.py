"""Tests for diff4splat.io.ply: INRIA 3DGS layout (checked with plyfile), round trips, errors."""
import math

import numpy as np
import plyfile
import pytest
import torch

from diff4splat.io import load_ply, ply_property_names, save_ply
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.constants import OPACITY_EPS

INRIA_DEG3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def random_gaussians(n=20, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, k, 3, generator=g),
    )


@pytest.mark.parametrize("degree", [0, 3])
def test_roundtrip(tmp_path, degree):
    g = random_gaussians(degree=degree)
    save_ply(tmp_path / "s.ply", g)
    h = load_ply(tmp_path / "s.ply")
    assert h.sh.shape == g.sh.shape and h.sh_degree == degree
    assert h.means.dtype == torch.float32
    torch.testing.assert_close(h.means, g.means)
    torch.testing.assert_close(h.quats, g.quats)  # stored unnormalised, as given
    torch.testing.assert_close(h.sh, g.sh)
    torch.testing.assert_close(h.scales, g.scales, rtol=1e-6, atol=0)
    torch.testing.assert_close(h.opacities, g.opacities, rtol=1e-5, atol=1e-7)


def test_property_names_order_and_binary_format_match_inria(tmp_path):
    assert ply_property_names(16) == INRIA_DEG3
    assert ply_property_names(1) == INRIA_DEG3[:9] + INRIA_DEG3[-8:]
    g = random_gaussians(n=7, degree=3)
    save_ply(tmp_path / "s.ply", g)
    ply = plyfile.PlyData.read(str(tmp_path / "s.ply"))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    el = ply["vertex"]
    assert [p.name for p in el.properties] == INRIA_DEG3
    assert all(v.dtype == np.dtype("<f4") for v in (el.data[name] for name in INRIA_DEG3))
    assert len(el.data) == 7
    d = el.data
    # Values in INRIA's storage conventions, computed independently here.
    np.testing.assert_allclose(d["f_dc_1"], g.sh[:, 0, 1].numpy())
    np.testing.assert_allclose(d["f_rest_0"], g.sh[:, 1, 0].numpy())  # R, first rest coefficient
    np.testing.assert_allclose(d["f_rest_14"], g.sh[:, 15, 0].numpy())  # R, last
    np.testing.assert_allclose(d["f_rest_15"], g.sh[:, 1, 1].numpy())  # G, first (channel-major)
    np.testing.assert_allclose(d["f_rest_44"], g.sh[:, 15, 2].numpy())  # B, last
    o = g.opacities.double().numpy()
    np.testing.assert_allclose(d["opacity"], np.log(o / (1 - o)), rtol=1e-5)
    np.testing.assert_allclose(d["scale_2"], np.log(g.scales[:, 2].double().numpy()), rtol=1e-6)
    np.testing.assert_allclose(d["rot_0"], g.quats[:, 0].numpy())  # w first
    for name in ("nx", "ny", "nz"):
        assert np.all(d[name] == 0)


def test_loads_inria_file_written_by_plyfile(tmp_path):
    # A file as the INRIA code writes it (plyfile, degree 1, plus an extra property we ignore).
    n, rng = 5, np.random.default_rng(0)
    names = INRIA_DEG3[:9] + [f"f_rest_{i}" for i in range(9)] + INRIA_DEG3[-8:] + ["extra"]
    arr = np.empty(n, dtype=[(nm, "f4") for nm in names])
    for nm in names:
        arr[nm] = rng.normal(size=n).astype("f4")
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "inria.ply"))
    g = load_ply(tmp_path / "inria.ply")
    assert g.sh.shape == (n, 4, 3)
    np.testing.assert_allclose(g.sh[:, 2, 0].numpy(), arr["f_rest_1"])
    np.testing.assert_allclose(g.sh[:, 1, 2].numpy(), arr["f_rest_6"])
    np.testing.assert_allclose(g.opacities.numpy(), 1 / (1 + np.exp(-arr["opacity"].astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(g.scales[:, 1].numpy(), np.exp(arr["scale_1"].astype(np.float64)), rtol=1e-6)
    np.testing.assert_allclose(g.means.numpy(), np.stack([arr["x"], arr["y"], arr["z"]], 1))


def test_extreme_opacities_are_clamped_before_logit(tmp_path):
    g = random_gaussians(n=3, degree=0)
    g.opacities = torch.tensor([0.0, 1.0, 0.5])
    save_ply(tmp_path / "s.ply", g)
    d = plyfile.PlyData.read(str(tmp_path / "s.ply"))["vertex"].data["opacity"]
    assert np.isfinite(d).all()
    assert d[0] == pytest.approx(math.log(OPACITY_EPS / (1 - OPACITY_EPS)), rel=1e-5)
    assert d[1] == pytest.approx(-d[0], rel=1e-5) and d[2] == 0
    h = load_ply(tmp_path / "s.ply")
    torch.testing.assert_close(h.opacities, torch.tensor([OPACITY_EPS, 1 - OPACITY_EPS, 0.5]), atol=1e-7, rtol=0)


def test_empty_and_autograd_tensors(tmp_path):
    g = random_gaussians(n=0, degree=1)
    save_ply(tmp_path / "e.ply", g)
    assert load_ply(tmp_path / "e.ply").num_gaussians == 0
    g = random_gaussians(n=4, degree=1)
    g.means.requires_grad_(True)
    save_ply(tmp_path / "g.ply", g)
    torch.testing.assert_close(load_ply(tmp_path / "g.ply").means, g.means.detach())


def test_atomic_write_leaves_no_temp_and_keeps_old_file_on_error(tmp_path):
    target = tmp_path / "s.ply"
    save_ply(target, random_gaussians(n=3, degree=0))
    before = target.read_bytes()
    bad = random_gaussians(n=3, degree=0)
    bad.scales = bad.scales.clone()
    bad.scales[0, 0] = -1.0
    with pytest.raises(ValueError, match="scales"):
        save_ply(target, bad)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.ply"]


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_ply(tmp_path / "missing.ply")
    (tmp_path / "a.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        load_ply(tmp_path / "a.ply")
    (tmp_path / "b.txt").write_bytes(b"hello\n")
    with pytest.raises(ValueError, match="not a PLY"):
        load_ply(tmp_path / "b.txt")
    save_ply(tmp_path / "t.ply", random_gaussians(n=10, degree=0))
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-8])
    with pytest.raises(ValueError, match="truncated"):
        load_ply(tmp_path / "t.ply")
    arr = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "m.ply"))
    with pytest.raises(ValueError, match="f_dc_0"):
        load_ply(tmp_path / "m.ply")


def _corrupt_ply(path, case):
    """A PLY of 10 Gaussians (SH degree 0) damaged as ``case`` says."""
    save_ply(path, random_gaussians(n=10, degree=0))
    data = bytearray(path.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    row = len(ply_property_names(1)) * 4
    names = ply_property_names(1)
    if case == "nan_mean":
        data[body + 5 * row:body + 5 * row + 4] = np.float32(np.nan).tobytes()  # x of Gaussian 5
    elif case == "nan_scale":
        i = names.index("scale_1")
        data[body + i * 4:body + i * 4 + 4] = np.float32(np.nan).tobytes()
    elif case == "scale_overflows_float32":
        i = names.index("scale_0")  # exp(100) is finite in float64, inf in float32
        data[body + i * 4:body + i * 4 + 4] = np.float32(100.0).tobytes()
    elif case == "zero_quaternion":
        i = names.index("rot_0")
        data[body + i * 4:body + i * 4 + 16] = np.zeros(4, np.float32).tobytes()
    elif case == "truncated_body":
        data = data[:body + 3 * row + 7]
    elif case == "truncated_header":
        data = data[:body - 30]
    elif case == "garbage":
        data = bytearray(np.random.default_rng(0).bytes(4096))
    elif case == "magic_then_garbage_without_line_breaks":
        data = bytearray(b"ply\n" + bytes(range(11, 256)) * 4000)
    elif case == "f_rest_name_not_a_number":
        data = data.replace(b"property float f_dc_2\n", b"property float f_dc_2\nproperty float f_rest_x\n")
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("case", ["nan_mean", "nan_scale", "scale_overflows_float32",
                                  "zero_quaternion", "truncated_body", "truncated_header", "garbage",
                                  "magic_then_garbage_without_line_breaks", "f_rest_name_not_a_number"])
def test_every_load_error_starts_with_the_file(tmp_path, case):
    """A corrupt PLY is one ValueError line that starts with its path (the CLI prints it as is)."""
    path = _corrupt_ply(tmp_path / "scene.ply", case)
    with pytest.raises(ValueError) as e:
        load_ply(path)
    message = str(e.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    if case == "nan_mean":
        assert "means contains 1 non-finite" in message
    if case == "magic_then_garbage_without_line_breaks":
        assert "longer than" in message
