"""Serve an ONNX export (:mod:`diff4splat.export`) with onnxruntime: :class:`OnnxRuntime`, a pipeline
:class:`~diff4splat.runtime.NetworkRuntime` (``generate --runtime onnxruntime --onnx DIR``), and the export folder's
names and checks (manifest, graph metadata). No ``nn.Module`` is built: torch tensors are only the glue between
sessions. A request for a part the export left out (text, deformation) is a ``ValueError``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from onnxruntime.capi import onnxruntime_pybind11_state as state
from torch import Tensor

from diff4splat.io.structured import read_json
from models.bundle import Diff4SplatConfig
from models.dit import check_dit_inputs
from models.flow_matching import sigma_schedule
from models.ldrm import LDRMOutput, check_ldrm_inputs
from models.pretrained import config_from_dict
from models.text_encoder import ByteTokenizer
from models.vae import check_latents, check_video

__all__ = ["OnnxRuntime", "load_manifest", "check_graph", "session_options", "default_providers", "MANIFEST_NAME",
           "MANIFEST_FORMAT", "STATIC_LDRM_OUTPUTS", "LDRM_OUTPUTS", "GRAPH_METADATA_KEYS"]

MANIFEST_NAME = "manifest.json"
"""The export folder's manifest."""
MANIFEST_FORMAT = "diff4splat-onnx/2"
"""/2: LDRM maps with a source-frame axis S and the optional ``image`` input (/1: maps of frame 0 only)."""
STATIC_LDRM_OUTPUTS = ("distance", "scales", "quats", "opacities", "colors")
"""Outputs of ``ldrm.onnx`` exported without deformation, in order."""
LDRM_OUTPUTS = STATIC_LDRM_OUTPUTS + ("d_means", "d_quats", "d_scales")
"""Outputs of ``ldrm.onnx`` with deformation, in order."""
GRAPH_METADATA_KEYS = ("diff4splat.part", "diff4splat.config", "diff4splat.dims")
"""Metadata keys of every exported graph (:func:`diff4splat.export.graph_metadata`)."""

_PARTS = ("vae_encoder", "vae_decoder", "text_encoder", "dit", "ldrm")
_ORT_DTYPES = {"float32": "tensor(float)", "float16": "tensor(float16)", "int64": "tensor(int64)",
               "int32": "tensor(int32)", "bool": "tensor(bool)"}
"""Manifest dtype (numpy name) → onnxruntime's type string of a graph input/output."""


def load_manifest(directory: str | os.PathLike) -> dict:
    """Read and check ``manifest.json`` of a folder written by :func:`diff4splat.export.export_onnx`.
    FileNotFoundError: no folder, no manifest, or a listed graph file is missing. ValueError naming the manifest: not
    JSON, not of :data:`MANIFEST_FORMAT`, a missing or mistyped key, parts that differ from the files listed, or a file
    that is not a plain name inside ``directory``."""
    directory = Path(directory)
    path = directory / MANIFEST_NAME
    if not directory.is_dir():
        raise FileNotFoundError(f"directory: {directory} is not a folder")
    if not path.is_file():
        raise FileNotFoundError(f"directory: {path} does not exist (give a folder written by `diff4splat export-onnx`)")
    manifest = read_json(path, "directory")
    if manifest.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"directory: {path} has format {manifest.get('format')!r}, expected {MANIFEST_FORMAT!r}")
    _check_manifest_keys(manifest, path)
    for name, entry in manifest["files"].items():
        for file in entry["files"]:
            _check_confined(directory, file, f"{path}: files.{name}")
            if not (directory / file).is_file():
                raise FileNotFoundError(f"directory: {directory / file} (part {name!r}) does not exist")
    return manifest


def _check_manifest_keys(manifest: dict, path: Path) -> None:
    """The keys :class:`OnnxRuntime` reads, with their types; the parts agree with the files listed."""
    def need(obj: dict, key: str, kind: type, where: str):
        if not isinstance(obj.get(key), kind):
            got = "missing" if key not in obj else f"a {type(obj[key]).__name__}"
            raise ValueError(f"{path}: {where}{key} must be a {kind.__name__}, got {got}")
        return obj[key]

    need(manifest, "config", dict, "")
    parts = need(manifest, "parts", dict, "")
    files = need(manifest, "files", dict, "")
    for part in (*_PARTS, "dit_text_inputs", "deformation", "ldrm_image_input"):
        need(parts, part, bool, "parts.")
    listed = {p for p in _PARTS if parts[p]}
    if set(files) != listed:
        raise ValueError(f"{path}: files lists parts {sorted(files)}, but parts names {sorted(listed)}")
    for name, entry in files.items():
        where = f"files.{name}."
        need(entry, "file", str, where)
        if entry["file"] not in need(entry, "files", list, where):
            raise ValueError(f"{path}: {where}file {entry['file']!r} is not among {where}files")
        for key in ("inputs", "outputs"):
            for value in need(entry, key, list, where):
                if not (isinstance(value, dict) and isinstance(value.get("name"), str)
                        and isinstance(value.get("shape"), list) and value.get("dtype") in _ORT_DTYPES):
                    raise ValueError(f"{path}: {where}{key} entries must be {{name, shape, dtype}}, got {value!r:.80}")
        for dim, bounds in need(entry, "dims", dict, where).items():
            if not (isinstance(bounds, list) and len(bounds) == 2 and all(type(b) is int for b in bounds)
                    and 0 <= bounds[0] <= bounds[1]):
                raise ValueError(f"{path}: {where}dims.{dim} must be [min, max] ints, got {bounds!r:.80}")


def _check_confined(directory: Path, file: object, where: str) -> None:
    """``file`` is a plain file name in ``directory`` whose real path (symlinks resolved) stays inside it."""
    if not isinstance(file, str) or not file or Path(file).name != file or file in (".", ".."):
        raise ValueError(f"{where}: {file!r} must be a plain file name inside the export folder "
                         "(no folders, '..' or absolute paths)")
    real, root = (directory / file).resolve(), directory.resolve()
    if real.parent != root:
        raise ValueError(f"{where}: {file!r} resolves to {real}, outside the export folder {root}")


def check_graph(name: str, entry: dict, session, manifest: dict, path: str | os.PathLike) -> None:
    """Check a manifest file entry against its session's inputs and outputs (names, dims, dtypes), its metadata
    (:func:`diff4splat.export.graph_metadata`: part, config, dim ranges) and the parts flags; ValueError naming ``path``
    (the graph file) and the first difference."""
    def signature(values) -> list[tuple]:
        return [(v.name, [d if isinstance(d, int) else str(d) for d in v.shape], v.type) for v in values]

    for key, values in (("inputs", session.get_inputs()), ("outputs", session.get_outputs())):
        graph = signature(values)
        listed = [(v["name"], list(v["shape"]), _ORT_DTYPES[v["dtype"]]) for v in entry[key]]
        if graph != listed:
            raise ValueError(f"{path}: the manifest's {key} of part {name!r} {listed} differ from the graph's {graph}")
    meta = session.get_modelmeta().custom_metadata_map
    missing = [k for k in GRAPH_METADATA_KEYS if k not in meta]
    if missing:
        raise ValueError(f"{path}: graph metadata lacks {missing} (not written by this version's export_onnx)")
    expected = {"diff4splat.part": name, "diff4splat.config": json.dumps(manifest["config"], sort_keys=True),
                "diff4splat.dims": json.dumps(entry["dims"], sort_keys=True)}
    for key, value in expected.items():
        if meta[key] != value:
            what = key.split(".", 1)[1]
            diff = _differences(json.loads(value), json.loads(meta[key]), what)
            raise ValueError(f"{path}: the manifest's {what} for part {name!r} differs from the one the graph was "
                             f"exported with: {'; '.join(diff[:3])}")
    names = [v.name for v in session.get_inputs()]
    parts = manifest["parts"]
    for part, flag, key in (("dit", "dit_text_inputs", "text"), ("ldrm", "deformation", "times"),
                            ("ldrm", "ldrm_image_input", "image")):
        if name == part and (key in names) != parts[flag]:
            raise ValueError(f"{path}: parts.{flag} is {parts[flag]} but the graph's inputs are {names}")


def _differences(manifest: object, graph: object, where: str) -> list[str]:
    """``"<key path>: manifest <value>, graph <value>"`` for each leaf where two JSON values differ."""
    if isinstance(manifest, dict) and isinstance(graph, dict):
        return [d for k in sorted(set(manifest) | set(graph), key=str)
                for d in _differences(manifest.get(k), graph.get(k), f"{where}.{k}")]
    return [] if manifest == graph else [f"{where}: manifest {json.dumps(manifest):.60}, graph {json.dumps(graph):.60}"]


def _session(path: Path, opts, providers: list[str]):
    """``InferenceSession`` of ``path``; ValueError when onnxruntime cannot load it."""
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=providers)
    except (state.Fail, state.InvalidArgument, state.InvalidGraph, state.InvalidProtobuf, state.NoSuchFile,
            state.NoModel, state.NotImplemented) as e:
        raise ValueError(f"{path}: onnxruntime cannot load this graph (truncated or corrupt?): "
                         f"{' '.join(str(e).split()):.300}") from None


def default_providers() -> list[str]:
    """``["CUDAExecutionProvider", "CPUExecutionProvider"]`` when CUDA is available to onnxruntime, else CPU only."""
    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def session_options(threads: int | None = None, profile_prefix: str | None = None):
    """onnxruntime ``SessionOptions``: ORT_ENABLE_ALL, ``threads`` intra-op threads (default: CPU cores), no
    spinning; ``profile_prefix`` turns on the profiler (JSON per session, ``session.end_profiling()``)."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    # idle threads sleep: spinning ones would take the cores PyTorch runs on between sessions
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile_prefix is not None:
        opts.enable_profiling = True
        opts.profile_file_prefix = profile_prefix
    return opts


def _numpy(t: Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


class OnnxRuntime:
    """:class:`diff4splat.runtime.NetworkRuntime` over an ``export-onnx`` folder ``directory`` (any batch);
    ``providers`` default :func:`default_providers`, ``threads`` and ``profile_prefix`` as :func:`session_options`.
    Raises as :func:`load_manifest`, and ValueError naming a graph file onnxruntime cannot load or that differs from
    the manifest (:func:`check_graph`).

    Attributes:
        manifest, config: the parsed manifest and model config; has_text, has_deformation, ldrm_image_input: parts.
        sessions: {part name: onnxruntime.InferenceSession} for the parts present.
    """

    name = "onnxruntime"
    encodes_empty_prompt = False  # our text encoder: no prompt, no text tokens
    input_dtype = torch.float32  # the graphs' inputs
    attention = None  # onnxruntime picks its own attention kernels
    compiled = False  # nothing runs torch.compile (onnxruntime optimises the graph itself)

    def __init__(self, directory: str | os.PathLike, providers: list[str] | None = None,
                 threads: int | None = None, profile_prefix: str | None = None):
        self.directory = Path(directory)
        self.manifest = load_manifest(self.directory)
        where = f"{self.directory / MANIFEST_NAME}: config"  # config_from_dict names it in every error
        self.config: Diff4SplatConfig = config_from_dict(Diff4SplatConfig, self.manifest["config"], where)
        parts = self.manifest["parts"]
        self.has_text = bool(parts["text_encoder"])
        self.dit_text_inputs = bool(parts["dit_text_inputs"])
        self.has_deformation = bool(parts["deformation"])
        self.has_motion = False  # the motion network is not exported
        self.has_motion_generator = False  # nor the motion generator
        self.ldrm_image_input = bool(parts["ldrm_image_input"])
        self.tokenizer = ByteTokenizer(self.config.text_encoder.max_length)
        self.latent = self.config.vae.latent_format
        self.providers = list(providers) if providers is not None else default_providers()
        opts = session_options(threads, profile_prefix)
        self.sessions = {}
        for name, entry in self.manifest["files"].items():
            path = self.directory / entry["file"]
            self.sessions[name] = _session(path, opts, self.providers)
            check_graph(name, entry, self.sessions[name], self.manifest, path)

    def release(self) -> None:
        """Nothing to free: the sessions keep their memory between scenes."""

    def sigmas(self, steps: int) -> Tensor:
        """(steps + 1,) float64 from 1 to 0 (:func:`models.flow_matching.sigma_schedule`, the config's shift)."""
        return sigma_schedule(steps, self.config.sampling.shift, dtype=torch.float64)

    def encode_image(self, video: Tensor) -> Tensor:
        """(B, 3, T, H, W) in [−1, 1] → (B, c, n, h, w) DiT latents; ValueError as :meth:`VideoVAE.encode`."""
        check_video(self.config.vae, video)
        (z,) = self.sessions["vae_encoder"].run(None, {"video": _numpy(video, np.float32)})
        return torch.from_numpy(z)

    def motion_network(self):
        """Not served (``has_motion`` is False): ValueError."""
        raise ValueError("this ONNX export has no motion network (has_motion is False): its scenes keep the "
                         "deformation network's maps")

    def motion_generator(self):
        """Not served (``has_motion_generator`` is False): ValueError."""
        raise ValueError("this ONNX export has no motion generator (has_motion_generator is False)")

    def decode_latents(self, latents: Tensor) -> Tensor:
        """(B, c, n, h, w) DiT latents → (B, 3, 1 + 4(n − 1), 8h, 8w) pixels on the latents' device; ValueError as
        :meth:`VideoVAE.decode`. Fewer latent frames than the graph's minimum are padded with the last one and cut
        back (the decoder is causal)."""
        check_latents(self.config.vae, latents)
        n, n_min = latents.shape[2], self.manifest["files"]["vae_decoder"]["dims"]["latent_frames"][0]
        padded = torch.cat([latents] + [latents[:, :, -1:]] * max(0, n_min - n), dim=2)
        (video,) = self.sessions["vae_decoder"].run(None, {"latents": _numpy(padded, np.float32)})
        return torch.from_numpy(video[:, :, : 1 + self.latent.temporal_factor * (n - 1)]).to(latents.device)

    def encode_text(self, prompt: str) -> tuple[Tensor, Tensor]:
        """Prompt → tokens (1, L, d_text), mask (1, L); ValueError when the export has no text encoder."""
        if not self.has_text:
            raise ValueError(f"prompt: the ONNX export in {self.directory} was made without the text encoder "
                             f"(text=False) and serves only the empty prompt, got prompt {prompt!r:.60}")
        ids, mask = self.tokenizer([prompt])
        feeds = {"ids": _numpy(ids, np.int64), "mask": _numpy(mask, np.bool_)}
        (tokens,) = self.sessions["text_encoder"].run(None, feeds)
        return torch.from_numpy(tokens), mask

    def velocity(self, x: Tensor, sigma: Tensor, image_latent: Tensor, plucker: Tensor, text: Tensor | None,
                 text_mask: Tensor | None, guidance: float = 1.0, uncond: Tensor | None = None,
                 uncond_mask: Tensor | None = None) -> Tensor:
        """:meth:`diff4splat.runtime.NetworkRuntime.velocity` by ``dit.onnx``, batch B, float32 on the CPU (a None mask:
        all True; no text: one zero token with an all-False mask). ValueError as :meth:`models.dit.VideoDiT.forward`, or
        for text given to a graph without text inputs."""
        sigma = sigma.expand(x.shape[0]) if sigma.dim() == 0 else sigma
        check_dit_inputs(self.config.dit, x, sigma, image_latent, plucker, text, text_mask)
        feeds = {"x": _numpy(x, np.float32), "sigma": _numpy(sigma, np.float32),
                 "image_latent": _numpy(image_latent, np.float32), "plucker": _numpy(plucker, np.float32)}
        dit = self.sessions["dit"]
        (v,) = dit.run(None, {**feeds, **self._text_feeds(x, text, text_mask)})
        if guidance == 1.0:
            return torch.from_numpy(v)
        check_dit_inputs(self.config.dit, x, sigma, image_latent, plucker, uncond, uncond_mask)
        (v_uncond,) = dit.run(None, {**feeds, **self._text_feeds(x, uncond, uncond_mask)})
        v, v_uncond = torch.from_numpy(v), torch.from_numpy(v_uncond)
        return v_uncond + guidance * (v - v_uncond)

    def _text_feeds(self, x: Tensor, text: Tensor | None, text_mask: Tensor | None) -> dict[str, np.ndarray]:
        """``dit.onnx``'s text inputs for the batch of ``x``; ValueError for text to a graph without them."""
        if not self.dit_text_inputs:
            if text is not None:
                raise ValueError(f"text: the ONNX export in {self.directory} was made without the text encoder "
                                 "(text=False): its DiT has no text inputs")
            return {}
        if text is None:
            text = torch.zeros(x.shape[0], 1, self.config.dit.text_dim, device=x.device)
            text_mask = torch.zeros(x.shape[0], 1, dtype=torch.bool, device=x.device)
        elif text_mask is None:
            text_mask = torch.ones(text.shape[:2], dtype=torch.bool, device=text.device)
        return {"text": _numpy(text, np.float32), "text_mask": _numpy(text_mask, np.bool_)}

    def reconstruct(self, latents: Tensor, plucker: Tensor, times: Tensor | None, image: Tensor | None) -> LDRMOutput:
        """``ldrm.onnx``: latents (B, c, n, h, w), plucker (B, 1536, n, h, w), times (K,) in [0, 1] or None, image
        (B, 3, 8h, 8w) in [−1, 1] (fed with an image branch) → maps (B, S, H, W, ·) [+ (B, K, S, H, W, ·)].
        ValueError as :meth:`models.ldrm.LDRM.forward`, or for ``times`` given to an export without deformation."""
        check_ldrm_inputs(self.config.ldrm, latents, plucker, times, image)
        feeds = {"latents": _numpy(latents, np.float32), "plucker": _numpy(plucker, np.float32)}
        if self.ldrm_image_input:
            feeds["image"] = _numpy(image, np.float32)
        if times is not None:
            if not self.has_deformation:
                raise ValueError(f"times: the ONNX export in {self.directory} was made without the deformation "
                                 "network (deformation=False) and makes static scenes only (times must be None)")
            feeds["times"] = _numpy(times, np.float32)
        elif self.has_deformation:  # the dynamic graph needs a times input; its maps are dropped below
            feeds["times"] = np.zeros(1, np.float32)
        outputs = self.sessions["ldrm"].run(None, feeds)
        names = LDRM_OUTPUTS if self.has_deformation else STATIC_LDRM_OUTPUTS
        maps = {name: torch.from_numpy(a) for name, a in zip(names, outputs, strict=True)}
        if times is None:  # the dynamic graph always computes them; a static request drops them
            maps = {k: maps[k] for k in STATIC_LDRM_OUTPUTS}
        return LDRMOutput(**maps)
