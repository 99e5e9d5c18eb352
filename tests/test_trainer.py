import csv
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest
import torch
from _trainer_toy import ToyData, ToyModel, toy_step

from training.checkpoint import latest_checkpoint, load_checkpoint
from training.trainer import NonFiniteLossError, Trainer, TrainerConfig, warmup_cosine

TESTS = Path(__file__).resolve().parent


def _cfg(run_dir, **kw):
    base = dict(run_dir=str(run_dir), total_steps=12, batch_size=4, lr=1e-2, warmup_steps=3, checkpoint_every=4,
                progress=False, seed=7, ema_decay=0.9)
    base.update(kw)
    return TrainerConfig(**base)


def _trainer(run_dir, data=None, **kw):
    torch.manual_seed(0)
    return Trainer(ToyModel(), data or ToyData(), toy_step, _cfg(run_dir, **kw))


def _losses(run_dir):
    rows = list(csv.DictReader(open(Path(run_dir) / "metrics.csv")))
    return {int(r["step"]): float(r["loss"]) for r in rows if r["skipped"] == "0"}


def test_warmup_cosine_closed_form():
    assert warmup_cosine(0, 4, 20, 0.1) == pytest.approx(0.25)
    assert warmup_cosine(3, 4, 20, 0.1) == pytest.approx(1.0)
    assert warmup_cosine(12, 4, 20, 0.1) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5)))
    assert warmup_cosine(20, 4, 20, 0.1) == pytest.approx(0.1)


@pytest.mark.slow
def test_training_reduces_the_loss_and_never_touches_frozen_weights(tmp_path):
    t = _trainer(tmp_path, total_steps=40, checkpoint_every=40, ema_decay=None, lr=5e-2)
    frozen = t.module.frozen.weight.clone()
    t.fit()
    losses = _losses(tmp_path)
    assert losses[40] < 0.5 * losses[1]
    assert torch.equal(t.module.frozen.weight, frozen)


def test_signal_stop_then_resume_matches_uninterrupted_run_exactly(tmp_path):
    ref = _trainer(tmp_path / "ref")
    ref.fit()
    calls = {"n": 0}

    def stopping_step(model, batch, gen):
        calls["n"] += 1
        if calls["n"] == 6:
            os.kill(os.getpid(), signal.SIGTERM)  # the trainer finishes this step, saves, returns
        return toy_step(model, batch, gen)

    torch.manual_seed(0)
    a = Trainer(ToyModel(), ToyData(), stopping_step, _cfg(tmp_path / "run"))
    out = a.fit()
    assert out["stopped"] and out["step"] == 6
    b = _trainer(tmp_path / "run")
    b.fit(resume=True)
    assert _losses(tmp_path / "run") == _losses(tmp_path / "ref")  # step for step, bit for bit
    for (k, v), (_, w) in zip(ref.module.state_dict().items(), b.module.state_dict().items(), strict=True):
        assert torch.equal(v, w), k
    assert all(torch.equal(ref.ema[k], b.ema[k]) for k in ref.ema)


@pytest.mark.slow
def test_hard_kill_then_resume_from_last_checkpoint_matches(tmp_path):
    ref = _trainer(tmp_path / "ref")
    ref.fit()
    run = tmp_path / "run"
    script = textwrap.dedent(f"""
        import os, signal, sys, torch
        sys.path.insert(0, {str(TESTS)!r})
        from _trainer_toy import ToyData, ToyModel, toy_step
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
        Trainer(ToyModel(), ToyData(), step, cfg).fit()
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert latest_checkpoint(run).name == "step_00000004"
    b = _trainer(run)
    b.fit(resume=True)
    assert _losses(run) == _losses(tmp_path / "ref")  # rows after the restored checkpoint were dropped, then redone
    steps = [int(r["step"]) for r in csv.DictReader(open(run / "metrics.csv"))]
    assert steps == list(range(1, 13))
    ref_state, b_state = ref.module.state_dict(), b.module.state_dict()
    assert all(torch.equal(v, w) for v, w in zip(ref_state.values(), b_state.values(), strict=True))


def test_nan_batch_skips_the_step_and_is_logged(tmp_path, capsys):
    data = ToyData(nan_at=range(32))
    clean = ToyData()
    t = _trainer(tmp_path, data=clean, total_steps=6, checkpoint_every=100)
    # poison exactly one batch: the second batch of epoch 0
    order = t._epoch_batches()
    data.nan_at = set(order[1])
    t.dataset = data
    t.fit()
    rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
    assert [r["skipped"] for r in rows].count("1") == 1
    assert t.step == 6 and all(torch.isfinite(p).all() for p in t.module.parameters())
    assert "non-finite" in capsys.readouterr().err


def test_k_nonfinite_in_a_row_stops_and_keeps_last_good_checkpoint(tmp_path):
    t = _trainer(tmp_path, total_steps=100, checkpoint_every=2, max_nonfinite=3)
    order = t._epoch_batches()
    t.dataset = ToyData(nan_at=[i for b in order[4:] for i in b])  # batches 4.. are poisoned
    with pytest.raises(NonFiniteLossError, match="3 consecutive"):
        t.fit()
    folder = latest_checkpoint(tmp_path)
    assert folder.name == "step_00000004"
    model_state, state, _ = load_checkpoint(folder)
    assert state["step"] == 4 and all(torch.isfinite(v).all() for v in model_state.values())


def test_ema_follows_its_recursion(tmp_path):
    t = _trainer(tmp_path, total_steps=1, checkpoint_every=100, ema_decay=0.5)
    before = {n: p.detach().clone() for n, p in t.module.named_parameters() if p.requires_grad}
    t.fit()
    for n, p in t.module.named_parameters():
        if p.requires_grad:
            torch.testing.assert_close(t.ema[n], 0.5 * before[n] + 0.5 * p.detach())
    assert "frozen.weight" not in t.ema


def test_bf16_autocast_trains(tmp_path):
    t = _trainer(tmp_path, total_steps=3, checkpoint_every=100, bf16=True)
    t.fit()
    assert all(math.isfinite(v) for v in _losses(tmp_path).values())


def test_bad_config_raises():
    with pytest.raises(ValueError, match="strategy"):
        TrainerConfig(strategy="horovod")
    with pytest.raises(ValueError, match="total_steps"):
        TrainerConfig(total_steps=0)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_two_ranks(script: str, attempts: int = 3) -> None:
    """Start ranks 0 and 1 of ``script`` (env:// rendezvous, as under torchrun) and wait for both.

    The port is free when picked but another process may take it before rank 0's store binds it; on
    "address already in use" both ranks are stopped and the run is repeated with a fresh port.
    """
    for attempt in range(attempts):
        port, procs, logs = _free_port(), [], []
        for rank in range(2):
            env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "WORLD_SIZE": "2",
                   "RANK": str(rank), "LOCAL_RANK": str(rank), "OMP_NUM_THREADS": "1"}
            logs.append(tempfile.TemporaryFile("w+"))  # a file, not a pipe: a chatty rank never blocks
            procs.append(subprocess.Popen([sys.executable, "-c", script], env=env, stderr=logs[-1], text=True))
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and any(p.poll() is None for p in procs):
            if any(p.poll() not in (None, 0) for p in procs):  # one rank failed: the other would wait forever
                for p in procs:
                    if p.poll() is None:
                        p.kill()
            time.sleep(0.05)
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()
        errs = []
        for log in logs:
            log.seek(0)
            errs.append(log.read())
            log.close()
        if all(p.returncode == 0 for p in procs):
            return
        port_taken = any("address already in use" in e.lower() or "eaddrinuse" in e.lower() for e in errs)
        if not port_taken or attempt == attempts - 1:
            pytest.fail(f"distributed run failed (attempt {attempt + 1}):\n" + "\n".join(errs))


@pytest.mark.parametrize("strategy", ["ddp", "fsdp"])
@pytest.mark.slow
def test_two_process_distributed_run_keeps_ranks_identical(tmp_path, strategy):
    script = textwrap.dedent(f"""
        import os, sys, torch, torch.distributed as dist
        sys.path.insert(0, {str(TESTS)!r})
        from _trainer_toy import ToyData, ToyModel, toy_step
        from training.trainer import Trainer, TrainerConfig
        torch.manual_seed(0)
        cfg = TrainerConfig(run_dir={str(tmp_path / 'run')!r}, total_steps=4, batch_size=4, lr=1e-2, warmup_steps=1,
                            checkpoint_every=100, progress=False, seed=3, strategy={strategy!r})
        t = Trainer(ToyModel(), ToyData(), toy_step, cfg)
        t.fit()
        state = t._model_state()
        if dist.get_rank() == 0 or {strategy!r} == "ddp":
            torch.save(state, {str(tmp_path)!r} + f"/rank{{dist.get_rank()}}.pt")
        dist.destroy_process_group()
    """)
    _run_two_ranks(script)
    r0 = torch.load(tmp_path / "rank0.pt")
    if strategy == "ddp":
        r1 = torch.load(tmp_path / "rank1.pt")
        assert all(torch.equal(r0[k], r1[k]) for k in r0)
    assert latest_checkpoint(tmp_path / "run").name == "step_00000004"
    assert all(torch.isfinite(v).all() for v in r0.values())
