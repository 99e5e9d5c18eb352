"""The CPU's bfloat16 matmul check (diff4splat.utils.devices.bf16_nan_leaks, oneDNN#5717) and the warning that trainers
and runtimes computing in bfloat16 on such a CPU give."""
import warnings

import pytest
import torch
from _trainer_toy import ToyData, ToyModel, toy_step
from helpers import tiny_model

from diff4splat.runtime import TorchRuntime
from diff4splat.utils import devices
from diff4splat.utils.devices import bf16_nan_leaks, cpu_bf16_warning
from training.trainer import Trainer, TrainerConfig


def _row_sum_mm(a, b):
    """A product that mixes rows, as the AMX kernel's over-read does: every row gets the sum of all of a's rows."""
    return torch.mm(a, b) + a.float().sum()


def test_the_check_tells_a_product_that_mixes_rows_from_one_that_does_not():
    exact = {"mm": lambda a, b: (a.double() @ b.double()), "bmm": lambda a, b: (a.double() @ b.double())}
    assert bf16_nan_leaks(**exact) == {"bmm": False, "mm": False}
    assert bf16_nan_leaks(mm=_row_sum_mm, bmm=exact["bmm"]) == {"bmm": False, "mm": True}
    assert bf16_nan_leaks(mm=exact["mm"], bmm=lambda a, b: torch.bmm(a, b) + a.float().sum()) == {"bmm": True,
                                                                                               "mm": False}
    # torch's own products: whatever this CPU does, a bool per product (True on the AMX Xeon hosts of torch 2.11)
    assert set(bf16_nan_leaks()) == {"bmm", "mm"}


@pytest.fixture
def leaking_cpu(monkeypatch):
    """This process's check says the CPU leaks (the cached answer is recomputed before and after)."""
    cpu_bf16_warning.cache_clear()
    monkeypatch.setattr(devices, "bf16_nan_leaks", lambda: {"bmm": False, "mm": True})
    yield
    cpu_bf16_warning.cache_clear()


def test_the_warning_names_the_bug_and_the_remedy(leaking_cpu):
    message = cpu_bf16_warning()
    assert "bfloat16 mm lets NaN" in message and "oneDNN#5717" in message
    assert "ONEDNN_MAX_CPU_ISA=AVX512_CORE_BF16" in message


def _trainer_warnings(tmp_path, **kw) -> list[str]:
    cfg = TrainerConfig(run_dir=str(tmp_path), total_steps=1, batch_size=2, progress=False, **kw)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Trainer(ToyModel(), ToyData(), toy_step, cfg, device="cpu")
    return [str(w.message) for w in caught if "oneDNN#5717" in str(w.message)]


def test_a_bf16_trainer_on_such_a_cpu_warns_and_a_float32_one_does_not(leaking_cpu, tmp_path):
    assert len(_trainer_warnings(tmp_path / "a", bf16=True)) == 1
    assert _trainer_warnings(tmp_path / "b", bf16=False) == []
    assert _trainer_warnings(tmp_path / "c") == []  # auto: float32 on the CPU


def test_a_bf16_runtime_on_such_a_cpu_warns_and_a_float32_one_does_not(leaking_cpu):
    for dtype, expected in ((torch.bfloat16, 1), (torch.float32, 0), (None, 0)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            TorchRuntime(tiny_model(), "cpu", dtype=dtype)
        assert sum("oneDNN#5717" in str(w.message) for w in caught) == expected, dtype


def test_no_warning_where_the_cpu_does_not_leak(monkeypatch, tmp_path):
    cpu_bf16_warning.cache_clear()
    monkeypatch.setattr(devices, "bf16_nan_leaks", lambda: {"bmm": False, "mm": False})
    try:
        assert cpu_bf16_warning() is None and _trainer_warnings(tmp_path, bf16=True) == []
    finally:
        cpu_bf16_warning.cache_clear()
