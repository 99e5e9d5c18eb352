"""The shipped default model (models/weights/base): loads, matches the base config, and is trained."""
import warnings

import pytest
from helpers import EXAMPLE_IMAGE

from diff4splat.pipeline import Diff4SplatPipeline, load_model
from models.bundle import DEFAULT_CONFIG, WEIGHTS_DIR, Diff4SplatModel, load_config
from training.evaluate import photo_fidelity


def test_shipped_weights_load_without_warning_and_match_the_base_config():
    assert DEFAULT_CONFIG == "base"
    assert (WEIGHTS_DIR / "base" / "MODEL_CARD.md").is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the random-model fallback would warn
        model, source = load_model()
    assert source.endswith("models/weights/base")
    # the architecture is the base config; only the VAE's latent scaling was calibrated (in its own stage)
    base = load_config("base")
    assert (base.vae.scaling_factor, base.vae.shift_factor) == (1.0, 0.0)
    assert model.config.vae.scaling_factor != 1.0
    base.vae.scaling_factor, base.vae.shift_factor = model.config.vae.scaling_factor, model.config.vae.shift_factor
    assert model.config == base
    assert model.config.ldrm.gaussian_frames == "latent" and model.config.ldrm.image_branch > 0


@pytest.mark.slow
def test_the_photograph_is_kept_whatever_the_weights():
    """The photograph is observed, not generated: rendered from the input camera at t = 0 (the scene generated
    along the 360° orbit, as ``evaluate --photo`` does), the shipped model and an untrained one both give it back
    (the photo layer, and no generated Gaussian over it); the model card's figure is 93.8 dB."""
    trained = photo_fidelity(Diff4SplatPipeline.from_pretrained(), EXAMPLE_IMAGE, "a cat turns its head")
    untrained = photo_fidelity(Diff4SplatPipeline(Diff4SplatModel.random(load_config("base"), seed=0)),
                               EXAMPLE_IMAGE, "a cat turns its head", resolution=96)
    for fid in (trained, untrained):
        assert fid["photo_psnr"] >= 40.0 and fid["photo_psnr_model"] >= 40.0, fid
        assert fid["photo_thumbnail"] < 25.0 and fid["photo_thumbnail_model"] < 25.0, fid  # a weak baseline
