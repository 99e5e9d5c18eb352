"""One error path for every command line tool (``diff4splat``, ``data_prep``, ``python -m training.train``).

An expected failure (bad input, a malformed file, an unavailable device, an OS error on the user's path, a GPU out
of memory) prints one line ``<prog>: error: <what>: <why>`` on stderr and exits :data:`EXIT_USAGE`; Ctrl-C prints
``<prog>: interrupted`` and exits :data:`EXIT_INTERRUPTED`, SIGTERM the same line and :data:`EXIT_TERMINATED`
(:func:`sigterm_raises`: it unwinds through every ``finally``, so temporary outputs are removed and worker processes
ended before the exit); anything else is a bug and keeps its traceback (exit 1).
:func:`quiet_c_stderr` silences C libraries (libpng, libjpeg) that write to file descriptor 2 directly.
"""
from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch

from diff4splat.utils.checks import MissingExtraError
from diff4splat.utils.preflight import EXIT_USAGE

__all__ = ["printed_warnings", "EXIT_USAGE", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "Terminated", "sigterm_raises",
           "EXPECTED_ERRNOS", "is_expected",
           "one_line", "run_cli", "quiet_c_stderr", "parse_naming"]

EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT, as shells report it)."""
EXIT_TERMINATED = 128 + signal.SIGTERM
"""Exit code after SIGTERM (143, as shells report it)."""

EXPECTED_ERRNOS = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENAMETOOLONG,
                             errno.ENOTDIR, errno.EEXIST, errno.ENOENT, errno.EISDIR, errno.EADDRINUSE})
"""``OSError`` numbers that describe the user's paths or machine; other numbers point at a bug and keep their
traceback."""

_EXPECTED_OS_ERRORS = (FileNotFoundError, FileExistsError, PermissionError, IsADirectoryError, NotADirectoryError)


def is_expected(exc: BaseException) -> bool:
    """True when ``exc`` is a failure the user can fix (one line, exit 2) rather than a bug: ``ValueError``,
    :class:`MissingExtraError`, ``torch.OutOfMemoryError`` and ``OSError`` with an errno in :data:`EXPECTED_ERRNOS`."""
    if isinstance(exc, (ValueError, MissingExtraError, torch.OutOfMemoryError, *_EXPECTED_OS_ERRORS)):  # message only
        return True
    return isinstance(exc, OSError) and exc.errno in EXPECTED_ERRNOS


def parse_naming(path: str | os.PathLike, parse: Callable[[Any], Any], data: Any) -> Any:
    """``parse(data)`` for data read from the file ``path``; a ``ValueError`` or ``TypeError`` it raises is raised
    again as ``ValueError("<path>: <message>")`` (no chained traceback), so a bad field names its file."""
    try:
        return parse(data)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: {e}") from None


def one_line(exc: BaseException) -> str:
    """``exc`` as one line: ``<path>: <reason>`` (``<path> -> <path2>: …`` for a rename) for an ``OSError`` with a file
    name; for a GPU out of memory, torch's first three sentences and the flags that lower the request; else the message
    with whitespace runs made one space, or the type name when empty."""
    if isinstance(exc, torch.OutOfMemoryError):  # torch's allocator advice follows what was asked and what is free
        asked = ". ".join(str(exc).split(". ")[:3]).rstrip(".")
        return (" ".join(asked.split()) + ". Lower the request (--frames, --resolution), or use --offload model or "
                "--dtype bfloat16 where the command has them")
    if isinstance(exc, OSError) and exc.filename is not None:
        where = os.fsdecode(exc.filename)
        if exc.filename2 is not None:
            where += f" -> {os.fsdecode(exc.filename2)}"
        why = exc.strerror or (errno.errorcode.get(exc.errno, "") if exc.errno else "") or type(exc).__name__
        text = f"{where}: {why}"
    else:
        text = str(exc)
    return " ".join(text.split()) or type(exc).__name__


class Terminated(SystemExit):
    """SIGTERM arrived while :func:`sigterm_raises` was active. A ``SystemExit`` of code :data:`EXIT_TERMINATED`:
    it unwinds through every ``finally`` like Ctrl-C, and uncaught it exits 143 without a traceback."""

    def __init__(self) -> None:
        super().__init__(EXIT_TERMINATED)


def _raise_terminated(signum, frame):
    raise Terminated


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """While the block runs, SIGTERM raises :class:`Terminated` in the main thread. Only over the default handler (one
    installed by someone else stays), and only in the main thread (where Python handles signals); the default is put
    back after the block."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return
    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def run_cli(prog: str, body: Callable[[], int], expected: tuple[type[BaseException], ...] = ()) -> int:
    """Run a command's ``body`` (returns its exit code) under the module docstring's rules; ``prog`` is printed before
    ``error:``, ``expected`` adds exception types reported as one line.

    Returns:
        ``body()``'s code; :data:`EXIT_USAGE` after an expected failure; :data:`EXIT_INTERRUPTED` after Ctrl-C,
        :data:`EXIT_TERMINATED` after SIGTERM (:func:`sigterm_raises` is active while ``body`` runs).

    Raises:
        Any other exception of ``body``, unchanged.
    """
    with sigterm_raises():
        try:
            return body()
        except KeyboardInterrupt:
            print(f"{prog}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except Terminated:
            print(f"{prog}: interrupted", file=sys.stderr)
            return EXIT_TERMINATED
        except Exception as e:
            if not (isinstance(e, expected) or is_expected(e)):
                raise
            print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
            return EXIT_USAGE


@contextlib.contextmanager
def quiet_c_stderr() -> Iterator[None]:
    """File descriptor 2 sent to ``/dev/null`` inside the block (restored on exit), for C libraries that print warnings
    themselves (``cv2.imread``, ``cv2.imwrite``). ``sys.stderr`` is flushed first; anything written to fd 2 meanwhile,
    by any thread, is lost. Without a real fd 2 it does nothing."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no fd 2 to redirect
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
        finally:
            os.close(devnull)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


_OUR_PACKAGES = tuple(str(Path(__file__).resolve().parents[2] / name) + os.sep
                      for name in ("diff4splat", "models", "training", "data_prep"))
"""The folders of this project's four packages: a warning raised from code in them is ours."""
_DEVELOPER_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, FutureWarning)
"""Categories that concern a library's developers, not the user."""


@contextlib.contextmanager
def printed_warnings(prog: str = "diff4splat") -> Iterator[None]:
    """Record the warnings raised inside the block and print those that concern the user once each on stderr when it
    ends, also when it ends by an exception (before that error's line). Ours as ``<prog>: warning: …``; a
    dependency's deprecation and future warnings dropped, any other printed as ``<module>: <Category>: …``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        finally:
            seen = set()
            for w in caught:
                ours = os.path.abspath(w.filename).startswith(_OUR_PACKAGES)
                if not ours and issubclass(w.category, _DEVELOPER_WARNINGS):
                    continue
                line = (f"{prog}: warning: {w.message}" if ours else
                        f"{Path(w.filename).stem}: {w.category.__name__}: {w.message}")
                if line not in seen:
                    seen.add(line)
                    print(line, file=sys.stderr)
