"""CogVideoX-5B-I2V (Yang et al. 2024) as a :class:`models.backbone.Backbone` over diffusers' components
(``THUDM/CogVideoX-5b-I2V``: ``CogVideoXTransformer3DModel``, ``AutoencoderKLCogVideoX``, T5-XXL,
``CogVideoXDDIMScheduler``), in the Hub folder layout (:mod:`.diffusers_backbone`).

CogVideoX is a v-prediction DDPM with zero terminal SNR (Salimans & Ho 2022 §4; Lin et al. 2024): at
σ = s/(α + s) the state x_t/(α + s) is our straight path and :func:`vpred_to_flow` its velocity; our Euler sampler
over :meth:`CogVideoXBackbone.sigmas` reproduces the pipeline's DDIM latents (docs/DESIGN.md, "Backbones"). Imports
diffusers."""
from __future__ import annotations

import torch
from diffusers import AutoencoderKLCogVideoX, CogVideoXImageToVideoPipeline
from torch import Tensor, nn

from ..backbone import LatentFormat, check_velocity_inputs
from .diffusers_backbone import DiffusersBackbone

__all__ = ["CogVideoXBackbone", "vpred_to_flow"]


def vpred_to_flow(x_t: Tensor, v: Tensor, alpha: Tensor, sigma_ddpm: Tensor) -> Tensor:
    """A v-prediction (v = α·ε − σ·x0, α² + σ² = 1) as the velocity ε − x0 = (σ − α)·x_t + (α + σ)·v.

    Args:
        x_t: (B, ...) the DDPM state α·x0 + σ·ε.
        v: (B, ...) the v-prediction.
        alpha, sigma_ddpm: (B,) √ᾱ_t and √(1 − ᾱ_t).

    Returns (B, ...).
    """
    shape = (-1,) + (1,) * (x_t.dim() - 1)
    a, s = alpha.reshape(shape).to(x_t), sigma_ddpm.reshape(shape).to(x_t)
    return (s - a) * x_t + (a + s) * v


def _check_int(name: str, value: int, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")


class CogVideoXBackbone(DiffusersBackbone):
    """CogVideoX-5B-I2V with a camera-widened patch embedding: per latent frame the transformer reads
    ``[x_t, image latent (frame 0) | zeros, Plücker rays]`` on channels, the rays through the zero-initialised camera
    weights of ``patch_embed.proj`` (:class:`.diffusers_backbone.CameraPatchConv`).

    Args:
        transformer: a CogVideoX 1.0 ``CogVideoXTransformer3DModel`` (``patch_size_t`` None) with
            ``in_channels = 2·latent_channels``.
        vae: ``AutoencoderKLCogVideoX``.
        text_encoder, tokenizer: T5.
        scheduler: a v-prediction scheduler with ``alphas_cumprod``; its timesteps define :meth:`sigmas` and
            :meth:`training_sigmas`.

    Attributes:
        max_sequence_length: text tokens, the transformer's ``max_text_seq_length``.

    Raises:
        ValueError: a CogVideoX 1.5 transformer (``patch_size_t`` set), channels that do not match the VAE, or a
            scheduler that is not v-prediction.
    """

    kind = "cogvideox-i2v"
    pipeline_class = CogVideoXImageToVideoPipeline
    pipeline_names = ("CogVideoXImageToVideoPipeline",)
    patch_conv_path = "patch_embed.proj"

    def __init__(self, transformer: nn.Module, vae: nn.Module, text_encoder: nn.Module, tokenizer, scheduler):
        cfg = transformer.config
        if cfg.patch_size_t is not None:
            raise ValueError(f"CogVideoX 1.5 transformers (patch_size_t={cfg.patch_size_t}: a Linear patch "
                             "embedding over temporal patches) are not supported; use CogVideoX-5B-I2V (1.0)")
        if getattr(scheduler.config, "prediction_type", None) != "v_prediction" \
                or not hasattr(scheduler, "alphas_cumprod"):
            raise ValueError(f"the scheduler must be a v-prediction DDPM scheduler with alphas_cumprod "
                             f"(CogVideoXDDIMScheduler), got {type(scheduler).__name__} with prediction_type="
                             f"{getattr(scheduler.config, 'prediction_type', None)!r}")
        c = self.latent_format(vae).latent_channels
        if cfg.in_channels != 2 * c or cfg.out_channels != c:
            raise ValueError(f"the transformer takes {cfg.in_channels} channels and returns {cfg.out_channels}; "
                             f"the VAE's latents need {2 * c} (noisy latent + image latent) and {c}")
        super().__init__(transformer, vae, text_encoder, tokenizer, scheduler)  # widens the patch conv in place
        self.max_sequence_length = int(cfg.max_text_seq_length)
        abar = scheduler.alphas_cumprod.detach().to("cpu", torch.float64)
        alpha, s = abar ** 0.5, (1.0 - abar) ** 0.5  # the scheduler's own float64 expressions
        # (3, num_train_timesteps) float64 on the CPU, t = 0..T-1: α = √ᾱ_t, s = √(1 − ᾱ_t), σ = s/(α + s).
        self._schedule = torch.stack([alpha, s, s / (alpha + s)])
        self._empty_text: Tensor | None = None

    @staticmethod
    def latent_format(vae: nn.Module) -> LatentFormat:
        """From ``AutoencoderKLCogVideoX``'s config: ``latent_channels``, ``temporal_compression_ratio``,
        2^(len(``block_out_channels``) − 1). TypeError for another VAE."""
        if not isinstance(vae, AutoencoderKLCogVideoX):
            raise TypeError(f"vae must be an AutoencoderKLCogVideoX, got {type(vae).__name__}")
        c = vae.config
        return LatentFormat(int(c.latent_channels), int(c.temporal_compression_ratio),
                            2 ** (len(c.block_out_channels) - 1))

    # ---------------------------------------------------------------------------------------------- VAE, text

    def encode_latents(self, video: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """(B, 3, T, H, W) in [−1, 1], T = 1 + 4k, H, W multiples of 8 → ``scaling_factor·z`` (B, c, n, h, w)
        float32, z the posterior mean or ``latent_dist.sample(generator)`` (as the pipeline's ``prepare_latents``);
        ``invert_scale_latents`` is applied in :meth:`forward`. ValueError on a wrong shape."""
        return self.vae.config.scaling_factor * self.posterior(video, generator)

    def decode_latents(self, latents: Tensor) -> Tensor:
        """Latents (B, c, n, h, w) → video (B, 3, 1 + 4(n − 1), 8h, 8w) float32 in about [−1, 1] (the pipeline's
        ``decode_latents``)."""
        z = 1 / self.vae.config.scaling_factor * latents.to(self.vae.dtype)
        return self.vae.decode(z).sample.float()

    def encode_text(self, prompts: list[str]) -> tuple[Tensor, Tensor]:
        """Prompts → T5 embeddings (B, :attr:`max_sequence_length`, d_text) in the encoder's dtype and an all-True mask
        (B, L), by ``CogVideoXImageToVideoPipeline.encode_prompt``. TypeError unless a list of str."""
        if not isinstance(prompts, list) or not all(isinstance(p, str) for p in prompts):
            raise TypeError(f"prompts must be a list of str, got {prompts!r}")
        embeds, _ = self.pipeline().encode_prompt(prompts, do_classifier_free_guidance=False,
                                                  max_sequence_length=self.max_sequence_length,
                                                  device=self.text_encoder.device)
        return embeds, torch.ones(embeds.shape[:2], dtype=torch.bool, device=embeds.device)

    def empty_text(self, batch: int, device: torch.device) -> Tensor:
        """The embedding of "" (``batch``, L, d_text) on ``device``, CogVideoX's unconditional input; encoded once."""
        if self._empty_text is None:
            with torch.no_grad():
                self._empty_text = self.encode_text([""])[0]
        return self._empty_text.to(device).expand(batch, -1, -1)

    # ---------------------------------------------------------------------------------------------- schedule

    def timesteps(self, sigma: Tensor) -> Tensor:
        """σ (B,) → the timesteps t (B,) int64 whose σ_t is nearest (exact for σ of :meth:`sigmas` and
        :meth:`training_sigmas`; pass float32 or float64)."""
        table = self._schedule[2].to(sigma.device)
        return (table[None, :] - sigma.to(torch.float64)[:, None]).abs().argmin(dim=1)

    def sigmas(self, steps: int) -> Tensor:
        """(steps + 1,) float64 on the CPU: σ_t of the scheduler's own timesteps (``set_timesteps`` on a copy,
        "trailing": t = 999, …, σ = 1 first), then 0. Equal to the pipeline's samples when ``steps`` divides 1000;
        otherwise diffusers' DDIM steps to t − 1000 // steps, while this grid follows the listed timesteps.

        Raises:
            ValueError: ``steps`` not an int in [1, num_train_timesteps].
        """
        _check_int("steps", steps, 1)
        scheduler = type(self.scheduler).from_config(self.scheduler.config)
        scheduler.set_timesteps(steps, device="cpu")
        sig = self._schedule[2][scheduler.timesteps.long()]
        return torch.cat([sig, sig.new_zeros(1)])

    def training_sigmas(self, n: int, generator: torch.Generator) -> Tensor:
        """(n,) float32 σ_t of timesteps drawn uniformly on ``generator``'s device (CogVideoX's training).
        ValueError: ``n`` not an int ≥ 1."""
        _check_int("n", n, 1)
        t = torch.randint(0, self._schedule.shape[1], (n,), generator=generator, device=generator.device)
        return self._schedule[2].to(generator.device)[t].float()

    # ---------------------------------------------------------------------------------------------- transformer

    def forward(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor,
                text: Tensor | None, text_mask: Tensor | None) -> Tensor:
        """Velocity ε − x0 from CogVideoX's v-prediction: σ → t (:meth:`timesteps`), x_t = (α + s)·x, the
        transformer run as ``CogVideoXImageToVideoPipeline.__call__`` runs it (rotary embeddings, ``ofs`` 2.0 where
        present) in its own dtype, then :func:`vpred_to_flow` in float32.

        Args:
            x: (B, c, n, h, w) the state at σ.
            sigma: (B,) σ in [0, 1], float32 or float64.
            image_latent: (B, c, 1, h, w) :meth:`encode_latents` of the photograph (divided by scaling_factor² when
                ``invert_scale_latents`` is set, as the pipeline).
            plucker: (B, 6·4·8², n, h, w) packed Plücker rays.
            text: (B, L, d_text) :meth:`encode_text` tokens, or None for :meth:`empty_text`.
            text_mask: ignored.

        Returns:
            (B, c, n, h, w) float32.

        Raises:
            ValueError: inconsistent shapes, or (h, w) other than ``sample_height``, ``sample_width`` with learned
                positional embeddings.
        """
        cfg = self.transformer.config
        check_velocity_inputs(x, sigma, image_latent, plucker, self.latent.latent_channels,
                              self.latent.camera_channels, (1, cfg.patch_size, cfg.patch_size))
        b, c, n, h, w = x.shape
        if cfg.use_learned_positional_embeddings and (h, w) != (cfg.sample_height, cfg.sample_width):
            raise ValueError(f"this CogVideoX transformer has learned positional embeddings for "
                             f"{cfg.sample_height}x{cfg.sample_width} latents; got {h}x{w}")
        t = self.timesteps(sigma)
        table = self._schedule.to(t.device)
        alpha, s = table[0, t], table[1, t]  # √ᾱ_t, √(1 − ᾱ_t): (B,) float64
        x_t = (alpha + s).float().view(-1, 1, 1, 1, 1) * x.float()
        if text is None:
            text = self.empty_text(b, x.device)
        image = image_latent.float()
        if getattr(self.vae.config, "invert_scale_latents", False):
            image = image / self.vae.config.scaling_factor ** 2  # sf·z → z/sf, the pipeline's image scaling
        image = torch.cat([image, image.new_zeros(b, c, n - 1, h, w)], dim=2)
        dtype = self.transformer.dtype
        hidden = torch.cat([x_t, image, plucker.float()], dim=1).to(dtype).permute(0, 2, 1, 3, 4)
        pipe = self.pipeline()
        scale = pipe.vae_scale_factor_spatial
        rotary = (pipe._prepare_rotary_positional_embeddings(h * scale, w * scale, n, x.device)
                  if cfg.use_rotary_positional_embeddings else None)
        ofs = None if cfg.ofs_embed_dim is None else hidden.new_full((1,), fill_value=2.0)
        v = self.transformer(hidden_states=hidden, encoder_hidden_states=text.to(dtype), timestep=t, ofs=ofs,
                             image_rotary_emb=rotary, return_dict=False)[0]
        return vpred_to_flow(x_t, v.float().permute(0, 2, 1, 3, 4), alpha, s)
