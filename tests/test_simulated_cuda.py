"""The library's CUDA code paths on a CPU-only machine (CI), on the simulated device of tests/simulated_cuda.py,
which raises PyTorch's own errors where a GPU would (mixed devices, numpy of a CUDA tensor). First, that the
simulation refuses what CUDA refuses, so a pass means something (the issue-26 tracebacks it reproduces are named
there). Then the suite's own CUDA tests, autograd included, in a pytest run with tests/simulated_cuda_plugin.py;
and, in this process, ``generate`` (bfloat16, offload), ``render`` (of a generated and of a fitted folder),
``evaluate``, ``benchmarks/gpu.py --part generate`` and the training objectives' forwards with ``--device cuda``,
which give the CPU's numbers."""
import contextlib
import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE, OBJECTIVE_CASES, benchmark_module, perturbed_field, tiny_model
from simulated_cuda import SimulatedCudaTensor, simulated_cuda
from torch.utils.data import default_collate

from data_prep.cli import main as data_prep_main
from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.cameras import CameraPath
from diff4splat.cli import main
from diff4splat.io import load_cameras_json
from diff4splat.io.image import read_image
from diff4splat.io.scene_folder import load_scene_folder
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.utils.devices import resolve_device
from diff4splat.utils.offload import ModelOffload
from models.hexplane import save_field
from training.eval_metrics import psnr_from_mse
from training.objectives import TrainingModule
from training.stage_config import StageConfig, apply_freezing

pytestmark = pytest.mark.slow  # the first dispatch mode of a process imports torch._dynamo (1.5 s)
PROMPT = "a cat turns its head"
ROOT = Path(__file__).resolve().parent.parent


def _cpu(x):
    """``x`` (a CUDA tensor of the simulation, or a CPU tensor) as a CPU tensor, outside the simulation too."""
    return x.elem if isinstance(x, SimulatedCudaTensor) else x


# ----------------------------------------------------------------------------------- the simulation itself
def test_the_simulation_refuses_what_cuda_refuses():
    """Mixed devices and numpy of a CUDA tensor raise as on a GPU; what CUDA accepts (CPU scalars in elementwise
    ops, CPU index tensors, copies) runs; autograd raises (no runtime in this process); nothing leaks out."""
    cpu_vec = torch.arange(4.0, device="cpu")
    with simulated_cuda(), torch.no_grad():
        assert resolve_device("cuda") == torch.device("cuda") and resolve_device("auto").type == "cuda"
        x = torch.arange(4.0, device="cuda")
        assert x.device == torch.device("cuda", 0) and x.is_cuda
        with pytest.raises(RuntimeError, match="same device.*cpu, cuda:0"):
            x + cpu_vec  # a CPU tensor made without device= beside a CUDA one
        with pytest.raises(RuntimeError, match="same device"):  # issue 26, scene.deformation_at: a CPU scalar
            torch.searchsorted(x, torch.tensor(1.5))  # is a number only in elementwise ops
        with pytest.raises(RuntimeError, match="same device"):  # issue 26, objectives._diffusion: a CPU mask
            (x > 1) & (cpu_vec > 1)
        with pytest.raises(TypeError, match="can't convert cuda:0 device type tensor to numpy"):
            x.numpy()  # issue 26, render/fused.py: numba handed CUDA tensors
        with pytest.raises(RuntimeError, match="same device"):
            torch.cat([x, cpu_vec])
        with pytest.raises(RuntimeError, match="same device"):
            x[x > 1] = cpu_vec[:2]
        with pytest.raises(IndexError, match="indices should be either on cpu"):  # prune.settle_generated: a CPU
            cpu_vec[torch.tensor([1, 0], device="cuda")]  # ``source`` indexed by the CUDA scene's indices
        # what CUDA accepts: CPU scalars in elementwise ops, CPU index tensors, copies, masked fills
        assert torch.equal(_cpu(x * torch.tensor(2.0) + 1), cpu_vec * 2 + 1)
        assert torch.equal(_cpu(x[torch.tensor([3, 0])]), torch.tensor([3.0, 0.0]))
        assert torch.equal(_cpu(x.masked_fill(x > 1, torch.tensor(-1.0))), torch.tensor([0.0, 1.0, -1.0, -1.0]))
        y = torch.zeros(4, device="cuda")
        y.copy_(cpu_vec)
        y[torch.tensor([0])] = 7.0
        assert type(y.cpu()) is torch.Tensor and torch.equal(y.cpu(), torch.tensor([7.0, 1.0, 2.0, 3.0]))
        assert float(x.sum()) == 6.0 and int(x.argmax()) == 3 and x.tolist() == [0.0, 1.0, 2.0, 3.0]
        assert torch.nn.Linear(4, 2).to("cuda").weight.device.type == "cuda"
    with simulated_cuda():  # no autograd: torch would abort, the simulation raises
        w = torch.ones(3, device="cuda", requires_grad=True)
        with pytest.raises(RuntimeError, match="no autograd"):
            w * 2
    assert not isinstance(torch.zeros(1), SimulatedCudaTensor)
    with pytest.raises(RuntimeError, match="outside simulated_cuda"):
        x + 1
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="not available"):
            resolve_device("cuda")


def test_the_simulation_computes_the_cpus_values():
    """A convolution, attention (its tensors by position, and by keyword as diffusers passes them: on a CUDA build
    SDPA would pick CUDA's kernel for them), sort, nonzero and indexing on the simulated device equal the CPU's,
    bit for bit."""
    g = torch.Generator().manual_seed(0)
    x, q = torch.randn(1, 2, 3, 8, 8, generator=g), torch.randn(1, 2, 7, 8, generator=g)
    k = torch.randn(2, 3, 50, 16, generator=g)  # large enough that the math kernel's sums differ from the CPU's
    conv = torch.nn.Conv3d(2, 3, 3, padding=1)

    def compute(dev):
        c = conv.to(dev)
        xd, qd = x.to(dev), q.to(dev)
        a = torch.nn.functional.scaled_dot_product_attention(qd, qd, qd)
        kd = k.to(dev)
        by_keyword = torch.nn.functional.scaled_dot_product_attention(query=kd, key=kd.flip(2), value=kd)
        s = c(xd).flatten().sort(stable=True)
        return [c(xd), a, by_keyword, s.values, s.indices, (xd > 0.5).nonzero(), xd[xd > 0.5],
                a[..., torch.tensor([1, 0])]]

    with torch.no_grad():
        ref = compute("cpu")
        with simulated_cuda():
            got = [_cpu(t) for t in compute("cuda")]
    for a, b in zip(got, ref, strict=True):
        assert torch.equal(a, b)


def test_the_simulations_side_streams_land_copies_only_when_waited_for():
    """A copy issued on a side stream reads as NaN until the current stream waits for an event recorded after it
    (or for the whole stream); copies on the current stream land at once."""
    src = torch.arange(1.0, 7.0, device="cpu")
    with simulated_cuda():
        main, side = torch.cuda.current_stream(), torch.cuda.Stream()
        a, b, now = (torch.empty(6, device="cuda") for _ in range(3))
        now.copy_(src)
        with torch.cuda.stream(side):
            a.copy_(src, non_blocking=True)
            first = torch.cuda.Event()
            first.record(side)
            b.copy_(src * 2, non_blocking=True)
        assert torch.equal(now.cpu(), src) and torch.isnan(a.cpu()).all() and torch.isnan(b.cpu()).all()
        main.wait_event(first)
        assert torch.equal(a.cpu(), src) and torch.isnan(b.cpu()).all()  # the event was recorded before b's copy
        main.wait_stream(side)
        assert torch.equal(b.cpu(), src * 2)


class _Blocks(torch.nn.Module):
    """An embedder, four blocks run in order, a head: the shape of a DiT for ModelOffload's prefetch."""

    def __init__(self):
        super().__init__()
        self.embed, self.head = torch.nn.Linear(3, 8), torch.nn.Linear(8, 2)
        self.blocks = torch.nn.ModuleList(torch.nn.Sequential(torch.nn.Linear(8, 8), torch.nn.GELU())
                                          for _ in range(4))
        self.register_buffer("scale", torch.tensor(0.5))

    def forward(self, x):
        x = self.embed(x) * self.scale
        for block in self.blocks:
            x = x + block(x)
        return self.head(x)


@pytest.mark.parametrize("waits", [True, False], ids=["as_written", "without_waits"])
def test_prefetch_waits_for_each_blocks_weights(waits, monkeypatch):
    """ModelOffload's prefetch on "cuda": each block waits for its own weights' copy on the side stream, so the
    first call gives the CPU's output; with the waits taken out, the blocks read weights still on their way
    (NaN on the simulated device), which shows the test can fail. The hooks are gone after the visit."""
    torch.manual_seed(0)
    net, x = _Blocks(), torch.randn(5, 3)
    with torch.no_grad():
        ref = net(x)
        with simulated_cuda():
            off = ModelOffload({"dit": net, "other": torch.nn.Linear(2, 2)}, "cuda", prefetch={"dit": net.blocks})
            if not waits:
                monkeypatch.setattr(type(torch.cuda.current_stream()), "wait_event", lambda self, event: None)
            with off.use("dit"):
                out = _cpu(net(x.to("cuda")))
            assert all(not b._forward_pre_hooks for b in net.blocks)
            with off.use("dit"):  # resident: no copy, the same output
                again = _cpu(net(x.to("cuda")))
    if waits:
        assert torch.equal(out, ref) and torch.equal(again, ref)
    else:
        assert torch.isnan(out).all() and torch.equal(again, ref)  # the visit's end waits for every copy


# ----------------------------------------------------------------------------------- the library on "cuda"
@pytest.mark.skipif(torch.version.cuda is not None, reason="a CUDA build of torch: python -m pytest -m cuda runs "
                    "the CUDA tests on its GPU, and the simulated runtime is for CPU-only builds")
@pytest.mark.skipif(shutil.which("g++") is None, reason="the simulated CUDA runtime is built with g++")
def test_the_suites_cuda_tests_pass_on_simulated_cuda(tmp_path):
    """``python -m pytest -m cuda`` with tests/simulated_cuda_plugin.py: every CUDA case of the suite (renderer
    forward and backward, fit, trainer and training stages, generate, evaluate, render; gsplat's and the
    ``real_gpu`` ones skip) passes on the simulated device, autograd included."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT / "tests"),
                                                                    os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-p", "simulated_cuda_plugin", "-m", "cuda", "-q",
                           "-o", "addopts=--strict-markers", "-p", "no:cacheprovider", "--basetemp", str(tmp_path)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    passed = int(re.search(r"(\d+) passed", summary).group(1))
    assert passed >= 35, summary  # 40 with torch 2.13.0 and no gsplat: the simulation runs, not skips, them


GENERATE_CASES = {  # dynamic, prompt, pipeline keywords
    "dynamic_prompt": (True, PROMPT, {}),
    "static_bfloat16": (False, "", dict(dtype=torch.bfloat16)),
    "offload_model_prompt": (True, PROMPT, dict(offload="model")),
    "offload_model_prefetch_prompt": (True, PROMPT, dict(offload="model-prefetch")),
}


@pytest.mark.parametrize("case", list(GENERATE_CASES))
def test_generate_on_simulated_cuda_gives_the_cpus_scene(case, cpu_tile_path):
    """The pipeline on "cuda" (in bfloat16; with model offload: networks moved in place between the CPU and the
    device) keeps every output there and gives the CPU's latents and geometry exactly (the same kernels; the
    duplicate and photo-layer steps take their non-CPU code paths, so the photo layer's colours, solved through
    renders, agree to 1e-4)."""
    dynamic, prompt, kwargs = GENERATE_CASES[case]
    image = torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(0), device="cpu")

    def run(device):
        pipe = Diff4SplatPipeline(tiny_model(dynamic=dynamic, active_dit=True), device, **kwargs)
        return pipe(image, pipe.default_cameras("arc", 5), prompt, steps=2)

    ref = run("cpu")
    with simulated_cuda():
        res = run("cuda")
    scene = res.scene.canonical
    assert {t.device.type for t in (res.latents, scene.means, scene.sh, res.gaussian_index)} == {"cuda"}
    assert torch.equal(_cpu(res.latents), ref.latents)
    assert (res.scene.d_means is None) == (not dynamic) == (ref.scene.d_means is None)
    assert torch.equal(_cpu(res.gaussian_index), ref.gaussian_index)
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(_cpu(getattr(scene, name)), getattr(ref.scene.canonical, name)), name
    torch.testing.assert_close(_cpu(scene.sh), ref.scene.canonical.sh, atol=1e-4, rtol=0)
    if dynamic:
        assert torch.equal(_cpu(res.scene.d_means), ref.scene.d_means)
    assert res.photo_psnr_db == pytest.approx(ref.photo_psnr_db, abs=1e-3)


def test_reconstruct_on_simulated_cuda_gives_the_cpus_scene(tmp_path, cpu_tile_path):
    """``reconstruct`` of a synthetic scene's moving camera on "cuda": the scene, its deformation and its temporal
    opacity stay there and equal the CPU's (the flow runs on CPU copies; the photo layers' colours are solved
    through renders, 1e-4)."""
    scene_dir = generate_scene(tmp_path, 0, seed=11)
    video = torch.stack([torch.from_numpy(read_image(scene_dir / "cam00" / "rgb" / f"{i:05d}.png")) for i in range(9)])
    cams = load_cameras_json(scene_dir / "cam00" / "cameras.json")
    cams = CameraPath(cams.viewmats[:9], cams.Ks[:9], cams.width, cams.height)

    def run(device):
        return Diff4SplatPipeline(tiny_model(), device).reconstruct(video.float() / 255, cams)

    ref = run("cpu")
    with simulated_cuda():
        res = run("cuda")
    assert res.scene.canonical.means.device.type == "cuda" and not ref.scene.is_static
    for name in ("means", "quats", "scales", "opacities"):
        torch.testing.assert_close(_cpu(getattr(res.scene.canonical, name)), getattr(ref.scene.canonical, name))
    torch.testing.assert_close(_cpu(res.scene.canonical.sh), ref.scene.canonical.sh, atol=1e-4, rtol=0)
    for name in ("d_means", "t_means", "t_scales"):
        torch.testing.assert_close(_cpu(getattr(res.scene, name)), getattr(ref.scene, name))


def _frames(folder, n):
    return np.stack([read_image(folder / "rgb" / f"{i:04d}.png") for i in range(n)]).astype(float)


def _psnr(a, b):
    return psnr_from_mse(float(np.mean(((a - b) / 255.0) ** 2)))


def test_generate_render_and_evaluate_commands_on_simulated_cuda(tmp_path, cpu_tile_path):
    """``diff4splat generate / render / evaluate --device cuda``: the folders are written from CUDA tensors (as
    the CPU's: the same Gaussians, frames above 45 dB PSNR), a fitted folder's HexPlane field renders there,
    and evaluate's table matches the CPU's."""
    gen = ["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "2", "--resolution", "64", "--quiet",
           "--prompt", PROMPT]
    render = ["render", "--trajectory", "orbit", "--frames", "4", "--quiet"]
    root = tmp_path / "data"
    generate_scene(root, 0, seed=5, size=64, frames=9, cameras=1, static_ratio=0.0)
    evaluate = ["evaluate", "--random", "--config", "tiny", "--data", str(root), "--frames", "9", "--steps", "1",
                "--limit", "1", "--quiet"]
    out = {}
    for dev in ("cpu", "cuda"):
        with simulated_cuda() if dev == "cuda" else contextlib.nullcontext():
            d = tmp_path / dev
            d.mkdir()
            assert main([*gen, "--device", dev, "--out", str(d / "gen")]) == 0
            assert main([render[0], str(d / "gen"), *render[1:], "--device", dev, "--out", str(d / "r")]) == 0
            folder = load_scene_folder(d / "gen", "cpu")
            save_field(d / "gen" / "field.safetensors", perturbed_field(folder.scene.canonical.means))
            assert main([render[0], str(d / "gen"), *render[1:], "--device", dev, "--out", str(d / "f")]) == 0
            assert main([*evaluate, "--device", dev, "--csv", str(d / "eval.csv")]) == 0
        with open(d / "eval.csv", newline="") as f:
            (row,) = list(csv.DictReader(f))
        out[dev] = folder, row
    (cpu, cpu_row), (cuda, cuda_row) = out["cpu"], out["cuda"]
    assert cuda.scene.canonical.means.shape == cpu.scene.canonical.means.shape
    torch.testing.assert_close(cuda.scene.canonical.means, cpu.scene.canonical.means, atol=1e-4, rtol=0)
    assert json.loads((tmp_path / "cuda" / "gen" / "meta.json").read_text())["device"] == "cuda"
    for sub, n in (("gen", 5), ("r", 4), ("f", 4)):
        assert _psnr(_frames(tmp_path / "cuda" / sub, n), _frames(tmp_path / "cpu" / sub, n)) > 45, sub
    assert json.loads((tmp_path / "cuda" / "f" / "meta.json").read_text())["deformation"] == "field.safetensors"
    for k in ("psnr_input", "psnr_novel", "psnr_novel_noise", "psnr_novel_gt", "vae_psnr", "motion_epe"):
        assert float(cuda_row[k]) == pytest.approx(float(cpu_row[k]), abs=0.02), k


def test_data_prep_synth_renders_on_simulated_cuda(tmp_path, cpu_tile_path):
    """``data_prep synth --device cuda``: the scene is rendered from CUDA tensors and holds the CPU's frames
    (the tile path on both: the same arithmetic up to rounding); the tracks come from the CPU scene, the same."""
    for dev in ("cpu", "cuda"):
        with simulated_cuda() if dev == "cuda" else contextlib.nullcontext():
            args = ["--size", "32", "--frames", "3", "--cameras", "1", "--static-ratio", "0", "--device", dev]
            assert data_prep_main(["synth", "--scenes", "1", *args, "--quiet", "--out", str(tmp_path / dev)]) == 0
    cpu, cuda = (tmp_path / d / "scene_00000" for d in ("cpu", "cuda"))
    frames = sorted(p.relative_to(cpu) for p in cpu.rglob("*.png"))
    assert frames and frames == sorted(p.relative_to(cuda) for p in cuda.rglob("*.png"))
    for f in frames:  # 8-bit frames: equal but for a rounding step
        a, b = (read_image(root / f).astype(np.int16) for root in (cpu, cuda))
        assert np.abs(a - b).max() <= 1, f
    assert (cpu / "tracks.npz").read_bytes() == (cuda / "tracks.npz").read_bytes()


def test_the_gpu_benchmarks_generate_part_runs_on_simulated_cuda(monkeypatch, capsys):
    """``benchmarks/gpu.py --part generate --quick --device cuda`` (every row: offload, compiled blocks, cuDNN
    attention, no prompt; tiny sizes) runs its CUDA branches to the end: what a GPU session runs first."""
    gpu = benchmark_module("gpu")
    monkeypatch.setattr(sys, "argv", ["gpu.py", "--device", "cuda", "--quick", "--part", "generate"])
    with simulated_cuda():
        assert gpu.main() == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "**" in line]
    assert len(rows) == len(gpu.GENERATE) and not any("out of memory" in r for r in rows)
    assert all(float(r.split("**")[1]) > 0 for r in rows)




def test_the_gpu_benchmarks_block_part_runs_on_simulated_cuda(monkeypatch, capsys):
    """``benchmarks/gpu.py --part block --quick --device cuda``: the op-by-op block, ours eager (the GELU epilogue on
    "cuda") and ours compiled, each to within bfloat16 rounding of the first."""
    gpu = benchmark_module("gpu")
    monkeypatch.setattr(sys, "argv", ["gpu.py", "--device", "cuda", "--quick", "--part", "block"])
    with simulated_cuda():
        assert gpu.main() == 0
    rows = [line.strip("|").split("|") for line in capsys.readouterr().out.splitlines() if line.startswith("| ")
            and not line.startswith("| block")]
    assert [r[0].strip() for r in rows] == ["op by op (`models.dit_reference`)", "ours, eager", "ours, `torch.compile`"]
    assert all(float(r[1]) > 0 and float(r[5]) < 0.05 for r in rows)

    def broken(*args, **kwargs):
        raise RuntimeError("no Triton here")

    monkeypatch.setattr(gpu.torch, "compile", lambda module: broken)  # a compile error is its row's, not the part's
    with simulated_cuda():
        assert gpu.main() == 0
    last = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ours, `torch.compile`")]
    assert last and "failed: RuntimeError: no Triton here" in last[0]


def test_training_forwards_on_simulated_cuda_give_the_cpus_losses(tmp_path):
    """Each objective's forward (the step generator on the CPU, the batch and model on "cuda") gives the CPU's
    losses, on "cuda". The backward is not simulated (no autograd for simulated tensors)."""
    size, frames = 32, 9
    generate_scene(tmp_path, 0, seed=11, size=size, frames=frames, cameras=1, static_ratio=1.0)
    generate_scene(tmp_path, 1, seed=11, size=size, frames=frames, cameras=1, static_ratio=0.0)
    ds = ClipDataset(tmp_path, ClipConfig(num_frames=frames, height=size, width=size, scenes="all",
                                          plucker="packed", num_tracks=64, seed=0))
    clips = [ds[0], ds[1]]
    for case, (kwargs, clip) in OBJECTIVE_CASES.items():
        stage = StageConfig(height=size, width=size, num_frames=frames, render_frames=2, **kwargs)
        model = tiny_model(seed=1, dynamic=True, active_dit=True)
        apply_freezing(model, stage.train)
        module = TrainingModule(model, stage).train()
        batch = default_collate(clips[clip:clip + 1])
        with torch.no_grad():
            ref = {k: float(v) for k, v in module(batch, torch.Generator().manual_seed(4)).items()}
            with simulated_cuda():
                module.to("cuda")
                losses = module({k: v.to("cuda") if isinstance(v, torch.Tensor) else v for k, v in batch.items()},
                                torch.Generator().manual_seed(4))
                assert {v.device.type for v in losses.values()} == {"cuda"}, case
                got = {k: float(v) for k, v in losses.items()}
        assert got == pytest.approx(ref, rel=1e-5, abs=1e-7), case
