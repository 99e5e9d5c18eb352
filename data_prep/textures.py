"""Image textures for synthetic scenes: crops of the real photographs bundled in ``data_prep/textures/``.

The bundled images (licences in ``data_prep/textures/README.md``) are the only real images training data
may use; the files are listed in :data:`IMAGE_TEXTURES` with the word a caption uses for them.

A texture spec (``kind: "image"``, sampled by :func:`data_prep.synth_world.sample_scene_spec`) places a
square crop of one image on a surface:

- ``file``: the image's file name (a key of :data:`IMAGE_TEXTURES`); ``grey``: whether it has one channel;
- ``crop`` [x0, y0, c]: the crop's top-left corner and side, pixels of the bundled image (pixel (i, j)
  has its centre at (j + 0.5, i + 0.5), as everywhere in diff4splat);
- ``metres``: the surface length one crop width covers (0.5–3 m); ``angle``: rotation of the crop on the
  surface, radians;
- ``tint`` (3,): multiplies the image (grey images: a bright version of the surface's base colour; RGB
  images: white or a light tint); ``noise``: the per-Gaussian jitter's standard deviation.

A surface point with coordinates uv (metres) is rotated by −angle, divided by ``metres`` and folded into
the crop by a **mirrored repeat** (s ↦ 1 − |(s mod 2) − 1|: continuous, no seams, period two crop widths),
then the image is sampled bilinearly there. To avoid aliasing when a Gaussian covers many texels, the
sample is read from the level of an area-averaged image pyramid (``cv2.INTER_AREA``, halving per level)
whose texels are about one Gaussian spacing wide.
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
    """A bundled texture image, decoded once per process (read-only array).

    Args:
        name: file name, one of :func:`texture_names`.

    Returns:
        (H, W) grey or (H, W, 3) RGB float32 in [0, 1] (uint8 / 255, channel order RGB).

    Raises:
        ValueError: ``name`` is not a bundled texture.
        FileNotFoundError: the file is missing from the installed package.
    """
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
    """Area-averaged pyramid of :func:`load_texture`: level 0 the image, each next level half the size
    (``cv2.INTER_AREA``, sides rounded up), down to a longest side of 4 px. Read-only float32 arrays."""
    levels = [load_texture(name)]
    while max(levels[-1].shape[:2]) > 4:
        h, w = levels[-1].shape[:2]
        nxt = cv2.resize(levels[-1], ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
        nxt.flags.writeable = False
        levels.append(nxt)
    return tuple(levels)


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``image`` at continuous pixel coordinates (pixel (i, j) centred at (j + 0.5, i + 0.5)).

    Coordinates beyond the outermost pixel centres clamp to the edge pixels.

    Args:
        image: (H, W) or (H, W, C) float array.
        x, y: (N,) column / row coordinates, pixels.

    Returns:
        (N,) or (N, C) float64.
    """
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
    """Pixel coordinates (x, y), each (N,), in the full-size image of surface coordinates ``uv`` (N, 2) metres.

    (u', v') = R(−angle)·uv / metres, folded by :func:`mirror` into [0, 1]², mapped to the crop
    [x0, x0 + c] × [y0, y0 + c].
    """
    x0, y0, c = tex["crop"]
    ca, sa = math.cos(tex["angle"]), math.sin(tex["angle"])
    u = (uv[:, 0] * ca + uv[:, 1] * sa) / tex["metres"]
    v = (-uv[:, 0] * sa + uv[:, 1] * ca) / tex["metres"]
    return x0 + mirror(u) * c, y0 + mirror(v) * c


def image_albedo(tex: dict[str, Any], uv: np.ndarray, spacing: float) -> np.ndarray:
    """Albedo (N, 3) of an image texture at surface coordinates ``uv`` (N, 2) metres, before jitter.

    The pyramid level L = ⌊log2(texels per Gaussian)⌋ (clamped to the pyramid), texels per Gaussian =
    ``spacing`` / metres · c; coordinates are scaled to that level and sampled by :func:`bilinear`.
    Grey images give grey·tint, RGB images rgb·tint.

    Args:
        tex: an image texture spec (module docstring).
        uv: (N, 2) surface coordinates, metres.
        spacing: distance between neighbouring Gaussians on the surface, metres (> 0).

    Returns:
        (N, 3) float64 in [0, 1] (tint components lie in [0, 1]).

    Raises:
        ValueError: ``spacing`` ≤ 0 or an unknown ``tex["file"]``.
    """
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
