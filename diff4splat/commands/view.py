"""``diff4splat view DIR [--port P]`` (flags: :func:`register`; the library function: :func:`serve`): serve an
output folder's 4D viewer on 127.0.0.1 only.

``/`` is the viewer (:mod:`diff4splat.io.viewer_page`) with the folder's full scene, fetched from
``/__diff4splat__/scene.ply`` and ``frames.bin`` (computed once at start); a folder without scene.ply serves its own
viewer.html. Otherwise only layout files (:func:`diff4splat.io.scene_folder.is_layout_file`) that are, symlinks
resolved, regular files inside the folder are served, matched on the raw request path; the rest is 404.
"""
from __future__ import annotations

import argparse
import errno
import os
import shutil
import signal
import socket
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from diff4splat.io.scene_folder import SCENE_FILE, is_layout_file, load_scene_folder, meta_background, meta_eps2d
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.io.viewer_data import ViewerPayload, viewer_payload
from diff4splat.io.viewer_page import VIEWER_NAME, viewer_html
from models.hexplane import load_field

__all__ = ["register", "run", "HOST", "DATA_PREFIX", "make_server", "folder_payload", "served_file", "serve"]

HOST = "127.0.0.1"
"""The only address the server listens on."""
DATA_PREFIX = "/__diff4splat__/"
"""URL prefix of the full-size data the served page fetches."""
_CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".json": "application/json", ".png": "image/png",
                  ".mp4": "video/mp4"}
"""Content types of the layout's files; the others are application/octet-stream."""


def folder_payload(folder: str | os.PathLike) -> ViewerPayload:
    """The unreduced viewer payload of an output folder with a scene; raises as
    :func:`diff4splat.io.scene_folder.load_scene_folder`."""
    src = load_scene_folder(folder, load_field=load_field)
    fps = src.meta.get("fps")  # checked by load_scene_folder when present
    return viewer_payload(src.scene, src.cameras, fps=DEFAULT_FPS if fps is None else fps, budget=None,
                          background=meta_background(src.meta), eps2d=meta_eps2d(src.meta))


def served_file(root: Path, url_path: str) -> Path | None:
    """The file of ``root`` (resolved) that the raw path ``url_path`` names (``/`` + a layout file; ``/``:
    viewer.html) if it is, symlinks resolved, a regular file inside ``root``; else None."""
    name = VIEWER_NAME if url_path == "/" else url_path[1:] if url_path.startswith("/") else ""
    if not is_layout_file(name):
        return None
    try:
        target = (root / name).resolve(strict=True)
    except (OSError, RuntimeError):  # missing, a symlink loop, …
        return None
    return target if target.is_relative_to(root) and target.is_file() else None


class _Handler(BaseHTTPRequestHandler):
    root: Path  # the folder, resolved (set by make_server's subclass)
    page: bytes | None = None
    data: dict[str, bytes] = {}
    payload: ViewerPayload | None = None  # what page and data were made from

    def log_message(self, format, *args):  # noqa: A002 (the base class's name): quiet
        pass

    def _headers(self, size: int, kind: str) -> None:
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(size))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()

    def _respond(self, body: bool) -> None:
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        if self.page is not None and path in ("/", "/" + VIEWER_NAME):
            blob, kind = self.page, "text/html; charset=utf-8"
        elif path.startswith(DATA_PREFIX) and path[len(DATA_PREFIX):] in self.data:
            blob, kind = self.data[path[len(DATA_PREFIX):]], "application/octet-stream"
        else:
            file = served_file(self.root, path)
            if file is None:
                return self.send_error(404)
            try:
                f = open(file, "rb")
            except OSError:
                return self.send_error(404)
            with f:
                self._headers(os.fstat(f.fileno()).st_size, _CONTENT_TYPES.get(file.suffix, "application/octet-stream"))
                if body:
                    shutil.copyfileobj(f, self.wfile)
            return None
        self._headers(len(blob), kind)
        if body:
            self.wfile.write(blob)
        return None

    def do_GET(self):  # noqa: N802 (http.server's name)
        self._respond(body=True)

    def do_HEAD(self):  # noqa: N802 (http.server's name)
        self._respond(body=False)


class _Server(ThreadingHTTPServer):
    """http.server's threading server with a listen backlog of ``socket.SOMAXCONN`` (the default 5 drops the SYNs of
    a burst of requests, whose clients then wait for TCP's retransmission: seconds each), quiet about clients that
    hang up mid-response."""

    request_queue_size = socket.SOMAXCONN

    def handle_error(self, request, client_address):
        if isinstance(sys.exc_info()[1], (ConnectionResetError, BrokenPipeError, ConnectionAbortedError)):
            return  # the client left (a page closed, a download stopped): nothing to report
        super().handle_error(request, client_address)


def make_server(folder: str | os.PathLike, port: int = 0) -> ThreadingHTTPServer:
    """A server for ``folder`` bound to 127.0.0.1:``port`` (0: any free port); the caller closes it.
    ``server.RequestHandlerClass.payload`` is the :class:`ViewerPayload` served (None: only viewer.html).
    FileNotFoundError: ``folder`` is not a folder, or holds neither scene.ply nor viewer.html. ValueError: ``port``
    outside 0 … 65535; a malformed file of the folder (named). OSError: the port is taken or needs privileges (the
    message names it and suggests ``--port 0``)."""
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"DIR: {root} is not a folder (give an output folder of generate, fit or render)")
    if not 0 <= port <= 65535:
        raise ValueError(f"--port must be in 0 … 65535, got {port}")
    page, data, payload = None, {}, None
    if (root / SCENE_FILE).exists() or (root / SCENE_FILE).is_symlink():
        payload = folder_payload(root)
        page = viewer_html(payload, f"diff4splat · {root.resolve().name}", full_url=DATA_PREFIX,
                           embed=False).encode("utf-8")
        data = {"scene.ply": payload.ply, **({"frames.bin": payload.frames} if payload.frames is not None else {})}
    elif served_file(root.resolve(), "/") is None:
        raise FileNotFoundError(f"DIR: {root} has neither {SCENE_FILE} nor {VIEWER_NAME} (not an output folder)")
    handler = type("Handler", (_Handler,), {"root": root.resolve(), "page": page, "data": data, "payload": payload})
    try:
        return _Server((HOST, port), handler)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            why = "already in use (another server?); choose another --port, or --port 0 for any free one"
        elif e.errno == errno.EACCES:
            why = "permission denied (ports below 1024 need privileges); choose --port 0 for any free one"
        else:
            raise
        raise OSError(e.errno, why, f"--port {port} ({HOST}:{port})") from None


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def serve(folder: str | os.PathLike, port: int = 8000) -> int:
    """Serve until Ctrl-C or SIGTERM (even in a background job), printing the address first and "stopped" last.
    Returns 0; raises as :func:`make_server`."""
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


def register(sub) -> argparse.ArgumentParser:
    """Add ``view`` and its flags to the ``diff4splat`` subparsers; returns its parser."""
    v = sub.add_parser("view", help="serve an output folder's interactive 4D viewer on 127.0.0.1",
                       description="Serve DIR's viewer (the full scene, never the size-reduced embedded copy) on "
                                   "127.0.0.1 only, and print the address; Ctrl-C stops. viewer.html in DIR "
                                   "also opens without a server (double click).")
    v.add_argument("folder", type=Path, metavar="DIR", help="output folder of `diff4splat generate`, `fit` or `render`")
    v.add_argument("--port", type=int, default=8000, help="TCP port on 127.0.0.1 (default: 8000; 0: any free port)")
    v.set_defaults(func=run)
    return v


def run(args: argparse.Namespace) -> int:
    """Serve the folder's viewer until Ctrl-C (:func:`serve`); returns its exit code."""
    return serve(args.folder, args.port)
