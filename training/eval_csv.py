"""The CSV files ``diff4splat evaluate`` appends to: every one checked before the evaluation starts, appended after.

``--csv FILE`` receives the aggregate row; with ``--per-clip`` ``<stem>_clips.csv`` the per-clip rows and with
``--sampling`` ``<stem>_sampling.csv`` the sampler rows (:func:`csv_outputs`). An evaluation takes minutes to
hours, so :func:`check_csv_outputs` refuses, before any model is loaded, each file that could not be appended
to afterwards: a missing or unwritable folder, a path that is a folder, a FIFO or a symlink loop, an unwritable
file, or an existing file with other columns (appending would misalign them).
"""
from __future__ import annotations

import csv
import os
from pathlib import Path

from diff4splat.io import atomic_output_path
from diff4splat.io.inputs import check_input_file

__all__ = ["csv_outputs", "check_csv_outputs", "check_output_file", "check_csv_header", "append_csv"]


def csv_outputs(path: Path, columns: list[str], clip_columns: list[str] | None,
                sampling_columns: list[str] | None) -> dict[str, tuple[Path, list[str]]]:
    """{"aggregate" / "clips" / "sampling": (file, its columns)} of every CSV an evaluation appends to: ``path``
    itself, and ``<stem>_clips.csv`` / ``<stem>_sampling.csv`` beside it when their columns are given
    (``--per-clip`` / ``--sampling``)."""
    out = {"aggregate": (path, columns)}
    for kind, cols in (("clips", clip_columns), ("sampling", sampling_columns)):
        if cols is not None:
            out[kind] = (path.with_name(f"{path.stem}_{kind}.csv"), cols)
    return out


def check_output_file(path: Path, what: str) -> None:
    """Refuse an output file that cannot be created or appended to.

    Args:
        path: the file.
        what: its name as the user knows it (``"--csv"``), first in every message.

    Raises:
        ValueError: ``path`` is a folder, a FIFO, a symlink loop or another non-regular file
            (:func:`diff4splat.io.inputs.check_input_file`); a file that is not writable; or, for a new file, a
            parent folder that does not exist, is not a folder or is not writable.
        FileNotFoundError: ``path`` is a dangling symlink.
    """
    if path.exists() or path.is_symlink():
        check_input_file(path, what)
        if not os.access(path, os.W_OK):
            raise ValueError(f"{what}: {path} is not writable")
        return
    parent = Path(os.path.abspath(path)).parent
    if not parent.exists():
        raise ValueError(f"{what}: {path}: folder {parent} does not exist")
    if not parent.is_dir():
        raise ValueError(f"{what}: {path}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{what}: {path}: folder {parent} is not writable")


def check_csv_header(path: Path, columns: list[str], what: str = "--csv") -> None:
    """Raise ValueError if ``path`` exists with other columns than ``columns`` (appending would misalign)."""
    if path.exists() and path.stat().st_size:
        with open(path, newline="") as f:
            header = next(csv.reader(f), [])
        if header != columns:
            raise ValueError(f"{what}: {path} has other columns ({len(header)}) than this evaluation writes "
                             f"({len(columns)}); name a new file")


def check_csv_outputs(outputs: dict[str, tuple[Path, list[str]]], what: str = "--csv") -> None:
    """:func:`check_output_file` and :func:`check_csv_header` of every (file, columns) of :func:`csv_outputs`.

    Raises:
        ValueError / FileNotFoundError: the first file that could not be appended to (named, with ``what``).
    """
    for path, columns in outputs.values():
        check_output_file(path, what)
        check_csv_header(path, columns, what)


def append_csv(path: Path, row: dict) -> None:
    """Append ``row`` to ``path`` (a new or empty file gets the header first). The file is written whole beside
    itself and renamed over (:func:`diff4splat.io.atomic_output_path`; a symlink's target is the file replaced), so a
    full disk leaves it as it was and the error names it.

    Raises:
        OSError: the write failed (naming ``path``).
    """
    path = Path(os.path.realpath(path))
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    with atomic_output_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        f.write(old)
        w = csv.DictWriter(f, fieldnames=list(row))
        if not old:
            w.writeheader()
        w.writerow(row)
