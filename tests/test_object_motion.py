"""Dense 3D tracks from object poses (data_prep.object_motion, objects.npz): closed forms, the synthetic scenes'
poses against their own Gaussians, id maps against depth, ClipDataset's pixel tracks against the exact point tracks,
and the dense scene-flow loss."""
from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch

from data_prep.clips import ClipDataset
from data_prep.format import SceneReader
from data_prep.object_motion import homogeneous, id_boundaries, pixel_tracks
from data_prep.scene_files import NO_SURFACE, OBJECTS_FILE
from data_prep.synth import build_scene, camera_path, generate_scene, object_poses, render_camera
from data_prep.synth_world import sample_scene_spec
from data_prep.validate import validate_scene
from diff4splat.cameras import project_points
from diff4splat.render.sequence import render_path
from training.losses import displacement_loss, scene_flow_loss


def _rot_z(a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_pixel_tracks_carry_each_object_by_its_poses_and_leave_the_background():
    """Object 0 translates by t·v, object 1 turns about a pivot p0 and scales by 2 at frame 2; a point seen at frame
    1 is at A_t·A_1⁻¹·(x − b_1) + b_t: the closed forms below. Background and no-surface pixels stay put."""
    F, v, p0 = 3, torch.tensor([1.0, 0.0, -2.0], dtype=torch.float64), torch.tensor([0.5, 1.0, 3.0],
                                                                                      dtype=torch.float64)
    poses = torch.zeros(2, F, 3, 4, dtype=torch.float64)
    for f in range(F):
        poses[0, f, :, :3], poses[0, f, :, 3] = torch.eye(3, dtype=torch.float64), f * v
        A = _rot_z(0.4 * f) * (2.0 if f == 2 else 1.0)
        poses[1, f, :, :3], poses[1, f, :, 3] = A, p0 - A @ p0
    ids = torch.tensor([[0, 1], [2, NO_SURFACE]], dtype=torch.uint8)
    points = torch.arange(12, dtype=torch.float32).reshape(2, 2, 3) / 7 + 1
    out = pixel_tracks(points, ids, poses, 1, torch.tensor([0, 1, 2]))
    x = points.double()
    assert out.dtype == torch.float32 and out.shape == (3, 2, 2, 3)
    torch.testing.assert_close(out[:, 0, 0], x[0, 0].expand(3, 3).float())  # background
    torch.testing.assert_close(out[:, 1, 1], x[1, 1].expand(3, 3).float())  # no surface
    for t in range(3):
        torch.testing.assert_close(out[t, 0, 1].double(), x[0, 1] + (t - 1) * v, atol=1e-6, rtol=0)
        turn = _rot_z(0.4 * (t - 1)) * (2.0 if t == 2 else 1.0)
        torch.testing.assert_close(out[t, 1, 0].double(), p0 + turn @ (x[1, 0] - p0), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="object id 3"):
        pixel_tracks(points, torch.full((2, 2), 3, dtype=torch.uint8), poses, 0, torch.tensor([0]))
    with pytest.raises(ValueError, match=r"lie in \[0, 3\)"):
        pixel_tracks(points, ids, poses, 0, torch.tensor([3]))


def test_homogeneous_and_id_boundaries():
    pose = torch.arange(12, dtype=torch.float64).reshape(3, 4)
    h = homogeneous(pose)
    assert h.shape == (4, 4) and torch.equal(h[:3], pose) and h[3].tolist() == [0, 0, 0, 1]
    ids = torch.zeros(6, 6, dtype=torch.uint8)
    ids[2:4, 2:4] = 1
    edge = id_boundaries(ids)
    assert edge[1:5, 1:5].all() and edge.sum() == 16  # the 2×2 block and its ring
    assert not id_boundaries(torch.full((4, 4), 3, dtype=torch.uint8)).any()


@pytest.mark.parametrize("seed", [3, 11])
def test_object_poses_move_the_synthetic_objects_gaussians_exactly(seed):
    """The poses written to objects.npz carry every object Gaussian's frame-0 mean to its mean at each frame, as
    build_scene deforms them (float32 scene)."""
    rng = np.random.default_rng(seed)
    spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=32, num_frames=5, texture_ratio=0.0)
    scene, ids = build_scene(spec, rng)
    poses = torch.from_numpy(object_poses(spec))
    assert poses.shape == (len(spec["objects"]), 5, 3, 4)
    means = [scene.at(float(t)).means.double() for t in scene.times]
    carry = homogeneous(poses) @ torch.linalg.inv(homogeneous(poses[:, :1]))  # (O, T, 4, 4): frame 0 → t
    moved = 0
    for k in range(len(spec["objects"])):
        sel = torch.from_numpy(ids == k)
        for t in range(5):
            want = means[0][sel] @ carry[k, t, :3, :3].T + carry[k, t, :3, 3]
            torch.testing.assert_close(means[t][sel], want, atol=2e-5, rtol=0)
            moved = max(moved, float((means[t][sel] - means[0][sel]).norm(dim=-1).max()))
    assert moved > 0.1  # something moved


def test_one_render_gives_render_paths_colours_and_depth_and_the_ids():
    """Compositing the one-hot ids beside the colours changes no colour or depth bit of render_path's frames."""
    rng = np.random.default_rng(3)
    spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=32, num_frames=3, texture_ratio=0.0)
    scene, ids = build_scene(spec, rng)
    path = camera_path(spec, spec["cameras"][0])
    rgb, depth, id_maps = render_camera(scene, ids, len(spec["objects"]), path, tuple(spec["background"]))
    colors, ed, alpha = render_path(scene, path, background=tuple(spec["background"]))
    np.testing.assert_array_equal(rgb, colors.numpy())
    np.testing.assert_array_equal(depth, torch.where(alpha >= 0.5, ed, torch.inf).numpy())
    assert set(np.unique(id_maps)) <= set(range(len(spec["objects"]) + 1)) | {NO_SURFACE}
    assert (id_maps[0] > 0).any()  # an object in view


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("objects")
    for i in range(4):  # seed 777's scenes 0–3 are dynamic, 2 cameras, 1–2 objects
        generate_scene(root, i, 777, size=48, frames=9)
    generate_scene(root, 4, 5, size=48, frames=9, static_ratio=1.0)
    return root


@pytest.mark.slow
def test_synthetic_scenes_write_valid_object_ids_exactly_where_there_is_depth(synth_root):
    for scene in sorted(synth_root.glob("scene_*")):
        r = SceneReader(scene)
        poses, ids = r.objects()
        assert validate_scene(scene) == []
        assert set(ids) == set(r.meta.cameras) and poses.shape[1] == r.num_frames
        for cam in r.meta.cameras:
            for f in (0, r.num_frames - 1):
                np.testing.assert_array_equal(ids[cam][f] == NO_SURFACE, np.isinf(r.depth(cam, f)))
        if r.meta.dynamic:
            assert set(np.unique(ids["cam00"][0])) >= {0, 1}  # background and an object in view
        else:
            assert np.abs(poses - poses[:, :1]).max() == 0


def test_a_broken_objects_file_is_reported_by_the_validator_and_the_reader(synth_root, tmp_path):
    scene = tmp_path / "s"
    shutil.copytree(synth_root / "scene_00000", scene)
    with np.load(scene / OBJECTS_FILE) as data:
        arrays = {k: np.asarray(data[k]) for k in data.files}
    arrays["ids_cam01"][0, 0, 0] = 9
    np.savez_compressed(scene / OBJECTS_FILE, **arrays)
    problems = validate_scene(scene)
    assert len(problems) == 1 and "'ids_cam01' has object id 9" in problems[0].message
    with pytest.raises(ValueError, match="object id 9"):
        SceneReader(scene).objects()


def test_clip_pixel_tracks_follow_the_exact_point_tracks(synth_root):
    """At the pixels of the exact (Gaussian-mean) tracks, the dense tracks' displacement from frame 0 matches theirs
    to within a fifth of holding still, through crop/resize to 32², strides and a random reference camera; a rotating
    object's surface point is not its Gaussian's centre, so not exactly."""
    ds = ClipDataset(synth_root, height=32, width=32, num_frames=5, min_stride=1, max_stride=2, scenes="dynamic",
                     reference_camera="random", num_tracks=256)
    err = hold = 0.0
    for i in range(len(ds)):
        item = ds[i]
        tracks, valid = item["pixel_tracks"].double(), item["pixel_track_valid"]
        assert tracks.shape == (5, 32, 32, 3) and valid.shape == (32, 32) and valid.float().mean() > 0.7
        pts = item["tracks"].double()
        uv, z = project_points(pts[:, 0], item["viewmats"][0].double(), item["Ks"][0].double())
        col, row = uv[:, 0].floor().long().clamp(0, 31), uv[:, 1].floor().long().clamp(0, 31)
        ok = item["track_mask"] & item["track_visibility"][:, 0] & valid[row, col]
        dense = (tracks[:, row, col] - tracks[:1, row, col]).transpose(0, 1)[ok]
        exact = (pts - pts[:, :1])[ok]
        err += float((dense - exact).norm(dim=-1).mean())
        hold += float(exact.norm(dim=-1).mean())
        # frame 0's points lie on the clip depth: z of frame 0's dense tracks is the depth map
        depth0 = item["depth"][0]
        torch.testing.assert_close(tracks[0, ..., 2][valid].float(), depth0[valid], rtol=1e-5, atol=1e-5)
    assert hold > 0.5 and err < 0.2 * hold, (err, hold)


@pytest.mark.slow
def test_static_scenes_pixel_tracks_stay_put_and_unknown_motion_is_not_supervised(synth_root, tmp_path):
    static = ClipDataset(synth_root, height=32, width=32, num_frames=5, scenes="static")[0]
    assert static["pixel_track_valid"].float().mean() > 0.7
    assert torch.equal(static["pixel_tracks"], static["pixel_tracks"][:1].expand(5, -1, -1, -1))
    for name in ("scene_00000", "scene_00004"):
        shutil.copytree(synth_root / name, tmp_path / name)
        (tmp_path / name / OBJECTS_FILE).unlink()
    items = {it["scene"]: it for it in (ClipDataset(tmp_path, height=32, width=32, num_frames=5)[i] for i in (0, 1))}
    assert not items["scene_00000"]["pixel_track_valid"].any()  # dynamic, no poses: unknown
    assert torch.equal(items["scene_00004"]["pixel_track_valid"], torch.isfinite(items["scene_00004"]["depth"][0]))


def test_scene_flow_loss_is_the_mean_displacement_error_over_valid_pixels_and_later_frames():
    g = torch.Generator().manual_seed(0)
    target = torch.randn(4, 3, 5, 3, generator=g, dtype=torch.float64)
    points = target + torch.randn(4, 3, 5, 3, generator=g, dtype=torch.float64)
    valid = torch.rand(3, 5, generator=g) > 0.4
    want = ((points[1:] - points[:1]) - (target[1:] - target[:1])).norm(dim=-1)[:, valid].mean()
    torch.testing.assert_close(scene_flow_loss(points, target, valid), want)
    # a shift common to every frame (a frame-0 depth error) costs nothing
    assert float(scene_flow_loss(target + 3.0, target, valid)) < 1e-5
    flat = lambda x: x.reshape(4, 15, 3).transpose(0, 1)[None]  # noqa: E731
    torch.testing.assert_close(scene_flow_loss(points, target, valid),
                               displacement_loss(flat(points), flat(target), valid.reshape(1, 15, 1).expand(1, 15, 4)))
    with pytest.raises(ValueError, match="must be"):
        scene_flow_loss(points, target, valid[:2])
