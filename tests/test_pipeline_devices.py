"""The generation pipeline on every device, in bfloat16 and with model CPU offload (diff4splat/utils/offload.py)."""
import numpy as np
import pytest
import torch
from helpers import tiny_model
from torch._dynamo.utils import counters
from torch.nn.attention import SDPBackend, sdpa_kernel

import models.layers
import models.text_encoder
from diff4splat.assembly.assemble import to_gaussians
from diff4splat.cameras import intrinsics_from_fov
from diff4splat.onnx_runtime import OnnxRuntime
from diff4splat.pipeline import Diff4SplatPipeline, load_model
from diff4splat.render.rasterize import gsplat_available
from diff4splat.runtime import ATTENTION_KERNELS, TorchRuntime, attention_priority
from diff4splat.utils.offload import (
    PIN_ALIGN,
    ModelOffload,
    _tensors,
    pin_packed,
    pin_plan,
    pinned_bytes,
    prefetch_groups,
    weight_bytes,
)
from models.bundle import Diff4SplatModel, load_config
from models.ldrm import LDRMConfig, LDRMOutput, gaussian_activations
from models.pretrained import skip_init

PROMPT = "a cat turns its head"


@pytest.fixture(scope="module")
def image():
    return torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(0), device="cpu")


def _run(image, device="cpu", **kw):
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True, active_dit=True), device, **kw)
    return pipe, pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)


_REFERENCES = {}


def _reference(image, device="cpu"):
    """The result of ``_run(image, device)`` (no options), made once per process for each device and, on CUDA,
    each TF32 and gsplat setting (``full_float32``, ``torch_tile_path``: they change only CUDA's kernels): the
    tests compare their own fresh runs with it and none changes it. Runs that observe something while they run
    (the attention spy, the memory high water) make their own."""
    device = torch.device(device)
    key = (device.type,) if device.type == "cpu" else (
        str(device), torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32, gsplat_available())
    if key not in _REFERENCES or not torch.equal(_REFERENCES[key][0], image):
        _REFERENCES[key] = image.clone(), _run(image, device)[1]
    return _REFERENCES[key][1]


def _close_scenes(a, b, atol, sh_atol):
    """The Gaussians both runs kept (matched by ``gaussian_index``) agree to ``atol``, their SH to ``sh_atol``;
    pruning decisions at its thresholds may differ for a few Gaussians (≤ 0.5 %) whose values sit on the
    boundary."""
    ia, ib = a.gaussian_index.cpu(), b.gaussian_index.cpu()
    common = torch.from_numpy(np.intersect1d(ia.numpy(), ib.numpy()))
    assert len(common) >= 0.995 * max(len(ia), len(ib))
    pa, pb = torch.searchsorted(ia, common), torch.searchsorted(ib, common)
    ga, gb = a.scene.canonical, b.scene.canonical
    for name in ("means", "quats", "scales", "opacities", "sh"):
        torch.testing.assert_close(getattr(ga, name).cpu()[pa], getattr(gb, name).cpu()[pb], rtol=0,
                                   atol=sh_atol if name == "sh" else atol, msg=lambda m, name=name: f"{name}: {m}")
    torch.testing.assert_close(a.scene.d_means.cpu()[:, pa], b.scene.d_means.cpu()[:, pb], atol=atol, rtol=0)


@pytest.mark.slow
def test_generate_on_each_device_matches_the_cpu(image, device, full_float32, torch_tile_path):
    """The CUDA run starts from the same noise (CPU generator) and gives the CPU's scene to float32 accuracy;
    every output lives on the pipeline's device. Both render through our rasterizer (the photo layer's colours
    are solved through renders at the input camera); gsplat's run is checked below."""
    ref = _reference(image)
    pipe, res = _run(image, device)
    assert res.scene.canonical.means.device.type == device.type and res.latents.device.type == device.type
    assert res.scene.d_means is not None
    torch.testing.assert_close(res.latents.cpu(), ref.latents, atol=1e-4, rtol=0)
    if device.type == "cpu":
        assert torch.equal(res.scene.canonical.means, ref.scene.canonical.means)
    else:  # the photo layer's colours are solved through renders (photo.refine_colors), whose fixed point moves
        # with the geometry's rounding: on an H100, 2 % of them by 1e-3 to 6.5e-3 in SH (2e-3 in RGB)
        _close_scenes(res, ref, atol=1e-3, sh_atol=1e-2)
        assert res.photo_psnr_db == pytest.approx(ref.photo_psnr_db, abs=0.05)


@pytest.mark.cuda
@pytest.mark.slow
def test_generate_on_cuda_with_gsplat_keeps_the_cpus_geometry_and_photo_fidelity(image, full_float32):
    """With gsplat rendering (where installed) the networks' geometry is the CPU's and the photo layer, whose
    colours are solved through gsplat's renders, reproduces the photo as well as on the CPU (±0.5 dB): the
    rasterizers differ by their documented differences only (tests/test_render_gsplat_backend.py)."""
    ref = _reference(image)
    _, res = _run(image, "cuda")
    torch.testing.assert_close(res.latents.cpu(), ref.latents, atol=1e-4, rtol=0)
    ia, ib = res.gaussian_index.cpu(), ref.gaussian_index.cpu()
    common = torch.from_numpy(np.intersect1d(ia.numpy(), ib.numpy()))
    common = common[common < ref.photo_gaussians]  # the photo layer: its geometry is the networks' depth
    assert len(common) >= 0.9 * int((ib < ref.photo_gaussians).sum())
    pa, pb = torch.searchsorted(ia, common), torch.searchsorted(ib, common)
    torch.testing.assert_close(res.scene.canonical.means.cpu()[pa], ref.scene.canonical.means[pb], atol=1e-3, rtol=0)
    assert res.photo_psnr_db == pytest.approx(ref.photo_psnr_db, abs=0.5)


@pytest.fixture
def cpu_pipe():
    return Diff4SplatPipeline(tiny_model(dynamic=True, active_dit=True), "cpu")


@pytest.mark.slow
def test_the_pipeline_creates_no_tensor_on_the_default_device(image, cpu_pipe, no_implicit_device):
    """Every tensor the pipeline makes is placed beside its inputs: with the default device set to ``meta`` a
    CPU run still completes (a CPU-made tensor beside CUDA inputs crashed `generate --device cuda`)."""
    pipe = cpu_pipe
    res = pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)
    assert res.scene.canonical.means.device.type == "cpu" and res.scene.num_gaussians > 0


@pytest.mark.slow
@pytest.mark.parametrize("offload", ["model", "model-prefetch"])
def test_model_offload_gives_the_same_scene_and_leaves_the_networks_on_the_cpu(image, device, offload):
    """Both offload modes give the scene of keeping the networks on the device (prefetch only reorders the
    copies and kernels) and leave the networks in CPU memory, with no hook left on the DiT's blocks."""
    ref = _reference(image, device)
    pipe, res = _run(image, device, offload=offload)
    assert torch.equal(res.latents, ref.latents)
    assert torch.equal(res.scene.canonical.means, ref.scene.canonical.means)
    assert pipe.runtime.offload.resident is None  # released after the LDRM
    assert {p.device.type for p in pipe.model.parameters()} == {"cpu"}
    assert not any(b._forward_pre_hooks for b in pipe.runtime.backbone.transformer_blocks())


def test_prefetch_groups_put_each_tensor_in_one_group_in_block_order():
    """[rest, block 0, block 1, …] over ``_tensors``' order (parameters, then buffers): a block's group is its own
    tensors; the embedder, the head, a root buffer and a weight two blocks share go to the rest."""
    embed, head = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
    blocks = torch.nn.ModuleList(torch.nn.Linear(2, 2) for _ in range(3))
    blocks[2].register_buffer("table", torch.zeros(2))
    shared = torch.nn.Linear(2, 2)
    net = torch.nn.Module()
    net.embed, net.blocks, net.head = embed, blocks, head
    net.register_buffer("scale", torch.ones(1))
    net.blocks[0].extra, net.blocks[1].extra = shared, shared  # one module in two blocks
    tensors = [*net.parameters(), *net.buffers()]
    groups = prefetch_groups(net, list(blocks))
    assert sorted(i for g in groups for i in g) == list(range(len(tensors)))
    ids = [{id(tensors[i]) for i in g} for g in groups]
    own = [{id(blocks[k].weight), id(blocks[k].bias)} for k in range(3)]
    assert ids[1] == own[0] and ids[2] == own[1] and ids[3] == own[2] | {id(blocks[2].table)}
    assert ids[0] == {id(t) for t in (embed.weight, embed.bias, head.weight, head.bias, net.scale, shared.weight,
                                      shared.bias)}
    with pytest.raises(ValueError, match="distinct submodules"):
        prefetch_groups(net, [blocks[0], torch.nn.Linear(2, 2)])
    with pytest.raises(ValueError, match="distinct submodules"):
        prefetch_groups(net, [blocks[0], blocks[0]])
    with pytest.raises(ValueError, match="not offloaded"):
        ModelOffload({"dit": net}, "cpu", prefetch={"vae": list(blocks)})


@pytest.mark.real_gpu  # pinned memory, streams
@pytest.mark.cuda
def test_prefetch_on_cuda_gives_the_plain_moves_output():
    """On a GPU, blocks large enough that their copies outlast a block's compute (16 × 64 MB): the first call
    with prefetch (copies on a side stream, each block waiting for its own) equals the plain move's, and a second
    visit after another network's does too; a block that did not wait would read memory still being copied."""
    torch.manual_seed(0)
    blocks = torch.nn.Sequential(*(torch.nn.Linear(4096, 4096) for _ in range(16)))
    x = torch.randn(64, 4096) / 64
    plain = ModelOffload({"dit": blocks}, "cuda")
    with torch.no_grad(), plain.use("dit"):
        ref = blocks(x.cuda()).cpu()
    plain.release()
    off = ModelOffload({"dit": blocks, "other": torch.nn.Linear(2, 2)}, "cuda", prefetch={"dit": list(blocks)})
    with torch.no_grad():
        for _ in range(2):
            with off.use("dit"):
                assert torch.equal(blocks(x.cuda()).cpu(), ref)
            with off.use("other"):
                pass
    assert not any(b._forward_pre_hooks for b in blocks)


def test_prefetch_does_not_combine_with_compile():
    with pytest.raises(ValueError, match="model-prefetch does not combine with --compile"):
        TorchRuntime(tiny_model(), offload="model-prefetch", compile=True)


@pytest.mark.slow
def test_bfloat16_weights_stay_close_to_float32(image):
    """bfloat16 weights (8 bits of mantissa): the latents move by a few 1e-3 after two steps on the tiny
    model; everything the pipeline returns is float32."""
    ref = _reference(image)
    pipe, res = _run(image, dtype=torch.bfloat16)
    assert {p.dtype for p in pipe.model.parameters()} == {torch.bfloat16}
    assert res.latents.dtype == torch.float32 and res.scene.canonical.means.dtype == torch.float32
    err = float((res.latents - ref.latents).abs().max())
    assert 0 < err < 0.05


def test_the_plucker_rays_are_made_once_in_the_runtimes_input_dtype(image, monkeypatch):
    """The pipeline casts its largest input once (runtime.input_dtype: the weights' dtype for TorchRuntime,
    float32 for onnxruntime's graphs): every velocity call and the reconstruction get the same bfloat16 tensor,
    with no float32 copy held beside it, and the scene is the one of casting at every call."""
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True, active_dit=True), "cpu", dtype=torch.bfloat16)
    assert pipe.runtime.input_dtype == torch.bfloat16 and OnnxRuntime.input_dtype == torch.float32
    seen = []
    for name in ("velocity", "reconstruct"):
        real = getattr(pipe.runtime, name)
        monkeypatch.setattr(pipe.runtime, name,
                            lambda *a, real=real, **k: seen.append(k.get("plucker", a[1])) or real(*a, **k))
    res = pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)
    assert len(seen) == 3 and all(p is seen[0] for p in seen) and seen[0].dtype == torch.bfloat16
    monkeypatch.undo()
    pipe.runtime.input_dtype = torch.float32  # the networks cast it themselves: the same values
    again = pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)
    assert torch.equal(res.latents, again.latents)
    assert torch.equal(res.scene.canonical.means, again.scene.canonical.means)


def test_offload_moves_one_network_at_a_time_and_restores_the_cpu_copies():
    """On the CPU nothing moves; the bookkeeping (one resident at a time, release) is the same everywhere."""
    a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 3)
    off = ModelOffload({"a": a, "b": b}, "cpu")
    w = a.weight.data_ptr()
    with off.use("a") as net:
        assert net is a and off.resident is None  # on the CPU nothing is ever resident elsewhere
    assert a.weight.data_ptr() == w
    with pytest.raises(KeyError):
        with off.use("c"):
            pass


def _pow2(n):
    return 1 << (n - 1).bit_length() if n else 0


def test_pin_plan_packs_without_overlap_and_never_pins_more_than_one_allocation_each():
    """Brute force over random sizes (small, around a block, above it): each tensor lies inside its block at an
    aligned offset, no two overlap, a tensor above the block is alone; what is pinned is at least the bytes and at
    most what pinning each tensor alone would pin (every allocation rounded up to a power of two)."""
    block = 4096
    rng = np.random.default_rng(0)
    for _ in range(200):
        nbytes = [int(x) for x in rng.choice([rng.integers(0, 64), rng.integers(64, 2000), rng.integers(2000, 9000)],
                                             size=int(rng.integers(1, 40)))]
        sizes, where = pin_plan(nbytes, block)
        assert len(where) == len(nbytes)
        spans = {}
        for n, (k, off) in zip(nbytes, where, strict=True):
            assert 0 <= off and off + n <= sizes[k] and off % PIN_ALIGN == 0
            spans.setdefault(k, []).append((off, off + n))
            if n > block:
                assert len([w for w in where if w[0] == k]) == 1
        for k, sp in spans.items():
            sp.sort()
            assert all(a[1] <= b[0] for a, b in zip(sp, sp[1:], strict=False)), (nbytes, k)
        assert set(spans) == set(range(len(sizes)))
        assert sum(nbytes) <= pinned_bytes(nbytes, block) <= sum(_pow2(n) for n in nbytes)


def test_pinned_paper_weights_cost_one_percent_not_twenty():
    """The paper-size networks in bfloat16 (counted on the meta device): 33.67 GB of weights pin as 40.55 GB one
    tensor at a time (each rounded up to a power of two) and as at most 1.5 % more than their bytes packed."""
    with torch.device("meta"), skip_init():
        model = Diff4SplatModel(load_config("paper")).to(torch.bfloat16)
    sizes = {name: weight_bytes(net) for name, net in model.networks().items()}
    raw = sum(map(sum, sizes.values()))
    assert sum(_pow2(n) for s in sizes.values() for n in s) / raw > 1.2
    assert sum(pinned_bytes(s) for s in sizes.values()) / raw < 1.015


def test_pin_packed_keeps_values_shapes_and_tied_weights():
    """Packed (plain blocks: pin=False), every weight keeps its values, shape and dtype, the network its output,
    a tied weight stays one tensor; the weights share as many storages as the plan has blocks."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Embedding(7, 5), torch.nn.Linear(5, 7), torch.nn.LayerNorm(7))
    net[1].weight = net[0].weight  # tied (7, 5)
    net.register_buffer("count", torch.tensor(3, dtype=torch.int64))
    net.register_buffer("flag", torch.ones(3, dtype=torch.bool))
    x = torch.tensor([[1, 4, 6]])
    before = [t.detach().clone() for t in _tensors(net)]
    ref = net[2](net[1](net[0](x)))
    tensors = list(_tensors(net))
    plan = pin_plan([t.numel() * t.element_size() for t in tensors], block=128)
    pin_packed(tensors, block=128, pin=False)
    after = list(_tensors(net))
    assert len(after) == len(before) and net[1].weight is net[0].weight
    for a, b in zip(after, before, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape and a.is_contiguous() and torch.equal(a, b)
    assert torch.equal(net[2](net[1](net[0](x))), ref)
    assert len({t.untyped_storage().data_ptr() for t in after}) == len(plan[0])


@pytest.mark.real_gpu  # pinned memory
@pytest.mark.cuda
def test_offload_pins_what_pinned_bytes_says():
    """On a GPU, torch's pinned allocator grows by :func:`pinned_bytes` of each network's weights (its blocks
    rounded up to a power of two: ``host_memory_stats``' "allocated_bytes")."""
    nets = {"a": torch.nn.Linear(1000, 300), "b": torch.nn.Sequential(torch.nn.Linear(3, 5), torch.nn.Linear(5, 9))}
    torch.cuda.init()
    torch._C._host_emptyCache()
    stat = "allocated_bytes.current"
    before = torch.cuda.host_memory_stats().get(stat)
    if before is None:
        pytest.skip(f"torch {torch.__version__}'s host_memory_stats has no {stat!r}")
    ModelOffload(nets, "cuda")
    want = sum(pinned_bytes(weight_bytes(n)) for n in nets.values())
    assert torch.cuda.host_memory_stats()[stat] - before == want
    assert all(t.is_pinned() for n in nets.values() for t in _tensors(n))


@pytest.mark.real_gpu  # pinned memory
@pytest.mark.cuda
def test_offload_on_cuda_moves_the_weights_and_back():
    a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 3)
    off = ModelOffload({"a": a, "b": b}, "cuda")
    assert a.weight.is_pinned()
    with off.use("a"):
        assert a.weight.is_cuda and not b.weight.is_cuda
    with off.use("b"):
        assert b.weight.is_cuda and not a.weight.is_cuda and off.resident == "b"
    off.release()
    assert not b.weight.is_cuda and off.resident is None


def test_runtime_rejects_unknown_offload_and_dtype():
    with pytest.raises(ValueError, match="offload must be one of"):
        TorchRuntime(tiny_model(), offload="disk")
    with pytest.raises(ValueError, match="dtype must be one of"):
        TorchRuntime(tiny_model(), dtype=torch.int8)


def test_attention_priority_puts_the_named_kernel_first_and_keeps_the_others():
    assert attention_priority("auto") is None
    every = {SDPBackend.CUDNN_ATTENTION, SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH}
    for name, first in ATTENTION_KERNELS.items():
        if first is not None:
            order = attention_priority(name)
            assert order[0] == first and set(order) == every and len(order) == 4
            assert first == SDPBackend.MATH or order[-1] == SDPBackend.MATH  # it takes every call: last
    with pytest.raises(ValueError, match="attention must be one of"):
        attention_priority("flash3")
    with pytest.raises(ValueError, match="attention must be one of"):
        TorchRuntime(tiny_model(), attention="xformers")


@pytest.mark.slow
def test_each_attention_kernel_runs_under_its_order_and_gives_the_same_scene(image, device, monkeypatch):
    """Every attention call of the networks sees the runtime's kernel order (read from torch at call time), every
    kernel stays enabled behind the first, torch's order is restored after the run, and the scene is the same
    up to the kernels' rounding (a kernel that cannot take a call hands it on: the CPU has no cuDNN attention)."""
    real, seen = torch.nn.functional.scaled_dot_product_attention, []

    def spy(*a, **k):
        seen.append(tuple(torch._C._get_sdp_priority_order())[:4])
        return real(*a, **k)

    for module in (models.layers, models.text_encoder):
        monkeypatch.setattr(module.F, "scaled_dot_product_attention", spy)
    before = tuple(torch._C._get_sdp_priority_order())
    _, ref = _run(image, device)
    assert seen and all(o == before[:4] for o in seen)
    for name in ("cudnn", "math"):
        seen.clear()
        pipe, res = _run(image, device, attention=name)
        assert pipe.runtime.attention == name
        assert seen and all(o == tuple(int(b) for b in attention_priority(name)) for o in seen)
        assert tuple(torch._C._get_sdp_priority_order()) == before
        assert torch.backends.cuda.flash_sdp_enabled() and torch.backends.cuda.math_sdp_enabled()
        torch.testing.assert_close(res.latents, ref.latents, atol=1e-4, rtol=0)


@pytest.mark.slow
@pytest.mark.real_gpu  # torch.compile does not trace a dispatch mode
def test_compiled_blocks_give_the_eager_scene(image, device):
    """``compile=True`` compiles every transformer block in place (regional compilation, the rest of the DiT
    eager); the sampled latents equal the eager run's to float32 rounding; the identical blocks share their graphs
    and the steps (a new σ each) reuse them: a second generation compiles nothing."""
    ref = _reference(image, device)
    torch._dynamo.reset()
    counters.clear()
    pipe = Diff4SplatPipeline(tiny_model(dynamic=True, active_dit=True), device, compile=True)
    blocks = pipe.runtime.backbone.transformer_blocks()
    assert pipe.runtime.compiled and len(blocks) == 2 and all(b._compiled_call_impl is not None for b in blocks)
    res = pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)
    torch.testing.assert_close(res.latents, ref.latents, atol=1e-4, rtol=0)
    graphs = counters["stats"]["unique_graphs"]
    assert 1 <= graphs <= 2  # with text; and at most one recompile (σ as a dynamic input)
    again = pipe(image, pipe.default_cameras("arc", 5), PROMPT, steps=2)
    assert counters["stats"]["unique_graphs"] == graphs
    torch.testing.assert_close(again.latents, res.latents, atol=0, rtol=0)


@pytest.mark.cuda
def test_cudnn_attention_matches_the_math_kernel_on_the_dits_layout():
    """cuDNN's fused attention, where the GPU takes it (sm80+; torch prefers FlashAttention-2), on the layout our
    attention hands it ((B, heads, N, head_dim) views of (B, N, heads, head_dim), head_dim 128 as in the paper
    model) in bfloat16 agrees with float32 math attention to bfloat16 rounding, and is the kernel chosen."""
    g = torch.Generator("cuda").manual_seed(0)
    q, k, v = (torch.randn(1, 2048, 4, 128, generator=g, device="cuda", dtype=torch.bfloat16).transpose(1, 2)
               for _ in range(3))
    ref = torch.nn.functional.scaled_dot_product_attention(q.float(), k.float(), v.float())
    with sdpa_kernel(attention_priority("cudnn"), set_priority=True):
        if torch.cuda.get_device_capability() >= (9, 0):
            assert torch._fused_sdp_choice(q, k, v) == int(SDPBackend.CUDNN_ATTENTION)
        out = torch.nn.functional.scaled_dot_product_attention(q, k, v)
    torch.testing.assert_close(out.float(), ref, atol=2e-2, rtol=2e-2)


@pytest.mark.slow
def test_random_models_are_built_in_the_dtype_and_on_the_device_asked_for():
    cfg = load_config("tiny")
    m = Diff4SplatModel.random(cfg, seed=0, dtype=torch.bfloat16)
    assert {p.dtype for p in m.parameters()} == {torch.bfloat16} and torch.get_default_dtype() == torch.float32
    again = Diff4SplatModel.random(cfg, seed=0, dtype=torch.bfloat16)
    assert all(torch.equal(p, q) for p, q in zip(again.parameters(), m.parameters(), strict=True))
    meta = Diff4SplatModel.random(load_config("paper"), device="meta", dtype=torch.bfloat16)
    dit = sum(p.numel() for p in meta.dit.parameters())
    assert meta.dit.blocks[0].attn.qkv.weight.dtype == torch.bfloat16 and dit > 11e9


def test_a_random_model_loads_in_the_dtype_asked_for():
    """`generate --config paper --dtype bfloat16` without weights: the random model is built in bfloat16 (33.7 GB),
    not in float32 (67.3 GB, then cast by the runtime)."""
    with pytest.warns(UserWarning, match="randomly initialised 'tiny' model"):
        model, source = load_model(config="tiny", dtype=torch.bfloat16)
    assert source == "random:tiny:seed=0" and {p.dtype for p in model.parameters()} == {torch.bfloat16}
    built = Diff4SplatModel.random(load_config("tiny"), seed=0, dtype=torch.bfloat16)
    assert all(torch.equal(p, q) for p, q in zip(model.parameters(), built.parameters(), strict=True))
    untrained, _ = load_model(config="tiny", untrained=True, dtype=torch.bfloat16)
    assert {p.dtype for p in untrained.parameters()} == {torch.bfloat16}


def test_gaussians_are_built_in_float32_inside_a_bfloat16_autocast_region():
    """Training renders the LDRM's maps under bf16 autocast: the ray geometry, the Gaussians and the LDRM's
    activations stay float32 (a bfloat16 einsum would move centres by ~0.2 % of their distance)."""
    g = torch.Generator().manual_seed(0)
    raw = torch.randn(1, 2, 8, 8, 12, generator=g, device="cpu")
    out = LDRMOutput(*gaussian_activations(raw.to(torch.bfloat16), LDRMConfig()))
    assert out.distance.dtype == torch.float32
    torch.testing.assert_close(out.distance, gaussian_activations(raw.to(torch.bfloat16).float(), LDRMConfig())[0])
    viewmats = torch.eye(4, device="cpu").repeat(2, 1, 1)
    viewmats[1, 0, 3] = 0.3
    Ks = intrinsics_from_fov(8, 8, fov_y_deg=50.0).expand(2, 3, 3)
    ref, *_ = to_gaussians(out, viewmats, Ks)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got, *_ = to_gaussians(out, viewmats, Ks)
    assert got.means.dtype == torch.float32 and torch.equal(got.means, ref.means)


@pytest.mark.slow
@pytest.mark.real_gpu  # memory figures
def test_high_water_names_the_stage_that_set_the_peak(image, device):
    """GenerationResult.high_water: on CUDA, the device's running peak (bytes) at the end of each timed stage,
    never decreasing, reaching the peak torch reports; empty on the CPU (no allocator statistics)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    _, res = _run(image, device)
    if device.type == "cpu":
        assert res.high_water == {}
        return
    values = list(res.high_water.values())
    assert list(res.high_water) == list(res.timings) and values == sorted(values) and values[0] > 0
    assert values[-1] <= torch.cuda.max_memory_allocated(device)
