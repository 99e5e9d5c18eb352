"""Rectified-flow / flow-matching schedule, training-time σ sampling and ODE samplers.

x_σ = (1 − σ)·x0 + σ·ε, σ ∈ [0, 1] (σ = 1 pure noise); the network learns v = dx_σ/dσ = ε − x0 (rectified flow,
Liu et al. 2022, Eq. 1; Lipman et al. 2023, Eq. 20–23 with t = 1 − σ; docs/DESIGN.md "Conventions"). Sampling integrates
dx/dσ = v_θ(x, σ) from σ = 1 to 0. ``velocity_fn(x, sigma)`` is any callable taking the state ``x`` (any shape)
and a 0-dim ``sigma`` of its dtype/device and returning a velocity of ``x``'s shape."""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm.auto import tqdm

__all__ = ["FlowMatchingConfig", "check_guidance", "check_sampler", "MAX_GUIDANCE", "PAPER_FLOW_MATCHING", "SAMPLERS",
           "ODESteps", "shift_sigmas", "sigma_schedule", "sample_logit_normal", "add_noise", "velocity_target",
           "euler_sample", "heun_sample", "sample"]

VelocityFn = Callable[[Tensor, Tensor], Tensor]
SAMPLERS = ("euler", "heun")


@dataclass
class FlowMatchingConfig:
    """Schedule and sampler settings (the single source of defaults; YAML files override fields).

    Attributes:
        shift: timestep shift s > 0 (:func:`shift_sigmas`); s > 1 spends more steps near noise (SD3 §5.3.2).
        sampler: ``"euler"`` (NFE = steps) or ``"heun"`` (NFE = 2·steps − 1).
        steps: integration steps ≥ 1.
        logit_normal_mean, logit_normal_std: m and s > 0 of the logit-normal training σ distribution (SD3 §3.1).
        guidance: classifier-free guidance scale g (:func:`check_guidance`; Ho & Salimans 2022, Eq. 6:
            v = v_uncond + g·(v_text − v_uncond)); 1 = none; applied only with a prompt.

    Raises:
        ValueError: a field out of range.
    """

    shift: float = 1.0
    sampler: str = "euler"
    steps: int = 8
    logit_normal_mean: float = 0.0
    logit_normal_std: float = 1.0
    guidance: float = 1.0

    def __post_init__(self) -> None:
        _check_shift(self.shift)
        check_sampler(self.sampler)
        _check_steps(self.steps)
        if not self.logit_normal_std > 0:
            raise ValueError(f"FlowMatchingConfig.logit_normal_std must be > 0, got {self.logit_normal_std}")
        check_guidance(self.guidance, "FlowMatchingConfig.guidance")

    @classmethod
    def paper(cls) -> FlowMatchingConfig:
        """Paper-scale settings (:data:`PAPER_FLOW_MATCHING`)."""
        return cls(**PAPER_FLOW_MATCHING)


PAPER_FLOW_MATCHING: dict = dict(shift=3.0, sampler="euler", steps=50, logit_normal_mean=0.0, logit_normal_std=1.0)
"""Paper-scale schedule (``configs/paper.yaml``): SD3's shift 3.0 and logit-normal(0, 1) (Esser et al. 2024, §3.1,
§5.3.2) and 50 Euler steps; our choices, not Diff4Splat's numbers."""


MAX_GUIDANCE = 30.0
"""Largest classifier-free guidance scale accepted: past a few tens w·(v_c − v_u) swamps the velocity and the
sampler saturates (the video backbones default to 5–6)."""


def check_guidance(guidance: float, name: str = "guidance") -> float:
    """``guidance`` as a float; ValueError (naming ``name``) unless finite in [0, :data:`MAX_GUIDANCE`]."""
    if isinstance(guidance, bool) or not isinstance(guidance, (int, float)) or not math.isfinite(guidance) \
            or not 0 <= guidance <= MAX_GUIDANCE:
        raise ValueError(f"{name} must be a finite number in [0, {MAX_GUIDANCE:g}] (1 = no guidance; the video "
                         f"backbones use 5-6), got {guidance!r}")
    return float(guidance)


def _check_shift(shift: float) -> None:
    if not (isinstance(shift, (int, float)) and math.isfinite(shift) and shift > 0):
        raise ValueError(f"shift must be a finite number > 0, got {shift!r}")


def check_sampler(sampler: str, name: str = "sampler") -> None:
    """ValueError (naming ``name``) unless ``sampler`` is one of :data:`SAMPLERS`."""
    if sampler not in SAMPLERS:
        raise ValueError(f"{name} must be one of {SAMPLERS}, got {sampler!r}")


def _check_steps(steps: int) -> None:
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1, got {steps!r}")


def shift_sigmas(sigma: Tensor | float, shift: float) -> Tensor | float:
    """Timestep shift σ' = s·σ / (1 + (s − 1)·σ) (SD3, Esser et al. 2024, §5.3.2, Eq. 23): increasing, fixes 0 and 1,
    s > 1 moves σ towards noise. ``sigma`` a float or tensor in [0, 1] → same type and shape.

    Raises:
        ValueError: ``shift`` is not a finite number > 0.
    """
    _check_shift(shift)
    return shift * sigma / (1.0 + (shift - 1.0) * sigma)


def sigma_schedule(steps: int, shift: float = 1.0, *, dtype: torch.dtype = torch.float32,
                   device: torch.device | str | None = None) -> Tensor:
    """``steps + 1`` strictly decreasing noise levels σ_i = shift_sigmas(1 − i/steps, shift), 1 → 0; computed in
    float64 on the CPU (the same on every device), cast to ``dtype`` on ``device``.

    Raises:
        ValueError: ``steps`` not an int ≥ 1, or ``shift`` not > 0.
    """
    _check_steps(steps)
    base = torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64, device="cpu")  # the same grid on every device
    return shift_sigmas(base, shift).to(dtype=dtype, device=device)


def sample_logit_normal(n: int, mean: float = 0.0, std: float = 1.0, generator: torch.Generator | None = None,
                        *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
    """(n,) training noise levels σ = sigmoid(u), u ~ N(mean, std²) (logit-normal, SD3 §3.1, Eq. 19), in (0, 1);
    ``generator`` must live on ``device``.

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
    """σ (scalar or (B,)) broadcast against x (B, ...); ValueError otherwise."""
    sigma = torch.as_tensor(sigma, dtype=x.dtype, device=x.device)
    if sigma.ndim == 0:
        return sigma
    if sigma.ndim != 1 or sigma.shape[0] != x.shape[0]:
        raise ValueError(f"{name} must be a scalar or have shape ({x.shape[0]},) (one per batch item), "
                         f"got shape {tuple(sigma.shape)}")
    return sigma.reshape(-1, *([1] * (x.ndim - 1)))


def _check_pair(x0: Tensor, noise: Tensor) -> None:
    if x0.shape != noise.shape:
        raise ValueError(f"noise shape {tuple(noise.shape)} must equal x0 shape {tuple(x0.shape)}")


def add_noise(x0: Tensor, noise: Tensor, sigma: Tensor | float) -> Tensor:
    """x_σ = (1 − σ)·x0 + σ·ε (Liu et al. 2022, Eq. 1): x0, noise (B, ...), sigma scalar or (B,) in [0, 1] → (B, ...).

    Raises:
        ValueError: ``x0`` and ``noise`` shapes differ, or ``sigma`` is not scalar/(B,).
    """
    _check_pair(x0, noise)
    s = _sigma_like(sigma, x0)
    return (1.0 - s) * x0 + s * noise


def velocity_target(x0: Tensor, noise: Tensor) -> Tensor:
    """Regression target v = ε − x0, (B, ...); ValueError on a shape mismatch."""
    _check_pair(x0, noise)
    return noise - x0


class ODESteps:
    """The samplers as a loop the caller drives, one velocity evaluation at a time (as diffusers' ``scheduler.step``):
    for each σ of :attr:`sigmas` evaluate v at the current state, and :meth:`step` returns the next state to evaluate
    at; after the last, the state at σ_N.

    - ``"euler"``: x_{i+1} = x_i + (σ_{i+1} − σ_i)·v(x_i, σ_i); NFE = N.
    - ``"heun"`` (Karras et al. 2022, Algorithm 1): d = v(x_i, σ_i), x̃ = x_i + h·d,
      x_{i+1} = x_i + h·(d + v(x̃, σ_{i+1}))/2; a step ending at σ = 0 is plain Euler (the network is never evaluated
      at σ = 0), so NFE = 2·N − 1.

    Args:
        sampler: one of :data:`SAMPLERS`.
        sigmas: (N + 1,) strictly decreasing, e.g. :func:`sigma_schedule`; cast to ``noise``'s dtype and device.
        noise: the state at σ_0 (any shape; its dtype and device are the loop's).

    Raises:
        ValueError: an unknown ``sampler``; ``sigmas`` not 1-D, shorter than 2 or not decreasing; (:meth:`step`) a
            velocity of the wrong shape.
    """

    def __init__(self, sampler: str, sigmas: Tensor, noise: Tensor):
        check_sampler(sampler)
        if sigmas.ndim != 1 or sigmas.shape[0] < 2:
            raise ValueError(f"sigmas must be a 1-D tensor with >= 2 entries, got shape {tuple(sigmas.shape)}")
        if bool((sigmas[1:] >= sigmas[:-1]).any()):
            raise ValueError("sigmas must be strictly decreasing (from noise to data)")
        self.sampler = sampler
        self._sig = sigmas.to(dtype=noise.dtype, device=noise.device)
        is_zero = (sigmas == 0).tolist()  # host-side flags: no device sync inside the loop
        # each evaluation: (step i, whether it is Heun's corrector at σ_{i+1})
        self._plan = [(i, corrector) for i in range(len(is_zero) - 1)
                      for corrector in ((False, True) if sampler == "heun" and not is_zero[i + 1] else (False,))]
        self.sigmas = [self._sig[i + corrector] for i, corrector in self._plan]  # (NFE,) 0-dim tensors
        self._k = 0
        self._x = self._d = None  # Heun: x_i and d while its corrector is pending

    def step(self, velocity: Tensor, x: Tensor) -> Tensor:
        """The velocity ``velocity`` at the state ``x`` and σ = ``sigmas[k]`` (the k-th call) → the next state."""
        if velocity.shape != x.shape:
            raise ValueError(f"velocity_fn returned shape {tuple(velocity.shape)}, expected {tuple(x.shape)}")
        i, corrector = self._plan[self._k]
        self._k += 1
        h = self._sig[i + 1] - self._sig[i]
        if corrector:
            return self._x + h * 0.5 * (self._d + velocity)
        if self._k < len(self._plan) and self._plan[self._k] == (i, True):
            self._x, self._d = x, velocity
        return x + h * velocity


def euler_sample(velocity_fn: VelocityFn, noise: Tensor, sigmas: Tensor, progress: bool = False) -> Tensor:
    """Integrate dx/dσ = v(x, σ) over ``sigmas`` with explicit Euler steps (:class:`ODESteps`); NFE = len(sigmas) − 1.

    Args:
        velocity_fn: ``f(x, sigma) -> v``.
        noise: the state at σ_0, any shape.
        sigmas: (N + 1,) strictly decreasing, e.g. :func:`sigma_schedule`.
        progress: show a tqdm bar.

    Returns the state at σ_N, shaped as ``noise``.

    Raises:
        ValueError: ``sigmas`` not 1-D, shorter than 2 or not decreasing; a velocity of the wrong shape.
    """
    return _integrate(ODESteps("euler", sigmas, noise), velocity_fn, noise, progress)


def heun_sample(velocity_fn: VelocityFn, noise: Tensor, sigmas: Tensor, progress: bool = False) -> Tensor:
    """Integrate dx/dσ = v(x, σ) with Heun's second-order method (:class:`ODESteps`); NFE = 2·N − 1. Args, returns,
    raises: as :func:`euler_sample`."""
    return _integrate(ODESteps("heun", sigmas, noise), velocity_fn, noise, progress)


def _integrate(steps: ODESteps, velocity_fn: VelocityFn, x: Tensor, progress: bool) -> Tensor:
    """``steps`` driven by ``velocity_fn`` from ``x``: the state at the last σ."""
    for sigma in tqdm(steps.sigmas, disable=not progress, desc=steps.sampler):
        x = steps.step(velocity_fn(x, sigma), x)
    return x


def sample(velocity_fn: VelocityFn, noise: Tensor, steps: int, sampler: str = "euler", shift: float = 1.0,
           progress: bool = False) -> Tensor:
    """Integrate from noise (σ = 1) to data (σ = 0) over :func:`sigma_schedule` ``(steps, shift)`` with the
    ``sampler`` (:class:`ODESteps`); ``noise`` standard normal, any shape → samples of its shape.

    Raises:
        ValueError: unknown ``sampler``, ``steps`` not an int ≥ 1, ``shift`` ≤ 0.
    """
    return _integrate(ODESteps(sampler, sigma_schedule(steps, shift, dtype=torch.float64), noise), velocity_fn,
                      noise, progress)
