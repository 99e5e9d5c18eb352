"""Where imports sit (docs/DESIGN.md, "Conventions"): at the top of the module. An import inside a function or method
is either of an optional dependency — a package of one of pyproject.toml's extras, which the base install may
lack, or a ``torch.distributed`` submodule, which torch builds without distributed support lack — or its lines
say why (``# lazy: …``, e.g. a cost every command would pay at start-up). Checked over the library, the
benchmarks and the test suite."""
import ast
import re
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python ≥ 3.11

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("diff4splat", "models", "training", "data_prep", "benchmarks", "tests")
REASON = "# lazy:"
IMPORT_NAMES = {"import-linter": "importlinter", "opencv-contrib-python-headless": "cv2", "pyyaml": "yaml"}
"""Distribution → top-level import name where the two differ."""
OPTIONAL_SUBMODULES = ("torch.distributed.",)
"""Modules a torch build may lack (``torch.distributed.is_available()`` is False there)."""
MAYBE_NESTED_IMPORT = re.compile(r"(^[ \t]+|:[ \t]*)(import|from)[ \t]", re.M)
"""An import that may sit inside a function: indented, or after a colon (``def f(): import x``); a source without
one is not parsed."""


def optional_modules() -> frozenset[str]:
    """Top-level import names of every package in pyproject.toml's optional dependencies (its extras)."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    dists = {re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0].strip().lower() for reqs in extras.values() for r in reqs}
    return frozenset(IMPORT_NAMES.get(d, d.replace("-", "_")) for d in dists)


def _is_optional(node: ast.Import | ast.ImportFrom, optional: frozenset[str]) -> bool:
    if isinstance(node, ast.ImportFrom):
        names = [] if node.level else [node.module or ""]
    else:
        names = [a.name for a in node.names]
    return bool(names) and all(n.split(".")[0] in optional or n.startswith(OPTIONAL_SUBMODULES) for n in names)


def _imports_in_functions(node: ast.AST, inside: bool = False):
    """Every import statement under ``node`` that sits inside a function or method (one pass over the tree)."""
    for child in ast.iter_child_nodes(node):
        if inside and isinstance(child, ast.Import | ast.ImportFrom):
            yield child
        yield from _imports_in_functions(child, inside or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))


def misplaced_imports(source: str, optional: frozenset[str], filename: str = "<string>") -> list[str]:
    """``file:line: import …`` for each import inside a function that is neither of an optional module nor
    carries a ``# lazy:`` reason on one of its lines."""
    if not MAYBE_NESTED_IMPORT.search(source):
        return []
    lines = source.splitlines()
    out = []
    for node in _imports_in_functions(ast.parse(source, filename)):
        span = lines[node.lineno - 1:node.end_lineno]
        if not _is_optional(node, optional) and not any(REASON in line for line in span):
            out.append(f"{filename}:{node.lineno}: {span[0].strip()}")
    return out


def test_the_check_finds_what_it_should():
    optional = frozenset({"gsplat"})
    bad = ("def f():\n    import json\n"
           "class A:\n    def g(self):\n        from .x import y\n"
           "def h():\n    def inner():\n        from torch.nn import functional\n    return inner\n"
           "def k():\n    from torch.distributed import fsdp\n"  # the package itself is not the optional part
           "def m(): import os\n")
    assert [v.split(":")[1] for v in misplaced_imports(bad, optional)] == ["2", "5", "8", "11", "12"]
    assert misplaced_imports("def m(): import os\n", optional) == ["<string>:1: def m(): import os"]  # no indent
    good = ("import json\nfrom torch import nn\n"
            "def f():\n    import gsplat\n    from gsplat.cuda import _backend\n"
            "def g():\n    from torch.distributed.fsdp import fully_shard\n"
            "def h():\n    import onnx  # lazy: 0.1 s at start-up\n"
            "def k():\n    from x import (  # lazy: a reason on the first line\n        a,\n        b,\n    )\n"
            "def m():\n    from x import (\n        a,  # lazy: or on any line of the statement\n    )\n")
    assert misplaced_imports(good, optional) == []


def test_the_optional_modules_are_the_extras():
    optional = optional_modules()
    assert {"gsplat", "diffusers", "transformers", "peft", "matplotlib", "playwright"} <= optional
    assert not {"torch", "numpy", "onnx", "onnxruntime", "safetensors", "h5py", "kornia"} & optional  # core


def test_imports_inside_functions_are_optional_or_say_why():
    optional = optional_modules()
    found = []
    for folder in CHECKED:
        for path in sorted((ROOT / folder).rglob("*.py")):
            found += misplaced_imports(path.read_text(encoding="utf-8"), optional, str(path.relative_to(ROOT)))
    assert not found, ("imports inside functions (move them to the top, or say why with '# lazy: …'):\n"
                       + "\n".join(found))
