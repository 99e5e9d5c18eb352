"""What ``diff4splat fit`` reads from a scene folder: training/held-out views and the initial Gaussians.

A *view* is one frame of one camera (image, optional metric depth, viewmat, K, time), on the device the fit
runs on (:func:`load_views`); everything here makes its tensors on the device of its inputs, and random draws
come from a CPU ``torch.Generator`` and are moved, so a seed gives the same draws on every device
(docs/DESIGN.md, "Devices"). Initialisation
follows 3DGS (Kerbl et al. 2023, §5.1): points with colours, isotropic scales from the mean squared
distance to the 3 nearest neighbours, opacity 0.1, identity rotation; 4DGS (Wu et al. 2024) uses the same
initialisation for its canonical Gaussians. Our points come from the scene's metric depth (back-projected
pixels) instead of SfM, or from a random box when the scene has no depth.
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
    """One training or evaluation frame.

    Attributes:
        image: (H, W, 3) float32 RGB in [0, 1].
        depth: (H, W) float32 metric z-depth (+inf where invalid), or None.
        viewmat: (4, 4) world-to-camera (OpenCV).
        K: (3, 3) pixels.
        time: clip time in [0, 1].
        camera: camera folder name.
        frame: frame index in the camera.
    """

    image: Tensor
    depth: Tensor | None
    viewmat: Tensor
    K: Tensor
    time: float
    camera: str
    frame: int

    @property
    def width(self) -> int:
        """W, the image width in pixels (``image.shape[1]``)."""
        return self.image.shape[1]

    @property
    def device(self) -> torch.device:
        """The device of ``image``, the view's device (:meth:`to` returns a copy with every tensor on another)."""
        return self.image.device

    def to(self, device: str | torch.device) -> View:
        """The view with its tensors on ``device``."""
        return View(self.image.to(device), None if self.depth is None else self.depth.to(device),
                    self.viewmat.to(device), self.K.to(device), self.time, self.camera, self.frame)

    @property
    def height(self) -> int:
        """H, the image height in pixels (``image.shape[0]``)."""
        return self.image.shape[0]


def split_cameras(scene: SceneReader, holdout_camera: int | None) -> tuple[list[str], list[str]]:
    """Training and held-out camera names: camera ``holdout_camera`` (index into ``meta["cameras"]``) is
    never trained on.

    Raises:
        ValueError: ``holdout_camera`` outside [0, number of cameras), or no camera left to train on.
    """
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
    """Back-project every valid depth pixel of ``views`` (:func:`diff4splat.cameras.unproject_depth`) and
    keep at most ``max_points``, spread over space (:func:`voxel_subsample`).

    Args:
        views: views with depth, on one device (the result's).
        generator: a CPU generator (the subsample's random order).

    Returns:
        means (N, 3) metres, colours (N, 3) in [0, 1], on the views' device.

    Raises:
        ValueError: a view has no depth, or no pixel has a finite depth.
    """
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
    """Indices of at most ``max_points`` of ``points`` (P, 3), one random point per occupied cell of the
    finest cubic grid that has at most ``max_points`` occupied cells (cell edge found by bisection).

    A uniform random subset of back-projected pixels follows pixel density: surfaces that many views see
    up close get most of the points, and a surface seen only at grazing angles or from far away gets
    almost none, so its Gaussians start sparse. One point per grid cell spreads them over the surfaces
    (the voxel-grid downsampling of point-cloud initialisations).

    Args:
        points: (P, 3) on any device.
        generator: a CPU generator: the random order is drawn there and moved, so it is the same on every device.

    Returns:
        (K,) int64 indices on ``points``' device, K ≤ max_points.
    """
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
    """Uniform random points with random colours in the box the cameras look into (3DGS's random
    initialisation for scenes without SfM points): centred on the camera centres' mean pushed one
    camera-spread (at least 1 m) times the mean of the unit viewing directions (not normalised: its length
    is 1 for parallel cameras and ~0 for a ring of cameras looking inwards, whose centre is then kept),
    half-size that spread (at least 1 m).

    Args:
        generator: a CPU generator (the draws are moved to the views' device).

    Returns:
        means (num_points, 3) metres, colours (num_points, 3) in [0, 1], on the views' device.
    """
    V = torch.stack([v.viewmat for v in views]).double()
    centres = camera_centers(V)
    forward = V[:, 2, :3].mean(0)  # (3,), length ≤ 1
    spread = max(float((centres - centres.mean(0)).norm(dim=-1).max()), 1.0)
    centre = centres.mean(0) + spread * forward
    dev = generator.device
    u = torch.rand(num_points, 3, generator=generator, dtype=torch.float64, device=dev).to(V.device) * 2 - 1
    return (centre + spread * u).float(), torch.rand(num_points, 3, generator=generator, device=dev).to(V.device)


def knn_scales(means: Tensor, k: int = 3, chunk: int = 1024) -> Tensor:
    """3DGS initial scale: sqrt of the mean squared distance to the ``k`` nearest other points
    (``distCUDA2`` in the reference code), the same on the three axes; clamped to ≥ 1e-7 m² before sqrt.

    Args:
        means: (N, 3) metres, N ≥ 2.

    Returns:
        (N, 3) scales, metres, > 0, on ``means``' device.
    """
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
    """The scene scale of 3DGS (``getNerfppNorm``): 1.1 × the largest distance of a camera centre from
    their mean, metres. Cameras that (almost) do not move give ~0, so the result is at least 10 % of the
    diagonal of ``points``' bounding box (when given), and at least 1e-3 m.
    """
    centres = camera_centers(torch.stack([v.viewmat for v in views]).double())
    radius = 1.1 * float((centres - centres.mean(0)).norm(dim=-1).max())
    if points is not None and points.shape[0]:
        radius = max(radius, 0.1 * float((points.max(0).values - points.min(0).values).norm()))
    return max(radius, 1e-3)


def covisible_masks(holdout: list[View], train: list[View], static: bool) -> list[Tensor] | None:
    """Co-visibility mask (H, W) bool of every held-out view (:func:`training.eval_metrics.covisible_mask`,
    DyCheck's mPSNR mask): the pixels whose surface point a training view sees — every training view for a
    static scene, those of the same frame (the same time) for a dynamic one. None without depth. On the views'
    device."""
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
