"""The renderer on every device (docs/DESIGN.md "The renderer", diff4splat/utils/devices.py "the device rule").

- Dispatch: :func:`diff4splat.render.rasterize.choose_path` never sends a non-CPU tensor to the fused (numba)
  path; meta tensors stand in for CUDA ones on a CPU-only machine (their device type is not "cpu" either).
- No implicit device: every renderer entry point runs with torch's default device set to "meta"
  (``no_implicit_device``) and gives bit-for-bit the result of a plain run, so no tensor is made off the
  inputs' device — what would crash beside CUDA inputs fails here on the CPU.
- Devices: on CUDA (the ``device`` fixture) every entry point gives the CPU's images and gradients to float32
  rounding. The scene keeps opacities ≤ 0.3, so the gsplat backend's documented differences (0.999 alpha
  clamp, 3σ vs 1/255 boxes) do not arise when ``rasterize`` hands the call to gsplat.
"""
import importlib

import pytest
import torch

from diff4splat.cameras import CameraPath, FisheyePolynomial, RollingShutter, ThinLens
from diff4splat.render import rasterize, rasterize_dense, render_rolling_shutter
from diff4splat.render.fused import bin_tiles_fused, composite_fused
from diff4splat.render.rasterize import DEFAULT_COMPOSITOR, DEVICE_COMPOSITOR, PATHS, choose_path
from diff4splat.render.sequence import render_path
from diff4splat.render.tiles import (
    PAIR_BUDGET,
    PAIR_BUDGET_DEVICE,
    _stable_argsort_small,
    composite_dense,
    composite_tiles,
    pair_budget,
)
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians

rasterize_module = importlib.import_module("diff4splat.render.rasterize")  # the package re-exports the function
CPU = torch.device("cpu")
META = torch.device("meta")
W, H, N = 24, 20, 40


# ---------------------------------------------------------------------------------------------- dispatch


def test_choose_path_keeps_device_tensors_off_the_fused_path():
    cpu, dev = torch.empty(3, 3, device="cpu"), torch.empty(3, 3, device="meta")
    assert choose_path(cpu) == DEFAULT_COMPOSITOR == "fused"
    assert choose_path(dev) == DEVICE_COMPOSITOR == "torch"
    assert choose_path(torch.empty(3, 3, dtype=torch.float64, device="meta")) == "torch"
    assert choose_path(cpu, compositor="torch") == choose_path(dev, compositor="torch") == "torch"
    assert choose_path(cpu, compositor="fused") == "fused"
    with pytest.raises(ValueError, match="compositor='fused' runs on the CPU only.*meta"):
        choose_path(dev, compositor="fused")
    with pytest.raises(ValueError, match="compositor must be one of"):
        choose_path(cpu, compositor="cuda")
    # camera effects go to the ray path on every device, whatever the compositor
    for means in (cpu, dev):
        assert choose_path(means, "fisheye") == "ray"
        assert choose_path(means, camera_params=ThinLens(0.05, 3.0)) == "ray"
        assert choose_path(means, "fisheye", compositor="fused") == "ray"
    assert set(PATHS) == {"ray", "gsplat", "fused", "torch"}


def test_choose_path_prefers_gsplat_for_device_tensors_unless_told(monkeypatch):
    """With gsplat "available" for non-CPU tensors: None → gsplat, an explicit "torch" is honoured, CPU
    tensors never go to gsplat."""
    monkeypatch.setattr(rasterize_module, "use_gsplat", lambda means: means.device.type != "cpu")
    dev = torch.empty(3, 3, device="meta")
    assert choose_path(dev) == "gsplat"
    assert choose_path(dev, compositor="torch") == "torch"
    assert choose_path(torch.empty(3, 3, device="cpu")) == "fused"


def test_rasterize_never_hands_device_tensors_to_the_fused_compositor(monkeypatch):
    """End to end through ``rasterize`` with meta tensors (non-CPU): the pipeline it calls gets the PyTorch
    tile compositor; ``compositor="fused"`` is one clear ValueError before anything runs."""
    calls = []

    def record(compositor, *args, project, **kwargs):
        calls.append((compositor, project))
        return "rendered"

    monkeypatch.setattr(rasterize_module, "render_pipeline", record)
    args = [torch.empty(s, device="meta") for s in ((N, 3), (N, 4), (N, 3), (N,), (N, 3), (1, 4, 4), (1, 3, 3))]
    assert rasterize(*args, W, H) == "rendered"
    assert rasterize(*args, W, H, compositor="torch") == "rendered"
    assert [c for c, _ in calls] == [composite_tiles, composite_tiles]
    with pytest.raises(ValueError, match="CPU only"):
        rasterize(*args, W, H, compositor="fused")
    assert len(calls) == 2
    # CPU tensors still take the fused path by default
    rasterize(*[torch.empty(a.shape, device="cpu") for a in args], W, H)
    assert calls[-1][0] is composite_fused


def test_fused_functions_refuse_device_tensors():
    m = 5
    args = (torch.empty(m, 2, device="meta"), torch.empty(m, 3, device="meta"), torch.empty(m, device="meta"),
            torch.empty(m, device="meta"))
    with pytest.raises(ValueError, match="composite_fused runs on the CPU only"):
        composite_fused(args[0], args[1], args[2], args[3], torch.empty(m, 3, device="meta"), args[1], None, W, H, 16)
    with pytest.raises(ValueError, match="bin_tiles_fused runs on the CPU only"):
        bin_tiles_fused(args[0], args[1], args[2], args[3], W, H, 16)


def test_tile_sort_and_budget_per_device():
    """The numpy radix sort is for CPU keys only; device keys use torch's stable sort (no numpy), and the
    chunk budget is the device's."""
    keys = torch.tensor([3, 1, 3, 0, 1, 2], device="cpu")
    expected = torch.tensor([3, 1, 4, 5, 0, 2], device="cpu")
    assert torch.equal(_stable_argsort_small(keys, 4), expected)
    assert torch.equal(_stable_argsort_small(keys, 1 << 20), expected)
    assert _stable_argsort_small(keys.to("meta"), 4).device == META  # never through numpy
    assert pair_budget(CPU) == PAIR_BUDGET and pair_budget(META) == PAIR_BUDGET_DEVICE >= PAIR_BUDGET


def test_tensors_on_different_devices_raise_naming_the_tensor():
    args = [torch.rand(s, device="cpu") for s in ((N, 3), (N, 4), (N, 3), (N,), (N, 3))]
    vm, K = torch.eye(4, device="cpu")[None], torch.tensor([[[20.0, 0, 12], [0, 20.0, 10], [0, 0, 1]]], device="cpu")
    with pytest.raises(ValueError, match="Ks is on meta but means on cpu"):
        rasterize(*args, vm, K.to("meta"), W, H)
    with pytest.raises(ValueError, match="backgrounds is on meta but means on cpu"):
        rasterize_dense(*args, vm, K, W, H, backgrounds=torch.zeros(1, 3, device="meta"))


# ---------------------------------------------------------------------------------------------- the calls

SPLAT_CASES = {
    # name: (entry point, keyword arguments); sh_degree also sets the colours' layout
    "rasterize": (rasterize, dict(sh_degree=3, render_mode="RGB+ED")),  # CPU: fused; CUDA: gsplat or torch
    "rasterize_torch": (rasterize, dict(compositor="torch", sh_degree=None, render_mode="RGB+D",
                                        rasterize_mode="antialiased")),
    "rasterize_dense": (rasterize_dense, dict(sh_degree=1, render_mode="ED")),
    "raytrace_fisheye": (rasterize, dict(camera_model="fisheye", camera_params=FisheyePolynomial(k1=0.03),
                                         sh_degree=2, render_mode="RGB+ED")),
    "raytrace_thin_lens": (rasterize, dict(camera_params=ThinLens(0.05, 3.0, spp=2), sh_degree=None,
                                           render_mode="RGB")),
}
SCENE_CASES = ("render_path", "render_rolling_shutter")
CASES = (*SPLAT_CASES, *SCENE_CASES)


def _gaussian_tensors(sh_degree, seed=0):
    """means, quats, scales, opacities, colours (SH (N, K, 3) or plain (N, 3)) on the CPU, float32; two
    cameras. Opacities ≤ 0.3 (see the module docstring)."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, device="cpu")  # noqa: E731
    means = torch.stack([(r(N) - 0.5) * 2.0, (r(N) - 0.5) * 1.5, 2.0 + 2.0 * r(N)], -1)
    colors = (r(N, 3) if sh_degree is None
              else 0.3 * torch.randn(N, (sh_degree + 1) ** 2, 3, generator=g, device="cpu"))
    gauss = [means, torch.randn(N, 4, generator=g, device="cpu"), 0.04 + 0.12 * r(N, 3), 0.05 + 0.25 * r(N), colors]
    vms = torch.eye(4, device="cpu").repeat(2, 1, 1)
    vms[1, :3, 3] = torch.tensor([0.15, -0.05, 0.1], device="cpu")
    Ks = torch.tensor([[20.0, 0, 12], [0, 20.0, 10], [0, 0, 1]], device="cpu").expand(2, 3, 3).clone()
    return gauss, r(2, 3), vms, Ks


def _scene_and_path():
    """A dynamic scene (SH degree 1, moving along x) and a 3-camera path, CPU float32."""
    gauss, _, _, _ = _gaussian_tensors(1, seed=1)
    times = torch.tensor([0.0, 1.0], device="cpu")
    d_means = torch.zeros(2, N, 3, device="cpu")
    d_means[1, :, 0] = 0.2
    d_quats = torch.zeros(2, N, 4, device="cpu")
    d_quats[..., 0] = 1.0
    scene = DynamicGaussians(Gaussians(*gauss), times, d_means, d_quats, torch.zeros(2, N, 3, device="cpu"))
    vms = torch.eye(4, device="cpu").repeat(3, 1, 1)
    vms[:, 0, 3] = torch.tensor([0.0, -0.1, -0.2], device="cpu")
    Ks = torch.tensor([[20.0, 0, 12], [0, 20.0, 10], [0, 0, 1]], device="cpu").expand(3, 3, 3).clone()
    return scene, CameraPath(vms, Ks, W, H, times=torch.tensor([0.0, 0.5, 1.0], device="cpu"))


def _render(case: str, device: torch.device):
    """Run ``case`` on ``device`` (inputs built on the CPU, then moved): (outputs, gradients), on the CPU."""
    if case in SPLAT_CASES:
        fn, kw = SPLAT_CASES[case]
        gauss, bg, vms, Ks = _gaussian_tensors(kw["sh_degree"])
        leaves = [t.to(device).requires_grad_() for t in (*gauss, bg)]
        col, alpha, _ = fn(*leaves[:5], vms.to(device), Ks.to(device), W, H, backgrounds=leaves[5], **kw)
        outputs = (col, alpha)
    else:
        scene, path = _scene_and_path()
        c = scene.canonical
        leaves = [t.to(device).requires_grad_() for t in (c.means, c.opacities, c.sh)]
        moved = DynamicGaussians(Gaussians(leaves[0], c.quats.to(device), c.scales.to(device), leaves[1], leaves[2]),
                                 *(t.to(device) for t in (scene.times, scene.d_means, scene.d_quats, scene.d_scales)))
        if case == "render_path":  # no_grad by design: images only
            outputs, leaves = render_path(moved, path, background=(0.2, 0.4, 0.6)), []
        else:
            outputs = render_rolling_shutter(moved, path, RollingShutter(0.3, chunks=4), frames=[1, 2],
                                             background=(0.2, 0.4, 0.6))
    for out in outputs:
        assert out.device.type == device.type, (case, out.device)
    grads = []
    if leaves:
        loss = sum((o * torch.linspace(0.5, 1.5, o.numel(), device=device).reshape(o.shape)).sum() for o in outputs)
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        assert all(g is None or g.device.type == device.type for g in grads)
    return [o.detach().cpu() for o in outputs], [None if g is None else g.cpu() for g in grads]


@pytest.mark.parametrize("case", CASES)
def test_no_tensor_is_made_off_the_inputs_device(case, no_implicit_device):
    """CPU inputs with torch's default device set to meta: every tensor the renderer makes must name its
    device (a tensor made without ``device=`` would land on meta and fail beside the CPU inputs), and the
    result is bit-for-bit that of a plain run."""
    with torch.device("cpu"):
        ref_out, ref_grads = _render(case, CPU)
    assert torch.empty(0).device == META  # the fixture is active
    out, grads = _render(case, CPU)
    assert all(torch.equal(a, b) for a, b in zip(out, ref_out, strict=True)), case
    assert all((a is None and b is None) or torch.equal(a, b) for a, b in zip(grads, ref_grads, strict=True)), case


@pytest.mark.parametrize("case", CASES)
def test_every_device_gives_the_cpu_result(case, device):
    """The same call on ``device`` (CUDA: gsplat or the PyTorch tile path, never the fused one) agrees with the
    CPU's images and gradients to float32 rounding (gradients: also summation order / atomics)."""
    ref_out, ref_grads = _render(case, CPU)
    out, grads = _render(case, device)
    assert float(ref_out[1].max()) > 0.1  # something is drawn
    for a, b in zip(out, ref_out, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4 * max(1.0, float(b.abs().max())), rtol=0, msg=case)
    for a, b in zip(grads, ref_grads, strict=True):
        assert (a is None) == (b is None), case
        if b is not None:
            torch.testing.assert_close(a, b, atol=1e-3 * float(b.abs().max()) + 1e-7, rtol=0, msg=case)


def test_dense_reference_runs_on_the_inputs_device(no_implicit_device):
    """The dense oracle's own tensors (pixel grid, transmittance) follow its inputs."""
    g = torch.Generator(device="cpu").manual_seed(3)
    m = 6
    means2d = torch.rand(m, 2, generator=g, device="cpu") * torch.tensor([W, H], device="cpu")
    conics = torch.tensor([0.5, 0.0, 0.5], device="cpu").repeat(m, 1)
    col, alpha, _ = composite_dense(means2d, conics, torch.full((m,), 0.5, device="cpu"),
                                    torch.rand(m, generator=g, device="cpu"), torch.ones(m, 2, device="cpu"),
                                    conics, torch.zeros(2, device="cpu"), W, H, 16)
    assert col.device == alpha.device == CPU and float(alpha.max()) > 0.3
