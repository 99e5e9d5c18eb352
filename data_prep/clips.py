"""Training clips: a map-style ``torch.utils.data.Dataset`` over a dataset root (FORMAT.md). :class:`ClipDataset` cuts
each scene into windows starting at 0, window_step, 2·window_step, … wherever a clip at the minimum stride fits, so
``len()`` depends only on the scenes' lengths and the config (``DistributedSampler`` can split it). Item ``i`` of epoch
``e`` draws its stride, reference and target cameras and tracks from a generator seeded with ``(seed, e, i)``. A clip of
T = 1 + 4k frames holds source frames ``start + k·stride``, frame 0 of the reference camera; images are centre-cropped
and resized (:func:`diff4splat.io.preprocess_image`, intrinsics alike: :meth:`~diff4splat.cameras.CameraPath.fitted`)
and cameras re-expressed relative to frame 0 (:meth:`~diff4splat.cameras.CameraPath.relative_to_first`).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from diff4splat.cameras import CameraPath, center_crop_box, pack_plucker, plucker_rays, unproject_depth
from diff4splat.io import preprocess_image
from diff4splat.utils.checks import check_int

from .format import SceneMeta, SceneReader, list_scenes, timestamps_to_times
from .object_motion import id_boundaries, pixel_tracks
from .scene_files import META_FILE, NO_SURFACE

__all__ = ["ClipConfig", "ClipItem", "ClipSpec", "ClipDataset", "resize_nearest", "OCCLUSION_TOL_M",
           "OCCLUSION_TOL_REL"]

OCCLUSION_TOL_M, OCCLUSION_TOL_REL = 0.02, 0.02
"""Visibility depth test of FORMAT.md (tracks.npz): visible iff depth ≥ z − max(0.02 m, 0.02·z)."""

_CHOICES = {"scenes": ("all", "static", "dynamic"), "reference_camera": ("first", "random"),
            "target_cameras": ("same", "random"), "plucker": ("raw", "packed", "both")}


@dataclass(frozen=True)
class ClipConfig:
    """Clip sampling options (the defaults). Raises ValueError naming the field, for a wrong type or value.

    Attributes:
        num_frames: T = 1 + 4k frames per clip (the VAE's causal grouping).
        height, width: clip resolution, pixels; multiples of 8 when ``plucker`` includes ``"packed"``.
        scenes: ``"static"``, ``"dynamic"`` or ``"all"``, by ``meta["dynamic"]``.
        min_stride, max_stride: temporal stride range in source frames, 1 ≤ min ≤ max.
        window_step: source frames between window starts; None → :attr:`span` (non-overlapping windows).
        reference_camera: ``"first"`` (the scene's reference camera) or ``"random"`` (any camera).
        target_cameras: ``"same"`` (a monocular clip) or ``"random"`` (each target frame from any camera).
        num_tracks: N tracks per clip (sampled without replacement; padded when the scene has fewer).
        plucker: ``"raw"`` (T, H, W, 6), ``"packed"`` (:func:`~diff4splat.cameras.pack_plucker`) or ``"both"``.
    """

    num_frames: int = 17
    height: int = 64
    width: int = 64
    scenes: str = "all"
    min_stride: int = 1
    max_stride: int = 1
    window_step: int | None = None
    reference_camera: str = "random"
    target_cameras: str = "same"
    num_tracks: int = 256
    plucker: str = "raw"
    seed: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in _CHOICES:
                if v not in _CHOICES[f.name]:
                    raise ValueError(f"{f.name} must be one of {list(_CHOICES[f.name])}, got {v!r}")
            elif not (v is None and f.name == "window_step"):
                low = 0 if f.name in ("num_tracks", "seed") else 1
                check_int(f.name, v, low)
        if (self.num_frames - 1) % 4:
            raise ValueError(f"num_frames must be 1 + 4k (1, 5, 9, 13, 17, …), got {self.num_frames}")
        if self.max_stride < self.min_stride:
            raise ValueError(f"max_stride ({self.max_stride}) must be ≥ min_stride ({self.min_stride})")
        if self.plucker != "raw" and (self.height % 8 or self.width % 8):
            raise ValueError(
                f"packed Plücker rays need height and width multiples of 8, got {self.height}×{self.width}")

    @property
    def span(self) -> int:
        """Source frames covered by a clip at the minimum stride: (T − 1)·min_stride + 1."""
        return (self.num_frames - 1) * self.min_stride + 1


@dataclass(frozen=True)
class ClipItem:
    """One index entry: a window of ``scene`` (folder name) starting at source frame ``start``."""

    scene: str
    start: int


@dataclass(frozen=True)
class ClipSpec:
    """What item i samples in one epoch: source ``frames`` (T,), their ``cameras`` (T,), the stride."""

    scene: str
    start: int
    stride: int
    frames: tuple[int, ...]
    cameras: tuple[str, ...]


def resize_nearest(values: np.ndarray, height: int, width: int) -> np.ndarray:
    """Centre-crop (:func:`center_crop_box`) and resize an (h, w) map of values that must not blend (a depth map in
    metres with +inf invalid, an id map) to (height, width) like images, by ``cv2.INTER_NEAREST_EXACT``, so every
    value stays a source value; the dtype is kept."""
    y0, x0, ch, cw = center_crop_box(values.shape[0], values.shape[1], height, width)
    crop = np.ascontiguousarray(values[y0:y0 + ch, x0:x0 + cw])
    if (ch, cw) == (height, width):
        return crop
    return cv2.resize(crop, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)


class ClipDataset(Dataset):
    """Clips of T frames at (height, width) from a dataset root (see the module docstring); ``overrides`` replace
    fields of ``config`` (None: the defaults); ``scene_names`` (None: all) restricts the scenes.

    ``__getitem__(i)`` returns a dict (collates with the default ``collate_fn``); float32 unless said:

    - ``video`` (3, T, H, W) RGB in [0, 1], frame 0 the reference image; ``viewmats`` (T, 4, 4) world-to-camera,
      metres, clip world = the reference camera at frame 0 (viewmats[0] = I); ``Ks`` (T, 3, 3) pixels, fitted to
      the crop/resize; ``times`` (T,) in [0, 1] from the source timestamps;
    - ``plucker`` (T, H, W, 6) ``[o × d, d]`` in the clip world (``"raw"``), ``plucker_packed`` (6·4·64,
      1 + (T−1)/4, H/8, W/8) its :func:`pack_plucker` (``"packed"``);
    - ``depth`` (T, H, W) metric z-depth, metres, +inf invalid (nearest resize), ``depth_valid`` (T, H, W) bool;
    - ``tracks`` (N, T, 3) clip-world metres (0 pads), ``track_visibility`` (N, T) bool: in front of frame k's
      camera, inside the image, and the stored flag (reference camera) or FORMAT.md's occlusion test on the clip
      depth (other cameras; skipped without depth), ``track_mask`` (N,) bool: a real track;
    - ``pixel_tracks`` (T, H, W, 3) clip-world metres: where the surface point seen at each pixel of frame 0 is at
      each frame (dense 3D tracks: ``objects.npz``'s poses, FORMAT.md; a static scene's stay put),
      ``pixel_track_valid`` (H, W) bool: known (``objects.npz`` or a static scene), a surface, not on an object
      boundary (:func:`data_prep.object_motion.id_boundaries`);
    - ``caption`` str (``""`` without one, or when the reference camera is not the scene's first, whose view the
      caption describes: FORMAT.md), ``dynamic`` () bool, ``frame_indices`` (T,) int64 source frames,
      ``camera_indices`` (T,) int64 into ``meta["cameras"]``, ``scene`` str, ``index`` () int64.

    Raises FileNotFoundError: ``root`` is not a folder; ValueError: bad config/overrides, no scene folder in ``root``,
    unknown ``scene_names``, or no scene long enough for one clip.
    """

    def __init__(self, root: str | os.PathLike, config: ClipConfig | None = None, *,
                 scene_names: list[str] | None = None, **overrides: Any) -> None:
        self.root = Path(root)
        unknown = sorted(set(overrides) - {f.name for f in fields(ClipConfig)})
        if unknown:
            raise ValueError(f"unknown ClipConfig field(s) {unknown}")
        self.config = replace(config or ClipConfig(), **overrides)
        cfg = self.config
        scenes = list_scenes(self.root)
        if not scenes:
            raise ValueError(f"no scene in {self.root}: a dataset root holds scene folders, each with a meta.json "
                             "(data_prep synth or data_prep convert make them)")
        if scene_names is not None:
            unknown = sorted(set(scene_names) - {p.name for p in scenes})
            if unknown:
                raise ValueError(f"scene_names not found in {self.root}: {unknown[:5]}")
            scenes = [p for p in scenes if p.name in set(scene_names)]
        self.metas: dict[str, SceneMeta] = {}
        items: list[ClipItem] = []
        step = cfg.window_step or cfg.span
        for p in scenes:
            meta = SceneMeta.load(p / META_FILE)
            if cfg.scenes != "all" and meta.dynamic != (cfg.scenes == "dynamic"):
                continue
            self.metas[p.name] = meta
            items += [ClipItem(p.name, s) for s in range(0, meta.num_frames - cfg.span + 1, step)]
        if not items:
            which = "scenes" if cfg.scenes == "all" else f"{cfg.scenes} scenes"
            raise ValueError(f"no clip of {cfg.num_frames} frames at stride {cfg.min_stride} fits in the "
                             f"{which} of {self.root} ({len(self.metas)} scene(s))")
        self.items: list[ClipItem] = items
        self.epoch = 0
        self._readers: dict[str, SceneReader] = {}

    def __len__(self) -> int:
        return len(self.items)

    def set_epoch(self, epoch: int) -> None:
        """Select the per-epoch randomness (stride, cameras, tracks) of every item; ``epoch`` ≥ 0."""
        self.epoch = check_int("epoch", epoch, 0)

    def _rng(self, index: int, stream: int) -> np.random.Generator:
        """Generator of item ``index`` in this epoch; stream 0: stride and cameras, 1: tracks."""
        return np.random.default_rng((self.config.seed, self.epoch, index, stream))

    def _check_index(self, index: int) -> int:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not -len(self) <= index < len(self):
            raise IndexError(f"clip index must be an int in [0, {len(self)}), got {index!r}")
        return int(index) % len(self)

    def sample(self, index: int) -> ClipSpec:
        """The frames, cameras and stride that item ``index`` uses in the current epoch (deterministic)."""
        index = self._check_index(index)
        cfg, item = self.config, self.items[index]
        meta, T, rng = self.metas[item.scene], cfg.num_frames, self._rng(index, 0)
        fit = (meta.num_frames - 1 - item.start) // (T - 1) if T > 1 else cfg.max_stride
        stride = int(rng.integers(cfg.min_stride, min(cfg.max_stride, fit) + 1))
        cams = meta.cameras
        ref = cams[0] if cfg.reference_camera == "first" else cams[int(rng.integers(len(cams)))]
        targets = ([ref] * (T - 1) if cfg.target_cameras == "same"
                   else [cams[int(j)] for j in rng.integers(len(cams), size=T - 1)])
        frames = tuple(item.start + k * stride for k in range(T))
        return ClipSpec(item.scene, item.start, stride, frames, (ref, *targets))

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = self._check_index(index)
        cfg, spec = self.config, self.sample(index)
        if spec.scene not in self._readers:
            self._readers[spec.scene] = SceneReader(self.root / spec.scene)
        reader, H, W, T = self._readers[spec.scene], cfg.height, cfg.width, cfg.num_frames
        fitted = {c: reader.cameras(c).fitted(W, H).to(torch.float64) for c in set(spec.cameras)}
        vm = torch.stack([fitted[c].viewmats[f] for c, f in zip(spec.cameras, spec.frames, strict=True)])
        Ks = torch.stack([fitted[c].Ks[f] for c, f in zip(spec.cameras, spec.frames, strict=True)])
        times = torch.from_numpy(timestamps_to_times(reader.timestamps()[list(spec.frames)]))
        clip = CameraPath(vm, Ks, W, H, times).relative_to_first()
        world_to_ref = vm[0]  # source world → clip world

        video = torch.stack([preprocess_image(reader.rgb(c, f), (H, W))
                             for c, f in zip(spec.cameras, spec.frames, strict=True)])
        if reader.has_depth:
            depth = torch.from_numpy(np.stack([resize_nearest(reader.depth(c, f), H, W)
                                               for c, f in zip(spec.cameras, spec.frames, strict=True)]))
        else:
            depth = torch.full((T, H, W), float("inf"), device="cpu")  # items are CPU tensors (DataLoader)
        out: dict[str, Any] = {
            "video": video.permute(3, 0, 1, 2).contiguous(),
            "viewmats": clip.viewmats.float(),
            "Ks": clip.Ks.float(),
            "times": clip.times.float(),
            "depth": depth,
            "depth_valid": torch.isfinite(depth),
        }
        rays = plucker_rays(clip.viewmats, clip.Ks, W, H).float()
        if cfg.plucker in ("raw", "both"):
            out["plucker"] = rays
        if cfg.plucker in ("packed", "both"):
            out["plucker_packed"] = pack_plucker(rays[None])[0]
        out.update(self._tracks(reader, spec, clip, world_to_ref, depth, self._rng(index, 1)))
        out.update(self._pixel_tracks(reader, spec, clip, world_to_ref, depth[0]))
        meta = reader.meta
        out.update({
            # a caption describes the scene as its first camera sees it (directions, the camera's motion): another
            # reference camera's clip would teach the opposite words, so it goes uncaptioned
            "caption": (reader.caption or "") if spec.cameras[0] == meta.cameras[0] else "",
            "dynamic": torch.tensor(meta.dynamic, device="cpu"),
            "frame_indices": torch.tensor(spec.frames, dtype=torch.int64, device="cpu"),
            "camera_indices": torch.tensor([meta.cameras.index(c) for c in spec.cameras], dtype=torch.int64,
                                           device="cpu"),
            "scene": spec.scene,
            "index": torch.tensor(index, dtype=torch.int64, device="cpu"),
        })
        return out

    def _tracks(self, reader: SceneReader, spec: ClipSpec, clip: CameraPath, world_to_ref: Tensor,
                depth: Tensor, rng: np.random.Generator) -> dict[str, Tensor]:
        """Tracks of the clip: N sampled points in the clip world with per-frame visibility and a pad mask."""
        N, T, H, W = self.config.num_tracks, len(spec.frames), clip.height, clip.width
        tracks = torch.zeros(N, T, 3, device="cpu")
        visible = torch.zeros(N, T, dtype=torch.bool, device="cpu")
        mask = torch.zeros(N, dtype=torch.bool, device="cpu")
        data = reader.tracks()
        if data is None or N == 0:
            return {"tracks": tracks, "track_visibility": visible, "track_mask": mask}
        pts, vis = data
        P = pts.shape[0]
        ids = np.sort(rng.permutation(P)[:N]) if P > N else np.arange(P)
        frames = list(spec.frames)
        X = torch.from_numpy(pts[ids][:, frames].astype(np.float64))  # (n, T, 3) source world
        X = X @ world_to_ref[:3, :3].T + world_to_ref[:3, 3]  # clip world
        cam = torch.einsum("tij,ntj->nti", clip.viewmats[:, :3, :3], X) + clip.viewmats[:, :3, 3]
        z = cam[..., 2]
        uv = torch.einsum("tij,ntj->nti", clip.Ks[:, :2, :], cam / z.clamp_min(1e-12)[..., None])
        inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
        col = uv[..., 0].floor().clamp(0, W - 1).long()
        row = uv[..., 1].floor().clamp(0, H - 1).long()
        d = depth[torch.arange(T, device="cpu")[None, :].expand_as(row), row, col].double()
        unoccluded = d >= z - torch.clamp(OCCLUSION_TOL_REL * z, min=OCCLUSION_TOL_M)
        stored = torch.from_numpy(vis[ids][:, frames])
        is_ref = torch.tensor([c == reader.meta.cameras[0] for c in spec.cameras], device="cpu")
        ok = torch.where(is_ref[None, :], stored, unoccluded if reader.has_depth else torch.ones_like(stored))
        n = len(ids)
        tracks[:n] = X.float()
        visible[:n] = inside & ok
        mask[:n] = True
        return {"tracks": tracks, "track_visibility": visible, "track_mask": mask}

    def _pixel_tracks(self, reader: SceneReader, spec: ClipSpec, clip: CameraPath, world_to_ref: Tensor,
                      depth0: Tensor) -> dict[str, Tensor]:
        """Dense 3D tracks of frame 0's pixels (the class docstring's ``pixel_tracks``, ``pixel_track_valid``)."""
        T, H, W = len(spec.frames), clip.height, clip.width
        valid = torch.isfinite(depth0)
        z = torch.where(valid, depth0.double(), 1.0)
        points = unproject_depth(clip.viewmats[:1], clip.Ks[:1], z[None])[0]  # (H, W, 3) clip world
        objects = reader.objects()
        if objects is None:
            valid &= not reader.meta.dynamic  # a static scene's points stay put; a dynamic one's are unknown
            tracks = points.expand(T, H, W, 3)
        else:
            poses, ids = objects
            idm = torch.from_numpy(resize_nearest(ids[spec.cameras[0]][spec.frames[0]], H, W))
            valid &= (idm != NO_SURFACE) & ~id_boundaries(idm)
            to_source = torch.linalg.inv(world_to_ref)
            world = points @ to_source[:3, :3].T + to_source[:3, 3]
            moved = pixel_tracks(world, idm, torch.from_numpy(poses), spec.frames[0],
                                 torch.tensor(spec.frames, device="cpu"))
            tracks = moved @ world_to_ref[:3, :3].T + world_to_ref[:3, 3]
        return {"pixel_tracks": torch.where(valid[..., None], tracks, 0).float().contiguous(),
                "pixel_track_valid": valid}
