"""The pretrained backbones' real sizes: their Hub configurations, shipped as data (``configs/backbones/<name>.json``,
each with its ``source``: the Hub folders and diffusers' conversion scripts; docs/DESIGN.md "Backbones"), instantiated
on ``torch.device("meta")`` (no weights, nothing downloaded) and counted. :func:`parameter_counts` builds the backbone
as :class:`models.backbone_model.BackboneModel` does (camera-widened patch embedding, the LDRM at
:meth:`BackboneModelConfig.for_backbone`'s sizes), so the counts are those of the model ``generate`` runs. Imports
diffusers and transformers."""
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
"""The networks of a backbone configuration (the scheduler and tokenizer have no weights)."""
COUNT_KEYS = ("transformer", "vae", "text_encoder", "camera", "ldrm", "total")
"""The keys of :func:`parameter_counts`."""

_LIBRARIES = {"diffusers": diffusers, "transformers": transformers}


def backbone_names() -> list[str]:
    """The shipped backbone configurations, sorted (``cogvideox-5b-i2v``, ``wan2.2-ti2v-5b``)."""
    return sorted(p.stem for p in BACKBONE_CONFIGS.glob("*.json"))


def backbone_config(name: str) -> dict:
    """``configs/backbones/<name>.json``: ``model_index``, ``transformer``, ``vae``, ``text_encoder``, ``scheduler``
    and ``source``. ValueError for an unknown name (listing the known ones) or a file lacking those keys."""
    if name not in backbone_names():
        raise ValueError(f"backbone config {name!r} does not exist; known: {', '.join(backbone_names())}")
    path = BACKBONE_CONFIGS / f"{name}.json"
    data = read_json(path, "backbone config")
    missing = [k for k in ("model_index", *COMPONENTS, "scheduler") if not isinstance(data.get(k), dict)]
    if missing:
        raise ValueError(f"backbone config: {path} lacks {', '.join(missing)}")
    return data


def _component_class(config: dict, component: str) -> type:
    """The class ``model_index.json`` names for ``component``."""
    library, class_name = config["model_index"][component]
    return getattr(_LIBRARIES[library], class_name)


def _diffusers_init_kwargs(cls: type, values: dict) -> dict:
    """The config's keys ``cls.__init__`` takes (a Hub file may hold keys the installed diffusers ignores)."""
    params = inspect.signature(cls.__init__).parameters
    return {k: v for k, v in values.items() if k in params}


def _build(config: dict, component: str) -> object:
    """``component`` of a backbone from its config: a network (an ``nn.Module``) or the scheduler."""
    cls = _component_class(config, component)
    values = config[component]
    if issubclass(cls, transformers.PreTrainedModel):
        return cls(cls.config_class.from_dict(values))
    return cls.from_config(_diffusers_init_kwargs(cls, values))


def meta_backbone(name: str) -> dict[str, nn.Module]:
    """The backbone's ``transformer`` (with its own patch embedding), ``vae`` and ``text_encoder`` on the meta device.
    ValueError for an unknown name."""
    config = backbone_config(name)
    with torch.device("meta"):
        return {component: _build(config, component) for component in COMPONENTS}


def meta_model(name: str) -> BackboneModel:
    """The :class:`BackboneModel` a Hub folder of this backbone loads as, on the meta device, without tokenizer.
    ValueError for an unknown name or a configuration the backbone class rejects."""
    config = backbone_config(name)
    kind = PIPELINES[config["model_index"]["_class_name"]]
    nets = meta_backbone(name)
    scheduler = _build(config, "scheduler")
    backbone = backbone_class(kind)(**nets, tokenizer=None, scheduler=scheduler)  # widens the patch conv
    model_config = BackboneModelConfig.for_backbone(kind, backbone.latent)
    with torch.device("meta"):
        ldrm = LDRM(model_config.ldrm)
    return BackboneModel(backbone, ldrm, model_config)


def parameter_counts(name: str) -> dict[str, int]:
    """Parameters of backbone ``name``: ``transformer`` (the Hub transformer), ``vae``, ``text_encoder``, ``camera``
    (the zero-initialised camera weights), ``ldrm`` (paper sizes on the backbone's latents) and ``total``; buffers not
    counted."""
    model = meta_model(name)
    counts = model.parameter_counts()  # vae, text_encoder, dit (with the camera weights), ldrm, total
    camera = model.backbone.camera_conv.camera_weight.numel()
    out = {"transformer": counts["dit"] - camera, "vae": counts["vae"], "text_encoder": counts["text_encoder"],
           "camera": camera, "ldrm": count_parameters(model.ldrm)}
    out["total"] = sum(out.values())
    return out
