"""Bytes one DiT sampling step moves outside its matmuls and attention, per aten op, on any machine.

The paper model's step is about 85 % GEMMs and attention; the rest (norms, modulation, RoPE, residuals, GELU,
copies) is memory-bound: each op reads its inputs and writes its outputs once, so on a GPU its time is about
its bytes over the memory bandwidth (3.35 TB/s on an H100 SXM) while the GEMMs are compute-bound. This script
counts those bytes: the DiT of a config (default ``paper``: 32 blocks, hidden 4,096, 49 frames, 512² → 13,312
tokens, 226 text tokens) is built in bfloat16 under torch's ``FakeTensorMode`` (shapes, dtypes and strides; no
storage, no GPU) and one no-grad forward runs as sampling runs it (feed-forward chunk
:data:`diff4splat.runtime.FF_CHUNK_TOKENS`) under a dispatch mode that adds up, per aten op, the bytes of the
tensors it reads and writes (a view moves nothing; an in-place op reads and writes its tensor; an ``out=`` op
writes its output; a broadcast counts once; every other element of a tensor counts as all of it,
:func:`moved_bytes`). It is a count, not a timing: a kernel can hit the cache, or move more than it uses.

``--device cuda`` counts the ops CUDA runs (fused RMSNorm; the attention as FlashAttention, as torch picks it on
an H100 without a mask); it needs a CUDA build of torch, not a GPU. ``--device cpu`` counts the CPU's ops (its
RMSNorm is several ops).

    python benchmarks/dit_traffic.py [--config paper] [--device cuda] [--write]

``--write`` replaces the section ``dit_traffic`` of docs/benchmarks.md.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import math
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import fake_dit_step, markdown_table, publish  # noqa: E402

from diff4splat.runtime import FF_CHUNK_TOKENS  # noqa: E402

__all__ = ["count_step", "ByteCount", "moved_bytes", "MATMUL_OPS", "FREE_OPS"]

MATMUL_OPS = frozenset({"mm", "addmm", "_addmm_activation", "bmm", "baddbmm", "_scaled_dot_product_flash_attention",
                        "_scaled_dot_product_flash_attention_for_cpu", "_scaled_dot_product_efficient_attention",
                        "_scaled_dot_product_cudnn_attention"})
"""GEMMs (``_addmm_activation``: with the GELU in its epilogue) and fused attention kernels: compute-bound at the
paper size, counted apart."""
FREE_OPS = frozenset({"view", "_unsafe_view", "t", "transpose", "unsqueeze", "squeeze", "expand", "split",
                      "split_with_sizes", "chunk", "slice", "select", "permute", "alias", "detach", "unflatten",
                      "as_strided", "unbind", "lift_fresh", "empty", "empty_like", "empty_strided", "promote_types",
                      "device"})
"""Ops that move no tensor bytes: views, allocations (counted where they are written) and `prim::device`."""
BEFORE_GB = 242.9
"""This count on main at 3b7e94c (2026-11-26), before the blocks were written for it: LayerNorm, then the adaLN
modulation's multiply and add; gated residuals as a multiply and an add; RoPE as four products, two sums and a
stack; attention handed heads-outer copies, so its output was copied back; the feed-forward's chunks concatenated;
GELU as its own kernel. GB per paper-size step, fake CUDA tensors (torch 2.14.1+cu130), counted by the rule
of :func:`moved_bytes`."""
SECTOR = 32
"""Bytes a GPU's memory system moves at least per access (an L2 sector)."""
H100_BANDWIDTH = 3.35e12
"""An H100 SXM's HBM3 bandwidth, bytes/s (NVIDIA's datasheet): the floor on the time of a memory-bound op."""


def moved_bytes(t: torch.Tensor) -> int:
    """Bytes a kernel moves to read or write ``t`` once: its elements, without the repeats of a broadcast (a zero
    stride), and times its last dimension's stride when that is 2–``SECTOR`` elements, as for the even or odd
    channels of pairs: a GPU moves whole sectors, so reading every other element moves them all."""
    if t.dim() == 0:
        return t.element_size()
    n = math.prod(size for size, stride in zip(t.shape, t.stride(), strict=True) if stride != 0)
    gap = t.stride(-1) if t.shape[-1] > 1 else 1
    return n * t.element_size() * min(max(gap, 1), max(1, SECTOR // t.element_size()))


class ByteCount(TorchDispatchMode):
    """Bytes read and written per aten op (see the module docstring for the rule)."""

    def __init__(self):
        super().__init__()
        self.bytes, self.calls = collections.Counter(), collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = func.overloadpacket.__name__
        if name not in FREE_OPS:
            read = {id(t): t for t in tree_flatten((args, {k: v for k, v in kwargs.items() if k != "out"}))[0]
                    if isinstance(t, torch.Tensor)}
            written = {id(t): t for t in tree_flatten(out)[0] if isinstance(t, torch.Tensor)}
            self.bytes[name] += sum(map(moved_bytes, [*read.values(), *written.values()]))
            self.calls[name] += 1
        return out


class _FlashAttention(TorchFunctionMode):
    """``scaled_dot_product_attention`` on fake CUDA tensors as FlashAttention, the kernel torch picks on an H100
    for an unmasked call (without a GPU, its kernel choice falls back to the unfused math path)."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func is F.scaled_dot_product_attention:
            if kwargs.get("attn_mask") is not None:
                raise ValueError("the count runs an unmasked prompt, as sampling a one-prompt batch does")
            return torch.ops.aten._scaled_dot_product_flash_attention(*args[:3])[0]
        return func(*args, **kwargs)


def count_step(config: str = "paper", device: str = "cuda", ff_chunk_tokens: int | None = FF_CHUNK_TOKENS,
               dtype: torch.dtype = torch.bfloat16) -> tuple[collections.Counter, collections.Counter, int]:
    """One no-grad forward of ``config``'s DiT at its frames and size with a full-length prompt, on fake tensors.

    Returns:
        (bytes per aten op, calls per aten op, tokens).

    Raises:
        RuntimeError: ``device`` is ``cuda`` and torch was built without CUDA.
    """
    if device == "cuda" and not torch.backends.cuda.is_built():
        raise RuntimeError("--device cuda counts CUDA's ops on fake tensors: it needs a CUDA build of torch "
                           "(no GPU); this torch is a CPU build: use --device cpu")
    count = ByteCount()
    with fake_dit_step(config, ff_chunk_tokens, dtype, device) as (dit, inputs, tokens):
        attention = _FlashAttention() if device == "cuda" else contextlib.nullcontext()
        with torch.no_grad(), attention, count:
            dit(*inputs)
    return count.bytes, count.calls, tokens


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="paper")
    ap.add_argument("--device", choices=("cuda", "cpu"), default="cuda" if torch.backends.cuda.is_built() else "cpu",
                    help="whose ops to count (cuda needs a CUDA build of torch, not a GPU)")
    ap.add_argument("--write", action="store_true", help="write the table into docs/benchmarks.md")
    args = ap.parse_args()
    moved, calls, tokens = count_step(args.config, args.device)
    other = {k: v for k, v in moved.items() if k not in MATMUL_OPS}
    rows = [[f"`{k}`", f"{calls[k]:,}", f"{v / 1e9:.1f}"] for k, v in sorted(other.items(), key=lambda kv: -kv[1])]
    total, matmul = sum(other.values()), sum(v for k, v in moved.items() if k in MATMUL_OPS)
    rows.append(["**outside matmuls and attention**", f"{sum(calls[k] for k in other):,}", f"**{total / 1e9:.1f}**"])
    rows.append(["matmuls and attention (their operands and outputs)", f"{sum(calls[k] for k in MATMUL_OPS):,}",
                 f"{matmul / 1e9:.1f}"])
    note = (f"One no-grad DiT forward of `{args.config}` ({tokens:,} tokens, bfloat16, feed-forward chunk "
            f"{FF_CHUNK_TOKENS:,}, full-length prompt) on fake `{args.device}` tensors; GB = 10⁹ bytes read + "
            f"written per step, by aten op. At an H100's {H100_BANDWIDTH / 1e12:.2f} TB/s the ops outside the "
            f"matmuls and attention take at least {1e3 * total / H100_BANDWIDTH:.0f} ms per step, "
            f"{50 * total / H100_BANDWIDTH:.1f} s over 50 steps.")
    if args.device == "cuda" and args.config == "paper":
        note += (f" Before the blocks were written for it (main at 3b7e94c): {BEFORE_GB:.1f} GB, at least "
                 f"{1e3 * BEFORE_GB * 1e9 / H100_BANDWIDTH:.0f} ms per step; the difference is "
                 f"{50 * (BEFORE_GB * 1e9 - total) / H100_BANDWIDTH:.1f} s over 50 steps at full bandwidth, what the "
                 f"eager paper-size `generate` should gain (measured on a GPU by `benchmarks/gpu.py --part "
                 f"generate`).")
    publish("dit_traffic", "Bytes moved by one DiT sampling step outside its matmuls (fake tensors, any machine)",
            note, markdown_table(["aten op", "calls", "GB"], rows), args.write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
