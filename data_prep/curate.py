"""Curation (``data_prep curate IN OUT``): per-scene :class:`SceneStats` judged by a :class:`CurationConfig`.

:func:`curate` writes into ``OUT`` ``manifest.jsonl`` (one ``{"scene", "accepted", "reasons", "messages", "stats"}``
per scene, sorted; ``reasons``: the violated config fields, or ``"error"``), ``accepted.txt``, ``curation.yaml``
(config and mode) and each accepted scene by ``mode`` (an absolute symlink, a copy, or none), so ``OUT`` is a
dataset root. Each scene's record ``OUT/.curation/<scene>.json`` is written atomically after its folder, so a rerun
resumes (docs/DESIGN.md, "Data preparation at scale"). One run at a time per ``OUT``.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import sys
import uuid
from dataclasses import asdict, dataclass, fields
from functools import partial
from pathlib import Path
from typing import Any

import kornia
import numpy as np
import torch
import yaml
from tqdm import tqdm

from diff4splat.cameras import camera_centers
from diff4splat.io import atomic_output_path, check_output_dir, output_dir
from diff4splat.io.structured import read_yaml
from diff4splat.utils.checks import check_int
from diff4splat.utils.config_files import CURATION_DEFAULT
from diff4splat.utils.errors import parse_naming
from diff4splat.utils.limits import check_disk

from .engine import Engine, engine_session, map_scenes
from .format import SCENE_KIND, SceneReader, list_scenes
from .validate import validate_scene

__all__ = ["DEFAULT_CONFIG_PATH", "MODES", "CurationConfig", "SceneStats", "laplacian_variance", "scene_statistics",
           "judge", "curate_scene", "curate", "read_manifest"]

DEFAULT_CONFIG_PATH = CURATION_DEFAULT
"""The shipped YAML; it holds exactly the defaults of :class:`CurationConfig`."""
MODES: tuple[str, ...] = ("symlink", "copy", "none")
"""How accepted scenes appear in ``OUT`` (see the module docstring)."""

MANIFEST, ACCEPTED, CONFIG_COPY, RECORDS = "manifest.jsonl", "accepted.txt", "curation.yaml", ".curation"


@dataclass(frozen=True)
class CurationConfig:
    """Filter thresholds (the defaults; ``curation_default.yaml`` mirrors them). ``min_*``/``max_*`` bound the
    :class:`SceneStats` of the same name (``max_*`` None: no bound; ratios in [0, 1]); ``require_depth`` and
    ``dynamic_requires_tracks`` reject scenes without depth / dynamic scenes without tracks;
    ``dynamic_motion_threshold_m``: metres from its frame-0 position beyond which a track moves; ``sample_frames`` (≥
    1): evenly spaced frames per camera read for sharpness and valid depth; ``validate``: also run
    :func:`data_prep.validate.validate_scene` (reason ``"validate"``). Raises ValueError naming the field, for a wrong
    type or an out-of-range value."""

    min_frames: int = 17
    min_translation_m: float = 0.05
    max_translation_m: float | None = None
    min_rotation_deg: float = 0.0
    max_rotation_deg: float | None = None
    require_depth: bool = False
    min_valid_depth_ratio: float = 0.3
    dynamic_motion_threshold_m: float = 0.05
    dynamic_requires_tracks: bool = True
    min_dynamic_ratio: float = 0.01
    max_dynamic_ratio: float | None = None
    min_sharpness: float = 20.0
    sample_frames: int = 3
    validate: bool = False

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            kind = f.type if isinstance(f.type, str) else str(f.type)
            if kind == "bool":
                ok = isinstance(v, bool)
            elif kind == "int":
                ok = isinstance(v, int) and not isinstance(v, bool) and v >= 1
            else:
                ok = (v is None and "None" in kind) or (
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0)
            if not ok:
                raise ValueError(f"curation config field {f.name!r} must be {kind.replace('|', 'or')}"
                                 f"{' ≥ 1' if kind == 'int' else ' ≥ 0' if kind != 'bool' else ''}, got {v!r}")
        for name in ("min_valid_depth_ratio", "min_dynamic_ratio", "max_dynamic_ratio"):
            v = getattr(self, name)
            if v is not None and v > 1:
                raise ValueError(f"curation config field {name!r} is a ratio in [0, 1], got {v!r}")
        for lo, hi in (("min_translation_m", "max_translation_m"), ("min_rotation_deg", "max_rotation_deg"),
                       ("min_dynamic_ratio", "max_dynamic_ratio")):
            if getattr(self, hi) is not None and getattr(self, lo) > getattr(self, hi):  # would reject every scene
                raise ValueError(f"curation config fields {lo!r} ({getattr(self, lo)!r}) and {hi!r} "
                                 f"({getattr(self, hi)!r}) leave no range: {lo} must be ≤ {hi}")

    @classmethod
    def from_dict(cls, data: Any) -> CurationConfig:
        """Build from a mapping; missing keys take the defaults. Raises ValueError: not a mapping, an unknown key or
        a bad value."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ValueError(f"curation config must be a mapping of field: value, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown curation config field(s) {unknown}; known: {sorted(known)}")
        return cls(**data)

    @classmethod
    def from_yaml(cls, path: str | os.PathLike) -> CurationConfig:
        """Read a YAML mapping. Raises FileNotFoundError, or ValueError (bad YAML or fields) naming ``path``."""
        return parse_naming(path, cls.from_dict, read_yaml(path, "curation config", expect=None))

    def to_dict(self) -> dict[str, Any]:
        """Field: value mapping (YAML/JSON-serialisable)."""
        return asdict(self)


@dataclass(frozen=True)
class SceneStats:
    """What curation measures of one scene.

    Attributes:
        translation_range_m: max distance, metres, of any camera centre (every camera, every frame) from the
            reference camera's centre at frame 0.
        rotation_range_deg: max angle arccos((tr(R·R₀ᵀ) − 1)/2), degrees in [0, 180], of any camera relative to
            the reference camera at frame 0.
        valid_depth_ratio: fraction of sampled pixels with finite depth > 0; None without depth.
        dynamic_ratio: fraction of visible track observations whose track moves (max_i ‖X_p(i) − X_p(0)‖ >
            ``dynamic_motion_threshold_m``); None without tracks.
        sharpness: median :func:`laplacian_variance` of the sampled frames.
    """

    num_frames: int
    num_cameras: int
    dynamic: bool
    translation_range_m: float
    rotation_range_deg: float
    valid_depth_ratio: float | None
    dynamic_ratio: float | None
    sharpness: float


def laplacian_variance(rgb: np.ndarray) -> float:
    """Sharpness of an (H, W, 3) float image in [0, 1]: the population variance, (8-bit grey units)² ≥ 0, of its
    Laplacian (Pech-Pacheco et al., ICPR 2000; kornia's ITU-R 601 grey and unnormalised 3×3 Laplacian)."""
    x = torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).permute(2, 0, 1)[None] * 255.0
    lap = kornia.filters.laplacian(kornia.color.rgb_to_grayscale(x), kernel_size=3, normalized=False)
    return float(lap.double().var(unbiased=False))


def scene_statistics(scene: SceneReader, config: CurationConfig) -> SceneStats:
    """Measure one scene (reads cameras, tracks and ``config.sample_frames`` frames per camera). Raises ValueError,
    FileNotFoundError or OSError: an unreadable file of the scene."""
    T, names = scene.num_frames, scene.camera_names
    ref = scene.cameras(names[0]).viewmats[0].double().cpu().numpy()
    trans, rot = 0.0, 0.0
    for name in names:
        vm = scene.cameras(name).viewmats.double().cpu().numpy()  # (T, 4, 4) world-to-camera
        centres = camera_centers(torch.from_numpy(vm)).numpy()  # −Rᵀt
        ref_centre = camera_centers(torch.from_numpy(ref)).numpy()
        trans = max(trans, float(np.linalg.norm(centres - ref_centre, axis=-1).max()))
        cos = (np.einsum("tij,ij->t", vm[:, :3, :3], ref[:3, :3]) - 1.0) / 2.0  # tr(R Rref^T)
        rot = max(rot, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max()))

    frames = sorted({int(round(x)) for x in np.linspace(0, T - 1, min(config.sample_frames, T))})  # first and last
    sharp, valid, total = [], 0, 0
    for name in names:
        for i in frames:
            sharp.append(laplacian_variance(scene.rgb(name, i)))
            if scene.has_depth:
                d = scene.depth(name, i)
                valid += int((np.isfinite(d) & (d > 0)).sum())
                total += d.size

    dyn_ratio = None
    tracks = scene.tracks()
    if tracks is not None:
        pts, vis = tracks
        moving = np.linalg.norm(pts - pts[:, :1], axis=-1).max(axis=1) > config.dynamic_motion_threshold_m  # (P,)
        seen = int(vis.sum())
        dyn_ratio = float((vis & moving[:, None]).sum() / seen) if seen else 0.0
    return SceneStats(
        num_frames=T, num_cameras=len(names), dynamic=scene.meta.dynamic, translation_range_m=trans,
        rotation_range_deg=rot, valid_depth_ratio=(valid / total) if scene.has_depth else None,
        dynamic_ratio=dyn_ratio, sharpness=float(np.median(sharp)),
    )


def judge(stats: SceneStats, config: CurationConfig) -> list[tuple[str, str]]:
    """The filters a scene fails: ``[(config field name, message), …]`` (empty = accepted). Equal passes; None
    statistics are judged only by ``require_*``; the dynamic ratio only for dynamic scenes."""
    c, out = config, []

    def bounds(value: float, lo: str, hi: str | None, what: str, unit: str) -> None:
        if value < getattr(c, lo):
            out.append((lo, f"{what} {value:.4g}{unit} < {lo} {getattr(c, lo)}{unit}"))
        if hi is not None and getattr(c, hi) is not None and value > getattr(c, hi):
            out.append((hi, f"{what} {value:.4g}{unit} > {hi} {getattr(c, hi)}{unit}"))

    bounds(stats.num_frames, "min_frames", None, "frames", "")
    bounds(stats.translation_range_m, "min_translation_m", "max_translation_m", "translation range", " m")
    bounds(stats.rotation_range_deg, "min_rotation_deg", "max_rotation_deg", "rotation range", "°")
    if stats.valid_depth_ratio is None:
        if c.require_depth:
            out.append(("require_depth", "no depth (depth_source 'none')"))
    else:
        bounds(stats.valid_depth_ratio, "min_valid_depth_ratio", None, "valid-depth ratio", "")
    if stats.dynamic:
        if stats.dynamic_ratio is None:
            if c.dynamic_requires_tracks:
                out.append(("dynamic_requires_tracks", "dynamic scene without tracks.npz"))
        else:
            bounds(stats.dynamic_ratio, "min_dynamic_ratio", "max_dynamic_ratio", "dynamic ratio", "")
    bounds(stats.sharpness, "min_sharpness", None, "sharpness", "")
    return out


def _place(src: Path, dst: Path, mode: str) -> None:
    """Make accepted scene ``src`` appear at ``dst`` atomically (skipped if ``dst`` already exists)."""
    if mode == "none" or dst.exists() or dst.is_symlink():
        return
    if mode == "symlink":
        tmp = dst.parent / f".{dst.name}.{uuid.uuid4().hex[:12]}.tmp"
        os.symlink(src.resolve(), tmp, target_is_directory=True)
        os.replace(tmp, dst)
    else:
        size = sum(f.stat().st_size for f in src.rglob("*") if f.is_file() and not f.name.startswith("."))
        check_disk(size, f"--mode copy of {src}", "--mode symlink", dst.parent)
        failures: list[OSError] = []

        def copy(a: str, b: str) -> None:
            try:
                shutil.copy2(a, b)
            except OSError as e:  # copytree keeps only the message; the first error is raised whole below
                failures.append(e)
                raise

        with output_dir(dst, kind=SCENE_KIND, replace=False, parents=True) as tmp:
            try:
                shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".*"), copy_function=copy)
            except shutil.Error as e:  # (src, dst, why) triples
                raise failures[0] if failures else ValueError(f"copying {src}: {e.args[0][0][2]}") from None


def curate_scene(src: str | os.PathLike, out_root: str | os.PathLike, config: CurationConfig,
                 mode: str = "symlink") -> dict[str, Any]:
    """Measure and judge one scene, place it in ``out_root`` if accepted, then write its record and return it.
    An unreadable scene is rejected with reason ``"error"`` (never raises for a bad scene)."""
    src, out_root = Path(src), Path(out_root)
    try:
        scene = SceneReader(src)
        failed = judge(stats := scene_statistics(scene, config), config)
        if config.validate:
            failed += [("validate", str(p)) for p in validate_scene(src)[:3]]
        stats_dict = asdict(stats)
    except (ValueError, FileNotFoundError, OSError) as e:
        failed, stats_dict = [("error", f"{type(e).__name__}: {e}")], {}
    record = {"scene": src.name, "accepted": not failed, "reasons": sorted({r for r, _ in failed}),
              "messages": [m for _, m in failed], "stats": stats_dict}
    if record["accepted"]:
        _place(src, out_root / src.name, mode)
    with atomic_output_path(out_root / RECORDS / f"{src.name}.json") as tmp:
        Path(tmp).write_text(json.dumps(record, sort_keys=True) + "\n", encoding="utf-8")
    return record


def _curate_task(src: Path, out_root: Path, config: CurationConfig, mode: str) -> None:
    """The engine's task: curate ``src`` unless an earlier attempt wrote its record."""
    if not (out_root / RECORDS / f"{src.name}.json").is_file():
        curate_scene(src, out_root, config, mode)


def _remove_leftovers(out_root: Path) -> None:
    """Delete the temporary files/folders a killed run left (hidden ``*.tmp*`` / ``*.old`` names)."""
    for folder in (out_root, out_root / RECORDS):
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if p.name.startswith(".") and (p.name.endswith((".tmp", ".old")) or ".tmp." in p.name):
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)


def read_manifest(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The records of a ``manifest.jsonl`` (or of an ``OUT`` folder holding one), in file order. Raises
    FileNotFoundError: no manifest; ValueError: a line that is not a JSON object (line number named)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    out = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}:{n}: not JSON: {e}") from None
        if not isinstance(rec, dict) or "scene" not in rec:
            raise ValueError(f"{path}:{n}: a record must be an object with 'scene'")
        out.append(rec)
    return out


def _finalize(out_root: Path) -> list[dict[str, Any]]:
    """Rebuild manifest.jsonl and accepted.txt atomically from the per-scene records (sorted by scene)."""
    records = []
    for f in sorted((out_root / RECORDS).glob("*.json")):
        if not f.name.startswith("."):
            records.append(json.loads(f.read_text(encoding="utf-8")))
    records.sort(key=lambda r: r["scene"])
    with atomic_output_path(out_root / MANIFEST) as tmp:
        Path(tmp).write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in records), encoding="utf-8")
    with atomic_output_path(out_root / ACCEPTED) as tmp:
        Path(tmp).write_text("".join(r["scene"] + "\n" for r in records if r["accepted"]), encoding="utf-8")
    return records


def _check_out_root(in_root: Path, out_root: Path) -> None:
    """Refuse an ``out_root`` that is not new, empty or an earlier curation, that is, holds or lies inside the input,
    or that the output-folder policy protects."""
    check_output_dir(out_root, inputs=[in_root], overwrite=True, kind="curation", parents=True)
    if in_root.resolve() in out_root.resolve().parents:
        raise ValueError(f"the output folder {out_root} is inside the input {in_root}: the curation would become "
                         "part of the dataset; choose a folder outside it")
    if out_root.is_dir() and not (out_root / CONFIG_COPY).is_file() and next(out_root.iterdir(), None) is not None:
        raise ValueError(f"the output folder {out_root} holds other files (no {CONFIG_COPY}): a curation goes to a "
                         "new or empty folder or continues an earlier one; choose another folder")


def curate(in_root: str | os.PathLike, out_root: str | os.PathLike, config: CurationConfig | None = None, *,
           workers: int = 1, mode: str = "symlink", progress: bool = True,
           engine: Engine | None = None) -> list[dict[str, Any]]:
    """Curate every scene of the dataset root ``in_root`` into ``out_root`` (resumable; see the module docstring).
    ``config`` None: the defaults; ``engine`` None: the local pool of ``workers`` (≥ 1) processes (results depend on
    neither); ``mode``: one of :data:`MODES`; ``progress``: a tqdm bar on stderr. Returns all manifest records (earlier
    runs' too), sorted by scene. Raises FileNotFoundError: ``in_root`` is not a folder; ValueError: bad
    ``workers``/``mode``; an ``in_root`` without scenes; an ``out_root`` that is ``in_root``, holds it or lies inside
    it, holds other files than an earlier curation, or was curated before with a different config or mode."""
    config = config or CurationConfig()
    in_root, out_root = Path(in_root), Path(out_root)
    workers = check_int("workers", workers, 1)
    engine = engine or Engine(workers=workers)
    if mode not in MODES:
        raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
    scenes = list_scenes(in_root)
    if not scenes:
        raise ValueError(f"{in_root} holds no scenes (a scene is a sub-folder with meta.json): nothing to curate")
    _check_out_root(in_root, out_root)
    settings = {"mode": mode, "config": config.to_dict()}
    cfg_file = out_root / CONFIG_COPY
    if cfg_file.is_file():
        previous = read_yaml(cfg_file, "curation config", expect=None)
        if previous != settings:
            raise ValueError(f"{out_root} was curated with a different config or mode ({cfg_file}); "
                             "use a new output folder or delete it")
    with engine_session(engine):  # a Ray that cannot be reached is refused here, before OUT is written
        (out_root / RECORDS).mkdir(parents=True, exist_ok=True)
        _remove_leftovers(out_root)
        if not cfg_file.is_file():
            with atomic_output_path(cfg_file) as tmp:
                Path(tmp).write_text(yaml.safe_dump(settings, sort_keys=False), encoding="utf-8")
        done = {f.stem for f in (out_root / RECORDS).glob("*.json") if not f.name.startswith(".")}
        todo = [s for s in scenes if s.name not in done]
        bar = tqdm(total=len(scenes), initial=len(scenes) - len(todo), desc="curate", unit="scene",
                   disable=not progress or engine.name != "local", file=sys.stderr)
        try:
            map_scenes(partial(_curate_task, out_root=out_root, config=config, mode=mode), todo, engine,
                       progress=progress, bar=bar)
        finally:
            bar.close()
            records = _finalize(out_root)
    return records
