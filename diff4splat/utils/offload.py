"""Model CPU offload: networks live in (pinned) CPU memory and visit the compute device only while they run.

A paper-size model does not fit one GPU's memory budget whole: in bfloat16 the DiT alone holds 23.8 GB and the
T5-XXL-shaped text encoder 9.5 GB (docs/benchmarks.md, "GPU"). With :class:`ModelOffload` at most one network is
on the device at a time — the one that runs now — so the peak is the largest network plus its activations
instead of the sum (diffusers' ``enable_model_cpu_offload`` does the same with hooks).

Inference only: the CPU copy of each weight is the master; moving a network off the device points its
parameters back at that copy (no device-to-host copy), so weights changed on the device are lost. On CUDA the CPU
copies are pinned once, and moving on is an asynchronous host-to-device copy on the current stream. The pinned
copies share blocks of :data:`PIN_BLOCK_BYTES` (:func:`pin_packed`): torch's pinned-memory allocator rounds each
allocation up to a power of two, so pinning every weight alone would pin up to twice its bytes (the paper-size
text encoder's 9.5 GB as 13.2 GB, the DiT's 23.8 GB as 27.1 GB).

Prefetch (``prefetch=``, CUDA only): the host-to-device copy of a network runs on a side stream, block by block in
the order the blocks run, and each block waits only for its own weights (a forward pre-hook, removed when the
visit's first call returns), so that call computes block i while blocks i + 1 … are still on their way (diffusers'
group offloading with ``use_stream``, but once per visit rather than at every call). A network's copy takes about as
long as one sampling step on an H100 (docs/benchmarks.md, "GPU"), so the copy can hide behind the first step. The
values are those of the plain move: only the order of the copies and the kernels changes.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["ModelOffload", "prefetch_groups", "weight_bytes", "pin_plan", "pin_packed", "pinned_bytes",
           "PIN_BLOCK_BYTES"]

PIN_BLOCK_BYTES = 1 << 29
"""Bytes of one pinned host block that weights share (512 MiB, a power of two: the allocator pins it as asked).
Each network's weights fill blocks first-fit in order; a weight larger than a block gets one of its own."""
PIN_ALIGN = 64
"""Byte alignment of each weight in a block (any element size; whole cache lines for the copy engine)."""


def _tensors(module: nn.Module) -> Iterator[torch.Tensor]:
    """The parameters, then the buffers, of ``module`` (each shared tensor once)."""
    yield from module.parameters()
    yield from (b for b in module.buffers() if b is not None)


def weight_bytes(module: nn.Module) -> list[int]:
    """Bytes of each parameter, then buffer, of ``module`` (each shared tensor once): what :class:`ModelOffload`
    keeps on the CPU, in the order it packs them (:func:`pin_plan`)."""
    return [t.numel() * t.element_size() for t in _tensors(module)]


def prefetch_groups(module: nn.Module, blocks: Sequence[nn.Module]) -> list[list[int]]:
    """The copy order of :class:`ModelOffload`'s prefetch: indices into ``list(_tensors(module))`` (parameters,
    then buffers), as ``[rest, block 0, block 1, …]``. ``rest`` holds every tensor outside ``blocks`` (embedders,
    final layers; copied first and waited for before the network runs) and every tensor that two blocks share
    (so no block waits on another block's copy); each tensor is in exactly one group.

    Raises:
        ValueError: a block is not a submodule of ``module``, or appears twice.
    """
    index = {id(t): i for i, t in enumerate(_tensors(module))}
    submodules = {id(m) for m in module.modules()}
    if any(id(b) not in submodules for b in blocks) or len({id(b) for b in blocks}) != len(blocks):
        raise ValueError("prefetch blocks must be distinct submodules of the network they move")
    owners: dict[int, int] = {}  # tensor index → the one block holding it (-1: shared)
    for k, block in enumerate(blocks):
        for t in _tensors(block):
            i = index[id(t)]
            owners[i] = k if owners.get(i, k) == k else -1
    groups: list[list[int]] = [[] for _ in range(len(blocks) + 1)]
    for i in range(len(index)):
        groups[owners.get(i, -1) + 1].append(i)
    return groups


def _pow2(n: int) -> int:
    """What torch's pinned-memory allocator (``CachingHostAllocator``) pins for ``n`` bytes: n rounded up to a
    power of two."""
    return 1 << max(n - 1, 0).bit_length() if n else 0


def pin_plan(nbytes: Sequence[int], block: int = PIN_BLOCK_BYTES) -> tuple[list[int], list[tuple[int, int]]]:
    """Where :func:`pin_packed` puts tensors of ``nbytes`` bytes: (the blocks' sizes, (block, byte offset) of each
    tensor). First fit in order, offsets multiples of :data:`PIN_ALIGN`; a tensor larger than ``block`` gets a block
    of its own size; each block is as large as what it holds. A block whose tensors alone would pin less than the
    block rounded up to a power of two (a network's last, part-filled block; a small network) is split into one
    block per tensor."""
    used: list[int] = []  # bytes used in each block so far
    where: list[tuple[int, int]] = []
    for n in map(int, nbytes):
        k = next((k for k, u in enumerate(used) if u <= block  # above ``block``: a tensor's own, full
                  and -(-u // PIN_ALIGN) * PIN_ALIGN + n <= block), None)
        if k is None:
            used.append(0)
            k = len(used) - 1
        offset = -(-used[k] // PIN_ALIGN) * PIN_ALIGN
        where.append((k, offset))
        used[k] = offset + n if n <= block else block + n
    held = [[i for i, (k, _) in enumerate(where) if k == b] for b in range(len(used))]
    sizes: list[int] = []
    out: list[tuple[int, int]] = [(0, 0)] * len(where)
    for b, u in enumerate(used):
        size = u - block if u > block else u
        if sum(_pow2(int(nbytes[i])) for i in held[b]) < _pow2(size):
            for i in held[b]:
                out[i] = (len(sizes), 0)
                sizes.append(int(nbytes[i]))
        else:
            for i in held[b]:
                out[i] = (len(sizes), where[i][1])
            sizes.append(size)
    return sizes, out


def pinned_bytes(nbytes: Sequence[int], block: int = PIN_BLOCK_BYTES) -> int:
    """Host bytes pinned for tensors of ``nbytes`` bytes by :func:`pin_packed`: its blocks, each rounded up to a
    power of two as torch's pinned-memory allocator does."""
    return sum(_pow2(size) for size in pin_plan(nbytes, block)[0])


def pin_packed(tensors: Sequence[torch.Tensor], block: int = PIN_BLOCK_BYTES, pin: bool = True) -> None:
    """Move CPU ``tensors`` (parameters or buffers) into shared pinned blocks laid out by :func:`pin_plan`, in
    place: each one's ``.data`` becomes a contiguous view of its block (same shape, dtype and values). A block is
    allocated when its first tensor arrives and each original is dropped as soon as it is copied, so the peak is the
    weights plus about one block, not twice the weights. ``pin=False`` allocates plain blocks (the layout without
    CUDA, for tests)."""
    sizes, where = pin_plan([t.numel() * t.element_size() for t in tensors], block)  # weight_bytes' order
    blocks: dict[int, torch.Tensor] = {}
    for t, (k, offset) in zip(tensors, where, strict=True):
        if k not in blocks:
            blocks[k] = torch.empty(sizes[k], dtype=torch.uint8, device="cpu", pin_memory=pin)  # not a copy
        view = blocks[k][offset:offset + t.numel() * t.element_size()].view(t.dtype).view(t.shape)
        view.copy_(t.data)
        t.data = view


class ModelOffload:
    """Keep the networks of ``modules`` on the CPU and move one at a time to ``device`` (see the module docstring).

    Args:
        modules: name → network; each is moved to the CPU here (in place) and stays there between calls.
        device: the compute device. On the CPU nothing ever moves.
        pin: pin the CPU copies when ``device`` is CUDA (faster, asynchronous copies; needs that much
            page-locked host memory).
        prefetch: name → that network's blocks in the order its forward runs them (e.g. the transformer blocks,
            :meth:`models.backbone.Backbone.transformer_blocks`): its move onto a CUDA device overlaps
            the first call (module docstring). The blocks must run as modules (their forward pre-hooks fire) and
            not be ``torch.compile``-d (a hook added to a compiled module recompiles it). Ignored off CUDA.

    Raises:
        ValueError: ``prefetch`` names a network that is not in ``modules``, or blocks that are not its
            submodules (:func:`prefetch_groups`).

    Attributes:
        resident: the name of the network now on ``device``, or None.
        pinned: whether the CPU copies are pinned (``pin`` on a CUDA device).
    """

    def __init__(self, modules: dict[str, nn.Module], device: str | torch.device, *, pin: bool = True,
                 prefetch: dict[str, Sequence[nn.Module]] | None = None):
        self.device = torch.device(device)
        self.modules = dict(modules)
        self.resident: str | None = None
        unknown = sorted(set(prefetch or {}) - set(self.modules))
        if unknown:
            raise ValueError(f"prefetch names networks that are not offloaded: {unknown}")
        self._groups = {name: (list(blocks), prefetch_groups(self.modules[name], blocks))
                        for name, blocks in (prefetch or {}).items()}
        self._home: dict[str, list[torch.Tensor]] = {}
        self.pinned = pin and self.device.type == "cuda"
        for name, module in self.modules.items():
            module.to("cpu")
            tensors = list(_tensors(module))
            if self.pinned:
                pin_packed(tensors)
            self._home[name] = [t.data for t in tensors]

    def host_bytes(self) -> int:
        """Bytes of host memory the CPU copies hold: their pinned blocks (:func:`pinned_bytes`, each rounded up to a
        power of two) where they are pinned, else their bytes."""
        sizes = [weight_bytes(module) for module in self.modules.values()]
        return sum(pinned_bytes(s) if self.pinned else sum(s) for s in sizes)

    @contextmanager
    def use(self, name: str) -> Iterator[nn.Module]:
        """The network ``name``, on the device for the body of the ``with``; the network that was resident
        before goes back to the CPU first. It stays resident afterwards (a sampler's next step reuses it),
        until another network is used or :meth:`release` is called.

        Raises:
            KeyError: ``name`` is not one of the modules.
        """
        module = self.modules[name]
        finish: Callable[[], None] | None = None
        if self.resident != name and self.device.type != "cpu":
            self.release()
            if name in self._groups and self.device.type == "cuda":
                finish = self._prefetch(name)
            else:
                for t, home in zip(_tensors(module), self._home[name], strict=True):
                    t.data = home.to(self.device, non_blocking=True)
            self.resident = name
        try:
            yield module
        finally:
            if finish is not None:
                finish()

    def _prefetch(self, name: str) -> Callable[[], None]:
        """Start moving ``name`` onto the CUDA device on a side stream, group by group (:func:`prefetch_groups`);
        return the call that ends the visit's hooks and makes the current stream wait for every copy."""
        blocks, groups = self._groups[name]
        tensors, homes = list(_tensors(self.modules[name])), self._home[name]
        main = torch.cuda.current_stream(self.device)
        side = torch.cuda.Stream(self.device)
        # The new tensors come from the current stream's memory pool (they live there), and memory that stream
        # freed may still be read by its queued kernels: the copies start after those.
        side.wait_stream(main)
        events = []
        for group in groups:
            for i in group:
                dst = torch.empty_like(homes[i], device=self.device)
                with torch.cuda.stream(side):
                    dst.copy_(homes[i], non_blocking=True)
                tensors[i].data = dst  # no record_stream: finish() orders the current stream after every copy
            event = torch.cuda.Event()
            event.record(side)
            events.append(event)
        main.wait_event(events[0])  # embedders and the rest run first, outside any block
        handles = []

        def waiter(event):
            def hook(module, args):
                torch.cuda.current_stream(self.device).wait_event(event)
            return hook

        for block, event in zip(blocks, events[1:], strict=True):
            handles.append(block.register_forward_pre_hook(waiter(event)))

        def finish() -> None:
            for h in handles:
                h.remove()
            torch.cuda.current_stream(self.device).wait_stream(side)

        return finish

    def release(self) -> None:
        """Move the resident network back to the CPU (its pinned master copy); frees its device memory."""
        if self.resident is None:
            return
        module = self.modules[self.resident]
        for t, home in zip(_tensors(module), self._home[self.resident], strict=True):
            t.data = home
        self.resident = None
