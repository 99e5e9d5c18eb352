"""The engine switch of ``data_prep`` (:mod:`data_prep.engine`) without starting Ray: the checks and one-line errors
of ``--engine``/``--workers``/``--ray-address``, the ray extra imported only when asked for, ``convert --each`` on
the local engine (resume, names, errors) and the fault hook's parsing. Ray itself: tests/test_data_prep_ray*.py."""
from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
from _data_prep_fixtures import dnerf_clip

import data_prep.engine as engine_mod
import data_prep.synth_dataset as sd
from data_prep.cli import main
from data_prep.converters import convert_each, list_sources
from data_prep.engine import FAULT_ENV, Engine, check_engine, fault_point, map_scenes

REPO = Path(__file__).resolve().parents[1]


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("data_prep: error: "), err
    return err


@pytest.mark.parametrize("args, message", [
    (("bogus", 1, None), "--engine must be one of local, ray, got 'bogus'"),
    (("local", 0, None), "--workers"),
    (("local", 1, "auto"), "--ray-address is for the ray engine; add --engine ray"),
    (("ray", 1, "  "), "--ray-address is empty"),
])
def test_check_engine_refuses_bad_requests(args, message, monkeypatch):
    monkeypatch.setattr(engine_mod, "import_ray", lambda: None)  # ray installed or not: the same checks first
    with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
        check_engine(*args)


def test_engine_ray_without_the_extra_is_one_line_naming_it_and_nothing_is_made(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray → ImportError, as on a machine without the extra
    rc = main(["synth", "--scenes", "2", "--out", str(tmp_path / "d"), "--size", "16", "--frames", "2",
               "--engine", "ray", "--quiet"])
    assert rc == 2 and "pip install 'diff4splat[ray]'" in _one_line_error(capsys)
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_the_default_engine_imports_no_ray(tmp_path):
    """``data_prep synth`` and ``curate`` on the local engine, in a fresh interpreter: ray is never imported."""
    code = (f"import sys; from data_prep.cli import main; "
            f"assert main(['synth', '--scenes', '2', '--out', {str(tmp_path / 'd')!r}, '--size', '16', "
            f"'--frames', '5', '--quiet']) == 0; "
            f"assert main(['curate', {str(tmp_path / 'd')!r}, {str(tmp_path / 'c')!r}, '--workers', '1', "
            f"'--quiet']) == 0; "
            f"assert 'ray' not in sys.modules, 'ray was imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=120)


def test_map_scenes_runs_each_item_once_and_raises_the_first_failure():
    seen = []
    map_scenes(seen.append, iter([3, 1, 2]), Engine(), progress=False)
    assert seen == [3, 1, 2]

    def fail_on_two(x):
        if x == 2:
            raise FileNotFoundError("item 2")
        seen.append(x)

    seen.clear()
    with pytest.raises(FileNotFoundError, match="item 2"):
        map_scenes(fail_on_two, [1, 2, 3], Engine(), progress=False)
    assert seen == [1]


def test_fault_point_fires_only_for_its_stage_and_scene(tmp_path, monkeypatch):
    killed = []
    monkeypatch.setattr(engine_mod.os, "kill", lambda pid, sig: killed.append(sig))
    flag = tmp_path / "flag"
    fault_point("write", "scene_00001")  # unset: nothing
    monkeypatch.setenv(FAULT_ENV, f"write:scene_00001:{flag}")
    fault_point("done", "scene_00001")
    fault_point("write", "scene_00002")
    assert not killed and not flag.exists()
    fault_point("write", "scene_00001")
    fault_point("write", "scene_00001")  # once: the flag file exists now
    assert killed == [engine_mod.signal.SIGKILL] and flag.exists()
    monkeypatch.setenv(FAULT_ENV, f"write:scene_00001:{flag},done:scene_00003:{tmp_path / 'flag2'}")  # several
    fault_point("done", "scene_00003")
    assert len(killed) == 2 and (tmp_path / "flag2").exists()


# ------------------------------------------------------------------------------------------------ convert --each
def _dnerf_clips(root: Path) -> None:
    dnerf_clip(root / "lego", times=(0.0, 0.5, 1.0))
    dnerf_clip(root / "mutant", times=(1.0, 0.0))


def test_convert_each_makes_one_scene_per_clip_and_a_rerun_resumes(tmp_path, capsys):
    _dnerf_clips(tmp_path / "src")
    out = tmp_path / "data"
    assert main(["convert", "dnerf", str(tmp_path / "src"), str(out), "--each", "--quiet"]) == 0
    assert "converted 2 dnerf clip(s)" in capsys.readouterr().out
    metas = {p.parent.name: json.loads(p.read_text())["num_frames"] for p in out.glob("*/meta.json")}
    assert metas == {"lego": 3, "mutant": 2}
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    dnerf_clip(tmp_path / "src" / "trex", times=(0.0, 1.0))
    names = tmp_path / "names.txt"
    names.write_text("# the clips\nlego\n\ntrex\n")
    assert main(["convert", "dnerf", str(tmp_path / "src"), str(out), "--each", str(names), "--quiet"]) == 0
    assert all(p.stat().st_mtime_ns == t for p, t in before.items())  # lego left as it was
    assert sorted(p.parent.name for p in out.glob("*/meta.json")) == ["lego", "mutant", "trex"]


@pytest.mark.parametrize("extra, message", [
    (["--each", "--replace"], "--replace does not go with --each"),
    (["--engine", "ray"], "--engine, --workers and --ray-address convert many clips: add --each"),
    (["--workers", "2"], "add --each"),
    (["--each", "missing.txt"], "--each: file of clip names not found"),
])
def test_convert_each_flag_errors_are_one_line(extra, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _dnerf_clips(tmp_path / "src")
    assert main(["convert", "dnerf", str(tmp_path / "src"), str(tmp_path / "out"), *extra]) == 2
    assert message in _one_line_error(capsys)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("names, message", [
    (["lego", "lego"], "clip names repeat"),
    (["../lego"], "is not a plain folder name"),
    ([".hidden"], "is not a plain folder name"),
])
def test_convert_each_refuses_bad_names_before_any_work(names, message, tmp_path):
    _dnerf_clips(tmp_path / "src")
    with pytest.raises(ValueError, match=message):
        convert_each("dnerf", tmp_path / "src", tmp_path / "out", names, progress=False)
    assert not (tmp_path / "out").exists()


def test_convert_each_refuses_an_output_inside_the_source_and_a_missing_clip(tmp_path):
    _dnerf_clips(tmp_path / "src")
    with pytest.raises(ValueError, match="is inside the source"):
        convert_each("dnerf", tmp_path / "src", tmp_path / "src" / "out", progress=False)
    with pytest.raises(FileNotFoundError):
        convert_each("dnerf", tmp_path / "src", tmp_path / "out", ["lego", "nope"], progress=False)
    assert not (tmp_path / "out").exists()


def test_list_sources_reads_clip_files_for_selecting_sources(tmp_path):
    for stem in ("b", "a"):
        (tmp_path / f"{stem}.txt").write_text("")
    (tmp_path / "a").mkdir()
    assert list_sources("realestate10k", tmp_path) == ["a", "b"]
    assert list_sources("dnerf", tmp_path) == ["a"]
    with pytest.raises(ValueError, match="name the sequences"):
        list_sources("dynamic_replica", tmp_path)
    with pytest.raises(ValueError, match="no stereo4d clips"):
        list_sources("stereo4d", tmp_path)


def test_synth_on_ray_with_a_cuda_device_asks_one_gpu_per_task(tmp_path, monkeypatch):
    """``synth --device cuda --engine ray``: each Ray task asks for a GPU (the local engine's processes share
    the device as before)."""
    seen = []
    monkeypatch.setattr(sd, "resolve_device", lambda device, flag: "cuda:0" if device == "cuda" else "cpu")
    monkeypatch.setattr(sd, "map_scenes", lambda fn, items, engine, **kw: seen.append(engine))
    monkeypatch.setattr(sd, "engine_session", lambda engine: contextlib.nullcontext())  # no Ray started
    for device, engine in (("cuda", Engine("ray")), ("cpu", Engine("ray")), ("cuda", None)):
        sd.synthesize(tmp_path / "d", 2, size=16, frames=2, device=device, engine=engine, progress=False)
    assert [e.gpus_per_task for e in seen] == [1.0, 0.0, 0.0]
