"""Image textures of synthetic scenes (data_prep/textures.py): bilinear sampling, mirrored repeat outside the
crop, pyramid level choice, decoding (RGB order, cache), and the bundled set (only the allowed photographs,
small, package data)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from data_prep.textures import (
    IMAGE_TEXTURES,
    TEXTURE_DIR,
    bilinear,
    crop_pixels,
    image_albedo,
    load_texture,
    mirror,
    texture_names,
    texture_pyramid,
)

tomllib = pytest.importorskip("tomllib")  # Python ≥ 3.11

ROOT = Path(__file__).resolve().parent.parent
ALLOWED = {"brick.png", "grass.png", "gravel.png", "camera.png", "coins.png", "text.png", "color.png",
           "hubble_deep_field.jpg", "retina.jpg"}


def _tent_reference(image, x, y):
    """Brute force: every pixel weighted by the tent max(0, 1 − |x' − j|)·max(0, 1 − |y' − i|) at the
    clamped centre-relative coordinates x' = clip(x − 0.5, 0, W − 1), y' likewise."""
    h, w = image.shape[:2]
    out = []
    for xs, ys in zip(x, y, strict=True):
        xc, yc = min(max(xs - 0.5, 0.0), w - 1.0), min(max(ys - 0.5, 0.0), h - 1.0)
        acc = np.zeros(image.shape[2:])
        for i in range(h):
            for j in range(w):
                acc = acc + max(0.0, 1 - abs(xc - j)) * max(0.0, 1 - abs(yc - i)) * image[i, j]
        out.append(acc)
    return np.asarray(out)


@pytest.mark.parametrize("channels", [None, 3])
def test_bilinear_equals_brute_force_tent_filter(channels):
    rng = np.random.default_rng(0)
    image = rng.random((5, 7) if channels is None else (5, 7, channels))
    x, y = rng.uniform(-1.0, 8.0, 60), rng.uniform(-1.0, 6.0, 60)  # inside, between and beyond the centres
    x[:3], y[:3] = [0.5, 3.5, 6.5], [0.5, 2.5, 4.5]  # exact pixel centres
    got = bilinear(image, x, y)
    np.testing.assert_allclose(got, _tent_reference(image, x, y), atol=1e-12)
    np.testing.assert_allclose(got[:3], image[[0, 2, 4], [0, 3, 6]], atol=1e-12)


def test_outside_the_crop_the_texture_mirror_repeats():
    s = np.array([0.0, 0.25, 1.0, 1.25, 1.75, 2.0, 2.25, -0.25, -1.0, 7.6])
    np.testing.assert_allclose(mirror(s), [0, 0.25, 1, 0.75, 0.25, 0, 0.25, 0.25, 1, 0.4], atol=1e-12)
    tex = {"file": "brick.png", "crop": [30.0, 40.0, 100.0], "metres": 1.5, "angle": 0.7,
           "tint": [1.0, 1.0, 1.0], "noise": 0.0}
    rng = np.random.default_rng(1)
    uv = rng.uniform(-10, 10, (500, 2))
    x, y = crop_pixels(tex, uv)
    assert (x >= 30).all() and (x <= 130).all() and (y >= 40).all() and (y <= 140).all()  # never leaves the crop
    # in the crop's own (rotated, metre-scaled) frame: period two crop widths, mirror image about a crop edge
    ca, sa = math.cos(0.7), math.sin(0.7)
    to_uv = lambda a, b: np.stack([a * ca - b * sa, a * sa + b * ca], 1) * 1.5  # noqa: E731  crop frame → uv
    a, b = rng.uniform(0, 1, 200), rng.uniform(0, 1, 200)
    base = crop_pixels(tex, to_uv(a, b))
    np.testing.assert_allclose(base[0], 30 + 100 * a, atol=1e-9)  # inside: the plain crop
    np.testing.assert_allclose(base[1], 40 + 100 * b, atol=1e-9)
    for shifted in (to_uv(a + 2, b - 4), to_uv(2 - a, b), to_uv(-a, -b)):
        np.testing.assert_allclose(np.stack(crop_pixels(tex, shifted)), np.stack(base), atol=1e-9)
    # the albedo repeats likewise (not clamped: a clamp would give the edge colour far outside)
    far = image_albedo(tex, to_uv(a + 6, b), 1e-3)
    np.testing.assert_allclose(far, image_albedo(tex, to_uv(a, b), 1e-3), atol=1e-9)
    assert far.std(0).max() > 0.05


def test_image_albedo_samples_the_pyramid_level_of_the_gaussian_spacing():
    tex = {"file": "retina.jpg", "crop": [20.0, 10.0, 200.0], "metres": 2.0, "angle": 0.3,
           "tint": [0.9, 0.5, 1.0], "noise": 0.0}
    uv = np.random.default_rng(2).uniform(-3, 3, (300, 2))
    x, y = crop_pixels(tex, uv)
    fine = image_albedo(tex, uv, 0.005)  # 0.5 texel per Gaussian: level 0
    np.testing.assert_allclose(fine, bilinear(load_texture("retina.jpg"), x, y) * tex["tint"], atol=1e-12)
    levels = texture_pyramid("retina.jpg")
    assert [lv.shape[0] for lv in levels] == [256, 128, 64, 32, 16, 8, 4]
    coarse = image_albedo(tex, uv, 0.09)  # 9 texels per Gaussian: level 3 (8×)
    np.testing.assert_allclose(coarse, bilinear(levels[3], x / 8, y / 8) * tex["tint"], atol=1e-12)
    assert not np.allclose(coarse, fine, atol=1e-3)
    grey = {**tex, "file": "brick.png", "tint": [1.0, 0.2, 0.4]}  # grey images: grey·tint
    got = image_albedo(grey, uv, 0.005)
    g = bilinear(load_texture("brick.png"), x, y)
    np.testing.assert_allclose(got, g[:, None] * [1.0, 0.2, 0.4], atol=1e-12)
    with pytest.raises(ValueError, match="spacing"):
        image_albedo(tex, uv, 0.0)


def test_load_texture_decodes_rgb_order_once():
    retina = load_texture("retina.jpg")
    assert retina.shape == (256, 256, 3) and retina.dtype == np.float32
    assert 0 <= retina.min() and retina.max() <= 1
    r, _, b = retina.reshape(-1, 3).mean(0)
    assert r > 2 * b  # a red fundus photograph: a BGR mix-up would make it blue
    brick = load_texture("brick.png")
    assert brick.ndim == 2 and brick.max() > 0.5
    assert load_texture("brick.png") is brick and not brick.flags.writeable  # cached, shared read-only
    with pytest.raises(ValueError, match="chelsea.png"):
        load_texture("chelsea.png")


def test_bundled_set_is_exactly_the_allowed_small_photographs():
    files = {p.name for p in TEXTURE_DIR.iterdir() if p.name != "README.md"}
    assert files == ALLOWED == set(IMAGE_TEXTURES) == set(texture_names())
    for forbidden in ("chelsea", "coffee", "astronaut"):
        assert not any(forbidden in f for f in files), forbidden
    assert sum((TEXTURE_DIR / f).stat().st_size for f in files) < 1.5e6
    for f in files:
        assert max(load_texture(f).shape[:2]) <= 256, f
    readme = (TEXTURE_DIR / "README.md").read_text()
    assert all(f"| {f} |" in readme for f in files) and "downscaled" in readme
    assert sum(load_texture(f).ndim == 2 for f in files) == 6  # brick, grass, gravel, camera, coins, text


def test_bundled_textures_are_package_data():
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["data_prep"]
    assert TEXTURE_DIR.parent == ROOT / "data_prep"
    for p in TEXTURE_DIR.iterdir():
        rel = p.relative_to(ROOT / "data_prep")
        assert any(rel.match(g) for g in globs), f"{rel} is not package data"
