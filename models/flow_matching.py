"""Rectified-flow / flow-matching schedule, training-time σ sampling and ODE samplers.

Convention (docs/DESIGN.md, "Flow matching"): a clean sample ``x0`` and Gaussian noise ``ε`` are joined by
the straight path

    x_σ = (1 − σ)·x0 + σ·ε,        σ ∈ [0, 1],  σ = 1 is pure noise,

and the network learns the velocity ``v = dx_σ/dσ = ε − x0`` (rectified flow, Liu et al. 2022,
"Flow Straight and Fast", Eq. 1; conditional flow matching with the optimal-transport path,
Lipman et al. 2023, "Flow Matching for Generative Modeling", Eq. 20–23, with their t = 1 − σ).
Training minimises ‖v_θ(x_σ, σ) − (ε − x0)‖², so v_θ regresses E[ε − x0 | x_σ]. Sampling integrates
the ODE dx/dσ = v_θ(x, σ) from σ = 1 (noise) down to σ = 0 (data).

Everything here is a pure function of tensors; ``velocity_fn(x, sigma)`` is any callable taking the
current state ``x`` (any shape, e.g. (B, c, n, h, w) video latents) and a 0-dim tensor ``sigma``
(same dtype/device as ``x``) and returning a velocity of the same shape as ``x``.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm.auto import tqdm

__all__ = [
    "FlowMatchingConfig",
    "check_guidance",
    "MAX_GUIDANCE",
    "PAPER_FLOW_MATCHING",
    "SAMPLERS",
    "integrator",
    "shift_sigmas",
    "sigma_schedule",
    "sample_logit_normal",
    "add_noise",
    "velocity_target",
    "euler_sample",
    "heun_sample",
    "sample",
]

VelocityFn = Callable[[Tensor, Tensor], Tensor]
SAMPLERS = ("euler", "heun")


@dataclass
class FlowMatchingConfig:
    """Schedule and sampler settings (the single source of defaults; YAML files override fields).

    Attributes:
        shift: timestep shift s > 0 of :func:`shift_sigmas`; 1 = no shift, s > 1 spends more steps
            (and more training samples) near pure noise (SD3 §5.3.2).
        sampler: ``"euler"`` (NFE = steps) or ``"heun"`` (NFE = 2·steps − 1).
        steps: number of integration steps ≥ 1.
        logit_normal_mean: mean m of the logit-normal training σ distribution (SD3 §3.1).
        logit_normal_std: standard deviation s > 0 of the logit-normal distribution.
        guidance: classifier-free guidance scale g ≥ 0 (Ho & Salimans 2022, Eq. 6, in velocity form:
            v = v_uncond + g·(v_text − v_uncond)); 1 = no guidance (one network call per step). Applied only when
            there is a prompt.
    """

    shift: float = 1.0
    sampler: str = "euler"
    steps: int = 8
    logit_normal_mean: float = 0.0
    logit_normal_std: float = 1.0
    guidance: float = 1.0

    def __post_init__(self) -> None:
        _check_shift(self.shift)
        _check_sampler(self.sampler)
        _check_steps(self.steps)
        if not self.logit_normal_std > 0:
            raise ValueError(f"FlowMatchingConfig.logit_normal_std must be > 0, got {self.logit_normal_std}")
        check_guidance(self.guidance, "FlowMatchingConfig.guidance")

    @classmethod
    def paper(cls) -> FlowMatchingConfig:
        """Paper-scale settings (:data:`PAPER_FLOW_MATCHING`)."""
        return cls(**PAPER_FLOW_MATCHING)


PAPER_FLOW_MATCHING: dict = dict(shift=3.0, sampler="euler", steps=50, logit_normal_mean=0.0, logit_normal_std=1.0)
"""Paper-scale schedule copied by ``configs/paper.yaml``: shift 3.0 and logit-normal(0, 1) are the
SD3 defaults for high-resolution training (Esser et al. 2024, §3.1 and §5.3.2); 50 Euler steps is the
usual sampling budget of flow-matching video DiTs. These are our choices, not numbers from Diff4Splat."""


MAX_GUIDANCE = 30.0
"""Largest classifier-free guidance scale accepted. The guided velocity is v_u + w·(v_c − v_u): past a few tens the
difference of the two predictions, scaled by w, swamps the velocity and the sampler integrates it into saturated
noise. The video backbones' own defaults are 5 (Wan2.2) and 6 (CogVideoX); image models are used up to ~20."""


def check_guidance(guidance: float, name: str = "guidance") -> float:
    """``guidance`` as a float; ValueError (naming ``name``) unless it is a finite number in [0,
    :data:`MAX_GUIDANCE`]."""
    if isinstance(guidance, bool) or not isinstance(guidance, (int, float)) or not math.isfinite(guidance) \
            or not 0 <= guidance <= MAX_GUIDANCE:
        raise ValueError(f"{name} must be a finite number in [0, {MAX_GUIDANCE:g}] (1 = no guidance; the video "
                         f"backbones use 5-6), got {guidance!r}")
    return float(guidance)


def _check_shift(shift: float) -> None:
    if not (isinstance(shift, (int, float)) and math.isfinite(shift) and shift > 0):
        raise ValueError(f"shift must be a finite number > 0, got {shift!r}")


def _check_sampler(sampler: str) -> None:
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")


def _check_steps(steps: int) -> None:
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, got {steps!r}")


def shift_sigmas(sigma: Tensor | float, shift: float) -> Tensor | float:
    """Timestep shift σ' = s·σ / (1 + (s − 1)·σ).

    Esser et al. 2024 (SD3, "Scaling Rectified Flow Transformers for High-Resolution Image
    Synthesis"), §5.3.2, Eq. 23 with s = √(m/n) (the resolution ratio); video DiTs use s as a free
    hyper-parameter. Properties: s = 1 is the identity, σ = 0 and σ = 1 are fixed, the map is strictly
    increasing, and s > 1 moves every interior σ towards noise (σ' > σ).

    Args:
        sigma: tensor of any shape, or a float, values in [0, 1].
        shift: s > 0.

    Returns:
        Same type and shape as ``sigma``, values in [0, 1].

    Raises:
        ValueError: ``shift`` is not a finite number > 0.
    """
    _check_shift(shift)
    return shift * sigma / (1.0 + (shift - 1.0) * sigma)


def sigma_schedule(steps: int, shift: float = 1.0, *, dtype: torch.dtype = torch.float32,
                   device: torch.device | str | None = None) -> Tensor:
    """Sampling grid: ``steps + 1`` noise levels from 1 to 0, uniform in σ before the shift.

    σ_i = shift_sigmas(1 − i/steps, shift), i = 0..steps, so σ_0 = 1 (pure noise) and σ_steps = 0
    (data). Computed in float64 on the CPU (the same bits on every device), then cast to ``dtype`` on ``device``.

    Returns:
        (steps + 1,) strictly decreasing tensor.

    Raises:
        ValueError: ``steps`` is not an int ≥ 1, or ``shift`` is not > 0.
    """
    _check_steps(steps)
    base = torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64, device="cpu")  # the same grid on every device
    return shift_sigmas(base, shift).to(dtype=dtype, device=device)


def sample_logit_normal(n: int, mean: float = 0.0, std: float = 1.0, generator: torch.Generator | None = None,
                        *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
    """Training noise levels σ = sigmoid(u), u ~ N(mean, std²) (logit-normal, SD3 §3.1, Eq. 19).

    The density π(σ) = 1/(std·√(2π)) · 1/(σ(1 − σ)) · exp(−(logit σ − mean)² / (2 std²)) puts more
    weight on intermediate σ, where the velocity is hardest to predict; ``mean`` > 0 favours noise.

    Args:
        n: number of samples ≥ 1.
        generator: optional ``torch.Generator`` for reproducibility (must live on ``device``).

    Returns:
        (n,) tensor with values in the open interval (0, 1) (up to float rounding at |u| ≫ 1).

    Raises:
        ValueError: ``n`` < 1 or ``std`` ≤ 0.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    if not std > 0:
        raise ValueError(f"std must be > 0, got {std!r}")
    u = torch.randn(n, generator=generator, device=device, dtype=torch.float64) * std + mean
    return torch.sigmoid(u).to(dtype)


def _sigma_like(sigma: Tensor | float, x: Tensor, name: str = "sigma") -> Tensor:
    """Broadcast σ (scalar, or (B,) per sample) against x (B, ...)."""
    sigma = torch.as_tensor(sigma, dtype=x.dtype, device=x.device)
    if sigma.ndim == 0:
        return sigma
    if sigma.ndim != 1 or sigma.shape[0] != x.shape[0]:
        raise ValueError(f"{name} must be a scalar or have shape ({x.shape[0]},) (one per batch item), "
                         f"got shape {tuple(sigma.shape)}")
    return sigma.reshape(-1, *([1] * (x.ndim - 1)))


def add_noise(x0: Tensor, noise: Tensor, sigma: Tensor | float) -> Tensor:
    """Point on the straight path x_σ = (1 − σ)·x0 + σ·ε (rectified flow, Liu et al. 2022, Eq. 1).

    Args:
        x0: (B, ...) clean samples (e.g. VAE latents (B, c, n, h, w)).
        noise: ε, same shape as ``x0``, usually standard normal.
        sigma: scalar or (B,) noise levels in [0, 1].

    Returns:
        (B, ...) noisy samples, same shape and dtype as ``x0``.

    Raises:
        ValueError: shape mismatch between ``x0`` and ``noise``, or ``sigma`` not scalar/(B,).
    """
    if x0.shape != noise.shape:
        raise ValueError(f"noise shape {tuple(noise.shape)} must equal x0 shape {tuple(x0.shape)}")
    s = _sigma_like(sigma, x0)
    return (1.0 - s) * x0 + s * noise


def velocity_target(x0: Tensor, noise: Tensor) -> Tensor:
    """Regression target v = dx_σ/dσ = ε − x0 (independent of σ for the straight path).

    Args:
        x0: (B, ...) clean samples; noise: ε of the same shape.

    Returns:
        (B, ...) target velocity.

    Raises:
        ValueError: shape mismatch.
    """
    if x0.shape != noise.shape:
        raise ValueError(f"noise shape {tuple(noise.shape)} must equal x0 shape {tuple(x0.shape)}")
    return noise - x0


def _check_sigmas(sigmas: Tensor) -> None:
    if sigmas.ndim != 1 or sigmas.shape[0] < 2:
        raise ValueError(f"sigmas must be a 1-D tensor with >= 2 entries, got shape {tuple(sigmas.shape)}")
    if bool((sigmas[1:] >= sigmas[:-1]).any()):
        raise ValueError("sigmas must be strictly decreasing (from noise to data)")


def _checked(v: Tensor, x: Tensor) -> Tensor:
    """``v``, the velocity at ``x``, after checking it has ``x``'s shape (called on the result, so the sampling
    loop calls ``velocity_fn`` itself)."""
    if v.shape != x.shape:
        raise ValueError(f"velocity_fn returned shape {tuple(v.shape)}, expected {tuple(x.shape)}")
    return v


def euler_sample(velocity_fn: VelocityFn, noise: Tensor, sigmas: Tensor, progress: bool = False) -> Tensor:
    """Integrate dx/dσ = v(x, σ) from σ_0 to σ_N with explicit Euler steps (first order).

    x_{i+1} = x_i + (σ_{i+1} − σ_i)·v(x_i, σ_i). NFE = N = len(sigmas) − 1. Global error O(h) in the
    step size h. A velocity field that is constant along its trajectories (one data point) is
    integrated exactly, in any number of steps.

    Args:
        velocity_fn: ``f(x, sigma) -> v``; ``sigma`` is a 0-dim tensor (dtype/device of ``noise``).
        noise: starting state at σ_0 (usually σ_0 = 1 and standard normal), any shape.
        sigmas: (N + 1,) strictly decreasing noise levels, e.g. :func:`sigma_schedule`.
        progress: show a tqdm progress bar.

    Returns:
        State at σ_N, same shape as ``noise``.

    Raises:
        ValueError: ``sigmas`` not 1-D, shorter than 2 or not strictly decreasing; the velocity has
            the wrong shape.
    """
    _check_sigmas(sigmas)
    sig = sigmas.to(dtype=noise.dtype, device=noise.device)
    x = noise
    for i in tqdm(range(sig.shape[0] - 1), disable=not progress, desc="euler"):
        x = x + (sig[i + 1] - sig[i]) * _checked(velocity_fn(x, sig[i]), x)
    return x


def heun_sample(velocity_fn: VelocityFn, noise: Tensor, sigmas: Tensor, progress: bool = False) -> Tensor:
    """Integrate dx/dσ = v(x, σ) with Heun's second-order method (explicit trapezoidal rule).

    Per step h = σ_{i+1} − σ_i (Karras et al. 2022, "Elucidating the Design Space of Diffusion-Based
    Generative Models", Algorithm 1):

        d  = v(x_i, σ_i)
        x̃  = x_i + h·d                           (Euler predictor)
        x_{i+1} = x_i + h·(d + v(x̃, σ_{i+1}))/2    (trapezoidal corrector)

    A step that ends at σ = 0 skips the corrector (plain Euler), because the network is never
    evaluated at σ = 0 (the learned field is ill-conditioned there: for a single data point the exact
    field is (x − x0)/σ). NFE = 2·N − 1 when only the last σ is 0, else 2·N; global error O(h²)
    (the single first-order last step adds only a local O(h²) error).

    Args / Returns / Raises: as :func:`euler_sample`.
    """
    _check_sigmas(sigmas)
    sig = sigmas.to(dtype=noise.dtype, device=noise.device)
    is_zero = (sigmas == 0).tolist()  # host-side flags: no device sync inside the loop
    x = noise
    for i in tqdm(range(sig.shape[0] - 1), disable=not progress, desc="heun"):
        h = sig[i + 1] - sig[i]
        d = _checked(velocity_fn(x, sig[i]), x)
        x_pred = x + h * d
        if is_zero[i + 1]:
            x = x_pred
        else:
            x = x + h * 0.5 * (d + _checked(velocity_fn(x_pred, sig[i + 1]), x_pred))
    return x


def sample(velocity_fn: VelocityFn, noise: Tensor, steps: int, sampler: str = "euler", shift: float = 1.0,
           progress: bool = False) -> Tensor:
    """Generate samples: integrate from pure noise (σ = 1) to data (σ = 0).

    Uses :func:`sigma_schedule` ``(steps, shift)`` and :func:`euler_sample` (NFE = steps) or
    :func:`heun_sample` (NFE = 2·steps − 1).

    Args:
        velocity_fn: ``f(x, sigma) -> v`` with ``sigma`` a 0-dim tensor.
        noise: standard-normal starting state, any shape (e.g. (B, c, n, h, w)).
        steps: integration steps ≥ 1.
        sampler: ``"euler"`` or ``"heun"``.
        shift: timestep shift s > 0 (:func:`shift_sigmas`).
        progress: tqdm progress bar.

    Returns:
        Samples at σ = 0, same shape as ``noise``.

    Raises:
        ValueError: unknown ``sampler``, ``steps`` not an int ≥ 1, ``shift`` ≤ 0.
    """
    fn = integrator(sampler)
    sigmas = sigma_schedule(steps, shift, dtype=torch.float64)
    return fn(velocity_fn, noise, sigmas, progress=progress)


def integrator(sampler: str) -> Callable[..., Tensor]:
    """The integration function of ``sampler``: :func:`euler_sample` or :func:`heun_sample`.

    Raises:
        ValueError: ``sampler`` not in :data:`SAMPLERS`.
    """
    _check_sampler(sampler)
    return {"euler": euler_sample, "heun": heun_sample}[sampler]
