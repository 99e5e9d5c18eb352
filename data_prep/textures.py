"""Image textures for synthetic scenes: crops of the photographs bundled in ``data_prep/textures/`` (licences in its
README.md; the only real images training data may use). A texture spec (``kind: "image"``,
:func:`data_prep.synth_world.sample_scene_spec`) places a square crop of one image on a surface: ``file`` (a key of
:data:`IMAGE_TEXTURES`), ``grey`` (one channel), ``crop`` [x0, y0, c] (top-left corner and side, pixels; pixel (i, j)
centred at (j + 0.5, i + 0.5)), ``metres`` (surface length per crop width), ``angle`` (radians), ``tint`` (3,)
multiplying the image, ``noise`` (the per-Gaussian jitter's std). A surface point uv (metres) is rotated by −angle,
divided by ``metres``, folded into the crop by a mirrored repeat and sampled bilinearly from the level of an
area-averaged pyramid whose texels are about one Gaussian spacing wide.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from diff4splat.io.image import read_image

__all__ = ["TEXTURE_DIR", "IMAGE_TEXTURES", "texture_names", "load_texture", "texture_pyramid", "bilinear",
           "mirror", "crop_pixels", "image_albedo"]

TEXTURE_DIR = Path(__file__).resolve().parent / "textures"
"""Folder of the bundled texture images (package data)."""

IMAGE_TEXTURES: dict[str, str] = {
    "brick.png": "brick", "grass.png": "grassy", "gravel.png": "gravel", "camera.png": "photo-printed",
    "coins.png": "coin-patterned", "text.png": "lettered", "color.png": "rainbow", "hubble_deep_field.jpg": "starry",
    "retina.jpg": "veined",
}
"""Bundled texture file → the adjective captions use ("a red brick box", "on a grassy floor")."""


def texture_names() -> list[str]:
    """Sorted file names of the bundled texture images (the keys of :data:`IMAGE_TEXTURES`)."""
    return sorted(IMAGE_TEXTURES)


@functools.lru_cache(maxsize=32)  # 9 bundled images
def load_texture(name: str) -> np.ndarray:
    """The bundled texture ``name``, decoded once per process: read-only (H, W) grey or (H, W, 3) RGB float32 in
    [0, 1]. Raises ValueError: not a bundled texture; FileNotFoundError: missing from the installed package."""
    if name not in IMAGE_TEXTURES:
        raise ValueError(f"texture must be one of {texture_names()}, got {name!r}")
    img = read_image(TEXTURE_DIR / name)  # OpenCV decode, BGR → RGB
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"texture {name} must be 8-bit grey or RGB, got {img.dtype} {img.shape}")
    out = img.astype(np.float32) / 255.0
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=32)  # 9 bundled images
def texture_pyramid(name: str) -> tuple[np.ndarray, ...]:
    """Area-averaged pyramid of :func:`load_texture` (``cv2.INTER_AREA``, halving, sides rounded up) down to 4 px."""
    levels = [load_texture(name)]
    while max(levels[-1].shape[:2]) > 4:
        h, w = levels[-1].shape[:2]
        nxt = cv2.resize(levels[-1], ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
        nxt.flags.writeable = False
        levels.append(nxt)
    return tuple(levels)


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample, (N,) or (N, C) float64, of an (H, W) or (H, W, C) ``image`` at (N,) pixel coordinates
    ``x``, ``y`` (pixel (i, j) centred at (j + 0.5, i + 0.5); beyond the edge centres clamped)."""
    h, w = image.shape[:2]
    xf = np.clip(np.asarray(x, dtype=np.float64) - 0.5, 0, w - 1)
    yf = np.clip(np.asarray(y, dtype=np.float64) - 0.5, 0, h - 1)
    j0, i0 = np.floor(xf).astype(np.int64), np.floor(yf).astype(np.int64)
    j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
    wx, wy = xf - j0, yf - i0
    if image.ndim == 3:
        wx, wy = wx[:, None], wy[:, None]
    img = image.astype(np.float64, copy=False)
    top = img[i0, j0] * (1 - wx) + img[i0, j1] * wx
    bottom = img[i1, j0] * (1 - wx) + img[i1, j1] * wx
    return top * (1 - wy) + bottom * wy


def mirror(s: np.ndarray) -> np.ndarray:
    """Mirrored repeat of crop coordinates: s ↦ 1 − |(s mod 2) − 1| ∈ [0, 1] (identity on [0, 1])."""
    return 1.0 - np.abs(np.mod(s, 2.0) - 1.0)


def crop_pixels(tex: dict[str, Any], uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (x, y), each (N,), in the full-size image of surface coordinates ``uv`` (N, 2) metres:
    R(−angle)·uv / metres, folded by :func:`mirror` into [0, 1]², mapped to the crop [x0, x0 + c] × [y0, y0 + c]."""
    x0, y0, c = tex["crop"]
    ca, sa = math.cos(tex["angle"]), math.sin(tex["angle"])
    u = (uv[:, 0] * ca + uv[:, 1] * sa) / tex["metres"]
    v = (-uv[:, 0] * sa + uv[:, 1] * ca) / tex["metres"]
    return x0 + mirror(u) * c, y0 + mirror(v) * c


def image_albedo(tex: dict[str, Any], uv: np.ndarray, spacing: float) -> np.ndarray:
    """Albedo (N, 3) float64 in [0, 1] (image·tint, before jitter) of an image texture at surface coordinates
    ``uv`` (N, 2) metres, read from pyramid level ⌊log2(``spacing`` / metres · c)⌋, ``spacing`` being the Gaussians'
    distance in metres. Raises ValueError: ``spacing`` ≤ 0 or an unknown ``tex["file"]``."""
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0 metres, got {spacing!r}")
    levels = texture_pyramid(tex["file"])
    texels = spacing / tex["metres"] * tex["crop"][2]
    level = int(np.clip(math.floor(math.log2(max(texels, 1.0))), 0, len(levels) - 1))
    img = levels[level]
    x, y = crop_pixels(tex, uv)
    sx, sy = img.shape[1] / levels[0].shape[1], img.shape[0] / levels[0].shape[0]
    val = bilinear(img, x * sx, y * sy)
    if val.ndim == 1:
        val = val[:, None]
    return val * np.asarray(tex["tint"], dtype=np.float64)
