"""What ``diff4splat fit`` reads from a scene folder: training/held-out views (one frame of one camera each) and the
initial points. Initialisation follows 3DGS (Kerbl et al. 2023, §5.1) with points from back-projected metric depth
instead of SfM, or a random box without depth. Tensors are made on their inputs' device; random draws come from a
CPU generator and are moved, so a seed gives the same draws on every device.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from data_prep.format import SceneReader
from diff4splat.cameras import camera_centers, unproject_depth
from training.eval_metrics import covisible_mask

__all__ = ["View", "load_views", "split_cameras", "depth_points", "random_box_points", "knn_scales",
           "scene_extent", "covisible_masks"]


@dataclass
class View:
    """One frame: ``image`` (H, W, 3) float32 RGB in [0, 1], ``depth`` (H, W) float32 metric z-depth (+inf where
    invalid) or None, ``viewmat`` (4, 4) world-to-camera (OpenCV), ``K`` (3, 3) pixels, ``time`` in [0, 1], the
    ``camera`` folder name and ``frame`` index."""

    image: Tensor
    depth: Tensor | None
    viewmat: Tensor
    K: Tensor
    time: float
    camera: str
    frame: int

    @property
    def width(self) -> int:
        """W, the image width in pixels."""
        return self.image.shape[1]

    @property
    def device(self) -> torch.device:
        """The view's device (that of ``image``)."""
        return self.image.device

    def to(self, device: str | torch.device) -> View:
        """The view with its tensors on ``device``."""
        return View(self.image.to(device), None if self.depth is None else self.depth.to(device),
                    self.viewmat.to(device), self.K.to(device), self.time, self.camera, self.frame)

    @property
    def height(self) -> int:
        """H, the image height in pixels."""
        return self.image.shape[0]


def split_cameras(scene: SceneReader, holdout_camera: int | None) -> tuple[list[str], list[str]]:
    """Training and held-out camera names, holding out camera index ``holdout_camera``. Raises ValueError for an
    index out of range or no camera left to train on."""
    names = scene.camera_names
    if holdout_camera is None:
        return names, []
    if not 0 <= holdout_camera < len(names):
        raise ValueError(f"--holdout-camera: {holdout_camera} is not a camera index of {scene.path} "
                         f"(it has {len(names)} camera(s): 0 … {len(names) - 1})")
    if len(names) == 1:
        raise ValueError(f"--holdout-camera: {scene.path} has one camera; holding it out leaves nothing to fit")
    return [n for i, n in enumerate(names) if i != holdout_camera], [names[holdout_camera]]


def load_views(scene: SceneReader, cameras: list[str], frames: list[int] | None = None,
               device: str | torch.device = "cpu") -> list[View]:
    """Every frame (or ``frames``) of ``cameras`` as :class:`View` (depth when the scene has it), on ``device``."""
    out = []
    for name in cameras:
        path = scene.cameras(name)
        for i in range(scene.num_frames) if frames is None else frames:
            depth = torch.from_numpy(scene.depth(name, i)) if scene.has_depth else None
            out.append(View(torch.from_numpy(scene.rgb(name, i)), depth, path.viewmats[i].float(),
                            path.Ks[i].float(), float(path.times[i]), name, i).to(device))
    return out


def depth_points(views: list[View], max_points: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Means (N, 3) metres and colours (N, 3) in [0, 1] of every finite depth pixel of ``views`` back-projected, at
    most ``max_points`` kept by :func:`voxel_subsample`. Raises ValueError for a view without depth or no finite
    depth at all."""
    pts, cols = [], []
    for v in views:
        if v.depth is None:
            raise ValueError(f"view {v.camera}/{v.frame} has no depth")
        valid = torch.isfinite(v.depth)
        p = unproject_depth(v.viewmat[None], v.K[None], torch.where(valid, v.depth, 1.0)[None])[0]
        pts.append(p[valid])
        cols.append(v.image[valid])
    means, colors = torch.cat(pts), torch.cat(cols)
    if means.shape[0] == 0:
        raise ValueError("no pixel of the training views has a finite depth; cannot initialise from depth")
    if means.shape[0] > max_points:
        keep = voxel_subsample(means, max_points, generator)
        means, colors = means[keep], colors[keep]
    return means.float(), colors.float()


def voxel_subsample(points: Tensor, max_points: int, generator: torch.Generator) -> Tensor:
    """(K,) int64 indices, K ≤ ``max_points``, of ``points`` (P, 3): one random point per occupied cell of the
    finest cubic grid with at most ``max_points`` occupied cells (edge found by bisection), so points spread over
    the surfaces instead of following pixel density (docs/DESIGN.md, "Fitting (4D Gaussian Splatting)")."""
    perm = torch.randperm(points.shape[0], generator=generator, device=generator.device).to(points.device)
    pts = points[perm].double()
    lo, span = pts.min(0).values, float((pts.max(0).values - pts.min(0).values).max())
    if span <= 0:
        return perm[:max_points]

    def cells(edge: float) -> tuple[Tensor, int]:
        q = ((pts - lo) / edge).floor().long()  # < 2²⁰ per axis for edge ≥ span·1e-6: one int64 key
        _, inverse = torch.unique((q[:, 0] << 40) | (q[:, 1] << 20) | q[:, 2], return_inverse=True)
        return inverse, int(inverse.max()) + 1

    small, big = span * 1e-6, span  # big has 1 occupied cell; small at least as many as max_points allows
    for _ in range(20):
        mid = (small * big) ** 0.5
        if cells(mid)[1] > max_points:
            small = mid
        else:
            big = mid
    inverse, n = cells(big)
    first = torch.full((n,), pts.shape[0], dtype=torch.long, device=pts.device).scatter_reduce_(
        0, inverse, torch.arange(pts.shape[0], device=pts.device), reduce="amin")  # a random point per cell
    return perm[first.sort().values]


def random_box_points(views: list[View], num_points: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Means (num_points, 3) metres and colours in [0, 1], uniform in the box the cameras look into (3DGS's random
    initialisation): centred on the camera centres' mean + spread × mean viewing direction (unnormalised), half-size
    the cameras' spread (at least 1 m)."""
    V = torch.stack([v.viewmat for v in views]).double()
    centres = camera_centers(V)
    forward = V[:, 2, :3].mean(0)  # (3,), length ≤ 1
    spread = max(float((centres - centres.mean(0)).norm(dim=-1).max()), 1.0)
    centre = centres.mean(0) + spread * forward
    dev = generator.device
    u = torch.rand(num_points, 3, generator=generator, dtype=torch.float64, device=dev).to(V.device) * 2 - 1
    return (centre + spread * u).float(), torch.rand(num_points, 3, generator=generator, device=dev).to(V.device)


def knn_scales(means: Tensor, k: int = 3, chunk: int = 1024) -> Tensor:
    """(N, 3) isotropic scales in metres of ``means`` (N, 3): sqrt of the mean squared distance to the ``k`` nearest
    other points, ≥ 1e-7 m² before sqrt (3DGS ``distCUDA2``); 1 cm for N < 2."""
    N, dev = means.shape[0], means.device
    if N < 2:
        return torch.full((N, 3), 1e-2, dtype=means.dtype, device=dev)
    k = min(k, N - 1)
    out = torch.empty(N, dtype=means.dtype, device=dev)
    for s in range(0, N, chunk):
        d2 = torch.cdist(means[s:s + chunk], means).square()
        rows = torch.arange(d2.shape[0], device=dev)
        d2[rows, rows + s] = float("inf")  # not itself
        out[s:s + chunk] = d2.topk(k, dim=1, largest=False).values.mean(1)
    return out.clamp_min(1e-7).sqrt()[:, None].expand(N, 3).clone()


def scene_extent(views: list[View], points: Tensor | None = None) -> float:
    """3DGS's scene scale (``getNerfppNorm``) in metres: 1.1 × the largest camera-centre distance from their mean,
    at least 10 % of ``points``' bounding-box diagonal (when given) and 1e-3 m."""
    centres = camera_centers(torch.stack([v.viewmat for v in views]).double())
    radius = 1.1 * float((centres - centres.mean(0)).norm(dim=-1).max())
    if points is not None and points.shape[0]:
        radius = max(radius, 0.1 * float((points.max(0).values - points.min(0).values).norm()))
    return max(radius, 1e-3)


def covisible_masks(holdout: list[View], train: list[View], static: bool) -> list[Tensor] | None:
    """:func:`training.eval_metrics.covisible_mask` (H, W) of every held-out view against every training view
    (static) or those of the same frame (dynamic); None without depth."""

    if not holdout or any(v.depth is None for v in holdout + train):
        return None
    out = []
    for v in holdout:
        src = train if static else [t for t in train if t.frame == v.frame]
        if not src:
            out.append(torch.zeros(v.depth.shape, dtype=torch.bool, device=v.depth.device))
            continue
        out.append(covisible_mask(v.depth, v.viewmat, v.K, torch.stack([t.depth for t in src]),
                                  torch.stack([t.viewmat for t in src]), torch.stack([t.K for t in src])))
    return out
