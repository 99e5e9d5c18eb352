"""Input validation is one function shared by every render entry point: the same bad argument gives the
same ValueError message from the tile path, the dense reference, the ray path and the gsplat backend."""
import pytest
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_focal
from diff4splat.render import rasterize, rasterize_dense, raytrace
from diff4splat.render.rasterize import rasterize_gsplat
from diff4splat.render.settings import RASTERIZE_MODES, RENDER_MODES, RasterSettings, validate_inputs


def gsplat_backend(*args, **keywords):
    """The gsplat backend as ``rasterize`` calls it: the keywords packed into one RasterSettings (it validates
    before importing gsplat, so this runs without it)."""
    return rasterize_gsplat(*args, RasterSettings(**keywords))


ENTRY_POINTS = [rasterize, rasterize_dense, raytrace, gsplat_backend]
D = torch.float64


def _args(n=3, w=8, h=6):
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g, dtype=D) * 0.2 + torch.tensor([0.0, 0.0, 2.0], dtype=D)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=D)
    K = torch.tensor([[[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]], dtype=D)
    return [means, quats, torch.full((n, 3), 0.1, dtype=D), torch.full((n,), 0.5, dtype=D),
            torch.rand(n, 3, generator=g, dtype=D), torch.eye(4, dtype=D)[None], K, w, h]


def _message(fn, args, **kw) -> str:
    with pytest.raises(ValueError) as e:
        fn(*args, **kw)
    return str(e.value)


@pytest.mark.parametrize("name, value", [("width", 0), ("width", -3), ("height", 2.5), ("height", True),
                                         ("tile_size", 0), ("tile_size", "16")])
def test_bad_size_gives_one_message_from_every_entry_point(name, value):
    args = _args()
    kw = {}
    if name == "width":
        args[7] = value
    elif name == "height":
        args[8] = value
    else:
        kw["tile_size"] = value
    messages = {fn.__name__: _message(fn, args, **kw) for fn in ENTRY_POINTS}
    want = f"{name} must be a positive int (pixels), got {value!r}"
    assert messages == {fn.__name__: want for fn in ENTRY_POINTS}


@pytest.mark.parametrize("kw, needle", [
    ({"render_mode": "RGBD"}, "render_mode must be one of"),
    ({"near_plane": 2.0, "far_plane": 1.0}, "near_plane < far_plane"),
    ({"eps2d": -1.0}, "eps2d must be a finite number >= 0"),
    ({"eps2d": float("inf")}, "eps2d must be a finite number >= 0"),  # culled every Gaussian, silently
    ({"eps2d": None}, "eps2d must be a finite number >= 0"),  # a TypeError from a comparison
    ({"sh_degree": True}, "sh_degree must be an int in 0..3, got True"),  # rendered as degree 1
])
def test_bad_option_gives_one_message_from_every_entry_point(kw, needle):
    messages = {_message(fn, _args(), **kw) for fn in ENTRY_POINTS}
    assert len(messages) == 1 and needle in messages.pop()


@pytest.mark.parametrize("index, edit, needle", [
    (5, lambda v: v[:0], "viewmats holds no camera"),  # stacked nothing: a RuntimeError from torch.stack
    (3, lambda o: o + 1.0, "opacities must be in [0, 1], got values from 1.5 to 1.5"),  # the fused path clamped
    (3, lambda o: o - 1.0, "opacities must be in [0, 1]"),
    (2, lambda s: -s, "scales must be >= 0 metres"),
    (6, lambda K: K * torch.tensor([0.0, 1, 1], dtype=D)[:, None], "Ks need focal lengths fx, fy > 0 pixels"),
    # the tile paths ignored skew and the last row, the ray path inverted them (and raised LinAlgError on a 0 row)
    (6, lambda K: K + torch.tensor([[0.0, 10, 0], [0, 0, 0], [0, 0, 0]], dtype=D), "Ks must be pinhole intrinsics"),
    (6, lambda K: K * torch.tensor([1.0, 1, 0], dtype=D)[:, None], "Ks must be pinhole intrinsics"),
    # a scaled camera: its centre −Rᵀt, and so every SH colour, was wrong
    (5, lambda V: V * torch.tensor([2.0, 2, 2, 1], dtype=D)[:, None], "viewmats must be rigid"),
])
def test_values_the_paths_assume_are_checked_by_every_entry_point(index, edit, needle):
    """Values that rendered before (zero cameras crashed in torch.stack): the same message from every path."""
    args = _args()
    args[index] = edit(args[index])
    if index == 5 and len(args[5]) == 0:
        args[6] = args[6][:0]
    messages = {_message(fn, args) for fn in ENTRY_POINTS}
    assert len(messages) == 1 and needle in messages.pop()


def test_non_finite_tensor_named_the_same_by_every_entry_point():
    args = _args()
    args[0] = args[0].clone()
    args[0][1, 2] = float("nan")
    messages = {_message(fn, args) for fn in ENTRY_POINTS}
    assert messages == {"means contains 1 non-finite value(s) (NaN or inf)"}


def test_size_message_matches_the_camera_layer():
    """The cameras use the same check, so a bad width reads the same wherever it is caught."""
    K = torch.eye(3, dtype=D)[None]
    with pytest.raises(ValueError) as cam:
        CameraPath(torch.eye(4, dtype=D)[None], K, 0, 4)
    with pytest.raises(ValueError) as intr:
        intrinsics_from_focal(10.0, 10.0, 0, 4)
    args = _args()
    args[7] = 0
    assert str(cam.value) == str(intr.value) == _message(rasterize,
                                                         args) == "width must be a positive int (pixels), got 0"


def test_validate_inputs_accepts_good_arguments_and_lists_gsplat_modes():
    validate_inputs(*_args(), RasterSettings())
    validate_inputs(*_args(), RasterSettings(near_plane=0.5, far_plane=9.0, eps2d=0.0, rasterize_mode="antialiased",
                                             render_mode="RGB", tile_size=4))
    validate_inputs(*_args(), RasterSettings(camera_model="fisheye"), camera_models=("pinhole", "fisheye"))
    with pytest.raises(ValueError, match="camera_model must be one of"):
        validate_inputs(*_args(), RasterSettings(camera_model="fisheye"))
    assert RENDER_MODES == ("RGB", "D", "ED", "RGB+D", "RGB+ED")
    assert RASTERIZE_MODES == ("classic", "antialiased")
