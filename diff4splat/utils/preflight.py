"""The check run on import of this module, which ``diff4splat`` imports first: before torch, OpenCV or any weights
load (:func:`check_address_space`). Under a virtual-memory limit (``ulimit -v``, RLIMIT_AS) smaller than
:data:`MIN_ADDRESS_SPACE` those loads fail in ways no later check can report — a segfault in OpenCV's initialisers,
an ImportError naming a shared object, ``std::bad_alloc``, a failed mmap of the weights. Above it, each command's own
memory estimate (:func:`diff4splat.utils.limits.check_memory`) refuses what would not fit, in one line.
"""
from __future__ import annotations

import resource
import sys
from pathlib import Path

__all__ = ["MIN_ADDRESS_SPACE", "EXIT_USAGE", "COMMANDS", "check_address_space", "address_space_limit"]

MIN_ADDRESS_SPACE = 3 << 29
"""Bytes of address space (1.5 GiB) that loading the package and a command's libraries needs. Measured with torch
2.13, OpenCV 4.13: at 0.95 GiB ``import cv2`` segfaults, at 1.0–1.1 GiB the imports or the weights' mmap fail, at
1.43 GiB ``generate`` reaches its memory estimate (and refuses in one line), at 1.9 GiB it runs."""
EXIT_USAGE = 2
"""Exit code of an expected failure (bad input, corrupt file, unavailable device, OS error on a path)."""
COMMANDS = {"diff4splat": "diff4splat", "data_prep": "data_prep", "diff4splat.cli": "diff4splat",
            "data_prep.cli": "data_prep", "training.train": "train", "training.compose": "compose"}
"""The commands, as console scripts or ``python -m`` modules, by the name their errors print: for them a failed
:func:`check_address_space` is one ``<name>: error:`` line and exit :data:`EXIT_USAGE` rather than an ImportError."""


def address_space_limit() -> int | None:
    """This process's soft ``ulimit -v`` (RLIMIT_AS), bytes; None where it is unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    return None if soft == resource.RLIM_INFINITY else int(soft)


def check_address_space() -> None:
    """Refuse a virtual-memory limit below :data:`MIN_ADDRESS_SPACE`.

    Raises:
        ImportError: the limit, named with what it needs (imported as a library).
        SystemExit: :data:`EXIT_USAGE`, after printing the same as one line (run as one of :data:`COMMANDS`).
    """
    soft = address_space_limit()
    if soft is None or soft >= MIN_ADDRESS_SPACE:
        return
    message = (f"this process may map {soft / 2**30:.2f} GiB (ulimit -v, RLIMIT_AS), and loading torch, OpenCV and "
               f"the model needs at least {MIN_ADDRESS_SPACE / 2**30:.1f} GiB: raise the limit (ulimit -v)")
    argv = list(getattr(sys, "orig_argv", ()))  # the interpreter's own arguments: `python -m MODULE …`
    module = argv[argv.index("-m") + 1] if "-m" in argv[:-1] else None
    command = COMMANDS.get(module or (Path(sys.argv[0]).name if sys.argv else ""))
    if command is not None:
        print(f"{command}: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)
    raise ImportError(f"diff4splat: {message}")


check_address_space()
