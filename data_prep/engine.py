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
import socket
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence, Sized
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from multiprocessing import active_children, get_context
from typing import Any

import torch
from tqdm.auto import tqdm

from diff4splat.utils.checks import MissingExtraError, check_int
from diff4splat.utils.errors import quiet_c_stderr
from diff4splat.utils.limits import LimitError, size_text
from diff4splat.utils.preflight import address_space_limit

__all__ = ["Engine", "ENGINES", "check_engine", "add_engine_arguments", "engine_from_args", "engine_session",
           "map_scenes", "fault_point", "import_ray", "FAULT_ENV", "RAY_EXTRA", "RAY_CONNECT_TIMEOUT_S",
           "RAY_MIN_ADDRESS_SPACE"]

ENGINES = ("local", "ray")
"""The engines :func:`map_scenes` runs on."""
FAULT_ENV = "DIFF4SPLAT_FAULT"
"""Environment variable of :func:`fault_point`."""
RAY_EXTRA = "pip install 'diff4splat[ray]'"
"""The install command named when Ray is asked for and missing."""
RAY_CONNECT_TIMEOUT_S = 10.0
"""Seconds ``--ray-address host:port`` (or ``ray://host:port``) gets to accept a TCP connection before it is refused."""
_GCS_WAIT_ENV = "RAY_gcs_server_port_wait_time_s"  # Ray's budget, in seconds, for reaching a cluster's GCS
RAY_MIN_ADDRESS_SPACE = 4 << 30
"""Bytes of ``ulimit -v`` (RLIMIT_AS) a Ray started here needs: every process of it (GCS, raylet, the driver and the
workers, which load torch) runs under the limit. Measured on Ray 2.60, torch 2.13: 3.8 GiB starts, 3.5 GiB aborts."""


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
        others = set(active_children())
        pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker)
        try:
            running: set = set()
            for item in items:
                running.add(pool.submit(fn, item))
                while len(running) >= 2 * workers:
                    running = _collect(running, bar)
            while running:
                running = _collect(running, bar)
        except Exception:  # a failed scene: those running finish (whole), the rest are not started
            pool.shutdown(cancel_futures=True)
            raise
        except BaseException:  # Ctrl-C, SIGTERM: the workers end now, with the command, not after their scenes
            for proc in set(active_children()) - others:
                proc.terminate()
                proc.join()
            pool.shutdown(cancel_futures=True)  # its queues' semaphores released (no resource_tracker warning)
            raise
        pool.shutdown()
    finally:
        if own_bar:
            bar.close()


def _init_worker() -> None:
    torch.set_num_threads(1)  # one process per core; no oversubscription
    # a thread lock for tqdm, not its default multiprocessing one: a worker terminated with the driver leaves no
    # semaphore for the resource tracker to report
    tqdm.set_lock(threading.RLock())


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


@contextmanager
def engine_session(engine: Engine) -> Iterator[None]:
    """Start or join ``engine``'s workers for the block; run it before anything is written, so a cluster that cannot be
    reached leaves no output behind. ``local``: nothing to start. ``ray``: ``ray.init`` unless this process already
    joined a Ray (then that one is used and left running): ``ray_address`` None starts a Ray here of ``workers`` CPUs
    (under a virtual-memory limit, ``ulimit -v``, its object store is sized to it), ``"auto"`` joins the cluster
    ``ray start`` left, ``host:port`` or ``ray://host:port`` must accept a TCP connection within
    :data:`RAY_CONNECT_TIMEOUT_S`; a Ray started here is shut down after the block. SIGTERM keeps the handler it had
    (Ray's ``init`` installs its own), so a terminated driver shuts its Ray down.

    Raises:
        ValueError: ``ray_address`` is not ``auto``, ``host:port`` or ``ray://host:port``; nothing answers there; no
            cluster is running for ``auto``; :class:`~diff4splat.utils.limits.LimitError`: a virtual-memory limit
            below :data:`RAY_MIN_ADDRESS_SPACE` for a Ray started here.
        MissingExtraError: Ray is not installed (:func:`import_ray`).
    """
    if engine.name != "ray":
        yield
        return
    ray = import_ray()
    if ray.is_initialized():
        yield
        return
    _init_ray(ray, engine)
    try:
        yield
    finally:
        ray.shutdown()


def _init_ray(ray, engine: Engine) -> None:
    """``ray.init`` for :func:`engine_session`, its failures as one-line ValueErrors naming ``--ray-address``."""
    address = engine.ray_address
    # "local": a new Ray here, even where `ray start` left one running (None would join that one)
    kw: dict[str, Any] = dict(address=address or "local", logging_level=logging.ERROR, log_to_driver=False,
                              include_dashboard=False)
    if address is None:
        soft = address_space_limit()
        if soft is not None and soft < RAY_MIN_ADDRESS_SPACE:
            raise LimitError(f"--engine ray: a Ray started here needs a virtual-memory limit (ulimit -v) of at least "
                             f"{size_text(RAY_MIN_ADDRESS_SPACE)}, and this process has {size_text(soft)}: raise it, "
                             "or use --engine local")
        # the object store is one mapping in every process of the Ray, driver included, which the limit caps; it
        # holds only the tasks' rows here (tens of bytes a scene): a sixteenth of the limit, Ray's minimum 75 MiB
        kw.update(num_cpus=engine.workers, object_store_memory=None if soft is None else max(75 << 20, soft // 16))
    elif address != "auto":
        _probe(address)
    handler = signal.getsignal(signal.SIGTERM)
    # joining: Ray's GCS client retries once a second (20 by default), each retry a warning on fd 2
    wait = os.environ.get(_GCS_WAIT_ENV)
    os.environ[_GCS_WAIT_ENV] = wait or str(int(RAY_CONNECT_TIMEOUT_S))
    try:
        with quiet_c_stderr() if address is not None else nullcontext():
            ray.init(**kw)
    except ConnectionError as e:  # "auto" with no cluster; a port that answers but is no Ray
        raise ValueError(f"--ray-address {address}: {str(e).split('. ')[0]}: start one with `ray start --head`, or "
                         "leave --ray-address out to start a Ray here") from None
    finally:
        if wait is None:
            del os.environ[_GCS_WAIT_ENV]
        if handler is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, handler)  # Ray's init replaced it with sys.exit(15)


def _probe(address: str) -> None:
    """Refuse ``host:port`` / ``ray://host:port`` unless it accepts a TCP connection within
    :data:`RAY_CONNECT_TIMEOUT_S` (``ray.init`` itself retries for minutes)."""
    hostport = address.split("://", 1)[1] if "://" in address else address
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"--ray-address {address}: give auto, host:port or ray://host:port")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=RAY_CONNECT_TIMEOUT_S).close()
    except OSError as e:
        why = "no answer" if isinstance(e, TimeoutError) else (e.strerror or type(e).__name__)
        raise ValueError(f"--ray-address {address}: no Ray cluster reached there ({why} within "
                         f"{RAY_CONNECT_TIMEOUT_S:g} s)") from None


def _map_ray(fn: Callable[[Any], Any], items: Sequence[Any], engine: Engine, progress: bool) -> None:
    ray = import_ray()
    with engine_session(engine):
        if ray.util.client.ray.is_connected():  # Ray Client: Ray Data's executor needs a driver on the cluster
            try:
                ray.get(ray.remote(num_cpus=0)(_run_dataset).remote(fn, items, engine, progress=False))
            except ray.exceptions.RayTaskError as e:  # fn's own exception, not Ray's wrapper and its traceback
                raise e.cause from None
        else:
            _run_dataset(fn, items, engine, progress)


def _run_dataset(fn: Callable[[Any], Any], items: Sequence[Any], engine: Engine, progress: bool) -> None:
    """The Ray Data dataset of one task per item, run to its end in this process (a driver, or a task on the cluster
    for a Ray Client); raises the first of ``fn``'s exceptions."""
    ray = import_ray()
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
