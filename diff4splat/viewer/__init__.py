"""The interactive 4D viewer: ``viewer.html`` in every output folder, ``diff4splat view`` (docs/DESIGN.md,
"Viewer"). :mod:`.data` computes what the page shows, :mod:`.page` writes the page, :mod:`.serve` serves a
folder on 127.0.0.1."""
from .data import VIEWER_BUDGET_BYTES, ViewerPayload, viewer_payload
from .page import VIEWER_NAME, viewer_html, write_viewer

__all__ = ["VIEWER_BUDGET_BYTES", "VIEWER_NAME", "ViewerPayload", "viewer_payload", "viewer_html", "write_viewer"]
