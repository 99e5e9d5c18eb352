"""Image + camera path + optional prompt → 4D Gaussian scene (Diff4Splat, Pan et al. 2025, Fig. 2).

The networks run at the model resolution, the photograph and path at the output resolution: VAE encoder → text
encoder (skipped for an empty prompt) → Plücker rays → flow-matching sampler over the DiT (frame 0 replaced by the
photograph's latent) → LDRM → :func:`diff4splat.assembly.assemble.assemble_scene` → pruning (docs/DESIGN.md, "Data
flow of generate"). :meth:`Diff4SplatPipeline.reconstruct` is the other route: a video's own latents → LDRM → its
frames as photo layers (:mod:`diff4splat.assembly.layers`). The networks are reached through a :class:`NetworkRuntime`.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm.auto import tqdm

from diff4splat.assembly.assemble import DEPTH_KINDS, assemble_scene, z_depth
from diff4splat.assembly.drag_scene import dragged_scene, moved_scene
from diff4splat.assembly.frame_motion import frame_motion
from diff4splat.assembly.generated_motion import generated_motion
from diff4splat.assembly.layers import (
    DEFAULT_LAYERS,
    LAYER_ORDER_OFFSET,
    check_layer_knobs,
    check_layers,
    layer_frames,
    layered_scene,
)
from diff4splat.assembly.photo import PHOTO_EPS2D, upsample_depth
from diff4splat.assembly.prune import settle_and_prune
from diff4splat.cameras import (
    DEFAULT_TRAJECTORY,
    CameraPath,
    intrinsics_from_fov,
    make_trajectory,
    pack_plucker,
    plucker_rays,
)
from diff4splat.cameras.path import check_field_of_view
from diff4splat.geometry.drags import Drags
from diff4splat.io.depth_maps import check_depth_values
from diff4splat.render.settings import BACKGROUND
from diff4splat.runtime import NetworkRuntime, TorchRuntime
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.checks import check_positive_int, is_int
from diff4splat.utils.devices import Stopwatch
from diff4splat.utils.limits import check_limit
from models.backbone_model import INDEX_FILE, BackboneModel
from models.bundle import DEFAULT_CONFIG, WEIGHTS_DIR, Diff4SplatModel, load_config, random_init_device
from models.flow_matching import ODESteps, check_guidance, check_sampler
from models.ldrm import source_frame_indices
from models.pretrained import CONFIG_NAME

__all__ = ["Diff4SplatPipeline", "SceneResult", "GenerationResult", "ReconstructionResult", "load_model",
           "check_seed", "check_prompt", "SEED_RANGE",
           "DEFAULT_RESOLUTION"]

DEFAULT_RESOLUTION = 256
"""Default output height, pixels, of ``generate`` (or the model's height if larger)."""

SEED_RANGE = (-(2**63), 2**64 - 1)
"""Seeds ``torch.Generator.manual_seed`` accepts (int64 or uint64)."""


def check_seed(seed: object, name: str = "seed") -> int:
    """``seed`` as an int (an int or numpy integer, not a bool); ValueError outside :data:`SEED_RANGE`."""
    lo, hi = SEED_RANGE
    if not is_int(seed) or not lo <= int(seed) <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}] (-2**63 … 2**64 − 1), got {seed!r}")
    return int(seed)


def check_prompt(prompt: object, name: str = "prompt") -> str:
    """``prompt`` if it is a str that encodes as UTF-8 (non-UTF-8 arguments arrive as lone surrogates); else
    ValueError (naming the first bad byte and its position)."""
    if not isinstance(prompt, str):
        raise ValueError(f"{name} must be a str, got {type(prompt).__name__}")
    try:
        prompt.encode("utf-8")
    except UnicodeEncodeError as e:
        bad = prompt[e.start]
        byte = f"byte {ord(bad) - 0xDC00:#04x}" if 0xDC80 <= ord(bad) <= 0xDCFF else f"character {ord(bad):#06x}"
        raise ValueError(f"{name}: not valid UTF-8 ({byte} at position {e.start}); "
                         f"give the text in UTF-8") from None
    return prompt


@dataclass(kw_only=True)
class SceneResult:
    """What the pipeline makes of a request: the scene and how it was built.

    Attributes:
        scene: the 4D scene (world frame = the first camera's, metres); the photo layer first.
        cameras: the camera path used, relative to its first camera, at the output resolution.
        latents: (1, c, n, h, w) the video latent fed to the LDRM.
        timings: seconds per stage, in the order they ran.
        high_water: on CUDA, the running peak of allocated memory (bytes) at the end of each stage; else empty.
        prune_stats: counts of the pruning (:mod:`diff4splat.assembly.prune`).
        source_frames: (S,) long, the video frame of each source frame (or photo layer).
        gaussian_index: (M,) long, increasing index of each kept Gaussian in the unpruned scene.
        eps2d, background: the screen-space dilation (pixels²) and RGB background in [0, 1] the scene is rendered with.
        photo_psnr_db: PSNR, dB, of the photo layer alone rendered at the input camera against the photograph.
        photo_gaussians, num_slots: the photo layer's share (H·W + ⌈H/2⌉·⌈W/2⌉) and size of the unpruned scene.
    """

    scene: DynamicGaussians
    cameras: CameraPath
    latents: Tensor
    timings: dict[str, float] = field(default_factory=dict)
    high_water: dict[str, int] = field(default_factory=dict)
    prune_stats: dict[str, int] = field(default_factory=dict)
    source_frames: Tensor | None = None
    gaussian_index: Tensor | None = None
    eps2d: float = PHOTO_EPS2D
    background: tuple[float, float, float] = BACKGROUND
    photo_psnr_db: float = float("nan")
    num_slots: int = 0
    photo_gaussians: int = 0


@dataclass(kw_only=True)
class GenerationResult(SceneResult):
    """What :meth:`Diff4SplatPipeline.__call__` returns: a :class:`SceneResult` (timings "encode_image",
    "encode_text", "sample", "reconstruct", "prune"; ``latents`` sampled; the unpruned order of
    :func:`diff4splat.assembly.assemble.assemble_scene`) and the sampling.

    Attributes:
        steps, sampler, shift, guidance: the sampler settings actually used (guidance 1 without a prompt).
        video: (1, 3, T, h, w) ``latents`` decoded by the VAE, in about [−1, 1], when ``generated_colors: video``
            needed it, else None.
    """

    steps: int
    sampler: str
    guidance: float
    shift: float
    video: Tensor | None = None


@dataclass(kw_only=True)
class ReconstructionResult(SceneResult):
    """What :meth:`Diff4SplatPipeline.reconstruct` returns: a :class:`SceneResult` of a clip's frames (timings
    "encode_video", "reconstruct", "backdrop", "motion", "assemble", "prune"; ``latents`` the clip's own;
    ``source_frames`` the frames that became photo layers; the unpruned order of
    :func:`diff4splat.assembly.layers.layered_scene`).

    Attributes:
        layers: which frames became photo layers (:data:`diff4splat.assembly.layers.LAYERS`).
    """

    layers: str


def load_model(checkpoint: str | Path | None = None, config: str = DEFAULT_CONFIG, seed: int = 0, *,
               untrained: bool = False, dtype: torch.dtype | None = None, init_device: str | torch.device = "cpu"
               ) -> tuple[Diff4SplatModel | BackboneModel, str]:
    """Load a checkpoint folder, else the shipped weights of ``config``, else a seeded random model (with a warning).

    A folder is ours (``config.json``) or a diffusers backbone's (``model_index.json``); weights load directly in
    ``dtype``. ``untrained=True`` returns the seeded random model without a warning. A random model is built on
    ``init_device`` when :func:`models.bundle.random_init_device` finds room there, then returned on the CPU; its
    source then ends in ``:<device type>``. Returns (model in eval mode, where the weights came from).

    Raises:
        FileNotFoundError: ``checkpoint`` given but missing, or an unknown config name.
        ValueError: a folder that is neither format.
        MissingExtraError: a diffusers folder without ``diff4splat[diffusers]`` installed.
    """
    random_source = f"random:{config}:seed={seed}"
    if untrained:
        return Diff4SplatModel.random(load_config(config), seed=seed, dtype=dtype).eval(), random_source
    if checkpoint is not None:
        path = Path(checkpoint)
        if not path.is_dir():
            raise FileNotFoundError(f"checkpoint: {path} is not a folder")
        if (path / INDEX_FILE).is_file():
            return BackboneModel.from_pretrained(path, torch_dtype=dtype, seed=seed).eval(), str(path)
        if not (path / CONFIG_NAME).is_file():
            raise ValueError(f"checkpoint: {path} is neither a diff4splat model (config.json) nor a diffusers backbone "
                             f"folder ({INDEX_FILE}, e.g. Wan-AI/Wan2.2-TI2V-5B-Diffusers)")
        return Diff4SplatModel.from_pretrained(path, dtype=dtype).eval(), str(path)
    shipped = WEIGHTS_DIR / config
    if (shipped / CONFIG_NAME).is_file():
        return Diff4SplatModel.from_pretrained(shipped, dtype=dtype).eval(), str(shipped)
    warnings.warn(f"no trained weights in {shipped}: using a randomly initialised '{config}' model "
                  f"(seed {seed}); its scenes show the pipeline working, not learned content", stacklevel=2)
    cfg = load_config(config)
    where = random_init_device(cfg, init_device, dtype)
    model = Diff4SplatModel.random(cfg, seed=seed, device=where, dtype=dtype, host=True).eval()
    return model, random_source + ("" if where.type == "cpu" else f":{where.type}")


def _without_full_mask(text: Tensor, mask: Tensor, device: torch.device) -> tuple[Tensor, Tensor | None]:
    """Tokens (1, L, d) and mask (1, L) on ``device``; an all-True mask becomes None (unmasked fused attention)."""
    text, mask = text.to(device), mask.to(device)
    return text, None if bool(mask.all()) else mask


class Diff4SplatPipeline:
    """Single image (+ camera path, + prompt) to a 4D Gaussian scene; raises TypeError for a ``model`` that is
    neither a Diff4SplatModel, a BackboneModel nor a NetworkRuntime.

    Args:
        model: a :class:`Diff4SplatModel` or :class:`BackboneModel` (run by a :class:`TorchRuntime`), or any
            :class:`NetworkRuntime` (e.g. ``OnnxRuntime``).
        device: torch device of the networks and the pipeline's tensors ("cpu" for a non-torch runtime).
        dtype, offload, attention, compile: as :class:`TorchRuntime` (sampling and Gaussians stay float32).

    Attributes:
        runtime, config, model: the :class:`NetworkRuntime`, the model's config, the PyTorch model (or None).
        source: where the weights came from (a folder, ``random:<config>:seed=<n>[:cuda]``, ``onnx:<folder> (…)``);
            None for a model in memory.
    """

    def __init__(self, model: Diff4SplatModel | BackboneModel | NetworkRuntime, device: str | torch.device = "cpu",
                 *, dtype: torch.dtype | None = None, offload: str = "none", attention: str = "auto",
                 compile: bool = False):
        if isinstance(model, (Diff4SplatModel, BackboneModel)):
            self.model: Diff4SplatModel | BackboneModel | None = model
            self.runtime: NetworkRuntime = TorchRuntime(model, device, dtype=dtype, offload=offload,
                                                         attention=attention, compile=compile)
        elif isinstance(model, NetworkRuntime):
            self.model, self.runtime = None, model
        else:
            raise TypeError(f"model must be a Diff4SplatModel, a BackboneModel or a NetworkRuntime, got "
                            f"{type(model).__name__}")
        self.device = torch.device(device)
        self.config = self.runtime.config
        self.source: str | None = None

    @classmethod
    def from_pretrained(cls, checkpoint: str | Path | None = None, config: str = DEFAULT_CONFIG,
                        device: str | torch.device = "cpu", *, dtype: torch.dtype | None = None,
                        offload: str = "none", attention: str = "auto",
                        compile: bool = False) -> Diff4SplatPipeline:
        """:func:`load_model` (random models initialised on ``device``), then the constructor; raises as both."""
        model, source = load_model(checkpoint, config, dtype=dtype, init_device=device)
        pipe = cls(model, device, dtype=dtype, offload=offload, attention=attention, compile=compile)
        pipe.source = source
        return pipe

    @classmethod
    def from_onnx(cls, directory: str | Path, providers: list[str] | None = None) -> Diff4SplatPipeline:
        """Pipeline over an ``export-onnx`` folder (:class:`diff4splat.onnx_runtime.OnnxRuntime`)."""
        from diff4splat.onnx_runtime import OnnxRuntime  # optional dependency, kept out of every command's start

        runtime = OnnxRuntime(directory, providers=providers)
        pipe = cls(runtime)
        pipe.source = f"onnx:{directory} ({runtime.manifest['source']})"
        return pipe

    def output_size(self, resolution: int | None = None) -> tuple[int, int]:
        """(width, height) of the output at ``resolution`` pixels of height (None: the model's) and its aspect ratio.
        ValueError: not a positive int, below the model's height, no whole width at that height, or above the
        ``resolution`` limit (:class:`diff4splat.utils.limits.LimitError`)."""
        c = self.config
        if resolution is None:
            return c.width, c.height
        resolution = check_limit("resolution", check_positive_int("resolution", resolution), "resolution")
        if resolution < c.height:
            raise ValueError(f"resolution {resolution} is below the model's {c.height} pixels of height: the output "
                             f"is at least the model resolution (--resolution {c.height} or more)")
        if (resolution * c.width) % c.height:
            raise ValueError(f"resolution {resolution}: the model's {c.width}×{c.height} aspect ratio gives no whole "
                             f"width at that height")
        return resolution * c.width // c.height, resolution

    def default_cameras(self, trajectory: str = DEFAULT_TRAJECTORY, num_frames: int | None = None,
                        amplitude: float | None = None, resolution: int | None = None) -> CameraPath:
        """A preset trajectory at the model's ``fov_y_deg`` and ``resolution`` (:meth:`output_size`); ``amplitude`` in
        radians for ``arc``, in units of ``config.scene_depth`` otherwise. ValueError: unknown preset, a bad frame
        count or resolution, or one above its limit."""
        c = self.config
        if num_frames is not None:
            check_limit("frames", num_frames, "frames")
        width, height = self.output_size(resolution)
        K = intrinsics_from_fov(width, height, fov_y_deg=c.fov_y_deg)
        return make_trajectory(trajectory, num_frames or c.num_frames, K, width, height,
                               scene_depth=c.scene_depth, amplitude=amplitude)

    @torch.no_grad()
    def __call__(self, image: Tensor, cameras: CameraPath, prompt: str = "", *, steps: int | None = None,
                 sampler: str | None = None, guidance: float | None = None, seed: int = 0, progress: bool = False,
                 video_latents: Tensor | None = None, depth: Tensor | None = None,
                 depth_kind: str = "metric", drags: Drags | None = None) -> GenerationResult:
        """Generate a 4D scene; returns a :class:`GenerationResult`.

        Args:
            image: (H, W, 3) float in [0, 1] at the output resolution and the model's aspect ratio.
            cameras: T = 1 + 4k cameras at W × H; re-expressed relative to the first.
            prompt: text describing the motion; "" runs no text encoder and, without ``drags``, gives a static scene.
                With a motion generator in the model, it generates the photo layer's motion
                (:mod:`diff4splat.assembly.generated_motion`, moved as drags move it) instead of the deformation
                network's.
            steps, sampler, guidance: sampler steps, "euler" | "heun" and the classifier-free guidance scale g ≥ 0,
                v_u + g·(v_p − v_u) (Ho & Salimans 2022; 1: one call per step); defaults: ``config.sampling``.
            seed, progress: seed of the initial noise (drawn on the CPU); tqdm progress bars.
            video_latents: (1, c, n, h, w) DiT-scaled latent used instead of sampling (ablations); frame 0 replaced.
            depth: (H, W) depth of the photograph for the photo layer (NaN/inf/≤ 0: holes the network fills);
                ``depth_kind``: "metric" (metres), "relative" or "inverse" (aligned to the network's depth).
            drags: motion of the photograph's points at its W × H (:class:`~diff4splat.geometry.drags.Drags`):
                their regions of the photo layer move with them (:mod:`diff4splat.assembly.drag_scene`) and the
                rest of the scene stays still; None: the networks' motion.

        Raises:
            ValueError: a bad image, cameras, T, sampler, steps, seed, prompt (not UTF-8, or no text encoder), depth map
                or ``depth_kind``, drags not a :class:`Drags` at W × H, limits exceeded
                (:class:`diff4splat.utils.limits.LimitError`), all before any network runs; ``video_latents`` of the
                wrong shape; a camera path that sees none of the scene.
        """
        steps, sampler, guidance, seed, prompt = self.check_inputs(image, cameras, prompt, steps, sampler, guidance,
                                                                   seed, depth, depth_kind, drags)
        cfg, runtime, dev = self.config, self.runtime, self.device
        H_o, W_o = int(image.shape[0]), int(image.shape[1])
        n = runtime.latent.num_latent_frames(len(cameras))
        cameras = cameras.relative_to_first().to(dtype=torch.float32, device=dev)
        cameras_model = cameras.resized(cfg.width, cfg.height)
        image = image.to(dev, torch.float32)
        timings: dict[str, float] = {}

        clock = Stopwatch(dev)
        small = image.permute(2, 0, 1)[None]
        if (H_o, W_o) != (cfg.height, cfg.width):
            small = F.interpolate(small, size=(cfg.height, cfg.width), mode="area")
        video = (small * 2 - 1)[:, :, None]  # (1, 3, 1, h·8, w·8) in [−1, 1]
        image_latent = runtime.encode_image(video)  # (1, c, 1, h, w)
        timings["encode_image"] = clock.lap()
        conditions, guidance = self._encode_prompt(prompt, guidance)
        timings["encode_text"] = clock.lap()

        plucker = self.packed_plucker(cameras_model)
        latents = self._sample(image_latent, plucker, conditions, guidance, n, steps, sampler, seed, video_latents,
                               progress)
        timings["sample"] = clock.lap()

        key_times = torch.unique(cameras.times)
        # Motion only where asked for: with a prompt the motion generator's (where the model has one), else the
        # networks' deformation; the drags' instead of either; no prompt and no drag is a static scene. A runtime
        # without the deformation network or the motion generator (a static ONNX export) is static too.
        prompted = bool(prompt.strip()) and drags is None
        generates_motion = prompted and runtime.has_motion_generator
        networks_move = prompted and runtime.has_deformation and not generates_motion
        out = runtime.reconstruct(latents, plucker, key_times if networks_move else None, video[:, :, 0])
        frames = self.source_frames(len(cameras))
        sources = torch.tensor(frames, device=dev)
        motion = runtime.has_motion and out.d_means is not None
        colors_from_video = cfg.generated_colors == "video" and len(frames) > 1  # the later frames' colours (assemble)
        decoded = runtime.decode_latents(latents) if colors_from_video or motion else None
        if motion:  # the motion network reads the decoded frames
            with runtime.motion_network() as net:
                out = frame_motion(net, out, ((decoded.transpose(1, 2) + 1) / 2).clamp(0, 1), cameras_model.times[None],
                                   cameras_model.viewmats[None], cameras_model.Ks[None], sources, key_times[None])
        if not colors_from_video:
            decoded = None
        runtime.release()  # frees an offloaded network before pruning renders
        times = key_times if out.d_means is not None else None
        scene, grid, photo = assemble_scene(out, sources, cameras_model, cameras, image, times, depth=depth,
                                            depth_kind=depth_kind, video=decoded, footprint=cfg.generated_footprint)
        scene = scene.without_deformation(cfg.static_atol)
        if drags is not None:
            scene, kept = dragged_scene(scene, grid, drags, image, photo["photo_depth"], cameras.Ks[0], key_times)
            grid = grid[kept]
        elif generates_motion:
            span = float(key_times[-1] - key_times[0]) or 1.0
            with runtime.motion_generator() as net:
                motion, moving = generated_motion(net, image, photo["photo_depth"], (key_times - key_times[0]) / span,
                                                  prompt, seed=seed)
            if bool(moving.any()):  # else nothing moves: the scene stays static
                scene, kept = moved_scene(scene, grid, motion, moving, photo["photo_depth"], cameras.Ks[0], key_times)
                grid = grid[kept]
        timings["reconstruct"] = clock.lap()

        scene, index, stats = settle_and_prune(scene, grid, cameras, sources, photo["photo_depth"],
                                               photo["photo_gaussians"], cfg.prune_opacity)
        timings["prune"] = clock.lap()
        return GenerationResult(scene=scene, cameras=cameras, latents=latents, timings=timings,
                                high_water=dict(zip(timings, clock.high_water, strict=False)), prune_stats=stats,
                                steps=steps, sampler=sampler, guidance=guidance, shift=cfg.sampling.shift,
                                source_frames=sources, gaussian_index=index, eps2d=PHOTO_EPS2D,
                                background=photo["background"],
                                photo_psnr_db=photo["photo_psnr_db"], num_slots=int(grid.shape[0]),
                                photo_gaussians=photo["photo_gaussians"], video=decoded)

    @torch.no_grad()
    def reconstruct(self, frames: Tensor, cameras: CameraPath, *, layers: str = DEFAULT_LAYERS,
                    order_offset: float = LAYER_ORDER_OFFSET, unchecked: int | None = None) -> ReconstructionResult:
        """The 4D scene of a video clip (``diff4splat reconstruct``; :mod:`diff4splat.assembly.layers`): the VAE
        encodes the clip and the LDRM gives its source frames' depth (nothing is sampled), then
        :func:`~diff4splat.assembly.layers.layered_scene` makes the frames photo layers moved by the motion measured
        from them.

        Args:
            frames: (T, H, W, 3) float in [0, 1] at the output resolution and the model's aspect ratio, T = 1 + 4k.
            cameras: T cameras at W × H; re-expressed relative to the first.
            layers, order_offset, unchecked: as :func:`~diff4splat.assembly.layers.layered_scene`
                (:data:`~diff4splat.assembly.layers.LAYERS`).

        Raises:
            ValueError: bad frames, T < 2 or T ≠ 1 + 4k, cameras not T at (W, H), an unknown ``layers``, an
                ``order_offset`` that is not a finite number ≥ 0, an ``unchecked`` that is not None or an int ≥ 0
                (all before any network runs); a path that sees nothing.
        """
        self.check_clip(frames, cameras, layers, order_offset, unchecked)
        cfg, runtime, dev = self.config, self.runtime, self.device
        T = frames.shape[0]
        cameras = cameras.relative_to_first().to(dtype=torch.float32, device=dev)
        cameras_model = cameras.resized(cfg.width, cfg.height)
        clock, timings = Stopwatch(dev), {}
        images = frames.to(dev, torch.float32)  # (T, H, W, 3)
        small = F.interpolate(images.permute(0, 3, 1, 2), size=(cfg.height, cfg.width), mode="area")
        video = (small * 2 - 1).transpose(0, 1)[None]  # (1, 3, T, h, w) in [−1, 1]
        latents = runtime.encode_image(video)  # the clip's own latents (posterior mean)
        timings["encode_video"] = clock.lap()
        out = runtime.reconstruct(latents, self.packed_plucker(cameras_model), None, video[:, :, 0])
        runtime.release()
        sources = self.source_frames(T)
        frames_of = layer_frames(sources, T, layers)
        index = torch.tensor(sources, device=dev)
        z_model = z_depth(out.distance[0], cameras_model.viewmats[index], cameras_model.Ks[index])  # (S, h, w)
        z_src = torch.stack([upsample_depth(z_model[s], images[f]) for s, f in enumerate(sources)])  # (S, H, W)
        timings["reconstruct"] = clock.lap()
        scene, kept, stats, photo_psnr, slots, n0 = layered_scene(
            images, z_src, sources, frames_of, cameras, static_atol=cfg.static_atol, prune_opacity=cfg.prune_opacity,
            order_offset=order_offset, unchecked=unchecked, clock=clock, timings=timings)
        return ReconstructionResult(scene=scene, cameras=cameras, latents=latents, layers=layers, timings=timings,
                                    high_water=dict(zip(timings, clock.high_water, strict=False)), prune_stats=stats,
                                    source_frames=torch.tensor(frames_of, device=dev), gaussian_index=kept,
                                    eps2d=PHOTO_EPS2D,
                                    background=tuple(float(c) for c in images[0].reshape(-1, 3).mean(0)),
                                    photo_psnr_db=photo_psnr, num_slots=slots, photo_gaussians=n0)

    def source_frames(self, num_frames: int) -> list[int]:
        """The video frame of each of the LDRM's source frames for a ``num_frames`` path
        (:func:`models.ldrm.source_frame_indices`). ValueError: ``num_frames`` not 1 + 4k."""
        latent = self.runtime.latent
        return source_frame_indices(self.config.ldrm.gaussian_frames, latent.num_latent_frames(num_frames),
                                    latent.temporal_factor)

    def check_frame_count(self, frames: int) -> None:
        """ValueError naming ``--frames`` unless ``frames`` is a length the VAE takes (T = 1 + 4k)."""
        try:
            self.runtime.latent.num_latent_frames(frames)
        except ValueError:
            raise ValueError(f"--frames {frames}: the frame count must be {self.runtime.latent.frames_rule}") from None

    @staticmethod
    def check_settings(prompt: object = "", steps: object = None, sampler: object = None, guidance: object = None,
                       seed: object = 0, *, flags: bool = False) -> None:
        """The checks of the sampling settings that need no model (:meth:`__call__`'s ``prompt``, ``steps``,
        ``sampler``, ``guidance``, ``seed``; None: the config's default), run by :meth:`check_inputs` and, before a
        model loads, by the request layer (``flags``: messages name the command's ``--flags``). ValueError: a prompt
        that is not UTF-8, steps not a positive int or above the limit, an unknown sampler, a guidance outside
        [0, 30], a seed outside :data:`SEED_RANGE`."""
        name = (lambda n: f"--{n}") if flags else (lambda n: n)  # noqa: E731
        if steps is not None:
            check_limit("steps", check_positive_int(name("steps"), steps), name("steps"))
        if sampler is not None:
            check_sampler(sampler, name("sampler"))
        if guidance is not None:
            check_guidance(guidance, name("guidance"))
        check_seed(seed, name("seed"))
        check_prompt(prompt, name("prompt"))

    def check_inputs(self, image: Tensor, cameras: CameraPath, prompt: str = "", steps: int | None = None,
                     sampler: str | None = None, guidance: float | None = None, seed: int = 0,
                     depth: Tensor | None = None, depth_kind: str = "metric",
                     drags: Drags | None = None) -> tuple[int, str, float, int, str]:
        """:meth:`__call__`'s checks, all before any network runs; returns (steps, sampler, guidance, seed, prompt)
        with the config's defaults. ValueError: as :meth:`__call__`."""
        cfg, runtime = self.config, self.runtime
        if not isinstance(image, Tensor):
            raise ValueError(f"image must be a torch.Tensor (H, W, 3) in [0, 1], got {type(image).__name__} "
                             "(torch.from_numpy converts an array; diff4splat.io.load_image reads a file)")
        if image.dim() != 3 or image.shape[-1] != 3 or image.shape[0] * cfg.width != image.shape[1] * cfg.height:
            raise ValueError(f"image must have shape (H, W, 3) with the model's aspect ratio {cfg.width}:{cfg.height} "
                             f"(e.g. ({cfg.height}, {cfg.width}, 3)), got {tuple(image.shape)}")
        H_o, W_o = int(image.shape[0]), int(image.shape[1])
        self.output_size(H_o)  # the resolution limit
        if not bool(torch.isfinite(image).all()) or float(image.min()) < 0 or float(image.max()) > 1:
            raise ValueError("image values must be finite and lie in [0, 1]")
        if (cameras.width, cameras.height) != (W_o, H_o):
            raise ValueError(f"cameras are {cameras.width}×{cameras.height}, the image is {W_o}×{H_o}")
        if depth_kind not in DEPTH_KINDS:
            raise ValueError(f"depth_kind must be one of {DEPTH_KINDS}, got {depth_kind!r}")
        if depth is not None:
            if tuple(depth.shape) != (H_o, W_o):
                raise ValueError(f"depth must have shape ({H_o}, {W_o}) like the image, got {tuple(depth.shape)}")
            check_depth_values(depth, depth_kind)
        if drags is not None and (not isinstance(drags, Drags) or (drags.width, drags.height) != (W_o, H_o)):
            size = f"at {drags.width}×{drags.height}" if isinstance(drags, Drags) else f"a {type(drags).__name__}"
            raise ValueError(f"drags must be Drags at the image's {W_o}×{H_o} (Drags.resized), got {size}")
        runtime.latent.num_latent_frames(len(cameras))  # raises for T ≠ 1 + t·k
        steps = cfg.sampling.steps if steps is None else steps
        sampler = cfg.sampling.sampler if sampler is None else sampler
        guidance = cfg.sampling.guidance if guidance is None else guidance
        self.check_settings(prompt, steps, sampler, guidance, seed)
        check_limit("frames", len(cameras), "cameras: a path of")
        check_field_of_view(cameras)
        return int(steps), sampler, float(guidance), int(seed), prompt

    def check_clip(self, frames: Tensor, cameras: CameraPath, layers: str = DEFAULT_LAYERS,
                   order_offset: float = LAYER_ORDER_OFFSET, unchecked: int | None = None) -> None:
        """:meth:`reconstruct`'s checks, all before any network runs. ValueError: as :meth:`reconstruct`."""
        cfg = self.config
        tensor = isinstance(frames, Tensor)
        if not tensor or frames.dim() != 4 or frames.shape[-1] != 3 or not frames.is_floating_point():
            shape = tuple(frames.shape) if tensor else type(frames).__name__
            raise ValueError(f"frames must be a float tensor (T, H, W, 3), got {shape} "
                             f"{getattr(frames, 'dtype', '')}".rstrip())
        T, H, W = frames.shape[:3]
        if not bool(((frames >= 0) & (frames <= 1)).all()):
            raise ValueError("frames must lie in [0, 1]")
        if H * cfg.width != W * cfg.height:
            raise ValueError(f"frames are {W}×{H}; the model's aspect ratio is {cfg.width}:{cfg.height}")
        if len(cameras) != T or (cameras.width, cameras.height) != (W, H):
            raise ValueError(f"cameras: {len(cameras)} at {cameras.width}×{cameras.height}, the frames: {T} at {W}×{H}")
        if T < 2:
            raise ValueError(f"frames: a clip needs at least 2 frames (a frame count the VAE takes: 5, 9, …), got {T}")
        self.check_frame_count(T)
        check_layers(layers)
        check_layer_knobs(order_offset, unchecked)

    def _encode_prompt(self, prompt: str, guidance: float) -> tuple[tuple, float]:
        """((text, text_mask), (uncond, uncond_mask)), None where unused, and the guidance (1 for an empty prompt)."""
        runtime, dev = self.runtime, self.device
        text = text_mask = uncond = uncond_mask = None
        if prompt.strip() or runtime.encodes_empty_prompt:
            text, text_mask = _without_full_mask(*runtime.encode_text(prompt), dev)
        if not prompt.strip():
            guidance = 1.0  # the prompt is the unconditional input: nothing to guide towards
        elif guidance != 1.0 and runtime.encodes_empty_prompt:
            uncond, uncond_mask = _without_full_mask(*runtime.encode_text(""), dev)
        return ((text, text_mask), (uncond, uncond_mask)), guidance

    def _sample(self, image_latent: Tensor, plucker: Tensor, conditions: tuple, guidance: float, n: int,
                steps: int, sampler: str, seed: int, video_latents: Tensor | None, progress: bool) -> Tensor:
        """Video latents (1, c, n, h, w) from seeded noise (or ``video_latents``), frame 0 = ``image_latent``."""
        runtime, dev = self.runtime, self.device
        (text, text_mask), (uncond, uncond_mask) = conditions
        gen = torch.Generator(device="cpu").manual_seed(seed)  # CPU draws: the same noise on every device
        noise = torch.randn((1, runtime.latent.latent_channels, n, *image_latent.shape[-2:]),  # CPU draw, moved
                            generator=gen, device="cpu").to(dev)
        if video_latents is None:  # the flow-matching ODE from σ = 1 to 0: one velocity a σ of ode.sigmas
            latents, ode = noise, ODESteps(sampler, runtime.sigmas(steps), noise)
            condition = dict(image_latent=image_latent, plucker=plucker, text=text, text_mask=text_mask,
                             guidance=guidance, uncond=uncond, uncond_mask=uncond_mask)
            for sigma in tqdm(ode.sigmas, disable=not progress, desc=sampler):
                latents = ode.step(runtime.velocity(latents, sigma, **condition), latents)
        elif tuple(video_latents.shape) != tuple(noise.shape):
            raise ValueError(f"video_latents must have shape {tuple(noise.shape)}, got {tuple(video_latents.shape)}")
        else:
            latents = video_latents.to(noise)
        return torch.cat([image_latent, latents[:, :, 1:]], dim=2)

    def packed_plucker(self, cameras_model: CameraPath) -> Tensor:
        """Plücker rays of a model-resolution path packed to the latent grid, (1, 6·t·s², n, h, w), ``input_dtype``."""
        cams, latent = cameras_model, self.runtime.latent
        rays = plucker_rays(cams.viewmats, cams.Ks, cams.width, cams.height)[None]
        return pack_plucker(rays, latent.temporal_factor, latent.spatial_factor).to(self.runtime.input_dtype)
