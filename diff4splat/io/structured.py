"""Reading text, JSON and YAML files, every decode error a ``ValueError`` naming the file
(``<what>: <path> is not valid JSON (Expecting value at line 1 column 2)``).
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import yaml

__all__ = ["read_text", "read_json", "read_yaml", "YamlLoader"]


class YamlLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that also reads YAML 1.2's floats without a dot (``1e-4``, ``-3E2``), which YAML 1.1 reads as
    strings; every YAML file the library reads goes through it (:func:`read_yaml`)."""

YamlLoader.add_implicit_resolver(  # copies SafeLoader's resolvers first; checked after them, so ints stay ints
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"), list("-+0123456789"))

_JSON_TYPES = {dict: "object", list: "list", str: "string", int: "number", float: "number", bool: "boolean",
               type(None): "null"}


def read_text(path: str | os.PathLike, what: str) -> str:
    """The UTF-8 text of ``path``; ``what`` (what the file is to the user) prefixes messages.

    Raises:
        FileNotFoundError: ``path`` is not a file (``<what>: <path> not found``).
        ValueError: not UTF-8, naming the first bad byte and its offset.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: {path} not found")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{what}: {path} is not UTF-8 text (byte {e.object[e.start]:#04x} at offset {e.start}; "
                         "a binary file?)") from None


def _check_type(data: Any, expect: type | None, what: str, path: Path, fmt: str) -> Any:
    if expect is not None and not isinstance(data, expect):
        name = _JSON_TYPES.get(type(data), type(data).__name__)
        raise ValueError(f"{what}: {path} must hold a {fmt} {_JSON_TYPES.get(expect, expect.__name__)}, "
                         f"got a {fmt} {name}")
    return data


def read_json(path: str | os.PathLike, what: str, expect: type | None = dict) -> Any:
    """Parse a JSON file whose top-level value must be an ``expect`` (``dict``: a JSON object; None: anything).

    Raises:
        FileNotFoundError / ValueError: :func:`read_text`; invalid JSON (message, line, column); another top-level type.
    """
    path = Path(path)
    text = read_text(path, what)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{what}: {path} is not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    return _check_type(data, expect, what, path, "JSON")


def read_yaml(path: str | os.PathLike, what: str, expect: type | None = dict) -> Any:
    """Parse a YAML file (:class:`YamlLoader`) as :func:`read_json` does JSON (invalid YAML: the parser's problem and
    line); an empty file is ``{}`` when ``expect`` is ``dict``."""
    path = Path(path)
    text = read_text(path, what)
    try:
        data = yaml.load(text, Loader=YamlLoader)  # noqa: S506 - YamlLoader is a SafeLoader
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ValueError(f"{what}: {path} is not valid YAML ({getattr(e, 'problem', None) or e}{where})") from None
    if data is None and expect is dict:
        data = {}
    return _check_type(data, expect, what, path, "YAML")
