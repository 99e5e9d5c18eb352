"""Numerical stability of the renderer at the edges of its domain.

Extreme scales (1e-6 … 1e3 m) and anisotropy (1e6), Gaussians behind the camera / straddling the
near plane / far outside the frustum / on the image border, unnormalised and zero-norm quaternions,
opacity 0 and 1, 10⁵ Gaussians on one pixel (transmittance underflow), float32 / float64 /
bfloat16 autocast, non-finite inputs. Every case checks: finite outputs and gradients, fast tile
path == dense reference (float64, atol 1e-10), culled Gaussians add nothing and get exactly zero
gradient, and low precision agrees with float64 within the tolerances below.

Tolerances established here (max abs error against the float64 render of the same scene):
float32 — colours/alpha 1e-5, expected depth 1e-5·z_max; gradients 1e-4·max|grad| per tensor
(measured: ≤ 1e-6 and ≤ 4e-6·max|grad| over these cases).
bfloat16 autocast — the renderer turns autocast off and computes in float32, so outputs and
gradients equal the float32 ones exactly (hence the same tolerances against float64), also when
the backward pass runs inside the autocast region. bfloat16 input tensors are computed in float32
(outputs float32, same tolerances against float64 of the rounded inputs); their gradients are
bfloat16: 1e-2·max|grad|.
"""
import math

import pytest
import torch

from diff4splat.render import rasterize, rasterize_dense

pytestmark = pytest.mark.usefixtures("each_compositor")  # every test on both CPU compositors

D = torch.float64
W, H = 32, 24
F = 28.8
K = torch.tensor([[[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]], dtype=D)
VM = torch.eye(4, dtype=D)[None]
ATOL_F32 = 1e-5  # colours and alpha, float32 vs float64
GRAD_RTOL_F32 = 1e-4  # gradients, float32 vs float64, relative to the largest |grad| of the tensor
PARAMS = ["means", "quats", "scales", "opacities", "colors"]


def _scene(n, scale, seed=0, z=3.0, aniso=1.0):
    """n Gaussians inside the view at depth z … z+1 with standard deviations ``scale`` (× ``aniso`` on y)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    means = torch.stack([(r(n) - 0.5) * 1.5, (r(n) - 0.5), z + r(n)], -1)
    scales = torch.full((n, 3), float(scale), dtype=D) * (0.5 + r(n, 3))
    scales[:, 1] *= aniso
    return [means, torch.randn(n, 4, generator=g, dtype=D), scales, 0.2 + 0.7 * r(n), r(n, 3)]


def _render(args, dtype=D, fn=rasterize, autocast=False, vm=VM, k=K, **kw):
    """Render RGB+ED and differentiate a fixed loss; returns (colours, alpha, grads as float64)."""
    leaves = [t.detach().to(dtype).requires_grad_() for t in args]
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        col, alpha, meta = fn(*leaves, vm.to(dtype), k.to(dtype), W, H, render_mode="RGB+ED", **kw)
        wts = torch.linspace(0.5, 1.5, col.numel(), dtype=col.dtype).reshape(col.shape)
        grads = torch.autograd.grad((col * wts).sum() + alpha.sum(), leaves)
    return col.detach(), alpha.detach(), [g.double() for g in grads], meta


def _finite(*ts):
    return all(bool(torch.isfinite(t).all()) for t in ts)


def _assert_close_to_f64(lo, hi, grad_rtol=GRAD_RTOL_F32):
    """lo, hi: results of :func:`_render` in low precision and in float64."""
    (c, a, g, _), (c64, a64, g64, _) = lo, hi
    assert _finite(c, a, *g)
    torch.testing.assert_close(c[..., :3].double(), c64[..., :3], atol=ATOL_F32, rtol=0)
    torch.testing.assert_close(a.double(), a64, atol=ATOL_F32, rtol=0)
    torch.testing.assert_close(c[..., 3].double(), c64[..., 3], atol=ATOL_F32 * float(c64[..., 3].max()), rtol=0)
    for name, x, y in zip(PARAMS, g, g64, strict=False):
        torch.testing.assert_close(x, y, atol=grad_rtol * float(y.abs().max()) + 1e-12, rtol=0, msg=name)


@pytest.mark.parametrize("scale,aniso", [(1e-6, 1.0), (1e-3, 1.0), (0.3, 1.0), (1e3, 1.0), (0.1, 1e-6), (1e2, 1e-6)])
def test_extreme_scales_and_anisotropy(scale, aniso):
    """Sub-pixel (eps2d-dominated) to camera-enclosing Gaussians, and needles with 1e6 axis ratio."""
    args = _scene(6, scale, seed=int(-math.log10(scale) * 7) % 97, aniso=aniso)
    hi = _render(args)
    dense = _render(args, fn=rasterize_dense)
    assert _finite(hi[0], hi[1], *hi[2]) and float(hi[1].max()) > 0.1
    torch.testing.assert_close(hi[0], dense[0], atol=1e-10, rtol=0)
    torch.testing.assert_close(hi[1], dense[1], atol=1e-10, rtol=0)
    for name, x, y in zip(PARAMS, hi[2], dense[2], strict=False):
        torch.testing.assert_close(x, y, atol=1e-9 * float(y.abs().max()) + 1e-14, rtol=1e-7, msg=name)
    _assert_close_to_f64(_render(args, torch.float32), hi)


@pytest.mark.parametrize("dtype", [D, torch.float32])
def test_absurd_scales_give_finite_images_and_non_negative_radii(dtype):
    """1e15–1e25 m: float64 keeps them (radius clamped to 2³⁰, never wrapped to a negative int32);
    float32 overflows Σ2d and culls them. Either way the image is finite."""
    args = [t.to(dtype) for t in _scene(3, 1e15)]
    args[2] = args[2] * torch.tensor([[1.0], [1e5], [1e10]], dtype=dtype)
    col, alpha, meta = rasterize(*args, VM.to(dtype), K.to(dtype), W, H)
    assert _finite(col, alpha) and bool((meta["radii"] >= 0).all())
    if dtype == D:
        assert meta["radii"][0].tolist() == [1 << 30] * 3 and float(alpha.min()) > 0


def _culled_cases():
    q = [1.0, 0.2, -0.1, 0.3]
    return {  # mean, quat, scale, all culled by projection
        "behind": ([0.0, 0.0, -2.0], q, 0.5),
        "behind_far": ([0.3, -0.2, -1e6], q, 1e3),
        "before_near": ([0.0, 0.0, 0.005], q, 0.5),
        "far_outside": ([1e4, 0.0, 3.0], q, 1.0),
        "far_outside_y": ([0.0, -1e3, 1.0], q, 10.0),
        "beyond_far_plane": ([0.0, 0.0, 2e10], q, 1e3),
    }


@pytest.mark.parametrize("dtype", [D, torch.float32])
def test_culled_gaussians_add_nothing_and_get_exactly_zero_gradient(dtype):
    base = _scene(20, 0.1, seed=1)
    cases = _culled_cases()
    extra = [torch.tensor([c[0] for c in cases.values()], dtype=D),
             torch.tensor([c[1] for c in cases.values()], dtype=D),
             torch.tensor([[c[2]] * 3 for c in cases.values()], dtype=D), torch.full((len(cases),), 0.9, dtype=D),
             torch.ones(len(cases), 3, dtype=D)]
    args = [torch.cat([b, e]) for b, e in zip(base, extra, strict=False)]
    for fn in (rasterize, rasterize_dense):
        col, alpha, grads, meta = _render(args, dtype, fn)
        ref_col, ref_alpha, ref_grads, _ = _render(base, dtype, fn)
        assert meta["radii"][0, -len(cases):].tolist() == [0] * len(cases)
        assert torch.equal(col, ref_col) and torch.equal(alpha, ref_alpha)
        for name, g, rg in zip(PARAMS, grads, ref_grads, strict=False):
            assert _finite(g) and bool((g[-len(cases):] == 0).all()), name
            assert torch.equal(g[:-len(cases)], rg), name


@pytest.mark.parametrize("case", ["straddles_near_plane", "at_near_plane", "huge_outside_reaching_in", "inside_camera"])
def test_gaussians_near_the_camera_or_outside_but_reaching_in(case):
    """Not culled, yet extreme: the fov-clamped Jacobian keeps Σ2d finite; fast == dense; float32 holds."""
    mean, scale = {
        "straddles_near_plane": ([0.05, -0.02, 0.05], 0.5),  # centre in front, body behind the camera
        "at_near_plane": ([0.0, 0.0, 0.01], 0.01),  # z exactly at near_plane is kept
        "huge_outside_reaching_in": ([40.0, 0.0, 3.0], 30.0),  # centre 13 tan-fov units outside
        "inside_camera": ([0.0, 0.0, 0.5], 1e3),  # the camera sits inside a huge Gaussian
    }[case]
    args = _scene(8, 0.1, seed=2)
    args = [torch.cat([a, b]) for a,
            b in zip(args, [torch.tensor([mean], dtype=D), torch.tensor([[0.9, 0.1, 0.3, -0.2]], dtype=D),
                                                    torch.full((1, 3), scale, dtype=D), torch.tensor([0.5], dtype=D),
                                                    torch.tensor([[0.1, 0.9, 0.2]], dtype=D)], strict=False)]
    hi = _render(args)
    assert int(hi[3]["radii"][0, -1]) > 0 and _finite(hi[0], hi[1], *hi[2])
    assert float(hi[2][3][-1].abs()) > 0  # it really contributes
    dense = _render(args, fn=rasterize_dense)
    torch.testing.assert_close(hi[0], dense[0], atol=1e-10, rtol=0)
    for name, x, y in zip(PARAMS, hi[2], dense[2], strict=False):
        torch.testing.assert_close(x, y, atol=1e-9 * float(y.abs().max()) + 1e-14, rtol=1e-7, msg=name)
    _assert_close_to_f64(_render(args, torch.float32), hi)


def test_gaussians_exactly_on_image_borders_and_corners():
    """Means projecting onto x ∈ {0, W}, y ∈ {0, H} (pixel edges, outside every pixel centre)."""
    z = 2.0
    uv = torch.tensor([[0, 5], [W, 7], [9, 0], [11, H], [0, 0], [W, H], [0, H], [W, 0]], dtype=D)
    means = torch.cat([(uv - K[0, :2, 2]) / F * z, torch.full((len(uv), 1), z, dtype=D)], -1)
    n = len(uv)
    g = torch.Generator().manual_seed(3)
    args = [means, torch.randn(n, 4, generator=g, dtype=D), torch.tensor([[0.05, 0.03, 0.08]], dtype=D).expand(n, 3),
            torch.full((n,), 0.8, dtype=D), torch.rand(n, 3, generator=g, dtype=D)]
    hi = _render(args)
    assert bool((hi[3]["radii"][0] > 0).all()) and _finite(*hi[2])
    assert float(hi[1][0, 0, 0, 0]) > 0.1 and float(hi[1][0, -1, -1, 0]) > 0.1  # corners are covered
    dense = _render(args, fn=rasterize_dense)
    torch.testing.assert_close(hi[0], dense[0], atol=1e-10, rtol=0)
    for name, x, y in zip(PARAMS, hi[2], dense[2], strict=False):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=1e-7, msg=name)
    torch.testing.assert_close(hi[3]["means2d"][0], uv, atol=1e-12, rtol=0)
    _assert_close_to_f64(_render(args, torch.float32), hi)


@pytest.mark.parametrize("dtype", [D, torch.float32])
def test_unnormalised_quaternions_render_as_normalised(dtype):
    args = _scene(10, 0.15, seed=4)
    unit = args[1] / args[1].norm(dim=-1, keepdim=True)
    norms = torch.logspace(-5, 5, 10, dtype=D)[:, None]
    ref = _render([args[0], unit] + args[2:], dtype)
    out = _render([args[0], unit * norms] + args[2:], dtype)
    tol = 1e-12 if dtype == D else 2e-6
    torch.testing.assert_close(out[0].double(), ref[0].double(), atol=tol, rtol=0)
    # scale invariance: the gradient is tangent (⟂ q) and shrinks as 1/|q|
    gq = out[2][1]
    assert float((gq * unit).sum(-1).abs().max()) <= 1e-3 * float(ref[2][1].abs().max()) * (1 if dtype == D else 10)
    torch.testing.assert_close(gq * norms, ref[2][1],
                               atol=(1e-9 if dtype == D else 1e-3) * float(ref[2][1].abs().max()), rtol=0)


@pytest.mark.parametrize("norm", [0.0, 1e-13])
@pytest.mark.parametrize("fn", [rasterize, rasterize_dense])
def test_zero_norm_quaternion_is_a_value_error(norm, fn):
    args = _scene(4, 0.1)
    args[1][2] = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=D) * norm
    with pytest.raises(ValueError, match="quats"):
        fn(*args, VM, K, W, H)


def test_opacity_zero_and_one():
    """o = 1 saturates at alpha 0.99 (3DGS clamp); o = 0 is invisible and gets zero gradient everywhere."""
    means = torch.tensor([[0.5 / F * 2.0, 0.5 / F * 2.0, 2.0], [0.3, 0.1, 2.5], [-0.2, 0.1, 1.5]],
                         dtype=D)  # 1st on a pixel centre
    args = [means, torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=D), torch.full((3, 3), 0.2, dtype=D),
            torch.tensor([1.0, 0.0, 0.0], dtype=D), torch.eye(3, dtype=D)]
    for fn in (rasterize, rasterize_dense):
        col, alpha, grads, _ = _render(args, fn=fn)
        assert float(alpha.max()) == pytest.approx(0.99, abs=1e-12)  # centre pixel of the o = 1 Gaussian
        only = _render([t[:1] for t in args], fn=fn)
        assert torch.equal(col, only[0]) and torch.equal(alpha, only[1])
        for name, g in zip(PARAMS, grads, strict=False):
            assert _finite(g) and bool((g[1:] == 0).all()), name
        assert float(grads[3][0]) == 0.0 or float(grads[0][0].abs().max()) > 0  # clamped pixels pass no ∂/∂o


@pytest.mark.parametrize("dtype", [D, torch.float32])
@pytest.mark.parametrize("a", [0.5, 0.0045])
@pytest.mark.slow
def test_1e5_gaussians_stacked_on_one_pixel(a, dtype):
    """10⁵ identical-depth Gaussians centred on the pixel of a 1×1 image, alpha a at its centre:
    T_k = (1−a)^k underflows float32 long before the stack ends; compositing stops at the first k
    with T_k·(1−a) < 1e-4 (a = 0.5: 13 layers; a = 0.0045: 2042 layers), closed form."""
    n, w = 100_000, 1
    k_mat = torch.tensor([[[10.0, 0, 0.5], [0, 10.0, 0.5], [0, 0, 1]]], dtype=D)
    means = torch.tensor([[0.0, 0.0, 2.0]], dtype=D).expand(n, 3)
    feats = torch.rand(n, 1, generator=torch.Generator().manual_seed(0), dtype=D)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=D).expand(n, 4)
    leaves = [t.to(dtype).clone().requires_grad_()
              for t in (means, quats, torch.full((n, 3), 0.02, dtype=D), torch.full((n,), a, dtype=D), feats)]
    col, alpha, _ = rasterize(*leaves, torch.eye(4, dtype=dtype)[None], k_mat.to(dtype), w, w, render_mode="RGB")
    grads = torch.autograd.grad(col[0, 0, 0].sum() + alpha[0, 0, 0].sum(), leaves)
    T = (1 - a) ** torch.arange(n + 1, dtype=D)
    k = int(torch.nonzero(T[1:] < 1e-4)[0])  # first layer that would bring T below 1e-4: not included
    wts = a * T[:k]
    tol = 1e-10 if dtype == D else 2e-5
    torch.testing.assert_close(col[0, 0, 0, 0].double(), (wts * feats[:k, 0]).sum(), atol=tol, rtol=0)
    torch.testing.assert_close(alpha[0, 0, 0, 0].double(), 1 - T[k], atol=tol, rtol=0)
    assert _finite(col, alpha, *grads)
    torch.testing.assert_close(grads[4][:k, 0].double(), wts, atol=tol, rtol=0)
    margin = 1 if dtype == torch.float32 else 0  # float32 may round the stop test one layer either way
    for g in grads:
        assert bool((g[k + margin:] == 0).all())


def test_bfloat16_autocast_matches_float32_and_float64():
    args = _scene(40, 0.12, seed=5)
    f32 = _render(args, torch.float32)
    bf = _render(args, torch.float32, autocast=True)
    assert bf[0].dtype == torch.float32
    for x, y in zip([bf[0], bf[1], *bf[2]], [f32[0], f32[1], *f32[2]], strict=False):
        torch.testing.assert_close(x, y, atol=0, rtol=0)
    _assert_close_to_f64(bf, _render(args))
    # low-precision input tensors are computed (and returned) in float32; their gradients are
    # bfloat16 (8-bit mantissa), hence 1e-2·max|grad|
    b16 = [t.to(torch.bfloat16) for t in args]
    out = _render(b16, torch.bfloat16)
    assert out[0].dtype == torch.float32 and _finite(out[0], *out[2])
    vm, k = VM.to(torch.bfloat16).double(), K.to(torch.bfloat16).double()  # the cameras are rounded too
    _assert_close_to_f64(out, _render([t.double() for t in b16], vm=vm, k=k), grad_rtol=1e-2)


BAD = {"means": 0, "quats": 1, "scales": 2, "opacities": 3, "colors": 4, "viewmats": 5, "Ks": 6}


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("name", list(BAD) + ["backgrounds"])
@pytest.mark.parametrize("fn", [rasterize, rasterize_dense])
def test_non_finite_inputs_raise_naming_the_tensor(fn, name, value):
    args = _scene(5, 0.1) + [VM.clone(), K.clone()]
    bg = torch.zeros(1, 3, dtype=D)
    t = bg if name == "backgrounds" else args[BAD[name]]
    t.view(-1)[t.numel() // 2] = value
    with pytest.raises(ValueError, match=f"{name} contains"):
        fn(*args, W, H, backgrounds=bg)
