"""Tests for diff4splat.io.video: MP4 (mp4v) round trips, RGB order, PNG writing, errors."""
import cv2
import numpy as np
import pytest
import torch

from diff4splat.io import load_video, save_image, save_video, to_uint8


def smooth_frames(T=6, H=48, W=64):
    y, x = np.mgrid[:H, :W]
    frames = [np.stack([(x * 3 + 8 * t) % 256, y * 4, np.full_like(x, 200 - 20 * t)], -1) for t in range(T)]
    return np.stack(frames).astype(np.uint8)


def test_uint8_video_roundtrip(tmp_path):
    frames = smooth_frames()
    save_video(tmp_path / "v.mp4", frames, fps=8)
    out = load_video(tmp_path / "v.mp4")
    assert out.shape == frames.shape and out.dtype == np.uint8
    err = np.abs(out.astype(float) - frames.astype(float))
    assert err.mean() < 8  # lossy MPEG-4 Part 2; a channel swap or wrong frame would give ≫ 30
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(8.0)
    # MPEG-4 Part 2 in an ISO-BMFF container (FFmpeg reports the codec tag as FMP4).
    assert int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") in (b"mp4v", b"FMP4")
    assert (tmp_path / "v.mp4").read_bytes()[4:8] == b"ftyp"
    cap.release()
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]


def test_float_frames_are_rgb_and_clipped(tmp_path):
    T, H, W = 3, 32, 32
    frames = torch.zeros(T, H, W, 3)
    frames[0, ..., 0] = 1.0  # red
    frames[1, ..., 1] = 1.2  # green, above 1 → clipped
    frames[2, ..., 2] = 1.0  # blue
    frames[2, ..., 0] = -0.3  # clipped to 0
    save_video(tmp_path / "c.mp4", frames, fps=4)
    out = load_video(tmp_path / "c.mp4").astype(float).mean(axis=(1, 2))
    for t in range(3):
        assert out[t].argmax() == t and out[t, t] > 200 and np.delete(out[t], t).max() < 40


def test_single_frame_video(tmp_path):
    save_video(tmp_path / "one.mp4", np.full((1, 16, 16, 3), 128, np.uint8))
    out = load_video(tmp_path / "one.mp4")
    assert out.shape == (1, 16, 16, 3) and abs(out.mean() - 128) < 8


def test_video_errors(tmp_path):
    ok = np.zeros((2, 16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="mp4"):
        save_video(tmp_path / "v.avi", ok)
    with pytest.raises(ValueError, match="fps"):
        save_video(tmp_path / "v.mp4", ok, fps=0)
    with pytest.raises(ValueError, match="even"):
        save_video(tmp_path / "v.mp4", np.zeros((2, 15, 16, 3), np.uint8))
    with pytest.raises(ValueError, match="frames must have shape"):
        save_video(tmp_path / "v.mp4", np.zeros((16, 16, 3), np.uint8))
    with pytest.raises(ValueError, match="NaN"):
        save_video(tmp_path / "v.mp4", np.full((2, 16, 16, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="uint8 or floating"):
        save_video(tmp_path / "v.mp4", np.zeros((2, 16, 16, 3), np.int32))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError):
        load_video(tmp_path / "none.mp4")
    (tmp_path / "bad.mp4").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="decode"):
        load_video(tmp_path / "bad.mp4")


def test_to_uint8_rounds():
    x = np.array([0.0, 0.5 / 255, 1.49 / 255, 0.5, 1.0, 2.0, -1.0])
    assert to_uint8(x).tolist() == [0, 0, 1, 128, 255, 255, 0]
    b = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.bfloat16)  # no numpy bfloat16: widened, same bytes
    assert to_uint8(b).tolist() == to_uint8(b.float()).tolist() == [0, 64, 128, 255]
    u = np.arange(5, dtype=np.uint8)
    assert to_uint8(u) is u


def test_save_image_png_is_lossless_and_rgb(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)
    save_image(tmp_path / "a.png", img)
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(back[..., ::-1], img)  # file is BGR, so the RGB input is reversed
    save_image(tmp_path / "f.png", torch.from_numpy(img).float() / 255)
    assert np.array_equal(cv2.imread(str(tmp_path / "f.png"))[..., ::-1], img)
    grey = rng.integers(0, 256, (5, 4), dtype=np.uint8)
    save_image(tmp_path / "g.png", grey)
    assert np.array_equal(cv2.imread(str(tmp_path / "g.png"), cv2.IMREAD_UNCHANGED), grey)
    rgba = rng.integers(0, 256, (5, 4, 4), dtype=np.uint8)
    save_image(tmp_path / "r.png", rgba)
    back = cv2.imread(str(tmp_path / "r.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(cv2.cvtColor(back, cv2.COLOR_BGRA2RGBA), rgba)
    with pytest.raises(ValueError, match="suffix"):
        save_image(tmp_path / "x.notanimage", img)
    with pytest.raises(ValueError, match="image must have shape"):
        save_image(tmp_path / "x.png", np.zeros((4, 4, 2), np.uint8))
