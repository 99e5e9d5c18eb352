"""ONNX export of the four networks: one graph per module plus ``manifest.json``.

:func:`export_onnx` (:func:`export_checkpoint`: the ``export-onnx`` command) writes, atomically (kind ``"onnx"``):

=====================  =====================================================  ==========================================
file                   inputs                                                 outputs
=====================  =====================================================  ==========================================
``vae_encoder.onnx``   video (B, 3, T=1+4k, H, W) in [−1, 1]                   latents (B, c, 1+k, H/8, W/8) (DiT scale)
``vae_decoder.onnx``   latents (B, c, n, h, w) (DiT scale)                    video (B, 3, 1+4(n−1), 8h, 8w)
``text_encoder.onnx``  ids (B, L) int64, mask (B, L) bool                     tokens (B, L, d_text)
``dit.onnx``           x (B, c, n, h, w), sigma (B,), image_latent            velocity (B, c, n, h, w)
                       (B, c, 1, h, w), plucker (B, 1536, n, h, w)
                       [, text (B, L, d_text), text_mask (B, L) bool]
``ldrm.onnx``          latents (B, c, n, h, w), plucker (B, 1536, n, h, w)    distance (B, S, H, W), scales, quats,
                       [, times (K,)] [, image (B, 3, 8h, 8w) in [−1, 1]]     opacities, colors (B, S, H, W, ·)
                                                                              [, d_means, d_quats, d_scales
                                                                              (B, K, S, H, W, ·)]
=====================  =====================================================  ==========================================

S is the source-frame count (``models.ldrm.source_frame_indices``); ``image`` is an input only with an image branch.
Batch, frame counts, resolution, text length L and times K are dynamic (traced with ``torch.export.export``, so an
axis the code cannot honour raises). ``text=False`` leaves out the text encoder and the DiT's text inputs (with text,
one zero token with an all-False mask gives exactly zero cross-attention, so one DiT graph serves both);
``deformation=False`` leaves the deformation network out of ``ldrm.onnx``. ``manifest.json`` records the opset, the
parts, every file's inputs and outputs, the model config and the SHA-256 of the weights; each graph carries its
part, config and dim ranges in its ONNX metadata (:func:`graph_metadata`).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.export import Dim

from diff4splat.io.output_folders import check_output_dir, output_dir
from diff4splat.onnx_runtime import (
    GRAPH_METADATA_KEYS,
    LDRM_OUTPUTS,
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    STATIC_LDRM_OUTPUTS,
)
from diff4splat.pipeline import load_model
from diff4splat.utils.limits import check_disk
from models.backbone_model import INDEX_FILE
from models.bundle import DEFAULT_CONFIG, NETWORKS, OPTIONAL_NETWORKS, Diff4SplatModel
from models.pretrained import WEIGHTS_NAME

__all__ = ["export_onnx", "export_checkpoint", "check_opset", "state_dict_sha256", "checkpoint_sha256",
           "MANIFEST_NAME", "MANIFEST_FORMAT", "MIN_OPSET", "MAX_OPSET", "EXTERNAL_DATA_BYTES", "LDRM_OUTPUTS",
           "STATIC_LDRM_OUTPUTS", "graph_metadata", "GRAPH_METADATA_KEYS"]

EXPORT_KIND = "onnx"
"""Output kind of an export folder (:data:`diff4splat.io.MARKER`)."""
MIN_OPSET = 18
"""The oldest opset the dynamo exporter emits."""
MAX_OPSET = 25
"""The newest opset whose graphs pass ``onnx.checker`` (from 26 on the exporter's Gelu/Attention fail it)."""
EXPORT_OVERHEAD_BYTES = 64 << 20
"""Bytes an export writes beside its weights (graphs, names, the manifest), with a margin: the free space it needs."""
EXTERNAL_DATA_BYTES = 2_000_000_000
"""Graphs with this many bytes of weights store them in ``<file>.onnx.data`` (a protobuf is at most 2 GiB)."""
_MAX = 1 << 14  # upper bound of every dynamic dimension


class _Part(nn.Module):
    """One network of the model (its attribute :attr:`part`), its graph's inputs the arguments of ``forward``."""

    part = ""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        setattr(self, self.part, getattr(model, self.part))


class _VAEEncoder(_Part):
    """video (B, 3, T, H, W) in [−1, 1] → DiT latents (:meth:`VideoVAE.encode_latents`)."""

    part = "vae"

    def forward(self, video: Tensor) -> Tensor:
        return self.vae.encode_latents(video)


class _VAEDecoder(_Part):
    """DiT latents (B, c, n, h, w) → video (B, 3, 1 + 4(n − 1), 8h, 8w) (:meth:`VideoVAE.decode_latents`)."""

    part = "vae"

    def forward(self, latents: Tensor) -> Tensor:
        return self.vae.decode_latents(latents)


class _TextEncoder(_Part):
    """ids (B, L) int64, mask (B, L) bool → tokens (B, L, d_text) (zeros at padding)."""

    part = "text_encoder"

    def forward(self, ids: Tensor, mask: Tensor) -> Tensor:
        return self.text_encoder(ids, mask)


class _TextDiT(_Part):
    """The DiT velocity with text cross-attention (all-False mask = exactly no cross-attention)."""

    part = "dit"

    def forward(self, x, sigma, image_latent, plucker, text, text_mask):
        return self.dit(x, sigma, image_latent, plucker, text, text_mask)


class _PlainDiT(_Part):
    """The DiT velocity without text (the cross-attention is not in the graph)."""

    part = "dit"

    def forward(self, x, sigma, image_latent, plucker):
        return self.dit(x, sigma, image_latent, plucker)


class _LDRM(_Part):
    """(latents, plucker[, times][, image]) → :data:`LDRM_OUTPUTS` with ``times``, else :data:`STATIC_LDRM_OUTPUTS`
    (an absent input is traced as None and is not a graph input)."""

    part = "ldrm"

    def forward(self, latents, plucker, times=None, image=None):
        out = self.ldrm(latents, plucker, times, image)
        return tuple(getattr(out, name) for name in (STATIC_LDRM_OUTPUTS if times is None else LDRM_OUTPUTS))


@dataclass
class _Graph:
    name: str
    module: nn.Module
    args: tuple[Tensor, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dynamic_shapes: dict


def _graphs(model: Diff4SplatModel, text: bool, deformation: bool) -> list[_Graph]:
    """Example inputs (batch 2, 3 latent frames: torch.export specialises sizes 0 and 1) and dynamic dims of every
    graph, resolutions as multiples of the VAE factor and patch sizes; minimums from the traced graphs' guards (the
    deformation pyramid needs ≥ 2 cells at its coarsest level, the VAE decoder n ≥ 3 latent frames)."""
    cfg = model.config
    c, s, tf = cfg.vae.latent_channels, cfg.vae.spatial_factor, cfg.vae.temporal_factor
    _, ph, pw = cfg.dit.patch_size
    pl = cfg.ldrm.patch_size
    h, w = cfg.height // s, cfg.width // s
    gen = torch.Generator().manual_seed(0)
    B, n, K, L = 2, 3, 5, 7

    def randn(*shape):
        return torch.randn(shape, generator=gen, device="cpu")  # the export traces on the CPU

    batch = Dim("batch", min=1, max=_MAX)
    k = Dim("k", min=0, max=_MAX)  # T = 1 + 4k frames
    nd = Dim("latent_frames", min=1, max=_MAX)
    hv, wv = Dim("h8", min=1, max=_MAX), Dim("w8", min=1, max=_MAX)
    hl, wl = Dim("latent_h", min=1, max=_MAX), Dim("latent_w", min=1, max=_MAX)
    ht, wt = Dim("dit_tokens_h", min=1, max=_MAX), Dim("dit_tokens_w", min=1, max=_MAX)
    levels = cfg.ldrm.deformation.levels if deformation else 1
    lmin = max(1, 2 ** (levels - 1) + 1) if deformation else 1
    hr, wr = Dim("ldrm_tokens_h", min=lmin, max=_MAX), Dim("ldrm_tokens_w", min=lmin, max=_MAX)
    L_d = Dim("text_tokens", min=1, max=_MAX)
    K_d = Dim("times", min=1, max=_MAX)
    video_ds = {0: batch, 2: tf * k + 1, 3: s * hv, 4: s * wv}
    dit_lat = {0: batch, 2: nd, 3: ph * ht, 4: pw * wt}
    ldrm_lat = {0: batch, 2: nd, 3: pl * hr, 4: pl * wr}

    graphs = [
        _Graph("vae_encoder", _VAEEncoder(model), (randn(B, 3, 1 + tf * (n - 1), cfg.height, cfg.width).tanh(),),
               ("video",), ("latents",), {"video": video_ds}),
        _Graph("vae_decoder", _VAEDecoder(model), (randn(B, c, n, h, w),), ("latents",), ("video",),
               {"latents": {0: batch, 2: Dim("latent_frames", min=3, max=_MAX), 3: hl, 4: wl}}),
    ]
    if text:
        ids = torch.randint(3, cfg.text_encoder.vocab_size, (B, L), generator=gen, device="cpu")
        mask = torch.tensor([[True] * L, [True] * (L - 3) + [False] * 3], device="cpu")
        graphs.append(_Graph("text_encoder", _TextEncoder(model), (ids, mask), ("ids", "mask"), ("tokens",),
                             {"ids": {0: batch, 1: L_d}, "mask": {0: batch, 1: L_d}}))
    dit_args = (randn(B, c, n, h, w), torch.rand(B, generator=gen, device="cpu"), randn(B, c, 1, h, w),
                randn(B, cfg.dit.camera_channels, n, h, w))
    dit_ds = {"x": dit_lat, "sigma": {0: batch}, "image_latent": {0: batch, 3: ph * ht, 4: pw * wt},
              "plucker": dit_lat}
    if text:
        graphs.append(_Graph(
            "dit", _TextDiT(model), dit_args + (randn(B, L, cfg.dit.text_dim), mask),
            ("x", "sigma", "image_latent", "plucker", "text", "text_mask"), ("velocity",),
            {**dit_ds, "text": {0: batch, 1: L_d}, "text_mask": {0: batch, 1: L_d}}))
    else:
        graphs.append(_Graph("dit", _PlainDiT(model), dit_args, ("x", "sigma", "image_latent", "plucker"),
                             ("velocity",), dit_ds))
    image = cfg.ldrm.image_branch > 0
    # traced on a grid of at least lmin tokens a side (torch.export's bound); the graph runs on smaller grids
    lh, lw = max(h, pl * lmin), max(w, pl * lmin)
    ldrm_args = (randn(B, c, n, lh, lw), randn(B, cfg.ldrm.plucker_channels, n, lh, lw),
                 torch.linspace(0, 1, K, device="cpu") if deformation else None,
                 randn(B, 3, s * lh, s * lw).tanh() if image else None)
    ldrm_ds = {"latents": ldrm_lat, "plucker": ldrm_lat, "times": {0: K_d} if deformation else None,
               "image": {0: batch, 2: (s * pl) * hr, 3: (s * pl) * wr} if image else None}
    names = tuple(k for k, a in zip(("latents", "plucker", "times", "image"), ldrm_args, strict=True) if a is not None)
    graphs.append(_Graph("ldrm", _LDRM(model), ldrm_args, names, LDRM_OUTPUTS if deformation else STATIC_LDRM_OUTPUTS,
                         ldrm_ds))
    return graphs


def state_dict_sha256(module: nn.Module) -> str:
    """SHA-256 over a state dict: each entry's key, dtype, shape and raw bytes, in sorted key order."""
    digest = hashlib.sha256()
    for key, value in sorted(module.state_dict().items()):
        t = value.detach().cpu().contiguous()
        digest.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # device: t is a CPU copy
    return digest.hexdigest()


def checkpoint_sha256(directory: str | os.PathLike) -> dict[str, str]:
    """{"vae/model.safetensors": hex SHA-256, …} of the networks of a :meth:`Diff4SplatModel.save_pretrained`
    folder (an optional network's when its folder is there). FileNotFoundError: a weights file is missing."""
    directory = Path(directory)
    out = {}
    for name in NETWORKS:
        path = directory / name / WEIGHTS_NAME
        if name in OPTIONAL_NETWORKS and not path.parent.exists():
            continue
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint: {path} does not exist")
        digest = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
        out[f"{name}/{WEIGHTS_NAME}"] = digest.hexdigest()
    return out


def _onnx():
    """The onnx package, imported on use (kept out of every command's start)."""
    import onnx  # lazy: onnx and protobuf would slow every command's start; only exports and checks use them

    return onnx


def _value_info(values) -> list[dict]:
    onnx = _onnx()
    out = []
    for v in values:
        t = v.type.tensor_type
        shape = [d.dim_param if d.HasField("dim_param") else int(d.dim_value) for d in t.shape.dim]
        out.append({"name": v.name, "shape": shape, "dtype": onnx.helper.tensor_dtype_to_np_dtype(t.elem_type).name})
    return out


def graph_metadata(part: str, config: dict, dims: dict[str, list[int]]) -> dict[str, str]:
    """A graph's ONNX ``metadata_props`` (keys :data:`GRAPH_METADATA_KEYS`): its part, config and dim ranges as
    canonical JSON, which :class:`diff4splat.onnx_runtime.OnnxRuntime` compares with ``manifest.json``."""
    return {"diff4splat.part": part, "diff4splat.config": json.dumps(config, sort_keys=True),
            "diff4splat.dims": json.dumps(dims, sort_keys=True)}


def _export_graph(graph: _Graph, path: Path, opset: int, external_data_bytes: int, config: dict) -> dict:
    """Trace, translate, save and check one graph (with :func:`graph_metadata`); returns its manifest entry."""
    onnx = _onnx()
    weight_bytes = sum(t.numel() * t.element_size() for t in graph.module.state_dict().values())
    # silence the exporter's chatter on stderr
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # deprecation notices of the tracing stack
            program = torch.export.export(graph.module.eval(), graph.args, dynamic_shapes=graph.dynamic_shapes,
                                          strict=False)
            onnx_program = torch.onnx.export(program, graph.args, dynamo=True, opset_version=opset,
                                             input_names=list(graph.input_names),
                                             output_names=list(graph.output_names), verbose=False)
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)
    external = weight_bytes >= external_data_bytes
    onnx_program.save(str(path), external_data=external)
    proto = onnx.load(str(path), load_external_data=False)  # external tensors keep their file references
    _name_dims(proto, graph)
    onnx.helper.set_model_props(proto, graph_metadata(graph.name, config, _dim_ranges(graph.dynamic_shapes)))
    onnx.save(proto, str(path))
    onnx.checker.check_model(str(path))  # by path: works for external data and > 2 GiB
    inputs, outputs = _value_info(proto.graph.input), _value_info(proto.graph.output)
    names_in, names_out = [i["name"] for i in inputs], [o["name"] for o in outputs]
    if names_in != list(graph.input_names) or names_out != list(graph.output_names):
        raise RuntimeError(f"{path.name}: exported names {[i['name'] for i in inputs]} → "
                           f"{[o['name'] for o in outputs]} differ from {graph.input_names} → {graph.output_names}")
    files = sorted(p.name for p in path.parent.iterdir() if p.name.startswith(path.name))
    return {"file": path.name, "files": files, "external_data": external, "weight_bytes": weight_bytes,
            "inputs": inputs, "outputs": outputs, "dims": _dim_ranges(graph.dynamic_shapes)}


def _name_dims(proto, graph: _Graph) -> None:
    """Rename torch.export's symbols (``4*s7 + 1``) to the Dim names (``4*k + 1``) in the graph, in place."""
    symbol = re.compile(r"\bs\d+\b")
    mapping: dict[str, str] = {}
    for value, name in zip(proto.graph.input, graph.input_names, strict=True):
        for axis, d in graph.dynamic_shapes.get(name, {}).items():
            found = symbol.findall(value.type.tensor_type.shape.dim[axis].dim_param)
            if len(found) == 1:
                mapping.setdefault(found[0], getattr(d, "root", d).__name__)
    for value in [*proto.graph.input, *proto.graph.output, *proto.graph.value_info]:
        for dim in value.type.tensor_type.shape.dim:
            if dim.HasField("dim_param"):
                dim.dim_param = symbol.sub(lambda m: mapping.get(m.group(0), m.group(0)), dim.dim_param)


def _dim_ranges(dynamic_shapes: dict) -> dict[str, list[int]]:
    """{root dim name: [min, max]} of a graph's dynamic dims (derived dims like ``4*k + 1`` report k)."""
    out = {}
    for axes in dynamic_shapes.values():
        for d in (axes or {}).values():  # None: an input left out of the graph
            root = getattr(d, "root", d)
            out[root.__name__] = [int(root.min), int(root.max)]
    return dict(sorted(out.items()))


def check_opset(opset: int) -> None:
    """ValueError unless ``opset`` is an int in [:data:`MIN_OPSET`, :data:`MAX_OPSET` or onnx's newest if older]."""
    newest = min(MAX_OPSET, _onnx().defs.onnx_opset_version())
    if isinstance(opset, bool) or not isinstance(opset, int) or not MIN_OPSET <= opset <= newest:
        raise ValueError(f"opset must be an int in [{MIN_OPSET}, {newest}] (the dynamo exporter needs ≥ {MIN_OPSET}), "
                         f"got {opset!r}")


def export_onnx(model: Diff4SplatModel, out_dir: str | os.PathLike, *, text: bool = True, deformation: bool = True,
                opset: int = MIN_OPSET, checkpoint: str | os.PathLike | None = None, source: str | None = None,
                external_data_bytes: int = EXTERNAL_DATA_BYTES, inputs: Iterable[str | os.PathLike | None] = (),
                overwrite: bool = False) -> dict:
    """Export ``model`` to ``out_dir`` (one ``.onnx`` per module + ``manifest.json``), atomically; returns the manifest.

    Args:
        model: the four networks; moved to the CPU in float32 and eval mode, in place.
        out_dir: output folder; replaced only when the whole export succeeded (or ``overwrite``, any folder).
        text, deformation: include the text encoder and text inputs (``--no-text``: False), the deformation network
            (``--static``: False).
        opset: ONNX opset (:func:`check_opset`).
        checkpoint: the folder ``model`` was loaded from, whose weight files are hashed; None hashes the state dict.
        source: free-text description of the weights' origin stored in the manifest.
        external_data_bytes: graphs with at least this many bytes of weights store them externally.
        inputs: paths the export reads (``checkpoint`` is added); ``out_dir`` may not hold them.

    Raises:
        ValueError: ``opset`` out of range; ``model`` is not a :class:`~models.bundle.Diff4SplatModel`.
        OutputDirError, FileNotFoundError: ``out_dir`` may not be written; ``checkpoint`` lacks a network's weights.
        LimitError: the weights (float32) and :data:`EXPORT_OVERHEAD_BYTES` above the free space of ``out_dir``'s
            disk (:func:`diff4splat.utils.limits.check_disk`), before anything is exported.
        torch._dynamo.exc.UserError: a dynamic dimension cannot be honoured by a network (a bug).
    """
    if not isinstance(model, Diff4SplatModel):
        raise ValueError(f"export-onnx exports our own networks (a Diff4SplatModel), not a {type(model).__name__}: "
                         "a diffusers backbone is served with --runtime torch")
    check_opset(opset)
    inputs = [*inputs, checkpoint]
    check_output_dir(out_dir, inputs=inputs, overwrite=overwrite, kind=EXPORT_KIND, parents=True)  # before the export
    return _export(model, out_dir, text=text, deformation=deformation, opset=opset, checkpoint=checkpoint,
                   source=source, external_data_bytes=external_data_bytes, inputs=inputs, overwrite=overwrite)


def export_checkpoint(checkpoint: str | os.PathLike | None, out_dir: str | os.PathLike, *, config: str = DEFAULT_CONFIG,
                      text: bool = True, deformation: bool = True, opset: int = MIN_OPSET, overwrite: bool = False,
                      load: Callable[..., tuple[Diff4SplatModel, str]] = load_model) -> dict:
    """The ``export-onnx`` command: ``out_dir``, ``opset`` and ``checkpoint`` checked before anything loads, then
    :func:`export_onnx`'s export of ``load(checkpoint, config, seed=0)`` → (model, source); returns the manifest.
    ``checkpoint``: our model folder (None: the shipped weights of ``config``, or a seeded random model); ``out_dir``:
    its parent must exist; ``load``: :func:`diff4splat.pipeline.load_model` or a wrapper; the rest as ``export_onnx``.

    Raises:
        OutputDirError, FileExistsError: ``out_dir`` may not be written.
        LimitError: as :func:`export_onnx`.
        ValueError: a bad ``opset``; ``checkpoint`` is a diffusers backbone folder or malformed.
        FileNotFoundError: ``checkpoint`` is not a folder; an unknown config name.
    """
    check_output_dir(out_dir, inputs=[checkpoint], overwrite=overwrite, kind=EXPORT_KIND)
    check_opset(opset)
    if checkpoint is not None and (Path(checkpoint) / INDEX_FILE).is_file():  # before loading gigabytes
        raise ValueError(f"--checkpoint {checkpoint} is a diffusers backbone ({INDEX_FILE}); export-onnx exports "
                         "our own networks only (serve a backbone with --runtime torch)")
    model, source = load(checkpoint, config, seed=0)
    weights = None if source.startswith("random:") else Path(source)  # the weight files read, hashed
    return _export(model, out_dir, text=text, deformation=deformation, opset=opset, checkpoint=weights, source=source,
                   external_data_bytes=EXTERNAL_DATA_BYTES, inputs=[checkpoint, weights], overwrite=overwrite)


def _export(model: Diff4SplatModel, out_dir: str | os.PathLike, *, text: bool, deformation: bool, opset: int,
            checkpoint: str | os.PathLike | None, source: str | None, external_data_bytes: int,
            inputs: list[str | os.PathLike | None], overwrite: bool) -> dict:
    """:func:`export_onnx` once its arguments are checked: hash the weights, write the graphs and the manifest."""
    onnx = _onnx()
    weights = ({"kind": "checkpoint", "path": str(checkpoint), "sha256": checkpoint_sha256(checkpoint)}
               if checkpoint is not None else {"kind": "state_dict", "sha256": state_dict_sha256(model)})
    model = model.to("cpu", torch.float32).eval()
    weight_bytes = 4 * sum(t.numel() for t in model.state_dict().values())  # float32 in the graphs, each weight once
    check_disk(weight_bytes + EXPORT_OVERHEAD_BYTES, f"export-onnx of {weight_bytes // 4:,} weights",
               "the model's size", out_dir)  # before the export's minutes, not at its write
    manifest = {
        "format": MANIFEST_FORMAT,
        "opset": opset,
        "exporter": f"torch {torch.__version__} (dynamo), onnx {onnx.__version__}",
        "parts": {"vae_encoder": True, "vae_decoder": True, "text_encoder": text, "dit": True,
                  "dit_text_inputs": text, "ldrm": True, "deformation": deformation,
                  "ldrm_image_input": model.config.ldrm.image_branch > 0},
        "dit_unconditional": ("text inputs with one zero token and an all-False mask (exactly zero "
                              "cross-attention)" if text else "graph without text inputs (no cross-attention)"),
        "config": model.config.to_dict(),
        "source": source,
        "weights": weights,
        "files": {},
    }
    with output_dir(out_dir, kind=EXPORT_KIND, inputs=inputs, overwrite=overwrite, parents=True) as tmp:
        for graph in _graphs(model, text, deformation):
            manifest["files"][graph.name] = _export_graph(graph, tmp / f"{graph.name}.onnx", opset,
                                                          external_data_bytes, manifest["config"])
        (tmp / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2))
    return manifest
