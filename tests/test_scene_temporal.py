"""4D Gaussians with temporal support (t_means, t_scales): marginal opacity, exact temporal gating,
gated Gaussians cost nothing, pruning and the deformation.npz round trip."""
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

import diff4splat.io.scene_folder as scene_folder
import diff4splat.render.sequence as render_sequence_module
from diff4splat.assembly.prune import prune_scene
from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.io.scene_folder import deformation_tensors, load_deformation, save_deformation
from diff4splat.render import rasterize, rasterize_dense
from diff4splat.render.sequence import render_path
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from diff4splat.utils.constants import ALPHA_MIN

D = torch.float64
W = H = 24


def _gaussians(m=60, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=D)  # noqa: E731
    means = torch.stack([(r(m) - 0.5) * 1.6, (r(m) - 0.5) * 1.6, 2 + 2 * r(m)], -1)
    return Gaussians(means, torch.randn(m, 4, generator=g, dtype=D), 0.05 + 0.1 * r(m, 3), 0.05 + 0.9 * r(m),
                     rgb_to_sh0(r(m, 1, 3)))


def _temporal_scene(m=60, seed=0, deform=False):
    g = torch.Generator().manual_seed(seed + 100)
    t_means = torch.rand(m, generator=g, dtype=D) * 1.4 - 0.2
    t_scales = 0.02 + 0.2 * torch.rand(m, generator=g, dtype=D)
    if not deform:
        return DynamicGaussians(_gaussians(m, seed), t_means=t_means, t_scales=t_scales)
    T = 3
    dq = torch.zeros(T, m, 4, dtype=D)
    dq[..., 0] = 1
    d_means = torch.randn(T, m, 3, generator=g, dtype=D) * 0.05
    return DynamicGaussians(_gaussians(m, seed), torch.linspace(0, 1, T, dtype=D), d_means, dq,
                            torch.zeros(T, m, 3, dtype=D), t_means, t_scales)


def _path(T=5):
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0, dtype=D)
    return CameraPath(torch.eye(4, dtype=D).repeat(T, 1, 1), K.expand(T, 3, 3).clone(), W, H)


def _render(g, fn=rasterize):
    cam = _path(1)
    return fn(g.means, g.quats, g.scales, g.opacities, g.sh, cam.viewmats, cam.Ks, W, H, sh_degree=0)


def test_opacity_is_multiplied_by_the_unnormalised_marginal():
    scene = _temporal_scene(deform=True)
    t = 0.37
    p = torch.exp(-0.5 * ((t - scene.t_means) / scene.t_scales) ** 2)
    torch.testing.assert_close(scene.temporal_opacity(t), p, rtol=1e-14, atol=0)
    i = int(torch.nonzero((scene.t_means >= 0) & (scene.t_means <= 1))[0])
    assert float(scene.temporal_opacity(float(scene.t_means[i]))[i]) == 1.0  # peak 1 at μ_t
    idx = scene.active_indices(t, gate=0.0)
    assert torch.equal(idx, torch.arange(scene.num_gaussians))  # gate 0 keeps everything
    g0, ref = scene.at(t, gate=0.0), DynamicGaussians(scene.canonical, scene.times, scene.d_means, scene.d_quats,
                                                     scene.d_scales).at(t)
    torch.testing.assert_close(g0.opacities, ref.opacities * p, rtol=1e-14, atol=0)
    torch.testing.assert_close(g0.means, ref.means, rtol=0, atol=0)


@pytest.mark.parametrize("deform", [False, True])
@pytest.mark.slow
def test_temporal_gating_is_exact(deform):
    """Leaving out the Gaussians with o·p(t) < 1/255 changes no pixel (fast and dense renderer)."""
    scene = _temporal_scene(m=80, seed=3, deform=deform)
    for t in (0.0, 0.3, 0.75, 1.0):
        op = scene.canonical.opacities * scene.temporal_opacity(t)
        gated = scene.at(t)
        full = scene.at(t, gate=0.0)
        assert 0 < gated.num_gaussians < full.num_gaussians == 80  # the gate really drops some
        assert gated.num_gaussians == int((op >= ALPHA_MIN).sum())
        (c1, a1, _), (c2, a2, _) = _render(gated), _render(full)
        assert float(a2.max()) > 0.3
        assert torch.equal(c1, c2) and torch.equal(a1, a2)
        (d1, e1, _), (d2, e2, _) = _render(gated, rasterize_dense), _render(full, rasterize_dense)
        torch.testing.assert_close(d1, d2, rtol=0, atol=1e-14)
        torch.testing.assert_close(e1, e2, rtol=0, atol=1e-14)
    # a gate above the alpha cut-off is not exact any more (the comparison above can fail)
    t = 0.5
    assert not torch.equal(_render(scene.at(t, gate=0.3))[0], _render(scene.at(t, gate=0.0))[0])


def test_gaussian_with_small_time_scale_appears_only_around_its_time():
    T = 9
    path = _path(T)
    g = Gaussians(torch.tensor([[0.0, 0.0, 2.0]], dtype=D), torch.tensor([[1.0, 0, 0, 0]], dtype=D),
                  torch.full((1, 3), 0.2, dtype=D), torch.tensor([0.9],
                                                                 dtype=D), rgb_to_sh0(torch.ones(1, 1, 3, dtype=D)))
    mu, sig = 0.5, 0.05
    scene = DynamicGaussians(g, t_means=torch.tensor([mu], dtype=D), t_scales=torch.tensor([sig], dtype=D))
    _, _, alphas = render_path(scene, path)
    peak = alphas.flatten(1).max(1).values
    times = path.times.to(D)
    p = torch.exp(-0.5 * ((times - mu) / sig) ** 2)
    # the mean projects onto the corner of 4 pixels (dx = dy = ½ px): alpha = o·p(t)·exp(−¼/var),
    # var = (f·s/z)² + eps2d, and 0 where that is below 1/255
    var = (float(path.Ks[0, 0, 0]) * 0.2 / 2.0) ** 2 + 0.3
    want = 0.9 * p * math.exp(-0.25 / var)
    torch.testing.assert_close(peak, torch.where(want >= 1 / 255, want, 0.0), rtol=1e-12, atol=1e-12)
    assert float(peak[4]) > 0.85 and bool((peak[abs(times - mu) > 3 * sig] == 0).all())


def test_gated_gaussians_are_never_passed_to_the_rasterizer(monkeypatch):
    """Render along a path: the rasterizer receives exactly the Gaussians with o·p(t_i) ≥ 1/255."""
    scene = _temporal_scene(m=200, seed=5, deform=True)
    path = _path(5)
    seen = []
    real = render_sequence_module.rasterize

    def spy(means, *args, **kw):
        seen.append(means.shape[0])
        return real(means, *args, **kw)

    monkeypatch.setattr(render_sequence_module, "rasterize", spy)
    render_path(scene, path)
    want = [int((scene.canonical.opacities * scene.temporal_opacity(float(t)) >= 1 / 255).sum()) for t in path.times]
    assert seen == want and max(want) < 0.6 * 200  # most Gaussians live only part of the clip


def test_validation_select_to_and_without_deformation():
    g = _gaussians(5)
    one = torch.ones(5, dtype=D)
    with pytest.raises(ValueError, match="together"):
        DynamicGaussians(g, t_means=one)
    with pytest.raises(ValueError, match="t_scales must have shape"):
        DynamicGaussians(g, t_means=one, t_scales=one[:4])
    with pytest.raises(ValueError, match="t_means contains"):
        DynamicGaussians(g, t_means=torch.tensor([0, math.nan, 0, 0, 0], dtype=D), t_scales=one)
    with pytest.raises(ValueError, match="t_scales must be > 0"):
        DynamicGaussians(g, t_means=one, t_scales=one * 0)
    with pytest.raises(ValueError, match="gate"):
        DynamicGaussians(g, t_means=one, t_scales=one).at(0.5, gate=-1.0)
    scene = _temporal_scene(m=10, deform=True)
    sub = scene.select(torch.tensor([7, 2]))
    assert torch.equal(sub.t_means, scene.t_means[[7, 2]]) and torch.equal(sub.t_scales, scene.t_scales[[7, 2]])
    f32 = scene.to(torch.float32)
    assert f32.t_means.dtype == f32.t_scales.dtype == torch.float32 and f32.has_temporal
    static = DynamicGaussians(scene.canonical, scene.times, torch.zeros_like(scene.d_means), scene.d_quats,
                              scene.d_scales, scene.t_means, scene.t_scales).without_deformation()
    assert static.is_static and static.has_temporal and torch.equal(static.t_scales, scene.t_scales)


def test_prune_drops_gaussians_gated_out_at_every_frame():
    scene = _temporal_scene(m=60, seed=2)
    path = _path(5)
    pruned, stats = prune_scene(scene, path, min_opacity=0.0)
    alive = torch.zeros(60, dtype=torch.bool)
    for t in path.times:
        alive |= scene.canonical.opacities * scene.temporal_opacity(float(t)) >= 1 / 255
    assert stats["after"] < int(alive.sum()) + 1 and stats["unseen"] >= int((~alive).sum()) > 0
    assert pruned.has_temporal and pruned.t_means.shape == (stats["after"],)
    # the pruned scene renders the same path identically
    torch.testing.assert_close(render_path(pruned, path)[0], render_path(scene, path)[0], rtol=0, atol=1e-14)


@pytest.mark.parametrize("deform", [False, True])
def test_deformation_npz_round_trip_with_temporal_support(tmp_path, deform):
    scene = _temporal_scene(m=12, deform=deform)
    save_deformation(tmp_path / "d.npz", scene)
    d = load_deformation(tmp_path / "d.npz")
    assert set(d) == ({"times", "d_means", "d_quats", "d_scales"} if deform else set()) | {"t_means", "t_scales"}
    np.testing.assert_allclose(d["t_means"], scene.t_means.float().numpy())
    back = DynamicGaussians(scene.canonical.to(torch.float32), **deformation_tensors(d))
    torch.testing.assert_close(back.at(0.4).opacities, scene.at(0.4).opacities.float())
    with pytest.raises(ValueError, match="no deformation"):
        save_deformation(tmp_path / "e.npz", DynamicGaussians(scene.canonical))
    np.savez(tmp_path / "bad.npz", t_means=d["t_means"])
    with pytest.raises(ValueError, match="t_scales"):
        load_deformation(tmp_path / "bad.npz")


def test_trapezoid_support_is_its_closed_form_and_a_box_is_open_at_its_ends():
    """With ramps, p(t) = clamp((σ_t − |t − μ_t|)/r_t, 0, 1): a triangle (r = σ) falls linearly to 0 at μ ± σ, a
    trapezoid is flat within σ − r, and a box (r = 0) is 1 strictly inside (μ − σ, μ + σ) and 0 at its ends."""
    g = _gaussians(4)
    scene = DynamicGaussians(g, t_means=torch.tensor([0.5, 0.5, 0.5, 0.5], dtype=D),
                             t_scales=torch.tensor([0.25, 0.25, 0.25, 0.25], dtype=D),
                             t_ramps=torch.tensor([0.25, 0.1, 0.0, 0.0], dtype=D))
    for t, want in ((0.5, [1, 1, 1, 1]), (0.375, [0.5, 1, 1, 1]), (0.7, [0.2, 0.5, 1, 1]), (0.75, [0, 0, 0, 0]),
                    (0.25, [0, 0, 0, 0]), (0.2, [0, 0, 0, 0]), (0.7499, [0.0004, 0.001, 1, 1])):
        torch.testing.assert_close(scene.temporal_opacity(t), torch.tensor(want, dtype=D), rtol=0, atol=1e-12)
    assert scene.active_indices(0.75, gate=1e-9).numel() == 0  # the box's end: gated out, as the triangle's
    torch.testing.assert_close(scene.at(0.375, gate=0.0).opacities, g.opacities * torch.tensor([0.5, 1, 1, 1], dtype=D))
    sub, f32 = scene.select(torch.tensor([3, 0])), scene.to(torch.float32)
    assert torch.equal(sub.t_ramps, scene.t_ramps[[3, 0]]) and f32.t_ramps.dtype == torch.float32
    one = torch.ones(4, dtype=D)
    with pytest.raises(ValueError, match="t_ramps needs"):
        DynamicGaussians(g, t_ramps=one)
    with pytest.raises(ValueError, match=r"t_ramps must lie in \[0, t_scales\]"):
        DynamicGaussians(g, t_means=one, t_scales=one, t_ramps=one * 2)
    with pytest.raises(ValueError, match=r"t_ramps must lie"):
        DynamicGaussians(g, t_means=one, t_scales=one, t_ramps=-one)
    with pytest.raises(ValueError, match="t_ramps must have shape"):
        DynamicGaussians(g, t_means=one, t_scales=one, t_ramps=one[:3])


def test_deformation_npz_round_trip_with_ramps(tmp_path):
    base = _temporal_scene(m=12)
    scene = DynamicGaussians(base.canonical, t_means=base.t_means, t_scales=base.t_scales,
                             t_ramps=base.t_scales * torch.linspace(0, 1, 12, dtype=D))
    save_deformation(tmp_path / "d.npz", scene)
    d = load_deformation(tmp_path / "d.npz")
    assert set(d) == {"t_means", "t_scales", "t_ramps"}
    back = DynamicGaussians(scene.canonical.to(torch.float32), **deformation_tensors(d))
    for t in (0.1, 0.45, 0.9):
        torch.testing.assert_close(back.temporal_opacity(t), scene.temporal_opacity(t).float(), rtol=0, atol=1e-5)
    np.savez(tmp_path / "bad.npz", t_ramps=d["t_ramps"])
    with pytest.raises(ValueError, match="t_ramps needs t_means"):
        load_deformation(tmp_path / "bad.npz")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rows_shared_by_every_gaussian_are_read_once_and_others_whole(tmp_path, monkeypatch, dtype):
    """load_deformation streams a (K, M, c) member key by key in small chunks (3 rows here): one row per key for
    every Gaussian comes back broadcast (stride 0, read-only) and as an expanded tensor through the folder loader;
    a row differing anywhere (the first Gaussian, mid-chunk, the very last) switches to the whole array, equal to
    np.load's to the bit, the rows already read written back; a truncated member is one error."""
    K, M = 3, 11
    monkeypatch.setattr(scene_folder, "READ_CHUNK_BYTES", 3 * 4 * np.dtype(dtype).itemsize)
    rng = np.random.default_rng(0)
    quats = np.broadcast_to(rng.normal(size=(K, 1, 4)).astype(dtype), (K, M, 4))
    rest = {"times": np.linspace(0, 1, K, dtype=dtype), "d_means": rng.normal(size=(K, M, 3)).astype(dtype),
            "d_scales": np.zeros((K, M, 3), dtype)}

    def written(name: str, d_quats: np.ndarray) -> Path:
        np.savez_compressed(tmp_path / name, d_quats=d_quats, **rest)
        return tmp_path / name

    d = load_deformation(written("shared.npz", quats))
    assert d["d_quats"].strides[1] == 0 and not d["d_quats"].flags.writeable and d["d_quats"].dtype == np.float32
    assert np.array_equal(d["d_quats"], quats.astype(np.float32)) and d["d_scales"].strides[1] == 0
    assert np.array_equal(d["d_means"], rest["d_means"].astype(np.float32))  # differs at once: read whole
    tensor = deformation_tensors({"d_quats": d["d_quats"]})["d_quats"]
    assert tensor.stride(1) == 0 and torch.equal(tensor, torch.from_numpy(quats.astype(np.float32)))
    for k, m in ((0, 0), (0, 1), (1, 4), (2, M - 1)):
        odd = quats.copy()
        odd[k, m, 2] += 1
        d = load_deformation(written("odd.npz", odd))["d_quats"]
        assert d.strides[1] != 0 and np.array_equal(d, np.load(tmp_path / "odd.npz")["d_quats"].astype(np.float32))
    with zipfile.ZipFile(tmp_path / "short.npz", "w") as zf:
        for key, value in {"d_quats": quats.copy(), **rest}.items():
            np.save(tmp_path / f"{key}.npy", value)
            raw = (tmp_path / f"{key}.npy").read_bytes()
            zf.writestr(f"{key}.npy", raw[:-5] if key == "d_quats" else raw)
    with pytest.raises(ValueError, match="truncated"):
        load_deformation(tmp_path / "short.npz")
