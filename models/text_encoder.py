"""T5-style text encoder (T5 v1.1 encoder architecture) and a dependency-free byte tokenizer.

Raffel et al. 2020 §2.1 with the v1.1 changes (gated-GELU feed-forward, Shazeer 2020 Eq. 6; no embedding
sharing): h_0 = Embed(ids); h' = h + SelfAttn(RMSNorm(h); B); h = h' + W_o(GELU(W_0 RMSNorm(h')) ⊙ W_1 RMSNorm(h'));
out = RMSNorm(h_L). B is the learned relative position bias per (bucket, head), computed once and shared by all
layers; logits are not scaled by 1/√d_kv (folded into W_q's initialisation). :meth:`TextEncoderConfig.paper` is
the T5-v1.1-XXL encoder's shape; :meth:`TextEncoder.forward` takes ids from any tokenizer,
:meth:`TextEncoder.encode_text` uses :class:`ByteTokenizer`."""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diff4splat.utils.checks import check_ranges, ranged
from models.pretrained import PretrainedMixin

__all__ = ["ByteTokenizer", "TextEncoderConfig", "TextEncoder", "relative_position_bucket", "RMSNorm"]


class ByteTokenizer:
    """UTF-8 byte tokenizer: id = byte + 3, pad = 0, bos = 1, eos = 2 (vocabulary 259). A prompt becomes
    ``[bos, b_1 + 3, …, eos]``, keeping its first ``max_length − 2`` bytes (a longer prompt is cut with a
    ``UserWarning``, as diffusers' pipelines warn of a truncated prompt; the rest never reaches the model); a batch is
    right-padded to the longest prompt, or to ``max_length`` with ``padding="max_length"``.

    Raises:
        ValueError: ``max_length`` (including bos and eos) < 2.
    """

    pad_id = 0
    bos_id = 1
    eos_id = 2
    offset = 3
    vocab_size = 256 + offset

    def __init__(self, max_length: int = 64):
        if isinstance(max_length, bool) or not isinstance(max_length, int) or max_length < 2:
            raise ValueError(f"max_length must be an int >= 2 (room for bos and eos), got {max_length!r}")
        self.max_length = max_length

    def __call__(self, prompts: list[str], padding: str = "longest") -> tuple[Tensor, Tensor]:
        """Tokenize B ≥ 1 strings ("" gives ``[bos, eos]``) → ids (B, L) int64 and mask (B, L) bool (True on real
        tokens), both on the CPU.

        Raises:
            ValueError: ``prompts`` empty or not a list of str; unknown ``padding``.
        """
        if isinstance(prompts, str) or not isinstance(prompts, (list, tuple)) or len(prompts) == 0:
            raise ValueError(f"prompts must be a non-empty list of str, got {type(prompts).__name__} {prompts!r:.60}")
        if not all(isinstance(p, str) for p in prompts):
            raise ValueError("prompts must contain only str")
        if padding not in ("longest", "max_length"):
            raise ValueError(f"padding must be 'longest' or 'max_length', got {padding!r}")
        seqs, room = [], self.max_length - 2
        if any(len(p.encode("utf-8")) > room for p in prompts):
            # one message per tokenizer size, so that a training run's captions warn once, not every step
            warnings.warn(f"a prompt longer than {room} UTF-8 bytes is cut to its first {room} (the byte tokenizer's "
                          f"max_length {self.max_length}): the rest does not reach the model", stacklevel=2)
        for p in prompts:
            body = [b + self.offset for b in p.encode("utf-8")[:room]]
            seqs.append([self.bos_id, *body, self.eos_id])
        length = self.max_length if padding == "max_length" else max(len(s) for s in seqs)
        ids = torch.full((len(seqs), length), self.pad_id, dtype=torch.long, device="cpu")  # as tokenizers do
        for i, s in enumerate(seqs):
            ids[i, : len(s)] = torch.tensor(s, dtype=torch.long, device="cpu")
        return ids, ids != self.pad_id

    def decode(self, ids: Tensor) -> list[str]:
        """Inverse of :meth:`__call__` for (B, L) ids: special ids dropped, invalid UTF-8 → U+FFFD."""
        return [bytes(int(i) - self.offset for i in row if int(i) >= self.offset).decode("utf-8", errors="replace")
                for row in ids]


@dataclass
class TextEncoderConfig:
    """T5-encoder hyper-parameters; defaults are the tiny CPU model.

    Attributes:
        vocab_size: embedding rows (≥ 259 for the byte tokenizer).
        d_model: token width = d_text of the output.
        num_layers, num_heads: transformer blocks and attention heads.
        d_kv: width per head (num_heads·d_kv need not equal d_model).
        d_ff: hidden width of the gated-GELU feed-forward.
        num_buckets: relative-position buckets (even, ≥ 4; half per direction).
        max_distance: offsets ≥ this share the last log-spaced bucket.
        max_length: tokenizer length limit used by :meth:`TextEncoder.encode_text`.
        eps: RMSNorm epsilon.

    Raises:
        ValueError: a field out of range.
    """

    vocab_size: int = ranged(259)
    d_model: int = ranged(64)
    num_layers: int = ranged(2)
    num_heads: int = ranged(4)
    d_kv: int = ranged(16)
    d_ff: int = ranged(128)
    num_buckets: int = ranged(32)
    max_distance: int = ranged(128)
    max_length: int = ranged(64)
    eps: float = 1e-6

    def __post_init__(self) -> None:
        check_ranges("TextEncoderConfig", self)
        if self.vocab_size < ByteTokenizer.vocab_size:
            raise ValueError(f"TextEncoderConfig.vocab_size must be >= {ByteTokenizer.vocab_size} "
                             f"(byte tokenizer), got {self.vocab_size}")
        if self.num_buckets < 4 or self.num_buckets % 2:
            raise ValueError(f"TextEncoderConfig.num_buckets must be an even int >= 4, got {self.num_buckets}")
        if self.max_length < 2:
            raise ValueError(f"TextEncoderConfig.max_length must be >= 2, got {self.max_length}")

    @classmethod
    def paper(cls) -> TextEncoderConfig:
        """T5-v1.1-XXL encoder shape (:data:`PAPER_TEXT_ENCODER`)."""
        return cls(**PAPER_TEXT_ENCODER)


PAPER_TEXT_ENCODER: dict = dict(vocab_size=32128, d_model=4096, num_layers=24, num_heads=64, d_kv=64, d_ff=10240,
                                num_buckets=32, max_distance=128, max_length=226, eps=1e-6)
"""google/t5-v1_1-xxl encoder; max_length 226 is CogVideoX's prompt length (our choice)."""


def relative_position_bucket(relative_position: Tensor, num_buckets: int = 32, max_distance: int = 128) -> Tensor:
    """Bidirectional T5 bucket of key − query offsets (Raffel et al. 2020 §2.1; Mesh-TF
    ``_relative_position_bucket``): half the buckets for positive offsets; within a half |r| < n/4 exact, larger ones
    b = n/4 + ⌊log(|r|/(n/4)) / log(max_distance/(n/4)) · (n/4)⌋, clipped. Integer tensor → int64 of its shape in
    [0, num_buckets)."""
    half = num_buckets // 2
    bucket = (relative_position > 0).long() * half
    n = relative_position.abs()
    max_exact = half // 2
    # Clamp to 1 before the log only to avoid log(0); those entries take the exact branch anyway.
    large = max_exact + (torch.log(n.clamp(min=1).float() / max_exact) / math.log(max_distance / max_exact)
                         * (half - max_exact)).long()
    large = large.clamp(max=half - 1)
    return bucket + torch.where(n < max_exact, n, large)


class RMSNorm(nn.Module):
    """T5 layer norm w · x / √(mean(x²) + eps) (Zhang & Sennrich 2019), statistic in float32. (..., d) → (..., d)."""

    def __init__(self, dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))  # device: the construction context's (torch.device(…), meta)

    def forward(self, x: Tensor) -> Tensor:
        var = x.float().pow(2).mean(-1, keepdim=True)
        return self.weight * (x.float() * torch.rsqrt(var + self.eps)).to(x.dtype)


class T5Attention(nn.Module):
    """Multi-head self-attention without biases or 1/√d scaling; adds the shared position bias."""

    def __init__(self, config: TextEncoderConfig):
        super().__init__()
        inner = config.num_heads * config.d_kv
        self.num_heads, self.d_kv = config.num_heads, config.d_kv
        self.q = nn.Linear(config.d_model, inner, bias=False)
        self.k = nn.Linear(config.d_model, inner, bias=False)
        self.v = nn.Linear(config.d_model, inner, bias=False)
        self.o = nn.Linear(inner, config.d_model, bias=False)

    def forward(self, x: Tensor, bias: Tensor) -> Tensor:
        """x (B, L, d_model), bias (B or 1, heads, L, L) position bias + additive mask → (B, L, d_model)."""
        b, length, _ = x.shape
        q, k, v = (proj(x).view(b, length, self.num_heads, self.d_kv).transpose(1, 2)
                   for proj in (self.q, self.k, self.v))
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias, scale=1.0)
        return self.o(out.transpose(1, 2).reshape(b, length, -1))


class T5Block(nn.Module):
    """Pre-norm residual block: self-attention then gated-GELU feed-forward (T5 v1.1)."""

    def __init__(self, config: TextEncoderConfig):
        super().__init__()
        self.attn_norm = RMSNorm(config.d_model, config.eps)
        self.attn = T5Attention(config)
        self.ff_norm = RMSNorm(config.d_model, config.eps)
        self.wi_0 = nn.Linear(config.d_model, config.d_ff, bias=False)
        self.wi_1 = nn.Linear(config.d_model, config.d_ff, bias=False)
        self.wo = nn.Linear(config.d_ff, config.d_model, bias=False)

    def forward(self, x: Tensor, bias: Tensor) -> Tensor:
        """x (B, L, d_model), bias as :class:`T5Attention` → (B, L, d_model)."""
        x = x + self.attn(self.attn_norm(x), bias)
        h = self.ff_norm(x)
        # GEGLU (Shazeer 2020, Eq. 6) with the tanh GELU approximation T5 v1.1 uses ("gelu_new").
        return x + self.wo(F.gelu(self.wi_0(h), approximate="tanh") * self.wi_1(h))


class TextEncoder(nn.Module, PretrainedMixin):
    """T5 v1.1 encoder: prompts → per-token features for the video DiT's cross-attention."""

    config_class = TextEncoderConfig

    def __init__(self, config: TextEncoderConfig):
        super().__init__()
        self.config = config
        self.tokenizer = ByteTokenizer(config.max_length)
        self.embed = nn.Embedding(config.vocab_size, config.d_model)
        # One table for all layers (T5 stores it in layer 0 and reuses the computed bias).
        self.relative_attention_bias = nn.Embedding(config.num_buckets, config.num_heads)
        self.blocks = nn.ModuleList([T5Block(config) for _ in range(config.num_layers)])
        self.final_norm = RMSNorm(config.d_model, config.eps)
        self._init_weights()

    def _init_weights(self) -> None:
        """Mesh-TF / HF T5 initialisation: N(0, fan-in⁻¹), W_q (d_model·d_kv)^-½ (the folded 1/√d_kv),
        embeddings σ = 1, norm weights 1."""
        c = self.config
        nn.init.normal_(self.embed.weight, std=1.0)
        nn.init.normal_(self.relative_attention_bias.weight, std=c.d_model ** -0.5)
        for block in self.blocks:
            nn.init.normal_(block.attn.q.weight, std=(c.d_model * c.d_kv) ** -0.5)
            for lin in (block.attn.k, block.attn.v, block.wi_0, block.wi_1):
                nn.init.normal_(lin.weight, std=c.d_model ** -0.5)
            nn.init.normal_(block.attn.o.weight, std=(c.num_heads * c.d_kv) ** -0.5)
            nn.init.normal_(block.wo.weight, std=c.d_ff ** -0.5)

    def position_bias(self, length: int) -> Tensor:
        """Relative position bias (1, heads, L, L), [0, h, i, j] for query i, key j."""
        pos = torch.arange(length, device=self.embed.weight.device)
        buckets = relative_position_bucket(pos[None, :] - pos[:, None], self.config.num_buckets,
                                           self.config.max_distance)
        return self.relative_attention_bias(buckets).permute(2, 0, 1)[None]

    def forward(self, ids: Tensor, mask: Tensor | None = None) -> Tensor:
        """Encode ids (B, L) int64 in [0, vocab_size) with ``mask`` (B, L) bool (None = all real; ≥ 1 real token a
        row; padded keys get −∞ logits) → (B, L, d_model) in the embedding dtype, zero at padding.

        Raises:
            ValueError: wrong ranks/shapes, ids out of range, or a row without real tokens.
        """
        if ids.ndim != 2:
            raise ValueError(f"ids must have shape (B, L), got {tuple(ids.shape)}")
        if mask is None:
            mask = torch.ones_like(ids, dtype=torch.bool)
        if mask.shape != ids.shape or mask.dtype != torch.bool:
            raise ValueError(f"mask must be bool with shape {tuple(ids.shape)}, got {mask.dtype} {tuple(mask.shape)}")
        # Value checks need data: not on meta tensors nor while exporting (the tokenizer checks ids there).
        if ids.device.type != "meta" and not torch.compiler.is_exporting():
            if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self.config.vocab_size):
                raise ValueError(f"ids must lie in [0, {self.config.vocab_size}), "
                                 f"got [{int(ids.min())}, {int(ids.max())}]")
            if not bool(mask.any(dim=1).all()):
                raise ValueError("mask: every sequence needs at least one real token")
        x = self.embed(ids)
        neg = torch.finfo(x.dtype).min
        key_mask = torch.zeros(mask.shape, dtype=x.dtype, device=x.device).masked_fill(~mask, neg)
        bias = self.position_bias(ids.shape[1]).to(x.dtype) + key_mask[:, None, None, :]
        for block in self.blocks:
            x = block(x, bias)
        return self.final_norm(x) * mask[..., None].to(x.dtype)

    def encode_text(self, prompts: list[str], padding: str = "longest") -> tuple[Tensor, Tensor]:
        """:class:`ByteTokenizer` then :meth:`forward` → tokens (B, L, d_model) and mask (B, L) on the model's
        device; with a graph where gradients are enabled (a stage that trains the text encoder), so inference calls
        it under ``torch.no_grad``. ValueError from the tokenizer."""
        ids, mask = self.tokenizer(prompts, padding=padding)
        device = self.embed.weight.device
        ids, mask = ids.to(device), mask.to(device)
        return self(ids, mask), mask
