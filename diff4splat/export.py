"""ONNX export of the four networks: one graph per module plus ``manifest.json``.

``export_onnx(model, out_dir)`` (or ``export_checkpoint(folder, out_dir)``, the ``export-onnx`` command) writes,
atomically (temp folder + rename, :func:`diff4splat.io.output_folders`, kind ``"onnx"``):

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

The LDRM's maps have a source-frame axis S (``models.ldrm.source_frame_indices``): S = n for
``gaussian_frames="latent"``, 1 + 4(n − 1) for ``"all"``, 1 for ``"reference"``; it follows the dynamic
latent frame count n (a symbolic dim of the outputs, e.g. ``latent_frames``). ``image`` (the photograph,
frame 0) is an input only when the LDRM has an image branch (``config.ldrm.image_branch`` > 0); the
manifest records it as ``parts.ldrm_image_input``.

Every graph has dynamic batch B and frame counts (T / n), dynamic resolution (multiples of the VAE
factor and patch sizes, above a minimum the guards of the traced graph need), dynamic text length L
and number of times K. Shapes are traced with ``torch.export.export`` (non-strict) first, so a
dynamic axis the code cannot honour raises instead of being silently specialised; the exported
program is translated by the dynamo ONNX exporter (opset ≥ 18) and checked with ``onnx.checker``.

Leaving parts out (CONTRIBUTING, "leave out what a scene does not need"):

- ``text=False`` (``--no-text``): no ``text_encoder.onnx``, and ``dit.onnx`` has no text inputs — it
  is the text=None graph (no cross-attention at all), serving the empty prompt only.
- With text, ``dit.onnx`` is the text-conditioned graph and also serves the empty prompt: one zero
  token with an all-False mask gives *exactly* zero cross-attention (``CrossAttention`` multiplies
  the output of an all-masked row by 0, and x + 0 = x in IEEE arithmetic), so it equals
  ``VideoDiT(text=None)`` bit for bit in PyTorch (and the ONNX graph equals the text=None PyTorch call). One DiT
  file serves both, so its weights are stored once.
- ``deformation=False`` (``--static``): ``ldrm.onnx`` has no ``times`` input and no deformation
  outputs (the deformation network is not in the graph); such an export only makes static scenes.
- The image branch is not optional: an LDRM trained with one needs the photograph, so its graph
  always has the ``image`` input.

``manifest.json`` records the opset, the parts, every file's input/output names, shapes (symbolic
dims as strings) and dtypes, the model config, and the SHA-256 of the weights (of each
``model.safetensors`` of the source checkpoint, or of the state dict of an in-memory model). Each graph
also carries its part name, config and dim ranges in its own ONNX metadata (:func:`graph_metadata`), which
:mod:`diff4splat.onnx_runtime` checks the manifest against.
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
from models.backbone_model import INDEX_FILE
from models.bundle import DEFAULT_CONFIG, NETWORKS, Diff4SplatModel
from models.pretrained import WEIGHTS_NAME

__all__ = ["export_onnx", "export_checkpoint", "check_opset", "state_dict_sha256", "checkpoint_sha256",
           "MANIFEST_NAME", "MANIFEST_FORMAT", "MIN_OPSET", "MAX_OPSET", "EXTERNAL_DATA_BYTES", "LDRM_OUTPUTS",
           "STATIC_LDRM_OUTPUTS", "graph_metadata", "GRAPH_METADATA_KEYS"]

EXPORT_KIND = "onnx"
"""Output kind of an export folder (:data:`diff4splat.io.MARKER`); ``generate`` replaces one only with --overwrite."""
MIN_OPSET = 18
"""The dynamo exporter emits opset ≥ 18 (LayerNorm, GroupNorm-free decompositions, ``ReduceMean`` axes inputs)."""
MAX_OPSET = 25
"""The newest opset whose graphs pass ``onnx.checker`` and load in onnxruntime. onnx 1.23 names opsets up to 28, but
the exporter's graphs fail its checker from 26 on (no Gelu/Attention registered at the version the exporter's
converter leaves them), after the whole export had run."""
EXTERNAL_DATA_BYTES = 2_000_000_000
"""Graphs whose weights reach 2 GB store them in a ``<file>.onnx.data`` beside the graph: a single
protobuf cannot exceed 2 GiB (``onnx.checker`` and onnxruntime read the external file by path)."""
_MAX = 1 << 14  # upper bound of every dynamic dimension (sizes, not memory: the graph has no limit)


class _VAEEncoder(nn.Module):
    """video (B, 3, T, H, W) in [−1, 1] → DiT latents a·(mean − b) (:meth:`VideoVAE.encode_latents`)."""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.vae = model.vae

    def forward(self, video: Tensor) -> Tensor:
        return self.vae.encode_latents(video)


class _VAEDecoder(nn.Module):
    """DiT latents (B, c, n, h, w) → video (B, 3, 1 + 4(n − 1), 8h, 8w) (:meth:`VideoVAE.decode_latents`)."""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.vae = model.vae

    def forward(self, latents: Tensor) -> Tensor:
        return self.vae.decode_latents(latents)


class _TextEncoder(nn.Module):
    """ids (B, L) int64, mask (B, L) bool → tokens (B, L, d_text) (zeros at padding)."""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.text_encoder = model.text_encoder

    def forward(self, ids: Tensor, mask: Tensor) -> Tensor:
        return self.text_encoder(ids, mask)


class _TextDiT(nn.Module):
    """The DiT velocity with text cross-attention (all-False mask = exactly no cross-attention)."""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.dit = model.dit

    def forward(self, x, sigma, image_latent, plucker, text, text_mask):
        return self.dit(x, sigma, image_latent, plucker, text, text_mask)


class _PlainDiT(nn.Module):
    """The DiT velocity without text (``text=None``: the cross-attention is not in the graph)."""

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.dit = model.dit

    def forward(self, x, sigma, image_latent, plucker):
        return self.dit(x, sigma, image_latent, plucker)


class _LDRM(nn.Module):
    """LDRM: (latents, plucker[, times][, image]) → the 8 maps of :data:`LDRM_OUTPUTS` with ``times``
    (the deformation network is in the graph), else the 5 of :data:`STATIC_LDRM_OUTPUTS`.

    An absent input is traced as ``None``: torch.export keeps only tensor inputs, so the graph's inputs
    are the present ones in this order.
    """

    def __init__(self, model: Diff4SplatModel):
        super().__init__()
        self.ldrm = model.ldrm

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
    """Example inputs (batch 2, 9 frames / 3 latent frames: sizes 0 and 1 would be specialised by
    torch.export) and the dynamic dims of every graph.

    Resolution dims are expressed as multiples of what the architecture needs: pixels of 8 (VAE),
    latent cells of the DiT patch, LDRM latents of its patch. Minimum sizes come from the guards of
    the traced graphs (the deformation pyramid halves the latent grid ``levels − 1`` times and
    needs ≥ 2 cells at its coarsest level; the VAE decoder's temporal upsampling is traced for
    n ≥ 3 latent frames (its graph has guards n − 1 ≠ 1); torch.export names any bound that is too low).
    """
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
    # traced on a grid of at least lmin tokens a side (a config whose own grid is smaller, e.g. ldrm.patch_size 2
    # at 64², failed the export on torch.export's bound); the graph itself runs on smaller grids
    lh, lw = max(h, pl * lmin), max(w, pl * lmin)
    ldrm_args = (randn(B, c, n, lh, lw), randn(B, cfg.ldrm.plucker_channels, n, lh, lw),
                 torch.linspace(0, 1, K, device="cpu") if deformation else None,
                 randn(B, 3, s * lh, s * lw).tanh() if image else None)
    ldrm_ds = {"latents": ldrm_lat, "plucker": ldrm_lat, "times": {0: K_d} if deformation else None,
               "image": {0: batch, 2: (s * pl) * hr, 3: (s * pl) * wr} if image else None}
    names = tuple(k for k, a in zip(("latents", "plucker", "times", "image"), ldrm_args, strict=True) if a is not None)
    # The image branch writes frame 0 with a torch.where over the frame axis (models/ldrm.py), not a cat with
    # an (n − 1)-frame slice, which would add a guard n − 1 ≠ 1 leaving out n = 2 (5 video frames).
    graphs.append(_Graph("ldrm", _LDRM(model), ldrm_args, names, LDRM_OUTPUTS if deformation else STATIC_LDRM_OUTPUTS,
                         ldrm_ds))
    return graphs


def state_dict_sha256(module: nn.Module) -> str:
    """SHA-256 over a state dict: for each entry in sorted key order, the key, dtype, shape and the
    tensor's raw bytes (CPU, contiguous). Equal for equal weights, independent of insertion order."""
    digest = hashlib.sha256()
    for key, value in sorted(module.state_dict().items()):
        t = value.detach().cpu().contiguous()
        digest.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # device: t is a CPU copy
    return digest.hexdigest()


def checkpoint_sha256(directory: str | os.PathLike) -> dict[str, str]:
    """SHA-256 of each network's ``model.safetensors`` in a :meth:`Diff4SplatModel.save_pretrained` folder.

    Returns:
        {"vae/model.safetensors": hex, …} for the four networks.

    Raises:
        FileNotFoundError: a network's weights file is missing.
    """
    directory = Path(directory)
    out = {}
    for name in NETWORKS:
        path = directory / name / WEIGHTS_NAME
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint: {path} does not exist")
        digest = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
        out[f"{name}/{WEIGHTS_NAME}"] = digest.hexdigest()
    return out


def _onnx():
    """The onnx package, imported where an export or check needs it (not at import of this module)."""
    import onnx  # lazy: onnx and protobuf add ~0.05 s to every command's start; only exports and checks use them

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
    """The facts a graph carries about itself in its ONNX ``metadata_props`` (keys :data:`GRAPH_METADATA_KEYS`):
    its part name, the model config it was exported from (the trained resolution, channels, …) and its
    dynamic dim ranges, each as canonical JSON. :class:`diff4splat.onnx_runtime.OnnxRuntime` compares them
    with ``manifest.json``, so an edited manifest cannot make a graph run with another config."""
    return {"diff4splat.part": part, "diff4splat.config": json.dumps(config, sort_keys=True),
            "diff4splat.dims": json.dumps(dims, sort_keys=True)}



def _export_graph(graph: _Graph, path: Path, opset: int, external_data_bytes: int, config: dict) -> dict:
    """Trace, translate, save and check one graph (with :func:`graph_metadata`); returns its manifest entry."""
    onnx = _onnx()

    weight_bytes = sum(t.numel() * t.element_size() for t in graph.module.state_dict().values())
    # exporter chatter on stderr: missing optional torchvision ops (torch.onnx), "Skipping constant folding for op
    # Split with multiple outputs" (onnxscript's optimizer, a dozen lines per export)
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
    """Replace torch.export's symbols (``s15``, ``4*s7 + 1``) by the Dim names (``batch``, ``4*k + 1``)
    in the graph's inputs, outputs and value infos (in place)."""
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
    """Raise ValueError unless ``opset`` is an int in [:data:`MIN_OPSET`, :data:`MAX_OPSET` or the installed onnx's
    newest if older]."""
    onnx = _onnx()

    newest = min(MAX_OPSET, onnx.defs.onnx_opset_version())
    if isinstance(opset, bool) or not isinstance(opset, int) or not MIN_OPSET <= opset <= newest:
        raise ValueError(f"opset must be an int in [{MIN_OPSET}, {newest}] (the dynamo exporter needs ≥ {MIN_OPSET}), "
                         f"got {opset!r}")


def export_onnx(
    model: Diff4SplatModel,
    out_dir: str | os.PathLike,
    *,
    text: bool = True,
    deformation: bool = True,
    opset: int = MIN_OPSET,
    checkpoint: str | os.PathLike | None = None,
    source: str | None = None,
    external_data_bytes: int = EXTERNAL_DATA_BYTES,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
) -> dict:
    """Export ``model`` to ``out_dir`` (one ``.onnx`` per module + ``manifest.json``), atomically.

    Args:
        model: the four networks. The export runs on the CPU in float32, whatever device the model was on:
            ``model`` is moved there (in place, as ``nn.Module.to`` does) and left in eval mode; move it
            back with ``model.to(device)`` to go on using it on a GPU. The graphs run on any onnxruntime
            provider (CUDA included) all the same.
        out_dir: output folder; replaced only when the whole export succeeded.
        text: include the text encoder and the text-conditioned DiT (False = ``--no-text``).
        deformation: include the deformation network in the LDRM graph (False = ``--static``).
        opset: ONNX opset in [:data:`MIN_OPSET`, :data:`MAX_OPSET`] (:func:`check_opset`).
        checkpoint: the folder ``model`` was loaded from; its weight files are hashed. None hashes
            the in-memory state dict (:func:`state_dict_sha256`), e.g. for a random model.
        source: free-text description of the weights' origin stored in the manifest.
        external_data_bytes: graphs with at least this many bytes of weights store them externally.
        inputs: paths the export reads (``checkpoint`` is added); ``out_dir`` may not hold them.
        overwrite: also replace a folder that is not an earlier ONNX export (:func:`diff4splat.io.output_folders`).

    Returns:
        The manifest dict (also written to ``out_dir/manifest.json``).

    Raises:
        ValueError: ``opset`` out of range; ``model`` is not a :class:`~models.bundle.Diff4SplatModel` (a diffusers
            backbone's networks are not exported).
        OutputDirError: ``out_dir`` may not be written (a file, holds inputs, not an ONNX export, …).
        FileNotFoundError: ``checkpoint`` lacks a network's weights.
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


def export_checkpoint(
    checkpoint: str | os.PathLike | None,
    out_dir: str | os.PathLike,
    *,
    config: str = DEFAULT_CONFIG,
    text: bool = True,
    deformation: bool = True,
    opset: int = MIN_OPSET,
    overwrite: bool = False,
    load: Callable[..., tuple[Diff4SplatModel, str]] = load_model,
) -> dict:
    """Export the networks of a model folder (the ``diff4splat export-onnx`` command): ``out_dir``, ``opset`` and
    ``checkpoint`` are checked before anything loads, then :func:`export_onnx`'s export of what ``load`` returns.

    Args:
        checkpoint: our model folder (its weight files are hashed); None: the shipped weights of ``config``, or a
            seeded random model with a warning when none ship (its state dict is hashed).
        out_dir: the export folder; its parent must exist. Replaced only when the whole export succeeded.
        config: shipped config name or YAML path, for ``checkpoint`` None.
        text, deformation, opset, overwrite: as :func:`export_onnx`.
        load: called as ``load(checkpoint, config, seed=0)`` after the checks, returning (model, source)
            (:func:`diff4splat.pipeline.load_model`; the command passes it wrapped to print its warnings).

    Returns:
        The manifest dict (also written to ``out_dir/manifest.json``).

    Raises:
        OutputDirError: (a ValueError) ``out_dir`` may not be written
            (:func:`diff4splat.io.output_folders.check_output_dir`); FileExistsError likewise.
        ValueError: an unsupported ``opset`` (:func:`check_opset`); ``checkpoint`` is a diffusers backbone folder
            (has ``model_index.json``: its networks are not exported); a malformed model folder.
        FileNotFoundError: ``checkpoint`` is not a folder; an unknown config name (:func:`load_model`).
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
    """:func:`export_onnx` once its arguments are checked: the weights hashed, the graphs and the manifest written
    (the folder checked again as it is written, :func:`diff4splat.io.output_folders.output_dir`)."""
    onnx = _onnx()
    weights = ({"kind": "checkpoint", "path": str(checkpoint), "sha256": checkpoint_sha256(checkpoint)}
               if checkpoint is not None else {"kind": "state_dict", "sha256": state_dict_sha256(model)})
    model = model.to("cpu", torch.float32).eval()
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
