"""The measured constants of the memory and time estimates checked before heavy work
(:meth:`diff4splat.pipeline.Diff4SplatPipeline.memory_estimate`, :func:`diff4splat.reconstruct.memory_estimate`,
:func:`diff4splat.render_command.render_memory_estimate`; :func:`diff4splat.utils.limits.check_memory`): bytes and
seconds on the reference 2-core CPU (docs/benchmarks.md)."""
from __future__ import annotations

__all__ = ["MEMORY_BASE_BYTES", "MEMORY_CUDA_BUILD_BYTES", "MEMORY_SCENE_COPIES", "MEMORY_MAP_COPIES",
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
