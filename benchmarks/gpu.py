"""GPU figures: the renderer, a DiT block, `generate` per stage with peak memory, and training steps per second.

Five parts, each small enough for one 10-minute command on one GPU:

- ``render``: gsplat (``compositor=None`` on CUDA), our pure-PyTorch tile path on CUDA (``compositor="torch"``)
  and the fused CPU path (``compositor="fused"``) on the LDRM-sized scenes of benchmarks/render_speed.py (one
  Gaussian per pixel) at 256² and 1024²: forward and forward+backward, median after warm-up.
- ``block``: one paper-size DiT block, op by op (:mod:`models.dit_reference`) against ours, eager and compiled
  (what the eager step's fewer passes over its tokens buy, benchmarks/dit_traffic.py), in about a minute.
- ``generate``: the pipeline's stages (synchronised, :class:`diff4splat.utils.devices.Stopwatch`) and the render along
  the path, with the peak of ``torch.cuda.max_memory_allocated``, for ``base`` (shipped weights, 17 frames, 64²),
  ``small`` (random, 17 frames, 128²) and ``paper`` (random weights built directly in bfloat16 on the GPU —
  nothing is downloaded; 49 frames, 512², 50 Euler steps), the paper model with model CPU offload and a prompt
  (eager, with the DiT's copy prefetched behind its first step (``--offload model-prefetch``), with its
  transformer blocks ``torch.compile``-d, and with cuDNN attention), with offload and no prompt,
  and without offload and no prompt. Goal (issue 26, the paper's figures): paper-size
  `generate` end to end ≤ 30 s and ≤ 25 GB.
- ``command``: the README's paper-size command (``diff4splat generate photo --config paper --dtype bfloat16
  --offload model --no-frame-plys --prompt …``) in a child process, once, as a user runs it: wall time of the
  whole process, its host memory peak, the GPU peak and the output folder's size.
- ``train``: optimizer steps per second and peak memory of ``train_base_dit``, ``train_base_ldrm`` and
  ``train_stage1`` with the ``small`` model on synthetic data made here (``data_prep synth``), on the trainer's
  defaults for the device (bf16 autocast and TF32 on CUDA).

    python benchmarks/gpu.py --part render|block|generate|command|train|all [--write]
    python benchmarks/gpu.py --device cpu --quick --part all     # a dry run of the code paths, no figures

``--write`` replaces the sections ``gpu_render``, ``gpu_block``, ``gpu_generate``, ``gpu_command`` and ``gpu_train`` of
docs/benchmarks.md; every table names the device it ran on. ``--part generate --rows N,…`` runs only those rows
and keeps the table's others where they ran on the same device and software, each row saying when it ran. Without
CUDA the script exits with one line and code 2 unless ``--device cpu``.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import gc
import json
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    machine,
    markdown_rows,
    markdown_table,
    peak_rss_mb,
    read_section,
    run_with_peak_memory,
    write_section,
)
from render_speed import ldrm_scene  # noqa: E402

from diff4splat.io import load_image  # noqa: E402
from diff4splat.pipeline import Diff4SplatPipeline, load_model  # noqa: E402
from diff4splat.render import rasterize  # noqa: E402
from diff4splat.render.rasterize import gsplat_available  # noqa: E402
from diff4splat.render.sequence import render_path  # noqa: E402
from diff4splat.runtime import FF_CHUNK_TOKENS  # noqa: E402
from diff4splat.utils.devices import Stopwatch, resolve_device  # noqa: E402
from models.bundle import Diff4SplatModel, load_config  # noqa: E402
from models.dit import VideoDiTBlock  # noqa: E402
from models.dit_reference import reference_block  # noqa: E402
from models.rope import rope_3d  # noqa: E402
from training.stage_config import load_stage  # noqa: E402
from training.train import build_training  # noqa: E402

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
PROMPT = "a cat turns its head"
GOAL = "paper-size generate (49 frames, 512², 50 steps) end to end ≤ 30 s and ≤ 25 GB peak (issue 26)"


def device_name(device: torch.device) -> str:
    """The GPU's name and memory, or the CPU line of :func:`_common.machine`."""
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        return (f"{p.name} ({p.total_memory / 2**30:.0f} GiB), CUDA {torch.version.cuda}, torch {torch.__version__}, "
                f"host: {machine()}")
    return machine()


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def free_memory(device: torch.device) -> None:
    """Give back what dropped models held: the GPU's cached blocks and the pinned host memory torch keeps cached
    after the offload's CPU copies are freed (``empty_cache`` does not release those; a paper model pins about
    40 GB), and ``torch.compile``'s caches. Call after the last reference to a model is gone."""
    gc.collect()
    if device.type == "cuda":
        torch._dynamo.reset()
        torch.cuda.empty_cache()
        if hasattr(torch._C, "_host_emptyCache"):  # torch ≥ 2.5; older builds keep the pinned cache
            torch._C._host_emptyCache()


def peak_gb(device: torch.device) -> str:
    """Peak allocated memory since :func:`reset_peak`: GPU memory on CUDA (GB = 10⁹ bytes), else the process's
    peak RSS."""
    if device.type == "cuda":
        return f"{torch.cuda.max_memory_allocated(device) / 1e9:.2f}"
    return f"{peak_rss_mb() * 2**20 / 1e9:.2f} (RSS)"


# --------------------------------------------------------------------------------------------------- render
def time_render(compositor: str | None, device: torch.device, size: int, runs: int) -> dict[str, float]:
    """Median forward and forward+backward ms of one camera, RGB+ED, on ``device``."""
    scene = [t.to(device) for t in ldrm_scene(size)]
    clock = Stopwatch(device)
    fwd, fb = [], []
    for k in range(runs + 2):  # two warm-ups: kernels compile / load and allocators settle
        clock.lap()
        with torch.no_grad():
            rasterize(*scene, size, size, render_mode="RGB+ED", compositor=compositor)
        t_f = clock.lap()
        leaves = [t.clone().requires_grad_() for t in scene[:5]]
        clock.lap()
        col, alpha, _ = rasterize(*leaves, *scene[5:], size, size, render_mode="RGB+ED", compositor=compositor)
        (col.sum() + alpha.sum()).backward()
        t_fb = clock.lap()
        if k >= 2:
            fwd.append(t_f)
            fb.append(t_fb)
    return {"fwd_ms": 1e3 * statistics.median(fwd), "fb_ms": 1e3 * statistics.median(fb)}


def part_render(device: torch.device, quick: bool) -> str:
    sizes = (64,) if quick else (256, 1024)
    rows = []
    for size in sizes:
        paths = [("fused (CPU, numba)", "fused", torch.device("cpu"))]
        if device.type != "cpu":
            paths.insert(0, ("PyTorch tile path", "torch", device))
            if gsplat_available():
                paths.insert(0, ("gsplat", None, device))
            else:
                rows.append(["gsplat", str(device), f"{size}²", "not installed", "—"])
        for label, compositor, dev in paths:
            runs = 2 if quick else (3 if dev.type == "cpu" and size > 256 else 10)
            r = time_render(compositor, dev, size, runs)
            rows.append([label, str(dev), f"{size}²", f"{r['fwd_ms']:.2f}", f"{r['fb_ms']:.2f}"])
            print(rows[-1], flush=True)
    return (f"### Renderer on the GPU (LDRM-sized scenes, one Gaussian per pixel, RGB+ED, 1 camera)\n\n"
            f"`python benchmarks/gpu.py --part render --write`; median after two warm-ups, CUDA synchronised. "
            f"Device: {device_name(device)}. The CPU row uses torch's {torch.get_num_threads()} threads.\n\n"
            + markdown_table(["path", "device", "image", "forward ms", "fwd+bwd ms"], rows))


# ---------------------------------------------------------------------------------------------------- block
def part_block(device: torch.device, quick: bool) -> str:
    """One DiT block of the paper model (random weights, bfloat16 on CUDA) at its sampling size (13,312 tokens,
    226 text tokens), no grad: :func:`models.dit_reference.reference_block` (each op on its own) against the block's
    eager forward (feed-forward chunk as sampling runs it) and its ``torch.compile``-d forward (``generate
    --compile``'s regional compilation), median of synchronised runs after warm-ups."""
    cfg = load_config("tiny" if quick else "paper")
    d, vae = cfg.dit, cfg.vae
    grid = (vae.num_latent_frames(cfg.num_frames) // d.patch_size[0],
            cfg.height // vae.spatial_factor // d.patch_size[1], cfg.width // vae.spatial_factor // d.patch_size[2])
    tokens = grid[0] * grid[1] * grid[2]
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    g = torch.Generator().manual_seed(0)  # inputs drawn on the CPU, then moved: the same values on any device
    with torch.device(device):
        block = VideoDiTBlock(d.hidden_size, d.num_heads, d.mlp_ratio, d.qk_norm, d.norm_eps).to(dtype).eval()
    x, c, text = (torch.randn(*shape, generator=g).to(device, dtype) for shape in
                  ((1, tokens, d.hidden_size), (1, d.hidden_size), (1, cfg.text_encoder.max_length, d.hidden_size)))
    rope = rope_3d(*grid, d.head_dim, d.rope_theta, dtype=dtype, device=device)
    variants = [("op by op (`models.dit_reference`)", lambda: reference_block(block, x, c, rope, text)),
                ("ours, eager", lambda: block(x, c, rope, text, None, FF_CHUNK_TOKENS))]
    if device.type == "cuda":  # regional compilation as `generate --compile` (Triton; not on the CPU dry run)
        compiled = torch.compile(block)
        variants.append(("ours, `torch.compile`", lambda: compiled(x, c, rope, text, None, FF_CHUNK_TOKENS)))
    clock, rows, reference = Stopwatch(device), [], None
    runs, warm = (2, 1) if quick else (10, 3)
    for label, run in variants:
        times = []
        reset_peak(device)
        try:
            with torch.no_grad():
                for k in range(warm + runs):
                    clock.lap()
                    out = run()
                    t = clock.lap()
                    if k >= warm:
                        times.append(t)
        except Exception as e:  # out of memory, a torch.compile error: the row says so, the next one runs
            rows.append([label, f"failed: {type(e).__name__}: {str(e).splitlines()[0][:100]}", "–", "–", "–", "–"])
            print(rows[-1], flush=True)
            free_memory(device)
            continue
        out = out.float().cpu()  # held on the host: the next variants' GPU peaks do not include it
        reference = out if reference is None else reference
        ms = 1e3 * statistics.median(times)
        diff = float((out - reference).abs().max())
        rows.append([label, f"{ms:.2f}", f"{ms * d.depth:.0f}", f"{ms * d.depth * 50 / 1e3:.2f}", peak_gb(device),
                     f"{diff:.3g}"])
        print(rows[-1], flush=True)
        del out
    return (f"### One DiT block on the GPU: op by op against ours\n\n"
            f"`python benchmarks/gpu.py --part block --write`; one block of the `{cfg.name}` DiT (random weights, "
            f"{str(dtype).removeprefix('torch.')}), {tokens:,} tokens and {cfg.text_encoder.max_length} text tokens, "
            f"no grad; median of {runs} synchronised runs after {warm} warm-up run(s); the step and 50-step columns "
            f"multiply by its {d.depth} blocks (the DiT's embedders and final layer are not in them); peak: the "
            f"block's weights, its inputs and the forward's activations (`torch.cuda.max_memory_allocated`, "
            f"GB = 10⁹ bytes); the last column is the largest difference from the op-by-op output. "
            f"Device: {device_name(device)}.\n\n"
            + markdown_table(["block", "ms", f"× {d.depth} blocks, ms per step", "50 steps, s", "peak GB",
                              "max abs Δ"], rows))


# ------------------------------------------------------------------------------------------------- generate
GENERATE = [  # (label, config, frames, dtype, offload, prompt, attention, compile)
    ("base (shipped weights)", "base", None, torch.float32, "none", PROMPT, "auto", False),
    ("small (random)", "small", None, torch.float32, "none", PROMPT, "auto", False),
    ("paper, bf16, offload model, prompt", "paper", 49, torch.bfloat16, "model", PROMPT, "auto", False),
    ("paper, bf16, offload model-prefetch, prompt", "paper", 49, torch.bfloat16, "model-prefetch", PROMPT, "auto",
     False),
    ("paper, bf16, offload model, prompt, cuDNN attention", "paper", 49, torch.bfloat16, "model", PROMPT, "cudnn",
     False),
    ("paper, bf16, offload model, no prompt", "paper", 49, torch.bfloat16, "model", "", "auto", False),
    ("paper, bf16, no offload, no prompt", "paper", 49, torch.bfloat16, "none", "", "auto", False),
    ("paper, bf16, offload model, prompt, compiled blocks", "paper", 49, torch.bfloat16, "model", PROMPT, "auto",
     True),
]
"""The rows, in the order they run: the rows of one model together (a paper model is built, and pinned by the
offload, once per key of :func:`part_generate`), the compiled one last (it changes its model's blocks in place)."""
STAGES = ("encode_image", "encode_text", "sample", "reconstruct", "prune", "render")
HEADER = ["model", "run", "Gaussians", *STAGES, "total s", "peak GB", "peak in", "warm-up s", "measured"]


def build_model(config: str, dtype: torch.dtype, device: torch.device, quick: bool):
    """Shipped weights where they exist; otherwise a seeded random model built directly on ``device`` in
    ``dtype`` (a paper-size model never passes through CPU float32)."""
    if config == "base":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return load_model(None, config)[0]
    cfg = load_config("tiny" if quick else config)
    return Diff4SplatModel.random(cfg, seed=0, device=device, dtype=dtype)


def run_generate(pipe: Diff4SplatPipeline, frames: int | None, prompt: str, steps: int | None) -> dict[str, float]:
    cfg = pipe.config
    image = load_image(EXAMPLE, size=(cfg.height, cfg.width))
    cams = pipe.default_cameras("arc", frames)
    res = pipe(image, cams, prompt, steps=steps)
    clock = Stopwatch(pipe.device)
    render_path(res.scene, res.cameras, eps2d=res.eps2d)
    timings = {**res.timings, "render": clock.lap()}
    high_water = {**res.high_water, **dict(zip(["render"], clock.high_water, strict=False))}
    # the stage that set the peak: the first whose running maximum reached the final one
    peak_stage = next((k for k, v in high_water.items() if v == max(high_water.values())), "")
    return {**timings, "peak_stage": peak_stage, "gaussians": res.scene.num_gaussians,
            "frames": len(res.cameras), "steps": res.steps, "size": f"{cfg.width}²"}


def part_generate(device: torch.device, quick: bool, emit: Callable[[str], None] | None = None,
                  only: list[int] | None = None, previous: str | None = None) -> str:
    """The ``generate`` table; ``emit`` (e.g. writing docs/benchmarks.md) gets the table so far after every row, so
    rows already measured survive a command stopped at its time limit. A row that fails (out of memory, a
    ``torch.compile`` error) is recorded with its error and the next row runs. ``only``: the 1-based numbers of
    the rows of :data:`GENERATE` to run (default all), in their order there. ``previous``: the section's body as
    it was (docs/benchmarks.md); its rows from this device that are not run now stay (:func:`earlier_rows`)."""
    selected = [r for i, r in enumerate(GENERATE, 1) if only is None or i in only]
    kept = earlier_rows(previous, device_name(device), {r[0] for r in selected})
    rows: dict[str, list[str]] = {}
    models: dict[tuple, object] = {}
    for label, config, frames, dtype, offload, prompt, attention, compile in selected:
        key = (config, dtype, compile)  # compiling changes the model's blocks in place: a model of its own
        pipe = model = None
        try:
            if key not in models:
                models.clear()  # one paper model at a time: free the last before building the next
                free_memory(device)
                reset_peak(device)
                models[key] = build_model(config, dtype, device, quick)
            model = models[key]
            pipe = Diff4SplatPipeline(model, device, dtype=dtype, offload=offload, attention=attention,
                                      compile=compile)
            t_warm = time.perf_counter()
            run_generate(pipe, 5 if quick else frames, prompt, 1)  # warm-up: kernels, allocator, compilation
            warm = time.perf_counter() - t_warm
            reset_peak(device)
            t = run_generate(pipe, 5 if quick else frames, prompt, 2 if quick else None)
        except Exception as e:  # noqa: BLE001 - a benchmark row: record what failed, measure the next
            kind = "out of memory" if isinstance(e, torch.OutOfMemoryError) else type(e).__name__
            rows[label] = ([label, f"{kind}: " + (str(e).splitlines() or [""])[0][:80]]
                           + [""] * (len(HEADER) - 3) + [measured_now()])
            print(rows[label], flush=True)
            pipe = model = None  # noqa: F841 - drop every reference before freeing the caches
            models.clear()
            free_memory(device)
            reset_peak(device)
            continue
        total = sum(t[s] for s in STAGES)
        rows[label] = ([label, f"{t['size']}, {t['frames']} fr, {t['steps']} st", f"{t['gaussians']:,}"]
                       + [f"{t[s]:.2f}" for s in STAGES]
                       + [f"**{total:.2f}**", peak_gb(device), t["peak_stage"], f"{warm:.1f}", measured_now()])
        print(rows[label], flush=True)
        if emit is not None:
            emit(_generate_table(device, rows, kept, selected, quick))
    pipe = model = None  # noqa: F841
    models.clear()
    free_memory(device)
    return _generate_table(device, rows, kept, selected, quick)


def measured_now() -> str:
    """The "measured" column: when a row ran, UTC to the minute (a table may keep rows of earlier runs)."""
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def earlier_rows(previous: str | None, device_label: str, running: set[str]) -> dict[str, list[str]]:
    """The rows of an earlier ``generate`` table that a run of some rows (``--rows``) keeps: those of ``previous``
    (the section's body in docs/benchmarks.md) whose label is a row of :data:`GENERATE` not in ``running``, when
    that table ran on the same device and software (its "Device:" text is ``device_label``); a table of another
    device gives none, its figures do not compare. Each row is mapped by column name onto :data:`HEADER`; a column
    the earlier table lacked holds "—". Returns ``{label: cells}``."""
    if not previous or f"Device: {device_label}.\n" not in previous:
        return {}
    labels = {r[0] for r in GENERATE} - running
    return {row["model"]: [row.get(h, "—") for h in HEADER] for row in markdown_rows(previous)
            if row.get("model") in labels}


def _verdict(label: str, cells: list[str]) -> str | None:
    """Whether a paper row with model offload and a prompt meets the goal (:data:`GOAL`); None for other rows
    and failed ones."""
    _, config, _, _, offload, prompt, _, compile = next(r for r in GENERATE if r[0] == label)
    try:
        total = float(cells[HEADER.index("total s")].strip("*"))
        peak = float(cells[HEADER.index("peak GB")].split()[0])
    except (ValueError, IndexError):
        return None
    if not (config == "paper" and offload == "model" and prompt):
        return None
    warm = cells[HEADER.index("warm-up s")]
    return (f"{label}: {total:.1f} s ({'meets' if total <= 30 else 'misses'} 30 s), peak {peak:.2f} GB "
            f"({'meets' if peak <= 25 else 'misses'} 25 GB)"
            + (f", after a {warm} s warm-up that compiled (once per process)." if compile else "."))


def _generate_table(device: torch.device, rows: dict[str, list[str]], kept: dict[str, list[str]],
                    selected: list[tuple], quick: bool) -> str:
    table = [(rows.get(r[0]) or kept[r[0]]) for r in GENERATE if r[0] in rows or r[0] in kept]
    verdicts = [] if quick else [v for v in (_verdict(c[0], c) for c in table) if v]
    verdict = "".join(f"\n\n{v}" for v in ([f"Goal: {GOAL}."] + verdicts if verdicts else []))
    ran = [r for r in selected if r[0] in rows]
    if len(ran) < len(selected):
        verdict += (f"\n\n{len(ran)} of {len(selected)} rows: the command stopped before the rest "
                    f"({'; '.join(r[0] for r in selected if r[0] not in rows)}).")
    if kept:
        verdict += (f"\n\nRows of an earlier run on this device, kept (\"measured\" says when): "
                    f"{'; '.join(kept)}.")
    missing = [r[0] for r in GENERATE if r not in selected and r[0] not in kept]
    if missing:
        verdict += f"\n\nRows not measured on this device (`--rows` left them out): {'; '.join(missing)}."
    return (f"### `generate` on the GPU per stage, seconds, with peak memory\n\n"
            f"`python benchmarks/gpu.py --part generate --write`; one run after a one-step warm-up (its wall time "
            f"is the warm-up column: model moves, kernel loads and, for \"compiled blocks\", `torch.compile` of one "
            f"transformer block, `--compile`), stages "
            f"synchronised; \"peak in\" is the stage that set the peak (`GenerationResult.high_water`). The paper "
            f"model holds random weights built in bfloat16 on the GPU (no download); "
            f"\"offload model\" keeps the networks in pinned CPU memory and moves one at a time to the GPU "
            f"(diff4splat/utils/offload.py), so its `sample` includes copying the DiT there; \"model-prefetch\" copies "
            f"the DiT block by block on a side stream while its first step runs; \"cuDNN attention\" runs "
            f"`--attention cudnn` (cuDNN's fused attention tried first; torch tries FlashAttention-2 first). Peak = "
            f"`torch.cuda.max_memory_allocated` over the run, GB = 10⁹ bytes. A run of some rows (`--rows`) keeps "
            f"the other rows of this table where they ran on the same device and software. "
            f"Device: {device_name(device)}.\n\n"
            + markdown_table(HEADER, table) + verdict)


# -------------------------------------------------------------------------------------------------- command
COMMAND = ("generate", str(EXAMPLE), "--config", "paper", "--dtype", "bfloat16", "--offload", "model",
           "--no-frame-plys", "--prompt", PROMPT)
"""The README's paper-size command ("On a GPU"), as a user types it."""


def part_command(device: torch.device, quick: bool) -> str:
    """The README's paper-size command in a child process, as a user runs it: the whole process's wall time
    (imports, initialising the random paper model in bfloat16, on the GPU when it has room, the checks, generate,
    writing the folder), its peak host memory (``run_with_peak_memory``), the stages and GPU peak from meta.json,
    and the folder's size. The child's progress goes to this process's output, so a run stopped at a time limit
    shows where it was (on an H100, 2026-11-26, the command ran past a 163 s limit with ``--quiet``, saying
    nothing: the random model was then filled on the CPU)."""
    argv = list(COMMAND) if not quick else ["generate", str(EXAMPLE), "--config", "base", "--steps", "1",
                                            "--frames", "5", "--no-frame-plys", "--prompt", PROMPT]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        t0 = time.perf_counter()
        done, host_peak = run_with_peak_memory([sys.executable, "-m", "diff4splat.cli", *argv, "--device",
                                                str(device), "--out", str(out)])
        wall = time.perf_counter() - t0
        if done.returncode:
            raise RuntimeError(f"{' '.join(argv)} exited with {done.returncode}")
        meta = json.loads((out / "meta.json").read_text())
        files = [f for f in out.rglob("*") if f.is_file()]
        size = sum(f.stat().st_size for f in files) / 1e9
        plys = sum(f.stat().st_size for f in files if f.parent.name == "frames") / 1e9
    t = meta["timings_s"]
    stages = sum(v for k, v in t.items() if k != "load_model")
    row = [f"`diff4splat {' '.join(argv[:1] + ['photo.png'] + argv[2:-2])} --prompt …`", f"{wall:.1f}",
           f"{t['load_model']:.1f}", f"{stages:.2f}", f"{wall - t['load_model'] - stages:.1f}",
           f"{host_peak / 1e9:.1f}", max((meta["peak_memory_gb"] or {"": "–"}).values()),
           f"{meta['num_gaussians']:,}", f"{size:.2f} ({plys:.2f} in frames/)"]
    print(row, flush=True)
    return ("### The paper-size command end to end\n\n"
            "`python benchmarks/gpu.py --part command --write`: the README's command (\"On a GPU\") in a child "
            "process, once, as a user runs it: \"wall\" is the whole process (imports, the random paper model "
            "initialised in bfloat16 on the GPU, the request's checks, generate, writing the folder); \"stages\" is "
            "the sum of meta.json's stage timings (encode … render, the table above) and \"rest\" the remainder "
            "(imports, checks, writing). Host peak = the child's own `ru_maxrss` (`_common.run_with_peak_memory`); "
            "GPU peak = meta.json's `peak_memory_gb`; "
            f"GB = 10⁹ bytes. Device: {device_name(device)}.\n\n"
            + markdown_table(["command", "wall s", "load_model s", "stages s", "rest s", "host peak GB",
                              "GPU peak GB", "Gaussians", "output folder GB"], [row]))


# ---------------------------------------------------------------------------------------------------- train
TRAIN = ("train_base_dit", "train_base_ldrm", "train_stage1")


def part_train(device: torch.device, quick: bool) -> str:
    steps, warm = (3, 1) if quick else (30, 5)
    config = "tiny" if quick else "small"
    cfg = load_config(config)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        subprocess.run([sys.executable, "-m", "data_prep.cli", "synth", "--scenes", "16", "--static-ratio", "0.5",
                        "--size", str(cfg.width), "--frames", "17", "--cameras", "2", "--workers", "8", "--quiet",
                        "--out", str(data)], check=True)
        for name in TRAIN:
            run = Path(tmp) / name
            stage = load_stage(name, data=str(data), init_from="", model_config=config,  # "": a random model
                               height=cfg.height if name != "train_stage1" else cfg.height // 2,
                               width=cfg.width if name != "train_stage1" else cfg.width // 2,
                               trainer={"run_dir": str(run), "total_steps": steps, "checkpoint_every": 10**6,
                                        "progress": False, "device": str(device)})
            reset_peak(device)
            trainer, _, counts = build_training(stage)
            trainer.fit()
            with open(run / "metrics.csv") as f:
                secs = [float(r["seconds"]) for r in csv.DictReader(f) if r["skipped"] == "0"][warm:]
            sps = 1 / statistics.median(secs)
            rows.append([name, f"{config}, {stage.width}², {stage.num_frames} fr, batch {stage.trainer.batch_size}",
                         f"{sum(counts.values()):,}", "bf16" if trainer.bf16 else "off", f"{sps:.2f}", peak_gb(device)])
            print(rows[-1], flush=True)
    return (f"### Training on the GPU: steps per second and peak memory\n\n"
            f"`python benchmarks/gpu.py --part train --write`; {steps} optimizer steps on 16 synthetic scenes "
            f"(half static, `data_prep synth`), median step time after {warm} warm-up step(s) (metrics.csv "
            f"`seconds`), the trainer's defaults for the device. Device: {device_name(device)}.\n\n"
            + markdown_table(["stage", "clips", "trainable parameters", "autocast", "steps/s", "peak GB"], rows))


def add_gpu_arguments(ap: argparse.ArgumentParser, quick_help: str) -> None:
    """``--device`` (default cuda), ``--quick`` (a dry run) and ``--write`` of the GPU benchmarks."""
    ap.add_argument("--device", default="cuda", help="cuda (default) or cpu for a dry run of the code paths")
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--write", action="store_true", help="write the tables into docs/benchmarks.md")


def gpu_device(args: argparse.Namespace) -> torch.device | None:
    """The device of :func:`add_gpu_arguments`' flags, or None after one line on stderr (exit 2): a device torch
    does not have, or ``--write`` without a full run on CUDA."""
    script = Path(sys.argv[0]).name
    try:
        device = resolve_device(args.device, "--device")
    except ValueError as e:
        print(f"{script}: error: {e} (this benchmark needs a CUDA GPU; --device cpu --quick is a dry run)",
              file=sys.stderr)
        return None
    if args.write and (args.quick or device.type != "cuda"):
        print(f"{script}: error: --write needs a full run on CUDA (no --quick)", file=sys.stderr)
        return None
    return device


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("render", "block", "generate", "command", "train", "all"), default="all")
    ap.add_argument("--rows", default=None, metavar="N,N,…",
                    help="generate: the 1-based numbers of the rows to run, of: "
                         + "; ".join(f"{i} {r[0]}" for i, r in enumerate(GENERATE, 1)) + " (default all)")
    add_gpu_arguments(ap, "tiny sizes: checks that every path runs, no figures")
    args = ap.parse_args()
    try:
        only = None if args.rows is None else sorted({int(n) for n in args.rows.split(",")})
        if only is not None and not all(1 <= n <= len(GENERATE) for n in only):
            raise ValueError
    except ValueError:
        print(f"gpu.py: error: --rows: comma-separated row numbers from 1 to {len(GENERATE)}, got {args.rows!r}",
              file=sys.stderr)
        return 2
    device = gpu_device(args)
    if device is None:
        return 2
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    if args.part == "all":  # each part in a process of its own: a part's pinned and cached memory dies with it
        flags = (["--device", args.device] + ["--quick"] * args.quick + ["--write"] * args.write
                 + ["--rows", args.rows] * (args.rows is not None))
        codes = [subprocess.run([sys.executable, __file__, "--part", part, *flags]).returncode
                 for part in ("render", "block", "generate", "command", "train")]
        return next((c for c in codes if c), 0)
    t0 = time.perf_counter()
    emit = (lambda body: write_section(f"gpu_{args.part}", body)) if args.write else None
    if args.part == "generate":
        body = part_generate(device, args.quick, emit, only, read_section("gpu_generate") if args.write else None)
    else:
        body = {"render": part_render, "block": part_block, "command": part_command,
                "train": part_train}[args.part](device, args.quick)
    print(body + f"\n\n({args.part}: {time.perf_counter() - t0:.0f} s)\n", flush=True)
    if emit is not None:
        emit(body)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
