"""Tests of the fused projection (diff4splat/render/fused.py, project_fused) against project_gaussians (every output
and the gradients of means, quats, scales, opacities; float64 and float32; culled, clamped and antialiased
cases), finite differences (gradcheck), thread-count determinism, the fallbacks and the errors."""
import math

import pytest
import torch

import diff4splat.render.fused as fused
from diff4splat.render.fused import project_fused
from diff4splat.render.projection import project_gaussians

pytestmark = pytest.mark.skipif(not fused.fused_available(), reason="numba is not installed")

W, H = 64, 48
OUTPUTS = ("means2d", "depths", "covars2d", "conics", "opacities", "compensations")


def _cameras(dtype):
    """Three cameras: identity, shifted 0.3 m in x, turned 0.3 rad about y; f = 50 px."""
    vm = torch.eye(4, dtype=dtype).repeat(3, 1, 1)
    vm[1, 0, 3] = 0.3
    c, s = math.cos(0.3), math.sin(0.3)
    vm[2, :3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=dtype)
    Ks = torch.tensor([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]], dtype=dtype).repeat(3, 1, 1)
    return vm, Ks


def _gaussians(dtype, n=400, seed=0):
    """Random Gaussians in front of the cameras, plus: behind the camera, beyond the far plane, centres far
    outside the field of view whose bodies reach in (clamped Jacobian), and one huge one."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.8 + torch.tensor([0, 0, 3.0], dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.2 + 0.01
    if n >= 30:
        means[:5, 2] = -1.0  # behind
        means[5:10, 2] = 200.0  # beyond far_plane = 100
        means[10:20] = torch.tensor([8.0, 0.5, 3.0], dtype=torch.float64) + 0.1 * torch.randn(10, 3, generator=g)
        scales[10:20] = 3.0  # reach into the image from outside
        scales[20] = 50.0
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacities = torch.rand(n, generator=g, dtype=torch.float64) * 0.98 + 0.01
    return [x.to(dtype) for x in (means, quats, scales, opacities)]


def _run(fn, xs, antialiased, weights=None, **kw):
    vm, Ks = _cameras(xs[0].dtype)
    xs = [x.clone().requires_grad_() for x in xs]
    p = fn(*xs, vm, Ks, W, H, far_plane=100.0, antialiased=antialiased, **kw)
    g = torch.Generator().manual_seed(7)
    names = [f for f in OUTPUTS if getattr(p, f) is not None]
    weights = weights or [torch.randn(getattr(p, f).shape, generator=g, dtype=torch.float64) for f in names]
    sum(((getattr(p, f).double() * w).sum() for f, w in zip(names, weights, strict=True))).backward()
    return p, [x.grad for x in xs], weights


@pytest.mark.parametrize("antialiased", [False, True])
def test_matches_the_reference_in_float64(antialiased):
    xs = _gaussians(torch.float64)
    ref, ref_grads, w = _run(project_gaussians, xs, antialiased)
    out, grads, _ = _run(project_fused, xs, antialiased, w)
    assert torch.equal(out.radii, ref.radii) and out.radii.dtype == torch.int32
    culled = ref.radii == 0
    assert bool(culled[:, :10].all()) and bool((ref.radii[:, 10:21] > 0).any()) and not bool(culled.all())
    for f in OUTPUTS:
        a, b = getattr(out, f), getattr(ref, f)
        if b is None:
            assert a is None and not antialiased
            continue
        torch.testing.assert_close(a, b, atol=1e-12 * float(b.detach().abs().max()), rtol=1e-12, msg=f)
    for name, a, b in zip("means quats scales opacities".split(), grads, ref_grads, strict=True):
        assert float(b.detach().abs().max()) > 0
        torch.testing.assert_close(a, b, atol=1e-11 * float(b.detach().abs().max()), rtol=0, msg=name)


@pytest.mark.parametrize("antialiased", [False, True])
def test_float32_is_as_accurate_as_the_reference(antialiased):
    """float32 inputs: the kernels compute in float64, the reference in float32. Against the float64 result,
    the fused outputs and gradients are within float32 rounding, or no further off than the reference's
    (the covariance of the Gaussians reaching in from outside cancels badly in float32), or within 2e-4 of the
    largest gradient: the quaternions' float32 normalisation, which both paths share, loses that much (0.125
    of 1019 on both before the reference's determinant became cancellation-free, then 0.094 there)."""
    xs = _gaussians(torch.float32)
    truth, truth_grads, w = _run(project_gaussians, [x.double() for x in xs], antialiased)
    ref, ref_grads, _ = _run(project_gaussians, xs, antialiased, w)
    out, grads, _ = _run(project_fused, xs, antialiased, w)
    assert out.means2d.dtype == torch.float32 and grads[0].dtype == torch.float32
    assert torch.equal(out.radii, truth.radii)
    for f in OUTPUTS:
        if getattr(truth, f) is not None:
            a, b = getattr(out, f).double(), getattr(truth, f)
            torch.testing.assert_close(a, b, atol=1e-6 * float(b.detach().abs().max()), rtol=1e-6, msg=f)
    for name, a, r, b in zip("means quats scales opacities".split(), grads, ref_grads, truth_grads, strict=True):
        err, ref_err = (a.double() - b).abs().max(), (r.double() - b).abs().max()
        assert float(err) <= max(float(ref_err), 2e-4 * float(b.abs().max())), name


def test_gradcheck_float64():
    xs = _gaussians(torch.float64, n=12, seed=3)  # (the clamped giants of n ≥ 30 defeat finite differences)
    vm, Ks = _cameras(torch.float64)

    def f(means, quats, scales, opacities):
        p = project_fused(means, quats, scales, opacities, vm, Ks, W, H, far_plane=100.0, antialiased=True)
        return p.means2d, p.depths, p.covars2d, p.conics, p.opacities, p.compensations

    xs = [x.clone().requires_grad_() for x in xs]
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_same_result_for_any_thread_count():
    xs = _gaussians(torch.float32, n=3000)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _run(project_fused, xs, True)
        torch.set_num_threads(2)
        two = _run(project_fused, xs, True, one[2])
    finally:
        torch.set_num_threads(n)
    for f in OUTPUTS + ("radii",):
        assert torch.equal(getattr(one[0], f), getattr(two[0], f)), f
    for a, b in zip(one[1], two[1], strict=True):
        assert torch.equal(a, b)


def test_camera_gradients_use_the_reference():
    """viewmats / Ks requiring gradients: the reference runs, so their gradients exist and are its."""
    xs = _gaussians(torch.float64, n=50)
    vm, Ks = _cameras(torch.float64)
    grads = []
    for fn in (project_fused, project_gaussians):
        v = vm.clone().requires_grad_()
        fn(*xs, v, Ks, W, H).means2d.sum().backward()
        grads.append(v.grad)
    assert grads[0] is not None and torch.equal(grads[0], grads[1])


def test_without_numba_it_is_the_reference(monkeypatch):
    xs = _gaussians(torch.float32, n=80)
    vm, Ks = _cameras(torch.float32)
    monkeypatch.setattr(fused, "_KERNELS", None)
    a, b = project_fused(*xs, vm, Ks, W, H), project_gaussians(*xs, vm, Ks, W, H)
    for f in OUTPUTS[:-1] + ("radii",):
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_errors_are_the_reference_ones():
    xs = _gaussians(torch.float32, n=10)
    xs[1][4] = 0.0
    vm, Ks = _cameras(torch.float32)
    with pytest.raises(ValueError, match="zero-norm quaternion at flat index 4"):
        project_fused(*xs, vm, Ks, W, H)
    with pytest.raises(ValueError, match="camera_model"):
        project_fused(*_gaussians(torch.float32, n=10), vm, Ks, W, H, camera_model="fisheye")
