"""Point tracks of the photograph from a file the user made elsewhere (``generate --tracks``): a ``.npy`` array
(N, T, 2) of pixel positions (x, y) of N points over T evenly spaced clip times, frame 0 the photograph's (the layout
TAPIR writes; CoTracker's (1, T, N, 2) is ``tracks[0].transpose(1, 0, 2)``)."""
from __future__ import annotations

import os

import numpy as np

from diff4splat.io.inputs import check_input_file

__all__ = ["read_tracks"]


def read_tracks(path: str | os.PathLike, what: str = "--tracks") -> np.ndarray:
    """The (N, T, 2) float64 tracks in ``path`` (module docstring); ``what`` names the flag in messages.

    Raises:
        FileNotFoundError / ValueError: naming the file: missing or not a file, not a ``.npy`` array (pickles are not
            read), not numeric (N ≥ 1, T ≥ 2, 2), or holding a NaN or inf.
    """
    path = check_input_file(path, what)
    try:
        tracks = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{what}: {path} is not a readable .npy array ({e})") from None
    if (tracks.ndim != 3 or tracks.shape[0] < 1 or tracks.shape[1] < 2 or tracks.shape[2] != 2
            or not np.issubdtype(tracks.dtype, np.number)):
        raise ValueError(f"{what}: {path} must hold N × T × 2 pixel positions (N ≥ 1 points, T ≥ 2 times), got "
                         f"{tracks.dtype} {tracks.shape}")
    tracks = tracks.astype(np.float64)
    if not np.isfinite(tracks).all():
        raise ValueError(f"{what}: {path} holds NaN or infinite positions")
    return tracks
