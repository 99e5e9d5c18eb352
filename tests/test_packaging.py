"""Packaging: every runtime import is a declared dependency, configs ship as package data, the README's test
command is the one CI runs, and the code cites the design doc that is in the repo.

Regression tests for a fresh install: round 1 shipped a main whose ONNX export failed on every clean
environment (``onnxscript`` undeclared) and whose installed wheel had no ``configs/``.
"""
import ast
import importlib.metadata
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from diff4splat.io.output_folders import INSTALLED_PACKAGES
from diff4splat.utils.config_files import CONFIGS_DIR
from models.bundle import CONFIG_DIR, DEFAULT_CONFIG, config_names, load_config
from training.stage_config import STAGE_CONFIG_DIR, load_stage, stage_names

tomllib = pytest.importorskip("tomllib")  # Python ≥ 3.11

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = INSTALLED_PACKAGES
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
IMPLICIT = {"onnxscript": "torch.onnx.export's dynamo exporter imports it; torch declares it optional"}
"""Modules our code never imports by name but a library call of ours needs at run time."""
MODULE_DIST = {"cv2": "opencv-contrib-python-headless", "yaml": "pyyaml", "OpenEXR": "openexr",
               "gsplat": "gsplat", "matplotlib": "matplotlib"}
"""Import name → distribution where the two differ (or where the installed metadata does not say)."""


def _dist_name(requirement: str) -> str:
    return re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].strip().lower()


def _third_party_imports(package: str) -> dict[str, str]:
    """Top-level module name → first file importing it, over every module of ``package`` (lazy imports too)."""
    found: dict[str, str] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in PACKAGES:
                    found.setdefault(top, str(path.relative_to(ROOT)))
    return found


def _module_to_dist(module: str) -> str | None:
    if module in MODULE_DIST:
        return MODULE_DIST[module]
    dists = importlib.metadata.packages_distributions().get(module)
    return dists[0].lower() if dists else None


@pytest.mark.slow
def test_every_runtime_import_is_a_declared_dependency():
    declared = {_dist_name(r) for r in PYPROJECT["project"]["dependencies"]}
    optional = {_dist_name(r) for reqs in PYPROJECT["project"]["optional-dependencies"].values() for r in reqs}
    missing = []
    for package in PACKAGES:
        for module, where in _third_party_imports(package).items():
            dist = _module_to_dist(module)
            if dist is None:
                missing.append(f"{module} ({where}): not installed, so not declared")
            elif dist not in declared and dist not in optional:
                missing.append(f"{module} → {dist} ({where})")
    for module, why in IMPLICIT.items():
        if _module_to_dist(module) not in declared:
            missing.append(f"{module}: {why}")
    assert not missing, "undeclared runtime dependencies: " + "; ".join(missing)


@pytest.mark.slow
def test_optional_imports_are_guarded():
    """gsplat (extra ``cuda``) and matplotlib (extra ``bench``) are imported only inside functions, so the
    base install never needs them."""
    optional_modules = {"gsplat", "matplotlib"}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in tree.body:  # module level only
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
                assert not optional_modules & {n.split(".")[0] for n in names}, f"{path}: top-level optional import"


DIFFUSERS_EXTRA = ("diffusers", "transformers", "peft", "sentencepiece", "ftfy")
"""The ``diffusers`` extra (pretrained backbones, models/backbones/)."""


@pytest.mark.slow
def test_the_default_paths_never_import_the_diffusers_extra():
    """The CPU default (generate with our networks, training our stages, ONNX export) imports none of the
    ``diffusers`` extra's packages: only a diffusers folder or a backbone stage loads them
    (``models.backbone_model.backbone_class``, ``training.backbone_training``)."""
    code = ("import sys, diff4splat.cli, diff4splat.generate, diff4splat.export, models.backbone_model, "
            "training.train, training.objectives, training.evaluate_cli; "
            f"print(sorted(m for m in {DIFFUSERS_EXTRA!r} if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_the_diffusers_extra_is_declared():
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert {re.split(r"[<>=!~ ]", r)[0] for r in extras["diffusers"]} == set(DIFFUSERS_EXTRA)


def test_the_protected_packages_are_the_ones_the_wheel_installs():
    """output_folders.INSTALLED_PACKAGES (what no output may replace) names pyproject's packages, and the
    import-linter's root packages."""
    include = PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
    assert sorted(f"{p}*" for p in INSTALLED_PACKAGES) == sorted(include)
    assert sorted(PYPROJECT["tool"]["importlinter"]["root_packages"]) == sorted(INSTALLED_PACKAGES)


def test_configs_are_package_data():
    """Every shipped YAML lies in the top-level configs/ (one home), reached from the package through the
    diff4splat/configs link, and matches a package-data glob of diff4splat in pyproject.toml."""
    package_data = PYPROJECT["tool"]["setuptools"]["package-data"]["diff4splat"]
    assert (ROOT / "diff4splat" / "configs").is_symlink() and CONFIGS_DIR.resolve() == ROOT / "configs"
    assert CONFIG_DIR.resolve() == ROOT / "configs" / "models"
    assert STAGE_CONFIG_DIR.resolve() == ROOT / "configs" / "training"
    files = sorted((ROOT / "configs").rglob("*.yaml"))
    assert {f.parent.name for f in files} == {"models", "training", "data_prep"}
    for f in files:
        rel = (CONFIGS_DIR / f.relative_to(ROOT / "configs")).relative_to(ROOT / "diff4splat")
        assert any(rel.match(g) for g in package_data), f"{f} is not package data"
    for package in ("models", "training", "data_prep"):  # the old homes are gone
        assert not list((ROOT / package).rglob("*.yaml")), package


def test_model_and_stage_config_names_are_separate():
    assert config_names() == ["base", "paper", "small", "tiny"]
    assert stage_names() == [
        "train_base_depth", "train_base_depth_scale", "train_base_dit", "train_base_ldrm", "train_base_ldrm_depth",
        "train_base_ldrm_distill", "train_base_motion", "train_base_motion_generator", "train_base_text",
        "train_base_text_mover",
        "train_base_vae_decoder", "train_cogvideox_stage1", "train_cogvideox_stage2", "train_cogvideox_stage3",
        "train_stage1", "train_stage2", "train_stage3", "train_vae", "train_wan_stage1", "train_wan_stage2",
        "train_wan_stage3"]
    assert load_config("small").height == 128
    assert load_stage("train_stage3").deformation


def test_unknown_config_lists_the_known_names():
    with pytest.raises(FileNotFoundError, match=r"'nonesuch' not found \(known: base, paper, small, tiny\)"):
        load_config("nonesuch")
    with pytest.raises(FileNotFoundError, match=r"train_stage1, train_stage2, train_stage3, train_vae"):
        load_stage("nonesuch")


def test_readme_starts_with_the_two_commands_ci_runs():
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", readme, re.S)
    assert block and readme.index("```bash") < 40, "the README opens with the command block"
    lines = block.group(1).strip().splitlines()
    assert len(lines) == 2
    assert "diff4splat generate examples/" in lines[0]
    # the backbone tests run, not skip; two pytest-xdist processes (the test extra installs pytest-xdist)
    assert lines[1] == 'pip install -e ".[test,diffusers]" && python -m pytest -n 2'
    ci = (ROOT / ".ci" / "run").read_text()
    assert "grep -m1 -F 'pip install -e \".[test' README.md" in ci and 'eval "$test_cmd"' in ci
    assert "-m venv" in ci and "torch==2.13.0" in ci


def test_code_cites_the_design_doc_in_the_repo():
    assert (ROOT / "docs" / "DESIGN.md").is_file()
    stale = []
    for package in (*PACKAGES, "benchmarks"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for i, line in enumerate(path.read_text().splitlines(), 1):
                if re.search(r"(?<![\w/])DESIGN\.md", line):
                    stale.append(f"{path.relative_to(ROOT)}:{i}")
    assert not stale, "cite docs/DESIGN.md, not DESIGN.md: " + ", ".join(stale)


def test_the_test_extra_installs_what_the_wheel_test_builds_with():
    """The wheel test builds without build isolation, in the test environment: the ``test`` extra holds the
    build-system's requirements (a Python 3.11 venv with torch 2.11 had setuptools 65, and the build failed)."""
    assert set(PYPROJECT["build-system"]["requires"]) <= set(PYPROJECT["project"]["optional-dependencies"]["test"])


def _missing_build_requirements() -> list[str]:
    """The build-system requirements (``name>=x.y`` or ``name``) this environment does not meet."""
    missing = []
    for req in PYPROJECT["build-system"]["requires"]:
        name, low = re.fullmatch(r"([A-Za-z0-9_.-]+)(?:>=([\d.]+))?", req).groups()
        try:
            have = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            missing.append(req)
            continue
        floor = [int(x) for x in (low or "0").split(".")]
        if [int(x) for x in re.findall(r"\d+", have)[:len(floor)]] < floor:
            missing.append(f"{req} (this environment has {have})")
    return missing


@pytest.mark.slow
def test_wheel_holds_configs_weights_and_entry_points(tmp_path):
    """The wheel a user installs (``pip install .`` or from a git URL) has the package data. Built without build
    isolation (nothing downloads), so from the build requirements the ``test`` extra installs; an environment set up
    otherwise (the GPU session installs the package with ``--no-deps``) is told what it lacks."""
    if missing := _missing_build_requirements():
        pytest.skip(f"the environment lacks the build requirements {missing}: pip install -e '.[test]'")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp_path), str(ROOT)], check=True, capture_output=True)
    (wheel,) = tmp_path.glob("diff4splat-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        entry_points = next(z.read(n).decode() for n in names if n.endswith("entry_points.txt"))
    for name in config_names():
        assert f"diff4splat/configs/models/{name}.yaml" in names
    for name in stage_names():
        assert f"diff4splat/configs/training/{name}.yaml" in names
    assert f"models/weights/{DEFAULT_CONFIG}/ldrm/model.safetensors" in names
    assert "diff4splat/configs/data_prep/curation_default.yaml" in names
    assert {"diff4splat/io/viewer_assets/viewer.js", "diff4splat/io/viewer_assets/LICENSES.txt"} <= names  # the viewer
    assert "diff4splat = diff4splat.cli:main" in entry_points and "evaluate = " in entry_points


def test_every_module_has_a_layer_in_the_import_contract():
    """A module the layers contract does not name is not checked by lint-imports: every top-level module of
    ``diff4splat`` (and the three other packages) must be named, itself or through its package."""
    (contract,) = [c for c in PYPROJECT["tool"]["importlinter"]["contracts"] if c["type"] == "layers"]
    named = {m.strip() for layer in contract["layers"] for m in re.split(r"[:|]", layer)}
    assert {"training", "data_prep", "models"} <= named
    pkg = ROOT / "diff4splat"
    modules = {f"diff4splat.{p.stem}" for p in pkg.glob("*.py") if p.stem != "__init__"}
    modules |= {f"diff4splat.{p.name}" for p in pkg.iterdir() if (p / "__init__.py").is_file()}
    assert modules, pkg
    missing = sorted(modules - named)
    assert not missing, f"add to a layer of [tool.importlinter] in pyproject.toml: {missing}"
