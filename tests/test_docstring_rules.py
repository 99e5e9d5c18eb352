"""The packages' docstrings and comments say what the code does, not its history: no git commit hashes and no
"main at …" / "until main" (history belongs in git log), no test file paths (test names belong in tests)."""
import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("diff4splat", "models", "training", "data_prep")

COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
"""A git commit hash, abbreviated (≥ 7 hex digits) or whole, with at least one digit and one letter (so neither a
number nor a word such as "defaced")."""
HISTORY = re.compile(r"\bmain at\b|\buntil main\b|\bon main\b", re.IGNORECASE)
TEST_PATH = re.compile(r"\btests/test_\w+\.py\b")


def _prose(source: str) -> list[tuple[int, str]]:
    """(line, text) of every docstring (module, class, function and attribute strings) and comment of ``source``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            out += [(node.lineno + i, line) for i, line in enumerate(node.value.value.splitlines())]
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            out.append((tok.start[0], tok.string))
    return out


def _violations(source: str) -> list[str]:
    return [f"{line}: {text.strip()}" for line, text in _prose(source)
            if COMMIT.search(text) or HISTORY.search(text) or TEST_PATH.search(text)]


@pytest.mark.slow
def test_no_commit_hash_history_or_test_path_in_the_packages_docstrings_and_comments():
    files = [f for p in PACKAGES for f in sorted((ROOT / p).rglob("*.py"))]
    assert len(files) > 100  # the glob found the packages
    bad = {str(f.relative_to(ROOT)): v for f in files if (v := _violations(f.read_text()))}
    assert bad == {}


@pytest.mark.parametrize("source", [
    '"""Three until main at 7e96020, now one."""',
    'def f():\n    """Fixed in 58eb52c0803ea9af3abec60841c2a093bdf1f951."""',
    'X = 1\n"""The value on main at the time."""',
    'x = 1  # was 2 before 1a2b3c4',
    'class A:\n    """Checked by tests/test_scene.py."""',
])
def test_the_rule_catches_each_kind(source):
    assert _violations(source)


@pytest.mark.parametrize("source", [
    '"""A 1024×1024 image, 0.4886025119029199, scene_00001, defaced, 0xff."""',
    'URL = "https://example.com/58eb52c0803ea9af3abec60841c2a093bdf1f951"  # a string value, not prose',
    '"""The main branch of the field: the domain at hand."""',
])
def test_the_rule_leaves_numbers_words_and_values_alone(source):
    assert not _violations(source)
