"""Curation: per-scene statistics, threshold filters, a resumable manifest and the accepted scenes.

``data_prep curate IN OUT [--config filters.yaml] [--workers K] [--mode symlink|copy|none]``
(:mod:`data_prep.cli`) calls :func:`curate`.

For every scene of the dataset root ``IN`` (:func:`data_prep.format.list_scenes`) it computes
:class:`SceneStats`, judges them against the thresholds of a :class:`CurationConfig` (YAML; the
shipped defaults are ``configs/data_prep/curation_default.yaml``) and writes into ``OUT``:

``OUT/manifest.jsonl``
    one JSON object per scene, sorted by scene id: ``{"scene", "accepted", "reasons", "messages",
    "stats"}``. ``reasons`` lists the names of the violated config fields (e.g. ``"min_frames"``),
    or ``"error"`` for a scene that could not be read; ``messages`` says the same in words.
``OUT/accepted.txt``
    the accepted scene ids, one per line, sorted.
``OUT/curation.yaml``
    the config of the run (a rerun with a different config is refused).
``OUT/<scene>``
    each accepted scene, by ``mode``: ``"symlink"`` (default; an absolute symbolic link to the
    source folder: instant and no extra space, but ``IN`` must stay where it is), ``"copy"`` (a full
    copy: a self-contained dataset root) or ``"none"`` (no scene folders, only the lists).
    ``OUT`` is then itself a dataset root readable by :class:`data_prep.clips.ClipDataset`.

Resumability and atomicity: each scene's record is written to ``OUT/.curation/<scene>.json``
(temporary file + rename) after its output folder or link is in place (temporary folder or link +
rename), so a killed run leaves whole scenes and whole records only. A rerun skips the scenes that
have a record, removes the temporary leftovers of a killed run, and rebuilds ``manifest.jsonl`` and
``accepted.txt`` (atomically) from all records: an interrupted run followed by a rerun gives the same
files as one uninterrupted run. Only one curation run may write to an ``OUT`` at a time.
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

from .engine import Engine, map_scenes
from .format import SCENE_KIND, SceneReader, list_scenes
from .validate import validate_scene

__all__ = [
    "DEFAULT_CONFIG_PATH",
    "MODES",
    "CurationConfig",
    "SceneStats",
    "laplacian_variance",
    "scene_statistics",
    "judge",
    "curate_scene",
    "curate",
    "read_manifest",
]

DEFAULT_CONFIG_PATH = CURATION_DEFAULT
"""The shipped YAML; it holds exactly the defaults of :class:`CurationConfig` (a test checks this)."""

MODES: tuple[str, ...] = ("symlink", "copy", "none")
"""How accepted scenes appear in ``OUT`` (see the module docstring)."""

MANIFEST, ACCEPTED, CONFIG_COPY, RECORDS = "manifest.jsonl", "accepted.txt", "curation.yaml", ".curation"


@dataclass(frozen=True)
class CurationConfig:
    """Filter thresholds (the single source of defaults; ``curation_default.yaml`` mirrors them).

    A ``max_*`` field set to ``None`` (YAML ``null``) disables that bound.

    Attributes:
        min_frames: reject scenes with fewer frames T per camera (a clip of T = 1 + 4k frames at
            stride s needs (T − 1)·s + 1 frames).
        min_translation_m, max_translation_m: bounds on the translation range, metres.
        min_rotation_deg, max_rotation_deg: bounds on the rotation range, degrees.
        require_depth: reject scenes without depth (``depth_source == "none"``).
        min_valid_depth_ratio: reject scenes with depth whose valid-depth ratio is lower, in [0, 1].
        dynamic_motion_threshold_m: a track "moves" when it gets farther than this from its
            frame-0 position, metres.
        dynamic_requires_tracks: reject dynamic scenes without ``tracks.npz`` (their motion is unknown).
        min_dynamic_ratio, max_dynamic_ratio: bounds on the dynamic ratio of dynamic scenes, in [0, 1]
            (static scenes are not judged on it).
        min_sharpness: reject scenes whose sharpness (variance of the Laplacian, 8-bit grey units) is lower.
        sample_frames: frames per camera read for sharpness and valid depth, evenly spaced, ≥ 1.
        validate: also run the full format validator (:func:`data_prep.validate.validate_scene`,
            decodes every file; slow) and reject invalid scenes (reason ``"validate"``).

    Raises:
        ValueError: naming the field, for a wrong type or an out-of-range value.
    """

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
        """Build from a mapping; unknown keys are errors, missing keys take the defaults.

        Raises:
            ValueError: not a mapping, an unknown key (named), or a bad value (see the class).
        """
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
        """Read a YAML mapping (see ``curation_default.yaml``).

        Raises:
            FileNotFoundError: ``path`` does not exist. ValueError: bad YAML or fields (prefixed with the path).
        """
        data = read_yaml(path, "curation config", expect=None)
        try:
            return cls.from_dict(data)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{path}: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        """Field: value mapping (YAML/JSON-serialisable)."""
        return asdict(self)


@dataclass(frozen=True)
class SceneStats:
    """What curation measures of one scene (``None``: not measurable, e.g. no depth or no tracks).

    Attributes:
        num_frames: T, frames per camera.
        num_cameras: synchronised cameras.
        dynamic: ``meta["dynamic"]``.
        translation_range_m: max distance, metres, of any camera centre (every camera, every frame)
            from the reference camera's centre at frame 0 — camera motion and multi-view baseline.
        rotation_range_deg: max rotation angle, degrees in [0, 180], of any camera relative to the
            reference camera at frame 0: arccos((tr(R·R₀ᵀ) − 1)/2).
        valid_depth_ratio: fraction in [0, 1] of pixels with finite depth > 0 over the sampled
            frames of every camera; ``None`` without depth.
        dynamic_ratio: fraction in [0, 1] of visible track observations (p, i) whose track p moves
            (max_i ‖X_p(i) − X_p(0)‖ > ``dynamic_motion_threshold_m``); ``None`` without tracks.
        sharpness: median over the sampled frames of every camera of :func:`laplacian_variance`.
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
    """Sharpness of an image: variance of its Laplacian (Pech-Pacheco et al., ICPR 2000).

    The image is converted to grey (``kornia.color.rgb_to_grayscale``, ITU-R 601 weights) in 8-bit
    units (0…255) and filtered with ``kornia.filters.laplacian`` (3×3 kernel of ones with −8 at the
    centre, not normalised, reflected border); the result is the population variance over pixels.
    Blur lowers it (a constant image gives 0). It grows with texture and depends on resolution.

    Args:
        rgb: (H, W, 3) float in [0, 1].

    Returns:
        variance, (8-bit grey units)², ≥ 0.
    """
    x = torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).permute(2, 0, 1)[None] * 255.0
    lap = kornia.filters.laplacian(kornia.color.rgb_to_grayscale(x), kernel_size=3, normalized=False)
    return float(lap.double().var(unbiased=False))


def _sample_indices(num_frames: int, k: int) -> list[int]:
    """k evenly spaced frame indices in [0, T) including the first and the last (unique, sorted)."""
    return sorted({int(round(x)) for x in np.linspace(0, num_frames - 1, min(k, num_frames))})


def scene_statistics(scene: SceneReader, config: CurationConfig) -> SceneStats:
    """Measure one scene (reads the cameras, tracks and ``config.sample_frames`` frames per camera).

    Raises:
        ValueError / FileNotFoundError / OSError: an unreadable file of the scene.
    """
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

    frames = _sample_indices(T, config.sample_frames)
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
    """The filters a scene fails: ``[(config field name, message), …]`` (empty = accepted).

    A scene is rejected by ``min_*`` when its statistic is below the threshold and by ``max_*`` when
    above (equal passes); ``None`` statistics are judged only by ``require_depth`` /
    ``dynamic_requires_tracks``; the dynamic ratio is judged for dynamic scenes only.
    """
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


def _write_json(path: Path, obj: Any) -> None:
    with atomic_output_path(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, sort_keys=True) + "\n", encoding="utf-8")


def _place(src: Path, dst: Path, mode: str) -> None:
    """Make accepted scene ``src`` appear at ``dst`` atomically (skipped if ``dst`` already exists)."""
    if mode == "none" or dst.exists() or dst.is_symlink():
        return
    if mode == "symlink":
        tmp = dst.parent / f".{dst.name}.{uuid.uuid4().hex[:12]}.tmp"
        os.symlink(src.resolve(), tmp, target_is_directory=True)
        os.replace(tmp, dst)
    else:
        with output_dir(dst, kind=SCENE_KIND, replace=False, parents=True) as tmp:
            shutil.copytree(src, tmp, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".*"))


def curate_scene(src: str | os.PathLike, out_root: str | os.PathLike, config: CurationConfig,
                 mode: str = "symlink") -> dict[str, Any]:
    """Measure and judge one scene, place it in ``out_root`` if accepted, then write its record.

    Order (for resumability): output folder/link first, record ``out_root/.curation/<scene>.json``
    last, each atomically. An unreadable scene is rejected with reason ``"error"`` (never raises for
    a bad scene).

    Returns:
        The manifest record ``{"scene", "accepted", "reasons", "messages", "stats"}``.
    """
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
    _write_json(out_root / RECORDS / f"{src.name}.json", record)
    return record


def _curate_task(src: Path, out_root: Path, config: CurationConfig, mode: str) -> None:
    """Curate scene ``src`` (the engine's task), unless a completed earlier attempt (a retried task, a resumed run)
    wrote its record already."""
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
    """The records of a ``manifest.jsonl`` (or of an ``OUT`` folder holding one), in file order.

    Raises:
        FileNotFoundError: no manifest. ValueError: a line that is not a JSON object (line number named).
    """
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
    """``out_root`` may receive a curation: new, empty or an earlier curation (its ``curation.yaml``); never the
    input, a folder holding it or inside it (the dataset would fail validation), a folder of other files (a user's
    ``manifest.jsonl`` was replaced) or the places the output-folder policy protects (diff4splat's packages, the
    current and home directories)."""
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
    """Curate every scene of ``in_root`` into ``out_root`` (resumable; see the module docstring).

    Args:
        in_root: dataset root (folder of scene folders).
        out_root: output folder (created); must not be ``in_root``.
        config: thresholds; ``None`` → :class:`CurationConfig` defaults.
        workers: processes (≥ 1); 1 runs in this process. Results do not depend on it.
        engine: where the scenes are curated (:func:`data_prep.engine.check_engine`); ``None``: the local pool of
            ``workers`` processes. Results do not depend on it either.
        mode: one of :data:`MODES`.
        progress: show a tqdm bar (on stderr).

    Returns:
        All manifest records (including those of earlier runs into ``out_root``), sorted by scene.

    Raises:
        FileNotFoundError: ``in_root`` is not a folder.
        ValueError: bad ``workers``/``mode``; an ``in_root`` without scenes; an ``out_root`` that is ``in_root``,
            holds it or lies inside it, holds other files than an earlier curation, or was curated before with a
            different config or mode.
    """
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
        map_scenes(partial(_curate_task, out_root=out_root, config=config, mode=mode), todo, engine, bar=bar)
    finally:
        bar.close()
        records = _finalize(out_root)
    return records
