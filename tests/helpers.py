"""Shared test helpers: small random models (no downloads), the shipped example photograph, and the
session-cached ONNX export. Test modules import from here, never from each other or from conftest."""
from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import json
import os
import shutil
import types
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from filelock import FileLock

import diff4splat.export
from diff4splat.cameras import intrinsics_from_fov
from diff4splat.cameras.path import CameraPath
from diff4splat.cli import main
from diff4splat.export import MANIFEST_NAME, export_onnx
from diff4splat.io import load_image
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from models.bundle import NETWORKS, Diff4SplatConfig, Diff4SplatModel
from models.hexplane import HexPlaneConfig, HexPlaneField
from models.motion import MotionConfig
from models.motion_generator import MotionGeneratorConfig
from models.text_encoder import TextEncoderConfig

OBJECTIVE_CASES = {
    "vae": (dict(train=("vae",), objectives=("vae",)), 0),
    "diffusion": (dict(objectives=("diffusion",), caption_dropout=0.5), 0),
    "reconstruction": (dict(train=("ldrm",), objectives=("reconstruction",), latent_noise=0.5), 0),
    "reconstruction_motion": (dict(train=("ldrm", "ldrm.deformation"), objectives=("reconstruction",),
                                   scenes="all", deformation=True, motion=True), 1),
}
"""The objective sets of the shipped stages as ``StageConfig`` keywords, with the clip each is run on (0: a static
clip, 1: a dynamic one), for the tiny model at 32² and 9 frames."""

EXAMPLE_IMAGE = Path(__file__).resolve().parent.parent / "examples" / "chelsea.png"
TEXTURES = Path(__file__).resolve().parent.parent / "data_prep" / "textures"
"""The bundled texture photographs (training data may use them; tests build videos from them)."""
BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def benchmark_module(name: str) -> types.ModuleType:
    """The script benchmarks/<name>.py loaded as a module (the benchmarks are scripts, not a package), so tests
    check its functions and measure as it does."""
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


TINY_MOTION = MotionConfig(features=4, hidden=8, levels=2, radius=1)
"""A motion network for the tiny model's tests (``tiny_model(motion=True)``)."""


def tiny_model(seed: int = 0, dynamic: bool = False, active_dit: bool = False, image_branch: int = 0,
               vae_upsample: str = "nearest", motion: bool = False):
    """A random tiny Diff4SplatModel (``vae_upsample``: its VAE decoder's ``VideoVAEConfig.upsample``).

    ``dynamic`` perturbs the zero-initialised deformation head; ``active_dit`` perturbs the DiT's
    zero-initialised layers (final layer, adaLN gates, camera and cross-attention projections), so its
    velocity is non-zero and depends on every input. ``image_branch`` > 0 gives the LDRM an image branch
    of that many channels (``LDRMConfig.image_branch``) whose zero-initialised last layer is perturbed,
    so the photograph changes frame 0's Gaussians. ``motion`` gives the LDRM the motion network :data:`TINY_MOTION`
    with its zero-initialised output perturbed (it moves pixels).
    """
    config = Diff4SplatConfig()
    if motion:
        config = dataclasses.replace(config, ldrm=dataclasses.replace(config.ldrm, motion=TINY_MOTION))
    config = dataclasses.replace(config, vae=dataclasses.replace(config.vae, upsample=vae_upsample))
    if image_branch:
        config = dataclasses.replace(config, ldrm=dataclasses.replace(config.ldrm, image_branch=image_branch))
    model = Diff4SplatModel.random(config, seed=seed).eval()
    if active_dit:
        g = torch.Generator().manual_seed(seed + 2)
        with torch.no_grad():
            for p in model.dit.parameters():
                if p.abs().sum() == 0:
                    p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    if dynamic:
        _perturb(model.ldrm.deformation.out_conv, seed + 1, weight_std=0.5)
    if image_branch:
        _perturb(model.ldrm.image_branch.out, seed + 3, weight_std=0.1)
    if motion:
        _perturb(model.ldrm.motion.out, seed + 4, weight_std=0.5, bias_std=1.0)
    return model


def _perturb(layer, seed: int, weight_std: float, bias_std: float = 0.1) -> None:
    """Overwrite a zero-initialised layer's weight and bias with seeded normal values (so it is no longer a no-op)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) * weight_std)
        layer.bias.copy_(torch.randn(layer.bias.shape, generator=g) * bias_std)


def parity_model(image_branch: int = 0):
    """tiny_model(dynamic=True) with every all-zero DiT tensor randomised: the zero-init final layer,
    cross-attention output projections, camera projection and adaLN gates (a default random model
    predicts v ≡ 0, which would make the DiT comparison trivial); ``image_branch`` as in :func:`tiny_model`, and
    then the shipped base model's layout: bilinear VAE upsampling too."""
    return tiny_model(seed=0, dynamic=True, active_dit=True, image_branch=image_branch,
                      vae_upsample="bilinear" if image_branch else "nearest")


def exported(tmp_path_factory, *, text=True, deformation=True, cli=False, image_branch=0):
    """(checkpoint folder, export folder) of :func:`parity_model`, built once per test run: under pytest-xdist in
    the run's temporary root that its workers share (each export takes about a minute of torch.export), one worker
    building it while the others wait on a file lock.

    ``cli`` makes the export through ``diff4splat export-onnx`` (flags ``--no-text`` / ``--static``);
    ``image_branch`` > 0 exports ``parity_model(image_branch)`` (its own checkpoint folder). Graphs an earlier
    export of the run already holds are copied from it (:func:`_graphs_from`): the lean export's from the full one,
    the image-branch export's from both.
    """
    own = tmp_path_factory.getbasetemp()
    base = (own.parent if os.environ.get("PYTEST_XDIST_WORKER") else own) / "onnx_cache"
    base.mkdir(parents=True, exist_ok=True)
    suffix = f"_image{image_branch}" if image_branch else ""
    ckpt = base / f"checkpoint{suffix}"
    out = base / f"export_text{int(text)}_deformation{int(deformation)}{suffix}"
    with FileLock(str(base / f"{ckpt.name}.lock")):
        if not (ckpt / "config.json").exists():
            parity_model(image_branch).save_pretrained(ckpt)
    with FileLock(str(base / f"{out.name}.lock")):
        if not (out / MANIFEST_NAME).exists():
            full = text and deformation and not image_branch
            sources = [] if full else [exported(tmp_path_factory)]
            if image_branch:
                sources.append(exported(tmp_path_factory, text=False, deformation=False, cli=True))
            with _graphs_from(sources):
                if cli:
                    flags = (["--no-text"] if not text else []) + (["--static"] if not deformation else [])
                    assert main(["export-onnx", "--checkpoint", str(ckpt), "--out", str(out), *flags]) == 0
                else:
                    model = Diff4SplatModel.from_pretrained(ckpt).eval()
                    export_onnx(model, out, text=text, deformation=deformation, checkpoint=ckpt, source=str(ckpt))
    return ckpt, out


UNREAD_CONFIG = {"vae_encoder": ("upsample",)}
"""Fields of its network's config a graph does not read (``VideoVAEConfig.upsample`` is the decoder's,
models/vae.py): left out when :func:`_graphs_from` compares two networks."""


def _graph_key(graph_name: str, part: str, network: torch.nn.Module, config: dict) -> tuple:
    """What a traced graph depends on: its network's weights and the model config without the other networks'
    configs and without its :data:`UNREAD_CONFIG` fields."""
    own = {k: v for k, v in config.items() if k == part or k not in NETWORKS}
    own[part] = {k: v for k, v in own[part].items() if k not in UNREAD_CONFIG.get(graph_name, ())}
    return diff4splat.export.state_dict_sha256(network), json.dumps(own, sort_keys=True)


@contextlib.contextmanager
def _graphs_from(sources: list[tuple[Path, Path]]):
    """Within it, an export copies a graph from an earlier export of the run instead of tracing it again (10–20 s a
    graph): from the first of ``sources`` ((checkpoint folder, export folder) pairs of :func:`exported`) whose graph
    of that name has the same opset, input and output names and the same :func:`_graph_key`; the copy's metadata is
    then the exporting model's (:func:`diff4splat.export.graph_metadata`). Each source graph is checked against
    PyTorch by the tests of its own export."""
    if not sources:
        yield
        return
    trace = diff4splat.export._export_graph
    known = [(Diff4SplatModel.from_pretrained(ckpt), out, json.loads((out / MANIFEST_NAME).read_text()))
             for ckpt, out in sources]

    def shared(graph, path: Path, opset: int, external_data_bytes: int, config: dict) -> dict:
        part = graph.module.part
        key = _graph_key(graph.name, part, getattr(graph.module, part), config)
        for model, out, manifest in known:
            entry = manifest["files"].get(graph.name)
            if (entry is None or manifest["opset"] != opset
                    or [i["name"] for i in entry["inputs"]] != list(graph.input_names)
                    or [o["name"] for o in entry["outputs"]] != list(graph.output_names)
                    or _graph_key(graph.name, part, getattr(model, part), manifest["config"]) != key):
                continue
            for name in entry["files"]:
                shutil.copyfile(out / name, path.parent / name)
            proto = onnx.load(str(path), load_external_data=False)
            onnx.helper.set_model_props(proto, diff4splat.export.graph_metadata(graph.name, config, entry["dims"]))
            onnx.save(proto, str(path))
            return entry
        return trace(graph, path, opset, external_data_bytes, config)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(diff4splat.export, "_export_graph", shared)
        yield


def moving_patch_scene(n: int = 400, frames: int = 5, shift: float = 0.6, sh_degree: int = 0, temporal: bool = False,
                       width: int = 128, height: int = 96, seed: int = 0):
    """A 1 m square patch of n random-coloured Gaussians 2.9–3.1 m in front of an identity camera (f = 80 px), moving
    ``shift`` metres along +x (to the right in the image) over the clip; ``shift`` 0 gives a static scene.

    Returns:
        (DynamicGaussians, CameraPath of ``frames`` identical cameras).
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 3.0 + 0.2 * torch.rand(n, 1, generator=g) - 0.1], 1)
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
    sh[:, 0] = rgb_to_sh0(0.2 + 0.8 * torch.rand(n, 3, generator=g))
    if sh_degree:
        sh[:, 1:] = 0.1 * torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=g)
    identity = torch.tensor([1.0, 0, 0, 0])
    canon = Gaussians(means, identity.repeat(n, 1), torch.full((n, 3), 0.04), torch.full((n,), 0.9), sh)
    temporal_args = {}
    if temporal:
        temporal_args = {"t_means": torch.rand(n, generator=g), "t_scales": torch.full((n,), 0.3)}
    times = torch.linspace(0, 1, frames)
    if shift == 0:
        scene = DynamicGaussians(canon, **temporal_args)
    else:
        d_means = torch.zeros(frames, n, 3)
        d_means[..., 0] = times[:, None] * shift
        d_quats = identity.repeat(frames, n, 1)
        d_quats[..., 3] = times[:, None] * 0.3  # a rotation about z growing with time (normalised on use)
        d_scales = times[:, None, None].expand(frames, n, 3) * 0.2
        scene = DynamicGaussians(canon, times, d_means, d_quats, d_scales.clone(), **temporal_args)
    K = torch.tensor([[80.0, 0, width / 2], [0, 80.0, height / 2], [0, 0, 1]])
    return scene, CameraPath(torch.eye(4).repeat(frames, 1, 1), K.repeat(frames, 1, 1), width, height)


def windowed_patch_scene(n: int = 60, frames: int = 9, seed: int = 1):
    """A moving patch whose Gaussians have bounded temporal support (trapezoids and boxes of random centre and
    half-width, some past the clip's ends) and whose first third does not move."""
    scene, cams = moving_patch_scene(n=n, frames=frames)
    g = torch.Generator().manual_seed(seed)
    t_means = 1.4 * torch.rand(n, generator=g) - 0.2
    t_scales = 0.02 + 0.4 * torch.rand(n, generator=g)
    t_ramps = torch.where(torch.arange(n) % 2 == 0, t_scales * torch.rand(n, generator=g), torch.zeros(n))
    spacing = 1 / (frames - 1)  # ten windows whose ends are key times, as reconstruct's layers
    t_means[20:30] = torch.arange(10) % frames * spacing
    t_scales[20:30] = spacing * (1 + torch.arange(10) % 2)
    t_ramps[20:30] = torch.where(torch.arange(10) % 3 == 0, 0.0, spacing)
    d_means, d_quats, d_scales = scene.d_means.clone(), scene.d_quats.clone(), scene.d_scales.clone()
    d_means[:, : n // 3] = 0
    d_quats[:, : n // 3] = torch.tensor([2.0, 0, 0, 0])  # the identity, unnormalised
    d_scales[:, : n // 3] = 0
    return DynamicGaussians(scene.canonical, scene.times, d_means, d_quats, d_scales, t_means, t_scales,
                            t_ramps), cams


def perturbed_field(means: torch.Tensor, seed: int = 0) -> HexPlaneField:
    """A small HexPlane field over the box of ``means`` (N, 3) whose deformation varies with time (every parameter
    perturbed by N(0, 0.3²); a new field is the identity), the same for a seed whatever torch's global generator
    holds (its initialisation draws from it)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        field = HexPlaneField(HexPlaneConfig(feature_dim=4, resolution=(4, 4, 4, 5), multires=(1,), net_width=16),
                              torch.stack([means.min(0).values, means.max(0).values]))
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in field.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.3)
    return field


def not_a_folder(path: Path, kind: str) -> Path:
    """Make ``path`` something that is not a folder: a FIFO ("fifo"), a symlink loop ("loop", through a sibling
    ``other``) or a regular file ("file"). Returns ``path``."""
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "loop":
        path.symlink_to(path.parent / "other")
        (path.parent / "other").symlink_to(path)
    elif kind == "file":
        path.write_text("x")
    else:
        raise ValueError(f"kind must be fifo, loop or file, got {kind!r}")
    return path


def adam_steps_on_the_default_device() -> bool:
    """Whether this torch's Adam makes its step counter on torch's default device rather than the CPU (torch 2.11
    does: ``torch.tensor(0.0)`` in ``Adam._init_group``; 2.13 passes ``device="cpu"``), so that no fit can run under
    the ``no_implicit_device`` fixture whatever our code does."""
    p = torch.zeros(1, device="cpu", requires_grad=True)
    p.grad = torch.zeros(1, device="cpu")
    opt = torch.optim.Adam([p])
    torch.set_default_device("meta")
    try:
        opt.step()
    except RuntimeError:
        return True
    finally:
        torch.set_default_device(None)
    return False


def moving_patch_video(frames: int, step: int = 1) -> np.ndarray:
    """(frames, 64, 64, 3) uint8: a 20-pixel grass patch moving ``step`` pixels right per frame over coins."""
    back = load_image(TEXTURES / "coins.png", (64, 64))
    patch = load_image(TEXTURES / "grass.png", (20, 20))
    out = []
    for t in range(frames):
        img = back.clone()
        x = 10 + step * t
        img[22:42, x:x + 20] = patch
        out.append((img.numpy() * 255).round().astype(np.uint8))
    return np.stack(out)


SQUARE_SIZE = 64
"""Side of :func:`square_scene`'s photograph, pixels."""


def square_scene():
    """A red 16×16 square (rows and columns 24–39) 2 m away before a grey wall 5 m away, 64² pixels; its camera
    (f = 60 px): (image (H, W, 3), depth (H, W) metres, K (3, 3))."""
    size = SQUARE_SIZE
    image = torch.full((size, size, 3), 0.5)
    image[24:40, 24:40] = torch.tensor([0.9, 0.1, 0.1])
    depth = torch.full((size, size), 5.0)
    depth[24:40, 24:40] = 2.0
    K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]])
    return image, depth, K


def still_path(pipe, frames=5):
    """``frames`` cameras at the identity with ``pipe``'s field of view at :data:`SQUARE_SIZE`², times 0…1."""
    size = SQUARE_SIZE
    K = intrinsics_from_fov(size, size, fov_y_deg=pipe.config.fov_y_deg)
    return CameraPath(torch.eye(4).expand(frames, 4, 4).clone(), K.expand(frames, 3, 3).clone(), size, size,
                      torch.linspace(0, 1, frames))


def tiny_motion_generator_config(**kw) -> MotionGeneratorConfig:
    """A motion generator small enough for a test: 16² photographs, 4² cells, 2 key times, a one-layer text encoder;
    ``kw`` overrides fields."""
    text = TextEncoderConfig(d_model=16, num_layers=1, num_heads=2, d_kv=8, d_ff=32, max_length=96)
    return MotionGeneratorConfig(**{"image_size": 16, "grid": 4, "key_frames": 2, "hidden_size": 24, "depth": 2,
                                    "num_heads": 2, "text": text, **kw})
