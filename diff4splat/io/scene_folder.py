"""The output folder of ``generate``, ``fit`` and ``render``: the names of its files (:data:`LAYOUT_FILES`,
:data:`LAYOUT_FRAMES`), writing it atomically (:func:`write_scene_folder`), the ``meta.json`` fields every folder
shares (:func:`scene_meta`) and reading it back as untrusted input (:func:`load_scene_folder`). The layout is listed
in docs/DESIGN.md, "Output folder of generate"; the folder policy is :mod:`diff4splat.io.output_folders`'s.
"""
from __future__ import annotations

import json
import math
import os
import platform
import zipfile
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diff4splat import __version__
from diff4splat.cameras.path import CameraPath
from diff4splat.io.atomic import atomic_output_path
from diff4splat.io.cameras import load_cameras_json, save_cameras_json
from diff4splat.io.exr import save_depth_exr
from diff4splat.io.inputs import check_input_file, check_input_folder
from diff4splat.io.output_folders import output_dir
from diff4splat.io.ply import load_ply, save_ply
from diff4splat.io.structured import read_json
from diff4splat.io.video import DEFAULT_FPS, check_fps, save_image, save_video, to_uint8
from diff4splat.io.viewer_page import VIEWER_NAME, write_viewer
from diff4splat.render.settings import BACKGROUND, EPS2D
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.checks import check_positive
from diff4splat.utils.constants import ALPHA_MIN
from diff4splat.utils.limits import check_limit

__all__ = ["write_scene_folder", "fill_empty_depth", "save_deformation", "load_deformation", "deformation_tensors",
           "json_default", "load_output_scene", "folder_file", "DEFORMATION_ARRAYS", "is_layout_file", "LAYOUT_FILES",
           "LAYOUT_FRAMES", "layout_frame", "SCENE_FILE", "DEFORMATION_FILE", "CAMERAS_FILE", "META_FILE", "VIDEO_FILE",
           "FIELD_FILE", "METRICS_FILE", "SceneFolder", "load_scene_folder", "scene_meta", "meta_background",
           "meta_eps2d"]

SCENE_FILE = "scene.ply"
"""The canonical Gaussians, INRIA PLY layout (:func:`diff4splat.io.ply.save_ply`)."""
DEFORMATION_FILE = "deformation.npz"
"""The deformation and temporal support of the canonical Gaussians (:func:`save_deformation`); absent if neither."""
CAMERAS_FILE = "cameras.json"
"""The camera path (:func:`diff4splat.io.save_cameras_json`)."""
META_FILE = "meta.json"
"""The run's settings, counts and timings, and the fields every folder shares (:func:`scene_meta`)."""
VIDEO_FILE = "video.mp4"
"""RGB along the camera path (:func:`diff4splat.io.video.save_video`)."""
FIELD_FILE = "field.safetensors"
"""The HexPlane field a ``fit`` output folder holds (:func:`models.hexplane.save_field`)."""
METRICS_FILE = "metrics.json"
"""A ``fit`` output folder's training and hold-out metrics."""
LAYOUT_FILES = (SCENE_FILE, DEFORMATION_FILE, CAMERAS_FILE, META_FILE, VIDEO_FILE, VIEWER_NAME, FIELD_FILE,
                METRICS_FILE)
"""The files at the top of an output folder of generate, fit or render (module docstring)."""
LAYOUT_FRAMES = {"frames": ".ply", "rgb": ".png", "depth": ".exr"}
"""The per-frame sub-folders of an output folder and the suffix of their files ``NNNN<suffix>`` (4+ digits)."""


def meta_background(meta: dict) -> tuple[float, float, float]:
    """An output folder's meta.json ``background`` (3 numbers in [0, 1], the colour the scene was fitted
    against), else :data:`~diff4splat.render.settings.BACKGROUND`."""
    bg = meta.get("background")
    if (isinstance(bg, list) and len(bg) == 3 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                      and 0.0 <= v <= 1.0 for v in bg)):
        return tuple(float(v) for v in bg)
    return BACKGROUND


def meta_eps2d(meta: dict) -> float:
    """An output folder's meta.json ``eps2d`` (screen-space dilation, pixels², in [0, 10]), else
    :data:`~diff4splat.render.settings.EPS2D`."""
    eps = meta.get("eps2d")
    if isinstance(eps, (int, float)) and not isinstance(eps, bool) and 0.0 <= eps <= 10.0:
        return float(eps)
    return EPS2D


def scene_meta(scene: DynamicGaussians, cameras: CameraPath, *, fps: float | None,
               background: Iterable[float] = BACKGROUND, eps2d: float = EPS2D,
               versions: dict | None = None) -> dict:
    """The ``meta.json`` fields every output folder writes: frames, width, height (of ``cameras``), fps, static,
    num_gaussians, background (RGB in [0, 1]), eps2d (pixels²) and versions (diff4splat, torch, python, plus
    ``versions``). Each command adds its own settings."""
    return {
        "frames": len(cameras),
        "width": cameras.width,
        "height": cameras.height,
        "fps": fps,
        "static": scene.is_static,
        "num_gaussians": scene.num_gaussians,
        "background": [float(v) for v in background],
        "eps2d": float(eps2d),
        "versions": {"diff4splat": __version__, "torch": torch.__version__, "python": platform.python_version(),
                     **(versions or {})},
    }


def fill_empty_depth(depths: Tensor, alphas: Tensor, fallback: float) -> Tensor:
    """(T, H, W) depth, metres, finite and > 0: pixels with alpha < ALPHA_MIN (1/255) get the largest depth of any
    covered pixel on the path, or ``fallback`` metres if none is covered (the EXR's "A" channel keeps the coverage).

    ``depths``: (T, H, W) metres, 0 where empty; ``alphas``: (T, H, W) coverage in [0, 1]; ``fallback`` > 0.
    """
    covered = alphas >= ALPHA_MIN
    # depths ≥ 0, so the largest of the covered is the largest with the uncovered read as 0 (no boolean gather)
    far = float(torch.where(covered, depths, 0.0).amax()) if bool(covered.any()) else float(fallback)
    return torch.where(covered & (depths > 0), depths, far)


READ_CHUNK_BYTES = 1 << 24
"""Bytes of a ``deformation.npz`` member read at a time (into the array's own buffer)."""
_DEFORMATION_KEYS = ("times", "d_means", "d_quats", "d_scales")
_TEMPORAL_KEYS = ("t_means", "t_scales")
_SHAPES = {"times": ("K",), "d_means": ("K", "M", 3), "d_quats": ("K", "M", 4), "d_scales": ("K", "M", 3),
           "t_means": ("M",), "t_scales": ("M",), "t_ramps": ("M",)}
"""Shape of each array of ``deformation.npz``: K key times, M Gaussians."""
DEFORMATION_ARRAYS = tuple(_SHAPES)
"""The arrays ``deformation.npz`` may hold, the keyword arguments of ``DynamicGaussians`` after the canonical ones."""
_NPZ_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, zlib.error,
               NotImplementedError,  # zipfile's error for a compression method it does not support: not a stub
               RuntimeError, ValueError, KeyError, OSError)
"""What zipfile and numpy's ``.npy`` header parser raise on a corrupt archive or member."""

def _zip_call(path: Path, what: str, fn: Callable, *args):
    """``fn(*args)``, its failures on a corrupt archive as one ``ValueError`` starting with ``path``."""
    try:
        return fn(*args)
    except _NPZ_ERRORS as e:
        raise ValueError(f"{path}: {what} ({' '.join(str(e).split()) or type(e).__name__})") from None


IDENTITY_DEFORMATION = {"d_means": (0.0, 0.0, 0.0), "d_quats": (1.0, 0.0, 0.0, 0.0), "d_scales": (0.0, 0.0, 0.0)}
"""Each deformation array's identity row: no displacement, no rotation (wxyz), no log-scale change."""
DEFLATE_LEVEL = 1
"""zlib level of the members :func:`save_deformation` deflates (level 6, numpy's, took 1.5× as long on a
``reconstruct`` scene for 12 % fewer bytes; docs/benchmarks.md, "deformation.npz: stored against deflated")."""
DEFLATE_SAMPLE_ROWS = 65536
"""At most this many evenly spaced rows of a deformation array are looked at by :func:`deflated`."""


def deflated(key: str, array: np.ndarray) -> bool:
    """Whether :func:`save_deformation` deflates the member ``key``: a deformation array (K, M, c) when at least half
    of its rows are the identity (:data:`IDENTITY_DEFORMATION`: a still Gaussian's, or a scene of layers, each moving
    near its own time: zlib shrinks those runs ~25×, where a dense deformation's float noise gains ~30 % for 20× the
    write time), counted over :data:`DEFLATE_SAMPLE_ROWS` evenly spaced rows when there are more (exact below); the
    per-Gaussian temporal arrays (M,) and ``times`` always (few distinct values, small)."""
    if key not in IDENTITY_DEFORMATION:
        return True
    n = math.prod(array.shape[:-1])  # rows picked by index: no copy of an expanded (stride-0) array
    rows = array[np.unravel_index(np.arange(0, n, max(1, -(-n // DEFLATE_SAMPLE_ROWS))), array.shape[:-1])]
    identity = (rows == np.asarray(IDENTITY_DEFORMATION[key], dtype=array.dtype)).all(axis=-1)
    return 2 * int(np.count_nonzero(identity)) >= identity.size


def save_deformation(path: str | os.PathLike, scene: DynamicGaussians, *, level: int = DEFLATE_LEVEL) -> None:
    """Write ``deformation.npz`` atomically: float32 times, d_means, d_quats, d_scales when the scene deforms, and
    t_means (M,), t_scales (M,) (and t_ramps (M,) for a trapezoid) when it has temporal support. A standard ``.npz``
    (``numpy.load`` reads it); the members :func:`deflated` says are zlib-deflated at ``level`` (1–9), the others
    stored.

    Raises:
        ValueError: the scene has neither (nothing to write); ``level`` not an int in 1–9.
    """
    if isinstance(level, bool) or not isinstance(level, int) or not 1 <= level <= 9:
        raise ValueError(f"level must be an int in 1–9 (zlib's), got {level!r}")
    if not scene.changes_with_time:
        raise ValueError("a static scene without temporal support has no deformation to save")
    keys = (() if scene.is_static else _DEFORMATION_KEYS) + (_TEMPORAL_KEYS if scene.has_temporal else ())
    keys += ("t_ramps",) if scene.t_ramps is not None else ()
    with atomic_output_path(Path(path)) as tmp, zipfile.ZipFile(tmp, "w") as zf:  # each member says its method
        for key in keys:  # one array at a time, streamed into its member as np.savez does
            array = getattr(scene, key).detach().cpu().float().numpy()  # device: the .npy bytes are written from host
            # the zip epoch as every member's time: the same scene gives the same bytes
            member = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            member.compress_type = zipfile.ZIP_DEFLATED if deflated(key, array) else zipfile.ZIP_STORED
            # a member's zlib level: ZipInfo.compress_level from Python 3.13, its _compresslevel slot before
            setattr(member, "compress_level" if hasattr(member, "compress_level") else "_compresslevel", level)
            with zf.open(member, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, array, allow_pickle=False)  # in chunks, strided or not


def _npy_header(f) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, Fortran order, dtype) from the header of the ``.npy`` file ``f`` (format 1.0 or 2.0)."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(f)
    raise ValueError(f".npy format version {version}, expected 1.0 or 2.0")


def _fill(read, view: memoryview, done: int) -> int:
    """Read into ``view`` from byte ``done`` on, :data:`READ_CHUNK_BYTES` at a time (one read of a deflated member
    would grow a bytes object); the bytes of ``view`` filled in all."""
    while done < len(view):
        chunk = read(min(READ_CHUNK_BYTES, len(view) - done))
        if not chunk:
            break
        view[done:done + len(chunk)] = chunk
        done += len(chunk)
    return done


def _read_rows(read, shape: tuple[int, int, int], dtype: np.dtype) -> tuple[np.ndarray, int]:
    """A C-order (K, M, c) array read key by key, (array, bytes read): while every Gaussian's row at each key equals
    that key's first, the K first rows broadcast to (K, M, c) (float32, read-only, stride 0 along M); at the first row
    that differs, the whole array in one buffer of ``dtype``, the rows already read written back from their key's
    first."""
    K, M, c = shape
    row = c * dtype.itemsize
    per_chunk = max(1, READ_CHUNK_BYTES // row)
    firsts = np.empty((K, 1, c), dtype=dtype)
    buffer = np.empty(min(per_chunk, M) * row, dtype=np.uint8)
    done = 0
    for k in range(K):
        for start in range(0, M, per_chunk):
            n = min(per_chunk, M - start)
            got = _fill(read, memoryview(buffer)[:n * row], 0)
            done += got
            if got < n * row:  # truncated: the caller says so
                return firsts, done
            piece = buffer[:n * row].view(dtype).reshape(n, c)
            if start == 0:
                firsts[k, 0] = piece[0]
            if not np.array_equal(piece, np.broadcast_to(firsts[k], (n, c))):
                full = np.empty(shape, dtype=dtype)
                full[:k], full[k, :start], full[k, start:start + n] = firsts[:k], firsts[k], piece
                return full, _fill(read, memoryview(full.reshape(-1).view(np.uint8)), done)
    return np.broadcast_to(firsts.astype(np.float32), shape), done


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, dims: dict[str, int]) -> np.ndarray:
    """One array of ``deformation.npz`` as float32, its header (floating dtype, :data:`_SHAPES` with K, M bound in
    ``dims`` on first sight) checked before its data is read. A (K, M, c) array in which every Gaussian has the same
    row at each key (``reconstruct``'s identity rotations and scales) comes back as those K rows broadcast (read-only,
    stride 0 along M; :func:`_read_rows`): it is never held whole."""
    key = info.filename[:-len(".npy")]
    corrupt = f"'{key}' is not a readable .npy array"
    with _zip_call(path, corrupt, zf.open, info) as f:
        shape, fortran, dtype = _zip_call(path, corrupt, _npy_header, f)
        expect = _SHAPES[key]
        if dtype.kind != "f":
            raise ValueError(f"{path}: '{key}' must hold floating-point numbers, got dtype {dtype}")
        if len(shape) == len(expect) and "K" in expect and "K" not in dims:
            check_limit("frames", shape[0], f"{path}: a deformation of")
        bound = [want if isinstance(want, int) else dims.setdefault(want, size)
                 for size, want in zip(shape, expect, strict=False)]
        if tuple(bound) != shape or len(shape) != len(expect):
            named = ", ".join(f"{w}={dims[w]}" if w in dims else str(w) for w in expect)
            raise ValueError(f"{path}: '{key}' must have shape ({named}) (K key times, M Gaussians of scene.ply), "
                             f"got {shape}")
        size = math.prod(shape) * dtype.itemsize  # bounded: K by the frames limit, M by scene.ply
        read = lambda n: _zip_call(path, corrupt, f.read, n)  # noqa: E731
        if len(shape) == 3 and not fortran:
            array, done = _read_rows(read, shape, dtype)
        else:
            data = np.empty(size, dtype=np.uint8)
            done = _fill(read, memoryview(data), 0)
            array = data.view(dtype).reshape(shape, order="F" if fortran else "C")
    if done != size:
        raise ValueError(f"{path}: '{key}' is truncated ({done} of {size} bytes)")
    return array.astype(np.float32, copy=False)


def deformation_tensors(arrays: dict[str, np.ndarray]) -> dict[str, Tensor]:
    """:func:`load_deformation`'s arrays as CPU tensors on their memory (``DynamicGaussians`` keyword arguments); a
    broadcast row (stride 0 along M) stays one row in memory, expanded."""
    return {k: torch.from_numpy(v[:, :1].copy()).expand(v.shape) if v.ndim == 3 and v.strides[1] == 0
            else torch.from_numpy(v) for k, v in arrays.items()}


def load_deformation(path: str | os.PathLike, num_gaussians: int | None = None) -> dict[str, np.ndarray]:
    """Read ``deformation.npz`` → float32 arrays {"times", "d_means", "d_quats", "d_scales"} and/or
    {"t_means", "t_scales"}, with "t_ramps" for a trapezoid (``DynamicGaussians`` keyword arguments), with
    :mod:`zipfile` and numpy's ``.npy`` header parser (never unpickling); each array's dtype and shape are checked
    before its data is read. A (K, M, c) array whose Gaussians all have the same row at each key comes back as
    those rows broadcast (read-only, stride 0 along M; :func:`deformation_tensors` keeps them so as tensors).

    Args:
        num_gaussians: M of the scene's ``scene.ply``, or None to take it from the file.

    Raises:
        FileNotFoundError / ValueError: ``path`` missing or not a regular file (:func:`check_input_file`).
        ValueError: starting with ``path``: not a zip archive, a corrupt member, an unknown entry, a partial set of
            either group, an array not floating-point or not of shape times (K,), d_means (K, M, 3), d_quats
            (K, M, 4), d_scales (K, M, 3), t_means / t_scales / t_ramps (M,); t_ramps without t_means; K above
            the ``frames`` limit (LimitError).
            Values are checked by ``DynamicGaussians``.
    """
    path = check_input_file(path, "deformation")
    dims = {} if num_gaussians is None else {"M": int(num_gaussians)}
    not_npz = "not a readable .npz archive"
    with _zip_call(path, not_npz, zipfile.ZipFile, path) as zf:
        infos = _zip_call(path, not_npz, zf.infolist)
        unknown = [i.filename for i in infos if not i.filename.endswith(".npy") or i.filename[:-4] not in _SHAPES]
        if unknown:
            raise ValueError(f"{path}: unexpected entries {unknown} (a deformation.npz holds "
                             f"{', '.join(_SHAPES)} as .npy arrays)")
        out = {info.filename[:-4]: _read_member(zf, info, path, dims) for info in infos}
    if not out:
        raise ValueError(f"{path}: holds no arrays (a deformation.npz holds {', '.join(_SHAPES)})")
    for group in (_DEFORMATION_KEYS, _TEMPORAL_KEYS):
        if 0 < sum(k in out for k in group) < len(group):
            raise ValueError(f"{path}: needs all of {group} or none, got {sorted(out)}")
    if "t_ramps" in out and "t_means" not in out:
        raise ValueError(f"{path}: t_ramps needs t_means and t_scales, got {sorted(out)}")
    return out


def write_scene_folder(
    out_dir: str | os.PathLike,
    scene: DynamicGaussians,
    cameras: CameraPath,
    colors: Tensor,  # (T, H, W, 3) in [0, 1]
    depths: Tensor,  # (T, H, W) metres
    alphas: Tensor,  # (T, H, W)
    meta: dict,
    *,
    fps: float = DEFAULT_FPS,
    depth_fallback: float = 1.0,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
    kind: str = "generate",
    extra: Callable[[Path], None] | None = None,
    with_scene: bool = True,
    frame_plys: bool = True,
) -> Path:
    """Write the output folder (docs/DESIGN.md, "Output folder of generate") through
    :func:`~diff4splat.io.output_folders.output_dir` with marker kind ``kind`` ("generate", "fit" or "render").

    ``extra(tmp)`` adds files of its own after the others and before ``meta.json`` (written last). ``with_scene``
    false (a render) leaves out scene.ply, deformation.npz and frames/, and pads an odd-sized video.mp4 to even
    sizes by repeating the last column/row; ``out_dir``'s parents must then exist. frames/ is written only with
    ``frame_plys`` and a scene that changes with time; ``meta["frame_plys"]`` records whether (with the scene).
    A failure part-way leaves ``out_dir`` as it was.

    Raises:
        ValueError: frame counts of colours/depths/alphas/cameras differ.
        OutputDirError: ``out_dir`` may not be written (:func:`~diff4splat.io.output_folders.check_output_dir`).
    """
    T = len(cameras)
    if not (colors.shape[0] == depths.shape[0] == alphas.shape[0] == T):
        raise ValueError(f"colors/depths/alphas must have {T} frames (one per camera), got "
                         f"{colors.shape[0]}/{depths.shape[0]}/{alphas.shape[0]}")
    depths = fill_empty_depth(depths, alphas, depth_fallback)
    if with_scene:
        frame_plys = meta["frame_plys"] = bool(frame_plys) and scene.changes_with_time
    rgb = to_uint8(colors.cpu(), "colors")  # (T, H, W, 3): rgb/*.png lossless beside the lossy video
    with output_dir(out_dir, kind=kind, inputs=inputs, overwrite=overwrite, parents=with_scene) as tmp:
        if with_scene:
            save_ply(tmp / SCENE_FILE, scene.canonical)
            if scene.changes_with_time:
                save_deformation(tmp / DEFORMATION_FILE, scene)
        for i in range(T):
            if with_scene and frame_plys:
                save_ply(tmp / layout_frame("frames", i), scene.at(float(cameras.times[i])))
            save_depth_exr(tmp / layout_frame("depth", i), depths[i].cpu(), alphas[i].clamp(0, 1).cpu())
            save_image(tmp / layout_frame("rgb", i), rgb[i])
        save_video(tmp / VIDEO_FILE, rgb if with_scene else _even(rgb), fps=fps)
        save_cameras_json(tmp / CAMERAS_FILE, cameras.to("cpu"))
        write_viewer(tmp / VIEWER_NAME, scene, cameras.to("cpu"), fps=fps, background=meta_background(meta),
                     eps2d=meta_eps2d(meta))
        if extra is not None:
            extra(tmp)
        (tmp / META_FILE).write_text(json.dumps(meta, indent=2, default=json_default))
    return Path(out_dir)


def _even(frames: np.ndarray) -> np.ndarray:
    """(T, H, W, 3) uint8 padded to even H and W by repeating the last row/column (MPEG-4 needs even sizes)."""
    _, H, W, _ = frames.shape
    return np.pad(frames, ((0, 0), (0, H % 2), (0, W % 2), (0, 0)), mode="edge")


def json_default(obj):
    """``json.dumps`` ``default=``: numpy scalars → Python numbers, paths → strings."""
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def layout_frame(folder: str, index: int) -> str:
    """Frame ``index``'s path in the sub-folder ``folder`` (a key of :data:`LAYOUT_FRAMES`): ``"depth/0000.exr"``."""
    return f"{folder}/{index:04d}{LAYOUT_FRAMES[folder]}"


def is_layout_file(name: str) -> bool:
    """Whether ``name`` (``/``-separated, relative to an output folder) is one of :data:`LAYOUT_FILES` or
    ``frames/NNNN.ply``, ``rgb/NNNN.png``, ``depth/NNNN.exr`` with 4 or more ASCII digits."""
    folder, _, file = name.rpartition("/")
    if not folder:
        return name in LAYOUT_FILES
    suffix = LAYOUT_FRAMES.get(folder)
    stem = file[:-len(suffix)] if suffix is not None and file.endswith(suffix) else ""
    return len(stem) >= 4 and stem.isascii() and stem.isdigit()


def folder_file(folder: str | os.PathLike, name: str) -> Path | None:
    """``folder / name`` if something is there, None if nothing is.

    Raises:
        FileNotFoundError / ValueError: it is not a regular file (a folder, a FIFO, a dangling symlink;
            :func:`~diff4splat.io.inputs.check_input_file`).
    """
    path = Path(folder) / name
    if not path.exists() and not path.is_symlink():
        return None
    return check_input_file(path, "scene folder")


def _check_meta(meta: dict, path: Path) -> None:
    """Check ``static``, ``fps``, ``background``, ``eps2d`` and ``scene_depth`` of ``meta.json`` where not null."""
    checks = {
        "static": ("true or false", lambda v: isinstance(v, bool)),
        "fps": ("a number of frames per second in (0, 1000]", lambda v: _passes(check_fps, v)),
        "background": ("3 numbers in [0, 1]", lambda v: list(meta_background(meta)) == v),
        "eps2d": ("a number in [0, 10] (pixels²)", lambda v: meta_eps2d(meta) == v),
        "scene_depth": ("a finite number > 0 (metres)", lambda v: _passes(check_positive, "scene_depth", v)),
    }
    for key, (want, ok) in checks.items():
        if meta.get(key) is not None and not ok(meta[key]):
            raise ValueError(f"{path}: \"{key}\" must be {want}, got {json.dumps(meta[key])[:80]}")


def _passes(check: Callable, *args) -> bool:
    try:
        check(*args)
    except ValueError:
        return False
    return True


def load_output_scene(folder: str | os.PathLike) -> tuple[DynamicGaussians, dict]:
    """The scene of an output folder of ``generate`` or ``fit``, read as untrusted input: ``scene.ply``,
    ``deformation.npz`` (checked against it) and ``meta.json`` (its fields checked, ``static`` agreeing with
    ``deformation.npz``).

    Returns:
        (the canonical Gaussians with their deformation and temporal support, on the CPU, an array that is one row
        for every Gaussian held once (stride 0, :func:`load_deformation`); ``meta.json``, {} if absent).

    Raises:
        FileNotFoundError: ``folder`` does not exist or has no ``scene.ply``.
        ValueError: ``folder`` is a file, FIFO or symlink loop (said as such); naming the file: a malformed or
            corrupt ``scene.ply`` (or one without Gaussians) or ``deformation.npz`` (:func:`load_deformation`), one
            not fitting the other, ``meta.json`` not a JSON
            object, with a bad field or a ``static`` the deformation contradicts; a file that is a folder, FIFO or
            dangling symlink; a deformation above the ``frames`` limit (LimitError).
    """
    path = check_input_folder(folder, "scene folder")  # says what is there instead: a file, a FIFO, a symlink loop
    ply = folder_file(path, SCENE_FILE)
    if ply is None:
        raise FileNotFoundError(f"scene folder {path} has no scene.ply (not an output folder of generate or fit)")
    meta_path = folder_file(path, META_FILE)
    meta = {} if meta_path is None else read_json(meta_path, META_FILE)
    if meta_path is not None:
        _check_meta(meta, meta_path)
    canonical = load_ply(ply)
    if canonical.num_gaussians == 0:
        raise ValueError(f"{ply}: holds no Gaussians")
    npz = folder_file(path, DEFORMATION_FILE)
    scene = DynamicGaussians(canonical)
    if npz is not None:
        arrays = load_deformation(npz, canonical.num_gaussians)
        try:
            scene = DynamicGaussians(canonical, **deformation_tensors(arrays))
        except ValueError as e:
            raise ValueError(f"{npz}: {e}") from None
    npz = path / DEFORMATION_FILE
    if meta.get("static") is False and scene.is_static:
        state = "holds no deformation" if npz.exists() else "is missing"
        raise ValueError(f"{npz}: {state}, but {meta_path} says the scene moves (\"static\": false)")
    if meta.get("static") is True and not scene.is_static:
        raise ValueError(f"{npz}: holds a deformation, but {meta_path} says the scene is static (\"static\": true)")
    return scene, meta


@dataclass
class SceneFolder:
    """An output folder of ``generate`` or ``fit``, loaded (:func:`load_scene_folder`).

    Attributes:
        scene: canonical Gaussians (M, float32, world frame, metres) with the deformation and temporal support of
            ``deformation.npz``, on the device given to :func:`load_scene_folder`.
        cameras: the folder's ``cameras.json`` (T cameras), on the CPU.
        meta: ``meta.json`` ({} if absent).
        field: the ``field.safetensors`` HexPlane field on the scene's device, or None.
    """

    path: Path
    scene: DynamicGaussians
    cameras: CameraPath
    meta: dict
    field: Any = None

    @property
    def deformation_source(self) -> str:
        """Where the deformation comes from: ``"field.safetensors"``, ``"deformation.npz"`` or ``"static"``."""
        if self.field is not None:
            return FIELD_FILE
        return DEFORMATION_FILE if self.scene.changes_with_time else "static"


def load_scene_folder(folder: str | os.PathLike, device: str | torch.device = "cpu", *,
                      load_field: Callable[..., Any] | None = None) -> SceneFolder:
    """Read an output folder of ``generate`` or ``fit`` as untrusted input: the scene (:func:`load_output_scene`) and
    field onto ``device``, ``cameras.json`` (:func:`~diff4splat.io.cameras.load_cameras_json`) on the CPU.

    Args:
        load_field: reader of ``field.safetensors`` (:func:`models.hexplane.load_field`, passed in because ``io``
            does not import ``models``), called as ``load_field(path, map_location=device)``; None leaves it unread.

    Raises:
        FileNotFoundError: ``folder`` does not exist, is not a folder, or lacks ``scene.ply`` or ``cameras.json``.
        ValueError: a malformed, corrupt or inconsistent file, named (:func:`load_output_scene`, ``cameras.json``,
            ``field.safetensors``).
    """
    path = Path(folder)
    scene, meta = load_output_scene(path)
    cameras_file = folder_file(path, CAMERAS_FILE)
    if cameras_file is None:
        raise FileNotFoundError(f"scene folder {path} has no cameras.json (not an output folder of generate or fit)")
    cameras = load_cameras_json(cameras_file)
    field_file = folder_file(path, FIELD_FILE) if load_field is not None else None
    field = None if field_file is None else load_field(field_file, map_location=device)
    return SceneFolder(path, scene.to(device), cameras, meta, field)
