"""Parameter counts and bf16 sizes of the pretrained backbones (Wan2.2-TI2V-5B, CogVideoX-5B-I2V) with our camera
weights and LDRM: their Hub configurations (configs/backbones/*.json) instantiated on the meta device
(models/backbones/sizes.py), so nothing is downloaded or allocated. Needs ``diff4splat[diffusers]``.

Prints the table of README.md's "Model sizes" (billions of parameters and GB = 10⁹ bytes at 2 bytes each) and the
exact counts.

    python benchmarks/backbone_sizes.py
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import markdown_table  # noqa: E402

from models.backbone_model import DEFAULTS, PIPELINES  # noqa: E402
from models.backbones.sizes import backbone_config, backbone_names, parameter_counts  # noqa: E402

COLUMNS = [("vae", "VAE"), ("text_encoder", "text encoder"), ("transformer", "transformer"),
           ("camera", "camera"), ("ldrm", "LDRM"), ("total", "total")]


def billions_and_bf16(n: int) -> str:
    return f"{n / 1e9:.3f} B · {2 * n / 1e9:.3f} GB"


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    rows, exact = [], []
    for name in sorted(backbone_names(), reverse=True):  # Wan first
        config = backbone_config(name)
        kind = PIPELINES[config["model_index"]["_class_name"]]
        d = DEFAULTS[kind]
        counts = parameter_counts(name)
        label = f"[{name}](https://huggingface.co/{config['hub_repo']})"
        shape = f"{d['width']}×{d['height']}, {d['num_frames']} frames"
        rows.append([label, shape] + [billions_and_bf16(counts[k]) for k, _ in COLUMNS])
        exact.append([name] + [f"{counts[k]:,}" for k, _ in COLUMNS])
    header = [title for _, title in COLUMNS]
    print(markdown_table(["backbone", "resolution"] + header, rows))
    print()
    print(markdown_table(["backbone"] + header, exact))


if __name__ == "__main__":
    main()
