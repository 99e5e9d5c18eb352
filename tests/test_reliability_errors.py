"""Issue 11, "one error path": every expected failure of the command line tools is one line
``<prog>: error: <what>: <why>`` on stderr, exit 2, nothing written; Ctrl-C is one line and exit 130;
a bug keeps its traceback; libpng noise is silenced; ONNX manifests are checked against their graphs."""
from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import warnings
import zlib
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers import EXAMPLE_IMAGE, exported

import data_prep.cli as dcli
import diff4splat.io.atomic as atomic
import diff4splat.io.scene_folder as output
import diff4splat.pipeline
import diff4splat.utils.errors as errors
import training.stage_config
from diff4splat.cameras import make_trajectory
from diff4splat.cli import main
from diff4splat.io import cameras, exr, ply, video
from diff4splat.io.atomic import atomic_output_path, naming_os_errors
from diff4splat.io.image import read_image
from diff4splat.onnx_runtime import OnnxRuntime, load_manifest
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.errors import EXIT_INTERRUPTED, EXIT_USAGE, is_expected, one_line, quiet_c_stderr, run_cli
from training.train import main as train_main

REPO = Path(__file__).resolve().parent.parent
FAST = ["--frames", "1", "--steps", "1", "--quiet"]


def _err_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def _one_line_exit_2(code: int, err: str, *needles: str, prog: str = "diff4splat") -> str:
    lines = _err_lines(err)
    assert code == EXIT_USAGE, (code, err)
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _checkpoint(tmp_path_factory, tmp_path) -> Path:
    ckpt, _ = exported(tmp_path_factory)
    return Path(shutil.copytree(ckpt, tmp_path / "ckpt"))


def _export(tmp_path_factory, tmp_path) -> Path:
    _, out = exported(tmp_path_factory)
    return Path(shutil.copytree(out, tmp_path / "export", symlinks=True))


def _png_with_bad_iccp(path: Path) -> Path:
    """The example photo re-encoded with a bogus iCCP chunk after IHDR: libpng prints
    ``libpng warning: iCCP: …`` to fd 2 while decoding it, and the image still decodes."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ok, buf = cv2.imencode(".png", cv2.imread(str(EXAMPLE_IMAGE)))
    assert ok
    png = buf.tobytes()
    end_ihdr = 8 + 8 + 13 + 4  # signature, IHDR length/type, IHDR data, CRC
    path.write_bytes(png[:end_ihdr] + chunk(b"iCCP", b"ICC\0\0" + zlib.compress(b"no profile" * 20)) + png[end_ihdr:])
    return path


# --- the helpers themselves ---------------------------------------------------------------------------------


def test_expected_errors_are_listed_not_everything():
    assert is_expected(ValueError("x")) and is_expected(FileNotFoundError("msg only, no errno"))
    for code in (errno.ENOSPC, errno.EROFS, errno.EACCES, errno.ENAMETOOLONG, errno.EDQUOT):
        assert is_expected(OSError(code, os.strerror(code), "/p"))
    for exc in (OSError(errno.EBADF, "Bad file descriptor"), RuntimeError("bug"), TypeError("bug"),
                AttributeError("bug"), KeyError("k"), OSError("no errno")):
        assert not is_expected(exc), exc
    assert one_line(OSError(errno.ENOSPC, "No space left on device", "/d/o")) == "/d/o: No space left on device"
    assert one_line(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")) == \
        "/a -> /b: Invalid cross-device link"
    assert one_line(ValueError("a\n  b\tc")) == "a b c"
    assert one_line(ValueError()) == "ValueError"


def test_run_cli_codes(capsys):
    def raiser(exc):
        def body():
            raise exc
        return body

    assert run_cli("t", lambda: 0) == 0
    assert run_cli("t", raiser(OSError(errno.EROFS, "Read-only file system", "/ro/out"))) == EXIT_USAGE
    assert capsys.readouterr().err == "t: error: /ro/out: Read-only file system\n"
    assert run_cli("t", raiser(KeyboardInterrupt())) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "t: interrupted\n"
    with pytest.raises(RuntimeError, match="bug"):
        run_cli("t", raiser(RuntimeError("bug")))


def test_quiet_c_stderr_silences_fd_2_and_restores_it(capfd):
    with quiet_c_stderr():
        os.write(2, b"from C\n")
    os.write(2, b"after\n")
    with pytest.raises(ZeroDivisionError), quiet_c_stderr():  # restored after an exception too
        os.write(2, b"lost\n")
        raise ZeroDivisionError
    os.write(2, b"again\n")
    assert capfd.readouterr().err == "after\nagain\n"


def test_libpng_warning_of_a_bad_iccp_chunk_is_silenced(tmp_path, capfd):
    photo = _png_with_bad_iccp(tmp_path / "cat.png")
    cv2.imread(str(photo))
    assert "libpng warning" in capfd.readouterr().err  # the file really makes libpng talk
    assert read_image(photo).shape[:2] == cv2.imread(str(EXAMPLE_IMAGE)).shape[:2]
    assert "libpng" not in capfd.readouterr().err


# --- diff4splat generate: each expected failure is one line, exit 2, nothing written --------------------------


@pytest.mark.xdist_group("onnx_export")  # the one worker that builds the shared export
@pytest.mark.slow
@pytest.mark.parametrize("case", ["truncated_weights", "garbage_weights", "config_list", "config_not_json"])
def test_corrupt_checkpoint_is_one_line(tmp_path_factory, tmp_path, capsys, case):
    ckpt = _checkpoint(tmp_path_factory, tmp_path)
    weights = ckpt / "vae" / "model.safetensors"
    if case == "truncated_weights":
        weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
        bad = weights
    elif case == "garbage_weights":
        weights.write_bytes(b"\xff" * 64)
        bad = weights
    else:
        bad = ckpt / "config.json"
        bad.write_text("[1, 2, 3]" if case == "config_list" else "{not json")
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--checkpoint", str(ckpt), "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, str(bad))
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("device, needle", [("cuda:99", "cuda:99 is not available"), ("gpu", "not a torch device"),
                                            ("cuda", "cuda is not available")])
def test_unavailable_device_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, device, needle):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a GPU")

    def no_model(*a, **k):
        raise AssertionError("the model was loaded before the device was checked")

    monkeypatch.setattr(diff4splat.pipeline, "load_model", no_model)
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--device", device, "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, "--device", needle)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("fps", ["1001", "65536"])
def test_fps_beyond_the_mp4_time_base_is_refused_up_front(tmp_path, capsys, monkeypatch, fps):
    monkeypatch.setattr(diff4splat.pipeline, "load_model", lambda *a, **k: pytest.fail("model loaded"))
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--fps", fps, "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, "--fps", "1000", fps)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_fps_1000_still_writes_a_video(tmp_path, capsys):
    assert main(["generate", str(EXAMPLE_IMAGE), *FAST, "--fps", "1000", "--out", str(tmp_path / "o")]) == 0
    assert json.loads((tmp_path / "o" / "meta.json").read_text())["fps"] == 1000


@pytest.mark.slow
@pytest.mark.parametrize("code_, strerror", [(errno.ENOSPC, "No space left on device"),
                                             (errno.EROFS, "Read-only file system"),
                                             (errno.EACCES, "Permission denied")])
def test_os_errors_while_writing_are_one_line_naming_the_path(tmp_path, capsys, monkeypatch, code_, strerror):
    """Disk full, read-only file system, permissions (faked: the tests may run as root): the error names the path."""
    def fail(path, *a, **k):
        raise OSError(code_, strerror, str(path))

    monkeypatch.setattr(output, "save_ply", fail)
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--out", str(tmp_path / "o")])
    line = _one_line_exit_2(code, capsys.readouterr().err, "scene.ply", strerror)
    assert line.endswith(f"scene.ply: {strerror}")
    assert not (tmp_path / "o").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []  # no temp folder left behind


@pytest.mark.parametrize("out", ["", ".", "n" * 300])
def test_impossible_out_is_one_line(tmp_path, capsys, monkeypatch, out):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("user file")
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--out", out])
    _one_line_exit_2(code, capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "user file"


@pytest.mark.slow
def test_camera_file_with_absurd_width_is_one_line(tmp_path, capsys):
    # an int: the float 1e30 was refused already
    cams = {"width": 10 ** 30, "height": 64, "Ks": [[[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]],
            "viewmats": [np.eye(4).tolist()], "times": [0.0]}
    (tmp_path / "c.json").write_text(json.dumps(cams))
    code = main(["generate", str(EXAMPLE_IMAGE), "--steps", "1", "--quiet", "--cameras", str(tmp_path / "c.json"),
                 "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, "width")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("resolution", ["63", "1"])
def test_a_resolution_below_the_models_is_one_line_naming_the_minimum(tmp_path, capsys, resolution):
    """The shipped base model works at 64²: a smaller --resolution was "guide (63×63) must be at least as large as
    depth (64×64)" from deep inside the photo layer."""
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--resolution", resolution, "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, f"resolution {resolution} is below the model's 64 pixels",
                     "--resolution 64 or more")
    assert not (tmp_path / "o").exists()


def test_a_depth_kind_without_a_depth_file_is_refused(tmp_path, capsys):
    """--depth-kind inverse without --depth was silently ignored (meta.json: depth_kind null)."""
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--depth-kind", "inverse", "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, "--depth-kind inverse describes a --depth file")
    assert not (tmp_path / "o").exists()


def test_a_camera_file_of_the_wrong_length_names_itself(tmp_path, capsys):
    """7 cameras cannot be a clip of 1 + 4k frames: the line names the file (it said "video: T=7 frames" alone)."""
    cams = {"width": 64, "height": 64, "Ks": [[[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]] * 7,
            "viewmats": [np.eye(4).tolist()] * 7, "times": np.linspace(0, 1, 7).tolist()}
    (tmp_path / "c.json").write_text(json.dumps(cams))
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST[2:], "--cameras", str(tmp_path / "c.json"), "--out",
                 str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, f"--cameras {tmp_path / 'c.json'}: 7 cameras", "1 + 4·k")
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_libpng_noise_never_adds_a_line(tmp_path, capfd):
    photo = _png_with_bad_iccp(tmp_path / "cat.png")
    (tmp_path / "c.json").write_text("{not json")  # fails after the photo was decoded
    code = main(["generate", str(photo), "--steps", "1", "--quiet", "--cameras", str(tmp_path / "c.json"),
                 "--out", str(tmp_path / "o")])
    err = capfd.readouterr().err
    _one_line_exit_2(code, err, "c.json")
    assert main(["generate", str(photo), *FAST, "--out", str(tmp_path / "ok")]) == 0
    assert "libpng" not in capfd.readouterr().err


# --- ONNX: manifests checked against the graphs; corrupt graphs named ------------------------------------------


def _edit_manifest(folder: Path, edit) -> None:
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def edit(m):
        for k in keys[:-1]:
            m = m[k]
        if value is KeyError:
            del m[keys[-1]]
        else:
            m[keys[-1]] = value
    return edit


MANIFEST_EDITS = {
    "no_files": (_set("files", KeyError), "files must be a dict"),
    "no_config": (_set("config", KeyError), "config must be a dict"),
    "entry_without_file_list": (_set("files", "dit", "files", KeyError), "files.dit.files"),
    "part_without_file": (_set("files", "text_encoder", KeyError), "parts"),
    "resolution": (_set("config", "height", 128, ), "config"),
    "width": (_set("config", "width", 256), "config"),
    "channels": (_set("config", "vae", "latent_channels", 8), "config"),
    "dim_range": (_set("files", "vae_decoder", "dims", "latent_frames", [1, 2 ** 20]), "dims"),
    "input_name": (_set("files", "dit", "inputs", 0, "name", "y"), "inputs"),
    "input_rank": (_set("files", "dit", "inputs", 0, "shape", ["batch", 4, "latent_frames", "h"]), "inputs"),
    "input_dtype": (_set("files", "dit", "inputs", 1, "dtype", "int64"), "inputs"),
    "output_shape": (_set("files", "vae_encoder", "outputs", 0, "shape", ["batch", 99, "n", "h", "w"]), "outputs"),
    "parts_text_flag": (_set("parts", "dit_text_inputs", False), "dit_text_inputs"),
    "parts_deformation_flag": (_set("parts", "deformation", False), "deformation"),
}


@pytest.mark.xdist_group("onnx_export")  # the one worker that builds the shared export
@pytest.mark.slow  # uses the session's ONNX export (tests/helpers.exported)
@pytest.mark.parametrize("case", sorted(MANIFEST_EDITS))
def test_edited_manifest_is_refused(tmp_path_factory, tmp_path, case):
    edit, needle = MANIFEST_EDITS[case]
    folder = _export(tmp_path_factory, tmp_path)
    OnnxRuntime(folder)  # the copy itself is fine
    _edit_manifest(folder, edit)
    with pytest.raises(ValueError, match=f"^{folder}/(manifest.json|[a-z_]+\\.onnx): ") as info:
        OnnxRuntime(folder)
    assert needle in str(info.value)


@pytest.mark.xdist_group("onnx_export")  # the one worker that builds the shared export
@pytest.mark.slow  # uses the session's ONNX export (tests/helpers.exported)
@pytest.mark.parametrize("case", ["parent", "absolute", "subfolder", "symlink_outside"])
def test_manifest_file_entries_stay_inside_the_export(tmp_path_factory, tmp_path, case):
    folder = _export(tmp_path_factory, tmp_path)
    outside = tmp_path / "elsewhere.onnx"
    shutil.copy(folder / "dit.onnx", outside)
    (folder / "sub").mkdir()
    shutil.copy(folder / "dit.onnx", folder / "sub" / "dit.onnx")
    if case == "symlink_outside":
        (folder / "dit.onnx").unlink()
        (folder / "dit.onnx").symlink_to(outside)
        name = "dit.onnx"
    else:
        name = {"parent": "../elsewhere.onnx", "absolute": str(outside), "subfolder": "sub/dit.onnx"}[case]

    def edit(m):
        m["files"]["dit"]["file"] = name
        m["files"]["dit"]["files"] = [name]

    _edit_manifest(folder, edit)
    with pytest.raises(ValueError, match="export folder"):
        load_manifest(folder)


@pytest.mark.xdist_group("onnx_export")  # the one worker that builds the shared export
@pytest.mark.slow
@pytest.mark.parametrize("case", ["no_files", "truncated_graph", "resolution"])
def test_cli_onnx_errors_are_one_line(tmp_path_factory, tmp_path, capsys, case):
    folder = _export(tmp_path_factory, tmp_path)
    if case == "truncated_graph":
        graph = folder / "dit.onnx"
        graph.write_bytes(graph.read_bytes()[: graph.stat().st_size // 3])
        needles = [str(graph), "onnxruntime cannot load"]
    else:
        _edit_manifest(folder, MANIFEST_EDITS[case][0])
        needles = ["manifest.json" if case == "no_files" else "config.height: manifest 128, graph 64"]
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--runtime", "onnxruntime", "--onnx", str(folder),
                 "--out", str(tmp_path / "o")])
    _one_line_exit_2(code, capsys.readouterr().err, *needles)
    assert not (tmp_path / "o").exists()


# --- the other tools share the path ----------------------------------------------------------------------------


@pytest.mark.xdist_group("onnx_export")  # the one worker that builds the shared export
@pytest.mark.slow
def test_evaluate_with_corrupt_weights_is_one_line(tmp_path_factory, tmp_path, capsys):
    ckpt = _checkpoint(tmp_path_factory, tmp_path)
    weights = ckpt / "dit" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])
    code = main(["evaluate", "--checkpoint", str(ckpt), "--data", str(tmp_path)])
    _one_line_exit_2(code, capsys.readouterr().err, str(weights))


def test_data_prep_os_error_and_ctrl_c(tmp_path, capsys, monkeypatch):
    def full(args):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "scene"))

    monkeypatch.setattr(dcli, "_validate", full)
    code = dcli.main(["validate", str(tmp_path)])
    _one_line_exit_2(code, capsys.readouterr().err, f"{tmp_path / 'scene'}: No space left on device", prog="data_prep")

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(dcli, "_validate", interrupted)
    assert dcli.main(["validate", str(tmp_path)]) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "data_prep: interrupted\n"


def test_train_os_error_bug_and_ctrl_c(tmp_path, capsys, monkeypatch):
    for exc, expect in ((OSError(errno.EROFS, "Read-only file system", "/runs/r"), None),
                        (KeyboardInterrupt(), EXIT_INTERRUPTED), (TypeError("a bug"), TypeError)):
        def load_stage(*a, exc=exc, **k):
            raise exc

        monkeypatch.setattr(training.stage_config, "load_stage", load_stage)
        if expect is TypeError:
            with pytest.raises(TypeError, match="a bug"):
                train_main(["--config", "train_vae"])
        elif expect is None:
            code = train_main(["--config", "train_vae"])
            _one_line_exit_2(code, capsys.readouterr().err, "/runs/r: Read-only file system", prog="train")
        else:
            assert train_main(["--config", "train_vae"]) == expect
            assert capsys.readouterr().err == "train: interrupted\n"


# --- real processes: Ctrl-C and tracebacks ---------------------------------------------------------------------

_DRIVER = """
import sys, time
import diff4splat.pipeline as p
def stage(*a, **k):
    {body}
p.Diff4SplatPipeline.__call__ = stage
from diff4splat.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _driver(tmp_path: Path, body: str, out: Path) -> subprocess.Popen:
    script = tmp_path / "driver.py"
    script.write_text(_DRIVER.format(body=body))
    return subprocess.Popen([sys.executable, str(script), "generate", str(EXAMPLE_IMAGE), *FAST, "--out", str(out)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_ctrl_c_is_one_line_exit_130_and_writes_nothing(tmp_path):
    proc = _driver(tmp_path, 'print("STAGE", flush=True); time.sleep(120)', tmp_path / "o")
    try:
        assert proc.stdout.readline().strip() == "STAGE"  # blocked inside the pipeline
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert _err_lines(err) == ["diff4splat: interrupted"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["driver.py"]


@pytest.mark.slow
def test_a_bug_keeps_its_traceback_and_exit_1(tmp_path):
    proc = _driver(tmp_path, 'raise RuntimeError("boom from inside the pipeline")', tmp_path / "o")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1
    assert "Traceback (most recent call last)" in err and "RuntimeError: boom from inside the pipeline" in err
    assert "diff4splat: error" not in err
    assert not (tmp_path / "o").exists()


# --- issue 28: a full disk names the file (`<path>: No space left on device`), whichever writer hit it ---------

DEV_FULL = Path("/dev/full")  # every write() fails with ENOSPC, and Python's OSError then names no file
NO_SPACE = "No space left on device"


def test_naming_os_errors_names_the_file_a_write_error_left_anonymous(tmp_path):
    final, temp = tmp_path / "out", tmp_path / ".out.123.abc.tmp"
    with pytest.raises(OSError) as info, naming_os_errors(final / "scene.ply"):
        raise OSError(errno.ENOSPC, NO_SPACE)  # what f.write() raises on a full disk
    assert one_line(info.value) == f"{final / 'scene.ply'}: {NO_SPACE}" and info.value.errno == errno.ENOSPC
    with pytest.raises(OSError) as info, naming_os_errors(final, temp):  # a file in the temporary folder
        raise OSError(errno.EDQUOT, "Disk quota exceeded", str(temp / "rgb" / "0000.png"))
    assert one_line(info.value) == f"{final / 'rgb' / '0000.png'}: Disk quota exceeded"
    with pytest.raises(PermissionError) as info, naming_os_errors(final, temp):  # the rename onto out
        raise OSError(errno.EACCES, "Permission denied", str(temp), None, str(final))
    assert one_line(info.value) == f"{final}: Permission denied"
    with pytest.raises(OSError) as info, naming_os_errors(final, temp):  # another file: kept
        raise OSError(errno.EROFS, "Read-only file system", "/elsewhere")
    assert one_line(info.value) == "/elsewhere: Read-only file system"
    with pytest.raises(ValueError, match="bad input"), naming_os_errors(final):  # not a write error
        raise ValueError("bad input")
    with pytest.raises(RuntimeError, match="a bug"), naming_os_errors(tmp_path):  # this disk has room: unchanged
        raise RuntimeError("a bug")


def test_a_library_error_on_a_full_disk_becomes_enospc_naming_the_file(tmp_path, monkeypatch):
    """OpenEXR and safetensors raise RuntimeError-like errors; the file system tells whether the disk was full."""
    monkeypatch.setattr(atomic, "disk_full_error", lambda where: OSError(errno.ENOSPC, NO_SPACE))
    with pytest.raises(OSError) as info, atomic.naming_os_errors(tmp_path / "field.safetensors"):
        raise RuntimeError("Error while serializing: I/O error: No space left on device (os error 28)")
    assert one_line(info.value) == f"{tmp_path / 'field.safetensors'}: {NO_SPACE}"
    assert isinstance(info.value.__cause__, RuntimeError)


def _fill_with_dev_full(monkeypatch, module):
    """``module``'s atomic_output_path, with the temporary file a link to /dev/full: real ENOSPC on every write."""
    @contextmanager
    def full(path):
        with atomic_output_path(path) as tmp:
            os.symlink(DEV_FULL, tmp)
            yield tmp

    monkeypatch.setattr(module, "atomic_output_path", full)


def _writers():
    rng = np.random.default_rng(0)
    img = (rng.random((32, 32, 3)) * 255).astype(np.uint8)
    n = 50
    g = Gaussians(torch.randn(n, 3), torch.nn.functional.normalize(torch.randn(n, 4), dim=-1),
                  torch.rand(n, 3) * 0.1 + 0.01, torch.rand(n) * 0.9 + 0.05, torch.rand(n, 1, 3))
    path = make_trajectory("arc", 3, [[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]], 32, 32)
    return {  # name: (module whose atomic_output_path it uses, file name, write(path), C library that hides errno)
        "ply": (ply, "scene.ply", lambda p: ply.save_ply(p, g), False),
        "png": (video, "0000.png", lambda p: video.save_image(p, img), False),
        "cameras": (cameras, "cameras.json", lambda p: cameras.save_cameras_json(p, path), False),
        "mp4": (video, "video.mp4", lambda p: video.save_video(p, np.stack([img] * 4)), True),
        "exr": (exr, "0000.exr", lambda p: exr.save_depth_exr(p, rng.random((32, 32)) + 1), True),
    }


@pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")
@pytest.mark.parametrize("writer", ["ply", "png", "cameras", "mp4", "exr"])
def test_every_writer_on_a_full_disk_names_its_file_and_leaves_nothing(tmp_path, monkeypatch, writer):
    module, name, write, c_library = _writers()[writer]
    _fill_with_dev_full(monkeypatch, module)
    if c_library:  # OpenCV / OpenEXR say nothing of errno: the probe of the disk (here: not full) must answer
        monkeypatch.setattr(atomic, "disk_full_error", lambda where: OSError(errno.ENOSPC, NO_SPACE))
    target = tmp_path / name
    with pytest.raises(OSError) as info:
        write(target)
    assert is_expected(info.value) and one_line(info.value) == f"{target}: {NO_SPACE}"
    assert list(tmp_path.iterdir()) == []  # no temporary file, no half-written target


@pytest.mark.slow
@pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")
def test_disk_full_during_generate_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    """scene.ply's write() hits ENOSPC, which names no file: the line names out/scene.ply, not a temporary."""
    _fill_with_dev_full(monkeypatch, ply)
    out = tmp_path / "o"
    code = main(["generate", str(EXAMPLE_IMAGE), *FAST, "--out", str(out)])
    line = _one_line_exit_2(code, capsys.readouterr().err)
    assert line == f"diff4splat: error: {out / 'scene.ply'}: {NO_SPACE}"
    assert list(tmp_path.iterdir()) == []


_FULL_DISK_SCRIPT = r"""
import os, sys
import numpy as np
from diff4splat.utils.errors import is_expected, one_line
from diff4splat.io.exr import save_depth_exr
from diff4splat.io.output_folders import output_dir
from diff4splat.io.video import save_image, save_video

root, slack = sys.argv[1], int(sys.argv[2])
fd = os.open(os.path.join(root, "filler"), os.O_WRONLY | os.O_CREAT)
try:
    while True:
        os.write(fd, bytes(65536))
except OSError:
    pass
os.ftruncate(fd, max(os.fstat(fd).st_size - slack, 0))  # leave `slack` bytes: the writers fill them, then fail
os.close(fd)
rng = np.random.default_rng(0)
img = (rng.random((256, 256, 3)) * 255).astype(np.uint8)

def meta(tmp):
    (tmp / "meta.json").write_text("x" * 300000)

def in_folder(tmp):
    save_image(tmp / "rgb" / "0000.png", img)

def folder(body):
    def write(out):
        with output_dir(out, kind="generate") as tmp:
            body(tmp)
    return write

writers = {"a.png": lambda p: save_image(p, img), "a.mp4": lambda p: save_video(p, np.stack([img] * 8)),
           "a.exr": lambda p: save_depth_exr(p, rng.random((256, 256)) + 1), "out1": folder(meta),
           "out2": folder(in_folder)}
for name, write in writers.items():
    try:
        write(os.path.join(root, name))
        print("written", name)
    except Exception as e:
        print(("expected " if is_expected(e) else "BUG ") + one_line(e))
    print("left", sorted(p for p in os.listdir(root) if p != "filler"))
"""


@pytest.mark.slow
@pytest.mark.parametrize("slack", [0, 20000])
def test_a_really_full_file_system_is_named_by_every_writer(tmp_path, slack):
    """A 512 KiB tmpfs filled up, in a user and mount namespace (skipped where unprivileged namespaces are off)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    script = tmp_path / "fill.py"
    script.write_text(_FULL_DISK_SCRIPT)
    shell = f"mount -t tmpfs -o size=512k none {mnt} && exec {sys.executable} {script} {mnt} {slack}"
    try:
        run = subprocess.run(["unshare", "-r", "-m", "sh", "-c", shell], capture_output=True, text=True, timeout=120,
                             cwd=REPO)
    except FileNotFoundError:
        pytest.skip("no unshare")
    if run.returncode != 0 and "mount" in run.stderr + run.stdout and "expected" not in run.stdout:
        pytest.skip(f"cannot mount a tmpfs in a user namespace here: {run.stderr.strip()[:200]}")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    expect = [f"expected {mnt / 'a.png'}: {NO_SPACE}", f"expected {mnt / 'a.mp4'}: {NO_SPACE}",
              f"expected {mnt / 'a.exr'}: {NO_SPACE}", f"expected {mnt / 'out1'}: {NO_SPACE}",
              f"expected {mnt / 'out2' / 'rgb' / '0000.png'}: {NO_SPACE}"]
    assert lines[0::2] == expect, run.stdout
    assert lines[1::2] == ["left []"] * len(expect), run.stdout  # nothing half-written or temporary left behind


def test_only_warnings_that_concern_the_user_are_printed_once_each(capsys):
    """``generate --compile --quiet`` printed torch's "`torch.jit.script_method` is deprecated" 14 times as
    ``diff4splat: warning:`` (issue 61): a dependency's deprecation is dropped, our own warning is printed once
    however often it is raised, and a dependency's other warnings keep their own label."""
    ours = str(Path(errors.__file__).resolve().parent / "pipeline.py")
    theirs = str(Path(torch.__file__).resolve().parent / "jit" / "_script.py")

    def run():
        for _ in range(14):
            warnings.warn_explicit("`torch.jit.script_method` is deprecated.", DeprecationWarning, theirs, 1)
            warnings.warn_explicit("`x` is deprecated.", FutureWarning, theirs, 2)
            warnings.warn_explicit("the model is random", UserWarning, ours, 3)
        warnings.warn_explicit("TF32 is off", UserWarning, theirs, 4)
        return 7

    with errors.printed_warnings():
        result = run()
    assert result == 7
    assert capsys.readouterr().err.splitlines() == ["diff4splat: warning: the model is random",
                                                    "_script: UserWarning: TF32 is off"]
    # a block that fails still prints what was raised before the failure (the error's own line comes after)
    with pytest.raises(ValueError, match="late"), errors.printed_warnings():
        warnings.warn_explicit("the model is random", UserWarning, ours, 3)
        raise ValueError("late")
    assert capsys.readouterr().err.splitlines() == ["diff4splat: warning: the model is random"]
