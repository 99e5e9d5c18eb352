"""Where ``data_prep``'s per-scene work runs (:func:`map_scenes`): ``local``, this process or a pool of spawned
processes, or ``ray``, Ray Data with one task per scene (the optional extra ``diff4splat[ray]``). The engine decides
where and in what order scenes are made, never what they hold (docs/DESIGN.md, "Data preparation at scale").
"""
from __future__ import annotations

import argparse
import functools
import logging
import os
import pickle
import signal
from collections.abc import Callable, Iterable, Sequence, Sized
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any

import torch
from tqdm.auto import tqdm

from diff4splat.utils.checks import MissingExtraError, check_int

__all__ = ["Engine", "ENGINES", "check_engine", "add_engine_arguments", "engine_from_args", "map_scenes",
           "fault_point", "import_ray", "FAULT_ENV", "RAY_EXTRA"]

ENGINES = ("local", "ray")
"""The engines :func:`map_scenes` runs on."""
FAULT_ENV = "DIFF4SPLAT_FAULT"
"""Environment variable of :func:`fault_point`."""
RAY_EXTRA = "pip install 'diff4splat[ray]'"
"""The install command named when Ray is asked for and missing."""


@dataclass(frozen=True)
class Engine:
    """Where :func:`map_scenes` runs the scenes: ``name`` one of :data:`ENGINES`; ``workers``: local processes
    (1: this process) or the CPUs of a Ray started here; ``ray_address``: ``ray.init``'s ``address`` (None: the Ray
    this process joined, else a new local one); ``cpus_per_task``, ``gpus_per_task``: what each Ray task asks for."""

    name: str = "local"
    workers: int = 1
    ray_address: str | None = None
    cpus_per_task: float = 1.0
    gpus_per_task: float = 0.0


def import_ray():
    """Import Ray. Raises MissingExtraError: Ray Data is not installed (naming :data:`RAY_EXTRA`)."""
    try:
        import ray  # optional dependency (extra [ray])
        import ray.data  # noqa: F401  (Ray Data comes with ray[data])
    except ImportError as e:
        raise MissingExtraError(f"--engine ray needs Ray Data, which is not installed ({e}): {RAY_EXTRA}") from None
    return ray


def check_engine(name: str, workers: int = 1, ray_address: str | None = None, *, gpus_per_task: float = 0.0,
                 flags: bool = True) -> Engine:
    """The :class:`Engine` of a request, checked before any work (for ``ray``: that Ray is installed); ``flags``: name
    the arguments by their ``data_prep`` flags. Raises ValueError: an unknown engine, ``workers`` < 1, a ``ray_address``
    without ``--engine ray``, an empty address; MissingExtraError: Ray missing (:func:`import_ray`)."""
    flag = {"name": "--engine", "workers": "--workers", "ray_address": "--ray-address"} if flags else {}
    if name not in ENGINES:
        raise ValueError(f"{flag.get('name', 'engine')} must be one of {', '.join(ENGINES)}, got {name!r}")
    workers = check_int(flag.get("workers", "workers"), workers, 1)
    if ray_address is not None:
        if name != "ray":
            raise ValueError(f"{flag.get('ray_address', 'ray_address')} is for the ray engine; add "
                             f"{flag.get('name', 'engine')} ray")
        if not str(ray_address).strip():
            raise ValueError(f"{flag.get('ray_address', 'ray_address')} is empty: give auto, host:port or "
                             "ray://host:10001")
    if name == "ray":
        import_ray()
    return Engine(name=name, workers=workers, ray_address=ray_address, gpus_per_task=float(gpus_per_task))


def add_engine_arguments(parser: argparse.ArgumentParser, default_workers: int = 1) -> None:
    """Add ``--engine``, ``--workers`` and ``--ray-address`` to a ``data_prep`` subcommand's parser."""
    parser.add_argument("--engine", default="local", choices=ENGINES,
                        help="local: a pool of --workers processes on this machine (default); ray: Ray Data tasks "
                             f"on a Ray cluster ({RAY_EXTRA})")
    parser.add_argument("--workers", type=int, default=default_workers,
                        help="local: worker processes; ray: the CPUs of a Ray started here "
                             f"(default {default_workers})")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="the Ray cluster, as ray.init takes it: auto (a running cluster), host:port, "
                             "ray://host:10001 (a client); default: start a local Ray")


def engine_from_args(args: argparse.Namespace) -> Engine:
    """The :class:`Engine` of the flags :func:`add_engine_arguments` added (checked: :func:`check_engine`)."""
    return check_engine(args.engine, args.workers, args.ray_address)


def fault_point(stage: str, scene: str) -> None:
    """Fault injection for the retry tests: SIGKILL this process the first time ``stage`` is reached for ``scene``
    while :data:`FAULT_ENV` holds ``"<stage>:<scene>:<flag file>"`` (comma-separated; the flag file marks it done)."""
    for spec in filter(None, os.environ.get(FAULT_ENV, "").split(",")):
        want_stage, want_scene, flag = spec.split(":", 2)
        if (want_stage, want_scene) != (stage, scene):
            continue
        try:
            fd = os.open(flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY)  # the first time only
        except FileExistsError:
            return
        os.close(fd)
        os.kill(os.getpid(), signal.SIGKILL)


def map_scenes(fn: Callable[[Any], Any], items: Iterable[Any], engine: Engine, *, desc: str = "scenes",
               progress: bool = True, bar: tqdm | None = None) -> None:
    """Call the picklable ``fn(item)`` once for each picklable item on ``engine`` and wait for all; return values are
    dropped. Items are handed out in order (the local engine draws them lazily) and finish in any order. ``progress``: a
    tqdm bar labelled ``desc`` (local; or count on ``bar`` when given) or Ray Data's bars. Raises the first exception
    raised by ``fn`` (on Ray too: ``fn``'s own exception)."""
    if engine.name == "ray":
        items = list(items)
        if items:
            _map_ray(fn, items, engine, progress)
        return
    workers = min(engine.workers, len(items)) if isinstance(items, Sized) else engine.workers
    own_bar = bar is None
    bar = bar if bar is not None else tqdm(total=len(items) if isinstance(items, Sized) else None, desc=desc,
                                           unit="scene", disable=not progress)
    try:
        if workers <= 1:
            for item in items:
                fn(item)
                bar.update()
            return
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker) as pool:
            running: set = set()
            for item in items:
                running.add(pool.submit(fn, item))
                while len(running) >= 2 * workers:
                    running = _collect(running, bar)
            while running:
                running = _collect(running, bar)
    finally:
        if own_bar:
            bar.close()


def _init_worker() -> None:
    torch.set_num_threads(1)  # one process per core; no oversubscription


def _collect(running: set, bar: tqdm) -> set:
    """Wait for a future of ``running`` to finish, re-raise its failure or count it; return those still running."""
    done, pending = wait(running, return_when=FIRST_COMPLETED)
    for fut in done:
        fut.result()
        bar.update()
    return pending


def _ray_row(row: dict[str, Any], fn: Callable[[Any], Any], items: Sequence[Any]) -> dict[str, Any]:
    """Ray Data's map function: run item ``row["index"]``; ``fn``'s exception comes back pickled in ``row["error"]``
    (Ray Data's own wrapper does not carry it to the driver)."""
    torch.set_num_threads(max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))))
    try:
        fn(items[row["index"]])
    except Exception as e:
        try:
            return {"index": row["index"], "error": pickle.dumps(e)}
        except Exception:  # an exception that does not pickle: its type and message
            return {"index": row["index"], "error": pickle.dumps(RuntimeError(f"{type(e).__name__}: {e}"))}
    return {"index": row["index"], "error": b""}


def _map_ray(fn: Callable[[Any], Any], items: Sequence[Any], engine: Engine, progress: bool) -> None:
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        # "local": a new Ray here, even where `ray start` left one running (None would join that one)
        kw: dict[str, Any] = dict(address=engine.ray_address or "local", logging_level=logging.ERROR,
                                  log_to_driver=False, include_dashboard=False)
        if engine.ray_address is None:
            kw["num_cpus"] = engine.workers
        ray.init(**kw)
    try:
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = progress
        ctx.print_on_execution_start = progress
        if not progress:  # no "progress bars disabled" warning, no execution log lines
            logging.getLogger("ray.data").setLevel(logging.ERROR)
        ds = ray.data.from_items([{"index": i} for i in range(len(items))], override_num_blocks=len(items))
        ds = ds.map(functools.partial(_ray_row, fn=fn, items=list(items)), num_cpus=engine.cpus_per_task,
                    num_gpus=engine.gpus_per_task or None)
        for row in ds.iter_rows():
            if row["error"]:
                raise pickle.loads(row["error"])
    finally:
        if started:
            ray.shutdown()
