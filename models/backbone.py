"""What the pipeline and the training stages need from a video backbone: VAE + text encoder + a
camera-conditioned video transformer (docs/DESIGN.md, "Backbones"): the :class:`Backbone` interface, the
:class:`LatentFormat` of its latents and the shape checks of its velocity (:func:`check_velocity_inputs`).

Three implementations, the adapters of :mod:`models.backbones`: our own networks (:mod:`models.backbones.ours`, the
CPU default), Wan2.2-TI2V-5B (:mod:`models.backbones.wan`) and CogVideoX-5B-I2V (:mod:`models.backbones.cogvideox`),
the last two built from diffusers' modules (the optional extra ``diff4splat[diffusers]``).

Conventions every backbone obeys, whatever its own:

- **Latents** are the transformer's inputs: the VAE's posterior mean *normalised the backbone's way* (ours
  ``a·(z − b)``, Wan ``(z − mean)/std`` per channel, CogVideoX ``z·scaling_factor``), shape (B, c, n, h, w)
  channel-first with n = 1 + (T − 1)/t latent frames, h = H/s, w = W/s (:class:`LatentFormat`).
- **Flow matching, σ convention**: ``x_σ = (1 − σ)·x0 + σ·ε`` with σ = 1 pure noise, and
  :attr:`Backbone.velocity_model` returns ``v = ε − x0`` (models/flow_matching.py). Wan is trained in exactly this
  convention (timestep = 1000·σ); CogVideoX is a v-prediction DDPM whose prediction is converted
  (:func:`models.backbones.cogvideox.vpred_to_flow`): a DDIM (η = 0) step between two of its timesteps is an Euler
  step of this ODE between their σ, so our samplers reproduce its scheduler's latents.
- **First-frame conditioning** happens inside :attr:`Backbone.velocity_model` from ``image_latent``
  (B, c, 1, h, w), the backbone's way (ours: concatenated with a frame mask; Wan: latent frame 0 replaced and its
  tokens given timestep 0; CogVideoX: the image latent concatenated on channels, zero after frame 0).
- **Camera conditioning**: ``plucker`` (B, 6·t·s², n, h, w) Plücker rays packed onto the latent grid
  (:func:`diff4splat.cameras.pack_plucker`). The diffusers transformers see them as extra input channels of their
  patch embedding, whose new weights start at zero (:class:`models.backbones.diffusers_backbone.CameraPatchConv`):
  an untrained camera branch leaves the pretrained transformer exactly as it was.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = ["LatentFormat", "Backbone", "check_velocity_inputs", "BACKBONE_KINDS"]

BACKBONE_KINDS = ("ours", "wan2.2-ti2v", "cogvideox-i2v")
"""The backbones: our networks, Wan2.2-TI2V-5B, CogVideoX-5B-I2V."""


@dataclass(frozen=True)
class LatentFormat:
    """How a backbone's VAE maps video to latents.

    Attributes:
        latent_channels: c (ours 4–16, Wan2.2 48, CogVideoX 16).
        temporal_factor: t, frames per latent frame after the first (4 for all three).
        spatial_factor: s, pixels per latent pixel along each side (ours and CogVideoX 8, Wan2.2 16).
    """

    latent_channels: int
    temporal_factor: int
    spatial_factor: int

    @property
    def camera_channels(self) -> int:
        """Channels of the packed Plücker rays on this latent grid: 6·t·s²."""
        return 6 * self.temporal_factor * self.spatial_factor ** 2

    @property
    def frames_rule(self) -> str:
        """The frame counts the VAE takes, in words: ``1 + 4·k (1, 5, 9, …)``."""
        t = self.temporal_factor
        return f"1 + {t}·k (1, {1 + t}, {1 + 2 * t}, …)"

    def num_latent_frames(self, num_frames: int) -> int:
        """n = 1 + (T − 1)/t. Raises ValueError unless T = 1 + t·k, k ≥ 0."""
        t = self.temporal_factor
        if num_frames < 1 or (num_frames - 1) % t:  # no isinstance: an ONNX export traces T as a SymInt
            raise ValueError(f"video: T={num_frames} frames; T must be {self.frames_rule}")
        return 1 + (num_frames - 1) // t

    def num_frames(self, num_latent_frames: int) -> int:
        """T = 1 + t·(n − 1), the decoded length of n ≥ 1 latent frames."""
        return 1 + self.temporal_factor * (num_latent_frames - 1)


def check_velocity_inputs(x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor | None,
                          latent_channels: int, camera_channels: int, patch_size: tuple[int, int, int]) -> None:
    """The shape checks every :attr:`Backbone.velocity_model` makes (static: safe under tracing).

    Args:
        x: (B, c, n, h, w) with c = ``latent_channels`` and (n, h, w) divisible by ``patch_size`` (p_t, p_h, p_w).
        sigma: (B,).  image_latent: (B, c, 1, h, w).  plucker: (B, ``camera_channels``, n, h, w) or None.

    Raises:
        ValueError: naming the first argument whose shape does not fit.
    """
    if x.dim() != 5 or x.shape[1] != latent_channels:
        raise ValueError(f"x must have shape (B, {latent_channels}, n, h, w), got {tuple(x.shape)}")
    B, c, n, h, w = x.shape
    if n % patch_size[0] or h % patch_size[1] or w % patch_size[2]:
        raise ValueError(f"x: latent size (n, h, w) = {(n, h, w)} must be divisible by patch_size {tuple(patch_size)}")
    if sigma.shape != (B,):
        raise ValueError(f"sigma must have shape ({B},), got {tuple(sigma.shape)}")
    if image_latent.shape != (B, c, 1, h, w):
        raise ValueError(f"image_latent must have shape {(B, c, 1, h, w)}, got {tuple(image_latent.shape)}")
    if plucker is not None and plucker.shape != (B, camera_channels, n, h, w):
        raise ValueError(f"plucker must have shape {(B, camera_channels, n, h, w)}, got {tuple(plucker.shape)}")


class Backbone(nn.Module, abc.ABC):
    """VAE + text encoder + camera-conditioned video transformer (module docstring: conventions).

    Attributes:
        kind: one of :data:`BACKBONE_KINDS`.
        latent: the :class:`LatentFormat`.
        encodes_empty_prompt: True when the transformer was trained with the empty prompt's text embedding as its
            unconditional input (the pretrained backbones), so the pipeline encodes "" when there is no prompt;
            False (ours): no prompt means no text tokens, and no text encoder runs.
    """

    kind: str
    latent: LatentFormat
    encodes_empty_prompt: bool = False

    @abc.abstractmethod
    def encode_video(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """(B, 3, T, H, W) pixels in [−1, 1], T = 1 + t·k → normalised latents (B, c, n, h, w): the posterior
        mean, or a posterior sample drawn with ``generator`` when given."""

    @abc.abstractmethod
    def decode_latents(self, latents: Tensor) -> Tensor:
        """Normalised latents (B, c, n, h, w) → video (B, 3, T, H, W) in about [−1, 1]."""

    @abc.abstractmethod
    def encode_text(self, prompts: list[str]) -> tuple[Tensor, Tensor]:
        """Prompts → tokens (B, L, d_text) and mask (B, L) bool (True = a token the transformer attends to)."""

    @property
    @abc.abstractmethod
    def velocity_model(self) -> nn.Module:
        """The network of the flow-matching velocity ``ε − x0`` (module docstring): the ``nn.Module`` whose call
        ``(x, sigma, image_latent, plucker, text, text_mask)`` computes it (ours: the DiT; a diffusers backbone: the
        backbone itself, whose ``forward`` converts to and from its transformer's conventions).

        Its call takes:
            x: (B, c, n, h, w) the state at ``sigma``.
            sigma: (B,) σ in [0, 1] (float32).
            image_latent: (B, c, 1, h, w) the photograph's normalised latent.
            plucker: (B, 6·t·s², n, h, w) packed Plücker rays.
            text, text_mask: (B, L, d_text), (B, L) bool, or None for no prompt (a backbone trained with a text
                embedding of the empty prompt encodes "" itself).

        and returns (B, c, n, h, w): float32 from a diffusers backbone, the DiT's parameter dtype from ours; a
        ValueError names an input of the wrong shape (:func:`check_velocity_inputs`).
        """

    @abc.abstractmethod
    def sigmas(self, steps: int) -> Tensor:
        """The inference schedule: (steps + 1,) float64 σ, decreasing from 1 to 0 (the backbone scheduler's)."""

    @abc.abstractmethod
    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) σ drawn for a training step on ``generator``'s device (a backbone with discrete timesteps returns
        σ of its timesteps)."""

    @abc.abstractmethod
    def transformer_blocks(self) -> list[nn.Module]:
        """The transformer's blocks (FSDP units, gradient checkpointing, regional compilation)."""

    def compile_blocks(self) -> None:
        """Regional compilation: ``torch.compile`` each of :meth:`transformer_blocks` in place
        (``nn.Module.compile``; the PyTorch recipe "regional compilation", diffusers' ``compile_repeated_blocks``).
        Identical blocks share one compiled graph, so the cold start compiles one block, not the transformer; the
        elementwise work between the matmuls (norms, adaLN modulation, RoPE, QK-norm, GELU, gated residuals) is
        fused into fewer kernels. The outputs equal the eager blocks' up to floating-point rounding. The first call
        at each new input shape (and with / without text) compiles, which needs a C++ compiler on the CPU and
        Triton on CUDA."""
        for block in self.transformer_blocks():
            block.compile()
