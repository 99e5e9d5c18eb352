"""The tile path never materialises a (pixels × Gaussians) tensor (the dense reference does)."""
import torch
from torch.profiler import ProfilerActivity, profile

from diff4splat.render import rasterize
from diff4splat.render.projection import splat_alpha


def _largest_allocation(fn, *args, **kw) -> int:
    """Largest single-op CPU allocation (bytes) while ``fn`` runs forward and backward."""
    leaves = [t.clone().requires_grad_() for t in args[:5]]
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        col, alpha, _ = fn(*leaves, *args[5:], **kw)
        (col.sum() + alpha.sum()).backward()
    return max(max(e.self_cpu_memory_usage, 0) for e in prof.events())


def _grid_scene(size):
    """One small Gaussian per pixel (the LDRM layout): P = N = size²."""
    f = float(size)
    i, j = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    z = torch.full((size, size), 2.0)
    means = torch.stack([(j - size / 2) / f * z, (i - size / 2) / f * z, z], -1).reshape(-1, 3)
    n = means.shape[0]
    g = torch.Generator().manual_seed(0)
    return [means, torch.randn(n, 4, generator=g), torch.full((n, 3), 0.5 * 2.0 / f),
            0.05 + 0.9 * torch.rand(n, generator=g),
            torch.rand(n, 3,
                       generator=g), torch.eye(4)[None], torch.tensor([[[f, 0, size / 2], [0, f, size / 2],
                                                                        [0, 0, 1]]]),
            size, size]


def test_tile_path_allocates_far_less_than_pixels_times_gaussians():
    size = 64
    args = _grid_scene(size)
    p_times_n = 4 * (size * size) ** 2  # bytes of one float32 (pixels × Gaussians) matrix: 67 MB here
    tile = _largest_allocation(rasterize, *args)
    assert tile < p_times_n / 20, (tile, p_times_n)  # measured 2.2 MB: O(pairs), not O(P·N)


def test_the_probe_sees_a_pixels_times_gaussians_allocation():
    """What the dense reference does (every pixel × every Gaussian through splat_alpha) is caught."""
    p, n = 4096, 1024
    x = torch.rand(p, 1)
    conics = torch.rand(1, n, 3).requires_grad_()
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        splat_alpha(x, x, conics, torch.rand(1, n)).sum().backward()
    assert max(e.self_cpu_memory_usage for e in prof.events()) >= 4 * p * n
