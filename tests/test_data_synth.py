"""Synthetic scenes: exact tracks (closed-form motion, rendered depth), determinism, captions, static
scenes, camera/motion directions, variety, resume, CLI."""
from __future__ import annotations

import copy
import hashlib
import json
import math
import time
import tracemalloc
from concurrent.futures import Future

import numpy as np
import psutil
import pytest

import data_prep.engine
import data_prep.synth_dataset
import diff4splat.utils.limits as limits
from data_prep.cli import main
from data_prep.format import load_scene
from data_prep.synth import (
    IMAGE_SPACING,
    VISIBILITY_TOL_M,
    VISIBILITY_TOL_REL,
    build_gaussians,
    camera_path,
    generate_scene,
    object_transform,
    render_spec,
    scene_name,
)
from data_prep.synth_dataset import max_gaussians, scene_bytes, synthesize
from data_prep.synth_world import CAMERA_MOTIONS, MOTIONS, SHAPES, TEXTURES, caption_for, sample_scene_spec
from data_prep.textures import IMAGE_TEXTURES, image_albedo
from data_prep.validate import validate_path, validate_scene
from diff4splat.scene.gaussians import sh0_to_rgb
from models.bundle import DEFAULT_CONFIG, WEIGHTS_DIR, load_config
from training.direction_test import caption_direction

SIZE, T = 32, 5
VERBS = {"translate": ("slides", "rolls"), "rotate": ("spins", "tumbles"), "bounce": ("bounces",),
         "deform": ("pulses", "squashes")}
CAM_VERBS = {"orbit": "orbits", "dolly": "dollies", "pan": "pans", "truck": "trucks", "static": "stays still"}


def _project(points, cams):
    """Independent pinhole projection: (P, T, 3) world → u, v pixels and z metres (P, T)."""
    V, K = cams.viewmats.double().numpy(), cams.Ks.double().numpy()
    X = np.einsum("tij,ptj->pti", V[:, :3, :3], points.astype(np.float64)) + V[None, :, :3, 3]
    z = X[..., 2]
    return K[None, :, 0, 0] * X[..., 0] / z + K[None, :, 0, 2], K[None, :, 1, 1] * X[..., 1] / z + K[None, :, 1, 2], z


def _depth_at(depth, u, v):
    H, W = depth.shape[1:]
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    frame = np.broadcast_to(np.arange(depth.shape[0]), u.shape)
    d = depth[frame, np.clip(np.floor(v), 0, H - 1).astype(int), np.clip(np.floor(u), 0, W - 1).astype(int)]
    return np.where(inside, d, np.nan), inside


@pytest.fixture(scope="module")
def rolling_ball():
    """A ball of radius r rolling 1.2 m to the right of a static reference camera looking along +z."""
    rng = np.random.default_rng([5, 0])
    spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=SIZE, num_frames=T)
    r, gy = 0.4, spec["ground_y"]
    ball = {**spec["objects"][0], "shape": "sphere", "half": [r, r, r], "lumps": [], "center": [-0.6, gy - r, 0.0],
            "motion": {"kind": "translate", "velocity": [1.2, 0.0, 0.0], "roll": True}}
    spec["objects"] = [ball]
    spec["cameras"] = [{"kind": "static", "fov_x_deg": 60.0, "azimuth": 0.0, "distance": 3.0, "height": 0.8,
                        "target_height": 0.4, "delta": 0.0}]
    return render_spec(spec, rng)


def test_tracks_follow_closed_form_rolling_motion(rolling_ball):
    res = rolling_ball
    pts = res.points.astype(np.float64)
    c0, r = np.asarray(res.spec["objects"][0]["center"]), 0.4
    t = np.linspace(0, 1, T)
    for i in range(T):  # rolling without slipping about +z (= up × x̂ with y down) by distance / r
        a = 1.2 * t[i] / r
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        expect = c0 + [1.2 * t[i], 0, 0] + (pts[:, 0] - c0) @ Rz.T
        np.testing.assert_allclose(pts[:, i], expect, atol=2e-5)
    # the contact point (bottom, y down) is at rest: finite difference of the motion formula
    bottom = c0 + [0, r, 0]
    p0, d0, R0, S0 = object_transform(res.spec["objects"][0], 0.5)
    p1, d1, R1, S1 = object_transform(res.spec["objects"][0], 0.5 + 1e-6)
    contact = bottom + d0
    x0 = p0 + d0 + R0 @ (R0.T @ (contact - p0 - d0))
    x1 = p1 + d1 + R1 @ (R0.T @ (contact - p0 - d0))
    assert np.linalg.norm(x1 - x0) / 1e-6 < 1e-3


def test_tracks_land_on_the_rendered_object(rolling_ball):
    res = rolling_ball
    depth, cams = res.depth[0], res.cameras[0]
    u, v, z = _project(res.points, cams)
    d, inside = _depth_at(depth, u, v)
    tol = VISIBILITY_TOL_M + VISIBILITY_TOL_REL * z
    expect_vis = inside & (z > 0) & (d >= z - tol)
    np.testing.assert_array_equal(res.visibility, expect_vis)
    assert (res.visibility.mean(0) > 0.15).all()  # the ball's front is seen in every frame
    # where visible, the rendered depth equals the point's depth (within tol, from both sides)
    vis = res.visibility
    assert (np.abs(d - z)[vis] <= tol[vis]).mean() > 0.97
    # control: tracks frozen at frame 0 no longer land on the ball once it has rolled away
    uf, vf, zf = _project(np.repeat(res.points[:, :1], T, 1), cams)
    df, _ = _depth_at(depth, uf, vf)
    on_true = (np.abs(d - z) <= tol)[:, -1].mean()
    on_frozen = (np.abs(df - zf) <= VISIBILITY_TOL_M + VISIBILITY_TOL_REL * zf)[:, -1].mean()
    assert on_frozen < 0.5 * on_true  # (≈ 0.29: only points near the ground contact still match)
    assert "rolls to the right" in res.caption


@pytest.mark.slow
def test_generate_is_deterministic_and_seed_dependent(tmp_path):
    a = generate_scene(tmp_path / "a", 3, 11, size=SIZE, frames=T, cameras=2)
    b = generate_scene(tmp_path / "b", 3, 11, size=SIZE, frames=T, cameras=2)
    c = generate_scene(tmp_path / "c", 3, 12, size=SIZE, frames=T, cameras=2)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.suffix != ".npz")
    # marker, meta, caption, per camera cameras.json + frames (npz: arrays below)
    assert len(files) == 3 + 2 * (1 + 2 * T) and files[0].name == ".diff4splat-output.json"
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    ra, rb, rc = load_scene(a), load_scene(b), load_scene(c)
    for x, y in zip(ra.tracks(), rb.tracks(), strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(ra.rgb("cam00", 0), rc.rgb("cam00", 0))
    assert ra.meta.extra["synth"]["spec"] != rc.meta.extra["synth"]["spec"]
    assert ra.meta.extra["synth"]["seed"] == 11 and ra.meta.extra["synth"]["index"] == 3
    assert validate_scene(a) == [] and validate_scene(c) == []


def test_static_and_dynamic_scenes(tmp_path):
    s = load_scene(generate_scene(tmp_path, 0, 4, size=SIZE, frames=T, cameras=1, static_ratio=1.0))
    d = load_scene(generate_scene(tmp_path, 1, 4, size=SIZE, frames=T, cameras=1, static_ratio=0.0))
    ps, _ = s.tracks()
    assert not s.meta.dynamic and np.array_equal(ps, np.repeat(ps[:, :1], T, 1))
    assert "static scene" in s.caption
    assert all(o["motion"] is None for o in s.meta.extra["synth"]["spec"]["objects"])
    pd, vd = d.tracks()
    assert d.meta.dynamic and np.abs(pd - pd[:, :1]).max() > 0.05 and vd.any()
    assert d.meta.depth_source == "ground_truth" and np.isfinite(d.depth("cam00", 0)).mean() > 0.5
    assert (d.depth("cam00", 0)[np.isfinite(d.depth("cam00", 0))] > 0).all()


@pytest.mark.slow
def test_shipped_tokenizer_holds_every_synthetic_caption_whole():
    # The shipped base model's text sees a training caption whole, direction words included (the byte tokenizer cuts
    # a longer one). About 1 in 600 sampled captions exceeds 254 bytes, so 3,000 of them catch a 256-token limit.
    room = min(load_config(c).text_encoder.max_length for c in (DEFAULT_CONFIG, WEIGHTS_DIR / DEFAULT_CONFIG /
                                                                "config.json")) - 2
    longest = 0
    for k in range(3000):
        rng = np.random.default_rng([2026, k])
        spec = sample_scene_spec(rng, dynamic=k % 4 != 0, num_cameras=1, size=SIZE, num_frames=T)
        longest = max(longest, len(caption_for(spec, np.eye(3)).encode("utf-8")))
    assert 254 < longest <= room


def test_captions_mention_sampled_motions():
    for k in range(150):
        rng = np.random.default_rng([99, k])
        spec = sample_scene_spec(rng, dynamic=k % 3 != 0, num_cameras=1, size=SIZE, num_frames=T)
        cap = caption_for(spec, np.eye(3))
        assert "\n" not in cap and spec["ground"]["material"] in cap
        assert not any(f" a {x}" in cap or cap.startswith(f"a {x}") for x in "aeiou"), cap  # "an orange ball"
        assert CAM_VERBS[spec["cameras"][0]["kind"]] in cap
        moving = [o for o in spec["objects"] if o["motion"]]
        assert bool(moving) == spec["dynamic"] and ("static scene" in cap) == (not moving)
        for o in spec["objects"]:
            tex = o["texture"]
            word = IMAGE_TEXTURES[tex["file"]] if tex["kind"] == "image" else TEXTURES[tex["kind"]]
            assert word in cap and SHAPES[o["shape"]] in cap
            if tex["kind"] != "image" or tex["grey"]:  # an RGB photograph shows its own colours: no colour word
                assert f"{o['color_name']} {word}".strip() in cap
        for o in moving:
            assert any(v in cap for v in VERBS[o["motion"]["kind"]]), (cap, o["motion"])


def test_caption_directions_match_geometry():
    rng = np.random.default_rng(0)
    spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=SIZE, num_frames=T)
    obj = spec["objects"][0]
    spec["objects"] = [obj]
    R = np.eye(3)
    for vel, word in (([1, 0, 0], "to the right"), ([-1, 0, 0], "to the left"), ([0, 0, -1], "towards the camera"),
                      ([0, 0, 1], "away from the camera")):
        obj["motion"] = {"kind": "translate", "velocity": vel, "roll": False}
        assert f"slides {word}" in caption_for(spec, R)
    obj["motion"] = {"kind": "rotate", "axis": [0, 1, 0], "omega": 1.0}  # +y points down
    assert "spins clockwise" in caption_for(spec, R)
    obj["motion"]["omega"] = -1.0
    assert "spins counter-clockwise" in caption_for(spec, R)


@pytest.mark.parametrize("kind,word", [("orbit", "right"), ("truck", "right"), ("pan", "right"), ("dolly", "forward")])
def test_camera_motion_direction_matches_caption(kind, word):
    spec = sample_scene_spec(np.random.default_rng(1), dynamic=False, num_cameras=1, size=SIZE, num_frames=T)
    cam = {"kind": kind, "fov_x_deg": 60.0, "azimuth": 0.7, "distance": 3.0, "height": 1.0, "target_height": 0.3,
           "delta": 0.5}
    spec["cameras"] = [cam]
    path = camera_path(spec, cam).relative_to_first()  # world = first camera: x right, z forward
    eye_last = path.camera_centers()[-1].numpy()
    fwd_last = path.viewmats[-1, 2, :3].numpy()  # camera z axis in world coordinates
    if kind in ("orbit", "truck"):
        assert eye_last[0] > 0.2
    elif kind == "dolly":
        assert eye_last[2] > 0.2 and abs(eye_last[0]) < 1e-5
    else:
        assert fwd_last[0] > 0.2 and np.linalg.norm(eye_last) < 1e-5
    assert f"{CAM_VERBS[kind]} {word}" in caption_for(spec, np.eye(3))
    neg = copy.deepcopy(spec)
    neg["cameras"][0]["delta"] = -0.5
    assert f"{CAM_VERBS[kind]} {word}" not in caption_for(neg, np.eye(3))


def test_motion_formulas():
    obj = {"center": [1.0, 0.5, 2.0], "half": [0.3, 0.3, 0.3], "shape": "box",
           "motion": {"kind": "bounce", "velocity": [0.4, 0, 0], "height": 0.7, "hops": 2}}
    for t, up in ((0.0, 0.0), (0.25, 0.7), (0.5, 0.0), (1.0, 0.0), (0.125, 0.7 * 0.75)):
        _, d, R, S = object_transform(obj, t)
        np.testing.assert_allclose(d, [0.4 * t, -up, 0], atol=1e-12)
        np.testing.assert_array_equal(R, np.eye(3))
    obj["motion"] = {"kind": "deform", "mode": "pulse", "amplitude": 0.2, "freq": 2.0}
    pivot, d, R, S = object_transform(obj, 1 / 8)
    np.testing.assert_allclose(S, 1.2)
    np.testing.assert_allclose(pivot, [1.0, 0.8, 2.0])  # bottom of the object stays on the ground
    obj["motion"] = {"kind": "rotate", "axis": [0, 1, 0], "omega": math.pi}
    _, d, R, S = object_transform(obj, 0.5)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, -1], atol=1e-12)  # +90° about +y: x → −z
    obj["motion"] = None
    assert np.array_equal(object_transform(obj, 0.3)[1], np.zeros(3))


def test_specs_are_varied():
    seen = {"motion": set(), "camera": set(), "shape": set(), "texture": set(), "colour": set(), "n_obj": set(),
            "image": set()}
    for k in range(60):
        spec = sample_scene_spec(np.random.default_rng([3, k]), dynamic=True, num_cameras=2, size=SIZE, num_frames=T)
        seen["n_obj"].add(len(spec["objects"]))
        seen["camera"].update(c["kind"] for c in spec["cameras"])
        for o in (*spec["objects"], spec["ground"], spec["wall"]):
            seen["image"].add(o["texture"].get("file"))
        for o in spec["objects"]:
            seen["shape"].add(o["shape"])
            seen["texture"].add(o["texture"]["kind"])
            seen["colour"].add(o["color_name"])
            if o["motion"]:
                seen["motion"].add(o["motion"]["kind"])
    assert seen["motion"] == set(MOTIONS) and seen["camera"] == set(CAMERA_MOTIONS)
    assert seen["shape"] == set(SHAPES) and seen["texture"] == {*TEXTURES, "image"}
    assert seen["image"] == {None, *IMAGE_TEXTURES}  # every bundled photograph is used
    assert len(seen["colour"]) >= 10 and seen["n_obj"] == {1, 2, 3, 4}


def test_synthesize_resumes_and_validates(tmp_path):
    kw = dict(size=16, frames=3, cameras=1, progress=False)
    synthesize(tmp_path, 2, 3, **kw)
    marker = tmp_path / scene_name(0) / "marker"
    marker.write_text("kept")
    paths = synthesize(tmp_path, 3, 3, **kw)
    assert paths == [tmp_path / scene_name(i) for i in range(3)] and marker.read_text() == "kept"
    assert validate_path(tmp_path) == (3, [])
    with pytest.raises(ValueError, match="static_ratio"):
        synthesize(tmp_path, 1, 0, static_ratio=1.5)
    with pytest.raises(ValueError, match="frames"):
        synthesize(tmp_path, 1, 0, frames=1)
    for bad in (-0.1, 1.5, math.nan, True, "0.5"):
        with pytest.raises(ValueError, match=r"texture_ratio must be a number in \[0, 1\]"):
            synthesize(tmp_path, 1, 0, texture_ratio=bad)


def test_synthesize_adds_scenes_to_a_dataset_root_only(tmp_path):
    """A folder of other files (a user's, a generate output) is refused before anything is written (synth wrote its
    scenes into any existing folder); a dataset root with a scene of another source gets the new scenes beside it."""
    kw = dict(size=16, frames=3, cameras=1, progress=False)
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"--out .*user holds notes.txt, which is not a scene folder"):
        synthesize(user, 1, 0, **kw)
    assert sorted(p.name for p in user.iterdir()) == ["notes.txt"]
    root = tmp_path / "data"
    (root / "vkitti2_scene01").mkdir(parents=True)
    (root / "vkitti2_scene01" / "meta.json").write_text("{}")
    assert synthesize(root, 1, 0, **kw) == [root / scene_name(0)]
    assert sorted(p.name for p in root.iterdir()) == [scene_name(0), "vkitti2_scene01"]


@pytest.mark.slow
def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "data"
    args = ["synth", "--scenes", "3", "--out", str(out), "--size", "16", "--frames", "3", "--cameras", "2", "--quiet"]
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == [scene_name(i) for i in range(3)]
    assert main(["validate", str(out)]) == 0
    assert "3 scene(s) checked: all valid" in capsys.readouterr().out
    assert main(["synth", "--scenes", "2", "--out", str(out), "--static-ratio", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("data_prep: error: --static-ratio") and err.count("\n") == 1
    assert main(["synth", "--scenes", "x", "--out", str(out)]) == 2
    assert main(["synth", "--out", str(out)]) == 2
    assert capsys.readouterr().err.count("\n") == 2
    assert main(["synth", "--scenes", "1", "--out", str(tmp_path / "gpu"), "--device", "cuda:7"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("data_prep: error: --device") and err.count("\n") == 1 and not (tmp_path / "gpu").exists()


# --------------------------------------------------------------------------- limits (issue 28)

@pytest.mark.parametrize("argv, message", [
    (["--size", "100000"], "--size 100000 exceeds the limit of 2048 pixels of output height "
                           "(set DIFF4SPLAT_MAX_RESOLUTION to raise it)"),  # a traceback at 7 GB before
    (["--frames", "1000000"], "--frames 1000000 exceeds the limit of 1001 frames (set DIFF4SPLAT_MAX_FRAMES"),
    (["--scenes", "1000000000"], "--scenes 1000000000 exceeds the limit of 100000 scenes (set DIFF4SPLAT_MAX_SCENES"),
    (["--cameras", "100000"], "one scene of --cameras 100000 × --frames 17 at --size 64: estimated "
                              f"{scene_bytes(64, 17, 100_000)} exceeds the limit of 4294967296 bytes "
                              "(set DIFF4SPLAT_MAX_SYNTH_BYTES"),
    (["--size", "1024", "--frames", "1001"], "one scene of --cameras 2 × --frames 1001 at --size 1024: estimated"),
    (["--size", "4"], "--size must be an integer ≥ 8, got 4"),
])
def test_cli_requests_above_a_limit_are_refused_at_once_leaving_no_folder(tmp_path, capsys, argv, message):
    out = tmp_path / "data"
    args = ["synth", "--scenes", "1", "--out", str(out), "--quiet", *argv]
    tracemalloc.start()
    t0 = time.perf_counter()
    code = main(args)
    elapsed, peak = time.perf_counter() - t0, tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"data_prep: error: {message}"), err
    assert elapsed < 1 and peak < 10 << 20
    assert not out.exists()  # no empty output folder either
    with pytest.raises(ValueError, match=r"(exceeds the limit|must be an integer)"):  # the library refuses too
        synthesize(out, **_library_args(["--scenes", "1", *argv]), progress=False)
    assert not out.exists()


def _library_args(argv):
    names = {"--scenes": "num_scenes", "--size": "size", "--frames": "frames", "--cameras": "cameras"}
    return {names[k]: int(v) for k, v in zip(argv[::2], argv[1::2], strict=True)}


def test_library_messages_name_the_parameters(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="^num_scenes 200000 exceeds the limit of 100000 scenes"):
        synthesize(tmp_path / "d", 200_000, progress=False)
    monkeypatch.setenv("DIFF4SPLAT_MAX_SCENES", "10")
    with pytest.raises(ValueError, match="^num_scenes 11 exceeds the limit of 10 scenes"):
        synthesize(tmp_path / "d", 11, progress=False)
    assert not (tmp_path / "d").exists()


class _FirstScene(Exception):
    pass


@pytest.mark.parametrize("workers", [1, 2])
def test_the_first_scene_is_started_without_looking_at_every_later_path(tmp_path, monkeypatch, workers):
    """``--scenes 1000000000`` printed nothing for 60 s: it checked 10⁹ paths before writing scene 0 (10⁶ took
    22 s on a 2-core CPU)."""
    monkeypatch.setenv("DIFF4SPLAT_MAX_SCENES", str(10**6))
    monkeypatch.setattr(data_prep.synth_dataset, "scene_bytes", lambda *a: 0)
    started = []

    def first(out, index, seed, **kw):
        started.append(index)
        raise _FirstScene

    monkeypatch.setattr(data_prep.synth_dataset, "generate_scene", first)
    if workers > 1:  # a spawned worker would import the real generate_scene: run the pool's tasks here
        monkeypatch.setattr(data_prep.engine, "ProcessPoolExecutor", _InlinePool)
    out = tmp_path / "data"
    t0 = time.perf_counter()
    with pytest.raises(_FirstScene):
        synthesize(out, 10**6, workers=workers, progress=False)
    assert time.perf_counter() - t0 < 2 and started[0] == 0
    assert not out.exists()  # created by this run and still empty: removed


class _InlinePool:
    """A stand-in for ProcessPoolExecutor running each task at submission (its result or error in a Future)."""

    def __init__(self, *args, **kwargs):
        pass

    def shutdown(self, wait=True, *, cancel_futures=False):
        pass

    def submit(self, fn, *args, **kwargs):
        fut = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as e:
            fut.set_exception(e)
        return fut


def test_max_gaussians_bounds_every_scene():
    """The memory estimate's Gaussian count is an upper bound, also for the densest (image-textured) scenes."""
    for size, k in ((64, 2), (128, 2)):  # the densest of seeds [11, 0…2]: 16 027 and 29 624 Gaussians
        rng = np.random.default_rng([11, k])
        spec = sample_scene_spec(rng, dynamic=True, num_cameras=1, size=size, num_frames=2, texture_ratio=1.0)
        n = build_gaussians(spec, rng)[0].num_gaussians
        assert n <= max_gaussians(size) < 1.2 * n, (size, n, max_gaussians(size))  # a bound, and not a loose one


# --------------------------------------------------------------------------- image textures (texture_ratio)

OLD_SPEC_SHA256 = ["84a895f8dfc6c3b600ead9088974f0605b20a928dcd9d8f73ac10bc6e7bbaf17",
                   "e07bcbca3765eed36c4465b5ebae1513154e16b673ef46254d6a28f020662c4e",
                   "fa2996ab418e0ce9d950189357acd2c3b5ed124188512cda8c043373b4a4495c"]
"""sha256 of json.dumps(spec, sort_keys=True) of default_rng([7, k]) specs (dynamic, 1 camera, 16 px, 3
frames), computed by the procedural-only code before image textures existed (commit 4123a18)."""


def _spec(seed, k, ratio, size=SIZE):
    rng = np.random.default_rng([seed, k])
    return sample_scene_spec(rng, dynamic=True, num_cameras=1, size=size, num_frames=3, texture_ratio=ratio), rng


def _surfaces(spec):
    return [spec["ground"], spec["wall"], *spec["objects"]]


def test_texture_ratio_zero_reproduces_the_procedural_scenes():
    for k, digest in enumerate(OLD_SPEC_SHA256):
        spec, _ = _spec(7, k, 0.0, size=16)
        assert hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest() == digest, k
    spec, rng = _spec(7, 0, 0, size=16)
    res = render_spec(spec, rng)
    rgb = np.stack(res.rgb).astype(np.float64)  # the old code's render of this scene (same commit as above)
    np.testing.assert_allclose([rgb.mean(), rgb.std()], [0.39332248614583576, 0.22421037246051173], rtol=1e-6)
    assert res.track_ids[:4].tolist() == [3110, 3111, 3112, 3113]
    assert res.caption == ("a yellow ball rolls towards the camera on a concrete floor, "
                           "while the camera trucks right")


def test_texture_ratio_one_textures_every_surface_and_changes_only_textures():
    for k in range(8):
        plain, _ = _spec(8, k, 0.0)
        full, _ = _spec(8, k, 1.0)
        half, _ = _spec(8, k, 0.5)
        assert all(s["texture"]["kind"] == "image" for s in _surfaces(full))
        assert not any(s["texture"]["kind"] == "image" for s in _surfaces(plain))
        for s in _surfaces(full):
            t = s["texture"]
            assert t["file"] in IMAGE_TEXTURES and 0.5 <= t["metres"] <= 3.0
            assert 0 <= min(t["tint"]) <= max(t["tint"]) <= 1
        assert full["ground"]["material"] == IMAGE_TEXTURES[full["ground"]["texture"]["file"]]
        for other in (full, half):  # layout, colours, motions and cameras do not depend on texture_ratio
            strip = lambda sp: {**sp, "ground": None, "wall": None,  # noqa: E731
                                "objects": [{**o, "texture": None} for o in sp["objects"]]}
            assert strip(other) == strip(plain)
            for a, b in zip(_surfaces(other), _surfaces(plain), strict=True):
                assert a["texture"] == b["texture"] or a["texture"]["kind"] == "image"
    kinds = [s["texture"]["kind"] == "image" for k in range(40) for s in _surfaces(_spec(9, k, 0.5)[0])]
    assert 0.35 < np.mean(kinds) < 0.65
    with pytest.raises(ValueError, match="texture_ratio"):
        _spec(9, 0, 1.01)


def test_image_textured_ground_shows_the_photograph():
    """The ground Gaussians' colours are the image texture at their (x, z), unjittered and unshaded here
    (noise 0, ambient 1, white light), and image-textured ground is IMAGE_SPACING × as finely sampled."""
    spec, _ = _spec(10, 0, 0.0, size=64)
    spec["light"] = {"direction": [0.0, -1.0, 0.0], "ambient": 1.0, "tint": [1.0, 1.0, 1.0]}
    on_ground = lambda g, ids: (g.means[:, 1] == spec["ground_y"]).numpy() & (ids == -1)  # noqa: E731  (not boxes)
    n_plain = int(on_ground(*build_gaussians(spec, np.random.default_rng(0))).sum())
    tex = {"kind": "image", "file": "camera.png", "grey": True, "crop": [10.0, 20.0, 200.0], "metres": 3.0,
           "angle": 0.4, "tint": [0.9, 0.6, 0.3], "noise": 0.0}
    spec["ground"]["texture"] = tex
    g, ids = build_gaussians(spec, np.random.default_rng(0))
    ground = on_ground(g, ids)
    assert abs(ground.sum() / n_plain - IMAGE_SPACING ** -2) < 0.3  # (3.8: the disc's rim)
    xz = g.means[ground][:, [0, 2]].double().numpy()
    rgb = sh0_to_rgb(g.sh[ground, 0]).double().numpy()
    expect = image_albedo(tex, xz, 0.25 * IMAGE_SPACING)
    np.testing.assert_allclose(rgb, expect, atol=1e-5)
    assert rgb.std(0).max() > 0.1  # the photograph (dark coat, bright sky), not a flat colour


def test_image_textured_scenes_are_deterministic(tmp_path):
    kw = dict(size=SIZE, frames=3, cameras=1, texture_ratio=1.0)
    a = load_scene(generate_scene(tmp_path / "a", 2, 21, **kw))
    b = load_scene(generate_scene(tmp_path / "b", 2, 21, **kw))
    plain = load_scene(generate_scene(tmp_path / "p", 2, 21, **{**kw, "texture_ratio": 0.0}))
    for i in range(3):
        assert np.array_equal(a.rgb("cam00", i), b.rgb("cam00", i))
    assert not np.allclose(a.rgb("cam00", 0), plain.rgb("cam00", 0), atol=0.02)
    spec = a.meta.extra["synth"]["spec"]
    assert all(s["texture"]["kind"] == "image" for s in _surfaces(spec))
    assert spec == b.meta.extra["synth"]["spec"] and validate_scene(tmp_path / "a" / scene_name(2)) == []


@pytest.mark.parametrize("value", ["1.5", "-0.1", "nan", "x"])
def test_cli_bad_texture_ratio_is_one_line_exit_2(tmp_path, capsys, value):
    assert main(["synth", "--scenes", "1", "--out", str(tmp_path / "d"), "--texture-ratio", value]) == 2
    err = capsys.readouterr().err
    assert err == f"data_prep: error: argument --texture-ratio: must be a number in [0, 1], got {value!r}\n"
    assert not (tmp_path / "d").exists()


def test_synth_checks_one_scene_per_worker_against_the_memory_it_may_use(tmp_path, monkeypatch, capsys):
    """The memory check sees the process's caps (here a monkeypatched room of the process's own memory plus
    1.5 scenes): one worker fits, two do not, and the refusal names --workers before anything is made."""
    one = data_prep.synth_dataset.scene_bytes(64, 17, 2)
    monkeypatch.setattr(limits, "available_memory", lambda: psutil.Process().memory_info().rss + int(1.5 * one))
    args = ["synth", "--scenes", "2", "--out", str(tmp_path / "d"), "--quiet"]
    assert main([*args, "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "2 at a time: estimated peak memory" in err and "--workers" in err and err.count("\n") == 1
    assert not (tmp_path / "d").exists()
    data_prep.synth_dataset.check_synth_request(2, 0, size=64, frames=17, cameras=2, workers=1, static_ratio=0.4,
                                                texture_ratio=0.5)


# --------------------------------------------------------------------------- motion kinds and movers (issue 58)

def test_default_motion_knobs_draw_the_recorded_scenes():
    """The held-out sets on record (seeds 777, 20261202, 20261203) were drawn before ``motions``/``max_movers``
    existed: the defaults must draw the same specs (this digest was taken from the sampler without the knobs)."""
    specs = [sample_scene_spec(np.random.default_rng([5, k]), dynamic=True, num_cameras=2, size=64, num_frames=17)
             for k in range(8)]
    digest = hashlib.sha256(json.dumps(specs, sort_keys=True).encode()).hexdigest()
    assert digest == "6b4df60abe8cc6a98cf7ac11c707f19f1a2dd1ae16e6fe879b73581a2c4e784b"
    explicit = [sample_scene_spec(np.random.default_rng([5, k]), dynamic=True, num_cameras=2, size=64, num_frames=17,
                                  motions=tuple(reversed(MOTIONS)), max_movers=None) for k in range(8)]
    assert explicit == specs  # the kinds are a set: their order does not change the draw


def test_one_translating_mover_names_one_direction():
    for k in range(20):
        spec = sample_scene_spec(np.random.default_rng([9, k]), dynamic=True, num_cameras=1, size=SIZE,
                                 num_frames=T, motions=("translate",), max_movers=1)
        moving = [o["motion"] for o in spec["objects"] if o["motion"] is not None]
        assert len(moving) == 1 and moving[0]["kind"] == "translate"
        assert caption_direction(caption_for(spec, np.eye(3))) is not None
    kinds = set()
    for k in range(30):
        spec = sample_scene_spec(np.random.default_rng([9, k]), dynamic=True, num_cameras=1, size=SIZE,
                                 num_frames=T, motions=["bounce", "rotate"], max_movers=2)
        moving = [o["motion"]["kind"] for o in spec["objects"] if o["motion"] is not None]
        assert 1 <= len(moving) <= 2
        kinds |= set(moving)
    assert kinds == {"bounce", "rotate"}


@pytest.mark.parametrize("motions, max_movers, message", [
    (("spin",), None, "motions must be distinct kinds"), ((), None, "motions must be distinct kinds"),
    (("translate", "translate"), None, "motions must be distinct kinds"), (None, None, "motions must be"),
    (MOTIONS, 0, "max_movers must be an integer ≥ 1"), (MOTIONS, 1.5, "max_movers must be an integer"),
])
def test_bad_motion_knobs_are_refused(motions, max_movers, message):
    with pytest.raises(ValueError, match=message):
        sample_scene_spec(np.random.default_rng(0), dynamic=True, num_cameras=1, size=SIZE, num_frames=T,
                          motions=motions, max_movers=max_movers)


def test_cli_motion_knobs(tmp_path, capsys):
    out = tmp_path / "dir"
    args = ["synth", "--scenes", "2", "--out", str(out), "--size", "16", "--frames", "3", "--static-ratio", "0",
            "--motions", " translate", "--max-movers", "1", "--quiet"]
    assert main(args) == 0
    for i in range(2):
        synth = load_scene(out / scene_name(i)).meta.extra["synth"]
        assert synth["motions"] == ["translate"] and synth["max_movers"] == 1
        assert [o["motion"]["kind"] for o in synth["spec"]["objects"] if o["motion"]] == ["translate"]
    default = tmp_path / "default"
    assert main(["synth", "--scenes", "1", "--out", str(default), "--size", "16", "--frames", "3", "--quiet"]) == 0
    assert set(load_scene(default / scene_name(0)).meta.extra["synth"]) == {"seed", "index", "spec"}
    for flag, value, start in (("--motions", "translate,spin", "data_prep: error: --motions"),
                               ("--max-movers", "0", "data_prep: error: --max-movers")):
        assert main(["synth", "--scenes", "1", "--out", str(tmp_path / "bad"), flag, value]) == 2
        err = capsys.readouterr().err
        assert err.startswith(start) and err.count("\n") == 1 and not (tmp_path / "bad").exists()
