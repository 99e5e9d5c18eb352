"""Tests of training/fit.py: learning-rate schedule, gradients through the HexPlane field against finite
differences (float64), the identity of a new field, optimisation progress, held-out metrics by hand, the
fitted scene, views that see nothing, and the device rule (a fit on each device; nothing made on the default
device)."""
import math

import kornia
import numpy as np
import pytest
import torch
from helpers import adam_steps_on_the_default_device
from torch import nn

from data_prep.format import load_scene
from data_prep.synth import generate_scene
from diff4splat.scene.dynamic import compose_deformation
from diff4splat.utils.constants import ALPHA_MIN
from models.hexplane import HexPlaneConfig
from training.densify import DensifyConfig
from training.eval_metrics import PSNR_CAP
from training.fit import (
    BACKGROUNDS,
    FitConfig,
    LearningRates,
    default_depth_weight,
    evaluate_views,
    expon_lr,
    fit_steps,
    init_background,
    init_state,
    psnr_from_mse,
    render_view,
    start_fine_stage,
    to_scene,
)
from training.fit_data import View, depth_points, load_views, scene_extent

TINY_FIELD = HexPlaneConfig(feature_dim=4, resolution=(4, 4, 4, 3), multires=(1,), net_width=8)
K = torch.tensor([[14.0, 0.0, 8.0], [0.0, 14.0, 6.0], [0.0, 0.0, 1.0]])


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def static_scene(tmp_path_factory):
    return load_scene(generate_scene(tmp_path_factory.mktemp("fit"), 0, 0, size=16, frames=2, cameras=2,
                                     static_ratio=1.0))


def _config(**kw) -> FitConfig:
    base = dict(iterations=10, coarse_iterations=0, init_points=64, sh_degree=0, field=TINY_FIELD,
                densify=DensifyConfig(start=1000, until=1000), depth_weight=0.1)
    return FitConfig(**{**base, **kw})


def _blob(n: int = 20, seed: int = 1, dynamic: bool = True, config: FitConfig | None = None, device="cpu"):
    """A FitState of ``n`` Gaussians 3 m in front of the identity camera, on ``device`` (drawn on the CPU)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([1.0, 1.0, 0.6]) + torch.tensor([0.0, 0.0, 3.0])
    state = init_state(means.to(device), torch.rand(n, 3, generator=g).to(device), config or _config(), 1.0, dynamic,
                       seed)
    with torch.no_grad():
        state.params["opacities"].fill_(0.0)  # 0.5
        state.params["scales"].add_(0.5)
    return state


def _view(image=None, time=0.4, viewmat=None, dtype=torch.float32) -> View:
    image = torch.zeros(12, 16, 3) if image is None else image
    viewmat = torch.eye(4) if viewmat is None else viewmat
    return View(image.to(dtype), None, viewmat.to(dtype), K.to(dtype), time, "c", 0)


def _perturb_heads(field, seed: int = 2) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for head in (field.d_means_head, field.d_quats_head, field.d_scales_head):
            w = head[-1].weight
            w.copy_(torch.randn(w.shape, generator=g, dtype=w.dtype) * 0.3)
            head[-1].bias.copy_(torch.randn(head[-1].bias.shape, generator=g, dtype=w.dtype) * 0.05)


def _reference_expon_lr(lr_init, lr_final, lr_delay_steps=0, lr_delay_mult=1.0, max_steps=1000000):
    """3DGS ``utils/general_utils.py`` ``get_expon_lr_func``, verbatim."""
    def helper(step):
        if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
            return 0.0
        if lr_delay_steps > 0:
            delay_rate = lr_delay_mult + (1 - lr_delay_mult) * np.sin(
                0.5 * np.pi * np.clip(step / lr_delay_steps, 0, 1))
        else:
            delay_rate = 1.0
        t = np.clip(step / max_steps, 0, 1)
        log_lerp = np.exp(np.log(lr_init) * (1 - t) + np.log(lr_final) * t)
        return delay_rate * log_lerp
    return helper


def test_expon_lr_matches_3dgs():
    for init, final, max_steps, delay, mult in ((1.6e-4, 1.6e-6, 3000, 0, 0.01), (1e-2, 1e-3, 500, 100, 0.01),
                                                (5e-3, 5e-3, 10, 0, 1.0), (1.6e-3, 1.6e-4, 1000, 20, 0.5)):
        ref = _reference_expon_lr(init, final, delay, mult, max_steps)
        for step in (-1, 0, 1, 7, delay // 2, delay, max_steps // 2, max_steps - 1, max_steps, 2 * max_steps):
            assert expon_lr(step, init, final, max_steps, delay, mult) == pytest.approx(float(ref(step)), rel=1e-12)
    assert expon_lr(0, 1e-2, 1e-4, 100) == pytest.approx(1e-2)
    assert expon_lr(50, 1e-2, 1e-4, 100) == pytest.approx(1e-3)  # geometric mean half-way
    assert expon_lr(100, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    assert expon_lr(0, 1e-2, 1e-4, 100, delay_steps=10, delay_mult=0.01) == pytest.approx(1e-4)
    assert expon_lr(3, 0.0, 0.0, 100) == 0.0


@pytest.mark.parametrize("kw", [dict(iterations=0), dict(coarse_iterations=-1), dict(sh_degree=4),
                                dict(sh_interval=0), dict(init_points=1.5), dict(ssim_weight=1.5),
                                dict(depth_weight=-0.1), dict(random_points=True)])
def test_fit_config_rejects_bad_values(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        FitConfig(**kw)


def test_gradients_through_the_field_agree_with_finite_differences():
    state = _blob()
    start_fine_stage(state, _config())
    state.field.double()
    state.params = {k: nn.Parameter(v.detach().double()) for k, v in state.params.items()}
    _perturb_heads(state.field)
    view = _view(dtype=torch.float64)
    weights = torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)

    def loss():
        return (render_view(state, view, 0, False)[0] * weights).sum()

    loss().backward()
    field = state.field
    lo, hi = field.bounds.double()
    means = state.params["means"]
    inside = ((means > lo) & (means < hi)).all(1)  # the box is the means' bounding box: its faces are kinks
    checks = []
    for p, k in ((field.grids[0][2], 3), (field.grids[0][0], 2), (field.d_means_head[-1].weight, 2),
                 (field.d_quats_head[-1].weight, 1), (field.trunk[0].weight, 2)):
        checks += [(p, int(i)) for i in p.grad.flatten().abs().topk(k).indices]
    checks += [(means, int(i)) for i in (means.grad.abs() * inside[:, None]).flatten().topk(4).indices]
    eps = 1e-6
    for p, i in checks:
        auto = float(p.grad.flatten()[i])
        with torch.no_grad():
            p.view(-1)[i] += eps
            up = float(loss())
            p.view(-1)[i] -= 2 * eps
            down = float(loss())
            p.view(-1)[i] += eps
        fd = (up - down) / (2 * eps)
        assert auto != 0.0
        assert auto == pytest.approx(fd, rel=1e-5, abs=1e-8), (p.shape, i)


def test_a_new_fine_stage_field_is_the_identity():
    state = _blob()
    with torch.no_grad():
        state.params["quats"].add_(torch.randn(20, 4, generator=torch.Generator().manual_seed(0)) * 0.3)
    view = _view()
    without = render_view(state, view, 0, True)
    start_fine_stage(state, _config())
    field = state.field
    means = state.params["means"].detach()
    assert torch.equal(field.bounds, torch.stack([means.min(0).values, means.max(0).values]))
    with_field = render_view(state, view, 0, True)
    for a, b in zip(without[:3], with_field[:3], strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-6)
    # the field's optimizer: planes in "grid", the MLP in "deformation", every parameter exactly once
    groups = {g["name"]: {id(p) for p in g["params"]} for g in state.field_optimizer.param_groups}
    planes = {id(p) for planes in field.grids for p in planes}
    assert groups["grid"] == planes
    assert groups["deformation"] == {id(p) for p in field.parameters()} - planes
    _perturb_heads(field)
    assert not torch.allclose(render_view(state, view, 0, False)[0], without[0], atol=1e-3)


def test_fit_steps_raise_training_psnr_on_a_static_scene(static_scene):
    views = load_views(static_scene, static_scene.camera_names)
    means, colors = depth_points(views, 300, torch.Generator().manual_seed(0))
    config = _config(iterations=60, coarse_iterations=60)
    state = init_state(means, colors, config, scene_extent(views, means), False, 0)
    before = evaluate_views(state, views, 0)["psnr"]
    fit_steps(state, views, config, 60)
    after = evaluate_views(state, views, 0)["psnr"]
    assert state.step == 60 and state.field is None  # static: never a field
    assert after > before + 2.0, (before, after)
    assert all(torch.isfinite(p).all() for p in state.params.values())


def test_fit_steps_start_the_field_after_the_coarse_stage_and_decay_the_rates():
    config = _config(iterations=8, coarse_iterations=3)
    state = _blob(config=config)
    views = [_view(torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(i)), time=i / 2) for i in range(3)]
    fit_steps(state, views, config, 3)
    assert state.field is None
    fit_steps(state, views, config, 8)
    assert state.field is not None and state.step == 8
    lr = LearningRates()
    # the rates of the last step taken (step 7 = stage step 4 of a 5-step fine stage), scaled by the extent
    rates = {g["name"]: g["lr"] for g in state.optimizer.param_groups}
    assert rates["means"] == pytest.approx(expon_lr(4, lr.position_init * state.extent,
                                                    lr.position_final * state.extent, 5))
    assert rates["opacities"] == lr.opacities and rates["scales"] == lr.scales
    field_rates = {g["name"]: g["lr"] for g in state.field_optimizer.param_groups}
    assert field_rates["grid"] == pytest.approx(expon_lr(4, lr.grid_init, lr.grid_final, 5))
    assert field_rates["deformation"] == pytest.approx(expon_lr(4, lr.deformation_init, lr.deformation_final, 5))
    assert any(float(p.detach().abs().sum()) > 0 for p in state.field.d_means_head[-1].parameters())  # it learns


def test_evaluate_views_psnr_of_the_pooled_mse():
    state = _blob(dynamic=False)
    g = torch.Generator().manual_seed(5)
    views = [_view(torch.rand(12, 16, 3, generator=g)),
             View(torch.rand(6, 9, 3, generator=g), None, torch.eye(4), K * 0.5 + torch.diag(torch.tensor([0, 0, 0.5])),
                  0.0, "d", 0)]
    out = evaluate_views(state, views, 0)
    se, n, ssim = 0.0, 0, []
    for v in views:
        rgb = render_view(state, v, 0, False)[0].detach().clamp(0, 1)
        se += float(((rgb.double() - v.image.double()) ** 2).sum())
        n += rgb.numel()
        ssim.append(float(kornia.metrics.ssim(rgb.permute(2, 0, 1)[None], v.image.permute(2, 0, 1)[None], 11).mean()))
    assert out["views"] == 2
    assert out["mse"] == pytest.approx(se / n, rel=1e-5)
    assert out["psnr"] == pytest.approx(10 * math.log10(n / se), abs=1e-4)
    mean_of_psnrs = np.mean([10 * math.log10(1 / m) for m in (  # not what is reported: the views differ in size
        float(((render_view(state, v, 0, False)[0].detach().clamp(0, 1) - v.image) ** 2).mean()) for v in views)])
    assert abs(out["psnr"] - mean_of_psnrs) > 1e-3
    assert out["ssim"] == pytest.approx(np.mean(ssim), rel=1e-5)
    assert math.isnan(out["masked_psnr"]) and math.isnan(out["covisible"])
    assert psnr_from_mse(0.0) == PSNR_CAP and psnr_from_mse(0.01) == pytest.approx(20.0)  # finite: JSON-safe
    # masked: the pooled squared error of the masked pixels only, and their share of all pixels
    masks = [torch.rand(12, 16, generator=g) < 0.5, torch.zeros(6, 9, dtype=torch.bool)]
    masks[1][0, :2] = True
    out = evaluate_views(state, views, 0, masks)
    se_m, n_m = 0.0, 0
    for v, m in zip(views, masks, strict=True):
        rgb = render_view(state, v, 0, False)[0].detach().clamp(0, 1)
        se_m += float(((rgb.double() - v.image.double()) ** 2)[m].sum())
        n_m += int(m.sum()) * 3
    assert out["masked_psnr"] == pytest.approx(10 * math.log10(n_m / se_m), abs=1e-4)
    assert out["covisible"] == pytest.approx(n_m / n)


def test_to_scene_prunes_invisible_gaussians_and_samples_the_field():
    state = _blob()
    start_fine_stage(state, _config())
    _perturb_heads(state.field)
    with torch.no_grad():
        state.params["opacities"][[2, 7]] = math.log(0.5 / 255 / (1 - 0.5 / 255))  # below 1/255
        state.params["opacities"][4] = math.log(2 / 255 / (1 - 2 / 255))  # above
    keep = [i for i in range(20) if i not in (2, 7)]
    means = state.params["means"].detach()[keep].clone()
    times = torch.tensor([0.0, 0.25, 1.0])
    pruned = state.counts["pruned"]
    scene = to_scene(state, times)
    assert scene.num_gaussians == 18 and state.num_gaussians == 18
    assert state.counts["pruned"] == pruned + 2  # metrics.json's densify.pruned counted none of these
    assert float(scene.canonical.opacities.min()) >= ALPHA_MIN
    torch.testing.assert_close(scene.canonical.means, means)
    assert torch.equal(scene.times, times)
    for k, t in enumerate(times.tolist()):
        d_means, d_quats, d_scales = state.field(means, t)
        torch.testing.assert_close(scene.d_means[k], d_means.detach())
        torch.testing.assert_close(scene.d_quats[k], d_quats.detach())
        torch.testing.assert_close(scene.d_scales[k], d_scales.detach())
        at = scene.at(t)
        ref = compose_deformation(means, scene.canonical.quats, scene.canonical.scales, d_means, d_quats, d_scales)
        torch.testing.assert_close(at.means, ref[0].detach())
    static = to_scene(_blob(dynamic=False), None)
    assert static.is_static and static.num_gaussians == 20


@pytest.mark.parametrize("coarse", [5, 0])
def test_a_view_that_sees_nothing_gives_a_finite_loss(coarse):
    config = _config(iterations=5, coarse_iterations=coarse)
    state = _blob(config=config)
    behind = torch.eye(4)
    behind[2, 3] = -10.0  # the camera stands at z = 10 looking along +z: every Gaussian is behind it
    view = _view(torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(0)), viewmat=behind)
    assert float(render_view(state, view, 0, False)[2].detach().abs().max()) == 0  # nothing is drawn
    before = {k: v.detach().clone() for k, v in state.params.items()}
    fit_steps(state, [view], config, 5)
    assert state.step == 5 and (state.field is not None) == (coarse == 0)
    for k, v in state.params.items():
        assert torch.isfinite(v).all()
        assert torch.equal(v.detach(), before[k])  # no gradient reached them


def test_gaussians_that_leave_the_field_box_stay_finite():
    config = _config(iterations=6, coarse_iterations=0)
    state = _blob(config=config)
    g = torch.Generator().manual_seed(4)
    views = [_view(torch.rand(12, 16, 3, generator=g), time=t) for t in (0.0, 0.5, 1.0)]
    fit_steps(state, views, config, 1)  # the field is made on the Gaussians' box
    _perturb_heads(state.field)
    with torch.no_grad():
        state.params["means"][:4] += torch.tensor([0.0, 0.0, 40.0])  # behind the box, still in view
        state.params["means"][4:8] += torch.tensor([3.0, -2.0, 1.0])  # beside it, partly in view
        state.params["means"][8:10] = torch.tensor([1e4, -1e4, 1e4])  # far away
    lo, hi = state.field.bounds
    assert ((state.params["means"] < lo) | (state.params["means"] > hi)).any(1)[:10].all()
    fit_steps(state, views, config, 6)
    assert state.step == 6
    for k, v in state.params.items():
        assert torch.isfinite(v).all(), k
    for name, p in state.field.named_parameters():
        assert torch.isfinite(p).all(), name
    with torch.no_grad():
        assert torch.isfinite(render_view(state, views[1], 0, True)[0]).all()


def test_a_static_fit_decays_the_position_rate_over_all_its_iterations():
    config = _config(iterations=12, coarse_iterations=3)
    state = _blob(dynamic=False, config=config)
    views = [_view(torch.rand(12, 16, 3, generator=torch.Generator().manual_seed(0)))]
    lr = LearningRates()
    for until in (2, 6, 12):
        fit_steps(state, views, config, until)
        rate = next(g["lr"] for g in state.optimizer.param_groups if g["name"] == "means")
        # static: no fine stage, so the coarse stage is the whole fit (the rate of step until − 1)
        assert rate == pytest.approx(expon_lr(until - 1, lr.position_init, lr.position_final, 12)), until
    assert state.field is None


def test_default_depth_weight_by_depth_source():
    assert default_depth_weight("ground_truth") == 1.0 and default_depth_weight("aligned_estimate") == 0.1
    assert default_depth_weight("none") == 0.0
    with pytest.raises(ValueError, match="depth_source"):
        default_depth_weight("lidar")
    with pytest.raises(ValueError, match="depth_weight is None"):  # fit_steps needs it resolved
        fit_steps(None, [], FitConfig(), 1)


def test_init_background_learned_or_fixed():
    state = _blob(dynamic=False)
    torch.testing.assert_close(state.background_rgb().detach(), torch.tensor(BACKGROUNDS["learned"]))
    assert state.background.requires_grad and state.background_optimizer is not None
    for name in ("black", "white"):
        init_background(state, _config(background=name))
        assert state.background_optimizer is None and not state.background.requires_grad
        assert state.background_rgb().tolist() == list(BACKGROUNDS[name])
    with pytest.raises(ValueError, match="background"):
        _config(background="green")


@pytest.mark.parametrize("background", ["learned", "white"])
def test_the_background_is_composited_behind_the_gaussians(background):
    state = _blob(dynamic=False, config=_config(background=background))
    rgb, _, alpha, _ = render_view(state, _view(), 0, False)
    black = _blob(dynamic=False, config=_config(background="black"))
    rgb0 = render_view(black, _view(), 0, False)[0]
    bg = state.background_rgb().detach()
    assert float(alpha.detach().min()) < 0.5  # the image has background showing
    torch.testing.assert_close(rgb.detach(), rgb0.detach() + (1 - alpha.detach())[..., None] * bg)


@pytest.mark.slow  # 2.5 s: 300 fitting iterations
def test_a_learned_background_fits_the_backdrop_colour():
    """Views of the blob over a backdrop colour: the learned colour (starting at grey, no depth) reaches it."""
    backdrop = torch.tensor([0.2, 0.7, 0.4])
    config = _config(iterations=300, coarse_iterations=300)
    state = _blob(dynamic=False, config=config)
    with torch.no_grad():
        rgb, _, alpha, _ = render_view(_blob(dynamic=False, config=_config(background="black")), _view(), 0, False)
        target = rgb + (1 - alpha)[..., None] * backdrop
    assert float((1 - alpha).mean()) > 0.2
    fit_steps(state, [_view(target)], config, 300)
    torch.testing.assert_close(state.background_rgb().detach(), backdrop, atol=0.03, rtol=0)


def _target_view(time=0.4, seed=7) -> View:
    """A view of another blob (the fit's target) with its expected depth where it is covered (+inf elsewhere)."""
    with torch.no_grad():
        rgb, depth, alpha, _ = render_view(_blob(seed=seed, dynamic=False, config=_config(background="black")),
                                           _view(), 0, True)
    depth = torch.where(alpha > 0.5, depth, math.inf)
    return View(rgb.detach(), depth.detach(), torch.eye(4), K, time, "c", 0)


def _device_fit(device, steps=8):
    """(per-step losses, state) of a fit of a blob to ``_target_view`` on ``device``: 3 coarse steps, then the
    fine stage (its field made at step 3), depth loss on, one view."""
    config = _config(iterations=steps, coarse_iterations=3)
    state = _blob(config=config, device=device)
    with torch.no_grad():  # opacity 0.25 < 0.35: gsplat's 3σ tiles drop no rim (render/rasterize.py, rasterize_gsplat)
        state.params["opacities"].fill_(math.log(0.25 / 0.75))
    losses = []
    fit_steps(state, [_target_view().to(device)], config, steps, on_step=lambda s: losses.append(float(s.loss)))
    return losses, state


def test_a_few_fit_steps_on_each_device(device):
    losses, state = _device_fit(device)
    assert len(losses) == 8 and all(math.isfinite(x) for x in losses)
    assert losses[-1] < losses[0]
    tensors = [*state.params.values(), state.background, state.stats.grad_accum, state.stats.max_radii,
               *state.field.parameters(), state.field.bounds]
    assert {t.device.type for t in tensors} == {device.type} and state.device.type == device.type
    if device.type == "cuda":  # the same draws (CPU generators, the field made on the CPU): the same first steps
        cpu, cpu_state = _device_fit(torch.device("cpu"))
        np.testing.assert_allclose(losses[:4], cpu[:4], rtol=1e-3)
        for name, p in state.field.named_parameters():
            assert p.shape == dict(cpu_state.field.named_parameters())[name].shape


def test_a_new_field_is_the_same_on_every_device(device):
    """The fine stage's field is drawn on the CPU from torch's seeded generator and moved."""
    fields = []
    for dev in ("cpu", device):
        state = _blob(device=dev)
        torch.manual_seed(11)
        start_fine_stage(state, _config())
        fields.append(state.field)
    assert fields[1].bounds.device.type == device.type
    for (name, a), b in zip(fields[0].state_dict().items(), fields[1].state_dict().values(), strict=True):
        torch.testing.assert_close(b.cpu(), a, rtol=0, atol=1e-6, msg=name)


@pytest.mark.skipif(adam_steps_on_the_default_device(), reason="this torch's Adam makes its step counter on "
                    "the default device (tests/helpers.py)")
def test_fit_steps_make_nothing_on_the_default_device(no_implicit_device):
    """Inputs made on the CPU, then a fit while torch's default device is "meta" (tests/conftest.py): a coarse step,
    the fine stage (a new field), the depth loss, densification (clone, split, prune), an opacity reset, the
    progress bar, evaluation and the fitted scene all stay on the CPU."""
    with torch.device("cpu"):
        config = _config(iterations=5, coarse_iterations=1, densify=DensifyConfig(
            start=1, until=5, interval=2, grad_threshold=0.0, opacity_reset_interval=3))
        state = _blob(config=config)
        views = [_target_view(0.0), _target_view(1.0, seed=8)]
        masks = [torch.rand(12, 16, generator=torch.Generator().manual_seed(0)) < 0.5] * 2
        times = torch.tensor([0.0, 0.5, 1.0])
    fit_steps(state, views, config, 5, progress=True)
    assert state.step == 5 and state.field is not None and state.counts["split"] + state.counts["cloned"] > 0
    assert {p.device.type for p in [*state.params.values(), *state.field.parameters()]} == {"cpu"}
    assert math.isfinite(float(state.loss)) and state.loss.device.type == "cpu"
    out = evaluate_views(state, views, 0, masks)
    assert all(math.isfinite(out[k]) for k in ("psnr", "ssim", "masked_psnr", "covisible"))
    scene = to_scene(state, times)
    assert scene.canonical.means.device.type == "cpu" and scene.d_means.device.type == "cpu"
