"""Tests for models/flow_matching.py: schedule, σ sampling, noising and the Euler/Heun samplers.

The samplers are checked against a closed form. For data x0 ~ N(m, s²) (per coordinate) and
independent ε ~ N(0, 1), x_σ = (1 − σ)·x0 + σ·ε is jointly Gaussian with (x0, ε), so

    V(σ)       = Var x_σ = (1 − σ)²·s² + σ²
    E[x0 | x]  = m + (1 − σ)·s²/V · (x − (1 − σ)·m)
    E[ε  | x]  =          σ/V       · (x − (1 − σ)·m)
    v(x, σ)    = E[ε − x0 | x] = (σ − (1 − σ)·s²)/V · (x − (1 − σ)·m) − m.

Its ODE flow from σ = 1 is x(σ) = (1 − σ)·m + √V(σ)·z with z = x(1) (differentiate: dx/dσ = −m +
V'/(2V)·(x − (1 − σ)m), V'/2 = σ − (1 − σ)s²), so the exact sample is x(0) = m + s·z for every noise z.
"""
from __future__ import annotations

import math

import pytest
import torch

from models.flow_matching import (
    PAPER_FLOW_MATCHING,
    FlowMatchingConfig,
    add_noise,
    euler_sample,
    heun_sample,
    sample,
    sample_logit_normal,
    shift_sigmas,
    sigma_schedule,
    velocity_target,
)

M, S = 0.7, 0.3


def gaussian_velocity(m: float, s: float):
    """Exact E[ε − x0 | x_σ = x] for x0 ~ N(m, s²), ε ~ N(0, 1) (derivation in the module docstring)."""

    def fn(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        var = (1 - sigma) ** 2 * s**2 + sigma**2
        return (sigma - (1 - sigma) * s**2) / var * (x - (1 - sigma) * m) - m

    return fn


def test_closed_form_velocity_is_the_regression_target():
    # v(x, σ) is the least-squares regressor of ε − x0 on x_σ (it is linear because everything is Gaussian).
    g = torch.Generator().manual_seed(0)
    n = 400_000
    x0 = M + S * torch.randn(n, generator=g, dtype=torch.float64)
    eps = torch.randn(n, generator=g, dtype=torch.float64)
    for sigma in (0.2, 0.5, 0.9):
        xs = add_noise(x0, eps, sigma)
        target = velocity_target(x0, eps)
        design = torch.stack([xs, torch.ones_like(xs)], dim=1)
        slope, intercept = torch.linalg.lstsq(design, target[:, None]).solution[:, 0]
        v = gaussian_velocity(M, S)
        sig = torch.tensor(sigma, dtype=torch.float64)
        exact_intercept = v(torch.tensor(0.0, dtype=torch.float64), sig)
        exact_slope = v(torch.tensor(1.0, dtype=torch.float64), sig) - exact_intercept
        assert abs(float(slope - exact_slope)) < 0.01
        assert abs(float(intercept - exact_intercept)) < 0.01


@pytest.mark.parametrize("sampler, steps, tol", [("euler", 200, 5e-3), ("heun", 40, 1.5e-3)])
def test_samplers_reproduce_gaussian_data(sampler, steps, tol):
    g = torch.Generator().manual_seed(1)
    z = torch.randn(20_000, generator=g, dtype=torch.float64)
    out = sample(gaussian_velocity(M, S), z, steps=steps, sampler=sampler)
    assert abs(float(out.mean()) - M) < 0.01
    assert abs(float(out.std()) - S) < 0.01
    # Pathwise: the exact flow maps z to m + s·z; the discretisation error grows linearly with |z|.
    assert bool(((out - (M + S * z)).abs() < tol * (1 + z.abs())).all())


def _max_err(sampler_fn, steps, shift, z, ref):
    return float((sampler_fn(gaussian_velocity(M, S), z, sigma_schedule(steps, shift, dtype=torch.float64))
                  - ref).abs().max())


@pytest.mark.parametrize("shift", [1.0, 3.0])
def test_convergence_orders_euler_1_heun_2(shift):
    z = torch.linspace(-3, 3, 13, dtype=torch.float64)
    ref = heun_sample(gaussian_velocity(M, S), z, sigma_schedule(1024, shift, dtype=torch.float64))
    # The reference agrees with the closed form far below the coarse-grid errors (≥ 2e-4 at 128 steps).
    assert float((ref - (M + S * z)).abs().max()) < 5e-5
    steps = [16, 32, 64, 128]  # asymptotic regime (8 steps is still pre-asymptotic for Heun)
    e_euler = [_max_err(euler_sample, n, shift, z, ref) for n in steps]
    e_heun = [_max_err(heun_sample, n, shift, z, ref) for n in steps]
    order_euler = [math.log2(a / b) for a, b in zip(e_euler, e_euler[1:], strict=False)]
    order_heun = [math.log2(a / b) for a, b in zip(e_heun, e_heun[1:], strict=False)]
    assert all(0.8 < p < 1.25 for p in order_euler), order_euler
    assert all(1.7 < p < 2.4 for p in order_heun), order_heun
    # Heun beats Euler at every step count, and its advantage doubles with every doubling of steps
    # (ratio ∝ h); at 64 and 128 steps Heun's error is below a fifth of Euler's (1/28 and 1/58 at shift 1).
    ratios = [b / a for a, b in zip(e_euler, e_heun, strict=True)]
    assert all(r < 1 for r in ratios), ratios
    assert all(r2 < 0.6 * r1 for r1, r2 in zip(ratios, ratios[1:], strict=False)), ratios
    assert all(r < 0.2 for r in ratios[2:]), ratios


def test_single_point_data_is_integrated_exactly_and_heun_avoids_sigma_zero():
    # Data = one point c: the exact field (x − c)/σ is constant (= ε − c) along each straight path.
    c = torch.tensor([0.25, -1.5, 2.0], dtype=torch.float64)
    calls = []

    def fn(x, sigma):
        calls.append(float(sigma))
        assert float(sigma) > 0, "velocity evaluated at sigma = 0"
        return (x - c) / sigma

    z = torch.tensor([1.0, -0.3, 0.4], dtype=torch.float64)
    out = euler_sample(fn, z, torch.tensor([1.0, 0.0], dtype=torch.float64))
    assert calls == [1.0]
    assert torch.allclose(out, c, atol=1e-15, rtol=0)
    for steps in (1, 2, 5):
        calls.clear()
        out = sample(fn, z, steps=steps, sampler="heun", shift=2.0)
        assert len(calls) == 2 * steps - 1  # NFE of Heun with the last step plain Euler
        assert torch.allclose(out, c, atol=1e-12, rtol=0)
        calls.clear()
        out = sample(fn, z, steps=steps, sampler="euler")
        assert len(calls) == steps
        assert torch.allclose(out, c, atol=1e-12, rtol=0)


def test_shift_properties():
    sig = torch.linspace(0, 1, 101, dtype=torch.float64)
    assert torch.equal(shift_sigmas(sig, 1.0), sig)
    for s in (0.5, 2.0, 3.0, 7.5):
        out = shift_sigmas(sig, s)
        assert float(out[0]) == 0.0 and float(out[-1]) == 1.0
        assert bool((out[1:] > out[:-1]).all())  # strictly increasing
        interior = out[1:-1] > sig[1:-1]
        assert bool(interior.all()) if s > 1 else not bool(interior.any())
    assert shift_sigmas(0.5, 3.0) == pytest.approx(0.75)  # 3·0.5 / (1 + 2·0.5)
    # Resolution-dependent shift composes: shifting by a then b equals shifting by a·b.
    assert torch.allclose(shift_sigmas(shift_sigmas(sig, 2.0), 1.5), shift_sigmas(sig, 3.0), atol=1e-15)


def test_sigma_schedule():
    s = sigma_schedule(4)
    assert s.shape == (5,) and s.dtype == torch.float32
    assert torch.allclose(s, torch.tensor([1.0, 0.75, 0.5, 0.25, 0.0]))
    s3 = sigma_schedule(10, 3.0, dtype=torch.float64)
    assert float(s3[0]) == 1.0 and float(s3[-1]) == 0.0
    assert torch.allclose(s3, shift_sigmas(torch.linspace(1, 0, 11, dtype=torch.float64), 3.0))


def test_logit_normal_statistics_and_reproducibility():
    g = torch.Generator().manual_seed(3)
    sig = sample_logit_normal(100_000, mean=0.5, std=0.8, generator=g)
    assert sig.shape == (100_000,) and bool(((sig > 0) & (sig < 1)).all())
    logit = torch.logit(sig.double())
    assert abs(float(logit.mean()) - 0.5) < 0.02
    assert abs(float(logit.std()) - 0.8) < 0.02
    a = sample_logit_normal(5, generator=torch.Generator().manual_seed(7))
    b = sample_logit_normal(5, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def test_add_noise_endpoints_broadcast_and_derivative():
    g = torch.Generator().manual_seed(4)
    x0 = torch.randn(3, 2, 5, 4, 4, generator=g, dtype=torch.float64)
    eps = torch.randn(3, 2, 5, 4, 4, generator=g, dtype=torch.float64)
    assert torch.equal(add_noise(x0, eps, 0.0), x0)
    assert torch.equal(add_noise(x0, eps, 1.0), eps)
    sig = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    out = add_noise(x0, eps, sig)
    for b in range(3):
        assert torch.allclose(out[b], (1 - sig[b]) * x0[b] + sig[b] * eps[b])
    # The target is the σ-derivative of the path.
    s = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    (jvp,) = torch.autograd.grad(add_noise(x0, eps, s), s, grad_outputs=torch.ones_like(x0))
    assert torch.allclose(jvp, velocity_target(x0, eps).sum())
    fd = (add_noise(x0, eps, 0.3 + 1e-6) - add_noise(x0, eps, 0.3 - 1e-6)) / 2e-6
    assert torch.allclose(fd, velocity_target(x0, eps), atol=1e-8)


def test_invalid_inputs_raise():
    fn = gaussian_velocity(M, S)
    z = torch.zeros(4)
    with pytest.raises(ValueError, match="sampler"):
        sample(fn, z, steps=4, sampler="dpm")
    for bad in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="steps"):
            sample(fn, z, steps=bad)
    with pytest.raises(ValueError, match="shift"):
        sample(fn, z, steps=4, shift=0.0)
    with pytest.raises(ValueError, match="decreasing"):
        euler_sample(fn, z, torch.tensor([0.0, 1.0]))
    with pytest.raises(ValueError, match="1-D"):
        heun_sample(fn, z, torch.tensor([1.0]))
    with pytest.raises(ValueError, match="velocity_fn"):
        euler_sample(lambda x, s: x[:2], z, sigma_schedule(2))
    with pytest.raises(ValueError, match="sigma"):
        add_noise(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(3))
    with pytest.raises(ValueError, match="noise shape"):
        add_noise(torch.zeros(2, 3), torch.zeros(2, 4), 0.5)
    with pytest.raises(ValueError, match="std"):
        sample_logit_normal(4, std=0.0)
    with pytest.raises(ValueError, match="sampler"):
        FlowMatchingConfig(sampler="ddim")


def test_config_defaults_paper_and_progress(capsys):
    cfg = FlowMatchingConfig()
    assert (cfg.shift, cfg.sampler, cfg.steps) == (1.0, "euler", 8)
    paper = FlowMatchingConfig.paper()
    assert paper.shift == PAPER_FLOW_MATCHING["shift"] == 3.0 and paper.steps == 50
    z = torch.randn(8, dtype=torch.float64)
    out = sample(gaussian_velocity(M, S), z, steps=3, sampler="heun", progress=True)
    assert out.shape == z.shape
    assert "heun" in capsys.readouterr().err
