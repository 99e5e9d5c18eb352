"""Scene format: SceneWriter → SceneReader round trip, atomic writes, writer and meta errors, list_scenes."""
from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest
import torch

from data_prep.format import (
    FORMAT_VERSION,
    SceneMeta,
    SceneWriter,
    list_scenes,
    load_scene,
    timestamps_to_times,
)
from data_prep.validate import validate_scene
from diff4splat.cameras import CameraPath, intrinsics_from_fov, make_trajectory
from diff4splat.io import save_depth_exr, save_image

H, W, T = 6, 8, 3


def _path(name: str = "orbit", width: int = W, height: int = H, times=None) -> CameraPath:
    K = intrinsics_from_fov(width, height, fov_x_deg=60.0)
    p = make_trajectory("pan-left" if name == "pan" else name, T, K, width, height)
    return p if times is None else CameraPath(p.viewmats, p.Ks, width, height, times)


def _data(seed: int = 0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (2, T, H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 9.0, (2, T, H, W)).astype(np.float32)
    depth[0, 1, 2, 3] = np.inf  # an invalid pixel
    points = rng.normal(size=(5, T, 3)).astype(np.float32)
    vis = rng.random((5, T)) < 0.5
    return rgb, depth, points, vis


def write_scene(path, dynamic=True, depth_source="ground_truth", **kw):
    rgb, depth, points, vis = _data()
    timestamps = np.array([10.0, 10.5, 11.0])
    with SceneWriter(path, source="synthetic", dynamic=dynamic, depth_source=depth_source, num_frames=T, fps=2.0,
                     extra={"origin": "test"}, **kw) as w:
        w.add_camera("cam00", _path("orbit"), timestamps)
        w.add_camera("cam01", _path("pan"), timestamps)
        for c, cam in enumerate(("cam00", "cam01")):
            for i in range(T):
                w.write_frame(cam, i, rgb[c, i], depth[c, i] if depth_source != "none" else None)
        w.write_tracks(points if dynamic else np.repeat(points[:, :1], T, 1), vis)
        w.write_caption("a ball rolls to the left\n")
    return rgb, depth, points, vis


def test_round_trip(tmp_path):
    rgb, depth, points, vis = write_scene(tmp_path / "s")
    r = load_scene(tmp_path / "s")
    assert r.meta.format_version == FORMAT_VERSION and r.meta.cameras == ["cam00", "cam01"]
    assert r.meta.extra == {"origin": "test"} and r.meta.dynamic is True and r.meta.fps == 2.0
    assert r.num_frames == T and r.caption == "a ball rolls to the left"
    for c, cam in enumerate(("cam00", "cam01")):
        for i in range(T):
            got = r.rgb(cam, i)
            assert got.dtype == np.float32 and got.shape == (H, W, 3)
            np.testing.assert_array_equal(np.round(got * 255).astype(np.uint8), rgb[c, i])
            np.testing.assert_array_equal(r.depth(cam, i), depth[c, i])  # lossless, inf kept
    assert np.isinf(r.depth("cam00", 1)[2, 3])
    cams = r.cameras("cam01")
    ref = _path("pan")
    torch.testing.assert_close(cams.viewmats, ref.viewmats, rtol=0, atol=0)
    torch.testing.assert_close(cams.Ks, ref.Ks, rtol=0, atol=0)
    np.testing.assert_array_equal(r.timestamps(), [10.0, 10.5, 11.0])
    np.testing.assert_array_equal(r.timestamps("cam01"), [10.0, 10.5, 11.0])
    p, v = r.tracks()
    np.testing.assert_array_equal(p, points)
    np.testing.assert_array_equal(v, vis)
    assert v.dtype == np.bool_ and p.dtype == np.float32
    assert r.video("cam00").shape == (T, H, W, 3)
    meta = json.loads((tmp_path / "s" / "meta.json").read_text())
    assert meta["cameras"] == ["cam00", "cam01"] and meta["depth_source"] == "ground_truth" and meta["origin"] == "test"


def test_default_timestamps_and_times():
    np.testing.assert_allclose(timestamps_to_times(np.array([3.0, 3.25, 4.0])), [0.0, 0.25, 1.0])
    np.testing.assert_array_equal(timestamps_to_times(np.array([5.0])), [0.0])


def test_default_timestamps_follow_times_and_fps(tmp_path):
    times = torch.tensor([0.0, 0.25, 1.0])
    with SceneWriter(tmp_path / "s", source="x", dynamic=False, depth_source="none", num_frames=T, fps=4.0) as w:
        w.add_camera("a", _path(times=times))
        for i in range(T):
            w.write_frame("a", i, np.zeros((H, W, 3)))
    r = load_scene(tmp_path / "s")
    np.testing.assert_allclose(r.timestamps(), [0.0, 0.125, 0.5])  # times·(T−1)/fps
    assert r.tracks() is None and r.caption is None and not r.has_depth
    assert not (tmp_path / "s" / "a" / "depth").exists()
    with pytest.raises(ValueError, match="no depth"):
        r.depth("a", 0)


def test_reader_errors(tmp_path):
    write_scene(tmp_path / "s")
    r = load_scene(tmp_path / "s")
    with pytest.raises(ValueError, match="unknown camera"):
        r.rgb("cam07", 0)
    with pytest.raises(ValueError, match="frame index"):
        r.depth("cam00", T)
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "nope")
    (tmp_path / "s" / "meta.json").write_text('{"format_version": 1}')
    with pytest.raises(ValueError, match="missing key"):
        load_scene(tmp_path / "s")


def test_reader_refuses_frames_validate_refuses(tmp_path):
    """A frame of another size than its camera's and a depth map with NaN, −inf or ≤ 0 values are errors naming
    the file, as `data_prep validate` reports them (fit crashed on the first with an IndexError, and trained on
    the second, back-projecting negative depths behind the camera)."""
    write_scene(tmp_path / "s")
    r = load_scene(tmp_path / "s")
    big = tmp_path / "s" / "cam01" / "rgb" / "00002.png"
    save_image(big, np.zeros((H + 8, W + 8, 3), np.uint8))
    with pytest.raises(ValueError, match=rf"{big}: image is {W + 8}×{H + 8}, cameras.json says {W}×{H}"):
        r.rgb("cam01", 2)
    f = tmp_path / "s" / "cam00" / "depth" / "00001.exr"
    z = np.full((H, W), 2.0, np.float32)
    z[0, :3] = [np.nan, -1.0, 0.0]  # written by another tool (ours refuses NaN and negative depths)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Z": z}).write(str(f))
    with pytest.raises(ValueError, match=rf"{f}: depth must be > 0 metres or \+inf \(invalid\): 1 NaN, 0 -inf, 2"):
        r.depth("cam00", 1)
    save_depth_exr(f, np.full((H // 2, W), 2.0, np.float32))
    with pytest.raises(ValueError, match=rf"{f}: depth is {W}×{H // 2}, cameras.json says {W}×{H}"):
        r.depth("cam00", 1)
    assert {p.file.name for p in validate_scene(tmp_path / "s")} == {"00002.png", "00001.exr"}  # the same two


def test_atomic_failure_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with SceneWriter(tmp_path / "s", source="x", dynamic=True, depth_source="none", num_frames=T, fps=1.0) as w:
            w.add_camera("cam00", _path())
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    # an incomplete scene (a missing frame) is refused on exit, and nothing appears either
    with pytest.raises(ValueError, match=r"misses rgb frame\(s\) \[2\]"):
        with SceneWriter(tmp_path / "s", source="x", dynamic=True, depth_source="none", num_frames=T, fps=1.0) as w:
            w.add_camera("cam00", _path())
            for i in range(T - 1):
                w.write_frame("cam00", i, np.zeros((H, W, 3)))
    assert list(tmp_path.iterdir()) == []


def test_existing_scene_is_kept_unless_replace(tmp_path):
    write_scene(tmp_path / "s")
    with pytest.raises(FileExistsError):
        write_scene(tmp_path / "s")
    write_scene(tmp_path / "s", replace=True)
    assert load_scene(tmp_path / "s").num_frames == T


@pytest.mark.parametrize("depth,match", [
    (np.full((H, W), np.nan, np.float32), "NaN"),
    (np.zeros((H, W), np.float32), "non-positive"),
    (np.full((H, W), -np.inf, np.float32), "-inf"),
    (np.ones((H + 1, W), np.float32), "shape"),
])
def test_writer_rejects_bad_depth(tmp_path, depth, match):
    with pytest.raises(ValueError, match=match):
        with SceneWriter(tmp_path / "s", source="x", dynamic=True, depth_source="ground_truth", num_frames=T,
                         fps=1.0) as w:
            w.add_camera("cam00", _path())
            w.write_frame("cam00", 0, np.zeros((H, W, 3)), depth)
    assert not (tmp_path / "s").exists()


def test_writer_input_errors(tmp_path):
    with SceneWriter(tmp_path / "s", source="x", dynamic=False, depth_source="ground_truth", num_frames=T, fps=1.0,
                     validate=False) as w:
        w.add_camera("cam00", _path(), np.array([0.0, 1.0, 2.0]))
        with pytest.raises(ValueError, match="already added"):
            w.add_camera("cam00", _path())
        with pytest.raises(ValueError, match="not a valid camera folder name"):
            w.add_camera("../x", _path())
        with pytest.raises(ValueError, match="not synchronised"):
            w.add_camera("cam01", _path(), np.array([0.0, 1.0, 2.0]) + 0.5)
        with pytest.raises(ValueError, match="normalised timestamps"):
            w.add_camera("cam02", _path(), np.array([0.0, 1.5, 2.0]))
        with pytest.raises(ValueError, match="unknown camera"):
            w.write_frame("cam09", 0, np.zeros((H, W, 3)), np.ones((H, W)))
        with pytest.raises(ValueError, match="frame index"):
            w.write_frame("cam00", T, np.zeros((H, W, 3)), np.ones((H, W)))
        with pytest.raises(ValueError, match="rgb"):
            w.write_frame("cam00", 0, np.zeros((W, H, 3)), np.ones((H, W)))
        with pytest.raises(ValueError, match="depth must be given"):
            w.write_frame("cam00", 0, np.zeros((H, W, 3)))
        with pytest.raises(ValueError, match="static scene"):
            w.write_tracks(np.random.default_rng(0).normal(size=(2, T, 3)), np.ones((2, T), bool))
        with pytest.raises(ValueError, match="visibility"):
            w.write_tracks(np.zeros((2, T, 3)), np.ones((2, T), np.uint8))
        with pytest.raises(ValueError, match="points"):
            w.write_tracks(np.zeros((2, T + 1, 3)), np.ones((2, T + 1), bool))
        with pytest.raises(ValueError, match="one non-empty line"):
            w.write_caption("two\nlines")
        for i in range(T):
            w.write_frame("cam00", i, np.zeros((H, W, 3)), np.ones((H, W)))


@pytest.mark.parametrize("field,value,match", [
    ("format_version", 2, "format_version"),
    ("dynamic", 1, "dynamic"),
    ("depth_source", "lidar", "depth_source"),
    ("num_frames", 0, "num_frames"),
    ("num_frames", 3.0, "num_frames"),
    ("fps", True, "fps"),
    ("fps", float("inf"), "fps"),
    ("depth_scale", 0.0, "depth_scale"),
    ("cameras", [], "cameras"),
    ("cameras", ["a", "a"], "unique"),
    ("cameras", [".hidden"], "camera folder name"),
    ("source", "", "source"),
])
def test_meta_field_errors(field, value, match):
    good = dict(format_version=1, source="synthetic", dynamic=True, depth_source="none", depth_scale=1.0,
                depth_shift=0.0, num_frames=3, cameras=["cam00"], fps=8.0)
    SceneMeta.from_dict(good)
    with pytest.raises(ValueError, match=match):
        SceneMeta.from_dict({**good, field: value})


def test_list_scenes(tmp_path):
    write_scene(tmp_path / "b")
    write_scene(tmp_path / "a")
    (tmp_path / ".a.tmp").mkdir()
    (tmp_path / ".a.tmp" / "meta.json").write_text("{}")
    (tmp_path / "notes").mkdir()
    (tmp_path / "index.json").write_text("{}")
    assert list_scenes(tmp_path) == [tmp_path / "a", tmp_path / "b"]
    with pytest.raises(FileNotFoundError):
        list_scenes(tmp_path / "missing")

