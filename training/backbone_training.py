"""Training stages of a pretrained diffusers backbone (Wan2.2-TI2V-5B, CogVideoX-5B-I2V) with our LDRM: loading (frozen
weights in ``stage.backbone_dtype``, trained ones float32), LoRA (Hu et al. 2022, peft: A from ``trainer.seed``, B
zero), freezing and saving with the adapters merged into the saved transformer only, under its own key names, so the
folder loads without peft (docs/DESIGN.md, "Backbones" and "Training"). Needs peft (``pip install
'diff4splat[diffusers]'``); :mod:`training.train` imports it only for such a stage.
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
    """``stage.init_from`` loaded on the CPU (frozen weights in ``stage.backbone_dtype``, camera weights and LDRM in
    float32), with LoRA when the stage has ``lora``; nothing is downloaded. Raises FileNotFoundError (not a diffusers
    folder), ValueError (another backbone kind, a folder that does not load, LoRA targets matching nothing),
    MissingExtraError (no diffusers)."""
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
    """Reload the LDRM and camera weights of a low-precision load in float32 from ``folder`` (else cast them)."""
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
    """Put float32 LoRA adapters (``default``) on ``transformer``'s ``settings.target_modules`` in place, A from
    ``seed`` (torch's global RNG left as it was), B zero; returns the number of adapted layers. Raises ValueError
    when no module matches or the transformer already has adapters."""
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
    """Freeze all but ``train``: ``dit`` is the LoRA adapters and the patch embedding's ``camera_weight``, the LDRM's
    names as :func:`training.stage_config.apply_freezing`; returns the trainable count per name. Raises ValueError
    for ``dit`` without adapters."""
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
    """Within the block, every LoRA layer of ``module`` is a plain ``nn.Linear`` under its own name with weight
    W + Σ (α/r)·B·A (float32 sum, W's dtype); the LoRA layers are put back after. TypeError for a non-Linear base."""
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
    """:meth:`BackboneModel.save_pretrained` with the LoRA merged (:func:`merged_lora`); OutputDirError as it."""
    with merged_lora(model.backbone.transformer):
        return model.save_pretrained(directory, overwrite=overwrite)


def pixel_multiple(model: BackboneModel) -> int:
    """Pixel multiple of clip sizes: the VAE's spatial factor × the larger patch size (transformer 2, LDRM)."""

    return model.backbone.latent.spatial_factor * max(2, model.config.ldrm.patch_size)
