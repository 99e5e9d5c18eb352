"""Tests for diff4splat.io.cameras: cameras.json and RealEstate10K round trips and errors."""
import json
import math

import pytest
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_focal, make_trajectory
from diff4splat.io import load_cameras_json, load_realestate10k, save_cameras_json, save_realestate10k
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat

W, H = 64, 48


def world_path(T=5, seed=0):
    """A float32 path in an arbitrary world frame (first viewmat not identity), non-uniform times."""
    g = torch.Generator().manual_seed(seed)
    R = quat_to_rotmat(axis_angle_to_quat(torch.randn(T, 3, generator=g, dtype=torch.float64),
                                          torch.rand(T, generator=g, dtype=torch.float64) * math.pi))
    V = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
    V[:, :3, :3] = R
    V[:, :3, 3] = torch.randn(T, 3, generator=g, dtype=torch.float64)
    K = torch.stack([intrinsics_from_focal(50.0 + i, 52.0, W, H, cx=31.0 + i, cy=25.5,
                                           dtype=torch.float64) for i in range(T)])
    times = torch.tensor([0.0, 0.1, 0.35, 0.9, 1.0], dtype=torch.float64)[:T]
    return CameraPath(V.float(), K.float(), W, H, times.float())


def test_json_roundtrip_is_exact_and_has_documented_keys(tmp_path):
    p = world_path()
    save_cameras_json(tmp_path / "cameras.json", p)
    data = json.loads((tmp_path / "cameras.json").read_text())
    assert set(data) == {"width", "height", "Ks", "viewmats", "times"}
    assert (data["width"], data["height"]) == (W, H)
    assert len(data["Ks"]) == 5 and len(data["Ks"][0]) == 3 and len(data["viewmats"][0][0]) == 4
    q = load_cameras_json(tmp_path / "cameras.json")
    assert torch.equal(q.viewmats, p.viewmats) and torch.equal(q.Ks, p.Ks) and torch.equal(q.times, p.times)
    assert (q.width, q.height) == (W, H)
    assert q.viewmats.dtype == torch.float32


def test_json_trajectory_roundtrip_and_default_times(tmp_path):
    p = make_trajectory("orbit", 9, intrinsics_from_focal(40.0, 40.0, W, H), W, H)
    save_cameras_json(tmp_path / "c.json", p)
    data = json.loads((tmp_path / "c.json").read_text())
    del data["times"]
    (tmp_path / "c.json").write_text(json.dumps(data))
    q = load_cameras_json(tmp_path / "c.json")
    torch.testing.assert_close(q.times, torch.arange(9) / 8.0)
    assert torch.equal(q.viewmats, p.viewmats)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda d: d.pop("Ks"), "missing key 'Ks'"),
        (lambda d: d.pop("width"), "missing key 'width'"),
        (lambda d: d.update(height=0), "'height' must be a positive int"),
        (lambda d: d.update(width=64.5), "'width' must be a positive int"),
        (lambda d: d.update(viewmats=[[[1, 0, 0], [0, 1, 0], [0, 0, 1]]] * 5), "'viewmats' must have shape"),
        (lambda d: d.update(Ks="abc"), "'Ks'"),
        (lambda d: d.update(times=[0, 0.5, 0.4, 0.9, 1.0]), "non-decreasing"),
        (lambda d: d["Ks"][2][0].__setitem__(0, -1.0), r"Ks\[2\] focal"),
        (lambda d: d["viewmats"][1][0].__setitem__(0, 3.0), r"viewmats\[1\] rotation"),
        (lambda d: d["Ks"].pop(), r"Ks must be a tensor of shape \(5, 3, 3\)"),
    ],
)
def test_json_bad_values_name_the_field(tmp_path, edit, match):
    save_cameras_json(tmp_path / "c.json", world_path())
    data = json.loads((tmp_path / "c.json").read_text())
    edit(data)
    (tmp_path / "c.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=match):
        load_cameras_json(tmp_path / "c.json")


def test_json_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_cameras_json(tmp_path / "none.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(ValueError, match="JSON"):
        load_cameras_json(tmp_path / "x.json")
    (tmp_path / "y.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="object"):
        load_cameras_json(tmp_path / "y.json")


def test_realestate10k_parses_the_documented_line_format(tmp_path):
    # Frame 1 is translated by 0.5 m along x and rotated 90° about y (world-to-camera).
    text = (
        "https://www.youtube.com/watch?v=abcdefghijk\n"
        "1000000 0.5 0.8 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n"
        "\n"
        "1500000 0.5 0.8 0.25 0.5 0 0 0 0 1 0.5 0 1 0 0 -1 0 0 0\n"
        "3000000 0.5 0.8 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 2\n"
    )
    (tmp_path / "re.txt").write_text(text)
    p = load_realestate10k(tmp_path / "re.txt", W, H, relative=False)
    assert len(p) == 3 and p.viewmats.dtype == torch.float32
    torch.testing.assert_close(p.Ks[0], torch.tensor([[32.0, 0, 32.0], [0, 38.4, 24.0], [0, 0, 1]]))
    assert p.Ks[1, 0, 2].item() == 16.0
    torch.testing.assert_close(p.viewmats[1],
                               torch.tensor([[0.0, 0, 1, 0.5], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]))
    torch.testing.assert_close(p.times, torch.tensor([0.0, 0.25, 1.0]))
    torch.testing.assert_close(p.camera_centers()[2], torch.tensor([0.0, 0.0, -2.0]))
    # relative=True re-expresses in frame 0's coordinates (frame 0 is identity here → unchanged).
    r = load_realestate10k(tmp_path / "re.txt", W, H)
    torch.testing.assert_close(r.viewmats, p.viewmats)


def test_realestate10k_roundtrip_and_relative(tmp_path):
    p = world_path()
    save_realestate10k(tmp_path / "c.txt", p, url="https://example.com/v", fps=30)
    lines = (tmp_path / "c.txt").read_text().splitlines()
    assert lines[0] == "https://example.com/v" and len(lines) == 6
    assert all(len(line.split()) == 19 for line in lines[1:])
    # Timestamps: the clip spans (T−1)/fps = 4/30 s; t = 0.35 → 0.35·4/30 s.
    assert int(lines[3].split()[0]) == round(0.35 * 4 / 30 * 1e6)
    q = load_realestate10k(tmp_path / "c.txt", W, H, relative=False)
    torch.testing.assert_close(q.viewmats, p.viewmats, atol=1e-6, rtol=0)
    torch.testing.assert_close(q.Ks, p.Ks, atol=1e-4, rtol=0)
    torch.testing.assert_close(q.times, p.times, atol=1e-5, rtol=0)
    r = load_realestate10k(tmp_path / "c.txt", W, H)  # relative to the first camera
    assert torch.equal(r.viewmats[0], torch.eye(4))
    torch.testing.assert_close(r.viewmats, p.relative_to_first().viewmats, atol=1e-5, rtol=0)
    # Intrinsics are normalised: a different image size rescales them.
    s = load_realestate10k(tmp_path / "c.txt", 2 * W, H, relative=False)
    torch.testing.assert_close(s.Ks[:, 0], p.Ks[:, 0] * torch.tensor([2.0, 1.0, 2.0]), atol=1e-4, rtol=0)


def test_realestate10k_without_url_single_frame(tmp_path):
    p = make_trajectory("forward", 1, intrinsics_from_focal(40.0, 40.0, W, H), W, H)
    save_realestate10k(tmp_path / "one.txt", p)
    assert (tmp_path / "one.txt").read_text().split()[0] == "0"
    q = load_realestate10k(tmp_path / "one.txt", W, H)
    assert len(q) == 1 and q.times.tolist() == [0.0]


@pytest.mark.parametrize(
    "text, match",
    [
        ("url\n0 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1\n", r":2: expected 19 values"),
        ("0 0.5 0.5 0.5 0.5 0.1 0 1 0 0 0 0 1 0 0 0 0 1 0\n", "distortion"),
        ("0 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 x\n", "numbers"),
        ("url only\n", "no camera lines"),
        ("5 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n1 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n",
         "non-decreasing"),
        ("5 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n5 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n", "equal"),
        ("0 0.5 0.5 0.5 0.5 0 0 2 0 0 0 0 1 0 0 0 0 1 0\n", r"viewmats\[0\] rotation"),
        ("0 0 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n", r"Ks\[0\] focal"),
    ],
)
def test_realestate10k_errors(tmp_path, text, match):
    (tmp_path / "c.txt").write_text(text)
    with pytest.raises(ValueError, match=match):
        load_realestate10k(tmp_path / "c.txt", W, H)


def test_realestate10k_argument_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_realestate10k(tmp_path / "none.txt", W, H)
    (tmp_path / "c.txt").write_text("0 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ValueError, match="width"):
        load_realestate10k(tmp_path / "c.txt", 0, H)
    p = world_path()
    with pytest.raises(ValueError, match="fps"):
        save_realestate10k(tmp_path / "o.txt", p, fps=0)
    with pytest.raises(ValueError, match="url"):
        save_realestate10k(tmp_path / "o.txt", p, url="a\nb")
    with pytest.raises(ValueError, match="url"):
        save_realestate10k(tmp_path / "o.txt", p, url="12345")
    assert not (tmp_path / "o.txt").exists()
