"""Tests of rolling-shutter rendering: static scenes equal the global shutter (every camera model), a moving
Gaussian or a moving camera shears by the closed-form number of pixels, bands, validation."""
import pytest
import torch

from diff4splat.cameras import CameraPath, FisheyePolynomial, RollingShutter, ThinLens
from diff4splat.render import raytrace, render_rolling_shutter
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0

D = torch.float64
W, H, F, Z = 48, 40, 40.0, 4.0


def _path(T=2, centres_x=(0.0, 0.0)):
    vms = torch.eye(4, dtype=D).repeat(T, 1, 1)
    vms[:, 0, 3] = -torch.tensor(centres_x, dtype=D)  # camera centre c = −t for R = I
    K = torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], dtype=D).expand(T, 3, 3).clone()
    return CameraPath(vms, K, W, H)


def _tall_gaussian(x0=0.0, dx=0.0):
    """One Gaussian tall in y (σy = 3 m, covering every row), σx = 0.1 m (1 px at z = 4 m, f = 40 px),
    moving from x0 to x0 + dx over the clip (key times 0 and 1, linear)."""
    g = Gaussians(torch.tensor([[x0, 0.0, Z]], dtype=D), torch.tensor([[1.0, 0, 0, 0]], dtype=D),
                  torch.tensor([[0.1, 3.0, 0.05]], dtype=D), torch.tensor([0.8], dtype=D),
                  rgb_to_sh0(torch.ones(1, 1, 3, dtype=D)))
    if dx == 0.0:
        return DynamicGaussians(g)
    d_means = torch.zeros(2, 1, 3, dtype=D)
    d_means[1, 0, 0] = dx
    dq = torch.zeros(2, 1, 4, dtype=D)
    dq[..., 0] = 1
    return DynamicGaussians(g, torch.tensor([0.0, 1.0], dtype=D), d_means, dq, torch.zeros_like(d_means))


def _row_centroids(alpha):
    xs = torch.arange(alpha.shape[-1], dtype=D) + 0.5
    return (alpha * xs).sum(-1) / alpha.sum(-1)


def _random_scene(n=60, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    means = torch.stack([(r(n) - 0.5) * 4, (r(n) - 0.5) * 3, 3 + 3 * r(n)], -1)
    return DynamicGaussians(Gaussians(means, torch.randn(n, 4, generator=g, dtype=D), 0.05 + 0.2 * r(n, 3),
                                      0.2 + 0.7 * r(n), 0.5 * torch.randn(n, 4, 3, generator=g, dtype=D)))


@pytest.mark.parametrize("kw", [{}, {"camera_model": "fisheye", "camera_params": FisheyePolynomial(k1=0.03, k2=-1e-4)},
                                {"camera_params": ThinLens(0.05, 4.0, spp=2)}])
@pytest.mark.slow
def test_static_scene_equals_global_shutter(kw):
    """Bands are ray traced with the principal point shifted by their first row, so per-row rendering of a
    static scene reproduces the one-shot frame for every camera model."""
    scene, path = _random_scene(), _path()
    per_row = render_rolling_shutter(scene, path, RollingShutter(0.6, chunks=None), frames=[1], **kw)
    glob = render_rolling_shutter(scene, path, RollingShutter(0.6, chunks=1), frames=[1], **kw)
    g = scene.at(1.0)
    out, alpha, _ = raytrace(g.means, g.quats, g.scales, g.opacities, g.sh, path.viewmats[1:], path.Ks[1:], W, H,
                             sh_degree=1, backgrounds=torch.zeros(1, 3, dtype=D), **kw)
    assert float(alpha.max()) > 0.5
    for a, b in zip(per_row, glob, strict=False):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    torch.testing.assert_close(glob[0][0], out[0, ..., :3].clamp(0, 1), rtol=0, atol=1e-10)
    torch.testing.assert_close(glob[2][0], alpha[0, ..., 0], rtol=0, atol=1e-10)


@pytest.mark.slow
def test_moving_gaussian_shears_by_velocity_times_readout():
    """x(t) = −1 + 2t m at z = 4 m, f = 40 px: v = 20 px per clip time. Row i is read at
    t_i = t_frame − D/2 + (i + ½)/H·D, so its centroid is cx + f·x(t_i)/z and the bottom row is
    v·D·(H − 1)/H px right of the top row. A row centroid of the ray-traced image sits within 7e-3 px
    of the projected centre (measured; perspective and the 1/255 cut on the pixel grid)."""
    dur = 0.5
    scene, path = _tall_gaussian(-1.0, 2.0), _path()
    cameras = CameraPath(path.viewmats[:1].repeat(3, 1, 1), path.Ks[:1].repeat(3, 1, 1), W, H)  # t = 0, ½, 1
    _, _, alpha = render_rolling_shutter(scene, cameras, RollingShutter(dur), frames=[1])
    c = _row_centroids(alpha[0])
    t = 0.5 - dur / 2 + (torch.arange(H, dtype=D) + 0.5) / H * dur
    expect = W / 2 + F * (-1.0 + 2.0 * t) / Z
    torch.testing.assert_close(c, expect, rtol=0, atol=1e-2)  # measured ≤ 7e-3 px (see below)
    assert float(c[-1] - c[0]) == pytest.approx(20.0 * dur * (H - 1) / H, abs=2e-2)
    # 4 bands: rows of a band share the band's mean time
    _, _, alpha4 = render_rolling_shutter(scene, cameras, RollingShutter(dur, chunks=4), frames=[1])
    c4 = _row_centroids(alpha4[0])
    for (r0, r1), tb in zip(RollingShutter(dur, chunks=4).row_bands(H),
                            RollingShutter(dur, chunks=4).band_times(H, 0.5), strict=False):
        torch.testing.assert_close(c4[r0:r1], torch.full((r1 - r0,), W / 2 + F * (-1.0 + 2.0 * tb) / Z, dtype=D),
                                   rtol=0, atol=1e-2)  # measured ≤ 7e-3 px (see below)
    # global shutter: no shear
    _, _, alpha1 = render_rolling_shutter(scene, cameras, RollingShutter(dur, chunks=1), frames=[1])
    c1 = _row_centroids(alpha1[0])
    assert float(c1.max() - c1.min()) < 1e-9


@pytest.mark.slow
def test_moving_camera_shears_only_with_pose_interpolation():
    """Camera centre x from 0 to 1 m over the clip: a static point at z = 4 m moves −f/z = −10 px per clip
    time in the image; the readout of frame 0 (anchor "start", D = 0.4) shears it by −10·D·(H − 1)/H px."""
    scene, path = _tall_gaussian(), _path(centres_x=(0.0, 1.0))
    rs = RollingShutter(0.4, anchor="start")
    _, _, alpha = render_rolling_shutter(scene, path, rs, frames=[0])
    c = _row_centroids(alpha[0])
    t = (torch.arange(H, dtype=D) + 0.5) / H * 0.4
    torch.testing.assert_close(c, W / 2 - F * t / Z, rtol=0, atol=1e-2)  # measured ≤ 7e-3 px (see below)
    _, _, alpha_fixed = render_rolling_shutter(scene, path, rs, frames=[0], interpolate_pose=False)
    c_fixed = _row_centroids(alpha_fixed[0])
    torch.testing.assert_close(c_fixed, torch.full_like(c_fixed, W / 2), rtol=0, atol=1e-9)


def test_gradients_flow_to_the_scene():
    scene = _tall_gaussian(-1.0, 2.0)
    means = scene.canonical.means.clone().requires_grad_()
    g = Gaussians(means, *(getattr(scene.canonical, k) for k in ("quats", "scales", "opacities", "sh")))
    scene = DynamicGaussians(g, scene.times, scene.d_means, scene.d_quats, scene.d_scales)
    colors, depths, alphas = render_rolling_shutter(scene, _path(), RollingShutter(0.3, chunks=5), frames=[0])
    (grad,) = torch.autograd.grad(alphas.sum() + colors.sum(), means)
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().max()) > 0


@pytest.mark.parametrize("call,match", [
    (lambda s, p: render_rolling_shutter(s, p, RollingShutter(0.1, chunks=H + 1)), "chunks"),
    (lambda s, p: render_rolling_shutter(s, p, RollingShutter(0.1), frames=[2]), "frames"),
    (lambda s, p: render_rolling_shutter(s, p, 0.1), "shutter"),
    (lambda s, p: render_rolling_shutter(s, p, RollingShutter(0.1), render_mode="RGB"), "render_mode"),
])
def test_bad_arguments_raise(call, match):
    with pytest.raises(ValueError, match=match):
        call(_tall_gaussian(), _path())
