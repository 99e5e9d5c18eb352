"""Tests for the converters of the 4D reconstruction benchmarks (data_prep.converters: dnerf, n3dv, hypernerf).

Kept apart from test_data_converters.py (the other nine sources) only for file length; same method.
Each fixture writes a tiny dataset in the source's native layout with a known 3D point, projects it
with the source's own camera convention written here independently of the converter (Blender/OpenGL
for D-NeRF, LLFF [down, right, backward] columns for N3DV, nerfies' ``Camera.project`` with lens
distortion for HyperNeRF) and draws it at that pixel. After conversion the point must project
through our world-to-camera OpenCV ``viewmats`` and pixel ``Ks`` to the same pixel, the drawn mark
must be found there in the converted frames, and ``validate_scene`` must accept the scene.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from data_prep.convert_cli import main
from data_prep.converters import convert
from data_prep.converters.hypernerf import undistort_rgb
from data_prep.format import load_scene
from data_prep.validate import validate_scene

P = np.array([0.3, -0.2, 0.4])  # the known point, source world units


def look_at(center, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """World-to-camera (4, 4) with OpenCV axes (x right, y down, z forward) looking at ``target``."""
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, np.cross(z, x), z])
    V[:3, 3] = -V[:3, :3] @ c
    return V


def centres(n, radius=4.0, phase=0.0):
    return [(radius * math.cos(phase + 0.4 * i), radius * math.sin(phase + 0.4 * i), 1.0 + 0.2 * i) for i in range(n)]


def project(scene, cam, i, point):
    """Pixel of ``point`` through the converted scene's camera ``cam`` at frame i (checks z > 0)."""
    path = scene.cameras(cam)
    V, K = path.viewmats.double().numpy()[i], path.Ks.double().numpy()[i]
    x = V[:3, :3] @ point + V[:3, 3]
    assert x[2] > 0
    return (K @ (x / x[2]))[:2]


def blob(w, h, uv, sigma=1.2):
    """(h, w, 3) uint8 grey Gaussian blob centred at continuous pixel ``uv`` (pixel centres at +0.5)."""
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    g = 255.0 * np.exp(-((jj - uv[0]) ** 2 + (ii - uv[1]) ** 2) / (2 * sigma ** 2))
    return np.repeat(np.round(g).astype(np.uint8)[..., None], 3, axis=-1)


def centroid(rgb):
    """Intensity-weighted centroid (u, v) of an (H, W, 3) image in [0, 1], pixel centres at +0.5."""
    g = rgb.mean(-1)
    g = np.where(g > 0.1 * g.max(), g, 0.0)
    ii, jj = np.nonzero(g)
    w = g[ii, jj]
    return np.array([(w * (jj + 0.5)).sum(), (w * (ii + 0.5)).sum()]) / w.sum()


def imwrite(path: Path, img):
    path.parent.mkdir(parents=True, exist_ok=True)
    code = cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR
    assert cv2.imwrite(str(path), cv2.cvtColor(img, code))


# ------------------------------------------------------------------------------------------- D-NeRF
DN_W, DN_H, DN_F = 24, 16, 20.0


def make_dnerf(root: Path, split="train", times=(0.5, 0.0, 1.0)):
    """Blender layout; frames listed out of time order; returns {time: native pixel of P}."""
    frames, uv = [], {}
    for i, (t, c) in enumerate(zip(times, centres(len(times)), strict=True)):
        c2w_cv = np.linalg.inv(look_at(c))
        c2w_gl = c2w_cv.copy()
        c2w_gl[:3, 1:3] *= -1  # camera y up, z backward
        pc = c2w_gl[:3, :3].T @ (P - c2w_gl[:3, 3])  # Blender camera coordinates: looks down −z
        uv[t] = np.array([DN_W / 2 + DN_F * pc[0] / -pc[2], DN_H / 2 - DN_F * pc[1] / -pc[2]])
        img = np.zeros((DN_H, DN_W, 4), np.uint8)
        img[..., :3] = np.random.default_rng(i).integers(0, 255, (DN_H, DN_W, 3))  # hidden by alpha 0
        img[int(uv[t][1]), int(uv[t][0])] = (255, 0, 0, 255)
        img[0, 0] = (0, 0, 255, 128)  # half-transparent blue
        imwrite(root / split / f"r_{i:03d}.png", img)
        frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t, "rotation": 0.1,
                       "transform_matrix": c2w_gl.tolist()})
    angle = 2 * math.atan(DN_W / 2 / DN_F)
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return uv


def test_dnerf_point_reprojects_and_times_are_the_datasets(tmp_path):
    uv = make_dnerf(tmp_path / "lego")
    out = convert("dnerf", tmp_path / "lego", tmp_path / "s")
    assert validate_scene(out) == []
    scene = load_scene(out)
    assert scene.meta.source == "dnerf" and scene.meta.dynamic and scene.meta.depth_source == "none"
    assert scene.camera_names == ["cam00"] and scene.num_frames == 3
    path = scene.cameras("cam00")
    np.testing.assert_allclose(path.times.numpy(), [0.0, 0.5, 1.0], atol=1e-9)  # sorted, equal to 'time'
    assert (path.width, path.height) == (DN_W, DN_H)
    for i, t in enumerate((0.0, 0.5, 1.0)):
        np.testing.assert_allclose(project(scene, "cam00", i, P), uv[t], atol=1e-6)
        rgb = np.round(scene.rgb("cam00", i) * 255)
        np.testing.assert_array_equal(rgb[int(uv[t][1]), int(uv[t][0])], [255, 0, 0])
        np.testing.assert_array_equal(rgb[DN_H - 1, DN_W - 1], [255, 255, 255])  # alpha 0 → white
        np.testing.assert_array_equal(rgb[0, 0], [127, 127, 255])  # blue·a + white·(1 − a), a = 128/255


def test_dnerf_downscale_black_background_and_refused_times(tmp_path):
    uv = make_dnerf(tmp_path / "lego")
    scene = load_scene(convert("dnerf", tmp_path / "lego", tmp_path / "s", downscale=2, background="black"))
    assert (scene.cameras("cam00").width, scene.cameras("cam00").height) == (DN_W // 2, DN_H // 2)
    for i, t in enumerate((0.0, 0.5, 1.0)):
        np.testing.assert_allclose(project(scene, "cam00", i, P), uv[t] / 2, atol=1e-6)
        rgb = scene.rgb("cam00", i)
        red = rgb[..., 0] - rgb[..., 1]
        assert np.unravel_index(red.argmax(), red.shape) == (int(uv[t][1] // 2), int(uv[t][0] // 2))
        assert rgb[-1, -1].max() == 0.0  # black background
    make_dnerf(tmp_path / "lego", split="val", times=(0.25, 0.75))
    with pytest.raises(ValueError, match=r"span \[0.25, 0.75\], not \[0, 1\]"):
        convert("dnerf", tmp_path / "lego", tmp_path / "v", split="val")
    with pytest.raises(ValueError, match="span"):  # a selection that drops time 1
        convert("dnerf", tmp_path / "lego", tmp_path / "v", max_frames=2)


def test_dnerf_bad_inputs(tmp_path):
    root = tmp_path / "lego"
    with pytest.raises(FileNotFoundError, match="source folder not found"):
        convert("dnerf", root, tmp_path / "o")
    root.mkdir()
    with pytest.raises(FileNotFoundError, match="transforms_train.json"):
        convert("dnerf", root, tmp_path / "o")
    make_dnerf(root)
    with pytest.raises(ValueError, match="background"):
        convert("dnerf", root, tmp_path / "o", background="grey")
    with pytest.raises(ValueError, match="downscale"):
        convert("dnerf", root, tmp_path / "o", downscale=0)
    meta = json.loads((root / "transforms_train.json").read_text())
    for field, value, match in (("camera_angle_x", None, "camera_angle_x"), ("time", "x", r"frames\[1\]\['time'\]"),
                                ("transform_matrix", [[1, 0]], r"frames\[1\]\['transform_matrix'\]")):
        bad = json.loads(json.dumps(meta))
        if field == "camera_angle_x":
            del bad[field]
        else:
            bad["frames"][1][field] = value
        (root / "transforms_train.json").write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=match):
            convert("dnerf", root, tmp_path / "o")
    (root / "transforms_train.json").write_text(json.dumps(meta))
    (root / "train" / "r_001.png").unlink()
    with pytest.raises(FileNotFoundError, match="r_001.png"):
        convert("dnerf", root, tmp_path / "o")


# --------------------------------------------------------------------------------------------- N3DV
NV_W, NV_H, NV_F, NV_T, NV_FPS = 48, 32, 30.0, 4, 30


def make_n3dv(root: Path, n_cams=3):
    """LLFF layout, hwf given at twice the video resolution; returns per camera the video pixel of P."""
    rows, uv = [], {}
    for k, c in enumerate(centres(n_cams, phase=0.3)):
        c2w = np.linalg.inv(look_at(c))
        R, t = c2w[:3, :3], c2w[:3, 3]
        llff = np.column_stack([R[:, 1], R[:, 0], -R[:, 2], t, [2 * NV_H, 2 * NV_W, 2 * NV_F]])  # down, right, back
        rows.append(np.concatenate([llff.reshape(-1), [0.5 + k, 20.0]]))
        d, r, b = llff[:, :3].T @ (P - t)  # LLFF camera coordinates (down, right, backward)
        uv[f"cam{k:02d}"] = np.array([NV_W / 2 + NV_F * r / -b, NV_H / 2 + NV_F * d / -b])
        vw = cv2.VideoWriter(str(root / f"cam{k:02d}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), NV_FPS, (NV_W, NV_H))
        for _ in range(NV_T):
            vw.write(blob(NV_W, NV_H, uv[f"cam{k:02d}"], sigma=2.0))
        vw.release()
    np.save(root / "poses_bounds.npy", np.stack(rows))
    return uv


def test_n3dv_llff_axes_reproject(tmp_path):
    root = tmp_path / "flame_steak"
    root.mkdir()
    uv = make_n3dv(root)
    out = convert("n3dv", root, tmp_path / "s")
    assert validate_scene(out) == []
    scene = load_scene(out)
    assert scene.camera_names == ["cam00", "cam01", "cam02"] and scene.num_frames == NV_T
    assert scene.meta.fps == NV_FPS and scene.meta.extra["near_far"]["cam01"] == [1.5, 20.0]
    np.testing.assert_allclose(scene.timestamps(), np.arange(NV_T) / NV_FPS)
    for cam, p in uv.items():
        for i in range(NV_T):
            np.testing.assert_allclose(project(scene, cam, i, P), p, atol=1e-6)
        np.testing.assert_allclose(centroid(scene.rgb(cam, 1)), p, atol=0.5)  # the drawn point is there


def test_n3dv_camera_subset_downscale_stride(tmp_path):
    root = tmp_path / "n3dv"
    root.mkdir()
    uv = make_n3dv(root)
    scene = load_scene(convert("n3dv", root, tmp_path / "s", cameras=("cam02", "cam00"), downscale=2, stride=2))
    assert scene.camera_names == ["cam02", "cam00"] and scene.num_frames == 2 and scene.meta.fps == NV_FPS / 2
    np.testing.assert_allclose(scene.timestamps(), [0.0, 2 / NV_FPS])
    assert (scene.cameras("cam00").width, scene.cameras("cam00").height) == (NV_W // 2, NV_H // 2)
    for cam in ("cam02", "cam00"):
        np.testing.assert_allclose(project(scene, cam, 1, P), uv[cam] / 2, atol=1e-6)
        np.testing.assert_allclose(centroid(scene.rgb(cam, 0)), uv[cam] / 2, atol=0.5)


def test_n3dv_bad_inputs(tmp_path):
    root = tmp_path / "n3dv"
    root.mkdir()
    with pytest.raises(FileNotFoundError, match="poses_bounds.npy"):
        convert("n3dv", root, tmp_path / "o")
    make_n3dv(root)
    with pytest.raises(ValueError, match="cameras must be"):
        convert("n3dv", root, tmp_path / "o", cameras=("cam07",))
    pb = np.load(root / "poses_bounds.npy")
    np.save(root / "poses_bounds.npy", pb[:, :16])
    with pytest.raises(ValueError, match=r"\(N_cams, 17\)"):
        convert("n3dv", root, tmp_path / "o")
    np.save(root / "poses_bounds.npy", pb[:2])
    with pytest.raises(ValueError, match="2 rows but .* 3 cam"):
        convert("n3dv", root, tmp_path / "o")
    bad = pb.copy()
    bad[0, 14] = 3 * NV_F  # the focal stays, the hwf width no longer matches the video's aspect
    bad[0, 9] = 5 * NV_W
    np.save(root / "poses_bounds.npy", bad)
    with pytest.raises(ValueError, match="aspect"):
        convert("n3dv", root, tmp_path / "o")


# ---------------------------------------------------------------------------------------- HyperNeRF
HN_W, HN_H, HN_F, HN_C, HN_RATIO = 48, 36, 40.0, (23.0, 17.5), 1.05
RADIAL, TANGENTIAL = (0.8, 0.1, 0.0), (0.01, -0.01)
SCENE = {"center": [0.1, 0.2, -0.1], "scale": 0.5, "near": 0.1, "far": 4.0}


def tilt(yaw, pitch):
    """Rotation of the camera about its y then x axis (so that P leaves the optical axis)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    return np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])


def nerfies_project(orientation, position, point, distorted=True):
    """nerfies ``Camera.project`` (camera.py), written out: distortion, then focal, ratio, principal point."""
    x, y, z = orientation @ (point - position)
    x, y = x / z, y / z
    if distorted:
        k1, k2, k3 = RADIAL
        p1, p2 = TANGENTIAL
        r2 = x * x + y * y
        d = 1 + r2 * (k1 + r2 * (k2 + k3 * r2))
        x, y = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * d + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    return np.array([HN_F * x + HN_C[0], HN_F * HN_RATIO * y + HN_C[1]])


def make_hypernerf(root: Path, times={0: (0, 1, 2), 1: (0, 1, 5)}):  # noqa: B006 (read-only default)
    """A vrig capture: camera 0 = left at time_ids 0, 1, 2; camera 1 = right at 0, 1, 5. Returns
    {(camera_id, time_id): undistorted native pixel of P}."""
    meta, ids, uv = {}, {0: [], 1: []}, {}
    for cam_id, tids in times.items():
        for t in tids:
            V = look_at(np.array(centres(6, phase=0.2)[t]) + [0.0, 0.3 * cam_id, 0.0], target=P)
            R, pos = tilt(-0.26 - 0.01 * t, 0.2 + 0.02 * cam_id) @ V[:3, :3], -V[:3, :3].T @ V[:3, 3]  # P off-axis
            item = f"{('left', 'right')[cam_id]}_{t:06d}"
            ids[cam_id].append(item)
            meta[item] = {"time_id": t, "warp_id": t, "appearance_id": t, "camera_id": cam_id}
            cam = {"orientation": R.tolist(), "position": pos.tolist(), "focal_length": HN_F,
                   "principal_point": list(HN_C), "skew": 0.0, "pixel_aspect_ratio": HN_RATIO,
                   "radial_distortion": list(RADIAL), "tangential_distortion": list(TANGENTIAL),
                   "image_size": [HN_W, HN_H]}
            (root / "camera").mkdir(parents=True, exist_ok=True)
            (root / "camera" / f"{item}.json").write_text(json.dumps(cam))
            ud, uv[cam_id, t] = nerfies_project(R, pos, P), nerfies_project(R, pos, P, distorted=False)
            assert np.linalg.norm(ud - uv[cam_id, t]) > 1.2  # the distortion is large enough to matter
            img = blob(HN_W, HN_H, ud)
            imwrite(root / "rgb" / "1x" / f"{item}.png", img)
            imwrite(root / "rgb" / "2x" / f"{item}.png", cv2.resize(img, (HN_W // 2, HN_H // 2),
                                                                     interpolation=cv2.INTER_AREA))
    all_ids = ids[0] + ids[1]
    (root / "dataset.json").write_text(json.dumps({"count": len(all_ids), "num_exemplars": len(ids[0]),
                                                   "ids": all_ids, "train_ids": ids[0], "val_ids": ids[1]}))
    (root / "metadata.json").write_text(json.dumps(meta))
    (root / "scene.json").write_text(json.dumps(SCENE))
    return uv


def test_hypernerf_vrig_undistorted_point_reprojects(tmp_path):
    uv = make_hypernerf(tmp_path / "broom")
    out = convert("hypernerf", tmp_path / "broom", tmp_path / "s")
    assert validate_scene(out) == []
    scene = load_scene(out)
    assert scene.camera_names == ["cam00", "cam01"] and scene.num_frames == 2  # time_ids both cameras have
    assert scene.meta.extra["camera_ids"] == {"cam00": 0, "cam01": 1}
    np.testing.assert_allclose(scene.timestamps(), [0.0, 1 / 15])
    for k, cam in enumerate(scene.camera_names):
        K = scene.cameras(cam).Ks[0].double().numpy()
        assert abs(K[1, 1] / K[0, 0] - HN_RATIO) < 1e-9
        for i, t in enumerate((0, 1)):
            np.testing.assert_allclose(project(scene, cam, i, P), uv[k, t], atol=1e-6)
            # the blob drawn at the distorted pixel is found at the undistorted one after conversion
            np.testing.assert_allclose(centroid(scene.rgb(cam, i)), uv[k, t], atol=0.3)


def test_hypernerf_split_scale_and_normalisation(tmp_path):
    root = tmp_path / "broom"
    uv = make_hypernerf(root)
    train = load_scene(convert("hypernerf", root, tmp_path / "t", split="train"))  # left camera only
    assert train.camera_names == ["cam00"] and train.num_frames == 3
    np.testing.assert_allclose(train.cameras("cam00").times.numpy(), [0.0, 0.5, 1.0])
    half = load_scene(convert("hypernerf", root, tmp_path / "h", scale=2, split="val"))
    assert (half.cameras("cam00").width, half.cameras("cam00").height) == (HN_W // 2, HN_H // 2)
    for i, t in enumerate((0, 1, 5)):
        np.testing.assert_allclose(project(half, "cam00", i, P), uv[1, t] / 2, atol=1e-6)
    norm = load_scene(convert("hypernerf", root, tmp_path / "n", normalize=True))
    P_norm = (P - np.array(SCENE["center"])) * SCENE["scale"]
    np.testing.assert_allclose(project(norm, "cam01", 1, P_norm), uv[1, 1], atol=1e-6)
    assert norm.meta.extra["normalized"] is True and norm.meta.extra["metric_scale"] is False


def test_hypernerf_bad_inputs(tmp_path):
    root = tmp_path / "broom"
    root.mkdir()
    with pytest.raises(FileNotFoundError, match="dataset.json"):
        convert("hypernerf", root, tmp_path / "o")
    make_hypernerf(root)
    with pytest.raises(ValueError, match="split"):
        convert("hypernerf", root, tmp_path / "o", split="test")
    with pytest.raises(FileNotFoundError, match="rgb/4x"):
        convert("hypernerf", root, tmp_path / "o", scale=4)
    meta = json.loads((root / "metadata.json").read_text())
    del meta["left_000001"]["camera_id"]
    (root / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"\['left_000001'\]\['camera_id'\]"):
        convert("hypernerf", root, tmp_path / "o")
    meta["left_000001"]["camera_id"] = 0
    (root / "metadata.json").write_text(json.dumps(meta))
    cam_file = root / "camera" / "right_000001.json"
    cam = json.loads(cam_file.read_text())
    for field, value in (("focal_length", "abc"), ("orientation", np.diag([1.0, 1.0, -1.0]).tolist()),
                         ("skew", 0.5)):
        cam_file.write_text(json.dumps(dict(cam, **{field: value})))
        with pytest.raises(ValueError, match=rf"right_000001.json: .*'{field}'"):
            convert("hypernerf", root, tmp_path / "o")
    cam_file.unlink()
    with pytest.raises(FileNotFoundError, match="right_000001.json"):
        convert("hypernerf", root, tmp_path / "o")


def test_hypernerf_undistort_samples_the_distorted_pixel():
    """Output pixel centre (u, v) takes the source value at nerfies' distorted projection of its ray. On a
    linear ramp bilinear sampling is exact, so a half-pixel convention error (≈ 0.1 px here) shows."""
    K = np.array([[HN_F, 0, HN_C[0]], [0, HN_F * HN_RATIO, HN_C[1]], [0, 0, 1]])
    (k1, k2, k3), (p1, p2) = RADIAL, TANGENTIAL
    u, v = np.meshgrid(np.arange(HN_W) + 0.5, np.arange(HN_H) + 0.5)
    ramp = np.repeat((3 * u + 2 * v)[..., None], 3, axis=-1)
    img = np.round(ramp).astype(np.uint8)
    out = undistort_rgb(img, K, np.array([k1, k2, p1, p2, k3]))[..., 0]
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    d = 1 + r2 * (k1 + r2 * (k2 + k3 * r2))
    xd, yd = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * d + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    ud, vd = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]
    inside = (ud > 1) & (ud < HN_W - 1) & (vd > 1) & (vd < HN_H - 1)
    assert inside.sum() > 0.5 * inside.size
    err = np.abs(out - (3 * ud + 2 * vd))[inside]
    assert err.max() < 1.0, err.max()  # uint8 rounding + OpenCV's 1/32-pixel remap grid
    np.testing.assert_array_equal(undistort_rgb(img, K, np.zeros(5)), img)  # no distortion: untouched


def test_convert_cli_runs_the_new_sources(tmp_path):
    root = tmp_path / "n3dv"
    root.mkdir()
    make_n3dv(root, n_cams=2)
    assert main(["n3dv", str(root), str(tmp_path / "o"), "--option", 'cameras=["cam01"]', "--max-frames", "2"]) == 0
    scene = load_scene(tmp_path / "o")
    assert scene.camera_names == ["cam01"] and scene.num_frames == 2
    make_dnerf(tmp_path / "lego")
    assert main(["dnerf", str(tmp_path / "lego"), str(tmp_path / "d"), "--option", "background=black"]) == 0
    assert load_scene(tmp_path / "d").meta.extra["background"] == "black"
