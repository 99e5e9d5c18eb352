"""What the commands cost, per unit of their request: the measured constants of the memory and time estimates that
are checked before any heavy work (:meth:`diff4splat.pipeline.Diff4SplatPipeline.memory_estimate` and
``time_estimate``, :func:`diff4splat.reconstruct.memory_estimate`,
:func:`diff4splat.render_command.render_memory_estimate`; checked by :func:`diff4splat.utils.limits.check_memory`).
Figures are bytes and seconds on the reference 2-core CPU (docs/benchmarks.md)."""
from __future__ import annotations

__all__ = ["MEMORY_BASE_BYTES", "MEMORY_CUDA_BUILD_BYTES", "MEMORY_SCENE_COPIES", "MEMORY_MAP_COPIES",
           "MEMORY_BYTES_PER_GAUSSIAN", "TIME_FIXED_SECONDS", "TIME_SECONDS_PER_PIXEL_FRAME", "TIME_ESTIMATE_PRINTED",
           "RENDER_BYTES_PER_GAUSSIAN", "RENDER_BASE_BYTES"]

MEMORY_BASE_BYTES = 640 << 20
"""The ``generate`` process before its tensors: Python, torch, numba, OpenCV (measured 0.57 GB with the base model)."""
MEMORY_CUDA_BUILD_BYTES = 320 << 20
"""What a CUDA build of torch adds to that process, GPU in use or not: the host memory of its CUDA libraries (288 MiB
more resident after ``import torch`` with torch 2.14.1+cu130 than with 2.13.0+cpu, on a machine without a GPU)."""
MEMORY_SCENE_COPIES = 2
"""Copies of the unpruned scene's deformation alive at once, at most (:meth:`Diff4SplatPipeline.memory_estimate`):
the scene ``assemble`` writes each field of once, and its pruned copy (docs/benchmarks.md, "Memory of generate")."""
MEMORY_MAP_COPIES = 2
"""Copies of the LDRM's deformation maps alive at once, at most (the network's output and its flattened view)."""
MEMORY_BYTES_PER_GAUSSIAN = 600
"""Memory per Gaussian slot besides its deformation: attributes, pruning masks, the renderer's tile lists."""
TIME_FIXED_SECONDS = 4.5
"""``generate``'s wall time that does not grow with the output (interpreter, imports, the base model's load and
sampling at its own resolution), seconds on the reference 2-core CPU (docs/benchmarks.md, "generate against the
output resolution": the 64² run)."""
TIME_SECONDS_PER_PIXEL_FRAME = 2.4e-6
"""``generate``'s wall time per output pixel and frame on the reference 2-core CPU (photo layer, assembly, pruning,
rendering, writing; the same table's slope to 2048², the steepest: 1.9e-6 to 1024²)."""
TIME_ESTIMATE_PRINTED = 60.0
"""Seconds above which ``generate`` prints its time estimate before the work."""
RENDER_BYTES_PER_GAUSSIAN = 1400
"""Peak memory per Gaussian of ``render`` beyond the loaded scene
(:func:`diff4splat.render_command.render_memory_estimate`): a frame's deformed copy and interpolation temporaries, the
renderer's tile lists."""
RENDER_BASE_BYTES = 384 << 20
"""Memory ``render`` adds once its first frame runs, whatever the scene: numba's compiled kernels and LLVM, the video
encoder. With :data:`RENDER_BYTES_PER_GAUSSIAN` the render estimate was 1.16-1.34× the measured peak (dynamic scenes of
0.09-5.3 M Gaussians rendered at 256²-1024², 17 frames, 2-core CPU)."""
