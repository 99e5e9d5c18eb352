"""data_prep.clips: index, determinism per (seed, epoch, i), DistributedSampler split, camera/image/depth/track
consistency after crop + resize, relative cameras, Plücker rays, scene filtering."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, DistributedSampler

from data_prep.clips import ClipConfig, ClipDataset, resize_nearest
from data_prep.format import SceneReader, SceneWriter
from diff4splat.cameras import CameraPath, center_crop_box, intrinsics_from_fov, invert_rigid, plucker_rays

SIZES = {"cam00": (40, 60), "cam01": (48, 40)}  # (H, W): wider (crop columns) and taller (crop rows)
PLANE_Z, DOT = 10.0, 2  # depth everywhere (but an invalid corner); dots are (2·DOT+1)² white squares


def _rot(axis: int, deg: float) -> np.ndarray:
    a, (i, j) = math.radians(deg), [(1, 2), (0, 2), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = math.cos(a)
    R[i, j], R[j, i] = -math.sin(a), math.sin(a)
    return R


def make_scene(root: Path, name: str, *, T: int, cams: list[str], dynamic: bool, depth: bool, caption: str | None,
               seed: int) -> Path:
    """Cameras in a rotated/offset world frame; tracks drawn as white squares on black at their projections.

    Tracks: 5 points 2–4 m in front (moving in y if dynamic) and one at 20 m, behind the depth plane (occluded);
    point 0 is flagged invisible in cam00 (stored visibility only: no depth or image evidence).
    """
    rng = np.random.default_rng(seed)
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = _rot(0, 20) @ _rot(2, 30), [1.0, -2.0, 0.5]  # rig frame → world
    local = np.concatenate([rng.uniform([-0.5, -0.3, 2.0], [0.5, 0.3, 4.0], (5, 3)), [[0.1, 0.0, 20.0]]])
    s = np.linspace(0, 1, T)
    pts_rig = np.repeat(local[:, None], T, 1)
    if dynamic:
        pts_rig[:5, :, 1] += 0.2 * s
    pts = (pts_rig @ G[:3, :3].T + G[:3, 3]).astype(np.float32)  # (P, T, 3) world
    vis = np.zeros(pts.shape[:2], bool)
    with SceneWriter(root / name, source="test", dynamic=dynamic, depth_source="ground_truth" if depth else "none",
                     num_frames=T, fps=10.0) as w:
        for c, cam in enumerate(cams):
            H, W = SIZES[cam]
            K = intrinsics_from_fov(W, H, fov_x_deg=60.0, dtype=torch.float64)
            vms = []
            for i in range(T):
                pose = np.eye(4)  # camera-to-rig
                pose[:3, :3], pose[:3, 3] = _rot(1, 5 * s[i] - 3 * c), [0.2 * s[i] + 0.15 * c, 0.05 * c, 0]
                vms.append(np.linalg.inv(G @ pose))
            path = CameraPath(torch.tensor(np.stack(vms)), K.expand(T, 3, 3).clone(), W, H)
            w.add_camera(cam, path)
            for i in range(T):
                V = path.viewmats[i].numpy()
                X = pts[:, i] @ V[:3, :3].T + V[:3, 3]
                uv = X @ K.numpy().T
                uv = uv[:, :2] / uv[:, 2:]
                inside = (X[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
                seen = inside & (X[:, 2] <= PLANE_Z)
                img = np.zeros((H, W, 3), np.float32)
                for u, v in uv[seen]:
                    img[max(int(v) - DOT, 0):int(v) + DOT + 1, max(int(u) - DOT, 0):int(u) + DOT + 1] = 1.0
                d = np.full((H, W), PLANE_Z, np.float32)
                d[30:33, 22:25] = np.inf  # inside the crop of both cameras, away from the 20 m point
                d[10:14, 15:19] = rng.uniform(1, 9, (4, 4))  # distinct values to check the nearest rule
                w.write_frame(cam, i, img, d if depth else None)
                if c == 0:
                    vis[:, i] = seen
        vis[0] = False  # a source's own occlusion flag for cam00 (not derivable from depth): point 0 hidden
        w.write_tracks(pts, vis)
        if caption:
            w.write_caption(caption)
    return root / name


CFG = ClipConfig(num_frames=5, height=32, width=32, min_stride=1, max_stride=3, reference_camera="random",
                 target_cameras="random", num_tracks=4, plucker="both", seed=7)


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    r = tmp_path_factory.mktemp("clips")
    make_scene(r, "dyn_a", T=21, cams=["cam00", "cam01"], dynamic=True, depth=True, caption="a ball rolls", seed=0)
    make_scene(r, "static_b", T=13, cams=["cam00"], dynamic=False, depth=False, caption=None, seed=1)
    return r


def _project(V: np.ndarray, K: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = X @ V[:3, :3].T + V[:3, 3]
    uv = x @ K.T
    return uv[..., :2] / uv[..., 2:]


def test_index_and_filtering(root):
    ds = ClipDataset(root, CFG)
    assert [(it.scene, it.start) for it in ds.items] == (
        [("dyn_a", s) for s in (0, 5, 10, 15)] + [("static_b", 0), ("static_b", 5)])
    assert [it.scene for it in ClipDataset(root, CFG, scenes="dynamic").items] == ["dyn_a"] * 4
    assert [it.scene for it in ClipDataset(root, CFG, scenes="static").items] == ["static_b"] * 2
    assert len(ClipDataset(root, CFG, scene_names=["static_b"])) == 2
    assert [it.start for it in ClipDataset(root, CFG, min_stride=3, window_step=4).items] == [0, 4, 8] + [0]
    assert bool(ClipDataset(root, CFG, scenes="dynamic")[0]["dynamic"])
    assert not bool(ClipDataset(root, CFG, scenes="static")[0]["dynamic"])
    with pytest.raises(ValueError, match="no clip"):
        ClipDataset(root, CFG, scenes="static", num_frames=17)
    with pytest.raises(ValueError, match="scene_names"):
        ClipDataset(root, CFG, scene_names=["nope"])
    for bad, match in [({"num_frames": 4}, "1 \\+ 4k"), ({"max_stride": 0}, "max_stride"),
                       ({"scenes": "moving"}, "scenes"), ({"height": 30}, "multiples of 8"),
                       ({"num_tracks": -1}, "num_tracks")]:
        with pytest.raises(ValueError, match=match):
            ClipDataset(root, CFG, **bad)
    with pytest.raises(ValueError, match="frames"):
        ClipDataset(root, CFG, frames=5)
    with pytest.raises(IndexError):
        ClipDataset(root, CFG)[6]


def test_shapes_and_dtypes(root):
    item = ClipDataset(root, CFG)[0]
    T, H, W = 5, 32, 32
    want = {"video": ((3, T, H, W), torch.float32), "viewmats": ((T, 4, 4), torch.float32),
            "Ks": ((T, 3, 3), torch.float32), "times": ((T,), torch.float32),
            "plucker": ((T, H, W, 6), torch.float32),
            "plucker_packed": ((6 * 4 * 64, 2, H // 8, W // 8), torch.float32),
            "depth": ((T, H, W), torch.float32), "depth_valid": ((T, H, W), torch.bool),
            "tracks": ((4, T, 3), torch.float32), "track_visibility": ((4, T), torch.bool),
            "track_mask": ((4,), torch.bool), "pixel_tracks": ((T, H, W, 3), torch.float32),
            "pixel_track_valid": ((H, W), torch.bool),
            "dynamic": ((), torch.bool), "frame_indices": ((T,), torch.int64),
            "camera_indices": ((T,), torch.int64), "index": ((), torch.int64)}
    assert set(item) == set(want) | {"caption", "scene"}
    for k, (shape, dtype) in want.items():
        assert tuple(item[k].shape) == shape and item[k].dtype == dtype, k
    ds = ClipDataset(root, CFG)
    first = [ds.sample(i).cameras[0] == "cam00" for i in range(3)]  # the caption describes cam00's view
    assert item["caption"] == ("a ball rolls" if first[0] else "") and item["scene"] == "dyn_a"
    assert 0 <= float(item["video"].min()) and float(item["video"].max()) <= 1
    raw = ClipDataset(root, CFG, plucker="raw")[0]
    assert "plucker" in raw and "plucker_packed" not in raw
    batch = next(iter(DataLoader(ClipDataset(root, CFG), batch_size=3)))
    assert batch["video"].shape == (3, 3, T, H, W)
    assert batch["caption"] == ["a ball rolls" if f else "" for f in first] and any(first) and not all(first)


def test_determinism_and_epochs(root):
    a, b = ClipDataset(root, CFG), ClipDataset(root, CFG)
    specs0 = [a.sample(i) for i in range(len(a))]
    assert specs0 == [b.sample(i) for i in range(len(b))]
    x, y = a[2], b[2]
    for k in x:
        assert (x[k] == y[k]) if isinstance(x[k], str) else torch.equal(x[k], y[k]), k
    a.set_epoch(1)
    specs1 = [a.sample(i) for i in range(len(a))]
    assert specs1 != specs0 and {s.stride for s in specs0 + specs1} == {1, 2, 3}
    assert any(len(set(s.cameras)) > 1 for s in specs0 + specs1)  # random target cameras
    assert [(s.scene, s.start) for s in specs1] == [(s.scene, s.start) for s in specs0]  # the index is fixed
    assert [s.frames[0] for s in specs1] == [s.start for s in specs1]
    assert [ClipDataset(root, CFG, seed=8).sample(i) for i in range(6)] != specs0
    a.set_epoch(0)
    assert [a.sample(i) for i in range(len(a))] == specs0
    for s in specs0 + specs1:  # clips fit in their scene
        assert s.frames[-1] <= {"dyn_a": 20, "static_b": 12}[s.scene]
        assert list(s.frames) == [s.start + k * s.stride for k in range(5)]
    first = ClipDataset(root, CFG, reference_camera="first", target_cameras="same")
    assert all(set(first.sample(i).cameras) == {"cam00"} for i in range(len(first)))


def test_distributed_sampler_splits_without_overlap(root):
    ds = ClipDataset(root, CFG)
    parts = []
    for rank in range(2):
        sampler = DistributedSampler(ds, num_replicas=2, rank=rank, shuffle=True, seed=3)
        sampler.set_epoch(4)
        parts.append(list(sampler))
    assert len(parts[0]) == len(parts[1]) == 3
    assert not set(parts[0]) & set(parts[1]) and set(parts[0]) | set(parts[1]) == set(range(len(ds)))


def test_relative_cameras_and_times(root):
    ds = ClipDataset(root, CFG)
    for epoch in range(2):
        ds.set_epoch(epoch)
        for i in range(len(ds)):
            item, spec = ds[i], ds.sample(i)
            r = SceneReader(root / spec.scene)
            assert torch.equal(item["viewmats"][0], torch.eye(4))
            src = [r.cameras(c).viewmats[f].double() for c, f in zip(spec.cameras, spec.frames, strict=True)]
            for k in range(5):  # V_k' = V_k · V_0⁻¹: relative poses between clip frames are the source ones
                torch.testing.assert_close(item["viewmats"][k].double(), src[k] @ invert_rigid(src[0]),
                                           atol=1e-5, rtol=0)
            torch.testing.assert_close(item["times"], torch.linspace(0, 1, 5))
            assert item["frame_indices"].tolist() == list(spec.frames)
            assert [r.camera_names[j] for j in item["camera_indices"]] == list(spec.cameras)


@pytest.mark.slow
def test_tracks_reproject_onto_images_after_crop_and_resize(root):
    """Closed form: source pixel (u, v) → ((u − x0)·32/cw, (v − y0)·32/ch); the clip image is white there."""
    ds = ClipDataset(root, CFG, num_tracks=6)
    checked = 0
    for epoch in range(2):
        ds.set_epoch(epoch)
        for i in range(len(ds)):
            item, spec = ds[i], ds.sample(i)
            r = SceneReader(root / spec.scene)
            pts, _ = r.tracks()
            for k, (c, f) in enumerate(zip(spec.cameras, spec.frames, strict=True)):
                src = r.cameras(c)
                y0, x0, ch, cw = center_crop_box(src.height, src.width, 32, 32)
                uv_src = _project(src.viewmats[f].double().numpy(), src.Ks[f].double().numpy(),
                                  pts[:, f].astype(np.float64))
                want = (uv_src - [x0, y0]) * [32 / cw, 32 / ch]
                X = item["tracks"][:, k].double().numpy()  # the clip world
                got = _project(item["viewmats"][k].double().numpy(), item["Ks"][k].double().numpy(), X)
                np.testing.assert_allclose(got, want, atol=1e-3)
                for p in np.nonzero(item["track_visibility"][:, k].numpy())[0]:
                    u, v = got[p]
                    assert float(item["video"][:, k, int(v), int(u)].min()) > 0.9  # the dot drawn in the source
                    checked += 1
    assert checked > 30


def test_track_visibility_rules(root):
    ds = ClipDataset(root, CFG, num_tracks=6)
    r = SceneReader(root / "dyn_a")
    pts, vis = r.tracks()
    for i in range(4):
        item, spec = ds[i], ds.sample(i)
        assert item["track_mask"].all()
        for k, (c, f) in enumerate(zip(spec.cameras, spec.frames, strict=True)):
            X = item["tracks"][:, k].double().numpy()
            uv = _project(item["viewmats"][k].double().numpy(), item["Ks"][k].double().numpy(), X)
            inside = ((uv >= 0) & (uv < 32)).all(-1)
            if c == "cam00":
                assert item["track_visibility"][:, k].tolist() == (vis[:, f] & inside).tolist()
            else:  # depth test: the point behind the plane (index 5) is never visible
                assert item["track_visibility"][:, k].tolist() == (inside & (np.arange(6) < 5)).tolist()
    static = ClipDataset(root, CFG, scenes="static")[0]  # 6 tracks, 4 sampled; constant in a static scene
    assert static["track_mask"].all() and torch.equal(static["tracks"], static["tracks"][:, :1].expand(-1, 5, -1))
    padded = ClipDataset(root, CFG, scenes="static", num_tracks=8)[1]
    assert padded["track_mask"].tolist() == [True] * 6 + [False] * 2
    assert not padded["track_visibility"][6:].any() and not padded["tracks"][6:].any()


def test_track_subsets_are_sampled_per_epoch(root):
    ds = ClipDataset(root, CFG, num_tracks=2)
    picks = set()
    for epoch in range(6):
        ds.set_epoch(epoch)
        item = ds[0]
        assert item["track_mask"].all()
        picks.add(tuple(item["tracks"][:, 0, 2].round(decimals=4).tolist()))
    assert len(picks) > 1


def test_depth_is_metric_and_nearest(root):
    d = np.arange(6 * 9, dtype=np.float32).reshape(6, 9) + 1
    d[0, 0] = np.inf
    out = resize_nearest(d, 2, 2)  # crop 6×6 at x0 = 1, then nearest at pixel centres: rows/cols 1 and 4
    np.testing.assert_array_equal(out, d[[1, 4]][:, [2, 5]])
    np.testing.assert_array_equal(resize_nearest(d, 6, 6), d[:, 1:7])
    up = resize_nearest(d, 12, 12)  # enlarging repeats pixels, inf stays inf
    assert np.isinf(up[:2, :2]).sum() == 0 and set(np.unique(up)) <= set(np.unique(d))
    assert np.isinf(resize_nearest(d, 12, 18)[:2, :2]).all()
    ds = ClipDataset(root, CFG)
    for i in range(4):
        item, spec = ds[i], ds.sample(i)
        r = SceneReader(root / spec.scene)
        for k, (c, f) in enumerate(zip(spec.cameras, spec.frames, strict=True)):
            np.testing.assert_array_equal(item["depth"][k].numpy(), resize_nearest(r.depth(c, f), 32, 32))
        assert torch.equal(item["depth_valid"], torch.isfinite(item["depth"]))
        vals = item["depth"][item["depth_valid"]]
        assert ((vals == PLANE_Z) | ((vals >= 1) & (vals <= 9))).all()  # only source values
        assert not item["depth_valid"].all()  # the invalid corner stays invalid
    nodepth = ClipDataset(root, CFG, scenes="static")[0]
    assert torch.isinf(nodepth["depth"]).all() and not nodepth["depth_valid"].any()


def test_plucker_rays_pass_through_tracks(root):
    ds = ClipDataset(root, CFG, num_tracks=6)
    item = ds[1]
    torch.testing.assert_close(item["plucker"], plucker_rays(item["viewmats"], item["Ks"], 32, 32), atol=1e-5, rtol=0)
    rays = item["plucker"]
    o = -item["viewmats"][:, :3, :3].transpose(1, 2) @ item["viewmats"][:, :3, 3:]  # (T, 3, 1) centres
    for k in range(5):
        for p in np.nonzero(item["track_visibility"][:, k].numpy())[0]:
            X = item["tracks"][p, k]
            uv = _project(item["viewmats"][k].double().numpy(), item["Ks"][k].double().numpy(), X.double().numpy())
            m, d = rays[k, int(uv[1]), int(uv[0]), :3], rays[k, int(uv[1]), int(uv[0]), 3:]
            dist = torch.linalg.cross(X - o[k, :, 0], d).norm()  # distance of X from the pixel's ray
            assert float(dist) < float((X - o[k, :, 0]).norm()) * 2.0 / float(item["Ks"][k, 0, 0])  # < ~1 pixel
            torch.testing.assert_close(m, torch.linalg.cross(o[k, :, 0], d), atol=1e-5, rtol=0)
    assert torch.equal(item["plucker_packed"][:6, 0], item["plucker"][0, ::8, ::8].permute(2, 0, 1))
