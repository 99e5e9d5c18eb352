"""``diff4splat view``: its flags and the call of :func:`diff4splat.viewer_server.serve`."""
from __future__ import annotations

import argparse
from pathlib import Path

from diff4splat.viewer_server import serve

__all__ = ["register", "run"]


def register(sub) -> argparse.ArgumentParser:
    """Add ``view`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
    v = sub.add_parser("view", help="serve an output folder's interactive 4D viewer on 127.0.0.1",
                       description="Serve DIR's viewer (the full scene, never the size-reduced embedded copy) on "
                                   "127.0.0.1 only, and print the address; Ctrl-C stops. viewer.html in DIR "
                                   "also opens without a server (double click).")
    v.add_argument("folder", type=Path, metavar="DIR", help="output folder of `diff4splat generate`, `fit` or `render`")
    v.add_argument("--port", type=int, default=8000, help="TCP port on 127.0.0.1 (default: 8000; 0: any free port)")
    v.set_defaults(func=run)
    return v


def run(args: argparse.Namespace) -> int:
    """Serve the folder's viewer until Ctrl-C (:func:`diff4splat.viewer_server.serve`); returns its exit code."""
    return serve(args.folder, args.port)
