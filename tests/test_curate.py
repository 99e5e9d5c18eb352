"""data_prep.curate: statistics, each filter, manifest, resumability (injected failure and a real kill), workers."""
from __future__ import annotations

import errno
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

import data_prep.curate as cm
from data_prep.cli import main as cli_main
from data_prep.curate import (
    DEFAULT_CONFIG_PATH,
    CurationConfig,
    curate,
    judge,
    laplacian_variance,
    read_manifest,
    scene_statistics,
)
from data_prep.format import SceneReader, SceneWriter, list_scenes
from data_prep.validate import validate_scene
from diff4splat.cameras import CameraPath, intrinsics_from_fov

H, W = 24, 32
CONFIG = CurationConfig(min_frames=9, min_translation_m=0.05, max_rotation_deg=30.0, min_valid_depth_ratio=0.3,
                        dynamic_motion_threshold_m=0.05, min_dynamic_ratio=0.2, min_sharpness=20.0, sample_frames=3)


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def make_scene(root: Path, name: str, *, T: int = 9, move: float = 0.3, turn_deg: float = 0.0, blur: bool = False,
               invalid_rows: int = 0, dynamic: bool = False, tracks: str | None = None, depth: bool = True,
               cams: int = 1, seed: int = 0) -> Path:
    """A scene whose camera(s) translate by ``move`` m along x and turn by ``turn_deg`` about y over T frames.

    tracks: None (no file), "static" (4 still points) or "half" (2 of 4 points move 0.5 m, all visible).
    """
    rng = np.random.default_rng(seed)
    K = intrinsics_from_fov(W, H, fov_x_deg=60.0, dtype=torch.float64)
    path = root / name
    with SceneWriter(path, source="test", dynamic=dynamic, depth_source="ground_truth" if depth else "none",
                     num_frames=T, fps=10.0) as w:
        for c in range(cams):
            vms = []
            for i in range(T):
                s = i / max(T - 1, 1)
                R = _rot_y(turn_deg * s)
                centre = np.array([move * s + 0.1 * c, 0.0, 0.0])
                V = np.eye(4)
                V[:3, :3], V[:3, 3] = R, -R @ centre
                vms.append(V)
            w.add_camera(f"cam{c:02d}", CameraPath(torch.tensor(np.stack(vms)), K.expand(T, 3, 3).clone(), W, H))
            for i in range(T):
                img = rng.random((H, W, 3)).astype(np.float32)
                if blur:
                    img = cv2.GaussianBlur(img, (0, 0), 4.0)
                d = np.full((H, W), 2.0, np.float32)
                d[:invalid_rows] = np.inf
                w.write_frame(f"cam{c:02d}", i, img, d if depth else None)
        if tracks is not None:
            pts = np.tile(rng.normal(size=(4, 1, 3)).astype(np.float32), (1, T, 1))
            if tracks == "half":
                pts[:2, :, 0] += np.linspace(0, 0.5, T, dtype=np.float32)
            w.write_tracks(pts, np.ones((4, T), bool))
    return path


EXPECTED = {  # scene name → reasons under CONFIG (each bad scene violates exactly one filter)
    "good_static": [],
    "good_dynamic": [],
    "good_multiview": [],
    "few_frames": ["min_frames"],
    "tiny_motion": ["min_translation_m"],
    "big_turn": ["max_rotation_deg"],
    "blurred": ["min_sharpness"],
    "bad_depth": ["min_valid_depth_ratio"],
    "static_tracks": ["min_dynamic_ratio"],
    "no_tracks": ["dynamic_requires_tracks"],
    "zz_broken": ["error"],
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("curate_in")
    make_scene(root, "good_static", turn_deg=10.0)
    make_scene(root, "good_dynamic", dynamic=True, tracks="half")
    make_scene(root, "good_multiview", move=0.0, cams=2)  # still cameras, 0.1 m baseline
    make_scene(root, "few_frames", T=5)
    make_scene(root, "tiny_motion", move=0.01)
    make_scene(root, "big_turn", turn_deg=45.0)
    make_scene(root, "blurred", blur=True)
    make_scene(root, "bad_depth", invalid_rows=20)  # 20/24 rows invalid → ratio 1/6
    make_scene(root, "static_tracks", dynamic=True, tracks="static")
    make_scene(root, "no_tracks", dynamic=True)
    (root / "zz_broken").mkdir()
    (root / "zz_broken" / "meta.json").write_text("{not json")
    return root


def _manifest_text(out: Path) -> str:
    return (out / "manifest.jsonl").read_text()


def test_laplacian_variance_matches_opencv_reference():
    img = np.random.default_rng(1).random((20, 30, 3)).astype(np.float32)
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64) * 255.0
    kernel = np.ones((3, 3))
    kernel[1, 1] = -8.0
    ref = cv2.filter2D(grey, -1, kernel, borderType=cv2.BORDER_REFLECT_101)
    assert laplacian_variance(img) == pytest.approx(ref.var(), rel=1e-4)
    assert laplacian_variance(np.full((8, 8, 3), 0.4, np.float32)) == pytest.approx(0.0, abs=1e-6)
    assert laplacian_variance(cv2.GaussianBlur(img, (0, 0), 2.0)) < 0.05 * laplacian_variance(img)


def test_statistics_closed_forms(dataset):
    s = scene_statistics(SceneReader(dataset / "good_static"), CONFIG)
    assert (s.num_frames, s.num_cameras, s.dynamic) == (9, 1, False)
    assert s.translation_range_m == pytest.approx(0.3, abs=1e-6)
    assert s.rotation_range_deg == pytest.approx(10.0, abs=1e-3)
    assert s.valid_depth_ratio == 1.0 and s.dynamic_ratio is None
    s = scene_statistics(SceneReader(dataset / "good_multiview"), CONFIG)
    assert s.translation_range_m == pytest.approx(0.1, abs=1e-6) and s.num_cameras == 2
    assert scene_statistics(SceneReader(dataset / "bad_depth"), CONFIG).valid_depth_ratio == pytest.approx(4 / 24)
    assert scene_statistics(SceneReader(dataset / "good_dynamic"), CONFIG).dynamic_ratio == pytest.approx(0.5)
    assert scene_statistics(SceneReader(dataset / "static_tracks"), CONFIG).dynamic_ratio == 0.0
    # sharpness is the median over the sampled frames (first, middle, last)
    r = SceneReader(dataset / "blurred")
    want = np.median([laplacian_variance(r.rgb("cam00", i)) for i in (0, 4, 8)])
    assert scene_statistics(r, CONFIG).sharpness == pytest.approx(want)


def test_dynamic_ratio_counts_visible_observations_only(tmp_path):
    path = make_scene(tmp_path, "d", dynamic=True, tracks="half")
    with np.load(path / "tracks.npz") as f:
        pts, vis = f["points"], f["visibility"].copy()
    vis[2:, :] = False  # only the two moving points are ever visible
    vis[0, :4] = False
    np.savez_compressed(path / "tracks.npz", points=pts, visibility=vis)
    assert scene_statistics(SceneReader(path), CONFIG).dynamic_ratio == 1.0
    vis[:2] = False
    vis[2:] = True  # only still points visible
    np.savez_compressed(path / "tracks.npz", points=pts, visibility=vis)
    assert scene_statistics(SceneReader(path), CONFIG).dynamic_ratio == 0.0


def test_each_filter_rejects_exactly_its_violators(dataset, tmp_path):
    records = curate(dataset, tmp_path / "out", CONFIG, progress=False)
    assert {r["scene"]: r["reasons"] for r in records} == EXPECTED
    for r in records:
        assert r["accepted"] == (not r["reasons"]) and len(r["messages"]) == len(r["reasons"])


def test_bounds_and_requirements(dataset):
    s = scene_statistics(SceneReader(dataset / "good_static"), CONFIG)
    assert judge(s, CONFIG) == []
    c = CurationConfig(min_frames=10, max_translation_m=0.2, min_rotation_deg=11.0, min_sharpness=1e9)
    assert [r for r, _ in judge(s, c)] == ["min_frames", "max_translation_m", "min_rotation_deg", "min_sharpness"]
    lenient = CurationConfig(min_frames=9, min_translation_m=0.3 - 1e-6, max_rotation_deg=10.0 + 1e-3, min_sharpness=0)
    assert judge(s, lenient) == []
    nodepth = scene_statistics(SceneReader(dataset / "good_static"), CONFIG).__class__(
        **{**s.__dict__, "valid_depth_ratio": None})
    assert judge(nodepth, CurationConfig(min_frames=9)) == []
    assert [r for r, _ in judge(nodepth, CurationConfig(min_frames=9, require_depth=True))] == ["require_depth"]
    dyn = scene_statistics(SceneReader(dataset / "good_dynamic"), CONFIG)
    assert [r for r, _ in judge(dyn, CurationConfig(min_frames=9, max_dynamic_ratio=0.4))] == ["max_dynamic_ratio"]


def test_manifest_and_outputs(dataset, tmp_path):
    out = tmp_path / "out"
    curate(dataset, out, CONFIG, progress=False)
    lines = _manifest_text(out).splitlines()
    recs = [json.loads(x) for x in lines]
    assert [r["scene"] for r in recs] == sorted(EXPECTED) and recs == read_manifest(out)
    assert set(recs[0]) == {"scene", "accepted", "reasons", "messages", "stats"}
    good = next(r for r in recs if r["scene"] == "good_static")
    assert set(good["stats"]) == {"num_frames", "num_cameras", "dynamic", "translation_range_m",
                                  "rotation_range_deg", "valid_depth_ratio", "dynamic_ratio", "sharpness"}
    accepted = sorted(s for s, r in EXPECTED.items() if not r)
    assert (out / "accepted.txt").read_text().split() == accepted
    assert [p.name for p in list_scenes(out)] == accepted  # OUT is a dataset root of the accepted scenes
    assert all((out / s).is_symlink() and (out / s).resolve() == (dataset / s).resolve() for s in accepted)
    assert yaml.safe_load((out / "curation.yaml").read_text()) == {"mode": "symlink", "config": CONFIG.to_dict()}
    with pytest.raises(ValueError, match="different config"):
        curate(dataset, out, CurationConfig(min_frames=3), progress=False)
    with pytest.raises(ValueError, match="different config"):
        curate(dataset, out, CONFIG, mode="copy", progress=False)


@pytest.mark.slow
def test_copy_and_none_modes(dataset, tmp_path):
    curate(dataset, tmp_path / "copy", CONFIG, mode="copy", progress=False)
    curate(dataset, tmp_path / "none", CONFIG, mode="none", progress=False)
    accepted = sorted(s for s, r in EXPECTED.items() if not r)
    for s in accepted:
        assert not (tmp_path / "copy" / s).is_symlink() and validate_scene(tmp_path / "copy" / s) == []
    assert list_scenes(tmp_path / "none") == []
    assert _manifest_text(tmp_path / "copy") == _manifest_text(tmp_path / "none")


def test_injected_failure_then_rerun_equals_uninterrupted(dataset, tmp_path, monkeypatch):
    full = tmp_path / "full"
    curate(dataset, full, CONFIG, progress=False)
    real, calls = cm.scene_statistics, []

    def dies_on_fourth(scene, config):
        calls.append(scene.path.name)
        if len(calls) == 4:
            raise RuntimeError("killed")
        return real(scene, config)

    monkeypatch.setattr(cm, "scene_statistics", dies_on_fourth)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="killed"):
        curate(dataset, out, CONFIG, progress=False)
    assert len(read_manifest(out)) == 3  # partial manifest of the finished scenes
    monkeypatch.setattr(cm, "scene_statistics", real)
    curate(dataset, out, CONFIG, progress=False)
    assert _manifest_text(out) == _manifest_text(full)
    assert (out / "accepted.txt").read_text() == (full / "accepted.txt").read_text()


def test_rerun_skips_recorded_scenes(dataset, tmp_path, monkeypatch):
    out = tmp_path / "out"
    curate(dataset, out, CONFIG, progress=False)
    before = _manifest_text(out)
    monkeypatch.setattr(cm, "scene_statistics", lambda *a: pytest.fail("a recorded scene was measured again"))
    assert len(curate(dataset, out, CONFIG, progress=False)) == len(EXPECTED)
    assert _manifest_text(out) == before


@pytest.mark.slow
def test_killed_process_then_rerun_equals_uninterrupted(dataset, tmp_path):
    """A real SIGKILL at a known point: the child (``data_prep curate --mode copy``) kills itself inside the
    copy of the second accepted scene (good_multiview), after the records of the five scenes before it
    (bad_depth … good_dynamic) were written and while that copy sits in its temporary folder. Nothing
    races: the kill point is fixed by the scene order."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG.to_dict()))
    full, out = tmp_path / "full", tmp_path / "out"
    curate(dataset, full, CONFIG, mode="copy", progress=False)
    script = textwrap.dedent(f"""
        import os, shutil, signal, sys, types
        import data_prep.curate as cm
        from data_prep.cli import main
        copies = []
        def copytree(src, dst, **kw):  # curate's scene copy (shutil's own recursion keeps the real one)
            shutil.copytree(src, dst, **kw)
            copies.append(src)
            if len(copies) == 2:
                os.kill(os.getpid(), signal.SIGKILL)  # copied, not yet renamed into place
            return dst
        cm.shutil = types.SimpleNamespace(**{{**vars(shutil), "copytree": copytree}})
        sys.exit(main(["curate", {str(dataset)!r}, {str(out)!r}, "--config", {str(cfg)!r}, "--workers", "1",
                       "--mode", "copy", "--quiet"]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr  # killed half way, not finished
    names = sorted(EXPECTED)
    assert sorted(f.stem for f in (out / ".curation").glob("*.json")) == names[:names.index("good_multiview")]
    assert not (out / "manifest.jsonl").exists() and not (out / "accepted.txt").exists()
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["curation.yaml", "good_dynamic"]
    assert validate_scene(out / "good_dynamic") == []  # whole scenes only
    leftovers = [p for p in out.iterdir() if p.name.startswith(".") and p.name != ".curation"]
    assert len(leftovers) == 1 and "good_multiview" in leftovers[0].name  # the interrupted copy, hidden
    curate(dataset, out, CONFIG, mode="copy", progress=False)  # the rerun (in-process: no second torch import)
    assert _manifest_text(out) == _manifest_text(full)
    assert (out / "accepted.txt").read_text() == (full / "accepted.txt").read_text()
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != ".curation"]  # leftovers removed
    for s in sorted(x for x, r in EXPECTED.items() if not r):
        assert validate_scene(out / s) == []


@pytest.mark.slow
def test_parallel_equals_sequential(dataset, tmp_path):
    seq = curate(dataset, tmp_path / "seq", CONFIG, workers=1, progress=False)
    par = curate(dataset, tmp_path / "par", CONFIG, workers=2, progress=False)
    assert seq == par
    assert _manifest_text(tmp_path / "seq") == _manifest_text(tmp_path / "par")


def test_config_yaml(tmp_path):
    assert CurationConfig.from_yaml(DEFAULT_CONFIG_PATH) == CurationConfig()
    f = tmp_path / "c.yaml"
    f.write_text("min_frames: 5\nmax_translation_m: 2.5\n")
    assert CurationConfig.from_yaml(f) == CurationConfig(min_frames=5, max_translation_m=2.5)
    for text, match in [("min_framez: 5\n", "min_framez"), ("min_frames: 0\n", "min_frames"),
                        ("min_sharpness: -1\n", "min_sharpness"), ("min_valid_depth_ratio: 1.5\n", "ratio"),
                        ("validate: 1\n", "validate"), ("- 1\n", "mapping"),
                        ("min_rotation_deg: 50\nmax_rotation_deg: 10\n", "leave no range")]:  # rejected every scene
        f.write_text(text)
        with pytest.raises(ValueError, match=match):
            CurationConfig.from_yaml(f)
    with pytest.raises(FileNotFoundError):
        CurationConfig.from_yaml(tmp_path / "missing.yaml")


def test_bad_arguments(dataset, tmp_path):
    with pytest.raises(ValueError, match="workers"):
        curate(dataset, tmp_path / "o", workers=0)
    with pytest.raises(ValueError, match="mode"):
        curate(dataset, tmp_path / "o", mode="hardlink")
    with pytest.raises(ValueError, match="is input"):
        curate(dataset, dataset)
    with pytest.raises(ValueError, match="holds input"):
        curate(dataset, dataset.parent)
    with pytest.raises(ValueError, match="is inside the input"):  # it was accepted: the dataset then failed validate
        curate(dataset, dataset / "curated")
    user = tmp_path / "user"
    user.mkdir()
    (user / "manifest.jsonl").write_text("{}\n")  # a user's own file: it was replaced
    with pytest.raises(ValueError, match="holds other files"):
        curate(dataset, user)
    assert (user / "manifest.jsonl").read_text() == "{}\n" and not (dataset / "curated").exists()
    with pytest.raises(FileNotFoundError):
        curate(tmp_path / "nope", tmp_path / "o")


def test_cli_subcommand(dataset, tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG.to_dict()))
    args = ["curate", str(dataset), str(tmp_path / "o"), "--config", str(cfg), "--workers", "1", "--quiet"]
    assert cli_main(args) == 0
    assert "11 scene(s): 3 accepted, 8 rejected" in capsys.readouterr().out
    assert read_manifest(tmp_path / "o") == curate(dataset, tmp_path / "o", CONFIG, progress=False)
    assert cli_main(["curate", str(dataset), str(tmp_path / "o2"), "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "not found" in capsys.readouterr().err
    assert cli_main(["curate", str(dataset), str(tmp_path / "o3"), "--mode", "hardlink"]) == 2
    assert "mode" in capsys.readouterr().err
    (tmp_path / "empty" / "not_a_scene").mkdir(parents=True)  # issue 61: exit 0 with an empty manifest, no word
    assert cli_main(["curate", str(tmp_path / "empty"), str(tmp_path / "o4")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds no scenes (a scene is a sub-folder with meta.json)" in err
    assert not (tmp_path / "o4").exists()


def _png_header(width: int, height: int) -> bytes:
    """The signature and IHDR chunk of an 8-bit RGB PNG of ``width`` × ``height`` (no pixel data: a truncated
    file whose header alone promises the size)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


@pytest.mark.parametrize("kind", ["huge", "fifo"])
def test_a_frame_too_large_or_not_a_file_is_rejected_before_decoding(tmp_path, kind):
    """issue 28: a frame whose header promises 100 000² pixels is refused by the image_pixels limit before any
    decoding (40 GB), and a FIFO frame is named as such instead of blocking the reader; the scene is rejected."""
    scene = make_scene(tmp_path / "in", "s", T=9)
    frame = scene / "cam00" / "rgb" / "00004.png"  # one of the 3 sampled frames (0, 4, 8)
    frame.unlink()
    if kind == "huge":
        frame.write_bytes(_png_header(100_000, 100_000))
    else:
        os.mkfifo(frame)
    t0 = time.perf_counter()
    (record,) = curate(tmp_path / "in", tmp_path / "out", CONFIG, progress=False)
    assert time.perf_counter() - t0 < 5
    assert not record["accepted"] and record["reasons"] == ["error"]
    expected = ("100000×100000 = 10000000000 exceeds the limit of 100000000 pixels" if kind == "huge"
                else "is a FIFO (named pipe), not a file")
    assert expected in record["messages"][0] and str(frame) in record["messages"][0], record["messages"]


def test_copy_onto_a_full_disk_is_one_line_naming_the_file_and_leaves_no_half_scene(dataset, tmp_path, capsys,
                                                                                  monkeypatch):
    """``--mode copy`` when the disk fills mid-scene (the third file copied fails with ENOSPC): one line naming the
    file under OUT, exit 2, no partly copied scene (copytree's shutil.Error was a 49-line traceback); a scene
    larger than the free space is refused before its copy starts."""
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG.to_dict()))
    real, copied = shutil.copy2, []

    def fills(src, dst, **kw):
        copied.append(dst)
        if len(copied) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", dst)
        return real(src, dst, **kw)

    monkeypatch.setattr(cm.shutil, "copy2", fills)
    out = tmp_path / "out"
    assert cli_main(["curate", str(dataset), str(out), "--config", str(cfg), "--mode", "copy", "--workers", "1",
                     "--quiet"]) == 2
    rel = Path(copied[2]).relative_to(out)  # .<scene>.<pid>.<random>.tmp/<file>: the scene's temporary folder
    named = out / rel.parts[0].split(".")[1] / Path(*rel.parts[1:])
    assert capsys.readouterr().err == f"data_prep: error: {named}: No space left on device\n"
    assert [p.name for p in out.iterdir() if p.name.startswith("scene")] == []  # nothing half-copied
    assert not [p for p in out.iterdir() if ".tmp" in p.name]
    monkeypatch.setattr(cm.shutil, "copy2", real)
    monkeypatch.setenv("DIFF4SPLAT_MAX_OUTPUT_BYTES", "1000")
    assert cli_main(["curate", str(dataset), str(tmp_path / "small"), "--config", str(cfg), "--mode", "copy",
                     "--workers", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--mode copy of" in err and "--mode symlink" in err, err
