"""diff4splat.utils.constants is the only home of the 3DGS thresholds: no other module of the repo defines a
module-level constant with one of their values or names (scene's gate, the output's empty-pixel cut,
the projection's thresholds and the PLY epsilon all used to be separate copies)."""
import ast
from pathlib import Path

import torch

from diff4splat.io.scene_folder import fill_empty_depth
from diff4splat.render.projection import splat_alpha
from diff4splat.utils import constants
from diff4splat.utils.constants import ALPHA_MAX, ALPHA_MIN, OPACITY_EPS, T_MIN

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("diff4splat", "models", "training", "data_prep", "benchmarks")


def _module_level_numbers(path: Path) -> dict[str, float]:
    """Names assigned a numeric expression at module level (e.g. ``X = 1.0 / 255.0``) → value."""
    out = {}
    for node in ast.parse(path.read_text(), str(path)).body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node,
                                                                                                ast.AnnAssign) else []
        value = getattr(node, "value", None)
        for t in targets:
            if isinstance(t, ast.Name) and value is not None:
                try:
                    v = eval(compile(ast.Expression(value), str(path), "eval"), {"__builtins__": {}})  # noqa: S307
                except Exception:  # noqa: BLE001 - not a literal expression
                    continue
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    out[t.id] = float(v)
    return out


def test_no_module_defines_its_own_copy_of_a_threshold():
    names = set(constants.__all__)
    copies = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path == ROOT / "diff4splat" / "utils" / "constants.py":
                continue
            for name, v in _module_level_numbers(path).items():
                if name.lstrip("_") in names or v in (ALPHA_MIN, ALPHA_MAX):
                    copies.append(f"{path.relative_to(ROOT)}: {name} = {v}")
    assert copies == []


def test_scanner_finds_a_copy(tmp_path):
    src = tmp_path / "probe.py"
    src.write_text("GATE = 1.0 / 255.0\n_T_MIN: float = 1e-4\nx = foo(3)\nclass A:\n    B = 0.99\n")
    assert _module_level_numbers(src) == {"GATE": ALPHA_MIN, "_T_MIN": T_MIN}


def test_the_values():
    assert (ALPHA_MAX, ALPHA_MIN, T_MIN, OPACITY_EPS) == (0.99, 1.0 / 255.0, 1e-4, 1e-6)


def test_renderer_and_output_agree_on_the_empty_pixel_threshold():
    """A pixel whose only Gaussian has alpha exactly ALPHA_MIN is drawn by the renderer and counted as
    covered by the depth writer; one just below is neither."""
    below = torch.nextafter(torch.tensor(ALPHA_MIN, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    o = torch.stack([torch.tensor(ALPHA_MIN, dtype=torch.float64), below])
    alpha = splat_alpha(torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64),
                        torch.tensor([[1.0, 0.0, 1.0]] * 2, dtype=torch.float64), o)
    assert alpha.tolist() == [ALPHA_MIN, 0.0]
    depth = fill_empty_depth(torch.tensor([[[2.0, 3.0]]]), o.reshape(1, 1, 2), fallback=9.0)
    assert depth.tolist() == [[[2.0, 2.0]]]  # the second pixel is empty: it gets the far depth of the path
