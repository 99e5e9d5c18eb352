"""Tests of diff4splat/render/fused.py: the fused compositor against the pure-PyTorch tile path (images and
gradients), its binning against bin_tiles, finite differences (gradcheck, float64), determinism over thread
counts, torch's thread count left alone, the fallback."""
import warnings

import pytest
import torch

import diff4splat.render.fused as fused
from diff4splat.render import rasterize
from diff4splat.render.fused import bin_tiles_fused, composite_fused
from diff4splat.render.tiles import bin_tiles, composite_tiles

pytestmark = pytest.mark.skipif(not fused.fused_available(), reason="numba is not installed")


def _screen(M=300, W=45, H=37, F=4, dtype=torch.float32, seed=1, stack=False):
    """Random screen-space Gaussians (means2d, conics, opacities, depths, feats, covars2d, background); with
    ``stack``, M nearly opaque Gaussians over the image centre so pixels stop at T < 1e-4."""
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(M, 2, generator=g) * torch.tensor([W, H])
    if stack:
        means2d = torch.tensor([W / 2, H / 2]) + 2 * torch.randn(M, 2, generator=g)
    L = torch.randn(M, 2, 2, generator=g) * 2 + torch.eye(2) * 3
    cov = L @ L.transpose(1, 2) + 0.3 * torch.eye(2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    covars2d = torch.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], -1)
    opacities = torch.full((M,), 0.98) if stack else torch.rand(M, generator=g) * 0.98 + 0.01
    depths = torch.rand(M, generator=g) * 5 + 1
    feats = torch.rand(M, F, generator=g)
    bg = torch.rand(F, generator=g)
    return [x.to(dtype) for x in (means2d, conics, opacities, depths, feats, covars2d, bg)]


def _run(fn, xs, W, H, tile, with_bg=True):
    xs = [x.clone().requires_grad_(i in (0, 1, 2, 4, 6)) for i, x in enumerate(xs)]
    col, acc, info = fn(xs[0], xs[1], xs[2], xs[3], xs[4], xs[5], xs[6] if with_bg else None, W, H, tile)
    g = torch.Generator().manual_seed(3)
    w_col = torch.rand(col.shape, generator=g, dtype=col.dtype)
    w_acc = torch.rand(acc.shape, generator=g, dtype=acc.dtype)
    ((col * w_col).sum() + (acc * w_acc).sum()).backward()
    grads = [xs[i].grad for i in (0, 1, 2, 4)] + ([xs[6].grad] if with_bg else [])
    return [col.detach(), acc.detach()], grads, info


@pytest.mark.parametrize("stack", [False, True])
@pytest.mark.parametrize("tile,W,H,with_bg", [(16, 45, 37, True), (8, 33, 20, False)])
def test_matches_the_tile_path_in_float32(stack, tile, W, H, with_bg):
    """Images to 1e-5 and gradients to 1e-5 relative to their largest value (float32): the kernels compute in
    float64, the tile path in float32 with float64 prefix sums."""
    xs = _screen(W=W, H=H, stack=stack)
    (c1, a1), g1, i1 = _run(composite_tiles, xs, W, H, tile, with_bg)
    (c2, a2), g2, i2 = _run(composite_fused, xs, W, H, tile, with_bg)
    assert c2.dtype == torch.float32 and c2.shape == (W * H, 4) and a2.shape == (W * H,)
    if stack:  # the stop rule is exercised: the centre reaches T < 1e-4 ...
        assert float(a1.max()) > 1 - 1e-3
    torch.testing.assert_close(c2, c1, atol=1e-5, rtol=0)
    torch.testing.assert_close(a2, a1, atol=1e-5, rtol=0)
    for a, b in zip(g2, g1, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=0)
    assert i2["n_pairs"] == i1["n_pairs"] and torch.equal(i2["flatten_ids"], i1["flatten_ids"])


def test_matches_the_tile_path_in_float64():
    xs = _screen(dtype=torch.float64, stack=True, M=120)
    out1, g1, _ = _run(composite_tiles, xs, 45, 37, 16)
    out2, g2, _ = _run(composite_fused, xs, 45, 37, 16)
    for a, b in zip(out2 + g2, out1 + g1, strict=True):
        torch.testing.assert_close(a, b, atol=1e-10 * max(1.0, float(b.abs().max())), rtol=0)


def test_gradcheck_float64():
    means2d, conics, opac, depths, feats, covars2d, bg = _screen(M=6, W=10, H=9, F=2, dtype=torch.float64, seed=4)

    def f(m, c, o, ft, b):
        col, acc, _ = composite_fused(m, c, o, depths, ft, covars2d, b, 10, 9, 4)
        return col, acc

    args = [x.clone().requires_grad_() for x in (means2d, conics, opac, feats, bg)]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


def test_same_result_for_any_thread_count():
    xs = _screen(M=800, W=64, H=48)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _run(composite_fused, xs, 64, 48, 16)
        torch.set_num_threads(2)
        two = _run(composite_fused, xs, 64, 48, 16)
    finally:
        torch.set_num_threads(n)
    for a, b in zip(one[0] + one[1], two[0] + two[1], strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("tile,W,H", [(16, 45, 37), (8, 33, 20), (4, 64, 48)])
def test_binning_equals_bin_tiles(tile, W, H):
    """The counting sort gives bin_tiles' dict exactly: same lists, same depth order inside each tile (ties in
    depth included: stable by index), Gaussians off the image or never visible in no tile."""
    means2d, _, opacities, depths, _, covars2d, _ = _screen(M=400, W=W, H=H)
    means2d[:20] += torch.tensor([W + 100.0, 0.0])  # far off the image to the right
    opacities[20:30] = 1e-3  # alpha < 1/255 everywhere
    depths[30:60] = 2.0  # ties
    ref, fast = bin_tiles(means2d, covars2d, opacities, depths, W, H, tile), \
        bin_tiles_fused(means2d, covars2d, opacities, depths, W, H, tile)
    assert ref.keys() == fast.keys()
    for k, v in ref.items():
        assert torch.equal(fast[k], v) if torch.is_tensor(v) else fast[k] == v, k
    assert int(ref["tiles_per_gauss"][:30].sum()) == 0 and int(ref["tile_counts"].sum()) > 400


def test_torch_thread_count_is_left_alone():
    """numba's OpenMP layer shares torch's pool and sets its thread count at each launch; it is restored."""
    xs = _screen(M=200, W=40, H=30)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        _run(composite_fused, xs, 40, 30, 16)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(n)


def test_falls_back_to_the_tile_path_without_numba(monkeypatch):
    xs = _screen(M=50, W=20, H=16)
    monkeypatch.setattr(fused, "_KERNELS", None)  # as if numba failed to import
    monkeypatch.setattr(fused, "_WARNED", [False])
    with pytest.warns(RuntimeWarning, match="numba is not installed"):
        (c1, _), _, _ = _run(composite_fused, xs, 20, 16, 16)
    with pytest.raises(RuntimeError, match="needs numba"):
        bin_tiles_fused(xs[0], xs[5], xs[2], xs[3], 20, 16, 16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once only
        _run(composite_fused, xs, 20, 16, 16)
    (c2, _), _, _ = _run(composite_tiles, xs, 20, 16, 16)
    assert torch.equal(c1, c2)


def test_rasterize_compositor_argument():
    g = torch.Generator().manual_seed(0)
    n = 60
    means = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) - 0.5,
                         2 + torch.rand(n, generator=g)], -1)
    args = (means, torch.randn(n, 4, generator=g), 0.05 + 0.1 * torch.rand(n, 3, generator=g),
            torch.rand(n, generator=g), torch.rand(n, 3, generator=g), torch.eye(4)[None],
            torch.tensor([[[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]]), 32, 24)
    a = rasterize(*args, compositor="fused")[0]
    b = rasterize(*args, compositor="torch")[0]
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="compositor"):
        rasterize(*args, compositor="cuda")

