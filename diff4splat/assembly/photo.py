"""The photo layer: the input photograph as Gaussians at the output resolution, observed rather than generated
(docs/DESIGN.md, "Data flow of generate", step 7; as Splatter Image, Flash3D and 3D photos keep observed pixels).

:func:`photo_layer` puts one thin **front** disk per pixel on its camera ray at a given depth (σ =
:data:`FRONT_SCALE_PX`, colours solved so that the render at the input camera is the photograph,
:func:`refine_colors`) and one **backing** disk per 2×2 block (σ = :data:`BACKING_SCALE_PX`, just behind the
deepest front disk it reaches) that fills the cracks a moving camera opens. Such scenes render with
:data:`PHOTO_EPS2D` = 0.1 px² rather than 3DGS's 0.3, whose bleed would cap the layer's fidelity. The depth is
upsampled from the model resolution with the photograph as the guide (:func:`upsample_depth`, Kopf et al. 2007).
:func:`backdrop_layer` continues the photograph beyond its borders, blurred and far away, behind everything.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.cameras import camera_rays
from diff4splat.render import rasterize
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from diff4splat.scene.quaternions import rotmat_to_quat

__all__ = ["PHOTO_EPS2D", "FRONT_SCALE_PX", "BACKING_SCALE_PX", "BACKING_OFFSET", "PHOTO_OPACITY", "THICKNESS",
           "REFINE_STEPS", "BACKDROP_CELLS", "BACKDROP_EXTEND", "BACKDROP_DEPTH", "pixel_disks", "photo_layer",
           "refine_colors", "upsample_depth", "render_input_view", "backdrop_layer", "layer_sizes",
           "MIN_PHOTO_PSNR_DB", "check_photo_fidelity", "backdrop_colors", "backdrop_colors_reference",
           "BACKDROP_SAMPLES"]

MIN_PHOTO_PSNR_DB = 30.0
"""Least PSNR (dB) of the photo layer rendered alone at the input camera against the photograph; below it frame 0 is
not the photograph (a depth that puts the disks off their pixels) and the scene is refused."""


def check_photo_fidelity(psnr_db: float, what: str = "the photograph") -> None:
    """Refuse a photo layer whose own render at the input camera is below :data:`MIN_PHOTO_PSNR_DB`.

    Raises:
        ValueError: naming the PSNR and the threshold (NaN included).
    """
    if not psnr_db >= MIN_PHOTO_PSNR_DB:
        raise ValueError(f"frame 0 would not be {what}: its photo layer renders it at {psnr_db:.1f} dB PSNR, below "
                         f"{MIN_PHOTO_PSNR_DB:g} dB (a depth far from the photo's surfaces, e.g. a --depth map in "
                         "other units than metres); nothing was written")

PHOTO_EPS2D = 0.1
"""Screen-space dilation, pixels², of scenes with a photo layer (meta.json ``eps2d``)."""
FRONT_SCALE_PX = 0.25
"""In-plane standard deviation of a front disk, pixels at the input camera."""
BACKING_SCALE_PX = 1.2
"""In-plane standard deviation of a backing disk (one per 2×2 pixels), pixels at the input camera."""
BACKING_OFFSET = 0.01
"""The backing layer lies this fraction behind the deepest front disk it can overlap."""
BACKING_REACH = 4
"""Pixels on each side of a backing disk's centre whose front disks it stays behind (its 3σ_eff reach)."""
PHOTO_OPACITY = 0.995
"""Opacity of every photo Gaussian (the renderer clamps alpha at 0.99)."""
THICKNESS = 0.1
"""Standard deviation along the ray as a fraction of the in-plane one."""
REFINE_STEPS = 2
"""Fixed-point steps of :func:`refine_colors` (one render each)."""
BACKDROP_CELLS = 16
"""Backdrop Gaussians per image height (:func:`backdrop_layer`)."""
BACKDROP_EXTEND = 2
"""Image sizes the backdrop reaches beyond each border of the photograph."""
BACKDROP_DEPTH = 1.5
"""The backdrop lies this many times farther than the photo layer's farthest pixel."""


def _check(image: Tensor, depth: Tensor, viewmat: Tensor, K: Tensor) -> tuple[int, int]:
    """Shape and value checks of the layers' inputs; returns (H, W)."""
    if image.dim() != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got {tuple(image.shape)}")
    H, W = image.shape[:2]
    if tuple(depth.shape) != (H, W):
        raise ValueError(f"depth must have shape ({H}, {W}) like the image, got {tuple(depth.shape)}")
    if not bool(torch.isfinite(image).all()) or float(image.min()) < 0 or float(image.max()) > 1:
        raise ValueError("image values must be finite and lie in [0, 1]")
    if not bool(torch.isfinite(depth.detach()).all()) or float(depth.detach().min()) <= 0:
        raise ValueError("depth must be finite and > 0 metres everywhere (fill holes first)")
    if tuple(viewmat.shape) != (4, 4) or tuple(K.shape) != (3, 3):
        raise ValueError(f"viewmat must be (4, 4) and K (3, 3), got {tuple(viewmat.shape)} and {tuple(K.shape)}")
    return H, W


def _disk_frames(dirs: Tensor, cam_x: Tensor) -> Tensor:
    """(N, 4) wxyz rotations: local z along the unit rays ``dirs`` (N, 3), local x along ``cam_x`` made orthogonal."""
    cam_x = cam_x.to(dirs)
    x = cam_x - (dirs * cam_x).sum(-1, keepdim=True) * dirs
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(dirs, x, dim=-1)
    return rotmat_to_quat(torch.stack([x, y, dirs], dim=-1))  # columns: local x, y, z in world coordinates


def pixel_disks(
    viewmats: Tensor,  # (S, 4, 4) world-to-camera (OpenCV)
    Ks: Tensor,  # (S, 3, 3) pixels, at height × width
    width: int,
    height: int,
    z: Tensor,  # (S, height, width) z-depth of each pixel, metres, > 0
    scale_px: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """One thin disk per pixel of S cameras: ``(means, quats, scales)``, (S·height·width, 3 / 4 / 3), camera-major, then
    row-major pixels; ``z``'s dtype and device.

    Pixel (i, j) at z-depth z sits at o + d·z/(d·ẑ) on its pixel-centre ray (o, d), its local z axis along d and x
    along the camera's x axis, in-plane σ = ``scale_px``·z/f (fx along x, fy along y) and :data:`THICKNESS`·min(σx, σy)
    along the ray.
    """
    viewmats, Ks = viewmats.to(z), Ks.to(z)
    origins, dirs = camera_rays(viewmats, Ks, width, height)  # (S, height, width, 3)
    S = z.shape[0]
    origins, dirs = origins.reshape(S, -1, 3), dirs.reshape(S, -1, 3)
    z = z.reshape(S, -1)
    cos = (dirs * viewmats[:, None, 2, :3]).sum(-1)  # d·ẑ: cos of the angle to the optical axis
    means = origins + (z / cos)[..., None] * dirs
    sx, sy = scale_px * z / Ks[:, None, 0, 0], scale_px * z / Ks[:, None, 1, 1]
    cam_x = viewmats[:, None, 0, :3].expand_as(dirs)  # each camera's x axis in world coordinates (first row of R)
    quats = _disk_frames(dirs.reshape(-1, 3), cam_x.reshape(-1, 3))
    scales = torch.stack([sx, sy, THICKNESS * torch.minimum(sx, sy)], dim=-1)
    return means.reshape(-1, 3), quats, scales.reshape(-1, 3)


def render_input_view(layer: Gaussians, viewmat: Tensor, K: Tensor, width: int, height: int,
                      eps2d: float = PHOTO_EPS2D) -> Tensor:
    """The layer (or any Gaussians) rendered at one camera over black: (H, W, 3) colour, linear (not clamped)."""
    out, _, _ = rasterize(layer.means, layer.quats, layer.scales, layer.opacities, layer.sh, viewmat[None], K[None],
                          width, height, eps2d=eps2d, sh_degree=layer.sh_degree, render_mode="RGB")
    return out[0]


@torch.no_grad()
def refine_colors(layer: Gaussians, image: Tensor, viewmat: Tensor, K: Tensor, num_front: int,
                  steps: int = REFINE_STEPS, eps2d: float = PHOTO_EPS2D) -> tuple[Gaussians, list[float]]:
    """Solve the first ``num_front`` Gaussians' colours (one per pixel, row-major) so that the render at the input
    camera equals ``image`` (H, W, 3): the render is linear in the colours and close to the identity, so the fixed-point
    iteration c ← c + (image − R(c)) converges in a few steps.

    Returns:
        The layer with solved front colours, and the input-view PSNR (dB) before each step and after the last
        (``steps + 1`` values).
    """
    H, W = image.shape[:2]
    target = image.reshape(-1, 3).to(layer.means)
    colors = target.clone()
    rest = layer.sh[num_front:]
    history = []
    for k in range(steps + 1):
        sh = torch.cat([rgb_to_sh0(colors)[:, None], rest])
        current = Gaussians(layer.means, layer.quats, layer.scales, layer.opacities, sh)
        rendered = render_input_view(current, viewmat, K, W, H, eps2d).reshape(-1, 3)
        mse = float(((rendered.clamp(0, 1) - target) ** 2).mean())
        history.append(-10 * math.log10(max(mse, 1e-20)))
        if k < steps:
            colors = colors + (target - rendered)
    return current, history


def photo_layer(
    image: Tensor,  # (H, W, 3) in [0, 1]
    depth: Tensor,  # (H, W) z-depth, metres
    viewmat: Tensor,  # (4, 4) world-to-camera of the input camera
    K: Tensor,  # (3, 3) pixels, at H × W
    *,
    refine_steps: int = REFINE_STEPS,
    eps2d: float = PHOTO_EPS2D,
) -> tuple[Gaussians, list[float]]:
    """The photograph (at the output resolution) as H·W front disks then ⌈H/2⌉·⌈W/2⌉ backing disks, each row-major
    (:func:`pixel_disks`, opacity :data:`PHOTO_OPACITY`, SH degree 0), colours solved by :func:`refine_colors`
    (``refine_steps`` 0: the photograph's own) for the dilation ``eps2d`` (pixels²) the scene will be rendered with.

    Returns:
        (float32 Gaussians on ``image``'s device, the input-view PSNR history of :func:`refine_colors`).

    Raises:
        ValueError: shapes that do not match, image values outside [0, 1], depth not finite and positive.
    """
    H, W = _check(image, depth, viewmat, K)
    dev = image.device
    viewmat, K, depth = viewmat.to(dev, torch.float32), K.to(dev, torch.float32), depth.to(dev, torch.float32)
    front = pixel_disks(viewmat[None], K[None], W, H, depth[None], FRONT_SCALE_PX)
    # The backing grid: pixel (i, j) of a half-resolution image is the 2×2 block whose centre is the full-resolution
    # point (2j + 1, 2i + 1), i.e. the intrinsics halved; its depth: the deepest front disk within ±BACKING_REACH.
    W2, H2 = -(-W // 2), -(-H // 2)
    K2 = K.clone()
    K2[:2] = K[:2] / 2
    reach = 2 * BACKING_REACH
    z_back = F.max_pool2d(depth[None, None], reach, stride=2, padding=BACKING_REACH - 1, ceil_mode=True)[0, 0]
    back = pixel_disks(viewmat[None], K2[None], W2, H2, z_back[None, :H2, :W2] * (1 + BACKING_OFFSET),
                       BACKING_SCALE_PX / 2)  # half-resolution pixels: σ = BACKING_SCALE_PX input-camera pixels
    rgb = image.to(torch.float32)
    block = F.avg_pool2d(rgb.permute(2, 0, 1)[None], 2, ceil_mode=True)[0].permute(1, 2, 0)
    sh = rgb_to_sh0(torch.cat([rgb.reshape(-1, 3), block.reshape(-1, 3)]))[:, None]
    n = H * W + H2 * W2
    layer = Gaussians(*(torch.cat([a, b]) for a, b in zip(front, back, strict=True)),
                      torch.full((n,), PHOTO_OPACITY, device=dev), sh)
    return refine_colors(layer, image, viewmat, K, H * W, refine_steps, eps2d)


def _backdrop_grid(width: int, height: int) -> tuple[int, int, int, int]:
    """(cell size px, border px, rows, columns) of the backdrop of a width × height photograph."""
    cell = max(1, round(height / BACKDROP_CELLS))
    pad = BACKDROP_EXTEND * max(height, width)
    return cell, pad, (height + 2 * pad) // cell, (width + 2 * pad) // cell


def layer_sizes(width: int, height: int) -> tuple[int, int]:
    """Gaussian counts of :func:`photo_layer` and :func:`backdrop_layer` for a ``width`` × ``height`` photograph."""
    _, _, rows, cols = _backdrop_grid(width, height)
    return width * height + (-(-height // 2)) * (-(-width // 2)), rows * cols


BACKDROP_SAMPLES = 4
"""Samples per backdrop cell side at which :func:`backdrop_colors` blurs (σ = one cell), so the blur's cost is fixed
per cell."""


def backdrop_colors(host: np.ndarray, cell: int, pad: int, h: int, w: int) -> np.ndarray:
    """The backdrop's (h, w, 3) cell colours of the photograph ``host`` (H, W, 3) float32: mirrored ``pad`` pixels
    beyond each border (BORDER_REFLECT), blurred with σ = ``cell`` pixels and area-averaged to cells, as
    :func:`backdrop_colors_reference` but on the photograph first area-averaged to :data:`BACKDROP_SAMPLES` per cell."""
    H, W = host.shape[:2]
    scale = BACKDROP_SAMPLES / cell
    if scale >= 1:  # cells of ≤ 4 pixels: the full-resolution blur is as cheap
        return backdrop_colors_reference(host, cell, pad, h, w)
    small = cv2.resize(host, (max(1, round(W * scale)), max(1, round(H * scale))), interpolation=cv2.INTER_AREA)
    border = round(pad * scale)
    big = cv2.GaussianBlur(cv2.copyMakeBorder(small, border, border, border, border, cv2.BORDER_REFLECT), (0, 0),
                           float(BACKDROP_SAMPLES))
    used = (min(big.shape[0], round(h * BACKDROP_SAMPLES)), min(big.shape[1], round(w * BACKDROP_SAMPLES)))
    return cv2.resize(big[:used[0], :used[1]], (w, h), interpolation=cv2.INTER_AREA)


def backdrop_colors_reference(host: np.ndarray, cell: int, pad: int, h: int, w: int) -> np.ndarray:
    """:func:`backdrop_colors` at full resolution (its kernel and cost grow with the photograph)."""
    big = cv2.GaussianBlur(cv2.copyMakeBorder(host, pad, pad, pad, pad, cv2.BORDER_REFLECT), (0, 0), float(cell))
    return cv2.resize(big[:h * cell, :w * cell], (w, h), interpolation=cv2.INTER_AREA)


def backdrop_layer(
    image: Tensor,  # (H, W, 3) in [0, 1]
    depth: Tensor,  # (H, W) the photo layer's z-depth, metres
    viewmat: Tensor,  # (4, 4)
    K: Tensor,  # (3, 3) at H × W
) -> Gaussians:
    """The photograph's surroundings: mirrored :data:`BACKDROP_EXTEND` image sizes beyond each border, blurred and
    averaged to cells of H / :data:`BACKDROP_CELLS` pixels (:func:`backdrop_colors`); one disk per cell facing the
    camera on the ray through its centre, at z = :data:`BACKDROP_DEPTH` × the largest ``depth``, σ = 0.8 cell, opacity
    :data:`PHOTO_OPACITY`. Float32 Gaussians, SH degree 0, on ``image``'s device.

    Raises:
        ValueError: as :func:`photo_layer`.
    """
    H, W = _check(image, depth, viewmat, K)
    dev = image.device
    viewmat, K = viewmat.to(dev, torch.float32), K.to(dev, torch.float32)
    cell, pad, h, w = _backdrop_grid(W, H)
    host = image.detach().float().cpu().numpy()  # device: cv2 pads and blurs on the host; moved back below
    small = torch.from_numpy(backdrop_colors(host, cell, pad, h, w)).to(dev)
    Kb = K.clone()
    Kb[0, 2], Kb[1, 2] = K[0, 2] + pad, K[1, 2] + pad
    Kb[:2] = Kb[:2] / cell
    origins, dirs = camera_rays(viewmat[None], Kb[None], w, h)
    origins, dirs = origins[0].reshape(-1, 3), dirs[0].reshape(-1, 3)
    z = BACKDROP_DEPTH * float(depth.detach().max())
    means = origins + (z / (dirs @ viewmat[2, :3]))[:, None] * dirs
    sigma = 0.8 * cell * z / float(torch.minimum(K[0, 0], K[1, 1]))
    n = means.shape[0]
    scales = torch.tensor([sigma, sigma, THICKNESS * sigma], device=dev).expand(n, 3).contiguous()
    colors = small.reshape(-1, 3).clamp(1e-4, 1 - 1e-4)
    return Gaussians(means, _disk_frames(dirs, viewmat[0, :3]), scales, torch.full((n,), PHOTO_OPACITY, device=dev),
                     rgb_to_sh0(colors)[:, None])


UPSAMPLE_SIGMA_SPATIAL = 0.75
"""Spatial standard deviation of :func:`upsample_depth`, in low-resolution cells."""
UPSAMPLE_RADIUS = 2
"""Cells on each side of the nearest one that :func:`upsample_depth` averages."""
UPSAMPLE_SIGMA_COLOR = 0.1
"""Colour standard deviation of :func:`upsample_depth` (RGB distance, photograph in [0, 1])."""
UPSAMPLE_FLOOR = 1e-3
"""Range weight floor of :func:`upsample_depth`: a pixel unlike every nearby cell falls back to spatial weights."""


def upsample_depth(depth: Tensor, guide: Tensor) -> Tensor:
    """Edge-aware upsampling of ``depth`` (h, w), metres, finite and > 0, to the resolution of ``guide`` (H, W, 3) in
    [0, 1], H ≥ h, W ≥ w: joint bilateral upsampling in log-depth (Kopf et al. 2007, Eq. 2). Each output pixel p
    averages the log-depths of the 5×5 cells q around its nearest with weights exp(−‖p − q‖² / 2σ_s²)·(exp(−‖I(p) −
    Ĩ(q)‖² / 2σ_c²) + floor), distances in cells, Ĩ the guide area-averaged over cell q.

    Returns:
        (H, W) z-depth, metres, on ``depth``'s device and dtype (a copy when the sizes are equal).

    Raises:
        ValueError: wrong shapes, a guide smaller than the depth map, or depth not finite and positive.
    """
    if depth.dim() != 2 or guide.dim() != 3 or guide.shape[-1] != 3:
        raise ValueError(f"depth must be (h, w) and guide (H, W, 3), got {tuple(depth.shape)}, {tuple(guide.shape)}")
    if not bool(torch.isfinite(depth.detach()).all()) or float(depth.detach().min()) <= 0:
        raise ValueError("depth must be finite and > 0 metres")
    (h, w), (H, W) = depth.shape, guide.shape[:2]
    if H < h or W < w:
        raise ValueError(f"guide ({H}×{W}) must be at least as large as depth ({h}×{w})")
    if (H, W) == (h, w):
        return depth.clone()
    dev, dt = depth.device, torch.float32
    log_d = depth.to(dt).log()
    guide = guide.to(dev, dt)
    cells = F.interpolate(guide.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)  # (h, w, 3)
    cy = (torch.arange(H, device=dev, dtype=dt) + 0.5) * (h / H) - 0.5  # low-res coordinates of the pixel centres
    cx = (torch.arange(W, device=dev, dtype=dt) + 0.5) * (w / W) - 0.5
    by, bx = cy.round().long(), cx.round().long()
    num = torch.zeros(H, W, device=dev, dtype=dt)
    den = torch.zeros(H, W, device=dev, dtype=dt)
    offsets = range(-UPSAMPLE_RADIUS, UPSAMPLE_RADIUS + 1)
    for dy in offsets:
        qy = (by + dy).clamp(0, h - 1)
        wy = torch.exp(-0.5 * ((cy - qy.to(dt)) / UPSAMPLE_SIGMA_SPATIAL) ** 2)
        for dx in offsets:
            qx = (bx + dx).clamp(0, w - 1)
            wx = torch.exp(-0.5 * ((cx - qx.to(dt)) / UPSAMPLE_SIGMA_SPATIAL) ** 2)
            diff = guide - cells[qy][:, qx]  # (H, W, 3)
            wr = torch.exp(-0.5 * (diff * diff).sum(-1) / UPSAMPLE_SIGMA_COLOR**2) + UPSAMPLE_FLOOR
            wgt = wy[:, None] * wx[None, :] * wr
            num += wgt * log_d[qy][:, qx]
            den += wgt
    return (num / den).exp().to(depth.dtype)
