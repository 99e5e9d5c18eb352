"""Where a random model is initialised (models.bundle.random_init_device, Diff4SplatModel.random(host=True),
load_model(init_device=)): a GPU with room for the largest network initialises it network by network, each moved
to the CPU as soon as it is built, so the GPU holds one network at a time and the model comes back on the CPU with
that GPU's values; anything else (the CPU, a GPU without room, a device whose memory cannot be read) initialises
on the CPU, as before, with the source unchanged."""
import pytest
import torch

from diff4splat.pipeline import load_model
from models.bundle import INIT_HEADROOM_BYTES, Diff4SplatModel, largest_network_bytes, load_config, random_init_device


def _network_bytes(cfg) -> list[int]:
    with torch.device("meta"):
        model = Diff4SplatModel(cfg)
    return [sum(t.numel() * t.element_size() for t in (*n.parameters(), *n.buffers()))
            for n in model.networks().values()]


def test_host_build_holds_the_devices_values_and_returns_on_the_cpu(device):
    """Values as the plain build on ``device`` (the same stream in NETWORKS order), every tensor on the CPU."""
    cfg = load_config("tiny")
    ref = {k: v.cpu() for k, v in Diff4SplatModel.random(cfg, seed=3, device=device).state_dict().items()}
    state = Diff4SplatModel.random(cfg, seed=3, device=device, host=True).state_dict()
    assert {v.device.type for v in state.values()} == {"cpu"} and state.keys() == ref.keys()
    assert all(torch.equal(state[k], v) for k, v in ref.items())


@pytest.mark.cuda
@pytest.mark.real_gpu  # memory figures (the simulated device reports 0)
def test_a_gpu_host_build_peaks_at_the_largest_network():
    """One network at a time on the GPU: the peak is the largest network, well under all four (tiny: 1.42 of
    3.84 MB), and the allocator's cache is handed back."""
    cfg = load_config("tiny")
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    before, reserved = torch.cuda.memory_allocated(), torch.cuda.memory_reserved()
    Diff4SplatModel.random(cfg, seed=3, device="cuda", host=True)
    peak = torch.cuda.max_memory_allocated() - before
    sizes = _network_bytes(cfg)
    largest, rest = max(sizes), sum(sizes) - max(sizes)
    assert largest == largest_network_bytes(cfg) and largest <= peak < largest + rest / 2, (peak, sizes)
    assert torch.cuda.memory_reserved() <= reserved + (2 << 20)  # the networks' cache was given back (one segment)


def test_largest_network_bytes_counts_the_dit_of_the_paper_model():
    """The paper DiT: 11,924,865,088 parameters (docs/benchmarks.md), 2 bytes each in bfloat16; no buffers."""
    cfg = load_config("paper")
    assert largest_network_bytes(cfg, torch.bfloat16) == 11_924_865_088 * 2
    assert largest_network_bytes(cfg) == 11_924_865_088 * 4


def test_a_gpu_initialises_only_with_room_for_the_largest_network(monkeypatch):
    cfg = load_config("tiny")
    need = largest_network_bytes(cfg, torch.bfloat16) + INIT_HEADROOM_BYTES
    free = {"bytes": need}
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free["bytes"], 80 << 30))
    assert random_init_device(cfg, "cuda", torch.bfloat16) == torch.device("cuda")
    assert random_init_device(cfg, "cuda:0", torch.bfloat16) == torch.device("cuda:0")
    free["bytes"] = need - 1
    assert random_init_device(cfg, "cuda", torch.bfloat16) == torch.device("cpu")
    assert random_init_device(cfg, "cpu", torch.bfloat16) == torch.device("cpu")
    assert random_init_device(cfg, "meta") == torch.device("cpu")


def test_a_gpu_whose_memory_cannot_be_read_initialises_on_the_cpu(monkeypatch):
    def unreadable(device=None):
        raise RuntimeError("no CUDA driver")

    monkeypatch.setattr(torch.cuda, "mem_get_info", unreadable)
    assert random_init_device(load_config("tiny"), "cuda") == torch.device("cpu")
    with pytest.warns(UserWarning, match="randomly initialised 'tiny' model"):
        model, source = load_model(config="tiny", init_device="cuda")
    assert source == "random:tiny:seed=0"  # the CPU's values, as every CPU build of this seed
    built = Diff4SplatModel.random(load_config("tiny"), seed=0)
    assert all(torch.equal(p, q) for p, q in zip(model.parameters(), built.parameters(), strict=True))


@pytest.mark.real_gpu  # a CUDA generator and free memory (the simulated device reports none)
def test_load_model_initialises_on_the_device_and_says_so(device):
    """On a GPU the source names it (its generator gives other values than the CPU's); on the CPU it is unchanged."""
    with pytest.warns(UserWarning, match="randomly initialised 'tiny' model"):
        model, source = load_model(config="tiny", init_device=device)
    assert source == "random:tiny:seed=0" + (":cuda" if device.type == "cuda" else "")
    assert {p.device.type for p in model.parameters()} == {"cpu"} and not model.training
    built = Diff4SplatModel.random(load_config("tiny"), seed=0, device=device)
    assert all(torch.equal(p, q.cpu()) for p, q in zip(model.parameters(), built.parameters(), strict=True))
