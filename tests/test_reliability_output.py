"""Issue 11, output folders (defects 1, 4, 5, 6): `--out` never destroys a user's files, is checked before
any compute, leaves no temporaries after signals or races, and follows the umask (diff4splat/io/output_folders.py)."""
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import torch
from helpers import EXAMPLE_IMAGE, tiny_model
from safetensors.torch import save_file

import diff4splat
from data_prep.format import SceneWriter
from diff4splat.cli import main
from diff4splat.io import MARKER, OutputDirError, check_output_dir, output_dir
from diff4splat.io.atomic import atomic_output_path, current_umask
from diff4splat.io.output_folders import remove_stale_temps
from training.checkpoint import save_checkpoint


def _snapshot(root: Path) -> dict:
    """Every entry under ``root`` (and ``root``'s parent listing): relative path → sha256 or "dir"/"link"."""
    out = {"..": sorted(p.name for p in root.parent.iterdir())}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            out[rel] = ("link" if p.is_symlink() else "dir" if p.is_dir()
                        else hashlib.sha256(p.read_bytes()).hexdigest())
    return out


@pytest.fixture
def no_model(monkeypatch):
    """Loading a model or an ONNX runtime fails the test: refusals must come before any compute."""
    def boom(*args, **kwargs):
        raise AssertionError("the model was loaded before --out was checked")

    monkeypatch.setattr("diff4splat.pipeline.load_model", boom)
    monkeypatch.setattr("diff4splat.onnx_runtime.OnnxRuntime", boom)


def _refused(capsys, argv, folder_text: str) -> str:
    code = main(argv)
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("diff4splat: warning")]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("diff4splat: error:") and folder_text in lines[0], err
    return lines[0]


def _user_folder(tmp_path: Path) -> Path:
    p = tmp_path / "p"
    p.mkdir()
    shutil.copy(EXAMPLE_IMAGE, p / "cat.png")
    (p / "notes.txt").write_text("x\n")
    return p


@pytest.mark.parametrize("overwrite", [False, True])
def test_generate_into_the_folder_of_its_photo_exits_2_and_leaves_it_byte_identical(tmp_path, capsys, no_model,
                                                                                    overwrite):
    p = _user_folder(tmp_path)
    before = _snapshot(p)
    line = _refused(capsys, ["generate", str(p / "cat.png"), "--out", str(p)] + ["--overwrite"] * overwrite, str(p))
    assert f"output folder {p} holds input {p / 'cat.png'}; refusing to replace it" in line
    assert _snapshot(p) == before


def test_generate_into_the_parent_of_its_checkpoint_is_refused_even_with_overwrite(tmp_path, capsys, no_model):
    p = tmp_path / "models"
    (p / "ck").mkdir(parents=True)
    (p / "ck" / "config.json").write_text("{}")
    before = _snapshot(p)
    for extra in ([], ["--overwrite"]):
        _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--checkpoint", str(p / "ck"), "--out", str(p), *extra],
                 str(p))
    assert _snapshot(p) == before


def test_generate_into_a_user_folder_is_refused_without_overwrite(tmp_path, capsys, no_model):
    p = tmp_path / "docs"
    p.mkdir()
    (p / "thesis.tex").write_text("years of work")
    before = _snapshot(p)
    line = _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(p)], str(p))
    assert "--overwrite" in line
    assert _snapshot(p) == before


@pytest.mark.parametrize(("out", "needle"), [(".", "current directory"), ("", "empty folder name ''"),
                                             ("  ", "argument --out: empty folder name")])
def test_generate_out_dot_or_empty_is_refused(tmp_path, capsys, no_model, monkeypatch, out, needle):
    p = _user_folder(tmp_path)
    monkeypatch.chdir(p)
    before = _snapshot(p)
    _refused(capsys, ["generate", "cat.png", "--out", out, "--overwrite"], needle)
    assert _snapshot(p) == before


def test_generate_into_home_or_an_ancestor_of_it_is_refused(tmp_path, capsys, no_model, monkeypatch):
    home = tmp_path / "home"
    home.mkdir()
    (home / ".bashrc").write_text("alias ll='ls -l'\n")
    monkeypatch.setenv("HOME", str(home))
    before = _snapshot(tmp_path)
    _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(home), "--overwrite"], "home directory")
    _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(tmp_path), "--overwrite"], "home directory")
    assert _snapshot(tmp_path) == before


def test_diff4splats_own_packages_are_never_replaced(capsys, no_model):
    """`--out <checkout>/models --overwrite` once deleted the models package and the shipped weights it holds (the
    default checkpoint, which no --checkpoint names): each installed package, any folder inside one (the weights)
    and any folder holding one (the checkout, site-packages, a virtual environment) is refused, even with
    --overwrite, before anything is written."""
    installed = Path(diff4splat.__file__).resolve().parent.parent
    names = [n for n in ("diff4splat", "models", "training", "data_prep") if (installed / n).is_dir()]
    assert "models" in names and (installed / "models" / "weights").is_dir()
    for folder in [installed / n for n in names] + [installed / "models" / "weights", installed]:
        with pytest.raises(OutputDirError, match="diff4splat's installed package"):
            check_output_dir(folder, overwrite=True)
    _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(installed / "models"), "--overwrite"],
             "diff4splat's installed package")
    assert (installed / "models" / "__init__.py").is_file()


def test_generate_into_a_filesystem_root_is_refused(capsys, no_model):
    _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", "/", "--overwrite"], "filesystem root")


def test_export_onnx_into_a_folder_with_other_files_is_refused(tmp_path, capsys, no_model):
    p = tmp_path / "serve"
    p.mkdir()
    (p / "app.py").write_text("print('hi')\n")
    before = _snapshot(p)
    _refused(capsys, ["export-onnx", "--out", str(p)], str(p))
    assert _snapshot(p) == before


def test_an_output_of_another_kind_is_replaced_only_with_overwrite(tmp_path):
    out = tmp_path / "out"
    with output_dir(out, kind="generate") as tmp:
        (tmp / "video.mp4").write_bytes(b"v")
    with pytest.raises(OutputDirError, match="'generate' output, not 'onnx'"):
        check_output_dir(out, kind="onnx")
    with output_dir(out, kind="onnx", overwrite=True) as tmp:
        (tmp / "manifest.json").write_text("{}")
    assert json.loads((out / MARKER).read_text())["kind"] == "onnx"
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "manifest.json"]


def test_an_earlier_output_holding_a_users_files_is_replaced_only_with_overwrite(tmp_path):
    """Re-exporting into an earlier export deleted the NOTES.md and results/ a user had added beside it."""
    out = tmp_path / "out"
    with output_dir(out, kind="onnx") as tmp:
        (tmp / "graphs").mkdir()
        (tmp / "graphs" / "dit.onnx").write_bytes(b"g")
        (tmp / "empty").mkdir()
    assert json.loads((out / MARKER).read_text())["files"] == ["empty/", "graphs/dit.onnx"]
    for added in ("NOTES.md", "graphs/mine.csv", "results/"):
        path = out / added
        path.mkdir() if added.endswith("/") else path.write_text("mine")
        with pytest.raises(OutputDirError, match=f"earlier diff4splat 'onnx' output that also holds {added}, which "
                                                 "diff4splat did not write; refusing to replace it"):
            check_output_dir(out, kind="onnx")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    (out / "graphs" / "dit.onnx").unlink()  # a user removing what we wrote leaves nothing of theirs
    with output_dir(out, kind="onnx") as tmp:
        (tmp / "manifest.json").write_text("{}")
    (out / "NOTES.md").write_text("mine")
    with output_dir(out, kind="onnx", overwrite=True) as tmp:
        (tmp / "manifest.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "manifest.json"]
    (out / MARKER).write_text(json.dumps({"tool": "diff4splat", "kind": "onnx", "format": 1}))  # no list: by kind
    (out / "NOTES.md").write_text("mine")
    check_output_dir(out, kind="onnx")


def test_overwrite_replaces_a_user_folder_that_holds_no_inputs(tmp_path):
    out = tmp_path / "old_results"
    out.mkdir()
    (out / "stale.txt").write_text("x")
    with pytest.raises(OutputDirError, match="not written by diff4splat"):
        check_output_dir(out, kind="generate")
    with output_dir(out, kind="generate", overwrite=True, inputs=[EXAMPLE_IMAGE]) as tmp:
        (tmp / "scene.ply").write_bytes(b"ply")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "scene.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old_results"]


@pytest.mark.slow
def test_rerun_generate_into_its_own_output_works_and_export_onnx_does_not_replace_it(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["generate", str(EXAMPLE_IMAGE), "--frames", "5", "--steps", "1", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    assert json.loads((out / MARKER).read_text())["kind"] == "generate"
    (out / "video.mp4").write_bytes(b"edited")  # the second run must really replace the folder
    assert main(argv) == 0
    assert (out / "video.mp4").read_bytes() != b"edited"
    capsys.readouterr()
    before = _snapshot(out)
    _refused(capsys, ["export-onnx", "--out", str(out)], str(out))
    assert _snapshot(out) == before


@pytest.mark.parametrize("case", ["parent_missing", "parent_is_file", "name_too_long"])
def test_bad_out_is_refused_before_any_model_loads(tmp_path, capsys, no_model, case):
    if case == "parent_missing":
        out, text = tmp_path / "missing" / "out", "does not exist"
    elif case == "parent_is_file":
        (tmp_path / "f.txt").write_text("x")
        out, text = tmp_path / "f.txt" / "out", "not a folder"
    else:
        out, text = tmp_path / ("n" * 256), "longer than"
    before = _snapshot(tmp_path)
    _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(out)], text)
    _refused(capsys, ["export-onnx", "--out", str(out)], text)
    assert _snapshot(tmp_path) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores folder permissions")
def test_unwritable_parent_is_refused_before_any_model_loads(tmp_path, capsys, no_model):
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o500)
    try:
        _refused(capsys, ["generate", str(EXAMPLE_IMAGE), "--out", str(parent / "out")], "not writable")
    finally:
        parent.chmod(0o700)


def test_a_250_character_name_works(tmp_path):
    out = tmp_path / ("n" * 250)
    with output_dir(out, kind="t") as tmp:
        (tmp / "a.txt").write_text("1")
    assert (out / "a.txt").read_text() == "1"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


_CHILD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from diff4splat.io import output_dir
    out, ready = Path(sys.argv[1]), Path(sys.argv[2])
    with output_dir(out, kind="t") as tmp:
        (tmp / "big.bin").write_bytes(b"x" * 100_000)
        ready.write_text(str(tmp))
        time.sleep(60)
""")


def _start_blocked_writer(tmp_path: Path):
    out, ready = tmp_path / "out", tmp_path / "ready"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(out), str(ready)], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not ready.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else "timeout"
        time.sleep(0.05)
    tmp = Path(ready.read_text())
    ready.unlink()
    assert tmp.is_dir() and str(proc.pid) in tmp.name
    return proc, out, tmp


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_and_sigint_while_writing_remove_the_temporary_folder(tmp_path, sig):
    proc, out, tmp = _start_blocked_writer(tmp_path)
    proc.send_signal(sig)
    proc.communicate(timeout=60)
    assert proc.returncode != 0
    if sig == signal.SIGTERM:
        assert proc.returncode == 143
    assert not tmp.exists() and not out.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_sigkill_leaves_a_temporary_folder_that_the_next_run_removes_but_never_a_live_ones(tmp_path):
    proc, out, tmp = _start_blocked_writer(tmp_path)
    proc.kill()
    proc.communicate(timeout=60)
    assert tmp.is_dir()  # SIGKILL cannot be caught: the owner pid in the name marks it
    live = tmp_path / f".out.{os.getpid()}.0123abcd.tmp"  # a live process's (ours) must survive
    live.mkdir()
    with output_dir(out, kind="t") as new:
        (new / "a.txt").write_text("1")
    assert not tmp.exists() and live.is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name, "out"]
    assert remove_stale_temps(out) == []


def test_symlinked_out_replaces_the_target_folder_and_leaves_no_stale_link(tmp_path):
    target = tmp_path / "real" / "out"
    target.parent.mkdir()
    with output_dir(target, kind="t") as tmp:
        (tmp / "a.txt").write_text("old")
    link = tmp_path / "link"
    link.symlink_to(target, target_is_directory=True)
    with output_dir(link, kind="t") as tmp:
        (tmp / "b.txt").write_text("new")
    assert link.is_symlink() and link.resolve() == target.resolve()
    assert sorted(p.name for p in target.iterdir()) == [MARKER, "b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]
    assert sorted(p.name for p in target.parent.iterdir()) == ["out"]


def test_concurrent_writers_of_one_out_are_serialised(tmp_path):
    out = tmp_path / "out"
    n, rounds = 8, 5
    errors = []
    for r in range(rounds):
        barrier = threading.Barrier(n)

        def write(i, barrier=barrier, r=r):
            try:
                barrier.wait()
                with output_dir(out, kind="t") as tmp:
                    for k in range(3):
                        (tmp / f"{k}.txt").write_text(f"{r}-{i}")
            except BaseException as e:  # collected: the test reports every failure
                errors.append(e)

        threads = [threading.Thread(target=write, args=(i,)) for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert errors == []
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no .old, .tmp or lock left
        contents = {(out / f"{k}.txt").read_text() for k in range(3)}
        assert len(contents) == 1 and contents.pop().startswith(f"{r}-")  # one writer's complete output


@pytest.mark.parametrize("umask, dir_mode, file_mode", [(0o022, 0o755, 0o644), (0o002, 0o775, 0o664)])
def test_output_folders_and_files_follow_the_umask(tmp_path, umask, dir_mode, file_mode):
    """Folders, files and what libraries write with their own modes: safetensors (and so diffusers) creates 0600
    files, which a saved model, checkpoint or field kept (unreadable to the group under umask 002)."""
    old = os.umask(umask)
    try:
        assert current_umask() == umask
        with output_dir(tmp_path / "out", kind="t") as tmp:
            (tmp / "a.txt").write_text("1")
            (tmp / "sub").mkdir()
            save_file({"w": torch.zeros(2)}, str(tmp / "sub" / "m.safetensors"))
        with atomic_output_path(tmp_path / "f.safetensors") as tmp:
            save_file({"w": torch.zeros(2)}, tmp)
    finally:
        os.umask(old)
    out = tmp_path / "out"
    assert (out.stat().st_mode & 0o777, (out / "sub").stat().st_mode & 0o777) == (dir_mode, dir_mode)
    assert ((out / "a.txt").stat().st_mode & 0o777, (out / MARKER).stat().st_mode & 0o777) == (file_mode, file_mode)
    assert (out / "sub" / "m.safetensors").stat().st_mode & 0o777 == file_mode
    assert (tmp_path / "f.safetensors").stat().st_mode & 0o777 == file_mode


def test_every_folder_writer_uses_the_policy(tmp_path):
    """save_pretrained, training checkpoints and data_prep scenes mark their folders and refuse user folders."""
    user = tmp_path / "user"
    user.mkdir()
    (user / "keep.txt").write_text("mine")
    step = tmp_path / "run" / "checkpoints" / "step_00000001"
    step.mkdir(parents=True)
    (step / "keep.txt").write_text("mine")
    before = _snapshot(user)
    model = tiny_model()
    with pytest.raises(OutputDirError, match="not written by diff4splat"):
        model.save_pretrained(user)
    with pytest.raises(OutputDirError, match="not written by diff4splat"):
        with SceneWriter(user, source="synthetic", dynamic=False, depth_source="none", num_frames=1, fps=8.0,
                         replace=True):
            pass
    state = {"w": torch.zeros(2)}
    with pytest.raises(OutputDirError, match="not written by diff4splat"):
        save_checkpoint(tmp_path / "run", 1, state, {}, {})
    assert _snapshot(user) == before and (step / "keep.txt").read_text() == "mine"
    model.save_pretrained(tmp_path / "model")
    model.save_pretrained(tmp_path / "model")  # its own earlier output is replaced
    assert json.loads((tmp_path / "model" / MARKER).read_text())["kind"] == "model"
    assert not (tmp_path / "model" / "vae" / MARKER).exists()  # one marker per output folder
    folder = save_checkpoint(tmp_path / "run2", 1, state, {}, {})
    assert save_checkpoint(tmp_path / "run2", 1, state, {}, {}) == folder  # a resumed run rewrites its step
    assert json.loads((folder / MARKER).read_text())["kind"] == "checkpoint"
