"""Wan2.2-TI2V-5B as a :class:`models.backbone.Backbone`: diffusers' ``AutoencoderKLWan`` (48 channels, 4×16×16),
the UMT5-XXL text encoder and ``WanTransformer3DModel`` with its patch embedding widened by the camera channels
(docs/DESIGN.md "Backbones").

Sources: the Wan report (arXiv 2503.20314), github.com/Wan-Video/Wan2.2 (``wan/textimage2video.py``,
``wan/configs/wan_ti2v_5B.py``), and diffusers' ``WanImageToVideoPipeline`` (``expand_timesteps=True``, the TI2V
image-to-video path), ``WanPipeline.encode_prompt`` and the flow-matching Euler / UniPC schedulers. The Hub folder
``Wan-AI/Wan2.2-TI2V-5B-Diffusers`` is a ``WanPipeline`` folder; we load and save it with
``WanImageToVideoPipeline`` and accept both names. Imports diffusers, transformers and ftfy (diffusers' Wan prompt
cleaning calls ``ftfy.fix_text``, so a missing ftfy fails here, at import)."""
from __future__ import annotations

import copy
from pathlib import Path

import ftfy  # noqa: F401  (needed by diffusers' Wan prompt cleaning; see the module docstring)
import torch
from diffusers import AutoencoderKLWan, WanImageToVideoPipeline
from torch import Tensor, nn

from ..backbone import LatentFormat, check_velocity_inputs
from ..flow_matching import sample_logit_normal, shift_sigmas
from .diffusers_backbone import DiffusersBackbone

__all__ = ["WanBackbone"]


class WanBackbone(DiffusersBackbone):
    """Wan2.2-TI2V-5B: ``AutoencoderKLWan`` + UMT5 + ``WanTransformer3DModel`` (camera-widened patch embedding).

    Conventions (:mod:`models.backbone`):

    - **Latents**: ``(z − latents_mean)·(1/latents_std)`` per channel, as ``prepare_latents``; (B, 48, n, H/16, W/16).
    - **Velocity**: the transformer predicts exactly our ``ε − x0`` at timestep ``1000·σ`` (the flow-matching
      schedulers' ``scale_noise``/``step`` and UniPC's ``flow_prediction`` say the same); nothing is converted.
    - **First frame** (TI2V): latent frame 0 is the photograph's latent, its tokens at timestep 0, the others at
      ``1000·σ`` (per-token timesteps (B, seq_len)).
    - **Text**: UMT5 embeddings, zeroed after the prompt's last token, padded to :attr:`max_sequence_length`; no text
      mask.

    Raises:
        TypeError: ``vae`` is not an ``AutoencoderKLWan``.
        ValueError: not a TI2V transformer (channels ≠ the VAE's ``z_dim``, or image embeddings), or a VAE config
            without its scale factors.
    """

    kind = "wan2.2-ti2v"
    pipeline_class = WanImageToVideoPipeline
    pipeline_names = ("WanPipeline", "WanImageToVideoPipeline")
    patch_conv_path = "patch_embedding"
    max_sequence_length: int = 512
    """Text tokens (the pipelines' default, Wan2.2's ``text_len``); longer prompts are cut."""

    def __init__(self, transformer: nn.Module, vae: nn.Module, text_encoder: nn.Module, tokenizer, scheduler):
        c, z = transformer.config, getattr(getattr(vae, "config", None), "z_dim", None)
        if c.in_channels != z or c.out_channels != z or c.image_dim is not None or len(c.patch_size) != 3:
            raise ValueError(f"WanBackbone runs a TI2V transformer ({z} latent channels in and out, no image "
                             f"embeddings); got in_channels {c.in_channels}, out_channels {c.out_channels}, "
                             f"image_dim {c.image_dim}, patch_size {c.patch_size}")
        super().__init__(transformer, vae, text_encoder, tokenizer, scheduler)
        self._empty_text: Tensor | None = None  # cached embedding of "" (the text encoder is frozen)

    @staticmethod
    def latent_format(vae: nn.Module) -> LatentFormat:
        """``LatentFormat(z_dim, scale_factor_temporal, scale_factor_spatial)`` of an ``AutoencoderKLWan``.

        Raises:
            TypeError: not an ``AutoencoderKLWan``.
            ValueError: a scale factor missing from its config.
        """
        if not isinstance(vae, AutoencoderKLWan):
            raise TypeError(f"vae must be an AutoencoderKLWan, got {type(vae).__name__}")
        c = vae.config
        if not isinstance(c.scale_factor_temporal, int) or not isinstance(c.scale_factor_spatial, int):
            raise ValueError(f"the VAE config needs scale_factor_temporal and scale_factor_spatial, got "
                             f"{c.scale_factor_temporal!r}, {c.scale_factor_spatial!r}")
        return LatentFormat(c.z_dim, c.scale_factor_temporal, c.scale_factor_spatial)

    def pipeline_kwargs(self) -> dict:
        """``expand_timesteps=True``: the TI2V path (first latent frame = the image, its tokens at timestep 0)."""
        return {"expand_timesteps": True}

    @classmethod
    def check_index(cls, index: dict, path: Path) -> None:
        """A Wan2.2-TI2V folder: ``expand_timesteps`` true and no ``transformer_2``; ValueError naming ``path``
        otherwise."""
        second = index.get("transformer_2")
        if index.get("expand_timesteps") is not True or second not in (None, [None, None]):
            raise ValueError(f"checkpoint: {path} is not a Wan2.2-TI2V folder (expand_timesteps "
                             f"{index.get('expand_timesteps')!r}, transformer_2 {second!r}; expected true and none)")

    # ---------------------------------------------------------------- VAE

    def _latent_stats(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """(1, c, 1, 1, 1) float32 ``latents_mean`` and ``1/latents_std``, as ``prepare_latents``."""
        c = self.vae.config
        mean = torch.tensor(c.latents_mean, dtype=torch.float32, device=device).view(1, c.z_dim, 1, 1, 1)
        inv_std = 1.0 / torch.tensor(c.latents_std, dtype=torch.float32, device=device).view(1, c.z_dim, 1, 1, 1)
        return mean, inv_std

    def encode_latents(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """(B, 3, T, H, W) in [−1, 1], T = 1 + 4k, H, W multiples of 16 → normalised latents
        (B, 48, n, H/16, W/16) float32: the posterior's mode, or a sample drawn with ``generator``. ValueError on a
        wrong shape."""
        mean, inv_std = self._latent_stats(video.device)
        return (self.posterior(video, generator) - mean) * inv_std

    def decode_latents(self, latents: Tensor) -> Tensor:
        """Normalised latents (B, 48, n, h, w) → video (B, 3, 1 + 4(n − 1), 16h, 16w) float32 in [−1, 1] (the VAE
        clamps). ValueError on another shape."""
        if latents.dim() != 5 or latents.shape[1] != self.latent.latent_channels:
            raise ValueError(f"latents must be (B, {self.latent.latent_channels}, n, h, w), got {tuple(latents.shape)}")
        mean, inv_std = self._latent_stats(latents.device)
        z = latents.to(torch.float32) / inv_std + mean
        return self.vae.decode(z.to(self.vae.dtype), return_dict=False)[0].to(torch.float32)

    # ---------------------------------------------------------------- text

    def encode_text(self, prompts: list[str]) -> tuple[Tensor, Tensor]:
        """B prompts ("" unconditional) → (embeds (B, L, d_text) float32, all-True mask (B, L)) with diffusers'
        ``WanPipeline.encode_prompt``, L = :attr:`max_sequence_length`, on the text encoder's device.

        Raises:
            TypeError: ``prompts`` is not a list of strings.
            ValueError: an empty list.
        """
        if not isinstance(prompts, (list, tuple)) or not all(isinstance(p, str) for p in prompts):
            raise TypeError(f"prompts must be a list of strings, got {prompts!r}")
        if not prompts:
            raise ValueError("prompts must not be empty")
        device = next(self.text_encoder.parameters()).device
        embeds, _ = self.pipeline().encode_prompt(list(prompts), do_classifier_free_guidance=False,
                                                  max_sequence_length=self.max_sequence_length, device=device,
                                                  dtype=torch.float32)
        return embeds, torch.ones(embeds.shape[:2], dtype=torch.bool, device=device)

    def _empty_prompt(self, device: torch.device) -> Tensor:
        """(1, L, d_text) embedding of "", computed once without gradients and cached."""
        cached = self._empty_text
        if cached is None or (cached.is_inference() and not torch.is_inference_mode_enabled()):
            with torch.no_grad():
                cached = self.encode_text([""])[0]
            self._empty_text = cached
        return cached.to(device)

    # ---------------------------------------------------------------- transformer

    def forward(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor,
                text: Tensor | None, text_mask: Tensor | None) -> Tensor:
        """Velocity ``ε − x0`` from the camera-conditioned transformer, called as ``WanImageToVideoPipeline`` does
        with ``expand_timesteps=True``: latent frame 0 replaced by ``image_latent``, per-token timesteps (0 for frame 0,
        ``σ·num_train_timesteps`` else; float32), Plücker rays as extra patch-embedding channels; inputs cast to the
        transformer's dtype.

        Args:
            x: (B, 48, n, h, w) the state at ``sigma``; frame 0 is not read.
            sigma: (B,) σ in [0, 1].
            image_latent: (B, 48, 1, h, w) the photograph's normalised latent.
            plucker: (B, 6·4·16², n, h, w) packed Plücker rays.
            text: (B, L, d_text) from :meth:`encode_text`, or None for the embedding of "" (diffusers' unconditional
                prompt).
            text_mask: not used.

        Returns:
            (B, 48, n, h, w) float32; frame 0 is unused (samplers set it to ``image_latent``).

        Raises:
            ValueError: shapes that disagree, or n, h, w not multiples of the patch size.
        """
        p_t, p_h, p_w = self.transformer.config.patch_size
        check_velocity_inputs(x, sigma, image_latent, plucker, self.latent.latent_channels,
                              self.latent.camera_channels, (p_t, p_h, p_w))
        b, c, n, h, w = x.shape
        if text is None:
            text = self._empty_prompt(x.device).expand(b, -1, -1)
        elif text.dim() != 3 or text.shape[0] != b:
            raise ValueError(f"text must be (B={b}, L, d_text), got {tuple(text.shape)}")
        if text_mask is not None and text_mask.shape != text.shape[:2]:
            raise ValueError(f"text_mask must have shape {tuple(text.shape[:2])}, got {tuple(text_mask.shape)}")

        dtype = self.transformer.dtype
        x_in = torch.cat([image_latent.to(x.dtype), x[:, :, 1:]], dim=2)
        first_frame_mask = torch.ones(n, h, w, dtype=torch.float32, device=x.device)
        first_frame_mask[0] = 0
        t = sigma.to(torch.float32).reshape(b, 1) * self.scheduler.config.num_train_timesteps
        timestep = first_frame_mask[::p_t, ::p_h, ::p_w].flatten().unsqueeze(0) * t  # (B, seq_len)
        out = self.transformer(hidden_states=torch.cat([x_in, plucker.to(x_in.dtype)], dim=1).to(dtype),
                               timestep=timestep, encoder_hidden_states=text.to(dtype), return_dict=False)[0]
        return out.to(torch.float32)

    # ---------------------------------------------------------------- schedule

    @property
    def shift(self) -> float:
        """The scheduler's ``shift`` or ``flow_shift`` (5.0 in the Hub folder); ValueError if it has neither."""
        config = self.scheduler.config
        for key in ("shift", "flow_shift"):
            if key in config:
                return float(config[key])
        raise ValueError(f"{type(self.scheduler).__name__} has no shift or flow_shift in its config")

    def sigmas(self, steps: int) -> Tensor:
        """The scheduler's own σ grid (``set_timesteps(steps)`` on a copy): (steps + 1,) float64 on the CPU, strictly
        decreasing from about 1 to 0, checked to have timesteps σ·num_train_timesteps (within 1: UniPC truncates).

        Raises:
            ValueError: ``steps`` not an int ≥ 1; a scheduler whose grid is not such a flow-matching one.
        """
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps must be an int >= 1, got {steps!r}")
        scheduler = copy.deepcopy(self.scheduler)
        scheduler.set_timesteps(steps, device="cpu")
        if getattr(scheduler, "sigmas", None) is None:
            raise ValueError(f"{type(self.scheduler).__name__} has no sigmas: not a flow-matching scheduler")
        sig = torch.as_tensor(scheduler.sigmas, device="cpu").detach().to(torch.float64)
        ts = torch.as_tensor(scheduler.timesteps, device="cpu").detach().to(torch.float64)
        n_train = scheduler.config.num_train_timesteps
        if sig.shape != (steps + 1,) or ts.shape != (steps,) or sig[-1] != 0 or not 0 < sig[0] <= 1 \
                or bool((sig[1:] >= sig[:-1]).any()) or bool(((ts - sig[:-1] * n_train).abs() >= 1).any()):
            raise ValueError(f"{type(self.scheduler).__name__}: not a flow-matching grid (sigmas {sig.tolist()}, "
                             f"timesteps {ts.tolist()}; expected {steps + 1} sigmas from at most 1 down to 0 and "
                             f"timesteps sigma·{n_train})")
        return sig

    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) float32 σ on ``generator``'s device: logit-normal(0, 1) (the Wan report) shifted by :attr:`shift`, as
        the inference grid. ValueError: ``n`` < 1 or no shift."""
        return shift_sigmas(sample_logit_normal(n, generator=generator, device=generator.device), self.shift)
