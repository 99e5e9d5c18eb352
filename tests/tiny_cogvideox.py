"""A tiny random CogVideoX-I2V backbone built in the tests (issue 30): nothing is downloaded.

Sizes follow diffusers' own fast tests (huggingface/diffusers, tests/pipelines/cogvideo/
test_cogvideox_image2video.py, ``get_dummy_components``): a one-layer transformer of 2 heads × 16 with rotary and
learned positional embeddings for 2×2 latents (16×16 pixels) and 9 frames (3 latent frames), a 4-block VAE of 8
channels with 4 latent channels; here a scaling factor of 0.7 (CogVideoX-5B's), a 2-layer T5 encoder of width 32
over :func:`tiny_backbones.tiny_tokenizer`, and the ``CogVideoXDDIMScheduler`` of ``THUDM/CogVideoX-5b-I2V``.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

diffusers = pytest.importorskip("diffusers", reason="the CogVideoX backbone needs diff4splat[diffusers]")

from diffusers import AutoencoderKLCogVideoX, CogVideoXDDIMScheduler, CogVideoXTransformer3DModel  # noqa: E402
from tiny_backbones import tiny_tokenizer  # noqa: E402
from transformers import T5Config, T5EncoderModel  # noqa: E402

from models.backbones.cogvideox import CogVideoXBackbone  # noqa: E402

HEIGHT = WIDTH = 16
"""Pixels (2×2 latents: the transformer's learned positional embeddings fix them)."""
FRAMES = 9
"""Frames (3 latent frames)."""
TEXT_LENGTH = 16
"""The transformer's ``max_text_seq_length`` (226 in CogVideoX)."""

SCHEDULER = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                 clip_sample=False, set_alpha_to_one=True, steps_offset=0, prediction_type="v_prediction",
                 timestep_spacing="trailing", rescale_betas_zero_snr=True, snr_shift_scale=1.0)
"""``THUDM/CogVideoX-5b-I2V``'s ``scheduler/scheduler_config.json``."""


def tiny_components(seed: int = 0) -> dict:
    """The pipeline's components, random and seeded: transformer, vae, text_encoder, tokenizer, scheduler."""
    torch.manual_seed(seed)
    transformer = CogVideoXTransformer3DModel(
        num_attention_heads=2, attention_head_dim=16, in_channels=8, out_channels=4, time_embed_dim=2,
        text_embed_dim=32, num_layers=1, sample_width=WIDTH // 8, sample_height=HEIGHT // 8, sample_frames=FRAMES,
        patch_size=2, temporal_compression_ratio=4, max_text_seq_length=TEXT_LENGTH,
        use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
    torch.manual_seed(seed + 1)
    vae = AutoencoderKLCogVideoX(
        in_channels=3, out_channels=3, down_block_types=("CogVideoXDownBlock3D",) * 4,
        up_block_types=("CogVideoXUpBlock3D",) * 4, block_out_channels=(8, 8, 8, 8), latent_channels=4,
        layers_per_block=1, norm_num_groups=2, temporal_compression_ratio=4, scaling_factor=0.7)
    tokenizer = tiny_tokenizer()
    torch.manual_seed(seed + 2)
    text_encoder = T5EncoderModel(T5Config(
        vocab_size=len(tokenizer), d_model=32, d_kv=8, d_ff=37, num_layers=2, num_heads=4,
        relative_attention_num_buckets=8, dropout_rate=0.0, pad_token_id=0, eos_token_id=1))
    return {"transformer": transformer.eval(), "vae": vae.eval(), "text_encoder": text_encoder.eval(),
            "tokenizer": tokenizer, "scheduler": CogVideoXDDIMScheduler(**SCHEDULER)}


def tiny_backbone(seed: int = 0, camera_std: float = 0.0) -> CogVideoXBackbone:
    """:class:`CogVideoXBackbone` over :func:`tiny_components`; ``camera_std`` > 0 fills the zero-initialised
    camera weights with N(0, camera_std²) (seeded)."""
    backbone = CogVideoXBackbone(**tiny_components(seed)).eval()
    if camera_std:
        g = torch.Generator().manual_seed(seed + 3)
        weight = backbone.camera_conv.camera_weight
        with torch.no_grad():
            weight.copy_(torch.randn(weight.shape, generator=g) * camera_std)
    return backbone


def write_tiny_folder(folder: Path, seed: int = 0, camera_std: float = 0.0) -> CogVideoXBackbone:
    """Write :func:`tiny_backbone`'s Hub-layout folder (and ``camera/``) into the existing ``folder``; returns
    the backbone written."""
    backbone = tiny_backbone(seed, camera_std)
    backbone.write_pretrained(Path(folder))
    return backbone


def tiny_inputs(backbone: CogVideoXBackbone, batch: int = 1, seed: int = 0) -> dict:
    """Random ``velocity`` inputs on the tiny grid: x, image_latent, plucker (float32, seeded)."""
    g = torch.Generator().manual_seed(seed)
    fmt = backbone.latent
    n, h, w = fmt.num_latent_frames(FRAMES), HEIGHT // fmt.spatial_factor, WIDTH // fmt.spatial_factor
    c = fmt.latent_channels
    return {"x": torch.randn(batch, c, n, h, w, generator=g),
            "image_latent": torch.randn(batch, c, 1, h, w, generator=g),
            "plucker": torch.randn(batch, fmt.camera_channels, n, h, w, generator=g)}
