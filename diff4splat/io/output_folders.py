"""The output-folder policy, one implementation for every command that writes a folder (README, "Output folders"):
``out`` is checked before any work (:func:`check_output_dir`), the folder is written into a temporary sibling
``.<name>.<pid>.<random>.tmp`` and renamed into place (:func:`output_dir`), and an existing folder is replaced only if
it is empty or an earlier output of the same kind holding only the files its :data:`MARKER` lists (or with
``overwrite``), never if it holds inputs. A symlink ``out`` is followed. Temporaries are removed on error, SIGINT
and SIGTERM (exit 143, :func:`diff4splat.utils.errors.sigterm_raises`), and those of killed runs by the next run;
concurrent writers are serialised by ``flock`` on ``.<name>.lock``. Files follow the umask, and write errors name the
file under ``out`` (:mod:`diff4splat.io.atomic`).
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from diff4splat.io.atomic import follow_umask, naming_os_errors
from diff4splat.utils.errors import sigterm_raises

__all__ = ["MARKER", "INSTALLED_PACKAGES", "OutputDirError", "check_output_dir", "output_dir", "read_marker",
           "remove_stale_temps"]

MARKER = ".diff4splat-output.json"
"""File written into every output folder: ``{"tool": "diff4splat", "kind": <kind>, "format": 2, "files": [...]}``,
``files`` the paths written, relative to the folder (POSIX, sorted; format 1 had no list)."""

INSTALLED_PACKAGES = ("diff4splat", "models", "training", "data_prep")
"""The top-level packages this distribution installs (pyproject's ``packages.find``); an output never replaces one
of them or a folder holding one."""

_MARKER_FORMAT = 2
_SHORT_NAME_BYTES = 200  # longer names use a hash in temporary/lock names (suffixes need ≤ 55 bytes)


class OutputDirError(ValueError):
    """``out`` may not be written or replaced; the message names the folder and why."""


class _ExistingFolderError(OutputDirError):
    """A refusal that depends on what the existing ``out`` holds (it may be seen mid-swap, unlocked)."""


def _stem(name: str) -> str:
    """The part of temporary/lock names that identifies ``name`` (a hash for long names)."""
    if len(os.fsencode(name)) <= _SHORT_NAME_BYTES:
        return name
    return "h" + hashlib.sha256(os.fsencode(name)).hexdigest()[:32]


def _resolve(out: Path) -> Path:
    """Absolute path with symlinks followed (a symlink ``out`` → its target); ``out`` need not exist."""
    return Path(os.path.realpath(out))


def _marker(folder: Path) -> dict | None:
    """``folder``'s marker as a dict, or None (no marker, unreadable, or not ours)."""
    try:
        data = json.loads((folder / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and data.get("tool") == "diff4splat" and isinstance(data.get("kind"), str):
        return data
    return None


def read_marker(folder: Path) -> str | None:
    """The kind recorded in ``folder``'s marker, or None (no marker or not ours)."""
    data = _marker(folder)
    return None if data is None else data["kind"]


def _files_under(folder: Path) -> list[str]:
    """Sorted POSIX paths of every file, link (not followed) and empty folder (ending "/") under ``folder``, but
    the marker."""
    found, top = [], os.fspath(folder)
    for root, dirs, files in os.walk(folder):
        rel = Path(root).relative_to(folder)
        links = [d for d in dirs if os.path.islink(os.path.join(root, d))]
        dirs[:] = [d for d in dirs if d not in links]
        found += [(rel / n).as_posix() for n in files + links]
        if root != top and not (dirs or files or links):
            found.append(rel.as_posix() + "/")
    return sorted(f for f in found if f != MARKER)


def _foreign_file(folder: Path, marker: dict) -> str | None:
    """The first path under ``folder`` its marker's ``files`` does not list (None: all listed, or no list)."""
    listed = marker.get("files")
    if not isinstance(listed, list):
        return None
    listed = {str(f) for f in listed}
    listed |= {p.as_posix() + "/" for f in listed for p in Path(f).parents if p != Path(".")}
    for f in _files_under(folder):
        if f not in listed:
            return f
    return None


def _installation() -> list[Path]:
    """The folders of :data:`INSTALLED_PACKAGES` beside this package (a checkout or site-packages), resolved."""
    root = Path(__file__).resolve().parents[2]  # diff4splat/io/output_folders.py → the folder holding diff4splat
    return [root / name for name in INSTALLED_PACKAGES if (root / name / "__init__.py").is_file()]


def _protected(inputs: Iterable[str | os.PathLike | None]) -> list[tuple[Path, str]]:
    """(resolved path, what it is) of everything an output may never replace or contain."""
    out = [(_resolve(Path(p)), f"input {p}") for p in inputs if p is not None and str(p) != ""]
    out += [(p, f"diff4splat's installed package {p}") for p in _installation()]
    out.append((_resolve(Path.cwd()), "the current directory"))
    home = os.environ.get("HOME")
    if home:
        out.append((_resolve(Path(home)), "the home directory"))
    return out


def _holds_inputs(target: Path, inputs) -> str | None:
    """Why ``target`` may not be replaced, as a predicate ("is the home directory", "holds input x.png")."""
    if target.parent == target:
        return "is a filesystem root"
    for p in _installation():
        if p in target.parents:
            return f"is inside diff4splat's installed package {p}"
    for p, what in _protected(inputs):
        if target == p or target in p.parents:
            return f"is {what}" if target == p else f"holds {what}"
    return None


def _check_existing(label: str, target: Path, kind: str, overwrite: bool, replace: bool,
                    overwrite_flag: str | None, replace_flag: str | None) -> None:
    """Raise unless the existing folder ``target`` may be replaced; a refusal names the flag that would lift it."""
    if not target.is_dir():
        raise _ExistingFolderError(f"{label} is a file, not a folder")
    try:
        with os.scandir(target) as entries:  # closed here: an open iterator would warn when collected
            empty = next(entries, None) is None
    except OSError as e:
        raise _ExistingFolderError(f"{label} cannot be read: {e.strerror}") from None
    data = None if empty else _marker(target)
    found = None if data is None else data["kind"]
    if not replace:
        ours = empty or found == kind or overwrite
        hint = f" (choose a new folder, or pass {replace_flag} to replace it)" if ours and replace_flag else ""
        raise FileExistsError(f"{label} already exists{hint}")
    if empty or overwrite:
        return
    hint = f"choose a new folder, or pass {overwrite_flag} to replace it" if overwrite_flag else "choose a new folder"
    if found is None:
        raise _ExistingFolderError(f"{label} is a non-empty folder not written by diff4splat; refusing to "
                                   f"replace it ({hint})")
    if found != kind:
        raise _ExistingFolderError(f"{label} holds a diff4splat {found!r} output, not {kind!r}; refusing to "
                                   f"replace it ({hint})")
    foreign = _foreign_file(target, data)
    if foreign is not None:
        raise _ExistingFolderError(f"{label} is an earlier diff4splat {kind!r} output that also holds {foreign}, "
                                   f"which diff4splat did not write; refusing to replace it ({hint})")


def check_output_dir(out: str | os.PathLike, *, inputs: Iterable[str | os.PathLike | None] = (),
                     overwrite: bool = False, kind: str = "generate", replace: bool = True,
                     parents: bool = False, overwrite_flag: str | None = "--overwrite",
                     replace_flag: str | None = None) -> Path:
    """Check that ``out`` may be written (module docstring) before any work is done; nothing is created.

    Args:
        out: the output folder as the user gave it.
        inputs: files/folders the command reads (None skipped); ``out`` may not be or contain one.
        overwrite: also replace a folder without the marker or of another kind (never one holding inputs).
        kind: what the command writes ("generate", "onnx", "model", "checkpoint", "scene", …).
        replace: False → an existing ``out`` is an error.
        parents: allow missing parents (the nearest existing ancestor must be a writable folder).
        overwrite_flag, replace_flag: the caller's options that set ``overwrite``/``replace``, named in a refusal
            they would lift (None: the caller has none).

    Returns:
        ``out`` made absolute with symlinks followed.

    Raises:
        OutputDirError: (a ValueError) ``out`` is empty, ".", a file, a symlink loop or dangling link, holds inputs,
            is a non-output folder, has a missing/non-folder/unwritable parent or too long a name.
        FileExistsError: ``out`` exists and ``replace`` is false.
    """
    raw = os.fspath(out)
    label = f"out {raw!r}" if raw in ("", ".") else f"output folder {raw}"
    if raw in ("", "."):
        raise OutputDirError(f"{label} names the current directory; give a new folder name")
    path = Path(raw)
    name = Path(os.path.abspath(path)).name  # checked before any stat: a too-long name fails them all
    if len(os.fsencode(name)) > 255:
        raise OutputDirError(f"{label}: name is {len(os.fsencode(name))} bytes, longer than the 255 file "
                             "systems allow")
    if path.is_symlink() and not path.exists():
        raise OutputDirError(f"{label} is a dangling symlink or a symlink loop")
    target = _resolve(path)
    why = _holds_inputs(target, inputs)
    if why is not None:
        raise OutputDirError(f"{label} {why}; refusing to replace it (choose a new folder)")
    parent = target.parent
    if parents:
        while not parent.exists() and not parent.is_symlink() and parent.parent != parent:
            parent = parent.parent
    elif not parent.exists():
        if any(p.exists() and not p.is_dir() for p in parent.parents):
            raise OutputDirError(f"{label}: parent {parent} is inside a file, not a folder")
        raise OutputDirError(f"{label}: parent folder {parent} does not exist")
    if not parent.is_dir():
        raise OutputDirError(f"{label}: parent {parent} is not a folder")
    try:
        name_max = int(os.pathconf(parent, "PC_NAME_MAX"))
    except (OSError, ValueError):
        name_max = 255
    if len(os.fsencode(target.name)) > name_max:
        raise OutputDirError(f"{label}: name is {len(os.fsencode(target.name))} bytes, longer than the "
                             f"{name_max} the file system allows")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputDirError(f"{label}: parent folder {parent} is not writable")
    if target.exists():
        _check_existing(label, target, kind, overwrite, replace, overwrite_flag, replace_flag)
    if parent != target.parent:  # missing parents will be created: no probe of the final folder
        return target
    probe = parent / _temp_name(target.name, "probe")
    try:  # the real test of writability (read-only mounts, ACLs) and of the temporary name
        os.mkdir(probe)
        os.rmdir(probe)
    except OSError as e:
        raise OutputDirError(f"{label}: cannot create a folder in {parent}: {e.strerror}") from None
    return target


def _temp_name(name: str, suffix: str) -> str:
    return f".{_stem(name)}.{os.getpid()}.{uuid.uuid4().hex[:8]}.{suffix}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(target: str | os.PathLike) -> list[Path]:
    """Remove ``.<name>.<pid>.<8 hex>.tmp``/``.old`` folders beside ``target`` whose owner pid is dead; returns them."""
    target = Path(target)
    pattern = re.compile(rf"^\.{re.escape(_stem(target.name))}\.(\d+)\.[0-9a-f]{{8}}\.(tmp|old)$")
    removed = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    for entry in entries:
        m = pattern.match(entry.name)
        if m and not _pid_alive(int(m.group(1))):
            shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(Path(entry.path))
    return removed


@contextmanager
def _locked(target: Path) -> Iterator[None]:
    """Hold ``fcntl.flock`` on ``.<name>.lock`` beside ``target``; the file is removed on release."""
    lock = target.parent / f".{_stem(target.name)}.lock"
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:  # the holder before us may have unlinked it: then lock the new file instead
                same = os.fstat(fd).st_ino == os.stat(lock).st_ino
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        try:
            os.unlink(lock)
        except OSError:
            pass
        os.close(fd)


@contextmanager
def output_dir(out: str | os.PathLike, *, kind: str, inputs: Iterable[str | os.PathLike | None] = (),
               overwrite: bool = False, replace: bool = True, parents: bool = False,
               overwrite_flag: str | None = "--overwrite", replace_flag: str | None = None) -> Iterator[Path]:
    """Yield a temporary folder beside ``out``; after the body the :data:`MARKER` is written and the folder replaces
    ``out``. If the body raises (or SIGINT/SIGTERM arrive) it is removed and ``out`` is left as it was.

    Arguments are :func:`check_output_dir`'s, checked on enter and again under the lock before the rename; missing
    parents are created with ``parents``.

    Raises:
        OutputDirError, FileExistsError: as :func:`check_output_dir`.
        OSError: writing failed, naming the file as it will be under ``out``
            (:func:`~diff4splat.io.atomic.naming_os_errors`).
    """
    inputs = list(inputs)
    flags = {"overwrite_flag": overwrite_flag, "replace_flag": replace_flag}
    target = _check_consistent(out, inputs=inputs, overwrite=overwrite, kind=kind, replace=replace, parents=parents,
                               **flags)
    if parents:
        target.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(target)
    tmp = target.parent / _temp_name(target.name, "tmp")
    with sigterm_raises():
        with naming_os_errors(out, tmp):
            os.mkdir(tmp)  # mode 0o777 & ~umask
        try:
            with naming_os_errors(out, tmp):  # inside: a full disk is seen before tmp is removed
                yield tmp
                marker = {"tool": "diff4splat", "kind": kind, "format": _MARKER_FORMAT, "files": _files_under(tmp)}
                (tmp / MARKER).write_text(json.dumps(marker))
                follow_umask(tmp)  # whatever wrote the files (safetensors: 0600), they get the umask's mode
                with _locked(target):
                    check_output_dir(out, inputs=inputs, overwrite=overwrite, kind=kind, replace=replace, **flags)
                    _swap_into_place(tmp, target)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)


def _check_consistent(out: str | os.PathLike, **kwargs) -> Path:
    """:func:`check_output_dir`; a refusal about the existing folder is confirmed under the writers' lock (unlocked,
    another writer's swap may be seen half done)."""
    try:
        return check_output_dir(out, **kwargs)
    except _ExistingFolderError:
        with _locked(_resolve(Path(os.fspath(out)))):
            return check_output_dir(out, **kwargs)


def _swap_into_place(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` onto ``target``; an existing ``target`` is renamed aside first and then deleted."""
    try:
        os.rename(tmp, target)  # fails with ENOTEMPTY/EEXIST when target is a non-empty folder
        return
    except OSError as e:
        if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    old = target.parent / _temp_name(target.name, "old")
    os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        os.rename(old, target)  # put the previous folder back
        raise
    shutil.rmtree(old, ignore_errors=True)
