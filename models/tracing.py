"""Whether a model is being traced: the networks then leave out value-dependent checks, data-dependent loops and
their one-sample / no-autograd fast paths, so the graph stays general."""
from __future__ import annotations

import torch

__all__ = ["tracing"]


def tracing() -> bool:
    """True while torch.jit / torch.compile / torch.export / torch.onnx trace a model."""
    return bool(torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.compiler.is_exporting()
                or torch.onnx.is_in_onnx_export())
