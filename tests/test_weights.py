"""The shipped default model (models/weights/tiny): loads, matches the tiny config, and is trained."""
import warnings

import pytest
from helpers import EXAMPLE_IMAGE

from diff4splat.pipeline import Diff4SplatPipeline, load_model
from models.bundle import WEIGHTS_DIR, Diff4SplatModel, load_config


def test_shipped_weights_load_without_warning_and_match_the_tiny_config():
    assert (WEIGHTS_DIR / "tiny" / "MODEL_CARD.md").is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the random-model fallback would warn
        model, source = load_model()
    assert source.endswith("models/weights/tiny")
    # the architecture is the tiny config; only the VAE's latent scaling was calibrated after its stage
    tiny = load_config("tiny")
    assert (tiny.vae.scaling_factor, tiny.vae.shift_factor) == (1.0, 0.0)
    assert model.config.vae.scaling_factor != 1.0
    tiny.vae.scaling_factor, tiny.vae.shift_factor = model.config.vae.scaling_factor, model.config.vae.shift_factor
    assert model.config == tiny


@pytest.mark.slow
def test_trained_model_reproduces_the_photograph_better_than_the_untrained_one():
    """Model card: 19.32 dB trained vs 15.71 dB untrained (input camera, t = 0, examples/chelsea.png)."""
    from training.evaluate import photo_psnr

    trained = photo_psnr(Diff4SplatPipeline.from_pretrained(), EXAMPLE_IMAGE, "a cat turns its head")
    untrained = photo_psnr(Diff4SplatPipeline(Diff4SplatModel.random(load_config("tiny"), seed=0)), EXAMPLE_IMAGE,
                           "a cat turns its head")
    assert trained == pytest.approx(19.32, abs=0.05) and untrained == pytest.approx(15.71, abs=0.05)
    assert trained > untrained + 3.0
