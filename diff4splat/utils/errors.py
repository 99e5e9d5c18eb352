"""One error path for every command line tool (``diff4splat``, ``data_prep``, ``python -m training.train``).

An *expected* failure — bad input, a malformed or corrupt file (the readers raise ``ValueError`` naming
the file), an unavailable device, an operating-system error on a path the user gave (permissions, disk
full, a name too long, …), a GPU out of memory — is printed as one line ``<prog>: error: <what>: <why>``
on stderr and the tool exits with :data:`EXIT_USAGE` (2). Ctrl-C prints ``<prog>: interrupted`` and exits
with :data:`EXIT_INTERRUPTED` (130, the shell's 128 + SIGINT). Anything else is a bug in this code and keeps
its traceback (exit 1): :func:`is_expected` lists what is expected instead of swallowing everything.

C libraries under OpenCV (libpng, libjpeg) print warnings such as ``libpng warning: iCCP: known
incorrect sRGB profile`` straight to file descriptor 2, past Python's ``sys.stderr``; the readers wrap
their decode calls in :func:`quiet_c_stderr` so a run's stderr holds only this tool's own lines.
"""
from __future__ import annotations

import contextlib
import errno
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from diff4splat.utils.checks import MissingExtraError

__all__ = ["print_warnings", "EXIT_USAGE", "EXIT_INTERRUPTED", "EXPECTED_ERRNOS", "is_expected",
           "one_line", "run_cli", "quiet_c_stderr"]

EXIT_USAGE = 2
"""Exit code of an expected failure (bad input, corrupt file, unavailable device, OS error on a path)."""
EXIT_INTERRUPTED = 130
"""Exit code after Ctrl-C (128 + SIGINT, as shells report it)."""

EXPECTED_ERRNOS = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENAMETOOLONG,
                             errno.ENOTDIR, errno.EEXIST, errno.ENOENT, errno.EISDIR, errno.EADDRINUSE})
"""``OSError`` numbers that describe the user's paths or machine (permissions, read-only or full disk,
quota, name too long, a file where a folder is needed or the reverse, missing or existing entries, a TCP port
already in use by ``diff4splat view``).
Other ``OSError`` numbers (``EBADF``, ``EINVAL``, …) point at a bug and keep their traceback."""

_EXPECTED_OS_ERRORS = (FileNotFoundError, FileExistsError, PermissionError, IsADirectoryError, NotADirectoryError)


def is_expected(exc: BaseException) -> bool:
    """True when ``exc`` is a failure the user can fix (one line, exit 2) rather than a bug (traceback).

    Expected: ``ValueError`` (every argument check and every reader of a malformed or corrupt file
    raises it, naming the parameter or the file) and ``OSError`` whose ``errno`` is in
    :data:`EXPECTED_ERRNOS` (``FileNotFoundError``, ``FileExistsError``, ``PermissionError``,
    ``IsADirectoryError``, ``NotADirectoryError`` and ``ENOSPC``/``EROFS``/``ENAMETOOLONG``/… errors), and
    ``torch.OutOfMemoryError`` (a request larger than the GPU: the user lowers it or offloads), and
    :class:`MissingExtraError` (an optional extra to install).
    """
    if isinstance(exc, (ValueError, MissingExtraError, torch.OutOfMemoryError, *_EXPECTED_OS_ERRORS)):  # message only
        return True
    return isinstance(exc, OSError) and exc.errno in EXPECTED_ERRNOS


def one_line(exc: BaseException) -> str:
    """``exc`` as one line: ``<path>: <reason>`` for an ``OSError`` with a file name (``<path> -> <path2>:``
    for a rename); for a GPU out of memory, torch's first three sentences (what was asked, what is free) and the
    flags that lower it; else the message with every run of whitespace (newlines included) made one space;
    the exception's type name when the message is empty."""
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


def run_cli(prog: str, body: Callable[[], int], expected: tuple[type[BaseException], ...] = ()) -> int:
    """Run a command's ``body`` and turn its failures into exit codes (see the module docstring).

    Args:
        prog: the tool's name printed before ``error:`` (``diff4splat``, ``data_prep``, ``train``).
        body: the command; returns its exit code.
        expected: extra exception types reported as one line (e.g. the tool's own usage error class).

    Returns:
        ``body()``'s code; :data:`EXIT_USAGE` after an expected failure; :data:`EXIT_INTERRUPTED` after Ctrl-C.

    Raises:
        Any other exception of ``body`` unchanged (a bug: Python prints its traceback, exit code 1).
    """
    try:
        return body()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:
        if not (isinstance(e, expected) or is_expected(e)):
            raise
        print(f"{prog}: error: {one_line(e)}", file=sys.stderr)
        return EXIT_USAGE


@contextlib.contextmanager
def quiet_c_stderr() -> Iterator[None]:
    """Send file descriptor 2 to ``/dev/null`` inside the block (restored on exit, also after an exception).

    For calls into C libraries that print warnings themselves (libpng and libjpeg under ``cv2.imread`` /
    ``cv2.imdecode`` / ``cv2.imwrite``). Python's ``sys.stderr`` is flushed first, so this tool's own
    lines written before the block are kept. Everything written to fd 2 meanwhile is lost, by any
    thread: keep the block around the C call only. Without a real fd 2 (e.g. ``sys.stderr`` replaced
    and fd 2 closed) it does nothing.
    """
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
"""Categories that tell a library's developers about its dependencies' APIs, not the user about the run."""


def print_warnings(call: Callable, *args, prog: str = "diff4splat", **kwargs):
    """``call(*args, **kwargs)`` with the warnings that concern the user printed once each on stderr. Returns what
    ``call`` returns.

    Ours (raised from this project's code, e.g. the random-model notice): one ``<prog>: warning: …`` line each, the
    command line's form. A dependency's: its deprecation and future warnings (which concern its callers' code, e.g.
    torch's ``torch.jit.script_method is deprecated`` under ``--compile``) are dropped; any other is printed once as
    ``<module>: <Category>: …``, not labelled as ours. A warning repeated with the same text is printed once."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = call(*args, **kwargs)
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
    return out
