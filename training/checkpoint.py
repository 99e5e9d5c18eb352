"""Training checkpoints that never lose work: ``<run>/checkpoints/step_00001000/`` holds ``model.safetensors`` (CPU
weights), ``ema.safetensors`` (with EMA), ``state.pt`` (optimizer, scheduler, RNG states, data position, non-finite
count) and ``meta.json``. Each folder is written to a temporary one and renamed; ``latest`` (a text file naming the
newest complete checkpoint) is replaced atomically after it, so a killed save loses nothing.
"""
from __future__ import annotations

import json
import os
import pickle
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from diff4splat.io.atomic import atomic_output_path
from diff4splat.io.output_folders import output_dir

__all__ = ["save_checkpoint", "load_checkpoint", "latest_checkpoint", "rng_state", "set_rng_state", "on_cpu"]

_NUMPY_STATE_GLOBALS = [np.ndarray, np.dtype, type(np.dtype(np.uint32)),
                        (np._core if hasattr(np, "_core") else np.core).multiarray._reconstruct]
"""What ``state.pt`` may hold beyond tensors and plain values (numpy's RNG state); nothing else is unpickled."""


def rng_state(step_generator: torch.Generator | None = None) -> dict[str, Any]:
    """Every random state a training step may draw from (torch CPU, numpy, python, the step generator)."""
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": np.random.get_state(),
        "python": random.getstate(),
        "step_generator": None if step_generator is None else step_generator.get_state(),
    }


def set_rng_state(state: dict[str, Any], step_generator: torch.Generator | None = None) -> None:
    """Restore the states of :func:`rng_state` (CUDA ones for the GPUs this machine has)."""
    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        for index, cuda_state in enumerate(state["cuda"][:torch.cuda.device_count()]):
            torch.cuda.set_rng_state(cuda_state, index)
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if step_generator is not None and state.get("step_generator") is not None:
        step_generator.set_state(state["step_generator"])


def save_checkpoint(
    run_dir: str | os.PathLike,
    step: int,
    model_state: dict[str, torch.Tensor],
    training_state: dict[str, Any],
    meta: dict[str, Any],
    ema_state: dict[str, torch.Tensor] | None = None,
    keep: int = 3,
) -> Path:
    """Write checkpoint ``step`` to ``run_dir/checkpoints`` atomically, point ``latest`` at it, keep the newest
    ``keep`` (≥ 1) and return its folder. ``training_state`` holds tensors (saved on the CPU), plain values and
    numpy's RNG state; ``meta`` is JSON-serialisable."""
    root = Path(run_dir) / "checkpoints"
    folder = root / f"step_{step:08d}"
    with output_dir(folder, kind="checkpoint", parents=True, overwrite_flag=None) as tmp:
        save_file({k: v.detach().contiguous().cpu() for k, v in model_state.items()}, str(tmp / "model.safetensors"))
        if ema_state is not None:
            save_file({k: v.detach().contiguous().cpu() for k, v in ema_state.items()}, str(tmp / "ema.safetensors"))
        torch.save(on_cpu(training_state), tmp / "state.pt")  # plain CPU tensors: loads anywhere, weights-only
        (tmp / "meta.json").write_text(json.dumps({"step": step, **meta}, indent=2, default=str))
    with atomic_output_path(root / "latest") as tmp:
        Path(tmp).write_text(folder.name)
    for old in sorted(p for p in root.glob("step_*") if p.is_dir())[:-max(1, keep)]:
        shutil.rmtree(old, ignore_errors=True)
    return folder


def on_cpu(obj: Any) -> Any:
    """``obj`` with every tensor in its dicts, lists and tuples detached and copied to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: on_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(on_cpu(v) for v in obj)
    return obj


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run, or None."""
    root = Path(run_dir) / "checkpoints"
    pointer = root / "latest"
    if pointer.is_file():
        folder = root / pointer.read_text().strip()
        if (folder / "state.pt").is_file():
            return folder
    return None


def load_checkpoint(
    folder: str | os.PathLike,
) -> tuple[dict[str, torch.Tensor], dict[str, Any], dict[str, torch.Tensor] | None]:
    """(model_state, training_state, ema_state or None) of a checkpoint folder, on the CPU. Raises FileNotFoundError
    without model.safetensors or state.pt, ValueError when state.pt holds other objects (``weights_only`` load)."""

    folder = Path(folder)
    for name in ("model.safetensors", "state.pt"):
        if not (folder / name).is_file():
            raise FileNotFoundError(f"checkpoint: {folder / name} does not exist")
    ema = load_file(str(folder / "ema.safetensors")) if (folder / "ema.safetensors").is_file() else None
    try:
        with torch.serialization.safe_globals(_NUMPY_STATE_GLOBALS):
            state = torch.load(folder / "state.pt", map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        found = next((line.strip() for line in str(e).splitlines() if "but got" in line), "")
        raise ValueError(f"checkpoint: {folder / 'state.pt'} holds objects other than tensors and plain values, "
                         f"which are not unpickled ({found or 'weights_only load failed'})") from None
    return load_file(str(folder / "model.safetensors"), device="cpu"), state, ema
