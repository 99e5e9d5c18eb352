"""Degenerate Gaussians and empty views that the renderer accepts, on every path (the default path: fused on the
CPU, gsplat on CUDA when installed; the PyTorch tile path, dense reference, ray path) and every device of the
``device`` fixture: finite images and gradients, and an image that stays in the autograd graph.

Each case was a failure before: a zero scale made the ray path's whitening infinite (NaN pixels and gradients);
a line Gaussian in antialiased mode backpropagated through sqrt at 0 on the PyTorch projection; near_plane = 0
let a centre on the camera plane divide by z = 0; a view that saw nothing returned a detached image on the
PyTorch, dense and ray paths, so ``loss.backward()`` raised.
"""
import pytest
import torch

from diff4splat.render import rasterize, rasterize_dense, raytrace
from diff4splat.render.rasterize import choose_path

D = torch.float64
W, H = 32, 24
K = torch.tensor([[[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]]], dtype=D)
VM = torch.eye(4, dtype=D)[None]  # never requires grad: a test that needs camera gradients clones it


def _scene(n=4, dtype=D):
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g, dtype=D) * 0.3 + torch.tensor([0, 0, 3.0], dtype=D)
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = torch.rand(n, 3, generator=g, dtype=D) * 0.2 + 0.05
    opacities = torch.rand(n, generator=g, dtype=D) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g, dtype=D)
    return [t.to(dtype) for t in (means, quats, scales, opacities, colors)]


PATHS = {
    "default": rasterize,  # fused on the CPU; gsplat on CUDA for float32 when installed, else the PyTorch path
    "torch": lambda *a, **k: rasterize(*a, compositor="torch", **k),
    "dense": rasterize_dense,
    "ray": raytrace,
}


def _render_and_backward(path, params, device="cpu", **kw):
    """Render on ``device`` with every parameter requiring grad, backpropagate a loss; return the image and the
    gradients (on ``device``)."""
    leaves = [t.to(device).requires_grad_(True) for t in params]
    dtype = params[0].dtype
    out, alpha, _ = PATHS[path](*leaves, VM.to(device, dtype), K.to(device, dtype), W, H, **kw)
    ((out - 0.5) ** 2).mean().add(alpha.mean()).backward()
    return out, [t.grad for t in leaves]


def _all_finite(out, grads):
    return bool(torch.isfinite(out).all()) and all(g is None or bool(torch.isfinite(g).all()) for g in grads)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("path", sorted(PATHS))
def test_a_zero_or_tiny_scale_renders_finite_images_and_gradients(path, dtype, device):
    for value in (0.0, 1e-20):
        params = _scene(dtype=dtype)
        params[2][0, 2] = value  # a flat disc
        params[2][1, 1:] = value  # a line
        out, grads = _render_and_backward(path, params, device)
        assert _all_finite(out, grads), (path, dtype, value)


@pytest.mark.parametrize("path", ["default", "torch", "dense"])
def test_a_line_gaussian_in_antialiased_mode_has_finite_gradients(path, device):
    params = _scene()
    params[1][0] = torch.tensor([1.0, 0, 0, 0], dtype=D)
    params[2][0] = torch.tensor([0.2, 0.0, 0.0], dtype=D)  # det Σ2d = 0: compensation 0
    out, grads = _render_and_backward(path, params, device, rasterize_mode="antialiased")
    assert _all_finite(out, grads)


@pytest.mark.parametrize("path", ["default", "torch", "dense"])
def test_near_plane_zero_culls_a_centre_on_the_camera_plane(path, device):
    params = _scene()
    params[0][0] = torch.tensor([0.3, 0.1, 0.0], dtype=D)  # z = 0
    out, grads = _render_and_backward(path, params, device, near_plane=0.0)
    assert _all_finite(out, grads)
    assert float(grads[0][0].abs().sum()) == 0.0  # culled: it adds nothing and learns nothing


def test_near_plane_zero_with_camera_gradients_stays_finite(device):
    """Camera gradients route the fused path through the PyTorch projection."""
    params = [t.to(device) for t in _scene()]
    params[0][0] = torch.tensor([0.3, 0.1, 0.0], dtype=D, device=device)
    viewmats = VM.clone().to(device).requires_grad_(True)  # a clone: VM itself must stay a constant
    out, _, _ = rasterize(*params, viewmats, K.to(device), W, H, near_plane=0.0)
    out.sum().backward()
    assert bool(torch.isfinite(viewmats.grad).all())


@pytest.mark.parametrize("path", sorted(PATHS))
def test_a_view_that_sees_nothing_stays_in_the_graph_with_zero_gradients(path, device):
    params = _scene()
    params[0][:, 2] = -3.0  # every Gaussian behind the camera
    out, grads = _render_and_backward(path, params, device)
    assert out.requires_grad and float(out.detach().abs().max()) == 0.0
    assert all(g is None or float(g.abs().max()) == 0.0 for g in grads)


@pytest.mark.parametrize("path", ["default", "torch"])
def test_an_elongated_gaussian_in_float32_renders_as_in_float64(path, device):
    """det Σ2d as sxx·syy − sxy² cancelled the long axis's L⁴ in float32: a 100 m × 1 cm Gaussian lost 3 % of its
    alpha on the PyTorch path and a 1 km × 1 cm one was culled; the minors of J·R·S do not cancel. (gsplat, the
    default path on CUDA, keeps the cancellation: a documented difference,
    diff4splat.render.rasterize.rasterize_gsplat.)"""
    if path == "default" and choose_path(torch.zeros(1, 3, device=device)) == "gsplat":
        pytest.skip("gsplat's float32 determinant cancels (documented in diff4splat.render.rasterize.rasterize_gsplat)")
    q = torch.tensor([[0.9394, 0.0, 0.0, 0.3429]], device=device)  # long axis 40° from the image's x axis
    for length in (100.0, 1000.0):
        params = [torch.tensor([[0.0, 0.0, 5.0]], device=device), q,
                  torch.tensor([[length, 1e-2, 1e-2]], device=device), torch.tensor([0.9], device=device),
                  torch.ones(1, 3, device=device)]
        vm, k = VM.to(device), K.to(device)
        out32, alpha32, meta = PATHS[path](*params, vm.float(), k.float(), W, H)
        out64, alpha64, _ = PATHS[path](*[t.double() for t in params], vm, k, W, H)
        assert int(meta["radii"].max()) > 0
        torch.testing.assert_close(alpha32.double().sum(), alpha64.sum(), rtol=1e-4, atol=0)
