"""A synthetic dataset: ``data_prep synth`` makes scenes 0 … N−1 of a seed (:func:`synthesize`), each with
:func:`data_prep.synth.generate_scene`, after checking the request against the limits (:func:`check_synth_request`:
its memory estimate is :func:`scene_bytes`)."""
from __future__ import annotations

import math
import os
from dataclasses import replace
from functools import partial
from pathlib import Path

import torch
from tqdm.auto import tqdm

from diff4splat.utils.checks import check_int, check_number
from diff4splat.utils.devices import resolve_device
from diff4splat.utils.limits import check_limit, check_memory, held_memory

from .engine import Engine, engine_session, fault_point, map_scenes
from .format import check_dataset_root
from .scene_files import is_scene
from .synth import generate_scene, scene_name
from .synth_world import SYNTH, check_motions

__all__ = ["synthesize", "check_synth_request", "max_gaussians", "scene_bytes", "BYTES_PER_PIXEL",
           "BYTES_PER_GAUSSIAN_FRAME"]

BYTES_PER_PIXEL = 24
"""Memory of a scene per pixel of every camera and frame: the float32 RGB (12 bytes) and depth (4) kept until the
scene is written, and the renderer's expected depth and alpha (8) of the camera being rendered."""
BYTES_PER_GAUSSIAN_FRAME = 120
"""Memory of a dynamic scene per Gaussian and frame: its float64 deformation (Δμ 3, Δq 4, Δs 3: 80 bytes) and the
float32 copy the scene holds (40)."""


def max_gaussians(size: int) -> int:
    """An upper bound of the Gaussians of any scene of ``size`` pixels (:func:`data_prep.synth.build_gaussians`):
    ground and wall grids of spacing sp = 0.25 m·min(1, 64/size)^½, halved where image-textured, hold at most
    13 940·max(1, size/64); at most 4 objects of ≤ 800 surface samples add 3 200."""
    return 14_000 * max(1, math.ceil(size / 64)) + 3_200


def scene_bytes(size: int, frames: int, cameras: int) -> int:
    """Estimated memory of one synthetic scene while it is made: cameras · frames · size² · :data:`BYTES_PER_PIXEL`
    plus frames · :func:`max_gaussians` · :data:`BYTES_PER_GAUSSIAN_FRAME`."""
    return cameras * frames * size * size * BYTES_PER_PIXEL + frames * max_gaussians(size) * BYTES_PER_GAUSSIAN_FRAME


_FLAGS = {"num_scenes": "--scenes", "seed": "--seed", "size": "--size", "frames": "--frames", "cameras": "--cameras",
          "workers": "--workers", "static_ratio": "--static-ratio", "texture_ratio": "--texture-ratio",
          "motions": "--motions", "max_movers": "--max-movers"}
"""The ``data_prep synth`` flag of each :func:`synthesize` argument (the CLI's messages name the flags)."""


def check_synth_request(num_scenes: int, seed: int, *, size: int, frames: int, cameras: int, workers: int,
                        static_ratio: float, texture_ratio: float, motions: tuple[str, ...] = SYNTH.motions,
                        max_movers: int | None = None, flags: bool = False) -> None:
    """Check :func:`synthesize`'s arguments and limits before anything is created; ``flags``: name the arguments by
    their ``data_prep synth`` flags. Raises ValueError: an argument out of range (named), bad ``motions`` or
    ``max_movers`` (:func:`data_prep.synth_world.check_motions`).
    :class:`diff4splat.utils.limits.LimitError` (a ValueError): ``num_scenes`` above the ``scenes`` limit, ``size``
    above ``resolution``, ``frames`` above ``frames``, :func:`scene_bytes` above ``synth_bytes``, or this process's
    memory plus one scene per worker above what it may use (:func:`diff4splat.utils.limits.check_memory`)."""
    name = _FLAGS.get if flags else str
    check_limit("scenes", check_int(name("num_scenes"), num_scenes, 1), name("num_scenes"))
    check_int(name("seed"), seed, 0)
    check_limit("resolution", check_int(name("size"), size, 8), name("size"))
    check_limit("frames", check_int(name("frames"), frames, 2), name("frames"))
    check_int(name("cameras"), cameras, 1)
    check_int(name("workers"), workers, 1)
    for key, value in (("static_ratio", static_ratio), ("texture_ratio", texture_ratio)):
        check_number(name(key), value, lo=0, hi=1)
    check_motions(motions, max_movers, (name("motions"), name("max_movers")))
    one = f"one scene of {name('cameras')} {cameras} × {name('frames')} {frames} at {name('size')} {size}"
    check_limit("synth_bytes", scene_bytes(size, frames, cameras), f"{one}: estimated")
    # the memory this process (and each worker, under the same ulimits) may use: its own plus one scene per worker
    check_memory(held_memory() + min(workers, num_scenes) * scene_bytes(size, frames, cameras),
                 f"{one}, {min(workers, num_scenes)} at a time", f"{name('size')}, {name('frames')}, "
                 f"{name('cameras')} or {name('workers')}")


def _make_scene(index: int, out: Path, seed: int, kw: dict) -> None:
    """The engine's task: make scene ``index`` unless an earlier attempt wrote it."""
    if is_scene(out / scene_name(index)):
        return
    generate_scene(out, index, seed, **kw)
    fault_point("done", scene_name(index))  # a test's injected worker death: the scene written, the task not done


def synthesize(out_dir: str | os.PathLike, num_scenes: int, seed: int = 0, *, size: int = SYNTH.size,
               frames: int = SYNTH.frames, cameras: int = SYNTH.cameras, static_ratio: float = SYNTH.static_ratio,
               texture_ratio: float = SYNTH.texture_ratio, motions: tuple[str, ...] = SYNTH.motions,
               max_movers: int | None = None, workers: int = 1,
               progress: bool = True, device: str | torch.device = "cpu", engine: Engine | None = None) -> list[Path]:
    """Generate scenes 0 … num_scenes−1 into the dataset root ``out_dir``, skipping scenes already present (resume).
    Every argument and limit is checked first (:func:`check_synth_request`), so a refused request creates nothing; an
    ``out_dir`` this run created is removed again if it fails before writing into it. Scene ``i`` depends on ``seed``
    and ``i`` alone (:func:`data_prep.synth.generate_scene`), whatever the engine, workers or order. ``num_scenes``,
    ``size``, ``frames``: ≥ 1, ≥ 8, ≥ 2, each at most its limit; ``static_ratio``, ``texture_ratio``: probabilities in
    [0, 1] of a static scene and of an image-textured surface; ``motions``, ``max_movers``: the kinds a moving object
    draws from and at most how many objects move (:func:`data_prep.synth_world.sample_scene_spec`); ``workers``: local
    processes (``engine`` None: the local pool); ``device``: where scenes render ("cpu": the same bytes on every
    machine; on Ray, CUDA gives each task one GPU). Returns all ``num_scenes`` scene folders, in index order. Raises
    ValueError: an argument out of range (named); an ``out_dir`` holding anything but scene folders; a ``device`` this
    machine does not have; :class:`diff4splat.utils.limits.LimitError` above a limit."""
    check_synth_request(num_scenes, seed, size=size, frames=frames, cameras=cameras, workers=workers,
                        static_ratio=static_ratio, texture_ratio=texture_ratio, motions=motions, max_movers=max_movers)
    motions, max_movers = check_motions(motions, max_movers)
    # numpy integers pass the checks; Python ints go on (the seed is written to meta.json)
    num_scenes, seed, size, frames, cameras, workers = map(int, (num_scenes, seed, size, frames, cameras, workers))
    engine = engine or Engine(workers=workers)
    device = str(resolve_device(device, "--device"))
    if engine.name == "ray" and device.startswith("cuda"):
        engine = replace(engine, gpus_per_task=engine.gpus_per_task or 1.0)
    out = Path(out_dir)
    check_dataset_root(out, "--out")
    with engine_session(engine):  # a Ray that cannot be reached is refused here, before --out is made
        created = not out.exists()
        out.mkdir(parents=True, exist_ok=True)
        kw = dict(size=size, frames=frames, cameras=cameras, static_ratio=float(static_ratio),
                  texture_ratio=float(texture_ratio), motions=motions, max_movers=max_movers, device=device)
        bar = tqdm(total=num_scenes, desc="synth", unit="scene", disable=not progress or engine.name != "local")

        def todo():
            for i in range(num_scenes):
                if is_scene(out / scene_name(i)):
                    bar.update()
                else:
                    yield i

        try:
            items = todo() if engine.name == "local" else range(num_scenes)
            map_scenes(partial(_make_scene, out=out, seed=seed, kw=kw), items, engine, progress=progress, bar=bar)
        except BaseException:
            if created and out.is_dir() and not any(out.iterdir()):
                out.rmdir()
            raise
        finally:
            bar.close()
    return [out / scene_name(i) for i in range(num_scenes)]
