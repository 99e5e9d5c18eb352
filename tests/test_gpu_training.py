"""benchmarks/gpu_training.py, the GPU session's training measurement, on the CPU, its three parts in turn as a
session runs them: the data (``--quick``: 4 + 4 scenes), training stopped by a SIGINT (gpu_session.sh's deadline),
which saves the step it stopped at, and the evaluations (several at once), one table row per model in step order."""
import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "gpu_training.py"


def _script(*args: str) -> list[str]:
    return [sys.executable, str(SCRIPT), "--device", "cpu", *args]


@pytest.mark.slow
def test_a_sigint_stopped_run_keeps_its_last_step_and_every_checkpoint_is_evaluated_in_order(tmp_path):
    """Only the script gets the signal (as ``kill -INT``): it passes it on and waits, so the trainer finishes its
    step and saves a checkpoint there (``subprocess.run`` killed it 0.25 s later, mid-step); ``eval`` then gives the
    shipped model's row and that checkpoint's, each its own evaluation's figures."""
    work = tmp_path / "work"
    data = subprocess.run(_script("--quick", "--part", "data", "--work", str(work)), cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert data.returncode == 0, data.stderr
    train = subprocess.Popen(_script("--part", "train", "--steps", "100000", "--every", "100000", "--work", str(work)),
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    metrics = work / "dit" / "metrics.csv"
    deadline = time.monotonic() + 240
    try:
        while not (metrics.is_file() and len(metrics.read_text().splitlines()) >= 3):  # the header and two steps
            assert train.poll() is None and time.monotonic() < deadline, train.communicate()
            time.sleep(0.1)
        os.kill(train.pid, signal.SIGINT)
        _, err = train.communicate(timeout=120)
    finally:  # a failure here must not leave a 100,000-step training run on the machine's cores
        if train.poll() is None:
            os.killpg(train.pid, signal.SIGKILL)
            train.communicate()
    assert train.returncode == 130 and "interrupted in part train" in err, err[-3000:]
    with open(metrics) as f:
        last = max(int(r["step"]) for r in csv.DictReader(f))
    saved = sorted(p.name for p in (work / "dit").glob("checkpoints/step_*"))
    assert f"step_{last:08d}" in saved, (last, saved)

    proc = subprocess.run(_script("--quick", "--part", "eval", "--work", str(work), "--jobs", "2"), cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line.split("|")[1:-1] for line in proc.stdout.splitlines() if line.startswith("| ")][-len(saved) - 1:]
    steps = [0] + [int(name.split("_")[1]) for name in saved]
    assert [int(r[0].replace(",", "")) for r in rows] == steps
    for row in rows:  # each row is its own model's evaluation (run at the same time as the others)
        with open(work / "eval" / f"step_{int(row[0].replace(',', ''))}.csv") as f:
            (e,) = csv.DictReader(f)
        assert row[3].strip() == f"{float(e['psnr_novel']):.2f}"
    assert rows[0][2].strip() == "nan" and float(rows[-1][2]) > 0  # the flow loss since the previous row
    assert f"min of wall time for its {last:,} steps" in proc.stdout  # the whole process, beside the step times
