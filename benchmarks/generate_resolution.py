"""Cost of ``diff4splat generate`` against its output resolution: wall time and peak memory at 64², 256², 512²,
1024², 2048² (the shipped base model, 17 frames, ``examples/chelsea.png``).

    python benchmarks/generate_resolution.py [--resolutions 64 256 512 1024 2048] [--repeats 3] [--label L] [--write]

Each row is the real command in a child process (``_common.run_with_peak_memory``: its own peak resident set), the
fastest of ``--repeats`` runs at every size (the ratios divide by the 256² run's few seconds beyond the fixed cost,
so one slow small run would move every ratio, and a 2048² run varies by ±10 % on a shared machine).
The networks run at the model's own resolution (64²) whatever the output, so the cost that grows with the output
is the photo layer, assembly, pruning, rendering and writing. ``fixed`` is the wall time at 64² (imports, model
load, sampling, the least output); ``× 256²`` is (wall − fixed) / (wall at 256² − fixed), to hold against the
pixel ratio (16× at 1024², 64× at 2048²: linear cost). ``estimate`` is what ``generate`` printed as its time
estimate (:func:`diff4splat.utils.costs.generate_seconds`; printed above a minute).

``--write`` puts the table into docs/benchmarks.md (section ``generate_resolution`` or ``generate_resolution_<label>``).
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table, publish, run_with_peak_memory  # noqa: E402

from diff4splat.pipeline import Diff4SplatPipeline, load_model  # noqa: E402
from diff4splat.utils.costs import generate_seconds  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"


def run(resolution: int) -> tuple[float, float, str]:
    """(wall s, peak GB, the estimate line or "") of one ``generate`` at ``resolution``."""
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["diff4splat", "generate", str(EXAMPLE), "--resolution", str(resolution), "--quiet", "--out",
                str(Path(tmp) / "out")]
        t0 = time.perf_counter()
        done, peak = run_with_peak_memory(argv, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"generate at {resolution}: {done.stderr[-2000:]}")
    found = re.search(r"estimated (\d+) s", done.stderr)
    return wall, peak / 1e9, found.group(1) if found else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[64, 256, 512, 1024, 2048])
    ap.add_argument("--repeats", type=int, default=3, help="runs per resolution (the fastest is kept)")
    ap.add_argument("--label", default="", help="section suffix, e.g. before")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    model, _ = load_model(None, "base")
    pipe = Diff4SplatPipeline(model)
    results = {}
    for r in args.resolutions:
        results[r] = min((run(r) for _ in range(args.repeats)), key=lambda x: x[0])
        print(r, results[r], flush=True)
    fixed = results[min(results)][0]
    base = results.get(256, (None,))[0]
    rows = []
    for r, (wall, peak, estimate) in results.items():
        width, height = pipe.output_size(r)
        ratio = "" if base is None or base == fixed else f"{(wall - fixed) / (base - fixed):.1f}×"
        rows.append([f"{width}×{height}", f"{wall:.1f}", ratio, f"{(width * height) / 256**2:g}×", f"{peak:.2f}",
                     f"{generate_seconds(width, height, 17):.0f}", estimate or "—"])
    table = markdown_table(["output", "wall s", "× 256² (less fixed)", "pixels × 256²", "peak GB",
                            "time_estimate s", "printed"], rows)
    note = (f"17 frames, the shipped base model, the fastest of {args.repeats} runs; fixed = "
            f"the 64² run's {fixed:.1f} s. The estimate is printed when above a minute.")
    name = "generate_resolution" + (f"_{args.label}" if args.label else "")
    publish(name, f"generate against the output resolution{' (' + args.label + ')' if args.label else ''}", note,
            table, args.write)


if __name__ == "__main__":
    main()
