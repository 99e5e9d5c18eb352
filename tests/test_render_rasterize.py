"""Tests of the fast tile rasterizer against the dense reference, closed forms and finite differences."""
import math

import pytest
import torch

from diff4splat.render import rasterize, rasterize_dense
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat

pytestmark = pytest.mark.usefixtures("each_compositor")  # every test on both CPU compositors

D = torch.float64


def _scene(n=80, c=2, w=32, h=24, seed=0, sh=None, d=3):
    """Random Gaussians in front of C cameras looking roughly down +z."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    means = torch.stack([(r(n) - 0.5) * 2.0, (r(n) - 0.5) * 1.6, 2 + 3 * r(n)], -1)
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = 0.02 + 0.15 * r(n, 3)
    opac = 0.05 + 0.9 * r(n)
    colors = r(n, d) if sh is None else 0.5 * torch.randn(n, (sh + 1) ** 2, 3, generator=g, dtype=D)
    vms = []
    for i in range(c):
        vm = torch.eye(4, dtype=D)
        axis = torch.tensor([0.2, 1.0, 0.1], dtype=D)
        vm[:3, :3] = quat_to_rotmat(axis_angle_to_quat(axis, torch.tensor(0.15 * i, dtype=D)))
        vm[:3, 3] = torch.tensor([0.1 * i, -0.05 * i, 0.2 * i], dtype=D)
        vms.append(vm)
    K = torch.tensor([[w * 0.9, 0, w / 2], [0, w * 0.9, h / 2], [0, 0, 1]], dtype=D).expand(c, 3, 3).clone()
    return [means, quats, scales, opac, colors, torch.stack(vms), K]


def _both(args, w=32, h=24, **kw):
    a = rasterize(*args, w, h, **kw)
    b = rasterize_dense(*args, w, h, **kw)
    return a, b


@pytest.mark.parametrize("render_mode", ["RGB", "D", "ED", "RGB+D", "RGB+ED"])
@pytest.mark.slow
def test_fast_matches_dense_every_render_mode(render_mode):
    args = _scene(seed=1)
    bg = torch.rand(2, 3, dtype=D, generator=torch.Generator().manual_seed(5))
    (c1, a1, m1), (c2, a2, _) = _both(args, render_mode=render_mode, backgrounds=bg, tile_size=8)
    assert c1.shape == (2, 24, 32, {"RGB": 3, "D": 1, "ED": 1}.get(render_mode, 4))
    assert a1.shape == (2, 24, 32, 1)
    assert float(a2.max()) > 0.5 and float(a2.min()) < 0.05  # the scene is neither empty nor saturated
    torch.testing.assert_close(c1, c2, atol=1e-5, rtol=0)
    torch.testing.assert_close(a1, a2, atol=1e-5, rtol=0)
    if render_mode == "RGB+ED":
        d_acc = rasterize(*args, 32, 24, render_mode="D")[0]
        torch.testing.assert_close(c1[..., -1:], torch.where(a1 > 0, d_acc / a1.clamp(min=1e-10), 0.0))


@pytest.mark.parametrize("sh_degree,mode,tile",
                         [(0, "classic", 16), (1, "antialiased", 4), (2, "classic", 1), (3, "antialiased", 5)])
@pytest.mark.slow
def test_fast_matches_dense_sh_antialiased_and_any_tile_size(sh_degree, mode, tile):
    args = _scene(n=60, c=3, w=29, h=21, seed=2 + sh_degree, sh=sh_degree)
    bg = torch.rand(3, 3, dtype=D)
    (c1, a1, m1), (c2, a2, m2) = _both(args, w=29, h=21, sh_degree=sh_degree, rasterize_mode=mode, backgrounds=bg,
                                       tile_size=tile)
    torch.testing.assert_close(c1, c2, atol=1e-5, rtol=0)
    torch.testing.assert_close(a1, a2, atol=1e-5, rtol=0)
    assert torch.equal(m1["radii"], m2["radii"]) and m1["tile_width"] == math.ceil(29 / tile)


def test_tile_lists_are_depth_sorted_and_cover_the_support():
    args = _scene(n=120, c=1, seed=7)
    _, _, meta = rasterize(*args, 32, 24, tile_size=8)
    info = meta["per_camera"][0]
    depths = meta["depths"][0, info["gaussian_ids"]]
    for t in range(info["tiles_x"] * info["tiles_y"]):
        s, n = int(info["isect_offsets"][t]), int(info["tile_counts"][t])
        d = depths[info["flatten_ids"][s : s + n]]
        assert bool((d[1:] >= d[:-1]).all())
    assert int(info["tiles_per_gauss"].sum()) == len(info["flatten_ids"])


@pytest.mark.parametrize("sh_degree,mode", [(None, "classic"), (3, "antialiased")])
@pytest.mark.slow
def test_fast_gradients_match_dense_reference(sh_degree, mode):
    args = _scene(n=50, c=2, seed=11, sh=sh_degree)
    bg = torch.rand(2, 3, dtype=D)
    weights = None
    grads = []
    for fn in (rasterize, rasterize_dense):
        leaves = [t.clone().requires_grad_() for t in args[:5]] + [bg.clone().requires_grad_()]
        col, alpha, meta = fn(*leaves[:5], args[5], args[6], 32, 24, sh_degree=sh_degree, rasterize_mode=mode,
                              backgrounds=leaves[5], render_mode="RGB+ED")
        if weights is None:
            weights = torch.rand(col.shape, dtype=D, generator=torch.Generator().manual_seed(0))
        loss = (col * weights).sum() + (alpha ** 2).sum()
        grads.append(torch.autograd.grad(loss, leaves))
    for name, g1, g2 in zip(["means", "quats", "scales", "opacities", "colors", "backgrounds"], *grads, strict=False):
        assert float(g2.abs().max()) > 0, name
        torch.testing.assert_close(g1, g2, atol=1e-7, rtol=1e-6, msg=name)


def _smooth_scene():
    """Three broad, well-separated-in-depth Gaussians filling an 8×8 image: every pixel is far from
    the 1/255 skip, the 0.99 clamp and the 1e-4 stop, so the image is smooth in every parameter."""
    means = torch.tensor([[0.05, -0.02, 2.0], [-0.1, 0.08, 2.5], [0.12, 0.1, 3.0]], dtype=D)
    quats = torch.tensor([[1.0, 0.1, -0.2, 0.05], [0.8, -0.3, 0.1, 0.2], [0.9, 0.0, 0.3, -0.1]], dtype=D)
    scales = torch.tensor([[0.5, 0.35, 0.2], [0.45, 0.6, 0.3], [0.7, 0.5, 0.4]], dtype=D)
    opac = torch.tensor([0.5, 0.6, 0.7], dtype=D)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.9]], dtype=D)
    K = torch.tensor([[[8.0, 0, 4.0], [0, 8.0, 4.0], [0, 0, 1]]], dtype=D)
    return means, quats, scales, opac, colors, torch.eye(4, dtype=D)[None], K


@pytest.mark.parametrize("fn", [rasterize, rasterize_dense])
@pytest.mark.slow
def test_gradcheck_tiny_scene(fn):
    means, quats, scales, opac, colors, vm, K = _smooth_scene()
    bg = torch.tensor([[0.3, 0.2, 0.1]], dtype=D)

    def f(m, q, s, o, c):
        col, alpha, _ = fn(m, q, s, o, c, vm, K, 8, 8, backgrounds=bg, render_mode="RGB+ED", tile_size=4)
        return col, alpha

    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales, opac, colors))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("fn", [rasterize, rasterize_dense])
def test_early_termination_stack_of_opaque_gaussians(fn):
    """Six layers with alpha 0.95 at the centre pixel: T = 1, .05, .0025, 1.25e-4, then 6.25e-6 < 1e-4,
    so layer 4 stops the pixel and neither it nor anything behind contributes."""
    n = 6
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.5 * i] for i in range(n)], dtype=D)
    means = means[torch.tensor([3, 0, 5, 1, 4, 2])]  # input order must not matter
    depth_rank = torch.argsort(torch.argsort(means[:, 2]))
    scales = torch.full((n, 3), 0.3, dtype=D) * means[:, 2:3]
    colors = torch.eye(n, dtype=D)
    K = torch.tensor([[[10.0, 0, 2.5], [0, 10.0, 2.5], [0, 0, 1]]], dtype=D)  # centre of pixel (2, 2)
    cols = colors.clone().requires_grad_()
    bg = torch.full((1, n), 0.5, dtype=D)
    out, alpha, _ = fn(means, torch.tensor([[1.0, 0, 0, 0]] * n, dtype=D), scales, torch.full((n,), 0.95, dtype=D),
                       cols, torch.eye(4, dtype=D)[None], K, 5, 5, render_mode="RGB", backgrounds=bg)
    w = torch.tensor([0.95 * 0.05**k if k < 3 else 0.0 for k in range(n)], dtype=D)[depth_rank]
    T = 0.05**3
    torch.testing.assert_close(out[0, 2, 2], w + T * 0.5, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alpha[0, 2, 2, 0], torch.tensor(1 - T, dtype=D), rtol=1e-12, atol=1e-12)
    (g,) = torch.autograd.grad(out[0, 2, 2].sum(), cols)
    torch.testing.assert_close(g, w[:, None].expand(n, n))  # layers from the 4th on get no gradient


def test_single_gaussian_closed_form_and_pixel_centres():
    """alpha at pixel (i, j) = o·exp(−½ dᵀ Σ⁻¹ d) with d = (j + 0.5, i + 0.5) − μ2d, Σ = (f s / z)² I + eps I."""
    f, z, s, o, eps = 10.0, 2.0, 0.3, 0.8, 0.3
    K = torch.tensor([[[f, 0, 3.2], [0, f, 2.7], [0, 0, 1]]], dtype=D)
    out, alpha, _ = rasterize(torch.tensor([[0.0, 0.0, z]], dtype=D), torch.tensor([[1.0, 0, 0, 0]], dtype=D),
                              torch.full((1, 3), s, dtype=D), torch.tensor([o], dtype=D), torch.tensor([[1.0]],
                                                                                                       dtype=D),
                              torch.eye(4, dtype=D)[None], K, 7, 6, render_mode="RGB", eps2d=eps)
    var = (f * s / z) ** 2 + eps
    i, j = torch.meshgrid(torch.arange(6, dtype=D), torch.arange(7, dtype=D), indexing="ij")
    a = o * torch.exp(-0.5 * ((j + 0.5 - 3.2) ** 2 + (i + 0.5 - 2.7) ** 2) / var)
    a = torch.where(a >= 1 / 255, a, 0.0)
    torch.testing.assert_close(out[0, ..., 0], a, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alpha[0, ..., 0], a, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("fn", [rasterize, rasterize_dense])
def test_culled_gaussians_contribute_nothing_and_get_zero_gradient(fn):
    args = _scene(n=30, c=1, seed=4)
    extra = torch.tensor([[0.0, 0.0, -1.5], [0.1, 0.0, 0.004], [0.0, 0.1, -0.2]], dtype=D)  # behind / before near
    means = torch.cat([args[0], extra]).requires_grad_()
    quats = torch.cat([args[1], torch.randn(3, 4, dtype=D)]).requires_grad_()
    scales = torch.cat([args[2], torch.full((3, 3), 0.5, dtype=D)]).requires_grad_()
    opac = torch.cat([args[3], torch.full((3,), 0.9, dtype=D)]).requires_grad_()
    cols = torch.cat([args[4], torch.ones(3, 3, dtype=D)]).requires_grad_()
    col, alpha, meta = fn(means, quats, scales, opac, cols, args[5], args[6], 32, 24)
    ref, ref_a, _ = fn(*args, 32, 24)
    torch.testing.assert_close(col, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(alpha, ref_a, rtol=0, atol=1e-12)
    assert meta["radii"][0, -3:].tolist() == [0, 0, 0]
    grads = torch.autograd.grad(col.sum() + alpha.sum(), [means, quats, scales, opac, cols])
    for g in grads:
        assert bool(torch.isfinite(g).all()) and bool((g[-3:] == 0).all())
    assert float(grads[0][:-3].abs().max()) > 0


def test_empty_view_gives_background_and_zero_alpha():
    args = _scene(n=10, c=1)
    args[0] = args[0] * torch.tensor([1.0, 1.0, -1.0], dtype=D)  # everything behind the camera
    bg = torch.tensor([[0.2, 0.4, 0.6]], dtype=D)
    col, alpha, _ = rasterize(*args, 32, 24, backgrounds=bg, render_mode="RGB+ED")
    assert bool((alpha == 0).all()) and bool((col[..., 3] == 0).all())
    torch.testing.assert_close(col[..., :3], bg.view(1, 1, 1, 3).expand(1, 24, 32, 3))


def test_float32_close_to_float64():
    args = _scene(n=80, c=1, seed=9)
    c64, a64, _ = rasterize(*args, 32, 24)
    c32, a32, _ = rasterize(*[t.float() for t in args], 32, 24)
    assert c32.dtype == torch.float32
    torch.testing.assert_close(c32.double(), c64, atol=1e-4, rtol=1e-4)


BAD_SHAPES = {
    "means": lambda a: a[0][:, :2], "quats": lambda a: a[1][:, :3], "scales": lambda a: a[2][:-1],
    "opacities": lambda a: a[3][:, None], "colors": lambda a: a[4][:-1], "viewmats": lambda a: a[5][:, :3],
    "Ks": lambda a: a[6][:1],
}
NAMES = ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks"]


@pytest.mark.parametrize("name", NAMES)
def test_wrong_shape_raises_naming_argument(name):
    args = _scene(n=5)
    args[NAMES.index(name)] = BAD_SHAPES[name](args)
    with pytest.raises(ValueError, match=name):
        rasterize(*args, 32, 24)


@pytest.mark.parametrize("name", NAMES)
def test_non_finite_raises_naming_tensor(name):
    args = _scene(n=5)
    t = args[NAMES.index(name)].clone()
    t.view(-1)[1] = float("nan") if name != "Ks" else float("inf")
    args[NAMES.index(name)] = t
    with pytest.raises(ValueError, match=f"{name} contains"):
        rasterize(*args, 32, 24)


@pytest.mark.parametrize("kw,match", [
    ({"camera_model": "orthographic"}, "camera_model"), ({"render_mode": "RGBD"}, "render_mode"),
    ({"rasterize_mode": "aa"}, "rasterize_mode"), ({"tile_size": 0}, "tile_size"), ({"sh_degree": 1}, "colors"),
    ({"backgrounds": torch.zeros(2, 4, dtype=D)}, "backgrounds"), ({"sh_degree": 5}, "sh_degree"),
])
def test_bad_options_raise(kw, match):
    with pytest.raises(ValueError, match=match):
        rasterize(*_scene(n=5), 32, 24, **kw)


def test_zero_norm_quaternion_raises():
    args = _scene(n=5)
    args[1][2] = 0.0
    with pytest.raises(ValueError, match="quats"):
        rasterize(*args, 32, 24)
