import json

import cv2
import numpy as np
import pytest
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_fov
from diff4splat.gaussians import Gaussians
from diff4splat.io import MARKER, load_depth_exr, load_ply, load_video
from diff4splat.io.output import fill_empty_depth, load_deformation, write_scene_folder
from diff4splat.scene import DynamicGaussians


def test_fill_empty_depth_uses_the_far_bound_and_keeps_covered_pixels():
    depths = torch.tensor([[[1.0, 0.0], [3.0, 0.0]]])
    alphas = torch.tensor([[[1.0, 0.0], [0.5, 0.001]]])
    out = fill_empty_depth(depths, alphas, fallback=7.0)
    torch.testing.assert_close(out, torch.tensor([[[1.0, 3.0], [3.0, 3.0]]]))
    torch.testing.assert_close(fill_empty_depth(depths, alphas * 0, fallback=7.0), torch.full_like(depths, 7.0))


def _inputs(T=5, M=10, W=16, H=16, dynamic=True):
    g = torch.Generator().manual_seed(0)
    gs = Gaussians(torch.randn(M, 3, generator=g) + torch.tensor([0, 0, 3.0]), torch.randn(M, 4, generator=g),
                   torch.rand(M, 3, generator=g) * 0.1 + 0.01, torch.rand(M, generator=g) * 0.9 + 0.05,
                   torch.randn(M, 1, 3, generator=g))
    K = intrinsics_from_fov(W, H, fov_y_deg=60.0).expand(T, 3, 3).clone()
    cams = CameraPath(torch.eye(4).repeat(T, 1, 1), K, W, H)
    scene = DynamicGaussians(gs)
    if dynamic:
        dq = torch.zeros(T, M, 4)
        dq[..., 0] = 1
        scene = DynamicGaussians(gs, cams.times, torch.randn(T, M, 3, generator=g) * 0.1, dq, torch.zeros(T, M, 3))
    colors = torch.rand(T, H, W, 3, generator=g)
    alphas = torch.ones(T, H, W)
    depths = torch.rand(T, H, W, generator=g) + 1
    return scene, cams, colors, depths, alphas


def test_folder_has_every_file_and_frames_follow_the_deformation(tmp_path):
    scene, cams, colors, depths, alphas = _inputs()
    write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {"seed": 0})
    out = tmp_path / "out"
    names = sorted(p.name for p in out.iterdir())
    assert names == [MARKER, "cameras.json", "deformation.npz", "depth", "frames", "meta.json", "rgb", "scene.ply",
                     "video.mp4", "viewer.html"]
    assert load_video(out / "video.mp4").shape == (5, 16, 16, 3)
    lossless = np.stack([cv2.imread(str(out / "rgb" / f"{i:04d}.png"))[..., ::-1] for i in range(5)])
    np.testing.assert_array_equal(lossless, np.round(colors.clamp(0, 1).numpy() * 255).astype(np.uint8))
    d = load_deformation(out / "deformation.npz")
    np.testing.assert_allclose(d["d_means"], scene.d_means.numpy())
    for i in range(5):
        np.testing.assert_allclose(load_ply(out / "frames" / f"{i:04d}.ply").means.numpy(),
                                   scene.at(float(cams.times[i])).means.numpy(), atol=1e-6)
        np.testing.assert_allclose(load_depth_exr(out / "depth" / f"{i:04d}.exr"), depths[i].numpy())
    assert json.loads((out / "meta.json").read_text()) == {"seed": 0}


def test_static_scene_writes_no_deformation(tmp_path):
    scene, cams, colors, depths, alphas = _inputs(dynamic=False)
    write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {})
    assert not (tmp_path / "out" / "deformation.npz").exists()
    assert load_ply(tmp_path / "out" / "scene.ply").num_gaussians == 10


def test_failure_part_way_leaves_no_folder(tmp_path):
    scene, cams, colors, depths, alphas = _inputs()
    with pytest.raises(TypeError):
        write_scene_folder(tmp_path / "out", scene, cams, colors, depths, alphas, {"bad": object()})
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="frames"):
        write_scene_folder(tmp_path / "out", scene, cams, colors[:2], depths, alphas, {})
