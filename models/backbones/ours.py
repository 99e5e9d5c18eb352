"""Our own networks (video VAE, byte-level T5 text encoder, VideoDiT of a :class:`models.bundle.Diff4SplatModel`)
as a :class:`models.backbone.Backbone`, the CPU default: every method calls the network's own, so outputs are
bit-identical to calling the networks directly."""
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
    """Backbone over our VAE, text encoder and DiT (shared, not copied).

    Args:
        vae, text_encoder, dit: the networks of a :class:`models.bundle.Diff4SplatModel`.
        shift: flow-matching timestep shift of :meth:`sigmas` and :meth:`training_sigmas`.
        logit_normal: (mean, std) of the logit-normal training σ before the shift (SD3 §3.1).
    """

    kind = "ours"

    def __init__(self, vae: VideoVAE, text_encoder: TextEncoder, dit: VideoDiT, shift: float = 1.0,
                 logit_normal: tuple[float, float] = (0.0, 1.0)):
        super().__init__()
        self.vae, self.text_encoder, self.dit, self.shift = vae, text_encoder, dit, shift
        self.logit_normal = tuple(logit_normal)
        self.latent = vae.config.latent_format

    @property
    def latent_model(self) -> VideoVAE:
        """The VAE (:meth:`VideoVAE.encode_latents`, :meth:`VideoVAE.decode_latents`)."""
        return self.vae

    @property
    def text_model(self) -> TextEncoder:
        """The text encoder (:meth:`TextEncoder.encode_text`)."""
        return self.text_encoder

    @property
    def velocity_model(self) -> VideoDiT:
        """The DiT (:meth:`VideoDiT.forward`); without a prompt no text tokens and no text encoder run."""
        return self.dit

    def sigmas(self, steps: int) -> Tensor:
        """:func:`models.flow_matching.sigma_schedule` with :attr:`shift`: (steps + 1,) float64 from 1 to 0."""
        return sigma_schedule(steps, self.shift, dtype=torch.float64)

    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) float32 logit-normal σ (:attr:`logit_normal`) shifted by :attr:`shift`, on ``generator``'s device."""
        mean, std = self.logit_normal
        return shift_sigmas(sample_logit_normal(n, mean, std, generator=generator, device=generator.device), self.shift)

    def transformer_blocks(self) -> list[nn.Module]:
        """The DiT's blocks in order."""
        return list(self.dit.blocks)
