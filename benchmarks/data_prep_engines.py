"""``data_prep`` on its two engines: scenes per second of ``synth`` and ``curate`` on the local pool and on Ray Data,
at 1 and 2 workers, and what starting Ray costs.

    python benchmarks/data_prep_engines.py [--scenes 24] [--write]

Each row is one whole command as a user runs it (``data_prep synth --scenes N …`` at the default 64², 17 frames,
2 cameras, then ``data_prep curate`` of that dataset with the shipped thresholds), in a child process, timed wall
clock from start to exit: ``--engine ray`` starts a local Ray of ``--workers`` CPUs and stops it inside that time.
``scene s`` is the work of one scene on one worker, (wall − fixed) · workers / N, where ``fixed`` is the same
command's wall time at 1 scene (interpreter, imports, Ray start and stop). The Ray start-up row is ``ray.init`` of a
local 2-CPU Ray, a dataset of one trivial task, and ``ray.shutdown`` in a fresh interpreter, less the interpreter's
bare ``import ray``. Every ray dataset is checked to be the local one byte for byte.

``--write`` puts the table into docs/benchmarks.md (section ``data_prep_engines``).
"""
from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish  # noqa: E402

RAY_START = """
import time, ray, ray.data
t = time.perf_counter()
ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
ray.data.DataContext.get_current().enable_progress_bars = False
ray.data.from_items([{"i": 0}]).map(lambda r: r).take_all()
ray.shutdown()
print(time.perf_counter() - t)
"""


def wall(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def same_tree(a: Path, b: Path) -> bool:
    cmp = filecmp.dircmp(a, b)
    if cmp.left_only or cmp.right_only or cmp.funny_files:
        return False
    _, mismatch, errors = filecmp.cmpfiles(a, b, cmp.common_files, shallow=False)
    return not mismatch and not errors and all(same_tree(a / d, b / d) for d in cmp.common_dirs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    exe = [sys.executable, "-m", "data_prep"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for engine in ("local", "ray"):
            for workers in (1, 2):
                tag = f"{engine}{workers}"
                flags = ["--engine", engine, "--workers", str(workers), "--quiet"]
                synth = [*exe, "synth", "--seed", "3", *flags]
                fixed = wall([*synth, "--scenes", "1", "--out", str(tmp / f"one_{tag}")])
                t = wall([*synth, "--scenes", str(args.scenes), "--out", str(tmp / f"synth_{tag}")])
                same = same_tree(tmp / "synth_local1", tmp / f"synth_{tag}")
                rows.append(["synth", engine, workers, args.scenes, f"{t:.1f}", f"{args.scenes / t:.2f}",
                             f"{fixed:.1f}", f"{(t - fixed) * workers / max(args.scenes - 1, 1):.2f}", same])
                print(rows[-1], flush=True)
                curate = [*exe, "curate", str(tmp / "synth_local1"), *flags]
                fixed = wall([*exe, "curate", str(tmp / f"one_{tag}"), str(tmp / f"cone_{tag}"), *flags])
                t = wall([*curate, str(tmp / f"curate_{tag}")])
                same = same_tree(tmp / "curate_local1", tmp / f"curate_{tag}")
                rows.append(["curate", engine, workers, args.scenes, f"{t:.1f}", f"{args.scenes / t:.2f}",
                             f"{fixed:.1f}", f"{(t - fixed) * workers / max(args.scenes - 1, 1):.2f}", same])
                print(rows[-1], flush=True)
    bare = wall([sys.executable, "-c", "import ray, ray.data"])
    start = float(subprocess.run([sys.executable, "-c", RAY_START], check=True, capture_output=True,
                                 text=True).stdout.split()[-1])
    table = markdown_table(["command", "engine", "workers", "scenes", "wall s", "scenes/s", "fixed s (1 scene)",
                            "scene s (per worker)", "same bytes as local, 1 worker"], rows)
    note = (f"Ray start-up: {start:.1f} s for `ray.init` of a local 2-CPU Ray, one trivial Ray Data task and "
            f"`ray.shutdown`; `import ray, ray.data` alone: {bare:.1f} s. The ray rows include both.")
    publish("data_prep_engines", "data_prep on the local pool and on Ray Data", note, table, args.write)


if __name__ == "__main__":
    main()
