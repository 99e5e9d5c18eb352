"""Loading input photographs (OpenCV decoding once, EXIF orientation, centre crop, resize)."""
from __future__ import annotations

import os
from collections.abc import Iterator

import cv2
import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras.intrinsics import center_crop_box
from diff4splat.io.inputs import check_input_file
from diff4splat.utils.errors import quiet_c_stderr
from diff4splat.utils.limits import check_limit

__all__ = ["load_image", "read_image", "preprocess_image", "exif_orientation", "apply_orientation",
           "header_size"]


def _check_size(size: tuple[int, int] | None) -> tuple[int, int] | None:
    if size is None:
        return None
    ok = isinstance(size, (tuple, list)) and len(size) == 2 and all(
        isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size
    )
    if not ok:
        raise ValueError(f"size must be (height, width) with positive ints, got {size!r}")
    return int(size[0]), int(size[1])


def _to_unit_float(array: np.ndarray) -> np.ndarray:
    """uint8 / 255, uint16 / 65535 or a float image checked to lie in [0, 1] → float32."""
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype == np.uint16:
        return array.astype(np.float32) / 65535.0
    if np.issubdtype(array.dtype, np.floating):
        out = array.astype(np.float32)
        if not np.isfinite(out).all():
            raise ValueError("image contains NaN or inf values")
        lo, hi = float(out.min()), float(out.max())
        if lo < -1e-6 or hi > 1 + 1e-6:
            raise ValueError(f"a floating-point image must lie in [0, 1], got range [{lo:.4g}, {hi:.4g}]")
        return np.clip(out, 0.0, 1.0)
    raise ValueError(f"image dtype must be uint8, uint16 or floating point, got {array.dtype}")


def preprocess_image(array: np.ndarray, size: tuple[int, int] | None = None) -> Tensor:
    """An in-memory image as a (height, width, 3) float32 RGB tensor in [0, 1]: scaled to [0, 1], grey repeated to
    RGB, alpha composited over white (rgb·a + (1 − a)) before any resampling, centre-cropped to the aspect ratio of
    ``size`` (:func:`~diff4splat.cameras.intrinsics.center_crop_box`) and resized with ``cv2.INTER_AREA`` when
    shrinking, ``cv2.INTER_LINEAR`` when enlarging (INTER_AREA gives blocks there).

    Args:
        array: (H, W), (H, W, 1) grey, (H, W, 2) grey+alpha, (H, W, 3) RGB or (H, W, 4) RGBA; uint8, uint16 or
            float in [0, 1].
        size: (height, width) of the output in pixels; None keeps the input size (no crop).

    Raises:
        ValueError: bad ``size``, another shape or dtype, an empty image, non-finite or out-of-range floats.
    """
    size = _check_size(size)
    array = np.asarray(array)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"image must have shape (H, W) or (H, W, C) with C in 1..4, got {array.shape}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"image is empty, shape {array.shape}")
    img = _to_unit_float(array)
    c = img.shape[-1]
    color = img[..., :1].repeat(3, axis=-1) if c in (1, 2) else img[..., :3]
    if c in (2, 4):
        alpha = img[..., -1:]
        color = color * alpha + (1.0 - alpha)  # composite over white
    if size is not None:
        h, w = size
        y0, x0, ch, cw = center_crop_box(*color.shape[:2], h, w)
        color = color[y0 : y0 + ch, x0 : x0 + cw]
        if (ch, cw) != (h, w):
            interp = cv2.INTER_AREA if (h <= ch and w <= cw) else cv2.INTER_LINEAR
            color = cv2.resize(np.ascontiguousarray(color), (w, h), interpolation=interp)
    return torch.from_numpy(np.ascontiguousarray(np.clip(color, 0.0, 1.0), dtype=np.float32))


def exif_orientation(data: bytes) -> int:
    """The EXIF Orientation tag (0x0112, 1…8, 1 = stored as displayed) of an encoded JPEG (APP1 ``Exif``) or PNG
    (``eXIf`` chunk); 1 for another format, no tag, or a value out of range."""
    tiff = _exif_tiff_block(data)
    if tiff is None or len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return 1
    order = "little" if tiff[:2] == b"II" else "big"
    for entry in _ifd_entries(tiff, order):
        if int.from_bytes(entry[:2], order) == 0x0112:  # type SHORT: the value sits in the first 2 bytes
            value = int.from_bytes(entry[8:10], order)
            return value if 1 <= value <= 8 else 1
    return 1


def _ifd_entries(tiff: bytes, order: str) -> Iterator[bytes]:
    """The 12-byte entries of the first IFD of a TIFF-structured block, up to where it is truncated."""
    ifd = int.from_bytes(tiff[4:8], order)
    if ifd + 2 > len(tiff):
        return
    for i in range(int.from_bytes(tiff[ifd : ifd + 2], order)):
        entry = tiff[ifd + 2 + 12 * i : ifd + 14 + 12 * i]
        if len(entry) < 12:
            return
        yield entry


def _exif_tiff_block(data: bytes) -> bytes | None:
    """The TIFF-structured EXIF block of a JPEG or PNG file, or None."""
    if data[:2] == b"\xff\xd8":  # JPEG: marker segments until start of scan
        pos = 2
        while pos + 4 <= len(data) and data[pos] == 0xFF:
            marker = data[pos + 1]
            if marker == 0xDA:
                break
            length = int.from_bytes(data[pos + 2 : pos + 4], "big")
            if marker == 0xE1 and data[pos + 4 : pos + 10] == b"Exif\x00\x00":
                return data[pos + 10 : pos + 2 + length]
            pos += 2 + length
        return None
    if data[:8] == b"\x89PNG\r\n\x1a\n":  # PNG: length, type, payload, CRC
        pos = 8
        while pos + 8 <= len(data):
            length = int.from_bytes(data[pos : pos + 4], "big")
            kind = data[pos + 4 : pos + 8]
            if kind == b"eXIf":
                return data[pos + 8 : pos + 8 + length]
            if kind in (b"IDAT", b"IEND"):
                break
            pos += 12 + length
    return None


_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # start-of-frame markers (not DHT, JPG, DAC)


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels as stored (before EXIF orientation) in an encoded image's header, without decoding:
    PNG ``IHDR``, the first JPEG start-of-frame segment, the BMP info header, WebP ``VP8 ``/``VP8L``/``VP8X``, TIFF's
    first IFD (tags 256/257). None for another format or a truncated header. A prefix of the file suffices (but for
    JPEGs with large APP segments)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) >= 24 and data[12:16] == b"IHDR":
            return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        return None
    if data[:2] == b"\xff\xd8":
        pos = 2
        while pos + 4 <= len(data):
            if data[pos] != 0xFF:
                return None
            marker = data[pos + 1]
            if marker == 0xFF:  # fill byte
                pos += 1
                continue
            if marker in (0x01, *range(0xD0, 0xD9)):  # no length field
                pos += 2
                continue
            if marker in _JPEG_SOF:
                if pos + 9 > len(data):
                    return None
                return int.from_bytes(data[pos + 7 : pos + 9], "big"), int.from_bytes(data[pos + 5 : pos + 7], "big")
            if marker in (0xD9, 0xDA):  # end of image / start of scan before any frame header
                return None
            pos += 2 + int.from_bytes(data[pos + 2 : pos + 4], "big")
        return None
    if data[:2] == b"BM" and len(data) >= 26:
        return (abs(int.from_bytes(data[18:22], "little", signed=True)),
                abs(int.from_bytes(data[22:26], "little", signed=True)))
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP" and len(data) >= 30:
        chunk = data[12:16]
        if chunk == b"VP8X":
            return int.from_bytes(data[24:27], "little") + 1, int.from_bytes(data[27:30], "little") + 1
        if chunk == b"VP8L":
            bits = int.from_bytes(data[21:25], "little")
            return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
        if chunk == b"VP8 ":
            return int.from_bytes(data[26:28], "little") & 0x3FFF, int.from_bytes(data[28:30], "little") & 0x3FFF
        return None
    if data[:4] in (b"II*\x00", b"MM\x00*") and len(data) >= 8:
        order = "little" if data[:2] == b"II" else "big"
        size: dict[int, int] = {}
        for entry in _ifd_entries(data, order):
            tag, kind = int.from_bytes(entry[:2], order), int.from_bytes(entry[2:4], order)
            if tag in (256, 257):
                size[tag] = int.from_bytes(entry[8:10] if kind == 3 else entry[8:12], order)
        return (size[256], size[257]) if len(size) == 2 else None
    return None


def check_image_pixels(path: str | os.PathLike, width: int, height: int) -> None:
    """LimitError if ``width`` × ``height`` exceeds the ``image_pixels`` limit."""
    check_limit("image_pixels", width * height, f"image {path}: {width}×{height} =")


def apply_orientation(array: np.ndarray, orientation: int) -> np.ndarray:
    """A stored image (H, W, ...) in its displayed orientation (EXIF 1…8: 2 mirror left-right, 3 rotate 180°,
    4 mirror top-bottom, 5 transpose, 6 rotate 90° clockwise, 7 transverse, 8 rotate 90° counter-clockwise);
    ValueError for another ``orientation``."""
    if orientation not in range(1, 9):
        raise ValueError(f"orientation must be an EXIF orientation in 1…8, got {orientation!r}")
    transposed = np.swapaxes(array, 0, 1)
    out = {1: array, 2: array[:, ::-1], 3: array[::-1, ::-1], 4: array[::-1],
           5: transposed, 6: transposed[:, ::-1], 7: transposed[::-1, ::-1], 8: transposed[::-1]}[orientation]
    return np.ascontiguousarray(out)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Decode an image file once (OpenCV ``IMREAD_UNCHANGED``: PNG, JPEG, TIFF, WebP, BMP, …) with its EXIF orientation
    applied (:func:`exif_orientation`), so ``shape[:2]`` is the displayed (H, W).

    Returns:
        (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA, uint8 or uint16 (or a float TIFF/EXR's dtype).

    Raises:
        FileNotFoundError / ValueError: not a regular file (:func:`check_input_file`); not decodable; more pixels than
            the ``image_pixels`` limit (LimitError; checked from the header before decoding where it is parsed).
    """
    path = check_input_file(path, "image")
    data = np.fromfile(path, dtype=np.uint8)
    raw = data.tobytes()
    stored = header_size(raw)
    if stored is not None:
        check_image_pixels(path, *stored)
    with quiet_c_stderr():  # libpng/libjpeg warnings (e.g. a bad iCCP profile) would add stderr lines
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ValueError(f"could not decode {path} as an image (OpenCV)")
    check_image_pixels(path, img.shape[1], img.shape[0])
    if img.ndim == 3 and img.shape[-1] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[-1] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return apply_orientation(img, exif_orientation(raw))


def load_image(path: str | os.PathLike, size: tuple[int, int] | None = None) -> Tensor:
    """:func:`preprocess_image` of :func:`read_image`: (height, width, 3) float32 RGB in [0, 1] (``size`` None: the
    displayed size). Raises as those two."""
    size = _check_size(size)
    return preprocess_image(read_image(path), size)
