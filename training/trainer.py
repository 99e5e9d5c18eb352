"""A trainer that never loses work: AdamW, warm-up + cosine, clipping, EMA, bf16, exact resume, DDP/FSDP.

The trainer is generic: a *step function* ``step_fn(model, batch, generator) -> {"loss": scalar, ...}``
computes the objective of a stage (see :mod:`training.objectives`); the trainer owns optimisation,
data order, checkpoints, logging and distribution.

Guarantees:
- **Exact resume.** Data order is a function of (seed, epoch) (``DistributedSampler`` permutation,
  ``dataset.set_epoch``), the position inside the epoch is checkpointed, and every random state
  (torch, numpy, python, the step generator handed to ``step_fn``, the loader's own generator) is
  saved, so ``--resume`` produces the same losses step for step as an uninterrupted run.
- **Non-finite losses** (or gradients) skip the optimizer step and are logged; ``max_nonfinite`` in a
  row stop the run with :class:`NonFiniteLossError`, leaving the last good checkpoint intact.
- **SIGTERM / SIGINT** finish the current step, save a checkpoint and return cleanly.
- **Distributed.** Under ``torchrun`` (``WORLD_SIZE`` > 1) the process group is initialised (gloo on
  CPU, nccl on CUDA), the model is wrapped in DDP (``strategy="ddp"``) or FSDP2 ``fully_shard``
  (``strategy="fsdp"``, for paper-size models), data is split by ``DistributedSampler``, and rank 0
  alone writes checkpoints and logs.
"""
from __future__ import annotations

import csv
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm.auto import tqdm

from diff4splat.io.atomic import atomic_output_path

from .checkpoint import latest_checkpoint, load_checkpoint, rng_state, save_checkpoint, set_rng_state

__all__ = ["TrainerConfig", "Trainer", "NonFiniteLossError", "warmup_cosine", "StepFn"]

StepFn = Callable[[nn.Module, Any, torch.Generator], dict[str, Tensor]]


class NonFiniteLossError(RuntimeError):
    """Raised after ``max_nonfinite`` consecutive non-finite losses."""


@dataclass
class TrainerConfig:
    """Optimisation and bookkeeping settings (YAML ``trainer:`` section overrides these).

    Attributes:
        run_dir: folder for checkpoints and ``metrics.csv``.
        total_steps: optimizer steps to take.
        batch_size: per-process batch size.
        lr: peak learning rate of AdamW (Loshchilov & Hutter 2019).
        betas, weight_decay: AdamW parameters.
        warmup_steps: linear warm-up from 0 to ``lr``.
        min_lr_ratio: the cosine decays to ``lr·min_lr_ratio`` at ``total_steps``.
        grad_clip: max global gradient norm (0 = off).
        ema_decay: EMA of weights (e.g. 0.999) or None.
        bf16: autocast to bfloat16 where the device supports it.
        seed: seed of data order and of the step generator.
        checkpoint_every: steps between checkpoints (a final one is always written).
        keep_checkpoints: newest checkpoints kept.
        log_every: steps between progress-bar updates (every step goes to metrics.csv).
        max_nonfinite: consecutive non-finite steps that stop the run.
        num_workers: DataLoader workers.
        strategy: "ddp" or "fsdp" when distributed.
        find_unused_parameters: DDP option for stages where some trainable modules may be unused.
        progress: show a tqdm bar.
    """

    run_dir: str = "runs/default"
    total_steps: int = 100
    batch_size: int = 2
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.01
    warmup_steps: int = 10
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0
    ema_decay: float | None = None
    bf16: bool = False
    seed: int = 0
    checkpoint_every: int = 50
    keep_checkpoints: int = 3
    log_every: int = 1
    max_nonfinite: int = 5
    num_workers: int = 0
    strategy: str = "ddp"
    find_unused_parameters: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        for name in ("total_steps", "batch_size", "checkpoint_every", "keep_checkpoints", "log_every", "max_nonfinite"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"trainer.{name} must be ≥ 1, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ValueError(f"trainer.lr must be > 0, got {self.lr}")
        if self.strategy not in ("ddp", "fsdp"):
            raise ValueError(f"trainer.strategy must be 'ddp' or 'fsdp', got {self.strategy!r}")
        if self.ema_decay is not None and not 0 < self.ema_decay < 1:
            raise ValueError(f"trainer.ema_decay must lie in (0, 1), got {self.ema_decay}")
        self.betas = tuple(self.betas)


def warmup_cosine(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """LR multiplier: linear warm-up (step+1)/warmup, then cosine from 1 to ``min_ratio`` at ``total``
    (SGDR, Loshchilov & Hutter 2017, without restarts)."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def _dist_info() -> tuple[int, int, bool]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), True
    return 0, 1, False


class Trainer:
    """Train ``model`` on ``dataset`` with ``step_fn`` (see module docstring).

    Args:
        model: the module; parameters with ``requires_grad=False`` are frozen (not optimised).
        dataset: map-style dataset; ``set_epoch(epoch)`` is called if it exists.
        step_fn: ``(model, batch, generator) -> {"loss": scalar, other scalars...}``.
        config: :class:`TrainerConfig`.
        collate_fn: DataLoader collate function.
        device: torch device (default: CUDA with the local rank if available, else CPU).
        extra_meta: JSON-able description stored in every checkpoint (e.g. the stage config).
    """

    def __init__(self, model: nn.Module, dataset: Dataset, step_fn: StepFn, config: TrainerConfig,
                 collate_fn: Callable | None = None, device: str | torch.device | None = None,
                 extra_meta: dict | None = None):
        self.config = config
        self.dataset = dataset
        self.step_fn = step_fn
        self.collate_fn = collate_fn
        self.extra_meta = extra_meta or {}
        self._init_distributed()
        self.rank, self.world, self.distributed = _dist_info()
        if device is None:
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        self.module = model.to(self.device)
        self.model = self._wrap(self.module)
        params = [p for p in self.model.parameters() if p.requires_grad]
        if not params:
            raise ValueError("model has no trainable parameters (all frozen)")
        self.optimizer = torch.optim.AdamW(params, lr=config.lr, betas=config.betas, weight_decay=config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: warmup_cosine(s, config.warmup_steps, config.total_steps, config.min_lr_ratio))
        self.ema = ({n: p.detach().clone().float() for n, p in self.module.named_parameters() if p.requires_grad}
                    if config.ema_decay else None)
        self.generator = torch.Generator().manual_seed(config.seed + 1000 * self.rank)
        self.loader_generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.epoch = 0
        self.position = 0  # batches consumed in the current epoch
        self.nonfinite = 0
        self._stop = False
        self.run_dir = Path(config.run_dir)

    # ----------------------------------------------------------------- distribution
    @staticmethod
    def _init_distributed() -> None:
        if int(os.environ.get("WORLD_SIZE", "1")) > 1 and dist.is_available() and not dist.is_initialized():
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")

    def _wrap(self, module: nn.Module) -> nn.Module:
        if not self.distributed:
            return module
        if self.config.strategy == "fsdp":
            from torch.distributed.fsdp import fully_shard

            return fully_shard(module)
        ids = [self.device.index] if self.device.type == "cuda" else None
        return nn.parallel.DistributedDataParallel(module, device_ids=ids,
                                                   find_unused_parameters=self.config.find_unused_parameters)

    def _model_state(self) -> dict[str, Tensor]:
        if self.distributed and self.config.strategy == "fsdp":
            from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

            return get_model_state_dict(self.model, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
        return self.module.state_dict()

    def _optimizer_state(self) -> dict:
        if self.distributed and self.config.strategy == "fsdp":
            from torch.distributed.checkpoint.state_dict import StateDictOptions, get_optimizer_state_dict

            return get_optimizer_state_dict(self.model, self.optimizer,
                                            options=StateDictOptions(full_state_dict=True, cpu_offload=True))
        return self.optimizer.state_dict()

    def _load_states(self, model_state: dict, optim_state: dict) -> None:
        if self.distributed and self.config.strategy == "fsdp":
            from torch.distributed.checkpoint.state_dict import StateDictOptions, set_state_dict

            set_state_dict(self.model, self.optimizer, model_state_dict=model_state, optim_state_dict=optim_state,
                           options=StateDictOptions(full_state_dict=True, broadcast_from_rank0=False))
        else:
            self.module.load_state_dict(model_state)
            self.optimizer.load_state_dict(optim_state)

    # ----------------------------------------------------------------- checkpoints
    def save(self) -> Path | None:
        """Write a checkpoint (rank 0; other ranks wait at a barrier). Returns its folder on rank 0."""
        model_state = self._model_state()
        optim_state = self._optimizer_state()
        folder = None
        if self.rank == 0:
            state = {"optimizer": optim_state, "scheduler": self.scheduler.state_dict(),
                     "rng": rng_state(self.generator), "loader_generator": self.loader_generator.get_state(),
                     "step": self.step, "epoch": self.epoch, "position": self.position, "nonfinite": self.nonfinite}
            meta = {"epoch": self.epoch, "position": self.position, "time": time.time(),
                    "trainer": asdict(self.config), **self.extra_meta}
            folder = save_checkpoint(self.run_dir, self.step, model_state, state, meta, self.ema,
                                     self.config.keep_checkpoints)
        if self.distributed:
            dist.barrier()
        return folder

    def resume(self, folder: str | os.PathLike | None = None) -> bool:
        """Restore the newest checkpoint of the run (or ``folder``). Returns False if there is none."""
        folder = Path(folder) if folder is not None else latest_checkpoint(self.run_dir)
        if folder is None:
            return False
        model_state, state, ema = load_checkpoint(folder)
        self._load_states(model_state, state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        set_rng_state(state["rng"], self.generator)
        if self.distributed:  # each rank continues its own step-generator stream
            self.generator.manual_seed(self.config.seed + 1000 * self.rank + state["step"])
        self.loader_generator.set_state(state["loader_generator"])
        self.step, self.epoch, self.position = state["step"], state["epoch"], state["position"]
        self.nonfinite = state.get("nonfinite", 0)
        if ema is not None and self.ema is not None:
            self.ema = {k: v.float() for k, v in ema.items()}
        self._truncate_metrics()
        return True

    def _truncate_metrics(self) -> None:
        """Drop metrics.csv rows logged after the restored step (work the checkpoint does not hold)."""
        path = self.run_dir / "metrics.csv"
        if self.rank != 0 or not path.is_file():
            return
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            fields, rows = reader.fieldnames, list(reader)
        keep = [r for r in rows if int(r["step"]) < self.step or (int(r["step"]) == self.step and r["skipped"] == "0")]
        with atomic_output_path(path) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(keep)

    # ----------------------------------------------------------------- data
    def _epoch_batches(self) -> list[list[int]]:
        sampler = DistributedSampler(self.dataset, num_replicas=self.world, rank=self.rank, shuffle=True,
                                     seed=self.config.seed, drop_last=True)
        sampler.set_epoch(self.epoch)
        idx = list(sampler)
        b = self.config.batch_size
        batches = [idx[i:i + b] for i in range(0, len(idx) - b + 1, b)]
        if not batches:
            raise ValueError(f"dataset of {len(self.dataset)} items is smaller than one batch "
                             f"({b} × {self.world} processes)")
        return batches

    def _loader(self, batches: list[list[int]]) -> DataLoader:
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(self.epoch)
        return DataLoader(self.dataset, batch_sampler=batches, num_workers=self.config.num_workers,
                          collate_fn=self.collate_fn, generator=self.loader_generator)

    # ----------------------------------------------------------------- loop
    def _request_stop(self, signum, frame) -> None:  # noqa: ARG002
        self._stop = True

    def _to_device(self, batch):
        if isinstance(batch, Tensor):
            return batch.to(self.device)
        if isinstance(batch, dict):
            return {k: self._to_device(v) for k, v in batch.items()}
        if isinstance(batch, (list, tuple)):
            return type(batch)(self._to_device(v) for v in batch)
        return batch

    def _all_finite(self, value: Tensor) -> bool:
        flag = torch.tensor([1.0 if bool(torch.isfinite(value).all()) else 0.0], device=self.device)
        if self.distributed:
            dist.all_reduce(flag, op=dist.ReduceOp.MIN)
        return bool(flag.item() > 0)

    def fit(self, resume: bool = False) -> dict[str, Any]:
        """Run until ``total_steps`` (or a stop signal). Returns a summary dict.

        Raises:
            NonFiniteLossError: ``max_nonfinite`` consecutive non-finite steps.
        """
        cfg = self.config
        if resume:
            self.resume()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        old_handlers = {}
        try:
            for sig in (signal.SIGTERM, signal.SIGINT):
                old_handlers[sig] = signal.signal(sig, self._request_stop)
        except ValueError:  # not the main thread: signals cannot be handled here
            old_handlers = {}
        csv_path = self.run_dir / "metrics.csv"
        bar = tqdm(total=cfg.total_steps, initial=self.step, disable=not cfg.progress or self.rank != 0,
                   desc="train", dynamic_ncols=True)
        last_losses: dict[str, float] = {}
        try:
            while self.step < cfg.total_steps and not self._stop:
                batches = self._epoch_batches()
                if self.position >= len(batches):
                    self.epoch, self.position = self.epoch + 1, 0
                    continue
                for batch in self._loader(batches[self.position:]):
                    last_losses = self._train_step(self._to_device(batch), csv_path, bar)
                    if self.step % cfg.checkpoint_every == 0 and last_losses.get("skipped", 0) == 0:
                        self.save()
                    if self.step >= cfg.total_steps or self._stop:
                        break
                else:
                    self.epoch, self.position = self.epoch + 1, 0
            self.save()
        finally:
            bar.close()
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)
        return {"step": self.step, "epoch": self.epoch, "stopped": self._stop, "last": last_losses}

    def _train_step(self, batch, csv_path: Path, bar) -> dict[str, float]:
        cfg = self.config
        self.model.train()
        t0 = time.perf_counter()
        autocast = torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cfg.bf16)
        with autocast:
            losses = self.step_fn(self.model, batch, self.generator)
        loss = losses["loss"]
        self.position += 1
        ok = self._all_finite(loss.detach())
        grad_norm = float("nan")
        if ok:
            loss.backward()
            params = [p for p in self.model.parameters() if p.grad is not None]
            norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip if cfg.grad_clip > 0 else float("inf"))
            grad_norm = float(norm)
            ok = self._all_finite(norm.detach().reshape(1))
        if not ok:
            self.optimizer.zero_grad(set_to_none=True)
            self.nonfinite += 1
            record = {"step": self.step, "epoch": self.epoch, "skipped": 1, "loss": float(loss.detach())}
            self._log(csv_path, record)
            if self.rank == 0:
                tqdm.write(f"train: non-finite loss/gradient at step {self.step} (epoch {self.epoch}, batch "
                           f"{self.position - 1}); step skipped ({self.nonfinite}/{cfg.max_nonfinite} in a row)",
                           file=sys.stderr)
            if self.nonfinite >= cfg.max_nonfinite:
                raise NonFiniteLossError(
                    f"{self.nonfinite} consecutive non-finite steps at step {self.step}; the last good "
                    f"checkpoint in {self.run_dir / 'checkpoints'} is intact")
            return record
        self.optimizer.step()
        self.scheduler.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.nonfinite = 0
        self.step += 1
        if self.ema is not None:
            with torch.no_grad():
                for n, p in self.module.named_parameters():
                    if n in self.ema:
                        self.ema[n].lerp_(p.detach().float(), 1 - cfg.ema_decay)
        record = {"step": self.step, "epoch": self.epoch, "skipped": 0, "lr": self.scheduler.get_last_lr()[0],
                  "grad_norm": grad_norm, "seconds": time.perf_counter() - t0,
                  **{k: float(v.detach()) for k, v in losses.items()}}
        self._log(csv_path, record)
        bar.update(1)
        if self.step % cfg.log_every == 0:
            bar.set_postfix(loss=f"{record['loss']:.4g}", lr=f"{record['lr']:.2e}")
        return record

    def _log(self, path: Path, record: dict) -> None:
        if self.rank != 0:
            return
        fields = ["step", "epoch", "skipped", "lr", "grad_norm", "seconds", "loss"]
        fields += sorted(k for k in record if k not in fields)
        new = not path.exists()
        if not new:
            with open(path) as f:
                header = f.readline().strip().split(",")
            if set(fields) - set(header):  # new columns: rewrite with the wider header
                rows = list(csv.DictReader(open(path)))
                fields = header + [k for k in fields if k not in header]
                with open(path, "w", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=fields)
                    w.writeheader()
                    w.writerows(rows)
            else:
                fields = header
        with open(path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
            if new:
                w.writeheader()
            w.writerow(record)

    def ema_state_dict(self) -> dict[str, Tensor] | None:
        """EMA weights merged into a full state dict (frozen weights as they are), or None."""
        if self.ema is None:
            return None
        state = {k: v.clone() for k, v in self.module.state_dict().items()}
        for k, v in self.ema.items():
            state[k] = v.to(state[k].dtype)
        return state
