"""Dense brute-force reference rasterizer and the render pipeline shared with the fast path.

:func:`rasterize_dense` evaluates every Gaussian at every pixel (a (pixels × Gaussians) alpha
matrix), sorts the Gaussians globally by depth and composites them one after the other exactly as
gsplat's ``rasterize_to_pixels`` kernel loop does. It is slow (O(H·W·N) memory) and meant for
tests and tiny images. The fast tile rasterizer (:mod:`diff4splat.render.rasterize`) reuses the
pipeline here (input checks, projection, colours/depth channels, render modes, meta), so the two
differ only in how Gaussians are composited.
"""
from __future__ import annotations

import contextlib
import functools
from typing import Callable

import torch
from torch import Tensor

from diff4splat.gaussians import check_finite
from diff4splat.render.projection import CAMERA_MODELS, T_MIN, project_gaussians, splat_alpha
from diff4splat.render.sh import num_sh_bases, sh_to_color, spherical_harmonics

__all__ = [
    "RENDER_MODES", "RASTERIZE_MODES", "rasterize_dense", "composite_dense", "render_pipeline", "color_features",
    "mode_backgrounds", "expected_depth",
]

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")

# A compositor renders one camera: (means2d (M,2), conics (M,3), opacities (M,), depths (M,),
# feats (M,F), covars2d (M,3), background (F,) or None, width, height, tile_size)
#   -> (colors (H*W, F), alphas (H*W,), info dict).  Only the M visible Gaussians are passed.
Compositor = Callable[..., tuple[Tensor, Tensor, dict]]

LOW_PRECISION = (torch.float16, torch.bfloat16)
"""Input dtypes the renderer computes in float32 instead (outputs are float32 then)."""


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype the renderer computes in for inputs of ``dtype``: float16/bfloat16 → float32, else itself."""
    return torch.float32 if dtype in LOW_PRECISION else dtype


def full_precision(fn: Callable) -> Callable:
    """Decorator: run ``fn`` with autocast disabled (CPU, and CUDA when available).

    Under ``torch.autocast(dtype=bfloat16)`` the projection's matmuls/einsums would run in bfloat16
    (8-bit mantissa: depth errors of metres, wrong culling); the renderer instead computes in the
    dtype of its inputs (float32 for float16/bfloat16 inputs, :func:`compute_dtype`), as gsplat's
    kernels compute in float32 whatever the autocast state.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with contextlib.ExitStack() as stack:
            stack.enter_context(torch.autocast("cpu", enabled=False))
            if torch.cuda.is_available():
                stack.enter_context(torch.autocast("cuda", enabled=False))
            return fn(*args, **kwargs)

    return wrapper


def _check_shape(name: str, t: Tensor, shape: tuple) -> None:
    """Raise ValueError naming ``name`` unless ``t`` has ``shape`` (None = any size)."""
    if not isinstance(t, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    ok = t.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")


def validate_inputs(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
    near_plane, far_plane, eps2d, sh_degree, backgrounds, render_mode, rasterize_mode, camera_model, tile_size,
) -> None:
    """Check every argument of ``rasterize``; raise one ``ValueError`` naming the first bad one."""
    _check_shape("means", means, (None, 3))
    n = means.shape[0]
    _check_shape("quats", quats, (n, 4))
    _check_shape("scales", scales, (n, 3))
    _check_shape("opacities", opacities, (n,))
    if sh_degree is None:
        _check_shape("colors", colors, (n, None))
    else:
        k = num_sh_bases(sh_degree)
        _check_shape("colors", colors, (n, None, 3))
        if colors.shape[1] < k:
            raise ValueError(f"colors holds {colors.shape[1]} SH coefficients, sh_degree={sh_degree} needs {k}")
    _check_shape("viewmats", viewmats, (None, 4, 4))
    c = viewmats.shape[0]
    _check_shape("Ks", Ks, (c, 3, 3))
    if backgrounds is not None:
        _check_shape("backgrounds", backgrounds, (c, colors.shape[-1]))
    for name, val in (("width", width), ("height", height), ("tile_size", tile_size)):
        if not isinstance(val, int) or isinstance(val, bool) or val <= 0:
            raise ValueError(f"{name} must be a positive int, got {val!r}")
    if not 0 <= near_plane < far_plane:
        raise ValueError(f"need 0 <= near_plane < far_plane, got near_plane={near_plane}, far_plane={far_plane}")
    if not eps2d >= 0:
        raise ValueError(f"eps2d must be >= 0 pixels², got {eps2d}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {CAMERA_MODELS} (others are not supported yet), got {camera_model!r}")
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("colors", colors), ("viewmats", viewmats), ("Ks", Ks), ("backgrounds", backgrounds)):
        if t is not None:
            if not t.is_floating_point():
                raise ValueError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")
            check_finite(name, t)


def color_features(
    colors: Tensor,  # (N, D) or (N, K, 3) SH
    means: Tensor,  # (N, 3)
    viewmats: Tensor,  # (C, 4, 4)
    sh_degree: int | None,
) -> Tensor:
    """Per-camera colour features (C, N, D): ``colors`` as given, or with ``sh_degree`` the INRIA
    SH colour max(SH(dir) + 0.5, 0) along dir = mean − camera centre (centre −Rᵀt, gsplat
    ``rasterization``; :mod:`diff4splat.render.sh`)."""
    C, N = viewmats.shape[0], means.shape[0]
    if sh_degree is None:
        return colors[None].expand(C, N, colors.shape[-1])
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    campos = -torch.einsum("cji,cj->ci", R, t)  # camera centres −Rᵀt, (C, 3)
    dirs = means[None] - campos[:, None]  # (C, N, 3)
    return sh_to_color(spherical_harmonics(sh_degree, dirs, colors[None]))


def mode_backgrounds(backgrounds: Tensor | None, render_mode: str, C: int, dtype: torch.dtype) -> Tensor | None:
    """Backgrounds (C, F) of the composited features for ``render_mode``: the colour for "RGB",
    0 for the depth channel ("D"/"ED" → (C, 1) zeros, "RGB+D"/"RGB+ED" → colour then 0); None stays None."""
    if backgrounds is None:
        return None
    bgs = backgrounds.to(dtype)
    if render_mode in ("D", "ED"):
        return bgs.new_zeros(C, 1)
    if render_mode != "RGB":
        return torch.cat([bgs, bgs.new_zeros(C, 1)], dim=-1)
    return bgs


def expected_depth(render_colors: Tensor, render_alphas: Tensor, render_mode: str) -> Tensor:
    """For "ED"/"RGB+ED", divide the accumulated depth (last channel) by max(alpha, 1e-10), so it is
    0 where alpha is 0; other modes are returned unchanged. (C, H, W, F), (C, H, W, 1) → (C, H, W, F)."""
    if render_mode not in ("ED", "RGB+ED"):
        return render_colors
    return torch.cat([render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1)


@full_precision
def render_pipeline(
    compositor: Compositor,
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
    viewmats: Tensor, Ks: Tensor, width: int, height: int, *,
    near_plane: float, far_plane: float, eps2d: float, sh_degree: int | None, backgrounds: Tensor | None,
    render_mode: str, rasterize_mode: str, camera_model: str, tile_size: int,
) -> tuple[Tensor, Tensor, dict]:
    """Validate, project, build per-Gaussian features, composite each camera, apply the render mode.

    Features follow gsplat's ``rasterization``: colours (SH evaluated along mean − camera centre,
    then max(·+0.5, 0)); "D"/"ED" replace them by camera-space depth z, "RGB+D"/"RGB+ED" append it;
    the depth channel's background is 0. "ED" divides the accumulated depth by max(alpha, 1e-10)
    (so it is 0 where alpha is 0). Arguments as in :func:`rasterize_dense`.
    """
    validate_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=backgrounds,
        render_mode=render_mode, rasterize_mode=rasterize_mode, camera_model=camera_model, tile_size=tile_size,
    )
    dtype = compute_dtype(means.dtype)  # autocast is off here (full_precision)
    means, quats, scales, opacities = means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype)
    viewmats, Ks = viewmats.to(dtype), Ks.to(dtype)
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height, near_plane=near_plane,
        far_plane=far_plane, eps2d=eps2d, antialiased=rasterize_mode == "antialiased", camera_model=camera_model,
    )
    C, N = proj.depths.shape
    feats = []
    if render_mode in ("RGB", "RGB+D", "RGB+ED"):
        feats.append(color_features(colors.to(dtype), means, viewmats, sh_degree))
    if render_mode != "RGB":
        feats.append(proj.depths[..., None])
    feats = torch.cat(feats, dim=-1)  # (C, N, F)
    bgs = mode_backgrounds(backgrounds, render_mode, C, dtype)

    out_colors, out_alphas, infos = [], [], []
    for c in range(C):
        vis = torch.nonzero(proj.radii[c] > 0).squeeze(1)
        col, alpha, info = compositor(
            proj.means2d[c, vis], proj.conics[c, vis], proj.opacities[c, vis], proj.depths[c, vis],
            feats[c, vis], proj.covars2d[c, vis], None if bgs is None else bgs[c], width, height, tile_size,
        )
        info["gaussian_ids"] = vis
        out_colors.append(col.reshape(height, width, -1))
        out_alphas.append(alpha.reshape(height, width, 1))
        infos.append(info)
    render_alphas = torch.stack(out_alphas)
    render_colors = expected_depth(torch.stack(out_colors), render_alphas, render_mode)
    meta = {
        "radii": proj.radii, "means2d": proj.means2d, "depths": proj.depths, "conics": proj.conics,
        "opacities": proj.opacities, "compensations": proj.compensations, "covars2d": proj.covars2d,
        "width": width, "height": height, "tile_size": tile_size, "n_cameras": C,
        "tile_width": -(-width // tile_size), "tile_height": -(-height // tile_size),
        "per_camera": infos,
    }
    return render_colors, render_alphas, meta


def composite_dense(
    means2d: Tensor,  # (M, 2)
    conics: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    feats: Tensor,  # (M, F)
    covars2d: Tensor,  # (M, 3), unused: every pixel is evaluated
    background: Tensor | None,  # (F,)
    width: int,
    height: int,
    tile_size: int,  # unused: no tiles
) -> tuple[Tensor, Tensor, dict]:
    """Composite one camera by brute force: all pixels × all Gaussians, sequential in depth.

    Gaussians are sorted by depth (stable, ties keep input order). For each pixel, T = 1; for each
    Gaussian front to back with alpha from :func:`splat_alpha` (0 = skipped): next_T = T·(1 − alpha);
    if next_T < 1e-4 the pixel stops and this Gaussian is not included; otherwise the pixel gains
    alpha·T·feat and T = next_T. Finally colour += T·background, alpha = 1 − T (gsplat
    ``rasterize_to_pixels_fwd``; 3DGS eq. 3).

    Returns:
        colors: (H·W, F), alphas: (H·W,), info {} (no tiles).
    """
    dtype = means2d.dtype
    order = torch.argsort(depths, stable=True)
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype) + 0.5, torch.arange(width, dtype=dtype) + 0.5, indexing="ij"
    )
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)  # (P, 1)
    m2, cn, op, ft = means2d[order], conics[order], opacities[order], feats[order]
    alphas = splat_alpha(px - m2[None, :, 0], py - m2[None, :, 1], cn[None], op[None])  # (P, M)
    n_pix = px.shape[0]
    T = torch.ones(n_pix, dtype=dtype)
    done = torch.zeros(n_pix, dtype=torch.bool)
    out = torch.zeros(n_pix, feats.shape[-1], dtype=dtype)
    for i in range(alphas.shape[1]):
        a = alphas[:, i]
        next_T = T * (1.0 - a)
        live = ~done & (a > 0)
        stop = live & (next_T < T_MIN)
        take = live & ~stop
        done = done | stop
        w = torch.where(take, a * T, torch.zeros_like(a))
        out = out + w[:, None] * ft[i]
        T = torch.where(take, next_T, T)
    if background is not None:
        out = out + T[:, None] * background
    return out, 1.0 - T, {}


def rasterize_dense(
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
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB+ED",
    rasterize_mode: str = "classic",
    camera_model: str = "pinhole",
    tile_size: int = 16,
) -> tuple[Tensor, Tensor, dict]:
    """Brute-force reference renderer; same arguments and outputs as :func:`diff4splat.render.rasterize`.

    Every visible Gaussian is evaluated at every pixel (memory O(H·W·N)) and composited by
    :func:`composite_dense`. Use for tests and tiny images only; ``tile_size`` is accepted for
    signature compatibility and only reported in ``meta``.

    Returns:
        render_colors (C, H, W, D[+1]), render_alphas (C, H, W, 1), meta (see ``rasterize``).

    Raises:
        ValueError: as :func:`diff4splat.render.rasterize`.
    """
    return render_pipeline(
        composite_dense, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=backgrounds,
        render_mode=render_mode, rasterize_mode=rasterize_mode, camera_model=camera_model, tile_size=tile_size,
    )
