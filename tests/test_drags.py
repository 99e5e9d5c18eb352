"""Drags (diff4splat/geometry/drags.py, assembly/drag_scene.py, ``generate --drag/--tracks``): the forms and their
errors, the dense motion against its closed form on a square at a known depth, the scene that moves only where
dragged, and the command end to end."""
import json
import math

import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE, benchmark_module, square_scene, still_path, tiny_model

from data_prep.cli import main as data_prep_main
from diff4splat.cli import main
from diff4splat.geometry.drags import drag_motion, drags_from_flags, drags_from_tracks, parse_drag, support_normal
from diff4splat.io.tracks import read_tracks
from diff4splat.pipeline import Diff4SplatPipeline
from training.drag_eval import true_drags
from training.evaluate import held_out_clips

SIZE = 64


def test_a_drag_reads_its_point_offset_and_time():
    assert parse_drag("10,20.5:-3,4") == (10.0, 20.5, -3.0, 4.0, 1.0)
    assert parse_drag(" 1,2:3,4@0.25 ") == (1.0, 2.0, 3.0, 4.0, 0.25)
    d = drags_from_flags(["10,20:8,0@0.5", "30,30:0,-6"], 64, 64)
    assert d.times.tolist() == [0.0, 0.5, 1.0]
    assert np.allclose(d.at(0.25), [[14, 20], [30, 28.5]]) and np.allclose(d.at(1.0), [[18, 20], [30, 24]])


@pytest.mark.parametrize("text, match", [("10,20", "expected X,Y:DX,DY"), ("a,2:3,4", "must be numbers"),
                                         ("nan,2:3,4", "finite"), ("1,2:3,4@0", r"T must lie in \(0, 1\]"),
                                         ("1,2:3,4@1.5", r"T must lie in \(0, 1\]")])
def test_a_malformed_drag_is_named(text, match):
    with pytest.raises(ValueError, match=match):
        parse_drag(text)


def test_drags_outside_the_photograph_or_its_crop_are_refused():
    with pytest.raises(ValueError, match=r"drag 2 starts at \(70, 3\), outside the 64×48 photograph"):
        drags_from_flags(["1,1:2,2", "70,3:1,1"], 64, 48)
    with pytest.raises(ValueError, match=r"must be \(N, T, 2\)"):
        drags_from_tracks(np.zeros((3, 1, 2)), 64, 48)
    d = drags_from_tracks(np.array([[[40.0, 10.0], [44.0, 10.0]]]), 100, 50)  # a 100×50 photo cropped to 50×50
    small = d.resized((25, 0, 75, 50), 64, 64)
    assert np.allclose(small.positions, [[[19.2, 12.8], [24.32, 12.8]]])
    with pytest.raises(ValueError, match="outside the part of the photograph the model sees"):
        drags_from_tracks(np.array([[[10.0, 10.0], [12.0, 10.0]]]), 100, 50).resized((25, 0, 75, 50), 64, 64)


def test_a_tracks_file_of_the_wrong_shape_or_kind_is_named(tmp_path):
    good = tmp_path / "good.npy"
    np.save(good, np.zeros((2, 5, 2), np.float32))
    assert read_tracks(good).shape == (2, 5, 2)
    for name, array in (("flat.npy", np.zeros((5, 2))), ("three.npy", np.zeros((2, 5, 3))),
                        ("nan.npy", np.full((1, 2, 2), np.nan))):
        np.save(tmp_path / name, array)
        with pytest.raises(ValueError, match=f"--tracks: .*{name}"):
            read_tracks(tmp_path / name)
    (tmp_path / "text.npy").write_text("not an array")
    with pytest.raises(ValueError, match="not a readable .npy"):
        read_tracks(tmp_path / "text.npy")


def test_a_dragged_square_moves_at_its_depth_and_nothing_else_moves():
    """Closed form: a drag of (dx, dy) px at depth z moves its region by z·(dx/fx, dy/fy, 0) m at the drag's time,
    linearly before it; the wall stays."""
    image, depth, K = square_scene()
    drags = drags_from_flags(["30,30:12,-6@0.5"], SIZE, SIZE)
    motion, moving = drag_motion(drags, image, depth, K, torch.tensor([0.0, 0.25, 0.5, 1.0]))
    square = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    square[24:40, 24:40] = True
    assert torch.equal(moving, square)
    full = torch.tensor([2.0 * 12 / 60, 2.0 * -6 / 60, 0.0])
    for k, w in enumerate((0.0, 0.5, 1.0, 1.0)):
        assert torch.allclose(motion[k][square], w * full, atol=1e-6)
        assert torch.equal(motion[k][~square], torch.zeros(int((~square).sum()), 3))


def test_two_drags_in_one_region_each_move_their_nearest_pixels():
    image, depth, K = square_scene()
    drags = drags_from_flags(["26,32:4,0", "38,32:-4,0"], SIZE, SIZE)
    motion, _ = drag_motion(drags, image, depth, K, torch.tensor([0.0, 1.0]))
    assert motion[1, 32, 25, 0] > 0 and motion[1, 32, 38, 0] < 0


def _floor_scene(pitch_deg=20.0, height=1.5):
    """A grey floor 1.5 m below a camera pitched down by 20° (f = 60 px), with a red block standing on it (rows 20–31,
    columns 26–37, a face at the depth of the floor under its bottom edge); the floor's up normal in the camera's
    frame."""
    c, s = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    up = torch.tensor([0.0, -c, -s], dtype=torch.float64)  # the world's up seen by a camera looking down
    K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    rays = torch.stack([(u - 32) / 60, (v - 32) / 60, torch.ones_like(u)], -1).double()
    along = rays @ up
    depth = torch.where(along < -1e-3, -height / along, torch.full_like(along, 50.0)).float()  # floor, else far
    image = torch.full((SIZE, SIZE, 3), 0.5)
    image[20:32, 26:38] = torch.tensor([0.9, 0.1, 0.1])
    depth[20:32, 26:38] = depth[31, 32]
    return image, depth, K, up


def test_a_drag_on_a_floor_moves_its_object_along_the_floor_to_the_dragged_pixel():
    """Closed form: the floor's normal is found (RANSAC) within 1°; a block dragged down the image by 2 px moves
    parallel to the floor (toward the camera, not into the floor) and lands where the drag ends: its point projects
    to the drag's target pixel. Dragged 10 px, the floor's target would change its depth by more than LIFT_RANGE: the
    drag is lifted at the point's depth instead (z·K⁻¹(Δu, Δv, 0))."""
    image, depth, K, up = _floor_scene()
    normal = support_normal(depth.double().numpy(), np.linalg.inv(K.double().numpy()))
    assert normal is not None and math.degrees(math.acos(min(1.0, float(normal @ up.numpy())))) < 1.0
    drags = drags_from_flags(["32,28:0,2"], SIZE, SIZE)
    motion, moving = drag_motion(drags, image, depth, K, torch.tensor([0.0, 1.0]))
    assert moving[25, 30] and not moving[50, 10]
    point = depth[28, 32].double() * torch.tensor([0.0, (28.0 - 32) / 60, 1.0], dtype=torch.float64)  # (32, 28)
    moved = point + motion[1, 28, 32].double()
    assert abs(float(motion[1, 28, 32].double() @ up)) < 1e-4  # along the floor
    assert float(motion[1, 28, 32, 2]) < -0.1  # toward the camera: dragged down the image
    target = K.double() @ (moved / moved[2])
    assert torch.allclose(target[:2], torch.tensor([32.0, 30.0], dtype=torch.float64), atol=1e-3)
    far, _ = drag_motion(drags_from_flags(["32,28:0,10"], SIZE, SIZE), image, depth, K, torch.tensor([1.0]))
    assert torch.allclose(far[0, 28, 32], depth[28, 32] * torch.tensor([0.0, 10 / 60, 0.0]), atol=1e-6)


@pytest.mark.slow
def test_the_generated_scene_moves_only_where_dragged():
    """The photo layer's front disks on the square move by the closed form at the last time (the photo layer is at
    the given depth); the wall's disks and the backdrop stay; the scene is dynamic only through the drags."""
    image, depth, _ = square_scene()
    pipe = Diff4SplatPipeline(tiny_model(dynamic=False))
    path = still_path(pipe)
    still = pipe(image, path, steps=1, depth=depth)
    assert still.scene.is_static
    drags = drags_from_flags(["30,30:12,0"], SIZE, SIZE)
    res = pipe(image, path, steps=1, depth=depth, drags=drags)
    scene = res.scene
    assert not scene.is_static
    front = res.gaussian_index < SIZE * SIZE  # the photo layer's front disks, pixel index = slot
    pixel = res.gaussian_index[front]
    rows, cols = pixel // SIZE, pixel % SIZE
    on_square = (rows >= 24) & (rows < 40) & (cols >= 24) & (cols < 40)
    d_last = scene.d_means[-1][front]
    fx = float(path.Ks[0, 0, 0])
    expected = torch.tensor([2.0 * 12 / fx, 0.0, 0.0])
    assert bool(on_square.any()) and torch.allclose(d_last[on_square], expected, atol=1e-5)
    assert float(d_last[~on_square].abs().max()) == 0.0
    others = ~(res.gaussian_index < SIZE * SIZE + (SIZE // 2) ** 2)  # backdrop and generated: still
    assert float(scene.d_means[:, others].abs().max()) == 0.0
    with pytest.raises(ValueError, match="drags must be Drags at the image's 64×64"):
        pipe(image, path, steps=1, drags=drags_from_flags(["3,3:1,1"], 32, 32))


@pytest.mark.slow
def test_generate_with_a_drag_writes_its_motion_and_records_it(tmp_path):
    out = tmp_path / "out"
    args = ["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "1", "--resolution", str(SIZE), "--quiet",
            "--no-frame-plys", "--out", str(out)]
    assert main(args + ["--drag", "225,150:40,0"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["drags"] == ["225,150:40,0"] and meta["tracks_file"] is None
    assert (out / "deformation.npz").is_file()
    tracks = tmp_path / "tracks.npy"
    np.save(tracks, np.array([[[225.0, 150.0], [245.0, 150.0], [265.0, 150.0]]]))
    assert main(args + ["--tracks", str(tracks), "--overwrite"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["drags"] == [] and meta["tracks_file"] == str(tracks)


@pytest.mark.parametrize("case", ["form", "outside", "outside_crop", "both", "tracks_shape", "tracks_missing"])
def test_bad_drags_are_one_line_exit_2_before_the_model_loads(tmp_path, capsys, monkeypatch, case):
    """chelsea.png is 451×300: the model sees its centre 300×300 (x 75–375)."""
    import diff4splat.request as request_module

    def never(*args, **kwargs):
        raise AssertionError("the model was loaded")

    if case != "outside_crop":  # the crop is known only with the model's aspect ratio
        monkeypatch.setattr(request_module, "load_pipeline", never)
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((4, 2)))
    extra = {"form": ["--drag", "1,2:3"], "outside": ["--drag", "460,10:1,1"], "outside_crop": ["--drag", "20,10:1,1"],
             "both": ["--drag", "100,100:1,1", "--tracks", str(bad)], "tracks_shape": ["--tracks", str(bad)],
             "tracks_missing": ["--tracks", str(tmp_path / "none.npy")]}[case]
    out = tmp_path / "out"
    capsys.readouterr()
    code = main(["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "1", "--resolution", str(SIZE),
                 "--quiet", "--out", str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("diff4splat: error:"), err
    assert ("--drag" in err[0] or "--tracks" in err[0]) and not out.exists(), err


def test_true_drags_follow_each_moving_object_from_its_central_pixel():
    """A 4×4 patch (rows/columns 10–13) of a still plane 2 m away moves 0.1 m along +x over 5 frames: one drag, at
    the patch pixel nearest its centroid, moving f·0.1/2 px right; a still clip has none."""
    T, H, W = 5, 24, 24
    K = torch.tensor([[30.0, 0.0, 12.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    points = torch.stack([(u - 12) / 30 * 2, (v - 12) / 30 * 2, torch.full((H, W), 2.0)], -1)  # (H, W, 3)
    tracks = points.expand(T, H, W, 3).clone()
    tracks[:, 10:14, 10:14, 0] += torch.linspace(0, 0.1, T)[:, None, None]
    clip = {"pixel_tracks": tracks, "pixel_track_valid": torch.ones(H, W, dtype=torch.bool), "Ks": K.expand(T, 3, 3)}
    drags = true_drags(clip)
    assert len(drags) == 1 and drags.times.tolist() == [0, 0.25, 0.5, 0.75, 1]
    x0, y0 = drags.positions[0, 0]
    assert 10 <= x0 - 0.5 <= 13 and 10 <= y0 - 0.5 <= 13
    assert np.allclose(drags.positions[0, :, 0] - x0, np.linspace(0, 30 * 0.1 / 2, T), atol=1e-9)
    assert np.allclose(drags.positions[0, :, 1], y0)
    assert len(true_drags(clip, per_object=3)) == 3
    clip["pixel_tracks"] = points.expand(T, H, W, 3).clone()
    assert true_drags(clip) is None


@pytest.mark.slow
def test_the_drags_benchmark_scores_every_variant_on_a_tiny_set(tmp_path):
    """benchmarks/drags.py's rows on two synthetic scenes at the tiny model: every variant scores, the oracle that
    moves the true objects by their true track beats holding still at the moving pixels."""
    bench = benchmark_module("drags")
    assert data_prep_main(["synth", "--scenes", "2", "--out", str(tmp_path / "d"), "--seed", "3", "--static-ratio",
                           "0", "--motions", "translate", "--max-movers", "1", "--frames", "5", "--quiet"]) == 0
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True))
    clips = [c for c in held_out_clips(tmp_path / "d", 64, 64, 5, None) if true_drags(c) is not None]
    assert clips
    for variant in bench.VARIANTS:
        row, _ = bench.clip_row(pipe, clips[0], variant)
        assert np.isfinite(row["moving_epe"]) and np.isfinite(row["motion_disp_hold"]), variant
        if variant == bench.VARIANTS[-1]:
            assert row["moving_epe"] < 0.5 * row["moving_hold"]
