"""Image + camera path + optional prompt → 4D Gaussian scene (Diff4Splat, Pan et al. 2025, Fig. 2).

Data flow (docs/DESIGN.md, "Data flow of generate"):

The photograph and the camera path come at the *output* resolution; the networks run at the model resolution
(the photograph area-resized, the intrinsics scaled).

1. VAE encoder: the photograph as a one-frame video → first-frame latent (1, c, 1, h, w).
2. Text encoder: prompt → tokens (1, L, d_text); skipped entirely for an empty prompt (a pretrained backbone
   encodes "", its unconditional input).
3. Plücker rays (T, H, W, 6) of the path → packed to the latent grid (1, 6·t·s², n, h, w).
4. Video transformer + flow-matching sampler (Euler/Heun over the backbone's σ schedule, NFE steps): noise →
   video latent (1, c, n, h, w);
   the sampled first latent frame is replaced by the photograph's own latent, which is known exactly.
5. LDRM(video latent, Plücker rays, frame times) → pixel-aligned maps of the source frames + deformation maps at
   every distinct frame time.
6. :func:`diff4splat.assembly.assemble.assemble_scene`: the photograph itself as the reference frame's Gaussians at the
   output resolution (the photo layer, on the LDRM's depth or the user's), the LDRM's Gaussians for the other
   source frames → :class:`DynamicGaussians` (static when the deformation is the identity), pruned of Gaussians
   that repeat a surface, hide the photograph at the input view or never contribute.

The networks are reached through a :class:`NetworkRuntime` (encode_image, encode_text, velocity,
reconstruct): :class:`TorchRuntime` runs the PyTorch modules (our networks or a pretrained diffusers backbone,
through :class:`models.backbone.Backbone`), ``diff4splat.onnx_runtime.OnnxRuntime``
runs an ONNX export with onnxruntime. Everything else (validation, Plücker rays, noise, sampler, the scene's
assembly, pruning) is this module's single implementation for both. (A *runtime* runs the networks; the
renderer's *backend*, gsplat or PyTorch, is another choice, made in :mod:`diff4splat.render`.)
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.assembly.assemble import DEPTH_KINDS, assemble_scene
from diff4splat.assembly.photo import PHOTO_EPS2D, layer_sizes
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
from diff4splat.io.depth_maps import check_depth_values
from diff4splat.render.settings import BACKGROUND
from diff4splat.runtime import NetworkRuntime, TorchRuntime
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.utils.checks import check_positive_int, is_int
from diff4splat.utils.costs import (
    MEMORY_BASE_BYTES,
    MEMORY_BYTES_PER_GAUSSIAN,
    MEMORY_CUDA_BUILD_BYTES,
    MEMORY_MAP_COPIES,
    MEMORY_SCENE_COPIES,
    TIME_FIXED_SECONDS,
    TIME_SECONDS_PER_PIXEL_FRAME,
)
from diff4splat.utils.devices import Stopwatch
from diff4splat.utils.limits import check_limit
from models.backbone_model import INDEX_FILE, BackboneModel
from models.bundle import DEFAULT_CONFIG, WEIGHTS_DIR, Diff4SplatModel, load_config, random_init_device
from models.flow_matching import check_guidance, integrator
from models.ldrm import source_frame_indices
from models.pretrained import CONFIG_NAME

__all__ = ["Diff4SplatPipeline", "GenerationResult", "load_model", "check_seed", "check_prompt", "SEED_RANGE",
           "DEFAULT_RESOLUTION"]

DEFAULT_RESOLUTION = 256
"""Output height, pixels, of ``generate`` when ``--resolution`` is not given (or the model's height if larger): the
photo layer keeps the photograph at this resolution whatever the model's (base: 64²)."""

SEED_RANGE = (-(2**63), 2**64 - 1)
"""Seeds ``torch.Generator.manual_seed`` accepts (int64 or uint64)."""


def check_seed(seed: object, name: str = "seed") -> int:
    """Return ``seed`` as an int if it lies in :data:`SEED_RANGE` (an int or numpy integer, not a bool, as every
    count this library takes).

    Raises:
        ValueError: ``seed`` is not an integer or lies outside the range (the message gives the range).
    """
    lo, hi = SEED_RANGE
    if not is_int(seed) or not lo <= int(seed) <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}] (-2**63 … 2**64 − 1), got {seed!r}")
    return int(seed)


def check_prompt(prompt: object, name: str = "prompt") -> str:
    """Return ``prompt`` if it is a str that encodes as UTF-8.

    Command-line arguments that are not UTF-8 reach Python as lone surrogates (``\\udcff`` for byte
    0xff); they cannot be tokenised.

    Raises:
        ValueError: not a str, or not valid UTF-8 (names the first bad byte and its position).
    """
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


@dataclass
class GenerationResult:
    """What :meth:`Diff4SplatPipeline.__call__` returns.

    Attributes:
        scene: the 4D scene (world frame = first camera's frame, metres); its first ``photo_gaussians`` are the
            photo layer (:mod:`diff4splat.assembly.photo`) where not pruned.
        cameras: the camera path used, re-expressed relative to its first camera, at the output resolution.
        latents: (1, c, n, h, w) the sampled video latent fed to the LDRM.
        steps: sampler steps actually run (the argument, or ``config.sampling.steps``).
        sampler: "euler" or "heun", the sampler actually used (the argument, or ``config.sampling.sampler``).
        shift: the flow-matching timestep shift used (``config.sampling.shift``).
        guidance: the classifier-free guidance scale applied (the argument, or ``config.sampling.guidance``; 1 when
            there is no prompt: nothing to guide towards).
        timings: seconds per stage ("encode_image", "encode_text", "sample", "reconstruct", "prune");
            "reconstruct" includes the VAE decode of ``generated_colors: video`` and the scene's assembly.
        high_water: on CUDA, the device's peak allocated memory (bytes, ``torch.cuda.max_memory_allocated``) at
            the end of each stage of ``timings``: a running maximum since the caller's last
            ``torch.cuda.reset_peak_memory_stats``, so the first stage that reaches the last value set the peak
            (:class:`diff4splat.utils.devices.Stopwatch`). Empty on other devices.
        prune_stats: counts from :func:`diff4splat.assembly.prune.prune_mask`, plus "duplicates" (Gaussians of a
            later source frame dropped as near-duplicates, :func:`diff4splat.assembly.prune.duplicate_mask`), "slid"
            (later-frame Gaussians that covered the photograph at the input view, moved back along their source
            rays, :func:`diff4splat.assembly.prune.slide_behind`) and "occluders" (those dropped because no slide freed
            them; :func:`diff4splat.assembly.prune.settle_generated`).
        source_frames: (S,) long, the video frame of each source frame whose rays carry a grid of
            Gaussians (``models.ldrm.source_frame_indices``).
        gaussian_index: (M,) long, index of each kept Gaussian in the unpruned scene, increasing: the photo
            layer's H_o·W_o front disks then ⌈H_o/2⌉·⌈W_o/2⌉ backing disks (row-major; output resolution), then
            source frames 1…S−1 with h·w each (model resolution, row-major;
            :func:`diff4splat.assembly.assemble.assemble_scene`).
        eps2d: the screen-space dilation, pixels², the scene is rendered with (meta.json ``eps2d``).
        background: RGB in [0, 1] behind the scene: the photograph's mean colour (meta.json ``background``).
        photo_psnr_db: PSNR of the photo layer alone rendered at the input camera against the photograph.
        photo_gaussians: H_o·W_o + ⌈H_o/2⌉·⌈W_o/2⌉, the photo layer's share of the unpruned scene (the backdrop
            follows it, :func:`diff4splat.assembly.assemble.assemble_scene`).
        num_slots: the unpruned scene's size, the range of ``gaussian_index``.
        video: (1, 3, T, h, w) ``latents`` decoded by the VAE, pixels in about [−1, 1] at the model resolution,
            when the pipeline decoded them for the generated frames' colours (``generated_colors: video``), else
            None (decode them with ``runtime.decode_latents``).
    """

    scene: DynamicGaussians
    cameras: CameraPath
    latents: Tensor
    steps: int
    sampler: str
    guidance: float
    shift: float
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
    video: Tensor | None = None


def load_model(checkpoint: str | Path | None = None, config: str = DEFAULT_CONFIG, seed: int = 0, *,
               untrained: bool = False, dtype: torch.dtype | None = None, init_device: str | torch.device = "cpu"
               ) -> tuple[Diff4SplatModel | BackboneModel, str]:
    """Load a checkpoint folder, else the shipped weights of ``config``, else a seeded random model.

    A checkpoint folder is ours (``config.json``: :meth:`Diff4SplatModel.from_pretrained`) or a pretrained diffusers
    backbone's (``model_index.json``: :meth:`models.backbone_model.BackboneModel.from_pretrained`, loaded directly
    in ``dtype``, e.g. bfloat16, never as a float32 copy first; so are our checkpoints and a random model).
    ``untrained=True`` skips checkpoint and shipped weights and returns the seeded random model without a warning
    (the baseline that evaluations compare against). A random model without ``untrained`` is initialised on
    ``init_device`` when :func:`models.bundle.random_init_device` finds room there (a GPU: seconds, where the CPU
    takes minutes for the paper size), then returned on the CPU like every other; its values are that device's
    generator's, and its source says so (``random:<config>:seed=<n>:cuda``).

    Returns:
        (model in eval mode, a description of where the weights came from).

    Raises:
        FileNotFoundError: ``checkpoint`` given but missing, or an unknown config name.
        ValueError: a folder that is neither format (one line naming both marker files).
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
    # built in ``dtype``: the paper-size model in bfloat16 is 33.7 GB, where a float32 build first held 67.3 GB
    model = Diff4SplatModel.random(cfg, seed=seed, device=where, dtype=dtype, host=True).eval()
    return model, random_source + ("" if where.type == "cpu" else f":{where.type}")


def _without_full_mask(text: Tensor, mask: Tensor, device: torch.device) -> tuple[Tensor, Tensor | None]:
    """Text tokens (1, L, d) and their mask (1, L) bool on ``device``; a mask that marks every token real is
    None, which means the same to every runtime (``VideoDiT.forward``: None = all tokens real): the DiT's
    cross-attention then runs unmasked (FlashAttention on CUDA; a mask sends it to another kernel) and skips its
    guard for samples without real tokens. One prompt, right-padded to its own length, has no padding."""
    text, mask = text.to(device), mask.to(device)
    return text, None if bool(mask.all()) else mask


class Diff4SplatPipeline:
    """Single image (+ camera path, + prompt) to a 4D Gaussian scene.

    Args:
        model: the four networks (:class:`models.bundle.Diff4SplatModel`, run by a
            :class:`TorchRuntime`), or any :class:`NetworkRuntime` (e.g. ``diff4splat.onnx_runtime.OnnxRuntime``).
        device: torch device of the PyTorch networks and the pipeline's tensors (a non-torch
            runtime takes CPU tensors: use "cpu").
        dtype: weight dtype of the PyTorch networks (:class:`TorchRuntime`; e.g. ``torch.bfloat16`` on a GPU);
            None keeps the model's. Sampling, Gaussians and rendering stay float32.
        offload: ``"model"`` keeps the PyTorch networks in CPU memory and moves one at a time to ``device``
            while it runs (the peak is the largest network, not all four: how a paper-size model fits a
            25 GB budget); ``"model-prefetch"`` as ``"model"``, the DiT's copy overlapping its first call on CUDA
            (:data:`diff4splat.runtime.OFFLOAD_MODES`); ``"none"`` (default) keeps them all on ``device``.
        attention: the fused attention kernel the PyTorch networks try first
            (:data:`diff4splat.runtime.ATTENTION_KERNELS`; default ``"auto"``, torch's order).
        compile: ``torch.compile`` the transformer's blocks (:class:`TorchRuntime`; default False).

    Attributes:
        runtime: the :class:`NetworkRuntime` that runs the networks.
        model: the :class:`Diff4SplatModel` or :class:`models.backbone_model.BackboneModel`, or None for another
            runtime.
        config: the model's :class:`Diff4SplatConfig` or :class:`models.backbone_model.BackboneModelConfig`.
        source: where the weights came from (a folder, ``random:<config>:seed=<n>[:cuda]``, ``onnx:<folder> (…)``),
            set by :meth:`from_pretrained` and :meth:`from_onnx`; None for a pipeline built from a model in memory.

    Raises:
        TypeError: ``model`` is neither a Diff4SplatModel, a BackboneModel nor a NetworkRuntime.
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
        """The one way to load the PyTorch networks: :func:`load_model` (a checkpoint folder, ours or a diffusers
        backbone's; the shipped weights of ``config`` when ``checkpoint`` is None; a seeded random model with a
        warning when none ship, initialised on ``device`` when it is a GPU with room), loaded directly in
        ``dtype``, then run on ``device`` as :class:`Diff4SplatPipeline`'s arguments say. :attr:`source` says
        where the weights came from.

        Raises:
            as :func:`load_model` and the constructor.
        """
        model, source = load_model(checkpoint, config, dtype=dtype, init_device=device)
        pipe = cls(model, device, dtype=dtype, offload=offload, attention=attention, compile=compile)
        pipe.source = source
        return pipe

    @classmethod
    def from_onnx(cls, directory: str | Path, providers: list[str] | None = None) -> Diff4SplatPipeline:
        """Pipeline over an ``export-onnx`` folder served by onnxruntime
        (:class:`diff4splat.onnx_runtime.OnnxRuntime`); :attr:`source` is ``onnx:<directory> (<its source>)``."""
        from diff4splat.onnx_runtime import OnnxRuntime  # lazy: onnxruntime adds ~0.1 s to every command's start

        runtime = OnnxRuntime(directory, providers=providers)
        pipe = cls(runtime)
        pipe.source = f"onnx:{directory} ({runtime.manifest['source']})"
        return pipe

    def scene_slots(self, width: int, height: int, num_frames: int) -> int:
        """Gaussians of the unpruned scene for a ``width`` × ``height`` output and ``num_frames`` frames: the photo
        layer and backdrop (:func:`diff4splat.assembly.photo.layer_sizes`) plus h·w per later source frame at the model
        resolution (``GenerationResult.num_slots``; an upper bound of the kept count).

        Raises:
            ValueError: ``num_frames`` not 1 + 4k (the VAE's grouping).
        """
        c = self.config
        latent = self.runtime.latent
        n = latent.num_latent_frames(num_frames)
        sources = source_frame_indices(c.ldrm.gaussian_frames, n, latent.temporal_factor)
        return sum(layer_sizes(width, height)) + (len(sources) - 1) * c.height * c.width

    def memory_estimate(self, width: int, height: int, num_frames: int) -> int:
        """Upper bound of ``generate``'s peak host memory, bytes, for a ``width`` × ``height`` output of
        ``num_frames`` frames, from the config alone (nothing is allocated; checked against the ``memory_bytes``
        limit before the networks run, :func:`diff4splat.utils.limits.check_memory`).

        Sum of: the process (more with a CUDA build of torch, :data:`MEMORY_CUDA_BUILD_BYTES`) and the weights it
        holds in host memory (:meth:`diff4splat.runtime.TorchRuntime.host_weight_bytes`: all of them on the CPU, the
        pinned copies with model offload, none on a GPU without it); the deformation of the unpruned scene,
        (:meth:`scene_slots` × K key times × 10 floats) × :data:`MEMORY_SCENE_COPIES` (the scene and its pruned
        copy); on the CPU the LDRM's deformation maps, n latent frames × K
        × the model grid × 10 floats × :data:`MEMORY_MAP_COPIES` (on a GPU they stay in its memory);
        :data:`MEMORY_BYTES_PER_GAUSSIAN` per slot (attributes, renderer tile lists); the rendered frames, T × H × W
        × 5 floats, twice (floats and encoded). The deformation terms vanish for a runtime without the deformation
        network. Measured against the peak resident memory of ``generate`` on the CPU in docs/benchmarks.md
        ("Memory of generate": 1.1-1.5× the measured peak at 17-149 frames, 64²-512²). GPU memory is not
        estimated: a request too large for it fails with torch's out-of-memory error, one line naming the knobs.

        Raises:
            ValueError: ``num_frames`` not 1 + 4k.
        """
        c = self.config
        n = self.runtime.latent.num_latent_frames(num_frames)
        slots = self.scene_slots(width, height, num_frames)
        keys = num_frames if self.runtime.has_deformation else 0
        weights = self.runtime.host_weight_bytes() if isinstance(self.runtime, TorchRuntime) else 0
        maps = MEMORY_MAP_COPIES * n * c.height * c.width if self.device.type == "cpu" else 0
        base = MEMORY_BASE_BYTES + (MEMORY_CUDA_BUILD_BYTES if torch.backends.cuda.is_built() else 0)
        return int(base + weights + MEMORY_BYTES_PER_GAUSSIAN * slots + 40 * keys * (MEMORY_SCENE_COPIES * slots + maps)
                   + 2 * 20 * num_frames * width * height)

    def time_estimate(self, width: int, height: int, num_frames: int) -> float:
        """Rough wall time of ``generate`` on the CPU for a ``width`` × ``height`` output of ``num_frames`` frames,
        seconds: :data:`TIME_FIXED_SECONDS` + :data:`TIME_SECONDS_PER_PIXEL_FRAME` · pixels · frames, measured with the
        base model on a 2-core CPU and scaled by 2 / the cores torch uses here. A larger model's sampling is not in
        it (its networks run at their own resolution); on a GPU it is an upper bound."""
        scale = 2 / max(1, torch.get_num_threads())
        return scale * (TIME_FIXED_SECONDS + TIME_SECONDS_PER_PIXEL_FRAME * width * height * num_frames)

    def output_size(self, resolution: int | None = None) -> tuple[int, int]:
        """(width, height) of the output for ``resolution`` pixels of height (None: the model resolution): the
        model's aspect ratio at that height.

        Raises:
            ValueError: ``resolution`` not a positive int, below the model's height (the output is the network's
                depth and motion upsampled to the photo, never downsampled), or one at which the model's aspect
                ratio gives no whole width; above the ``resolution`` limit
                (:class:`diff4splat.utils.limits.LimitError`).
        """
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
        """A preset trajectory at the model's field of view (``fov_y_deg``) and ``resolution`` pixels of height
        (:meth:`output_size`; None: the model resolution); ``amplitude`` is in radians for ``arc`` and in units of
        ``config.scene_depth`` for the other presets.

        Raises:
            ValueError: unknown preset or an invalid frame count or resolution; ``num_frames`` above the ``frames``
                limit (:class:`diff4splat.utils.limits.LimitError`).
        """
        c = self.config
        if num_frames is not None:
            check_limit("frames", num_frames, "frames")
        width, height = self.output_size(resolution)
        K = intrinsics_from_fov(width, height, fov_y_deg=c.fov_y_deg)
        return make_trajectory(trajectory, num_frames or c.num_frames, K, width, height,
                               scene_depth=c.scene_depth, amplitude=amplitude)

    @torch.no_grad()
    def __call__(
        self,
        image: Tensor,  # (H, W, 3) in [0, 1] at the output resolution
        cameras: CameraPath,
        prompt: str = "",
        *,
        steps: int | None = None,
        sampler: str | None = None,
        guidance: float | None = None,
        seed: int = 0,
        progress: bool = False,
        video_latents: Tensor | None = None,
        depth: Tensor | None = None,
        depth_kind: str = "metric",
    ) -> GenerationResult:
        """Generate a 4D scene.

        Args:
            image: (H, W, 3) float in [0, 1] at the output resolution, the model's aspect ratio (H×W = the model
                resolution, or e.g. :meth:`output_size`; see :func:`diff4splat.io.load_image`). The networks see it
                area-resized to the model resolution; the photo layer keeps every pixel.
            cameras: T = 1 + 4k cameras at the output resolution (W × H); re-expressed relative to the first.
            prompt: text describing the motion; "" runs no text encoder.
            steps: sampler steps (default: config.sampling.steps).
            sampler: "euler" or "heun" (default: config.sampling.sampler).
            guidance: classifier-free guidance scale g ≥ 0 (default: config.sampling.guidance): with a prompt, each
                step runs the transformer with the prompt and with the unconditional input (no text for ours, the
                empty prompt's embedding for a pretrained backbone) and integrates v_u + g·(v_p − v_u) (Ho &
                Salimans 2022); g = 1 is one call per step.
            seed: seed of the initial noise.
            progress: tqdm progress bars.
            video_latents: (1, c, n, h, w) DiT-scaled video latent used instead of sampling one (ablations:
                pure noise, or the encoded true video); its frame 0 is replaced by the photograph's latent.
            depth: (H, W) a depth map of the photograph for the photo layer instead of the network's (NaN/inf or
                ≤ 0 pixels are holes the network's depth fills); ``depth_kind``: "metric" (z-depth, metres, used as
                given), "relative" or "inverse" (aligned to the network's depth;
                :func:`diff4splat.assembly.assemble.photo_depth`).

        Returns:
            :class:`GenerationResult`.

        Raises:
            ValueError: wrong image shape or range (not the model's aspect ratio), cameras at another resolution
                than the image, T ≠ 1 + 4k, an unknown sampler or steps < 1; a prompt the runtime cannot encode (an
                ONNX export made without the text encoder) or that is not valid UTF-8; a seed outside
                :data:`SEED_RANGE`; steps, T or the resolution above their limits
                (:class:`diff4splat.utils.limits.LimitError`, checked before any network runs); a camera path that sees
                none of the scene (every Gaussian pruned, e.g. focal lengths so long that the field of view is
                empty); ``video_latents`` of another shape than the sampler's; a depth map that is not (H, W), has
                no valid pixel or cannot be aligned; an unknown ``depth_kind``.
        """
        steps, sampler, guidance, seed, prompt = self._check_call(image, cameras, prompt, steps, sampler, guidance,
                                                                  seed, depth, depth_kind)
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
        # A runtime without the deformation network (a static ONNX export) makes static scenes.
        out = runtime.reconstruct(latents, plucker, key_times if runtime.has_deformation else None, video[:, :, 0])
        frames = source_frame_indices(cfg.ldrm.gaussian_frames, n, runtime.latent.temporal_factor)
        sources = torch.tensor(frames, device=dev)
        motion = runtime.has_motion and out.d_means is not None
        colors_from_video = cfg.generated_colors == "video" and len(frames) > 1  # the later frames' colours (assemble)
        decoded = runtime.decode_latents(latents) if colors_from_video or motion else None
        if motion:  # the motion network reads the decoded frames (diff4splat.assembly.frame_motion)
            out = runtime.motion(out, ((decoded[0].transpose(0, 1) + 1) / 2).clamp(0, 1), cameras_model.times,
                                 cameras_model.viewmats, cameras_model.Ks, sources, key_times)
        if not colors_from_video:
            decoded = None
        runtime.release()  # the networks are done: an offloaded one leaves the device before pruning renders
        times = key_times if out.d_means is not None else None
        scene, grid, photo = assemble_scene(out, sources, cameras_model, cameras, image, times, depth=depth,
                                            depth_kind=depth_kind, video=decoded, footprint=cfg.generated_footprint)
        scene = scene.without_deformation(cfg.static_atol)
        timings["reconstruct"] = clock.lap()

        scene, index, stats = settle_and_prune(scene, grid, cameras, sources, photo["photo_depth"],
                                               photo["photo_gaussians"], cfg.prune_opacity)
        timings["prune"] = clock.lap()
        return GenerationResult(scene=scene, cameras=cameras, latents=latents, timings=timings,
                                high_water=dict(zip(timings, clock.high_water, strict=False)), prune_stats=stats,
                                steps=steps, sampler=sampler, guidance=guidance, shift=cfg.sampling.shift,
                                source_frames=sources,
                                gaussian_index=index, eps2d=PHOTO_EPS2D, background=photo["background"],
                                photo_psnr_db=photo["photo_psnr_db"], num_slots=int(grid.shape[0]),
                                photo_gaussians=photo["photo_gaussians"], video=decoded)

    def _check_call(self, image, cameras, prompt, steps, sampler, guidance, seed, depth, depth_kind) -> tuple:
        """Check :meth:`__call__`'s arguments before any network runs (its Raises) and resolve the config's
        defaults: returns (steps, sampler, guidance, seed, prompt)."""
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
        runtime.latent.num_latent_frames(len(cameras))  # raises for T ≠ 1 + t·k
        steps = cfg.sampling.steps if steps is None else steps
        sampler = cfg.sampling.sampler if sampler is None else sampler
        integrator(sampler)  # raises for an unknown sampler
        steps = check_limit("steps", check_positive_int("steps", steps), "steps")
        guidance = check_guidance(cfg.sampling.guidance if guidance is None else guidance)
        check_limit("frames", len(cameras), "cameras: a path of")
        check_field_of_view(cameras)
        return steps, sampler, guidance, check_seed(seed), check_prompt(prompt)

    def _encode_prompt(self, prompt: str, guidance: float) -> tuple[tuple, float]:
        """The text conditions ((text, text_mask), (uncond, uncond_mask)), each pair None where no text is used,
        and the guidance that applies: an empty prompt is the unconditional input itself (guidance 1, no text
        encoder unless the runtime encodes the empty prompt)."""
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
        """The video latents (1, c, n, h, w): integrated from seeded noise with classifier-free guidance (or
        ``video_latents``), frame 0 replaced by the photograph's latent ``image_latent`` (1, c, 1, h, w)."""
        runtime, dev = self.runtime, self.device
        (text, text_mask), (uncond, uncond_mask) = conditions
        gen = torch.Generator(device="cpu").manual_seed(seed)  # CPU draws: the same noise on every device
        noise = torch.randn((1, runtime.latent.latent_channels, n, *image_latent.shape[-2:]),  # CPU draw, moved
                            generator=gen, device="cpu").to(dev)

        # the runtime's velocity itself, its conditions bound: each step calls the network directly
        velocity = partial(runtime.velocity, image_latent=image_latent, plucker=plucker, text=text,
                           text_mask=text_mask, guidance=guidance, uncond=uncond, uncond_mask=uncond_mask)
        if video_latents is None:
            latents = integrator(sampler)(velocity, noise, runtime.sigmas(steps), progress=progress)
        elif tuple(video_latents.shape) != tuple(noise.shape):
            raise ValueError(f"video_latents must have shape {tuple(noise.shape)}, got {tuple(video_latents.shape)}")
        else:
            latents = video_latents.to(noise)
        return torch.cat([image_latent, latents[:, :, 1:]], dim=2)

    def packed_plucker(self, cameras_model: CameraPath) -> Tensor:
        """Plücker rays of a path at the model resolution packed to the latent grid, (1, 6·t·s², n, h, w), in the
        runtime's ``input_dtype`` (cast once: no float32 copy beside it)."""
        cams, latent = cameras_model, self.runtime.latent
        rays = plucker_rays(cams.viewmats, cams.Ks, cams.width, cams.height)[None]
        return pack_plucker(rays, latent.temporal_factor, latent.spatial_factor).to(self.runtime.input_dtype)
