"""Image + camera path + optional prompt → 4D Gaussian scene (Diff4Splat, Pan et al. 2025, Fig. 2).

Data flow (DESIGN.md, "Data flow of generate"):

1. VAE encoder: the photograph as a one-frame video → first-frame latent (1, c, 1, h, w).
2. Text encoder: prompt → tokens (1, L, d_text); skipped entirely for an empty prompt.
3. Plücker rays (T, H, W, 6) of the path → packed to the latent grid (1, 1536, n, h, w).
4. VideoDiT + flow-matching sampler (Euler/Heun, NFE steps): noise → video latent (1, c, n, h, w);
   the sampled first latent frame is replaced by the photograph's own latent, which is known exactly.
5. LDRM(video latent, Plücker rays, frame times) → one Gaussian per pixel of the reference frame +
   deformation maps at every distinct frame time → :class:`DynamicGaussians` (static when the
   deformation is the identity), pruned of Gaussians that never contribute.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from models.bundle import WEIGHTS_DIR, Diff4SplatModel, load_config
from models.flow_matching import sample
from models.ldrm import to_gaussians

from .cameras import CameraPath, intrinsics_from_fov, make_trajectory, pack_plucker, plucker_rays
from .prune import prune_scene
from .scene import DynamicGaussians

__all__ = ["Diff4SplatPipeline", "GenerationResult", "load_model"]


@dataclass
class GenerationResult:
    """What :meth:`Diff4SplatPipeline.__call__` returns.

    Attributes:
        scene: the 4D scene (world frame = first camera's frame, metres).
        cameras: the camera path used, re-expressed relative to its first camera.
        latents: (1, c, n, h, w) the sampled video latent fed to the LDRM.
        timings: seconds per stage ("encode_image", "encode_text", "sample", "reconstruct", "prune").
        prune_stats: counts from :func:`diff4splat.prune.prune_scene`.
    """

    scene: DynamicGaussians
    cameras: CameraPath
    latents: Tensor
    timings: dict[str, float] = field(default_factory=dict)
    prune_stats: dict[str, int] = field(default_factory=dict)


def load_model(checkpoint: str | Path | None = None, config: str = "tiny", seed: int = 0) -> tuple[Diff4SplatModel, str]:
    """Load a checkpoint folder, else the shipped weights of ``config``, else a seeded random model.

    Returns:
        (model in eval mode, a description of where the weights came from).

    Raises:
        FileNotFoundError: ``checkpoint`` given but missing, or an unknown config name.
    """
    if checkpoint is not None:
        path = Path(checkpoint)
        if not path.is_dir():
            raise FileNotFoundError(f"checkpoint: {path} is not a folder")
        return Diff4SplatModel.from_pretrained(path).eval(), str(path)
    shipped = WEIGHTS_DIR / config
    if (shipped / "config.json").is_file():
        return Diff4SplatModel.from_pretrained(shipped).eval(), str(shipped)
    warnings.warn(f"no trained weights in {shipped}: using a randomly initialised '{config}' model "
                  f"(seed {seed}); its scenes show the pipeline working, not learned content", stacklevel=2)
    return Diff4SplatModel.random(load_config(config), seed=seed).eval(), f"random:{config}:seed={seed}"


class Diff4SplatPipeline:
    """Single image (+ camera path, + prompt) to a 4D Gaussian scene.

    Args:
        model: the four networks (:class:`models.bundle.Diff4SplatModel`).
        device: torch device to run on.
    """

    def __init__(self, model: Diff4SplatModel, device: str | torch.device = "cpu"):
        self.model = model.to(device).eval()
        self.device = torch.device(device)
        self.config = model.config

    @classmethod
    def from_pretrained(cls, checkpoint: str | Path | None = None, config: str = "tiny",
                        device: str | torch.device = "cpu") -> "Diff4SplatPipeline":
        """Pipeline over :func:`load_model` (shipped weights when ``checkpoint`` is None)."""
        return cls(load_model(checkpoint, config)[0], device)

    def default_cameras(self, trajectory: str = "orbit", num_frames: int | None = None,
                        amplitude: float | None = None) -> CameraPath:
        """A preset trajectory at the model's resolution and field of view (``fov_y_deg``), with
        amplitudes in units of ``config.scene_depth``.

        Raises:
            ValueError: unknown preset or an invalid frame count.
        """
        c = self.config
        K = intrinsics_from_fov(c.width, c.height, fov_y_deg=c.fov_y_deg)
        return make_trajectory(trajectory, num_frames or c.num_frames, K, c.width, c.height,
                               scene_depth=c.scene_depth, amplitude=amplitude)

    @torch.no_grad()
    def __call__(
        self,
        image: Tensor,  # (H, W, 3) in [0, 1] at the model resolution
        cameras: CameraPath,
        prompt: str = "",
        *,
        steps: int | None = None,
        sampler: str | None = None,
        seed: int = 0,
        progress: bool = False,
    ) -> GenerationResult:
        """Generate a 4D scene.

        Args:
            image: (H, W, 3) float in [0, 1], H×W = the model resolution (see :func:`diff4splat.io.load_image`).
            cameras: T = 1 + 4k cameras at the model resolution; re-expressed relative to the first.
            prompt: text describing the motion; "" runs no text encoder.
            steps: sampler steps (default: config.sampling.steps).
            sampler: "euler" or "heun" (default: config.sampling.sampler).
            seed: seed of the initial noise.
            progress: tqdm progress bars.

        Returns:
            :class:`GenerationResult`.

        Raises:
            ValueError: wrong image shape or range, cameras at another resolution, T ≠ 1 + 4k,
                an unknown sampler or steps < 1.
        """
        cfg, m = self.config, self.model
        dev = self.device
        if image.dim() != 3 or tuple(image.shape) != (cfg.height, cfg.width, 3):
            raise ValueError(f"image must have shape ({cfg.height}, {cfg.width}, 3), got {tuple(image.shape)}")
        if not bool(torch.isfinite(image).all()) or float(image.min()) < 0 or float(image.max()) > 1:
            raise ValueError("image values must be finite and lie in [0, 1]")
        if (cameras.width, cameras.height) != (cfg.width, cfg.height):
            raise ValueError(f"cameras are {cameras.width}×{cameras.height}, the model runs at {cfg.width}×{cfg.height}")
        n = cfg.vae.num_latent_frames(len(cameras))  # raises for T ≠ 1 + 4k
        steps = cfg.sampling.steps if steps is None else steps
        sampler = cfg.sampling.sampler if sampler is None else sampler
        if sampler not in ("euler", "heun"):
            raise ValueError(f"sampler must be 'euler' or 'heun', got {sampler!r}")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps must be an int ≥ 1, got {steps!r}")
        cameras = cameras.relative_to_first().to(dtype=torch.float32, device=dev)
        timings: dict[str, float] = {}

        t0 = time.perf_counter()
        video = (image.to(dev, torch.float32) * 2 - 1).permute(2, 0, 1)[None, :, None]  # (1, 3, 1, H, W)
        image_latent = m.vae.encode_latents(video)  # (1, c, 1, h, w)
        timings["encode_image"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        text = text_mask = None
        if prompt.strip():
            text, text_mask = m.text_encoder.encode([prompt])
            text, text_mask = text.to(dev), text_mask.to(dev)
        timings["encode_text"] = time.perf_counter() - t0

        plucker = pack_plucker(plucker_rays(cameras.viewmats, cameras.Ks, cfg.width, cfg.height)[None],
                               cfg.vae.temporal_factor, cfg.vae.spatial_factor)  # (1, 1536, n, h, w)

        t0 = time.perf_counter()
        gen = torch.Generator(device="cpu").manual_seed(seed)
        noise = torch.randn((1, cfg.vae.latent_channels, n, *image_latent.shape[-2:]), generator=gen).to(dev)

        def velocity(x: Tensor, sigma: Tensor) -> Tensor:
            return m.dit(x, sigma.reshape(1).to(x), image_latent, plucker, text, text_mask)

        latents = sample(velocity, noise, steps, sampler=sampler, shift=cfg.sampling.shift, progress=progress)
        latents = torch.cat([image_latent, latents[:, :, 1:]], dim=2)
        timings["sample"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        key_times = torch.unique(cameras.times)
        out = m.ldrm(latents, plucker, key_times)
        gaussians, d_means, d_quats, d_scales = to_gaussians(out, cameras.viewmats[0], cameras.Ks[0])
        scene = DynamicGaussians(gaussians, key_times, d_means, d_quats, d_scales).without_deformation(cfg.static_atol)
        timings["reconstruct"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        scene, stats = prune_scene(scene, cameras, min_opacity=cfg.prune_opacity)
        timings["prune"] = time.perf_counter() - t0
        return GenerationResult(scene=scene, cameras=cameras, latents=latents, timings=timings, prune_stats=stats)
