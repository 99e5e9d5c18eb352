"""Faults are the normal case at scale: a Ray worker killed mid-scene (``DIFF4SPLAT_FAULT``,
:func:`data_prep.engine.fault_point`), a node removed mid-run, and a whole run interrupted and resumed on the other
engine all end with the dataset a clean local run writes — every scene whole, exactly once, nothing left over."""
from __future__ import annotations

import threading
import time
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


@pytest.fixture
def no_ray():
    assert not ray.is_initialized()
    yield
    ray.shutdown()


@pytest.mark.parametrize("stage", ["write", "done"])
def test_a_ray_worker_killed_mid_scene_is_retried_and_the_dataset_is_whole(reference, tmp_path, monkeypatch, no_ray,
                                                                           stage):
    """SIGKILL of the worker making scene 2: after every file is written but before the rename (``write``: the
    retry must not trip over the half-made temporary folder, which is removed), or after the rename but before
    the task returns (``done``: the retry must find the scene whole and leave it)."""
    flag = tmp_path / "killed"
    monkeypatch.setenv(FAULT_ENV, f"{stage}:scene_00002:{flag}")  # before Ray starts: its workers inherit it
    synthesize(tmp_path / "data", 6, **KW, engine=Engine("ray", workers=2))
    assert flag.exists()  # the worker was killed once
    got = tree(tmp_path / "data")
    assert got.keys() == reference.keys() and all(got[k] == reference[k] for k in got)


def test_a_run_killed_on_the_local_engine_resumes_on_ray(reference, tmp_path, monkeypatch, no_ray):
    """A local pool whose worker is killed fails the run; the same command on Ray finishes it."""
    flag = tmp_path / "killed"
    monkeypatch.setenv(FAULT_ENV, f"done:scene_00001:{flag}")
    with pytest.raises(BrokenProcessPool):
        synthesize(tmp_path / "data", 6, **KW, workers=2)
    assert flag.exists() and len(list((tmp_path / "data").glob("scene_*/meta.json"))) < 6
    synthesize(tmp_path / "data", 6, **KW, engine=Engine("ray", workers=2))
    got = tree(tmp_path / "data")
    assert got.keys() == reference.keys() and all(got[k] == reference[k] for k in got)


def test_removing_one_of_two_nodes_mid_run_still_completes(reference, tmp_path, no_ray):
    """A Ray cluster of two nodes (one CPU each, ``ray.cluster_utils.Cluster``); the worker node is removed once
    the first scene is written, while the other node's task runs: Ray Data retries its tasks on the head."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        node = cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False, logging_level="ERROR")
        failure = []

        def run():
            try:
                synthesize(tmp_path / "data", 6, **KW, engine=Engine("ray"))
            except BaseException as e:  # noqa: BLE001 — reported by the test
                failure.append(e)

        thread = threading.Thread(target=run)
        thread.start()
        deadline = time.monotonic() + 120
        while not list((tmp_path / "data").glob("scene_*/meta.json")) and time.monotonic() < deadline:
            time.sleep(0.05)
        cluster.remove_node(node)
        thread.join(timeout=300)
        assert not thread.is_alive() and not failure, failure
    finally:
        ray.shutdown()
        cluster.shutdown()
    got = tree(tmp_path / "data")
    assert got.keys() == reference.keys() and all(got[k] == reference[k] for k in got)
