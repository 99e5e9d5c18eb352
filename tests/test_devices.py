"""The device rule (diff4splat/utils/devices.py, docs/DESIGN.md "Devices"): ``resolve_device``, and a check of the
library's source that no tensor is created without a device and no tensor reaches numpy without ``.cpu()``
unless the line says why (``# device: …``)."""
import ast
from pathlib import Path

import pytest
import torch

from diff4splat.utils.devices import resolve_device

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ("diff4splat", "models", "training", "data_prep")
FACTORIES = frozenset({
    "tensor", "as_tensor", "scalar_tensor", "zeros", "ones", "empty", "full", "arange", "linspace", "logspace",
    "eye", "rand", "randn", "randint", "randperm", "normal", "tril_indices", "triu_indices", "empty_strided",
})
"""``torch.<name>(…)`` calls that create a tensor on the default device unless given ``device=``."""
REASON = "# device:"


def _has_reason(lines: list[str], node: ast.AST) -> bool:
    return any(REASON in lines[i - 1] for i in range(node.lineno, (node.end_lineno or node.lineno) + 1))


def _calls_attr(expr: ast.AST, names: set[str]) -> bool:
    """Whether ``expr`` holds a call ``….name(…)``, ``torch.name(…)`` or ``name(…)`` for a name in ``names``."""
    return any(isinstance(n, ast.Call) and (n.func.attr if isinstance(n.func, ast.Attribute) else
                                            getattr(n.func, "id", None)) in names for n in ast.walk(expr))


def device_rule_violations(source: str, filename: str = "<string>") -> list[str]:
    """``file:line: what`` for each tensor factory call without ``device=`` and each ``.numpy()`` whose
    receiver is not moved to the CPU (``.cpu()``, ``devices.host_values``) or made there (``torch.from_numpy``),
    where the call's lines carry no ``# device:`` reason."""
    lines = source.splitlines()
    out = []
    for node in ast.walk(ast.parse(source, filename)):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        f = node.func
        if (isinstance(f.value, ast.Name) and f.value.id == "torch" and f.attr in FACTORIES
                and not any(k.arg == "device" for k in node.keywords) and not _has_reason(lines, node)):
            out.append(f"{filename}:{node.lineno}: torch.{f.attr}(…) without device= (or a '{REASON}' reason)")
        if (f.attr == "numpy" and not node.args and not _has_reason(lines, node)
                and not _calls_attr(f.value, {"cpu", "from_numpy", "host_values"})):
            out.append(f"{filename}:{node.lineno}: .numpy() without .cpu() (or a '{REASON}' reason)")
    return out


def test_the_check_finds_what_it_should():
    bad = "x = torch.zeros(3)\ny = t.numpy()\nz = torch.randn(2, generator=g)\n"
    assert len(device_rule_violations(bad)) == 3
    good = ("x = torch.zeros(3, device=t.device)\ny = t.detach().cpu().numpy()\n"
            "z = torch.tensor([1.0])  # device: a CPU constant, moved with .to(x) below\n"
            "w = torch.from_numpy(a).double().numpy()\nv = torch.randn(\n  3,  # device: CPU generator\n)\n"
            "u = host_values(t).numpy()\n")
    assert device_rule_violations(good) == []


def test_library_code_creates_no_tensor_without_a_device():
    found = []
    for package in LIBRARY:
        for path in sorted((ROOT / package).rglob("*.py")):
            found += device_rule_violations(path.read_text(encoding="utf-8"), str(path.relative_to(ROOT)))
    assert not found, "the device rule (diff4splat/utils/devices.py) is broken at:\n" + "\n".join(found)


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    expected = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("auto") == resolve_device(None) == resolve_device(" AUTO ") == expected
    with pytest.raises(ValueError, match="--device: 'gpu' is not a torch device"):
        resolve_device("gpu", "--device")
    with pytest.raises(ValueError, match="trainer.device: cuda:99 is not available"):
        resolve_device("cuda:99", "trainer.device")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="cuda is not available"):
            resolve_device("cuda")
