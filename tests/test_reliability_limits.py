"""Issue 11, limits and nonsense input: absurd requests are refused before allocation, in one line with the
value and the limit (exit 2); nonsense inputs are errors; messages say what is wrong in the user's terms."""
import json
import os
import struct
import sys
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE, benchmark_module, not_a_folder, tiny_model
from simulated_cuda import simulated_cuda
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

import diff4splat.export as export_module
import diff4splat.pipeline as pipeline
import training.fit_cli as fit_cli
from data_prep.cli import main as data_prep_main
from data_prep.clips import ClipConfig, ClipDataset
from data_prep.synth import generate_scene
from diff4splat.cameras import CameraPath
from diff4splat.cli import main
from diff4splat.generate import memory_estimate
from diff4splat.io import load_cameras_json, load_realestate10k, save_cameras_json
from diff4splat.io.image import header_size, read_image
from diff4splat.pipeline import Diff4SplatPipeline, load_model
from diff4splat.runtime import TorchRuntime
from diff4splat.utils.costs import MEMORY_MAP_COPIES
from diff4splat.utils.limits import (
    LIMITS,
    OUTPUT_BYTES_PER_GAUSSIAN,
    LimitError,
    check_limit,
    check_memory,
    check_output_size,
    limit,
)
from diff4splat.utils.offload import pinned_bytes, weight_bytes
from models.bundle import Diff4SplatModel, load_config
from models.pretrained import config_from_dict
from models.vae import VideoVAEConfig

run_with_peak_memory = benchmark_module("_common").run_with_peak_memory

def _cli(capsys, *args):
    """Run ``diff4splat`` in-process; (exit code, the stderr lines that are not warnings)."""
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, [line for line in err.splitlines() if line.strip() and not line.startswith("diff4splat: warning")]


def _generate(capsys, tmp_path, *extra, image=EXAMPLE_IMAGE):
    out = tmp_path / "out"
    code, lines = _cli(capsys, "generate", image, "--quiet", "--out", out, *extra)
    assert not out.exists()
    return code, lines


def _zero_png(width: int, height: int, rows: int = 500) -> bytes:
    """A valid grey 8-bit PNG of zeros, built without compressing width × height bytes: each block of
    ``rows`` rows is deflated once and ended by a full flush (no back-references across blocks), so the
    identical compressed block is repeated; the Adler-32 of n zero bytes is (1, n mod 65521)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    assert height % rows == 0
    block = b"\x00" * ((width + 1) * rows)  # filter byte 0 + zero pixels per row
    c = zlib.compressobj(9)
    first = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    adler = (((width + 1) * height % 65521) << 16) | 1
    idat = first + again * (height // rows - 1) + b"\x03\x00" + struct.pack(">I", adler)  # final empty block
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _one_line(code, lines, *needles):
    assert code == 2, lines
    assert len(lines) == 1 and lines[0].startswith("diff4splat: error:"), lines
    for n in needles:
        assert n in lines[0], lines[0]


# --------------------------------------------------------------------------- the limits table

def test_limits_read_their_env_var_at_each_check(monkeypatch):
    assert check_limit("steps", LIMITS["steps"].default, "--steps") == LIMITS["steps"].default
    monkeypatch.setenv("DIFF4SPLAT_MAX_STEPS", "5")
    assert check_limit("steps", 5, "--steps") == 5
    with pytest.raises(LimitError, match=r"--steps 6 exceeds the limit of 5 sampler steps \(set DIFF4SPLAT_MAX_STEPS"):
        check_limit("steps", 6, "--steps")
    monkeypatch.setenv("DIFF4SPLAT_MAX_STEPS", "lots")
    with pytest.raises(ValueError, match="DIFF4SPLAT_MAX_STEPS must be a positive integer, got 'lots'"):
        limit("steps")


def test_output_size_estimate_is_frames_times_resolution():
    assert check_output_size(17, 64, 64) == 17 * 64 * 64 * 16
    # with the scene: scene.ply plus one PLY row and one deformation row per Gaussian and frame (17 + 10 float32)
    assert check_output_size(17, 64, 64, gaussians=1000) == 17 * 64 * 64 * 16 + 18 * 1000 * 112
    assert OUTPUT_BYTES_PER_GAUSSIAN >= (17 + 10) * 4
    with pytest.raises(LimitError, match=r"1001 frames at 4096×4096: estimated 250.2 GiB exceeds the limit of 4.0 GiB "
                                         r"\(4294967296 bytes; lower --frames or --resolution, or set "
                                         r"DIFF4SPLAT_MAX_OUTPUT_BYTES to raise it\)"):
        check_output_size(1001, 4096, 4096, knobs="--frames or --resolution")


# --------------------------------------------------------------------------- CLI: refused before any work

@pytest.mark.parametrize("flag, value, limit_text", [("--steps", 10**9, "limit of 1000 sampler steps"),
                                                     ("--frames", 10001, "limit of 1001 frames")])
def test_steps_and_frames_above_the_limit_exit_2_at_once(tmp_path, capsys, flag, value, limit_text):
    t0 = time.perf_counter()
    code, lines = _generate(capsys, tmp_path, flag, value)
    _one_line(code, lines, f"{flag} {value}", limit_text)
    assert time.perf_counter() - t0 < 5  # the old code ran (steps: 20 GB in 24 s; frames: wrote ~3 GB)


@pytest.mark.slow
def test_output_size_estimate_is_checked_before_the_networks_run(tmp_path, capsys, monkeypatch):
    def never(*a, **k):
        raise AssertionError("the pipeline ran")

    monkeypatch.setattr(pipeline.Diff4SplatPipeline, "__call__", never)
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", "100000")
    code, lines = _generate(capsys, tmp_path, "--frames", "9", "--steps", "1")
    _one_line(code, lines, "output of 9 frames at 256×256: estimated", "DIFF4SPLAT_MAX_OUTPUT_BYTES")


@pytest.mark.slow
def test_memory_estimate_is_checked_before_the_networks_run_and_names_the_knobs(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(Diff4SplatPipeline, "__call__", _never)
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", str(1 << 40))  # the output check would refuse 401 frames first
    monkeypatch.setenv("DIFF4SPLAT_MAX_MEMORY_BYTES", str(8 << 30))  # a laptop, whatever this machine has
    code, lines = _generate(capsys, tmp_path, "--frames", "401")
    _one_line(code, lines, "401 frames at 256×256: estimated peak memory", "GiB exceeds the limit of 8.0 GiB",
              "lower --frames or --resolution", "DIFF4SPLAT_MAX_MEMORY_BYTES")


def _never(*args, **kwargs):
    raise AssertionError("the pipeline ran")


def test_memory_estimate_grows_with_key_times_times_slots():
    """The deformation of the unpruned scene (key times × slots) dominates long paths: doubling the path about
    quadruples the excess over the fixed part; a runtime without deformation leaves the key-time terms out."""
    pipe = Diff4SplatPipeline(TorchRuntime(Diff4SplatModel(load_config("tiny"))))
    c = pipe.config
    fixed = memory_estimate(pipe, c.width, c.height, 1)
    grow = [memory_estimate(pipe, c.width, c.height, t) - fixed for t in (201, 401)]
    assert 3.5 < grow[1] / grow[0] < 4.5
    pipe.runtime.has_deformation = False
    assert memory_estimate(pipe, c.width, c.height, 401) - fixed < grow[1] / 10
    pipe.runtime.has_deformation = True
    huge = memory_estimate(pipe, 4096, 4096, 1001)
    assert huge > 2**41  # 2 TiB: above any one machine's memory (the GPU machines have 128 GB)
    with pytest.raises(LimitError, match="GiB exceeds the .* GiB"):
        check_memory(huge, "x", "y")


@pytest.mark.slow  # the simulation's first dispatch mode imports torch._dynamo
def test_memory_estimate_on_a_gpu_counts_host_memory_only():
    """On CUDA (simulated) the estimate leaves out what lives in GPU memory: the weights without offload, the LDRM's
    deformation maps always; with model offload it counts the weights' pinned copies (pinned_bytes, not their
    bytes). Against the CPU's estimate for the same request: differences equal to those terms."""
    cfg = load_config("tiny")
    frames = 9
    n = 1 + (frames - 1) // 4  # latent frames of the tiny model's 4× temporal compression
    with simulated_cuda(), torch.no_grad():
        cpu = Diff4SplatPipeline(Diff4SplatModel(cfg), "cpu")
        gpu = Diff4SplatPipeline(Diff4SplatModel(cfg), "cuda")
        off = Diff4SplatPipeline(Diff4SplatModel(cfg), "cuda", offload="model")
        est = {k: memory_estimate(p, cfg.width, cfg.height, frames) for k, p in (("cpu", cpu), ("gpu", gpu),
                                                                                   ("off", off))}
        nets = cpu.runtime.networks.values()
        assert n == cpu.runtime.latent.num_latent_frames(frames)
    raw = sum(sum(weight_bytes(net)) for net in nets)
    pinned = sum(pinned_bytes(weight_bytes(net)) for net in nets)
    maps = 40 * frames * MEMORY_MAP_COPIES * n * cfg.height * cfg.width
    assert est["cpu"] - est["gpu"] == raw + maps
    assert est["off"] - est["gpu"] == pinned and pinned > raw


@pytest.mark.slow
def test_memory_estimate_bounds_the_measured_peak_of_generate(tmp_path):
    """The whole command in a child process (peak resident memory ``ru_maxrss``) stays under the estimate that
    ``generate`` checks, and the estimate is not so loose that it refuses what runs (≤ 2× the peak). On the CPU
    (``--device cpu``), what the estimate bounds: on a GPU machine ``auto`` would put the tensors it counts on the
    GPU. The peak is the command's own (``run_with_peak_memory``): started straight from a pytest worker, it read
    the worker's 2.72 GB on a GPU machine against its own 1.34 GB."""
    frames, res = 65, 64
    done, peak = run_with_peak_memory([sys.executable, "-m", "diff4splat.cli", "generate", str(EXAMPLE_IMAGE),
                                       "--frames", str(frames), "--resolution", str(res), "--device", "cpu",
                                       "--prompt", "a cat turns its head", "--quiet", "--out", str(tmp_path / "o")])
    assert done.returncode == 0
    estimate = memory_estimate(Diff4SplatPipeline.from_pretrained(), res, res, frames)
    assert peak <= estimate <= 2 * peak, (peak, estimate)


# --------------------------------------------------------------------------- camera files

def test_camera_file_of_a_million_frames_is_refused_unparsed(tmp_path):
    K, V = "[[100,0,32],[0,100,32],[0,0,1]]", "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"
    path = tmp_path / "cameras.json"  # compact JSON, 74 MB
    path.write_text(f'{{"width":64,"height":64,"Ks":[{",".join([K] * 10**6)}],"viewmats":[{",".join([V] * 10**6)}]}}')
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(LimitError, match=rf"{path}: \d+ bytes is too large for a camera path of at most 1001 "
                                         r"frames \(limit \d+ bytes; set DIFF4SPLAT_MAX_FRAMES"):
        load_cameras_json(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert time.perf_counter() - t0 < 1 and peak < 10 << 20  # the old code parsed it all (49 GB asked)


def _camera_json(T: int) -> dict:
    K = [[50.0, 0.0, 32.0], [0.0, 50.0, 32.0], [0.0, 0.0, 1.0]]
    V = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    return {"width": 64, "height": 64, "Ks": [K] * T, "viewmats": [V] * T}


def test_camera_path_longer_than_the_frame_limit_is_refused_before_tensors(tmp_path, capsys):
    path = tmp_path / "cams.json"
    path.write_text(json.dumps(_camera_json(1005)))
    with pytest.raises(LimitError, match=r"a camera path of 1005 exceeds the limit of 1001 frames"):
        load_cameras_json(path)
    code, lines = _generate(capsys, tmp_path, "--cameras", path, "--steps", "1")
    _one_line(code, lines, "1005", "1001", "DIFF4SPLAT_MAX_FRAMES")
    rows = "\n".join(f"{i} 0.5 0.5 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0" for i in range(1002))
    (tmp_path / "cams.txt").write_text(rows + "\n")
    with pytest.raises(LimitError, match="a camera path of 1002 exceeds the limit of 1001 frames"):
        load_realestate10k(tmp_path / "cams.txt", 64, 64)


def test_camera_width_times_height_is_bounded(tmp_path):
    data = _camera_json(5)
    data["width"] = data["height"] = 10**15
    path = tmp_path / "cams.json"
    path.write_text(json.dumps(data))
    with pytest.raises(LimitError, match=r"width × height = 1000000000000000×1000000000000000 = \d+ exceeds"):
        load_cameras_json(path)


def test_binary_camera_file_names_the_file(tmp_path):
    path = tmp_path / "cams.json"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe binary")
    with pytest.raises(ValueError, match=rf"camera file: {path} is not UTF-8 text \(byte 0x89 at offset 0"):
        load_cameras_json(path)
    with pytest.raises(ValueError, match=rf"camera file: {path} is not UTF-8 text"):
        load_realestate10k(path, 64, 64)


# --------------------------------------------------------------------------- images

def test_header_size_reads_every_parsed_format_without_decoding():
    img = np.zeros((37, 53, 3), np.uint8)
    for ext, params in [(".png", []), (".jpg", []), (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), (".bmp", []),
                        (".webp", []), (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101]), (".tiff", [])]:
        ok, data = cv2.imencode(ext, img, params)
        assert ok and header_size(data.tobytes()) == (53, 37), ext
    assert header_size(b"GIF89a....") is None


def test_huge_png_is_refused_from_its_header_fast_and_small(tmp_path, capsys):
    path = tmp_path / "huge.png"
    path.write_bytes(_zero_png(30000, 30000))
    assert path.stat().st_size < 1 << 20  # 0.9 MB that decodes to 900 MB (16 GB peak in the old code)
    t0 = time.perf_counter()
    with pytest.raises(LimitError, match=r"30000×30000 = 900000000 exceeds the limit of 100000000 pixels "
                                         r"\(set DIFF4SPLAT_MAX_IMAGE_PIXELS"):
        read_image(path)
    assert time.perf_counter() - t0 < 1
    code, lines = _generate(capsys, tmp_path, image=path)
    _one_line(code, lines, "900000000", "100000000")


@pytest.mark.slow
def test_huge_png_refusal_stays_under_200_mb_of_memory(tmp_path):
    path = tmp_path / "huge.png"
    path.write_bytes(_zero_png(30000, 30000))
    script = ("import resource, sys\nfrom diff4splat.io.image import read_image\n"
              "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
              "try:\n    read_image(sys.argv[1])\nexcept ValueError as e:\n    print(e)\n"
              "print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)\n")
    # started by a small process: a child started straight from this one would begin at this process's peak
    out, _ = run_with_peak_memory([sys.executable, "-c", script, str(path)], capture_output=True, text=True,
                                  timeout=120)
    message, grown_mb = out.stdout.splitlines()
    assert "exceeds the limit" in message and int(grown_mb) < 200, out.stdout


def test_small_zero_png_from_the_helper_decodes():  # the huge one is the same construction
    path_bytes = _zero_png(300, 1000)
    img = cv2.imdecode(np.frombuffer(path_bytes, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (1000, 300) and int(img.max()) == 0


@pytest.mark.parametrize("kind, text", [("folder", "is a folder, not a file"), ("fifo", "is a FIFO (named pipe)"),
                                        ("loop", "is a symlink loop"), ("missing", "does not exist")])
def test_image_that_is_not_a_file_says_what_it_is(tmp_path, capsys, kind, text):
    path = tmp_path / "photo.png"
    if kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "loop":
        path.symlink_to(tmp_path / "other.png")
        (tmp_path / "other.png").symlink_to(path)
    code, lines = _generate(capsys, tmp_path, image=path)
    _one_line(code, lines, f"image: {path} {text}")
    with pytest.raises((ValueError, FileNotFoundError), match=text.replace("(", r"\(").replace(")", r"\)")):
        read_image(path)


# --------------------------------------------------------------------------- models

def _checkpoint(tmp_path, **vae):
    folder = tmp_path / "ckpt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        Diff4SplatModel.random(load_config("tiny")).save_pretrained(folder)
    cfg = json.loads((folder / "config.json").read_text())
    cfg["vae"].update(vae)
    (folder / "config.json").write_text(json.dumps(cfg))
    return folder


class _LargestTensor(TorchDispatchMode):
    """Records the largest tensor (bytes) any torch op returns off the ``meta`` device while active."""

    def __init__(self):
        super().__init__()
        self.largest = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor) and t.device.type != "meta":
                self.largest = max(self.largest, t.numel() * t.element_size())
        return out


def test_largest_tensor_sees_an_allocation():
    with _LargestTensor() as seen:
        torch.zeros(1 << 20, dtype=torch.uint8)
    assert seen.largest == 1 << 20


@pytest.mark.slow
@pytest.mark.parametrize("channels", [10**9, 10**5])
def test_config_implying_a_huge_model_is_refused_before_allocation(tmp_path, capsys, channels):
    folder = _checkpoint(tmp_path, base_channels=channels)
    tracemalloc.start()
    with _LargestTensor() as torch_side, pytest.raises(
            LimitError, match=rf"{folder / 'config.json'}: .*(overflows|exceeds the limit of "
                              r"20000000000 parameters).*DIFF4SPLAT_MAX_PARAMETERS"):
        Diff4SplatModel.from_pretrained(folder)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50 << 20  # Python objects
    assert torch_side.largest < 1 << 20, torch_side.largest  # no weight allocated (the old code asked for 324 GB)
    code, lines = _generate(capsys, tmp_path, "--checkpoint", folder)
    _one_line(code, lines, "DIFF4SPLAT_MAX_PARAMETERS")


def test_float_for_an_int_config_field_is_a_clear_type_error(tmp_path):
    folder = _checkpoint(tmp_path, base_channels=1e9)
    with pytest.raises(ValueError, match=r"field 'base_channels' of VideoVAEConfig must be an integer, "
                                         r"got 1000000000.0 \(float"):
        Diff4SplatModel.from_pretrained(folder)
    with pytest.raises(ValueError, match="field 'depth' of LDRMConfig must be an integer, got 1000000000.0"):
        config_from_dict(load_config("tiny").__class__, {"ldrm": {"depth": 1e9}})  # accepted by the old code
    assert config_from_dict(VideoVAEConfig, {"base_channels": 16}).base_channels == 16


def test_a_checkpoint_config_of_sizes_that_do_not_fit_names_its_file(tmp_path, capsys):
    """issue 81, case 14: a config.json whose LDRM embed_dim no longer fits its deformation network said only
    "LDRMConfig.deformation.in_channels (…) must equal embed_dim (…)"; now the file is named, one line, exit 2."""
    ckpt = tmp_path / "ckpt"
    tiny_model().save_pretrained(ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    config["ldrm"]["embed_dim"] = 10**9
    (ckpt / "config.json").write_text(json.dumps(config))
    code, lines = _generate(capsys, tmp_path, "--checkpoint", ckpt)
    _one_line(code, lines, f"{ckpt / 'config.json'}.ldrm: ", "must equal embed_dim (1000000000)")


@pytest.mark.parametrize("command", ["export-onnx", "fit"])
def test_fit_and_export_check_the_free_space_before_their_work(tmp_path, capsys, monkeypatch, command):
    """issue 81, case 19: onto a full disk, fit and export-onnx failed cleanly but only at the write (after 58 s and
    87 s). The output's estimate is checked against the disk's free space (here a limit of 100 kB) before any work:
    one line naming the request and the variable, exit 2, nothing written."""
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", "100000")
    out = tmp_path / "out"

    def never(*args, **kwargs):
        raise AssertionError("the work started")

    if command == "fit":
        scene = generate_scene(tmp_path / "data", 0, seed=3)
        args = ["fit", str(scene), "--out", str(out), "--iterations", "10"]
        monkeypatch.setattr(fit_cli, "load_views", never)  # the frames are read only once the checks pass
    else:
        args = ["export-onnx", "--config", "tiny", "--out", str(out)]
        monkeypatch.setattr(export_module, "_export_graph", never)
    code, lines = _cli(capsys, *args)
    _one_line(code, lines, "exceeds the limit of 97.7 KiB", "DIFF4SPLAT_MAX_OUTPUT_BYTES")
    assert not out.exists()


def test_random_model_counts_its_parameters_first(monkeypatch):
    monkeypatch.setenv("DIFF4SPLAT_MAX_PARAMETERS", "1000")
    with pytest.raises(LimitError, match=r"config 'tiny': a model of \d+ exceeds the limit of 1000 parameters"):
        Diff4SplatModel.random(load_config("tiny"))


# --------------------------------------------------------------------------- nonsense input

def _pipeline():
    model, _ = load_model(config="tiny", untrained=True)
    return Diff4SplatPipeline(model)


@pytest.mark.slow
def test_camera_that_sees_none_of_the_scene_is_an_error(tmp_path, capsys):
    pipe = _pipeline()
    cams = pipe.default_cameras("orbit", 5)
    Ks = cams.Ks.clone()
    Ks[:, 0, 0] = Ks[:, 1, 1] = 1e30
    blind = CameraPath(cams.viewmats, Ks, cams.width, cams.height, cams.times)
    with pytest.raises(ValueError, match=r"cameras: focal lengths fx=1e\+30, fy=1e\+30 pixels give a field of view "
                                         r"of .* below 0.1°"):
        pipe(torch.rand(64, 64, 3), blind, steps=1)
    save_cameras_json(tmp_path / "blind.json", blind)
    code, lines = _generate(capsys, tmp_path, "--cameras", tmp_path / "blind.json", "--steps", "1")
    _one_line(code, lines, "field of view", "below 0.1°")  # before any network runs


def test_amplitude_with_a_camera_file_is_an_error(tmp_path, capsys):
    path = tmp_path / "cams.json"
    path.write_text(json.dumps(_camera_json(5)))
    code, lines = _generate(capsys, tmp_path, "--cameras", path, "--amplitude", "3", "--steps", "1")
    _one_line(code, lines, "--amplitude", "--cameras")


@pytest.mark.parametrize("seed", [10**30, -(2**63) - 1, 2**64])
def test_seed_out_of_range_gives_the_range(tmp_path, capsys, seed):
    code, lines = _generate(capsys, tmp_path, "--seed", seed, "--frames", "1", "--steps", "1")
    _one_line(code, lines, "--seed must be an integer in [-9223372036854775808, 18446744073709551615]", str(seed))
    with pytest.raises(ValueError, match="seed must be an integer in"):
        _pipeline()(torch.rand(64, 64, 3), _pipeline().default_cameras("orbit", 1), steps=1, seed=seed)


def test_non_utf8_prompt_is_named(tmp_path, capsys):
    prompt = os.fsdecode(b"a cat \xff jumps")  # what Python makes of a non-UTF-8 argv byte
    code, lines = _generate(capsys, tmp_path, "--prompt", prompt, "--frames", "1", "--steps", "1")
    _one_line(code, lines, "--prompt: not valid UTF-8 (byte 0xff at position 6)")


@pytest.mark.slow
def test_a_prompt_cut_to_the_tokenizers_length_is_one_warning_line(tmp_path, capsys):
    """A 100 k-character prompt: the text encoder's truncation warning is one ``diff4splat: warning:`` line (it was
    Python's raw ``UserWarning`` with its file and source line), and the scene is written."""
    code = main(["generate", str(EXAMPLE_IMAGE), "--quiet", "--out", str(tmp_path / "out"), "--prompt", "a" * 100_000,
                 "--frames", "5", "--steps", "1", "--no-frame-plys"])
    lines = capsys.readouterr().err.splitlines()
    assert code == 0 and (tmp_path / "out" / "meta.json").is_file(), lines
    warned = [line for line in lines if "prompt longer than" in line]
    assert len(warned) == 1 and warned[0].startswith("diff4splat: warning: a prompt longer than "), lines
    assert not [line for line in lines if "UserWarning" in line or "ids, mask" in line], lines


# --------------------------------------------------------------------------- data_prep and evaluate wording

def test_validate_on_an_empty_folder_says_no_scenes(tmp_path, capsys):
    assert data_prep_main(["validate", str(tmp_path)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == [f"no scenes found in {tmp_path} (a scene is a sub-folder with meta.json): 0 scenes checked"]


def test_convert_of_a_missing_folder_says_it_is_missing(tmp_path, capsys):
    code = data_prep_main(["convert", "realestate10k", str(tmp_path / "nope"), str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and f"source folder not found: {tmp_path / 'nope'}" in err and "must be given" not in err


@pytest.mark.parametrize("kind, text", [("fifo", "is a FIFO (named pipe), not a folder"),
                                        ("loop", "is a symlink loop, not a folder"),
                                        ("file", "is a regular file, not a folder")])
def test_convert_source_that_is_not_a_folder_says_what_it_is(tmp_path, capsys, kind, text):
    """issue 28: a FIFO source was "source folder not found"."""
    src = not_a_folder(tmp_path / "src", kind)
    code = data_prep_main(["convert", "realestate10k", str(src), str(tmp_path / "out")])
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err == [f"data_prep: error: source folder: {src} {text}"], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kind, text", [("fifo", "is a FIFO (named pipe), not a folder"),
                                        ("loop", "is a symlink loop, not a folder"),
                                        ("file", "is a regular file, not a folder")])
@pytest.mark.parametrize("command", ["fit", "fit --init", "render", "evaluate"])
def test_a_folder_argument_that_is_not_a_folder_says_what_it_is(tmp_path, capsys, kind, text, command):
    """issue 81, cases 8 and 15: ``fit`` with a symlink loop as the scene or ``--init`` printed a 34-line traceback;
    ``evaluate --data``, ``fit SCENE`` and ``render DIR`` said "not found" / "does not exist" of a FIFO, a loop or
    a file. Now one line naming the argument and what is there, exit 2, nothing written."""
    bad = not_a_folder(tmp_path / "bad", kind)
    out = tmp_path / "out"
    (tmp_path / "scene").mkdir()
    args, name = {"fit": (["fit", str(bad), "--out", str(out)], "scene"),
                  "fit --init": (["fit", str(tmp_path / "scene"), "--init", str(bad), "--out", str(out)], "--init"),
                  "render": (["render", str(bad), "--trajectory", "arc", "--out", str(out)], "scene folder"),
                  "evaluate": (["evaluate", "--data", str(bad), "--random", "--config", "tiny"], "--data")}[command]
    code = main(args)
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err == [f"diff4splat: error: {name}: {bad} {text}"], err
    assert not out.exists()


def test_convert_of_an_empty_camera_file_names_it(tmp_path, capsys):
    """issue 28: an empty RealEstate10K ``clip.txt`` said "the source sequence has no frames" without naming it."""
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "clip.txt").write_text("")
    code = data_prep_main(["convert", "realestate10k", str(tmp_path / "src"), str(tmp_path / "out")])
    err = capsys.readouterr().err.splitlines()
    assert code == 2 and err == [f"data_prep: error: {tmp_path / 'src' / 'clip.txt'} has no frames"], err
    assert not (tmp_path / "out").exists()


def test_no_clip_message_reads_as_english(tmp_path):
    """An empty or non-dataset folder says so (it said "no clip of 17 frames … fits in the scenes of X (0 scene(s))"
    to `evaluate --data`); a dataset of short scenes says that no clip fits."""
    with pytest.raises(ValueError, match=rf"no scene in {tmp_path}: a dataset root holds scene folders"):
        ClipDataset(tmp_path, ClipConfig(scenes="all"))
    generate_scene(tmp_path, 0, seed=0, size=16, frames=3, cameras=1)
    with pytest.raises(ValueError, match=rf"no clip of 17 frames .* fits in the scenes of {tmp_path} \(1 scene"):
        ClipDataset(tmp_path, ClipConfig(scenes="all"))


def test_readme_limits_table_names_every_limit_and_its_default():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    table = readme.split("### Limits", 1)[1].split("\n#", 1)[0]
    for lim in LIMITS.values():
        row = next(line for line in table.splitlines() if f"`{lim.env}`" in line)
        assert f"{lim.default:_}".replace("_", " ") in row or str(lim.default) in row, row


@pytest.mark.parametrize("extra, text, knob", [
    (("--frames", "401"), "401 frames at 64×64: estimated peak memory", "lower --frames"),
    (("--photo", EXAMPLE_IMAGE, "--resolution", "2048"), "--photo at ", "lower --resolution")])
def test_evaluate_checks_its_memory_before_any_clip_loads(tmp_path, capsys, monkeypatch, extra, text, knob):
    """issue 61: ``evaluate`` generates a scene per clip (and one for ``--photo`` at ``--resolution``); each
    estimate is checked against the process's memory before the clips load (no dataset is given: loading would
    fail on the empty folder with another message)."""
    monkeypatch.setenv("DIFF4SPLAT_MAX_MEMORY_BYTES", str(2 << 30))
    code, lines = _cli(capsys, "evaluate", "--random", "--config", "tiny", "--data", tmp_path, *extra)
    _one_line(code, lines, text, "GiB exceeds the limit of 2.0 GiB", knob, "DIFF4SPLAT_MAX_MEMORY_BYTES")
