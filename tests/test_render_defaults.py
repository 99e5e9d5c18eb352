"""The render entry points take their default values from one home, diff4splat.render.settings, and those
are gsplat's ``rasterization`` defaults (except the render mode, "RGB+ED" in this project). The public entry
points keep gsplat's keyword list and pack it into one RasterSettings, which every function behind them takes."""
import ast
import importlib
import inspect
import itertools
from pathlib import Path

import pytest
import torch

import diff4splat
from diff4splat.assembly.prune import prune_scene, visibility_mask
from diff4splat.cameras.lenses import ThinLens
from diff4splat.render import rasterize, rasterize_dense, raytrace, render_rolling_shutter
from diff4splat.render import settings as render_settings
from diff4splat.render.fused import project_fused
from diff4splat.render.projection import project_gaussians
from diff4splat.render.rasterize import choose_path, rasterize_gsplat, render_pipeline
from diff4splat.render.raytrace import render_rays
from diff4splat.render.sequence import render_path
from diff4splat.render.settings import GSPLAT_KEYWORDS, RasterSettings, validate_inputs

RENDERERS = {"rasterize": rasterize, "rasterize_dense": rasterize_dense, "raytrace": raytrace}
"""The public entry points with gsplat's keyword list (users call them)."""
SETTINGS_TAKERS = {"rasterize_gsplat": rasterize_gsplat, "render_pipeline": render_pipeline,
                   "render_rays": render_rays, "validate_inputs": validate_inputs}
"""The functions behind them: they take one RasterSettings instead of the keywords."""
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
    return {**RENDERERS, **SCENE_RENDERERS, "visibility_mask": visibility_mask,
            "prune_scene": prune_scene, "RasterSettings": RasterSettings, "project_gaussians": project_gaussians,
            "choose_path": choose_path}


def test_the_fused_projection_takes_the_reference_signature_as_its_own():
    """project_fused's settings are project_gaussians' keywords with its defaults (one home): an unknown keyword is
    refused as the reference refuses it, and omitted ones take the reference's defaults."""
    g = torch.Generator().manual_seed(0)
    f64 = {"generator": g, "dtype": torch.float64}
    K = torch.tensor([[[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]], dtype=torch.float64)
    args = (torch.randn(20, 3, **f64) * 0.3 + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64),
            torch.nn.functional.normalize(torch.randn(20, 4, **f64), dim=-1), torch.rand(20, 3, **f64) * 0.05 + 0.01,
            torch.rand(20, **f64), torch.eye(4, dtype=torch.float64)[None], K, 32, 24)
    with pytest.raises(TypeError, match="near"):
        project_fused(*args, near=0.5)
    explicit = {n: p.default for n, p in inspect.signature(project_gaussians).parameters.items()
                if p.default is not inspect.Parameter.empty}
    a, b = project_fused(*args), project_fused(*args, **explicit)
    torch.testing.assert_close(a.means2d, b.means2d, rtol=0, atol=0)
    torch.testing.assert_close(a.conics, b.conics, rtol=0, atol=0)


def test_every_shared_parameter_has_the_same_default_everywhere():
    entry = {name: _defaults(fn) for name, fn in _all_entry_points().items()}
    for (a, da), (b, db) in itertools.combinations(entry.items(), 2):
        for p in da.keys() & db.keys():
            assert da[p] == db[p], f"{p}: {a} has {da[p]!r}, {b} has {db[p]!r}"


@pytest.mark.parametrize("name", sorted(_all_entry_points()))
def test_defaults_are_the_named_constants_of_the_one_home(name):
    """Each default is the object in diff4splat.render.settings, not a literal that happens to be equal
    (a float literal written in a signature is another object, so ``is`` tells them apart)."""
    found = 0
    for p, value in _defaults(_all_entry_points()[name]).items():
        if p in HOME:
            home = getattr(render_settings, HOME[p])
            assert value == home, f"{name}({p}=...) default {value!r} != settings.{HOME[p]} {home!r}"
            if isinstance(home, (float, tuple)):
                assert value is home, f"{name}({p}=...) repeats the value instead of using settings.{HOME[p]}"
            found += 1
    assert found >= 1


def test_renderers_share_the_full_gsplat_argument_list():
    for name, fn in RENDERERS.items():
        assert set(HOME) - {"background"} <= set(_defaults(fn)), name


def test_defaults_are_gsplats_except_the_render_mode():
    ours = {p: getattr(render_settings, HOME[p]) for p in GSPLAT_RASTERIZATION}
    assert {p: v for p, v in ours.items() if p != "render_mode"} == {
        p: v for p, v in GSPLAT_RASTERIZATION.items() if p != "render_mode"}
    assert render_settings.RENDER_MODE == "RGB+ED"  # this project's choice: colour + expected depth
    assert render_settings.BACKGROUND == (0.0, 0.0, 0.0)


def test_functions_behind_the_entry_points_take_the_settings_not_the_keywords():
    for name, fn in SETTINGS_TAKERS.items():
        params = inspect.signature(fn).parameters
        assert "settings" in params, name
        assert not set(params) & (set(HOME) | set(GSPLAT_KEYWORDS)), f"{name} re-lists renderer keywords"


def test_settings_fields_are_gsplats_keywords_plus_camera_params():
    fields = list(inspect.signature(RasterSettings).parameters)
    assert fields == [*GSPLAT_KEYWORDS, "camera_params"]
    assert set(_defaults(rasterize)) - {"compositor"} == set(fields)
    s = RasterSettings()
    assert s.gsplat_keywords() == {k: getattr(render_settings, HOME[k]) if k in HOME else None for k in GSPLAT_KEYWORDS}
    assert not s.antialiased and RasterSettings(rasterize_mode="antialiased").antialiased
    assert set(s.projection_keywords()) == set(_defaults(project_gaussians))


CUSTOM = dict(near_plane=0.5, far_plane=20.0, eps2d=0.2, sh_degree=0, render_mode="RGB+D",
              rasterize_mode="antialiased", tile_size=8)


@pytest.mark.parametrize("entry, module, inner, extra", [
    (rasterize, "diff4splat.render.rasterize", "render_pipeline", {}),
    (rasterize, "diff4splat.render.rasterize", "render_rays", {"camera_model": "fisheye"}),
    (rasterize, "diff4splat.render.rasterize", "render_rays", {"camera_params": ThinLens(0.05, 3.0)}),
    (rasterize_dense, "diff4splat.render.rasterize", "render_pipeline", {}),
    (raytrace, "diff4splat.render.raytrace", "render_rays", {"camera_params": ThinLens(0.05, 3.0)}),
])
def test_each_entry_point_packs_every_keyword_into_the_settings(monkeypatch, entry, module, inner, extra):
    """Every keyword given to a public entry point reaches the function behind it, once, in the settings."""
    seen = []
    monkeypatch.setattr(importlib.import_module(module), inner, lambda *a, **kw: seen.append(a) or "done")
    args = [torch.zeros(s) for s in ((2, 3), (2, 4), (2, 3), (2,), (2, 3), (1, 4, 4), (1, 3, 3))]
    bg = torch.ones(1, 3)
    assert entry(*args, 8, 6, backgrounds=bg, **CUSTOM, **extra) == "done"
    (got,) = seen
    settings = got[-1]
    assert isinstance(settings, RasterSettings) and got[-2:-1] == (6,)
    want = {**{k: v for k, v in RasterSettings().__dict__.items()}, **CUSTOM, "backgrounds": bg, **extra}
    assert settings.__dict__ == want


def _literal_defaults(path: Path):
    """(function or class, parameter or field) of every default written as a literal in ``path`` for a
    parameter named like a render setting (HOME); a name (``NEAR_PLANE``, ``settings.EPS2D``) is not a literal."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            pos = a.posonlyargs + a.args
            pairs = [*zip(pos[len(pos) - len(a.defaults):], a.defaults, strict=True),
                     *((k, d) for k, d in zip(a.kwonlyargs, a.kw_defaults, strict=True) if d is not None)]
            for arg, default in pairs:
                if arg.arg in HOME and not isinstance(default, (ast.Name, ast.Attribute)):
                    yield node.name, arg.arg
        elif isinstance(node, ast.ClassDef):
            for st in node.body:
                if (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name) and st.target.id in HOME
                        and st.value is not None and not isinstance(st.value, (ast.Name, ast.Attribute))):
                    yield node.name, st.target.id



def test_no_default_is_written_anywhere_but_the_home():
    """A render setting's default written as a literal anywhere in the library (a signature's ``0.01``, a
    dataclass field's ``"pinhole"``) fails here: defaults live in diff4splat/render/settings.py only (as module
    constants, which this does not flag)."""
    root = Path(diff4splat.__file__).parent
    found = {(str(path.relative_to(root)), fn, p) for path in sorted(root.rglob("*.py"))
             for fn, p in _literal_defaults(path)}
    assert found == set(), found
