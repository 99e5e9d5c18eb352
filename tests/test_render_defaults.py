"""The render entry points take their default values from one home, diff4splat.render.defaults, and those
are gsplat's ``rasterization`` defaults (except the render mode, "RGB+ED" in this project)."""
import inspect
import itertools

import pytest

from diff4splat.prune import prune_scene, visibility_mask
from diff4splat.render import defaults, rasterize, rasterize_dense, raytrace, render_rolling_shutter
from diff4splat.render.gsplat_backend import rasterize_gsplat, use_gsplat
from diff4splat.render.sequence import render_path

RENDERERS = {"rasterize": rasterize, "rasterize_dense": rasterize_dense, "raytrace": raytrace,
             "rasterize_gsplat": rasterize_gsplat}
SCENE_RENDERERS = {"render_path": render_path, "render_rolling_shutter": render_rolling_shutter}
HOME = {
    "near_plane": "NEAR_PLANE", "far_plane": "FAR_PLANE", "eps2d": "EPS2D", "sh_degree": "SH_DEGREE",
    "render_mode": "RENDER_MODE", "rasterize_mode": "RASTERIZE_MODE", "camera_model": "CAMERA_MODEL",
    "tile_size": "TILE_SIZE", "background": "BACKGROUND",
}
GSPLAT_RASTERIZATION = {  # gsplat 1.4 ``rasterization`` signature defaults (docs.gsplat.studio, rasterization)
    "near_plane": 0.01, "far_plane": 1e10, "eps2d": 0.3, "sh_degree": None, "tile_size": 16,
    "rasterize_mode": "classic", "camera_model": "pinhole", "render_mode": "RGB",
}


def _defaults(fn) -> dict:
    return {n: p.default for n,
            p in inspect.signature(fn).parameters.items() if p.default is not inspect.Parameter.empty}


def _all_entry_points():
    return {**RENDERERS, **SCENE_RENDERERS, "use_gsplat": use_gsplat, "visibility_mask": visibility_mask,
            "prune_scene": prune_scene}


def test_every_shared_parameter_has_the_same_default_everywhere():
    entry = {name: _defaults(fn) for name, fn in _all_entry_points().items()}
    for (a, da), (b, db) in itertools.combinations(entry.items(), 2):
        for p in da.keys() & db.keys():
            assert da[p] == db[p], f"{p}: {a} has {da[p]!r}, {b} has {db[p]!r}"


@pytest.mark.parametrize("name", sorted(_all_entry_points()))
def test_defaults_are_the_named_constants_of_the_one_home(name):
    """Each default is the object in diff4splat.render.defaults, not a literal that happens to be equal
    (a float literal written in a signature is another object, so ``is`` tells them apart)."""
    found = 0
    for p, value in _defaults(_all_entry_points()[name]).items():
        if p in HOME:
            home = getattr(defaults, HOME[p])
            assert value == home, f"{name}({p}=...) default {value!r} != defaults.{HOME[p]} {home!r}"
            if isinstance(home, (float, tuple)):
                assert value is home, f"{name}({p}=...) repeats the value instead of using defaults.{HOME[p]}"
            found += 1
    assert found >= 1


def test_renderers_share_the_full_gsplat_argument_list():
    for name, fn in RENDERERS.items():
        assert set(HOME) - {"background"} <= set(_defaults(fn)), name


def test_defaults_are_gsplats_except_the_render_mode():
    ours = {p: getattr(defaults, HOME[p]) for p in GSPLAT_RASTERIZATION}
    assert {p: v for p, v in ours.items() if p != "render_mode"} == {
        p: v for p, v in GSPLAT_RASTERIZATION.items() if p != "render_mode"}
    assert defaults.RENDER_MODE == "RGB+ED"  # this project's choice: colour + expected depth
    assert defaults.BACKGROUND == (0.0, 0.0, 0.0)
