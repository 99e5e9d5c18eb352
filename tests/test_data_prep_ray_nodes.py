"""A Ray node removed mid-run (``ray.cluster_utils.Cluster``): ``data_prep synth --engine ray`` still completes
with the dataset a clean local run writes, every scene whole exactly once."""
from __future__ import annotations

import threading
import time

import pytest

ray = pytest.importorskip("ray", reason="the ray extra (diff4splat[ray]) is not installed")

from _data_prep_fixtures import tree  # noqa: E402
from ray.cluster_utils import Cluster  # noqa: E402

from data_prep.engine import Engine  # noqa: E402
from data_prep.synth_dataset import synthesize  # noqa: E402

pytestmark = pytest.mark.slow

KW = dict(seed=4, size=32, frames=9, cameras=2, static_ratio=0.3, progress=False)


def test_removing_one_of_two_nodes_mid_run_still_completes(tmp_path):
    """Two nodes of one CPU each; the worker node is removed once the first scene is written, while the other
    node's task runs: Ray Data re-runs its tasks (and those whose outputs were on it) on the head, and the
    idempotent tasks leave finished scenes as they are."""
    synthesize(tmp_path / "reference", 6, **KW)
    assert not ray.is_initialized()
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
    got, want = tree(tmp_path / "data"), tree(tmp_path / "reference")
    assert got.keys() == want.keys() and all(got[k] == want[k] for k in got)
