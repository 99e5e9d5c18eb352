"""The test suite's own layout rule: a test module imports shared code from tests/helpers.py only, never
from conftest or another test module (pytest may import them under other names, or twice)."""
import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


def _imported_modules(tree: ast.AST) -> list[str]:
    names = []
    for node in ast.walk(tree):  # also imports inside functions
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
        elif isinstance(node, ast.ImportFrom):  # relative: from . import x / from .x import y
            names += [node.module or ""] + [a.name for a in node.names]
    return names


def _forbidden(name: str) -> bool:
    top = name.split(".")[0]
    return top == "conftest" or top.startswith("test_") or name.startswith("tests.")


@pytest.mark.slow
def test_no_test_module_imports_conftest_or_another_test_module():
    files = sorted(TESTS.glob("test_*.py"))
    assert len(files) > 40  # the glob really found the suite
    bad = {f.name: [n for n in _imported_modules(ast.parse(f.read_text(), str(f))) if _forbidden(n)] for f in files}
    assert {k: v for k, v in bad.items() if v} == {}


def test_the_rule_catches_each_kind_of_forbidden_import():
    for src in ("from conftest import x", "import test_cli", "from test_io_ply import f", "import conftest",
                "def f():\n    from test_scene import g", "from tests.test_cli import main", "from . import test_cli"):
        assert any(_forbidden(n) for n in _imported_modules(ast.parse(src))), src
    for src in ("from helpers import tiny_model", "import testing_utils", "from _trainer_toy import ToyData"):
        assert not any(_forbidden(n) for n in _imported_modules(ast.parse(src))), src
