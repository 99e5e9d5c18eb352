"""``data_prep`` command line: ``validate``, ``synth``, ``curate``, ``convert``. Each subcommand is an
``_add_<name>(sub)`` adder in :data:`SUBCOMMANDS` that sets ``func=<handler>`` (parsed arguments → exit code).
Bad input gets one line on stderr and exit code 2; Ctrl-C exits 130 (:func:`diff4splat.utils.errors.run_cli`).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

from diff4splat.utils.devices import resolve_device
from diff4splat.utils.errors import run_cli

from .convert_cli import register as _add_convert  # data_prep convert SOURCE IN OUT
from .curate import DEFAULT_CONFIG_PATH, MODES, CurationConfig, curate
from .engine import add_engine_arguments, engine_from_args
from .synth_dataset import check_synth_request, synthesize
from .synth_world import SYNTH
from .validate import summarize, validate_path

__all__ = ["main", "build_parser", "SUBCOMMANDS"]


class CLIError(Exception):
    """A user error reported as one line with exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse would print usage + message)
        raise CLIError(message)


def _validate(args: argparse.Namespace) -> int:
    n, problems = validate_path(args.dir)
    if n == 0:  # nothing was checked: no "problems in scenes" summary; the root-level line is the summary
        for p in problems:
            if Path(p.file) != Path(args.dir):
                print(p)
        print(f"no scenes found in {args.dir} (a scene is a sub-folder with meta.json): 0 scenes checked")
        return 1
    for p in problems:
        print(p)
    print(summarize(n, problems))
    return 1 if problems else 0


def _add_validate(sub) -> None:
    p = sub.add_parser("validate", help="check scene folders against data_prep/FORMAT.md",
                       description="Check a dataset root (folder of scenes) or one scene folder; print each "
                                   "problem as '<file>: <problem>'. Exit 1 if any problem, 0 otherwise.")
    p.add_argument("dir", type=Path, help="dataset root or scene folder")
    p.set_defaults(func=_validate)


def _synth(args: argparse.Namespace) -> int:
    check_synth_request(args.scenes, args.seed, size=args.size, frames=args.frames, cameras=args.cameras,
                        workers=args.workers, static_ratio=args.static_ratio, texture_ratio=args.texture_ratio,
                        motions=args.motions, max_movers=args.max_movers, flags=True)  # the messages name the flags
    t0 = time.perf_counter()
    resolve_device(args.device, "--device")  # before anything is created
    engine = engine_from_args(args)
    paths = synthesize(args.out, args.scenes, args.seed, size=args.size, frames=args.frames, cameras=args.cameras,
                       static_ratio=args.static_ratio, texture_ratio=args.texture_ratio, motions=args.motions,
                       max_movers=args.max_movers, workers=args.workers,
                       progress=not args.quiet, device=args.device, engine=engine)
    print(f"{len(paths)} scene(s) in {args.out} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _add_synth(sub) -> None:
    p = sub.add_parser("synth", help="generate synthetic dynamic Gaussian scenes",
                       description="Render procedural scenes (room, 1-4 moving objects, synchronised cameras; "
                                   "surfaces textured procedurally or with crops of the bundled photographs "
                                   "in data_prep/textures/) with RGB, metric depth, 3D tracks and captions. "
                                   "Scenes already present are skipped, so a rerun resumes.")
    p.add_argument("--scenes", type=int, required=True, help="number of scenes N (scene_00000 … )")
    p.add_argument("--out", type=Path, required=True, help="dataset root to write")
    p.add_argument("--seed", type=int, default=0, help="global seed ≥ 0 (default 0)")
    p.add_argument("--size", type=int, default=SYNTH.size,
                   help=f"image width = height, pixels (default {SYNTH.size})")
    p.add_argument("--frames", type=int, default=SYNTH.frames, help=f"frames per camera (default {SYNTH.frames})")
    p.add_argument("--cameras", type=int, default=SYNTH.cameras,
                   help=f"synchronised cameras per scene (default {SYNTH.cameras})")
    p.add_argument("--static-ratio", type=float, default=SYNTH.static_ratio,
                   help=f"fraction of static scenes in [0, 1] (default {SYNTH.static_ratio})")
    p.add_argument("--texture-ratio", type=_unit_float, default=SYNTH.texture_ratio,
                   help="probability in [0, 1] that a surface gets a crop of a bundled photograph as texture "
                        f"(data_prep/textures/); 0: procedural textures only (default {SYNTH.texture_ratio})")
    p.add_argument("--motions", type=lambda text: tuple(k.strip() for k in text.split(",")), default=SYNTH.motions,
                   help=f"comma-separated kinds a moving object draws from (default: all, {','.join(SYNTH.motions)})")
    p.add_argument("--max-movers", type=int, default=None,
                   help="at most this many objects move in a dynamic scene (default: each with probability 0.7, at "
                        "least one); --motions translate --max-movers 1 makes every dynamic caption name one "
                        "direction (the direction test, training/direction_test.py)")
    add_engine_arguments(p, default_workers=1)
    p.add_argument("--device", default="cpu",
                   help="torch device that renders the scenes: cpu, cuda, cuda:N or auto (default: cpu, so a seed "
                        "gives the same bytes on every machine; CUDA renders with gsplat when installed)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_synth)


def _unit_float(text: str) -> float:
    """argparse type: a float in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 <= value <= 1:  # also NaN
        raise argparse.ArgumentTypeError(f"must be a number in [0, 1], got {text!r}")
    return value


def _curate(args: argparse.Namespace) -> int:
    config = CurationConfig.from_yaml(args.config or DEFAULT_CONFIG_PATH)
    records = curate(args.input, args.output, config, workers=args.workers, mode=args.mode, progress=not args.quiet,
                     engine=engine_from_args(args))
    n_ok = sum(r["accepted"] for r in records)
    print(f"curated {len(records)} scene(s): {n_ok} accepted, {len(records) - n_ok} rejected "
          f"-> {args.output / 'manifest.jsonl'}")
    return 0


def _add_curate(sub) -> None:
    p = sub.add_parser("curate", help="filter scenes; write a manifest and the accepted scenes",
                       description="Measure and filter the scenes of IN (data_prep/curate.py); write "
                                   "OUT/manifest.jsonl, OUT/accepted.txt and the accepted scenes. A rerun "
                                   "resumes: scenes already in the manifest are skipped.")
    p.add_argument("input", type=Path, help="dataset root (folder of scene folders)")
    p.add_argument("output", type=Path, help="output folder (created; must differ from IN)")
    p.add_argument("--config", type=Path, default=None,
                   help="YAML thresholds (default: configs/data_prep/curation_default.yaml)")
    add_engine_arguments(p, default_workers=os.cpu_count() or 1)
    p.add_argument("--mode", default="symlink", choices=MODES,
                   help="accepted scenes in OUT as absolute symlinks (symlink), full copies (copy) or not at all "
                        "(none; default: symlink)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_curate)


SUBCOMMANDS: list[Callable] = [_add_validate, _add_synth, _add_curate, _add_convert]
"""Parser adders, one per subcommand, in help order."""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="data_prep", description="diff4splat dataset tools (format: data_prep/FORMAT.md).")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``data_prep`` console script: the exit code (0 ok, 1 problems, 2 bad input, 130 Ctrl-C)."""
    def run() -> int:
        args = build_parser().parse_args(argv)
        return int(args.func(args))

    return run_cli("data_prep", run, expected=(CLIError,))


if __name__ == "__main__":
    sys.exit(main())
