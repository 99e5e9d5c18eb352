"""Input files the user names: say what the path is when it is not a readable regular file."""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["check_input_file", "check_input_folder"]


def check_input_file(path: str | os.PathLike, what: str) -> Path:
    """``Path(path)`` if it is a regular file (or a link to one); ``what`` names it in messages (``"--cameras"``).

    Raises:
        FileNotFoundError: nothing exists at ``path`` (``"<what>: <path> does not exist"``), or a dangling symlink.
        ValueError: a folder, FIFO, socket, device or symlink loop (``"<what>: <path> is a folder, not a file"``).
    """
    return _check_input(path, what, stat.S_ISREG, "a file")


def check_input_folder(path: str | os.PathLike, what: str) -> Path:
    """``Path(path)`` if it is a folder (or a link to one); ``what`` names it in messages (``"--data"``).

    Raises:
        FileNotFoundError: nothing exists at ``path`` (``"<what>: <path> does not exist"``), or a dangling symlink.
        ValueError: a file, FIFO, socket, device or symlink loop (``"<what>: <path> is a FIFO (named pipe), not a
            folder"``).
    """
    return _check_input(path, what, stat.S_ISDIR, "a folder")


def _check_input(path: str | os.PathLike, what: str, wanted, noun: str) -> Path:
    """``Path(path)`` if ``wanted(st_mode)``; else the error saying what it is instead of ``noun``."""
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        if os.path.islink(p):
            raise FileNotFoundError(f"{what}: {p} is a symlink to a missing {noun[2:]} ({os.readlink(p)})") from None
        raise FileNotFoundError(f"{what}: {p} does not exist") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ValueError(f"{what}: {p} is a symlink loop, not {noun}") from None
        if e.errno == errno.ENOTDIR:
            raise FileNotFoundError(f"{what}: {p} does not exist (a parent is not a folder)") from None
        raise
    if wanted(mode):
        return p
    kind = ("a folder" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode)
            else "a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a special file")
    raise ValueError(f"{what}: {p} is {kind}, not {noun}")
