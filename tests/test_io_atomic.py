from pathlib import Path

import pytest

from diff4splat.io import atomic_output_dir, atomic_output_path


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


def test_atomic_output_dir_replaces_only_on_success(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(out) as tmp:
        (tmp / "a.txt").write_text("1")
        assert not out.exists()
    assert (out / "a.txt").read_text() == "1"
    with pytest.raises(RuntimeError):
        with atomic_output_dir(out) as tmp:
            (tmp / "b.txt").write_text("half")
            raise RuntimeError("crash")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temp folder left behind
    with atomic_output_dir(out) as tmp:
        (tmp / "c.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["c.txt"]
    with pytest.raises(FileExistsError):
        with atomic_output_dir(out, replace=False):
            pass
