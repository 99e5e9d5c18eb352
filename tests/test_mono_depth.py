"""Tests of models/mono_depth.py, the LDRM's frame-0 depth from it (``LDRMConfig.image_depth``) and the ``depth``
training objective (training/objectives.py)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import onnxruntime as ort
import pytest
import torch
from helpers import tiny_model
from torch.utils.data import default_collate

from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.cameras import camera_rays
from models.ldrm import LDRM, LDRMConfig, distance_activation, gaussian_activations
from models.mono_depth import MonoDepth
from training.objectives import TrainingModule
from training.stage_config import StageConfig, apply_freezing

H = W = 64


def _inputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    latents = torch.randn(1, 4, 2, H // 8, W // 8, generator=g)
    plucker = torch.randn(1, 1536, 2, H // 8, W // 8, generator=g)
    image = torch.rand(1, 3, H, W, generator=g) * 2 - 1
    return latents, plucker, image


def _randomise(module: torch.nn.Module, seed: int, std: float = 0.2) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * std)


def _ldrm(image_depth: int, seed: int = 0, grid: int = 0) -> LDRM:
    torch.manual_seed(seed)
    model = LDRM(LDRMConfig(image_branch=8, image_depth=image_depth, image_depth_grid=grid))
    _randomise(model.image_branch, 1)  # a trained branch: non-zero residuals on every channel
    return model


def test_a_new_depth_network_puts_frame_0_at_the_default_depth_and_changes_nothing_else():
    """Zero-initialised last layer: frame 0's distance is ``default_depth`` everywhere; every other map of frame
    0 and every map of the later frames are the LDRM's without the network."""
    plain, with_depth = _ldrm(0), _ldrm(8)
    missing = with_depth.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("image_depth.") for k in missing)
    latents, plucker, image = _inputs()
    a, b = plain(latents, plucker, image=image), with_depth(latents, plucker, image=image)
    torch.testing.assert_close(b.distance[:, 0], torch.full_like(b.distance[:, 0], 2.0), atol=1e-5, rtol=0)
    assert not torch.allclose(a.distance[:, 0], b.distance[:, 0])
    # the same values (up to the vectorised activations' rounding on a differently laid out tensor)
    torch.testing.assert_close(a.distance[:, 1:], b.distance[:, 1:], atol=1e-6, rtol=1e-6)
    for name in ("quats", "opacities", "colors"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), atol=1e-6, rtol=1e-6, msg=name)
    # scales are distance × a footprint factor: the factor is unchanged
    torch.testing.assert_close(a.scales / a.distance[..., None], b.scales / b.distance[..., None])


def test_frame_0_depth_reads_the_photograph_alone_and_the_whole_of_it():
    model = _ldrm(8)
    _randomise(model.image_depth, 2)
    latents, plucker, image = _inputs()
    with torch.no_grad():
        ref = model(latents, plucker, image=image).distance[:, 0]
        other_latents = model(latents.flip(-1) + 1.0, plucker * 0.5, image=image).distance[:, 0]
        poked = image.clone()
        poked[..., :2, :2] = -poked[..., :2, :2]
        far = model(latents, plucker, image=poked).distance[0, 0, -8:, -8:] - ref[0, -8:, -8:]
    assert torch.equal(ref, other_latents)  # not the latents, not the rays
    assert bool((far.abs() > 0).any())  # one corner of the photo reaches the opposite corner (global context)


def _bilinear_reference(cells: np.ndarray, size: int) -> np.ndarray:
    """(g, g) cell values → (size, size) by separable linear interpolation between cell centres, clamped at the
    borders (align_corners False), written out per pixel."""
    g = len(cells)
    weights = np.zeros((size, g))
    for p in range(size):
        x = min(max((p + 0.5) * g / size - 0.5, 0.0), g - 1.0)
        i = min(int(x), g - 2) if g > 1 else 0
        f = x - i
        weights[p, i] += 1 - f
        if g > 1:
            weights[p, i + 1] += f
    return weights @ cells @ weights.T


@pytest.mark.parametrize("grid", [1, 2, 4])
def test_a_depth_grid_is_the_bilinear_interpolation_of_the_cell_means(grid):
    """``grid`` g: the full-resolution output averaged over g×g cells (a loop over the cells here), interpolated
    bilinearly back (a per-pixel reference here); g = 1 is the image's mean everywhere."""
    full, coarse = MonoDepth(8), MonoDepth(8, grid=grid)
    _randomise(full, 4, std=0.05)
    coarse.load_state_dict(full.state_dict())
    image = _inputs()[2]
    with torch.no_grad():
        y, c = full(image)[0].double().numpy(), coarse(image)[0].double().numpy()
    s = H // grid
    means = np.array([[y[i * s:(i + 1) * s, j * s:(j + 1) * s].mean() for j in range(grid)] for i in range(grid)])
    np.testing.assert_allclose(c, _bilinear_reference(means, H), rtol=1e-5, atol=1e-5 * np.abs(y).max())
    assert np.abs(y - c).max() > 1e-3 * np.abs(y).max()  # not the full-resolution output


def test_distance_activation_is_the_one_of_gaussian_activations():
    cfg = LDRMConfig()
    raw = torch.randn(5, 7, 12, generator=torch.Generator().manual_seed(3)) * 4
    assert torch.equal(distance_activation(raw[..., 0], cfg), gaussian_activations(raw, cfg)[0])
    lo, hi = math.log(cfg.depth_min), math.log(cfg.depth_max)  # closed form at 0: the default depth
    assert float(distance_activation(torch.zeros(()), cfg)) == pytest.approx(cfg.default_depth, rel=1e-6)
    assert float(distance_activation(torch.tensor(80.0), cfg)) == pytest.approx(math.exp(hi), rel=1e-6)
    assert float(distance_activation(torch.tensor(-80.0), cfg)) == pytest.approx(math.exp(lo), rel=1e-6)


def test_errors_and_parameter_count():
    with pytest.raises(ValueError, match="levels ≥ 1"):
        MonoDepth(8, 0)
    with pytest.raises(ValueError, match="divisible by 8"):
        MonoDepth(8)(torch.zeros(1, 3, 12, 16))
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        MonoDepth(8)(torch.zeros(1, 4, 16, 16))
    with pytest.raises(ValueError, match="needs image_branch"):
        LDRMConfig(image_depth=8)
    with pytest.raises(ValueError, match="grid ≥ 0"):
        MonoDepth(8, grid=-1)
    with pytest.raises(ValueError, match="image_depth_grid must be ≥ 0"):
        LDRMConfig(image_branch=8, image_depth=8, image_depth_grid=-2)
    assert LDRM(LDRMConfig(image_branch=8, image_depth=8, image_depth_grid=4)).image_depth.grid == 4
    # closed form: stem 3·3·(3·C + C²) + 2C; encoder i: 3·3·(w_i·w_{i+1} + w_{i+1}²) + 2·w_{i+1}; global 1×1:
    # w_L² + w_L; decoder i: 3·3·((w_{i+1} + w_i)·w_i + w_i²) + 2·w_i; last 3×3: 9·C + 1
    C, L = 16, 3
    w = [C * 2 ** i for i in range(L + 1)]
    n = 9 * (3 * C + C * C) + 2 * C + w[L] ** 2 + w[L] + 9 * C + 1
    n += sum(9 * (w[i] * w[i + 1] + w[i + 1] ** 2) + 2 * w[i + 1] for i in range(L))
    n += sum(9 * ((w[i + 1] + w[i]) * w[i] + w[i] ** 2) + 2 * w[i] for i in range(L))
    assert sum(p.numel() for p in MonoDepth(C, L).parameters()) == n


SIZE, FRAMES = 32, 5


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("mono_depth_data")
    generate_scene(root, 0, seed=5, size=SIZE, frames=FRAMES, cameras=1, static_ratio=0.0)
    ds = ClipDataset(root, ClipConfig(num_frames=FRAMES, height=SIZE, width=SIZE, scenes="all", seed=0))
    return default_collate([ds[0]])


def _depth_module():
    model = tiny_model(image_branch=8)
    cfg = dataclasses.replace(model.config, ldrm=dataclasses.replace(model.config.ldrm, image_depth=4))
    model = type(model).random(cfg, seed=0)
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, objectives=("depth",), train=("ldrm.image_depth",))
    counts = apply_freezing(model, stage.train)
    assert counts["ldrm.image_depth"] == sum(p.numel() for p in model.ldrm.image_depth.parameters())
    return TrainingModule(model, stage), model


def test_the_depth_objective_is_the_log_loss_of_each_frames_z_depth(batch, monkeypatch):
    """Closed form: a network whose ray distances are the true ones × 2 everywhere has log error log 2 at every
    pixel, so the loss is (1 − λ)·(log 2)² = 0.5·(log 2)²; with the true ones it is 0. Only the depth network
    receives gradients."""
    module, model = _depth_module()
    cfg = model.ldrm.config
    Ks, depth = batch["Ks"][0], batch["depth"][0]  # (T, 3, 3), (T, H, W)
    _, dirs = camera_rays(torch.eye(4).expand(FRAMES, 4, 4), Ks, SIZE, SIZE)
    lo, hi = math.log(cfg.depth_min), math.log(cfg.depth_max)
    frac = (math.log(cfg.default_depth) - lo) / (hi - lo)

    def raw_for(distance):  # the inverse of distance_activation
        t = ((distance.log() - lo) / (hi - lo)).clamp(1e-6, 1 - 1e-6)
        return torch.logit(t) - math.log(frac / (1 - frac))

    for factor, expected in ((1.0, 0.0), (2.0, 0.5 * math.log(2.0) ** 2)):
        target = raw_for(torch.where(batch["depth_valid"][0], depth, 1.0) / dirs[..., 2] * factor)
        monkeypatch.setattr(model.ldrm.image_depth, "forward", lambda image, t=target: t)
        loss = float(module(batch, torch.Generator().manual_seed(0))["mono_depth"])
        assert loss == pytest.approx(expected, abs=2e-4)
    monkeypatch.undo()
    out = module(batch, torch.Generator().manual_seed(0))
    assert set(out) == {"mono_depth", "loss"}
    out["loss"].backward()
    trained = {n for n, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained and all(n.startswith("ldrm.image_depth.") for n in trained)


def test_the_depth_objective_needs_a_depth_network(batch):
    stage = StageConfig(height=SIZE, width=SIZE, num_frames=FRAMES, objectives=("depth",), train=("ldrm",))
    with pytest.raises(ValueError, match="image_depth"):
        TrainingModule(tiny_model(image_branch=8), stage)(batch, torch.Generator().manual_seed(0))


@pytest.mark.slow
@pytest.mark.parametrize("grid", [0, 4])
def test_ldrm_with_a_depth_network_exports_to_onnx(tmp_path, grid):
    model = _ldrm(4, grid=grid).eval()
    _randomise(model.image_depth, 6)
    latents, plucker, image = _inputs()
    path = tmp_path / "ldrm.onnx"
    torch.onnx.export(model, (latents, plucker, None, image), str(path), dynamo=True, opset_version=18, verbose=False)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feeds = {i.name: x.numpy() for i, x in zip(session.get_inputs(), (latents, plucker, image), strict=True)}
    got = session.run(None, feeds)
    with torch.no_grad():
        ref = model(latents, plucker, None, image)
    np.testing.assert_allclose(got[0], ref.distance.numpy(), atol=1e-4, rtol=1e-4)
