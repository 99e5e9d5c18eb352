"""Shared fixtures (session-scoped checkpoints); plain helpers live in tests/helpers.py."""
import pytest
from helpers import tiny_model


@pytest.fixture(scope="session")
def dynamic_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "dynamic"
    tiny_model(seed=0, dynamic=True).save_pretrained(path)
    return path
