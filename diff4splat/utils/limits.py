"""Resource limits checked before anything is allocated: one table, environment overrides, one message format.

A value above its limit raises :class:`LimitError` naming the value, the limit and the variable that raises it
(README, "Limits"). Limits are read from the environment at each check. Peak memory and output size default to the
machine's own room (:func:`available_memory`, :func:`free_disk`); their fixed defaults apply only where that cannot
be measured.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import psutil

try:
    import resource  # POSIX only: the process's ulimits
except ImportError:  # Windows
    resource = None

__all__ = ["Limit", "LIMITS", "LimitError", "limit", "check_limit", "check_output_size", "check_disk", "check_memory",
           "available_memory", "held_memory", "memory_caps", "tightest_memory_cap", "cgroup_room", "free_disk",
           "OUTPUT_BYTES_PER_PIXEL", "OUTPUT_BYTES_PER_GAUSSIAN", "OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN", "size_text"]


@dataclass(frozen=True)
class Limit:
    """One limit: its ``name`` in :data:`LIMITS`, ``default`` value, the ``env`` variable that overrides it (a positive
    integer), the ``unit`` it counts (for messages) and ``when`` a real use needs more (README table)."""

    name: str
    default: int
    env: str
    unit: str
    when: str


LIMITS: dict[str, Limit] = {lim.name: lim for lim in (
    Limit("steps", 1000, "DIFF4SPLAT_MAX_STEPS", "sampler steps",
          "never for sampling quality (the shipped configs use 8-50); only to study the sampler's convergence"),
    Limit("frames", 1001, "DIFF4SPLAT_MAX_FRAMES", "frames",
          "camera paths longer than 1001 frames (about 2 min at 8 fps) on a machine with the memory for them"),
    Limit("resolution", 2048, "DIFF4SPLAT_MAX_RESOLUTION", "pixels of output height",
          "output videos taller than 2048 pixels (the photo layer holds 1.25 Gaussians per output pixel, a front "
          "disk per pixel and a backing disk per 2×2 block: 5.2 M at 2048², about 0.6 GB with its deformation) on a "
          "machine with the memory for them"),
    Limit("image_pixels", 100_000_000, "DIFF4SPLAT_MAX_IMAGE_PIXELS", "pixels",
          "input photographs above 100 megapixels (the photo is decoded at full size before it is resized)"),
    Limit("output_bytes", 4 << 30, "DIFF4SPLAT_MAX_OUTPUT_BYTES", "bytes",
          "a fixed size instead of the output disk's free space (the default wherever that is measured): an "
          "estimate above the free space of a disk that will have room (the estimate is an upper bound), or a "
          "smaller cap"),
    Limit("memory_bytes", 8 << 30, "DIFF4SPLAT_MAX_MEMORY_BYTES", "bytes of memory",
          "a fixed size instead of the memory available when the check runs (the default wherever that is "
          "measured): the estimate is an upper bound, 1.1-1.45x the measured peak (docs/benchmarks.md, 'Memory of "
          "generate'), so a request just above the available memory may still fit; or a smaller cap"),
    Limit("parameters", 20_000_000_000, "DIFF4SPLAT_MAX_PARAMETERS", "parameters",
          "model configs larger than the paper's (16.8 billion parameters), on a machine with 4 bytes each"),
    Limit("iterations", 100_000, "DIFF4SPLAT_MAX_ITERATIONS", "optimisation steps",
          "fits longer than 100 000 steps (fit's default is 1800; 4DGS trains 14 000-20 000, 3DGS 30 000), which "
          "take hours on a GPU and days on a CPU"),
    Limit("gaussians", 10_000_000, "DIFF4SPLAT_MAX_GAUSSIANS", "Gaussians",
          "fits of more than 10 million Gaussians (3DGS's largest scenes hold about 6 million; each costs about 1 KB "
          "of parameters, gradients and Adam moments) on a machine with the memory for them"),
    Limit("scenes", 100_000, "DIFF4SPLAT_MAX_SCENES", "scenes",
          "synthetic datasets of more than 100 000 scenes (about 100 GB of disk and 40 core-hours at the default "
          "64², 17 frames, 2 cameras)"),
    Limit("synth_bytes", 4 << 30, "DIFF4SPLAT_MAX_SYNTH_BYTES", "bytes",
          "synthetic scenes with long or large camera paths, on a machine with the memory for one such scene per "
          "--workers process"),
)}
"""Every limit, by name (README, "Limits", renders this table)."""

OUTPUT_BYTES_PER_PIXEL = 16
"""Upper bound of what ``generate`` writes per frame pixel: RGB, alpha and float32 depth, with margin for
incompressible videos and PNGs."""


OUTPUT_BYTES_PER_GAUSSIAN = 112
"""Upper bound of what ``generate`` writes per Gaussian and frame: a float32 PLY row (17 × 4 bytes) plus its
deformation (10 × 4 bytes), with margin."""

OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN = 44
"""The same without the frame's PLY row (``generate --no-frame-plys``)."""


class LimitError(ValueError):
    """A request above a resource limit (the message names the value, the limit and how to raise it)."""


def limit(name: str) -> int:
    """The current value of limit ``name``: its environment variable if set, else its default.

    Raises:
        KeyError: unknown ``name``.
        ValueError: the variable is set but is not a positive integer.
    """
    lim = LIMITS[name]
    raw = os.environ.get(lim.env)
    if raw is None or not raw.strip():
        return lim.default
    try:
        value = int(raw.strip().replace("_", ""))
    except ValueError:
        value = 0
    if value < 1:
        raise ValueError(f"{lim.env} must be a positive integer, got {raw!r}")
    return value


def check_limit(name: str, value: int, what: str) -> int:
    """``value`` if it is at most limit ``name``; ``what`` names it as the user knows it (``"--steps"``).

    Raises:
        LimitError: ``value`` > the limit; one line with the value, the limit and its variable.
    """
    lim = LIMITS[name]
    bound = limit(name)
    if value > bound:
        raise LimitError(f"{what} {value} exceeds the limit of {bound} {lim.unit} "
                         f"(set {lim.env} to raise it)")
    return value


def memory_caps() -> dict[str, int] | None:
    """Bytes this process can still allocate under each cap that applies, by name: ``"available"`` (psutil), ``"cgroup
    memory.max"`` (:func:`cgroup_room`) and the ``ulimit -v`` / ``-d`` limits less the process's current use. None where
    psutil cannot measure the memory."""
    try:
        mem = psutil.Process().memory_info()
        caps = {"available": int(psutil.virtual_memory().available)}
    except (OSError, RuntimeError, NotImplementedError, psutil.Error):  # no /proc in a sandbox; psutil's
        return None  # NotImplementedError is its error for a call this platform lacks: not a stub
    room = cgroup_room()
    if room is not None:
        caps["cgroup memory.max"] = room
    for name, which, used in (("address-space limit (ulimit -v, RLIMIT_AS)", "RLIMIT_AS", mem.vms),
                              ("data-segment limit (ulimit -d, RLIMIT_DATA)", "RLIMIT_DATA",
                               getattr(mem, "data", None))):
        cap = _rlimit(which)
        if cap is not None and used is not None:
            caps[name] = max(0, cap - int(used))
    return caps


def _rlimit(which: str) -> int | None:
    """The soft limit ``resource.<which>`` in bytes, None where unlimited or not available."""
    if resource is None or not hasattr(resource, which):
        return None
    soft, _ = resource.getrlimit(getattr(resource, which))
    return None if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


def available_memory() -> int | None:
    """Bytes this process may reach at its peak: its resident set plus the least room of :func:`memory_caps`; None where
    unmeasurable. The default bound of :func:`check_memory`."""
    caps = memory_caps()
    return None if caps is None else held_memory() + min(caps.values())


def held_memory() -> int:
    """Bytes this process holds now (its resident set); 0 where unmeasurable."""
    try:
        return int(psutil.Process().memory_info().rss)
    except (OSError, RuntimeError, NotImplementedError, psutil.Error):
        return 0


def tightest_memory_cap() -> str:
    """The name of the cap of :func:`memory_caps` with the least room ("available" where none can be measured)."""
    caps = memory_caps()
    return "available" if not caps else min(caps, key=caps.get)


_CGROUP_UNLIMITED = 1 << 62
"""cgroup v1 writes "no limit" as a number near 2⁶³: anything above this is no limit."""


def cgroup_room(proc_cgroup: str | os.PathLike = "/proc/self/cgroup",
                root: str | os.PathLike = "/sys/fs/cgroup") -> int | None:
    """Bytes this process's Linux memory cgroup can still take, the least along its hierarchy: limit − (usage − inactive
    file cache) (v2: ``memory.max``, ``memory.current``, ``inactive_file``; v1: ``memory.limit_in_bytes``,
    ``memory.usage_in_bytes``, ``total_inactive_file``). None without a limit or a cgroup file system.
    ``proc_cgroup``, ``root``: the files read."""
    try:
        lines = Path(proc_cgroup).read_text().splitlines()
    except OSError:
        return None
    root = Path(root)
    v1 = next((ln.split(":", 2)[2] for ln in lines if "memory" in ln.split(":", 2)[1].split(",")), None)
    v2 = next((ln.split(":", 2)[2] for ln in lines if ln.startswith("0::")), None)
    if v1 is not None:
        base, files = root / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
        path = v1
    elif v2 is not None:
        base, files, path = root, ("memory.max", "memory.current", "inactive_file"), v2
    else:
        return None
    folder = base / path.strip("/")
    if not folder.is_dir():  # a cgroup namespace shows the process's own cgroup at the mount's root
        folder = base
    rooms = []
    while True:
        room = _cgroup_level_room(folder, *files)
        if room is not None:
            rooms.append(room)
        if folder == base or base not in folder.parents:
            break
        folder = folder.parent
    return max(0, min(rooms)) if rooms else None


def _cgroup_level_room(folder: Path, limit_file: str, usage_file: str, inactive_key: str) -> int | None:
    """limit − (usage − inactive file cache) of one cgroup folder, None without a limit or unreadable."""
    try:
        raw = (folder / limit_file).read_text().strip()
        if raw == "max" or int(raw) >= _CGROUP_UNLIMITED:
            return None
        usage = int((folder / usage_file).read_text().strip())
        stat = dict(line.split() for line in (folder / "memory.stat").read_text().splitlines() if line.strip())
        return int(raw) - (usage - int(stat.get(inactive_key, 0)))
    except (OSError, ValueError):
        return None


def free_disk(path: str | os.PathLike) -> int | None:
    """Free bytes for an unprivileged user on the disk of ``path`` (its nearest existing ancestor), None where
    unmeasurable. The default bound of :func:`check_output_size`."""
    p = Path(os.path.abspath(path))
    while not p.exists() and p.parent != p:
        p = p.parent
    try:
        return int(shutil.disk_usage(p).free)
    except OSError:
        return None


def size_text(n_bytes: float) -> str:
    """A byte count for a message: GiB from 1 GiB, else MiB from 1 MiB, else KiB, one decimal."""
    for unit, power in (("GiB", 30), ("MiB", 20)):
        if n_bytes >= 2**power:
            return f"{n_bytes / 2**power:.1f} {unit}"
    return f"{n_bytes / 2**10:.1f} KiB"


def _bound(name: str, measured: int | None, resource: str, knobs: str) -> tuple[int, str]:
    """Limit ``name``'s bound and its text for a message: its variable if set, else ``measured``, else its default."""
    lim = LIMITS[name]
    if os.environ.get(lim.env, "").strip() or measured is None:
        bound = limit(name)
        return bound, (f"the limit of {size_text(bound)} ({bound} bytes; lower {knobs}, or set {lim.env} to "
                       "raise it)")
    return measured, f"the {size_text(measured)} {resource} (lower {knobs}, or set {lim.env} to a size in bytes)"


def check_output_size(frames: int, width: int, height: int, gaussians: int = 0,
                      knobs: str = "--frames or the resolution", out: str | os.PathLike | None = None,
                      frame_plys: bool = True) -> int:
    """Estimate the bytes ``generate`` (or ``render``) writes and check it against the free space of ``out``'s disk;
    returns the estimate.

    The estimate: frames·width·height·:data:`OUTPUT_BYTES_PER_PIXEL` plus (frames + 1)·gaussians·
    :data:`OUTPUT_BYTES_PER_GAUSSIAN`, or without ``frame_plys`` gaussians·(:data:`OUTPUT_BYTES_PER_GAUSSIAN` +
    frames·:data:`OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN`). The bound: ``DIFF4SPLAT_MAX_OUTPUT_BYTES`` when set, else
    :func:`free_disk`, else the ``output_bytes`` limit.

    Raises:
        LimitError: the estimate exceeds the bound (the message names ``knobs``, the arguments that lower it).
    """
    estimate = int(frames) * int(width) * int(height) * OUTPUT_BYTES_PER_PIXEL
    per_frame = OUTPUT_BYTES_PER_GAUSSIAN if frame_plys else OUTPUT_DEFORMATION_BYTES_PER_GAUSSIAN
    estimate += int(gaussians) * (OUTPUT_BYTES_PER_GAUSSIAN + int(frames) * per_frame)
    return check_disk(estimate, f"output of {frames} frames at {width}×{height}", knobs, out)


def check_disk(estimate: int, request: str, knobs: str, out: str | os.PathLike | None) -> int:
    """Check an estimate (bytes, an upper bound) of what a command writes to ``out`` against
    ``DIFF4SPLAT_MAX_OUTPUT_BYTES`` when set, else :func:`free_disk` of ``out``, else the ``output_bytes`` limit;
    returns it. ``request``: what was asked; ``knobs``: the arguments that lower the estimate.

    Raises:
        LimitError: one line with the request, the estimate and the bound, the knobs and the variable.
    """
    bound, then = _bound("output_bytes", None if out is None else free_disk(out), f"free on the disk of {out}", knobs)
    if estimate > bound:
        raise LimitError(f"{request}: estimated {size_text(estimate)} exceeds {then}")
    return estimate


def check_memory(estimate: int, request: str, knobs: str) -> int:
    """Check an estimate (bytes, an upper bound) of a command's peak memory against ``DIFF4SPLAT_MAX_MEMORY_BYTES`` when
    set, else :func:`available_memory`, else the ``memory_bytes`` limit; returns it. ``request``: what was asked, as
    the user wrote it; ``knobs``: the arguments that lower the estimate.

    Raises:
        LimitError: one line with the request, the estimate and the bound in GiB, the knobs and the variable.
    """
    cap = tightest_memory_cap()
    resource_text = ("of memory available to this process" if cap == "available" else
                     f"this process may still use under its {cap}")
    bound, then = _bound("memory_bytes", available_memory(), resource_text, knobs)
    if estimate > bound:
        raise LimitError(f"{request}: estimated peak memory {size_text(estimate)} exceeds "
                         f"{then}")
    return estimate
