"""3D rotary position embedding (RoPE) for video tokens, real-valued (ONNX-exportable).

RoPE (Su et al. 2021, RoFormer, Eq. 13–15) rotates each channel pair (x_{2i}, x_{2i+1}) of a query/key by m·θ_i,
θ_i = theta^(−2i/d), so logits depend on m − n only. For video the head dimension is split into frame, row and
column parts, each with its own frequency ladder (3D RoPE as in Wan 2.1 / HunyuanVideo).
:func:`apply_rope_complex` is the textbook complex form, the reference of the tests."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["rope_split", "rope_frequencies", "rope_3d", "apply_rope", "apply_rope_complex"]


def rope_split(head_dim: int) -> tuple[int, int, int]:
    """Channels of one head for (frame, row, column): (d − 4⌊d/6⌋, 2⌊d/6⌋, 2⌊d/6⌋), Wan 2.1's rule.

    Raises:
        ValueError: ``head_dim`` is odd or smaller than 6.
    """
    if head_dim % 2 or head_dim < 6:
        raise ValueError(f"head_dim must be even and >= 6 for 3D RoPE, got {head_dim}")
    d_hw = 2 * (head_dim // 6)
    return head_dim - 2 * d_hw, d_hw, d_hw


def rope_frequencies(dim: int, theta: float = 10000.0, device=None) -> Tensor:
    """(dim/2,) float64 angular frequencies θ_i = theta^(−2i/dim), radians per position (RoFormer Eq. 15).

    Raises:
        ValueError: ``dim`` not positive and even, or ``theta`` ≤ 1.
    """
    if dim % 2 or dim <= 0:
        raise ValueError(f"dim must be a positive even number, got {dim}")
    if not theta > 1.0:
        raise ValueError(f"theta must be > 1, got {theta}")
    exponent = torch.arange(0, dim, 2, dtype=torch.float64, device=device) / dim
    return theta ** (-exponent)


def rope_3d(n: int, h: int, w: int, head_dim: int, theta: float = 10000.0, *, dtype: torch.dtype = torch.float32,
            device=None) -> tuple[Tensor, Tensor]:
    """cos/sin tables of 3D RoPE for an n×h×w token grid flattened frame-major: token (f, y, x)'s pairs in the
    :func:`rope_split` parts rotate by f·θ_i, y·θ_i, x·θ_i (RoFormer Eq. 13 per axis); angles in float64, then
    ``dtype``.

    Returns:
        cos, sin: each (n·h·w, head_dim/2); column j rotates channel pair (2j, 2j+1).

    Raises:
        ValueError: a grid size < 1 or an unusable ``head_dim`` / ``theta``.
    """
    for name, size in (("n", n), ("h", h), ("w", w)):
        if size < 1:
            raise ValueError(f"{name} must be >= 1, got {size}")
    d_t, d_h, d_w = rope_split(head_dim)
    parts = []
    for size, dim in ((n, d_t), (h, d_h), (w, d_w)):
        pos = torch.arange(size, dtype=torch.float64, device=device)
        parts.append(pos[:, None] * rope_frequencies(dim, theta, device)[None, :])  # (size, dim/2)
    ang_t = parts[0][:, None, None, :].expand(n, h, w, d_t // 2)
    ang_h = parts[1][None, :, None, :].expand(n, h, w, d_h // 2)
    ang_w = parts[2][None, None, :, :].expand(n, h, w, d_w // 2)
    angles = torch.cat([ang_t, ang_h, ang_w], dim=-1).reshape(n * h * w, head_dim // 2)
    return angles.cos().to(dtype), angles.sin().to(dtype)


def apply_rope(
    x: Tensor,  # (..., N, D) queries or keys; (..., N, heads, D) with token_dim=-3
    cos: Tensor,  # (N, D/2)
    sin: Tensor,  # (N, D/2)
    token_dim: int = -2,
) -> Tensor:
    """Rotate channel pairs of ``x`` by the tabulated angles (RoFormer Eq. 14): (x_{2j}, x_{2j+1}) ↦
    (x_{2j} cos φ − x_{2j+1} sin φ, x_{2j} sin φ + x_{2j+1} cos φ), computed on whole channels as
    x ⊙ cos' + swap(x) ⊙ sin' (contiguous reads).

    Args:
        x: (..., N, D), or (..., N, heads, D) with ``token_dim=-3``; D even.
        cos, sin: (N, D/2) from :func:`rope_3d`.
        token_dim: the dimension of ``x`` the tables' N runs along, −2 or −3.

    Returns ``x``'s shape, dtype and layout.

    Raises:
        ValueError: tables that do not match ``x``, or another ``token_dim``.
    """
    if token_dim not in (-2, -3) or x.dim() < -token_dim:
        raise ValueError(f"token_dim must be -2 or -3 for x of shape {tuple(x.shape)}, got {token_dim}")
    N, D = x.shape[token_dim], x.shape[-1]
    if D % 2 or cos.shape != (N, D // 2) or sin.shape != (N, D // 2):
        raise ValueError(f"cos/sin must have shape ({N}, {D // 2}) for x of shape {tuple(x.shape)}, "
                         f"got {tuple(cos.shape)} and {tuple(sin.shape)}")
    cos2 = torch.stack([cos, cos], dim=-1).flatten(-2).to(x.dtype)  # (N, D): cos φ_j at channels 2j and 2j + 1
    sin2 = torch.stack([-sin, sin], dim=-1).flatten(-2).to(x.dtype)  # (N, D): −sin φ_j, then sin φ_j
    if token_dim == -3:  # (N, 1, D): broadcast over the heads
        cos2, sin2 = cos2[:, None], sin2[:, None]
    swapped = x.unflatten(-1, (D // 2, 2)).flip(-1).flatten(-2)  # (x_{2j+1}, x_{2j}) at channels (2j, 2j + 1)
    return torch.addcmul(x * cos2, swapped, sin2)


def apply_rope_complex(
    x: Tensor,  # (..., N, D)
    freqs_cis: Tensor,  # (N, D/2) complex, unit modulus e^{iφ}
) -> Tensor:
    """Reference: (x_{2j} + i·x_{2j+1})·e^{iφ_j} with ``freqs_cis`` (N, D/2) complex (RoFormer §3.2.2); not
    exportable. Returns ``x``'s shape and dtype."""
    xc = torch.view_as_complex(x.double().unflatten(-1, (x.shape[-1] // 2, 2)).contiguous())
    return torch.view_as_real(xc * freqs_cis.to(torch.complex128)).flatten(-2).to(x.dtype)
