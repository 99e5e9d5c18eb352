"""Atomic file writes: a file appears complete or not at all (folders: :mod:`diff4splat.io.outdir`)."""
from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_output_path"]


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
