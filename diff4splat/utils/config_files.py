"""Where the shipped YAML configs live: the repository's top-level ``configs/``, which a checkout links as
``diff4splat/configs`` and a wheel holds as package data (docs/DESIGN.md, "Layout")."""
from __future__ import annotations

from pathlib import Path

__all__ = ["CONFIGS_DIR", "MODEL_CONFIGS", "STAGE_CONFIGS", "CURATION_DEFAULT", "BACKBONE_CONFIGS"]

CONFIGS_DIR = Path(__file__).resolve().parents[1] / "configs"
"""Every shipped YAML config, by kind in the sub-folders below."""
MODEL_CONFIGS = CONFIGS_DIR / "models"
"""Model size configs (``base``, ``tiny``, ``small``, ``paper``)."""
STAGE_CONFIGS = CONFIGS_DIR / "training"
"""Training stage configs (``train_stage1`` …, the backbones' ``train_wan_stage*``, ``train_cogvideox_stage*``)."""
CURATION_DEFAULT = CONFIGS_DIR / "data_prep" / "curation_default.yaml"
"""The curation thresholds ``data_prep curate`` uses by default."""
BACKBONE_CONFIGS = CONFIGS_DIR / "backbones"
"""The pretrained backbones' Hub configurations, ``<name>.json``, instantiated on the meta device by
:mod:`models.backbones.sizes`."""
