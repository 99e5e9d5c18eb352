"""``viewer.html``: one self-contained page (opens from ``file://``): this module's HTML, the bundled renderer
(``viewer_assets/viewer.js``, built from ``viewer_js/``; licences in ``viewer_assets/LICENSES.txt``) and the payload of
:mod:`diff4splat.io.viewer_data` as base64 in ``<script>`` elements. docs/DESIGN.md, "Viewer".
"""
from __future__ import annotations

import base64
import html
import json
import os
from importlib import resources

from diff4splat.cameras.path import CameraPath
from diff4splat.io.atomic import atomic_output_path
from diff4splat.io.video import DEFAULT_FPS
from diff4splat.io.viewer_data import VIEWER_BUDGET_BYTES, ViewerPayload, viewer_payload
from diff4splat.render.settings import BACKGROUND, EPS2D
from diff4splat.scene.dynamic import DynamicGaussians

__all__ = ["viewer_html", "write_viewer", "bundle_js", "VIEWER_NAME"]

VIEWER_NAME = "viewer.html"
"""File name of the page in every output folder."""

_STYLE = """
html, body { margin: 0; background: #111; color: #ddd; font: 13px system-ui, sans-serif; overflow: hidden; }
#view { display: block; margin: 0 auto; }
#ui { padding: 6px 10px; display: flex; gap: 10px; align-items: center; flex-wrap: wrap; }
#time { flex: 1; min-width: 120px; }
#note { color: #fc6; }
"""


def bundle_js() -> str:
    """The bundled page code (three.js + Spark + the viewer), shipped as package data."""
    return resources.files("diff4splat.io").joinpath("viewer_assets/viewer.js").read_text(encoding="utf-8")


def _script(kind: str, ident: str, text: str) -> str:
    return f'<script type="{kind}" id="{ident}">{text}</script>\n'


def viewer_html(payload: ViewerPayload, title: str = "diff4splat viewer", *, full_url: str | None = None,
                embed: bool = True) -> str:
    """The page (module docstring) as a str; ``title`` is HTML-escaped.

    Args:
        payload: the scene's bytes and page config.
        full_url: where ``diff4splat view`` serves the data (``scene.ply``, ``frames.bin``), which the page then
            fetches instead of the embedded copy; None reads the embedded copy.
        embed: put ``scene.ply`` (and ``frames.bin``, if any) into the page, base64 encoded.

    Raises:
        ValueError: ``embed`` false without ``full_url``.
    """
    if not embed and full_url is None:
        raise ValueError("embed=False needs full_url (the page must get its data somewhere)")
    config = dict(payload.config, fullUrl=full_url)
    # "</" cannot occur in base64; JSON gets "<" escaped so nothing closes the script element early
    cfg = json.dumps(config).replace("<", "\\u003c")
    parts = [
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><link rel=\"icon\" href=\"data:,\">",
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>\n",
        '<canvas id="view"></canvas>\n<div id="ui" hidden>',
        '<select id="camera" title="jump to a camera of the path"></select>',
        '<span id="timecontrols"><button id="play">play</button>',
        '<input id="time" type="range" min="0" max="1000" value="0"><span id="tlabel"></span></span>',
        f'<span>{payload.config["numGaussians"]:,} Gaussians</span><span id="note"></span></div>\n',
        _script("application/json", "d4s-config", cfg),
    ]
    if embed:
        parts.append(_script("application/octet-stream", "d4s-ply", base64.b64encode(payload.ply).decode("ascii")))
    if embed and payload.frames is not None:
        frames = base64.b64encode(payload.frames).decode("ascii")
        parts.append(_script("application/octet-stream", "d4s-frames", frames))
    parts.append("<script>\n" + bundle_js().replace("</script", "<\\/script") + "\n</script>\n</body></html>\n")
    return "".join(parts)


def write_viewer(path: str | os.PathLike, scene: DynamicGaussians, cameras: CameraPath, *, fps: float = DEFAULT_FPS,
                 budget: int | None = VIEWER_BUDGET_BYTES, title: str = "diff4splat viewer",
                 background: tuple[float, float, float] = BACKGROUND, eps2d: float = EPS2D) -> ViewerPayload:
    """Write ``viewer.html`` for ``scene`` seen along ``cameras`` (the first one is where it opens),
    atomically. Returns the payload (its ``config`` holds the sizes and any reduction).

    Raises:
        ValueError: see :func:`diff4splat.io.viewer_data.viewer_payload`.
    """
    payload = viewer_payload(scene, cameras, fps=fps, budget=budget, background=background, eps2d=eps2d)
    text = viewer_html(payload, title)
    with atomic_output_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    return payload
