"""The photo layer (diff4splat/assembly/photo.py): the photograph reproduced at the input camera, no gaps a sub-pixel
motion can open, disks on their rays facing the camera, edge-aware depth upsampling."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import EXAMPLE_IMAGE

from diff4splat.assembly.photo import (
    BACKDROP_DEPTH,
    BACKING_SCALE_PX,
    FRONT_SCALE_PX,
    PHOTO_EPS2D,
    _backdrop_grid,
    backdrop_colors,
    backdrop_colors_reference,
    backdrop_layer,
    photo_layer,
    render_input_view,
    upsample_depth,
)
from diff4splat.cameras import camera_rays, intrinsics_from_fov
from diff4splat.io import load_image
from diff4splat.render import rasterize
from diff4splat.scene.gaussians import Gaussians, sh0_to_rgb
from diff4splat.scene.quaternions import quat_to_rotmat

TEXTURE = Path(__file__).resolve().parent.parent / "data_prep" / "textures" / "grass.png"  # fine detail


def _psnr(a, b):
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


def _depths(H, W, seed=0):
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, H), torch.linspace(-1, 1, W), indexing="ij")
    return {
        "plane": torch.full((H, W), 2.0),
        "tilted": 2.0 + 0.8 * xx + 0.3 * yy,
        "noisy": 2.0 + 0.3 * torch.rand(H, W, generator=g),
        "steps": 2.0 + (xx > 0).float() + 0.5 * (yy > 0.3).float(),
    }


@pytest.mark.parametrize("H,W", [(16, 16), (48, 80), pytest.param(256, 256, marks=pytest.mark.slow)])
@pytest.mark.parametrize("photo", ["chelsea", "grass"])
def test_the_layer_alone_reproduces_the_photo_at_the_input_camera(H, W, photo):
    """≥ 40 dB for every depth map (plane, tilt, noise, depth steps) at low and high resolution, on the demo photo
    and a finely textured one (grass). Off-centre, rotated camera: the layer follows any input pose."""
    image = load_image(EXAMPLE_IMAGE if photo == "chelsea" else TEXTURE, size=(H, W))
    K = intrinsics_from_fov(W, H, fov_y_deg=50.0)
    viewmat = torch.eye(4, device="cpu")
    viewmat[:3, :3] = quat_to_rotmat(torch.tensor([0.95, 0.1, -0.2, 0.05], device="cpu"))
    viewmat[:3, 3] = torch.tensor([0.3, -0.1, 0.5], device="cpu")
    for name, depth in _depths(H, W).items():
        layer, history = photo_layer(image, depth, viewmat, K)
        assert layer.num_gaussians == H * W + (-(-H // 2)) * (-(-W // 2))
        rendered = render_input_view(layer, viewmat, K, W, H).clamp(0, 1)
        psnr = _psnr(rendered, image)
        assert psnr >= 40.0, (name, psnr, history)
        assert history[-1] == pytest.approx(psnr, abs=1e-3)
        assert history[-1] > history[0]  # the colour solve helps


def test_a_sub_pixel_camera_motion_opens_no_gaps():
    """The backing disks fill what the small front disks leave between pixel centres when the view moves by a
    fraction of a pixel: coverage ≥ 0.97 everywhere (front disks alone: ~0.5)."""
    H = W = 64
    image = load_image(EXAMPLE_IMAGE, size=(H, W))
    K = intrinsics_from_fov(W, H, fov_y_deg=50.0)
    eye = torch.eye(4, device="cpu")
    f = float(K[0, 0])
    for depth in _depths(H, W).values():
        layer, _ = photo_layer(image, depth, eye, K)
        for dx, dy in ((0.5, 0.5), (0.5, 0.0), (0.25, 0.75), (1.0, 1.0)):  # pixels at 2 m
            moved = eye.clone()
            moved[0, 3], moved[1, 3] = dx * 2.0 / f, dy * 2.0 / f
            _, alpha, _ = rasterize(layer.means, layer.quats, layer.scales, layer.opacities, layer.sh, moved[None],
                                    K[None], W, H, eps2d=PHOTO_EPS2D, sh_degree=0, render_mode="RGB")
            assert float(alpha[0, 4:-4, 4:-4].min()) >= 0.97, (dx, dy)
        moved = eye.clone()
        moved[:2, 3] = 0.5 * 2.0 / f
        front = torch.arange(H * W)
        _, alpha, _ = rasterize(layer.means[front], layer.quats[front], layer.scales[front], layer.opacities[front],
                                layer.sh[front], moved[None], K[None], W, H, eps2d=PHOTO_EPS2D, sh_degree=0,
                                render_mode="RGB")
        assert float(alpha[0, 4:-4, 4:-4].min()) < 0.8  # what the backing layer is for


def test_disks_sit_on_their_rays_at_the_depth_and_face_the_camera():
    H, W = 12, 20
    image = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
    depth = _depths(H, W)["tilted"]
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0)
    viewmat = torch.eye(4, device="cpu")
    viewmat[:3, 3] = torch.tensor([0.2, 0.0, -0.4], device="cpu")
    layer, _ = photo_layer(image, depth, viewmat, K, refine_steps=0)
    front = layer.means[: H * W]
    cam = front @ viewmat[:3, :3].T + viewmat[:3, 3]
    torch.testing.assert_close(cam[:, 2], depth.reshape(-1), atol=1e-5, rtol=0)  # z-depth as given
    uv = cam[:, :2] / cam[:, 2:] @ K[:2, :2].T + K[:2, 2]
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(-1, 2), atol=1e-4, rtol=0)  # pixel centres
    _, dirs = camera_rays(viewmat[None], K[None], W, H)
    axes = quat_to_rotmat(layer.quats[: H * W])
    torch.testing.assert_close(axes[:, :, 2], dirs[0].reshape(-1, 3), atol=1e-5, rtol=0)  # thin axis along the ray
    assert bool((layer.scales[: H * W, 2] < 0.2 * layer.scales[: H * W, 0]).all())
    back = layer.means[H * W:] @ viewmat[:3, :3].T + viewmat[:3, 3]
    assert back.shape[0] == (H // 2) * (W // 2)
    # σ in pixels of the input camera (the backing grid's too: its half-resolution intrinsics do not halve it)
    torch.testing.assert_close(layer.scales[: H * W, 0], FRONT_SCALE_PX * depth.reshape(-1) / K[0, 0])
    torch.testing.assert_close(layer.scales[H * W:, 1], BACKING_SCALE_PX * back[:, 2] / K[1, 1])
    uv = back[:, :2] / back[:, 2:] @ K[:2, :2].T + K[:2, 2]
    v, u = torch.meshgrid(2 * torch.arange(H // 2) + 1.0, 2 * torch.arange(W // 2) + 1.0, indexing="ij")
    torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(-1, 2), atol=1e-4, rtol=0)  # 2×2 block centres
    for k, (cu, cv) in enumerate(uv.tolist()):  # behind every front disk whose centre is within ±4 pixels
        rows = slice(max(0, math.ceil(cv - 4.5 - 1e-6)), math.floor(cv + 3.5 + 1e-6) + 1)
        cols = slice(max(0, math.ceil(cu - 4.5 - 1e-6)), math.floor(cu + 3.5 + 1e-6) + 1)
        assert float(back[k, 2]) > float(depth[rows, cols].max())
    blocks = F.avg_pool2d(image.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0).reshape(-1, 3)
    torch.testing.assert_close(sh0_to_rgb(layer.sh[H * W:, 0]), blocks)  # the photo's own (block) colours


def test_edge_aware_upsampling_puts_depth_edges_on_colour_edges():
    """A depth step known only at 8× lower resolution, and a photo whose colour edge sits inside a low-res cell:
    the joint bilateral upsampling moves the depth edge onto the colour edge, bilinear leaves it smeared."""
    H = W = 64
    edge = 29  # not on the 8-pixel grid
    truth = torch.where(torch.arange(W)[None].expand(H, W) < edge, 1.0, 3.0)
    low = F.interpolate(truth[None, None], size=(8, 8), mode="area")[0, 0]
    guide = torch.zeros(H, W, 3)
    guide[:, edge:] = 1.0
    up = upsample_depth(low, guide)
    bilinear = F.interpolate(low.log()[None, None], size=(H, W), mode="bilinear", align_corners=False)[0, 0].exp()
    err_up, err_bi = (up - truth).abs().mean(), (bilinear - truth).abs().mean()
    assert up.shape == (H, W) and bool((up > 0).all())
    assert err_up < 0.01 * err_bi and float(err_bi) > 0.1  # 0.0004 m against 0.12 m
    ramp = torch.linspace(0.0, 1.0, 16)[None].expand(16, 16).exp()  # no colour edge: log-linear depth stays so
    flat = upsample_depth(ramp, torch.full((128, 128, 3), 0.5))
    reference = F.interpolate(ramp.log()[None, None], size=(128, 128), mode="bilinear", align_corners=False)[0, 0]
    assert float((flat.log() - reference)[24:-24, 24:-24].abs().max()) < 5e-4  # 3 cells from the clamped borders
    torch.testing.assert_close(upsample_depth(low, guide[:8, :8]), low)  # no upsampling: the same map


def test_bad_inputs_are_one_clear_error():
    image, K, eye = torch.rand(8, 8, 3), intrinsics_from_fov(8, 8, fov_y_deg=50.0), torch.eye(4)
    with pytest.raises(ValueError, match="depth must have shape"):
        photo_layer(image, torch.ones(8, 9), eye, K)
    with pytest.raises(ValueError, match="finite and > 0"):
        photo_layer(image, torch.zeros(8, 8), eye, K)
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        photo_layer(image * 2, torch.ones(8, 8), eye, K)
    with pytest.raises(ValueError, match="finite and > 0"):
        upsample_depth(torch.full((2, 2), float("nan")), image)
    with pytest.raises(ValueError, match="at least as large"):
        upsample_depth(torch.ones(16, 16), image)


def test_the_layer_is_built_beside_its_inputs(device, no_implicit_device):
    image = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(0), device="cpu").to(device)
    depth = torch.full((16, 16), 2.0, device=device)
    K = intrinsics_from_fov(16, 16, fov_y_deg=50.0, device=device)
    layer, history = photo_layer(image, depth, torch.eye(4, device=device), K)
    assert layer.means.device.type == device.type and history[-1] >= 40.0
    assert upsample_depth(depth[::4, ::4], image).device.type == device.type


def test_the_backdrop_hides_behind_the_photo_and_fills_what_it_cannot_show():
    """Behind the photo layer the backdrop changes nothing at the input camera; alone it is the photograph blurred
    (close to it at the input view), and a camera turned 40° away still sees it everywhere (coverage ≥ 0.99),
    far behind the photo layer."""
    H = W = 48
    image = load_image(EXAMPLE_IMAGE, size=(H, W))
    K = intrinsics_from_fov(W, H, fov_y_deg=50.0)
    eye = torch.eye(4)
    depth = _depths(H, W)["tilted"]
    layer, _ = photo_layer(image, depth, eye, K)
    back = backdrop_layer(image, depth, eye, K)
    both = Gaussians(*(torch.cat([getattr(layer, f), getattr(back, f)]) for f in ("means", "quats", "scales",
                                                                                   "opacities", "sh")))
    assert _psnr(render_input_view(both, eye, K, W, H).clamp(0, 1), image) >= 40.0
    alone = render_input_view(back, eye, K, W, H).clamp(0, 1)
    assert 18.0 < _psnr(alone, image) < 35.0  # blurred, not the photograph
    z = back.means[:, 2]
    torch.testing.assert_close(z, torch.full_like(z, BACKDROP_DEPTH * float(depth.max())))
    turned = eye.clone()
    turned[:3, :3] = quat_to_rotmat(torch.tensor([math.cos(math.radians(20)), 0.0, math.sin(math.radians(20)), 0.0]))
    _, alpha, _ = rasterize(back.means, back.quats, back.scales, back.opacities, back.sh, turned[None], K[None], W, H,
                            eps2d=PHOTO_EPS2D, sh_degree=0, render_mode="RGB")
    assert float(alpha.min()) >= 0.99


@pytest.mark.parametrize("H, W", [(256, 256), (200, 300), (176, 320)])
def test_the_backdrop_blur_at_four_samples_per_cell_is_the_full_resolution_one(H, W):
    """``backdrop_colors`` blurs the mirrored photograph at 4 samples per cell instead of every pixel (its kernel
    grew with the photograph: 14.8 s of a 1024² ``generate``): the same cells within a grey level on average and
    a few percent at worst (the sample grid is up to half a sample off the pixel grid)."""
    image = load_image(EXAMPLE_IMAGE, size=(H, W)).numpy().astype(np.float32)
    cell, pad, h, w = _backdrop_grid(W, H)
    fast, exact = backdrop_colors(image, cell, pad, h, w), backdrop_colors_reference(image, cell, pad, h, w)
    assert fast.shape == exact.shape == (h, w, 3)
    err = np.abs(fast - exact)
    assert err.mean() < 0.006 and err.max() < 0.06, (err.mean(), err.max())
    small = load_image(EXAMPLE_IMAGE, size=(48, 48)).numpy().astype(np.float32)  # cells of 3 px: exact itself
    args = _backdrop_grid(48, 48)
    assert np.array_equal(backdrop_colors(small, *args), backdrop_colors_reference(small, *args))
