import pytest
import torch
from helpers import moving_patch_scene

from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.render.sequence import render_path
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0, sh0_to_rgb


def test_each_frame_renders_the_scene_at_its_own_time():
    """A small bright Gaussian moving along x: frame i shows it where its mean at t_i projects."""
    W = H = 32
    T = 5
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0, dtype=torch.float64)
    path = CameraPath(torch.eye(4, dtype=torch.float64).repeat(T, 1, 1), K.expand(T, 3, 3).clone(), W, H)
    g = Gaussians(torch.tensor([[-0.5, 0.0, 2.0]], dtype=torch.float64),
                  torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                  torch.full((1, 3), 0.03, dtype=torch.float64), torch.tensor([0.95], dtype=torch.float64),
                  rgb_to_sh0(torch.ones(1, 1, 3, dtype=torch.float64)))
    d_means = torch.zeros(T, 1, 3, dtype=torch.float64)
    d_means[:, 0, 0] = torch.linspace(0, 1.0, T, dtype=torch.float64)
    dq = torch.zeros(T, 1, 4, dtype=torch.float64)
    dq[..., 0] = 1
    scene = DynamicGaussians(g, path.times, d_means, dq, torch.zeros_like(d_means))
    colors, depths, alphas = render_path(scene, path)
    assert colors.shape == (T, H, W, 3) and depths.shape == alphas.shape == (T, H, W)
    xs = torch.arange(W, dtype=torch.float64) + 0.5
    for i in range(T):
        w = alphas[i].sum(0)
        centroid_x = float((w * xs).sum() / w.sum())
        x = -0.5 + float(d_means[i, 0, 0])
        expected = float(K[0, 0] * x / 2.0 + K[0, 2])
        assert abs(centroid_x - expected) < 0.2, (i, centroid_x, expected)
        peak = alphas[i].argmax()
        torch.testing.assert_close(depths[i].flatten()[peak], torch.tensor(2.0, dtype=torch.float64), atol=1e-9, rtol=0)


def test_features_are_composited_beside_the_colours_in_the_same_pass():
    """With temporal support (only the Gaussians seen at t are drawn): a feature equal to each Gaussian's own colour
    (SH degree 0) renders as the colour over a black background, the scene's depth and alpha unchanged; one-hot
    channels sum to the alpha (they are composited over 0); a (M, C) shape is required."""
    scene, cams = moving_patch_scene(n=200, frames=5, temporal=True, width=48, height=40)
    rgb = sh0_to_rgb(scene.canonical.sh[:, 0])
    plain, depth, alpha = render_path(scene, cams, background=(0.0, 0.0, 0.0))
    both, depth2, alpha2 = render_path(scene, cams, background=(0.0, 0.0, 0.0),
                                       features=torch.cat([rgb, torch.nn.functional.one_hot(
                                           torch.arange(200) % 3, 3).float()], 1))
    assert both.shape == (5, 40, 48, 9) and torch.equal(both[..., :3], plain)
    torch.testing.assert_close(both[..., 3:6], plain, atol=1e-5, rtol=0)
    torch.testing.assert_close(both[..., 6:].sum(-1), alpha, atol=1e-5, rtol=0)
    assert torch.equal(depth, depth2) and torch.equal(alpha, alpha2)
    assert float(alpha.amax()) > 0.5  # something is drawn at every one of these times
    with pytest.raises(ValueError, match="features"):
        render_path(scene, cams, features=torch.zeros(199, 2))
