"""Source dataset converters: each reads one dataset's published on-disk layout and writes the scene format.

Conventions, layouts and what is not converted are documented per source in
``data_prep/CONVERTERS.md``; shared axis/pose/depth helpers live in :mod:`.common`.
"""
from __future__ import annotations

import inspect
import os
from collections.abc import Sequence
from functools import partial
from pathlib import Path

from ..engine import Engine, engine_session, map_scenes
from ..format import check_dataset_root
from ..scene_files import is_scene
from .common import require_dir
from .dnerf import convert_dnerf
from .dynamic_replica import convert_dynamic_replica
from .hypernerf import convert_hypernerf
from .matrixcity import convert_matrixcity
from .multicamvideo import convert_multicamvideo
from .n3dv import convert_n3dv
from .pointodyssey import convert_pointodyssey
from .realestate10k import convert_realestate10k
from .spring import convert_spring
from .stereo4d import convert_stereo4d
from .tartanair import convert_tartanair
from .vkitti2 import convert_vkitti2

__all__ = ["CONVERTERS", "SELECTORS", "convert", "convert_each", "check_options", "list_sources"]

CONVERTERS = {"pointodyssey": convert_pointodyssey, "spring": convert_spring, "vkitti2": convert_vkitti2,
              "tartanair": convert_tartanair, "matrixcity": convert_matrixcity,
              "dynamic_replica": convert_dynamic_replica, "realestate10k": convert_realestate10k,
              "stereo4d": convert_stereo4d, "multicamvideo": convert_multicamvideo, "dnerf": convert_dnerf,
              "n3dv": convert_n3dv, "hypernerf": convert_hypernerf}
"""Source name → ``convert_<source>(src, out, **options) -> Path``."""
SELECTORS = {"dynamic_replica": "sequence", "realestate10k": "clip", "stereo4d": "name"}
"""Sources whose folder holds many clips, each picked by this option of the converter; every other source's scene
is a folder of its own."""


def check_options(source: str, options: dict) -> None:
    """Check that ``source`` is known and takes every option in ``options``; ValueError (naming the known) if not."""
    if source not in CONVERTERS:
        raise ValueError(f"unknown source {source!r}; known: {sorted(CONVERTERS)}")
    known = [p for p in inspect.signature(CONVERTERS[source]).parameters if p not in ("src", "out")]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(f"{source} takes no option {', '.join(unknown)}; its options: {', '.join(known)}")


def _check_apart(src: str | os.PathLike, out: str | os.PathLike, what: str) -> None:
    a, b = Path(src).resolve(), Path(out).resolve()
    if a == b or a in b.parents or b in a.parents:
        raise ValueError(f"{what} {out} {'is' if a == b else 'is inside' if a in b.parents else 'holds'} "
                         f"the source {src}; choose a folder outside it")


def convert(source: str, src: str | os.PathLike, out: str | os.PathLike, **options) -> Path:
    """Convert one scene/sequence folder ``src`` of ``source`` (layout: CONVERTERS.md) to the scene folder ``out``.
    Raises ValueError: unknown ``source`` or option (:func:`check_options`); ``out`` equal to ``src``, holding it or
    inside it; ``src`` not a folder (:func:`.common.require_dir`); the converter's errors; FileNotFoundError: no
    ``src``, missing source files."""
    check_options(source, options)
    require_dir(src, "source")
    _check_apart(src, out, "output scene folder")
    return CONVERTERS[source](src, out, **options)


def list_sources(source: str, src_root: str | os.PathLike) -> list[str]:
    """The clips :func:`convert_each` converts when no names are given: the sorted visible sub-folders of ``src_root``,
    or the stems of its per-clip files (RealEstate10K ``*.txt``, Stereo4D ``*.npz``). Raises ValueError: Dynamic Replica
    (give the names) or no clips; FileNotFoundError: no ``src_root``."""
    root = require_dir(src_root, "source")
    pattern = {"realestate10k": "*.txt", "stereo4d": "*.npz"}.get(source)
    if source in SELECTORS and pattern is None:
        raise ValueError(f"{source}: name the {SELECTORS[source]}s to convert (a file of names, one per line); "
                         f"they are not folders of {root}")
    found = (sorted(p.stem for p in root.glob(pattern) if not p.name.startswith(".")) if pattern else
             sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")))
    if not found:
        raise ValueError(f"no {source} clips in {root} ({pattern or 'sub-folders'})")
    return found


def convert_each(source: str, src_root: str | os.PathLike, out_root: str | os.PathLike,
                 names: Sequence[str] | None = None, *, engine: Engine | None = None, progress: bool = True,
                 **options) -> list[Path]:
    """Convert the clips ``names`` (None: :func:`list_sources`) of ``src_root`` into the dataset root ``out_root``,
    scene ``out_root/name`` each, skipping complete ones (a rerun resumes); everything is checked first. Clip ``name``
    is the folder ``src_root/name``, or for a source of :data:`SELECTORS` the clip its selecting option names.
    ``engine`` None: this process. ``options`` go to every clip's converter (neither ``replace`` nor the selecting
    option). Returns the scene folders, in the order of ``names``. Raises ValueError: what :func:`check_options` raises;
    ``replace`` or the selecting option among ``options``; a name that is empty, hidden, a path or repeated;
    ``out_root`` equal to ``src_root``, inside it or holding it, or holding anything but scene folders; a clip's
    conversion error (naming the clip); FileNotFoundError: no ``src_root``; a named clip folder missing."""
    check_options(source, options)
    selector = SELECTORS.get(source)
    for bad in ("replace", selector):
        if bad in options:
            raise ValueError(f"{bad} is not an option of a conversion of many clips" +
                             ("" if bad != "replace" else ": a rerun resumes, skipping the scenes already written"))
    src_root, out_root = require_dir(src_root, "source"), Path(out_root)
    names = list_sources(source, src_root) if names is None else [str(n) for n in names]
    for n in names:
        if not n or n.startswith(".") or Path(n).name != n or n in ("..",):
            raise ValueError(f"clip name {n!r} is not a plain folder name")
    if len(set(names)) != len(names):
        raise ValueError(f"clip names repeat: {sorted({n for n in names if names.count(n) > 1})}")
    if selector is None:
        for n in names:
            require_dir(src_root / n, "source")
    _check_apart(src_root, out_root, "output dataset root")
    check_dataset_root(out_root, "OUT")
    engine = engine or Engine()
    with engine_session(engine):  # a Ray that cannot be reached is refused here, before OUT is made
        created = not out_root.exists()
        out_root.mkdir(parents=True, exist_ok=True)
        task = partial(_convert_task, source=source, src_root=src_root, out_root=out_root, options=options)
        try:
            map_scenes(task, names, engine, desc=f"convert {source}", progress=progress)
        except BaseException:
            if created and not any(out_root.iterdir()):  # nothing written: no empty folder left behind
                out_root.rmdir()
            raise
    return [out_root / n for n in names]


def _convert_task(name: str, source: str, src_root: Path, out_root: Path, options: dict) -> None:
    """The engine's task: clip ``name`` into ``out_root/name`` unless an earlier attempt wrote it."""
    out = out_root / name
    if is_scene(out):
        return
    selector = SELECTORS.get(source)
    src, opts = (src_root, {**options, selector: name}) if selector else (src_root / name, options)
    try:
        CONVERTERS[source](src, out, **opts)
    except ValueError as e:  # the clip named: one of thousands
        raise ValueError(f"{source} clip {name}: {e}") from None
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{source} clip {name}: {e}") from None
