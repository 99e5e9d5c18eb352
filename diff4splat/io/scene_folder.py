"""The output folder of ``diff4splat generate`` (docs/DESIGN.md, "Output folder of generate"), written atomically
(:func:`write_scene_folder`), and read back as input, every file checked (:func:`load_output_scene`)::

    scene.ply           canonical Gaussians, INRIA layout
    deformation.npz     times (T,), d_means (T,M,3), d_quats (T,M,4), d_scales (T,M,3) (absent if static),
                        t_means (M,), t_scales (M,) (4D temporal support, when present); no file if neither
    frames/0000.ply …   the Gaussians deformed to each frame's time
    rgb/0000.png …      the render along the camera path, 8-bit lossless
    video.mp4           RGB along the camera path
    depth/0000.exr …    float32 expected depth "Z" (metres) and coverage "A"
    cameras.json        Ks, viewmats, width, height, times
    viewer.html         the interactive 4D viewer, self-contained (diff4splat.viewer)
    meta.json           model, seed, steps, timings, counts, "static", "background", "eps2d", "fps"
    field.safetensors   (``fit`` only) the HexPlane field;  metrics.json (``fit`` only)

A ``render`` output holds rgb/, video.mp4, depth/, cameras.json, viewer.html and meta.json of the same layout
(:func:`is_layout_file` names every file of it).
"""
from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..cameras.path import CameraPath
from ..checks import check_positive
from ..constants import ALPHA_MIN
from ..limits import check_limit
from ..render.defaults import meta_background, meta_eps2d
from ..scene import DynamicGaussians
from ..viewer.page import VIEWER_NAME, write_viewer
from .atomic import atomic_output_path
from .cameras import save_cameras_json
from .exr import save_depth_exr
from .inputs import check_input_file
from .outdir import output_dir
from .ply import load_ply, save_ply
from .structured import read_json
from .video import check_fps, save_image, save_video, to_uint8

__all__ = ["write_scene_folder", "fill_empty_depth", "save_deformation", "load_deformation", "json_default",
           "load_output_scene", "folder_file", "DEFORMATION_ARRAYS", "is_layout_file", "LAYOUT_FILES", "LAYOUT_FRAMES"]

LAYOUT_FILES = ("scene.ply", "deformation.npz", "cameras.json", "meta.json", "video.mp4", VIEWER_NAME,
                "field.safetensors", "metrics.json")
"""The files at the top of an output folder of generate, fit or render (module docstring)."""
LAYOUT_FRAMES = {"frames": ".ply", "rgb": ".png", "depth": ".exr"}
"""The per-frame sub-folders of an output folder and the suffix of their files ``NNNN<suffix>`` (4+ digits)."""


def fill_empty_depth(depths: Tensor, alphas: Tensor, fallback: float) -> Tensor:
    """Give pixels without geometry the far distance of the scene, so every depth is finite and > 0.

    Empty pixels (alpha < :data:`~diff4splat.constants.ALPHA_MIN` = 1/255) get the largest depth rendered
    anywhere on the path (the scene's far bound along these views), or ``fallback`` metres if no pixel is
    covered; the "A" channel of the EXR keeps the coverage so users can mask them.

    Args:
        depths: (T, H, W) expected depth, metres (0 where empty).
        alphas: (T, H, W) coverage in [0, 1].
        fallback: metres > 0.

    Returns:
        (T, H, W) depth, metres, finite and > 0.
    """
    covered = alphas >= ALPHA_MIN
    far = float(depths[covered].max()) if bool(covered.any()) else float(fallback)
    return torch.where(covered & (depths > 0), depths, torch.full_like(depths, far))


_DEFORMATION_KEYS = ("times", "d_means", "d_quats", "d_scales")
_TEMPORAL_KEYS = ("t_means", "t_scales")
_SHAPES = {"times": ("K",), "d_means": ("K", "M", 3), "d_quats": ("K", "M", 4), "d_scales": ("K", "M", 3),
           "t_means": ("M",), "t_scales": ("M",)}
"""Shape of each array of ``deformation.npz``: K key times, M Gaussians."""
DEFORMATION_ARRAYS = tuple(_SHAPES)
"""The arrays ``deformation.npz`` may hold, the keyword arguments of ``DynamicGaussians`` after the canonical ones."""
_NPZ_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, zlib.error, NotImplementedError, RuntimeError,
               ValueError, KeyError, OSError)
"""What zipfile and numpy's header parser raise on a corrupt archive or member (not a zip file, a bad CRC, a
truncated member, an unsupported compression or encryption, a malformed ``.npy`` header)."""


def _zip_call(path: Path, what: str, fn: Callable, *args):
    """``fn(*args)``, its failures on a corrupt archive as one ``ValueError`` starting with ``path``."""
    try:
        return fn(*args)
    except _NPZ_ERRORS as e:
        raise ValueError(f"{path}: {what} ({' '.join(str(e).split()) or type(e).__name__})") from None


def save_deformation(path: str | os.PathLike, scene: DynamicGaussians) -> None:
    """Write ``deformation.npz``: float32 times, d_means, d_quats, d_scales when the scene deforms and
    t_means (M,), t_scales (M,) (clip time) when it has temporal support.

    Raises:
        ValueError: the scene has neither a deformation nor temporal support (nothing to write).
    """
    if scene.is_static and not scene.has_temporal:
        raise ValueError("a static scene without temporal support has no deformation to save")
    keys = (() if scene.is_static else _DEFORMATION_KEYS) + (_TEMPORAL_KEYS if scene.has_temporal else ())
    arrays = {k: getattr(scene, k).detach().cpu().float().numpy() for k in keys}
    with atomic_output_path(Path(path)) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def _npy_header(f) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, Fortran order, dtype) from the header of the ``.npy`` file ``f`` (format 1.0 or 2.0)."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(f)
    raise ValueError(f".npy format version {version}, expected 1.0 or 2.0")


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, dims: dict[str, int]) -> np.ndarray:
    """One array of ``deformation.npz`` as float32: its header checked (a real floating-point dtype, the shape of
    :data:`_SHAPES` with the sizes in ``dims``, where K and M are bound on first sight) before its data is read."""
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
        data = _zip_call(path, corrupt, f.read, size)
    if len(data) != size:
        raise ValueError(f"{path}: '{key}' is truncated ({len(data)} of {size} bytes)")
    return np.frombuffer(data, dtype=dtype).reshape(shape, order="F" if fortran else "C").astype(np.float32)


def load_deformation(path: str | os.PathLike, num_gaussians: int | None = None) -> dict[str, np.ndarray]:
    """Read ``deformation.npz`` → float32 numpy arrays {"times", "d_means", "d_quats", "d_scales"} and/or
    {"t_means", "t_scales"}, whichever the file holds (keyword arguments of ``DynamicGaussians``).

    The archive is read with :mod:`zipfile` and numpy's ``.npy`` header parser, never unpickling anything; each
    array's dtype and shape are checked from its header before its data is read.

    Args:
        path: the file.
        num_gaussians: M, the Gaussian count of the scene the file belongs to (``scene.ply``), or None to take
            it from the file.

    Raises:
        FileNotFoundError / ValueError: ``path`` is missing or not a regular file
            (:func:`diff4splat.io.inputs.check_input_file`).
        ValueError: every message starts with ``path``: not a zip archive (random bytes, a truncated file), a
            corrupt member, an entry that is not one of the six arrays above, a partial set of either group, an
            array that is not floating-point (pickled objects included) or of another shape than
            times (K,), d_means (K, M, 3), d_quats (K, M, 4), d_scales (K, M, 3), t_means (M,), t_scales (M,)
            (one K, M = ``num_gaussians``); K above the ``frames`` limit
            (:class:`~diff4splat.limits.LimitError`). Values (finite, times increasing) are checked by
            ``DynamicGaussians``.
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
    fps: int = 8,
    depth_fallback: float = 1.0,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
    kind: str = "generate",
    extra: Callable[[Path], None] | None = None,
) -> Path:
    """Write the whole output folder into a temporary folder, then rename it onto ``out_dir``
    (:func:`~diff4splat.io.outdir.output_dir`, marker kind ``kind``: "generate", or "fit" for
    ``diff4splat fit``, whose ``extra`` writes field.safetensors and metrics.json).

    ``extra(tmp)`` is called with the temporary folder after the standard files, to add files of its own.

    A failure part-way leaves no ``out_dir`` (or the previous one untouched). An existing ``out_dir`` is
    replaced only if it is empty or an earlier ``generate`` output (or ``overwrite``), never if it holds
    one of ``inputs``.

    Raises:
        ValueError: frame counts of colours/depths/alphas/cameras differ.
        OutputDirError: ``out_dir`` may not be written (a file, holds inputs, not an output, …).
    """
    T = len(cameras)
    if not (colors.shape[0] == depths.shape[0] == alphas.shape[0] == T):
        raise ValueError(f"colors/depths/alphas must have {T} frames (one per camera), got "
                         f"{colors.shape[0]}/{depths.shape[0]}/{alphas.shape[0]}")
    depths = fill_empty_depth(depths, alphas, depth_fallback)
    rgb = to_uint8(colors.cpu(), "colors")  # (T, H, W, 3): rgb/*.png lossless beside the lossy video
    with output_dir(out_dir, kind=kind, inputs=inputs, overwrite=overwrite, parents=True) as tmp:
        save_ply(tmp / "scene.ply", scene.canonical)
        if not scene.is_static or scene.has_temporal:
            save_deformation(tmp / "deformation.npz", scene)
        for i in range(T):
            save_ply(tmp / "frames" / f"{i:04d}.ply", scene.at(float(cameras.times[i])))
            save_depth_exr(tmp / "depth" / f"{i:04d}.exr", depths[i].cpu(), alphas[i].clamp(0, 1).cpu())
            save_image(tmp / "rgb" / f"{i:04d}.png", rgb[i])
        save_video(tmp / "video.mp4", rgb, fps=fps)
        save_cameras_json(tmp / "cameras.json", cameras.to("cpu"))
        write_viewer(tmp / VIEWER_NAME, scene, cameras.to("cpu"), fps=fps, background=meta_background(meta),
                     eps2d=meta_eps2d(meta))
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, default=json_default))
        if extra is not None:
            extra(tmp)
    return Path(out_dir)


def json_default(obj):
    """``json.dumps`` ``default=``: numpy scalars → Python numbers, paths → strings."""
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def is_layout_file(name: str) -> bool:
    """True when ``name``, a ``/``-separated path relative to an output folder, is a file of the output-folder layout
    (:data:`LAYOUT_FILES`, or ``frames/NNNN.ply``, ``rgb/NNNN.png``, ``depth/NNNN.exr`` with 4 or more ASCII
    digits); any other name (``..``, a backslash, a percent sign, a leading ``/``, …) is not."""
    folder, _, file = name.rpartition("/")
    if not folder:
        return name in LAYOUT_FILES
    suffix = LAYOUT_FRAMES.get(folder)
    stem = file[:-len(suffix)] if suffix is not None and file.endswith(suffix) else ""
    return len(stem) >= 4 and stem.isascii() and stem.isdigit()


def folder_file(folder: str | os.PathLike, name: str) -> Path | None:
    """``folder / name`` if something is there, None if nothing is.

    Raises:
        FileNotFoundError / ValueError: something is there but it is not a regular file (a folder, a FIFO, a
            dangling symlink, …; :func:`diff4splat.io.inputs.check_input_file`), naming it: reading a FIFO would
            block forever.
    """
    path = Path(folder) / name
    if not path.exists() and not path.is_symlink():
        return None
    return check_input_file(path, "scene folder")


def _check_meta(meta: dict, path: Path) -> None:
    """The fields of ``meta.json`` that the readers use, where present and not null: ``static`` (a boolean),
    ``fps`` (:func:`~diff4splat.io.video.check_fps`), ``background`` (:func:`meta_background` takes it as given),
    ``eps2d`` (:func:`meta_eps2d` takes it as given), ``scene_depth`` (a finite number > 0)."""
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
    """The scene of an output folder of ``generate`` or ``fit`` (module docstring), read as untrusted input:
    ``scene.ply`` (:func:`~diff4splat.io.ply.load_ply`), ``deformation.npz`` (:func:`load_deformation`, checked
    against ``scene.ply``) and ``meta.json`` (a JSON object whose ``static``, ``fps``, ``background``, ``eps2d`` and
    ``scene_depth``, where present and not null, are valid; its ``static`` must agree with ``deformation.npz``).
    The camera path and a fit's field are the caller's (:func:`diff4splat.rerender.load_scene_folder`).

    Returns:
        (canonical Gaussians with the deformation and temporal support of ``deformation.npz``, on the CPU;
        ``meta.json`` as a dict, {} if absent).

    Raises:
        FileNotFoundError: ``folder`` does not exist, is not a folder, or has no ``scene.ply`` (each named).
        ValueError: naming the file, its path first (``meta.json``'s JSON errors as
            :func:`~diff4splat.io.structured.read_json`: ``meta.json: <path> …``): a malformed or corrupt
            ``scene.ply`` or ``deformation.npz`` (truncated, random bytes, wrong keys, shapes or dtypes, NaN/inf),
            a ``scene.ply`` without Gaussians, ``deformation.npz`` not fitting ``scene.ply``, ``deformation.npz``
            missing (or holding no deformation) while ``meta.json`` says ``"static": false`` or holding one while it
            says ``true``, ``meta.json`` not a JSON object or with a bad field; a file of the folder that is a
            folder, a FIFO or a dangling symlink; a deformation above the ``frames`` limit
            (:class:`~diff4splat.limits.LimitError`).
    """
    path = Path(folder)
    if not path.exists():
        raise FileNotFoundError(f"scene folder {path} does not exist")
    if not path.is_dir():
        raise FileNotFoundError(f"scene folder {path} is not a folder (give an output folder of generate or fit)")
    ply = folder_file(path, "scene.ply")
    if ply is None:
        raise FileNotFoundError(f"scene folder {path} has no scene.ply (not an output folder of generate or fit)")
    meta_path = folder_file(path, "meta.json")
    meta = {} if meta_path is None else read_json(meta_path, "meta.json")
    if meta_path is not None:
        _check_meta(meta, meta_path)
    canonical = load_ply(ply)
    if canonical.num_gaussians == 0:
        raise ValueError(f"{ply}: holds no Gaussians")
    npz = folder_file(path, "deformation.npz")
    scene = DynamicGaussians(canonical)
    if npz is not None:
        arrays = load_deformation(npz, canonical.num_gaussians)
        try:
            scene = DynamicGaussians(canonical, **{k: torch.from_numpy(v) for k, v in arrays.items()})
        except ValueError as e:
            raise ValueError(f"{npz}: {e}") from None
    npz = path / "deformation.npz"
    if meta.get("static") is False and scene.is_static:
        state = "holds no deformation" if npz.exists() else "is missing"
        raise ValueError(f"{npz}: {state}, but {meta_path} says the scene moves (\"static\": false)")
    if meta.get("static") is True and not scene.is_static:
        raise ValueError(f"{npz}: holds a deformation, but {meta_path} says the scene is static (\"static\": true)")
    return scene, meta
