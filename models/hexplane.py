"""HexPlane deformation field of 4D Gaussian Splatting (Wu et al., CVPR 2024, §3.2).

A Gaussian's canonical mean μ and a time t ∈ [0, 1] give a deformation (Δμ, Δq, Δs). The field returns these
tensors only (:meth:`HexPlaneField.forward` at one time, :meth:`HexPlaneField.deformations_at` at T key times); the
``diff4splat`` layer composes them with the canonical Gaussians (:func:`diff4splat.scene.dynamic.compose_deformation`,
:class:`diff4splat.scene.dynamic.DynamicGaussians`; docs/DESIGN.md, "Conventions" and "Layers").
Public reference code: hustvl/4DGaussians ``scene/hexplane.py`` (planes, sampling), ``scene/deformation.py``
(MLP), ``scene/regulation.py`` + ``scene/gaussian_model.py`` (regularisers), defaults from
``arguments/__init__.py`` (``ModelHiddenParams``) overridden by ``arguments/dnerf/dnerf_default.py``.

Pipeline for N points (shapes in comments; F = ``feature_dim``, S = ``len(multires)``, W = ``net_width``):

1. μ (N, 3) metres → box coordinates x = (μ − c)·2/e ∈ [−1, 1]³ (c the centre, e the extent of ``bounds``),
   clamped to [−1, 1] (points outside the box take the border value, as the reference's
   ``padding_mode='border'``); time → 2t − 1 ∈ [−1, 1].
2. Per scale s (spatial resolution × ``multires[s]``, time resolution unchanged): six planes, the pairs of
   ``itertools.combinations(range(4), 2)`` = xy, xz, xt, yz, yt, zt; plane (a, b) has shape
   (1, F, res_b, res_a) and is sampled bilinearly at (coord_a, coord_b) (``grid_sample``,
   ``align_corners=True``, ``padding_mode='border'``); the six (N, F) samples are multiplied (Hadamard).
3. The S products are concatenated → (N, S·F) → trunk Linear(S·F, W) then ``trunk_depth`` × (ReLU, Linear(W, W))
   → three heads ReLU-Linear(W, W)-ReLU-Linear(W, k): Δμ (k = 3, metres), Δq (k = 4, added to (1, 0, 0, 0)),
   Δs (k = 3, log-scale offset).

Initialisation as the reference: spatial planes U(0.1, 0.5), time planes 1 (so a new field's features do not
depend on t), Linear weights Xavier-uniform (gain 1), biases PyTorch's default. **Beyond the reference**, the
last Linear of each head is zero-initialised (weights and bias), so a new field is exactly the identity
(Δμ = 0, Δq = (1, 0, 0, 0), Δs = 0); the reference code does not do this.

Deliberate differences from the reference, all documented where they act:

- **Time coordinate.** The reference feeds t ∈ [0, 1] directly as the grid coordinate in [−1, 1]
  (``gaussian_renderer/__init__.py``: ``time = viewpoint_camera.time``; D-NeRF times are ``time / max_time``),
  so only the upper half of the time axis (rows 12…24 of 25) is ever sampled. We map t → 2t − 1, so the
  whole time axis spans the clip.
- **Box orientation.** The reference's ``set_aabb(xyz_max, xyz_min)`` stores [max, min], so its
  ``normalize_aabb`` maps max → −1 and min → +1 (a mirror image). We map min → −1, max → +1; the function
  class is the same.
- **Rotation.** The reference adds the head output to the canonical quaternion (``apply_rotation=False``);
  we compose normalize(Δq ⊗ q) with Δq = (1, 0, 0, 0) + head (docs/DESIGN.md). Its scale update
  ``log s + Δs`` equals our s·exp(Δs).
- Δopacity and ΔSH heads are not built: the reference has them off in every config (``no_do=True``,
  ``no_dshs=True``).

Parameter count of the default config (:class:`HexPlaneConfig()`): 2,444,170 — planes 2,426,880
(scale 1: 3·32·64² + 3·32·64·25; scale 2: 3·32·128² + 3·32·128·25), trunk 4,160, heads 13,130.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file
from torch import Tensor, nn

from diff4splat.io.atomic import atomic_output_path
from diff4splat.utils.checks import check_finite, check_int, check_number, check_positive_int, is_int
from diff4splat.utils.limits import check_limit

from .deformation import IDENTITY_QUAT
from .pretrained import config_from_dict

__all__ = [
    "HexPlaneConfig",
    "HexPlaneField",
    "sample_plane",
    "plane_tv",
    "time_smoothness",
    "time_l1",
    "save_field",
    "load_field",
    "PLANE_AXES",
    "SPATIAL_PLANES",
    "TIME_PLANES",
    "MIN_EXTENT",
    "FIELD_FORMAT",
    "FIELD_FORMAT_VERSION",
]

PLANE_AXES: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))
"""Coordinate pairs of the six planes (0 = x, 1 = y, 2 = z, 3 = t): xy, xz, xt, yz, yt, zt."""
SPATIAL_PLANES = (0, 1, 3)
"""Indices into :data:`PLANE_AXES` of the spatial planes xy, xz, yz (the reference's ``[0, 1, 3]``)."""
TIME_PLANES = (2, 4, 5)
"""Indices into :data:`PLANE_AXES` of the space-time planes xt, yt, zt (the reference's ``[2, 4, 5]``)."""
MIN_EXTENT = 1e-6
"""Smallest box extent per axis, metres: a degenerate axis (max − min below it) is treated as this wide."""
FIELD_FORMAT = "diff4splat-hexplane"
FIELD_FORMAT_VERSION = 1
_SPATIAL_INIT = (0.1, 0.5)  # reference init_grid_param(a=0.1, b=0.5)
_PLANE_REGS = ("smoothness", "tv")


@dataclass
class HexPlaneConfig:
    """Sizes and regulariser weights of :class:`HexPlaneField` (defaults: the reference's D-NeRF config).

    Attributes:
        feature_dim: F, channels per plane (reference ``kplanes_config['output_coordinate_dim']`` = 32).
        resolution: (x, y, z, t) plane resolution at scale 1, each ≥ 3 (reference [64, 64, 64, 25]).
        multires: spatial resolution multipliers, one scale each (``dnerf_default.py``: [1, 2]); the time
            resolution is the same at every scale, as the reference.
        net_width: W, width of the trunk and heads (reference ``net_width`` = 64).
        trunk_depth: hidden (ReLU, Linear(W, W)) blocks after the first Linear, ≥ 0. The reference's
            ``defor_depth`` D builds max(D − 1, 0) of them; D-NeRF's D = 0 → 0.
        plane_tv_weight: weight of the spatial-plane regulariser (reference 1e-4).
        time_smoothness_weight: weight of the second-difference smoothness of the time planes (reference 1e-2).
        l1_time_planes: weight of mean |1 − plane| of the time planes (reference 1e-4).
        plane_reg: regulariser of the spatial planes under ``plane_tv_weight``. ``"smoothness"`` (default)
            follows 4DGaussians' ``_plane_regulation``, which despite the weight's name applies the
            second-difference ``compute_plane_smoothness`` (:func:`time_smoothness`) to the spatial planes;
            ``"tv"`` is K-Planes' total variation ``compute_plane_tv`` (:func:`plane_tv`).

    Raises:
        ValueError: a field out of range, naming the field and the value.
    """

    feature_dim: int = 32
    resolution: tuple[int, int, int, int] = (64, 64, 64, 25)
    multires: tuple[int, ...] = (1, 2)
    net_width: int = 64
    trunk_depth: int = 0
    plane_tv_weight: float = 1e-4
    time_smoothness_weight: float = 1e-2
    l1_time_planes: float = 1e-4
    plane_reg: str = "smoothness"

    def __post_init__(self) -> None:
        # diff4splat.utils.checks; integers and numbers are stored as Python int / float (the config is saved as JSON)
        for name in ("feature_dim", "net_width"):
            setattr(self, name, check_positive_int(name, getattr(self, name)))
        self.trunk_depth = check_int("trunk_depth", self.trunk_depth, 0)
        self.resolution = tuple(self.resolution) if isinstance(self.resolution, (list, tuple)) else self.resolution
        if not (isinstance(self.resolution, tuple) and len(self.resolution) == 4
                and all(is_int(r) and r >= 3 for r in self.resolution)):
            raise ValueError(f"resolution must be 4 ints >= 3 (x, y, z, t), got {self.resolution!r}")
        self.resolution = tuple(int(r) for r in self.resolution)
        self.multires = tuple(self.multires) if isinstance(self.multires, (list, tuple)) else self.multires
        if not (isinstance(self.multires, tuple) and self.multires
                and all(is_int(m) and m >= 1 for m in self.multires)):
            raise ValueError(f"multires must be a non-empty sequence of positive ints, got {self.multires!r}")
        self.multires = tuple(int(m) for m in self.multires)
        for name in ("plane_tv_weight", "time_smoothness_weight", "l1_time_planes"):
            setattr(self, name, check_number(name, getattr(self, name), lo=0))
        if self.plane_reg not in _PLANE_REGS:
            raise ValueError(f"plane_reg must be one of {_PLANE_REGS}, got {self.plane_reg!r}")

    @property
    def feature_channels(self) -> int:
        """S·F, the trunk's input width (features concatenated over scales)."""
        return self.feature_dim * len(self.multires)

    @property
    def num_parameters(self) -> int:
        """Parameter count of a :class:`HexPlaneField` of this config, in closed form (nothing allocated).

        Σ_scales Σ_planes F·res_a·res_b + trunk (S·F·W + W + depth·(W² + W)) + heads (3·(W² + W) + 10·W + 10);
        2,444,170 for the defaults.
        """
        W, planes = self.net_width, 0
        for mult in self.multires:
            res = [r * mult for r in self.resolution[:3]] + [self.resolution[3]]
            planes += sum(self.feature_dim * res[a] * res[b] for a, b in PLANE_AXES)
        trunk = self.feature_channels * W + W + self.trunk_depth * (W * W + W)
        return planes + trunk + 3 * (W * W + W) + 10 * W + 10


# ---------------------------------------------------------------- pure functions on planes


def sample_plane(plane: Tensor, coords: Tensor) -> Tensor:
    """Bilinear sample of one plane at normalised coordinates (reference ``grid_sample_wrapper``).

    Args:
        plane: (1, C, H, W) feature plane.
        coords: (N, 2) coordinates (u, v) ∈ [−1, 1]: u indexes W (u = −1 the first column, +1 the last),
            v indexes H (``align_corners=True``). Coordinates outside are clamped to the border.

    Returns:
        (N, C) features.
    """
    C = plane.shape[1]
    grid = coords.clamp(-1.0, 1.0).view(1, 1, -1, 2)  # (1, 1, N, 2)
    out = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)  # (1, C, 1, N)
    return out.view(C, -1).transpose(0, 1)


def _check_plane(name: str, plane: Tensor, min_h: int, min_w: int) -> tuple[int, int]:
    if plane.dim() != 4 or plane.shape[-2] < min_h or plane.shape[-1] < min_w:
        raise ValueError(f"{name}: plane must have shape (B, C, H, W) with H >= {min_h}, W >= {min_w}, "
                         f"got {tuple(plane.shape)}")
    return plane.shape[-2], plane.shape[-1]


def plane_tv(plane: Tensor) -> Tensor:
    """K-Planes total variation (reference ``scene/regulation.py`` ``compute_plane_tv``).

    2·(mean over (B, C, H−1, W) of (p[h+1] − p[h])² + mean over (B, C, H, W−1) of (p[w+1] − p[w])²).

    Args:
        plane: (B, C, H, W), H, W ≥ 2.

    Returns:
        scalar Tensor ≥ 0.

    Raises:
        ValueError: another shape.
    """
    _check_plane("plane_tv", plane, 2, 2)
    h_tv = torch.square(plane[..., 1:, :] - plane[..., :-1, :]).mean()
    w_tv = torch.square(plane[..., :, 1:] - plane[..., :, :-1]).mean()
    return 2 * (h_tv + w_tv)


def time_smoothness(plane: Tensor) -> Tensor:
    """Mean squared second difference along H (reference ``compute_plane_smoothness``).

    On a time plane (a, t) of shape (1, C, res_t, res_a) H is the time axis; on a spatial plane (a, b) it is b.

    Args:
        plane: (B, C, H, W), H ≥ 3.

    Returns:
        scalar Tensor ≥ 0: mean over (B, C, H−2, W) of (p[h+2] − 2p[h+1] + p[h])².

    Raises:
        ValueError: another shape.
    """
    _check_plane("time_smoothness", plane, 3, 1)
    first = plane[..., 1:, :] - plane[..., :-1, :]
    return torch.square(first[..., 1:, :] - first[..., :-1, :]).mean()


def time_l1(plane: Tensor) -> Tensor:
    """Mean |1 − plane| (reference ``gaussian_model.py`` ``_l1_regulation``): pulls time planes to 1 (static).

    Args:
        plane: (B, C, H, W).

    Returns:
        scalar Tensor ≥ 0.
    """
    _check_plane("time_l1", plane, 1, 1)
    return torch.abs(1 - plane).mean()


# ---------------------------------------------------------------- the field


def _check_bounds(bounds: Tensor) -> Tensor:
    if not isinstance(bounds, Tensor):  # a nested sequence of numbers: read on the CPU
        bounds = torch.as_tensor(bounds, device="cpu")
    if tuple(bounds.shape) != (2, 3) or not bounds.is_floating_point():
        raise ValueError(f"bounds must be a float tensor of shape (2, 3) = [min, max] metres, "
                         f"got {bounds.dtype} {tuple(bounds.shape)}")
    check_finite("bounds", bounds)
    if bool((bounds[1] < bounds[0]).any()):
        raise ValueError(f"bounds must have max >= min on every axis, got min {bounds[0].tolist()}, "
                         f"max {bounds[1].tolist()}")
    return bounds


def _head(width: int, out: int, device: torch.device) -> nn.Sequential:
    return nn.Sequential(nn.ReLU(), nn.Linear(width, width, device=device), nn.ReLU(),
                         nn.Linear(width, out, device=device))


class HexPlaneField(nn.Module):
    """The HexPlane deformation field (module docstring; reference ``scene/hexplane.py`` +
    ``scene/deformation.py``).

    Args:
        config: sizes and regulariser weights.
        bounds: (2, 3) float tensor [min, max] of the scene box, metres, finite, max ≥ min per axis. An axis
            with max − min < :data:`MIN_EXTENT` (a planar or single-point scene) is treated as
            :data:`MIN_EXTENT` wide about its centre instead of dividing by zero. Stored as the buffer
            ``bounds`` (float32, saved and loaded with the state dict).
        device: where the parameters and ``bounds`` are made (default: ``bounds``' device). The random
            initialisation draws from that device's default generator (``torch.manual_seed`` seeds them all,
            but CUDA draws other numbers than the CPU): to get the same field on every device, make it on the
            CPU and move it (``HexPlaneField(config, bounds, device="cpu").to(dev)``, as ``fit`` does).

    Attributes:
        grids: ``grids[s][i]`` the plane :data:`PLANE_AXES` ``[i]`` of scale s, (1, F, res_b, res_a).
        trunk, d_means_head, d_quats_head, d_scales_head: the MLP (module docstring).

    Raises:
        ValueError: bad ``bounds`` (shape, non-finite, max < min).
    """

    def __init__(self, config: HexPlaneConfig, bounds: Tensor, device: str | torch.device | None = None) -> None:
        super().__init__()
        if not isinstance(config, HexPlaneConfig):
            raise ValueError(f"config must be a HexPlaneConfig, got {type(config).__name__}")
        self.config = config
        bounds = _check_bounds(bounds)
        device = bounds.device if device is None else torch.device(device)
        self.register_buffer("bounds", bounds.detach().to(device=device, dtype=torch.float32).clone())
        self.grids = nn.ModuleList()
        for mult in config.multires:
            res = [r * mult for r in config.resolution[:3]] + [config.resolution[3]]
            planes = nn.ParameterList()
            for a, b in PLANE_AXES:
                p = nn.Parameter(torch.empty(1, config.feature_dim, res[b], res[a], device=device))  # (1, F, rb, ra)
                if b == 3:
                    nn.init.ones_(p)
                else:
                    nn.init.uniform_(p, *_SPATIAL_INIT)
                planes.append(p)
            self.grids.append(planes)
        W = config.net_width
        layers: list[nn.Module] = [nn.Linear(config.feature_channels, W, device=device)]
        for _ in range(config.trunk_depth):
            layers += [nn.ReLU(), nn.Linear(W, W, device=device)]
        self.trunk = nn.Sequential(*layers)
        self.d_means_head = _head(W, 3, device)
        self.d_quats_head = _head(W, 4, device)
        self.d_scales_head = _head(W, 3, device)
        for m in self.modules():  # reference deformation.py initialize_weights: Xavier weights, default biases
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight, gain=1.0)
        for head in (self.d_means_head, self.d_quats_head, self.d_scales_head):  # ours: identity at init
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)

    def normalize(self, means: Tensor) -> Tensor:
        """Box coordinates of ``means`` (N, 3) metres → (N, 3) in [−1, 1] (min → −1, max → +1, clamped).

        ±inf coordinates clamp to the border; an inf·0 that an overflowing box extent (|bounds| near the
        float limit) would give maps to the centre, so the result is always finite for NaN-free means.
        """
        lo, hi = self.bounds[0].to(means.dtype), self.bounds[1].to(means.dtype)
        scale = 2.0 / (hi - lo).clamp_min(MIN_EXTENT)  # (3,), 0 if the extent overflows
        x = (means - (0.5 * lo + 0.5 * hi)) * scale
        return torch.nan_to_num(x, nan=0.0).clamp(-1.0, 1.0)

    def _times(self, t: float | Tensor, n: int, like: Tensor) -> Tensor:
        """(N, 1) grid time coordinates 2t − 1 from a float or a (N,) / 0-d tensor in [0, 1]."""
        if isinstance(t, Tensor):
            if t.dim() == 0:
                t = t.reshape(1).expand(n)
            if tuple(t.shape) != (n,):
                raise ValueError(f"t must be a float or a tensor of shape ({n},) (one per point), "
                                 f"got {tuple(t.shape)}")
            t = t.to(like)
            if n and not bool(((t >= 0) & (t <= 1)).all()):
                raise ValueError(f"t must lie in [0, 1], got values from {float(t.min())} to {float(t.max())}")
            return (2.0 * t - 1.0).unsqueeze(1)
        return like.new_full((n, 1), 2.0 * check_number("t", t, lo=0, hi=1) - 1.0)

    def features(self, means: Tensor, t: float | Tensor) -> Tensor:
        """Plane features of points at time ``t``.

        Args:
            means: (N, 3) canonical means, metres (outside the box, ±inf included: clamped to its border).
            t: time in [0, 1], a float or a (N,) tensor.

        Returns:
            (N, S·F): per scale the product of the six plane samples, scales concatenated.

        Raises:
            ValueError: ``means`` not (N, 3) of the field's dtype or holding NaN (which would crash
                ``grid_sample``'s CPU backward); ``t`` not a float / (N,) tensor in [0, 1].
        """
        if means.dim() != 2 or means.shape[1] != 3 or not means.is_floating_point():
            raise ValueError(f"means must be a float tensor of shape (N, 3), got {means.dtype} {tuple(means.shape)}")
        if means.numel() and bool(torch.isnan(means).any()):  # NaN grid coordinates crash grid_sample's backward
            raise ValueError(f"means contains {int(torch.isnan(means).sum())} NaN value(s)")
        if means.dtype != self.grids[0][0].dtype:
            raise ValueError(f"means must have the field's dtype {self.grids[0][0].dtype}, got {means.dtype}")
        pts = torch.cat([self.normalize(means), self._times(t, means.shape[0], means)], dim=1)  # (N, 4)
        per_scale = []
        for planes in self.grids:
            prod = None
            for (a, b), plane in zip(PLANE_AXES, planes, strict=True):
                s = sample_plane(plane, pts[:, [a, b]])  # (N, F)
                prod = s if prod is None else prod * s
            per_scale.append(prod)
        return torch.cat(per_scale, dim=1)

    def forward(self, means: Tensor, t: float | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Deformation of Gaussians with canonical means ``means`` at time ``t``.

        Args:
            means: (N, 3) canonical means, metres, N ≥ 0.
            t: time in [0, 1], a float or a (N,) tensor.

        Returns:
            d_means (N, 3) metres; d_quats (N, 4) wxyz, unnormalised, (1, 0, 0, 0) + head output (exactly
            the identity at init); d_scales (N, 3) log-scale offsets. Differentiable w.r.t. the parameters
            and ``means`` (zero gradient w.r.t. means outside the box).

        Raises:
            ValueError: as :meth:`features`.
        """
        h = self.trunk(self.features(means, t))  # (N, W)
        d_quats = self.d_quats_head(h) + h.new_tensor(IDENTITY_QUAT)
        return self.d_means_head(h), d_quats, self.d_scales_head(h)

    @torch.no_grad()
    def deformations_at(self, means: Tensor, times: Tensor, chunk: int = 65536) -> tuple[Tensor, Tensor, Tensor]:
        """The deformation of M points at each of T key times, evaluated ``chunk`` points at a time (no gradient).

        The tensors of :class:`~diff4splat.scene.dynamic.DynamicGaussians` (which the caller builds:
        ``DynamicGaussians(canonical, times, *field.deformations_at(canonical.means, times))``).

        Args:
            means: (M, 3) canonical means, metres, on any device and of any float dtype (evaluated on the
                field's device in its dtype), M ≥ 0.
            times: (T,) key times in [0, 1], T ≥ 1 (a tensor on any device, or a sequence of numbers).
            chunk: points per field evaluation (bounds memory), ≥ 1.

        Returns:
            d_means (T, M, 3) metres, d_quats (T, M, 4) wxyz unnormalised, d_scales (T, M, 3) log-scale
            offsets: exactly :meth:`forward` at each key time, on ``means``' device and dtype.

        Raises:
            ValueError: ``times`` not (T,) with T ≥ 1, non-finite or outside [0, 1]; ``chunk`` < 1; ``means``
                not (M, 3) or holding NaN (:meth:`features`).
        """
        check_positive_int("chunk", chunk)
        times = torch.as_tensor(times, dtype=means.dtype, device=means.device)
        if times.dim() != 1 or times.shape[0] < 1:
            raise ValueError(f"times must have shape (T,) with T >= 1, got {tuple(times.shape)}")
        check_finite("times", times)
        p = next(self.parameters())
        pts = means.to(device=p.device, dtype=p.dtype)
        out: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([], [], [])
        for t in times.tolist():
            if not 0.0 <= t <= 1.0:
                raise ValueError(f"times must lie in [0, 1], got {times.tolist()}")
            parts = [self(pts[i:i + chunk], t) for i in range(0, pts.shape[0], chunk)] or [self(pts, t)]
            for k, acc in enumerate(out):
                acc.append(torch.cat([pt[k] for pt in parts], dim=0))
        d_means, d_quats, d_scales = (torch.stack(a).to(means) for a in out)
        return d_means, d_quats, d_scales

    def regularization(self) -> Tensor:
        """Weighted regulariser of the planes (reference ``gaussian_model.py`` ``compute_regulation``).

        Σ over scales of ``plane_tv_weight``·Σ_{xy,xz,yz} R(p) + ``time_smoothness_weight``·Σ_{xt,yt,zt}
        :func:`time_smoothness` (p) + ``l1_time_planes``·Σ_{xt,yt,zt} :func:`time_l1` (p), with R =
        :func:`time_smoothness` (the reference, ``plane_reg="smoothness"``) or :func:`plane_tv`
        (``plane_reg="tv"``).

        Returns:
            scalar Tensor ≥ 0, differentiable w.r.t. the planes.
        """
        cfg = self.config
        spatial = time_smoothness if cfg.plane_reg == "smoothness" else plane_tv
        total = self.grids[0][0].new_zeros(())
        for planes in self.grids:
            total = total + cfg.plane_tv_weight * sum(spatial(planes[i]) for i in SPATIAL_PLANES)
            total = total + cfg.time_smoothness_weight * sum(time_smoothness(planes[i]) for i in TIME_PLANES)
            total = total + cfg.l1_time_planes * sum(time_l1(planes[i]) for i in TIME_PLANES)
        return total


# ---------------------------------------------------------------- file IO


def save_field(path: str | os.PathLike, field: HexPlaneField) -> None:
    """Write ``field`` to one safetensors file, atomically (:func:`diff4splat.io.atomic.atomic_output_path`).

    Tensors: the state dict (planes ``grids.s.i``, MLP weights, the ``bounds`` buffer). Metadata:
    ``format`` = :data:`FIELD_FORMAT`, ``version`` = :data:`FIELD_FORMAT_VERSION`, ``config`` = the
    :class:`HexPlaneConfig` as JSON.

    Raises:
        ValueError: ``field`` is not a :class:`HexPlaneField`.
    """
    if not isinstance(field, HexPlaneField):
        raise ValueError(f"field must be a HexPlaneField, got {type(field).__name__}")
    tensors = {k: v.detach().contiguous().cpu() for k, v in field.state_dict().items()}
    meta = {"format": FIELD_FORMAT, "version": str(FIELD_FORMAT_VERSION),
            "config": json.dumps(dataclasses.asdict(field.config))}
    with atomic_output_path(path) as tmp:
        save_file(tensors, tmp, metadata=meta)


def load_field(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> HexPlaneField:
    """Read a field written by :func:`save_field` (in the dtype it was saved in) onto ``map_location``.

    The file's tensors are read on the CPU and become the field's (nothing is initialised at random: the global
    random state is left as it was), then moved to ``map_location``.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming ``path``: not a readable safetensors file, metadata of another format or version,
            a bad config, or tensors that do not match the config.
        diff4splat.utils.limits.LimitError: the config describes more parameters than the ``parameters`` limit.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"HexPlane field: no file at {path}")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, UnicodeDecodeError, json.JSONDecodeError, OSError) as e:
        raise ValueError(f"HexPlane field: {path} is not a readable safetensors file "
                         f"({' '.join(str(e).split())})") from None
    if meta.get("format") != FIELD_FORMAT:
        raise ValueError(f"HexPlane field: {path} has format {meta.get('format')!r}, expected {FIELD_FORMAT!r}")
    if meta.get("version") != str(FIELD_FORMAT_VERSION):
        raise ValueError(f"HexPlane field: {path} has format version {meta.get('version')!r}, "
                         f"this code reads {FIELD_FORMAT_VERSION}")
    try:
        config = config_from_dict(HexPlaneConfig, json.loads(meta.get("config", "")), f"{path} config")
    except json.JSONDecodeError as e:
        raise ValueError(f"HexPlane field: {path} config metadata is not JSON ({e})") from None
    if "bounds" not in tensors:
        raise ValueError(f"HexPlane field: {path} holds no 'bounds' tensor")
    bounds = tensors["bounds"]
    check_limit("parameters", config.num_parameters, f"HexPlane field: {path}: a field of")
    field = HexPlaneField(config, bounds, device="meta")  # shapes only: the file's tensors are assigned below
    try:
        field.load_state_dict(tensors, strict=True, assign=True)
    except RuntimeError as e:
        raise ValueError(f"HexPlane field: {path} does not match its config ({' '.join(str(e).split())})") from None
    return field.to(device=map_location, dtype=bounds.dtype)
