"""benchmarks/gpu_session.sh, the GPU session's runbook: every step names a command that exists here with the flags
it passes (a renamed part or flag would otherwise first fail on a lent GPU, whose minutes are few), and a bad step
is one line, exit 2."""
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
    assert len(commands) == 13
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
    assert "Rows not asked for in this run (`--rows`): base (shipped weights); paper, bf16" in one.stdout


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


def test_the_amx_check_runs_its_matmul_case_under_both_instruction_sets():
    """benchmarks/amx_nan_check.py (step ``amx``): the host line, then the matmul case in a child per ISA; whether
    NaN leaks depends on the CPU (oneDNN#5717 needs AMX), so only the report's form is asserted here."""
    proc = subprocess.run([sys.executable, "benchmarks/amx_nan_check.py", "--no-test"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("torch ") and "AMX flags:" in lines[0] and len(lines) == 3
    for line, isa in zip(lines[1:], ("DEFAULT", "AVX512_CORE_BF16"), strict=True):
        assert re.fullmatch(rf"ONEDNN_MAX_CPU_ISA={isa} matmul: bmm: (clean|NaN leaked into a clean row) "
                            r"mm: (clean|NaN leaked into a clean row)", line), line
