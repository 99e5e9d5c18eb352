"""``data_prep`` under faults a cluster user meets: a Ray that cannot be reached or started is one line and exit 2
within seconds with nothing written; ``ray://`` (Ray Client) runs the same dataset; SIGTERM of the driver, on Ray
or on the local pool, is one ``interrupted`` line and exit 143 with no process of the command left behind and no
scene written after it; ``curate --quiet`` on Ray prints nothing but its summary."""
from __future__ import annotations

import os
import resource
import signal
import socket
import subprocess
import sys
import time

import pytest

ray = pytest.importorskip("ray", reason="the ray extra (diff4splat[ray]) is not installed")
psutil = pytest.importorskip("psutil")

from _data_prep_fixtures import tree  # noqa: E402

from data_prep.cli import main  # noqa: E402
from data_prep.engine import RAY_CONNECT_TIMEOUT_S, RAY_MIN_ADDRESS_SPACE  # noqa: E402

pytestmark = pytest.mark.slow

SYNTH = ["synth", "--size", "32", "--frames", "9", "--cameras", "2", "--seed", "4", "--quiet"]


def _one_line(capsys, argv: list[str], needle: str) -> float:
    t0 = time.monotonic()
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("data_prep: error: ") and needle in err, err
    return time.monotonic() - t0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two scenes made on the local engine: curate's input, and the bytes every engine must write."""
    root = tmp_path_factory.mktemp("data") / "data"
    assert main([*SYNTH, "--scenes", "2", "--out", str(root)]) == 0
    return root


@pytest.mark.parametrize("address", ["127.0.0.1:1", "ray://127.0.0.1:1"])
def test_an_address_nobody_answers_is_refused_at_once_and_writes_nothing(tmp_path, capsys, dataset, address):
    port = _free_port()  # closed: the connection is refused
    address = address.replace(":1", f":{port}")
    took = _one_line(capsys, [*SYNTH, "--scenes", "1", "--out", str(tmp_path / "o"), "--engine", "ray",
                              "--ray-address", address], f"--ray-address {address}: no Ray cluster reached there")
    took += _one_line(capsys, ["curate", str(dataset), str(tmp_path / "c"), "--engine", "ray", "--ray-address",
                               address, "--quiet"], "--ray-address")
    assert took < 2 * RAY_CONNECT_TIMEOUT_S and sorted(tmp_path.iterdir()) == []


def test_auto_without_a_running_cluster_is_one_line(tmp_path, capsys, monkeypatch):
    """``auto`` on a machine where Ray finds no cluster: its lookup (the address file of a ``ray start`` and any
    running ``gcs_server``, which includes the Rays of the suite's other worker) is made to find none."""
    monkeypatch.delenv("RAY_ADDRESS", raising=False)

    def no_gcs():
        return []

    no_gcs.cache_clear = lambda: None  # ray.init clears the cache of the function it replaces
    monkeypatch.setattr(ray._private.services, "find_gcs_addresses", no_gcs)
    monkeypatch.setattr(ray._private.services, "find_bootstrap_address", lambda temp_dir: None)
    _one_line(capsys, [*SYNTH, "--scenes", "1", "--out", str(tmp_path / "o"), "--engine", "ray", "--ray-address",
                       "auto"], "--ray-address auto: Could not find any running Ray instance")
    assert sorted(tmp_path.iterdir()) == []


def test_an_address_space_too_small_for_a_ray_is_refused_before_it_starts(tmp_path):
    """``ulimit -v`` below what a Ray's processes need: refused in one line; at 8 GB (where Ray's own store, 30 % of
    the RAM, fails to map on a large machine) the store is sized to the limit and the run completes."""
    def limit(n_bytes):
        return lambda: resource.setrlimit(resource.RLIMIT_AS, (n_bytes, n_bytes))

    argv = [sys.executable, "-m", "data_prep.cli", *SYNTH, "--scenes", "1", "--engine", "ray"]
    small = subprocess.run([*argv, "--out", str(tmp_path / "small")], preexec_fn=limit(RAY_MIN_ADDRESS_SPACE // 2),
                           capture_output=True, text=True, timeout=120)
    assert small.returncode == 2 and small.stderr.count("\n") == 1, small.stderr
    assert "ulimit -v" in small.stderr and "--engine local" in small.stderr
    assert not (tmp_path / "small").exists()
    ok = subprocess.run([*argv, "--out", str(tmp_path / "ok")], preexec_fn=limit(8 * 10**9), capture_output=True,
                        text=True, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "ok" / "scene_00000" / "meta.json").is_file()


def test_ray_client_address_runs_the_local_dataset(tmp_path, capsys, dataset):
    """``--ray-address ray://host:port`` (the ``[ray]`` extra installs Ray's client): the dataset runs as a task on
    the cluster and writes the bytes of the local engine."""
    pytest.importorskip("grpc", reason="Ray's client (grpcio) is not installed")
    from ray.cluster_utils import Cluster

    port = _free_port()
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2, "ray_client_server_port": port})
    try:
        deadline = time.monotonic() + 120  # the client server starts after the head, and slower on a loaded machine
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "Ray's client server did not start"
                time.sleep(0.2)
        for _ in range(3):  # Ray's proxier starts a server per client; on a loaded machine that can time out, or
            # the server dies before the proxier reads its command line (psutil.ZombieProcess)
            code = main([*SYNTH, "--scenes", "2", "--out", str(tmp_path / "o"), "--engine", "ray",
                         "--ray-address", f"ray://127.0.0.1:{port}"])
            err = capsys.readouterr().err
            if not any(m in err for m in ("Starting Ray client server failed", "Initialization failure from server")):
                break
    finally:
        cluster.shutdown()
    assert code == 0 and err == "", err
    got, want = tree(tmp_path / "o"), tree(dataset)
    assert got.keys() == want.keys() and all(got[k] == want[k] for k in got)


def test_curate_on_ray_is_quiet_with_quiet(tmp_path, dataset):
    run = subprocess.run([sys.executable, "-m", "data_prep.cli", "curate", str(dataset), str(tmp_path / "c"),
                          "--engine", "ray", "--workers", "2", "--quiet"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and run.stderr == "", run.stderr
    assert run.stdout.startswith("curated 2 scene(s)")


def _descendants(pid: int) -> list[psutil.Process]:
    return psutil.Process(pid).children(recursive=True)


@pytest.mark.parametrize("engine", [["--engine", "local", "--workers", "2"], ["--engine", "ray", "--workers", "2"]])
def test_sigterm_of_the_driver_ends_its_workers_with_it(tmp_path, engine):
    """SIGTERM once scenes are being written: exit 143, one ``interrupted`` line, every process the command started
    (pool workers, Ray's GCS, raylet and workers) gone within seconds, no scene written after the exit."""
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "data_prep.cli", *SYNTH, "--scenes", "40", "--out", str(out),
                             *engine], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not (out / "scene_00001" / "meta.json").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else "timeout"
        time.sleep(0.05)
    workers = _descendants(proc.pid)
    assert workers
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and err == "data_prep: interrupted\n", (proc.returncode, err)
    scenes = sorted(os.listdir(out))
    gone, alive = psutil.wait_procs(workers, timeout=15)
    assert not alive, [p.info for p in alive]
    time.sleep(1)
    assert sorted(os.listdir(out)) == scenes and len(scenes) < 40
    for name in scenes:  # a scene folder is whole (written beside and renamed); a killed one's temporary is hidden
        assert name.startswith(".") or (out / name / "meta.json").is_file(), name
