"""Tests for diff4splat.geometry.depth_alignment: exact recovery, robustness to outliers, shared video fit, errors."""
import numpy as np
import pytest

from diff4splat.geometry.depth_alignment import (
    DepthAlignment,
    align_video,
    fit_scale_shift,
    fit_scale_shift_robust,
    valid_depth_mask,
)

S_TRUE, T_TRUE = 2.5, 0.75


def _depth_pair(seed=0, shape=(24, 32)):
    """Relative depth x and metric depth y = s·x + t (exact)."""
    rng = np.random.default_rng(seed)
    rel = rng.uniform(0.5, 5.0, size=shape)
    return rel, S_TRUE * rel + T_TRUE


def _disp_pair(seed=0, shape=(24, 32)):
    """Relative disparity x and metric depth 1/(s·x + t) (exact)."""
    rng = np.random.default_rng(seed)
    disp = rng.uniform(0.1, 2.0, size=shape)
    return disp, 1.0 / (0.4 * disp + 0.05)


def _brute_force_ls(x, y):
    """Reference: numpy's least-squares solver on the design matrix [x, 1]."""
    A = np.stack([x, np.ones_like(x)], -1)
    return np.linalg.lstsq(A, y, rcond=None)[0]


@pytest.mark.parametrize("fit", [fit_scale_shift, fit_scale_shift_robust])
def test_exact_recovery_depth_space(fit):
    rel, met = _depth_pair()
    a = fit(rel, met, space="depth")
    assert abs(a.scale - S_TRUE) < 1e-9 and abs(a.shift - T_TRUE) < 1e-9
    np.testing.assert_allclose(a.apply(rel), met, rtol=0, atol=1e-9)
    assert a.num_valid == rel.size and a.rms < 1e-9


@pytest.mark.parametrize("fit", [fit_scale_shift, fit_scale_shift_robust])
def test_exact_recovery_disparity_space(fit):
    disp, met = _disp_pair()
    a = fit(disp, met, space="disparity")
    assert abs(a.scale - 0.4) < 1e-9 and abs(a.shift - 0.05) < 1e-9
    np.testing.assert_allclose(a.apply(disp), met, rtol=1e-9)
    # fitting the same pair in depth space is wrong (non-linear relation): it must not recover it
    wrong = fit_scale_shift(1.0 / disp, met, space="depth")
    assert np.abs(wrong.apply(1.0 / disp) - met).max() > 1e-3


def test_matches_brute_force_least_squares_with_noise_and_mask():
    rng = np.random.default_rng(3)
    rel = rng.uniform(1, 4, size=(20, 20))
    met = 1.7 * rel + 0.2 + rng.normal(0, 0.05, size=rel.shape)
    mask = rng.uniform(size=rel.shape) > 0.3
    a = fit_scale_shift(rel, met, mask)
    s, t = _brute_force_ls(rel[mask], met[mask])
    assert abs(a.scale - s) < 1e-10 and abs(a.shift - t) < 1e-10
    assert a.num_valid == int(mask.sum())
    # masked-out garbage (even NaN) is ignored
    met2 = met.copy()
    met2[~mask] = np.nan
    b = fit_scale_shift(rel, met2, mask)
    assert (b.scale, b.shift) == (a.scale, a.shift)


def _with_outliers(space, frac=0.3, noise=0.01, seed=5):
    rng = np.random.default_rng(seed)
    n = 4000
    if space == "depth":
        x = rng.uniform(0.5, 5.0, n)
        y = S_TRUE * x + T_TRUE + rng.normal(0, noise, n)
    else:
        x = rng.uniform(0.1, 2.0, n)
        y = 1.0 / (0.4 * x + 0.05 + rng.normal(0, noise * 0.1, n))
    out = rng.permutation(n)[: int(frac * n)]
    # gross outliers: one-sided (e.g. sky / far background), up to 10× the scene depth
    y[out] = rng.uniform(20.0, 60.0, out.size)
    return x, y, out


# Tolerances with 30 % gross outliers and 1 % noise, on the relative error of scale and shift:
# Tukey (redescending, outliers get weight 0) within 1 %; Huber (bounded but non-zero outlier
# influence, so a small bias remains) within 5 %. Plain least squares misses even the 5 % tolerance.
ROBUST_RTOL = {"tukey": 0.01, "huber": 0.05}


@pytest.mark.parametrize("space", ["depth", "disparity"])
@pytest.mark.parametrize("loss", ["tukey", "huber"])
def test_robust_fit_with_30_percent_outliers(space, loss):
    x, y, out = _with_outliers(space)
    s_true, t_true = (S_TRUE, T_TRUE) if space == "depth" else (0.4, 0.05)
    tol = ROBUST_RTOL[loss]
    rob = fit_scale_shift_robust(x, y, space=space, loss=loss, seed=0)
    assert abs(rob.scale - s_true) / s_true < tol
    assert abs(rob.shift - t_true) / t_true < tol
    if loss == "tukey":  # redescending: exactly the gross outliers get weight zero
        assert rob.num_inliers == x.size - out.size
    ls = fit_scale_shift(x, y, space=space)
    assert max(abs(ls.scale - s_true) / s_true, abs(ls.shift - t_true) / t_true) > ROBUST_RTOL["huber"]


def test_robust_fit_is_seeded():
    x, y, _ = _with_outliers("depth")
    a = fit_scale_shift_robust(x, y, seed=7)
    b = fit_scale_shift_robust(x, y, seed=7)
    assert (a.scale, a.shift) == (b.scale, b.shift)
    c = fit_scale_shift_robust(x, y, seed=8)  # another sample set converges to the same inliers
    assert abs(c.scale - a.scale) < 1e-6 and abs(c.shift - a.shift) < 1e-6


def test_video_shared_fit_equals_concatenated_fit():
    rng = np.random.default_rng(11)
    frames_rel, frames_met, masks = [], [], []
    for i, shape in enumerate([(8, 10), (8, 10), (6, 12)]):
        rel = rng.uniform(1, 3, shape)
        met = 1.3 * rel + 0.4 + rng.normal(0, 0.02 * (i + 1), shape)
        frames_rel.append(rel)
        frames_met.append(met)
        masks.append(rng.uniform(size=shape) > 0.2)
    x = np.concatenate([r.ravel() for r in frames_rel])
    y = np.concatenate([m.ravel() for m in frames_met])
    k = np.concatenate([m.ravel() for m in masks])
    for robust in (False, True):
        fit, aligned = align_video(frames_rel, frames_met, masks, robust=robust)
        ref = (fit_scale_shift_robust if robust else fit_scale_shift)(x, y, k)
        assert (fit.scale, fit.shift) == (ref.scale, ref.shift)
        assert len(aligned) == 3 and aligned[2].shape == (6, 12)
        np.testing.assert_allclose(aligned[1], fit.scale * frames_rel[1] + fit.shift)
    # one shared scale differs from per-frame fits (the noise differs per frame)
    per_frame = [fit_scale_shift(r, m, k_) for r, m, k_ in zip(frames_rel, frames_met, masks, strict=True)]
    fit, _ = align_video(frames_rel, frames_met, masks, robust=False)
    assert all(abs(p.scale - fit.scale) > 1e-6 for p in per_frame)


def test_apply_marks_non_positive_depth_invalid():
    a = DepthAlignment(scale=1.0, shift=-1.0, space="depth", num_valid=2, num_inliers=2, rms=0.0)
    out = a.apply(np.array([0.5, 1.0, 3.0, np.nan]))
    assert np.isinf(out[0]) and np.isinf(out[1]) and out[2] == 2.0 and np.isinf(out[3])
    d = DepthAlignment(scale=2.0, shift=-1.0, space="disparity", num_valid=2, num_inliers=2, rms=0.0)
    out = d.apply(np.array([0.25, 1.0]))
    assert np.isinf(out[0]) and out[1] == 1.0


def test_valid_depth_mask():
    m = valid_depth_mask(np.array([1.0, 0.0, np.inf, np.nan, -1.0]))
    assert m.tolist() == [True, False, False, False, False]


@pytest.mark.parametrize("fit", [fit_scale_shift, fit_scale_shift_robust])
def test_degenerate_inputs_raise(fit):
    rel, met = _depth_pair(shape=(4, 4))
    one = np.zeros((4, 4), dtype=bool)
    one[0, 0] = True
    with pytest.raises(ValueError, match="at least 2 valid pixels"):
        fit(rel, met, one)
    with pytest.raises(ValueError, match="constant"):
        fit(np.full((4, 4), 3.0), met)
    bad = rel.copy()
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="relative depth has 1 NaN/inf"):
        fit(bad, met)
    bad = met.copy()
    bad[2, 2] = np.inf
    with pytest.raises(ValueError, match="metric depth has 1 NaN/inf"):
        fit(rel, bad)
    with pytest.raises(ValueError, match="scale is .* ≤ 0"):
        fit(rel, 10.0 - met)  # anti-correlated: negative scale
    with pytest.raises(ValueError, match="metric depth must be > 0"):
        fit(rel, met - 100.0, space="disparity")
    with pytest.raises(ValueError, match="space"):
        fit(rel, met, space="log")
    with pytest.raises(ValueError, match="same shape"):
        fit(rel, met[:2])
    with pytest.raises(ValueError, match="boolean"):
        fit(rel, met, np.ones((4, 4)))


def test_bad_options_and_video_inputs_raise():
    rel, met = _depth_pair(shape=(4, 4))
    with pytest.raises(ValueError, match="loss"):
        fit_scale_shift_robust(rel, met, loss="cauchy")
    with pytest.raises(ValueError, match="ransac_iters"):
        fit_scale_shift_robust(rel, met, ransac_iters=-1)
    with pytest.raises(ValueError, match="number of frames"):
        align_video([rel, rel], [met])
    with pytest.raises(ValueError, match="at least one frame"):
        align_video([], [])
    with pytest.raises(ValueError, match="frame 1"):
        align_video([rel, rel], [met, met[:2]])
    with pytest.raises(ValueError, match="robust=True"):
        align_video([rel], [met], robust=False, seed=3)
