"""benchmarks/gpu_training.py, the GPU session's training measurement, on the CPU: its dry run gives one table row
per evaluated model in step order (the evaluations run several at once), and a SIGINT (gpu_session.sh's deadline)
lets the training run save the checkpoint of the step it stopped at."""
import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "gpu_training.py"


def _script(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", *args], cwd=ROOT, capture_output=True,
                          text=True, **kwargs)


@pytest.fixture(scope="module")
def quick_data(tmp_path_factory) -> Path:
    """The dry run's data: 4 training and 4 held-out scenes (``--part data --quick``)."""
    work = tmp_path_factory.mktemp("gt")
    proc = _script("--quick", "--part", "data", "--work", str(work), timeout=300)
    assert proc.returncode == 0, proc.stderr
    return work


@pytest.mark.slow
def test_the_dry_run_evaluates_every_checkpoint_in_step_order(quick_data, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(quick_data, work)
    proc = _script("--quick", "--work", str(work), "--jobs", "2", timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line.split("|")[1:-1] for line in proc.stdout.splitlines() if line.startswith("| ")]
    assert [r[0].strip() for r in rows[-3:]] == ["0", "2", "4"]
    for row in rows[-3:]:  # each row is its own model's evaluation (run at the same time as the others)
        with open(work / "eval" / f"step_{row[0].strip()}.csv") as f:
            (e,) = csv.DictReader(f)
        assert row[3].strip() == f"{float(e['psnr_novel']):.2f}"
    assert float(rows[-1][2]) > 0 and rows[-3][2].strip() == "nan"  # the flow loss since the previous row
    assert "min of wall time for its 4 steps" in proc.stdout  # the whole training process, beside the step times


@pytest.mark.slow
def test_a_sigint_lets_the_training_run_save_the_step_it_stopped_at(quick_data, tmp_path):
    """Only the script gets the signal (as ``kill -INT``): it passes it on and waits, so the trainer finishes its
    step and saves a checkpoint there; ``subprocess.run`` killed it 0.25 s later, mid-step."""
    work = tmp_path / "work"
    shutil.copytree(quick_data / "train", work / "train")
    proc = subprocess.Popen([sys.executable, str(SCRIPT), "--device", "cpu", "--part", "train", "--steps", "100000",
                             "--every", "100000", "--work", str(work)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    metrics = work / "dit" / "metrics.csv"
    deadline = time.monotonic() + 240
    while not (metrics.is_file() and len(metrics.read_text().splitlines()) >= 3):  # the header and two steps
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.1)
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    assert "interrupted in part train" in err
    with open(metrics) as f:
        last = max(int(r["step"]) for r in csv.DictReader(f))
    saved = sorted(p.name for p in (work / "dit").glob("checkpoints/step_*"))
    assert f"step_{last:08d}" in saved, (last, saved)
