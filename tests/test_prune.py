import math

import pytest
import torch

from diff4splat.assembly.prune import (
    SLIDE_FACTORS,
    _footprint_max,
    duplicate_mask,
    occluder_mask,
    prune_scene,
    settle_generated,
    slide_behind,
    visibility_mask,
)
from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.render import rasterize_dense
from diff4splat.render.sequence import render_path
from diff4splat.render.settings import NEAR_PLANE
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians


def _path(T=3, W=32, H=32):
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0, dtype=torch.float64).expand(T, 3, 3).clone()
    return CameraPath(torch.eye(4, dtype=torch.float64).repeat(T, 1, 1), K, W, H)


def _scene(means, opacities, d_means=None):
    n = means.shape[0]
    q = torch.zeros(n, 4, dtype=torch.float64)
    q[:, 0] = 1
    g = Gaussians(means, q, torch.full((n, 3), 0.05, dtype=torch.float64), opacities,
                  torch.rand(n, 1, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))
    if d_means is None:
        return DynamicGaussians(g)
    T = d_means.shape[0]
    dq = torch.zeros(T, n, 4, dtype=torch.float64)
    dq[..., 0] = 1
    return DynamicGaussians(g, torch.linspace(0, 1, T, dtype=torch.float64), d_means, dq, torch.zeros_like(d_means))


def test_prunes_low_opacity_behind_camera_and_out_of_frustum_only():
    means = torch.tensor([[0.0, 0, 2], [0.1, 0, 2], [0, 0, -2], [50.0, 0, 2], [0, 0.1, 3]], dtype=torch.float64)
    opac = torch.tensor([0.9, 0.001, 0.9, 0.9, 0.5], dtype=torch.float64)
    pruned, stats = prune_scene(_scene(means, opac), _path(), min_opacity=0.005)
    assert stats == {"before": 5, "low_opacity": 1, "unseen": 2, "after": 2}
    torch.testing.assert_close(pruned.canonical.means, means[[0, 4]])


def test_a_gaussian_seen_only_at_a_later_time_is_kept():
    means = torch.tensor([[0.0, 0, 2], [50.0, 0, 2]], dtype=torch.float64)
    d = torch.zeros(3, 2, 3, dtype=torch.float64)
    d[2, 1, 0] = -50.0  # the second Gaussian moves into view at the last frame
    scene = _scene(means, torch.tensor([0.9, 0.9], dtype=torch.float64), d)
    assert visibility_mask(scene, _path()).tolist() == [True, True]
    d[2, 1, 0] = 0.0
    scene = _scene(means, torch.tensor([0.9, 0.9], dtype=torch.float64), d)
    assert visibility_mask(scene, _path()).tolist() == [True, False]


def test_pruning_does_not_change_any_rendered_frame():
    g = torch.Generator().manual_seed(1)
    means = torch.randn(200, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 3.0, 2.0], dtype=torch.float64)
    means[:, 2] += 2.0
    opac = torch.rand(200, generator=g, dtype=torch.float64) * 0.6
    opac[:20] = 1 / 512  # below 1/255: can never pass the alpha threshold
    scene = _scene(means, opac)
    path = _path()
    pruned, stats = prune_scene(scene, path, min_opacity=1 / 255)
    assert stats["after"] < 200 and stats["unseen"] > 0 and stats["low_opacity"] == 20
    for a, b in zip(render_path(scene, path), render_path(pruned, path), strict=False):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_min_opacity_out_of_range_raises():
    with pytest.raises(ValueError, match="min_opacity"):
        prune_scene(_scene(torch.zeros(1, 3, dtype=torch.float64) + 1, torch.ones(1, dtype=torch.float64) * 0.5), None,
                    1.0)


# --- duplicate_mask: near-duplicate Gaussians across source frames ------------------------------------------------

W_DUP = H_DUP = 16


def _K(n=1):
    return intrinsics_from_fov(W_DUP, H_DUP, fov_y_deg=60.0, dtype=torch.float64).expand(n, 3, 3).clone()


def _plane(z, rows=range(H_DUP), cols=range(W_DUP), viewmat=None, K=None):
    """Points on the pixel-centre rays of camera ``viewmat`` (default identity) at camera depth ``z``."""
    K = _K()[0] if K is None else K
    vm = torch.eye(4, dtype=torch.float64) if viewmat is None else viewmat
    pts = []
    for i in rows:
        for j in cols:
            pc = torch.tensor([(j + 0.5 - K[0, 2]) / K[0, 0] * z, (i + 0.5 - K[1, 2]) / K[1, 1] * z, z],
                              dtype=torch.float64)
            pts.append(vm[:3, :3].T @ (pc - vm[:3, 3]))  # camera → world
    return torch.stack(pts)


def _gaussians(means, opacity=0.9, scale=0.12, d_means=None, key_times=None):
    n = means.shape[0]
    q = torch.zeros(n, 4, dtype=torch.float64)
    q[:, 0] = 1
    g = Gaussians(means, q, torch.full((n, 3), scale, dtype=torch.float64),
                  torch.full((n,), opacity, dtype=torch.float64), torch.zeros(n, 1, 3, dtype=torch.float64))
    if d_means is None:
        return DynamicGaussians(g)
    dq = torch.zeros(*d_means.shape[:2], 4, dtype=torch.float64)
    dq[..., 0] = 1
    return DynamicGaussians(g, key_times, d_means, dq, torch.zeros_like(d_means))


def _cat(*scenes):
    return DynamicGaussians(Gaussians(*(torch.cat([getattr(s.canonical, f) for s in scenes])
                                        for f in ("means", "quats", "scales", "opacities", "sh"))))


def _source(*counts):
    return torch.cat([torch.full((c,), s, dtype=torch.long) for s, c in enumerate(counts)])


def _eye(n):
    return torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)


def _times(*t):
    return torch.tensor(t, dtype=torch.float64)


def _rot_y(deg, z=0.0):
    a = math.radians(deg)
    vm = torch.eye(4, dtype=torch.float64)
    vm[0, 0], vm[0, 2], vm[2, 0], vm[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
    vm[2, 3] = z
    return vm


def test_same_plane_from_the_same_camera_is_all_duplicate_in_the_later_source():
    p = _plane(2.0)
    n = p.shape[0]
    scene = _cat(_gaussians(p), _gaussians(p + 0.01))  # source 1: the same surface, 1 cm off
    dup = duplicate_mask(scene, _source(n, n), _eye(2), _K(2), _times(0.0, 0.5), W_DUP, H_DUP)
    assert dup.dtype == torch.bool and dup.shape == (2 * n,)
    assert not dup[:n].any()  # source 0 is never a duplicate
    assert dup[n:].all()


def test_a_source_frame_seeing_new_content_is_kept():
    # source 0 covers only the left half of the image; source 1 covers all of it from the same camera
    left = _plane(2.0, cols=range(W_DUP // 2))
    full = _plane(2.0)
    scene = _cat(_gaussians(left), _gaussians(full))
    dup = duplicate_mask(scene, _source(len(left), len(full)), _eye(2), _K(2), _times(0.0, 1.0), W_DUP, H_DUP)
    grid = dup[len(left):].reshape(H_DUP, W_DUP)
    assert grid[:, :W_DUP // 2 - 1].all()  # already covered
    assert not grid[:, W_DUP // 2 + 1:].any()  # never covered: A < min_alpha
    # camera 1 turned around (looking along −z): source 0's plane is behind it, its own plane is new
    back = _rot_y(180.0)
    behind = _plane(2.0, viewmat=back)
    scene = _cat(_gaussians(full), _gaussians(behind))
    vms = torch.stack([torch.eye(4, dtype=torch.float64), back])
    dup = duplicate_mask(scene, _source(len(full), len(behind)), vms, _K(2), _times(0.0, 1.0), W_DUP, H_DUP)
    assert not dup.any()


def test_gaussians_in_front_of_or_behind_the_earlier_surface_are_kept():
    wall = _plane(3.0)
    rows, cols = range(6, 10), range(6, 10)
    front, on, back = _plane(2.0, rows, cols), _plane(3.0, rows, cols), _plane(4.0, rows, cols)
    scene = _cat(_gaussians(wall), _gaussians(front), _gaussians(on), _gaussians(back))
    source = torch.cat([_source(len(wall)), torch.ones(3 * len(front), dtype=torch.long)])
    dup = duplicate_mask(scene, source, _eye(2), _K(2), _times(0.0, 1.0), W_DUP, H_DUP)
    k = len(front)
    assert not dup[len(wall):len(wall) + k].any()  # 1 m in front: a new occluder
    assert dup[len(wall) + k:len(wall) + 2 * k].all()  # on the surface: a duplicate
    assert not dup[len(wall) + 2 * k:].any()  # 1 m behind: hidden surface, kept


def _on_world_plane(z_world, row, col, viewmat):
    """(1, 3) point where the ray through pixel (row, col) of camera ``viewmat`` meets the plane z = z_world."""
    K = _K()[0]
    d_cam = torch.tensor([(col + 0.5 - K[0, 2]) / K[0, 0], (row + 0.5 - K[1, 2]) / K[1, 1], 1.0], dtype=torch.float64)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    centre, d = -R.T @ t, R.T @ d_cam
    return (centre + (z_world - centre[2]) / d[2] * d)[None]


def _brute_force(scene, source, viewmats, Ks, times, width, height, min_alpha=0.5, depth_tolerance=0.05,
                 exclude_duplicates=True):
    """Per-candidate loop: render the earlier sources' kept Gaussians with the dense reference renderer and
    test each Gaussian of source s by hand (``exclude_duplicates=False`` is the wrong rule that renders
    earlier duplicates too)."""
    M, S = scene.num_gaussians, viewmats.shape[0]
    dup = [False] * M
    for s in range(1, S):
        g = scene.at(float(times[s]), gate=0.0)
        earlier = [i for i in range(M) if source[i] < s and (not dup[i] or not exclude_duplicates)]
        if not earlier:
            continue
        e = torch.tensor(earlier)
        out, alpha, _ = rasterize_dense(g.means[e], g.quats[e], g.scales[e], g.opacities[e], g.opacities[e, None],
                                        viewmats[s:s + 1], Ks[s:s + 1], width, height, render_mode="ED")
        R, t, K = viewmats[s, :3, :3].tolist(), viewmats[s, :3, 3].tolist(), Ks[s].tolist()
        for i in range(M):
            if int(source[i]) != s:
                continue
            m = g.means[i].tolist()
            x, y, z = (sum(R[r][c] * m[c] for c in range(3)) + t[r] for r in range(3))
            if z <= NEAR_PLANE:
                continue
            u, v = K[0][0] * x / z + K[0][2], K[1][1] * y / z + K[1][2]
            if not (0 <= u < width and 0 <= v < height):
                continue
            a, d = float(alpha[0, math.floor(v), math.floor(u), 0]), float(out[0, math.floor(v), math.floor(u), 0])
            dup[i] = a >= min_alpha and abs(z - d) <= depth_tolerance * d
    return torch.tensor(dup)


def _random_scene(per=160, seed=3):
    """Three source cameras (turned ±8°, moved ±0.1 m) see the world plane z = 2.5 that moves with time;
    ``per`` Gaussians each on random pixels' rays, 10 % of them off the plane, random opacities and scales."""
    gen = torch.Generator().manual_seed(seed)
    vms = torch.stack([_rot_y(0.0), _rot_y(8.0, 0.1), _rot_y(-6.0, -0.1)])
    parts = []
    for s in range(3):
        rows = torch.randint(0, H_DUP, (per,), generator=gen).tolist()
        cols = torch.randint(0, W_DUP, (per,), generator=gen).tolist()
        on = torch.cat([_on_world_plane(2.5, r, c, vms[s]) for r, c in zip(rows, cols, strict=True)])
        off = torch.where(torch.rand(per, 1, generator=gen) < 0.1,
                          torch.randn(per, 1, generator=gen, dtype=torch.float64), 0.0)
        centre = -vms[s, :3, :3].T @ vms[s, :3, 3]
        parts.append(on + off * (on - centre) / (on - centre).norm(dim=1, keepdim=True))
    means = torch.cat(parts)
    M = means.shape[0]
    d_means = 0.03 * torch.randn(3, M, 3, generator=gen, dtype=torch.float64)  # a common motion + jitter
    d_means[0] = 0
    d_means[1:, :, 2] += torch.tensor([[0.2], [0.4]], dtype=torch.float64)
    scene = _gaussians(means, 0.9, 0.15, d_means, _times(0.0, 0.5, 1.0))
    scene.canonical.opacities = 0.2 + 0.79 * torch.rand(M, generator=gen, dtype=torch.float64)
    scene.canonical.scales = 0.04 + 0.08 * torch.rand(M, 3, generator=gen, dtype=torch.float64)
    return scene, _source(per, per, per), vms, _K(3), _times(0.0, 0.25, 0.75)


def test_matches_the_brute_force_on_a_random_dynamic_scene():
    per = 160
    scene, source, vms, Ks, times = _random_scene(per)
    dup = duplicate_mask(scene, source, vms, Ks, times, W_DUP, H_DUP)
    expected = _brute_force(scene, source, vms, Ks, times, W_DUP, H_DUP)
    assert dup.tolist() == expected.tolist()
    assert 10 < int(dup.sum()) < 2 * per - 10  # both outcomes occur
    # the scene is sensitive to the sequential rule: rendering earlier duplicates too changes the answer
    assert _brute_force(scene, source, vms, Ks, times, W_DUP, H_DUP, exclude_duplicates=False).tolist() \
        != expected.tolist()


def test_the_deformation_at_the_source_time_is_applied():
    # source 0's plane is at z = 2 at t = 0 and moves 0.5 m away by t = 1; source 1 (frame at t = 1)
    # places the same surface at z = 2.5 (static). At t = 1 both lie at 2.5: a duplicate.
    # (source 0's plane extends 4 pixels past the image at z = 2, so at z = 2.5 it still fills the image)
    p0, p1 = _plane(2.0, range(-4, H_DUP + 4), range(-4, W_DUP + 4)), _plane(2.5)
    n0, n1 = p0.shape[0], p1.shape[0]
    d = torch.zeros(2, n0 + n1, 3, dtype=torch.float64)
    d[1, :n0, 2] = 0.5
    both = _cat(_gaussians(p0), _gaussians(p1))
    scene = DynamicGaussians(both.canonical, _times(0.0, 1.0), d,
                             torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(2, n0 + n1, 4).clone(),
                             torch.zeros_like(d))
    source = _source(n0, n1)
    assert duplicate_mask(scene, source, _eye(2), _K(2), _times(0.0, 1.0), W_DUP, H_DUP)[n0:].all()
    # ignoring the time (every source evaluated at t = 0, the canonical positions): source 0 is at z = 2,
    # 0.5 m in front of source 1's surface, so source 1 is (wrongly) kept as new content behind it
    assert not duplicate_mask(scene, source, _eye(2), _K(2), _times(0.0, 0.0), W_DUP, H_DUP).any()


def test_a_single_source_frame_has_no_duplicates():
    p = _plane(2.0)
    dup = duplicate_mask(_gaussians(p), _source(len(p)), _eye(1), _K(1), _times(0.0), W_DUP, H_DUP)
    assert dup.shape == (len(p),) and not dup.any()


@pytest.mark.parametrize("change, match", [
    ({"source": torch.zeros(3, dtype=torch.long)}, r"source must have shape \(M,\) = \(8,\).*\(3,\)"),
    ({"source": torch.zeros(8)}, r"source must be an integer tensor.*float32"),
    ({"source": torch.full((8,), 2)}, r"source must lie in \[0, S\) = \[0, 2\).*\[2, 2\]"),
    ({"source": torch.full((8,), -1)}, r"source must lie in \[0, S\).*\[-1, -1\]"),
    ({"viewmats": torch.eye(4, dtype=torch.float64)[None].repeat(0, 1, 1)},
     r"viewmats must have shape \(S, 4, 4\) with S ≥ 1.*\(0, 4, 4\)"),
    ({"viewmats": torch.eye(3).repeat(2, 1, 1)}, r"viewmats must have shape.*\(2, 3, 3\)"),
    ({"Ks": torch.eye(3)[None]}, r"Ks must have shape \(S, 3, 3\) = \(2, 3, 3\).*\(1, 3, 3\)"),
    ({"times": torch.zeros(3)}, r"times must have shape \(S,\) = \(2,\).*\(3,\)"),
    ({"times": torch.tensor([0.0, 1.5])}, r"times must lie in \[0, 1\].*1\.5"),
    ({"times": torch.tensor([0.0, float("nan")])}, r"times contains 1 non-finite"),
    ({"width": 0}, r"width must be a positive int.*0"),
    ({"height": 2.5}, r"height must be a positive int.*2\.5"),
    ({"min_alpha": 0.0}, r"min_alpha must lie in \(0, 1\].*0\.0"),
    ({"min_alpha": 1.5}, r"min_alpha must lie in \(0, 1\].*1\.5"),
    ({"min_alpha": float("nan")}, r"min_alpha must lie in \(0, 1\].*nan"),
    ({"min_alpha": "0.5"}, r"min_alpha must lie in \(0, 1\].*'0\.5'"),
    ({"min_alpha": None}, r"min_alpha must lie in \(0, 1\].*None"),
    ({"depth_tolerance": 0.0}, r"depth_tolerance must be a positive finite number.*0\.0"),
    ({"depth_tolerance": -0.1}, r"depth_tolerance must be a positive finite number.*-0\.1"),
])
def test_duplicate_mask_bad_inputs_raise(change, match):
    args = {"scene": _gaussians(_plane(2.0, range(2), range(4))), "source": _source(4, 4), "viewmats": _eye(2),
            "Ks": _K(2), "times": _times(0.0, 1.0), "width": W_DUP, "height": H_DUP}
    args.update(change)
    kw = {k: args.pop(k) for k in ("min_alpha", "depth_tolerance") if k in args}
    with pytest.raises(ValueError, match=match):
        duplicate_mask(*args.values(), **kw)


def test_occluder_mask_drops_later_gaussians_in_front_of_or_on_the_photo_only():
    """In front of the input view's surface at the photo's time or on it: dropped; behind it, outside the image or
    where the input frame covers nothing: kept; source 0 never."""
    wall = _plane(3.0, cols=range(W_DUP // 2))  # the photo's surface covers the left half
    rows = range(6, 10)
    front, on, back = _plane(2.0, rows, range(2, 6)), _plane(3.0, rows, range(2, 6)), _plane(4.0, rows, range(2, 6))
    uncovered = _plane(2.0, rows, range(W_DUP // 2 + 5, W_DUP))  # in front of nothing
    outside = _plane(2.0, rows, range(2, 6), viewmat=_rot_y(180.0))  # behind the input camera
    parts = (wall, front, on, back, uncovered, outside)
    # small candidates (2 cm: a 2-pixel footprint here), so that "uncovered" reaches no covered pixel
    scene = _cat(_gaussians(wall), *(_gaussians(p, scale=0.02) for p in parts[1:]))
    source = torch.cat([_source(len(wall)), torch.full((sum(len(p) for p in parts[1:]),), 2, dtype=torch.long)])
    drop = occluder_mask(scene, source, torch.eye(4, dtype=torch.float64), _K()[0], 0.0, W_DUP, H_DUP)
    sizes = [len(p) for p in parts]
    chunks = drop.split(sizes)
    assert [bool(c.all()) for c in chunks] == [False, True, True, False, False, False]
    assert [bool(c.any()) for c in chunks] == [False, True, True, False, False, False]
    # brute force: a render of the wall alone, each point projected by hand
    K = _K()[0]
    for p, expect in zip(parts[1:], [True, True, False, False, False], strict=True):
        z = p[:, 2]
        u, v = K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]
        inside = (z > 0) & (u >= 0) & (u < W_DUP // 2) & (v >= 0) & (v < H_DUP)
        assert bool((inside & (z < 1.05 * 3.0)).all()) == expect


def test_occluder_mask_tests_the_whole_footprint():
    """A large Gaussian behind the near half of the photo's surface but in front of its far half, which its
    footprint reaches, would cover the photograph there: dropped. Small at the same place: kept."""
    near, far = _plane(2.0, cols=range(W_DUP // 2)), _plane(4.0, cols=range(W_DUP // 2, W_DUP))
    point = _plane(3.0, range(7, 8), range(3, 4))  # behind the near half at its centre pixel (column 3)
    scene = _cat(_gaussians(near), _gaussians(far), _gaussians(point, scale=0.5), _gaussians(point, scale=0.01))
    source = torch.cat([_source(len(near) + len(far)), torch.full((2,), 1, dtype=torch.long)])
    drop = occluder_mask(scene, source, torch.eye(4, dtype=torch.float64), _K()[0], 0.0, W_DUP, H_DUP)
    assert drop.tolist()[-2:] == [True, False] and not drop[:-2].any()


def test_occluder_mask_takes_an_exact_surface_depth():
    """With the surface's depth map given, a Gaussian just in front of its own pixel's surface is dropped even where
    rendering the surface would blend a much nearer neighbour into the expected depth (a rough depth map)."""
    near = _plane(1.0, cols=range(0, W_DUP, 2))  # every other column near, the others far: a comb
    far = _plane(3.0, cols=range(1, W_DUP, 2))
    point = _plane(2.9, range(7, 8), range(5, 6))  # just in front of the far surface at column 5
    scene = _cat(_gaussians(near), _gaussians(far), _gaussians(point, scale=0.005))
    source = torch.cat([_source(len(near) + len(far)), torch.ones(1, dtype=torch.long)])
    depth = torch.where(torch.arange(W_DUP) % 2 == 0, 1.0, 3.0).to(torch.float64).expand(H_DUP, W_DUP)
    vm, K = torch.eye(4, dtype=torch.float64), _K()[0]
    assert occluder_mask(scene, source, vm, K, 0.0, W_DUP, H_DUP, surface_depth=depth)[-1]
    with pytest.raises(ValueError, match="surface_depth must have shape"):
        occluder_mask(scene, source, vm, K, 0.0, W_DUP, H_DUP, surface_depth=depth[1:])


def _slid(scene, index, origin, factors):
    """Brute force: every Gaussian of ``index`` moved by each factor (one scene per factor)."""
    out = []
    for f in factors:
        means, scales = scene.canonical.means.clone(), scene.canonical.scales.clone()
        means[index] = origin + f * (means[index] - origin)
        scales[index] = scales[index] * f
        g = scene.canonical
        out.append(DynamicGaussians(Gaussians(means, g.quats, scales, g.opacities, g.sh), scene.times, scene.d_means,
                                    scene.d_quats, scene.d_scales))
    return out


def test_slide_behind_moves_occluders_along_their_source_rays_to_the_first_free_factor():
    """Gaussians of a side camera in front of the photo's surface move along their own rays (same direction and
    angular size from that camera) to the first factor at which occluder_mask, against the exact surface depth,
    no longer drops them — checked against occluder_mask on every factor's scene; the input is not modified; the
    moved means carry the gradient λ; with factors too small nothing moves."""
    vm1 = torch.eye(4, dtype=torch.float64)
    vm1[0, 3] = -0.4  # camera 1 at x = 0.4 m
    origin = torch.tensor([0.4, 0.0, 0.0], dtype=torch.float64)
    wall = _plane(3.0)
    pts = torch.cat([_plane(z, range(6, 10), range(4, 8), viewmat=vm1) for z in (1.2, 1.8, 2.6)])
    scene = _cat(_gaussians(wall), _gaussians(pts, scale=0.02))
    source = torch.cat([_source(len(wall)), torch.ones(len(pts), dtype=torch.long)])
    idx = torch.arange(len(wall), len(wall) + len(pts))
    depth = torch.full((H_DUP, W_DUP), 3.0, dtype=torch.float64)
    vm0, K = torch.eye(4, dtype=torch.float64), _K()[0]
    assert occluder_mask(scene, source, vm0, K, 0.0, W_DUP, H_DUP, surface_depth=depth)[idx].all()
    before = scene.canonical.means.clone()
    out, moved = slide_behind(scene, idx, origin.expand(len(idx), 3), vm0, K, 0.0, W_DUP, H_DUP, depth)
    assert moved.all() and torch.equal(scene.canonical.means, before)
    assert not occluder_mask(out, source, vm0, K, 0.0, W_DUP, H_DUP, surface_depth=depth).any()
    covers = torch.stack([occluder_mask(s, source, vm0, K, 0.0, W_DUP, H_DUP, surface_depth=depth)[idx]
                          for s in _slid(scene, idx, origin, SLIDE_FACTORS)])  # (F, P)
    first = torch.tensor(SLIDE_FACTORS, dtype=torch.float64)[(~covers).double().argmax(0)]
    ray0, ray1 = before[idx] - origin, out.canonical.means[idx] - origin
    torch.testing.assert_close(ray1.norm(dim=1) / ray0.norm(dim=1), first)
    torch.testing.assert_close(torch.linalg.cross(ray0, ray1).norm(dim=1), torch.zeros(len(idx), dtype=torch.float64),
                               atol=1e-12, rtol=0)
    torch.testing.assert_close(out.canonical.scales[idx], 0.02 * first[:, None].expand(-1, 3))
    assert len(set(first.tolist())) == 3  # the three depths need three different factors
    torch.testing.assert_close(out.canonical.means[:len(wall)], wall)
    means = scene.canonical.means.clone().requires_grad_(True)
    g = scene.canonical
    s_grad = DynamicGaussians(Gaussians(means, g.quats, g.scales, g.opacities, g.sh))
    out2, _ = slide_behind(s_grad, idx, origin.expand(len(idx), 3), vm0, K, 0.0, W_DUP, H_DUP, depth)
    out2.canonical.means[idx].sum().backward()
    torch.testing.assert_close(means.grad[idx], first[:, None].expand(-1, 3))
    stuck, none = slide_behind(scene, idx, origin.expand(len(idx), 3), vm0, K, 0.0, W_DUP, H_DUP, depth,
                               factors=(1.01,))
    assert not none.any() and torch.equal(stuck.canonical.means, before)


def test_slide_behind_tests_positions_at_the_photo_time():
    """A Gaussian whose deformation pushes it 1 m back at t = 1 needs a smaller factor when the photograph is at
    t = 1 (λ·1.5 + 1 ≥ 3.15 → 1.475) than at t = 0 (λ·1.5 ≥ 3.15 → 2.32); its deformation is kept."""
    wall = _plane(3.0)
    pt = _plane(1.5, range(8, 9), range(8, 9))
    d = torch.zeros(2, len(wall) + 1, 3, dtype=torch.float64)
    d[1, -1, 2] = 1.0
    scene = _gaussians(torch.cat([wall, pt]), scale=0.01, d_means=d, key_times=_times(0.0, 1.0))
    depth = torch.full((H_DUP, W_DUP), 3.0, dtype=torch.float64)
    idx, origin = torch.tensor([len(wall)]), torch.zeros(1, 3, dtype=torch.float64)
    for t, lam in ((0.0, 1.05 * 1.12**7), (1.0, 1.05 * 1.12**3)):
        out, moved = slide_behind(scene, idx, origin, torch.eye(4, dtype=torch.float64), _K()[0], t, W_DUP, H_DUP,
                                  depth)
        assert moved.all()
        torch.testing.assert_close(out.canonical.means[-1], lam * pt[0])
        assert torch.equal(out.d_means, scene.d_means)


def test_slide_behind_rejects_bad_arguments_and_moves_nothing_unasked():
    scene = _gaussians(_plane(3.0))
    depth = torch.full((H_DUP, W_DUP), 3.0, dtype=torch.float64)
    args = (torch.eye(4, dtype=torch.float64), _K()[0], 0.0, W_DUP, H_DUP)
    out, moved = slide_behind(scene, torch.zeros(0, dtype=torch.long), torch.zeros(0, 3), *args, depth)
    assert moved.shape == (0,) and torch.equal(out.canonical.means, scene.canonical.means)
    with pytest.raises(ValueError, match="origins"):
        slide_behind(scene, torch.tensor([0, 1]), torch.zeros(3, 3), *args, depth)
    with pytest.raises(ValueError, match="factors"):
        slide_behind(scene, torch.tensor([0]), torch.zeros(1, 3), *args, depth, factors=(0.9, 1.2))
    with pytest.raises(ValueError, match="surface_depth"):
        slide_behind(scene, torch.tensor([0]), torch.zeros(1, 3), *args, depth[1:])


def test_settle_generated_drops_duplicates_and_slides_occluders():
    """settle_generated: a later frame's copy of the photo's surface is dropped as duplicate, its Gaussians in front
    of the surface slide behind it (none dropped), and the counts add up; source 0 is untouched."""
    wall = _plane(3.0)
    path = CameraPath(torch.eye(4, dtype=torch.float64).repeat(2, 1, 1), _K(2), W_DUP, H_DUP,
                      torch.tensor([0.0, 1.0], dtype=torch.float64))
    copy, front = _plane(3.0, range(0, 4)), _plane(1.5, range(8, 12), range(4, 8))
    scene = _cat(_gaussians(wall), _gaussians(copy), _gaussians(front, scale=0.01))
    source = _source(len(wall), len(copy) + len(front))
    depth = torch.full((H_DUP, W_DUP), 3.0, dtype=torch.float64)
    out, drop, counts = settle_generated(scene, source, path, torch.tensor([0, 1]), depth)
    assert counts == {"duplicates": len(copy), "slid": len(front), "occluders": 0}
    assert drop.tolist() == [False] * len(wall) + [True] * len(copy) + [False] * len(front)
    assert not occluder_mask(out.select(~drop), source[~drop], torch.eye(4, dtype=torch.float64), _K()[0], 0.0, W_DUP,
                             H_DUP, surface_depth=depth).any()
    n = len(wall) + len(copy)
    torch.testing.assert_close(out.canonical.means[:n], scene.canonical.means[:n])
    # factors=(): the rule before the slide, every occluder dropped, nothing moved
    same, drop0, counts0 = settle_generated(scene, source, path, torch.tensor([0, 1]), depth, factors=())
    assert counts0 == {"duplicates": len(copy), "slid": 0, "occluders": len(front)}
    assert drop0.tolist() == [False] * len(wall) + [True] * (len(copy) + len(front))
    assert torch.equal(same.canonical.means, scene.canonical.means)


def test_settle_generated_on_each_device_matches_the_cpu(device):
    """The same drops, slides and counts on every device, everything made on the scene's device; ``source`` and
    ``sources`` may stay on the CPU (as duplicate_mask and occluder_mask take them)."""
    wall = _plane(3.0)
    vm1 = torch.eye(4, dtype=torch.float64)
    vm1[0, 3] = -0.4  # camera 1 at x = 0.4 m
    path = CameraPath(torch.stack([torch.eye(4, dtype=torch.float64), vm1]), _K(2), W_DUP, H_DUP,
                      torch.tensor([0.0, 1.0], dtype=torch.float64))
    front = torch.cat([_plane(z, range(6, 10), range(4, 8), viewmat=vm1) for z in (1.2, 2.6)])
    scene = _cat(_gaussians(wall), _gaussians(_plane(3.0, range(0, 4))), _gaussians(front, scale=0.02))
    source = _source(len(wall), 16 * 4 + len(front))
    depth = torch.full((H_DUP, W_DUP), 3.0, dtype=torch.float64)
    ref = settle_generated(scene, source, path, torch.tensor([0, 1]), depth)
    dev = torch.device(device)
    out, drop, counts = settle_generated(scene.to(dev), source.to(dev), path.to(dev), torch.tensor([0, 1], device=dev),
                                         depth.to(dev))
    assert out.canonical.means.device.type == drop.device.type == dev.type
    assert counts == ref[2] and counts["slid"] >= len(front) and torch.equal(drop.cpu(), ref[1])
    torch.testing.assert_close(out.canonical.means.cpu(), ref[0].canonical.means)
    torch.testing.assert_close(out.canonical.scales.cpu(), ref[0].canonical.scales)
    mixed = settle_generated(scene.to(dev), source, path.to(dev), torch.tensor([0, 1]), depth.to(dev))
    assert mixed[2] == ref[2] and torch.equal(mixed[1].cpu(), ref[1])


def test_footprint_max_bounds_the_brute_force_maximum():
    """At least the exact maximum over the square within the image, at most the maximum over a square 20 % wider;
    0 where the square misses the image."""
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(37, 53, generator=g, dtype=torch.float64) + 1
    u = torch.rand(400, generator=g, dtype=torch.float64) * 90 - 20
    v = torch.rand(400, generator=g, dtype=torch.float64) * 70 - 20
    r = torch.rand(400, generator=g, dtype=torch.float64) * 15
    got = _footprint_max(depth, u, v, r)

    def box_max(i, rr, clamp=False):
        cu = min(max(float(u[i]), 0.5), 52.5) if clamp else float(u[i])
        cv = min(max(float(v[i]), 0.5), 36.5) if clamp else float(v[i])
        cols = [j for j in range(53) if abs(j + 0.5 - cu) <= rr + 0.5]
        rows = [j for j in range(37) if abs(j + 0.5 - cv) <= rr + 0.5]
        return float(depth[rows][:, cols].max()) if rows and cols else 0.0

    hits = 0
    for i in range(400):
        exact = box_max(i, float(r[i]))
        if exact == 0.0:
            assert got[i] == 0.0
            continue
        hits += 1
        assert exact <= got[i] <= box_max(i, math.ceil(1.2 * max(float(r[i]), 1.0)) + 1.0, clamp=True)
    assert hits > 200


def test_occluder_mask_tests_positions_at_the_photo_time():
    """A later-frame Gaussian that moves in front of the surface only after t = 0 does not contradict the photo."""
    wall = _plane(3.0)
    mover = _plane(3.5, range(6, 10), range(6, 10))  # behind the wall at t = 0
    key = _times(0.0, 1.0)
    d = torch.zeros(2, len(mover), 3, dtype=torch.float64)
    d[1, :, 2] = -1.0  # 1 m towards the camera at t = 1
    scene = DynamicGaussians(
        _cat(_gaussians(wall), _gaussians(mover)).canonical, key,
        torch.cat([torch.zeros(2, len(wall), 3, dtype=torch.float64), d], 1),
        torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(2, len(wall) + len(mover), 4).clone(),
        torch.zeros(2, len(wall) + len(mover), 3, dtype=torch.float64))
    source = _source(len(wall), len(mover))
    vm, K = torch.eye(4, dtype=torch.float64), _K()[0]
    assert not occluder_mask(scene, source, vm, K, 0.0, W_DUP, H_DUP).any()
    assert occluder_mask(scene, source, vm, K, 1.0, W_DUP, H_DUP)[len(wall):].all()
    with pytest.raises(ValueError, match="min_alpha"):
        occluder_mask(scene, source, vm, K, 0.0, W_DUP, H_DUP, min_alpha=0.0)
    with pytest.raises(ValueError, match="depth_tolerance"):
        occluder_mask(scene, source, vm, K, 0.0, W_DUP, H_DUP, depth_tolerance=-1.0)
    with pytest.raises(ValueError, match="source"):
        occluder_mask(scene, source.double(), vm, K, 0.0, W_DUP, H_DUP)
