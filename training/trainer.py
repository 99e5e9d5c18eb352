"""A trainer that never loses work: AdamW, warm-up + cosine, clipping, EMA, bf16, exact resume, DDP/FSDP.

A *step function* ``step_fn(model, batch, generator) -> {"loss": scalar, ...}`` computes a stage's objective
(:mod:`training.objectives`); the trainer owns optimisation, data order, checkpoints, logging, devices and
distribution. Resume is exact: data order is a function of (seed, epoch), the position in the epoch and every
random state are checkpointed. The step generator is a CPU ``torch.Generator`` (draw on it, move the draw), so a
float32 run gives the CPU's losses on CUDA to float32 rounding. Non-finite losses or gradients skip the step;
``max_nonfinite`` in a row raise :class:`NonFiniteLossError`. SIGTERM/SIGINT save a checkpoint and return.
Devices, bf16/TF32, gradient checkpointing, torchrun with DDP or FSDP2 (``model.fsdp_units()`` sharded first, bf16
parameters with float32 reduction; the root in float32): docs/DESIGN.md, "Training". Rank 0 alone writes.
"""
from __future__ import annotations

import csv
import math
import os
import signal
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.distributed.checkpoint.state_dict import (
    StateDictOptions,
    get_model_state_dict,
    get_optimizer_state_dict,
    set_state_dict,
)
from torch.distributed.device_mesh import init_device_mesh
from torch.distributed.fsdp import MixedPrecisionPolicy, fully_shard
from torch.distributed.tensor import distribute_tensor
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm.auto import tqdm

from diff4splat.io.atomic import atomic_output_path
from diff4splat.utils.checks import check_number, check_ranges, ranged
from diff4splat.utils.devices import AUTO, cpu_bf16_warning

from .checkpoint import latest_checkpoint, load_checkpoint, rng_state, save_checkpoint, set_rng_state
from .placement import dist_info, resolve_bf16, training_device

__all__ = ["TrainerConfig", "Trainer", "NonFiniteLossError", "warmup_cosine", "StepFn"]

StepFn = Callable[[nn.Module, Any, torch.Generator], dict[str, Tensor]]


def _nonfinite_part(values: dict[str, float], loss_ok: bool, grad_norm: float) -> str:
    """What was not finite in a skipped step: the loss terms, the gradient norm, or another rank's loss."""
    if loss_ok:
        return f"gradient (norm {grad_norm})"
    bad = [f"{k} {v}" for k, v in values.items() if k != "loss" and not math.isfinite(v)]
    if math.isfinite(values["loss"]):
        return "loss on another rank"
    return "loss (" + (", ".join(bad) if bad else f"the sum {values['loss']} of finite terms") + ")"


class NonFiniteLossError(RuntimeError):
    """Raised after ``max_nonfinite`` consecutive non-finite losses."""


@dataclass
class TrainerConfig:
    """Optimisation and bookkeeping settings (the YAML ``trainer:`` section).

    AdamW (Loshchilov & Hutter 2019) at peak ``lr`` after ``warmup_steps``, cosine to ``lr·min_lr_ratio``;
    ``grad_clip`` 0 is off; ``ema_decay`` None is off; ``device`` ``auto``/``cpu``/``cuda``/``cuda:N``
    (:func:`training_device`, checked by :class:`Trainer`); ``bf16`` None/``auto`` = on for CUDA
    (:func:`resolve_bf16`); ``tf32`` on CUDA only; ``log_every`` paces the bar (every step goes to metrics.csv);
    ``strategy`` "ddp" or "fsdp" when distributed. Raises ValueError naming ``trainer.<field>`` for a count < 1,
    lr ≤ 0, a negative warmup_steps/grad_clip/weight_decay/num_workers, min_lr_ratio outside [0, 1], an unknown
    strategy, ema_decay outside (0, 1), a non-string device, or a bf16 not true/false/null/``auto``.
    """

    run_dir: str = "runs/default"
    total_steps: int = ranged(100)
    batch_size: int = ranged(2)
    lr: float = ranged(1e-4, check_number, lo=0, lo_open=True)
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = ranged(0.01, check_number, lo=0)
    warmup_steps: int = ranged(10, check_number, lo=0)
    min_lr_ratio: float = 0.1
    grad_clip: float = ranged(1.0, check_number, lo=0)
    ema_decay: float | None = None
    device: str = AUTO
    bf16: bool | None = None
    tf32: bool = True
    gradient_checkpointing: bool = False
    seed: int = 0
    checkpoint_every: int = ranged(50)
    keep_checkpoints: int = ranged(3)
    log_every: int = ranged(1)
    max_nonfinite: int = ranged(5)
    num_workers: int = ranged(0, check_number, lo=0)
    strategy: str = "ddp"
    find_unused_parameters: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        check_ranges("trainer", self)  # grad_clip < 0 turned clipping off
        if not 0 <= self.min_lr_ratio <= 1:
            raise ValueError(f"trainer.min_lr_ratio must lie in [0, 1], got {self.min_lr_ratio}")
        if self.strategy not in ("ddp", "fsdp"):
            raise ValueError(f"trainer.strategy must be 'ddp' or 'fsdp', got {self.strategy!r}")
        if self.ema_decay is not None and not 0 < self.ema_decay < 1:
            raise ValueError(f"trainer.ema_decay must lie in (0, 1), got {self.ema_decay}")
        if isinstance(self.device, torch.device):
            self.device = str(self.device)
        if not isinstance(self.device, str) or not self.device.strip():
            raise ValueError(f"trainer.device must be a device name (auto, cpu, cuda, cuda:1, …), got {self.device!r}")
        if isinstance(self.bf16, str) and self.bf16.strip().lower() == AUTO:
            self.bf16 = None
        if self.bf16 is not None and not isinstance(self.bf16, bool):
            raise ValueError(f"trainer.bf16 must be true, false or null/auto (on for CUDA), got {self.bf16!r}")
        self.betas = tuple(self.betas)


def warmup_cosine(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """LR multiplier: linear warm-up (step+1)/warmup, then cosine from 1 to ``min_ratio`` at ``total``
    (SGDR, Loshchilov & Hutter 2017, without restarts)."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


class Trainer:
    """Train ``model`` (frozen parameters: ``requires_grad=False``) on a map-style ``dataset`` (``set_epoch`` called
    if present) with ``step_fn``. Optional model hooks: ``fsdp_units()``, ``checkpoint_frozen`` (False: frozen weights
    left out of checkpoints, rebuilt before :meth:`resume`), ``enable_gradient_checkpointing()``. ``device`` wins over
    ``config.device``; ``extra_meta`` is stored in every checkpoint.

    Raises ValueError for an unusable device, a dataset smaller than one batch per process, no trainable parameter,
    or ``gradient_checkpointing`` without a supporting module. Warns (UserWarning) for bf16 on a CPU whose bfloat16
    matmul leaks NaN (:func:`diff4splat.utils.devices.cpu_bf16_warning`).
    """

    def __init__(self, model: nn.Module, dataset: Dataset, step_fn: StepFn, config: TrainerConfig,
                 collate_fn: Callable | None = None, device: str | torch.device | None = None,
                 extra_meta: dict | None = None):
        self.config = config
        self.dataset = dataset
        self.step_fn = step_fn
        self.collate_fn = collate_fn
        self.extra_meta = extra_meta or {}
        self.device = (training_device(config.device, "trainer.device") if device is None
                       else training_device(device, "device"))
        self.bf16 = resolve_bf16(config.bf16, self.device)
        if self.bf16 and self.device.type == "cpu" and (message := cpu_bf16_warning()):
            warnings.warn(message, stacklevel=2)
        if self.device.type == "cuda":  # before the process group and the model: NCCL and FSDP use this GPU
            torch.cuda.set_device(self.device)
            torch.backends.cuda.matmul.allow_tf32 = config.tf32
            torch.backends.cudnn.allow_tf32 = config.tf32
        self._init_distributed(self.device)
        self.rank, self.world, self.distributed = dist_info()
        self.sharded = self.distributed and config.strategy == "fsdp"
        self._check_one_batch()  # before anything is built or written
        if config.gradient_checkpointing:
            self._enable_gradient_checkpointing(model)
        self.checkpoint_frozen = bool(getattr(model, "checkpoint_frozen", True))
        self.module = model.to(self.device)
        self.model = self._wrap(self.module)
        params = [p for p in self.model.parameters() if p.requires_grad]
        if not params:
            raise ValueError("model has no trainable parameters (all frozen)")
        self.optimizer = torch.optim.AdamW(params, lr=config.lr, betas=config.betas, weight_decay=config.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer, lambda s: warmup_cosine(s, config.warmup_steps, config.total_steps, config.min_lr_ratio))
        # EMA of the trainable weights, float32 on the device (FSDP: of this rank's shards)
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

    # ----------------------------------------------------------------- devices and distribution
    @staticmethod
    def _enable_gradient_checkpointing(model: nn.Module) -> None:
        hook = getattr(model, "enable_gradient_checkpointing", None)
        if callable(hook):  # the model picks its modules (TrainingModule: the video transformer, ours or diffusers')
            hook()
            return
        found = [m for m in model.modules() if hasattr(m, "gradient_checkpointing")]
        if not found:
            raise ValueError(f"trainer.gradient_checkpointing: no module of the {type(model).__name__} supports it "
                             "(a `gradient_checkpointing` attribute, as models.dit.VideoDiT has)")
        for m in found:
            m.gradient_checkpointing = True

    @staticmethod
    def _init_distributed(device: torch.device) -> None:
        """Join the process group (NCCL on CUDA, else gloo) when ``torchrun`` started this process, even alone."""
        launched = all(k in os.environ for k in ("MASTER_ADDR", "MASTER_PORT", "RANK", "WORLD_SIZE"))
        if launched and dist.is_available() and not dist.is_initialized():
            if device.type == "cuda":
                dist.init_process_group("nccl", device_id=device)
            else:
                dist.init_process_group("gloo")

    def _wrap(self, module: nn.Module) -> nn.Module:
        if not self.distributed:
            return module
        if self.sharded:
            mesh = init_device_mesh(self.device.type, (self.world,))  # not FSDP's default: CUDA whenever present
            blocks = (MixedPrecisionPolicy(param_dtype=torch.bfloat16, reduce_dtype=torch.float32) if self.bf16
                      else MixedPrecisionPolicy())
            units = module.fsdp_units() if hasattr(module, "fsdp_units") else []
            for unit in units:  # inner units first: each block's weights are gathered only while it runs
                fully_shard(unit, mesh=mesh, mp_policy=blocks)
            return fully_shard(module, mesh=mesh)
        ids = [self.device.index] if self.device.type == "cuda" else None
        return nn.parallel.DistributedDataParallel(module, device_ids=ids,
                                                   find_unused_parameters=self.config.find_unused_parameters)

    def _model_state(self, frozen: bool = True) -> dict[str, Tensor]:
        """Full weights (collective under FSDP: on the CPU on rank 0, ``{}`` elsewhere), without the frozen ones when
        ``frozen`` is False."""
        if self.sharded:
            state = get_model_state_dict(self.model, options=StateDictOptions(
                full_state_dict=True, cpu_offload=True, ignore_frozen_params=not frozen))
        else:
            state = self.module.state_dict()
        # every name of a frozen parameter (get_model_state_dict keeps the second name of a tied one)
        return state if frozen else {k: v for k, v in state.items() if k not in self._frozen_names()}

    def _frozen_names(self) -> set[str]:
        """State-dict names of the frozen parameters (every name of a shared one)."""
        return {n for n, p in self.module.named_parameters(remove_duplicate=False) if not p.requires_grad}

    def _ema_state(self) -> dict[str, Tensor] | None:
        """Full EMA weights (an FSDP2 shard is a DTensor: collective, every rank calls it), or None without EMA."""
        if self.ema is None:
            return None
        return {k: v.full_tensor() if hasattr(v, "full_tensor") else v for k, v in self.ema.items()}

    def _load_states(self, model_state: dict, optim_state: dict, ema: dict[str, Tensor] | None) -> None:
        if self.sharded:
            set_state_dict(self.model, self.optimizer, model_state_dict=model_state, optim_state_dict=optim_state,
                           options=StateDictOptions(full_state_dict=True, broadcast_from_rank0=False,
                                                    strict=self.checkpoint_frozen))
            if ema is not None and self.ema is not None:  # this rank's shard of each full EMA tensor
                self.ema = {k: distribute_tensor(ema[k].to(self.device, torch.float32), v.device_mesh, v.placements)
                            if hasattr(v, "device_mesh") else ema[k].to(self.device, torch.float32)
                            for k, v in self.ema.items()}
            return
        result = self.module.load_state_dict(model_state, strict=self.checkpoint_frozen)
        missing = set(result.missing_keys) - self._frozen_names()
        if missing or result.unexpected_keys:  # only frozen weights may be absent (checkpoint_frozen False)
            raise RuntimeError(f"checkpoint: weights missing {sorted(missing)[:5]}, unexpected "
                               f"{sorted(result.unexpected_keys)[:5]}")
        self.optimizer.load_state_dict(optim_state)
        if ema is not None and self.ema is not None:
            self.ema = {k: v.to(self.device, torch.float32) for k, v in ema.items()}

    # ----------------------------------------------------------------- checkpoints
    def save(self) -> Path | None:
        """Write a checkpoint (rank 0; other ranks wait at a barrier). Returns its folder on rank 0."""
        model_state = self._model_state(frozen=self.checkpoint_frozen)
        optim_state = (get_optimizer_state_dict(self.model, self.optimizer,
                                                options=StateDictOptions(full_state_dict=True, cpu_offload=True))
                       if self.sharded else self.optimizer.state_dict())
        ema_state = self._ema_state()
        folder = None
        if self.rank == 0:
            state = {"optimizer": optim_state, "scheduler": self.scheduler.state_dict(),
                     "rng": rng_state(self.generator), "loader_generator": self.loader_generator.get_state(),
                     "step": self.step, "epoch": self.epoch, "position": self.position, "nonfinite": self.nonfinite}
            meta = {"epoch": self.epoch, "position": self.position, "time": time.time(),
                    "trainer": asdict(self.config), **self.extra_meta}
            folder = save_checkpoint(self.run_dir, self.step, model_state, state, meta, ema_state,
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
        self._load_states(model_state, state["optimizer"], ema)
        self.scheduler.load_state_dict(state["scheduler"])
        set_rng_state(state["rng"], self.generator)
        if self.world > 1:  # the checkpoint holds rank 0's stream only: with several ranks each reseeds its own
            self.generator.manual_seed(self.config.seed + 1000 * self.rank + state["step"])
        self.loader_generator.set_state(state["loader_generator"])
        self.step, self.epoch, self.position = state["step"], state["epoch"], state["position"]
        self.nonfinite = state.get("nonfinite", 0)
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
        return [idx[i:i + b] for i in range(0, len(idx) - b + 1, b)]  # at least one (_check_one_batch)

    def _check_one_batch(self) -> None:
        """Each rank's share of the dataset (``DistributedSampler``, drop_last) holds at least one batch."""
        if len(self.dataset) // self.world < self.config.batch_size:
            raise ValueError(f"dataset of {len(self.dataset)} items is smaller than one batch "
                             f"({self.config.batch_size} × {self.world} processes)")

    def _loader(self, batches: list[list[int]]) -> DataLoader:
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(self.epoch)
        return DataLoader(self.dataset, batch_sampler=batches, num_workers=self.config.num_workers,
                          collate_fn=self.collate_fn, generator=self.loader_generator,
                          pin_memory=self.device.type == "cuda")

    # ----------------------------------------------------------------- loop
    def _request_stop(self, signum, frame) -> None:  # noqa: ARG002
        self._stop = True

    def _to_device(self, batch):
        """``batch``'s tensors (in nested dicts, lists, tuples) copied non-blocking to the trainer's device."""
        if isinstance(batch, Tensor):
            return batch.to(self.device, non_blocking=True)
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
        """Run until ``total_steps`` or a stop signal; returns a summary. Raises :class:`NonFiniteLossError`."""
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
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            losses = self.step_fn(self.model, batch, self.generator)
        loss = losses["loss"]
        self.position += 1
        loss_ok = ok = self._all_finite(loss.detach())
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
            values = {k: float(v.detach()) for k, v in losses.items()}
            record = {"step": self.step, "epoch": self.epoch, "skipped": 1, "grad_norm": grad_norm, **values}
            self._log(csv_path, record)
            if self.rank == 0:
                tqdm.write(f"train: non-finite {_nonfinite_part(values, loss_ok, grad_norm)} at step {self.step} "
                           f"(epoch {self.epoch}, batch {self.position - 1}); step skipped "
                           f"({self.nonfinite}/{cfg.max_nonfinite} in a row)", file=sys.stderr)
            if self.nonfinite >= cfg.max_nonfinite:
                raise NonFiniteLossError(
                    f"{self.nonfinite} consecutive non-finite steps at step {self.step}; the last good "
                    f"checkpoint in {self.run_dir / 'checkpoints'} is intact")
            return record
        lr = self.scheduler.get_last_lr()[0]  # the rate this step used (after scheduler.step() it is the next one's)
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
        record = {"step": self.step, "epoch": self.epoch, "skipped": 0, "lr": lr,
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
        """EMA weights merged into a full state dict (frozen weights as they are), or None without EMA; collective
        under FSDP, complete on rank 0 only."""
        if self.ema is None:
            return None
        state = {k: v.clone() for k, v in self._model_state().items()}
        for k, v in self._ema_state().items():
            if k in state:
                state[k] = v.to(state[k])  # the weight's dtype and device
        return state

    def final_state_dict(self) -> dict[str, Tensor]:
        """The weights to publish: :meth:`ema_state_dict` with EMA, else the model's own, full (as it, collective)."""
        ema = self.ema_state_dict()
        return ema if ema is not None else self._model_state()
