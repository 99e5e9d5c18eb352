"""Shared fixtures (session-scoped checkpoints); plain helpers live in tests/helpers.py."""
import pytest
import torch
from helpers import tiny_model


@pytest.fixture(scope="module")
def one_thread():
    """torch on one thread for a module of tiny tensors: threads only add overhead on a busy 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def dynamic_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "dynamic"
    tiny_model(seed=0, dynamic=True).save_pretrained(path)
    return path
