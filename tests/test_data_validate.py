"""Validator: every corruption of a valid scene is reported against the right file; CLI exit codes."""
from __future__ import annotations

import ast
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest

import data_prep.format
import data_prep.scene_files
import data_prep.validate
from data_prep.cli import main
from data_prep.format import SceneWriter
from data_prep.validate import Problem, summarize, validate_path, validate_scene
from diff4splat.cameras import intrinsics_from_fov, make_trajectory
from diff4splat.io import save_depth_exr, save_image

H, W, T = 6, 8, 3


def make_scene(path, depth_source="ground_truth", dynamic=True):
    rng = np.random.default_rng(1)
    K = intrinsics_from_fov(W, H, fov_x_deg=60.0)
    with SceneWriter(path, source="synthetic", dynamic=dynamic, depth_source=depth_source, num_frames=T, fps=8.0) as w:
        for name, traj in (("cam00", "orbit"), ("cam01", "forward")):
            w.add_camera(name, make_trajectory(traj, T, K, W, H))
            for i in range(T):
                depth = rng.uniform(1, 5, (H, W)) if depth_source != "none" else None
                w.write_frame(name, i, rng.random((H, W, 3)), depth)
        pts = rng.normal(size=(4, T, 3)).astype(np.float32)
        w.write_tracks(pts if dynamic else np.repeat(pts[:, :1], T, 1), rng.random((4, T)) < 0.5)
        w.write_caption("a box slides to the left")
    return path


def _edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _raw_exr(path, z):
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"Z": z.astype(np.float32)}) as f:
        f.write(str(path))


def _npz(path, **arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)


P_OK = np.zeros((4, T, 3), np.float32)
V_OK = np.ones((4, T), bool)

# (name, corruption(scene), file relative to the scene, message fragment)
CORRUPTIONS = [
    ("missing rgb", lambda s: (s / "cam01/rgb/00001.png").unlink(), "cam01/rgb/00001.png", "missing frame"),
    ("missing depth", lambda s: (s / "cam00/depth/00002.exr").unlink(), "cam00/depth/00002.exr", "missing frame"),
    ("garbage png", lambda s: (s / "cam00/rgb/00000.png").write_bytes(b"not a png"),
     "cam00/rgb/00000.png", "could not decode"),
    ("grey png", lambda s: cv2.imwrite(str(s / "cam00/rgb/00001.png"), np.zeros((H, W), np.uint8)),
     "cam00/rgb/00001.png", "8-bit RGB"),
    ("16-bit png", lambda s: cv2.imwrite(str(s / "cam00/rgb/00001.png"), np.zeros((H, W, 3), np.uint16)),
     "cam00/rgb/00001.png", "8-bit RGB"),
    ("wrong rgb size", lambda s: save_image(s / "cam01/rgb/00002.png", np.zeros((H, W + 2, 3))),
     "cam01/rgb/00002.png", "cameras.json says"),
    ("extra frame", lambda s: save_image(s / "cam00/rgb/00003.png", np.zeros((H, W, 3))),
     "cam00/rgb/00003.png", "unexpected file"),
    ("garbage exr", lambda s: (s / "cam01/depth/00000.exr").write_bytes(b"\x76\x2f\x31\x01junk"),
     "cam01/depth/00000.exr", "could not read"),
    ("nan depth", lambda s: _raw_exr(s / "cam00/depth/00001.exr", np.full((H, W), np.nan)),
     "cam00/depth/00001.exr", "48 NaN"),
    ("-inf depth", lambda s: _raw_exr(s / "cam00/depth/00001.exr", np.full((H, W), -np.inf)),
     "cam00/depth/00001.exr", "48 -inf"),
    ("zero depth", lambda s: save_depth_exr(s / "cam00/depth/00001.exr", np.zeros((H, W))),
     "cam00/depth/00001.exr", "48 ≤ 0"),
    ("wrong depth size", lambda s: save_depth_exr(s / "cam01/depth/00001.exr", np.ones((H + 1, W))),
     "cam01/depth/00001.exr", "cameras.json says"),
    ("no Z channel", lambda s: OpenEXR.File({"type": OpenEXR.scanlineimage}, {"R": np.ones((H, W), np.float32)}).write(
        str(s / "cam01/depth/00001.exr")), "cam01/depth/00001.exr", "no depth channel"),
    ("meta missing key", lambda s: _edit_json(s / "meta.json", lambda d: d.pop("fps")), "meta.json", "missing key"),
    ("meta bad type", lambda s: _edit_json(s / "meta.json", lambda d: d.update(num_frames="3")),
     "meta.json", "num_frames"),
    ("meta bad json", lambda s: (s / "meta.json").write_text("{"), "meta.json", "Expecting"),
    ("meta missing", lambda s: (s / "meta.json").unlink(), "meta.json", "missing file"),
    ("meta T mismatch", lambda s: _edit_json(s / "meta.json", lambda d: d.update(num_frames=2)),
     "cam00/cameras.json", "num_frames is 2"),
    ("camera folder missing", lambda s: shutil.rmtree(s / "cam01"), "cam01", "missing camera folder"),
    ("camera not listed", lambda s: shutil.copytree(s / "cam01", s / "cam02"), "cam02", "not listed"),
    ("bad rotation", lambda s: _edit_json(s / "cam01/cameras.json", lambda d: d["viewmats"][1][0].__setitem__(0, 2.0)),
     "cam01/cameras.json", "not a proper rotation"),
    ("cameras missing key", lambda s: _edit_json(s / "cam00/cameras.json", lambda d: d.pop("Ks")),
     "cam00/cameras.json", "missing key 'Ks'"),
    ("cameras.json missing", lambda s: (s / "cam00/cameras.json").unlink(), "cam00/cameras.json", "missing file"),
    ("timestamps missing", lambda s: _edit_json(s / "cam01/cameras.json", lambda d: d.pop("timestamps")),
     "cam01/cameras.json", "timestamps"),
    ("timestamps decreasing",
     lambda s: _edit_json(s / "cam01/cameras.json", lambda d: d.update(timestamps=[0.0, 0.3, 0.2])),
     "cam01/cameras.json", "non-decreasing"),
    ("not synchronised",
     lambda s: _edit_json(s / "cam01/cameras.json", lambda d: d.update(timestamps=[1.0, 1.125, 1.25])),
     "cam01/cameras.json", "not synchronised"),
    ("times vs timestamps", lambda s: _edit_json(s / "cam00/cameras.json", lambda d: d.update(times=[0.0, 0.7, 1.0])),
     "cam00/cameras.json", "normalised 'timestamps'"),
    ("tracks wrong T",
     lambda s: _npz(s / "tracks.npz", points=np.zeros((4, T + 1, 3), np.float32), visibility=np.ones((4, T + 1), bool)),
     "tracks.npz", "'points' must be float32"),
    ("tracks float64", lambda s: _npz(s / "tracks.npz", points=P_OK.astype(np.float64), visibility=V_OK),
     "tracks.npz", "float32"),
    ("visibility not bool", lambda s: _npz(s / "tracks.npz", points=P_OK, visibility=V_OK.astype(np.uint8)),
     "tracks.npz", "'visibility' must be bool"),
    ("tracks nan", lambda s: _npz(s / "tracks.npz", points=np.full((4, T, 3), np.nan, np.float32), visibility=V_OK),
     "tracks.npz", "non-finite"),
    ("tracks missing array", lambda s: _npz(s / "tracks.npz", points=P_OK), "tracks.npz", "missing array"),
    ("tracks garbage", lambda s: (s / "tracks.npz").write_bytes(b"nope"), "tracks.npz", "could not read"),
    ("caption two lines", lambda s: (s / "caption.txt").write_text("one\ntwo\n"), "caption.txt", "one non-empty line"),
    ("caption not utf8", lambda s: (s / "caption.txt").write_bytes(b"\xff\xfe\xfa"), "caption.txt", "UTF-8"),
]


@pytest.fixture(scope="module")
def valid_scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("valid") / "scene")


def test_valid_scene_has_no_problem(valid_scene):
    assert validate_scene(valid_scene) == []


@pytest.mark.parametrize("name,corrupt,file,fragment", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
def test_corruption_is_reported_with_its_file(valid_scene, tmp_path, name, corrupt, file, fragment):
    scene = tmp_path / "scene"
    shutil.copytree(valid_scene, scene)
    corrupt(scene)
    problems = validate_scene(scene)
    assert problems, f"{name}: no problem reported"
    hits = [p for p in problems if p.file == scene / file]
    assert hits, f"{name}: expected a problem for {file}, got {[str(p) for p in problems]}"
    assert any(fragment in p.message for p in hits), [str(p) for p in hits]
    assert str(hits[0]) == f"{scene / file}: {hits[0].message}"


def test_static_scene_with_moving_tracks(tmp_path):
    scene = make_scene(tmp_path / "s", dynamic=False)
    assert validate_scene(scene) == []
    moving = np.zeros((4, T, 3), np.float32)
    moving[0, 2, 0] = 1e-3
    _npz(scene / "tracks.npz", points=moving, visibility=V_OK)
    assert [p.file.name for p in validate_scene(scene)] == ["tracks.npz"]
    assert "static scene" in validate_scene(scene)[0].message


def test_depth_folder_with_depth_source_none(tmp_path):
    scene = make_scene(tmp_path / "s", depth_source="none")
    assert validate_scene(scene) == []
    save_depth_exr(scene / "cam00" / "depth" / "00000.exr", np.ones((H, W)))
    assert validate_scene(scene) == [
        Problem(scene / "cam00" / "depth", "depth folder present but meta.json depth_source is 'none'")]


def test_dataset_root(tmp_path, valid_scene):
    shutil.copytree(valid_scene, tmp_path / "a")
    shutil.copytree(valid_scene, tmp_path / "b")
    assert validate_path(tmp_path) == (2, [])
    (tmp_path / "b" / "cam00" / "rgb" / "00000.png").unlink()
    (tmp_path / "c").mkdir()  # not a scene
    n, problems = validate_path(tmp_path)
    assert n == 2 and {p.file for p in problems} == {tmp_path / "b/cam00/rgb/00000.png", tmp_path / "c/meta.json"}
    empty = tmp_path / "empty"
    shutil.rmtree(tmp_path / "a"), shutil.rmtree(tmp_path / "b"), shutil.rmtree(tmp_path / "c")
    empty.mkdir()
    assert validate_path(empty)[1][0].message.startswith("no scene folders")
    with pytest.raises(FileNotFoundError):
        validate_path(tmp_path / "missing")


def test_cli_validate(tmp_path, valid_scene, capsys):
    shutil.copytree(valid_scene, tmp_path / "a")
    shutil.copytree(valid_scene, tmp_path / "b")
    assert main(["validate", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == "2 scene(s) checked: all valid"
    assert main(["validate", str(tmp_path / "a")]) == 0
    capsys.readouterr()
    save_depth_exr(tmp_path / "b" / "cam01" / "depth" / "00002.exr", np.zeros((H, W)))
    (tmp_path / "b" / "caption.txt").write_text("x\ny")
    assert main(["validate", str(tmp_path)]) == 1
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == f"{tmp_path / 'b' / 'caption.txt'}: caption must be one non-empty line"
    assert lines[1].startswith(f"{tmp_path / 'b' / 'cam01' / 'depth' / '00002.exr'}: depth must be > 0")
    assert lines[-1] == "2 scene(s) checked: 2 problem(s) in 1 scene(s)"
    assert main(["validate", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("data_prep: error: not a folder") and err.count("\n") == 1


# --------------------------------------------------------------------------- issue 28

@pytest.mark.parametrize("content", [b"", b'{"width": 8, "height": 6, "Ks": [[[1'], ids=["empty", "truncated"])
def test_unreadable_cameras_json_is_one_problem(valid_scene, tmp_path, capsys, content):
    """A 0-byte or truncated cameras.json was reported twice (as cameras and as timestamps) and counted as 2."""
    scene = tmp_path / "scene"
    shutil.copytree(valid_scene, scene)
    (scene / "cam00" / "cameras.json").write_bytes(content)
    problems = validate_scene(scene)
    assert len(problems) == 1 and problems[0].file == scene / "cam00" / "cameras.json", problems
    assert problems[0].message.startswith("not valid JSON (Expecting") and str(scene) not in problems[0].message
    assert main(["validate", str(scene)]) == 1
    assert capsys.readouterr().out.splitlines() == [str(problems[0]), "1 scene(s) checked: 1 problem(s) in 1 scene(s)"]


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)


def _loop(path):
    path.unlink(missing_ok=True)
    other = path.with_name(path.name + ".other")
    path.symlink_to(other)
    other.symlink_to(path)


def _dangling(path):
    path.unlink(missing_ok=True)
    path.symlink_to(path.with_name("gone"))


@pytest.mark.parametrize("file", ["cam00/rgb/00001.png", "cam01/depth/00002.exr", "cam00/cameras.json", "meta.json",
                                  "caption.txt", "tracks.npz"])
@pytest.mark.parametrize("make, message", [
    (_fifo, "is a FIFO (named pipe), not a regular file"), (_loop, "is a symlink loop, not a regular file"),
    (_dangling, "is a symlink to a missing file"),
    (lambda p: (p.unlink(), p.mkdir()), "is a folder, not a regular file"),
], ids=["fifo", "loop", "dangling", "folder"])
def test_a_path_that_is_not_a_regular_file_says_what_it_is(valid_scene, tmp_path, file, make, message):
    """A FIFO frame was a "missing frame", a symlink-loop cameras.json a "missing file" (a FIFO caption.txt or
    tracks.npz would have blocked the validator, which opened it)."""
    scene = tmp_path / "scene"
    shutil.copytree(valid_scene, scene)
    make(scene / file)
    hits = [p for p in validate_scene(scene) if p.file == scene / file]
    assert len(hits) == 1 and hits[0].message.startswith(message), hits


def test_summary_counts_agree_with_the_problems(tmp_path, valid_scene, capsys):
    """One scene with problems in two cameras read "1 scene(s) checked: 2 problem(s) in 2 scene(s)"."""
    scene = tmp_path / "root" / "a"
    shutil.copytree(valid_scene, scene)
    (scene / "cam00" / "rgb" / "00000.png").unlink()
    (scene / "cam01" / "rgb" / "00000.png").unlink()
    assert main(["validate", str(scene)]) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "1 scene(s) checked: 2 problem(s) in 1 scene(s)"
    shutil.copytree(valid_scene, tmp_path / "root" / "b")
    (tmp_path / "root" / "notes").mkdir()  # not a scene: a problem of the root, not of a scene
    assert main(["validate", str(tmp_path / "root")]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 4
    assert lines[-1] == "2 scene(s) checked: 2 problem(s) in 1 scene(s); 1 sub-folder(s) not a scene"
    shutil.rmtree(scene)
    assert main(["validate", str(tmp_path / "root")]) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "1 scene(s) checked: all valid; 1 sub-folder(s) not a scene"
    n, problems = validate_path(tmp_path / "root")
    assert summarize(n, problems) == "1 scene(s) checked: all valid; 1 sub-folder(s) not a scene"
    assert [p.scene for p in problems] == [None]


def _imports(module):
    """(module imported, whether at the top level) for every import of ``module``'s source (relative ones resolved
    within data_prep)."""
    tree = ast.parse(Path(module.__file__).read_text())
    top = {id(node) for node in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            name = ("data_prep." + (node.module or "")) if node.level else node.module
            out.append((name, id(node) in top))
        elif isinstance(node, ast.Import):
            out += [(a.name, id(node) in top) for a in node.names]
    return out


def test_validate_and_format_import_each_other_no_more():
    """data_prep.format (the writer) validates with data_prep.validate; validate imported format back (the circle
    was dodged with an import inside a function). Now validate and format share data_prep.scene_files."""
    for module in (data_prep.validate, data_prep.scene_files):
        assert not [n for n, _ in _imports(module) if n == "data_prep.format"], module.__name__
    assert ("data_prep.validate", True) in _imports(data_prep.format)
    assert all(top for _, top in _imports(data_prep.format))  # no import inside a function
