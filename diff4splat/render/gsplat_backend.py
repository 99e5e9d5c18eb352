"""Optional CUDA backend: gsplat's ``rasterization`` serving :func:`diff4splat.render.rasterize` calls.

With the ``[cuda]`` extra installed (``pip install diff4splat[cuda]``, gsplat ≥ 1.4) and the tensors
on a CUDA device, ``rasterize`` hands the call to gsplat's fused CUDA kernels (Ye et al. 2024,
"gsplat: An Open-Source Library for Gaussian Splatting"); otherwise the PyTorch tile path runs
(docs/DESIGN.md, "The renderer": the PyTorch path stays the CPU path and the reference). The argument
names, shapes, render modes ("RGB", "D", "ED", "RGB+D", "RGB+ED"), rasterize modes and camera model
names are gsplat's own, so they are passed through unchanged after the same input validation.

Known differences of the gsplat backend (gsplat 1.4 CUDA kernels) from the PyTorch path:
  * alpha is clamped to 0.999 (``min(0.999f, …)`` in ``rasterize_to_pixels``), not 0.99 (INRIA);
  * a pixel stops at next_T ≤ 1e-4 (PyTorch path: < 1e-4; differs only on exact ties);
  * gsplat 1.4 assigns tiles by the 3σ radius, so where o·exp(−4.5) ≥ 1/255 (o ≳ 0.35) the faint
    rim between 3σ and the 1/255 contour is dropped, which the PyTorch path renders (it uses the
    opacity-aware box; check the installed gsplat version's ``fully_fused_projection``);
  * computation is float32 (float64 inputs therefore stay on the PyTorch path), float16/bfloat16
    inputs are cast to float32 as in the PyTorch path;
  * ``meta`` holds gsplat's keys (radii, means2d, depths, conics, opacities, tile_width, …, with
    gsplat's packed layout), not ``per_camera``;
  * gradients are gsplat's (float32 atomics: not bitwise reproducible).
"""
from __future__ import annotations

import functools
import importlib.util

import torch
from torch import Tensor

from diff4splat.render.defaults import (
    CAMERA_MODEL,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    RASTERIZE_MODE,
    RENDER_MODE,
    SH_DEGREE,
    TILE_SIZE,
)
from diff4splat.render.stages import compute_dtype, full_precision
from diff4splat.render.validate import validate_inputs

__all__ = ["gsplat_available", "use_gsplat", "rasterize_gsplat"]


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when the ``gsplat`` package can be imported and CUDA is available (checked once)."""
    return importlib.util.find_spec("gsplat") is not None and torch.cuda.is_available()


def use_gsplat(means: Tensor, camera_model: str = CAMERA_MODEL) -> bool:
    """Whether ``rasterize`` should dispatch to gsplat: CUDA tensors that are not float64, a pinhole
    camera (other camera models go through the ray path), and gsplat importable."""
    return (means.is_cuda and means.dtype != torch.float64 and camera_model == "pinhole"
            and gsplat_available())


@full_precision
def rasterize_gsplat(
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
    tile_size: int = TILE_SIZE,
) -> tuple[Tensor, Tensor, dict]:
    """Render with ``gsplat.rasterization``; arguments and outputs as :func:`diff4splat.render.rasterize`.

    Inputs are validated exactly as on the PyTorch path (same ``ValueError`` messages: shapes,
    non-finite values, zero-norm quaternions, modes), then cast to float32 and passed to gsplat with
    autocast off. See the module docstring for the differences of the result.

    Returns:
        render_colors (C, H, W, D[+1]) float32, render_alphas (C, H, W, 1) float32, gsplat's meta dict.

    Raises:
        ValueError: as :func:`diff4splat.render.rasterize`.
        ImportError: gsplat is not installed.
    """
    validate_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=backgrounds,
        render_mode=render_mode, rasterize_mode=rasterize_mode, camera_model=camera_model, tile_size=tile_size,
    )
    from diff4splat.quaternions import quat_normalize

    quat_normalize(quats)  # zero-norm → ValueError naming quats (gsplat would return NaN)
    from gsplat import rasterization

    dtype = compute_dtype(means.dtype)
    cast = lambda t: None if t is None else t.to(dtype)  # noqa: E731
    return rasterization(
        cast(means), cast(quats), cast(scales), cast(opacities), cast(colors), cast(viewmats), cast(Ks), width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, backgrounds=cast(backgrounds),
        render_mode=render_mode, rasterize_mode=rasterize_mode, camera_model=camera_model, tile_size=tile_size,
    )
