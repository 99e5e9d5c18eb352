"""``diff4splat fit SCENE_DIR --out DIR``: fit a 4D Gaussian scene to a scene folder (:mod:`training.fit`), registered
through the ``diff4splat.commands`` entry point. The output has ``generate``'s layout (docs/DESIGN.md, "Output folder
of generate"; marker kind "fit") in the scene's world frame, plus ``field.safetensors`` (dynamic fits) and
``metrics.json``. Checkpoints (CPU tensors, resumable on any device) go to ``DIR.checkpoints/`` every
``--checkpoint-every`` steps and on SIGTERM/SIGINT, and are removed once the output is written; ``--resume`` refuses
a checkpoint of another fit. Every argument is checked, limits included, before the scene is read.
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import signal
import sys
import time
from pathlib import Path

import torch

from data_prep.format import load_scene
from diff4splat.io.inputs import check_input_folder
from diff4splat.io.output_folders import check_output_dir
from diff4splat.io.scene_folder import (
    DEFORMATION_ARRAYS,
    FIELD_FILE,
    METRICS_FILE,
    SCENE_FILE,
    load_output_scene,
    scene_meta,
    write_scene_folder,
)
from diff4splat.io.video import DEFAULT_FPS, check_fps
from diff4splat.pipeline import check_seed
from diff4splat.render.sequence import render_path
from diff4splat.render.sh import rotate_sh
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.scene.quaternions import quat_conjugate, quat_multiply, rotmat_to_quat
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.costs import RENDER_BASE_BYTES
from diff4splat.utils.devices import AUTO, DEVICE_HELP, resolve_device
from diff4splat.utils.limits import check_limit, check_memory, check_output_size, held_memory
from models.hexplane import save_field
from training.checkpoint import latest_checkpoint, load_checkpoint, on_cpu, save_checkpoint
from training.densify import DensityStats
from training.fit import (
    BACKGROUNDS,
    DEPTH_WEIGHTS,
    FitConfig,
    FitState,
    config_dict,
    default_depth_weight,
    evaluate_views,
    fit_steps,
    gaussian_adam,
    init_background,
    init_state,
    start_fine_stage,
    to_scene,
)
from training.fit_data import (
    covisible_masks,
    depth_points,
    load_views,
    random_box_points,
    scene_extent,
    split_cameras,
)

__all__ = ["register", "run", "run_fit", "FitInterrupted", "place_generate_output", "run_differences",
           "check_out_outside_inputs", "fit_memory_estimate", "FIT_BYTES_PER_GAUSSIAN", "FIT_BYTES_PER_VIEW_PIXEL"]

MAX_LISTED_DIFFERENCES = 6
"""Settings named in the message of a refused ``--resume`` (the rest are counted)."""


class FitInterrupted(Exception):
    """SIGTERM/SIGINT stopped the fit after a checkpoint was written; the command exits 128 + ``signum``."""

    def __init__(self, message: str, signum: int = signal.SIGTERM) -> None:
        super().__init__(message)
        self.signum = int(signum)


def _moves(views) -> bool:
    """Whether the views' cameras move."""
    V = torch.stack([v.viewmat for v in views])
    return bool((V - V[0]).abs().max() > 1e-6)


def place_generate_output(init_dir: Path, scene, ref_camera: str) -> DynamicGaussians:
    """A ``generate`` output folder's scene moved into the scene's world: generate's world is ``ref_camera`` at
    frame 0 (c2w = [R | c]), scaled by s = median valid depth / median Gaussian depth when the scene has depth.
    μ → s·R μ + c, q → q_R ⊗ q, scales × s, SH rotated by R (:func:`diff4splat.render.sh.rotate_sh`); Δμ → s·R Δμ,
    Δq → q_R ⊗ Δq ⊗ q_R⁻¹. Raises FileNotFoundError without scene.ply, ValueError for a bad file (named)."""
    if not (init_dir / SCENE_FILE).is_file():
        raise FileNotFoundError(f"--init: {init_dir / SCENE_FILE} does not exist (give a generate output folder)")
    loaded, _ = load_output_scene(init_dir)  # scene.ply, deformation.npz and meta.json checked as input
    g = loaded.canonical
    arrays = {k: getattr(loaded, k) for k in DEFORMATION_ARRAYS if getattr(loaded, k) is not None}
    scale = 1.0
    if scene.has_depth:
        depth = torch.from_numpy(scene.depth(ref_camera, 0))
        z = g.means[:, 2][g.means[:, 2] > 0]
        if bool(torch.isfinite(depth).any()) and z.numel():
            scale = float(depth[torch.isfinite(depth)].median() / z.median())
    c2w = torch.linalg.inv(scene.cameras(ref_camera).viewmats[0].double()).float()
    R, q_r = c2w[:3, :3], rotmat_to_quat(c2w[:3, :3])
    canonical = Gaussians(g.means * scale @ R.T + c2w[:3, 3], quat_multiply(q_r[None], g.quats),
                          g.scales * scale, g.opacities, rotate_sh(g.sh, R))
    if "d_means" in arrays:
        arrays["d_means"] = arrays["d_means"] * scale @ R.T
        arrays["d_quats"] = quat_multiply(quat_multiply(q_r, arrays["d_quats"]), quat_conjugate(q_r))
    return DynamicGaussians(canonical, **arrays)


def _generate_init(init_dir: Path, scene, ref_camera: str):
    """(means, quats, scales, opacities, sh) of :func:`place_generate_output` at t = 0."""
    g = place_generate_output(init_dir, scene, ref_camera).at(0.0)
    return g.means, g.quats, g.scales, g.opacities, g.sh


def _plain(value):
    """``value`` as JSON would store it (tuples as lists), so that equal settings compare equal."""
    return json.loads(json.dumps(value))


def run_differences(saved: dict | None, now: dict, prefix: str = "") -> list[str]:
    """One phrase per setting in which a checkpoint's run (``saved``) and this run (``now``) differ, with dotted
    names for nested dicts (the fit config's without ``config.``)."""
    saved, now = _plain(saved or {}), _plain(now)
    out = []
    for key in [*now, *(k for k in saved if k not in now)]:
        a, b = saved.get(key, "(absent)"), now.get(key, "(absent)")
        name = "" if (prefix, key) == ("", "config") else f"{prefix}{key}."
        if isinstance(a, dict) and isinstance(b, dict):
            out += run_differences(a, b, name)
        elif a != b:
            out.append(f"{prefix}{key} {a} in the checkpoint vs {b} now")
    return out


def _state_from_checkpoint(folder: Path, config: FitConfig, dynamic: bool, run: dict,
                           device: torch.device) -> FitState:
    """The :class:`FitState` of checkpoint ``folder`` on ``device``; ValueError naming the differing settings when
    the checkpoint is of another fit."""
    weights, saved, _ = load_checkpoint(folder)
    differences = run_differences(saved.get("run"), run)
    if differences:
        more = len(differences) - MAX_LISTED_DIFFERENCES
        listed = "; ".join(differences[:MAX_LISTED_DIFFERENCES]) + (f"; and {more} more" if more > 0 else "")
        raise ValueError(f"--resume: the checkpoint in {folder} is of another fit: {listed} (resume with the "
                         "checkpoint's settings, or fit into a new --out)")
    names = ("means", "scales", "quats", "opacities", "sh0", "shN")
    params = {k: torch.nn.Parameter(weights[k].to(device)) for k in names}
    extent = saved["extent"]
    state = FitState(params, gaussian_adam(params, config.lr, extent), DensityStats(0, device), extent, dynamic)
    state.optimizer.load_state_dict(saved["optimizer"])
    init_background(state, config)
    with torch.no_grad():
        state.background.copy_(weights["background"])
    if state.background_optimizer is not None:
        state.background_optimizer.load_state_dict(saved["background_optimizer"])
    state.stats.grad_accum, state.stats.denom, state.stats.max_radii = (t.to(device) for t in saved["stats"])
    if saved["field_optimizer"] is not None:
        start_fine_stage(state, config)
        state.field.load_state_dict({k[len("field."):]: v for k, v in weights.items() if k.startswith("field.")})
        state.field_optimizer.load_state_dict(saved["field_optimizer"])
    state.step, state.order, state.train_time = saved["step"], saved["order"], saved["train_time"]
    state.history, state.counts = saved["history"], saved["counts"]
    state.generator.set_state(saved["generator"])
    return state


def _save(run_dir: Path, state: FitState, config: FitConfig, run: dict) -> None:
    """Checkpoint ``state`` with CPU tensors only; meta.json records the device."""
    weights = {k: v.detach() for k, v in state.params.items()}
    weights["background"] = state.background.detach()
    if state.field is not None:
        weights.update({f"field.{k}": v for k, v in state.field.state_dict().items()})
    saved = {"optimizer": state.optimizer.state_dict(), "extent": state.extent,
             "stats": (state.stats.grad_accum, state.stats.denom, state.stats.max_radii),
             "field_optimizer": None if state.field_optimizer is None else state.field_optimizer.state_dict(),
             "background_optimizer": None if state.background_optimizer is None
             else state.background_optimizer.state_dict(),
             "step": state.step, "order": list(state.order), "train_time": state.train_time,
             "history": state.history, "counts": state.counts, "generator": state.generator.get_state(),
             "run": run}
    save_checkpoint(run_dir, state.step, on_cpu(weights), on_cpu(saved),
                    {"config": config_dict(config), "device": str(state.device)}, keep=1)


def check_out_outside_inputs(out: str | Path, scene_dir: str | Path, init: str | Path | None = None) -> None:
    """ValueError when ``out`` lies inside ``scene_dir`` or ``init`` (symlinks followed): the fit would write into
    its own input (equal or ancestor folders are :func:`diff4splat.io.output_folders.check_output_dir`'s)."""
    target = Path(out).resolve()
    for what, folder in (("the scene folder", scene_dir), ("the --init folder", init)):
        if folder is not None and target != Path(folder).resolve() and target.is_relative_to(Path(folder).resolve()):
            raise ValueError(f"--out {out} is inside {what} {folder}: the fit would write into its own input; "
                             "choose a folder outside it")


FIT_BYTES_PER_GAUSSIAN = 14_000
"""Peak memory of ``fit`` per Gaussian (parameters, gradients, Adam moments, field queries, renderer), with a margin
over the measured value (docs/benchmarks.md)."""
FIT_BYTES_PER_VIEW_PIXEL = 64
"""Memory of ``fit`` per pixel of every view kept in memory (colour, depth, masks, float32), with a margin."""


def _most_gaussians(config: FitConfig) -> int:
    """The most Gaussians a fit may hold: the densification cap or the initial points."""
    return max(config.densify.max_gaussians, config.init_points, config.random_points)


def fit_memory_estimate(scene, config: FitConfig) -> int:
    """Upper bound in bytes of ``fit``'s peak host memory, before the frames are loaded: memory held now,
    :data:`diff4splat.utils.costs.RENDER_BASE_BYTES`, :data:`FIT_BYTES_PER_VIEW_PIXEL` per pixel of every camera and
    frame, :data:`FIT_BYTES_PER_GAUSSIAN` per Gaussian at the most it may hold."""
    pixels = sum(c.width * c.height for c in map(scene.cameras, scene.camera_names)) * scene.num_frames
    return int(held_memory() + RENDER_BASE_BYTES + FIT_BYTES_PER_VIEW_PIXEL * pixels
               + FIT_BYTES_PER_GAUSSIAN * _most_gaussians(config))


def run_fit(scene_dir: Path, out: Path, config: FitConfig, *, holdout_camera: int | None = None, seed: int = 0,
            init: Path | None = None, resume: bool = False, eval_every: int = 250, checkpoint_every: int = 500,
            fps: float = DEFAULT_FPS, progress: bool = False, overwrite: bool = False,
            device: str | torch.device = "cpu") -> dict:
    """Fit ``scene_dir`` on ``device`` (:func:`diff4splat.utils.devices.resolve_device`) and write ``out``; returns
    metrics.json's dict. ``checkpoint_every`` 0 checkpoints only on SIGTERM/SIGINT.

    Raises FileNotFoundError (scene or ``init`` missing); ValueError for a bad argument, an unfittable scene (one
    still camera, no depth), ``resume`` without a checkpoint or with another fit's, or a missing device; LimitError: the
    fit's memory or its output folder above the machine's room (before any fitting);
    :class:`FitInterrupted` on SIGTERM/SIGINT after a checkpoint.
    """
    t_start = time.perf_counter()
    device = resolve_device(device, "device")
    check_positive_int("eval_every", eval_every)
    if checkpoint_every != 0:
        check_positive_int("checkpoint_every", checkpoint_every, "steps; 0: only on SIGTERM")
    scene = load_scene(scene_dir)
    check_out_outside_inputs(out, scene_dir, init)
    check_output_dir(out, inputs=[scene_dir, init], overwrite=overwrite, kind="fit")
    gaussians = _most_gaussians(config)
    check_memory(fit_memory_estimate(scene, config), f"a fit of up to {gaussians:,} Gaussians on {scene_dir}",
                 "--max-gaussians or --init-points")
    ref = scene.cameras(scene.camera_names[0])  # the written folder: the fit rendered along the first camera
    check_output_size(len(ref), ref.width, ref.height, gaussians, knobs="--max-gaussians or --init-points", out=out)
    torch.manual_seed(seed)
    train_names, holdout_names = split_cameras(scene, holdout_camera)
    train = load_views(scene, train_names, device=device)
    holdout = load_views(scene, holdout_names, device=device)
    dynamic = bool(scene.meta.dynamic) and scene.num_frames > 1
    masks = covisible_masks(holdout, train, static=not dynamic)
    if config.depth_weight is None:  # stored resolved: meta.json, checkpoints
        config = dataclasses.replace(config, depth_weight=default_depth_weight(scene.meta.depth_source))
    if dynamic and config.coarse_iterations >= config.iterations:
        raise ValueError(f"--coarse-iterations {config.coarse_iterations} leaves no fine stage for the dynamic scene "
                         f"{scene_dir} (--iterations {config.iterations}); give fewer coarse iterations")
    if len(train_names) == 1 and not _moves(train) and not scene.has_depth:
        raise ValueError(f"{scene_dir}: cannot fit: one camera that does not move and no depth give no parallax "
                         "to place anything (add cameras or depth)")
    run_dir = Path(str(out) + ".checkpoints")
    run = {"scene": str(Path(scene_dir).resolve()), "holdout_camera": holdout_camera, "seed": seed,
           "init": None if init is None else str(Path(init).resolve()), "config": config_dict(config)}
    if resume:
        folder = latest_checkpoint(run_dir)
        if folder is None:
            raise ValueError(f"--resume: no checkpoint in {run_dir}")
        state = _state_from_checkpoint(folder, config, dynamic, run, device)
    else:
        gen = torch.Generator(device="cpu").manual_seed(seed)
        if init is not None:
            means, quats, scales, opac, sh = (x.to(device) for x in
                                              _generate_init(Path(init), scene, scene.camera_names[0]))
            state = init_state(means, torch.zeros_like(means), config, scene_extent(train, means), dynamic, seed,
                               scales=scales, quats=quats, opacities=opac, sh=sh)
        else:
            if scene.has_depth:
                init_views = [v for v in train if v.frame == 0] if dynamic and config.init_first_frame else train
                means, colors = depth_points(init_views, config.init_points, gen)
            else:
                means, colors = random_box_points(train, config.random_points, gen)
            state = init_state(means, colors, config, scene_extent(train, means), dynamic, seed)
    degree = lambda s: min(config.sh_degree, s.step // config.sh_interval)  # noqa: E731

    def on_step(s: FitState) -> None:
        if holdout and (s.step % eval_every == 0 or s.step == config.iterations):
            s.history.append(_history_entry(s, holdout, degree(s), masks))
        if checkpoint_every and s.step % checkpoint_every == 0 and s.step < config.iterations:
            _save(run_dir, s, config, run)

    if holdout and not resume:  # the starting point (for a generate init: generate's Gaussians at t = 0)
        state.history.append(_history_entry(state, holdout, 0, masks))
    stop = {"flag": False, "signum": signal.SIGTERM}
    handlers = {}
    try:
        for sig in (signal.SIGTERM, signal.SIGINT):
            handlers[sig] = signal.signal(sig, lambda signum, _: stop.update(flag=True, signum=signum))
    except ValueError:  # not the main thread
        pass
    try:
        fit_steps(state, train, config, config.iterations, progress=progress, should_stop=lambda: stop["flag"],
                  on_step=on_step)
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)
    if stop["flag"] and state.step < config.iterations:
        _save(run_dir, state, config, run)
        raise FitInterrupted(f"stopped at step {state.step}; checkpoint in {run_dir}; rerun with --resume",
                             stop["signum"])
    return _write_output(scene, out, state, config, train, holdout, masks, dict(
        scene=str(scene_dir), holdout_camera=holdout_camera, seed=seed, init=None if init is None else str(init),
        fps=fps, overwrite=overwrite, t_start=t_start, run_dir=run_dir, progress=progress, device=str(device)))


def _history_entry(state: FitState, holdout, sh_degree: int, masks) -> dict:
    """One metrics.json ``history`` row: held-out PSNRs at the current step."""
    held = evaluate_views(state, holdout, sh_degree, masks)
    return {"step": state.step, "train_time_s": state.train_time, "num_gaussians": state.num_gaussians,
            "holdout_psnr": held["psnr"], "holdout_masked_psnr": _number(held["masked_psnr"])}


def _number(x: float) -> float | None:
    """None for NaN (JSON)."""
    return None if math.isnan(x) else x


def _write_output(scene, out: Path, state: FitState, config: FitConfig, train, holdout, masks, opts: dict) -> dict:
    """Evaluate, render along the reference camera, write ``out`` and remove the checkpoints; metrics.json's dict."""
    deg = min(config.sh_degree, state.step // config.sh_interval)
    ref = scene.cameras(scene.camera_names[0])
    fitted = to_scene(state, ref.times if state.field is not None else None)
    train_eval = evaluate_views(state, train, deg)
    held = evaluate_views(state, holdout, deg, masks) if holdout else None
    background = tuple(state.background_rgb().detach().tolist())
    colors, depths, alphas = (x.cpu() for x in render_path(fitted, ref.to(state.device), background=background,
                                                           progress=opts["progress"]))
    fitted = fitted.to("cpu")  # the files are written from CPU copies
    metrics = {
        "train_psnr": train_eval["psnr"], "train_ssim": train_eval["ssim"],
        "holdout_psnr": None if held is None else held["psnr"], "holdout_ssim": None if held is None else held["ssim"],
        "holdout_masked_psnr": None if held is None else _number(held["masked_psnr"]),
        "holdout_covisible": None if held is None else _number(held["covisible"]),
        "holdout_camera": None if not holdout else holdout[0].camera, "iterations": state.step,
        "wall_time_s": time.perf_counter() - opts["t_start"], "train_time_s": state.train_time,
        "ms_per_iteration": 1000 * state.train_time / max(state.step, 1),
        "num_gaussians": fitted.num_gaussians, "static": fitted.is_static, "densify": state.counts,
        "device": opts["device"], "history": state.history,
    }
    meta = {"command": "fit", "scene": opts["scene"], "init": opts["init"], "seed": opts["seed"],
            "holdout_camera": opts["holdout_camera"], "train_cameras": sorted({v.camera for v in train}),
            "sh_degree": deg, "device": opts["device"],
            "config": config_dict(config), "cameras": f"{scene.camera_names[0]} (scene world frame)",
            **scene_meta(fitted, ref, fps=opts["fps"], background=background)}

    def extra(tmp: Path) -> None:
        if state.field is not None:
            save_field(tmp / FIELD_FILE, state.field)
        (tmp / METRICS_FILE).write_text(json.dumps(metrics, indent=2))

    write_scene_folder(out, fitted, ref, colors, depths, alphas, meta, fps=opts["fps"],
                       inputs=[opts["scene"], opts["init"]], overwrite=opts["overwrite"], kind="fit", extra=extra)
    if latest_checkpoint(opts["run_dir"]) is not None or (opts["run_dir"] / "checkpoints").is_dir():
        shutil.rmtree(opts["run_dir"], ignore_errors=True)
    return metrics


def register(subparsers) -> None:
    """Add ``fit`` to ``diff4splat``'s CLI (entry point ``diff4splat.commands``)."""
    d = FitConfig()
    p = subparsers.add_parser("fit", help="fit a 4D Gaussian scene to a multi-view video scene folder (4DGS)",
                              description="Optimise canonical Gaussians + a HexPlane deformation field "
                                          "(4D Gaussian Splatting, Wu et al. 2024) on a data_prep scene folder.")
    p.add_argument("scene", type=Path, help="scene folder (data_prep format: synthetic or a converter's output)")
    p.add_argument("--out", type=Path, required=True, help="output folder (generate's layout + field.safetensors, "
                   "metrics.json), written atomically; replaces only an earlier fit output")
    p.add_argument("--iterations", type=int, default=d.iterations, help=f"total steps (default {d.iterations})")
    p.add_argument("--coarse-iterations", type=int, default=d.coarse_iterations,
                   help=f"static coarse-stage steps (default {d.coarse_iterations})")
    p.add_argument("--holdout-camera", type=int, default=None,
                   help="camera index never trained on; its frames give holdout_psnr/holdout_ssim (and, with depth, "
                        "holdout_masked_psnr over the pixels some training view sees)")
    p.add_argument("--seed", type=int, default=0, help="seed (initial subset, view order, splits; default 0)")
    p.add_argument("--max-gaussians", type=int, default=d.densify.max_gaussians,
                   help=f"densification adds Gaussians up to this count (default {d.densify.max_gaussians}; an --init "
                        "scene that holds more keeps them, less what pruning removes)")
    p.add_argument("--init-points", type=int, default=d.init_points,
                   help=f"at most this many back-projected depth points initialise the fit (default {d.init_points})")
    p.add_argument("--sh-degree", type=int, default=d.sh_degree, help=f"largest SH degree (default {d.sh_degree})")
    p.add_argument("--depth-weight", type=float, default=None,
                   help="weight of the depth L1 (0: off; default: by the scene's depth source, "
                        + ", ".join(f"{k} {v:g}" for k, v in DEPTH_WEIGHTS.items() if k != "none") + ")")
    p.add_argument("--background", choices=sorted(BACKGROUNDS), default=d.background,
                   help="colour behind the Gaussians: learned (one RGB optimised with the fit, written to meta.json), "
                        f"black or white (default {d.background})")
    p.add_argument("--init", type=Path, default=None,
                   help="initialise from a generate output folder (made from the reference camera's frame 0)")
    p.add_argument("--eval-every", type=int, default=250, help="held-out evaluation interval, steps (default 250)")
    p.add_argument("--checkpoint-every", type=int, default=500, help="checkpoint interval, steps, ≥ 1 (one "
                   "larger than --iterations: only on SIGTERM; default 500)")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in OUT.checkpoints")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS, help=f"video frame rate (default {DEFAULT_FPS:g})")
    p.add_argument("--device", default=AUTO, help=DEVICE_HELP + "; where the Gaussians, the field and the views "
                   "live (a checkpoint resumes on any device)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--overwrite", action="store_true", help="also replace an --out that is not an earlier fit output")
    p.set_defaults(func=run)


def run(args) -> int:
    """The ``fit`` command: one summary line; 143 after SIGTERM, 130 after SIGINT (checkpoint written first).
    Raises ValueError naming the flag of a bad argument, one above its limit, or a missing ``--device``."""

    device = resolve_device(args.device, "--device")  # before any work
    flag = lambda name: "--" + name.replace("_", "-")  # noqa: E731
    for name in ("iterations", "eval_every", "checkpoint_every", "max_gaussians", "init_points"):
        check_positive_int(flag(name), getattr(args, name))
    check_limit("iterations", args.iterations, "--iterations")
    for name in ("max_gaussians", "init_points"):
        check_limit("gaussians", getattr(args, name), flag(name))
    check_fps(args.fps, "--fps")
    check_seed(args.seed, "--seed")
    check_input_folder(args.scene, "scene")  # a file, FIFO or symlink loop said as such, before any path is resolved
    if args.init is not None:
        check_input_folder(args.init, "--init")
    check_out_outside_inputs(args.out, args.scene, args.init)
    d = FitConfig()
    config = FitConfig(iterations=args.iterations, coarse_iterations=args.coarse_iterations,
                       sh_degree=args.sh_degree, init_points=args.init_points, depth_weight=args.depth_weight,
                       background=args.background,
                       densify=dataclasses.replace(d.densify, max_gaussians=args.max_gaussians))
    try:
        m = run_fit(args.scene, args.out, config, holdout_camera=args.holdout_camera, seed=args.seed,
                    init=args.init, resume=args.resume, eval_every=args.eval_every,
                    checkpoint_every=args.checkpoint_every, fps=args.fps, progress=not args.quiet,
                    overwrite=args.overwrite, device=device)
    except FitInterrupted as e:
        print(f"diff4splat fit: interrupted: {e}", file=sys.stderr)
        return 128 + e.signum
    held = "" if m["holdout_psnr"] is None else f", held-out {m['holdout_psnr']:.2f} dB"
    if m["holdout_masked_psnr"] is not None:
        held += f" (co-visible pixels {m['holdout_masked_psnr']:.2f} dB)"
    print(f"wrote {args.out} ({m['num_gaussians']} Gaussians, {'static' if m['static'] else 'dynamic'}, "
          f"train {m['train_psnr']:.2f} dB{held}) in {m['wall_time_s']:.1f} s on {m['device']}")
    return 0
