"""What the pipeline and the training stages need from a video backbone (VAE + text encoder + camera-conditioned
video transformer): the :class:`Backbone` interface, the :class:`LatentFormat` of its latents and the shape checks
of its velocity. Implementations in :mod:`models.backbones`: ours (the CPU default), Wan2.2-TI2V-5B and
CogVideoX-5B-I2V (diffusers, the ``diff4splat[diffusers]`` extra).

Conventions every backbone obeys (docs/DESIGN.md "Backbones"): latents are the VAE posterior mean normalised the
backbone's way, (B, c, n, h, w), n = 1 + (T − 1)/t; x_σ = (1 − σ)·x0 + σ·ε and :attr:`Backbone.velocity_model`
returns v = ε − x0 (CogVideoX's v-prediction converted, :func:`models.backbones.cogvideox.vpred_to_flow`);
first-frame conditioning from ``image_latent`` (B, c, 1, h, w) happens inside the velocity model; ``plucker``
(B, 6·t·s², n, h, w) packed rays enter through zero-initialised weights, so an untrained camera branch leaves a
pretrained transformer unchanged."""
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
        latent_channels: c.
        temporal_factor: t, frames per latent frame after the first.
        spatial_factor: s, pixels per latent pixel along each side.
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
        """n = 1 + (T − 1)/t; ValueError unless T = 1 + t·k, k ≥ 0."""
        t = self.temporal_factor
        if num_frames < 1 or (num_frames - 1) % t:  # no isinstance: an ONNX export traces T as a SymInt
            raise ValueError(f"video: T={num_frames} frames; T must be {self.frames_rule}")
        return 1 + (num_frames - 1) // t

    def num_frames(self, num_latent_frames: int) -> int:
        """T = 1 + t·(n − 1), the decoded length of n ≥ 1 latent frames."""
        return 1 + self.temporal_factor * (num_latent_frames - 1)


def check_velocity_inputs(x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor | None,
                          latent_channels: int, camera_channels: int, patch_size: tuple[int, int, int]) -> None:
    """The shape checks of every :attr:`Backbone.velocity_model` (static: safe under tracing): x (B, c, n, h, w)
    with (n, h, w) divisible by ``patch_size``, sigma (B,), image_latent (B, c, 1, h, w), plucker
    (B, camera_channels, n, h, w) or None; ValueError naming the first that does not fit."""
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
        encodes_empty_prompt: True when the transformer's unconditional input is the embedding of "" (the pretrained
            backbones); False (ours): no prompt means no text tokens.
    """

    kind: str
    latent: LatentFormat
    encodes_empty_prompt: bool = False

    @property
    @abc.abstractmethod
    def latent_model(self) -> nn.Module:
        """The ``nn.Module`` that maps pixels to the DiT's normalised latents and back (ours: the VAE; a diffusers
        backbone: itself):

        - ``encode_latents(video, generator=None)``: (B, 3, T, H, W) in [−1, 1], T = 1 + t·k, H, W multiples of s →
          (B, c, n, H/s, W/s), the posterior mean or a sample drawn with ``generator``; ValueError on another shape;
        - ``decode_latents(latents)``: (B, c, n, h, w) → video (B, 3, 1 + t·(n − 1), s·h, s·w) in about [−1, 1].
        """

    @property
    @abc.abstractmethod
    def text_model(self) -> nn.Module:
        """The ``nn.Module`` whose ``encode_text(prompts)`` maps B prompts to tokens (B, L, d_text) and mask (B, L) bool
        (True = a token the transformer attends to) on its own device (ours: the text encoder; a diffusers backbone:
        itself)."""

    @property
    @abc.abstractmethod
    def velocity_model(self) -> nn.Module:
        """The ``nn.Module`` whose call ``(x, sigma, image_latent, plucker, text, text_mask)`` computes ε − x0 (ours:
        the DiT; a diffusers backbone: itself): x (B, c, n, h, w), sigma (B,) float32 in [0, 1], image_latent
        (B, c, 1, h, w), plucker (B, 6·t·s², n, h, w), text (B, L, d_text) and mask (B, L) or None →
        (B, c, n, h, w) (float32 from a diffusers backbone, the DiT's dtype from ours); ValueError from
        :func:`check_velocity_inputs`."""

    @abc.abstractmethod
    def sigmas(self, steps: int) -> Tensor:
        """The inference schedule: (steps + 1,) float64 σ from 1 down to 0 (the backbone scheduler's)."""

    @abc.abstractmethod
    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) σ for a training step on ``generator``'s device."""

    @abc.abstractmethod
    def transformer_blocks(self) -> list[nn.Module]:
        """The transformer's blocks (FSDP units, gradient checkpointing, regional compilation)."""

    def compile_blocks(self) -> None:
        """Regional compilation: ``torch.compile`` each of :meth:`transformer_blocks` in place (diffusers'
        ``compile_repeated_blocks``); identical blocks share one graph. Same outputs up to rounding; needs a C++
        compiler on the CPU and Triton on CUDA."""
        for block in self.transformer_blocks():
            block.compile()
