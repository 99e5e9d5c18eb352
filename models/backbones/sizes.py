"""The pretrained backbones' real sizes: their Hub configurations, shipped as data
(``configs/backbones/<name>.json``, :data:`diff4splat.utils.config_files.BACKBONE_CONFIGS`), instantiated on
``torch.device("meta")`` — shapes only, no weight allocated, nothing downloaded — and counted.

Sources of the configurations (each file's ``source`` says which for every component): the Hub folders
``Wan-AI/Wan2.2-TI2V-5B-Diffusers`` and ``THUDM/CogVideoX-5b-I2V``, and diffusers' conversion scripts that wrote
them, ``scripts/convert_wan_to_diffusers.py`` (``get_transformer_config("Wan2.2-TI2V-5B")``,
``vae22_diffusers_config``, the UniPC scheduler with ``flow_shift`` 5.0, ``google/umt5-xxl``) and
``scripts/convert_cogvideox_to_diffusers.py`` (``--num_layers 42 --num_attention_heads 48 --i2v``, VAE
``scaling_factor`` 0.7, ``snr_shift_scale`` 1.0, ``google/t5-v1_1-xxl``) of github.com/huggingface/diffusers
(the revision read: docs/DESIGN.md, "Backbones").

:func:`parameter_counts` builds the backbone the way :class:`models.backbone_model.BackboneModel` does — the
:class:`~models.backbone.Backbone` subclass of the folder's pipeline (which checks the configuration: channels,
VAE factors, scheduler) with its camera-widened patch embedding, and the LDRM at
:meth:`BackboneModelConfig.for_backbone`'s sizes — so the counts are those of the model ``generate`` would run.

This module imports diffusers and transformers (``diff4splat[diffusers]``); only the backbone size table and its
test import it.
"""
from __future__ import annotations

import inspect

import diffusers
import torch
import transformers
from torch import nn

from diff4splat.io.structured import read_json
from diff4splat.utils.config_files import BACKBONE_CONFIGS

from ..backbone_model import PIPELINES, BackboneModel, BackboneModelConfig, backbone_class
from ..ldrm import LDRM
from ..pretrained import count_parameters

__all__ = ["backbone_names", "backbone_config", "meta_backbone", "meta_model", "parameter_counts", "COMPONENTS",
           "COUNT_KEYS"]

COMPONENTS = ("transformer", "vae", "text_encoder")
"""The networks of a backbone configuration (``scheduler`` is the fourth component; the tokenizer has no weights)."""
COUNT_KEYS = ("transformer", "vae", "text_encoder", "camera", "ldrm", "total")
"""The keys of :func:`parameter_counts`."""

_LIBRARIES = {"diffusers": diffusers, "transformers": transformers}


def backbone_names() -> list[str]:
    """The shipped backbone configurations, sorted (``cogvideox-5b-i2v``, ``wan2.2-ti2v-5b``)."""
    return sorted(p.stem for p in BACKBONE_CONFIGS.glob("*.json"))


def backbone_config(name: str) -> dict:
    """``configs/backbones/<name>.json``: ``model_index``, ``transformer``, ``vae``, ``text_encoder``,
    ``scheduler`` (the Hub folder's config files) and ``source``.

    Raises:
        ValueError: an unknown name (the message lists the known ones), or a file without those keys.
    """
    if name not in backbone_names():
        raise ValueError(f"backbone config {name!r} does not exist; known: {', '.join(backbone_names())}")
    path = BACKBONE_CONFIGS / f"{name}.json"
    data = read_json(path, "backbone config")
    missing = [k for k in ("model_index", *COMPONENTS, "scheduler") if not isinstance(data.get(k), dict)]
    if missing:
        raise ValueError(f"backbone config: {path} lacks {', '.join(missing)}")
    return data


def _component_class(config: dict, component: str) -> type:
    """The class ``model_index.json`` names for ``component`` (``["diffusers", "WanTransformer3DModel"]``)."""
    library, class_name = config["model_index"][component]
    return getattr(_LIBRARIES[library], class_name)


def _diffusers_init_kwargs(cls: type, values: dict) -> dict:
    """The config's keys that ``cls.__init__`` takes: a Hub file may hold keys the installed diffusers ignores
    (Wan2.2's VAE: ``clip_output``), which ``from_config`` would only warn about."""
    params = inspect.signature(cls.__init__).parameters
    return {k: v for k, v in values.items() if k in params}


def _build(config: dict, component: str) -> nn.Module:
    cls = _component_class(config, component)
    values = config[component]
    if issubclass(cls, transformers.PreTrainedModel):
        model_config = cls.config_class.from_dict(values)
        return cls(model_config)
    return cls.from_config(_diffusers_init_kwargs(cls, values))


def meta_backbone(name: str) -> dict[str, nn.Module]:
    """The backbone's ``transformer``, ``vae`` and ``text_encoder`` as the Hub folder defines them (the transformer
    with its own patch embedding), every parameter and buffer on the meta device.

    Raises:
        ValueError: an unknown name.
    """
    config = backbone_config(name)
    with torch.device("meta"):
        return {component: _build(config, component) for component in COMPONENTS}


def _scheduler(config: dict):
    cls = _component_class(config, "scheduler")
    return cls.from_config(_diffusers_init_kwargs(cls, config["scheduler"]))


def meta_model(name: str) -> BackboneModel:
    """The :class:`BackboneModel` a Hub folder of this backbone loads as (camera weights, the LDRM at
    :meth:`BackboneModelConfig.for_backbone`'s defaults), on the meta device; no tokenizer.

    Raises:
        ValueError: an unknown name, or a configuration the backbone class rejects.
    """
    config = backbone_config(name)
    kind = PIPELINES[config["model_index"]["_class_name"]]
    nets = meta_backbone(name)
    backbone = backbone_class(kind)(**nets, tokenizer=None, scheduler=_scheduler(config))  # widens the patch conv
    model_config = BackboneModelConfig.for_backbone(kind, backbone.latent)
    with torch.device("meta"):
        ldrm = LDRM(model_config.ldrm)
    return BackboneModel(backbone, ldrm, model_config)


def parameter_counts(name: str) -> dict[str, int]:
    """Parameters of backbone ``name`` on the meta device.

    Returns:
        ``transformer`` (the Hub transformer), ``vae``, ``text_encoder`` (the encoder only), ``camera`` (the
        :class:`~models.backbones.diffusers_backbone.CameraPatchConv`'s zero-initialised weights: out_channels ×
        6·t·s² × the patch kernel), ``ldrm`` (:class:`models.ldrm.LDRM` on the backbone's latents at the paper's
        sizes) and ``total``. Buffers are not counted (CogVideoX-5B-I2V's learned positional embedding is a
        diffusers buffer).
    """
    model = meta_model(name)
    counts = model.parameter_counts()  # vae, text_encoder, dit (with the camera weights), ldrm, total
    camera = model.backbone.camera_conv.camera_weight.numel()
    out = {"transformer": counts["dit"] - camera, "vae": counts["vae"], "text_encoder": counts["text_encoder"],
           "camera": camera, "ldrm": count_parameters(model.ldrm)}
    out["total"] = sum(out.values())
    return out
