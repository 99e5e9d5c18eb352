"""Whether a model is being traced (torch.jit, torch.compile, torch.export, torch.onnx).

While tracing, the networks leave out value-dependent checks, Python loops over data-dependent sizes and their
fast paths for one sample or for no autograd (a LayerNorm affine made of the input, residuals added in place),
so the graph stays general.
"""
from __future__ import annotations

import torch

__all__ = ["tracing"]


def tracing() -> bool:
    """True while torch.jit / torch.compile / torch.export / torch.onnx trace a model: value-dependent checks and
    Python loops over data-dependent sizes are then left out, so the graph stays general."""
    return bool(torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.compiler.is_exporting()
                or torch.onnx.is_in_onnx_export())
