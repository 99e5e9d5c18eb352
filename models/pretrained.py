"""`save_pretrained` / `from_pretrained` for every network: safetensors weights + config.json."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar, TypeVar, get_type_hints

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from diff4splat.io.output_folders import output_dir
from diff4splat.io.structured import read_json
from diff4splat.utils.limits import LIMITS, LimitError, check_limit, check_memory, limit

T = TypeVar("T", bound="PretrainedMixin")

WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
MODEL_KIND = "model"
"""Output kind of a saved model folder (:data:`diff4splat.io.MARKER`)."""


def load_weights(path: str | os.PathLike, map_location: str = "cpu",
                 dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
    """Read a ``model.safetensors`` file tensor by tensor, floating-point tensors cast to ``dtype`` as read (None: as
    stored): the peak is the result plus one tensor.

    Raises:
        ValueError: naming ``path`` when the file is truncated or corrupt.
    """
    try:
        state = {}
        with safe_open(str(path), framework="pt", device=map_location) as f:
            for key in f.keys():  # noqa: SIM118 - safe_open has keys(), no __iter__
                t = f.get_tensor(key)
                state[key] = t.to(dtype) if dtype is not None and t.is_floating_point() else t
        return state
    except (SafetensorError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"checkpoint: {path} is not a readable safetensors file (truncated or corrupt: "
                         f"{' '.join(str(e).split())})") from None


def config_from_dict(cls: type, data: dict[str, Any], where: str = "config") -> Any:
    """Build dataclass ``cls`` from a dict over its defaults, rejecting unknown fields. A nested dataclass field given
    as a dict overrides that field's default value field by field; lists become tuples for tuple fields.

    Raises:
        ValueError: naming the field and ``where``: ``data`` not a dict, an unknown field, a non-integer for an
            ``int`` field (e.g. ``1e9``), a non-number (a string, a bool) for a ``float`` field, or values the
            config's own checks refuse (e.g. sizes that do not fit each other).
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object of config fields, got {type(data).__name__} {data!r:.60}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise ValueError(f"{where}: unknown field {key!r} for {cls.__name__} (known: {sorted(fields)})")
        hint = get_type_hints(cls).get(key)
        if hint is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise ValueError(f"{where}: field {key!r} of {cls.__name__} must be an integer, got {value!r} "
                             f"({type(value).__name__}; write 1000, not 1e3 or 1000.0)")
        if hint in (float, float | None) and value is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{where}: field {key!r} of {cls.__name__} must be a number, got {value!r} "
                                 f"({type(value).__name__})")
            value = float(value)
        f = fields[key]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            base = f.default_factory() if f.default_factory is not dataclasses.MISSING else (
                f.default if f.default is not dataclasses.MISSING else None)
            merged = _shallow_asdict(base) if dataclasses.is_dataclass(base) else {}
            for k, v in value.items():
                merged[k] = {**merged[k], **v} if isinstance(v, dict) and isinstance(merged.get(k), dict) else v
            value = config_from_dict(hint, merged, f"{where}.{key}")
        elif isinstance(value, list) and (isinstance(f.default, tuple) or "tuple" in str(f.type)):
            value = tuple(value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except ValueError as e:  # the config's own consistency checks (__post_init__), named by where they were read
        raise ValueError(f"{where}: {e}") from None


def _shallow_asdict(obj: Any) -> dict[str, Any]:
    """Field dict of a dataclass instance, nested dataclasses as dicts."""
    return {f.name: (_shallow_asdict(v) if dataclasses.is_dataclass(v := getattr(obj, f.name)) else v)
            for f in dataclasses.fields(obj)}


@contextlib.contextmanager
def skip_init() -> Iterator[None]:
    """Within the block ``torch.nn.init``'s in-place initialisers return their tensor untouched (for building on the
    ``meta`` device; transformers' ``no_init_weights``)."""
    names = [n for n in dir(torch.nn.init) if n.endswith("_") and not n.startswith("_")]
    saved = {n: getattr(torch.nn.init, n) for n in names}
    try:
        for n in names:
            setattr(torch.nn.init, n, lambda tensor, *args, **kwargs: tensor)
        yield
    finally:
        for n, fn in saved.items():
            setattr(torch.nn.init, n, fn)


def check_model_size(build: Any, where: str, host_dtype: torch.dtype | None = None) -> int:
    """Count the parameters ``build()`` allocates, on the ``meta`` device under :func:`skip_init`, and check the
    ``parameters`` limit (:mod:`diff4splat.utils.limits`); with ``host_dtype`` (weights built in CPU memory in that
    dtype) also check their bytes against the memory available. ``where`` names the config's source. Returns the
    count.

    Raises:
        LimitError: more parameters than the limit or a tensor size overflow; weights larger than the memory
            available.
    """
    try:
        with torch.device("meta"), skip_init():
            n = count_parameters(build())
    except RuntimeError as e:
        if "overflow" not in str(e).lower():
            raise
        raise LimitError(f"{where}: the model this config describes is too large to count (a tensor size "
                         f"overflows); the limit is {limit('parameters')} parameters "
                         f"(set {LIMITS['parameters'].env} to raise it)") from None
    check_limit("parameters", n, f"{where}: a model of")
    if host_dtype is not None:
        size = "the model size (--config)"
        check_memory(n * host_dtype.itemsize, f"{where}: the weights of {n:,} parameters in {str(host_dtype)[6:]}",
                     f"the weights' dtype (--dtype bfloat16 halves float32) or {size}" if host_dtype.itemsize > 2
                     else size)
    return n


def save_model_folder(directory: str | os.PathLike, write: Callable[[Path], None], overwrite: bool = False) -> Path:
    """``write(folder)`` into a new folder then replacing ``directory`` atomically (:func:`diff4splat.io.output_dir`,
    kind :data:`MODEL_KIND`: an existing folder is replaced only if empty, an earlier saved model, or ``overwrite``).
    Returns ``directory`` as a Path; raises OutputDirError where ``directory`` may not be written or replaced."""
    directory = Path(directory)
    with output_dir(directory, kind=MODEL_KIND, overwrite=overwrite, parents=True,
                    overwrite_flag="overwrite=True") as tmp:
        write(tmp)
    return directory


class PretrainedMixin:
    """Mixin for ``nn.Module`` subclasses with a dataclass ``config``; subclasses set ``config_class`` and take the
    config as their only ``__init__`` argument."""

    config_class: ClassVar[type]

    def save_pretrained(self, directory: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write ``model.safetensors`` and ``config.json`` into ``directory`` (:func:`save_model_folder`: atomic, its
        replacement rules and errors). Returns the directory."""
        return save_model_folder(directory, self.write_pretrained, overwrite)

    def write_pretrained(self, folder: Path) -> None:
        """Write ``model.safetensors`` and ``config.json`` into the existing ``folder`` (the caller owns it)."""
        folder.mkdir(exist_ok=True)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        save_file(state, str(folder / WEIGHTS_NAME), metadata={"class": type(self).__name__})
        cfg = dataclasses.asdict(self.config)
        (folder / CONFIG_NAME).write_text(json.dumps({"class": type(self).__name__, **cfg}, indent=2))

    @classmethod
    def from_pretrained(cls: type[T], directory: str | os.PathLike, map_location: str = "cpu",
                        dtype: torch.dtype | None = None) -> T:
        """Load a model written by :meth:`save_pretrained`: built on the ``meta`` device, its parameters the file's
        tensors cast to ``dtype`` (None: the default dtype) as read (:func:`load_weights`).

        Raises:
            FileNotFoundError: ``directory`` lacks config.json or model.safetensors.
            ValueError: the config names another class or has unknown fields, the weights do not match, or a file is
                corrupt.
        """
        directory = Path(directory)
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (directory / name).is_file():
                raise FileNotFoundError(f"checkpoint: {directory / name} does not exist")
        data = read_json(directory / CONFIG_NAME, "checkpoint")
        saved_class = data.pop("class", cls.__name__)
        if saved_class != cls.__name__:
            raise ValueError(f"checkpoint: {directory} holds a {saved_class}, not a {cls.__name__}")
        data = {**getattr(cls.config_class, "SAVED_DEFAULTS", {}), **data}
        config = config_from_dict(cls.config_class, data, str(directory / CONFIG_NAME))
        check_model_size(lambda: cls(config), str(directory / CONFIG_NAME),
                         host_dtype=dtype or torch.get_default_dtype() if map_location == "cpu" else None)
        with torch.device("meta"), skip_init():  # every tensor comes from the file
            model = cls(config)
        state = load_weights(directory / WEIGHTS_NAME, map_location, dtype or torch.get_default_dtype())
        try:
            missing, unexpected = model.load_state_dict(state, strict=False, assign=True)
        except RuntimeError as e:  # tensor shapes that differ from the config's
            raise ValueError(f"checkpoint: {directory / WEIGHTS_NAME} does not fit {directory / CONFIG_NAME}: "
                             f"{e}") from None
        if missing or unexpected:
            raise ValueError(f"checkpoint: {directory} weights do not match {cls.__name__}: "
                             f"missing {missing[:5]}, unexpected {unexpected[:5]}")
        return model


def count_parameters(module: torch.nn.Module) -> int:
    """Number of parameters (works on the meta device)."""
    return sum(p.numel() for p in module.parameters())
