"""Faults are the normal case at scale: Ray workers killed mid-scene (``DIFF4SPLAT_FAULT``,
:func:`data_prep.engine.fault_point`) and a whole run interrupted on the local engine then resumed on Ray all end with
the dataset a clean local run writes — every scene whole, exactly once, nothing left over. (A node removed mid-run:
tests/test_data_prep_ray_nodes.py.)"""
from __future__ import annotations

from concurrent.futures.process import BrokenProcessPool

import pytest

ray = pytest.importorskip("ray", reason="the ray extra (diff4splat[ray]) is not installed")

from _data_prep_fixtures import tree  # noqa: E402

from data_prep.engine import FAULT_ENV, Engine  # noqa: E402
from data_prep.synth_dataset import synthesize  # noqa: E402

pytestmark = pytest.mark.slow

KW = dict(seed=4, size=32, frames=9, cameras=2, static_ratio=0.3, progress=False)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """6 scenes made in this process, one after another (``--engine local --workers 1``)."""
    root = tmp_path_factory.mktemp("reference") / "data"
    synthesize(root, 6, **KW)
    return tree(root)


@pytest.fixture(scope="module")
def flags(tmp_path_factory):
    """A local Ray of 2 CPUs started with ``DIFF4SPLAT_FAULT`` set (its workers inherit it): the worker making
    scene 2 dies after every file is written but before the rename (``write``), the one making scene 4 after the
    rename but before its task returns (``done``). Yields the two flag files."""
    root = tmp_path_factory.mktemp("faults")
    flag_write, flag_done = root / "write", root / "done"
    mp = pytest.MonkeyPatch()
    mp.setenv(FAULT_ENV, f"write:scene_00002:{flag_write},done:scene_00004:{flag_done}")
    assert not ray.is_initialized()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    mp.delenv(FAULT_ENV)  # this process (and a local pool it spawns) runs without faults unless a test sets one
    yield flag_write, flag_done
    ray.shutdown()
    mp.undo()


def test_ray_workers_killed_mid_scene_are_retried_and_the_dataset_is_whole(reference, flags, tmp_path):
    """The ``write`` retry must not trip over the half-made temporary folder (it is removed); the ``done`` retry
    must find its scene whole and leave it."""
    synthesize(tmp_path / "data", 6, **KW, engine=Engine("ray"))
    assert all(f.exists() for f in flags)  # both workers were killed once
    got = tree(tmp_path / "data")
    assert got.keys() == reference.keys() and all(got[k] == reference[k] for k in got)


def test_a_run_killed_on_the_local_engine_resumes_on_ray(reference, flags, tmp_path, monkeypatch):
    """A local pool whose worker is killed mid-scene fails the run, its scene left unfinished (the other worker may
    finish every other scene first); the same command on Ray finishes it."""
    flag = tmp_path / "killed"
    monkeypatch.setenv(FAULT_ENV, f"write:scene_00001:{flag}")  # read by the pool's spawned workers
    with pytest.raises(BrokenProcessPool):
        synthesize(tmp_path / "data", 6, **KW, workers=2)
    assert flag.exists() and not (tmp_path / "data" / "scene_00001" / "meta.json").exists()
    synthesize(tmp_path / "data", 6, **KW, engine=Engine("ray"))
    got = tree(tmp_path / "data")
    assert got.keys() == reference.keys() and all(got[k] == reference[k] for k in got)
