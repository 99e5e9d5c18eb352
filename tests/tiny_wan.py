"""A tiny random Wan2.2-TI2V backbone for the tests (issue 30): nothing is downloaded.

Sizes follow diffusers' own Wan2.2 TI2V-5B pipeline tests (tests/pipelines/wan/test_wan_22_image_to_video.py,
``Wan225BImageToVideoPipelineFastTests``): a 2-layer transformer of 2 heads of 12 channels, ffn 32, 48 channels in
and out, patch (1, 2, 2); a Wan2.2-style VAE (base_dim 3, z_dim 48, residual, patch_size 2, 4×16×16) — here with
non-trivial ``latents_mean``/``latents_std`` so that the normalisation is exercised. The text encoder is a 2-layer
UMT5 of width 16 over :func:`tests.tiny_backbones.tiny_tokenizer`; the scheduler is the flow-matching Euler one
with Wan2.2 TI2V-5B's shift 5.0 (the Hub folder's UniPC is a multistep solver, which our Euler sampler does not
reproduce step for step).
"""
from __future__ import annotations

from pathlib import Path

import pytest

diffusers = pytest.importorskip("diffusers", reason="the diffusers backbones need diff4splat[diffusers]")
pytest.importorskip("ftfy", reason="diffusers' Wan prompt cleaning needs ftfy (diff4splat[diffusers])")

import torch  # noqa: E402
from tiny_backbones import tiny_tokenizer  # noqa: E402
from transformers import UMT5Config, UMT5EncoderModel  # noqa: E402

from models.backbones.wan import WanBackbone  # noqa: E402

TEXT_DIM = 16
HEIGHT, WIDTH, FRAMES = 64, 32, 9
"""Pixels of the tiny clips: latents (48, 3, 4, 2), 2×1 tokens a latent frame (patch 2×2)."""


def tiny_wan_components(seed: int = 0) -> dict:
    """Random components of a Wan2.2-TI2V pipeline (the transformer, VAE and text encoder seeded)."""
    torch.manual_seed(seed)
    transformer = diffusers.WanTransformer3DModel(
        patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=12, in_channels=48, out_channels=48,
        text_dim=TEXT_DIM, freq_dim=256, ffn_dim=32, num_layers=2, cross_attn_norm=True,
        qk_norm="rms_norm_across_heads", rope_max_seq_len=32)
    torch.manual_seed(seed + 1)
    vae = diffusers.AutoencoderKLWan(
        base_dim=3, z_dim=48, in_channels=12, out_channels=12, is_residual=True, patch_size=2,
        latents_mean=[0.05 * (i - 24) for i in range(48)], latents_std=[0.5 + 0.03 * i for i in range(48)],
        dim_mult=[1, 1, 1, 1], num_res_blocks=1, scale_factor_spatial=16, scale_factor_temporal=4,
        temperal_downsample=[False, True, True])
    tokenizer = tiny_tokenizer()
    torch.manual_seed(seed + 2)
    # 64 rows, or one per piece where the tokenizer has more: sentencepiece 0.2.3 trains 59 pieces, 0.2.2 trains 68
    # (an id beyond the table is an IndexError in the encoder's embedding).
    text_encoder = UMT5EncoderModel(UMT5Config(
        vocab_size=max(64, len(tokenizer)), d_model=TEXT_DIM, d_kv=8, d_ff=32, num_layers=2, num_heads=2,
        relative_attention_num_buckets=8, relative_attention_max_distance=16, pad_token_id=0, eos_token_id=1,
        decoder_start_token_id=0))
    scheduler = diffusers.FlowMatchEulerDiscreteScheduler(shift=5.0)
    return {"transformer": transformer, "vae": vae, "text_encoder": text_encoder, "tokenizer": tokenizer,
            "scheduler": scheduler}


def tiny_wan(seed: int = 0) -> WanBackbone:
    """A :class:`WanBackbone` over :func:`tiny_wan_components` (eval mode, camera weights zero)."""
    return WanBackbone(**tiny_wan_components(seed)).eval()


def write_tiny_wan(folder: Path, seed: int = 0, camera_seed: int | None = None) -> WanBackbone:
    """Write a tiny backbone's Hub-layout folder into ``folder`` (created) and return the backbone written.

    Args:
        camera_seed: when given, the camera weights are random (seeded) instead of zero.
    """
    backbone = tiny_wan(seed)
    if camera_seed is not None:
        weight = backbone.camera_conv.camera_weight
        with torch.no_grad():
            weight.copy_(torch.randn(weight.shape, generator=torch.Generator().manual_seed(camera_seed)) * 0.02)
    folder.mkdir(parents=True, exist_ok=True)
    backbone.write_pretrained(folder)
    return backbone
