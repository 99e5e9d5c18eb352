"""Ray-traced rendering of 3D Gaussians for camera effects (fisheye, thin lens): the ray path, on every device.

The particle response of 3DGRT (Moenne-Loccoz et al., ACM TOG 43(6), 2024, arXiv:2407.07090), as 4D-GRT
(Liu et al., arXiv:2509.10759) uses for camera effects: each Gaussian counts at its maximum along the ray. In the
Gaussian's whitened frame

    o' = S⁻¹Rᵀ(o − μ),   d' = S⁻¹Rᵀd,
    t_max = −(o'·d') / ‖d'‖²                 (ray parameter of the maximum; ‖d‖ = 1, so metres),
    response = exp(−½ ‖d' × o'‖² / ‖d'‖²)    (= exp(−½ min_t ‖o' + t·d'‖²), Lagrange's identity).

The 3DGS rules are the rasterizer's, along t_max (:func:`composite_rays`). Rays are grouped by pixel tiles, each
keeping the Gaussians its ray cone can meet (:func:`cull_tiles`); plain autograd gives the gradients.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from diff4splat.cameras.lenses import RAY_CAMERA_MODELS, ThinLens, check_camera, generate_rays
from diff4splat.cameras.path import camera_centers
from diff4splat.render.settings import (
    CAMERA_MODEL,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    RASTERIZE_MODE,
    RENDER_MODE,
    SH_DEGREE,
    TILE_SIZE,
    RasterSettings,
    compute_dtype,
    expected_depth,
    mode_backgrounds,
    validate_inputs,
)
from diff4splat.render.sh import color_features
from diff4splat.render.tiles import keep_in_graph
from diff4splat.scene.quaternions import quat_to_rotmat
from diff4splat.utils.constants import ALPHA_MAX, ALPHA_MIN, LOG_T_MIN, OPACITY_LOG_FLOOR
from diff4splat.utils.devices import full_precision

__all__ = ["raytrace", "render_rays", "whitening", "ray_gaussian_response", "composite_rays", "support_radius",
           "tile_cones", "cull_tiles", "RAY_PAIR_BUDGET"]

RAY_PAIR_BUDGET = 1 << 20
"""Most (ray, Gaussian) pairs evaluated, and (tile, Gaussian) pairs culled, at once (bounds a batch's memory)."""

RAY_SCALE_FLOOR = 1e-6
"""Smallest standard deviation the ray path whitens by, metres: smaller scales (0: a flat Gaussian) are raised to
it, so 1/s stays finite and float32's ‖d' × o'‖² cannot overflow for offsets up to 10 km."""


def whitening(quats: Tensor, scales: Tensor) -> Tensor:
    """Whitening matrices W = S⁻¹Rᵀ (Σ⁻¹ = WᵀW), (N, 3, 3) 1/metres, from quats (N, 4) wxyz and scales (N, 3)
    metres ≥ 0 (raised to :data:`RAY_SCALE_FLOOR`; no gradient flows to a scale below it)."""
    return quat_to_rotmat(quats).transpose(-1, -2) / scales.clamp_min(RAY_SCALE_FLOOR)[..., :, None]


def ray_gaussian_response(
    origins: Tensor,  # (R, 3) or (1, 3)
    dirs: Tensor,  # (R, 3) unit
    means: Tensor,  # (G, 3)
    whiten: Tensor,  # (G, 3, 3)
) -> tuple[Tensor, Tensor]:
    """3DGRT response of every Gaussian at its maximum along every ray (module docstring; the cross-product form
    keeps float32 accurate far from the origin).

    Returns:
        response (R, G) in (0, 1], t_max (R, G) metres along the (unit) rays (negative: behind the origin).
    """
    m2, t_max = _ray_gaussian_m2(origins, dirs, means, whiten)
    return torch.exp(-0.5 * m2), t_max


def _ray_gaussian_m2(origins: Tensor, dirs: Tensor, means: Tensor, whiten: Tensor) -> tuple[Tensor, Tensor]:
    """Squared Mahalanobis distance ‖d' × o'‖²/‖d'‖² of each ray's closest point and its t_max, (R, G) each."""
    dw, ow = [], []
    for i in range(3):
        w_i = whiten[:, i, :]  # (G, 3): row i of every W
        dw.append(dirs @ w_i.T)  # (R, G)
        ow.append(origins @ w_i.T - (w_i * means).sum(-1))  # (R or 1, G)
    cx = dw[1] * ow[2] - dw[2] * ow[1]
    cy = dw[2] * ow[0] - dw[0] * ow[2]
    cz = dw[0] * ow[1] - dw[1] * ow[0]
    dd = dw[0] * dw[0] + dw[1] * dw[1] + dw[2] * dw[2]
    m2 = (cx * cx + cy * cy + cz * cz) / dd
    t_max = -(ow[0] * dw[0] + ow[1] * dw[1] + ow[2] * dw[2]) / dd
    return m2, t_max


def composite_rays(
    origins: Tensor,  # (R, 3) or (1, 3)
    dirs: Tensor,  # (R, 3)
    means: Tensor,  # (G, 3)
    whiten: Tensor,  # (G, 3, 3)
    opacities: Tensor,  # (G,)
    feats: Tensor,  # (G, F)
    near_plane: float,
    far_plane: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite G Gaussians along R rays by brute force (every pair), 3DGS rules along t_max.

    alpha = min(0.99, o·response), kept iff alpha ≥ 1/255 and near_plane ≤ t_max ≤ far_plane; kept hits sorted by
    (t_max, index); log T before hit i is the exclusive prefix sum of log(1 − alpha); hit i is included iff
    T_i·(1 − alpha_i) ≥ 1e-4 (later hits are dropped too); w_i = alpha_i·T_i.

    Returns:
        colour Σ w·feat (R, F) (no background), alpha Σ w (R,), distance Σ w·t_max (R,) metres.
    """
    m2, t = _ray_gaussian_m2(origins, dirs, means, whiten)
    # alpha ≥ 1/255 ⇔ ½m² ≤ ln(255·o): a slightly loose pre-test on every pair, exact test on the hits
    tau = 2.0 * torch.log(torch.clamp(opacities.detach(), min=OPACITY_LOG_FLOOR) / ALPHA_MIN) * (1 + 1e-6) + 1e-6
    keep = (m2 <= tau) & (t >= near_plane) & (t <= far_plane)
    R, F = dirs.shape[0], feats.shape[-1]
    k = int(keep.sum(1).max()) if keep.numel() else 0
    if k == 0:
        zero = feats.new_zeros(R)
        return feats.new_zeros(R, F), zero, zero
    with torch.no_grad():
        key = torch.where(keep, t, torch.full_like(t, math.inf))
        _, idx = torch.topk(key, k, dim=1, largest=False, sorted=False)
        idx, _ = idx.sort(dim=1)  # input order, so the stable sort below breaks ties by index
        idx = idx.gather(1, torch.argsort(key.gather(1, idx), dim=1, stable=True))
    alpha = torch.clamp(opacities[idx] * torch.exp(-0.5 * m2.gather(1, idx)), max=ALPHA_MAX)  # (R, k)
    hit = keep.gather(1, idx) & (alpha >= ALPHA_MIN)
    a = torch.where(hit, alpha, torch.zeros_like(alpha))
    log_1ma = torch.log1p(-a)
    log_t_next = torch.cumsum(log_1ma, dim=1)
    incl = (log_t_next >= LOG_T_MIN) & hit
    w = torch.where(incl, a * torch.exp(log_t_next - log_1ma), torch.zeros_like(a))  # (R, k)
    f = feats.index_select(0, idx.reshape(-1)).reshape(R, k, F)
    return (w[..., None] * f).sum(1), w.sum(1), (w * t.gather(1, idx)).sum(1)


def support_radius(scales: Tensor, opacities: Tensor) -> Tensor:
    """Radius max(s)·sqrt(2 ln(255·o)) outside which a Gaussian's alpha is below 1/255, metres (alpha ≥ 1/255 needs
    ½m² ≤ ln(255·o), and ‖x − μ‖ ≤ max(s)·m). (N, 3), (N,) → (N,); −1 where o < 1/255."""
    tau = torch.log(torch.clamp(opacities, min=OPACITY_LOG_FLOOR) / ALPHA_MIN)
    r = scales.amax(-1) * torch.sqrt(2.0 * tau.clamp(min=0.0)) * 1.001 + 1e-9
    return torch.where(tau >= 0, r, torch.full_like(r, -1.0))


@torch.no_grad()
def tile_cones(
    dirs: Tensor,  # (R, 3) unit
    valid: Tensor,  # (R,) bool
    tile_of_ray: Tensor,  # (R,) int64
    n_tiles: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Each tile's cone of valid ray directions, float64: axis (T, 3) (normalised mean direction), half-angle β (T,)
    radians (π where the directions cancel), count (T,) of valid rays."""
    d = dirs.double()
    v = valid.double()[:, None]
    axis = d.new_zeros(n_tiles, 3).index_add_(0, tile_of_ray, d * v)
    count = d.new_zeros(n_tiles).index_add_(0, tile_of_ray, v[:, 0])
    norm = axis.norm(dim=-1)
    axis = axis / norm.clamp(min=1e-300)[:, None]
    cos = torch.where(valid, (d * axis[tile_of_ray]).sum(-1), torch.full_like(v[:, 0], 2.0))
    cos_b = d.new_full((n_tiles,), 2.0).scatter_reduce(0, tile_of_ray, cos, "amin")
    beta = torch.acos(cos_b.clamp(-1.0, 1.0))
    beta = torch.where(norm < 1e-9 * count.clamp(min=1), torch.full_like(beta, math.pi), beta)
    return axis, beta, count


def cull_tiles(
    cones: tuple[Tensor, Tensor, Tensor],  # tile_cones of some tiles: (t, 3), (t,), (t,)
    centre: Tensor,  # (3,)
    origin_spread: float,
    means: Tensor,  # (N, 3)
    radii: Tensor,  # (N,)
) -> Tensor:
    """Conservative (tile, Gaussian) visibility: can a valid ray of the tile meet the support sphere? (t, N) bool.

    Rays start within ε = ``origin_spread`` metres of ``centre``, directions within the cone (axis a, half-angle β)
    of :func:`tile_cones`; they can meet the sphere (μ, ρ) only if L = ‖μ − centre‖ ≤ ρ + ε or
    angle(a, μ − centre) ≤ β + asin((ρ + ε)/L). False for a tile without valid rays or a radius < 0. Float64.
    """
    axis, beta, count = cones
    rel = means.double() - centre.double()
    L = rel.norm(dim=-1)
    b = radii.double() + origin_spread
    ang = torch.acos(((rel @ axis.T) / L.clamp(min=1e-300)[:, None]).clamp(-1.0, 1.0)).T  # (t, N)
    half = torch.asin((b / L.clamp(min=1e-300)).clamp(max=1.0))
    hit = (L <= b)[None] | (ang <= beta[:, None] + half[None] + 1e-9)
    return hit & (radii >= 0)[None] & (count > 0)[:, None]


def raytrace(
    means: Tensor,  # (N, 3)
    quats: Tensor,  # (N, 4)
    scales: Tensor,  # (N, 3)
    opacities: Tensor,  # (N,)
    colors: Tensor,  # (N, D) or (N, K, 3) with sh_degree
    viewmats: Tensor,  # (C, 4, 4)
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
    sh_degree: int | None = SH_DEGREE,
    backgrounds: Tensor | None = None,
    render_mode: str = RENDER_MODE,
    rasterize_mode: str = RASTERIZE_MODE,
    camera_model: str = CAMERA_MODEL,
    camera_params: object = None,
    tile_size: int = TILE_SIZE,
    budget: int | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """Render Gaussians by ray tracing; same arguments and outputs as :func:`diff4splat.render.rasterize`.

    Rays come from :func:`diff4splat.cameras.lenses.generate_rays` (pixel centres; ``camera_params.spp`` lens
    samples per pixel for :class:`ThinLens`, else 1), each composited by :func:`composite_rays`; a pixel is the
    mean of its rays. Differences from the rasterizer: the response is exact along the ray (no EWA
    approximation); ``eps2d`` is ignored (a pinhole ray trace matches ``rasterize(..., eps2d=0)`` for small
    Gaussians); hits are kept by t_max ∈ [near_plane, far_plane], not centres by camera z. The depth channel is
    camera z, each hit's o_z + t_max·d_z in camera axes, so "ED" is the expected z-depth of the surface seen.

    Args: as :func:`diff4splat.render.rasterize`, with ``camera_model`` in
    :data:`diff4splat.cameras.lenses.RAY_CAMERA_MODELS`, ``rasterize_mode`` "classic", ``tile_size`` grouping rays
    for culling and ``budget`` the most (ray, Gaussian) pairs per batch (default :data:`RAY_PAIR_BUDGET`).

    Returns render_colors (C, H, W, D[+1]), render_alphas (C, H, W, 1), meta — camera_model, camera_params, width,
    height, n_cameras, tile_size, samples_per_pixel, n_pairs (list of C ints: pairs evaluated).

    Raises:
        ValueError: as ``rasterize``; unknown camera model or mismatched ``camera_params``;
            ``rasterize_mode="antialiased"`` (a screen-space filter with no ray counterpart).
    """
    settings = RasterSettings(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                              backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
                              camera_model=camera_model, tile_size=tile_size, camera_params=camera_params)
    return render_rays(means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings, budget=budget)


@full_precision
def render_rays(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmats: Tensor, Ks: Tensor,
    width: int, height: int, settings: RasterSettings, *, budget: int | None = None,
) -> tuple[Tensor, Tensor, dict]:
    """:func:`raytrace` with its keywords in ``settings`` (what :func:`raytrace` and ``rasterize`` call); the same
    arguments (``budget`` None: :data:`RAY_PAIR_BUDGET`), outputs and errors."""
    params = check_camera(settings.camera_model, settings.camera_params)
    validate_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, settings,
                    camera_models=RAY_CAMERA_MODELS)
    if settings.rasterize_mode != "classic":
        raise ValueError(f"rasterize_mode must be 'classic' on the ray path, got {settings.rasterize_mode!r}")
    near_plane, far_plane, tile_size = settings.near_plane, settings.far_plane, settings.tile_size
    render_mode, camera_model = settings.render_mode, settings.camera_model
    budget = RAY_PAIR_BUDGET if budget is None else int(budget)
    dtype = compute_dtype(means.dtype)  # float16/bfloat16 inputs in float32, autocast off: as the tile path
    means, quats, scales, opacities = means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype)
    viewmats, Ks = viewmats.to(dtype), Ks.to(dtype)
    C = viewmats.shape[0]
    origins, dirs, valid = generate_rays(viewmats, Ks, width, height, camera_model, params)
    S = dirs.shape[3]
    spread = params.aperture_radius if isinstance(params, ThinLens) else 0.0
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        feats = color_features(colors.to(dtype), means, viewmats, settings.sh_degree)  # (C, N, D)
    else:
        feats = means.new_zeros(C, means.shape[0], 0)
    bgs = mode_backgrounds(settings.backgrounds, render_mode, C, dtype)
    whiten = whitening(quats, scales)
    radii = support_radius(scales.detach(), opacities.detach())
    # rays ordered by pixel tile: ray r = (pixel p, sample s), p = i·W + j
    tiles_x = -(-width // tile_size)
    device = means.device
    i, j = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    pix_tile = ((i // tile_size) * tiles_x + j // tile_size).reshape(-1)
    n_tiles = tiles_x * -(-height // tile_size)
    pix_order = torch.argsort(pix_tile, stable=True)
    ray_order = (pix_order[:, None] * S + torch.arange(S, device=device)).reshape(-1)
    tile_of_ray = pix_tile.repeat_interleave(S)[ray_order]
    tile_ends = torch.cumsum(torch.bincount(tile_of_ray, minlength=n_tiles), 0).tolist()
    n_rays = height * width * S
    out_c, out_a, n_pairs = [], [], []
    for c in range(C):
        o_all, d_all = origins[c].reshape(n_rays, 3), dirs[c].reshape(n_rays, 3)
        ok_all = valid[c].reshape(n_rays)
        d_sorted, ok_sorted = d_all[ray_order], ok_all[ray_order]
        centre = camera_centers(viewmats[c])
        cones = tile_cones(d_sorted, ok_sorted, tile_of_ray, n_tiles)
        per_cull = max(1, budget // max(means.shape[0], 1))  # tiles culled at once: (tiles × N) within the budget
        ids, cols, accs, dists, pairs, start = [], [], [], [], 0, 0
        for t in range(n_tiles):
            if t % per_cull == 0:
                vis = cull_tiles(tuple(x[t:t + per_cull] for x in cones), centre.detach(), spread, means.detach(),
                                 radii)
            lo, start = start, tile_ends[t]
            g = torch.nonzero(vis[t % per_cull]).squeeze(1)
            if len(g) == 0:
                continue
            ray_ids = ray_order[lo:start][ok_sorted[lo:start]]
            step = max(1, budget // len(g))
            m, w, o, f = means[g], whiten[g], opacities[g], feats[c, g]
            for b0 in range(0, len(ray_ids), step):
                r = ray_ids[b0:b0 + step]
                orig = o_all[r] if spread > 0 else o_all[r[:1]]
                col, acc, dist = composite_rays(orig, d_all[r], m, w, o, f, near_plane, far_plane)
                ids.append(r), cols.append(col), accs.append(acc), dists.append(dist)
                pairs += len(r) * len(g)
        n_pairs.append(pairs)
        col_img = feats.new_zeros(n_rays, feats.shape[-1])
        acc_img, dist_img = feats.new_zeros(n_rays), feats.new_zeros(n_rays)
        if ids:
            all_ids = torch.cat(ids)
            col_img = col_img.index_copy(0, all_ids, torch.cat(cols))
            acc_img = acc_img.index_copy(0, all_ids, torch.cat(accs))
            dist_img = dist_img.index_copy(0, all_ids, torch.cat(dists))
        # Σ w·t_max along each ray → Σ w·z in this camera, exact per ray: a hit's camera z is o_z + t·d_z for the
        # ray's origin and direction in camera axes (o_z = 0 at a pinhole or a lens's centre plane)
        z_axis = viewmats[c, 2]
        depth_img = (o_all @ z_axis[:3] + z_axis[3]) * acc_img + (d_all @ z_axis[:3]) * dist_img
        out = torch.cat([col_img, depth_img[:, None]], dim=-1) if render_mode != "RGB" else col_img
        if render_mode in ("D", "ED"):
            out = depth_img[:, None]
        if bgs is not None:
            out = out + (1.0 - acc_img)[:, None] * bgs[c]
        anchors = (feats, means, whiten, opacities, viewmats, Ks)  # attached even when camera c sees nothing
        out_c.append(keep_in_graph(out, *anchors).reshape(height, width, S, -1).mean(2))
        out_a.append(keep_in_graph(acc_img, *anchors).reshape(height, width, S, 1).mean(2))
    render_alphas = torch.stack(out_a)
    render_colors = expected_depth(torch.stack(out_c), render_alphas, render_mode)
    meta = {
        "camera_model": camera_model, "camera_params": params, "width": width, "height": height, "n_cameras": C,
        "tile_size": tile_size, "samples_per_pixel": S, "n_pairs": n_pairs,
    }
    return render_colors, render_alphas, meta
