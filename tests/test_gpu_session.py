"""benchmarks/gpu_session.sh, the GPU session's runbook: every step names a command that exists here with the flags
it passes (a renamed part or flag would otherwise first fail on a lent GPU, whose minutes are few), and a bad step
is one line, exit 2."""
import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "gpu_session.sh"


def _session(*args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "GPU_SESSION_DRY": "1", **env})


@pytest.mark.slow
def test_every_step_runs_a_command_that_accepts_its_flags():
    proc = _session("all")
    assert proc.returncode == 0, proc.stderr
    commands = [shlex.split(line) for line in proc.stdout.splitlines()]
    assert len(commands) == 15
    helps: dict[str, str] = {}
    halves, whole = [], []
    for cmd in commands:
        assert cmd[0] == "python"
        if cmd[1] == "-m":  # pytest: its markers are registered (--strict-markers)
            assert cmd[2] == "pytest"
            if "-m" in cmd[3:]:
                marker = cmd[cmd.index("-m", 3) + 1]
                assert re.search(rf'^\s*"{marker}:', (ROOT / "pyproject.toml").read_text(), re.M), marker
            globs = [a for a in cmd[3:] if a.startswith("tests/")]
            if globs:
                halves.append({p for g in globs for p in ROOT.glob(g)})
            elif "-m" not in cmd[3:]:
                whole.append(cmd)
            continue
        script = ROOT / cmd[1]
        assert script.is_file(), cmd
        if cmd[1] not in helps:
            helps[cmd[1]] = subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT, capture_output=True,
                                           text=True, timeout=120, check=True).stdout
        for flag in (a for a in cmd[2:] if a.startswith("--")):
            assert flag in helps[cmd[1]], (cmd, flag)
        if "--part" in cmd:
            part = cmd[cmd.index("--part") + 1]
            assert re.search(rf"--part \{{[^}}]*\b{part}\b", helps[cmd[1]]), (cmd, part)
    assert len(whole) == 1  # the step `suite`: every test, in 8 processes where pytest-xdist is installed
    # the suite's halves: every test file in exactly one
    assert len(halves) == 2 and halves[0] and halves[1] and not halves[0] & halves[1]
    assert halves[0] | halves[1] == set((ROOT / "tests").glob("test_*.py"))


@pytest.mark.slow
def test_steps_at_once_and_generate_rows():
    """``a+b`` names both steps' commands (run at the same time), and GPU_GENERATE_ROWS reaches gpu.py's
    ``--rows``, which refuses a row that does not exist in one line, exit 2."""
    proc = _session("suite+command", "generate", GPU_GENERATE_ROWS="3,8")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 3 and lines[0].startswith("python -m pytest")
    assert lines[1:] == ["python benchmarks/gpu.py --part command --write",
                         "python benchmarks/gpu.py --part generate --write --rows 3,8"]
    bad = subprocess.run([sys.executable, "benchmarks/gpu.py", "--device", "cpu", "--quick", "--part", "generate",
                          "--rows", "3,99"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--rows" in bad.stderr
    one = subprocess.run([sys.executable, "benchmarks/gpu.py", "--device", "cpu", "--quick", "--part", "generate",
                          "--rows", "2"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert one.returncode == 0, one.stderr
    rows = [line for line in one.stdout.splitlines() if line.startswith("| ") and "**" in line]
    assert len(rows) == 1 and rows[0].startswith("| small (random) |")
    assert ("Rows not measured on this device (`--rows` left them out): base (shipped weights); paper, bf16"
            in one.stdout)


@pytest.mark.slow
def test_an_unknown_or_missing_step_is_one_line_exit_2():
    for args in (("bogus",), (), ("suite+bogus",)):
        proc = _session(*args)
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("gpu_session.sh: error: ")


@pytest.mark.slow
def test_the_command_part_runs_the_readme_command_in_a_child_and_measures_its_folder():
    """`benchmarks/gpu.py --part command` on the CPU, quick (the base model, 5 frames, 1 step, the README command's
    flags otherwise): the child writes its folder, and the row reads its stages and size back; with
    --no-frame-plys, frames/ holds nothing."""
    proc = subprocess.run([sys.executable, "benchmarks/gpu.py", "--device", "cpu", "--quick", "--part", "command"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = next(line for line in proc.stdout.splitlines() if line.startswith("| `diff4splat generate"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert "--no-frame-plys" in cells[0] and "--config base" in cells[0]
    wall, load, stages, rest = (float(c) for c in cells[1:5])
    assert wall > 0 and load > 0 and stages > 0 and abs(wall - load - stages - rest) < 0.15
    assert cells[6] == "–" and int(cells[7].replace(",", "")) > 0  # no GPU peak on the CPU
    assert float(cells[8].split()[0]) > 0 and cells[8].endswith("(0.00 in frames/)")


@pytest.mark.slow
def test_the_amx_check_runs_its_matmul_case_under_both_instruction_sets():
    """benchmarks/amx_nan_check.py (step ``amx``): the host line, then the matmul case in a child per ISA; whether
    NaN leaks depends on the CPU (oneDNN#5717 needs AMX), so only the report's form is asserted here."""
    proc = subprocess.run([sys.executable, "benchmarks/amx_nan_check.py", "--no-test"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("torch ") and "AMX flags:" in lines[0] and len(lines) == 3
    for line, isa in zip(lines[1:], ("DEFAULT", "AVX512_CORE_BF16"), strict=True):
        said = r"bmm: (clean|NaN leaked into a clean row) mm: (clean|NaN leaked into a clean row)"
        assert re.fullmatch(rf"ONEDNN_MAX_CPU_ISA={isa} matmul: {said}; without oneDNN \(torch.backends.mkldnn "
                            rf"off\): {said}", line), line


@pytest.fixture(scope="module")
def gpu_benchmark():
    """benchmarks/gpu.py as a module (it puts benchmarks/ on sys.path for its own imports)."""
    spec = importlib.util.spec_from_file_location("gpu_benchmark", ROOT / "benchmarks" / "gpu.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(gpu, label: str, total: str, peak: str, measured: str) -> list[str]:
    row = [label, "512², 49 fr, 50 st", "1,310,919", *["0.10"] * len(gpu.STAGES), f"**{total}**", peak, "sample",
           "4.1", measured]
    assert len(row) == len(gpu.HEADER)
    return row


def test_a_run_of_some_generate_rows_keeps_the_others_of_the_same_device(gpu_benchmark, monkeypatch, tmp_path):
    """``gpu.py --part generate --rows N --write`` keeps the table's other rows where the earlier table ran on the
    same device and software (its "Device:" text), in GENERATE's order, each with when it ran; an earlier table
    from another device gives none; a table written before the "measured" column maps by column name (—); the
    goal's verdicts are recomputed from every row kept or run."""
    gpu = gpu_benchmark
    eager, prefetch = (r[0] for r in gpu.GENERATE[2:4])
    compiled = gpu.GENERATE[7][0]
    monkeypatch.setattr(gpu, "device_name", lambda device: "GPU A, torch x")
    earlier = gpu._generate_table(None, {eager: _row(gpu, eager, "31.45", "24.95", "2026-11-25 10:00 UTC"),
                                         compiled: _row(gpu, compiled, "27.63", "24.82", "2026-11-25 10:05 UTC")},
                                  {}, [r for r in gpu.GENERATE if r[0] in (eager, compiled)], quick=False)
    path = tmp_path / "benchmarks.md"
    gpu.write_section("gpu_generate", earlier, path)  # benchmarks/_common.py's, as gpu.py imports them
    previous = gpu.read_section("gpu_generate", path)
    assert previous == earlier.strip()

    kept = gpu.earlier_rows(previous, "GPU A, torch x", {compiled})
    assert list(kept) == [eager] and kept[eager][-1] == "2026-11-25 10:00 UTC" and kept[eager][9] == "**31.45**"
    assert gpu.earlier_rows(previous, "GPU B, torch x", {compiled}) == {}
    assert gpu.earlier_rows(None, "GPU A, torch x", set()) == {}

    fresh = {prefetch: _row(gpu, prefetch, "28.10", "24.90", "2026-11-26 19:00 UTC"),
             compiled: _row(gpu, compiled, "26.38", "24.85", "2026-11-26 19:05 UTC")}
    merged = gpu._generate_table(None, fresh, kept, [r for r in gpu.GENERATE if r[0] in fresh], quick=False)
    lines = [line for line in merged.splitlines() if line.startswith("| ") and "**" in line]
    assert [line.split(" | ")[0][2:] for line in lines] == [eager, prefetch, compiled]  # GENERATE's order
    assert "2026-11-25 10:00 UTC" in lines[0] and "26.38" in lines[2] and "27.63" not in merged
    assert f"{eager}: 31.4 s (misses 30 s), peak 24.95 GB (meets 25 GB)." in merged
    assert f"{compiled}: 26.4 s (meets 30 s), peak 24.85 GB (meets 25 GB), after a 4.1 s warm-up" in merged
    assert f"kept (\"measured\" says when): {eager}." in merged
    assert "Rows not measured on this device (`--rows` left them out): base (shipped weights); small" in merged

    old = previous.replace(" | measured |", " |").replace("|---:|---:|\n", "|---:|\n", 1)
    old = re.sub(r" \| 2026-11-25 10:0\d UTC \|", " |", old)
    assert "measured" not in old.split("\n\n")[2]
    assert gpu.earlier_rows(old, "GPU A, torch x", set())[compiled][-1] == "—"
