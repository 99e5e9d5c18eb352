"""HexPlane deformation field of 4D Gaussian Splatting (Wu et al., CVPR 2024, §3.2).

A canonical mean μ (metres) and a time t ∈ [0, 1] give a deformation (Δμ, Δq, Δs), composed with the canonical
Gaussians by :mod:`diff4splat.scene.dynamic` (docs/DESIGN.md "Conventions"). μ maps to box coordinates in [−1, 1]³
(clamped) and t to 2t − 1; per scale, six planes (xy, xz, xt, yz, yt, zt) of shape (1, F, res_b, res_a) are sampled
bilinearly and multiplied; the scales are concatenated, (N, S·F) → trunk → three heads Δμ (metres), Δq (added to
(1, 0, 0, 0)), Δs (log-scale offset). Reference: hustvl/4DGaussians ``scene/hexplane.py``, ``scene/deformation.py``,
``scene/regulation.py``; defaults from its D-NeRF config; the same initialisation (spatial planes U(0.1, 0.5), time
planes 1, Xavier Linear weights). Differences from the reference: docs/DESIGN.md, "Fitting (4D Gaussian Splatting)"."""
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

__all__ = ["HexPlaneConfig", "HexPlaneField", "sample_plane", "plane_tv", "time_smoothness", "time_l1", "save_field",
           "load_field", "PLANE_AXES", "SPATIAL_PLANES", "TIME_PLANES", "MIN_EXTENT", "FIELD_FORMAT",
           "FIELD_FORMAT_VERSION"]

PLANE_AXES: tuple[tuple[int, int], ...] = tuple(itertools.combinations(range(4), 2))
"""Coordinate pairs of the six planes (0 = x, 1 = y, 2 = z, 3 = t): xy, xz, xt, yz, yt, zt."""
SPATIAL_PLANES = (0, 1, 3)
"""Indices into :data:`PLANE_AXES` of the spatial planes xy, xz, yz (the reference's ``[0, 1, 3]``)."""
TIME_PLANES = (2, 4, 5)
"""Indices into :data:`PLANE_AXES` of the space-time planes xt, yt, zt (the reference's ``[2, 4, 5]``)."""
MIN_EXTENT = 1e-6
"""Smallest box extent per axis, metres: a degenerate axis is treated as this wide."""
FIELD_FORMAT = "diff4splat-hexplane"
FIELD_FORMAT_VERSION = 1
_SPATIAL_INIT = (0.1, 0.5)  # reference init_grid_param(a=0.1, b=0.5)
_PLANE_REGS = ("smoothness", "tv")


@dataclass
class HexPlaneConfig:
    """Sizes and regulariser weights of :class:`HexPlaneField` (defaults: the reference's D-NeRF config).

    Attributes:
        feature_dim: F, channels per plane.
        resolution: (x, y, z, t) plane resolution at scale 1, each ≥ 3.
        multires: spatial resolution multipliers, one scale each; time resolution is the same at every scale.
        net_width: W, width of the trunk and heads.
        trunk_depth: hidden (ReLU, Linear(W, W)) blocks after the first Linear, ≥ 0 (the reference's
            max(defor_depth − 1, 0)).
        plane_tv_weight: weight of the spatial-plane regulariser.
        time_smoothness_weight: weight of the time planes' second-difference smoothness.
        l1_time_planes: weight of mean |1 − plane| of the time planes.
        plane_reg: the spatial regulariser: ``"smoothness"`` (the reference's ``_plane_regulation``, which applies
            :func:`time_smoothness` to the spatial planes) or ``"tv"`` (K-Planes, :func:`plane_tv`).

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
        """Parameter count of a :class:`HexPlaneField` of this config, in closed form: planes + trunk
        (S·F·W + W + depth·(W² + W)) + heads (3·(W² + W) + 10·W + 10)."""
        W, planes = self.net_width, 0
        for mult in self.multires:
            res = [r * mult for r in self.resolution[:3]] + [self.resolution[3]]
            planes += sum(self.feature_dim * res[a] * res[b] for a, b in PLANE_AXES)
        trunk = self.feature_channels * W + W + self.trunk_depth * (W * W + W)
        return planes + trunk + 3 * (W * W + W) + 10 * W + 10


# ---------------------------------------------------------------- pure functions on planes


def sample_plane(plane: Tensor, coords: Tensor) -> Tensor:
    """Bilinear sample (``align_corners=True``, border-clamped) of a (1, C, H, W) plane at (N, 2) coordinates
    (u, v) ∈ [−1, 1], u along W, v along H → (N, C) (reference ``grid_sample_wrapper``)."""
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
    """K-Planes total variation (reference ``compute_plane_tv``): 2·(mean of squared H differences + mean of
    squared W differences) of a (B, C, H, W) plane, H, W ≥ 2 → scalar ≥ 0. ValueError on another shape."""
    _check_plane("plane_tv", plane, 2, 2)
    h_tv = torch.square(plane[..., 1:, :] - plane[..., :-1, :]).mean()
    w_tv = torch.square(plane[..., :, 1:] - plane[..., :, :-1]).mean()
    return 2 * (h_tv + w_tv)


def time_smoothness(plane: Tensor) -> Tensor:
    """Mean squared second difference along H (reference ``compute_plane_smoothness``; H is time on a time
    plane) of a (B, C, H, W) plane, H ≥ 3 → scalar ≥ 0. ValueError on another shape."""
    _check_plane("time_smoothness", plane, 3, 1)
    first = plane[..., 1:, :] - plane[..., :-1, :]
    return torch.square(first[..., 1:, :] - first[..., :-1, :]).mean()


def time_l1(plane: Tensor) -> Tensor:
    """Mean |1 − plane| of a (B, C, H, W) plane (reference ``_l1_regulation``), pulling time planes to 1 (static)
    → scalar ≥ 0."""
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
    """The HexPlane deformation field (module docstring).

    Args:
        config: sizes and regulariser weights.
        bounds: (2, 3) float [min, max] of the scene box, metres, finite, max ≥ min; an axis narrower than
            :data:`MIN_EXTENT` is treated as that wide. Stored as the float32 buffer ``bounds``.
        device: where the parameters are made (default ``bounds``' device); random init draws from that device's
            generator, so make the field on the CPU and move it for the same field on every device.

    Attributes:
        grids: ``grids[s][i]`` the plane :data:`PLANE_AXES` ``[i]`` of scale s, (1, F, res_b, res_a).

    Raises:
        ValueError: bad ``config`` or ``bounds`` (shape, non-finite, max < min).
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
        """``means`` (N, 3) metres → box coordinates (N, 3) in [−1, 1] (min → −1, clamped); finite for
        NaN-free means, even with ±inf or an overflowing box extent."""
        lo, hi = self.bounds[0].to(means.dtype), self.bounds[1].to(means.dtype)
        scale = 2.0 / (hi - lo).clamp_min(MIN_EXTENT)  # (3,), 0 if the extent overflows
        x = (means - (0.5 * lo + 0.5 * hi)) * scale
        return torch.nan_to_num(x, nan=0.0).clamp(-1.0, 1.0)

    def _times(self, t: float | Tensor, n: int, like: Tensor) -> Tensor:
        """(N, 1) grid times 2t − 1 from a float or a (N,) / 0-d tensor in [0, 1]."""
        if isinstance(t, Tensor):
            if t.dim() == 0:
                t = t.reshape(1).expand(n)
            if tuple(t.shape) != (n,):
                raise ValueError(f"t must be a float or a tensor of shape ({n},) (one per point), got {tuple(t.shape)}")
            t = t.to(like)
            if n and not bool(((t >= 0) & (t <= 1)).all()):
                raise ValueError(f"t must lie in [0, 1], got values from {float(t.min())} to {float(t.max())}")
            return (2.0 * t - 1.0).unsqueeze(1)
        return like.new_full((n, 1), 2.0 * check_number("t", t, lo=0, hi=1) - 1.0)

    def features(self, means: Tensor, t: float | Tensor) -> Tensor:
        """Plane features (N, S·F) of ``means`` (N, 3) metres at time ``t`` ∈ [0, 1] (float or (N,)).

        Raises:
            ValueError: ``means`` not (N, 3) of the field's dtype or holding NaN; ``t`` not a float / (N,) in [0, 1].
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
        """Deformation at time ``t``: d_means (N, 3) metres, d_quats (N, 4) wxyz unnormalised ((1, 0, 0, 0) + head),
        d_scales (N, 3) log-scale offsets; differentiable. ValueError as :meth:`features`."""
        h = self.trunk(self.features(means, t))  # (N, W)
        d_quats = self.d_quats_head(h) + h.new_tensor(IDENTITY_QUAT)
        return self.d_means_head(h), d_quats, self.d_scales_head(h)

    @torch.no_grad()
    def deformations_at(self, means: Tensor, times: Tensor, chunk: int = 65536) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`forward` at each of T key times, ``chunk`` points at a time, without gradient: the tensors of
        :class:`~diff4splat.scene.dynamic.DynamicGaussians`.

        Args:
            means: (M, 3) canonical means, metres, any device and float dtype.
            times: (T,) key times in [0, 1], T ≥ 1 (tensor or sequence).
            chunk: points per evaluation, ≥ 1.

        Returns:
            d_means (T, M, 3), d_quats (T, M, 4), d_scales (T, M, 3) on ``means``' device and dtype.

        Raises:
            ValueError: bad ``times`` or ``chunk``; ``means`` as :meth:`features`.
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
        """Weighted plane regulariser (reference ``compute_regulation``), summed over scales:
        ``plane_tv_weight``·Σ_spatial R + ``time_smoothness_weight``·Σ_time :func:`time_smoothness` +
        ``l1_time_planes``·Σ_time :func:`time_l1`, R chosen by ``plane_reg``. Scalar ≥ 0, differentiable."""
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
    """Write ``field`` atomically to one safetensors file: its state dict, metadata ``format`` (:data:`FIELD_FORMAT`),
    ``version`` and ``config`` (JSON). ValueError unless ``field`` is a :class:`HexPlaneField`."""
    if not isinstance(field, HexPlaneField):
        raise ValueError(f"field must be a HexPlaneField, got {type(field).__name__}")
    tensors = {k: v.detach().contiguous().cpu() for k, v in field.state_dict().items()}
    meta = {"format": FIELD_FORMAT, "version": str(FIELD_FORMAT_VERSION),
            "config": json.dumps(dataclasses.asdict(field.config))}
    with atomic_output_path(path) as tmp:
        save_file(tensors, tmp, metadata=meta)


def load_field(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> HexPlaneField:
    """Read a field written by :func:`save_field` (in its saved dtype) onto ``map_location``; the global random
    state is untouched.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: naming ``path``: unreadable, another format or version, a bad config, or tensors that do not
            match it.
        diff4splat.utils.limits.LimitError: more parameters than the ``parameters`` limit.
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
