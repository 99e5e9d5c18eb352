"""Physical camera models of 4D-GRT (Liu et al., "Every Camera Effect, Every Time, All at Once: 4D Gaussian Ray
Tracing for Physics-based Camera Effect Data Generation", arXiv:2509.10759, 2025) for the ray path of the renderer
(:mod:`diff4splat.render.raytrace`) and :func:`diff4splat.render.render_rolling_shutter`: the polynomial fisheye of
Blender Cycles (:class:`FisheyePolynomial`), OpenCV's Kannala–Brandt fisheye (:class:`FisheyeKB`), thin-lens depth of
field after PBRT 3rd ed. §6.2.3 (:class:`ThinLens`) and a rolling shutter (:class:`RollingShutter`).

Camera frame: OpenCV (x right, y down, z forward); θ = atan2(‖(x, y)‖, z) ∈ [0, π], so a fisheye wider than 180°
sees points with z < 0. Fisheye maps use the principal point (cx, cy) of K; only :class:`FisheyeKB` uses fx, fy.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras.path import camera_centers
from diff4splat.cameras.rays import camera_rays
from diff4splat.utils.checks import check_number, check_positive_int, check_ranges, ranged
from diff4splat.utils.constants import CAMERA_MODEL

__all__ = ["RAY_CAMERA_MODELS", "FisheyePolynomial", "FisheyeKB", "ThinLens", "RollingShutter", "check_camera",
           "generate_rays", "concentric_disk", "hammersley"]

RAY_CAMERA_MODELS = ("pinhole", "fisheye")
"""Camera models of the ray path: "pinhole" (optionally with :class:`ThinLens`) and "fisheye"
(:class:`FisheyeKB` — the default, equidistant r = f·θ when all k are 0 — or :class:`FisheyePolynomial`)."""

_NEWTON_ITERS = 60


def _smallest_positive_root(coeffs_low_first: list[float]) -> float:
    """Smallest real root > 0 of Σ c_i xⁱ (numpy companion matrix, float64); inf if none."""
    c = list(coeffs_low_first)
    while len(c) > 1 and c[-1] == 0.0:
        c.pop()
    if len(c) < 2:
        return math.inf
    roots = np.roots(c[::-1])
    scale = max(1.0, float(np.abs(roots).max())) if len(roots) else 1.0
    real = [float(r.real) for r in roots if abs(r.imag) <= 1e-9 * scale and r.real > 0]
    return min(real) if real else math.inf


def _solve_increasing(f: Callable[[Tensor], Tensor], df: Callable[[Tensor], Tensor], y: Tensor, hi: float) -> Tensor:
    """x ∈ [0, hi] with f(x) = y for f increasing on [0, hi] (y clamped to [f(0), f(hi)]): Newton steps, bisection
    when a step leaves the bracket, without autograd; a last Newton step with autograd gives dx/dy = 1/f'(x)."""
    with torch.no_grad():
        yd = y.detach()
        lo_b, hi_b = torch.zeros_like(yd), torch.full_like(yd, hi)
        x = torch.clamp(yd / df(torch.zeros_like(yd)).clamp(min=1e-30), max=hi)
        for _ in range(_NEWTON_ITERS):
            fx = f(x) - yd
            lo_b = torch.where(fx < 0, x, lo_b)
            hi_b = torch.where(fx > 0, x, hi_b)
            step = x - fx / df(x).clamp(min=1e-30)
            inside = (step > lo_b) & (step < hi_b)
            x_new = torch.where(inside, step, 0.5 * (lo_b + hi_b))
            if bool(((x_new - x).abs() <= 1e-15 * (1.0 + x.abs())).all()):
                x = x_new
                break
            x = x_new
    return x - (f(x) - y) / df(x).clamp(min=1e-12)


def _polyval(coeffs: tuple[float, ...], x: Tensor) -> Tensor:
    """Σ c_i xⁱ by Horner's rule; coefficients lowest degree first."""
    out = torch.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * x + c
    return out


def _pixel_offsets(pixels: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """(u − cx, v − cy) of pixel positions (..., 2) for intrinsics K (3, 3)."""
    return pixels[..., 0] - K[0, 2], pixels[..., 1] - K[1, 2]


def _direction(theta: Tensor, ex: Tensor, ey: Tensor, rho: Tensor) -> Tensor:
    """Unit camera-frame direction at angle θ from +z with azimuth (ex, ey)/ρ ((0, 0, 1) at ρ = 0)."""
    pos = rho > 0
    safe = torch.where(pos, rho, torch.ones_like(rho))
    s = torch.sin(theta)
    cx = torch.where(pos, ex / safe, torch.zeros_like(ex))
    cy = torch.where(pos, ey / safe, torch.zeros_like(ey))
    return torch.stack([s * cx, s * cy, torch.cos(theta)], dim=-1)


def _radial(points: Tensor, theta_max: float, fn: Callable[[Tensor], Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """fn(θ) of camera-frame points (..., 3), valid (θ < theta_max, not the origin) and ρ (1 where 0)."""
    rho = torch.sqrt(points[..., 0] ** 2 + points[..., 1] ** 2)
    theta = torch.atan2(rho, points[..., 2])  # ∈ [0, π]
    valid = (theta < theta_max) & (points.norm(dim=-1) > 0)
    safe = torch.where(rho > 0, rho, torch.ones_like(rho))
    return fn(torch.where(valid, theta, torch.zeros_like(theta))), valid, safe


@dataclass(frozen=True)
class FisheyePolynomial:
    """Polynomial fisheye lens θ(r) = k0 + k1·r + k2·r² + k3·r³ + k4·r⁴ (4D-GRT, Blender Cycles): r the distance
    of a pixel position from (cx, cy) in pixels (square pixels), θ its ray's angle from the optical axis, radians.

    Attributes:
        k0: must be 0 (r = 0 is the optical axis).  k1: > 0, radians per pixel.  k2, k3, k4: radians per pixel^n.
        r_max: (derived) largest valid radius, pixels: the first turning point θ'(r) = 0 or where θ reaches π.
        theta_max: (derived) θ(r_max) ≤ π; the field of view is 2·theta_max. Pixels beyond r_max get no ray,
            points beyond theta_max do not project.

    Raises:
        ValueError: naming the field: a non-finite coefficient, k0 ≠ 0 or k1 ≤ 0.
    """

    k0: float = ranged(0.0, check_number)
    k1: float = ranged(0.0, check_number)
    k2: float = ranged(0.0, check_number)
    k3: float = ranged(0.0, check_number)
    k4: float = ranged(0.0, check_number)
    r_max: float = field(init=False, repr=False, compare=False)
    theta_max: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_ranges("FisheyePolynomial", self)
        if self.k0 != 0.0:
            raise ValueError(f"FisheyePolynomial.k0 must be 0 (r = 0 is the optical axis), got {self.k0!r}")
        if not self.k1 > 0:
            raise ValueError(f"FisheyePolynomial.k1 must be > 0 radians/pixel, got {self.k1!r}")
        c = self.coeffs
        r_turn = _smallest_positive_root([c[1], 2 * c[2], 3 * c[3], 4 * c[4]])
        r_pi = _smallest_positive_root([c[0] - math.pi, *c[1:]])
        r_max = min(r_turn, r_pi)
        object.__setattr__(self, "r_max", r_max)
        object.__setattr__(self, "theta_max", min(math.pi, float(np.polyval(c[::-1], r_max))))

    @property
    def coeffs(self) -> tuple[float, float, float, float, float]:
        """(k0, k1, k2, k3, k4)."""
        return (self.k0, self.k1, self.k2, self.k3, self.k4)

    def theta(self, r: Tensor) -> Tensor:
        """Forward lens map θ(r), radians, for radii r (...) in pixels (valid for r ≤ r_max)."""
        return _polyval(self.coeffs, r)

    def dtheta(self, r: Tensor) -> Tensor:
        """θ'(r) = k1 + 2k2·r + 3k3·r² + 4k4·r³, radians per pixel."""
        return _polyval((self.k1, 2 * self.k2, 3 * self.k3, 4 * self.k4), r)

    def radius(self, theta: Tensor) -> Tensor:
        """Inverse map r(θ), pixels, for θ (...) radians clamped to [0, theta_max]; differentiable."""
        return _solve_increasing(self.theta, self.dtheta, theta.clamp(0.0, self.theta_max), self.r_max)

    def unproject(self, pixels: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame unit directions (..., 3) of pixel positions (..., 2) for K (3, 3), and valid (...) bool
        (r ≤ r_max; invalid rays get a finite dummy direction)."""
        ex, ey = _pixel_offsets(pixels, K)
        r = torch.sqrt(ex * ex + ey * ey)
        valid = r <= self.r_max
        theta = self.theta(torch.where(valid, r, torch.zeros_like(r)))
        return _direction(theta, ex, ey, r), valid

    def project(self, points: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """Pixel positions (..., 2) = c + r(θ)·(x, y)/ρ of camera-frame points (..., 3), metres, and valid (...) bool
        (θ < theta_max, not the origin)."""
        r, valid, safe = _radial(points, self.theta_max, self.radius)
        return torch.stack([K[0, 2] + r * points[..., 0] / safe, K[1, 2] + r * points[..., 1] / safe], -1), valid


@dataclass(frozen=True)
class FisheyeKB:
    """OpenCV fisheye (``cv::fisheye::projectPoints``, θ extended past 90°) / Kannala–Brandt lens (TPAMI 2006, eq. 6):
    θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸), pixel = (fx·θ_d·x/ρ + cx, fy·θ_d·y/ρ + cy), ρ = ‖(x, y)‖; all k = 0 is the
    equidistant fisheye r = f·θ. Unprojection inverts θ_d(θ) by Newton.

    Attributes:
        k1, k2, k3, k4: distortion coefficients (dimensionless).
        theta_max: (derived) first root of dθ_d/dθ, capped at π, radians.
        theta_d_max: (derived) θ_d(theta_max); pixels with ‖((u−cx)/fx, (v−cy)/fy)‖ beyond it get no ray.

    Raises:
        ValueError: naming the field: a non-finite coefficient.
    """

    k1: float = ranged(0.0, check_number)
    k2: float = ranged(0.0, check_number)
    k3: float = ranged(0.0, check_number)
    k4: float = ranged(0.0, check_number)
    theta_max: float = field(init=False, repr=False, compare=False)
    theta_d_max: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_ranges("FisheyeKB", self)
        x_turn = _smallest_positive_root([1.0, 3 * self.k1, 5 * self.k2, 7 * self.k3, 9 * self.k4])
        theta_max = min(math.pi, math.sqrt(x_turn))
        object.__setattr__(self, "theta_max", theta_max)
        t2 = theta_max * theta_max
        object.__setattr__(self, "theta_d_max", theta_max * float(np.polyval(
            [self.k4, self.k3, self.k2, self.k1, 1.0], t2)))

    def distort(self, theta: Tensor) -> Tensor:
        """θ_d(θ) (...) → (...), radians (valid for θ ≤ theta_max)."""
        return theta * _polyval((1.0, self.k1, self.k2, self.k3, self.k4), theta * theta)

    def ddistort(self, theta: Tensor) -> Tensor:
        """dθ_d/dθ = 1 + 3k1θ² + 5k2θ⁴ + 7k3θ⁶ + 9k4θ⁸."""
        return _polyval((1.0, 3 * self.k1, 5 * self.k2, 7 * self.k3, 9 * self.k4), theta * theta)

    def undistort(self, theta_d: Tensor) -> Tensor:
        """θ(θ_d) by safeguarded Newton iteration on [0, theta_max] (θ_d clamped to [0, theta_d_max])."""
        return _solve_increasing(self.distort, self.ddistort, theta_d.clamp(0.0, self.theta_d_max), self.theta_max)

    def unproject(self, pixels: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame unit directions (..., 3) of pixels (..., 2) for K (3, 3), valid if θ_d ≤ theta_d_max."""
        ex, ey = _pixel_offsets(pixels, K)
        mx, my = ex / K[0, 0], ey / K[1, 1]
        theta_d = torch.sqrt(mx * mx + my * my)
        valid = theta_d <= self.theta_d_max
        theta = self.undistort(torch.where(valid, theta_d, torch.zeros_like(theta_d)))
        return _direction(theta, mx, my, theta_d), valid

    def project(self, points: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """Pixel positions (..., 2) of camera-frame points (..., 3) and validity (θ < theta_max)."""
        td, valid, safe = _radial(points, self.theta_max, self.distort)
        u = K[0, 0] * td * points[..., 0] / safe + K[0, 2]
        v = K[1, 1] * td * points[..., 1] / safe + K[1, 2]
        return torch.stack([u, v], dim=-1), valid


def hammersley(n: int, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> Tensor:
    """Centred 2-D Hammersley points ((i + ½)/n, φ₂(i) + ½/n), i < n, φ₂ the base-2 radical inverse: (n, 2) in
    (0, 1)² on ``device`` (PBRT 3rd ed. §7.4.1)."""
    i = torch.arange(n, dtype=torch.int64, device=device)
    inv = torch.zeros(n, dtype=torch.float64, device=device)
    bits, scale = i.clone(), 0.5
    while bool((bits > 0).any()):
        inv = inv + (bits & 1).double() * scale
        bits, scale = bits >> 1, scale * 0.5
    pts = torch.stack([(i.double() + 0.5) / n, (inv + 0.5 / n) % 1.0], dim=-1)
    return pts.to(dtype)


def concentric_disk(u: Tensor) -> Tensor:
    """Shirley–Chiu concentric, area-preserving map of the unit square onto the unit disk (PBRT 3rd ed. §13.6.2):
    (..., 2) in [0, 1]² → (..., 2) with ‖·‖ ≤ 1."""
    a, b = 2.0 * u[..., 0] - 1.0, 2.0 * u[..., 1] - 1.0
    first = a.abs() > b.abs()
    safe_a = torch.where(a == 0, torch.ones_like(a), a)
    safe_b = torch.where(b == 0, torch.ones_like(b), b)
    r = torch.where(first, a, b)
    phi = torch.where(first, (math.pi / 4) * b / safe_a, math.pi / 2 - (math.pi / 4) * a / safe_b)
    zero = (a == 0) & (b == 0)
    r = torch.where(zero, torch.zeros_like(r), r)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], dim=-1)


@dataclass(frozen=True)
class ThinLens:
    """Thin-lens depth of field (PBRT 3rd ed. §6.2.3; 4D-GRT): each pixel is the mean of ``spp`` rays from points of
    the aperture disk (camera frame, z = 0) through the point where its pinhole ray meets z = focus_distance. A point
    at depth z spreads over a disk of radius f·A·|1/z − 1/z_f| pixels (f the focal length in pixels).

    Attributes:
        aperture_radius: A, metres, ≥ 0 (0 = pinhole).
        focus_distance: z_f, metres, > 0.
        spp: samples per pixel, ≥ 1: the concentric map of ``spp`` centred Hammersley points, the same for every
            pixel (spp = 1 is the lens centre).

    Raises:
        ValueError: naming the field: a non-finite or negative aperture, focus ≤ 0, spp not an int ≥ 1.
    """

    aperture_radius: float
    focus_distance: float
    spp: int = 16

    def __post_init__(self) -> None:
        check_number("ThinLens.aperture_radius", self.aperture_radius, lo=0, what="metres")
        check_number("ThinLens.focus_distance", self.focus_distance, lo=0, lo_open=True, what="metres")
        check_positive_int("ThinLens.spp", self.spp)

    def aperture_samples(self, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> Tensor:
        """(spp, 2) lens points (x, y) in the camera frame, metres, inside the aperture disk."""
        return self.aperture_radius * concentric_disk(hammersley(self.spp, torch.float64, device)).to(dtype)


@dataclass(frozen=True)
class RollingShutter:
    """Rolling-shutter readout, top row first (4D-GRT): row i of H is captured at t0 + (i + ½)/H · duration, with
    t0 = t_frame − duration/2 (``anchor="center"``) or t_frame (``"start"``), clamped to [0, 1]. Rows are rendered in
    ``chunks`` contiguous bands (band k = rows ⌊kH/n⌋ … ⌊(k+1)H/n⌋ − 1), each at the mean time of its rows:
    1 chunk is a global shutter, None (H chunks) is exact per row.

    Attributes:
        duration: readout time from first to last row, clip-time units, in [0, 1].
        chunks: row bands, int ≥ 1, or None for one per row.
        anchor: "center" or "start".

    Raises:
        ValueError: naming the field: duration not in [0, 1], chunks not an int ≥ 1 (or above the image height,
            in :meth:`row_bands`), unknown anchor.
    """

    duration: float
    chunks: int | None = None
    anchor: str = "center"

    def __post_init__(self) -> None:
        check_number("RollingShutter.duration", self.duration, lo=0, hi=1, what="clip-time units")
        if self.chunks is not None:
            check_positive_int("RollingShutter.chunks", self.chunks)
        if self.anchor not in ("center", "start"):
            raise ValueError(f"RollingShutter.anchor must be 'center' or 'start', got {self.anchor!r}")

    def start_time(self, t_frame: float) -> float:
        """t0 of the readout of a frame at clip time ``t_frame`` (unclamped)."""
        return float(t_frame) - (0.5 * self.duration if self.anchor == "center" else 0.0)

    def row_times(self, height: int, t_frame: float, device: torch.device | str = "cpu") -> Tensor:
        """(H,) float64 capture time of every row, clip units in [0, 1], on ``device``."""
        i = torch.arange(height, dtype=torch.float64, device=device)
        return (self.start_time(t_frame) + (i + 0.5) / height * self.duration).clamp(0.0, 1.0)

    def row_bands(self, height: int) -> list[tuple[int, int]]:
        """Row ranges [r0, r1) of the chunks, top to bottom; ValueError if ``chunks`` > height."""
        n = height if self.chunks is None else self.chunks
        if n > height:
            raise ValueError(f"RollingShutter.chunks must be <= the image height {height}, got {n}")
        edges = [k * height // n for k in range(n + 1)]
        return [(edges[k], edges[k + 1]) for k in range(n)]

    def band_times(self, height: int, t_frame: float) -> list[float]:
        """Clip time of each band of :meth:`row_bands`: the mean of its rows' times, clamped to [0, 1]."""
        t0 = self.start_time(t_frame)
        return [min(1.0, max(0.0, t0 + (r0 + r1) / (2.0 * height) * self.duration))
                for r0, r1 in self.row_bands(height)]


def check_camera(camera_model: str, camera_params: object) -> object:
    """Validate a (camera_model, camera_params) pair of the ray path and return the effective params: ("pinhole",
    None | ThinLens) or ("fisheye", None → FisheyeKB() | FisheyeKB | FisheyePolynomial).

    Raises:
        ValueError: unknown ``camera_model``, params of the wrong type (a RollingShutter points to
            ``render_rolling_shutter``).
    """
    if camera_model not in RAY_CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {RAY_CAMERA_MODELS}, got {camera_model!r}")
    if isinstance(camera_params, RollingShutter):
        raise ValueError("camera_params=RollingShutter needs the scene at several times: use "
                         "diff4splat.render.render_rolling_shutter(scene, cameras, shutter)")
    ok = {"pinhole": (ThinLens,), "fisheye": (FisheyeKB, FisheyePolynomial)}[camera_model]
    if camera_params is None:
        return FisheyeKB() if camera_model == "fisheye" else None
    if not isinstance(camera_params, ok):
        names = " or ".join(c.__name__ for c in ok)
        raise ValueError(f"camera_params for camera_model={camera_model!r} must be None or {names}, "
                         f"got {type(camera_params).__name__}")
    return camera_params


def generate_rays(
    viewmats: Tensor,  # (C, 4, 4) world-to-camera
    Ks: Tensor,  # (C, 3, 3) pixels
    width: int,
    height: int,
    camera_model: str = CAMERA_MODEL,
    camera_params: object = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """World-frame rays of every pixel (centre (j + ½, i + ½)) for a camera model of the ray path: pinhole
    (:func:`~diff4splat.cameras.camera_rays`, S = 1); fisheye (the lens's ``unproject``, S = 1); pinhole +
    :class:`ThinLens` (S = spp rays from lens points l towards the pinhole ray's point at depth z_f:
    o = −Rᵀt + Rᵀl, d = Rᵀ normalise(p_f − l)).

    Returns:
        origins (C, H, W, S, 3) metres, dirs (C, H, W, S, 3) unit world vectors, valid (C, H, W, S) bool.

    Raises:
        ValueError: as :func:`check_camera`.
    """
    params = check_camera(camera_model, camera_params)
    dtype, C, dev = viewmats.dtype, viewmats.shape[0], viewmats.device
    R = viewmats[:, :3, :3]
    centres = camera_centers(viewmats)  # (C, 3)
    if params is None:
        o, d = camera_rays(viewmats, Ks, width, height)
        return o[:, :, :, None], d[:, :, :, None], torch.ones(C, height, width, 1, dtype=torch.bool, device=dev)
    if isinstance(params, ThinLens):
        eye = torch.eye(4, dtype=dtype, device=dev).expand(C, 4, 4)
        _, d_pin = camera_rays(eye, Ks, width, height)  # (C, H, W, 3) camera frame, z > 0
        lens = params.aperture_samples(dtype, dev)  # (S, 2)
        lens3 = torch.cat([lens, torch.zeros_like(lens[:, :1])], dim=-1)  # (S, 3)
        p_f = d_pin * (params.focus_distance / d_pin[..., 2:3])
        d_cam = p_f[:, :, :, None, :] - lens3  # (C, H, W, S, 3)
        d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
        dirs = torch.einsum("cji,chwsj->chwsi", R, d_cam)
        origins = centres[:, None, None, None, :] + torch.einsum("cji,sj->csi", R, lens3)[:, None, None]
        valid = torch.ones(dirs.shape[:-1], dtype=torch.bool, device=dev)
        return origins.expand_as(dirs), dirs, valid
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=dev) + 0.5,
                          torch.arange(width, dtype=dtype, device=dev) + 0.5, indexing="ij")
    pix = torch.stack([u, v], dim=-1)  # (H, W, 2)
    dirs, valid = [], []
    for c in range(C):
        d_cam, ok = params.unproject(pix, Ks[c].to(dtype))
        dirs.append(d_cam @ R[c])  # Rᵀ d as a row-vector product
        valid.append(ok)
    dirs = torch.stack(dirs)[:, :, :, None]
    return centres[:, None, None, None, :].expand_as(dirs), dirs, torch.stack(valid)[..., None]
