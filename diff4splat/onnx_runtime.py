"""Serve an ONNX export (:mod:`diff4splat.export`) with onnxruntime: a pipeline
:class:`~diff4splat.pipeline.NetworkRuntime`.

``Diff4SplatPipeline(OnnxRuntime(dir))`` (or ``Diff4SplatPipeline.from_onnx(dir)``, or
``diff4splat generate --runtime onnxruntime --onnx DIR``) runs image encoding, text encoding, the
DiT velocity of every sampler step and the LDRM through onnxruntime sessions; the pipeline's own
code (validation, Plücker rays, noise, sampler, Gaussians, pruning) and the renderer are the same
as with PyTorch. No ``nn.Module`` is built and no PyTorch weights are read: torch tensors are only
the glue between sessions, and ``models`` supplies the config dataclasses and the byte tokenizer.

Sessions use ``ORT_ENABLE_ALL`` graph optimisations and as many intra-op threads as CPU cores, with
``CUDAExecutionProvider`` first when this onnxruntime build offers it, else ``CPUExecutionProvider``.

A request that needs a part the export left out raises ``ValueError``: a non-empty prompt for an
export without the text encoder (``export_onnx(text=False)``), deformation ``times`` for an export
without the deformation network (``export_onnx(deformation=False)``).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from models.bundle import Diff4SplatConfig
from models.ldrm import LDRMOutput
from models.pretrained import config_from_dict
from models.text_encoder import ByteTokenizer

from .export import LDRM_OUTPUTS, MANIFEST_FORMAT, MANIFEST_NAME, STATIC_LDRM_OUTPUTS

__all__ = ["OnnxRuntime", "load_manifest", "session_options", "default_providers"]


def load_manifest(directory: str | os.PathLike) -> dict:
    """Read and check ``manifest.json`` of an export folder.

    Args:
        directory: folder written by :func:`diff4splat.export.export_onnx`.

    Returns:
        The manifest dict (see :func:`diff4splat.export.export_onnx`).

    Raises:
        FileNotFoundError: no folder, no manifest, or a graph file the manifest lists is missing
            (messages start with ``directory:``).
        ValueError: the manifest is not JSON or not of format :data:`diff4splat.export.MANIFEST_FORMAT`.
    """
    directory = Path(directory)
    path = directory / MANIFEST_NAME
    if not directory.is_dir():
        raise FileNotFoundError(f"directory: {directory} is not a folder")
    if not path.is_file():
        raise FileNotFoundError(f"directory: {path} does not exist (not a folder written by export_onnx)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"directory: {path} is not valid JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise ValueError(f"directory: {path} has format {got!r}, expected {MANIFEST_FORMAT!r}")
    for name, entry in manifest["files"].items():
        for file in entry["files"]:
            if not (directory / file).is_file():
                raise FileNotFoundError(f"directory: {directory / file} (part {name!r}) does not exist")
    return manifest


def default_providers() -> list[str]:
    """``["CUDAExecutionProvider", "CPUExecutionProvider"]`` when CUDA is available to onnxruntime, else CPU only."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def session_options(threads: int | None = None, profile_prefix: str | None = None):
    """onnxruntime ``SessionOptions``: ORT_ENABLE_ALL, ``threads`` intra-op threads (default: CPU cores),
    no spin-waiting of idle threads.

    ``profile_prefix`` turns on onnxruntime's profiler (a Chrome-trace JSON per session, written by
    ``session.end_profiling()``).
    """
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    # Idle pool threads sleep instead of spinning: the pipeline alternates onnxruntime with PyTorch
    # (glue, renderer), and spinning threads would take the cores PyTorch runs on.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile_prefix is not None:
        opts.enable_profiling = True
        opts.profile_file_prefix = profile_prefix
    return opts


def _numpy(t: Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


class OnnxRuntime:
    """:class:`diff4splat.pipeline.NetworkRuntime` over an ``export-onnx`` folder (batch 1 per call here;
    the graphs themselves take any batch).

    Args:
        directory: folder written by :func:`diff4splat.export.export_onnx`.
        providers: onnxruntime execution providers (default :func:`default_providers`).
        threads: intra-op threads per session (default: CPU cores).
        profile_prefix: enable onnxruntime profiling (see :func:`session_options`).

    Attributes:
        manifest: the parsed manifest; config: the model config; has_text / has_deformation: the parts.
        sessions: {part name: onnxruntime.InferenceSession} for the parts present.

    Raises:
        FileNotFoundError / ValueError: see :func:`load_manifest`; ``ImportError`` without onnxruntime.
    """

    name = "onnxruntime"

    def __init__(self, directory: str | os.PathLike, providers: list[str] | None = None,
                 threads: int | None = None, profile_prefix: str | None = None):
        import onnxruntime as ort

        self.directory = Path(directory)
        self.manifest = load_manifest(self.directory)
        self.config: Diff4SplatConfig = config_from_dict(Diff4SplatConfig, self.manifest["config"],
                                                         str(self.directory / MANIFEST_NAME))
        parts = self.manifest["parts"]
        self.has_text = bool(parts["text_encoder"])
        self.dit_text_inputs = bool(parts["dit_text_inputs"])
        self.has_deformation = bool(parts["deformation"])
        self.tokenizer = ByteTokenizer(self.config.text_encoder.max_length)
        self.providers = list(providers) if providers is not None else default_providers()
        opts = session_options(threads, profile_prefix)
        self.sessions = {name: ort.InferenceSession(str(self.directory / entry["file"]), sess_options=opts,
                                                    providers=self.providers)
                         for name, entry in self.manifest["files"].items()}

    def _run(self, part: str, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self.sessions[part].run(None, feeds)

    def encode_image(self, video: Tensor) -> Tensor:
        """(B, 3, T, H, W) in [−1, 1] → (B, c, n, h, w) DiT latents (``vae_encoder.onnx``)."""
        (z,) = self._run("vae_encoder", {"video": _numpy(video, np.float32)})
        return torch.from_numpy(z)

    def decode_latents(self, latents: Tensor) -> Tensor:
        """(B, c, n, h, w) DiT latents → (B, 3, 1 + 4(n − 1), 8h, 8w) pixels (``vae_decoder.onnx``).

        Raises:
            ValueError: fewer latent frames than the decoder graph was traced for (manifest ``dims``).
        """
        n_min = self.manifest["files"]["vae_decoder"]["dims"]["latent_frames"][0]
        if latents.dim() != 5 or latents.shape[2] < n_min:
            raise ValueError(f"latents must have shape (B, c, n ≥ {n_min}, h, w) for the exported decoder, "
                             f"got {tuple(latents.shape)}")
        (video,) = self._run("vae_decoder", {"latents": _numpy(latents, np.float32)})
        return torch.from_numpy(video)

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Prompt → tokens (1, L, d_text), mask (1, L) via the byte tokenizer and ``text_encoder.onnx``.

        Raises:
            ValueError: the export has no text encoder (``export_onnx(text=False)``).
        """
        if not self.has_text:
            raise ValueError(f"prompt: the ONNX export in {self.directory} was made without the text encoder "
                             f"(text=False) and serves only the empty prompt, got prompt {prompt!r:.60}")
        ids, mask = self.tokenizer([prompt])
        (tokens,) = self._run("text_encoder", {"ids": _numpy(ids, np.int64), "mask": _numpy(mask, np.bool_)})
        return torch.from_numpy(tokens), mask

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor,
                 text: Tensor | None, text_mask: Tensor | None) -> Tensor:
        """``dit.onnx``; without text on a text-conditioned graph, one zero token with an all-False
        mask (exactly zero cross-attention, see :mod:`diff4splat.export`).

        Raises:
            ValueError: text given to a graph exported without text inputs.
        """
        feeds = {"x": _numpy(x, np.float32), "sigma": _numpy(sigma, np.float32),
                 "image_latent": _numpy(image_latent, np.float32), "plucker": _numpy(plucker, np.float32)}
        if self.dit_text_inputs:
            B = x.shape[0]
            if text is None:
                text = torch.zeros(B, 1, self.config.dit.text_dim)
                text_mask = torch.zeros(B, 1, dtype=torch.bool)
            elif text_mask is None:
                text_mask = torch.ones(text.shape[:2], dtype=torch.bool)
            feeds["text"], feeds["text_mask"] = _numpy(text, np.float32), _numpy(text_mask, np.bool_)
        elif text is not None:
            raise ValueError(f"text: the ONNX export in {self.directory} was made without the text encoder "
                             "(text=False): its DiT has no text inputs")
        (v,) = self._run("dit", feeds)
        return torch.from_numpy(v)

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None) -> LDRMOutput:
        """``ldrm.onnx`` → :class:`LDRMOutput` (deformation maps when ``times`` (K,) is given).

        Raises:
            ValueError: ``times`` given to an export without the deformation network
                (``export_onnx(deformation=False)``).
        """
        feeds = {"latents": _numpy(latents, np.float32), "plucker": _numpy(plucker, np.float32)}
        if times is not None:
            if not self.has_deformation:
                raise ValueError(f"times: the ONNX export in {self.directory} was made without the deformation "
                                 "network (deformation=False) and makes static scenes only (times must be None)")
            feeds["times"] = _numpy(times, np.float32)
        elif self.has_deformation:  # the dynamic graph needs a times input; its maps are dropped below
            feeds["times"] = np.zeros(1, np.float32)
        outputs = self._run("ldrm", feeds)
        names = LDRM_OUTPUTS if self.has_deformation else STATIC_LDRM_OUTPUTS
        maps = {name: torch.from_numpy(a) for name, a in zip(names, outputs, strict=True)}
        if times is None:  # the dynamic graph always computes them; a static request drops them
            maps = {k: maps[k] for k in STATIC_LDRM_OUTPUTS}
        return LDRMOutput(**maps)
