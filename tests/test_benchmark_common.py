"""benchmarks/_common.py: what the benchmarks and the memory tests measure with."""
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import benchmark_module

common = benchmark_module("_common")


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
    assert usage.ru_maxrss * 1024 > 1e9  # what a child started straight from here reports
    done, bare = common.run_with_peak_memory([sys.executable, "-c", "pass"])
    assert done.returncode == 0 and bare < 100e6
    done, big = common.run_with_peak_memory(
        [sys.executable, "-c", "import numpy as np; a = np.ones(50_000_000); raise SystemExit(3)"],
        capture_output=True)
    assert done.returncode == 3 and 400e6 < big < 600e6
