"""Model CPU offload: networks live in (pinned) CPU memory and visit the compute device one at a time, only while they
run, so the peak is the largest network (docs/DESIGN.md, "Devices"; diffusers' ``enable_model_cpu_offload``).
Inference only: the CPU copy is the master (weights changed on the device are lost). On CUDA the copies are pinned
in shared blocks (:func:`pin_packed`), since torch's pinned allocator rounds each allocation up to a power of two.
Prefetch (CUDA only) copies a network on a side stream block by block, each block waiting only for its own weights
(diffusers' group offloading with ``use_stream``, once per visit)."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import nn

__all__ = ["ModelOffload", "prefetch_groups", "weight_bytes", "pin_plan", "pin_packed", "pinned_bytes",
           "PIN_BLOCK_BYTES"]

PIN_BLOCK_BYTES = 1 << 29
"""Bytes of one pinned host block that weights share (512 MiB, a power of two); a larger weight gets its own block."""
PIN_ALIGN = 64
"""Byte alignment of each weight in a block."""


def _tensors(module: nn.Module) -> Iterator[torch.Tensor]:
    """The parameters, then the buffers, of ``module`` (each shared tensor once)."""
    yield from module.parameters()
    yield from (b for b in module.buffers() if b is not None)


def weight_bytes(module: nn.Module) -> list[int]:
    """Bytes of each parameter, then buffer, of ``module`` (shared tensors once), in :func:`pin_plan`'s order."""
    return [t.numel() * t.element_size() for t in _tensors(module)]


def prefetch_groups(module: nn.Module, blocks: Sequence[nn.Module]) -> list[list[int]]:
    """The copy order of :class:`ModelOffload`'s prefetch: indices into ``list(_tensors(module))`` as ``[rest, block 0,
    block 1, …]``; ``rest`` holds every tensor outside ``blocks`` or shared by two of them. Each tensor is in one group.

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
    """What torch's pinned-memory allocator pins for ``n`` bytes: n rounded up to a power of two."""
    return 1 << max(n - 1, 0).bit_length() if n else 0


def pin_plan(nbytes: Sequence[int], block: int = PIN_BLOCK_BYTES) -> tuple[list[int], list[tuple[int, int]]]:
    """Where :func:`pin_packed` puts tensors of ``nbytes`` bytes: (the blocks' sizes, (block, byte offset) of each
    tensor). First fit in order, offsets multiples of :data:`PIN_ALIGN`; a tensor larger than ``block`` gets a block of
    its own; a block whose tensors alone would pin less than it does is split into one block per tensor."""
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
    """Host bytes :func:`pin_packed` pins for tensors of ``nbytes`` bytes (each block rounded up to a power of two)."""
    return sum(_pow2(size) for size in pin_plan(nbytes, block)[0])


def pin_packed(tensors: Sequence[torch.Tensor], block: int = PIN_BLOCK_BYTES, pin: bool = True) -> None:
    """Move CPU ``tensors`` into shared blocks laid out by :func:`pin_plan`, in place (each ``.data`` becomes a view of
    its block). Each original is dropped once copied, so the peak is the weights plus about one block. ``pin=False``
    allocates plain blocks."""
    sizes, where = pin_plan([t.numel() * t.element_size() for t in tensors], block)  # weight_bytes' order
    blocks: dict[int, torch.Tensor] = {}
    for t, (k, offset) in zip(tensors, where, strict=True):
        if k not in blocks:
            blocks[k] = torch.empty(sizes[k], dtype=torch.uint8, device="cpu", pin_memory=pin)  # not a copy
        view = blocks[k][offset:offset + t.numel() * t.element_size()].view(t.dtype).view(t.shape)
        view.copy_(t.data)
        t.data = view


class ModelOffload:
    """Keep the networks of ``modules`` (name → network, moved to the CPU here) on the CPU and move one at a time to
    ``device`` (module docstring; on the CPU nothing moves). ``pin``: pin the copies when ``device`` is CUDA.
    ``prefetch``: name → that network's blocks in the order its forward runs them (as non-compiled modules), whose
    move onto a CUDA device overlaps its first call; ignored off CUDA.

    Raises:
        ValueError: ``prefetch`` names a network not in ``modules``, or blocks that are not its submodules.

    Attributes:
        resident: the name of the network now on ``device``, or None.
        pinned: whether the CPU copies are pinned.
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
        """Bytes of host memory the CPU copies hold (their pinned blocks where pinned)."""
        sizes = [weight_bytes(module) for module in self.modules.values()]
        return sum(pinned_bytes(s) if self.pinned else sum(s) for s in sizes)

    @contextmanager
    def use(self, name: str) -> Iterator[nn.Module]:
        """The network ``name``, on the device for the body of the ``with`` (the previous resident goes back first); it
        stays resident until another is used or :meth:`release` is called.

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
        """Start copying ``name`` to the CUDA device on a side stream, group by group; returns the call that removes the
        visit's hooks and makes the current stream wait for every copy."""
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
        """Move the resident network back to its CPU master copy, freeing its device memory."""
        if self.resident is None:
            return
        module = self.modules[self.resident]
        for t, home in zip(_tensors(module), self._home[self.resident], strict=True):
            t.data = home
        self.resident = None
