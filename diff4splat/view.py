"""``diff4splat view DIR [--port P]``: serve an output folder's 4D viewer on 127.0.0.1 only.

The page at ``/`` (and ``/viewer.html``) is the viewer (:mod:`diff4splat.viewer`) with the folder's **full**
scene, never reduced to the size budget of the embedded ``viewer.html``: the page fetches the canonical
Gaussians and the keyframes from ``/__diff4splat__/scene.ply`` and ``/__diff4splat__/frames.bin``, which are
computed once at start from the folder's scene.ply, deformation.npz, cameras.json and meta.json
(:func:`diff4splat.rerender.load_scene_folder`). A folder without scene.ply (a ``render`` output) is served
as it is, its own viewer.html at ``/``. Every other path is a file of the folder.

The server binds 127.0.0.1 (loopback only: nothing on another interface can reach it); Ctrl-C stops it.
"""
from __future__ import annotations

import functools
import os
import signal
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from .render.defaults import meta_background, meta_eps2d
from .viewer.data import ViewerPayload, viewer_payload
from .viewer.page import VIEWER_NAME, viewer_html

__all__ = ["HOST", "DATA_PREFIX", "make_server", "folder_payload"]

HOST = "127.0.0.1"
"""The only address the server listens on."""
DATA_PREFIX = "/__diff4splat__/"
"""URL prefix of the full-size data the served page fetches."""


def folder_payload(folder: str | os.PathLike) -> ViewerPayload:
    """The unreduced viewer payload of an output folder of generate, fit or render-with-scene.

    Raises:
        FileNotFoundError / ValueError: as :func:`diff4splat.rerender.load_scene_folder`.
    """
    from .rerender import load_scene_folder

    src = load_scene_folder(folder)
    fps = src.meta.get("fps")
    fps = fps if isinstance(fps, (int, float)) and not isinstance(fps, bool) and fps > 0 else 8
    return viewer_payload(src.scene, src.cameras, fps=fps, budget=None, background=meta_background(src.meta),
                          eps2d=meta_eps2d(src.meta))


class _Handler(SimpleHTTPRequestHandler):
    page: bytes | None = None
    data: dict[str, bytes] = {}

    def log_message(self, format, *args):  # noqa: A002 (the base class's name): quiet
        pass

    def _send(self, body: bytes, kind: str) -> None:
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self):  # noqa: N802 (http.server's name)
        path = self.path.split("?", 1)[0]
        if self.page is not None and path in ("/", "/" + VIEWER_NAME):
            return self._send(self.page, "text/html; charset=utf-8")
        if path.startswith(DATA_PREFIX) and path[len(DATA_PREFIX):] in self.data:
            return self._send(self.data[path[len(DATA_PREFIX):]], "application/octet-stream")
        if path == "/" and self.page is None:
            self.path = "/" + VIEWER_NAME
        return super().do_GET()


def make_server(folder: str | os.PathLike, port: int = 0) -> ThreadingHTTPServer:
    """A server for ``folder`` bound to 127.0.0.1:``port`` (0: any free port; ``server.server_address[1]``).
    Call ``serve_forever()``; the caller closes it.

    Raises:
        FileNotFoundError: ``folder`` is not a folder, or holds neither scene.ply nor viewer.html.
        ValueError: ``port`` outside 0 … 65535; a malformed file of the folder.
        OSError: the port is taken.
    """
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"DIR: {root} is not a folder (give an output folder of generate, fit or render)")
    if not 0 <= port <= 65535:
        raise ValueError(f"--port must be in 0 … 65535, got {port}")
    page, data = None, {}
    if (root / "scene.ply").is_file():
        payload = folder_payload(root)
        page = viewer_html(payload, f"diff4splat · {root.resolve().name}", full_url=DATA_PREFIX,
                           embed=False).encode("utf-8")
        data = {"scene.ply": payload.ply, **({"frames.bin": payload.frames} if payload.frames is not None else {})}
    elif not (root / VIEWER_NAME).is_file():
        raise FileNotFoundError(f"DIR: {root} has neither scene.ply nor {VIEWER_NAME} (not an output folder)")
    handler = type("Handler", (_Handler,), {"page": page, "data": data})
    return ThreadingHTTPServer((HOST, port), functools.partial(handler, directory=str(root)))


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def serve(folder: str | os.PathLike, port: int = 8000) -> int:
    """Serve until Ctrl-C or SIGTERM (prints the address first, "stopped" last). Returns 0.

    SIGINT is handled even where the shell started the process with it ignored (a background job).

    Raises:
        as :func:`make_server`.
    """
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, _interrupt)
    try:
        server = make_server(folder, port)
        try:
            host, bound = server.server_address[:2]
            print(f"serving {folder} at http://{host}:{bound}/ (Ctrl-C stops)", flush=True)
            server.serve_forever()
        finally:
            server.server_close()
    except KeyboardInterrupt:
        print("stopped", flush=True)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
