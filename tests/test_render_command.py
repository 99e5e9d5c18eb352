"""``diff4splat render`` (diff4splat/commands/render.py): re-rendering an output folder along any camera path and
time."""
import json
import re

import cv2
import numpy as np
import psutil
import pytest
import torch
from helpers import perturbed_field

import diff4splat.utils.limits as limits
from diff4splat.cameras import CameraPath, intrinsics_from_fov, look_at, make_trajectory
from diff4splat.cameras.trajectories import check_amplitude
from diff4splat.cli import main
from diff4splat.commands.render import path_scene, rerender, resize_cameras, scene_depth
from diff4splat.commands.view import folder_payload, make_server
from diff4splat.io import MARKER, OutputDirError, load_cameras_json, load_depth_exr, load_video, save_realestate10k
from diff4splat.io.image import read_image
from diff4splat.io.scene_folder import SceneFolder, fill_empty_depth, write_scene_folder
from diff4splat.io.scene_folder import load_scene_folder as _load_scene_folder
from diff4splat.io.video import to_uint8
from diff4splat.render.sequence import render_path
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.errors import one_line
from diff4splat.utils.limits import LimitError
from models.hexplane import load_field, save_field
from training.fit_cli import place_generate_output


def load_scene_folder(folder, device="cpu"):
    """The folder as ``render`` reads it: with its field (models.hexplane.load_field)."""
    return _load_scene_folder(folder, device, load_field=load_field)


W, H, T, M = 24, 16, 5, 40


def _world_pose() -> torch.Tensor:
    """A world-to-camera pose far from the identity: the world frame of a data_prep scene."""
    (vm,) = look_at(torch.tensor([[1.5, -0.4, -0.7]], dtype=torch.float64), torch.tensor([0.2, 0.1, 1.8]))
    return vm.float()


def _scene(first: torch.Tensor, dynamic: bool = True, seed: int = 0) -> DynamicGaussians:
    """M Gaussians about 2 m ahead of the camera ``first`` (world-to-camera), with a deformation at T key times
    that moves them by ~0.15 m between keys."""
    g = torch.Generator().manual_seed(seed)
    cam = torch.randn(M, 3, generator=g) * torch.tensor([0.5, 0.35, 0.2]) + torch.tensor([0.0, 0.0, 2.0])
    c2w = torch.linalg.inv(first)
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    gs = Gaussians(means, torch.randn(M, 4, generator=g), torch.rand(M, 3, generator=g) * 0.08 + 0.04,
                   torch.rand(M, generator=g) * 0.5 + 0.45, torch.randn(M, 1, 3, generator=g))
    if not dynamic:
        return DynamicGaussians(gs)
    dq = torch.zeros(T, M, 4)
    dq[..., 0] = 1
    dq[..., 1:] = torch.randn(T, M, 3, generator=g) * 0.2
    return DynamicGaussians(gs, torch.linspace(0, 1, T), torch.randn(T, M, 3, generator=g) * 0.15, dq,
                            torch.randn(T, M, 3, generator=g) * 0.2)


def _path(first: torch.Tensor, frames: int = T) -> CameraPath:
    K = intrinsics_from_fov(W, H, fov_y_deg=55.0)
    rel = make_trajectory("arc", frames, K, W, H, scene_depth=2.0, amplitude=0.4)
    return CameraPath(rel.viewmats @ first, rel.Ks, W, H, rel.times)  # camera i relative to the first kept


def _folder(tmp_path, first=None, dynamic=True, name="gen"):
    """A generate-like output folder; ``first`` (default I) is the world-to-camera pose of its first camera."""
    first = torch.eye(4) if first is None else first
    scene, cams = _scene(first, dynamic), _path(first)
    colors, depths, alphas = render_path(scene, cams)
    out = write_scene_folder(tmp_path / name, scene, cams, colors, depths, alphas, {"seed": 0})
    return out, scene, cams, (colors, depths, alphas)


def _rgb(out, n):
    return np.stack([read_image(out / "rgb" / f"{i:04d}.png") for i in range(n)])


def _assert_frames(out, scene, cams, tol=1):
    """out/rgb equals the quantised render of the in-memory ``scene`` along ``cams`` (within ``tol`` grey levels:
    scene.ply stores float32 log-scales and logit-opacities), and most pixels exactly."""
    ref = to_uint8(render_path(scene, cams)[0])
    got = _rgb(out, len(cams))
    diff = np.abs(got.astype(int) - ref.astype(int))
    assert got.shape == ref.shape and diff.max() <= tol and (diff == 0).mean() > 0.99, diff.max()


def test_own_cameras_reproduce_the_folder(tmp_path):
    folder, scene, cams, (colors, depths, alphas) = _folder(tmp_path)
    meta = rerender(folder, tmp_path / "r", cameras=folder / "cameras.json")
    out = tmp_path / "r"
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, "cameras.json", "depth", "meta.json", "rgb",
                                                            "video.mp4", "viewer.html"])
    assert json.loads((out / MARKER).read_text())["kind"] == "render"
    _assert_frames(out, scene, cams)
    got = _rgb(out, T)
    assert np.abs(got.astype(int) - to_uint8(colors).astype(int)).max() <= 1  # the folder's own frames
    filled = fill_empty_depth(depths, alphas, 1.0)
    for i in range(T):
        z, a = load_depth_exr(out / "depth" / f"{i:04d}.exr", return_alpha=True)
        np.testing.assert_allclose(z, filled[i].numpy(), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(a, alphas[i].numpy(), atol=1e-4)
    back = load_cameras_json(out / "cameras.json")
    torch.testing.assert_close(back.viewmats, cams.viewmats)
    torch.testing.assert_close(back.times, cams.times)
    assert load_video(out / "video.mp4").shape == (T, H, W, 3)
    assert json.loads((out / "meta.json").read_text()) == meta
    assert (meta["frames"], meta["width"], meta["height"], meta["deformation"]) == (T, W, H, "deformation.npz")
    assert meta["source"] == str(folder) and meta["source_kind"] == "generate"
    assert set(meta["timings_s"]) == {"load", "render", "write", "total"}


def test_static_folder_renders_the_canonical_scene(tmp_path):
    folder, scene, cams, _ = _folder(tmp_path, dynamic=False)
    assert rerender(folder, tmp_path / "r", cameras=folder / "cameras.json")["deformation"] == "static"
    _assert_frames(tmp_path / "r", scene, cams)


def _data_prep_cameras(path, cams: CameraPath, seconds: np.ndarray):
    data = {"width": cams.width, "height": cams.height, "Ks": cams.Ks.double().tolist(),
            "viewmats": cams.viewmats.double().tolist(), "times": cams.times.double().tolist(),
            "timestamps": seconds.tolist()}
    path.write_text(json.dumps(data))
    return path


def test_data_prep_cameras_are_used_as_is_in_the_world_frame(tmp_path):
    """A scene in a world frame where the first camera is not the identity: the file's poses are used as they are
    (re-expressing them relative to their first camera would look elsewhere), with their own times."""
    first = _world_pose()
    folder, scene, cams, _ = _folder(tmp_path, first)
    other = _path(first, 3)
    other = CameraPath(other.viewmats[[2, 1, 0]].contiguous(), other.Ks, W, H, torch.tensor([0.0, 0.5, 1.0]))
    seconds = 12.5 + np.array([0.0, 0.5, 1.0])
    cam_file = _data_prep_cameras(tmp_path / "cam01_cameras.json", other, seconds)
    rerender(folder, tmp_path / "r", cameras=cam_file)
    _assert_frames(tmp_path / "r", scene, other)
    wrong = to_uint8(render_path(scene, other.relative_to_first())[0])
    assert np.abs(_rgb(tmp_path / "r", 3).astype(int) - wrong.astype(int)).max() > 50  # the test can tell


def test_times_between_key_times_interpolate(tmp_path):
    folder, scene, cams, _ = _folder(tmp_path)
    mid = CameraPath(cams.viewmats[[1, 1, 2, 3]].contiguous(), cams.Ks[:4], W, H, torch.tensor([0.1, 0.3, 0.55, 0.9]))
    cam_file = _data_prep_cameras(tmp_path / "mid.json", mid, np.array([0.1, 0.3, 0.55, 0.9]))
    rerender(folder, tmp_path / "r", cameras=cam_file)
    _assert_frames(tmp_path / "r", scene, mid)  # render_path renders DynamicGaussians.at(t)
    nearest = CameraPath(mid.viewmats, mid.Ks, W, H, torch.round(mid.times * (T - 1)) / (T - 1))
    wrong = to_uint8(render_path(scene, nearest)[0])
    assert np.abs(_rgb(tmp_path / "r", 4).astype(int) - wrong.astype(int)).max() > 20  # nearest key differs


def test_field_is_sampled_at_exactly_the_distinct_path_times(tmp_path):
    folder, scene, cams, _ = _folder(tmp_path)
    src = load_scene_folder(folder)
    field = perturbed_field(src.scene.canonical.means)
    times = torch.tensor([0.0, 0.13, 0.13, 0.62, 0.97])
    dyn = path_scene(SceneFolder(src.path, src.scene, src.cameras, src.meta, field), times)
    torch.testing.assert_close(dyn.times, torch.tensor([0.0, 0.13, 0.62, 0.97]))  # distinct, sorted
    for t in times.tolist():
        d_means, d_quats, d_scales = field(src.scene.canonical.means, t)
        expect = DynamicGaussians(src.scene.canonical, torch.tensor([t]), d_means[None], d_quats[None],
                                  d_scales[None]).at(t)
        got = dyn.at(t)
        for name in ("means", "quats", "scales"):
            torch.testing.assert_close(getattr(got, name), getattr(expect, name))
    assert path_scene(src, times) is src.scene  # no field: the folder's interpolated deformation


def test_fit_folder_renders_its_field_safetensors_at_the_path_times(tmp_path):
    """A folder holding field.safetensors (as fit writes it) renders the field sampled at the path's times,
    also between the key times of its deformation.npz, not the npz's interpolation."""
    folder, scene, cams, _ = _folder(tmp_path)
    canonical = load_scene_folder(folder).scene.canonical
    field = perturbed_field(canonical.means)
    save_field(folder / "field.safetensors", field)
    mid = CameraPath(cams.viewmats[[0, 2, 4]].contiguous(), cams.Ks[:3], W, H, torch.tensor([0.1, 0.37, 0.8]))
    cam_file = _data_prep_cameras(tmp_path / "mid.json", mid, np.array([0.1, 0.37, 0.8]))
    meta = rerender(folder, tmp_path / "r", cameras=cam_file)
    assert meta["deformation"] == "field.safetensors"
    sampled = DynamicGaussians(canonical, mid.times, *field.deformations_at(canonical.means, mid.times))
    _assert_frames(tmp_path / "r", sampled, mid, tol=0)
    npz = to_uint8(render_path(scene, mid)[0])
    assert np.abs(_rgb(tmp_path / "r", 3).astype(int) - npz.astype(int)).max() > 20  # the test can tell


def test_trajectory_starts_at_the_folder_first_camera_around_the_scene_depth(tmp_path):
    first = _world_pose()
    folder, scene, cams, (_, depths, alphas) = _folder(tmp_path, first)
    z, a = load_depth_exr(folder / "depth" / "0000.exr", return_alpha=True)
    depth = float(np.median(z[a > 0.5]))
    meta = rerender(folder, tmp_path / "r", trajectory="orbit", frames=4)
    out = load_cameras_json(tmp_path / "r" / "cameras.json")
    assert len(out) == 4 and (out.width, out.height) == (W, H) and meta["scene_depth"] == pytest.approx(depth)
    torch.testing.assert_close(out.viewmats[0], cams.viewmats[0])
    torch.testing.assert_close(out.Ks, cams.Ks[:1].expand(4, 3, 3))
    centre = cams.camera_centers()[0] + depth * torch.linalg.inv(cams.viewmats[0])[:3, 2]  # on the optical axis
    radii = (out.camera_centers() - centre).norm(dim=-1)
    torch.testing.assert_close(radii, torch.full((4,), depth), atol=1e-4, rtol=1e-4)
    _assert_frames(tmp_path / "r", scene, out)


def test_scene_depth_sources(tmp_path):
    folder, scene, cams, _ = _folder(tmp_path)
    src = load_scene_folder(folder)
    z, a = load_depth_exr(folder / "depth" / "0000.exr", return_alpha=True)
    assert scene_depth(src) == pytest.approx(float(np.median(z[a > 0.5])))
    src.meta["scene_depth"] = 3.25
    assert scene_depth(src) == 3.25
    src.meta.clear()
    (folder / "depth" / "0000.exr").unlink()
    assert scene_depth(src) == pytest.approx(float(scene.canonical.means[:, 2].median()))


def test_realestate10k_file_is_placed_at_the_folder_first_camera(tmp_path):
    first = _world_pose()
    folder, scene, cams, _ = _folder(tmp_path, first)
    rel = cams.relative_to_first()
    save_realestate10k(tmp_path / "path.txt", CameraPath(rel.viewmats[:3], rel.Ks[:3], W, H, rel.times[:3]))
    rerender(folder, tmp_path / "r", cameras=tmp_path / "path.txt")
    out = load_cameras_json(tmp_path / "r" / "cameras.json")
    torch.testing.assert_close(out.viewmats, cams.viewmats[:3], atol=1e-5, rtol=0)
    torch.testing.assert_close(out.Ks, cams.Ks[:3], atol=1e-3, rtol=0)


def test_width_height_resize_the_intrinsics_and_odd_sizes_pad_only_the_video(tmp_path):
    folder, scene, cams, _ = _folder(tmp_path)
    assert resize_cameras(cams, width=12).height == 8
    assert resize_cameras(cams) is cams
    rerender(folder, tmp_path / "r", cameras=folder / "cameras.json", width=11, height=7)
    out = load_cameras_json(tmp_path / "r" / "cameras.json")
    assert (out.width, out.height) == (11, 7)
    torch.testing.assert_close(out.Ks, cams.fitted(11, 7).Ks)
    assert read_image(tmp_path / "r" / "rgb" / "0000.png").shape == (7, 11, 3)
    assert load_video(tmp_path / "r" / "video.mp4").shape == (T, 8, 12, 3)
    _assert_frames(tmp_path / "r", scene, out)


def test_bad_folders_raise_naming_them(tmp_path):
    """A missing folder or one without a scene: FileNotFoundError; a file where the folder should be: ValueError
    saying so (issue 81: it was "not found")."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "empty").mkdir()
    for bad, error in (("missing", FileNotFoundError), ("afile", ValueError), ("empty", FileNotFoundError)):
        with pytest.raises(error, match=re.escape(str(tmp_path / bad))):
            load_scene_folder(tmp_path / bad)
        with pytest.raises(error, match=re.escape(str(tmp_path / bad))):
            rerender(tmp_path / bad, tmp_path / "r", trajectory="arc")
    with pytest.raises(ValueError, match="is a regular file, not a folder"):
        load_scene_folder(tmp_path / "afile")
    assert not (tmp_path / "r").exists()


def test_output_never_replaces_a_user_folder_or_the_input(tmp_path):
    folder, *_ = _folder(tmp_path)
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    with pytest.raises(OutputDirError, match="not written by diff4splat"):
        rerender(folder, user, cameras=folder / "cameras.json")
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    before = sorted(p.name for p in folder.iterdir())
    for out in (folder, tmp_path):
        with pytest.raises(OutputDirError, match="input"):
            rerender(folder, out, cameras=folder / "cameras.json", overwrite=True)
    assert sorted(p.name for p in folder.iterdir()) == before
    rerender(folder, tmp_path / "r", cameras=folder / "cameras.json")
    rerender(folder, tmp_path / "r", trajectory="arc", frames=2)  # an earlier render output is replaced
    assert len(list((tmp_path / "r" / "rgb").iterdir())) == 2


def test_exactly_one_camera_source(tmp_path):
    folder, *_ = _folder(tmp_path)
    with pytest.raises(ValueError, match="both"):
        rerender(folder, tmp_path / "r", cameras=folder / "cameras.json", trajectory="arc")
    with pytest.raises(ValueError, match="neither"):
        rerender(folder, tmp_path / "r")
    with pytest.raises(ValueError, match="do not apply to --cameras"):
        rerender(folder, tmp_path / "r", cameras=folder / "cameras.json", frames=3)
    assert not (tmp_path / "r").exists()


def test_cli_render_writes_the_folder_and_reports_it(tmp_path, capsys):
    folder, scene, cams, _ = _folder(tmp_path)
    out = tmp_path / "r"
    code = main(["render", str(folder), "--trajectory", "pan-left", "--frames", "3", "--amplitude", "0.1",
                 "--fps", "7.5", "--quiet", "--out", str(out)])
    assert code == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"wrote {out} (3 frames, {W}x{H})"
    meta = json.loads((out / "meta.json").read_text())
    assert (meta["trajectory"], meta["amplitude"], meta["fps"], meta["frames"]) == ("pan-left", 0.1, 7.5, 3)
    assert cv2.VideoCapture(str(out / "video.mp4")).get(cv2.CAP_PROP_FPS) == 7.5  # a rate that is not an integer
    path = load_cameras_json(out / "cameras.json")
    torch.testing.assert_close(path.camera_centers()[-1], torch.tensor([-0.1 * meta["scene_depth"], 0.0, 0.0]))


@pytest.mark.parametrize("case", ["missing_folder", "both", "neither", "amplitude_with_cameras", "out_is_input",
                                  "user_folder", "missing_cameras", "huge_focal"])
def test_cli_bad_input_one_line_exit_2(tmp_path, capsys, case):
    folder, *_ = _folder(tmp_path)
    out = tmp_path / "r"
    args = ["render", str(folder), "--cameras", str(folder / "cameras.json"), "--quiet", "--out", str(out)]
    if case == "missing_folder":
        args[1] = str(tmp_path / "nope")
    elif case == "both":
        args += ["--trajectory", "arc"]
    elif case == "neither":
        args = args[:2] + args[4:]
    elif case == "amplitude_with_cameras":
        args += ["--amplitude", "0.3"]
    elif case == "out_is_input":
        args[-1] = str(folder)
    elif case == "user_folder":
        out.mkdir()
        (out / "notes.txt").write_text("keep")
    elif case == "huge_focal":  # generate refused this path (field of view 1e-26°); render drew flat frames
        cam = json.loads((folder / "cameras.json").read_text())
        cam["Ks"] = [[[1e30, 0.0, k[0][2]], [0.0, 1e30, k[1][2]], [0.0, 0.0, 1.0]] for k in cam["Ks"]]
        (tmp_path / "huge.json").write_text(json.dumps(cam))
        args[3] = str(tmp_path / "huge.json")
    else:
        args[3] = str(tmp_path / "none.json")
    before = sorted(p.name for p in folder.iterdir())
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("diff4splat: error:"), err
    assert case != "huge_focal" or "field of view" in lines[0]
    assert sorted(p.name for p in folder.iterdir()) == before
    assert (sorted(p.name for p in out.iterdir()) == ["notes.txt"]) if case == "user_folder" else not out.exists()


def _fit_like_folder(tmp_path):
    """A folder with a deformation.npz and a field.safetensors (what fit writes), and a camera file of 3 cameras at
    times between the npz's key times."""
    folder, scene, cams, _ = _folder(tmp_path)
    field = perturbed_field(load_scene_folder(folder).scene.canonical.means)
    save_field(folder / "field.safetensors", field)
    mid = CameraPath(cams.viewmats[[0, 2, 4]].contiguous(), cams.Ks[:3], W, H, torch.tensor([0.1, 0.37, 0.8]))
    return folder, field, _data_prep_cameras(tmp_path / "mid.json", mid, np.array([0.1, 0.37, 0.8]))


def test_rerender_on_each_device(tmp_path, device):
    """The scene, its field and the cameras are moved to ``device``; the frames equal the CPU's (on CUDA within
    a few grey levels: gsplat, docs/DESIGN.md "The renderer") and the files are written as on the CPU."""
    folder, _, cam_file = _fit_like_folder(tmp_path)
    meta = rerender(folder, tmp_path / "dev", cameras=cam_file, device=device)
    rerender(folder, tmp_path / "cpu", cameras=cam_file, device="cpu")
    assert meta["device"] == str(device) and meta["deformation"] == "field.safetensors"
    got, ref = _rgb(tmp_path / "dev", 3).astype(int), _rgb(tmp_path / "cpu", 3).astype(int)
    diff = np.abs(got - ref)
    if device.type == "cpu":
        assert diff.max() == 0
    else:
        assert diff.max() <= 3 and (diff == 0).mean() > 0.9, diff.max()
    for i in range(3):
        z, a = load_depth_exr(tmp_path / "dev" / "depth" / f"{i:04d}.exr", return_alpha=True)
        z0, a0 = load_depth_exr(tmp_path / "cpu" / "depth" / f"{i:04d}.exr", return_alpha=True)
        np.testing.assert_allclose(a, a0, atol=0 if device.type == "cpu" else 0.02)
    src = load_scene_folder(folder, device)
    assert src.scene.canonical.means.device.type == device.type and src.cameras.viewmats.device.type == "cpu"
    assert next(src.field.parameters()).device.type == device.type
    dyn = path_scene(src, torch.tensor([0.1, 0.8]))
    assert dyn.d_means.device.type == device.type


def test_load_path_scene_and_rerender_make_nothing_on_the_default_device(tmp_path, no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py) a folder is read, its field sampled at the path's
    times and the scene rendered and written, all on the CPU."""
    with torch.device("cpu"):
        folder, field, cam_file = _fit_like_folder(tmp_path)
        times = torch.tensor([0.1, 0.37, 0.8])
    src = load_scene_folder(folder)
    assert src.scene.canonical.means.device.type == "cpu" and next(src.field.parameters()).device.type == "cpu"
    dyn = path_scene(src, times)
    assert dyn.d_means.device.type == "cpu" and dyn.times.device.type == "cpu"
    assert scene_depth(src) > 0
    meta = rerender(folder, tmp_path / "r", cameras=cam_file, device="cpu")
    assert meta["frames"] == 3 and meta["device"] == "cpu"


def test_a_preset_path_makes_nothing_on_the_default_device(tmp_path, no_implicit_device):
    """A preset trajectory (scene depth, placement) under torch's default device "meta" stays on the CPU."""
    with torch.device("cpu"):
        folder, *_ = _folder(tmp_path)
    assert rerender(folder, tmp_path / "t", trajectory="orbit", frames=2)["frames"] == 2


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cli_render_on_a_missing_device_is_one_line_exit_2(tmp_path, capsys):
    folder, *_ = _folder(tmp_path)
    code = main(["render", str(folder), "--trajectory", "arc", "--quiet", "--device", "cuda", "--out",
                 str(tmp_path / "r")])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error: --device: cuda is not available")
    assert not (tmp_path / "r").exists()
    with pytest.raises(ValueError, match="device: cuda is not available"):
        rerender(folder, tmp_path / "r", trajectory="arc", device="cuda")


# --- the folder is input: every file checked, named in one line (issue 28) ------------------------------------------

def _set_meta(folder, **fields):
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, **fields}))


def _patch_npz(folder, **changes):
    with np.load(folder / "deformation.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    with open(folder / "deformation.npz", "wb") as f:
        np.savez(f, **arrays)


def _first_vertex(folder, value):
    data = bytearray((folder / "scene.ply").read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body:body + 4] = np.float32(value).tobytes()
    (folder / "scene.ply").write_bytes(bytes(data))


CORRUPTIONS = {  # case: (damage, the file the message starts with, a word it contains)
    "npz_truncated": (lambda f: (f / "deformation.npz").write_bytes((f / "deformation.npz").read_bytes()[:700]),
                      "deformation.npz", "not a readable .npz"),
    "npz_random_bytes": (lambda f: (f / "deformation.npz").write_bytes(np.random.default_rng(0).bytes(4000)),
                         "deformation.npz", "not a readable .npz"),
    "npz_pickled_objects": (lambda f: _patch_npz(f, times=np.array([0.0, 0.25, 0.5, 0.75, 1.0], dtype=object)),
                            "deformation.npz", "dtype object"),
    "npz_wrong_key": (lambda f: _patch_npz(f, d_means=None, offsets=np.zeros((T, M, 3), np.float32)),
                      "deformation.npz", "unexpected entries"),
    "npz_wrong_shape": (lambda f: _patch_npz(f, d_means=np.zeros((T, M - 1, 3), np.float32)),
                        "deformation.npz", "must have shape"),
    "npz_wrong_dtype": (lambda f: _patch_npz(f, d_scales=np.zeros((T, M, 3), np.int64)),
                        "deformation.npz", "floating-point"),
    "npz_nan": (lambda f: _patch_npz(f, d_means=np.full((T, M, 3), np.nan, np.float32)),
                "deformation.npz", "non-finite"),
    "npz_times_decreasing": (lambda f: _patch_npz(f, times=np.linspace(1, 0, T, dtype=np.float32)),
                             "deformation.npz", "increasing"),
    "npz_missing_but_meta_says_dynamic": (lambda f: (f / "deformation.npz").unlink(), "deformation.npz",
                                          '"static": false'),
    "npz_present_but_meta_says_static": (lambda f: _set_meta(f, static=True), "deformation.npz", '"static": true'),
    "ply_nan": (lambda f: _first_vertex(f, np.nan), "scene.ply", "non-finite"),
    "ply_truncated": (lambda f: (f / "scene.ply").write_bytes((f / "scene.ply").read_bytes()[:900]),
                      "scene.ply", "truncated"),
    "ply_garbage": (lambda f: (f / "scene.ply").write_bytes(np.random.default_rng(1).bytes(3000)),
                    "scene.ply", "not a PLY"),
    "meta_bad_field": (lambda f: _set_meta(f, background="red"), "meta.json", '"background"'),
    "cameras_missing_key": (lambda f: (f / "cameras.json").write_text('{"width": 24, "height": 16}'),
                            "cameras.json", "missing key"),
    "cameras_bad_shape": (lambda f: (f / "cameras.json").write_text(
        '{"width": 24, "height": 16, "Ks": [[1, 2]], "viewmats": [[1]]}'), "cameras.json", "shape"),
    "depth_exr_garbage": (lambda f: (f / "depth" / "0000.exr").write_bytes(b"not an exr"), "depth/0000.exr", "EXR"),
}


@pytest.mark.parametrize("camera_source", ["trajectory", "cameras"])
@pytest.mark.parametrize("case", sorted(CORRUPTIONS))
def test_cli_corrupt_folder_is_one_line_naming_the_file(tmp_path, capsys, case, camera_source):
    """Before: BadZipFile/pickle tracebacks, messages without the file, and a dynamic folder without its
    deformation.npz rendered static with exit 0."""
    folder, *_ = _folder(tmp_path)
    _set_meta(folder, static=False)
    cam_file = tmp_path / "path.json"  # an intact camera file: the folder's own, copied before the damage
    cam_file.write_bytes((folder / "cameras.json").read_bytes())
    damage, name, word = CORRUPTIONS[case]
    damage(folder)
    out = tmp_path / "r"
    source = ["--trajectory", "arc"] if camera_source == "trajectory" else ["--cameras", str(cam_file)]
    code = main(["render", str(folder), *source, "--quiet", "--out", str(out)])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, lines
    assert str(folder / name) in lines[0] and word in lines[0], lines[0]
    if not case.startswith(("meta", "cameras", "depth")):  # JSON/EXR readers say "<what>: <path> …"
        assert lines[0].startswith(f"diff4splat: error: {folder / name}: "), lines[0]
    assert not out.exists()


def test_the_folder_readers_share_the_checks(tmp_path):
    """render, view and fit --init read a folder through one validated reader."""
    folder, *_ = _folder(tmp_path)
    (folder / "deformation.npz").write_bytes(b"PK\x03\x04 truncated")
    readers = [load_scene_folder, folder_payload, lambda f: make_server(f, 0),
               lambda f: place_generate_output(f, None, "cam00")]  # fails on the folder before the scene is used
    for read in readers:
        with pytest.raises(ValueError) as e:
            read(folder)
        assert str(e.value).startswith(f"{folder / 'deformation.npz'}: not a readable .npz archive"), e.value


def test_amplitude_is_checked_as_generate_checks_it(tmp_path, capsys):
    """Before: --trajectory forward --amplitude 1e30 wrote black frames with exit 0. The preset's amplitude goes
    through generate's check (diff4splat.cameras.trajectories.check_amplitude) before the folder is read."""

    folder, *_ = _folder(tmp_path)
    (folder / "scene.ply").write_bytes(b"garbage")  # never read: the amplitude is refused first
    for trajectory, amplitude in (("forward", "1e30"), ("arc", "10"), ("pan-left", "-0.1"), ("orbit", "0.3"),
                                  ("spiral", "nan")):
        with pytest.raises(ValueError) as want:
            check_amplitude(trajectory, float(amplitude), "--amplitude")
        code = main(["render", str(folder), "--trajectory", trajectory, "--amplitude", amplitude, "--quiet",
                     "--out", str(tmp_path / "r")])
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert code == 2 and err == [f"diff4splat: error: {one_line(want.value)}"], err
    assert not (tmp_path / "r").exists()


def test_frames_and_output_size_go_through_the_limits(tmp_path, monkeypatch):
    folder, *_ = _folder(tmp_path)
    monkeypatch.setenv("DIFF4SPLAT_MAX_FRAMES", "3")
    (folder / "scene.ply").write_bytes(b"garbage")  # never read: the frame count is refused first
    with pytest.raises(LimitError, match="frames 4 exceeds the limit of 3 frames"):
        rerender(folder, tmp_path / "r", trajectory="arc", frames=4)
    folder, *_ = _folder(tmp_path, name="gen2")
    with pytest.raises(LimitError, match="deformation.npz: a deformation of 5 exceeds"):  # its 5 key times
        rerender(folder, tmp_path / "r", trajectory="arc", frames=2)
    static, *_ = _folder(tmp_path, dynamic=False, name="static")
    with pytest.raises(LimitError, match="cameras.json: a camera path of 5 exceeds"):
        rerender(static, tmp_path / "r", trajectory="arc", frames=2)
    monkeypatch.delenv("DIFF4SPLAT_MAX_FRAMES")
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", str(T * W * H * 16 - 1))
    with pytest.raises(LimitError, match=f"output of {T} frames at {W}×{H}"):
        rerender(folder, tmp_path / "r", cameras=folder / "cameras.json")
    with pytest.raises(LimitError, match="output of 2 frames at 2000×1000"):
        rerender(folder, tmp_path / "r", trajectory="arc", frames=2, width=2000, height=1000)
    assert not (tmp_path / "r").exists()


def test_a_path_that_sees_none_of_the_scene_is_refused(tmp_path):
    """As generate refuses a camera path that sees none of its scene: every frame would be the background."""
    folder, _, cams, _ = _folder(tmp_path)
    away = cams.viewmats.clone()
    away[:, :3, :] = -away[:, :3, :]  # turned around: the scene is behind every camera
    away[:, 1, :] = -away[:, 1, :]  # (a rotation, det +1)
    cam_file = _data_prep_cameras(tmp_path / "away.json", CameraPath(away, cams.Ks, W, H, cams.times),
                                  np.zeros(T))
    with pytest.raises(ValueError, match="sees none of the scene: all 5 frames"):
        rerender(folder, tmp_path / "r", cameras=cam_file)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("width, height", [(1, 100_000), (8192, 8)])
def test_a_size_mp4_cannot_hold_is_refused_before_rendering(tmp_path, capsys, monkeypatch, width, height):
    """``render --width 1 --height 100000`` rendered every frame, then died in OpenCV's video writer (issue 61):
    MPEG-4 allows at most 8190 pixels a side, checked before any frame is rendered."""
    folder, *_ = _folder(tmp_path)
    monkeypatch.setattr("diff4splat.commands.render.render_path", _never)
    code = main(["render", str(folder), "--trajectory", "arc", "--frames", "2", "--width", str(width), "--height",
                 str(height), "--quiet", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "MPEG-4 allows at most 8190 pixels a side" in err, err
    assert not (tmp_path / "r").exists()


def _never(*args, **kwargs):
    raise AssertionError("rendered before the size check")


def test_render_checks_its_memory_against_what_the_process_may_use_before_rendering(tmp_path, capsys, monkeypatch):
    """With room for less than the estimate (the machine's, a cgroup's or a ulimit's: limits.available_memory),
    ``render`` is one line naming the request and the knobs, exit 2, before any frame; with room it renders."""
    folder, *_ = _folder(tmp_path)
    monkeypatch.setattr("diff4splat.commands.render.render_path", _never)
    monkeypatch.setattr(limits, "available_memory", lambda: psutil.Process().memory_info().rss + (64 << 20))
    code = main(["render", str(folder), "--trajectory", "arc", "--frames", "3", "--quiet", "--out",
                 str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "estimated peak memory" in err and "--width or --height" in err, err
    assert not (tmp_path / "r").exists()
