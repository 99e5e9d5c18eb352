from pathlib import Path

import pytest

from diff4splat.io import MARKER, OutputDirError, atomic_output_path, output_dir


def test_atomic_output_path(tmp_path):
    target = tmp_path / "deep" / "x.txt"
    with atomic_output_path(target) as tmp:
        assert tmp.endswith(".txt") and Path(tmp).parent == target.parent
        Path(tmp).write_text("new")
        assert not target.exists()  # nothing visible until the block succeeds
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError):
        with atomic_output_path(target) as tmp:
            Path(tmp).write_text("half")
            raise RuntimeError("crash")
    assert target.read_text() == "new"
    assert [p.name for p in target.parent.iterdir()] == ["x.txt"]


def test_output_dir_replaces_only_on_success(tmp_path):
    out = tmp_path / "out"
    with output_dir(out, kind="test") as tmp:
        (tmp / "a.txt").write_text("1")
        assert not out.exists()
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "a.txt"]
    with pytest.raises(RuntimeError):
        with output_dir(out, kind="test") as tmp:
            (tmp / "b.txt").write_text("half")
            raise RuntimeError("crash")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "a.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp folder or lock file left behind
    with output_dir(out, kind="test") as tmp:
        (tmp / "c.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "c.txt"]
    with pytest.raises(FileExistsError):
        with output_dir(out, kind="test", replace=False):
            pass
    with pytest.raises(OutputDirError, match="'test' output, not 'other'"):
        with output_dir(out, kind="other"):
            pass
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "c.txt"]
