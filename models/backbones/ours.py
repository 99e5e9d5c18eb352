"""Our own networks as a :class:`models.backbone.Backbone`: the video VAE, the byte-level T5 text encoder
and the VideoDiT of a :class:`models.bundle.Diff4SplatModel` (the CPU default), unchanged: every method is a call
of the network's own method, and the velocity network is the DiT itself, so outputs are bit-identical to calling
the networks directly."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..backbone import Backbone
from ..dit import VideoDiT
from ..flow_matching import sample_logit_normal, shift_sigmas, sigma_schedule
from ..text_encoder import TextEncoder
from ..vae import VideoVAE

__all__ = ["OursBackbone"]


class OursBackbone(Backbone):
    """Backbone over our VAE, text encoder and DiT (their modules are shared, not copied).

    Args:
        vae, text_encoder, dit: the networks of a :class:`models.bundle.Diff4SplatModel`.
        shift: the flow-matching timestep shift of the inference schedule and of :meth:`training_sigmas`
            (``config.sampling.shift``; a training stage passes its ``flow_shift``).
        logit_normal: (mean, std) of the logit-normal training σ before the shift (``config.sampling``'s
            ``logit_normal_mean``, ``logit_normal_std``; SD3 §3.1 uses (0, 1)).
    """

    kind = "ours"

    def __init__(self, vae: VideoVAE, text_encoder: TextEncoder, dit: VideoDiT, shift: float = 1.0,
                 logit_normal: tuple[float, float] = (0.0, 1.0)):
        super().__init__()
        self.vae, self.text_encoder, self.dit, self.shift = vae, text_encoder, dit, shift
        self.logit_normal = tuple(logit_normal)
        self.latent = vae.config.latent_format

    def encode_video(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """:meth:`VideoVAE.encode_latents`: video (B, 3, T, H, W) pixels in [−1, 1], T = 1 + 4k, H and W multiples
        of 8 → DiT-scaled latents (B, c, 1 + k, H/8, W/8): the posterior mean, or a sample drawn with ``generator``.

        Raises:
            ValueError: from :meth:`VideoVAE.encode` (wrong rank or channels, T ≠ 1 + 4k, H/W not multiples of 8).
        """
        return self.vae.encode_latents(video, sample_posterior=generator is not None, generator=generator)

    def decode_latents(self, latents: Tensor) -> Tensor:
        """:meth:`VideoVAE.decode_latents`: DiT-scaled latents (B, c, n, h, w) → video (B, 3, 1 + 4(n − 1), 8h, 8w),
        pixels nominally in [−1, 1]."""
        return self.vae.decode_latents(latents)

    def encode_text(self, prompts: list[str]) -> tuple[Tensor, Tensor]:
        """:meth:`TextEncoder.encode` (byte tokens): B prompts → tokens (B, L, d_text) (zeros at padding) and
        mask (B, L) bool (True = real token), on the text encoder's device.

        Raises:
            ValueError: from :meth:`TextEncoder.encode` (:meth:`models.text_encoder.ByteTokenizer.__call__`).
        """
        return self.text_encoder.encode(prompts)

    @property
    def velocity_model(self) -> VideoDiT:
        """The DiT: :meth:`VideoDiT.forward` is the velocity (the image latent concatenated with a frame-0 mask; no
        prompt: no text tokens, the text encoder does not run). It takes x (B, c, n, h, w), sigma (B,) in [0, 1],
        image_latent (B, c, 1, h, w), plucker (B, 6·t·s², n, h, w), text (B, L, d_text) and text_mask (B, L) bool
        or None, and returns (B, c, n, h, w) ε − x0 in its parameter dtype; ValueError for a shape or dtype, σ
        outside [0, 1], a mask without text."""
        return self.dit

    def sigmas(self, steps: int) -> Tensor:
        """:func:`models.flow_matching.sigma_schedule` with :attr:`shift`: (steps + 1,) float64, decreasing from
        1 to 0."""
        return sigma_schedule(steps, self.shift, dtype=torch.float64)

    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) float32 logit-normal σ in [0, 1] (SD3 §3.1, :attr:`logit_normal`) shifted by :attr:`shift`, on
        ``generator``'s device (``training.losses.sample_training_sigmas``' draw)."""
        mean, std = self.logit_normal
        return shift_sigmas(sample_logit_normal(n, mean, std, generator=generator, device=generator.device), self.shift)

    def transformer_blocks(self) -> list[nn.Module]:
        """The DiT's ``config.depth`` blocks (:class:`models.dit.VideoDiTBlock`), in order; each maps tokens
        (B, N, D) → (B, N, D)."""
        return list(self.dit.blocks)
