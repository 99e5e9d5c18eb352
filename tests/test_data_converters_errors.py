"""data_prep convert on sources that are not what they claim to be (issue 28): a source that is not a folder, and
an empty, truncated or foreign camera or annotation file inside one, each give one ``data_prep: error:`` line naming
the path, exit code 2 and no output folder."""
from __future__ import annotations

import gzip
import io

import numpy as np
import pytest
from helpers import not_a_folder

from data_prep.cli import main
from data_prep.converters import CONVERTERS


def _only_error_line(capsys) -> str:
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("data_prep: error: "), err
    return err[0]


@pytest.mark.parametrize("kind, text", [("fifo", "is a FIFO (named pipe), not a folder"),
                                        ("loop", "is a symlink loop, not a folder"),
                                        ("missing", None)])
def test_every_converter_names_a_source_that_is_not_a_folder(tmp_path, capsys, kind, text):
    """issue 28: only realestate10k/stereo4d said a FIFO or looping source was one; the others looked for their
    first file inside it ("D-NeRF transforms: fifo/transforms_train.json not found")."""
    src = tmp_path / "src" if kind == "missing" else not_a_folder(tmp_path / "src", kind)
    for source in sorted(CONVERTERS):
        assert main(["convert", source, str(src), str(tmp_path / "out")]) == 2, source
        line = _only_error_line(capsys)
        want = f"source folder: {src} {text}" if text else f"source folder not found: {src}"
        assert line == f"data_prep: error: {want}", (source, line)
    assert not (tmp_path / "out").exists()


def _gz(data: bytes) -> bytes:
    return gzip.compress(data, mtime=0)  # no time stamp: the bytes (and the test ids) are the same in every process


def _truncated_npz() -> bytes:
    buf = io.BytesIO()
    np.savez(buf, a=np.zeros((4, 4)))
    return buf.getvalue()[:40]


def _pickled_npy() -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    return buf.getvalue()


def _plain_npy() -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.zeros(3))
    return buf.getvalue()


# (source, file inside the source folder, its bytes, words the one error line holds besides the file's path)
_BAD_SOURCE_FILES = [
    ("tartanair", "pose_left.txt", b"", "no lines of numbers (an empty file)"),
    ("tartanair", "pose_left.txt", b"1 2 3\n", "expected 7 values per line"),
    ("spring", "cam_data/intrinsics.txt", b"", "no lines of numbers (an empty file)"),
    ("spring", "cam_data/intrinsics.txt", b"\xff\xfe\x00garbage", ""),
    ("n3dv", "poses_bounds.npy", b"", "is not a readable .npy array"),
    ("n3dv", "poses_bounds.npy", _pickled_npy(), "pickled Python objects, which are never loaded"),
    ("pointodyssey", "anno.npz", b"", "is not a readable .npz archive"),
    ("pointodyssey", "anno.npz", _truncated_npz(), "is not a readable .npz archive"),
    ("stereo4d", "clip.npz", _plain_npy(), "is a .npy array, not a .npz archive"),
    ("matrixcity", "transforms.json", b"", "is not valid JSON"),
    ("multicamvideo", "cameras/camera_extrinsics.json", b'{"frame0": ', "is not valid JSON"),
    ("dynamic_replica", "frame_annotations_train.jgz", b"not gzip at all", "is not gzip-compressed JSON"),
    ("dynamic_replica", "frame_annotations_train.jgz", _gz(b"[{"), "is not valid JSON"),
    ("realestate10k", "clip.txt", b"\x9d\xff\x00", "is not UTF-8 text"),
    ("realestate10k", "clip.txt", b"https://x\n1000 0.5 0.5 0.5 0.5 0 0 1 0 0 0", ":2: expected 19 values per frame"),
    ("realestate10k", "clip.txt", b"https://x\nabc" + b" 0" * 18 + b"\n", ":2: values must be numbers"),
    ("vkitti2", "intrinsic.txt", b"\xff\xfe\x00", "is not UTF-8 text"),
]


@pytest.mark.parametrize("source, name, data, words", _BAD_SOURCE_FILES)
def test_an_empty_truncated_or_foreign_source_file_is_one_line_naming_it(tmp_path, capsys, source, name, data,
                                                                         words):
    """issue 28 (data_prep convert with truncated or 0-byte camera files): a 0-byte ``anno.npz``/``poses_bounds.npy``
    was an ``EOFError`` traceback, a 0-byte MatrixCity/MultiCamVideo/Dynamic Replica JSON "Expecting value: line 1
    column 1 (char 0)" with no file, a RealEstate10K ``clip.txt`` of random bytes a bare ``'utf-8' codec …``, a
    truncated line "has no frames", an empty TartanAir/Spring file a numpy warning and "got 1" value."""

    src = tmp_path / "src"
    path = src / name
    path.parent.mkdir(parents=True)
    path.write_bytes(data)
    assert main(["convert", source, str(src), str(tmp_path / "out")]) == 2
    line = _only_error_line(capsys)
    assert str(path) in line and words in line, line
    assert not (tmp_path / "out").exists()


def test_an_unknown_option_or_an_output_inside_the_source_is_one_line(tmp_path, capsys):
    """``--option bogus=1`` was a TypeError traceback from the converter's call; an output folder inside the source
    was accepted and written into the source dataset."""
    src = tmp_path / "src"
    src.mkdir()
    assert main(["convert", "dnerf", str(src), str(tmp_path / "out"), "--option", "bogus=1"]) == 2
    line = _only_error_line(capsys)
    assert "dnerf takes no option bogus; its options: split, background" in line, line
    for out, word in ((src / "out", "is inside"), (src, "is"), (tmp_path, "holds")):
        assert main(["convert", "dnerf", str(src), str(out)]) == 2
        assert f"output scene folder {out} {word} the source {src}" in _only_error_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"] and not any(src.iterdir())
