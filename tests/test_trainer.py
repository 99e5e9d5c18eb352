"""Tests of training/trainer.py on the toy problem (tests/_trainer_toy.py): schedule, exact resume after a signal
or a kill, non-finite steps, EMA, bf16, devices (the ``device`` fixture: the CPU, and CUDA where present, always
passed explicitly), TF32 flags, gradient checkpointing, and two-process DDP/FSDP runs on gloo."""
import csv
import math
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from _trainer_toy import ToyData, ToyModel, run_two_ranks, toy_step
from torch import nn

from training.checkpoint import latest_checkpoint, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from training.placement import resolve_bf16, training_device
from training.trainer import NonFiniteLossError, Trainer, TrainerConfig, warmup_cosine

TESTS = Path(__file__).resolve().parent


def _tf32_flags():
    return torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32


def _set_tf32_flags(matmul, cudnn):
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


@pytest.fixture(autouse=True)
def _restore_tf32_flags():
    """A trainer on CUDA sets the process-wide TF32 flags: the tests after this one see them as they were."""
    flags = _tf32_flags()
    yield
    _set_tf32_flags(*flags)


def _cfg(run_dir, **kw):
    base = dict(run_dir=str(run_dir), total_steps=12, batch_size=4, lr=1e-2, warmup_steps=3, checkpoint_every=4,
                progress=False, seed=7, ema_decay=0.9)
    base.update(kw)
    return TrainerConfig(**base)


def _trainer(run_dir, device, data=None, model=None, **kw):
    """A toy trainer on ``device`` (explicit: the CPU case is the CPU on a GPU machine too)."""
    torch.manual_seed(0)
    return Trainer(model or ToyModel(), data or ToyData(), toy_step, _cfg(run_dir, **kw), device=device)


def _losses(run_dir):
    rows = list(csv.DictReader(open(Path(run_dir) / "metrics.csv")))
    return {int(r["step"]): float(r["loss"]) for r in rows if r["skipped"] == "0"}


def test_warmup_cosine_closed_form():
    assert warmup_cosine(0, 4, 20, 0.1) == pytest.approx(0.25)
    assert warmup_cosine(3, 4, 20, 0.1) == pytest.approx(1.0)
    assert warmup_cosine(12, 4, 20, 0.1) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert warmup_cosine(20, 4, 20, 0.1) == pytest.approx(0.1)


@pytest.mark.slow
def test_training_reduces_the_loss_and_never_touches_frozen_weights(tmp_path, device):
    t = _trainer(tmp_path, device, total_steps=40, checkpoint_every=40, ema_decay=None, lr=5e-2)
    frozen = t.module.frozen.weight.clone()
    t.fit()
    losses = _losses(tmp_path)
    assert losses[40] < 0.5 * losses[1]
    assert torch.equal(t.module.frozen.weight, frozen)


def _run_stopped_by_sigterm(run_dir, device, at: int = 6) -> dict:
    """The toy run to ``run_dir``, sent SIGTERM during its ``at``-th step: it finishes that step, saves, returns."""
    calls = {"n": 0}

    def stopping_step(model, batch, gen):
        calls["n"] += 1
        if calls["n"] == at:
            os.kill(os.getpid(), signal.SIGTERM)
        return toy_step(model, batch, gen)

    torch.manual_seed(0)
    return Trainer(ToyModel(), ToyData(), stopping_step, _cfg(run_dir), device=device).fit()


def test_signal_stop_then_resume_matches_uninterrupted_run_exactly(tmp_path, device):
    ref = _trainer(tmp_path / "ref", device)
    ref.fit()
    out = _run_stopped_by_sigterm(tmp_path / "run", device)
    assert out["stopped"] and out["step"] == 6
    b = _trainer(tmp_path / "run", device)
    b.fit(resume=True)
    assert _losses(tmp_path / "run") == _losses(tmp_path / "ref")  # step for step, bit for bit
    for (k, v), (_, w) in zip(ref.module.state_dict().items(), b.module.state_dict().items(), strict=True):
        assert torch.equal(v, w), k
    assert all(torch.equal(ref.ema[k], b.ema[k]) for k in ref.ema)


def test_a_process_group_of_one_resumes_exactly(tmp_path):
    """``torchrun --nproc_per_node 1`` (a gloo group of one here): the run is distributed (DDP), and a stop and
    resume gives the uninterrupted run's losses bit for bit, as without a group (rank 0's step generator is the
    checkpoint's; only with several ranks, whose streams it does not hold, are they reseeded)."""
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        ref = _trainer(tmp_path / "ref", "cpu")
        assert ref.distributed and isinstance(ref.model, nn.parallel.DistributedDataParallel)
        ref.fit()
        assert _run_stopped_by_sigterm(tmp_path / "run", "cpu")["step"] == 6
        b = _trainer(tmp_path / "run", "cpu")
        b.fit(resume=True)
    finally:
        dist.destroy_process_group()
    assert _losses(tmp_path / "run") == _losses(tmp_path / "ref")


@pytest.mark.slow
@pytest.mark.real_gpu  # a child process, outside the simulation
def test_hard_kill_then_resume_from_last_checkpoint_matches(tmp_path, device):
    ref = _trainer(tmp_path / "ref", device)
    ref.fit()
    run = tmp_path / "run"
    script = textwrap.dedent(f"""
        import os, signal, sys, torch
        sys.path.insert(0, {str(TESTS)!r})
        from _trainer_toy import ToyData, ToyModel, run_two_ranks, toy_step
        from training.trainer import Trainer, TrainerConfig
        n = 0
        def step(model, batch, gen):
            global n
            n += 1
            if n == 7:
                os.kill(os.getpid(), signal.SIGKILL)  # no chance to save
            return toy_step(model, batch, gen)
        torch.manual_seed(0)
        cfg = TrainerConfig(run_dir={str(run)!r}, total_steps=12, batch_size=4, lr=1e-2, warmup_steps=3,
                            checkpoint_every=4, progress=False, seed=7, ema_decay=0.9)
        Trainer(ToyModel(), ToyData(), step, cfg, device={str(device)!r}).fit()
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert latest_checkpoint(run).name == "step_00000004"
    b = _trainer(run, device)
    b.fit(resume=True)
    assert _losses(run) == _losses(tmp_path / "ref")  # rows after the restored checkpoint were dropped, then redone
    steps = [int(r["step"]) for r in csv.DictReader(open(run / "metrics.csv"))]
    assert steps == list(range(1, 13))
    ref_state, b_state = ref.module.state_dict(), b.module.state_dict()
    assert all(torch.equal(v, w) for v, w in zip(ref_state.values(), b_state.values(), strict=True))


def test_nan_batch_skips_the_step_and_is_logged(tmp_path, capsys, device):
    data = ToyData(nan_at=range(32))
    clean = ToyData()
    t = _trainer(tmp_path, device, data=clean, total_steps=6, checkpoint_every=100)
    # poison exactly one batch: the second batch of epoch 0
    order = t._epoch_batches()
    data.nan_at = set(order[1])
    t.dataset = data
    t.fit()
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [r["skipped"] for r in rows].count("1") == 1
    skipped = next(r for r in rows if r["skipped"] == "1")
    assert math.isnan(float(skipped["loss"])) and math.isnan(float(skipped["mae"]))  # every term is logged
    assert t.step == 6 and all(torch.isfinite(p).all() for p in t.module.parameters())
    # the message names the terms that were not finite
    assert "train: non-finite loss (mae nan) at step 1 (epoch 0, batch 1); step skipped" in capsys.readouterr().err


def test_a_nonfinite_gradient_skips_the_step_and_says_so(tmp_path, capsys, device):
    """A finite loss whose gradient is not (its first backward returns inf, as an overflow would): the step is
    skipped and logged with its finite loss, and its message says gradient, not loss."""
    calls = []

    class InfGradientOnce(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, grad):
            calls.append(1)
            return grad * math.inf if len(calls) == 1 else grad

    def step(model, batch, generator):
        losses = toy_step(model, batch, generator)
        return {**losses, "loss": InfGradientOnce.apply(losses["loss"])}

    t = _trainer(tmp_path, device, total_steps=3, checkpoint_every=100)
    t.step_fn = step
    t.fit()
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    skipped = [r for r in rows if r["skipped"] == "1"]
    assert len(skipped) == 1 and math.isfinite(float(skipped[0]["loss"])) and t.step == 3
    assert "train: non-finite gradient (norm " in capsys.readouterr().err


def test_k_nonfinite_in_a_row_stops_and_keeps_last_good_checkpoint(tmp_path, device):
    t = _trainer(tmp_path, device, total_steps=100, checkpoint_every=2, max_nonfinite=3)
    order = t._epoch_batches()
    t.dataset = ToyData(nan_at=[i for b in order[4:] for i in b])  # batches 4.. are poisoned
    with pytest.raises(NonFiniteLossError, match="3 consecutive"):
        t.fit()
    folder = latest_checkpoint(tmp_path)
    assert folder.name == "step_00000004"
    model_state, state, _ = load_checkpoint(folder)
    assert state["step"] == 4 and all(torch.isfinite(v).all() for v in model_state.values())


def test_ema_follows_its_recursion(tmp_path, device):
    t = _trainer(tmp_path, device, total_steps=1, checkpoint_every=100, ema_decay=0.5)
    before = {n: p.detach().clone() for n, p in t.module.named_parameters() if p.requires_grad}
    t.fit()
    for n, p in t.module.named_parameters():
        if p.requires_grad:
            torch.testing.assert_close(t.ema[n], 0.5 * before[n] + 0.5 * p.detach())
    assert "frozen.weight" not in t.ema


def test_bf16_autocast_trains(tmp_path, device):
    t = _trainer(tmp_path, device, total_steps=3, checkpoint_every=100, bf16=True)
    assert t.bf16 is True
    t.fit()
    assert all(math.isfinite(v) for v in _losses(tmp_path).values())
    assert all(p.dtype == torch.float32 for p in t.module.parameters())  # autocast: float32 weights, EMA, state
    assert all(v.dtype == torch.float32 for v in t.ema.values())


def test_bf16_auto_is_on_for_cuda_and_off_for_the_cpu():
    assert TrainerConfig().bf16 is None and TrainerConfig(bf16="auto").bf16 is None  # the default: auto
    assert resolve_bf16(None, "cpu") is False and resolve_bf16(None, torch.device("cpu")) is False
    assert resolve_bf16(None, "cuda") is True and resolve_bf16(None, torch.device("cuda", 1)) is True
    assert resolve_bf16(True, "cpu") is True and resolve_bf16(False, "cuda:0") is False  # a setting wins
    with pytest.raises(ValueError, match="trainer.bf16"):
        TrainerConfig(bf16="yes")


def test_cpu_trainer_trains_in_float32_with_pageable_batches_and_leaves_tf32_alone(tmp_path):
    for tf32 in (True, False):
        _set_tf32_flags(not tf32, not tf32)  # what a CUDA trainer would overwrite
        t = _trainer(tmp_path / str(tf32), "cpu", tf32=tf32)
        assert _tf32_flags() == (not tf32, not tf32)
    assert t.device == torch.device("cpu") and t.bf16 is False
    loader = t._loader(t._epoch_batches())
    assert loader.pin_memory is False
    batch = t._to_device(next(iter(loader)))
    assert batch["x"].device.type == "cpu" and batch["x"].shape == (4, 8)


@pytest.mark.cuda
def test_cuda_trainer_sets_tf32_autocasts_and_pins_batches(tmp_path):
    for tf32 in (True, False):
        _set_tf32_flags(not tf32, not tf32)
        t = _trainer(tmp_path / str(tf32), "cuda", tf32=tf32)
        assert _tf32_flags() == (tf32, tf32)
    assert t.device == torch.device("cuda", torch.cuda.current_device()) and t.bf16 is True  # auto: on for CUDA
    loader = t._loader(t._epoch_batches())
    assert loader.pin_memory is True
    batch = t._to_device(next(iter(loader)))
    assert batch["x"].device == t.device and torch.isfinite(batch["x"]).all()
    assert all(p.device == t.device for p in t.module.parameters())


@pytest.mark.cuda
def test_cuda_gives_the_cpu_losses_in_float32(tmp_path):
    """bf16 and TF32 off, no dropout (it draws from each device's own RNG): the toy run's losses on CUDA are the
    CPU's to float32 rounding, the step generator's noise being the same numbers on both devices."""
    losses = {}
    for device in ("cpu", "cuda"):
        torch.manual_seed(0)
        model = ToyModel(dropout=0.0)
        _trainer(tmp_path / device, device, model=model, total_steps=3, checkpoint_every=100, bf16=False,
                 tf32=False).fit()
        losses[device] = _losses(tmp_path / device)
    assert sorted(losses["cuda"]) == sorted(losses["cpu"]) == [1, 2, 3]
    for step, loss in losses["cpu"].items():
        assert losses["cuda"][step] == pytest.approx(loss, rel=1e-4, abs=1e-7), step


def test_a_checkpoint_from_a_node_with_more_gpus_restores_the_gpus_there_are(monkeypatch):
    """Resuming on a machine with fewer GPUs than the one that saved: each present GPU gets its saved state, the
    others' states are left out (``set_rng_state_all`` indexed GPUs that are not there)."""
    restored, state = {}, rng_state()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "set_rng_state", lambda s, device="cuda": restored.__setitem__(device, s))
    saved = [torch.full((8,), i, dtype=torch.uint8) for i in range(8)]  # the states of 8 GPUs
    set_rng_state({**state, "cuda": saved})
    assert sorted(restored) == [0, 1] and all(torch.equal(restored[i], saved[i]) for i in (0, 1))


@pytest.mark.cuda
def test_a_checkpoint_from_a_node_with_more_gpus_resumes_here():
    """The real CUDA generators: the saved state of GPU 0 is restored, the extra GPUs' states raise nothing."""
    first = torch.cuda.get_rng_state(0)
    torch.cuda.manual_seed_all(123)
    set_rng_state({**rng_state(), "cuda": [first] * (torch.cuda.device_count() + 3)})
    assert torch.equal(torch.cuda.get_rng_state(0), first)


def test_device_comes_from_the_config_unless_given(tmp_path, monkeypatch):
    """trainer.device decides the device, checked with one ValueError naming it; an explicit device= wins."""
    torch.manual_seed(0)
    t = Trainer(ToyModel(), ToyData(), toy_step, _cfg(tmp_path, device="cpu"))
    assert t.device == torch.device("cpu")
    with pytest.raises(ValueError, match="trainer.device: cuda:99 is not available"):
        Trainer(ToyModel(), ToyData(), toy_step, _cfg(tmp_path, device="cuda:99"))
    with pytest.raises(ValueError, match="trainer.device: 'gpu' is not a torch device"):
        Trainer(ToyModel(), ToyData(), toy_step, _cfg(tmp_path, device="gpu"))
    t = Trainer(ToyModel(), ToyData(), toy_step, _cfg(tmp_path, device="cuda:99"), device="cpu")
    assert t.device == torch.device("cpu")
    with pytest.raises(ValueError, match="device: cuda:99 is not available"):
        Trainer(ToyModel(), ToyData(), toy_step, _cfg(tmp_path, device="cpu"), device="cuda:99")
    with pytest.raises(ValueError, match="trainer.device"):
        TrainerConfig(device=3)
    assert TrainerConfig(device=torch.device("cpu")).device == "cpu"
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert training_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        assert training_device("auto") == torch.device("cpu")  # no GPU: the CPU, whatever the local rank


@pytest.mark.cuda
def test_auto_device_under_torchrun_is_the_local_rank_gpu(monkeypatch):
    monkeypatch.setenv("LOCAL_RANK", "0")
    assert training_device("auto") == torch.device("cuda", 0) and training_device("cuda") == torch.device("cuda", 0)
    monkeypatch.setenv("LOCAL_RANK", str(torch.cuda.device_count()))  # one rank more than the GPUs
    with pytest.raises(ValueError, match="trainer.device: cuda:"):
        training_device("auto")


def test_gradient_checkpointing_switch_reaches_the_modules_that_support_it(tmp_path):
    model = ToyModel()
    model.net.gradient_checkpointing = False  # as models.dit.VideoDiT declares it
    _trainer(tmp_path, "cpu", model=model)
    assert model.net.gradient_checkpointing is False  # off by default
    t = _trainer(tmp_path, "cpu", model=model, gradient_checkpointing=True)
    assert model.net.gradient_checkpointing is True and t.module is model
    with pytest.raises(ValueError, match="gradient_checkpointing: no module"):
        _trainer(tmp_path, "cpu", gradient_checkpointing=True)  # the plain ToyModel has no such module


def test_bad_config_raises():
    with pytest.raises(ValueError, match="strategy"):
        TrainerConfig(strategy="horovod")
    with pytest.raises(ValueError, match="total_steps"):
        TrainerConfig(total_steps=0)
    # each trained without complaint: grad_clip −1 turned clipping off
    for field, value in (("grad_clip", -1.0), ("warmup_steps", -2), ("weight_decay", -0.1), ("min_lr_ratio", 1.5)):
        with pytest.raises(ValueError, match=f"trainer.{field} must"):
            TrainerConfig(**{field: value})


def test_metrics_csv_logs_the_learning_rate_each_step_used(tmp_path):
    """The lr column was read after scheduler.step(): the next step's rate, one step late."""
    t = _trainer(tmp_path, "cpu", total_steps=6, warmup_steps=3, checkpoint_every=100, min_lr_ratio=0.1)
    t.fit()
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    want = [1e-2 * warmup_cosine(i, 3, 6, 0.1) for i in range(6)]  # step k (1-based) ran with the multiplier at k − 1
    assert [float(r["lr"]) for r in rows] == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("strategy, bf16", [("ddp", False), ("fsdp", False), ("fsdp", True)])
@pytest.mark.slow
def test_two_process_distributed_run_keeps_ranks_identical(tmp_path, strategy, bf16):
    """Two gloo ranks on the CPU: DDP keeps the ranks' weights identical; FSDP2 shards the model's fsdp_units
    (ToyModel: its two Linear layers) one by one before the root, with bfloat16 weights inside those units only
    when bf16 is on (the root's frozen layer stays float32), gathers full weights and EMA for the checkpoint and
    the final weights, and resumes from its checkpoint."""
    script = textwrap.dedent(f"""
        import os, sys, torch, torch.distributed as dist
        sys.path.insert(0, {str(TESTS)!r})
        from torch.distributed.fsdp import FSDPModule
        from _trainer_toy import ToyData, ToyModel, toy_step
        from training.trainer import Trainer, TrainerConfig
        strategy, bf16 = {strategy!r}, {bf16!r}
        torch.manual_seed(0)
        cfg = dict(run_dir={str(tmp_path / 'run')!r}, total_steps=4, batch_size=4, lr=1e-2, warmup_steps=1,
                   checkpoint_every=100, progress=False, seed=3, strategy=strategy, device="cpu", bf16=bf16,
                   ema_decay=0.9)
        t = Trainer(ToyModel(), ToyData(), toy_step, TrainerConfig(**cfg))
        net = t.module.net
        assert all(isinstance(m, FSDPModule) == (strategy == "fsdp") for m in (t.module, net[0], net[3]))
        seen = {{}}
        def record(name):  # the dtype of a layer's weight while it runs (FSDP's own hook runs first)
            return lambda m, args: None if seen.setdefault(name, m.weight.dtype) else None
        net[3].register_forward_pre_hook(record("unit"))
        t.module.frozen.register_forward_pre_hook(record("root"))
        t.fit()
        if strategy == "fsdp":
            assert seen == {{"unit": torch.bfloat16 if bf16 else torch.float32, "root": torch.float32}}, seen
        state, ema = t._model_state(), t.ema_state_dict()  # collective under FSDP
        rank = dist.get_rank()
        if rank == 0 or strategy == "ddp":
            torch.save((state, ema), {str(tmp_path)!r} + f"/rank{{rank}}.pt")
        t2 = Trainer(ToyModel(), ToyData(), toy_step, TrainerConfig(**{{**cfg, "total_steps": 6}}))
        t2.fit(resume=True)
        assert t2.step == 6
        dist.destroy_process_group()
    """)
    run_two_ranks(script, fresh=(tmp_path / "run",))
    r0, ema0 = torch.load(tmp_path / "rank0.pt")
    if strategy == "ddp":
        r1, ema1 = torch.load(tmp_path / "rank1.pt")
        assert all(torch.equal(r0[k], r1[k]) for k in r0) and all(torch.equal(ema0[k], ema1[k]) for k in ema0)
    full = ToyModel().state_dict()
    assert {k: v.shape for k, v in r0.items()} == {k: v.shape for k, v in full.items()}  # whole tensors
    assert {k: v.shape for k, v in ema0.items()} == {k: v.shape for k, v in full.items()}
    assert not torch.equal(ema0["net.0.weight"], r0["net.0.weight"])  # the EMA, not the weights
    assert all(torch.isfinite(v).all() for v in [*r0.values(), *ema0.values()])
    assert latest_checkpoint(tmp_path / "run").name == "step_00000006"
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert [int(r["step"]) for r in rows] == list(range(1, 7))
    _, _, saved_ema = load_checkpoint(tmp_path / "run" / "checkpoints" / "step_00000006")
    assert {k: v.shape for k, v in saved_ema.items()} == {k: v.shape for k, v in full.items() if "frozen" not in k}


def test_run_two_ranks_repeats_an_aborted_run_from_a_fresh_run_folder(tmp_path):
    """A rank torn down by Gloo's exit race (SIGABRT, "terminate called …", no traceback) is run again, and the run
    folder named ``fresh`` is removed first: the repeat must not find the first attempt's files (in CI a repeated
    run appended its metrics to the first attempt's)."""
    run, marker = tmp_path / "run", tmp_path / "aborted"
    script = textwrap.dedent(f"""
        import os, pathlib, sys
        run, marker = pathlib.Path({str(run)!r}), pathlib.Path({str(marker)!r})
        rank = os.environ["RANK"]
        assert not (run / f"rank{{rank}}").exists(), "the first attempt's files are still there"
        run.mkdir(exist_ok=True)
        (run / f"rank{{rank}}").touch()
        if rank == "0" and not marker.exists():  # the first attempt: die as Gloo's teardown does
            marker.touch()
            sys.stderr.write("terminate called without an active exception\\n")
            sys.stderr.flush()
            os.abort()
    """)
    run_two_ranks(script, fresh=(run,))
    assert marker.exists() and (run / "rank0").exists()  # aborted once, then run again to the end


class _RunsCode:
    """Unpickling this calls a function: what a crafted state.pt could do with weights_only=False."""

    def __reduce__(self):
        return (os.getcwd, ())


def test_a_checkpoint_state_is_never_unpickled_beyond_tensors_and_plain_values(tmp_path):
    folder = save_checkpoint(tmp_path, 1, {"w": torch.zeros(2)}, {"rng": rng_state(), "step": 1}, {})
    model_state, state, _ = load_checkpoint(folder)  # numpy's RNG state (an ndarray) is allowed
    assert state["step"] == 1 and state["rng"]["numpy"][0] == "MT19937"
    torch.save({"step": 1, "payload": _RunsCode()}, folder / "state.pt")
    with pytest.raises(ValueError, match=r"state.pt holds objects other than tensors and plain values"):
        load_checkpoint(folder)
