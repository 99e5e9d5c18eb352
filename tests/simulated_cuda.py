"""A simulated CUDA device for CPU-only machines: tensors that say ``cuda:0`` and compute on the CPU.

Inside :func:`simulated_cuda`, ``torch.cuda.is_available()`` is True, a tensor created with ``device="cuda"``
or moved with ``.to("cuda")`` / ``.cuda()`` is a :class:`SimulatedCudaTensor` (its values are a CPU tensor,
its ``device`` is ``cuda:0``), and every ATen op checks its tensor arguments' devices the way PyTorch's CUDA
kernels do (CPU tensors of zero dimensions may join a CUDA op, index tensors and copies may cross devices)
before it runs on the CPU values. So the library's code paths for CUDA run on CI, and what breaks on a GPU
for device reasons breaks here with PyTorch's own message:

* an op mixing a CUDA tensor with a CPU tensor made without ``device=`` → ``RuntimeError: Expected all
  tensors to be on the same device, but found at least two devices, cuda:0 and cpu!``;
* ``.numpy()`` of a CUDA tensor → ``TypeError: can't convert cuda:0 device type tensor to numpy``.

The values are the CPU kernels' (no TF32; ``torch.autocast("cuda")`` casts as on a GPU, then the CPU computes
in that dtype; draws on "cuda" come from the CPU's generator; an op whose CUDA kernel computes another function than
the CPU's runs as CUDA's, :data:`CUDA_SEMANTICS`), so a run on the simulated device can be compared
with the CPU run of the same code path. Model offload's in-place moves (``tensor.data = cuda_tensor`` and back)
are simulated too.

Two ways to use it:

* in a test's process, ``with simulated_cuda():`` — no autograd: torch needs a CUDA device guard and CUDA
  hooks to record a graph of CUDA tensors, which a CPU-only build lacks (an op on a tensor that requires grad
  raises here instead of aborting the process; forwards run under ``torch.no_grad()``); the Python bindings
  that would enter the device (indexing, ``.to("cuda")``, ``.item()``…) are computed on the CPU values, and
  SDPA runs the CPU's kernel;
* a whole pytest run with tests/simulated_cuda_plugin.py, which loads tests/simulated_cuda_runtime.cpp (that
  guard and those hooks) before torch: autograd runs (:data:`RUNTIME`), so does every binding.

Streams are simulated for their ordering: the current stream runs everything at once, and a copy into a CUDA tensor
issued on another stream (``with torch.cuda.stream(side):``) lands only when a stream waits for it (``wait_event``
of an event recorded after it, ``wait_stream``, ``synchronize``); until then its destination holds NaN (integers:
the dtype's smallest value), so a kernel that reads a prefetched tensor before waiting for it computes garbage
here, as it may on a GPU (:class:`_Stream`).

Neither can run CUDA-only kernels (gsplat: the PyTorch tile path renders), ``torch.compile`` (it does not trace a
dispatch mode), pinned memory, memory figures (reported as 0) or measure speed. Nothing leaks out of
the block: the patches are undone and a simulated tensor used after it raises.
"""
from __future__ import annotations

import contextlib
import os
import types
from unittest import mock

import torch
from torch.overrides import TorchFunctionMode
from torch.utils import _pytree
from torch.utils._python_dispatch import TorchDispatchMode

from diff4splat.render.rasterize import NO_GSPLAT_ENV, gsplat_available

NAME = "simulated CUDA (CPU)"
"""``torch.cuda.get_device_name()`` inside :func:`simulated_cuda`."""
CUDA = torch.device("cuda", 0)
CPU = torch.device("cpu")
RUNTIME = torch.version.cuda is None and torch.accelerator.current_accelerator() == torch.device("cuda")
"""Whether tests/simulated_cuda_runtime.cpp is loaded (tests/simulated_cuda_plugin.py): a CPU-only torch that
sees a CUDA accelerator. Then autograd runs, and the Python bindings that enter the device work as they are."""
CROSS_DEVICE_OPS = frozenset({
    torch.ops.aten.copy_.default, torch.ops.aten._to_copy.default, torch.ops.aten.copy.default,
    torch.ops.aten._copy_from.default, torch.ops.aten._copy_from_and_resize.default,
})
"""Ops that move values between devices: their arguments may sit on different devices."""
INDEX_OPS = frozenset({
    torch.ops.aten.index.Tensor, torch.ops.aten.index_put_.default, torch.ops.aten.index_put.default,
    torch.ops.aten._index_put_impl_.default,
})
"""Ops whose index tensors (argument 1, a list) may be CPU tensors indexing a CUDA tensor (not the reverse: a CPU
tensor indexed by CUDA indices raises IndexError, ATen's ``check_indices_on_cpu_or_selfdevice``)."""
SCALAR_VALUE_OPS = INDEX_OPS | frozenset({
    torch.ops.aten.masked_fill_.Tensor, torch.ops.aten.masked_fill.Tensor, torch.ops.aten.fill_.Tensor,
    torch.ops.aten.fill.Tensor,
})
"""Ops beside the elementwise ones whose value may be a CPU tensor of zero dimensions (read as a number)."""


_LEAVES = (type(None), bool, int, float, complex, str, torch.dtype, torch.device, torch.layout, torch.memory_format)
"""Types that torch's pytree takes as leaves, checked first: :func:`tree_leaves` and :func:`tree_map` run for every
op, and torch.utils._pytree's generic walk was a third of a simulated run's time."""


def tree_leaves(tree) -> list:
    """``torch.utils._pytree.tree_leaves``, walking plain lists, tuples and dicts (what ATen ops take and return) itself
    and handing anything else (torch.Size, named tuples…) to pytree."""
    t = type(tree)
    if t is list or t is tuple:
        out = []
        for x in tree:
            if isinstance(x, torch.Tensor) or type(x) in _LEAVES:
                out.append(x)
            else:
                out.extend(tree_leaves(x))
        return out
    if t is dict:
        return tree_leaves(list(tree.values()))
    if isinstance(tree, torch.Tensor) or t in _LEAVES:
        return [tree]
    return _pytree.tree_leaves(tree)


def tree_map(fn, tree):
    """``torch.utils._pytree.tree_map`` (one tree), walking plain lists, tuples and dicts itself as :func:`tree_leaves`
    does."""
    t = type(tree)
    if t is list or t is tuple:
        out = [fn(x) if isinstance(x, torch.Tensor) or type(x) in _LEAVES else tree_map(fn, x) for x in tree]
        return out if t is list else tuple(out)
    if t is dict:
        return {k: tree_map(fn, v) for k, v in tree.items()}
    if isinstance(tree, torch.Tensor) or t in _LEAVES:
        return fn(tree)
    return _pytree.tree_map(fn, tree)


class SimulatedCudaTensor(torch.Tensor):
    """A tensor whose ``device`` is ``cuda:0`` and whose values are the CPU tensor ``elem``."""

    elem: torch.Tensor  # no __slots__: a CPU tensor moved in place takes this class (:func:`_set_data`)

    @staticmethod
    def __new__(cls, elem: torch.Tensor):
        assert elem.device.type == "cpu" and not isinstance(elem, SimulatedCudaTensor)
        out = torch.Tensor._make_wrapper_subclass(
            cls, elem.size(), strides=elem.stride(), storage_offset=elem.storage_offset(), dtype=elem.dtype,
            layout=elem.layout, requires_grad=elem.requires_grad, device=CUDA)
        out.elem = elem
        return out

    def __repr__(self):
        return f"SimulatedCudaTensor({self.elem!r})"

    def numpy(self, *args, **kwargs):
        raise TypeError("can't convert cuda:0 device type tensor to numpy. Use Tensor.cpu() to copy the tensor "
                        "to host memory first.")

    __torch_function__ = torch._C._disabled_torch_function_impl

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        raise RuntimeError(f"{func}: a simulated CUDA tensor used outside simulated_cuda()")


def _is_cuda(device) -> bool:
    return device is not None and torch.device(device).type == "cuda"


def _check_devices(func, args, kwargs) -> torch.device | None:
    """The common device of ``func``'s tensor arguments (None if it has none), raising PyTorch's error where a
    CUDA kernel would: tensors on different devices, except the arguments of :data:`CROSS_DEVICE_OPS`, the
    index tensors of :data:`INDEX_OPS`, and CPU tensors of zero dimensions in elementwise ops (TensorIterator's
    CPU scalars: ops tagged ``pointwise``) and in :data:`SCALAR_VALUE_OPS`."""
    flat = []
    for i, a in enumerate(args):
        if func in INDEX_OPS and i == 1:  # indices: CPU or the indexed tensor's device ("dev_tensor[{cpu,dev}_tensor]")
            if not isinstance(args[0], SimulatedCudaTensor) and any(
                    isinstance(x, SimulatedCudaTensor) for x in tree_leaves(a)):
                raise IndexError(f"indices should be either on cpu or on the same device as the indexed tensor "
                                 f"({args[0].device}) (simulated CUDA, in {func})")
            continue
        flat.extend(x for x in tree_leaves(a) if isinstance(x, torch.Tensor))
    flat.extend(x for x in tree_leaves(kwargs) if isinstance(x, torch.Tensor))
    scalars_ok = torch.Tag.pointwise in getattr(func, "tags", ()) or func in SCALAR_VALUE_OPS
    devices = {CUDA if isinstance(x, SimulatedCudaTensor) else x.device for x in flat
               if isinstance(x, SimulatedCudaTensor) or x.dim() > 0 or not scalars_ok}
    if func not in CROSS_DEVICE_OPS and len(devices) > 1:
        raise RuntimeError("Expected all tensors to be on the same device, but found at least two devices, "
                           f"{', '.join(sorted(str(d) for d in devices))}! (simulated CUDA, in {func})")
    if any(isinstance(x, SimulatedCudaTensor) for x in flat):
        return CUDA
    return CPU if flat else None


class _Stream:
    """A simulated CUDA stream (module docstring): copies into CUDA tensors issued while it is current and not the
    default stream are held, their destinations filled with NaN (integers: the dtype's smallest value), until a
    wait lands them."""

    def __init__(self, device=None, priority: int = 0):
        self.held: list[tuple[int, torch.Tensor, torch.Tensor]] = []  # (sequence number, destination, source)
        self.issued = 0
        _STREAMS.all.append(self)

    def hold(self, dst: torch.Tensor, src: torch.Tensor) -> None:
        """Issue the copy ``src`` → ``dst`` (CPU values) on this stream."""
        self.held.append((self.issued, dst, src.clone()))
        self.issued += 1
        dst.fill_(float("nan") if dst.is_floating_point() else torch.iinfo(dst.dtype).min if dst.dtype != torch.bool
                  else False)

    def land(self, upto: int) -> None:
        """Complete the copies issued before sequence number ``upto``."""
        for _, dst, src in (h for h in self.held if h[0] < upto):
            dst.copy_(src)
        self.held = [h for h in self.held if h[0] >= upto]

    def wait_event(self, event: _Event) -> None:
        if event.stream is not None:
            event.stream.land(event.count)

    def wait_stream(self, stream: _Stream) -> None:
        stream.land(stream.issued)

    def synchronize(self) -> None:
        self.land(self.issued)


class _Event:
    """A simulated CUDA event: the point of a :class:`_Stream`'s work it was recorded at (``record``; streams
    wait for it with ``wait_event``)."""

    def __init__(self, *args, **kwargs):
        self.stream: _Stream | None = None
        self.count = 0

    def record(self, stream: _Stream | None = None) -> None:
        self.stream = stream or _STREAMS.current[-1]
        self.count = self.stream.issued


_STREAMS = types.SimpleNamespace(all=[], current=[])
"""The simulated streams of the running :func:`simulated_cuda` block; ``current[-1]`` is the current one,
``current[0]`` the default."""


@contextlib.contextmanager
def _stream_context(stream: _Stream | None):
    """``torch.cuda.stream(stream)``: ``stream`` is current in the block (None: no change)."""
    _STREAMS.current.append(stream or _STREAMS.current[-1])
    try:
        yield
    finally:
        _STREAMS.current.pop()


def _synchronize(*args, **kwargs) -> None:
    for stream in _STREAMS.all:
        stream.synchronize()


def _copy(dst: torch.Tensor, src: torch.Tensor, *args, **kwargs) -> torch.Tensor:
    """``dst.copy_(src)`` on the values; held back when another stream than the default is current and ``dst`` is
    on the simulated device (:class:`_Stream`)."""
    stream = _STREAMS.current[-1]
    if stream is not _STREAMS.current[0] and isinstance(dst, SimulatedCudaTensor):
        stream.hold(dst.elem, _unwrap(src).to(dst.dtype))
    else:
        _unwrap(dst).copy_(_unwrap(src), *args, **kwargs)
    return dst


class _Dispatch(TorchDispatchMode):
    """Runs every ATen op on the CPU values after :func:`_check_devices`; outputs land on the device that
    CUDA would give them (the ``device=`` keyword, else the inputs' common device)."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        common = _check_devices(func, args, kwargs)
        if func is torch.ops.aten._pin_memory.default:
            return args[0]
        if func is torch.ops.aten.is_pinned.default:
            return False
        if func is torch.ops.aten.copy_.default:
            return _copy(*args, **kwargs)
        to_cuda = common == CUDA
        if "device" in kwargs:
            to_cuda = _is_cuda(kwargs["device"])
            kwargs["device"] = CPU if to_cuda else kwargs["device"]
        wrappers = {id(x.elem): x for x in tree_leaves((args, kwargs)) if isinstance(x, SimulatedCudaTensor)}
        impl = CUDA_SEMANTICS.get(func, func) if to_cuda else func
        result = impl(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))

        def back(x):  # an in-place op's (or out=) result is its argument; a new CPU tensor goes to CUDA if due
            if isinstance(x, torch.Tensor) and id(x) in wrappers:
                return wrappers[id(x)]
            return _wrap(x) if to_cuda else x

        return tree_map(back, result)


def _addmm_activation_cuda(bias, mat1, mat2, beta=1, alpha=1, use_gelu=False):
    """``aten._addmm_activation`` as CUDA computes it: addmm, then GELU in its tanh form (cuBLASLt's epilogue, and
    ATen's CUDA fallback ``gelu_(result, "tanh")``) or ReLU. The CPU kernel applies the erf GELU."""
    out = torch.addmm(bias, mat1, mat2, beta=beta, alpha=alpha)
    return torch.nn.functional.gelu(out, approximate="tanh") if use_gelu else torch.relu(out)


CUDA_SEMANTICS = {torch.ops.aten._addmm_activation.default: _addmm_activation_cuda}
"""Ops whose CUDA kernel computes something else than the CPU's: run on the simulated device as CUDA runs them."""


ON_VALUES = frozenset({
    torch.Tensor.nonzero, torch.nonzero, torch.Tensor.item, torch.Tensor.__int__,
    torch.Tensor.__float__, torch.Tensor.__bool__, torch.Tensor.__index__, torch.Tensor.__format__,
    torch.Tensor.__invert__, torch.Tensor.contiguous,
    torch.nn.functional.scaled_dot_product_attention,
})
"""Functions called on the CPU values: tensor methods whose Python bindings enter the tensor's device before
any ATen op (so a CPU-only build refuses ``cuda``), and SDPA, which would otherwise pick its kernel by the
device (the math kernel: not the CPU's arithmetic; on a CUDA build, CUDA's kernels, which refuse CPU values),
whether the tensors come by position or by keyword (diffusers' attention passes ``query=``…)."""


NO_GRAPH = frozenset({
    "__get__", "__set__", "numel", "nelement", "element_size", "dim", "size", "stride", "storage_offset",
    "is_contiguous", "is_floating_point", "is_complex", "data_ptr", "__len__", "__hash__", "__repr__",
    "requires_grad_", "detach", "detach_", "_has_compatible_shallow_copy_type",
})
"""Tensor functions that record no autograd graph (metadata, ``.detach()``): allowed on a tensor that requires
grad outside ``torch.no_grad()``; so are ``torch.nn.init``'s functions (they run under ``torch.no_grad()``)."""


class _Functions(TorchFunctionMode):
    """What a CPU-only build refuses before an ATen op is dispatched (``Tensor.to("cuda")``, ``.cuda()``,
    ``torch.tensor(…, device="cuda")``, indexing, ``copy_``, ``pin_memory`` and :data:`ON_VALUES`), written as the
    ops they stand for on the CPU values (with the runtime loaded only ``torch.tensor(…, device="cuda")``,
    ``new_tensor`` and list indices need that); and autograd without the runtime, refused with a message."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if not RUNTIME and torch.is_grad_enabled() and getattr(func, "__name__", "") not in NO_GRAPH \
                and getattr(func, "__module__", "") != "torch.nn.init" \
                and any(isinstance(x, SimulatedCudaTensor) and x.requires_grad for x in tree_leaves((args, kwargs))):
            raise RuntimeError(f"simulated CUDA has no autograd (torch aborts on it): {func} of a tensor that "
                               "requires grad; run the forward under torch.no_grad()")
        if getattr(func, "__name__", "") == "__set__" and getattr(func, "__self__", None) is DATA:
            return _set_data(*args)
        if func is torch.Tensor.pin_memory:
            return args[0]
        if kwargs.get("pin_memory") and getattr(func, "__module__", "").startswith("torch"):  # a factory's pinned
            kwargs = {**kwargs, "pin_memory": False}  # host memory: plain memory here, as pin_memory() above
        if func is torch.Tensor.tolist and isinstance(args[0], SimulatedCudaTensor):  # refused for subclasses
            return args[0].elem.tolist()
        if func in (torch.tensor, torch.as_tensor) and _is_cuda(kwargs.get("device")):
            if isinstance(args[0], SimulatedCudaTensor):
                return args[0] if func is torch.as_tensor and kwargs.get("dtype") in (None, args[0].dtype) \
                    else args[0].to(kwargs.get("dtype") or args[0].dtype, copy=func is torch.tensor)
            return _wrap(func(*args, **{**kwargs, "device": CPU}))
        if func is torch.Tensor.new_tensor and isinstance(args[0], SimulatedCudaTensor) \
                and _is_cuda(kwargs.get("device", CUDA)):  # like torch.tensor: made apart from the dispatcher
            return _wrap(args[0].elem.new_tensor(*args[1:], **{**kwargs, "device": CPU}))
        if RUNTIME:  # the bindings below enter the device, which the runtime provides
            if func in (torch.Tensor.__getitem__, torch.Tensor.__setitem__):  # a list index becomes a tensor
                args = (args[0], _list_indices_as_tensors(args[1]), *args[2:])  # made apart from the dispatcher
            return func(*args, **kwargs)
        if func is torch.Tensor.cuda:
            return _move(args[0], CUDA, kwargs.get("non_blocking", False))
        if func is torch.Tensor.to:
            device, dtype, non_blocking, _ = torch._C._nn._parse_to(*args[1:], **kwargs)
            if device is not None and _is_cuda(device):
                out = _move(args[0], CUDA, non_blocking)
                return out if dtype is None else out.to(dtype)
        if func is torch.Tensor.copy_:  # any devices: a copy
            return _copy(*args, **kwargs)
        if func is torch.Tensor.__getitem__ and isinstance(args[0], SimulatedCudaTensor):
            return _wrap(args[0].elem[_index(args[1])])
        if func is torch.Tensor.__setitem__ and isinstance(args[0], SimulatedCudaTensor):
            value = args[2]
            if isinstance(value, torch.Tensor) and not isinstance(value, SimulatedCudaTensor) and value.dim() > 0:
                _check_devices(torch.ops.aten.index_put_.default, (args[0], None, value), {})
            args[0].elem[_index(args[1])] = _unwrap(value)
            return None
        if func in ON_VALUES and any(isinstance(a, SimulatedCudaTensor) for a in tree_leaves((args, kwargs))):
            _check_devices(func, args, kwargs)
            to_cuda = _is_cuda(kwargs.pop("device", CUDA))
            out = func(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))
            return tree_map(_wrap, out) if to_cuda else out
        return func(*args, **kwargs)


DATA = torch._C.TensorBase.__dict__["data"]
"""The ``tensor.data`` descriptor: its ``__set__`` moves a tensor in place (model offload)."""


def _set_data(target: torch.Tensor, value: torch.Tensor) -> None:
    """``target.data = value`` where either side may be a simulated CUDA tensor. torch copies ``value``'s
    metadata (device, dispatch keys) into ``target``; the simulation then gives ``target`` the class and values
    that go with them: a CPU tensor moved to "cuda" becomes a :class:`SimulatedCudaTensor` (its own class kept
    to return to), and one moved back returns to its class."""
    DATA.__set__(target, value)
    if isinstance(value, SimulatedCudaTensor):
        if not isinstance(target, SimulatedCudaTensor):
            target.__dict__["_simulated_from"] = type(target), getattr(target, "_is_param", None)
            target._is_param = isinstance(target, torch.nn.Parameter)  # isinstance(…, Parameter) stays true
            target.__class__ = SimulatedCudaTensor
        target.elem = value.elem
    elif isinstance(target, SimulatedCudaTensor):
        if "_simulated_from" not in target.__dict__:
            raise NotImplementedError("simulated CUDA: a tensor made on cuda cannot be moved to the CPU in place")
        cls, is_param = target.__dict__.pop("_simulated_from")
        del target.elem
        target.__class__ = cls
        if is_param is None:
            del target._is_param
        else:
            target._is_param = is_param


def _unwrap(x):
    return x.elem if isinstance(x, SimulatedCudaTensor) else x


def _wrap(x):
    return SimulatedCudaTensor(x) if isinstance(x, torch.Tensor) and x.device == CPU else x


def _index(index):
    """A Python index (int, slice, None, Ellipsis, tensors, or a tuple of them) with its tensors' CPU values:
    CUDA indexing takes index tensors on the CPU or on the indexed tensor's device."""
    return tuple(_unwrap(i) for i in index) if isinstance(index, tuple) else _unwrap(index)


def _list_indices_as_tensors(index):
    """A Python index with its lists as CPU index tensors (CUDA indexing takes those, through the dispatcher)."""
    if isinstance(index, tuple):
        return tuple(_list_indices_as_tensors(i) for i in index)
    return torch.tensor(index, device="cpu") if isinstance(index, list) else index


def _move(t: torch.Tensor, device: torch.device, non_blocking: bool) -> torch.Tensor:
    if isinstance(t, SimulatedCudaTensor):
        return t
    return torch.ops.aten._to_copy.default(t, device=device, non_blocking=non_blocking)


@contextlib.contextmanager
def simulated_cuda():
    """Within this block ``cuda`` is a device of this machine: see the module's docstring."""
    zero = lambda *a, **k: 0  # noqa: E731
    stack = contextlib.ExitStack()
    patches = [
        mock.patch("torch.cuda.is_available", lambda: True),
        mock.patch("torch.cuda._lazy_init", lambda: None),
        mock.patch("torch.cuda.device_count", lambda: 1),
        mock.patch("torch.cuda.current_device", lambda: 0),
        mock.patch("torch.cuda.set_device", lambda *a, **k: None),
        mock.patch("torch.cuda.synchronize", _synchronize),
        mock.patch("torch.cuda.Stream", _Stream),
        mock.patch("torch.cuda.Event", _Event),
        mock.patch("torch.cuda.stream", _stream_context),
        mock.patch("torch.cuda.current_stream", lambda *a, **k: _STREAMS.current[-1]),
        mock.patch("torch.cuda.default_stream", lambda *a, **k: _STREAMS.current[0]),
        mock.patch("torch.cuda.max_memory_allocated", zero),
        mock.patch("torch.cuda.memory_allocated", zero),
        mock.patch("torch.cuda.reset_peak_memory_stats", lambda *a, **k: None),
        mock.patch("torch.cuda.mem_get_info", lambda *a, **k: (0, 0)),  # (free, total): no room for anything
        mock.patch("torch.cuda.empty_cache", lambda: None),
        mock.patch("torch.cuda.get_device_name", lambda *a: NAME),
        mock.patch("torch.cuda.get_device_properties", lambda *a: types.SimpleNamespace(
            name=NAME, total_memory=0, major=0, minor=0, multi_processor_count=0)),
        mock.patch("torch.cuda.is_bf16_supported", lambda *a, **k: True),
        # CUDA's generators: draws on "cuda" come from the CPU's (the ops run there); their states are empty
        mock.patch("torch.cuda.get_rng_state", lambda *a, **k: torch.empty(0, dtype=torch.uint8, device="cpu")),
        mock.patch("torch.cuda.get_rng_state_all", lambda: [torch.empty(0, dtype=torch.uint8, device="cpu")]),
        mock.patch("torch.cuda.set_rng_state", lambda *a, **k: None),
        mock.patch("torch.cuda.set_rng_state_all", lambda *a, **k: None),
        mock.patch("torch.cuda.manual_seed", lambda *a, **k: None),
        mock.patch("torch.cuda.manual_seed_all", lambda *a, **k: None),
        mock.patch.dict(os.environ, {NO_GSPLAT_ENV: "1"}),  # gsplat's kernels need a real GPU
    ]
    gsplat_available.cache_clear()
    stack.callback(gsplat_available.cache_clear)
    overwrite = torch.__future__.get_overwrite_module_params_on_conversion()
    torch.__future__.set_overwrite_module_params_on_conversion(True)  # Module.to: new Parameters, not .data =
    stack.callback(torch.__future__.set_overwrite_module_params_on_conversion, overwrite)
    _STREAMS.all, _STREAMS.current = [], []
    _STREAMS.current.append(_Stream())  # the default stream
    stack.callback(_STREAMS.__init__, all=[], current=[])
    with stack:
        for p in patches:
            stack.enter_context(p)
        stack.enter_context(_Functions())
        stack.enter_context(_Dispatch())
        yield
