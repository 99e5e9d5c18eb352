"""What the commands share: the output-folder flags, the model-config help and the line a written scene reports."""
from __future__ import annotations

import argparse
from pathlib import Path

from models.bundle import DEFAULT_CONFIG, config_names

__all__ = ["OUT_HELP", "OVERWRITE_HELP", "out_path", "add_out_flags", "add_model_flags", "report_scene"]

OUT_HELP = ("output folder, written atomically; an existing one is replaced only if it is empty or an "
            "earlier output of this command (README, 'Output folders')")
OVERWRITE_HELP = ("also replace an existing --out that is not an earlier output of this command "
                  "(never a folder holding the inputs, the current or home directory)")


def out_path(value: str) -> Path:
    """``--out`` as a Path; an empty name (the current directory) is an error."""
    if not value.strip():
        raise argparse.ArgumentTypeError(f"empty folder name {value!r}; give a new folder name")
    return Path(value)


def add_out_flags(parser: argparse.ArgumentParser) -> None:
    """``--out DIR`` (required) and ``--overwrite``."""
    parser.add_argument("--out", type=out_path, required=True, help=OUT_HELP)
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def add_model_flags(parser: argparse.ArgumentParser, config_default: str | None = None) -> None:
    """``--checkpoint DIR`` and ``--config NAME|YAML`` (default ``config_default``; None: the checkpoint's, else
    :data:`models.bundle.DEFAULT_CONFIG`)."""
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="model folder (default: the shipped weights of --config)")
    parser.add_argument("--config", default=config_default, help=f"shipped model config ({', '.join(config_names())}) "
                        f"or a YAML path (default: {DEFAULT_CONFIG})")


def report_scene(out: Path, meta: dict) -> int:
    """Print the line of a written ``generate`` or ``reconstruct`` folder (its meta.json ``meta``); returns 0."""
    print(f"wrote {out} ({meta['frames']} frames, {meta['num_gaussians']} Gaussians, "
          f"{'static' if meta['static'] else 'dynamic'}) in {meta['timings_s']['total']:.1f} s")
    return 0
