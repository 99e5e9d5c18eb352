"""Shared fixtures (devices, session-scoped checkpoints); plain helpers live in tests/helpers.py."""
import importlib
import os
import shutil
import signal

import pytest
import torch
from helpers import tiny_model

from diff4splat.render.rasterize import NO_GSPLAT_ENV, gsplat_available

CUDA = torch.cuda.is_available()
DEVICES = [pytest.param("cpu", id="cpu"),
           pytest.param("cuda", id="cuda", marks=pytest.mark.cuda)]
"""The ``device`` fixture's values: the CPU always, CUDA where torch sees a GPU (skipped elsewhere)."""


DIFFUSERS_TESTS = ("test_backbone_*.py", "test_training_backbone.py")
"""The pretrained-backbone tests: every test in them is ``slow`` (module ``pytestmark``), because importing diffusers
and transformers alone takes ~8 s on 2 cores; the fast loop does not even collect them."""


def pytest_configure(config):
    """SIGINT is Python's KeyboardInterrupt in this process, so in the processes the tests start: a suite started in
    the background by a non-interactive shell (``nohup .ci/run &``) inherits SIGINT ignored and passes that on, and
    the tests that interrupt a command (Ctrl-C, a session's deadline) then wait on a child that never stops."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_ignore_collect(collection_path, config):
    """``-m "not slow"`` skips collecting :data:`DIFFUSERS_TESTS` (their imports would cost the fast loop ~8 s)."""
    if "not slow" in (config.getoption("markexpr") or "") and any(collection_path.match(p) for p in DIFFUSERS_TESTS):
        return True
    return None


def pytest_collection_modifyitems(config, items):
    """Tests marked ``cuda`` (the ``device`` fixture's CUDA case included) skip cleanly without a GPU;
    ``python -m pytest -m cuda`` runs only them."""
    if CUDA:
        return
    skip = pytest.mark.skip(reason="needs CUDA (torch.cuda.is_available() is False)")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(params=DEVICES)
def device(request):
    """The device a test runs on: ``cpu``, and ``cuda`` on a machine with a GPU (docs/DESIGN.md "Devices")."""
    return torch.device(request.param)


@pytest.fixture
def no_implicit_device():
    """For the test's body, tensors created without ``device=`` land on the ``meta`` device: code that makes a
    tensor on the default device beside CPU inputs then fails (mixed devices, or a meta value read) on a
    CPU-only machine, as it would beside CUDA inputs on a GPU. Build models and inputs before using it."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


@pytest.fixture
def full_float32():
    """TF32 off for the body (cuDNN convolutions default to TF32 on Ampere and later: 10-bit mantissas, results
    off by ~5e-4), so a CUDA run is compared with the CPU's float32 arithmetic."""
    flags = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags


@pytest.fixture
def cpu_tile_path(monkeypatch):
    """For the test's body, CPU tensors render through the PyTorch tile path (as CUDA without gsplat does), not
    numba's fused one: a CPU run then follows a simulated CUDA run's code path (tests/simulated_cuda.py)."""
    rasterize_module = importlib.import_module("diff4splat.render.rasterize")  # the package exports a function
    monkeypatch.setattr(rasterize_module, "DEFAULT_COMPOSITOR", rasterize_module.DEVICE_COMPOSITOR)  # so named


@pytest.fixture
def torch_tile_path(monkeypatch):
    """For the test's body, CUDA tensors render through our PyTorch tile path even where gsplat is installed
    (``DIFF4SPLAT_NO_GSPLAT``): a CPU/CUDA comparison then compares the same arithmetic, not two rasterizers."""
    monkeypatch.setenv(NO_GSPLAT_ENV, "1")
    gsplat_available.cache_clear()
    yield
    monkeypatch.undo()
    gsplat_available.cache_clear()


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


CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
"""Software WebGL (SwiftShader) in headless Chromium: no GPU needed."""


def _chromium_path():
    return os.environ.get("DIFF4SPLAT_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="session")
def browser():
    """Headless system Chromium driven by Playwright (Playwright's own browser download is not used). Skips,
    saying how to install it, where Chromium or Playwright is missing; .ci/run installs both."""
    path = _chromium_path()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("browser tests need Playwright: pip install -e '.[test]' (and apt-get install chromium)")
    if path is None:
        pytest.skip("browser tests need Chromium: apt-get install chromium (or set DIFF4SPLAT_CHROMIUM to its path)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=path, args=CHROMIUM_FLAGS)
        yield b
        b.close()


@pytest.fixture(params=["fused", "torch"])
def each_compositor(request, monkeypatch):
    """Run a renderer test once per CPU compositor (diff4splat.render.rasterize.COMPOSITORS): the fused JIT
    path and the pure-PyTorch reference, which must give the same results."""
    module = importlib.import_module("diff4splat.render.rasterize")  # the package exports a function of that name
    monkeypatch.setattr(module, "DEFAULT_COMPOSITOR", request.param)
    return request.param
