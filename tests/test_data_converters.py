"""Tests for data_prep.converters: every source read from a tiny fixture written in its native layout.

Each fixture places a known 3D point in the source's world, projects it into the source's native
camera convention with a formula written here independently of the converter (OpenCV, OpenGL,
PyTorch3D, NED, Unreal), and encodes the depth of that pixel in the source's native unit and file
encoding. After conversion the test reads the scene with ``data_prep.format.load_scene`` and checks
that the point — expressed in our world frame (metres) — projects through our world-to-camera
OpenCV ``viewmats`` and pixel ``Ks`` to the same pixel, with the stored metric z-depth at that pixel
equal to the point's depth, and that background / invalid pixels decode to the right metres / +inf.
"""
from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import h5py
import numpy as np
import OpenEXR
import pytest
import torch

from data_prep.cli import main
from data_prep.convert_cli import main as convert_main
from data_prep.convert_cli import parse_options
from data_prep.converters import convert
from data_prep.converters.camera_conventions import normalize_rotation
from data_prep.converters.common import decode_scaled_uint16, disparity_to_depth, float16_bits_to_float, select_frames
from data_prep.converters.multicamvideo import parse_ue_matrix
from data_prep.converters.stereo4d import decode_stereo4d_tracks
from data_prep.format import load_scene
from diff4splat.scene.quaternions import rotmat_to_quat

W, H = 16, 12
FX = FY = 20.0
CX, CY = 8.0, 6.0
BG = 7.5  # metres, background depth
T = 3


def look_at_cv(center, target):
    """World-to-camera (4, 4), OpenCV axes (z forward, y down), world y pointing down."""
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ c
    return V


P_WORLD = np.array([0.4, -0.3, 5.0])


def cv_poses(n=T, shift=(0.0, 0.0, 0.0)):
    """n world-to-camera OpenCV poses looking near P_WORLD from moving centres (rotation + translation)."""
    s = np.asarray(shift)
    return [look_at_cv(s + [0.15 * i, -0.05 * i, -0.3 * i], s + P_WORLD + [0.25 - 0.1 * i, 0.15, 0.0])
            for i in range(n)]


def project_cv(V, P, fx=FX, fy=FY, cx=CX, cy=CY):
    x = V[:3, :3] @ P + V[:3, 3]
    return np.array([fx * x[0] / x[2] + cx, fy * x[1] / x[2] + cy]), x[2]


@dataclass
class Expect:
    """What a converted scene must satisfy."""

    point: np.ndarray  # (3,) in our world frame, metres
    uv: dict  # camera -> list of (2,) native pixel coordinates per frame
    z: dict  # camera -> list of metric z-depths per frame
    depth_tol: float = 1e-4  # metres, the encoding's resolution at these depths
    background: float | None = BG  # metres at background_pixel, None without depth
    invalid_pixel: tuple | None = (0, W - 1)  # encoded as the source's invalid value
    background_pixel: tuple = (H - 1, 0)
    num_frames: int = T
    tracks: bool = False
    kwargs: dict = field(default_factory=dict)


def depth_map(uv, z, bg_code, point_code, invalid_code):
    """Native-coded depth map: background everywhere, the point's pixel, one invalid pixel."""
    d = np.full((H, W), bg_code, dtype=np.asarray(bg_code).dtype)
    d[int(math.floor(uv[1])), int(math.floor(uv[0]))] = point_code
    d[0, W - 1] = invalid_code
    return d


def rgb_image(i):
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 40 * i
    img[..., 1] = np.arange(W)[None, :] * 10
    return img


def write_png(path, img):
    """Write an image with OpenCV (format from the suffix: PNG, JPEG); RGB input."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), img)


# --------------------------------------------------------------------------------------- sources
def make_vkitti2(root: Path) -> tuple[Path, Expect]:
    def cm(m):  # metres → uint16 centimetres
        return np.uint16(round(m * 100))

    src = root / "Scene01" / "clone"
    intr = ["frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]"]
    extr = ["frame cameraID r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1"]
    uv, z = {"cam00": [], "cam01": []}, {"cam00": [], "cam01": []}
    for c, name in ((0, "cam00"), (1, "cam01")):
        for i, V in enumerate(cv_poses(shift=(0.5 * c, 0, 0))):
            intr.append(f"{i} {c} {FX} {FY} {CX - 0.5} {CY - 0.5}")  # VKITTI2 counts pixel centres at integers
            extr.append(f"{i} {c} " + " ".join(f"{v:.12g}" for v in V.reshape(-1)))
            p, zz = project_cv(V, P_WORLD)
            uv[name].append(p)
            z[name].append(zz)
            write_png(src / "frames" / "depth" / f"Camera_{c}" / f"depth_{i:05d}.png",
                      depth_map(p, zz, cm(BG), cm(zz), np.uint16(65535)))
            write_png(src / "frames" / "rgb" / f"Camera_{c}" / f"rgb_{i:05d}.jpg", rgb_image(i))
    (src / "intrinsic.txt").write_text("\n".join(intr) + "\n")
    (src / "extrinsic.txt").write_text("\n".join(extr) + "\n")
    return src, Expect(P_WORLD, uv, z, depth_tol=0.005 + 1e-6)


def make_pointodyssey(root: Path) -> tuple[Path, Expect]:
    src = root / "seq"
    poses = cv_poses()
    uv, z, codes = [], [], lambda m: np.uint16(round(m / 1000.0 * 65535))
    moving = P_WORLD[None, :] + np.array([[0.0, 0.0, 0.0], [0.01, 0, 0], [0.02, 0, 0]])  # a second, moving track
    for i, V in enumerate(poses):
        p, zz = project_cv(V, P_WORLD)
        uv.append(p)
        z.append(zz)
        write_png(src / "depths" / f"depth_{i:05d}.png", depth_map(p, zz, codes(BG), codes(zz), np.uint16(0)))
        write_png(src / "rgbs" / f"rgb_{i:05d}.jpg", rgb_image(i))
    trajs = np.stack([np.stack([P_WORLD] * T), moving, np.full((T, 3), np.nan)], axis=1)  # (T, 3, 3); third is NaN
    Ks = np.stack([[[FX, 0, CX], [0, FY, CY], [0, 0, 1]]] * T)
    np.savez(src / "anno.npz", trajs_2d=np.zeros((T, 3, 2)), trajs_3d=trajs, valids=np.ones((T, 3), bool),
             visibs=np.array([[1, 1, 0], [1, 0, 0], [1, 1, 0]], bool), intrinsics=Ks, extrinsics=np.stack(poses))
    return src, Expect(P_WORLD, {"cam00": uv}, {"cam00": z}, depth_tol=1000 / 65535 / 2 + 1e-6, tracks=True)


def make_tartanair(root: Path) -> tuple[Path, Expect]:
    src = root / "P000"
    fx, fy, cx, cy, w, h = 320.0, 320.0, 320.0, 240.0, 640, 480  # TartanAir's fixed camera
    uv, z = {}, {}
    for k, side in enumerate(("left", "right")):
        lines, uv[f"cam{k:02d}"], z[f"cam{k:02d}"] = [], [], []
        for i, V in enumerate(cv_poses(shift=(0, 0.25 * k, 0))):
            # NED body axes in world: forward = camera z, right = camera x, down = camera y
            R_cv_c2w = V[:3, :3].T
            R_ned = np.stack([R_cv_c2w[:, 2], R_cv_c2w[:, 0], R_cv_c2w[:, 1]], axis=1)
            t = -R_cv_c2w @ V[:3, 3]
            q = rotmat_to_quat(torch.from_numpy(R_ned)).numpy()  # wxyz
            lines.append(" ".join(f"{v:.12g}" for v in [*t, q[1], q[2], q[3], q[0]]))
            b = R_ned.T @ (P_WORLD - t)  # native NED projection: forward x, right y, down z
            p = np.array([fx * b[1] / b[0] + cx, fy * b[2] / b[0] + cy])
            uv[f"cam{k:02d}"].append(p)
            z[f"cam{k:02d}"].append(b[0])
            d = np.full((h, w), BG, np.float32)
            d[int(p[1]), int(p[0])] = b[0]
            d[0, w - 1] = 10000.0  # sky dome
            (src / f"depth_{side}").mkdir(parents=True, exist_ok=True)
            np.save(src / f"depth_{side}" / f"{i:06d}_{side}_depth.npy", d)
            write_png(src / f"image_{side}" / f"{i:06d}_{side}.png", np.zeros((h, w, 3), np.uint8))
        (src / f"pose_{side}.txt").write_text("\n".join(lines) + "\n")
    return src, Expect(P_WORLD, uv, z, depth_tol=1e-5, invalid_pixel=(0, w - 1), background_pixel=(h - 1, 0))


def make_spring(root: Path) -> tuple[Path, Expect]:
    src = root / "0001"
    poses = cv_poses()
    B = 0.065
    fx_i = [FX, FX * 1.1, FX * 0.9]  # per-frame focal lengths
    uv, z = {"cam00": [], "cam01": []}, {"cam00": [], "cam01": []}
    for i, V in enumerate(poses):
        for k, side in enumerate(("left", "right")):
            Vs = V.copy()
            Vs[0, 3] -= B * k  # right camera: 6.5 cm to the right along the left camera's x axis
            p, zz = project_cv(Vs, P_WORLD, fx=fx_i[i], fy=fx_i[i])
            uv[f"cam{k:02d}"].append(p)
            z[f"cam{k:02d}"].append(zz)
            disp = np.full((2 * H, 2 * W), fx_i[i] * B / BG, np.float32)
            r, c = int(p[1]), int(p[0])
            disp[2 * r:2 * r + 2, 2 * c:2 * c + 2] = fx_i[i] * B / zz
            disp[0:2, 2 * (W - 1):] = np.nan
            (src / f"disp1_{side}").mkdir(parents=True, exist_ok=True)
            with h5py.File(src / f"disp1_{side}" / f"disp1_{side}_{i + 1:04d}.dsp5", "w") as f:
                f.create_dataset("disparity", data=disp)
            write_png(src / f"frame_{side}" / f"frame_{side}_{i + 1:04d}.png", rgb_image(i))
    (src / "cam_data").mkdir()
    (src / "cam_data" / "intrinsics.txt").write_text("".join(f"{f} {f} {CX} {CY}\n" for f in fx_i))
    (src / "cam_data" / "extrinsics.txt").write_text(
        "".join(" ".join(f"{v:.12g}" for v in V.reshape(-1)) + "\n" for V in poses))
    return src, Expect(P_WORLD, uv, z, depth_tol=1e-4)


def write_exr_half(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"R": arr.astype(np.float16), "G": arr.astype(np.float16), "B": arr.astype(np.float16)}) as f:
        f.write(str(path))


def make_matrixcity(root: Path) -> tuple[Path, Expect]:
    src = root / "block_1"
    src.mkdir(parents=True)
    frames, uv, z = [], [], []
    for i, V in enumerate(cv_poses()):
        R_c2w_cv, t = V[:3, :3].T, -V[:3, :3].T @ V[:3, 3]
        R_gl = R_c2w_cv * np.array([1.0, -1.0, -1.0])  # camera y up, z backward
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = 0.01 * R_gl, t  # rotation stored ×0.01, position in metres
        frames.append({"file_path": f"{i:04d}.png", "transform_matrix": M.tolist()})
        pc = R_gl.T @ (P_WORLD - t)  # native OpenGL projection: camera looks down −z, y up
        p = np.array([CX + FX * pc[0] / -pc[2], CY - FY * pc[1] / -pc[2]])
        uv.append(p)
        z.append(-pc[2])
        write_png(src / f"{i:04d}.png", rgb_image(i))
        write_exr_half(root / "block_1_depth" / f"{i:04d}.exr", depth_map(p, -pc[2], BG * 100, -pc[2] * 100, 65504.0))
    angle = 2 * math.atan(W / 2 / FX)
    (src / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "w": W, "h": H, "frames": frames}))
    return src, Expect(P_WORLD, {"cam00": uv}, {"cam00": z}, depth_tol=0.005,
                       kwargs={"depth_dir": root / "block_1_depth"})


D_P3D = np.diag([-1.0, -1.0, 1.0])


def make_dynamic_replica(root: Path) -> tuple[Path, Expect]:
    def half(m):  # stored ×scale_adjustment = 2, as float16 bits
        return np.float16(m / 2.0).view(np.uint16)

    annots, uv, z = [], {"cam00": [], "cam01": []}, {"cam00": [], "cam01": []}
    s_ndc = min(W, H) / 2.0  # "ndc_isotropic"
    cx, cy = 7.5, 6.5  # off-centre principal point, pixels
    for k, side in enumerate(("left", "right")):
        for i, V in enumerate(cv_poses(shift=(0.1 * k, 0, 0))):
            R = V[:3, :3].T @ D_P3D  # PyTorch3D: X_cam = X_world @ R + T, camera x left, y up
            Tv = D_P3D @ V[:3, 3]
            f_ndc, p_ndc = FX / s_ndc, [(W / 2 - cx) / s_ndc, (H / 2 - cy) / s_ndc]
            Xc = P_WORLD @ R + Tv
            ndc = f_ndc * Xc[:2] / Xc[2] + np.array(p_ndc)  # PyTorch3D NDC: +x left, +y up
            p = np.array([W / 2 - ndc[0] * s_ndc, H / 2 - ndc[1] * s_ndc])
            uv[f"cam{k:02d}"].append(p)
            z[f"cam{k:02d}"].append(Xc[2])
            rel_d, rel_i = f"seq/depths/{side}_{i:04d}.geometric.png", f"seq/images/{side}_{i:04d}.png"
            write_png(root / "train" / rel_d, depth_map(p, Xc[2], half(BG), half(Xc[2]), np.uint16(0)))
            write_png(root / "train" / rel_i, rgb_image(i))
            annots.append({"sequence_name": "seq", "camera_name": side, "frame_number": i,
                           "frame_timestamp": i / 30.0, "image": {"path": rel_i, "size": [H, W]},
                           "depth": {"path": rel_d, "scale_adjustment": 2.0, "mask_path": None},
                           "viewpoint": {"R": R.tolist(), "T": Tv.tolist(), "focal_length": [f_ndc, f_ndc],
                                         "principal_point": p_ndc, "intrinsics_format": "ndc_isotropic"}})
    annots.append(dict(annots[0], sequence_name="other"))  # a second sequence in the split
    with gzip.open(root / "frame_annotations_train.jgz", "wt", encoding="utf8") as f:
        json.dump(annots, f)
    return root, Expect(P_WORLD, uv, z, depth_tol=0.01, kwargs={"sequence": "seq"})


F_UE = np.diag([1.0, -1.0, 1.0])
Q_UE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def write_video(path, frames, fps=15):
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for fr in frames:
        vw.write(cv2.cvtColor(fr, cv2.COLOR_RGB2BGR))
    vw.release()


def make_multicamvideo(root: Path) -> tuple[Path, Expect]:
    src = root / "f18_aperture10" / "scene1"
    n = 16  # square frames like the 1280x1280 release
    f_px = 18.0 / 23.76 * n
    P_ue = 100.0 * F_UE @ P_WORLD  # native world: left-handed UE, centimetres
    data = {f"frame{i}": {} for i in range(T)}
    uv, z = {}, {}
    for k, cam in enumerate(("cam01", "cam02")):
        uv[cam], z[cam] = [], []
        for i, V in enumerate(cv_poses(shift=(0, 0.2 * k, 0))):
            R_c, c = V[:3, :3].T, -V[:3, :3].T @ V[:3, 3]
            R_ue, t_ue = F_UE @ R_c @ Q_UE.T, 100.0 * F_UE @ c
            rows = [list(R_ue[:, j]) + [0.0] for j in range(3)] + [list(t_ue) + [1.0]]  # row-vector form
            data[f"frame{i}"][cam] = " ".join("[" + " ".join(f"{v:.12g}" for v in r) + "]" for r in rows)
            loc = R_ue.T @ (P_ue - t_ue)  # native UE camera: x forward, y right, z up (cm)
            uv[cam].append(np.array([n / 2 + f_px * loc[1] / loc[0], n / 2 - f_px * loc[2] / loc[0]]))
            z[cam].append(loc[0] / 100.0)
        write_video(src / "videos" / f"{cam}.mp4", [np.full((n, n, 3), 30 * i, np.uint8) for i in range(T)])
    (src / "cameras").mkdir(parents=True)
    (src / "cameras" / "camera_extrinsics.json").write_text(json.dumps(data))
    return src, Expect(P_WORLD, uv, z, background=None, invalid_pixel=None)


def make_stereo4d(root: Path) -> tuple[Path, Expect]:
    root.mkdir(parents=True)
    n = 16
    f = (n / 2) / math.tan(math.radians(30.0))
    poses = cv_poses()
    uv = [project_cv(V, P_WORLD, fx=f, fy=f, cx=n / 2, cy=n / 2)[0] for V in poses]
    z = [project_cv(V, P_WORLD)[1] for V in poses]
    c2w = np.stack([np.linalg.inv(V)[:3] for V in poses])  # (T, 3, 4)
    moving = [P_WORLD + [0.05 * i, 0, 0] for i in range(T)]
    # track 0: P at every frame; track 1: frames 0, 1 only (dropped); track 2: moving, every frame
    lengths = np.array([T, 2, T])
    indices = np.array([0, 1, 2, 0, 1, 0, 1, 2])
    coords = np.array([P_WORLD] * T + [P_WORLD, P_WORLD] + moving)
    name = "vid_130030030"
    np.savez(root / f"{name}.npz", name=name, video_id="vid", timestamps=130030030 + 33367 * np.arange(T),
             camera2world=c2w, track_lengths=lengths, track_indices=indices, track_coordinates=coords,
             rectified2rig=np.eye(3), fov_bounds=np.zeros(4))
    write_video(root / f"{name}-left_rectified.mp4", [np.full((n, n, 3), 50 * i, np.uint8) for i in range(T)], fps=30)
    return root, Expect(P_WORLD, {"cam00": uv}, {"cam00": z}, background=None, invalid_pixel=None, tracks=True)


RE10K_S, RE10K_T = 0.35, 0.02  # metric disparity = s * estimate + t


def make_realestate10k(root: Path) -> tuple[Path, Expect]:
    clip = root / "clip"
    stamps = [1000000 + 33366 * i for i in range(T)]
    lines = ["https://www.youtube.com/watch?v=xyz"]
    uv, z = [], []
    rng = np.random.default_rng(0)
    for i, (ts, V) in enumerate(zip(stamps, cv_poses(), strict=True)):
        fields = (FX / W, FY / H, CX / W, CY / H, 0, 0, *V[:3].reshape(-1))
        lines.append(" ".join([str(ts)] + [f"{v:.12g}" for v in fields]))
        p, zz = project_cv(V, P_WORLD)
        uv.append(p)
        z.append(zz)
        truth = depth_map(p, zz, BG, zz, BG)
        est = (1.0 / truth - RE10K_T) / RE10K_S  # a relative disparity estimate, exact up to (s, t)
        est[0, W - 1] = -1.0  # aligned disparity < 0: no valid depth → +inf
        ref = np.where(rng.uniform(size=(H, W)) < 0.3, truth, np.nan)  # sparse reference
        ref[0, W - 1] = np.nan
        ref[1, 1] = 40.0  # a gross outlier in the reference
        (root / "est").mkdir(parents=True, exist_ok=True)
        (root / "ref").mkdir(parents=True, exist_ok=True)
        np.save(root / "est" / f"{ts}.npy", est)
        np.save(root / "ref" / f"{ts}.npy", ref)
        write_png(clip / f"{ts}.png", rgb_image(i))
    (root / "clip.txt").write_text("\n".join(lines) + "\n")
    return root, Expect(P_WORLD, {"cam00": uv}, {"cam00": z}, depth_tol=1e-4,
                        kwargs={"estimates_dir": root / "est", "reference_dir": root / "ref"})


SOURCES = {
    "dynamic_replica": make_dynamic_replica,
    "multicamvideo": make_multicamvideo,
    "stereo4d": make_stereo4d,
    "realestate10k": make_realestate10k,
    "tartanair": make_tartanair,
    "spring": make_spring,
    "matrixcity": make_matrixcity,
    "vkitti2": make_vkitti2,
    "pointodyssey": make_pointodyssey,
}


# ----------------------------------------------------------------------------------------- checks
@pytest.mark.parametrize("source", sorted(SOURCES))
def test_known_point_reprojects_with_metric_depth(source, tmp_path):
    src, exp = SOURCES[source](tmp_path / "native")
    out = convert(source, src, tmp_path / "scene", **exp.kwargs)
    scene = load_scene(out)
    assert scene.meta.source == source and scene.num_frames == exp.num_frames
    assert scene.camera_names == list(exp.uv)
    point = exp.point
    for cam in exp.uv:
        path = scene.cameras(cam)
        V = path.viewmats.double().numpy()
        K = path.Ks.double().numpy()
        for i in range(exp.num_frames):
            R = V[i, :3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-5) and abs(np.linalg.det(R) - 1) < 1e-5
            x = R @ point + V[i, :3, 3]  # world-to-camera, OpenCV: z forward
            assert x[2] > 0
            uv = (K[i] @ (x / x[2]))[:2]
            np.testing.assert_allclose(uv, exp.uv[cam][i], atol=2e-3, err_msg=f"{source} {cam} frame {i}")
            assert abs(x[2] - exp.z[cam][i]) < 1e-3 * exp.z[cam][i]
            if exp.background is None:
                continue
            d = scene.depth(cam, i)
            assert d.shape == (path.height, path.width)
            col, row = int(math.floor(uv[0])), int(math.floor(uv[1]))
            assert abs(d[row, col] - exp.z[cam][i]) <= exp.depth_tol, (source, cam, i, d[row, col], exp.z[cam][i])
            assert abs(d[exp.background_pixel] - exp.background) <= exp.depth_tol + 1e-3 * exp.background
            if exp.invalid_pixel is not None:
                assert np.isposinf(d[exp.invalid_pixel])
    if exp.tracks:
        pts, vis = scene.tracks()
        assert pts.shape[1:] == (exp.num_frames, 3) and vis.shape == pts.shape[:2]
        np.testing.assert_allclose(pts[0], np.stack([point] * exp.num_frames), atol=1e-5)
    assert scene.meta.fps > 0


# ------------------------------------------------------------------------- per-source details
def test_realestate10k_alignment_and_units(tmp_path):
    src, exp = make_realestate10k(tmp_path / "native")
    scene = load_scene(convert("realestate10k", src, tmp_path / "aligned", **exp.kwargs))
    m = scene.meta
    assert m.depth_source == "aligned_estimate" and m.extra["metric_scale"] is False
    assert abs(m.depth_scale - RE10K_S) < 1e-6 and abs(m.depth_shift - RE10K_T) < 1e-6  # outlier rejected
    # no estimates: no depth; estimates without a metric/SfM reference: refused
    plain = load_scene(convert("realestate10k", src, tmp_path / "plain"))
    assert plain.meta.depth_source == "none" and not (tmp_path / "plain" / "cam00" / "depth").exists()
    with pytest.raises(ValueError, match="reference"):
        convert("realestate10k", src, tmp_path / "bad", estimates_dir=src / "est")
    # a metric scale for the SfM units multiplies translations (and depth)
    scaled = load_scene(convert("realestate10k", src, tmp_path / "scaled", metres_per_unit=2.0, **exp.kwargs))
    assert scaled.meta.extra["metric_scale"] is True
    v1, v2 = plain.cameras("cam00").viewmats, scaled.cameras("cam00").viewmats
    np.testing.assert_allclose(v2[:, :3, 3].numpy(), 2 * v1[:, :3, 3].numpy(), rtol=1e-6, atol=1e-6)
    i = 1
    d1, d2 = load_scene(tmp_path / "aligned").depth("cam00", i), scaled.depth("cam00", i)
    np.testing.assert_allclose(d2[np.isfinite(d1)], 2 * d1[np.isfinite(d1)], rtol=1e-6)


def test_pointodyssey_tracks_keep_source_visibility(tmp_path):
    src, _ = make_pointodyssey(tmp_path / "native")
    pts, vis = load_scene(convert("pointodyssey", src, tmp_path / "s")).tracks()
    assert pts.shape == (2, T, 3)  # the NaN track is dropped
    np.testing.assert_allclose(pts[1, :, 0], P_WORLD[0] + np.array([0.0, 0.01, 0.02]), atol=1e-6)
    assert vis.tolist() == [[True, True, True], [True, False, True]]  # visibs & valids, transposed to (P, T)
    assert load_scene(convert("pointodyssey", src, tmp_path / "n", max_tracks=0)).tracks() is None


def test_stereo4d_tracks_and_decoding(tmp_path):
    src, _ = make_stereo4d(tmp_path / "native")
    scene = load_scene(convert("stereo4d", src, tmp_path / "s"))
    pts, vis = scene.tracks()
    assert pts.shape == (2, T, 3)  # the track defined on 2 of 3 frames is dropped
    np.testing.assert_allclose(pts[1, :, 0], P_WORLD[0] + 0.05 * np.arange(T), atol=1e-6)
    assert vis[0].all()
    np.testing.assert_allclose(scene.timestamps(), (130030030 + 33367 * np.arange(T)) * 1e-6)
    full = decode_stereo4d_tracks([2, 1], [0, 2, 1], np.arange(9.0).reshape(3, 3), 3)
    assert np.isnan(full[0, 1]).all() and (full[0, 2] == [3, 4, 5]).all() and (full[1, 1] == [6, 7, 8]).all()
    with pytest.raises(ValueError, match="track_lengths"):
        decode_stereo4d_tracks([3], [0, 1], np.zeros((2, 3)), 3)
    with pytest.raises(ValueError, match="track_indices"):
        decode_stereo4d_tracks([1], [5], np.zeros((1, 3)), 3)


def test_frame_selection_stride_and_fps(tmp_path):
    src, exp = make_vkitti2(tmp_path / "native")
    scene = load_scene(convert("vkitti2", src, tmp_path / "s", stride=2, cameras=(1,)))
    assert scene.num_frames == 2 and scene.meta.fps == 5.0 and scene.meta.extra["source_frames"] == [0, 2]
    np.testing.assert_allclose(scene.timestamps(), [0.0, 0.2])
    V = scene.cameras("cam00").viewmats.double().numpy()
    x = V[1, :3, :3] @ P_WORLD + V[1, :3, 3]
    np.testing.assert_allclose(FX * x[0] / x[2] + CX, exp.uv["cam01"][2][0], atol=2e-3)


def test_bad_inputs_raise(tmp_path):
    with pytest.raises(ValueError, match="unknown source"):
        convert("kitti", tmp_path, tmp_path / "o")
    with pytest.raises(FileNotFoundError):
        convert("pointodyssey", tmp_path / "missing", tmp_path / "o")
    src, _ = make_dynamic_replica(tmp_path / "dr")
    with pytest.raises(ValueError, match="sequence must be given"):
        convert("dynamic_replica", src, tmp_path / "o")
    with pytest.raises(ValueError, match="must be a uniformly scaled rotation"):
        normalize_rotation(np.diag([1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="non-positive determinant"):
        normalize_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="stride"):
        select_frames(5, stride=0)
    with pytest.raises(ValueError, match="start"):
        select_frames(5, start=5)
    with pytest.raises(ValueError, match="4×4"):
        parse_ue_matrix("[1 0 0] [0 1 0] [0 0 1]")


def test_depth_decoders():
    raw = np.array([[0, 100, 65535]], np.uint16)
    d = decode_scaled_uint16(raw, 0.01, invalid=(0, 65535))
    assert np.isposinf(d[0, 0]) and d[0, 1] == np.float32(1.0) and np.isposinf(d[0, 2])
    z = disparity_to_depth(np.array([[2.0, 0.0, np.nan, -1.0]]), fx=100.0, baseline=0.1)
    assert z[0, 0] == np.float32(5.0) and np.isposinf(z[0, 1:]).all()
    bits = np.array([[1.5, 1000.0]], np.float16).view(np.uint16)
    np.testing.assert_array_equal(float16_bits_to_float(bits), [[1.5, 1000.0]])
    with pytest.raises(ValueError, match="16-bit"):
        decode_scaled_uint16(np.zeros((1, 1), np.uint8), 1.0)


def test_convert_cli(tmp_path, capsys):
    src, _ = make_dynamic_replica(tmp_path / "dr")
    rc = convert_main(["dynamic_replica", str(src), str(tmp_path / "out"), "--option", "sequence=seq",
                       "--option", 'sides=["left"]', "--max-frames", "2"])
    assert rc == 0 and "converted" in capsys.readouterr().out
    scene = load_scene(tmp_path / "out")
    assert scene.camera_names == ["cam00"] and scene.num_frames == 2
    assert convert_main(["dynamic_replica", str(src), str(tmp_path / "out2")]) == 2  # ambiguous sequence
    assert "sequence must be given" in capsys.readouterr().err
    assert parse_options(["a=1", "b=x", "c=[1, 2]"]) == {"a": 1, "b": "x", "c": (1, 2)}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_options(["novalue"])


def test_data_prep_cli_has_convert(tmp_path):

    src, _ = make_pointodyssey(tmp_path / "po")
    assert main(["convert", "pointodyssey", str(src), str(tmp_path / "out"), "--option", "max_tracks=1"]) == 0
    assert load_scene(tmp_path / "out").tracks()[0].shape[0] == 1
    assert main(["convert", "pointodyssey", str(src), str(tmp_path / "out")]) == 2  # exists, no --replace


def test_a_refused_output_folder_names_only_the_flag_that_would_lift_the_refusal(tmp_path, capsys):
    """convert has --replace and no --overwrite: its refusal of a user's folder suggested --overwrite, and its
    refusal of an earlier conversion suggested nothing."""
    src, _ = make_vkitti2(tmp_path / "vk")
    out = tmp_path / "out"
    assert main(["convert", "vkitti2", str(src), str(out)]) == 0
    capsys.readouterr()
    assert main(["convert", "vkitti2", str(src), str(out)]) == 2
    assert capsys.readouterr().err.strip().endswith(f"output folder {out} already exists (choose a new folder, or pass "
                                             "--replace to replace it)")
    assert main(["convert", "vkitti2", str(src), str(out), "--replace"]) == 0
    capsys.readouterr()
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    for extra in ([], ["--replace"]):
        assert main(["convert", "vkitti2", str(src), str(user), *extra]) == 2
        line = capsys.readouterr().err.strip()
        assert "--overwrite" not in line and "--replace" not in line, line
    assert [p.name for p in user.iterdir()] == ["notes.txt"]
