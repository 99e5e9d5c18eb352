"""Per-scene fitting of a 4D Gaussian scene to multi-view video (4D Gaussian Splatting, Wu et al., CVPR 2024):
canonical 3D Gaussians, a static coarse stage, then a fine stage with a HexPlane field (:mod:`models.hexplane`)
deforming them to each view's time (static scenes have no fine stage). One view per step in a seeded order; loss
(1 − λ)·L1 + λ·(1 − SSIM) (3DGS Eq. 7) + ``depth_weight``·mean |D̂ − D| / extent + the field's regularisers; Adam
with 3DGS's rates; density control in :mod:`training.densify`. Schedule, background and differences from the
reference: docs/DESIGN.md, "Fitting (4D Gaussian Splatting)". Everything lives on the initial points' device;
every random draw is made on the CPU and moved, so a seed gives the same fit on every device.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from dataclasses import field as dc_field

import kornia
import torch
from torch import Tensor, nn
from tqdm import tqdm

from diff4splat.render import rasterize
from diff4splat.scene.dynamic import DynamicGaussians, compose_deformation
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from diff4splat.utils.constants import ALPHA_MIN
from diff4splat.utils.devices import synchronize
from diff4splat.utils.limits import check_limit
from models.deformation import IDENTITY_QUAT
from models.hexplane import HexPlaneConfig, HexPlaneField
from training.densify import DensifyConfig, DensityStats, densify_and_prune, prune, reset_opacity
from training.eval_metrics import PSNR_CAP, psnr_from_mse
from training.fit_data import View, knn_scales
from training.losses import photometric_loss

__all__ = ["BACKGROUNDS", "init_background",
           "DEPTH_WEIGHTS", "default_depth_weight", "FitConfig", "LearningRates", "FitState", "expon_lr",
           "init_state", "fit_steps", "evaluate_views", "to_scene", "psnr_from_mse", "render_view", "start_fine_stage",
           "gaussian_adam", "config_dict", "POSTFIX_EVERY"]

POSTFIX_EVERY = 10
"""Steps between readings of the training PSNR for the progress bar (each reading waits for the device)."""


@dataclass
class LearningRates:
    """Adam learning rates (3DGS ``arguments/__init__.py``; field rates from 4DGS's D-NeRF config). Positions and the
    field are scaled by the scene extent and decay from init to final over the stage (:func:`expon_lr`, no delay)."""

    position_init: float = 1.6e-4
    position_final: float = 1.6e-6
    sh0: float = 2.5e-3
    shN: float = 2.5e-3 / 20
    opacities: float = 0.05
    scales: float = 5e-3
    quats: float = 1e-3
    deformation_init: float = 1.6e-4
    deformation_final: float = 1.6e-5
    grid_init: float = 1.6e-3
    grid_final: float = 1.6e-4
    background: float = 0.01


BACKGROUNDS = {"learned": (0.5, 0.5, 0.5), "black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
"""``FitConfig.background`` choices and their (starting) RGB in [0, 1]."""

DEPTH_WEIGHTS = {"ground_truth": 1.0, "aligned_estimate": 0.1, "none": 0.0}
"""Default depth-L1 weight by the scene's ``meta["depth_source"]`` (data_prep FORMAT.md): true depth is trusted,
an aligned monocular estimate is a weak prior."""


def default_depth_weight(depth_source: str) -> float:
    """:data:`DEPTH_WEIGHTS` of a scene's depth source; ValueError for an unknown one."""
    if depth_source not in DEPTH_WEIGHTS:
        raise ValueError(f"depth_source must be one of {sorted(DEPTH_WEIGHTS)}, got {depth_source!r}")
    return DEPTH_WEIGHTS[depth_source]


@dataclass
class FitConfig:
    """Settings of :func:`fit_steps` (CLI: ``diff4splat fit``; defaults scaled to CPU fits of minutes, see
    docs/DESIGN.md, "Fitting (4D Gaussian Splatting)").

    ``iterations`` counts coarse + fine steps; the SH degree grows by one every ``sh_interval`` steps up to
    ``sh_degree``; ``init_points`` caps the depth points, ``random_points`` sizes the random-box start;
    ``init_first_frame`` starts a dynamic scene from frame 0 alone; ``depth_weight`` None picks
    :func:`default_depth_weight`, 0 turns the depth L1 off; ``background`` is one of :data:`BACKGROUNDS`
    ("learned": 3 sigmoid logits at ``lr.background``).
    Raises ValueError naming a field out of range; :class:`diff4splat.utils.limits.LimitError` for ``iterations``
    or a Gaussian count (``init_points``, ``random_points``, ``densify.max_gaussians``) above its limit.
    """

    iterations: int = 1800
    coarse_iterations: int = 300
    sh_degree: int = 1
    sh_interval: int = 1000
    init_points: int = 15_000
    init_first_frame: bool = False
    random_points: int = 20_000
    ssim_weight: float = 0.2
    depth_weight: float | None = None
    densify: DensifyConfig = dc_field(
        default_factory=lambda: DensifyConfig(start=300, until=1200, interval=100, max_gaussians=25_000))
    field: HexPlaneConfig = dc_field(
        default_factory=lambda: HexPlaneConfig(feature_dim=16, resolution=(32, 32, 32, 25)))
    background: str = "learned"
    lr: LearningRates = dc_field(default_factory=LearningRates)

    def __post_init__(self) -> None:
        if self.background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {sorted(BACKGROUNDS)}, got {self.background!r}")
        for name in ("iterations", "coarse_iterations", "sh_degree", "sh_interval", "init_points", "random_points"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name} must be an int ≥ 0, got {v!r}")
        if self.iterations < 1 or self.sh_interval < 1 or self.init_points < 1 or self.random_points < 1:
            raise ValueError(f"iterations, sh_interval, init_points and random_points must be ≥ 1, got "
                             f"{self.iterations}, {self.sh_interval}, {self.init_points}, {self.random_points}")
        if self.sh_degree > 3:
            raise ValueError(f"sh_degree must be in 0 … 3, got {self.sh_degree}")
        check_limit("iterations", self.iterations, "iterations")
        for name, value in (("init_points", self.init_points), ("random_points", self.random_points),
                            ("densify.max_gaussians", self.densify.max_gaussians)):
            check_limit("gaussians", value, name)
        for name in ("ssim_weight", "depth_weight"):
            v = getattr(self, name)
            if v is None and name == "depth_weight":
                continue
            if not isinstance(v, (int, float)) or not 0 <= v <= (1 if name == "ssim_weight" else math.inf):
                raise ValueError(f"{name} must be a number ≥ 0 (ssim_weight ≤ 1), got {v!r}")


def expon_lr(step: int, lr_init: float, lr_final: float, max_steps: int, delay_steps: int = 0,
             delay_mult: float = 1.0) -> float:
    """Log-linear decay from ``lr_init`` to ``lr_final`` over ``max_steps``, optional sine warm-up (3DGS
    ``get_expon_lr_func``)."""
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    delay = 1.0
    if delay_steps > 0:
        delay = delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0.0), 1.0))
    t = min(max(step / max(max_steps, 1), 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


@dataclass
class FitState:
    """Everything a fit needs to continue, on :attr:`device` (``generator`` is a CPU generator).

    ``params``: "means" (N,3) metres, "scales" (N,3) log metres, "quats" (N,4) wxyz unnormalised,
    "opacities" (N,) logits, "sh0" (N,1,3), "shN" (N,K−1,3) (K = (sh_degree+1)²). ``background``: (3,) logits
    when learned (with ``background_optimizer``), else RGB in [0, 1] (:meth:`background_rgb`). ``loss``: the last
    step's detached loss (None before the first step; not checkpointed).
    """

    params: dict[str, nn.Parameter]
    optimizer: torch.optim.Adam
    stats: DensityStats
    extent: float
    dynamic: bool
    field: HexPlaneField | None = None
    field_optimizer: torch.optim.Adam | None = None
    background: Tensor = dc_field(default_factory=lambda: torch.zeros(3, device="cpu"))  # init_background sets it
    background_optimizer: torch.optim.Adam | None = None
    step: int = 0
    generator: torch.Generator = dc_field(default_factory=torch.Generator)
    order: list[int] = dc_field(default_factory=list)
    train_time: float = 0.0
    history: list[dict] = dc_field(default_factory=list)
    counts: dict[str, int] = dc_field(default_factory=lambda: {"cloned": 0, "split": 0, "pruned": 0})
    loss: Tensor | None = None

    @property
    def num_gaussians(self) -> int:
        """N, the current number of Gaussians."""
        return self.params["means"].shape[0]

    @property
    def device(self) -> torch.device:
        """The device of the Gaussians, where the fit runs."""
        return self.params["means"].device

    def background_rgb(self) -> Tensor:
        """(3,) RGB in [0, 1] behind the Gaussians (differentiable when learned)."""
        return torch.sigmoid(self.background) if self.background_optimizer is not None else self.background


def init_background(state: FitState, config: FitConfig) -> None:
    """Set ``state.background`` from ``config.background`` (:data:`BACKGROUNDS`) on the Gaussians' device: learned,
    3 logits from 0.5 grey with an Adam at ``config.lr.background``; fixed, the colour."""
    rgb = torch.tensor(BACKGROUNDS[config.background], device=state.device)
    if config.background == "learned":
        state.background = nn.Parameter(torch.logit(rgb))
        state.background_optimizer = torch.optim.Adam([state.background], lr=config.lr.background)
    else:
        state.background, state.background_optimizer = rgb, None


def gaussian_adam(params: dict[str, nn.Parameter], lr: LearningRates, extent: float) -> torch.optim.Adam:
    """Adam over :class:`FitState` ``params``, one group per name (``group["name"]``, edited by
    :mod:`training.densify`), 3DGS's rates with positions × ``extent`` (metres), eps 1e-15."""
    rates = {"means": lr.position_init * extent, "sh0": lr.sh0, "shN": lr.shN, "opacities": lr.opacities,
             "scales": lr.scales, "quats": lr.quats}
    return torch.optim.Adam([{"params": [p], "lr": rates[k], "name": k} for k, p in params.items()], lr=0.0, eps=1e-15)


def init_state(means: Tensor, colors: Tensor, config: FitConfig, extent: float, dynamic: bool, seed: int,
               scales: Tensor | None = None, quats: Tensor | None = None, opacities: Tensor | None = None,
               sh: Tensor | None = None) -> FitState:
    """Gaussians from points ``means`` (N, 3) metres, on the fit's device (3DGS ``create_from_pcd``): SH DC from
    ``colors`` (N, 3) in [0, 1], kNN scales, identity rotation, opacity 0.1 — or the given
    ``scales``/``quats``/``opacities``/``sh`` (a ``generate`` start). ``seed`` seeds the CPU generator."""
    n, dev = means.shape[0], means.device
    K = (config.sh_degree + 1) ** 2
    sh_full = torch.zeros(n, K, 3, device=dev)
    if sh is not None:
        k = min(K, sh.shape[1])
        sh_full[:, :k] = sh[:, :k].to(dev)
    else:
        sh_full[:, 0] = rgb_to_sh0(colors.to(dev))
    params = {
        "means": means.float(),
        "scales": torch.log(knn_scales(means.float()) if scales is None else scales.to(dev).float()),
        "quats": (torch.tensor(IDENTITY_QUAT, device=dev).repeat(n, 1) if quats is None
                  else quats.to(dev).float()),
        "opacities": torch.logit(torch.full((n,), 0.1, device=dev) if opacities is None
                                     else opacities.to(dev).float().clamp(1e-4, 1 - 1e-4)),
        "sh0": sh_full[:, :1],
        "shN": sh_full[:, 1:],
    }
    params = {k: nn.Parameter(v.contiguous()) for k, v in params.items()}
    state = FitState(params, gaussian_adam(params, config.lr, extent), DensityStats(n, dev), extent, dynamic)
    init_background(state, config)
    state.generator.manual_seed(seed)
    return state


def _activated(params: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(means, quats, scales, opacities, sh) as the renderer takes them."""
    return (params["means"], params["quats"], params["scales"].exp(), torch.sigmoid(params["opacities"]),
            torch.cat([params["sh0"], params["shN"]], dim=1))


def render_view(state: FitState, view: View, sh_degree: int, with_depth: bool):
    """(rgb (H, W, 3), depth (H, W) or None, alpha (H, W), rasterize meta) of one view, deformed to its time."""
    means, quats, scales, opac, sh = _activated(state.params)
    if state.field is not None:
        means, quats, scales = compose_deformation(means, quats, scales, *state.field(means, view.time))
    colors, alphas, meta = rasterize(means, quats, scales, opac, sh, view.viewmat[None], view.K[None],
                                     view.width, view.height, sh_degree=sh_degree,
                                     backgrounds=state.background_rgb()[None].to(means.dtype),
                                     render_mode="RGB+ED" if with_depth else "RGB")
    depth = colors[0, ..., 3] if with_depth else None
    return colors[0, ..., :3], depth, alphas[0, ..., 0], meta


def start_fine_stage(state: FitState, config: FitConfig) -> None:
    """Start the fine stage: an identity HexPlane field on the Gaussians' bounding box (built on the CPU from torch's
    global generator, then moved) and its Adam with groups "deformation" (MLP) and "grid" (planes) at 4DGS's rates."""
    means = state.params["means"].detach()
    bounds = torch.stack([means.min(0).values, means.max(0).values])
    state.field = HexPlaneField(config.field, bounds, device="cpu").to(state.device)
    grids = [p for n, p in state.field.named_parameters() if "grid" in n or "plane" in n]
    ids = {id(p) for p in grids}
    mlp = [p for p in state.field.parameters() if id(p) not in ids]
    state.field_optimizer = torch.optim.Adam(
        [{"params": mlp, "lr": config.lr.deformation_init * state.extent, "name": "deformation"},
         {"params": grids, "lr": config.lr.grid_init * state.extent, "name": "grid"}], lr=0.0, eps=1e-15)


def _set_lrs(state: FitState, config: FitConfig) -> None:
    """Decay the position and field learning rates over the current stage."""
    lr, step = config.lr, state.step
    fine = state.field_optimizer is not None
    stage_step = step - config.coarse_iterations if fine else step
    coarse_len = config.coarse_iterations if state.dynamic else config.iterations  # static: one stage, the whole fit
    stage_len = config.iterations - config.coarse_iterations if fine else max(coarse_len, 1)
    for g in state.optimizer.param_groups:
        if g["name"] == "means":
            g["lr"] = expon_lr(stage_step, lr.position_init * state.extent, lr.position_final * state.extent, stage_len)
    if fine:
        for g in state.field_optimizer.param_groups:
            init, final = ((lr.deformation_init, lr.deformation_final) if g["name"] == "deformation"
                           else (lr.grid_init, lr.grid_final))
            g["lr"] = expon_lr(stage_step, init * state.extent, final * state.extent, stage_len)


def fit_steps(state: FitState, views: list[View], config: FitConfig, until: int, *, progress: bool = False,
              should_stop=lambda: False, on_step=None) -> FitState:
    """Advance ``state`` in place to step ``until`` (≤ ``config.iterations``) over ``views`` (not empty, on
    ``state.device``), stopping early when ``should_stop()``; ``on_step(state)`` after every step. ``progress``
    shows a tqdm bar (EMA PSNR read every :data:`POSTFIX_EVERY` steps). ``state.train_time`` adds the steps' wall time
    (the device is synchronised once at the end). Raises ValueError when ``config.depth_weight`` is None."""
    if config.depth_weight is None:
        raise ValueError("depth_weight is None: resolve it first (default_depth_weight of the scene's depth source)")
    with_depth = config.depth_weight > 0 and views[0].depth is not None
    bar = tqdm(total=until, initial=state.step, desc="fit", disable=not progress, dynamic_ncols=True)
    ema_psnr = None  # a 0-d tensor on the device: read for the bar only every POSTFIX_EVERY steps
    while state.step < until and not should_stop():
        t0 = time.perf_counter()
        if state.dynamic and state.field is None and state.step >= config.coarse_iterations:
            start_fine_stage(state, config)
        if not state.order:
            g = state.generator
            state.order = torch.randperm(len(views), generator=g, device=g.device).tolist()
        view = views[state.order.pop()]
        _set_lrs(state, config)
        degree = min(config.sh_degree, state.step // config.sh_interval)
        rgb, depth, _, meta = render_view(state, view, degree, with_depth)
        meta["means2d"].retain_grad()
        target = view.image
        loss = photometric_loss(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], config.ssim_weight)
        if with_depth:  # mean |D̂ − D| over the valid pixels (0 without any), masked without a host sync
            valid = torch.isfinite(view.depth)
            err = torch.where(valid, depth - view.depth, 0.0).abs().sum() / valid.sum().clamp_min(1)
            loss = loss + config.depth_weight * err / state.extent
        if state.field is not None:
            loss = loss + state.field.regularization()
        if loss.requires_grad:  # a view that sees no Gaussian renders a constant: no graph, no gradient
            loss.backward()
        state.loss = loss.detach()
        state.step += 1
        with torch.no_grad():
            if meta["means2d"].grad is not None:
                state.stats.update(meta["means2d"].grad[0], meta["radii"][0], view.width, view.height)
            state.optimizer.step()
            state.optimizer.zero_grad(set_to_none=True)
            for opt in (state.field_optimizer, state.background_optimizer):
                if opt is not None:
                    opt.step()
                    opt.zero_grad(set_to_none=True)
            _density_control(state, config)
        if progress:
            with torch.no_grad():
                mse = ((rgb.detach().clamp(0, 1) - target) ** 2).mean()
                psnr = -10.0 * torch.log10(mse.clamp_min(10 ** (-PSNR_CAP / 10)))  # psnr_from_mse, on the device
                ema_psnr = psnr if ema_psnr is None else 0.9 * ema_psnr + 0.1 * psnr
        state.train_time += time.perf_counter() - t0
        bar.update(1)
        if progress and (state.step % POSTFIX_EVERY == 0 or state.step == until):
            bar.set_postfix(psnr=f"{float(ema_psnr):.2f}", gaussians=state.num_gaussians,
                            stage="fine" if state.field is not None else "coarse")
        if on_step is not None:
            on_step(state)
    t0 = time.perf_counter()
    synchronize(state.device)  # the queued steps' work counts in train_time
    state.train_time += time.perf_counter() - t0
    bar.close()
    return state


def _density_control(state: FitState, config: FitConfig) -> None:
    """Densify/prune and reset opacities on the steps of ``config.densify``."""
    d, step = config.densify, state.step
    if d.active(step):
        state.params, counts = densify_and_prune(
            state.params, state.optimizer, state.stats, d, state.extent,
            prune_large=d.opacity_reset_interval > 0 and step > d.opacity_reset_interval,
            generator=state.generator)
        for k, v in counts.items():
            state.counts[k] += v
    if d.opacity_reset_interval and step % d.opacity_reset_interval == 0 and step <= d.until:
        state.params = reset_opacity(state.params, state.optimizer)


@torch.no_grad()
def evaluate_views(state: FitState, views: list[View], sh_degree: int,
                   masks: list[Tensor] | None = None) -> dict[str, float]:
    """{"psnr" (pooled MSE), "ssim" (mean, kornia window 11), "mse", "views", "masked_psnr" (DyCheck's mPSNR over
    ``masks``, (H, W) bool per view), "covisible" (masked fraction)} of renders clamped to [0, 1]; the masked
    values are NaN without masks. Sums stay on ``state.device`` (float64), read once."""
    zero = torch.zeros((), dtype=torch.float64, device=state.device)
    se, ssim, mse_m, n_m, n = zero, zero, zero, zero, 0
    for i, v in enumerate(views):
        rgb = render_view(state, v, sh_degree, False)[0].clamp(0, 1)
        err = (rgb - v.image) ** 2
        se = se + err.sum().double()
        n += rgb.numel()
        if masks is not None:
            mse_m = mse_m + torch.where(masks[i][..., None], err, 0.0).sum().double()
            n_m = n_m + masks[i].sum().double() * 3
        ssim = ssim + kornia.metrics.ssim(rgb.permute(2, 0, 1)[None], v.image.permute(2, 0, 1)[None], 11).mean()
    se, ssim, mse_m, n_m = torch.stack([se, ssim, mse_m, n_m]).tolist()  # one read of the device
    mse = se / max(n, 1)
    return {"psnr": psnr_from_mse(mse), "ssim": ssim / max(len(views), 1), "mse": mse, "views": len(views),
            "masked_psnr": psnr_from_mse(mse_m / n_m) if n_m else math.nan,
            "covisible": n_m / max(n, 1) if masks is not None else math.nan}


@torch.no_grad()
def to_scene(state: FitState, times: Tensor | None) -> DynamicGaussians:
    """The fitted scene on ``state.device``: activated Gaussians (opacity < 1/255 pruned and counted in
    ``state.counts["pruned"]``) and, with a field, its deformations at ``times`` (T,)."""

    keep = torch.sigmoid(state.params["opacities"]) >= ALPHA_MIN
    if not bool(keep.all()):
        state.params = prune(state.params, state.optimizer, ~keep, state.stats)
        state.counts["pruned"] += int((~keep).sum())  # metrics.json's count: densification's and these
    means, quats, scales, opac, sh = (x.detach() for x in _activated(state.params))
    canonical = Gaussians(means, quats, scales, opac, sh)
    if state.field is None or times is None:
        return DynamicGaussians(canonical)
    times = times.to(canonical.means)
    return DynamicGaussians(canonical, times, *state.field.deformations_at(canonical.means, times))


def config_dict(config: FitConfig) -> dict:
    """JSON-ready settings (meta.json / checkpoints)."""
    return asdict(config)

