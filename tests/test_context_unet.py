"""Tests of models/context_unet.py and the LDRM image branch's context path (``LDRMConfig.image_context``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models.context_unet import ContextUNet
from models.ldrm import LDRM, LDRMConfig

H = W = 64


def _inputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    latents = torch.randn(1, 4, 2, H // 8, W // 8, generator=g)
    plucker = torch.randn(1, 1536, 2, H // 8, W // 8, generator=g)
    image = torch.rand(1, 3, H, W, generator=g) * 2 - 1
    return latents, plucker, image


def _randomise(module: torch.nn.Module, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.2)


def test_a_new_context_path_keeps_a_trained_branchs_function_exactly():
    """Zero convolution: an LDRM whose image branch has trained (non-zero) weights gives exactly the same maps
    once a context path is added and the old weights loaded (how training/compose.py warm-starts it)."""
    torch.manual_seed(0)
    plain = LDRM(LDRMConfig(image_branch=8))
    _randomise(plain.image_branch, 1)
    torch.manual_seed(0)
    with_context = LDRM(LDRMConfig(image_branch=8, image_context=2))
    missing = with_context.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("image_branch.context.") for k in missing)
    a, b = plain(*_inputs()[:2], image=_inputs()[2]), with_context(*_inputs()[:2], image=_inputs()[2])
    for name in ("distance", "scales", "quats", "opacities", "colors"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_each_pixel_sees_the_whole_image_through_the_context_path():
    """A change in one corner of the photograph reaches the opposite corner of the branch's raw maps through the
    context path (its global mean at the coarsest level), and not through the plain branch, whose window is 5×5 pixels."""
    g = torch.Generator().manual_seed(0)
    image, raw = torch.rand(1, 3, H, W, generator=g) * 2 - 1, torch.randn(1, 12, H, W, generator=g)
    poked = image.clone()
    poked[..., :2, :2] = -poked[..., :2, :2]
    for levels, reaches in ((0, False), (3, True)):
        torch.manual_seed(0)
        branch = LDRM(LDRMConfig(image_branch=8, image_context=levels)).image_branch
        _randomise(branch, 2)
        with torch.no_grad():
            far = branch(image, raw)[..., -8:, -8:] - branch(poked, raw)[..., -8:, -8:]
        assert bool((far.abs() > 0).any()) == reaches, levels
        with torch.no_grad():
            near = branch(image, raw)[..., :4, :4] - branch(poked, raw)[..., :4, :4]
        assert bool((near.abs() > 0).any())


def test_gradients_reach_every_context_parameter():
    net = ContextUNet(4, 2)
    _randomise(net, 3)
    x = torch.randn(2, 4, 16, 16, generator=torch.Generator().manual_seed(4))
    (net(x) * torch.randn(2, 4, 16, 16, generator=torch.Generator().manual_seed(5))).sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_context_errors_and_parameter_count():
    with pytest.raises(ValueError, match="levels ≥ 1"):
        ContextUNet(4, 0)
    with pytest.raises(ValueError, match="divisible by 8"):
        ContextUNet(4, 3)(torch.zeros(1, 4, 12, 16))
    with pytest.raises(ValueError, match="needs image_branch"):
        LDRMConfig(image_context=3)
    with pytest.raises(ValueError, match="image_context"):
        LDRMConfig(image_branch=16, image_context=-1)
    # closed form: encoder i: 3·3·(w_i·w_{i+1} + w_{i+1}²) + 2·w_{i+1}; decoder i: 3·3·((w_{i+1} + w_i)·w_i + w_i²)
    # + 2·w_i; the global 1×1: w_L² + w_L; the zero 1×1: C² + C
    C, L = 16, 3
    w = [C * 2 ** i for i in range(L + 1)]
    expected = sum(9 * (w[i] * w[i + 1] + w[i + 1] ** 2) + 2 * w[i + 1] for i in range(L)) + w[L] ** 2 + w[L]
    expected += sum(9 * ((w[i + 1] + w[i]) * w[i] + w[i] ** 2) + 2 * w[i] for i in range(L)) + C * C + C
    assert sum(p.numel() for p in ContextUNet(C, L).parameters()) == expected


@pytest.mark.slow
def test_context_path_exports_to_onnx(tmp_path):
    import onnxruntime as ort

    net = ContextUNet(4, 3).eval()
    _randomise(net, 6)
    x = torch.randn(1, 4, 64, 64, generator=torch.Generator().manual_seed(7))
    path = tmp_path / "context.onnx"
    torch.onnx.export(net, (x,), str(path), dynamo=True, opset_version=18, verbose=False)
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x.numpy()})[0]
    with torch.no_grad():
        np.testing.assert_allclose(got, net(x).numpy(), atol=1e-4, rtol=1e-4)
