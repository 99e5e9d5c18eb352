"""benchmarks/dit_traffic.py: its byte-counting rule on ops whose traffic is known, and a count on a tiny DiT."""
import pytest
import torch
from helpers import benchmark_module

traffic = benchmark_module("dit_traffic")


def test_the_count_reads_inputs_writes_outputs_and_skips_views():
    """An out-of-place op reads its inputs and writes its output; an in-place op reads and writes its tensor; an
    ``out=`` op writes its output once; a view and an allocation move nothing."""
    a, b = torch.randn(4, 8), torch.randn(4, 8)  # 128 bytes each
    out = torch.empty(4, 8)
    with traffic.ByteCount() as count:
        a + b
        a.add_(b)
        torch.mul(a, b, out=out)
        a.view(8, 4).t()
        torch.empty_like(a)
    assert dict(count.bytes) == {"add": 3 * 128, "add_": 3 * 128, "mul": 3 * 128}
    assert dict(count.calls) == {"add": 1, "add_": 1, "mul": 1}
    row = torch.randn(8)
    with traffic.ByteCount() as count:
        a * row  # the row broadcast over a's 4 rows: read once
        a[:, ::2] + 1  # every other element read: the sectors of all of them move (output 4 × 4 floats)
    assert dict(count.bytes) == {"mul": 128 + 32 + 128, "add": 128 + 64}


@pytest.mark.slow
def test_a_tiny_dit_step_is_counted_on_the_cpu():
    """The tiny DiT's step: its GEMMs and attention are counted apart, and its LayerNorms move what their inputs
    and outputs hold (one no-grad forward, fake tensors)."""
    moved, calls, tokens = traffic.count_step("tiny", "cpu")
    assert tokens > 0 and calls["addmm"] > 0 and any(k in moved for k in traffic.MATMUL_OPS)
    assert calls["native_layer_norm"] >= 1 and moved["native_layer_norm"] > 0
    assert not set(moved) & traffic.FREE_OPS
