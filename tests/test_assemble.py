"""The generated frames' pixel footprint (diff4splat/assembly/assemble.py ``pixel_footprint``,
diff4splat/assembly/photo.py ``pixel_disks``): a source frame's disks rendered alone at its own camera cover it edge to
edge and reproduce its colours, where the LDRM's own footprint of a small model leaves most of it to what lies behind;
disks on their rays, facing their camera, σ in pixels at that camera; ``assemble_scene`` changes nothing else."""
from pathlib import Path

import pytest
import torch
from helpers import EXAMPLE_IMAGE

from diff4splat.assembly.assemble import GENERATED_SCALE_PX, assemble_scene, pixel_footprint, to_gaussians
from diff4splat.assembly.photo import PHOTO_EPS2D, PHOTO_OPACITY, THICKNESS, pixel_disks
from diff4splat.cameras import CameraPath, camera_rays, intrinsics_from_fov, make_trajectory
from diff4splat.io import load_image
from diff4splat.render import rasterize
from diff4splat.scene.gaussians import sh0_to_rgb
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat
from models.ldrm import LDRMOutput

TEXTURE = Path(__file__).resolve().parent.parent / "data_prep" / "textures" / "grass.png"  # fine detail
H, W = 32, 48


def _cameras(S: int) -> tuple[torch.Tensor, torch.Tensor]:
    """S cameras 2 m from the origin, rotated about y by 0, 0.35, 0.7… rad: (S, 4, 4) viewmats, (S, 3, 3) Ks."""
    viewmats = torch.eye(4, device="cpu").repeat(S, 1, 1)
    for s in range(S):
        axis, angle = torch.tensor([0.0, 1.0, 0.0], device="cpu"), torch.tensor(0.35 * s, device="cpu")
        R = quat_to_rotmat(axis_angle_to_quat(axis, angle))
        viewmats[s, :3, :3] = R
        viewmats[s, :3, 3] = torch.tensor([0.1 * s, 0.0, 2.0], device="cpu")
    return viewmats, intrinsics_from_fov(W, H, fov_y_deg=50.0).repeat(S, 1, 1)


def _ldrm_out(S: int, colors: torch.Tensor, seed: int = 0) -> LDRMOutput:
    """LDRM maps (1, S, H, W, ·) with ``colors`` (S, H, W, 3) and the footprint a small LDRM learns: low opacities,
    random small scales and rotations; ray distances about 2 m with a depth step."""
    g = torch.Generator().manual_seed(seed)
    xx = torch.linspace(-1, 1, W, device="cpu").expand(S, H, W)
    distance = 2.0 + 0.3 * xx + 0.5 * (xx > 0.3).float() + 0.05 * torch.rand(S, H, W, generator=g, device="cpu")
    quats = torch.nn.functional.normalize(torch.randn(S, H, W, 4, generator=g, device="cpu"), dim=-1)
    scales = 0.004 * torch.rand(1, S, H, W, 3, generator=g, device="cpu") + 1e-4
    opacities = 0.2 * torch.rand(1, S, H, W, generator=g, device="cpu")
    return LDRMOutput(distance=distance[None], scales=scales, quats=quats[None], opacities=opacities,
                      colors=colors[None])


def _render_alone(g, viewmat, K, up: int = 1):
    """Render at the frame's camera, magnified ``up`` times (K and size scaled: the output at a higher resolution
    than the model's frames, as `generate` renders them)."""
    Ku = K.clone()
    Ku[:2] *= up
    rgb, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, viewmat[None], Ku[None], up * W, up * H,
                              eps2d=PHOTO_EPS2D, sh_degree=0, render_mode="RGB")
    return rgb[0], alpha[0, ..., 0]


@pytest.mark.parametrize("photo", ["chelsea", "grass"])
def test_a_source_frames_disks_cover_it_and_reproduce_its_colours_at_its_own_camera(photo):
    """Each source frame's disks alone at its own camera: alpha ≥ 0.98 on every pixel off the 2-pixel border, at
    the frame's resolution and magnified 4× (as a 64² frame in a 256² output: σ = 0.5 px left 0.87 at the corners
    there), colours ≥ 24 dB against the frame (24.9–25.4 here; 29–30 with σ = 0.5 px, which left the holes); the
    LDRM footprint they replace (a small LDRM's low opacities) covers a tenth of the frame and scores ~7 dB."""
    image = load_image(EXAMPLE_IMAGE if photo == "chelsea" else TEXTURE, size=(H, W))
    S = 3
    colors = torch.stack([image, image.flip(1), image.flip(0)])  # (S, H, W, 3) a different frame per camera
    viewmats, Ks = _cameras(S)
    gaussians, *_ = to_gaussians(_ldrm_out(S, colors), viewmats, Ks)
    disks = pixel_footprint(gaussians, viewmats, Ks, W, H)
    for s in range(S):
        own = torch.arange(s * H * W, (s + 1) * H * W)
        rgb, alpha = _render_alone(disks.select(own), viewmats[s], Ks[s])
        assert float(alpha[2:-2, 2:-2].min()) >= 0.98, s
        psnr = float(-10 * torch.log10(((rgb[2:-2, 2:-2].clamp(0, 1) - colors[s, 2:-2, 2:-2]) ** 2).mean()))
        assert psnr >= 24.0, (s, psnr)
        _, alpha4 = _render_alone(disks.select(own), viewmats[s], Ks[s], up=4)
        assert float(alpha4[8:-8, 8:-8].min()) >= 0.98, s
        rgb_ldrm, alpha_ldrm = _render_alone(gaussians.select(own), viewmats[s], Ks[s])
        assert float(alpha_ldrm.mean()) < 0.5
        assert float(-10 * torch.log10(((rgb_ldrm.clamp(0, 1) - colors[s]) ** 2).mean())) < psnr - 5


def test_pixel_footprint_keeps_means_and_colours_faces_each_source_camera_and_refuses_bad_input():
    S = 2
    viewmats, Ks = _cameras(S)
    colors = torch.rand(S, H, W, 3, generator=torch.Generator().manual_seed(1))
    gaussians, *_ = to_gaussians(_ldrm_out(S, colors), viewmats, Ks)
    disks = pixel_footprint(gaussians, viewmats, Ks, W, H)
    assert torch.equal(disks.means, gaussians.means) and torch.equal(disks.sh, gaussians.sh)
    assert bool((disks.opacities == PHOTO_OPACITY).all())
    _, dirs = camera_rays(viewmats, Ks, W, H)
    axes = quat_to_rotmat(disks.quats)
    torch.testing.assert_close(axes[:, :, 2], dirs.reshape(-1, 3), atol=1e-5, rtol=0)  # thin axis along the ray
    z = torch.cat([gaussians.means[s * H * W:(s + 1) * H * W] @ viewmats[s, 2, :3] + viewmats[s, 2, 3]
                   for s in range(S)])
    torch.testing.assert_close(disks.scales[:, 0], GENERATED_SCALE_PX * z / Ks[0, 0, 0])  # σ in pixels at its camera
    torch.testing.assert_close(disks.scales[:, 1], GENERATED_SCALE_PX * z / Ks[0, 1, 1])
    torch.testing.assert_close(disks.scales[:, 2], THICKNESS * disks.scales[:, :2].min(-1).values)
    with pytest.raises(ValueError, match="expected 2·31·48 Gaussians"):
        pixel_footprint(gaussians, viewmats, Ks, W, H - 1)
    behind = viewmats.clone()
    behind[1, 2, 3] = -5.0  # the second camera's plane moves past the scene
    with pytest.raises(ValueError, match="in front of its source camera"):
        pixel_footprint(gaussians, behind, Ks, W, H)


def test_pixel_disks_of_several_cameras_are_each_cameras_own():
    """One call for S cameras = S calls for one (camera-major order); means on the pixel-centre rays at the z-depth
    given."""
    viewmats, Ks = _cameras(3)
    Ks[1, 0, 0] *= 1.3  # a different focal length per camera
    z = 1.5 + torch.rand(3, H, W, generator=torch.Generator().manual_seed(2))
    together = pixel_disks(viewmats, Ks, W, H, z, 0.7)
    for s in range(3):
        alone = pixel_disks(viewmats[s:s + 1], Ks[s:s + 1], W, H, z[s:s + 1], 0.7)
        for a, b in zip(together, alone, strict=True):
            torch.testing.assert_close(a[s * H * W:(s + 1) * H * W], b, atol=1e-6, rtol=0)
    means = together[0].reshape(3, H * W, 3)
    cam = torch.einsum("sij,snj->sni", viewmats[:, :3, :3], means) + viewmats[:, None, :3, 3]
    torch.testing.assert_close(cam[..., 2], z.reshape(3, -1), atol=1e-5, rtol=0)
    uv = cam[..., :2] / cam[..., 2:] * torch.stack([Ks[:, 0, 0], Ks[:, 1, 1]], -1)[:, None] + Ks[:, None, :2, 2]
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    torch.testing.assert_close(uv, torch.stack([u, v], -1).reshape(1, -1, 2).expand(3, -1, -1), atol=1e-4, rtol=0)


def test_assemble_scene_footprint_changes_only_the_generated_frames_footprint():
    """``footprint="pixel"``: the photo layer, the backdrop, every mean, colour and the deformation as with
    ``"ldrm"``; the generated Gaussians' opacities, rotations and scales those of :func:`pixel_footprint`. An
    unknown footprint is refused."""
    S = 3
    K = intrinsics_from_fov(W, H, fov_y_deg=50.0)
    cams = make_trajectory("orbit", 9, K, W, H)
    sources = torch.tensor([0, 4, 8])
    image = load_image(EXAMPLE_IMAGE, size=(H, W))
    out = _ldrm_out(S, torch.rand(S, H, W, 3, generator=torch.Generator().manual_seed(3)))
    ldrm, _, stats = assemble_scene(out, sources, cams, cams, image, None)
    pixel, _, _ = assemble_scene(out, sources, cams, cams, image, None, footprint="pixel")
    n = stats["photo_gaussians"] + stats["backdrop_gaussians"]
    a, b = ldrm.canonical, pixel.canonical
    assert torch.equal(a.means, b.means) and torch.equal(a.sh, b.sh)
    for f in ("quats", "scales", "opacities"):
        assert torch.equal(getattr(a, f)[:n], getattr(b, f)[:n])
    gaussians, *_ = to_gaussians(out, cams.viewmats[sources], cams.Ks[sources])
    want = pixel_footprint(gaussians.select(torch.arange(H * W, S * H * W)), cams.viewmats[sources[1:]],
                           cams.Ks[sources[1:]], W, H)
    for f in ("quats", "scales", "opacities"):
        torch.testing.assert_close(getattr(b, f)[n:], getattr(want, f))
    torch.testing.assert_close(sh0_to_rgb(b.sh[n:, 0]), out.colors[0, 1:].reshape(-1, 3).clamp(1e-4, 1 - 1e-4))
    with pytest.raises(ValueError, match="footprint must be one of"):
        assemble_scene(out, sources, cams, cams, image, None, footprint="disk")
    assert isinstance(cams, CameraPath)


def test_the_footprint_is_made_beside_its_inputs(device, no_implicit_device):
    """Every tensor on the Gaussians' device (nothing on the default one); the same values as on the CPU."""
    S = 2
    viewmats, Ks = _cameras(S)
    colors = torch.rand(S, H, W, 3, generator=torch.Generator().manual_seed(4), device="cpu")
    cpu, *_ = to_gaussians(_ldrm_out(S, colors), viewmats, Ks)
    got = pixel_footprint(cpu.to(device), viewmats.to(device), Ks.to(device), W, H)
    want = pixel_footprint(cpu, viewmats, Ks, W, H)
    for f in ("means", "quats", "scales", "opacities", "sh"):
        assert getattr(got, f).device.type == device.type
        torch.testing.assert_close(getattr(got, f).cpu(), getattr(want, f), atol=1e-6, rtol=1e-5)
