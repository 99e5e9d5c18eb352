"""Tests for diff4splat.cameras.trajectories: preset motions, look-at signs and validation."""
import math

import pytest
import torch

from diff4splat.cameras import (
    DEFAULT_AMPLITUDES,
    TRAJECTORIES,
    CameraPath,
    intrinsics_from_fov,
    look_at,
    make_trajectory,
)
from diff4splat.cameras.trajectories import AMPLITUDE_LIMITS, amplitude_help, check_amplitude

W, H = 64, 48
K = intrinsics_from_fov(W, H, fov_x_deg=60.0, dtype=torch.float64)
_MOVES = ("pan-left", "pan-right", "up", "down")


def project(path: CameraPath, X: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates (T, 2) and depths (T,) of a world point X (3,) in every frame."""
    Xh = torch.cat([X, X.new_ones(1)])
    cam = (path.viewmats @ Xh)[:, :3]
    uvw = torch.einsum("tij,tj->ti", path.Ks, cam)
    return uvw[:, :2] / uvw[:, 2:], cam[:, 2]


@pytest.mark.parametrize("name", TRAJECTORIES)
@pytest.mark.parametrize("T", [1, 2, 9])
def test_every_preset_is_valid_and_starts_at_identity(name, T):
    p = make_trajectory(name, T, K, W, H, scene_depth=3.0)
    assert isinstance(p, CameraPath) and len(p) == T
    p.validate()
    assert torch.equal(p.viewmats[0], torch.eye(4, dtype=torch.float64))
    assert (p.width, p.height) == (W, H)
    torch.testing.assert_close(p.Ks, K.expand(T, 3, 3))
    expect_t = torch.arange(T, dtype=torch.float64) / max(T - 1, 1)
    torch.testing.assert_close(p.times, expect_t)
    if T > 1:  # every preset actually moves the camera
        assert p.camera_centers()[-1].norm() > 0.1


def test_orbit_keeps_target_centred_and_closes_the_loop():
    T, d = 24, 2.5
    p = make_trajectory("orbit", T, K, W, H, scene_depth=d)
    target = torch.tensor([0.0, 0.0, d], dtype=torch.float64)
    uv, depth = project(p, target)
    torch.testing.assert_close(uv, torch.tensor([[W / 2, H / 2]], dtype=torch.float64).expand(T, 2), atol=1e-9, rtol=0)
    torch.testing.assert_close(depth, torch.full((T,), d, dtype=torch.float64))  # always in front, at distance d
    c = p.camera_centers()
    # Horizontal circle (y = 0) of radius d around the target.
    torch.testing.assert_close(c[:, 1], torch.zeros(T, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close((c - target).norm(dim=-1), torch.full((T,), d, dtype=torch.float64))
    # Full 360°: azimuth advances 2π/T per frame, so the last frame is one step from the first.
    az = torch.atan2(c[:, 0] - target[0], -(c[:, 2] - target[2]))
    steps = torch.remainder(az[1:] - az[:-1], 2 * math.pi)
    torch.testing.assert_close(steps, torch.full((T - 1,), 2 * math.pi / T, dtype=torch.float64))
    assert (c[-1] - c[0]).norm().item() == pytest.approx(2 * d * math.sin(math.pi / T))
    R_last = p.viewmats[-1, :3, :3]
    angle = math.acos((torch.trace(R_last).item() - 1) / 2)
    assert angle == pytest.approx(2 * math.pi / T)
    # Starts by moving to the camera's right (+x) and the image stays upright (y of R is world y).
    assert c[1, 0] > 0
    torch.testing.assert_close(p.viewmats[:, 1, :3], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(T, 3))


@pytest.mark.parametrize("a", [0.5, -0.8, 2.0])
def test_arc_sweeps_its_angle_on_the_circle_around_the_target(a):
    T, d = 9, 2.5
    p = make_trajectory("arc", T, K, W, H, scene_depth=d, amplitude=a)
    assert len(p) == T and torch.equal(p.viewmats[0], torch.eye(4, dtype=torch.float64))
    target = torch.tensor([0.0, 0.0, d], dtype=torch.float64)
    uv, depth = project(p, target)  # every camera looks at c, from distance d
    torch.testing.assert_close(uv, torch.tensor([[W / 2, H / 2]], dtype=torch.float64).expand(T, 2), atol=1e-9, rtol=0)
    torch.testing.assert_close(depth, torch.full((T,), d, dtype=torch.float64))
    c = p.camera_centers()
    torch.testing.assert_close((c - target).norm(dim=-1), torch.full((T,), d, dtype=torch.float64))
    torch.testing.assert_close(c[:, 1], torch.zeros(T, dtype=torch.float64), atol=1e-12, rtol=0)
    # The angle at c between the first and last centres is |a| (chord 2d·sin(|a|/2)), in equal steps.
    u = (c - target) / d
    angle = torch.atan2(torch.linalg.cross(u[0], u[-1], dim=-1).norm(), u[0] @ u[-1]).item()
    assert angle == pytest.approx(abs(a), abs=1e-12)
    assert (c[-1] - c[0]).norm().item() == pytest.approx(2 * d * math.sin(abs(a) / 2))
    az = torch.atan2(u[:, 0], -u[:, 2])
    torch.testing.assert_close(az, a * p.times)
    # a > 0: the eye moves to the first camera's right (+x); a < 0: to its left. Image stays upright.
    assert math.copysign(1.0, c[-1, 0].item()) == math.copysign(1.0, a) and abs(c[-1, 0].item()) > 0.1
    torch.testing.assert_close(p.viewmats[:, 1, :3], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(T, 3))


def test_arc_default_angle_and_mirror_symmetry():
    d = 2.0
    p = make_trajectory("arc", 5, K, W, H, scene_depth=d)
    assert DEFAULT_AMPLITUDES["arc"] == 0.5
    c = p.camera_centers()
    assert (c[-1] - c[0]).norm().item() == pytest.approx(2 * d * math.sin(0.25))
    mirror = make_trajectory("arc", 5, K, W, H, scene_depth=d, amplitude=-0.5).camera_centers()
    torch.testing.assert_close(mirror, c * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))


def test_arc_coincides_with_orbit():
    """orbit advances 2π/T per frame; arc advances a/(T−1): they agree for a = 2π·(T−1)/T, and the
    full-turn arc (a = 2π) is orbit of T−1 frames plus the frame that closes the loop."""
    T, d = 8, 3.0
    orbit = make_trajectory("orbit", T, K, W, H, scene_depth=d)
    arc = make_trajectory("arc", T, K, W, H, scene_depth=d, amplitude=2 * math.pi * (T - 1) / T)
    torch.testing.assert_close(arc.viewmats, orbit.viewmats, atol=1e-12, rtol=0)
    full = make_trajectory("arc", T, K, W, H, scene_depth=d, amplitude=2 * math.pi)
    short = make_trajectory("orbit", T - 1, K, W, H, scene_depth=d)
    torch.testing.assert_close(full.viewmats[:-1], short.viewmats, atol=1e-12, rtol=0)
    torch.testing.assert_close(full.viewmats[-1], torch.eye(4, dtype=torch.float64), atol=1e-12, rtol=0)


def test_spiral_looks_at_target_and_reaches_its_radius():
    T, d, a = 17, 2.0, 0.3
    p = make_trajectory("spiral", T, K, W, H, scene_depth=d, amplitude=a)
    uv, _ = project(p, torch.tensor([0.0, 0.0, d], dtype=torch.float64))
    torch.testing.assert_close(uv, torch.tensor([[W / 2, H / 2]], dtype=torch.float64).expand(T, 2), atol=1e-9, rtol=0)
    c = p.camera_centers()
    t = p.times
    torch.testing.assert_close(c[:, :2].norm(dim=-1), a * d * t)
    torch.testing.assert_close(c[:, 2], torch.zeros(T, dtype=torch.float64), atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    "name, direction",
    [
        ("forward", (0, 0, 1)),
        ("backward", (0, 0, -1)),
        ("up", (0, -1, 0)),
        ("down", (0, 1, 0)),
        ("pan-left", (-1, 0, 0)),
        ("pan-right", (1, 0, 0)),
    ],
)
def test_translation_presets_move_along_their_axis_and_keep_orientation(name, direction):
    T, d = 5, 2.0
    p = make_trajectory(name, T, K, W, H, scene_depth=d)
    a = DEFAULT_AMPLITUDES[name]
    expect = a * d * p.times[:, None] * torch.tensor(direction, dtype=torch.float64)
    torch.testing.assert_close(p.camera_centers(), expect)
    torch.testing.assert_close(p.viewmats[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(T, 3, 3))
    p2 = make_trajectory(name, T, K, W, H, scene_depth=d, amplitude=2 * a)
    torch.testing.assert_close(p2.camera_centers(), 2 * expect)


def test_translation_image_motion_signs():
    d = 2.0
    target = torch.tensor([0.0, 0.0, d], dtype=torch.float64)
    off_axis = torch.tensor([0.3, 0.2, d], dtype=torch.float64)
    uv = {n: project(make_trajectory(n, 3, K, W, H, scene_depth=d), target)[0][-1] for n in _MOVES}
    assert uv["pan-right"][0] < W / 2 and uv["pan-left"][0] > W / 2  # scene slides opposite to the camera
    assert uv["up"][1] > H / 2 and uv["down"][1] < H / 2  # camera up → scene moves down in the image (y down)
    centre = torch.tensor([W / 2, H / 2], dtype=torch.float64)
    r0 = (project(make_trajectory("forward", 3, K, W, H, scene_depth=d), off_axis)[0] - centre).norm(dim=-1)
    r1 = (project(make_trajectory("backward", 3, K, W, H, scene_depth=d), off_axis)[0] - centre).norm(dim=-1)
    assert r0[2] > r0[1] > r0[0] and r1[2] < r1[1] < r1[0]  # dolly in magnifies, dolly out shrinks


def test_look_at_identity_and_up_direction():
    eye = torch.zeros(1, 3, dtype=torch.float64)
    V = look_at(eye, torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64))
    assert torch.equal(V[0], torch.eye(4, dtype=torch.float64))
    eyes = torch.tensor([[1.0, -0.5, -2.0], [-3.0, 0.2, 1.0]], dtype=torch.float64)
    tgt = torch.tensor([0.2, 0.1, 0.4], dtype=torch.float64)
    V = look_at(eyes, tgt)
    R = V[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, dtype=torch.float64))
    path = CameraPath(V, K.expand(2, 3, 3).clone(), W, H)
    uv, depth = project(path, tgt)
    torch.testing.assert_close(uv, torch.tensor([[W / 2, H / 2]] * 2, dtype=torch.float64), atol=1e-9, rtol=0)
    assert bool((depth > 0).all())
    above, _ = project(path, tgt + torch.tensor([0.0, -0.3, 0.0], dtype=torch.float64))  # world up = −y
    assert bool((above[:, 1] < H / 2).all())
    with pytest.raises(ValueError, match="up"):
        look_at(torch.zeros(1, 3, dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(name="zoom"), "name"),
        (dict(num_frames=0), "num_frames"),
        (dict(num_frames=2.0), "num_frames"),
        (dict(scene_depth=0.0), "scene_depth"),
        (dict(scene_depth=-1.0), "scene_depth"),
        (dict(scene_depth=float("inf")), "scene_depth"),
        (dict(name="forward", amplitude=0.0), "amplitude"),
        (dict(name="forward", amplitude=-0.5), "amplitude"),
        (dict(name="arc", amplitude=0.0), "amplitude"),
        (dict(name="arc", amplitude=30.0), "amplitude"),  # degrees by mistake: > 2π
        (dict(name="arc", amplitude=-6.3), "amplitude"),
        (dict(name="arc", amplitude=float("nan")), "amplitude"),
        (dict(name="orbit", amplitude=0.5), "amplitude"),
        (dict(K=torch.eye(4)), "K"),
        (dict(K=torch.diag(torch.tensor([-1.0, 1.0, 1.0]))), "Ks"),
    ],
)
def test_validation_names_the_field(kwargs, field):
    args = dict(name="spiral", num_frames=5, K=K, width=W, height=H)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        make_trajectory(**args)


def test_float32_intrinsics_give_float32_path():
    p = make_trajectory("orbit", 9, K.float(), W, H)
    assert p.viewmats.dtype == p.Ks.dtype == p.times.dtype == torch.float32
    assert torch.equal(p.viewmats[0], torch.eye(4))


# --- amplitude ranges (issue 28): every preset refuses what it cannot show, naming the flag, range and unit ---


@pytest.mark.parametrize("name", [n for n in TRAJECTORIES if n != "orbit"])
def test_every_preset_is_a_finite_path_up_to_its_amplitude_limit(name):
    limit = AMPLITUDE_LIMITS[name]
    assert 0 < DEFAULT_AMPLITUDES[name] <= limit
    assert check_amplitude(name, None) == DEFAULT_AMPLITUDES[name] and check_amplitude(name, limit) == limit
    for a in (limit, limit * 1e-6) + ((-limit,) if name == "arc" else ()):
        p = make_trajectory(name, 9, K.float(), W, H, scene_depth=2.0, amplitude=a)
        assert bool(torch.isfinite(p.viewmats).all())
        torch.testing.assert_close(p.camera_centers()[-1].double().norm(),  # the last eye moves as far as asked
                                   torch.tensor(2.0 * (2 * math.sin(abs(a) / 2) if name == "arc" else abs(a)),
                                                dtype=torch.float64), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", [n for n in TRAJECTORIES if n != "orbit"])
@pytest.mark.parametrize("bad", ["just_above", "huge", "zero", "negative", "nan", "inf", "string", "bool"])
def test_amplitude_outside_the_preset_range_names_flag_preset_range_and_unit(name, bad):
    limit = AMPLITUDE_LIMITS[name]
    value = {"just_above": limit * (1 + 1e-9), "huge": 1e30, "zero": 0.0, "negative": -limit * 1.01,
             "nan": math.nan, "inf": math.inf, "string": "0.5", "bool": True}[bad]
    if name != "arc" and bad == "negative":
        value = -0.1  # arc accepts negative angles (to the left); the others accept none
    unit = "radians" if name == "arc" else "scene depths"
    with pytest.raises(ValueError) as info:
        check_amplitude(name, value, "--amplitude")
    msg = str(info.value)
    assert msg.startswith("--amplitude ") and f" for {name} must be in " in msg and unit in msg, msg
    assert ("2π ≈ 6.283" if name == "arc" else f"(0, {limit:g}]") in msg, msg
    assert f"default {DEFAULT_AMPLITUDES[name]:g}" in msg and "\n" not in msg
    with pytest.raises(ValueError, match=f"^amplitude .* for {name} must be in"):  # the library's own name
        make_trajectory(name, 5, K, W, H, amplitude=value)


def test_huge_amplitudes_no_longer_surface_as_geometry_errors():
    """The messages users saw before: non-finite means (forward) and a parallel up vector (spiral)."""
    for name in ("forward", "spiral", "backward", "pan-left"):
        with pytest.raises(ValueError, match="--amplitude 1e\\+30 for") as info:
            check_amplitude(name, 1e30, "--amplitude")
        assert "up" not in str(info.value).split(";")[0] and "non-finite" not in str(info.value)


def test_arc_in_degrees_by_mistake_is_converted_in_the_message():
    with pytest.raises(ValueError, match="30° would be 0.524 rad"):
        check_amplitude("arc", 30, "--amplitude")


def test_orbit_amplitude_explains_itself_without_api_jargon():
    assert check_amplitude("orbit", None) is None
    with pytest.raises(ValueError) as info:
        check_amplitude("orbit", 1.0, "--amplitude")
    msg = str(info.value)
    assert msg.startswith("--amplitude does not apply to orbit") and "360°" in msg and "leave --amplitude out" in msg
    assert "None" not in msg
    with pytest.raises(ValueError, match="unknown|must be one of"):
        check_amplitude("loop", 1.0)


def test_amplitude_help_lists_every_range():
    text = amplitude_help()
    for name, limit in AMPLITUDE_LIMITS.items():
        assert name in text and (f"(0, {limit:g}]" in text or name == "arc")
    assert "2π" in text and "orbit takes none" in text
