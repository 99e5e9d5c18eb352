"""The memory model checked before heavy work (:func:`diff4splat.utils.limits.check_memory`): one estimate per
command (:func:`generate_memory`, :func:`reconstruct_memory`, :func:`render_memory`) built from shared terms, and its
measured constants: bytes and seconds on the reference 2-core CPU (docs/benchmarks.md)."""
from __future__ import annotations

import torch

__all__ = ["process_bytes", "frames_bytes", "generate_memory", "generate_seconds", "reconstruct_memory",
           "render_memory", "MEMORY_BASE_BYTES", "MEMORY_CUDA_BUILD_BYTES", "MEMORY_SCENE_COPIES", "MEMORY_MAP_COPIES",
           "MEMORY_BYTES_PER_GAUSSIAN", "TIME_FIXED_SECONDS", "TIME_SECONDS_PER_PIXEL_FRAME", "TIME_ESTIMATE_PRINTED",
           "RENDER_BYTES_PER_GAUSSIAN", "RENDER_BASE_BYTES"]

MEMORY_BASE_BYTES = 640 << 20
"""The ``generate`` process before its tensors: Python, torch, numba, OpenCV."""
MEMORY_CUDA_BUILD_BYTES = 320 << 20
"""Host memory a CUDA build of torch adds to that process (its CUDA libraries), GPU in use or not."""
MEMORY_SCENE_COPIES = 2
"""Copies of the unpruned scene's deformation alive at once, at most (the assembled scene and its pruned copy)."""
MEMORY_MAP_COPIES = 2
"""Copies of the LDRM's deformation maps alive at once, at most (the network's output and its flattened view)."""
MEMORY_BYTES_PER_GAUSSIAN = 600
"""Memory per Gaussian slot besides its deformation: attributes, pruning masks, the renderer's tile lists."""
TIME_FIXED_SECONDS = 4.0
"""``generate``'s wall time that does not grow with the output (interpreter, imports, loading, sampling), seconds
(docs/benchmarks.md, "generate against the output resolution": the 64² run)."""
TIME_SECONDS_PER_PIXEL_FRAME = 1.9e-6
"""``generate``'s wall time per output pixel and frame, seconds (the same table's slope to 2048², its steepest)."""
TIME_ESTIMATE_PRINTED = 60.0
"""Seconds above which ``generate`` prints its time estimate before the work."""
RENDER_BYTES_PER_GAUSSIAN = 1400
"""Peak memory per Gaussian of ``render`` beyond the loaded scene: a frame's deformed copy, temporaries, tile lists."""
RENDER_BASE_BYTES = 384 << 20
"""Memory ``render`` adds once its first frame runs, whatever the scene: numba's kernels and LLVM, the video encoder."""


def process_bytes() -> int:
    """The process before its tensors, bytes: :data:`MEMORY_BASE_BYTES`, plus :data:`MEMORY_CUDA_BUILD_BYTES` on a
    CUDA build of torch."""
    return MEMORY_BASE_BYTES + (MEMORY_CUDA_BUILD_BYTES if torch.backends.cuda.is_built() else 0)


def frames_bytes(frames: int, width: int, height: int) -> int:
    """The rendered frames of a path, bytes: T × H × W × 5 floats (colour, depth, alpha), twice (the tensors and the
    encoder's copy)."""
    return 2 * 20 * frames * width * height


def generate_memory(*, slots: int, keys: int, maps: int, weights: int, frames: int, width: int, height: int) -> int:
    """Upper bound of ``generate``'s peak host memory, bytes: the process and the ``weights`` held in host memory;
    the unpruned scene's deformation (``slots`` × ``keys`` times × 10 floats × :data:`MEMORY_SCENE_COPIES`); the
    LDRM's deformation maps on the CPU (``keys`` × ``maps`` cells × 10 floats, ``maps`` already × their copies);
    :data:`MEMORY_BYTES_PER_GAUSSIAN` per slot; :func:`frames_bytes`."""
    return int(process_bytes() + weights + MEMORY_BYTES_PER_GAUSSIAN * slots
               + 40 * keys * (MEMORY_SCENE_COPIES * slots + maps) + frames_bytes(frames, width, height))


def generate_seconds(width: int, height: int, frames: int) -> float:
    """Rough CPU wall time of ``generate``, seconds: (:data:`TIME_FIXED_SECONDS` + :data:`TIME_SECONDS_PER_PIXEL_FRAME`
    · pixels · frames) scaled by 2 / torch's threads (base model)."""
    scale = 2 / max(1, torch.get_num_threads())
    return scale * (TIME_FIXED_SECONDS + TIME_SECONDS_PER_PIXEL_FRAME * width * height * frames)


def reconstruct_memory(*, slots: int, weights: int, frames: int, width: int, height: int) -> int:
    """Upper bound of ``reconstruct``'s peak host memory, bytes: the process and the ``weights``; per slot its
    attributes and its Δμ, T × 3 floats, × (:data:`MEMORY_SCENE_COPIES` + 1) (the rotations and scales are one row
    shared by every Gaussian); one layer's motion over the whole clip (frame 0's), T × H × W × 3 floats, four times
    (its tracks, its lifting and its layer's copy); the flows (T × H × W × 4 floats); :func:`frames_bytes`."""
    pixels = width * height
    return int(process_bytes() + weights + slots * (MEMORY_BYTES_PER_GAUSSIAN + 12 * frames * (MEMORY_SCENE_COPIES + 1))
               + 4 * 12 * frames * pixels + 16 * frames * pixels + frames_bytes(frames, width, height))


def render_memory(*, held: int, gaussians: int, sampled_times: int, frames: int, width: int, height: int) -> int:
    """Upper bound of ``render``'s peak host memory, bytes, once its folder is loaded: what the process ``held``,
    :data:`RENDER_BASE_BYTES`, a field's deformation sampled at ``sampled_times`` (10 floats per Gaussian and time; 0
    without a field), :data:`RENDER_BYTES_PER_GAUSSIAN` per Gaussian and :func:`frames_bytes`."""
    return int(held + RENDER_BASE_BYTES + 40 * gaussians * sampled_times + RENDER_BYTES_PER_GAUSSIAN * gaussians
               + frames_bytes(frames, width, height))
