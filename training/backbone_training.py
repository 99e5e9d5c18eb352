"""Training stages of a pretrained diffusers backbone (Wan2.2-TI2V-5B, CogVideoX-5B-I2V) with our LDRM: loading, LoRA,
freezing and saving (docs/DESIGN.md, "Backbones"; issue 30). The objectives are :mod:`training.objectives`'.

Design:

- **Loading** (:func:`load_backbone_model`). A stage with ``backbone: wan2.2-ti2v`` or ``cogvideox-i2v`` starts from a
  diffusers folder (``init_from`` with ``model_index.json``: the Hub's, or the previous stage's ``<run_dir>/model``),
  loaded by :meth:`models.backbone_model.BackboneModel.from_pretrained` with the frozen weights in
  ``stage.backbone_dtype``. The weights that train (the patch embedding's camera weights, the LDRM) are float32: with
  a bfloat16 backbone they are read again from the folder in float32, so a bfloat16 load never rounds them.
- **LoRA** (Hu et al. 2022) through peft's ``inject_adapter_in_model`` on the transformer's attention and FFN linear
  layers (:class:`training.stage_config.LoraSettings`, :data:`training.stage_config.LORA_TARGETS`): A drawn from
  ``trainer.seed``, B zero, so step 0 runs the loaded transformer exactly; the adapters are float32.
- **Freezing** (:func:`apply_backbone_freezing`): ``dit`` trains the adapters and ``camera_weight`` of the
  :class:`models.backbones.diffusers_backbone.CameraPatchConv`, ``ldrm`` (and its parts) the LDRM in full; everything
  else of the backbone (VAE, text encoder, the transformer's own weights) is frozen.
- **Checkpoints** (:mod:`training.checkpoint`) hold the training module's state dict as it is, the adapters under
  peft's names (``…attn1.to_q.base_layer.weight``, ``…attn1.to_q.lora_A.default.weight``); a resumed run builds the
  same model and loads them (exact resume, :class:`training.trainer.Trainer`).
- **Saving** (:func:`save_backbone_model`): the adapters are merged into the saved copy of the transformer only.
  For the time of the save every adapted ``nn.Linear`` is swapped for a plain one with weight W + (α/r)·B·A (summed
  in float32, stored in W's dtype) under its own name (:func:`merged_lora`), so ``transformer/`` keeps the
  checkpoint's key names and the folder is an ordinary :class:`BackboneModel` folder: ``BackboneModel.from_pretrained``
  and ``generate --checkpoint`` load it without peft, and the next stage puts fresh adapters on the merged weights.
  The live model is unchanged (its adapters stay separate; no merge/unmerge round trip).

This module imports peft (``pip install 'diff4splat[diffusers]'``); :mod:`training.train` imports it only for a
diffusers backbone stage.
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import torch
from peft import LoraConfig, inject_adapter_in_model
from peft.tuners.lora import LoraLayer
from safetensors.torch import load_file
from torch import nn

from models.backbone_model import LDRM_FOLDER, BackboneModel, folder_backbone
from models.backbones.diffusers_backbone import CAMERA_FOLDER, CAMERA_WEIGHTS
from models.ldrm import LDRM

from .stage_config import LoraSettings, StageConfig, apply_freezing

__all__ = ["load_backbone_model", "add_lora", "lora_layers", "apply_backbone_freezing", "merged_lora",
           "save_backbone_model", "pixel_multiple", "DTYPES"]

DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
"""``stage.backbone_dtype`` → torch dtype."""


def load_backbone_model(stage: StageConfig) -> BackboneModel:
    """The model a diffusers backbone stage trains: ``stage.init_from`` loaded (frozen weights in
    ``stage.backbone_dtype``, camera weights and LDRM in float32), with LoRA adapters on its transformer when the
    stage trains ``dit`` (module docstring). Nothing is downloaded; the model is on the CPU.

    Raises:
        FileNotFoundError: ``init_from`` is not a diffusers folder (no ``model_index.json``).
        ValueError: the folder holds another backbone than ``stage.backbone``, or does not load
            (:meth:`BackboneModel.from_pretrained`); no transformer module matches ``stage.lora.target_modules``.
        MissingExtraError: diffusers missing.
    """
    folder = Path(stage.init_from) if stage.init_from else None
    if folder is None:
        raise FileNotFoundError(f"init_from: a {stage.backbone} stage starts from a diffusers folder "
                                "(model_index.json, e.g. Wan-AI/Wan2.2-TI2V-5B-Diffusers downloaded); got none")
    kind = folder_backbone(folder)
    if kind != stage.backbone:
        raise ValueError(f"init_from: {folder} holds a {kind} backbone; stage.backbone is {stage.backbone}")
    dtype = DTYPES[stage.backbone_dtype]
    model = BackboneModel.from_pretrained(folder, torch_dtype=dtype, seed=stage.trainer.seed)
    if dtype != torch.float32:
        _float32_trainables(model, folder)
    if stage.lora is not None:
        add_lora(model.backbone.transformer, stage.lora, seed=stage.trainer.seed)
    return model


def _float32_trainables(model: BackboneModel, folder: Path) -> None:
    """Replace the LDRM and the camera weights of a model loaded in a low-precision dtype by their float32 values in
    ``folder`` (a random LDRM / zero camera weights of a fresh Hub folder: cast)."""
    ldrm = folder / LDRM_FOLDER
    model.ldrm = LDRM.from_pretrained(ldrm) if ldrm.is_dir() else model.ldrm.float()
    conv, camera = model.backbone.camera_conv, folder / CAMERA_FOLDER / CAMERA_WEIGHTS
    weight = (load_file(str(camera))[f"{model.backbone.patch_conv_path}.camera_weight"] if camera.is_file()
              else conv.camera_weight.detach())  # checked by BackboneModel.from_pretrained
    conv.camera_weight = nn.Parameter(weight.to(conv.camera_weight.device, torch.float32))


def lora_layers(module: nn.Module) -> list[tuple[str, LoraLayer]]:
    """The peft LoRA layers of ``module`` as (qualified name, layer), in module order."""
    return [(name, m) for name, m in module.named_modules() if isinstance(m, LoraLayer)]


def add_lora(transformer: nn.Module, settings: LoraSettings, seed: int = 0) -> int:
    """Put LoRA adapters (adapter name ``default``) on the modules of ``transformer`` named by
    ``settings.target_modules``, in place.

    A is initialised from ``seed`` (Kaiming-uniform, peft's default; torch's global RNG is left as it was), B is
    zero; the adapters are float32 whatever the transformer's dtype.

    Returns:
        The number of adapted layers.

    Raises:
        ValueError: no module matches (naming ``stage.lora.target_modules``), or the transformer already has adapters.
    """
    if lora_layers(transformer):
        raise ValueError("the transformer already has LoRA adapters")
    config = LoraConfig(r=settings.rank, lora_alpha=settings.alpha, lora_dropout=settings.dropout,
                        target_modules=list(settings.target_modules))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        try:
            inject_adapter_in_model(config, transformer)
        except ValueError as e:
            raise ValueError(f"stage.lora.target_modules {list(settings.target_modules)} match no module of the "
                             f"{type(transformer).__name__}: {e}") from None
    layers = lora_layers(transformer)
    for _, layer in layers:
        layer.lora_A.float()
        layer.lora_B.float()
    return len(layers)


def apply_backbone_freezing(model: BackboneModel, train: tuple[str, ...]) -> dict[str, int]:
    """Freeze every parameter of a backbone model except: for ``dit`` the transformer's LoRA adapters and the patch
    embedding's ``camera_weight``; for ``ldrm``, ``ldrm.deformation``, ``ldrm.head``, ``ldrm.image_branch`` as
    :func:`training.stage_config.apply_freezing`.

    Returns:
        Trainable parameter count per name of ``train``.

    Raises:
        ValueError: ``dit`` listed but the transformer has no adapters (:func:`add_lora` first). (``vae`` and
            ``text_encoder`` are refused by :class:`training.stage_config.StageConfig`.)
    """
    counts = apply_freezing(model, tuple(t for t in train if t != "dit"))
    if "dit" in train:
        layers = lora_layers(model.backbone.transformer)
        if not layers:
            raise ValueError("stage.train lists dit but the transformer has no LoRA adapters")
        params = [p for _, layer in layers for p in (*layer.lora_A.parameters(), *layer.lora_B.parameters())]
        params.append(model.backbone.camera_conv.camera_weight)
        for p in params:
            p.requires_grad_(True)
        counts["dit"] = sum(p.numel() for p in params)
    return {name: counts[name] for name in train}


@contextlib.contextmanager
def merged_lora(module: nn.Module) -> Iterator[nn.Module]:
    """Within the block, every LoRA layer of ``module`` is replaced by a plain ``nn.Linear`` with the merged weight
    W + Σ (α/r)·B·A over its active adapters (float32 sum, W's dtype) and W's bias, under the layer's own name; the
    LoRA layers are put back after (their weights untouched). A module without adapters is yielded as it is.

    Raises:
        TypeError: an adapted layer that is not an ``nn.Linear``.
    """
    swaps = []
    for name, layer in lora_layers(module):
        base = layer.get_base_layer()
        if type(base) is not nn.Linear:
            raise TypeError(f"merged_lora: {name} adapts a {type(base).__name__}; only nn.Linear is merged")
        with torch.no_grad():
            weight = base.weight.float() + sum(layer.get_delta_weight(a).float() for a in layer.active_adapters)
        with torch.device("meta"):
            plain = nn.Linear(base.in_features, base.out_features, bias=base.bias is not None)
        plain.weight = nn.Parameter(weight.to(base.weight.dtype), requires_grad=False)
        plain.bias = base.bias
        swaps.append((name, layer, plain))
    for name, _, plain in swaps:
        module.set_submodule(name, plain)
    try:
        yield module
    finally:
        for name, layer, _ in swaps:
            module.set_submodule(name, layer)


def save_backbone_model(model: BackboneModel, directory: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """:meth:`BackboneModel.save_pretrained` with the transformer's LoRA merged into the saved weights
    (:func:`merged_lora`): a folder that ``BackboneModel.from_pretrained`` and ``generate --checkpoint`` load.

    Raises:
        OutputDirError: ``directory`` may not be written or replaced.
    """
    with merged_lora(model.backbone.transformer):
        return model.save_pretrained(directory, overwrite=overwrite)


def pixel_multiple(model: BackboneModel) -> int:
    """Clip heights and widths must be multiples of this many pixels: the VAE's spatial factor × the patch size of the
    transformer (2×2) and of the LDRM (as :class:`models.backbone_model.BackboneModelConfig` checks its own size)."""
    return model.backbone.latent.spatial_factor * max(2, model.config.ldrm.patch_size)
