"""Tests for models/backbones/sizes.py: the shipped Hub configurations of Wan2.2-TI2V-5B and CogVideoX-5B-I2V
(configs/backbones/*.json), instantiated on the meta device, have the published sizes and fit our backbone code."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

pytest.importorskip("diffusers", reason="the backbone sizes build diffusers models (diff4splat[diffusers])")
pytestmark = pytest.mark.slow  # every test here: diffusers costs ~8 s to import (tests/conftest.py)
pytest.importorskip("ftfy", reason="the Wan backbone module needs ftfy (diff4splat[diffusers])")

from diff4splat.utils.config_files import BACKBONE_CONFIGS  # noqa: E402
from models.backbone import LatentFormat  # noqa: E402
from models.backbone_model import DEFAULTS, PIPELINES, BackboneModelConfig  # noqa: E402
from models.backbones.diffusers_backbone import CameraPatchConv  # noqa: E402
from models.backbones.sizes import (  # noqa: E402
    COMPONENTS,
    COUNT_KEYS,
    backbone_config,
    backbone_names,
    meta_backbone,
    meta_model,
    parameter_counts,
)

ROOT = Path(__file__).resolve().parent.parent
WAN, COG = "wan2.2-ti2v-5b", "cogvideox-5b-i2v"
TEXT_SHAPE = ("vocab_size", "d_model", "d_kv", "d_ff", "num_layers", "num_heads", "feed_forward_proj",
              "relative_attention_num_buckets")

# Exact counts of the shipped configurations (what the published figures below are checked against once more).
EXACT = {
    WAN: {"transformer": 4_999_787_712, "vae": 704_688_668, "text_encoder": 5_680_910_336},
    COG: {"transformer": 5_570_479_680, "vae": 215_583_907, "text_encoder": 4_762_310_656},
}

# Published sizes, (value, relative tolerance, where from). A file of n GB in bf16 holds n/2 billion parameters, in
# float32 n/4; the Hub rounds file sizes to 3 significant digits, hence the tolerances.
PUBLISHED = {
    WAN: {
        # "TI2V-5B" (Wan-Video/Wan2.2 README; the Hub lists Wan-AI/Wan2.2-TI2V-5B-Diffusers as 5B). The original
        # checkpoint Wan-AI/Wan2.2-TI2V-5B is 825 float32 tensors of 19,999,150,848 bytes = 4,999,787,712 × 4 (its
        # safetensors sizes as recorded by public code that loads it): equal to EXACT.
        "transformer": (5.0e9, 1e-3, "Wan2.2 README: TI2V-5B"),
        # Wan-AI/Wan2.2-TI2V-5B-Diffusers vae/diffusion_pytorch_model.safetensors: 2.82 GB in float32.
        "vae": (2.82e9 / 4, 5e-3, "Hub vae file 2.82 GB, float32"),
        # Wan-AI/Wan2.2-TI2V-5B-Diffusers text_encoder/model-0000{1,2,3}-of-00003.safetensors: 4.94 + 4.98 + 1.44 GB
        # in bf16 (umT5-XXL's encoder, ≈ 5.7 B).
        "text_encoder": ((4.94 + 4.98 + 1.44) * 1e9 / 2, 3e-3, "Hub text_encoder shards 11.36 GB, bf16"),
    },
    COG: {
        # CogVideoX-5B's transformer: 5.57 B; THUDM/CogVideoX-5b transformer/ shards 9.93 + 1.22 GB in bf16 (the
        # text-to-video model; the I2V one has 16 more input channels, 16·3072·2·2 = 196,608 weights).
        "transformer": ((9.93 + 1.22) * 1e9 / 2, 2e-3, "THUDM/CogVideoX-5b transformer shards 11.15 GB, bf16"),
        # The CogVideoX-5b VAE in bf16: 431 MB (as repackaged in Kijai/CogVideoX-5b-Tora vae/).
        "vae": (0.431e9 / 2, 5e-3, "VAE 431 MB, bf16"),
        # google/t5-v1_1-xxl's encoder, 4.76 B (the `paper` row of README.md's model sizes uses the same encoder).
        "text_encoder": (4.762e9, 1e-3, "T5-v1.1-XXL encoder 4.76 B"),
    },
}


@pytest.fixture(scope="module")
def counts() -> dict[str, dict[str, int]]:
    return {name: parameter_counts(name) for name in (WAN, COG)}


def test_the_configs_ship_as_package_data():
    assert backbone_names() == [COG, WAN]
    assert BACKBONE_CONFIGS.resolve() == ROOT / "configs" / "backbones"
    assert 'diff4splat = ["configs/*/*.yaml", "configs/*/*.json"]' in (ROOT / "pyproject.toml").read_text()
    for name in backbone_names():
        config = backbone_config(name)
        assert config["name"] == name and set(config["source"]) >= {"model_index", *COMPONENTS, "scheduler"}
        assert config["model_index"]["_class_name"] in PIPELINES


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="cogvideox-5b-i2v, wan2.2-ti2v-5b"):
        backbone_config("wan2.1-t2v-14b")


@pytest.mark.parametrize("name", [WAN, COG])
def test_counts_equal_the_published_sizes(counts, name):
    got = counts[name]
    assert set(got) == set(COUNT_KEYS)
    assert {k: got[k] for k in EXACT[name]} == EXACT[name]
    for key, (value, rel, where) in PUBLISHED[name].items():
        assert math.isclose(got[key], value, rel_tol=rel), f"{name} {key}: {got[key]:,} vs {value:,.0f} ({where})"
    assert got["total"] == sum(got[k] for k in COUNT_KEYS if k != "total")


def test_text_encoder_counts_by_hand(counts):
    """The encoders from their shapes: embedding + 24 blocks of attention (4·d²), gated FFN (3·d·d_ff) and two RMS
    norms, + the final norm; relative-position biases (32 buckets × 64 heads) in every block for umT5, in the
    first only for T5."""
    d, ff, blocks, bias = 4096, 10240, 24, 32 * 64
    block = 4 * d * d + 3 * d * ff + 2 * d
    assert counts[WAN]["text_encoder"] == 256_384 * d + blocks * (block + bias) + d
    assert counts[COG]["text_encoder"] == 32_128 * d + blocks * block + bias + d


def test_camera_weights_are_out_channels_by_packed_rays_by_kernel(counts):
    """CameraPatchConv adds out_channels × 6·t·s² × kernel weights: Wan 3072 × 6·4·16² × 1·2·2, CogVideoX
    3072 × 6·4·8² × 2·2."""
    assert counts[WAN]["camera"] == 3072 * (6 * 4 * 16 ** 2) * (1 * 2 * 2) == 75_497_472
    assert counts[COG]["camera"] == 3072 * (6 * 4 * 8 ** 2) * (2 * 2) == 18_874_368


@pytest.mark.parametrize("name", [WAN, COG])
def test_meta_backbone_allocates_nothing_and_keeps_the_config(name):
    config = backbone_config(name)
    nets = meta_backbone(name)
    assert set(nets) == set(COMPONENTS)
    for component, net in nets.items():
        assert all(t.device.type == "meta" for t in (*net.parameters(), *net.buffers())), component
    text = nets["text_encoder"].config  # transformers keeps every key; the shapes must be the file's
    assert {k: getattr(text, k) for k in TEXT_SHAPE} == {k: config["text_encoder"][k] for k in TEXT_SHAPE}
    for component in ("transformer", "vae"):  # diffusers drops unknown keys: a misspelt one would pass unnoticed
        built = {k: list(v) if isinstance(v, tuple) else v for k, v in nets[component].config.items()}
        values = {k: v for k, v in config[component].items() if k != "_class_name"}
        assert set(values) - set(built) <= {"clip_output"}, component  # in Wan2.2's Hub VAE file; diffusers ignores it
        assert {k: built[k] for k in values if k in built} == {k: v for k, v in values.items() if k in built}


def test_configs_fit_our_backbones():
    """What models/backbones needs of the real configurations: the backbone classes accept them (channels, VAE
    factors, v-prediction), the latent formats are 48/4/16 and 16/4/8, the released resolutions divide into
    patches, the schedulers give valid σ grids and the text widths match."""
    wan = meta_model(WAN)
    assert wan.backbone.kind == "wan2.2-ti2v" and wan.backbone.latent == LatentFormat(48, 4, 16)
    assert isinstance(wan.backbone.camera_conv, CameraPatchConv)
    assert wan.config == BackboneModelConfig.for_backbone("wan2.2-ti2v", LatentFormat(48, 4, 16))
    t = wan.backbone.transformer.config
    assert tuple(t.patch_size) == (1, 2, 2) and t.text_dim == wan.backbone.text_encoder.config.d_model
    assert wan.backbone.shift == 5.0  # Wan2.2 wan/configs/wan_ti2v_5B.py: sample_shift 5.0
    assert wan.backbone.sigmas(50).shape == (51,)

    cog = meta_model(COG)
    assert cog.backbone.kind == "cogvideox-i2v" and cog.backbone.latent == LatentFormat(16, 4, 8)
    assert cog.config == BackboneModelConfig.for_backbone("cogvideox-i2v", LatentFormat(16, 4, 8))
    t = cog.backbone.transformer.config
    s, released = cog.backbone.latent.spatial_factor, DEFAULTS["cogvideox-i2v"]
    assert (t.sample_height * s, t.sample_width * s, t.sample_frames) == (
        released["height"], released["width"], released["num_frames"])
    assert t.text_embed_dim == cog.backbone.text_encoder.config.d_model and cog.backbone.max_sequence_length == 226
    assert cog.backbone.sigmas(50)[0] == 1.0

    for model in (wan, cog):
        c, v = model.config, model.config.vae
        unit = v.spatial_factor * 2  # the transformers' 2×2 patches
        assert c.height % unit == 0 and c.width % unit == 0
        assert v.num_frames(v.num_latent_frames(c.num_frames)) == c.num_frames
        assert c.ldrm.latent_channels == v.latent_channels and c.ldrm.vae_spatial == v.spatial_factor
        assert all(p.device.type == "meta" for p in model.parameters())
        assert torch.device("meta") == next(model.backbone.transformer.parameters()).device
