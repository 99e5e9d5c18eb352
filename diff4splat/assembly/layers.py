"""A video's frames as photo layers that move as the video does (``reconstruct``; docs/DESIGN.md, "Motion measured
from frames …").

Every frame (or the source frames alone) becomes a photo layer (:func:`diff4splat.assembly.photo.photo_layer`) on
its source frame's depth carried along the optical flow (:func:`carried_depth`), moved by the motion measured from the
frames (:func:`diff4splat.geometry.scene_flow.source_motion`) and shown only between its neighbours' times, where the
two layers around a time cross-fade exactly (:func:`layer_support`), so only there is it tracked (:func:`layer_spans`;
frame 0's layer over the whole clip); a still clip gives a static scene. :func:`layered_scene` builds it.
Order: frame 0's layer, the backdrop (its unseen cells pruned when the scene moves), the other layers.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.assembly.photo import backdrop_layer, layer_sizes, photo_layer
from diff4splat.assembly.prune import prune_mask, settle_and_prune
from diff4splat.cameras import CameraPath
from diff4splat.cameras.path import camera_centers
from diff4splat.geometry.scene_flow import chain_flows, consecutive_flows, sample_pixels, source_motion
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.devices import Stopwatch
from models.deformation import IDENTITY_QUAT

__all__ = ["LAYERS", "DEFAULT_LAYERS", "LAYER_ORDER_OFFSET", "GATE_PX", "FB_TOLERANCE_PX", "MOVING_FRACTION",
           "FLOW_SIZE", "check_layers", "check_layer_knobs", "layer_frames", "layer_slots", "carried_depth",
           "layer_support", "layer_spans", "layered_scene"]

LAYERS = ("every", "source")
"""Which frames of the clip become photo layers (``--layers``, :func:`layer_frames`)."""
DEFAULT_LAYERS = "every"
"""Every frame (T·1.25 Gaussians per output pixel): an in-between time is drawn from its two neighbours' pixels."""
LAYER_ORDER_OFFSET = 0.015
"""The odd layers lie this fraction farther along their camera's rays than the even ones (more than a photo layer's
backing, :data:`~diff4splat.assembly.photo.BACKING_OFFSET`), so an even layer fading in front of an opaque odd
one cross-fades the two (:func:`layer_support`)."""
GATE_PX = 0.5
"""Rigidity gate of the motion, pixels of the output frames (``scene_flow.lift_tracks``)."""
FB_TOLERANCE_PX = 1.5
"""Forward-backward tolerance of the tracking, pixels of the output frames."""
MOVING_FRACTION = 0.005
"""A clip is dynamic when, at some frame, more than this fraction of a layer's pixels has moved by more than the
config's ``static_atol`` (so codec noise does not make a still video move)."""
FLOW_SIZE = 256
"""Pixels of height the frames are tracked at (the output upsampled by the nearest whole factor)."""


def check_layers(layers: object) -> str:
    """``layers`` if it is one of :data:`LAYERS`; else ValueError naming ``--layers``."""
    if layers not in LAYERS:
        raise ValueError(f"--layers must be one of {LAYERS}, got {layers!r}")
    return layers


def check_layer_knobs(order_offset: object, unchecked: object) -> None:
    """ValueError unless ``order_offset`` is a finite number ≥ 0 and ``unchecked`` None or an int ≥ 0
    (:func:`layered_scene`)."""
    if isinstance(order_offset, bool) or not isinstance(order_offset, (int, float)) or not 0 <= order_offset < math.inf:
        raise ValueError(f"order_offset must be a finite number >= 0, got {order_offset!r}")
    if unchecked is not None and (isinstance(unchecked, bool) or not isinstance(unchecked, int) or unchecked < 0):
        raise ValueError(f"unchecked must be None or an int >= 0, got {unchecked!r}")


def layer_frames(sources: list[int], num_frames: int, layers: str) -> list[int]:
    """The frames of a ``num_frames`` clip that become photo layers: all for "every", the LDRM's ``sources`` else."""
    return list(range(num_frames)) if layers == "every" else list(sources)


def layer_slots(width: int, height: int, num_layers: int) -> int:
    """Slots of the unpruned scene: ``num_layers`` photo layers at ``width`` × ``height`` and one backdrop."""
    photo, backdrop = layer_sizes(width, height)
    return num_layers * photo + backdrop


def carried_depth(depths: Tensor, sources: list[int], frame: int, flows: tuple[Tensor, Tensor]) -> Tensor:
    """(H, W) z-depth, metres, of video frame ``frame`` in [0, T): its source frame's, or the nearest source frame's
    (the earlier on a tie) sampled bilinearly where the chained ``flows``
    (:func:`diff4splat.geometry.scene_flow.consecutive_flows`) carry each pixel; ``depths`` (S, H, W) are those of
    ``sources`` (increasing)."""
    if frame in sources:
        return depths[sources.index(frame)]
    s = min(range(len(sources)), key=lambda i: (abs(sources[i] - frame), sources[i]))
    f = sources[s]
    fw, bw = flows
    pair = (fw[frame:f], bw[frame:f]) if f > frame else (bw[f:frame].flip(0), fw[f:frame].flip(0))
    positions, _ = chain_flows(*pair, fb_tolerance=float("inf"))
    return sample_pixels(depths[s][None, ..., None], positions[-1][None])[0, ..., 0]


def layer_support(times: Tensor, layer: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Temporal support (t_means, t_scales, t_ramps; ``DynamicGaussians``' trapezoid) of Gaussians of the layers
    ``layer`` (K,) int64 (−1: the backdrop), the layers at the equally spaced clip times ``times`` (L,), spacing Δ:

    - an even layer is the triangle 1 − |t − t_l|/Δ, in front (:data:`LAYER_ORDER_OFFSET`);
    - an odd layer is the box |t − t_l| < Δ·(1 − 10⁻³), opaque behind (the margin: off at its neighbours' times
      whatever the rounding of clip times like i/12);
    - the backdrop is there at every t ∈ [0, 1].

    Between two layers' times exactly one is even, in front at opacity (1 − α)·o (α the weight of the later time), over
    the other at o: with the photo layers' o ≈ 1, (1 − α)·front + α·back, the cross-fade of the two, each moved to t.
    At a layer's own time only that layer is shown, so the given frames come back as their photo layers render them.
    """
    L = times.shape[0]
    spacing = times[1] - times[0] if L > 1 else times.new_tensor(1.0)
    own = times[layer.clamp(min=0)]
    even = layer % 2 == 0
    back = layer < 0
    t_means = torch.where(back, times.new_tensor(0.5), own)
    t_scales = torch.where(back, times.new_tensor(1.0), torch.where(even, spacing, spacing * (1 - 1e-3)))
    t_ramps = torch.where(even & ~back, spacing.expand_as(own), times.new_zeros(()))
    return t_means, t_scales, t_ramps


def _pushed_back(layer: Gaussians, viewmat: Tensor, factor: float) -> Gaussians:
    """``layer`` scaled by ``factor`` about its camera's centre (``viewmat`` (4, 4) world-to-camera): each Gaussian
    ``factor`` times as far along its ray, and as large, so its image does not change."""
    centre = camera_centers(viewmat[None])[0]
    return Gaussians(centre + (layer.means - centre) * factor, layer.quats, layer.scales * factor, layer.opacities,
                     layer.sh)


def layer_spans(frames_of: list[int]) -> list[tuple[int, int]]:
    """Each layer's tracked frames (first, last): frame 0's layer over the whole clip (the clip's 3D tracks), every
    other from its previous layer's frame to its next one's, the only times it is shown (:func:`layer_support`)."""
    last = frames_of[-1]
    return [(0, last) if s == 0 else (frames_of[s - 1], frames_of[min(s + 1, len(frames_of) - 1)])
            for s in range(len(frames_of))]


def layered_scene(images: Tensor, depths: Tensor, sources: list[int], frames_of: list[int], cameras: CameraPath, *,
                  static_atol: float, prune_opacity: float, order_offset: float = LAYER_ORDER_OFFSET,
                  unchecked: int | None = None, clock: Stopwatch, timings: dict[str, float]
                  ) -> tuple[DynamicGaussians, Tensor, dict[str, int], float, int, int]:
    """The 4D scene (module docstring) of a clip's frames ``images`` (T, H, W, 3) in [0, 1] seen by ``cameras`` (T at
    W × H, relative to the first), on the z-depths ``depths`` (S, H, W), metres, of its source frames ``sources``;
    ``frames_of`` the frames that become layers (:func:`layer_frames`), ``static_atol`` (metres) and
    ``prune_opacity`` the config's; ``order_offset`` how far odd layers are pushed back along their rays (a fraction
    of their distance, :func:`layer_support`); ``unchecked`` how many first links of flow each layer follows whatever
    their forward-backward error (None: the spacing of layer frames, as far as the layer is seen;
    :func:`~diff4splat.geometry.scene_flow.chain_flows`). ``clock``'s lap after each stage is stored in ``timings``
    (seconds) under "backdrop", "motion", "assemble" and "prune".

    Returns (scene, gaussian_index (M,) of each kept Gaussian in the unpruned order, prune stats, the photo PSNR of
    frame 0's layer (dB), the unpruned slot count, frame 0's layer's Gaussian count).

    Raises:
        ValueError: a path that sees nothing of the scene.
    """
    T, H, W = images.shape[:3]
    dev = images.device
    flows = consecutive_flows(images.permute(0, 3, 1, 2), upsample=max(1, round(FLOW_SIZE / H)))
    z = torch.stack([carried_depth(depths, sources, f, flows) for f in frames_of])  # (L, H, W)
    spacing = frames_of[1] - frames_of[0] if len(frames_of) > 1 else 1  # a layer is seen this far from its frame
    # The backdrop (static, behind everything) first: when the scene moves, the only pruning is of its cells that no
    # camera sees, so the layers' motion is laid out for the kept cells alone and never copied by a selection.
    backdrop = backdrop_layer(images[0], z[0], cameras.viewmats[0], cameras.Ks[0])
    seen, stats = prune_mask(DynamicGaussians(backdrop), cameras, min_opacity=prune_opacity)
    timings["backdrop"] = clock.lap()
    photo, L = layer_sizes(W, H)[0], len(frames_of)
    kept = int(seen.sum())
    offsets = [0] + [photo + kept + (s - 1) * photo for s in range(1, L)]  # each layer's first Gaussian
    # Each layer's motion, tracked only over the frames it is shown at (layer_spans), written in place: the scene's
    # (T, N, 3) is the one copy of it.
    d_means = z.new_zeros(T, L * photo + kept, 3)
    dynamic = False
    for s, (lo, hi) in enumerate(layer_spans(frames_of)):
        motion = source_motion(flows, z, frames_of, s, cameras.Ks, cameras.viewmats, (lo, hi),
                               fb_tolerance=FB_TOLERANCE_PX, gate_px=GATE_PX,
                               unchecked=spacing if unchecked is None else unchecked)  # (hi − lo + 1, H, W, 3)
        moved = (motion.abs() > static_atol).any(dim=-1).flatten(1).float().mean(dim=-1)  # (hi − lo + 1,)
        dynamic = dynamic or bool((moved > MOVING_FRACTION).any())
        # the photo layer's (H·W + ⌈H/2⌉·⌈W/2⌉) Gaussians: the pixels', then the backing's (2×2 means)
        block = F.avg_pool2d(motion.permute(0, 3, 1, 2), 2, ceil_mode=True).permute(0, 2, 3, 1)
        d_means[lo:hi + 1, offsets[s]:offsets[s] + photo] = torch.cat([motion.flatten(1, 2), block.flatten(1, 2)], 1)
        del motion
    timings["motion"] = clock.lap()
    if not dynamic:  # a still world: every backdrop cell goes to settle_and_prune with the layers
        del d_means
    parts, grid = [], []  # the layers and the backdrop, in the scene's order
    for s, f in enumerate(frames_of):
        layer, history = photo_layer(images[f], z[s], cameras.viewmats[f], cameras.Ks[f])
        if dynamic and s % 2:  # odd layers behind (layer_support)
            parts.append(_pushed_back(layer, cameras.viewmats[f], 1 + order_offset))
            d_means[:, offsets[s]:offsets[s] + photo] *= 1 + order_offset
        else:
            parts.append(layer)
        grid.append(torch.full((layer.num_gaussians,), s, dtype=torch.long, device=dev))
        if s == 0:
            photo_psnr = history[-1]
            parts.append(backdrop.select(seen) if dynamic else backdrop)
            grid.append(torch.zeros(parts[-1].num_gaussians, dtype=torch.long, device=dev))
    canonical = Gaussians(*(torch.cat([getattr(g, f) for g in parts])
                            for f in ("means", "quats", "scales", "opacities", "sh")))
    grid = torch.cat(grid)
    N, n0, n_back = L * photo + backdrop.num_gaussians, parts[0].num_gaussians, parts[1].num_gaussians
    if dynamic:  # each layer between its neighbours' times, the two around a time cross-faded (layer_support)
        layer_of = grid.clone()
        layer_of[n0:n0 + n_back] = -1  # the backdrop
        support = layer_support(cameras.times[torch.tensor(frames_of, device=dev)].float(), layer_of)
        M = canonical.num_gaussians
        scene = DynamicGaussians(canonical, cameras.times, d_means,
                                 canonical.means.new_tensor(IDENTITY_QUAT).expand(T, M, 4),
                                 canonical.means.new_zeros(()).expand(T, M, 3), *support)
        timings["assemble"] = clock.lap()
        # every layer is observed: only the backdrop's unseen cells went (above)
        slots, end = torch.arange(N, device=dev), n0 + backdrop.num_gaussians
        index = torch.cat([slots[:n0], slots[n0:end][seen], slots[end:]])
        stats = {**stats, "before": N, "after": M, "duplicates": 0, "slid": 0, "occluders": 0}
    else:  # a still world: the layers of one static scene, overlaps settled as generate settles its frames
        scene = DynamicGaussians(canonical)
        timings["assemble"] = clock.lap()
        scene, index, stats = settle_and_prune(scene, grid, cameras, torch.tensor(frames_of, device=dev), z[0], n0,
                                               prune_opacity)
    timings["prune"] = clock.lap()
    return scene, index, stats, photo_psnr, N, n0
