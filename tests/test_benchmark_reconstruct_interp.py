"""benchmarks/reconstruct_interp.py and benchmarks/_common.py's strip: the 2D flow-interpolation baseline the 4D
scene is measured against, and the frame strip the docs show."""
import torch
from helpers import TEXTURES, benchmark_module

from diff4splat.io import load_image

interp = benchmark_module("reconstruct_interp")
common = benchmark_module("_common")


def _shifted(image: torch.Tensor, dx: int, size: int = 64) -> torch.Tensor:
    return image[8:8 + size, 16 - dx:16 - dx + size]  # content moves dx pixels right


def test_flow_interpolation_is_the_frame_between_a_translation():
    """Content moving 4 px right between the neighbours: the interpolation is the frame moved 2 px (away from the
    borders: within 0.005 mean absolute colour, ten times closer than the blend of the two); identical
    neighbours give the frame back."""
    texture = load_image(TEXTURES / "coins.png", (96, 96))
    prev, mid, nxt = (_shifted(texture, d)[None] for d in (0, 2, 4))
    got = interp.flow_interpolation(prev, nxt, upsample=2)
    assert got.shape == mid.shape and got.dtype == mid.dtype
    inner = (slice(None), slice(8, -8), slice(8, -8))
    err = float((got - mid)[inner].abs().mean())
    blend = float(((prev + nxt) / 2 - mid)[inner].abs().mean())
    assert err < 0.005 and err < blend / 10, (err, blend)  # a flow of the wrong sign: 0.12
    same = interp.flow_interpolation(prev, prev, upsample=1)
    torch.testing.assert_close(same, prev, rtol=0, atol=1e-4)


def test_a_strip_is_the_chosen_frames_of_each_row(tmp_path):
    """``save_strip``: rows × columns tiles of the frames at evenly spaced indices (first and last), enlarged."""
    frames = torch.linspace(0, 1, 5)[:, None, None, None].expand(5, 6, 8, 3).contiguous()
    common.save_strip(tmp_path / "s.png", {"a": frames, "b": 1 - frames}, columns=3, scale=2)
    strip = load_image(tmp_path / "s.png")
    assert strip.shape == (2 * 6 * 2, 3 * 8 * 2, 3)
    tile = lambda r, c: strip[r * 12 + 8:r * 12 + 12, c * 16 + 12:c * 16 + 16]  # noqa: E731  (right of the label)
    for c, i in enumerate((0, 2, 4)):
        assert float((tile(0, c) - i / 4).abs().max()) < 1 / 255 + 1e-6
        assert float((tile(1, c) - (1 - i / 4)).abs().max()) < 1 / 255 + 1e-6
