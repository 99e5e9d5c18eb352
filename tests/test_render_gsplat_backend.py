"""The optional gsplat backend: dispatch rule, argument pass-through (backgrounds composited here), and (with
CUDA + gsplat) agreement with the PyTorch path in every render mode, SH degree, background and rasterize mode."""
import importlib
import sys
import types

import pytest
import torch

from diff4splat.render import rasterize, rasterize_dense
from diff4splat.render.rasterize import NO_GSPLAT_ENV, choose_path, gsplat_available, use_gsplat

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


@pytest.mark.parametrize("extension", ["none", "raises", "loads"])
def test_gsplat_is_used_only_when_its_cuda_extension_loads(monkeypatch, extension):
    """gsplat builds its CUDA extension on first use; where the build fails (gsplat then sets ``_C = None`` or
    raises) renders fall back to the PyTorch tile path with one warning instead of failing at the first call.
    Stand-in ``gsplat`` modules and a CUDA that reports itself available: nothing here needs a GPU."""
    backend = types.ModuleType("gsplat.cuda._backend")
    if extension == "raises":
        def __getattr__(name):  # noqa: N807 - a module-level __getattr__: importing _C fails like a failed build
            raise RuntimeError("Error building extension 'gsplat_cuda'")
        backend.__getattr__ = __getattr__
    else:
        backend._C = object() if extension == "loads" else None
    pkg = types.ModuleType("gsplat")
    pkg.__path__ = []
    cuda = types.ModuleType("gsplat.cuda")
    cuda.__path__ = []
    monkeypatch.setitem(sys.modules, "gsplat", pkg)
    monkeypatch.setitem(sys.modules, "gsplat.cuda", cuda)
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    monkeypatch.setattr(rasterize_module.importlib.util, "find_spec", lambda name: object())
    monkeypatch.setattr(rasterize_module.torch.cuda, "is_available", lambda: True)
    gsplat_available.cache_clear()
    try:
        if extension == "loads":
            assert gsplat_available()
            monkeypatch.setenv(NO_GSPLAT_ENV, "1")
            gsplat_available.cache_clear()
            assert not gsplat_available()
        else:
            with pytest.warns(UserWarning, match="CUDA extension could not be loaded"):
                assert not gsplat_available()
    finally:
        gsplat_available.cache_clear()


def test_dispatch_passes_the_same_call_to_gsplat(monkeypatch):
    """With the dispatch forced on and a stand-in ``gsplat`` module, rasterize validates the inputs
    exactly as the PyTorch path does and hands every argument through unchanged (float32), with
    ``packed=False`` (meta in the PyTorch path's (C, N, …) layout) and without the backgrounds (gsplat 1.5.3
    rejects them in its packed layout): they are composited afterwards as T_final·bg, the PyTorch path's
    formula."""
    calls = []

    def fake_rasterization(*args, **kwargs):
        calls.append((args, kwargs))
        assert kwargs.pop("packed") is False and kwargs["backgrounds"] is None
        return rasterize_dense(*args, **kwargs)

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=fake_rasterization))
    monkeypatch.setattr(rasterize_module, "use_gsplat", lambda means: True)
    args = _scene()
    bg = torch.rand(1, 3)
    kw = dict(near_plane=0.5, far_plane=50.0, eps2d=0.2, backgrounds=bg, render_mode="RGB+D",
              rasterize_mode="antialiased", tile_size=8)
    col, alpha, meta = rasterize(*args, W, H, **kw)
    (got_args, got_kw), = calls
    assert all(torch.equal(a, b) for a, b in zip(got_args[:7], args, strict=False)) and got_args[7:] == (W, H)
    assert got_kw == {**kw, "sh_degree": None, "camera_model": "pinhole", "backgrounds": None}
    plain, plain_alpha, _ = rasterize_dense(*args, W, H, **{**kw, "backgrounds": None})
    bg4 = torch.cat([bg, torch.zeros(1, 1)], -1)  # the depth channel's background is 0
    assert torch.equal(alpha, plain_alpha) and torch.equal(col, plain + (1.0 - plain_alpha) * bg4[:, None, None])
    ref = rasterize_dense(*args, W, H, **kw)
    torch.testing.assert_close(col, ref[0], atol=1e-6, rtol=0)
    # every render mode: the background only reaches the colour channels, "ED" stays Σ w·z / alpha
    for mode in ("RGB", "D", "ED", "RGB+ED"):
        col = rasterize(*args, W, H, **{**kw, "render_mode": mode})[0]
        torch.testing.assert_close(col, rasterize_dense(*args, W, H, **{**kw, "render_mode": mode})[0], atol=1e-6,
                                   rtol=0)
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


MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
PARITY = [
    pytest.param(mode, sh, bg, am, id=f"{mode}-sh{sh}-{'bg' if bg else 'nobg'}-{am}")
    for mode in MODES for sh in (None, 0, 3) for bg in (False, True) for am in ("classic", "antialiased")
] + [pytest.param("RGB+ED", sh, True, "classic", id=f"RGB+ED-sh{sh}-bg-classic") for sh in (1, 2)]


@pytest.mark.cuda
@pytest.mark.parametrize("render_mode,sh_degree,with_bg,rasterize_mode", PARITY)
def test_gsplat_matches_the_pytorch_path(render_mode, sh_degree, with_bg, rasterize_mode):
    """gsplat on CUDA (float32) against our path on the CPU (float64, so its rounding is negligible), forward
    and gradients (Gaussians and backgrounds). The scene (opacities ≤ 0.3) keeps clear of every documented
    difference (0.999 vs 0.99 alpha clamp, tile boxes/off-image cull, next_T ≤ vs < 1e-4 ties), so the
    tolerances are float32 rounding: 1e-4 of the output scale, 1e-3 of each gradient's largest entry (float32
    atomics)."""
    pytest.importorskip("gsplat")
    args = _scene(seed=1, dtype=torch.float64)
    g = torch.Generator().manual_seed(2)
    if sh_degree is not None:
        args[4] = 0.3 * torch.randn(args[0].shape[0], (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
    bg = torch.rand(1, 3, generator=g, dtype=torch.float64) if with_bg else None
    kw = dict(render_mode=render_mode, sh_degree=sh_degree, rasterize_mode=rasterize_mode)
    grad_inputs = args[:5] + ([bg] if with_bg else [])
    outs = []
    for dev, dtype in (("cpu", torch.float64), ("cuda", torch.float32)):
        leaves = [t.to(dev, dtype).requires_grad_() for t in grad_inputs]
        if dev == "cuda":
            assert use_gsplat(leaves[0]) and choose_path(leaves[0]) == "gsplat"
        col, alpha, meta = rasterize(*leaves[:5], args[5].to(dev, dtype), args[6].to(dev, dtype), W, H,
                                     backgrounds=leaves[5] if with_bg else None, **kw)
        assert ("per_camera" in meta) == (dev == "cpu")  # gsplat's meta on CUDA, in the (C, N, …) layout
        assert meta["means2d"].shape == (1, args[0].shape[0], 2) and meta["radii"].shape[:2] == (1, args[0].shape[0])
        wts = torch.linspace(0.5, 1.5, col.numel(), dtype=torch.float64).reshape(col.shape).to(dev, dtype)
        grads = torch.autograd.grad((col * wts).sum() + alpha.sum(), leaves, allow_unused=True)
        grads = [None if x is None else x.double().cpu() for x in grads]
        outs.append((col.double().cpu(), alpha.double().cpu(), grads))
    (c1, a1, g1), (c2, a2, g2) = outs
    assert float(a1.max()) > 0.3
    torch.testing.assert_close(c2, c1, atol=1e-4 * max(1.0, float(c1.abs().max())), rtol=0)
    torch.testing.assert_close(a2, a1, atol=1e-4, rtol=0)
    for name, x, y in zip(["means", "quats", "scales", "opacities", "colors", "backgrounds"], g2, g1, strict=False):
        assert (x is None) == (y is None), name  # the depth modes do not use the background
        if y is not None:
            torch.testing.assert_close(x, y, atol=1e-3 * float(y.abs().max()) + 1e-8, rtol=0, msg=name)
