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


def _session(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "GPU_SESSION_DRY": "1"})


@pytest.mark.slow
def test_every_step_runs_a_command_that_accepts_its_flags():
    proc = _session("all")
    assert proc.returncode == 0, proc.stderr
    commands = [shlex.split(line) for line in proc.stdout.splitlines()]
    assert len(commands) == 10
    helps: dict[str, str] = {}
    halves = []
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
            continue
        script = ROOT / cmd[1]
        assert script.is_file(), cmd
        if cmd[1] not in helps:
            helps[cmd[1]] = subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT, capture_output=True,
                                           text=True, timeout=120, check=True).stdout
        for flag in (a for a in cmd[2:] if a.startswith("--")):
            assert flag in helps[cmd[1]], (cmd, flag)
        part = cmd[cmd.index("--part") + 1]
        assert re.search(rf"--part \{{[^}}]*\b{part}\b", helps[cmd[1]]), (cmd, part)
    # the suite's halves: every test file in exactly one
    assert len(halves) == 2 and halves[0] and halves[1] and not halves[0] & halves[1]
    assert halves[0] | halves[1] == set((ROOT / "tests").glob("test_*.py"))


def test_an_unknown_or_missing_step_is_one_line_exit_2():
    for args in (("bogus",), ()):
        proc = _session(*args)
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("gpu_session.sh: error: ")
