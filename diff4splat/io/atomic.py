"""Atomic writes: a file or a whole folder appears complete or not at all."""
from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_output_path", "atomic_output_dir"]


@contextmanager
def atomic_output_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path`` (``os.replace``).

    The temporary name keeps the final suffix (writers such as OpenCV pick the container from it):
    ``<folder>/.<name>.<random>.tmp<suffix>``. If the body raises, the temporary file is removed and
    ``path`` is left untouched, so readers never see a half-written file. Missing parent folders
    are created.

    Args:
        path: final file path.

    Yields:
        The temporary path (str) to write to.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"
    try:
        yield str(tmp)
        if not tmp.is_file():
            raise OSError(f"writer produced no file at {tmp} for {path}")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_output_dir(path: str | os.PathLike, replace: bool = True) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success rename it onto ``path``.

    If the body raises, the temporary folder is deleted and ``path`` is left as it was, so a
    killed or failed run never leaves a half-written output folder. An existing ``path`` is
    replaced only when ``replace`` is true: it is first renamed aside, then removed once the new
    folder is in place.

    Args:
        path: final folder path.
        replace: allow replacing an existing folder.

    Yields:
        The temporary folder (Path) to write into.

    Raises:
        FileExistsError: ``path`` exists and ``replace`` is false, or ``path`` is a file.
    """
    path = Path(path)
    if path.exists() and (not replace or not path.is_dir()):
        raise FileExistsError(f"output folder {path} already exists")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            old = path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.old"
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
