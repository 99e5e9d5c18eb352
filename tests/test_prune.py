import pytest
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.gaussians import Gaussians
from diff4splat.prune import prune_scene, visibility_mask
from diff4splat.render.sequence import render_path
from diff4splat.scene import DynamicGaussians


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
