"""Numerical constants shared by the renderer, the scene, pruning and IO: the 3DGS thresholds of the INRIA rasterizer
(Kerbl et al. 2023, §4) and gsplat's ``rasterize_to_pixels``."""
from __future__ import annotations

import math

__all__ = ["ALPHA_MAX", "ALPHA_MIN", "T_MIN", "LOG_T_MIN", "OPACITY_EPS", "OPACITY_LOG_FLOOR", "CAMERA_MODEL"]

ALPHA_MAX = 0.99
"""Per-Gaussian alpha is clamped to this (INRIA 3DGS ``min(0.99f, …)``)."""
ALPHA_MIN = 1.0 / 255.0
"""Alpha below which a Gaussian is skipped at a pixel (3DGS, gsplat); also the empty-pixel coverage and the temporal
gate."""
T_MIN = 1e-4
"""Compositing stops before a Gaussian that would bring transmittance below this (3DGS)."""
LOG_T_MIN = math.log(T_MIN)
"""ln :data:`T_MIN`, the same test on log-transmittance (the PyTorch and ray compositors accumulate log T)."""
OPACITY_EPS = 1e-6
"""Opacities are clamped to [OPACITY_EPS, 1 − OPACITY_EPS] before the logit (PLY storage), so it stays finite."""
OPACITY_LOG_FLOOR = 1e-30
"""Opacities are clamped to at least this before ln(o / ALPHA_MIN), so a zero opacity gives a finite value."""

CAMERA_MODEL = "pinhole"
"""Default camera model of the renderer and the ray path (gsplat "pinhole")."""
