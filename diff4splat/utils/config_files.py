"""Where the shipped YAML configs live: the repository's top-level ``configs/`` (docs/DESIGN.md, "Layout").

``configs/models/<name>.yaml`` (model sizes: ``load_config("small")``), ``configs/training/<name>.yaml`` (training
stages: ``load_stage("train_stage1")``) and ``configs/data_prep/curation_default.yaml`` (curation thresholds). In a
checkout ``diff4splat/configs`` is a link to the top-level folder; a wheel holds the files themselves as package data
of ``diff4splat``, so the same paths work in both.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["CONFIGS_DIR", "MODEL_CONFIGS", "STAGE_CONFIGS", "CURATION_DEFAULT", "BACKBONE_CONFIGS"]

CONFIGS_DIR = Path(__file__).resolve().parents[1] / "configs"
"""Every shipped YAML config, by kind in the sub-folders below."""
MODEL_CONFIGS = CONFIGS_DIR / "models"
"""Model size configs (``base``, ``tiny``, ``small``, ``paper``)."""
STAGE_CONFIGS = CONFIGS_DIR / "training"
"""Training stage configs (``train_vae``, ``train_stage1`` … ``train_stage3``, ``train_base_*``; the backbones'
``train_wan_stage*``, ``train_cogvideox_stage*``)."""
CURATION_DEFAULT = CONFIGS_DIR / "data_prep" / "curation_default.yaml"
"""The curation thresholds ``data_prep curate`` uses by default."""
BACKBONE_CONFIGS = CONFIGS_DIR / "backbones"
"""The pretrained backbones' Hub configurations, ``<name>.json`` (``wan2.2-ti2v-5b``, ``cogvideox-5b-i2v``): what
:mod:`models.backbones.sizes` instantiates on the meta device."""
