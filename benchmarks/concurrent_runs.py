"""Two `generate` runs at once against one alone: wall time of the whole command, as a user runs it.

    python benchmarks/concurrent_runs.py [--repeats 3] [--setting LABEL=KEY=VALUE[,KEY=VALUE] ...] [--write]

Runs ``diff4splat generate examples/chelsea.png --out DIR --quiet`` alone and two at once (two processes started
together, each timed from its start to its exit), ``--repeats`` rounds; in each round every ``--setting`` runs
alone, then every setting runs its pair, so a drift of the machine's load reaches every setting alike. Prints,
per setting, min and median wall seconds alone and of each run of the pairs, the ratio of the medians (two at
once / alone) and the median CPU seconds (user + system) of a run. Two runs at once on a machine whose cores one
run already keeps busy should take about 2× one alone, and no more than 2.5×.

A setting adds variables to the commands' environment, e.g. ``spin=GOMP_SPINCOUNT=300000`` (libgomp's own
default: the package's thread settings, diff4splat/utils/devices.py, step aside when it is set) against
``passive=OMP_WAIT_POLICY=PASSIVE``; without ``--setting`` the package's defaults run. Other load on the machine
moves the figures: repeat, and quote medians.

``--write`` puts the table into docs/benchmarks.md (section ``concurrent_runs``).
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BASE_ENV = dict(os.environ)  # before diff4splat is imported: it sets OMP_WAIT_POLICY in this process (devices.py)
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, markdown_table, write_section  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def _start(out: Path, env: dict[str, str], log: Path) -> tuple[subprocess.Popen, float, Path]:
    cmd = [sys.executable, "-m", "diff4splat.cli", "generate", str(EXAMPLE), "--out", str(out), "--quiet",
           "--overwrite"]
    with open(log, "wb") as err:
        return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err), time.perf_counter(), log


def _wait(proc: subprocess.Popen, t0: float, log: Path) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of the finished process."""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"generate failed ({proc.returncode}): {log.read_text(errors='replace')[-500:]}")
    return wall, usage.ru_utime + usage.ru_stime


def measure(settings: dict[str, dict[str, str]], repeats: int) -> dict[str, dict[str, list]]:
    """{label: {"alone": [(wall, cpu)], "pair": [(wall, cpu)]}} over ``repeats`` interleaved rounds."""
    work = Path(tempfile.mkdtemp(prefix="concurrent_runs_"))
    results = {label: {"alone": [], "pair": []} for label in settings}
    try:
        for r in range(repeats):
            for label, extra in settings.items():
                env = {**BASE_ENV, **extra}
                results[label]["alone"].append(_wait(*_start(work / "a", env, work / "a.log")))
                print(f"round {r + 1} {label} alone: {results[label]['alone'][-1][0]:.1f} s", flush=True)
            for label, extra in settings.items():
                env = {**BASE_ENV, **extra}
                started = [_start(work / name, env, work / f"{name}.log") for name in ("a", "b")]
                results[label]["pair"] += [_wait(*s) for s in started]
                print(f"round {r + 1} {label} pair: {', '.join(f'{w:.1f}' for w, _ in results[label]['pair'][-2:])} s",
                      flush=True)
        return results
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _setting(text: str) -> tuple[str, dict[str, str]]:
    label, _, assignments = text.partition("=")
    return label, dict(item.split("=", 1) for item in assignments.split(",") if item)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--setting", action="append", default=[], metavar="LABEL=KEY=VALUE[,KEY=VALUE]")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    settings = dict(map(_setting, args.setting)) or {"package defaults": {}}
    results = measure(settings, args.repeats)
    rows = []
    for label, res in results.items():
        alone, pair = [w for w, _ in res["alone"]], [w for w, _ in res["pair"]]
        env = ", ".join(f"`{k}={v}`" for k, v in settings[label].items()) or "package defaults"
        rows.append([f"{label} ({env})", f"{min(alone):.1f} / {statistics.median(alone):.1f}",
                     f"{min(pair):.1f} / {statistics.median(pair):.1f}",
                     f"{statistics.median(pair) / statistics.median(alone):.2f}×",
                     f"{statistics.median(c for _, c in res['alone']):.1f} / "
                     f"{statistics.median(c for _, c in res['pair']):.1f}"])
    table = markdown_table(["setting", "alone: min / median s", "two at once, each: min / median s",
                            "ratio of medians", "CPU s per run: alone / two at once"], rows)
    body = (f"### Concurrent runs: two `generate` at once (CPU)\n\n`python benchmarks/concurrent_runs.py "
            f"{' '.join(sys.argv[1:])}` on {machine()}: `diff4splat generate examples/chelsea.png --out DIR` (base "
            f"model, 17 frames, 256×256) alone and two at once, {args.repeats} interleaved rounds; whole process, "
            f"imports and model loading included.\n\n{table}\n")
    print(body)
    if args.write:
        write_section("concurrent_runs", body)


if __name__ == "__main__":
    main()
