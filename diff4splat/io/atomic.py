"""Atomic file writes (a file appears complete or not at all; folders: :mod:`diff4splat.io.output_folders`), and
write errors as ``OSError(errno, strerror, <path>)`` naming the file the user asked for (README, "Errors"), also
where Python's ``write()`` gives no name, OpenCV fails silently or OpenEXR/safetensors raise other errors
(:func:`naming_os_errors`, asking the file system via :func:`disk_full_error`).
"""
from __future__ import annotations

import errno
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_output_path", "naming_os_errors", "disk_full_error", "current_umask", "follow_umask"]

_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def current_umask() -> int:
    """The process's umask (from ``/proc/self/status`` on Linux; elsewhere set and put back at once)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def follow_umask(root: str | os.PathLike) -> None:
    """Give the file ``root``, or every file under the folder ``root``, the mode 0o666 & ~umask (symlinks are left
    alone): safetensors creates its files 0600."""
    mode = 0o666 & ~current_umask()
    root = Path(root)
    files = [root] if not root.is_dir() else [Path(d) / n for d, _, names in os.walk(root) for n in names]
    for p in files:
        if not p.is_symlink() and (p.stat().st_mode & 0o777) != mode:
            os.chmod(p, mode)


def disk_full_error(where: str | os.PathLike) -> OSError | None:
    """``OSError(ENOSPC or EDQUOT, strerror)`` (no file name) if one more block cannot be allocated in ``where``'s
    folder, else None (room, or cannot tell): after a writer failed without saying why (a probe file
    ``.<random>.space`` is created there and removed)."""
    where = Path(where)
    folder = where if where.is_dir() else where.parent
    probe = folder / f".{uuid.uuid4().hex[:12]}.space"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as e:
        return OSError(e.errno, e.strerror) if e.errno in _SPACE_ERRNOS else None
    try:
        block = max(os.fstatvfs(fd).f_bsize, 4096)
        if hasattr(os, "posix_fallocate"):
            os.posix_fallocate(fd, 0, block)
        else:  # macOS: no posix_fallocate
            os.write(fd, bytes(block))
            os.fsync(fd)
    except OSError as e:
        return OSError(e.errno, e.strerror) if e.errno in _SPACE_ERRNOS else None
    finally:
        os.close(fd)
        os.unlink(probe)
    return None


def _renamed(name: str | bytes | os.PathLike | None, temp: str | None, final: str) -> str | None:
    """``name`` with the temporary path ``temp`` (a file, or a folder and everything in it) shown as ``final``."""
    if name is None:
        return None
    text = os.fsdecode(name)
    if temp is not None and (text == temp or text.startswith(temp + os.sep)):
        return final + text[len(temp):]
    return text


@contextmanager
def naming_os_errors(path: str | os.PathLike, temp: str | os.PathLike | None = None) -> Iterator[None]:
    """Re-raise the block's write errors as ``OSError``\\ s naming ``path`` (the original chained as ``__cause__``).

    An ``OSError`` without a file name gets ``path``; one naming ``temp`` (the temporary file or folder standing in
    for ``path``) or a file in it is renamed to the same place under ``path`` (a rename's second name dropped when
    it is the same file); any other exception but ``ValueError`` becomes ``OSError(ENOSPC/EDQUOT, strerror, path)``
    when :func:`disk_full_error` finds the disk full. Others pass unchanged.
    """
    final = os.fspath(path)
    temp = None if temp is None else os.fspath(temp)
    try:
        yield
    except OSError as e:
        if e.errno is None:  # a message only: nothing to name
            raise
        name = _renamed(e.filename, temp, final) if e.filename is not None else final
        name2 = _renamed(e.filename2, temp, final)
        if name2 is not None and os.path.realpath(name2) == os.path.realpath(name):
            name2 = None
        if (name, name2) == (e.filename, e.filename2):
            raise
        raise OSError(e.errno, e.strerror, name, None, name2) from e
    except ValueError:
        raise
    except Exception as e:
        full = disk_full_error(temp if temp is not None else final)
        if full is None:
            raise
        raise OSError(full.errno, full.strerror, final) from e


@contextmanager
def atomic_output_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path ``<folder>/.<name>.<random>.tmp<suffix>`` (the suffix kept for writers that pick the
    format from it) beside ``path``, missing parents created; on success ``os.replace`` it onto ``path``, on error
    remove it, leaving ``path`` untouched.

    Raises:
        OSError: naming ``path`` (:func:`naming_os_errors`); the body's other exceptions unchanged.
    """
    path = Path(path)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"
    try:
        with naming_os_errors(path, tmp):
            path.parent.mkdir(parents=True, exist_ok=True)
            yield str(tmp)
            if not tmp.is_file():
                full = disk_full_error(path.parent)
                if full is not None:
                    raise full
                raise OSError(f"writer produced no file at {tmp} for {path}")
            follow_umask(tmp)
            os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
