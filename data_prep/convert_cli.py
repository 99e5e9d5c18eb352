"""``data_prep convert SOURCE IN OUT``: convert one source scene to the scene format; with ``--each``, every clip of
``IN`` into the dataset root ``OUT``. :func:`register` adds it to the ``data_prep`` parser;
``python -m data_prep.convert_cli`` runs it alone. Source options (CONVERTERS.md): ``--option KEY=VALUE``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from diff4splat.utils.errors import run_cli

from .converters import CONVERTERS, convert, convert_each
from .engine import add_engine_arguments, engine_from_args

__all__ = ["register", "parse_options", "read_names", "main"]


def parse_options(items: list[str]) -> dict:
    """``["key=value", …]`` → {key: value}; a value that is valid JSON is decoded (lists become tuples), any
    other kept as a string. Raises ValueError: an item without ``=`` or with an empty key."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--option must be KEY=VALUE, got {item!r}")
        try:
            v = json.loads(value)
        except json.JSONDecodeError:
            v = value
        out[key.strip()] = tuple(v) if isinstance(v, list) else v
    return out


def _convert(args: argparse.Namespace) -> int:
    opts = parse_options(args.option)
    opts.update(start=args.start, stride=args.stride, max_frames=args.max_frames)
    if args.each is None:
        if args.engine != "local" or args.ray_address is not None or args.workers != 1:
            raise ValueError("--engine, --workers and --ray-address convert many clips: add --each")
        out = convert(args.source, args.input, args.output, replace=args.replace, **opts)
        print(f"converted {args.source} {args.input} -> {out}")
        return 0
    if args.replace:
        raise ValueError("--replace does not go with --each: a rerun resumes, skipping the scenes already written")
    names = read_names(args.each) if args.each else None
    engine = engine_from_args(args)
    outs = convert_each(args.source, args.input, args.output, names, engine=engine, progress=not args.quiet, **opts)
    print(f"converted {len(outs)} {args.source} clip(s) from {args.input} -> {args.output}")
    return 0


def read_names(path: str | Path) -> list[str]:
    """The clip names of a ``--each`` file: one per line, blank lines and ``#`` comments skipped. Raises
    FileNotFoundError: no such file; ValueError: no names in it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--each: file of clip names not found: {path}")
    names = [ln.strip() for ln in path.read_text(encoding="utf-8").splitlines()]
    names = [n for n in names if n and not n.startswith("#")]
    if not names:
        raise ValueError(f"--each: {path} names no clips (one name per line)")
    return names


def register(sub) -> None:
    """Add the ``convert`` subparser to an argparse sub-parsers object (sets ``func``)."""
    p = sub.add_parser("convert", help="convert a source dataset scene to the scene format",
                       description="Read one scene/sequence of SOURCE in its published layout (data_prep/"
                                   "CONVERTERS.md) and write a validated scene folder OUT.")
    p.add_argument("source", choices=sorted(CONVERTERS), help="source dataset")
    p.add_argument("input", type=Path, help="source scene/sequence folder (--each: the folder holding the clips)")
    p.add_argument("output", type=Path, help="output scene folder (--each: the dataset root to write)")
    p.add_argument("--each", nargs="?", const="", default=None, metavar="FILE",
                   help="convert every clip of INPUT into OUTPUT/<clip>: its sub-folders (RealEstate10K, Stereo4D: "
                        "its clip files), or the clip names listed in FILE, one per line; a rerun resumes")
    add_engine_arguments(p, default_workers=1)
    p.add_argument("--quiet", action="store_true", help="no progress bar (--each)")
    p.add_argument("--start", type=int, default=0, help="first source frame (default 0)")
    p.add_argument("--stride", type=int, default=1, help="keep every n-th frame (default 1)")
    p.add_argument("--max-frames", type=int, default=None, help="at most this many frames (default: all)")
    p.add_argument("--replace", action="store_true", help="replace an existing output folder (one clip)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="source-specific option, repeatable (e.g. --option sequence=abc --option depth_dir=/d)")
    p.set_defaults(func=_convert)


def main(argv: list[str] | None = None) -> int:
    """Run ``convert`` alone; errors print one line and return 2."""
    parser = argparse.ArgumentParser(prog="data_prep")
    register(parser.add_subparsers(dest="command", required=True))

    def run() -> int:
        args = parser.parse_args(["convert", *(sys.argv[1:] if argv is None else argv)])
        return int(args.func(args))

    return run_cli("data_prep", run, expected=(ImportError,))  # ImportError: a converter's optional dependency


if __name__ == "__main__":
    sys.exit(main())
