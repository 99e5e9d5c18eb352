"""benchmarks/_common.py: what the benchmarks and the memory tests measure with."""
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import benchmark_module

common = benchmark_module("_common")
pytestmark = pytest.mark.slow  # each test starts processes


@pytest.mark.skipif(sys.platform != "linux", reason="ru_maxrss in KiB and its carry across exec are Linux's")
def test_a_commands_peak_memory_is_its_own_not_its_parents():
    """A child's ``ru_maxrss`` read straight through ``os.wait4`` starts at its parent's peak (Linux carries the
    peak of the memory map that ``exec`` replaces into the new program's); ``run_with_peak_memory`` reads the
    command's own: a bare interpreter under 100 MB after this process touched 1 GB, a command that touches
    400 MB between 400 and 600 MB, and the command's exit code."""
    touched = np.ones(125_000_000)  # 1 GB: this process's peak is above it from here on
    del touched
    naive = subprocess.Popen([sys.executable, "-c", "pass"])
    _, _, usage = os.wait4(naive.pid, 0)
    # what a child started straight from here reports: above 1 GB on Linux (CI); a sandbox kernel (gVisor) may not
    # carry the peak across exec, and then only the assertions below hold
    print(f"a bare interpreter started from this process: ru_maxrss {usage.ru_maxrss * 1024 / 1e9:.2f} GB")
    done, bare = common.run_with_peak_memory([sys.executable, "-c", "pass"])
    assert done.returncode == 0 and bare < 100e6
    done, big = common.run_with_peak_memory(
        [sys.executable, "-c", "import numpy as np; a = np.ones(50_000_000); raise SystemExit(3)"],
        capture_output=True)
    assert done.returncode == 3 and 400e6 < big < 600e6


def test_a_command_past_its_timeout_is_killed_and_raises(tmp_path):
    """``timeout``: the command is killed (not left running behind its starter) and TimeoutExpired is raised; a
    program that does not exist is one RuntimeError."""
    pid_file = tmp_path / "pid"
    script = "import os, sys, time; open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(60)"
    t0 = time.monotonic()
    with pytest.raises(subprocess.TimeoutExpired):
        common.run_with_peak_memory([sys.executable, "-c", script, str(pid_file)], timeout=2)
    assert time.monotonic() - t0 < 30
    with pytest.raises(ProcessLookupError):  # killed and reaped
        os.kill(int(pid_file.read_text()), 0)
    with pytest.raises(RuntimeError, match="did not start"):
        common.run_with_peak_memory(["/nonexistent/program"], capture_output=True)
