"""The optional gsplat backend: dispatch rule, argument pass-through, and (with CUDA + gsplat) agreement
with the PyTorch tile path."""
import importlib
import sys
import types

import pytest
import torch

from diff4splat.render import rasterize, rasterize_dense
from diff4splat.render.gsplat_backend import gsplat_available, use_gsplat

rasterize_module = importlib.import_module("diff4splat.render.rasterize")  # the package re-exports the function
W, H = 32, 24


def _scene(n=60, seed=0, dtype=torch.float32, device="cpu"):
    """Opacities ≤ 0.3: alpha never reaches the 0.99/0.999 clamps and o·exp(−4.5) < 1/255, so gsplat's
    3σ tiles and the PyTorch path's opacity-aware boxes cover the same pixels."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    means = torch.stack([(r(n) - 0.5) * 2.0, (r(n) - 0.5) * 1.5, 2 + 3 * r(n)], -1)
    args = [means, torch.randn(n, 4, generator=g, dtype=torch.float64), 0.03 + 0.15 * r(n, 3), 0.05 + 0.25 * r(n),
            r(n, 3),
            torch.eye(4, dtype=torch.float64)[None],
            torch.tensor([[[W * 0.9, 0, W / 2], [0, W * 0.9, H / 2], [0, 0, 1]]], dtype=torch.float64)]
    return [t.to(dtype=dtype, device=device) for t in args]


def test_cpu_and_float64_tensors_use_the_pytorch_path():
    assert not use_gsplat(torch.zeros(3, 3))
    assert not use_gsplat(torch.zeros(3, 3, dtype=torch.float64))
    if not torch.cuda.is_available():
        assert not gsplat_available()


def test_dispatch_passes_the_same_call_to_gsplat(monkeypatch):
    """With the dispatch forced on and a stand-in ``gsplat`` module, rasterize validates the inputs
    exactly as the PyTorch path does and hands every argument through unchanged (float32)."""
    calls = []

    def fake_rasterization(*args, **kwargs):
        calls.append((args, kwargs))
        return rasterize_dense(*args, **kwargs)

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=fake_rasterization))
    monkeypatch.setattr(rasterize_module, "use_gsplat", lambda means, camera_model="pinhole": True)
    args = _scene()
    bg = torch.rand(1, 3)
    kw = dict(near_plane=0.5, far_plane=50.0, eps2d=0.2, backgrounds=bg, render_mode="RGB+D",
              rasterize_mode="antialiased", tile_size=8)
    col, alpha, meta = rasterize(*args, W, H, **kw)
    (got_args, got_kw), = calls
    assert all(torch.equal(a, b) for a, b in zip(got_args[:7], args, strict=False)) and got_args[7:] == (W, H)
    assert got_kw == {**kw, "sh_degree": None, "camera_model": "pinhole", "backgrounds": got_kw["backgrounds"]}
    assert torch.equal(got_kw["backgrounds"], bg)
    ref = rasterize_dense(*args, W, H, **kw)
    assert torch.equal(col, ref[0]) and torch.equal(alpha, ref[1])
    # low precision is cast to float32 before gsplat sees it; bad input never reaches gsplat
    rasterize(*[t.to(torch.bfloat16) for t in args], W, H)
    assert all(t.dtype == torch.float32 for t in calls[-1][0][:7])
    n = len(calls)
    bad = [t.clone() for t in args]
    bad[0][3, 1] = float("nan")
    with pytest.raises(ValueError, match="means contains"):
        rasterize(*bad, W, H)
    bad = [t.clone() for t in args]
    bad[1][2] = 0.0
    with pytest.raises(ValueError, match="quats"):
        rasterize(*bad, W, H)
    assert len(calls) == n


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("render_mode,sh_degree", [("RGB+ED", None), ("RGB", 2), ("D", None)])
def test_gsplat_matches_the_pytorch_path(render_mode, sh_degree):
    pytest.importorskip("gsplat")
    args = _scene(seed=1)
    if sh_degree is not None:
        args[4] = 0.3 * torch.randn(args[0].shape[0], (sh_degree + 1) ** 2, 3,
                                    generator=torch.Generator().manual_seed(2))
    bg = torch.rand(1, 3)
    kw = dict(render_mode=render_mode, sh_degree=sh_degree, backgrounds=None if render_mode == "D" else bg)
    cpu_leaves = [t.clone().requires_grad_() for t in args[:5]]
    cuda_leaves = [t.cuda().requires_grad_() for t in args[:5]]
    assert use_gsplat(cuda_leaves[0])
    outs = []
    for leaves, dev in ((cpu_leaves, "cpu"), (cuda_leaves, "cuda")):
        extra = {k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in kw.items()}
        col, alpha, _ = rasterize(*leaves, args[5].to(dev), args[6].to(dev), W, H, **extra)
        wts = torch.linspace(0.5, 1.5, col.numel(), device=dev).reshape(col.shape)
        grads = torch.autograd.grad((col * wts).sum() + alpha.sum(), leaves)
        outs.append((col.cpu(), alpha.cpu(), [g.cpu() for g in grads]))
    (c1, a1, g1), (c2, a2, g2) = outs
    assert float(a1.max()) > 0.3
    torch.testing.assert_close(c2, c1, atol=1e-4 * max(1.0, float(c1.abs().max())), rtol=0)
    torch.testing.assert_close(a2, a1, atol=1e-4, rtol=0)
    for name, x, y in zip(["means", "quats", "scales", "opacities", "colors"], g2, g1, strict=False):
        torch.testing.assert_close(x, y, atol=1e-3 * float(y.abs().max()), rtol=0, msg=name)
