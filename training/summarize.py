"""Summarise training runs for a model card: steps, wall time and loss curves per stage.

    python -m training.summarize RUN_DIR [RUN_DIR ...]

Prints a markdown table: per stage the steps taken, the summed step time (s), and for every logged loss
the mean over the first and the last 10 % of steps.
"""
from __future__ import annotations

import csv
import statistics
import sys
from pathlib import Path

__all__ = ["summarize_run", "main"]

SKIP = {"step", "epoch", "skipped", "lr", "grad_norm", "seconds"}


def summarize_run(run_dir: str | Path) -> dict:
    """{"stage", "steps", "seconds", "skipped", "losses": {name: (first-10 % mean, last-10 % mean)}}."""
    run_dir = Path(run_dir)
    rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
    done = [r for r in rows if r["skipped"] == "0"]
    k = max(1, len(done) // 10)
    losses = {}
    for name in done[0]:
        if name in SKIP or not done[0][name]:
            continue
        vals = [float(r[name]) for r in done if r.get(name)]
        losses[name] = (statistics.fmean(vals[:k]), statistics.fmean(vals[-k:]))
    return {"stage": run_dir.name, "steps": int(done[-1]["step"]), "seconds": sum(float(r["seconds"]) for r in done),
            "skipped": len(rows) - len(done), "losses": losses}


def main(argv: list[str] | None = None) -> int:
    runs = [summarize_run(p) for p in (argv if argv is not None else sys.argv[1:])]
    print("| stage | steps | step time (s) | skipped | losses: first 10 % → last 10 % |")
    print("|---|---:|---:|---:|---|")
    for r in runs:
        losses = ", ".join(f"{k} {a:.3g} → {b:.3g}" for k, (a, b) in r["losses"].items())
        print(f"| {r['stage']} | {r['steps']} | {r['seconds']:.0f} | {r['skipped']} | {losses} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
