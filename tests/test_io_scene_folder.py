import json
import os
import signal
import zipfile

import cv2
import numpy as np
import pytest
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.io import MARKER, load_depth_exr, load_ply, load_video, save_ply
from diff4splat.io.scene_folder import (
    DEFORMATION_ARRAYS,
    deflated,
    fill_empty_depth,
    is_layout_file,
    load_deformation,
    load_output_scene,
    save_deformation,
    write_scene_folder,
)
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians


def test_fill_empty_depth_uses_the_far_bound_and_keeps_covered_pixels():
    depths = torch.tensor([[[1.0, 0.0], [3.0, 0.0]]])
    alphas = torch.tensor([[[1.0, 0.0], [0.5, 0.001]]])
    out = fill_empty_depth(depths, alphas, fallback=7.0)
    torch.testing.assert_close(out, torch.tensor([[[1.0, 3.0], [3.0, 3.0]]]))
    torch.testing.assert_close(fill_empty_depth(depths, alphas * 0, fallback=7.0), torch.full_like(depths, 7.0))


def _inputs(T=5, M=10, W=16, H=16, dynamic=True):
    g = torch.Generator().manual_seed(0)
    gs = Gaussians(torch.randn(M, 3, generator=g) + torch.tensor([0, 0, 3.0]), torch.randn(M, 4, generator=g),
                   torch.rand(M, 3, generator=g) * 0.1 + 0.01, torch.rand(M, generator=g) * 0.9 + 0.05,
                   torch.randn(M, 1, 3, generator=g))
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0).expand(T, 3, 3).clone()
    cams = CameraPath(torch.eye(4).repeat(T, 1, 1), K, W, H)
    scene = DynamicGaussians(gs)
    if dynamic:
        dq = torch.zeros(T, M, 4)
        dq[..., 0] = 1
        scene = DynamicGaussians(gs, cams.times, torch.randn(T, M, 3, generator=g) * 0.1, dq, torch.zeros(T, M, 3))
    colors = torch.rand(T, H, W, 3, generator=g)
    alphas = torch.ones(T, H, W)
    depths = torch.rand(T, H, W, generator=g) + 1
    return scene, cams, colors, depths, alphas


def test_folder_has_every_file_and_frames_follow_the_deformation(tmp_path):
    scene, cams, colors, depths, alphas = _inputs()
    write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {"seed": 0})
    out = tmp_path / "out"
    names = sorted(p.name for p in out.iterdir())
    assert names == [MARKER, "cameras.json", "deformation.npz", "depth", "frames", "meta.json", "rgb", "scene.ply",
                     "video.mp4", "viewer.html"]
    assert load_video(out / "video.mp4").shape == (5, 16, 16, 3)
    lossless = np.stack([cv2.imread(str(out / "rgb" / f"{i:04d}.png"))[..., ::-1] for i in range(5)])
    np.testing.assert_array_equal(lossless, np.round(colors.clamp(0, 1).numpy() * 255).astype(np.uint8))
    d = load_deformation(out / "deformation.npz")
    np.testing.assert_allclose(d["d_means"], scene.d_means.numpy())
    for i in range(5):
        np.testing.assert_allclose(load_ply(out / "frames" / f"{i:04d}.ply").means.numpy(),
                                   scene.at(float(cams.times[i])).means.numpy(), atol=1e-6)
        np.testing.assert_allclose(load_depth_exr(out / "depth" / f"{i:04d}.exr"), depths[i].numpy())
    assert json.loads((out / "meta.json").read_text()) == {"seed": 0, "frame_plys": True}


def test_static_scene_writes_no_deformation_and_no_copies_of_scene_ply(tmp_path):
    """A static scene's frames/ held T copies of scene.ply; with temporal support each frame differs, so they stay."""
    scene, cams, colors, depths, alphas = _inputs(dynamic=False)
    write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {})
    out = tmp_path / "out"
    assert not (out / "deformation.npz").exists() and not (out / "frames").exists()
    assert json.loads((out / "meta.json").read_text())["frame_plys"] is False
    assert load_ply(out / "scene.ply").num_gaussians == 10
    g = scene.canonical
    temporal = DynamicGaussians(g, t_means=torch.linspace(0, 1, 10), t_scales=torch.full((10,), 0.2))
    write_scene_folder(tmp_path / "t", temporal, cams, colors, depths, alphas, {})
    first, last = (load_ply(tmp_path / "t" / "frames" / f"{i:04d}.ply").opacities for i in (0, 4))
    assert not torch.allclose(first, last)


def test_failure_part_way_leaves_no_folder(tmp_path):
    scene, cams, colors, depths, alphas = _inputs()
    with pytest.raises(TypeError):
        write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {"bad": object()})
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="frames"):
        write_scene_folder(tmp_path / "out", scene, cams, colors[:2], depths, alphas, {})


# --- reading an output folder back as input: every file checked, every message starting with the file ---------

def _npz(path, **arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def _arrays(T=5, M=10):
    scene, *_ = _inputs(T=T, M=M)
    return {k: getattr(scene, k).numpy() for k in ("times", "d_means", "d_quats", "d_scales")}


def _refused(path, fn, *args, match=""):
    """``fn(*args)`` raises one ValueError line that starts with ``path`` (and contains ``match``)."""
    with pytest.raises(ValueError) as e:
        fn(*args)
    message = str(e.value)
    assert message.startswith(f"{path}: ") and "\n" not in message and match in message, message
    return message


class _Pickled:
    loaded = 0

    def __reduce__(self):
        return (_Pickled._mark, ())

    @staticmethod
    def _mark():
        _Pickled.loaded += 1
        return 0.0


@pytest.mark.parametrize("case", ["truncated", "random_bytes", "npy_not_npz", "pickled_object_array", "unknown_key",
                                  "partial_group", "int_dtype", "complex_dtype", "wrong_trailing_dim", "K_differs",
                                  "M_differs_from_the_ply", "bad_crc", "empty_archive", "npy_header_garbage"])
def test_load_deformation_refuses_corrupt_files_naming_them(tmp_path, case):
    path = tmp_path / "deformation.npz"
    a = _arrays()
    if case == "truncated":
        data = _npz(path, **a).read_bytes()
        for cut in (0, 10, len(data) // 2, len(data) - 30):
            path.write_bytes(data[:cut])
            _refused(path, load_deformation, path, 10)
        return
    if case == "random_bytes":
        path.write_bytes(np.random.default_rng(0).bytes(5000))
    elif case == "npy_not_npz":
        np.save(open(path, "wb"), a["times"])
    elif case == "pickled_object_array":
        _npz(path, **{**a, "times": np.array([_Pickled()] * 5, dtype=object)})
    elif case == "unknown_key":
        _npz(path, **a, extra=np.zeros(3, np.float32))
    elif case == "partial_group":
        _npz(path, **{k: v for k, v in a.items() if k != "d_scales"})
    elif case == "int_dtype":
        _npz(path, **{**a, "d_means": a["d_means"].astype(np.int32)})
    elif case == "complex_dtype":
        _npz(path, **{**a, "d_quats": a["d_quats"].astype(np.complex64)})
    elif case == "wrong_trailing_dim":
        _npz(path, **{**a, "d_quats": a["d_quats"][..., :3]})
    elif case == "K_differs":
        _npz(path, **{**a, "d_scales": a["d_scales"][:4]})
    elif case == "M_differs_from_the_ply":
        _npz(path, **a)
        _refused(path, load_deformation, path, 11, match="M=11")
        assert load_deformation(path, 10).keys() == a.keys()  # the same file fits 10 Gaussians
        return
    elif case == "bad_crc":
        data = bytearray(_npz(path, **a).read_bytes())
        at = data.index(a["d_means"].tobytes()[:16])  # a byte of d_means' data (stored uncompressed)
        data[at] ^= 0xFF
        path.write_bytes(bytes(data))
    elif case == "empty_archive":
        _npz(path)
    elif case == "npy_header_garbage":
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("times.npy", b"\x93NUMPY\x01\x00\x10\x00{not a dict}    \n")
    _refused(path, load_deformation, path, 10)
    assert _Pickled.loaded == 0  # nothing in the file was ever unpickled


def test_load_deformation_round_trip_and_frames_limit(tmp_path, monkeypatch):
    a = _arrays()
    path = _npz(tmp_path / "deformation.npz", **{k: v.astype(np.float64) for k, v in a.items()})
    got = load_deformation(path)
    assert got.keys() == a.keys() and all(v.dtype == np.float32 for v in got.values())
    np.testing.assert_array_equal(got["d_means"], a["d_means"])
    monkeypatch.setenv("DIFF4SPLAT_MAX_FRAMES", "4")  # K = 5 key times: checked from the header, before reading
    _refused(path, load_deformation, path, match="exceeds the limit of 4 frames")


def _layered_scene(M=400, K=5, moving=10, dense=False):
    """A scene of M Gaussians, ``moving`` of them displaced (all with ``dense``), identity rotations and scales,
    trapezoid temporal support: a ``reconstruct``-like deformation, mostly identity rows."""
    scene, *_ = _inputs(T=K, M=M)
    g = torch.Generator().manual_seed(1)
    d_means = torch.randn(K, M, 3, generator=g) * 0.1
    if not dense:
        d_means[:, moving:] = 0
    return DynamicGaussians(scene.canonical, scene.times, d_means, scene.d_quats, scene.d_scales,
                            torch.rand(M, generator=g), torch.full((M,), 0.25), torch.full((M,), 0.25))


def test_save_deformation_deflates_mostly_identity_arrays_and_stores_dense_ones(tmp_path):
    path = tmp_path / "deformation.npz"
    scene = _layered_scene()
    save_deformation(path, scene)
    keys = ("times", "d_means", "d_quats", "d_scales", "t_means", "t_scales", "t_ramps")
    with zipfile.ZipFile(path) as zf:
        infos = {i.filename: i for i in zf.infolist()}
    assert sorted(infos) == sorted(f"{k}.npy" for k in keys)
    assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in infos.values())
    assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in infos.values())  # no clock: the same bytes each time
    fast = path.stat().st_size
    save_deformation(path, scene, level=9)  # the level reaches zlib: smaller at 9 than at 1
    assert path.stat().st_size < fast
    save_deformation(path, scene)
    raw = sum(getattr(scene, k).numel() * 4 for k in keys)
    assert path.stat().st_size < raw / 5  # the identity rows are runs zlib shrinks
    got, plain = load_deformation(path, 400), np.load(path)  # ours and numpy's own reader: the same exact arrays
    for k in keys:
        np.testing.assert_array_equal(got[k], getattr(scene, k).numpy())
        np.testing.assert_array_equal(plain[k], got[k])
    dense = _layered_scene(dense=True)
    save_deformation(path, dense)
    with zipfile.ZipFile(path) as zf:
        methods = {i.filename: i.compress_type for i in zf.infolist()}
    assert methods["d_means.npy"] == zipfile.ZIP_STORED and methods["d_quats.npy"] == zipfile.ZIP_DEFLATED
    np.testing.assert_array_equal(load_deformation(path, 400)["d_means"], dense.d_means.numpy())
    data = bytearray(path.read_bytes())  # a deflated member's stream broken: one error naming the file
    at = data.index(b"t_means.npy") + 40
    data[at:at + 8] = bytes(8)
    path.write_bytes(bytes(data))
    _refused(path, load_deformation, path, 400)
    for level in (0, 10, 1.0, True):
        with pytest.raises(ValueError, match="level must be an int in 1–9"):
            save_deformation(tmp_path / "other.npz", scene, level=level)
    assert not (tmp_path / "other.npz").exists()


def test_deflated_counts_identity_rows_not_values():
    rows = np.zeros((2, 4, 3), np.float32)
    assert deflated("d_means", rows)
    rows[:, :, 1] = 1.0  # two of three values zero in every row, but no row the identity
    assert not deflated("d_means", rows)
    rows[:, :2, 1] = 0.0  # exactly half the rows the identity
    assert deflated("d_means", rows)
    rows[0, 1, 1] = 1.0  # one row fewer
    assert not deflated("d_means", rows)
    quats = np.zeros((1, 4, 4), np.float32)
    quats[..., 0] = 1.0
    assert deflated("d_quats", quats) and not deflated("d_quats", -quats)  # (−1, 0, 0, 0): not the stored identity
    assert not deflated("d_scales", np.full((1, 4, 3), 0.1, np.float32))
    assert deflated("t_means", np.random.default_rng(0).random(8).astype(np.float32))
    big = np.zeros((2, 50_000, 3), np.float32)  # more rows than are sampled: the sample still tells the share
    big[:, ::4, 2] = 0.5
    assert deflated("d_scales", big)
    big[:, 1::4, 2] = big[:, 2::4, 2] = 0.5
    assert not deflated("d_scales", big)


def _folder(tmp_path, dynamic=True, meta=None):
    scene, cams, colors, depths, alphas = _inputs(dynamic=dynamic)
    meta = {"static": scene.is_static, "fps": 8, "background": [0.1, 0.2, 0.3], "eps2d": 0.1} if meta is None else meta
    return write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, meta), scene


def test_load_output_scene_reads_what_write_scene_folder_wrote(tmp_path):
    out, scene = _folder(tmp_path)
    got, meta = load_output_scene(out)
    assert meta["eps2d"] == 0.1 and not got.is_static
    for k in DEFORMATION_ARRAYS[:4]:
        torch.testing.assert_close(getattr(got, k), getattr(scene, k))
    torch.testing.assert_close(got.canonical.means, scene.canonical.means)
    static, _ = _folder(tmp_path / "s", dynamic=False)
    assert load_output_scene(static)[0].is_static


def test_deformation_missing_while_meta_says_the_scene_moves(tmp_path):
    """Before: the scene was silently rendered static (exit 0)."""
    out, _ = _folder(tmp_path)
    (out / "deformation.npz").unlink()
    message = _refused(out / "deformation.npz", load_output_scene, out, match="is missing")
    assert str(out / "meta.json") in message and '"static": false' in message
    _npz(out / "deformation.npz", t_means=np.zeros(10, np.float32), t_scales=np.ones(10, np.float32))
    _refused(out / "deformation.npz", load_output_scene, out, match="holds no deformation")
    (out / "meta.json").write_text(json.dumps({"static": True}))
    load_output_scene(out)  # temporal support alone: static, as meta says
    _npz(out / "deformation.npz", **_arrays())
    _refused(out / "deformation.npz", load_output_scene, out, match='"static": true')


@pytest.mark.parametrize("meta, match", [
    ({"static": "no"}, '"static" must be true or false'),
    ({"static": False, "fps": -1}, '"fps"'),
    ({"static": False, "fps": "8"}, '"fps"'),
    ({"static": False, "background": "red"}, '"background"'),
    ({"static": False, "background": [0, 0, 2]}, '"background"'),
    ({"static": False, "eps2d": 99}, '"eps2d"'),
    ({"static": False, "eps2d": True}, '"eps2d"'),
    ({"static": False, "scene_depth": -1}, '"scene_depth"'),
])
def test_bad_meta_fields_name_meta_json(tmp_path, meta, match):
    out, _ = _folder(tmp_path, meta=meta)
    _refused(out / "meta.json", load_output_scene, out, match=match)


@pytest.mark.parametrize("text, match", [("[1, 2]", "must hold a JSON object"), ("{", "is not valid JSON"),
                                         ("\ud800".encode("utf-8", "surrogatepass"), "not UTF-8")])
def test_meta_json_not_an_object(tmp_path, text, match):
    out, _ = _folder(tmp_path)
    (out / "meta.json").write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ValueError, match=match) as e:
        load_output_scene(out)
    assert str(out / "meta.json") in str(e.value) and "\n" not in str(e.value)


def test_scene_ply_errors_name_it_and_an_empty_scene_is_refused(tmp_path):
    out, scene = _folder(tmp_path)
    data = bytearray((out / "scene.ply").read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body:body + 4] = np.float32(np.inf).tobytes()
    (out / "scene.ply").write_bytes(bytes(data))
    _refused(out / "scene.ply", load_output_scene, out, match="means contains 1 non-finite")
    save_ply(out / "scene.ply", scene.canonical.select(torch.zeros(10, dtype=torch.bool)))
    _refused(out / "scene.ply", load_output_scene, out, match="holds no Gaussians")


def test_a_fifo_or_folder_in_place_of_a_file_is_refused_without_reading_it(tmp_path):
    out, _ = _folder(tmp_path)
    (out / "deformation.npz").unlink()
    os.mkfifo(out / "deformation.npz")  # opening it would block until a writer came
    signal.alarm(20)  # a wrong implementation fails instead of hanging
    try:
        with pytest.raises(ValueError, match="FIFO") as e:
            load_output_scene(out)
    finally:
        signal.alarm(0)
    assert str(out / "deformation.npz") in str(e.value)
    (out / "deformation.npz").unlink()
    (out / "deformation.npz").mkdir()
    with pytest.raises(ValueError, match="is a folder"):
        load_output_scene(out)
    with pytest.raises(FileNotFoundError, match="has no scene.ply"):
        load_output_scene(tmp_path)


@pytest.mark.parametrize("name, ok", [
    ("scene.ply", True), ("viewer.html", True), ("video.mp4", True), ("cameras.json", True), ("meta.json", True),
    ("deformation.npz", True), ("field.safetensors", True), ("metrics.json", True), ("rgb/0000.png", True),
    ("depth/0012.exr", True), ("frames/10000.ply", True), ("rgb/000.png", False), ("rgb/0000.exr", False),
    ("rgb/00a0.png", False), ("rgb/٠٠٠٠.png", False), ("../scene.ply", False), ("rgb/../meta.json", False),
    ("/scene.ply", False), ("a/rgb/0000.png", False), ("notes.txt", False), (MARKER, False), ("", False),
    ("%2e%2e/scene.ply", False), ("rgb%2F0000.png", False), ("scene.ply%00", False), ("rgb\\0000.png", False),
    ("scene.ply/", False), ("rgb//0000.png", False),
])
def test_is_layout_file(name, ok):
    assert is_layout_file(name) is ok
