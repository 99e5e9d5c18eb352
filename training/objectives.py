"""The training objectives of each stage: :class:`TrainingModule`, whose ``forward(batch, generator)`` returns the
losses (so DDP/FSDP wrap it as usual). Video networks are reached through a :class:`models.backbone.Backbone`, so the
same objectives train our networks and a diffusers backbone with our LDRM (docs/DESIGN.md, "Training"). Batches are
collated :class:`data_prep.clips.ClipDataset` items (keys in :meth:`TrainingModule.forward`). Every draw is made on
the CPU step generator and moved to the data, so a seed gives the same numbers on every device; under bf16 autocast
the VAE latents (the flow targets) stay float32. ``plucker_packed`` fits our 4×8×8 latent grid; for another grid
the rays are packed here for the backbone's :class:`models.backbone.LatentFormat`.
"""
from __future__ import annotations

import contextlib
from functools import partial

import torch
from torch import Tensor, nn

from diff4splat.assembly.assemble import assemble_scene, to_gaussians
from diff4splat.assembly.frame_motion import frame_motion
from diff4splat.assembly.photo import PHOTO_EPS2D
from diff4splat.assembly.prune import settle_generated
from diff4splat.cameras import camera_rays, pack_plucker, plucker_rays
from diff4splat.cameras.path import CameraPath
from diff4splat.render import rasterize
from diff4splat.render.settings import EPS2D
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.devices import autocast_off
from models.backbone import Backbone, LatentFormat
from models.backbone_model import BackboneModel
from models.backbones.ours import OursBackbone
from models.bundle import Diff4SplatModel
from models.ldrm import LDRM, LDRMOutput, distance_activation, source_frame_indices
from models.motion_generator import motion_targets
from models.vae import kl_divergence

from .losses import (
    depth_correlation_loss,
    depth_smoothness_loss,
    displacement_loss,
    flow_matching_errors,
    gather_track_predictions,
    head_distillation_loss,
    log_depth_loss,
    motion_loss,
    moving_cells,
    photometric_loss,
    scene_flow_loss,
    warp_loss,
)
from .motion_generation import mirrored_loss
from .stage_config import StageConfig

__all__ = ["TrainingModule", "render_frames", "track_query_index", "FLOW_LOSS_FROM_FRAME"]

FLOW_LOSS_FROM_FRAME = {"wan2.2-ti2v": 1}
"""First latent frame of the flow-matching loss per backbone kind (0 when absent): Wan2.2-TI2V replaces latent
frame 0 by the photograph's latent (:mod:`models.backbones.wan`), so its output there has no target."""


def render_frames(scene: DynamicGaussians, viewmats: Tensor, Ks: Tensor, times: Tensor, frames: list[int],
                  width: int, height: int, *, eps2d: float = EPS2D, background: Tensor | None = None
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable renders (rgb (F, 3, H, W), expected depth (F, H, W) metres, alpha (F, H, W)) of ``frames`` of a
    clip (``viewmats`` (T, 4, 4), ``Ks`` (T, 3, 3), ``times`` (T,)), each with the scene at its own time; ``eps2d``
    in pixels², ``background`` (3,) RGB in [0, 1] or None (black)."""
    bg = None if background is None else background.to(viewmats)[None]  # (1, 3)

    def draw(g, vm: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        out, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, vm, K, width, height,
                                  sh_degree=g.sh_degree, render_mode="RGB+ED", eps2d=eps2d,
                                  backgrounds=None if bg is None else bg.expand(len(vm), 3))
        return out, alpha

    if scene.is_static:  # one call, all cameras
        out, alpha = draw(scene.canonical, viewmats[frames], Ks[frames])
    else:
        parts = [draw(scene.at(float(times[f])), viewmats[f:f + 1], Ks[f:f + 1]) for f in frames]
        out, alpha = torch.cat([o for o, _ in parts]), torch.cat([a for _, a in parts])
    return out[..., :3].permute(0, 3, 1, 2), out[..., 3], alpha[..., 0]


def track_query_index(tracks0: Tensor, K: Tensor, width: int, height: int, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Row-major pixel index (N,) long (0 where invalid) of each frame-0 track point ``tracks0`` (N, 3) metres in the
    reference camera (u = fx·x/z + cx, pixel (⌊v⌋, ⌊u⌋)), and ``valid`` (N,) narrowed to points in front and inside."""
    z = tracks0[:, 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    u = K[0, 0] * tracks0[:, 0] / zs + K[0, 2]
    v = K[1, 1] * tracks0[:, 1] / zs + K[1, 2]
    ok = valid & (z > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx = torch.where(ok, v.floor().long().clamp(0, height - 1) * width + u.floor().long().clamp(0, width - 1), 0)
    return idx, ok


class TrainingModule(nn.Module):
    """Wraps a :class:`Diff4SplatModel` or a :class:`BackboneModel` with a stage's objectives.

    Loss components: ``vae_l1``, ``vae_kl`` (vae), ``flow`` (diffusion), ``photo``, ``depth``, ``smooth``, ``motion``,
    ``displacement``, ``metric_depth`` (reconstruction; the last with a weight > 0), ``displacement`` and ``warp``
    (tracking), ``distill``, ``mono_depth`` (depth), ``motion_flow`` (motion_generation). ``teacher``: the frozen
    LDRM that ``distill`` follows, required by it alone (ValueError otherwise).
    """

    def __init__(self, model: Diff4SplatModel | BackboneModel, stage: StageConfig, teacher: LDRM | None = None):
        super().__init__()
        self.model = model
        self.stage = stage
        if ("distill" in stage.objectives) != (teacher is not None):
            raise ValueError("teacher: the distill objective needs a teacher LDRM, and only it uses one")
        self.teacher = None if teacher is None else teacher.requires_grad_(False).eval()

    def backbone(self) -> Backbone:
        """The model's video backbone: a diffusers model's own, or a per-call :class:`OursBackbone` view of our
        networks with σ shifted by the stage's ``flow_shift``."""
        m = self.model
        if isinstance(m, BackboneModel):
            return m.backbone
        s = m.config.sampling
        return OursBackbone(m.vae, m.text_encoder, m.dit, shift=self.stage.flow_shift,
                            logit_normal=(s.logit_normal_mean, s.logit_normal_std))

    @property
    def checkpoint_frozen(self) -> bool:
        """Whether checkpoints hold the frozen weights too: ours do; a diffusers backbone's are rebuilt from
        ``init_from`` on resume."""
        return not isinstance(self.model, BackboneModel)

    def fsdp_units(self) -> list[nn.Module]:
        """The modules FSDP shards one by one before the root: the blocks of the video transformer, the LDRM and the
        text encoder (a diffusers T5/umT5's ``encoder.block``)."""
        m = self.model
        if isinstance(m, BackboneModel):
            b = m.backbone
            text_blocks = getattr(getattr(b.text_encoder, "encoder", None), "block", None) or []
            return [*b.transformer_blocks(), *m.ldrm.blocks, *text_blocks]
        return [*m.dit.blocks, *m.ldrm.blocks, *m.text_encoder.blocks]

    def enable_gradient_checkpointing(self) -> None:
        """Recompute the video transformer's blocks in the backward pass (``trainer.gradient_checkpointing``)."""
        if isinstance(self.model, BackboneModel):
            self.model.backbone.transformer.enable_gradient_checkpointing()
        else:
            self.model.dit.gradient_checkpointing = True

    def train(self, mode: bool = True) -> TrainingModule:
        """As :meth:`nn.Module.train`; the teacher and a diffusers backbone's VAE and text encoder stay in eval."""
        super().train(mode)
        if self.teacher is not None:
            self.teacher.eval()
        if isinstance(self.model, BackboneModel):
            self.model.backbone.vae.eval()
            self.model.backbone.text_encoder.eval()
        return self

    def forward(self, batch: dict, generator: torch.Generator) -> dict[str, Tensor]:
        """{"loss": weighted total, <component>: value} (0-dim tensors) of the stage's objectives on one batch.

        ``batch``: ``video`` (B, 3, T, H, W) in [0, 1], ``viewmats`` (B, T, 4, 4) world-to-camera (metres), ``Ks``
        (B, T, 3, 3) pixels, ``times`` (B, T) in [0, 1], ``plucker_packed`` (B, 1536, n, h, w) and/or ``plucker``
        (B, T, H, W, 6), ``depth``/``depth_valid`` (B, T, H, W), ``tracks`` (B, N, T, 3) metres,
        ``track_visibility`` (B, N, T), ``track_mask`` (B, N), ``caption`` list of B str. ``generator``: the CPU
        step generator. Raises ValueError when ``depth`` or ``tracking`` lacks its LDRM network.
        """
        st, m = self.stage, self.model
        video = batch["video"] * 2 - 1  # (B, 3, T, H, W) in [−1, 1]
        losses: dict[str, Tensor] = {}
        total = video.new_zeros(())
        if "vae" in st.objectives:  # ε on the CPU step generator, moved (vae.sample_posterior)
            recon, mean, logvar = m.vae(video, sample_posterior=True, generator=generator)
            losses["vae_l1"] = (recon - video).abs().mean()
            losses["vae_kl"] = kl_divergence(mean, logvar).mean() / mean[0].numel()
            total = total + losses["vae_l1"] + st.kl_weight * losses["vae_kl"]
        if {"diffusion", "reconstruction", "distill", "tracking"} & set(st.objectives):
            backbone = self.backbone()
            with torch.no_grad():  # the VAE is frozen after its own stage
                latents = backbone.latent_model.encode_latents(video).to(video.dtype)  # float32 under bf16 autocast
            plucker = self._plucker(batch, backbone.latent, tuple(latents.shape[2:]))
        if "diffusion" in st.objectives:
            losses.update(self._diffusion(backbone, latents, plucker, batch, generator))
            total = total + losses["flow"] + st.weights.mover * losses.get("flow_mover", 0)
        if "distill" in st.objectives:
            losses["distill"] = self._distill(latents, plucker, generator)
            total = total + losses["distill"]
        if "reconstruction" in st.objectives:
            rec = self._reconstruction(backbone.latent, latents, plucker, batch, generator)
            losses.update(rec)
            w = st.weights
            total = total + w.rgb * rec["photo"] + w.depth * rec["depth"] + w.smooth * rec["smooth"]
            if "metric_depth" in rec:
                total = total + w.metric_depth * rec["metric_depth"]
            if "motion" in rec:
                total = total + w.motion * rec["motion"] + w.displacement * rec["displacement"]
            if "scene_flow" in rec:
                total = total + w.scene_flow * rec["scene_flow"]
        if "tracking" in st.objectives:
            tracking = self._tracking(latents, plucker, batch, generator)
            losses.update(tracking)
            w = st.weights
            total = total + w.displacement * tracking["displacement"] + w.warp * tracking["warp"]
            if "scene_flow" in tracking:
                total = total + w.scene_flow * tracking["scene_flow"]
        if "depth" in st.objectives:
            losses["mono_depth"] = self._mono_depth(batch)
            total = total + losses["mono_depth"]
        if "motion_generation" in st.objectives:
            losses["motion_flow"] = self._motion_generation(batch, generator)
            total = total + st.weights.motion_flow * losses["motion_flow"]
        losses["loss"] = total
        return losses

    def _motion_generation(self, batch: dict, generator: torch.Generator) -> Tensor:
        """:func:`training.motion_generation.mirrored_loss` of the motion generator on frame 0 of each clip and its
        dense true tracks, the caption dropped at ``caption_dropout``. ValueError: the model has no motion generator,
        or the clips are not its ``image_size``."""
        mg = self.model.motion_generator
        if mg is None:
            raise ValueError("the motion_generation objective trains motion_generator; this model has none")
        cfg, (H, W) = mg.config, batch["video"].shape[-2:]
        if H != cfg.image_size or W != cfg.image_size:
            raise ValueError(f"motion_generation: clips of {H}×{W} pixels, the motion generator reads "
                             f"{cfg.image_size}×{cfg.image_size} (set stage.height and width)")
        with autocast_off():
            motion, weight = motion_targets(batch["pixel_tracks"].float(), batch["pixel_track_valid"],
                                            cfg.key_frames, cfg.grid, cfg.motion_scale)
        return mirrored_loss(mg, batch["video"][:, :, 0] * 2 - 1, batch["depth"][:, 0], motion, weight,
                             list(batch["caption"]), generator, p_uncond=self.stage.caption_dropout)

    def _mono_depth(self, batch: dict) -> Tensor:
        """Scale-invariant log loss (λ 0.5) of ``ldrm.image_depth``'s z-depth on every frame against the valid metric
        depth; ValueError when the LDRM has none."""
        ldrm = self.model.ldrm
        if ldrm.image_depth is None:
            raise ValueError("the depth objective trains ldrm.image_depth; this LDRM has none (image_depth: 0)")
        H, W = batch["video"].shape[-2:]
        frames = batch["video"].transpose(1, 2).flatten(0, 1) * 2 - 1  # (B·T, 3, H, W) in [−1, 1]
        distance = distance_activation(ldrm.image_depth(frames), ldrm.config)  # (B·T, H, W) metres
        with autocast_off():
            Ks = batch["Ks"].flatten(0, 1).float()
            eye = torch.eye(4, device=Ks.device).expand(len(Ks), 4, 4)
            _, dirs = camera_rays(eye, Ks, W, H)  # camera frame: the z component is cos θ
            z = distance.float() * dirs[..., 2]
            return log_depth_loss(z, batch["depth"].flatten(0, 1).float(), batch["depth_valid"].flatten(0, 1))

    @staticmethod
    def _plucker(batch: dict, latent: LatentFormat, grid: tuple[int, int, int]) -> Tensor:
        """(B, 6·t·s², n, h, w) Plücker rays on ``grid`` = (n, h, w): the dataset's when packed for ``latent``."""
        packed = batch.get("plucker_packed")
        if packed is not None and packed.shape[1] == latent.camera_channels and tuple(packed.shape[2:]) == grid:
            return packed
        with autocast_off():
            rays = batch.get("plucker")  # (B, T, H, W, 6)
            if rays is None:
                (B, T), (H, W) = batch["viewmats"].shape[:2], batch["video"].shape[-2:]
                rays = plucker_rays(batch["viewmats"].flatten(0, 1).float(), batch["Ks"].flatten(0, 1).float(), W, H)
                rays = rays.reshape(B, T, H, W, 6)
            return pack_plucker(rays.float(), latent.temporal_factor, latent.spatial_factor)

    def _diffusion(self, backbone: Backbone, latents: Tensor, plucker: Tensor, batch: dict, gen: torch.Generator
                   ) -> dict[str, Tensor]:
        """{"flow": flow-matching loss on ``latents`` (B, c, n, h, w)} and, with ``weights.mover`` > 0, "flow_mover":
        its mean over the cells moving objects cover (:func:`training.losses.moving_cells`; 0 where none does); draws
        caption dropout (B,), σ (B,), then ε. ValueError when ``weights.mover`` > 0 and the batch has no
        ``pixel_tracks``."""
        st = self.stage
        B, dev = latents.shape[0], latents.device
        captions = list(batch["caption"])
        drop = (torch.rand(B, generator=gen, device=gen.device) < st.caption_dropout).to(dev)
        has_text = torch.tensor([bool(c.strip()) for c in captions], device=dev)
        keep = ~drop & has_text
        # the paper's T5 is frozen (no graph); a stage that lists text_encoder trains ours through this loss
        trains_text = any(p.requires_grad for p in backbone.text_model.parameters())
        with contextlib.nullcontext() if trains_text else torch.no_grad():
            if backbone.encodes_empty_prompt:  # its unconditional input: the embedding of "" (text=None)
                prompts = [c if k else "" for c, k in zip(captions, keep.tolist(), strict=True)]
                text, mask = backbone.text_model.encode_text(prompts)
            else:  # ours: no prompt is no text tokens, and an all-false mask is exactly that path
                text, mask = backbone.text_model.encode_text(captions)
                mask = mask.to(dev) & keep[:, None]
        text, mask = text.to(dev), mask.to(dev)
        image_latent = latents[:, :, :1]
        sigma = backbone.training_sigmas(B, gen).to(latents)
        noise = torch.randn(latents.shape, generator=gen, device=gen.device).to(latents)
        velocity = partial(backbone.velocity_model, image_latent=image_latent, plucker=plucker, text=text,
                           text_mask=mask)
        err = flow_matching_errors(velocity, latents, noise, sigma)  # (B, c, n, h, w)
        first = FLOW_LOSS_FROM_FRAME.get(backbone.kind, 0)
        out = {"flow": err[:, :, first:].mean()}
        if st.weights.mover > 0:
            if "pixel_tracks" not in batch:
                raise ValueError("weights.mover > 0 needs the batch's pixel_tracks and pixel_track_valid "
                                 "(data_prep.clips.ClipDataset gives them)")
            cells = moving_cells(batch["pixel_tracks"], batch["pixel_track_valid"], batch["viewmats"], batch["Ks"],
                                 tuple(latents.shape[2:]), backbone.latent.temporal_factor)
            cells[:, :first] = False  # frames the backbone replaces by a condition have no target
            per_cell = err.mean(1)  # (B, n, h, w)
            out["flow_mover"] = (per_cell * cells).sum() / cells.sum().clamp(min=1)
        return out

    def _assemble(self, out: LDRMOutput, sources: Tensor, batch: dict, b: int, times: Tensor | None
                  ) -> tuple[DynamicGaussians, dict]:
        """Clip b's scene as ``generate`` builds it (``stage.scene: assembled``): photo layer, backdrop and the settled
        generated Gaussians (drops and slides chosen without gradient), and the photo layer's info."""
        H, W = batch["video"].shape[-2:]
        with autocast_off():
            cams = CameraPath(batch["viewmats"][b].float(), batch["Ks"][b].float(), W, H, batch["times"][b].float())
            image = batch["video"][b, :, 0].permute(1, 2, 0).float().clamp(0, 1)  # (H, W, 3)
            scene, grid, photo = assemble_scene(out, sources, cams, cams, image, times)
            scene, drop, _ = settle_generated(scene, grid, cams, sources, photo["photo_depth"].detach())
        photo["background"] = torch.tensor(photo["background"], device=image.device)
        return scene.select(~drop), photo

    def _decoded(self, out: LDRMOutput, sources: Tensor, batch: dict, b: int, times: Tensor) -> DynamicGaussians:
        """Clip b's decoded scene (``stage.scene: decoded``): every source frame's pixel-aligned Gaussians."""
        with autocast_off():
            g, d_means, d_quats, d_scales = to_gaussians(out, batch["viewmats"][b][sources].float(),
                                                         batch["Ks"][b][sources].float())
        return DynamicGaussians(g) if d_means is None else DynamicGaussians(g, times, d_means, d_quats, d_scales)

    def _decoded_frames(self, latents: Tensor) -> Tensor:
        """The VAE's decoding of DiT-scaled ``latents`` (B, c, n, h, w): (B, T, 3, H, W) in [0, 1], no gradient."""
        with torch.no_grad():
            video = self.backbone().latent_model.decode_latents(latents)  # (B, 3, T, H, W) in about [−1, 1]
        return ((video.float() + 1) / 2).clamp(0, 1).transpose(1, 2)

    def _tracking(self, latents: Tensor, plucker: Tensor, batch: dict, gen: torch.Generator) -> dict[str, Tensor]:
        """The ``tracking`` objective: the motion network alone follows frame 0's pixels through the decoded (noised)
        latents on the LDRM's frame-0 depth (no gradient, no renders); batch means of ``displacement`` and ``warp``.
        Raises ValueError when the LDRM has no motion network."""
        m = self.model
        if m.ldrm.motion is None:
            raise ValueError("the tracking objective trains ldrm.motion; this LDRM has none (ldrm.motion: null)")
        B, _, T, H, W = batch["video"].shape
        latents = self._noised(latents, gen)
        frames = self._decoded_frames(latents)
        with torch.no_grad():
            distance = m.ldrm(latents, plucker, None, batch["video"][:, :, 0] * 2 - 1).distance[:, :1].float()
        source = torch.zeros(1, dtype=torch.long, device=latents.device)
        sums: dict[str, Tensor] = {}
        with autocast_off():  # the B clips' pixels through the motion network together
            times, viewmats, intrinsics = batch["times"].float(), batch["viewmats"].float(), batch["Ks"].float()
            maps = LDRMOutput(distance=distance, scales=None, quats=None, opacities=None, colors=None)
            moved = frame_motion(m.ldrm.motion, maps, frames, times, viewmats, intrinsics, source, times)
        for b in range(B):
            with autocast_off():
                vm, Ks, d = viewmats[b], intrinsics[b], moved.d_means[b, :, 0]  # d: (T, H, W, 3)
                o, dirs = camera_rays(vm[:1], Ks[:1], W, H)
                points = (o + dirs * distance[b, 0, ..., None])[0] + d  # (T, H, W, 3)
                tracks = batch["tracks"][b]
                vis = batch["track_visibility"][b] & batch["track_mask"][b][:, None]
                idx, ok = track_query_index(tracks[:, 0], Ks[0], W, H, vis[:, 0])
                pred = points.reshape(T, H * W, 3)[:, idx].transpose(0, 1)  # (N, T, 3)
                parts = {"displacement": displacement_loss(pred[None], tracks[None], (vis & ok[:, None])[None]),
                         "warp": warp_loss(frames[b], points, vm, Ks)}
                if self.stage.weights.scene_flow > 0:
                    parts["scene_flow"] = scene_flow_loss(points, *self._pixel_tracks(batch, b))
            for k, v in parts.items():
                sums[k] = sums.get(k, 0) + v / B
        return sums

    @staticmethod
    def _pixel_tracks(batch: dict, b: int) -> tuple[Tensor, Tensor]:
        """Clip ``b``'s dense 3D tracks (T, H, W, 3) metres and their valid pixels (H, W) (``ClipDataset``). Raises
        ValueError when the batch has none (weights.scene_flow > 0 needs them)."""
        if "pixel_tracks" not in batch:
            raise ValueError("weights.scene_flow > 0 needs the batch's pixel_tracks and pixel_track_valid "
                             "(data_prep.clips.ClipDataset gives them)")
        return batch["pixel_tracks"][b], batch["pixel_track_valid"][b]

    def _noised(self, latents: Tensor, gen: torch.Generator) -> Tensor:
        """``latents`` with frames 1… noised to (1 − σ)z + σε, σ ~ U(0, ``stage.latent_noise``) per clip (draws σ,
        then ε); unchanged when it is 0."""
        if self.stage.latent_noise <= 0:
            return latents
        B = latents.shape[0]
        sigma = (torch.rand(B, generator=gen, device=gen.device) * self.stage.latent_noise).to(latents)
        sigma = sigma[:, None, None, None, None]
        eps = torch.randn(latents.shape, generator=gen, device=gen.device).to(latents)
        noisy = (1 - sigma) * latents + sigma * eps
        return torch.cat([latents[:, :, :1], noisy[:, :, 1:]], dim=2)

    def _distill(self, latents: Tensor, plucker: Tensor, gen: torch.Generator) -> Tensor:
        """The ``distill`` objective: :func:`training.losses.head_distillation_loss` of the head's maps on the noised
        latents against the teacher's."""
        ldrm, latents = self.model.ldrm, self._noised(latents, gen)
        with torch.no_grad():
            target = self.teacher.head_maps(self.teacher.features(latents, plucker))
        return head_distillation_loss(ldrm.head_maps(ldrm.features(latents, plucker)), target, self.stage.distill_sigma)

    def _reconstruction(self, latent: LatentFormat, latents: Tensor, plucker: Tensor, batch: dict,
                        gen: torch.Generator) -> dict[str, Tensor]:
        """Rendering losses of the LDRM's scenes from ``latents`` (B, c, n, h, w), averaged over the batch."""
        m, st = self.model, self.stage
        B, _, T, H, W = batch["video"].shape
        image = batch["video"][:, :, 0] * 2 - 1  # (B, 3, H, W) the photograph, for an image branch
        latents = self._noised(latents, gen)
        sources = torch.tensor(source_frame_indices(m.ldrm.config.gaussian_frames, latents.shape[2],
                                                    latent.temporal_factor), device=latents.device)
        sums: dict[str, Tensor] = {}
        outs = None if st.deformation else m.ldrm(latents, plucker, None, image)
        # the frames the motion network reads, as generate gives them: the decoding of the latents the LDRM reads
        seen = self._decoded_frames(latents) if st.deformation and m.ldrm.motion is not None else None
        for b in range(B):
            times = batch["times"][b].to(torch.promote_types(latents.dtype, torch.float32))  # never bf16
            if st.deformation:
                out = m.ldrm(latents[b:b + 1], plucker[b:b + 1], times, image[b:b + 1])
                if seen is not None:  # the motion path reads the frames (diff4splat.assembly.frame_motion)
                    with autocast_off():
                        out = frame_motion(m.ldrm.motion, out, seen[b:b + 1], batch["times"][b:b + 1].float(),
                                           batch["viewmats"][b:b + 1].float(), batch["Ks"][b:b + 1].float(),
                                           sources, times[None])
            else:
                out = LDRMOutput(**{k: None if v is None else v[b:b + 1] for k, v in vars(outs).items()})
            if st.scene == "assembled":
                scene, photo = self._assemble(out, sources, batch, b, times if st.deformation else None)
                eps2d, background = PHOTO_EPS2D, photo["background"]
            else:
                scene, eps2d, background = self._decoded(out, sources, batch, b, times), EPS2D, None
            others = torch.randperm(T - 1, generator=gen, device=gen.device)[: st.render_frames - 1] + 1
            frames = [0] + sorted(others.tolist())
            rgb, depth, alpha = render_frames(scene, batch["viewmats"][b], batch["Ks"][b], times, frames, W, H,
                                              eps2d=eps2d, background=background)
            target = batch["video"][b][:, frames].permute(1, 0, 2, 3)  # (F, 3, H, W)
            gt_depth, valid = batch["depth"][b][frames], batch["depth_valid"][b][frames]
            parts = {
                "photo": photometric_loss(rgb, target, st.weights.ssim),
                "depth": depth_correlation_loss(depth, gt_depth, valid & (alpha > 0.5)),
                "smooth": depth_smoothness_loss(depth, target, alpha > 0.5),
            }
            if st.weights.metric_depth > 0:
                parts["metric_depth"] = log_depth_loss(depth, gt_depth, valid & (alpha > 0.5))
            if st.motion:
                tracks, vis = batch["tracks"][b], batch["track_visibility"][b] & batch["track_mask"][b][:, None]
                idx, ok = track_query_index(tracks[:, 0], batch["Ks"][b, 0], W, H, vis[:, 0])
                # idx < H·W: frame 0's Gaussians (or the photo layer's front disks) come first

                pred = gather_track_predictions(scene.canonical.means[None], scene.d_means[None], idx[None])[0]
                parts["motion"] = motion_loss(pred, tracks, vis & ok[:, None])
                parts["displacement"] = displacement_loss(pred[None], tracks[None], (vis & ok[:, None])[None])
            if st.motion and st.weights.scene_flow > 0:  # frame 0's Gaussians: the first H·W, pixel-aligned
                g = scene.canonical.means[None, :H * W] + scene.d_means[:, :H * W]  # (T, H·W, 3)
                parts["scene_flow"] = scene_flow_loss(g.reshape(T, H, W, 3), *self._pixel_tracks(batch, b))
            for k, v in parts.items():
                sums[k] = sums.get(k, 0) + v / B
        return sums
