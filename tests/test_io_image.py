"""Tests for diff4splat.io.image: decoding every image kind, alpha over white, crop/resize, errors."""
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from diff4splat.io import load_image, preprocess_image
from diff4splat.io.image import apply_orientation, exif_orientation, read_image

CHELSEA = Path(__file__).resolve().parents[1] / "examples" / "chelsea.png"


def write(path, array_rgb_or_grey):
    """Write with OpenCV, converting RGB(A) to the BGR(A) order OpenCV files use."""
    a = array_rgb_or_grey
    if a.ndim == 3 and a.shape[-1] == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    elif a.ndim == 3 and a.shape[-1] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_RGBA2BGRA)
    assert cv2.imwrite(str(path), a)
    return path


def test_rgb8_exact_values_and_channel_order(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    out = load_image(write(tmp_path / "a.png", img))
    assert out.dtype == torch.float32 and out.shape == (6, 7, 3)
    torch.testing.assert_close(out, torch.from_numpy(img).float() / 255, atol=1e-7, rtol=0)


def test_grey8_and_grey16(tmp_path):
    grey = np.array([[0, 64], [128, 255]], dtype=np.uint8)
    out = load_image(write(tmp_path / "g.png", grey))
    torch.testing.assert_close(out, (torch.from_numpy(grey).float() / 255)[..., None].expand(2, 2, 3))
    g16 = np.array([[0, 1000], [19661, 65535]], dtype=np.uint16)
    out = load_image(write(tmp_path / "g16.png", g16))
    torch.testing.assert_close(out[..., 1], torch.from_numpy(g16.astype(np.float32)) / 65535)


def test_rgb16_scaled_by_65535(tmp_path):
    img = np.zeros((3, 4, 3), np.uint16)
    img[..., 0], img[..., 1], img[..., 2] = 65535, 32768, 300
    out = load_image(write(tmp_path / "c16.png", img))
    torch.testing.assert_close(out[0, 0], torch.tensor([1.0, 32768 / 65535, 300 / 65535]))


def test_rgba_composited_over_white(tmp_path):
    img = np.zeros((1, 3, 4), np.uint8)
    img[0, :, :3] = [200, 40, 10]
    img[0, :, 3] = [0, 255, 102]  # transparent, opaque, 40 %
    out = load_image(write(tmp_path / "r.png", img))
    c = torch.tensor([200, 40, 10]) / 255
    torch.testing.assert_close(out[0, 0], torch.ones(3))
    torch.testing.assert_close(out[0, 1], c)
    torch.testing.assert_close(out[0, 2], c * 0.4 + 0.6)
    # 16-bit RGBA and in-memory grey+alpha follow the same rule.
    img16 = (img.astype(np.uint16) * 257)
    torch.testing.assert_close(load_image(write(tmp_path / "r16.png", img16)), out)
    ga = np.array([[[100, 0], [100, 255]]], dtype=np.uint8)
    torch.testing.assert_close(preprocess_image(ga)[0, :, 0], torch.tensor([1.0, 100 / 255]))


def test_jpeg_and_exif_orientation(tmp_path):
    img = np.zeros((20, 40, 3), np.uint8)
    img[:, :20] = [255, 0, 0]  # left half red
    img[:, 20:] = [0, 0, 255]  # right half blue
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    plain = load_image(write_bytes(tmp_path / "p.jpg", jpg.tobytes()))
    assert plain.shape == (20, 40, 3) and (plain - torch.from_numpy(img) / 255).abs().mean() < 0.03
    # EXIF orientation 6 (display rotated 90° clockwise): left half ends up on top.
    tiff = _exif_tiff(6)
    app1 = b"\xff\xe1" + struct.pack(">H", 2 + 6 + len(tiff)) + b"Exif\x00\x00" + tiff
    data = jpg.tobytes()
    rotated = load_image(write_bytes(tmp_path / "r.jpg", data[:2] + app1 + data[2:]))
    assert rotated.shape == (40, 20, 3)
    assert rotated[:18, :, 0].mean() > 0.9 and rotated[22:, :, 2].mean() > 0.9


def write_bytes(path, data):
    path.write_bytes(data)
    return path


def test_centre_crop_to_target_aspect(tmp_path):
    wide = np.zeros((20, 40, 3), np.uint8)
    wide[:, :10], wide[:, 10:30], wide[:, 30:] = [0, 255, 0], [255, 0, 0], [0, 0, 255]
    out = load_image(write(tmp_path / "w.png", wide), size=(10, 10))
    torch.testing.assert_close(out, torch.tensor([1.0, 0, 0]).expand(10, 10, 3))
    tall = np.transpose(wide, (1, 0, 2)).copy()
    out = preprocess_image(tall, size=(5, 5))
    torch.testing.assert_close(out, torch.tensor([1.0, 0, 0]).expand(5, 5, 3))
    # Non-integer crop: 3:2 input to 1:1 keeps the central 20 of 30 columns.
    ramp = np.tile(np.arange(30, dtype=np.uint8)[None, :, None], (20, 1, 3))
    out = preprocess_image(ramp, size=(20, 20))
    torch.testing.assert_close(out[0, :, 0], torch.arange(5, 25).float() / 255)


def test_area_downsampling_is_block_mean_and_upsampling_interpolates():
    rng = np.random.default_rng(1)
    img = rng.random((8, 12, 3)).astype(np.float32)
    out = preprocess_image(img, size=(4, 6))
    expect = img.reshape(4, 2, 6, 2, 3).mean(axis=(1, 3))
    torch.testing.assert_close(out, torch.from_numpy(expect), atol=1e-6, rtol=0)
    ramp = np.array([[0.0, 1.0]], np.float32).repeat(2, axis=0)  # (2, 2) grey
    up = preprocess_image(ramp, size=(4, 4))
    torch.testing.assert_close(up[0, :, 0], torch.tensor([0.0, 0.25, 0.75, 1.0]))


def test_real_photograph():
    full = load_image(CHELSEA)
    assert full.shape == (300, 451, 3)
    out = load_image(CHELSEA, size=(64, 96))
    assert out.shape == (64, 96, 3) and out.dtype == torch.float32
    assert 0.0 <= float(out.min()) and float(out.max()) <= 1.0
    # Area resampling preserves the mean colour; the orange cat is red-dominant in RGB order.
    torch.testing.assert_close(out.mean(dim=(0, 1)), full.mean(dim=(0, 1)), atol=0.01, rtol=0)
    m = out.mean(dim=(0, 1))
    assert m[0] > m[1] > m[2]


def test_preprocess_float_and_validation():
    f = np.full((4, 4, 3), 0.25, np.float64)
    torch.testing.assert_close(preprocess_image(f), torch.full((4, 4, 3), 0.25))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        preprocess_image(np.full((4, 4, 3), 2.0, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        preprocess_image(np.full((4, 4, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="shape"):
        preprocess_image(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(ValueError, match="dtype"):
        preprocess_image(np.zeros((4, 4, 3), np.int32))
    with pytest.raises(ValueError, match="empty"):
        preprocess_image(np.zeros((0, 4, 3), np.uint8))
    for size in [(0, 4), (4,), (4.0, 4), "64x64"]:
        with pytest.raises(ValueError, match="size"):
            preprocess_image(np.zeros((4, 4, 3), np.uint8), size=size)


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_image(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="is a folder, not a file"):
        load_image(tmp_path)
    (tmp_path / "bad.png").write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="decode"):
        load_image(tmp_path / "bad.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="decode"):
        load_image(tmp_path / "empty.png")
    with pytest.raises(ValueError, match="size"):
        load_image(CHELSEA, size=(64, -1))


def _exif_tiff(orientation: int) -> bytes:
    """A little-endian TIFF block whose IFD0 holds only the Orientation tag (SHORT)."""
    return (b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1)
            + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack("<I", 0))


def _jpeg_with_orientation(rgb: np.ndarray, orientation: int) -> bytes:
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    body = b"Exif\x00\x00" + _exif_tiff(orientation)
    data = jpg.tobytes()
    return data[:2] + b"\xff\xe1" + struct.pack(">H", 2 + len(body)) + body + data[2:]


@pytest.mark.parametrize("orientation", range(1, 9))
def test_read_image_decodes_once_and_orients_like_opencv(tmp_path, orientation, monkeypatch):
    """All eight EXIF orientations agree with OpenCV's own oriented decode (IMREAD_COLOR), with one decode."""
    rng = np.random.default_rng(orientation)
    rgb = cv2.resize(rng.integers(0, 256, (3, 5, 3), dtype=np.uint8), (40, 24), interpolation=cv2.INTER_NEAREST)
    path = write_bytes(tmp_path / "o.jpg", _jpeg_with_orientation(rgb, orientation))
    reference = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    calls = []
    real = cv2.imdecode
    monkeypatch.setattr(cv2, "imdecode", lambda *a: calls.append(1) or real(*a))
    got = read_image(path)
    assert len(calls) == 1
    assert exif_orientation(path.read_bytes()) == orientation
    assert got.shape == reference.shape == ((24, 40, 3) if orientation <= 4 else (40, 24, 3))
    np.testing.assert_array_equal(got, reference)


def test_png_exif_orientation_applies_to_rgba_and_16_bit(tmp_path):
    """IMREAD_UNCHANGED (needed for alpha and 16 bits) ignores EXIF: the tag is applied after decoding."""
    rgba = np.zeros((6, 10, 4), np.uint16)
    rgba[..., 0] = np.arange(10) * 6000  # red ramps left → right
    rgba[..., 3] = 65535
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    assert ok
    data = png.tobytes()
    payload = _exif_tiff(8)  # rotate 90° counter-clockwise: the ramp runs bottom → top
    chunk = struct.pack(">I", len(payload)) + b"eXIf" + payload + struct.pack(">I", zlib.crc32(b"eXIf" + payload))
    path = write_bytes(tmp_path / "o.png", data[:33] + chunk + data[33:])  # after the 25-byte IHDR chunk
    got = read_image(path)
    assert got.dtype == np.uint16 and got.shape == (10, 6, 4)
    np.testing.assert_array_equal(got, np.rot90(rgba, k=1))
    assert load_image(path).shape == (10, 6, 3)


def test_apply_orientation_inverts_and_rejects_bad_values():
    a = np.arange(12).reshape(3, 4)
    np.testing.assert_array_equal(apply_orientation(a, 6), np.rot90(a, k=-1))
    np.testing.assert_array_equal(apply_orientation(apply_orientation(a, 6), 8), a)
    np.testing.assert_array_equal(apply_orientation(apply_orientation(a, 5), 5), a)
    assert exif_orientation(b"not an image") == 1
    with pytest.raises(ValueError, match="orientation"):
        apply_orientation(a, 9)
