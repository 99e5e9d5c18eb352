"""Source dataset converters: each reads one dataset's published on-disk layout and writes the scene format.

Conventions, layouts and what is not converted are documented per source in
``data_prep/CONVERTERS.md``; shared axis/pose/depth helpers live in :mod:`.common`.
"""
from __future__ import annotations

import inspect
import os
from pathlib import Path

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

__all__ = ["CONVERTERS", "convert"]

CONVERTERS = {
    "pointodyssey": convert_pointodyssey,
    "spring": convert_spring,
    "vkitti2": convert_vkitti2,
    "tartanair": convert_tartanair,
    "matrixcity": convert_matrixcity,
    "dynamic_replica": convert_dynamic_replica,
    "realestate10k": convert_realestate10k,
    "stereo4d": convert_stereo4d,
    "multicamvideo": convert_multicamvideo,
    "dnerf": convert_dnerf,
    "n3dv": convert_n3dv,
    "hypernerf": convert_hypernerf,
}
"""Source name → ``convert_<source>(src, out, **options) -> Path``."""


def convert(source: str, src: str | os.PathLike, out: str | os.PathLike, **options) -> Path:
    """Convert one source scene/sequence ``src`` to the scene folder ``out``.

    Args:
        source: a key of :data:`CONVERTERS`.
        src: the source's scene/sequence folder (layout in CONVERTERS.md).
        out: output scene folder.
        **options: passed to the source's converter.

    Raises:
        ValueError: unknown ``source``; an option the source's converter does not take (naming its options); ``out``
            equal to ``src``, holding it or inside it; ``src`` is not a folder but a FIFO, a symlink loop, a
            file, … (said as such, :func:`.common.require_dir`, before the converter looks for its files); the
            converter's errors.
        FileNotFoundError: no ``src`` (``"source folder not found: <src>"``), missing source files.
    """
    if source not in CONVERTERS:
        raise ValueError(f"unknown source {source!r}; known: {sorted(CONVERTERS)}")
    known = [p for p in inspect.signature(CONVERTERS[source]).parameters if p not in ("src", "out")]
    unknown = sorted(set(options) - set(known))
    if unknown:  # a TypeError traceback from the converter's call before
        raise ValueError(f"{source} takes no option {', '.join(unknown)}; its options: {', '.join(known)}")
    require_dir(src, "source")
    a, b = Path(src).resolve(), Path(out).resolve()
    if a == b or a in b.parents or b in a.parents:
        raise ValueError(f"output scene folder {out} {'is' if a == b else 'is inside' if a in b.parents else 'holds'} "
                         f"the source {src}; choose a folder outside it")
    return CONVERTERS[source](src, out, **options)
