"""Adaptive density control of 3D Gaussian Splatting (Kerbl et al. 2023, §5.2), as ``diff4splat fit`` uses it.

Every ``interval`` iterations between ``start`` and ``until``: **clone** Gaussians whose mean NDC positional
gradient (pixel gradient × (W/2, H/2), over the views that saw them) is ≥ ``grad_threshold`` and whose largest scale
is ≤ ``percent_dense`` × extent; **split** the larger ones into ``split_n`` samples of N(μ, Σ) with scales
/ (0.8·split_n); **prune** opacity < ``min_opacity`` and, after the first opacity reset, radii > ``max_screen_size``
pixels or scales > ``max_world_size`` × extent. Opacities are reset to min(o, 0.01) every ``opacity_reset_interval``.
Parameters are a dict ``{name: nn.Parameter}`` with one Adam group per name (``group["name"]``); these functions
replace each parameter and its Adam moments together.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from diff4splat.scene.quaternions import quat_to_rotmat
from diff4splat.utils.checks import check_int, check_number, check_ranges, ranged

__all__ = ["DensifyConfig", "DensityStats", "densify_and_prune", "prune", "reset_opacity", "replace_params"]


@dataclass
class DensifyConfig:
    """Density control settings (module docstring); defaults are 3DGS's (``arguments/__init__.py``).
    ``opacity_reset_interval`` 0 never resets; ``max_gaussians`` caps the count, candidates taken by largest
    gradient first. Raises ValueError naming ``densify.<field>`` out of range."""

    start: int = ranged(500, check_int, lo=0)
    until: int = ranged(15000, check_int, lo=0)
    interval: int = ranged(100, check_int, lo=0)
    grad_threshold: float = ranged(2e-4, check_number, lo=0)
    percent_dense: float = ranged(0.01, check_number, lo=0)
    min_opacity: float = ranged(0.005, check_number, lo=0)
    max_screen_size: float = ranged(20.0, check_number, lo=0)
    max_world_size: float = ranged(0.1, check_number, lo=0)
    opacity_reset_interval: int = ranged(3000, check_int, lo=0)
    split_n: int = ranged(2, check_int, lo=0)
    max_gaussians: int = ranged(200_000, check_int, lo=0)

    def __post_init__(self) -> None:
        check_ranges("densify", self)
        if self.interval < 1 or self.split_n < 2 or self.max_gaussians < 1:
            raise ValueError(f"densify: interval ≥ 1, split_n ≥ 2, max_gaussians ≥ 1 required, got "
                             f"{self.interval}, {self.split_n}, {self.max_gaussians}")

    def active(self, iteration: int) -> bool:
        """True when ``iteration`` (1-based count of steps taken) densifies."""
        return self.start < iteration <= self.until and iteration % self.interval == 0


class DensityStats:
    """Per-Gaussian statistics of ``n`` Gaussians on ``device``, (N,) float32 each: ``grad_accum`` the sum of NDC
    gradient norms over the views that saw it, ``denom`` the number of those views, ``max_radii`` in pixels."""

    def __init__(self, n: int, device: str | torch.device = "cpu") -> None:
        self.grad_accum = torch.zeros(n, device=device)
        self.denom = torch.zeros(n, device=device)
        self.max_radii = torch.zeros(n, device=device)

    @property
    def device(self) -> torch.device:
        """The device of the statistics."""
        return self.grad_accum.device

    def update(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one view's ``means2d_grad`` (N, 2) per pixel and ``radii`` (N,) or per-axis (N, 2) pixels, 0 where
        culled, for an image of ``width``×``height`` (no host synchronisation)."""
        if radii.dim() == 2:
            radii = radii.amax(dim=-1)
        radii = radii.float()
        vis = radii > 0
        g = means2d_grad.detach() * means2d_grad.new_tensor([width / 2.0, height / 2.0])
        self.grad_accum = torch.where(vis, self.grad_accum + g.norm(dim=-1), self.grad_accum)
        self.denom = torch.where(vis, self.denom + 1, self.denom)
        self.max_radii = torch.where(vis, torch.maximum(self.max_radii, radii), self.max_radii)

    def mean_grad(self) -> Tensor:
        """(N,) accumulated gradient norm / views that saw the Gaussian (0 if none)."""
        return torch.where(self.denom > 0, self.grad_accum / self.denom.clamp_min(1), 0.0)


def replace_params(params: dict[str, nn.Parameter], optimizer: torch.optim.Optimizer,
                   new: dict[str, Tensor], keep: Tensor | None) -> dict[str, nn.Parameter]:
    """Replace every parameter by ``cat(param[keep], new[name])`` ((N, ...) kept rows, ``keep`` None: all; (M, ...)
    new rows with zero Adam moments) and its moments likewise; returns the new dict, which the optimizer's groups
    point at. Raises ValueError for a name of ``params`` without an Adam group (after replacing the groups)."""
    out = {}
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        kept = old.detach() if keep is None else old.detach()[keep]
        p = nn.Parameter(torch.cat([kept, new[name].to(old.dtype)]))
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                s = state[key] if keep is None else state[key][keep]
                state[key] = torch.cat([s, torch.zeros_like(new[name], dtype=s.dtype)])
            optimizer.state[p] = state
        group["params"][0] = p
        out[name] = p
    missing = set(params) - set(out)
    if missing:
        raise ValueError(f"parameters without an Adam group: {sorted(missing)}")
    return out


def prune(params: dict[str, nn.Parameter], optimizer: torch.optim.Optimizer, remove: Tensor,
          stats: DensityStats | None = None) -> dict[str, nn.Parameter]:
    """Remove the Gaussians where ``remove`` (N,) bool is true (parameters, moments and ``stats``)."""
    keep = ~remove
    out = replace_params(params, optimizer, {k: v.detach()[:0] for k, v in params.items()}, keep)
    if stats is not None:
        stats.grad_accum, stats.denom = stats.grad_accum[keep], stats.denom[keep]
        stats.max_radii = stats.max_radii[keep]
    return out


def densify_and_prune(params: dict[str, nn.Parameter], optimizer: torch.optim.Optimizer, stats: DensityStats,
                      config: DensifyConfig, extent: float, prune_large: bool,
                      generator: torch.Generator) -> tuple[dict[str, nn.Parameter], dict[str, int]]:
    """Clone, split (positions drawn on the CPU ``generator``), then prune (by size too when ``prune_large``);
    ``params`` "means" (N,3), "scales" (N,3) log, "quats" (N,4), "opacities" (N,) logit, others copied; ``extent``
    in metres. Returns (new params, {"cloned", "split", "pruned"}); ``stats`` is reset to the new count."""
    grad = stats.mean_grad()
    scales = params["scales"].detach().exp()
    big = scales.max(dim=1).values > config.percent_dense * extent
    hot = grad >= config.grad_threshold
    room = max(config.max_gaussians - grad.shape[0], 0)
    clone, split = hot & ~big, hot & big
    if int(clone.sum()) + int(split.sum()) * (config.split_n - 1) > room:  # cap: largest gradients first
        order = torch.argsort(torch.where(hot, grad, -1.0), descending=True)
        cost = torch.where(big, config.split_n - 1, 1)[order]
        take = torch.zeros_like(hot)
        take[order[(torch.cumsum(cost, 0) <= room) & hot[order]]] = True
        clone, split = clone & take, split & take
    n_clone, n_split = int(clone.sum()), int(split.sum())
    new = {k: v.detach()[clone] for k, v in params.items()}
    if n_split:
        n = config.split_n
        std = scales[split].repeat(n, 1)
        R = quat_to_rotmat(params["quats"].detach()[split]).repeat(n, 1, 1)
        # drawn by the (CPU) generator, then moved: a seed splits alike on every device
        sample = torch.randn(std.shape, generator=generator, dtype=std.dtype, device=generator.device).to(std.device)
        sample = sample * std
        split_rows = {k: v.detach()[split].repeat(n, *([1] * (v.dim() - 1))) for k, v in params.items()}
        split_rows["means"] = split_rows["means"] + (R @ sample[..., None])[..., 0]
        split_rows["scales"] = torch.log(std / (0.8 * n))
        new = {k: torch.cat([new[k], split_rows[k]]) for k in params}
    params = replace_params(params, optimizer, new, None)
    N = params["means"].shape[0]
    originals = torch.cat([split, torch.zeros(N - split.shape[0], dtype=torch.bool, device=split.device)])
    opac = torch.sigmoid(params["opacities"].detach())
    remove = originals | (opac < config.min_opacity)
    if prune_large:
        radii = torch.cat([stats.max_radii, stats.max_radii.new_zeros(N - stats.max_radii.shape[0])])
        world = params["scales"].detach().exp().max(dim=1).values
        remove |= (radii > config.max_screen_size) | (world > config.max_world_size * extent)
    n_pruned = int(remove.sum()) - n_split
    params = prune(params, optimizer, remove)
    stats.__init__(params["means"].shape[0], device=params["means"].device)
    return params, {"cloned": n_clone, "split": n_split, "pruned": n_pruned}


def reset_opacity(params: dict[str, nn.Parameter], optimizer: torch.optim.Optimizer,
                  value: float = 0.01) -> dict[str, nn.Parameter]:
    """``params`` with opacity logits capped at logit(``value``) and their Adam moments zeroed (3DGS
    ``reset_opacity``); ValueError when no Adam group is named "opacities"."""

    for group in optimizer.param_groups:
        if group["name"] == "opacities":
            old = group["params"][0]
            p = nn.Parameter(torch.minimum(old.detach(), torch.logit(torch.tensor(value, device=old.device))))
            state = optimizer.state.pop(old, None)
            if state:
                state["exp_avg"], state["exp_avg_sq"] = torch.zeros_like(p), torch.zeros_like(p)
                optimizer.state[p] = state
            group["params"][0] = p
            return {**params, "opacities": p}
    raise ValueError("no Adam group named 'opacities'")
