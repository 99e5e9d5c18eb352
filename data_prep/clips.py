"""Training clips: a map-style ``torch.utils.data.Dataset`` over a dataset root in our format (FORMAT.md).

**Index.** :class:`ClipDataset` lists the scenes of the root (optionally only static or only dynamic
ones, or a given subset) and cuts each into windows: items ``(scene, start frame)`` with
``start = 0, window_step, 2·window_step, …`` such that a clip at the minimum stride fits
(``start + (T − 1)·min_stride ≤ T_scene − 1``). The index depends only on the scenes' lengths and the
config, so ``len()`` is fixed and ``DistributedSampler`` can split it.

**Per-item randomness.** Item ``i`` in epoch ``e`` draws, from a generator seeded with
``(seed, e, i)``: the temporal stride (uniform in ``[min_stride, max_stride]``, capped so the clip fits
in the scene), the reference camera (``"first"`` = the scene's reference camera, ``"random"`` = any of
its synchronised cameras), the camera of every target frame (``"same"`` as the reference, or
``"random"``) and the subset of tracks. ``__getitem__(i)`` is a pure function of (config, i, epoch);
:meth:`ClipDataset.set_epoch` changes the epoch (the trainer calls it before each epoch).

**A clip** of T = 1 + 4k frames: frame 0 is the reference image (source frame ``start`` of the
reference camera); frame k > 0 is source frame ``start + k·stride`` of its camera. Images are
centre-cropped to the aspect ratio of (height, width) and resized by
:func:`diff4splat.io.preprocess_image`; intrinsics follow the same crop and resize
(:meth:`diff4splat.cameras.CameraPath.fitted`, the same :func:`~diff4splat.cameras.center_crop_box`);
cameras are re-expressed relative to the reference camera (:meth:`CameraPath.relative_to_first`,
``viewmats[0] = I``), so the clip's world frame is the reference camera's frame at frame 0.
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

from diff4splat.cameras import CameraPath, center_crop_box, pack_plucker, plucker_rays
from diff4splat.io import preprocess_image
from diff4splat.utils.checks import check_int

from .format import SceneMeta, SceneReader, list_scenes, timestamps_to_times
from .scene_files import META_FILE

__all__ = ["ClipConfig", "ClipItem", "ClipSpec", "ClipDataset", "resize_depth", "OCCLUSION_TOL_M", "OCCLUSION_TOL_REL"]

OCCLUSION_TOL_M, OCCLUSION_TOL_REL = 0.02, 0.02
"""Visibility depth test of FORMAT.md (tracks.npz): visible iff depth ≥ z − max(0.02 m, 0.02·z)."""

_CHOICES = {"scenes": ("all", "static", "dynamic"), "reference_camera": ("first", "random"),
            "target_cameras": ("same", "random"), "plucker": ("raw", "packed", "both")}


@dataclass(frozen=True)
class ClipConfig:
    """Clip sampling options (the single source of defaults).

    Attributes:
        num_frames: T = 1 + 4k frames per clip (the VAE's causal grouping), ≥ 1.
        height, width: clip resolution, pixels; multiples of 8 when ``plucker`` includes ``"packed"``.
        scenes: ``"static"`` (stages 1–2), ``"dynamic"`` (stage 3) or ``"all"``, by ``meta["dynamic"]``.
        min_stride, max_stride: temporal stride range in source frames, 1 ≤ min ≤ max.
        window_step: source frames between consecutive window starts; ``None`` → (T − 1)·min_stride + 1
            (non-overlapping windows at the minimum stride).
        reference_camera: ``"first"`` (the scene's reference camera) or ``"random"`` (any camera).
        target_cameras: ``"same"`` (a monocular clip) or ``"random"`` (each target frame from any
            synchronised camera).
        num_tracks: N tracks per clip (sampled without replacement; padded when the scene has fewer).
        plucker: ``"raw"`` (T, H, W, 6), ``"packed"`` (:func:`~diff4splat.cameras.pack_plucker`) or ``"both"``.
        seed: base seed of the per-item randomness.

    Raises:
        ValueError: naming the field, for a wrong type or value.
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


def resize_depth(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Centre-crop and resize a metric depth map exactly like images (:func:`center_crop_box`), by nearest.

    Nearest-neighbour with pixel-centre alignment (``cv2.INTER_NEAREST_EXACT``: output pixel j samples
    source pixel ⌊(j + 0.5)·src/dst⌋) keeps every value a source value: metric z-depth is unchanged by
    a crop/resize of the image (the camera does not move) and +inf (invalid) is never blended with
    valid depth.

    Args:
        depth: (h, w) float32 metres, +inf invalid.
        height, width: output size, pixels.

    Returns:
        (height, width) float32.
    """
    y0, x0, ch, cw = center_crop_box(depth.shape[0], depth.shape[1], height, width)
    crop = np.ascontiguousarray(depth[y0:y0 + ch, x0:x0 + cw], dtype=np.float32)
    if (ch, cw) == (height, width):
        return crop
    return cv2.resize(crop, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)


class ClipDataset(Dataset):
    """Clips of T frames at (height, width) from a dataset root (see the module docstring).

    Args:
        root: dataset root (folder of scene folders, FORMAT.md), e.g. the output of ``data_prep curate``.
        config: :class:`ClipConfig`; ``None`` → defaults. ``overrides``: fields replacing those of ``config``.
        scene_names: restrict to these scene folder names (e.g. ``accepted.txt``); ``None`` → all.

    ``__getitem__(i)`` returns a dict (collates with the default ``collate_fn``; B is the batch):

    ============== =============================== ========= ================================================
    key            shape                           dtype     meaning
    ============== =============================== ========= ================================================
    video          (3, T, H, W)                    float32   RGB in [0, 1]; frame 0 is the reference image
    viewmats       (T, 4, 4)                       float32   world-to-camera, clip world = reference camera
                                                             at frame 0 (viewmats[0] = I), metres
    Ks             (T, 3, 3)                       float32   pixels, fitted to the crop/resize of ``video``
    times          (T,)                            float32   clip times in [0, 1] from the source timestamps
    plucker        (T, H, W, 6)                    float32   ``[o × d, d]`` in the clip world (``"raw"``)
    plucker_packed (6·4·64, 1 + (T−1)/4, H/8, W/8) float32   :func:`pack_plucker` of ``plucker`` (``"packed"``)
    depth          (T, H, W)                       float32   metric z-depth, metres; +inf invalid (nearest resize)
    depth_valid    (T, H, W)                       bool      finite depth (all False without depth)
    tracks         (N, T, 3)                       float32   track positions in the clip world, metres (0 pads)
    track_visibility (N, T)                        bool      visible in frame k's camera (see below)
    track_mask     (N,)                            bool      real track (False for padding)
    caption        —                               str       ``caption.txt`` or ``""``
    dynamic        ()                              bool      ``meta["dynamic"]``
    frame_indices  (T,)                            int64     source frame of each clip frame
    camera_indices (T,)                            int64     index into the scene's ``meta["cameras"]``
    scene          —                               str       scene folder name
    index          ()                              int64     i
    ============== =============================== ========= ================================================

    Track visibility of clip frame k: the point lies in front of frame k's camera and projects inside
    the clip image; if that camera is the scene's reference camera, its stored ``visibility`` flag
    (FORMAT.md) must also hold; for other cameras the occlusion test of FORMAT.md is applied to the
    clip depth (nearest pixel; skipped for scenes without depth).

    Raises:
        FileNotFoundError: ``root`` is not a folder.
        ValueError: bad config/overrides, no scene folder in ``root``, unknown ``scene_names``, or no scene long
            enough for one clip.
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

    def _reader(self, scene: str) -> SceneReader:
        if scene not in self._readers:
            self._readers[scene] = SceneReader(self.root / scene)
        return self._readers[scene]

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
        if cfg.target_cameras == "same":
            targets = [ref] * (T - 1)
        else:
            targets = [cams[int(j)] for j in rng.integers(len(cams), size=T - 1)]
        frames = tuple(item.start + k * stride for k in range(T))
        return ClipSpec(item.scene, item.start, stride, frames, (ref, *targets))

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = self._check_index(index)
        cfg, spec = self.config, self.sample(index)
        reader, H, W, T = self._reader(spec.scene), cfg.height, cfg.width, cfg.num_frames
        fitted = {c: reader.cameras(c).fitted(W, H).to(torch.float64) for c in set(spec.cameras)}
        vm = torch.stack([fitted[c].viewmats[f] for c, f in zip(spec.cameras, spec.frames, strict=True)])
        Ks = torch.stack([fitted[c].Ks[f] for c, f in zip(spec.cameras, spec.frames, strict=True)])
        times = torch.from_numpy(timestamps_to_times(reader.timestamps()[list(spec.frames)]))
        clip = CameraPath(vm, Ks, W, H, times).relative_to_first()
        world_to_ref = vm[0]  # source world → clip world

        video = torch.stack([preprocess_image(reader.rgb(c, f), (H, W))
                             for c, f in zip(spec.cameras, spec.frames, strict=True)])
        if reader.has_depth:
            depth = torch.from_numpy(np.stack([resize_depth(reader.depth(c, f), H, W)
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
        meta = reader.meta
        out.update({
            "caption": reader.caption or "",
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
