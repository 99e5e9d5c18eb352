import math

import pytest
import torch

from models.rope import apply_rope, apply_rope_complex, rope_3d, rope_frequencies, rope_split


def _grid_index(f, y, x, h, w):
    return (f * h + y) * w + x


def _complex_freqs_reference(n, h, w, head_dim, theta):
    """Independent per-token construction of e^{iφ} (LLaMA / Wan style), float64 complex."""
    d_t, d_h, d_w = rope_split(head_dim)
    rows = []
    for f in range(n):
        for y in range(h):
            for x in range(w):
                phases = []
                for pos, dim in ((f, d_t), (y, d_h), (x, d_w)):
                    phases += [pos * theta ** (-(2 * i) / dim) for i in range(dim // 2)]
                rows.append(torch.polar(torch.ones(len(phases), dtype=torch.float64),
                                        torch.tensor(phases, dtype=torch.float64)))
    return torch.stack(rows)


def test_split_matches_wan_rule():
    assert rope_split(128) == (44, 42, 42)
    assert rope_split(16) == (8, 4, 4)
    assert sum(rope_split(64)) == 64 and all(d % 2 == 0 for d in rope_split(64))
    with pytest.raises(ValueError, match="head_dim"):
        rope_split(15)
    with pytest.raises(ValueError, match="head_dim"):
        rope_split(4)


def test_frequencies_closed_form():
    f = rope_frequencies(8, theta=10000.0)
    expected = torch.tensor([1.0, 10000 ** -0.25, 10000 ** -0.5, 10000 ** -0.75], dtype=torch.float64)
    torch.testing.assert_close(f, expected, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="dim"):
        rope_frequencies(7)
    with pytest.raises(ValueError, match="theta"):
        rope_frequencies(8, theta=1.0)


def test_tables_equal_complex_formulation():
    n, h, w, d, theta = 3, 2, 4, 16, 100.0
    cos, sin = rope_3d(n, h, w, d, theta, dtype=torch.float64)
    ref = _complex_freqs_reference(n, h, w, d, theta)
    assert cos.shape == sin.shape == (n * h * w, d // 2)
    torch.testing.assert_close(cos, ref.real, rtol=0, atol=1e-12)
    torch.testing.assert_close(sin, ref.imag, rtol=0, atol=1e-12)
    x = torch.randn(2, 3, n * h * w, d, dtype=torch.float64)
    torch.testing.assert_close(apply_rope(x, cos, sin), apply_rope_complex(x, ref), rtol=0, atol=1e-12)


def test_rotation_gives_the_reference_in_both_layouts_and_its_gradients():
    """apply_rope equals the complex-number reference for heads-outer (B, heads, N, D) and heads-inner (B, N, heads,
    D, ``token_dim=-3``) tensors, keeps the input's memory layout, and passes gradcheck."""
    n, h, w, d = 2, 2, 3, 12
    cos, sin = rope_3d(n, h, w, d, theta=30.0, dtype=torch.float64)
    ref_tables = _complex_freqs_reference(n, h, w, d, 30.0)
    x = torch.randn(2, 3, n * h * w, d, dtype=torch.float64)  # (B, heads, N, D)
    expected = apply_rope_complex(x, ref_tables)
    torch.testing.assert_close(apply_rope(x, cos, sin), expected, rtol=0, atol=1e-12)
    inner = x.transpose(1, 2)  # (B, N, heads, D), a strided view of x's storage
    out = apply_rope(inner, cos, sin, token_dim=-3)
    assert out.stride() == inner.stride()  # the layout the caller handed in
    torch.testing.assert_close(out, expected.transpose(1, 2), rtol=0, atol=1e-12)
    torch.testing.assert_close(apply_rope(inner.contiguous(), cos, sin, token_dim=-3), out, rtol=0, atol=1e-12)
    small = torch.randn(1, n * h * w, 2, d, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: apply_rope(t, cos, sin, token_dim=-3), (small,))
    with pytest.raises(ValueError, match="token_dim"):
        apply_rope(x, cos, sin, token_dim=-1)


def test_bfloat16_rotation_rounds_no_worse_than_the_textbook_formula():
    """A multiply and a fused multiply-add round twice per output channel, the textbook four products and two sums
    three times: against the float64 rotation of the same bfloat16 input and tables, the mean error is no larger
    (9.7e-4 against 1.04e-3 here; the last rounding, of the output, dominates both)."""
    cos, sin = rope_3d(4, 8, 8, 64, dtype=torch.bfloat16)
    x = torch.randn(2, 4, 256, 64, generator=torch.Generator().manual_seed(0)).bfloat16()
    truth = apply_rope(x.double(), cos.double(), sin.double())
    c, s = cos, sin
    pairs = x.unflatten(-1, (32, 2))
    x0, x1 = pairs[..., 0], pairs[..., 1]
    textbook = torch.stack([x0 * c - x1 * s, x0 * s + x1 * c], dim=-1).flatten(-2)
    ours = apply_rope(x, c, s)
    assert ours.dtype == torch.bfloat16
    err_ours = float((ours.double() - truth).abs().mean())
    err_textbook = float((textbook.double() - truth).abs().mean())
    assert err_ours <= err_textbook, (err_ours, err_textbook)


def test_norm_preserved_and_origin_untouched():
    cos, sin = rope_3d(2, 3, 3, 24, dtype=torch.float64)
    x = torch.randn(4, 18, 24, dtype=torch.float64)
    y = apply_rope(x, cos, sin)
    torch.testing.assert_close(y.norm(dim=-1), x.norm(dim=-1), rtol=1e-12, atol=0)
    torch.testing.assert_close(y[:, 0], x[:, 0], rtol=0, atol=0)  # position (0, 0, 0) → angle 0
    assert not torch.allclose(y[:, 1:], x[:, 1:])


def test_dot_product_depends_only_on_offset():
    n, h, w, d = 4, 5, 6, 24
    cos, sin = rope_3d(n, h, w, d, theta=50.0, dtype=torch.float64)
    q = torch.randn(d, dtype=torch.float64)
    k = torch.randn(d, dtype=torch.float64)
    qs = apply_rope(q.expand(n * h * w, d), cos, sin)
    ks = apply_rope(k.expand(n * h * w, d), cos, sin)
    offset = (1, 2, -3)
    dots = []
    for f, y, x in [(0, 0, 3), (2, 1, 4), (1, 2, 5), (2, 2, 3)]:  # all pairs inside the grid
        i = _grid_index(f, y, x, h, w)
        j = _grid_index(f + offset[0], y + offset[1], x + offset[2], h, w)
        dots.append(qs[i] @ ks[j])
    for dot in dots[1:]:
        assert math.isclose(dot.item(), dots[0].item(), rel_tol=0, abs_tol=1e-10)
    # a different offset gives a different logit (the rotation is not trivial along any axis)
    i = _grid_index(0, 0, 3, h, w)
    for other in [(1, 2, -2), (1, 1, -3), (0, 2, -3)]:
        j = _grid_index(other[0], other[1], 3 + other[2], h, w)
        assert abs((qs[i] @ ks[j]).item() - dots[0].item()) > 1e-6


def test_axes_rotate_their_own_channels():
    n, h, w, d = 3, 3, 3, 16
    d_t, d_h, _ = rope_split(d)
    cos, sin = rope_3d(n, h, w, d)
    moved_t = _grid_index(1, 0, 0, h, w)  # only the frame index changes
    assert torch.all(sin[moved_t, : d_t // 2] != 0)
    assert torch.all(sin[moved_t, d_t // 2:] == 0)
    moved_w = _grid_index(0, 0, 2, h, w)  # only the column index changes
    assert torch.all(sin[moved_w, : (d_t + d_h) // 2] == 0)
    assert torch.all(sin[moved_w, (d_t + d_h) // 2:] != 0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="n must be"):
        rope_3d(0, 2, 2, 16)
    cos, sin = rope_3d(1, 2, 2, 16)
    with pytest.raises(ValueError, match="cos/sin"):
        apply_rope(torch.randn(2, 5, 16), cos, sin)
