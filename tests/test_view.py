"""Tests of diff4splat/view.py (``diff4splat view``): served on 127.0.0.1 only, the full scene (not the
size-reduced embedded copy), files of the folder, clear errors, Ctrl-C stops it."""
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import urllib.request

import pytest
from helpers import moving_patch_scene

from diff4splat.io.output import write_scene_folder
from diff4splat.view import DATA_PREFIX, HOST, folder_payload, make_server


def _folder(tmp_path, **kw):
    import torch

    scene, cams = moving_patch_scene(n=120, **kw)
    T, H, W = len(cams), cams.height, cams.width
    out = tmp_path / "out"
    write_scene_folder(out, scene, cams, torch.zeros(T, H, W, 3), torch.ones(T, H, W), torch.ones(T, H, W), {})
    return out, scene


@pytest.fixture
def served(tmp_path):
    out, scene = _folder(tmp_path, sh_degree=1)
    server = make_server(out, 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield out, scene, server.server_address[1]
    server.shutdown()
    server.server_close()


def _get(port, path, host=HOST):
    with urllib.request.urlopen(f"http://{host}:{port}{path}", timeout=10) as r:
        return r.status, r.read()


def test_serves_the_full_scene_and_the_folder(served):
    out, scene, port = served
    status, page = _get(port, "/")
    assert status == 200 and b'id="d4s-ply"' not in page  # the data is fetched, not embedded
    cfg = json.loads(page.split(b'id="d4s-config">')[1].split(b"</script>")[0])
    assert cfg["fullUrl"] == DATA_PREFIX and cfg["numGaussians"] == 120 and cfg["note"] == ""
    payload = folder_payload(out)
    assert _get(port, DATA_PREFIX + "scene.ply")[1] == payload.ply
    assert _get(port, DATA_PREFIX + "frames.bin")[1] == payload.frames
    assert _get(port, "/cameras.json")[1] == (out / "cameras.json").read_bytes()
    with pytest.raises(urllib.error.HTTPError):
        _get(port, DATA_PREFIX + "nothing")


def test_listens_on_loopback_127_0_0_1_only(served):
    _, _, port = served
    with socket.create_connection((HOST, port), timeout=5):
        pass
    # another loopback address (all of 127/8 is local on Linux) and this machine's other addresses are refused
    others = {"127.0.0.2"}
    try:
        others |= {a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)} - {HOST}
    except OSError:
        pass
    for addr in others:
        with pytest.raises(OSError):
            socket.create_connection((addr, port), timeout=2).close()


def test_full_scene_even_when_the_page_on_disk_is_reduced(tmp_path):
    from diff4splat.rerender import load_scene_folder
    from diff4splat.viewer.data import payload_bytes
    from diff4splat.viewer.page import write_viewer

    out, scene = _folder(tmp_path, sh_degree=2)
    src = load_scene_folder(out)
    small = write_viewer(out / "viewer.html", src.scene, src.cameras, budget=payload_bytes(120, 0, 5, False, 2))
    assert small.config["shDegree"] == 0
    assert folder_payload(out).config["shDegree"] == 2 and folder_payload(out).reductions == []


@pytest.mark.slow
def test_served_page_loads_the_full_data_in_a_browser(browser, served):
    _, _, port = served
    page = browser.new_page(viewport={"width": 384, "height": 340})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(f"http://{HOST}:{port}/")
    page.wait_for_function("window.d4s && (window.d4s.ready || window.d4s.error)", timeout=60_000)
    assert page.evaluate("d4s.error") is None and page.evaluate("d4s.numGaussians") == 120
    assert page.evaluate("d4s.config.shDegree") == 1 and errors == []
    page.close()


def test_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        make_server(tmp_path / "missing", 0)
    with pytest.raises(FileNotFoundError, match="neither scene.ply"):
        make_server(tmp_path, 0)
    with pytest.raises(ValueError, match="--port"):
        make_server(tmp_path, 70000)


@pytest.mark.slow
def test_cli_prints_the_address_and_stops_on_ctrl_c(tmp_path):
    out, _ = _folder(tmp_path)
    with socket.socket() as s:
        s.bind((HOST, 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "diff4splat.cli", "view", str(out), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line.strip() == f"serving {out} at http://{HOST}:{port}/ (Ctrl-C stops)"
        assert _get(port, "/")[0] == 200
        # the port is now taken: a second server is one line and exit 2
        second = subprocess.run([sys.executable, "-m", "diff4splat.cli", "view", str(out), "--port", str(port)],
                                capture_output=True, text=True, timeout=120)
        assert second.returncode == 2 and len(second.stderr.strip().splitlines()) == 1, second.stderr
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0 and stdout.strip() == "stopped" and stderr == ""
