"""Loading input photographs (OpenCV decoding once, EXIF orientation, centre crop, resize)."""
from __future__ import annotations

import os

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
    """Integer or float image → float32 in [0, 1] (uint8 / 255, uint16 / 65535, floats checked)."""
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
    """Convert an in-memory RGB(A)/grey image to a float RGB tensor, centre-cropped and resized.

    Steps: (1) scale to [0, 1] (uint8 / 255, uint16 / 65535, floats must already lie in [0, 1]);
    (2) grey → RGB by repeating the channel; alpha is composited over a white background,
    rgb·a + (1 − a), before any resampling (so transparent pixels never bleed colour);
    (3) centre-crop to the aspect ratio width/height of ``size`` (the crop keeps the full extent
    along the constrained axis, rounded to whole pixels); (4) resize with ``cv2.INTER_AREA`` when
    shrinking (area averaging, no aliasing) and ``cv2.INTER_LINEAR`` when enlarging (OpenCV's
    INTER_AREA degenerates to nearest-neighbour blocks for integer up-scaling).

    Args:
        array: (H, W), (H, W, 1) grey, (H, W, 2) grey+alpha, (H, W, 3) RGB or (H, W, 4) RGBA;
            uint8, uint16 or float in [0, 1]. Channel order is RGB (not OpenCV's BGR).
        size: (height, width) of the output in pixels; ``None`` keeps the input size (no crop).

    Returns:
        (height, width, 3) float32 tensor in [0, 1], RGB.

    Raises:
        ValueError: bad ``size``, a shape or dtype listed as unsupported above, an empty image,
            or non-finite / out-of-range float values.
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
    """The EXIF Orientation tag (0x0112) of an encoded JPEG (APP1 ``Exif``) or PNG (``eXIf`` chunk).

    Args:
        data: the encoded file's bytes.

    Returns:
        1…8 as in the EXIF 2.3 specification (1 = stored as displayed); 1 when the file is another
        format, carries no EXIF block or no Orientation tag, or the value is out of range.
    """
    tiff = _exif_tiff_block(data)
    if tiff is None or len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return 1
    order = "little" if tiff[:2] == b"II" else "big"
    ifd = int.from_bytes(tiff[4:8], order)
    if ifd + 2 > len(tiff):
        return 1
    for i in range(int.from_bytes(tiff[ifd : ifd + 2], order)):
        entry = tiff[ifd + 2 + 12 * i : ifd + 14 + 12 * i]
        if len(entry) < 12:
            break
        if int.from_bytes(entry[:2], order) == 0x0112:  # type SHORT: the value sits in the first 2 bytes
            value = int.from_bytes(entry[8:10], order)
            return value if 1 <= value <= 8 else 1
    return 1


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
    """(width, height) in pixels as stored in an encoded image's header, read without decoding.

    Reads the PNG ``IHDR`` chunk, the first JPEG start-of-frame segment (SOF0…SOF15), the BMP info
    header, the WebP ``VP8 ``/``VP8L``/``VP8X`` chunk, or the TIFF first IFD (tags 256/257): the
    sizes a decoder would allocate. Stored size, before EXIF orientation (the pixel count is the same).

    Args:
        data: the encoded file's bytes (a prefix suffices for all but JPEGs with large APP segments).

    Returns:
        (width, height), or None when the format is another one or the header is truncated.
    """
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
        ifd = int.from_bytes(data[4:8], order)
        if ifd + 2 > len(data):
            return None
        size: dict[int, int] = {}
        for i in range(int.from_bytes(data[ifd : ifd + 2], order)):
            entry = data[ifd + 2 + 12 * i : ifd + 14 + 12 * i]
            if len(entry) < 12:
                break
            tag, kind = int.from_bytes(entry[:2], order), int.from_bytes(entry[2:4], order)
            if tag in (256, 257):
                size[tag] = int.from_bytes(entry[8:10] if kind == 3 else entry[8:12], order)
        return (size[256], size[257]) if len(size) == 2 else None
    return None


def check_image_pixels(path: str | os.PathLike, width: int, height: int) -> None:
    """Raise :class:`diff4splat.utils.limits.LimitError` if ``width`` × ``height`` exceeds the ``image_pixels``
    limit."""
    check_limit("image_pixels", width * height, f"image {path}: {width}×{height} =")


def apply_orientation(array: np.ndarray, orientation: int) -> np.ndarray:
    """Transform a stored image (H, W, ...) to its displayed orientation (EXIF Orientation 1…8).

    2: mirror left-right; 3: rotate 180°; 4: mirror top-bottom; 5: transpose; 6: rotate 90° clockwise;
    7: transverse (transpose, then rotate 180°); 8: rotate 90° counter-clockwise. Orientations 5…8
    swap H and W.

    Raises:
        ValueError: ``orientation`` not in 1…8.
    """
    if orientation not in range(1, 9):
        raise ValueError(f"orientation must be an EXIF orientation in 1…8, got {orientation!r}")
    transposed = np.swapaxes(array, 0, 1)
    out = {1: array, 2: array[:, ::-1], 3: array[::-1, ::-1], 4: array[::-1],
           5: transposed, 6: transposed[:, ::-1], 7: transposed[::-1, ::-1], 8: transposed[::-1]}[orientation]
    return np.ascontiguousarray(out)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Decode an image file once, as displayed: RGB(A) or grey, EXIF orientation applied.

    Any format OpenCV decodes (PNG, JPEG, TIFF, WebP, BMP, …) in 8 or 16 bits, grey, RGB or RGBA.
    The file is decoded once with ``IMREAD_UNCHANGED`` (which keeps alpha and 16 bits but ignores
    EXIF orientation); the EXIF Orientation tag of a JPEG or PNG (:func:`exif_orientation`) is then
    applied (:func:`apply_orientation`), so ``array.shape[:2]`` is the displayed (H, W) — the size
    that camera intrinsics normalised by the photograph (RealEstate10K) refer to.

    Args:
        path: image file.

    Returns:
        (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA array (channel order RGB, not OpenCV's BGR),
        uint8 or uint16 (or the float dtype of a float TIFF/EXR).

    The pixel count is checked against the ``image_pixels`` limit (:mod:`diff4splat.utils.limits`) from the
    header (:func:`header_size`) before decoding; formats whose header is not parsed are checked after.

    Raises:
        FileNotFoundError: nothing exists at ``path``.
        ValueError: ``path`` is a folder, FIFO or symlink loop (:func:`diff4splat.io.inputs.check_input_file`),
            the file cannot be decoded as an image, or it has more pixels than the ``image_pixels`` limit
            (:class:`diff4splat.utils.limits.LimitError`).
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
    """Read an image file (:func:`read_image`) and preprocess it (:func:`preprocess_image`).

    Alpha is composited over white; the EXIF orientation is applied before the centre crop.

    Args:
        path: image file.
        size: (height, width) in pixels, or ``None`` to keep the file's (displayed) size.

    Returns:
        (height, width, 3) float32 tensor in [0, 1], RGB.

    Raises:
        FileNotFoundError: ``path`` is not an existing file.
        ValueError: the file cannot be decoded as an image, or a bad ``size``.
    """
    size = _check_size(size)
    return preprocess_image(read_image(path), size)
