"""Tests of training/fit_data.py: views of a scene folder, the depth / random-box initial points, the 3DGS
kNN scales and the scene extent (brute-force references and closed forms)."""
import math

import numpy as np
import pytest
import torch

from data_prep.format import load_scene
from data_prep.synth import generate_scene
from diff4splat.cameras.trajectories import look_at
from training.fit_data import (
    View,
    covisible_masks,
    depth_points,
    knn_scales,
    load_views,
    random_box_points,
    scene_extent,
    split_cameras,
    voxel_subsample,
)

K = torch.tensor([[10.0, 0.0, 6.5], [0.0, 11.0, 4.5], [0.0, 0.0, 1.0]])


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(generate_scene(tmp_path_factory.mktemp("fit_data"), 0, 0, size=16, frames=2, cameras=3))


def _view(viewmat, image, depth=None, index=0) -> View:
    return View(image, depth, viewmat.float(), K, 0.0, f"c{index}", 0)


def _coded_views(n: int = 2, H: int = 9, W: int = 13) -> list[View]:
    """Views whose colour encodes (row, column, view) and whose depth is random with some invalid pixels."""
    g = torch.Generator().manual_seed(0)
    eyes = torch.tensor([[0.0, 0.0, 0.0], [0.7, -0.2, 0.3], [-0.5, 0.1, 0.2]])[:n]
    V = look_at(eyes, torch.tensor([0.1, 0.2, 4.0]))
    views = []
    for c in range(n):
        ii, jj = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        image = torch.stack([ii / H, jj / W, torch.full((H, W), c / n)], -1).float()
        depth = 1.0 + 4.0 * torch.rand(H, W, generator=g)
        depth[torch.rand(H, W, generator=g) < 0.2] = math.inf
        views.append(_view(V[c], image, depth, c))
    return views


def _check_reprojection(views: list[View], means, colors) -> None:
    """Every point lies on the ray of the pixel its colour names, at that pixel's depth."""
    n, H, W = len(views), views[0].height, views[0].width
    for p, col in zip(means.double(), colors.double(), strict=True):
        i, j, c = round(float(col[0]) * H), round(float(col[1]) * W), round(float(col[2]) * n)
        v = views[c]
        assert torch.equal(v.image[i, j], col.float())  # the colour is the pixel's
        x = v.viewmat.double()[:3, :3] @ p + v.viewmat.double()[:3, 3]
        uv = (v.K.double() @ x)[:2] / x[2]
        assert float(x[2]) == pytest.approx(float(v.depth[i, j]), rel=1e-5)
        assert uv.tolist() == pytest.approx([j + 0.5, i + 0.5], abs=1e-3)


def test_depth_points_reproject_to_their_pixel_with_its_colour():
    views = _coded_views()
    valid = sum(int(torch.isfinite(v.depth).sum()) for v in views)
    means, colors = depth_points(views, 10_000, torch.Generator().manual_seed(0))
    assert means.shape == (valid, 3) and colors.shape == (valid, 3)  # every finite pixel, no inf one
    assert torch.isfinite(means).all()
    _check_reprojection(views, means, colors)
    pixels = {(round(float(c[0]) * 9), round(float(c[1]) * 13), round(float(c[2]) * 2)) for c in colors}
    assert len(pixels) == valid  # each valid pixel exactly once


def test_depth_points_subsample_a_random_subset_of_at_most_max_points():
    views = _coded_views()
    a, ca = depth_points(views, 37, torch.Generator().manual_seed(1))
    b, cb = depth_points(views, 37, torch.Generator().manual_seed(2))
    assert 30 <= a.shape[0] <= 37 and 30 <= b.shape[0] <= 37 and a.shape[1] == 3
    assert not torch.equal(a, b)  # the generator picks the subset
    _check_reprojection(views, a, ca)
    again, _ = depth_points(views, 37, torch.Generator().manual_seed(1))
    assert torch.equal(a, again)


def test_voxel_subsample_spreads_points_over_space():
    """A dense cluster (20,000 points in a 1 cm cube) beside a sparse plane (500 points over 4 m²): a uniform
    random 1,000 would keep ~24 plane points; one point per grid cell keeps most of the plane."""
    g = torch.Generator().manual_seed(0)
    cluster = 0.01 * torch.rand(20_000, 3, generator=g)
    plane = torch.cat([2 * torch.rand(500, 2, generator=g) - 1, torch.full((500, 1), 3.0)], 1)
    pts = torch.cat([cluster, plane])
    keep = voxel_subsample(pts, 1000, torch.Generator().manual_seed(1))
    assert 900 <= keep.numel() <= 1000 and keep.unique().numel() == keep.numel()
    assert int((keep >= 20_000).sum()) >= 400  # most of the plane
    again = voxel_subsample(pts, 1000, torch.Generator().manual_seed(1))
    other = voxel_subsample(pts, 1000, torch.Generator().manual_seed(2))
    assert torch.equal(keep, again) and not torch.equal(keep, other)  # the generator picks within cells
    assert voxel_subsample(torch.ones(50, 3), 10, g).numel() == 10  # all points equal: a random 10


def test_depth_points_errors():
    views = _coded_views()
    with pytest.raises(ValueError, match="has no depth"):
        depth_points([_view(views[0].viewmat, views[0].image)], 10, torch.Generator())
    dead = _view(views[0].viewmat, views[0].image, torch.full((9, 13), math.inf))
    with pytest.raises(ValueError, match="finite depth"):
        depth_points([dead], 10, torch.Generator())


def test_random_box_points_lie_in_front_of_a_forward_facing_rig():
    # three cameras in the plane z = 0, all looking along +z: the box is centred one spread ahead
    eyes = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    V = look_at(eyes, eyes + torch.tensor([0.0, 0.0, 5.0]))
    views = [_view(V[i], torch.zeros(4, 4, 3), index=i) for i in range(3)]
    means, colors = random_box_points(views, 4000, torch.Generator().manual_seed(0))
    assert means.shape == (4000, 3) and colors.shape == (4000, 3)
    assert float(colors.min()) >= 0 and float(colors.max()) <= 1
    mean_eye = eyes.mean(0)
    spread = float((eyes - mean_eye).norm(dim=1).max())
    centre = mean_eye + torch.tensor([0.0, 0.0, spread])
    assert float((means - centre).abs().max()) <= spread + 1e-5  # inside the box
    assert means.mean(0).tolist() == pytest.approx(centre.tolist(), abs=0.1 * spread)  # uniform in it
    z = torch.einsum("cij,nj->cni", V[:, :3, :3], means) + V[:, None, :3, 3]
    assert float(z[..., 2].min()) > 0  # in front of every camera
    # one camera: the spread is at least 1 m
    one, _ = random_box_points(views[:1], 500, torch.Generator().manual_seed(0))
    assert float(one[:, 2].min()) > 0 and float((one - torch.tensor([0.0, 0.0, 1.0])).abs().max()) <= 1 + 1e-6


def test_random_box_points_of_an_inward_ring_surround_the_look_at_point():
    # cameras on a full ring looking at the origin: their viewing directions cancel, so the box must stay
    # centred on the ring (not pushed along a direction made of rounding noise)
    for n in (4, 5, 6):
        ang = torch.arange(n) * 2 * math.pi / n
        eyes = torch.stack([3 * torch.cos(ang), torch.zeros(n), 3 * torch.sin(ang)], 1)
        V = look_at(eyes, torch.zeros(3))
        views = [_view(V[i], torch.zeros(4, 4, 3), index=i) for i in range(n)]
        means, _ = random_box_points(views, 4000, torch.Generator().manual_seed(0))
        assert torch.isfinite(means).all()
        assert float(means.mean(0).norm()) < 0.3, n
        z = torch.einsum("cij,nj->cni", V[:, :3, :3], means) + V[:, None, :3, 3]
        assert float((z[..., 2] > 0).float().mean()) > 0.8


def _knn_reference(x: np.ndarray, k: int) -> np.ndarray:
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.sqrt(np.maximum(np.sort(d2, axis=1)[:, :k].mean(1), 1e-7))


@pytest.mark.parametrize("chunk", [7, 1024])
def test_knn_scales_equal_brute_force(chunk):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(60, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    x[5] = x[6]  # a duplicate point: distance 0 to its twin
    out = knn_scales(x, chunk=chunk)
    assert out.shape == (60, 3) and out.dtype == torch.float64
    ref = _knn_reference(x.numpy(), 3)
    np.testing.assert_allclose(out.numpy(), np.repeat(ref[:, None], 3, 1), rtol=1e-10)
    # k is capped at N − 1; every point coincident → the clamp 1e-7 m²
    np.testing.assert_allclose(knn_scales(x[:2]).numpy()[:, 0], _knn_reference(x[:2].numpy(), 1), rtol=1e-10)
    np.testing.assert_allclose(knn_scales(torch.zeros(4, 3)).numpy(), math.sqrt(1e-7), rtol=1e-6)
    assert knn_scales(torch.zeros(1, 3)).shape == (1, 3)


def test_scene_extent_is_1_1_radius_for_cameras_on_a_circle():
    r = 2.5
    ang = torch.linspace(0, 2 * math.pi, 9)[:-1]
    eyes = torch.stack([r * torch.cos(ang) + 1.0, torch.full_like(ang, -3.0), r * torch.sin(ang)], 1)
    V = look_at(eyes, torch.tensor([1.0, -3.0, 0.0]))
    views = [_view(V[i], torch.zeros(2, 2, 3), index=i) for i in range(8)]
    assert scene_extent(views) == pytest.approx(1.1 * r, rel=1e-5)
    small_points = torch.rand(50, 3)  # diagonal ≤ √3: 10 % of it is below 1.1·r
    assert scene_extent(views, small_points) == pytest.approx(1.1 * r, rel=1e-5)


def test_scene_extent_floor_for_a_camera_that_does_not_move():
    V = look_at(torch.tensor([[0.3, 0.2, -1.0]]), torch.zeros(3))[0]
    views = [_view(V, torch.zeros(2, 2, 3), index=i) for i in range(3)]
    assert scene_extent(views) == 1e-3
    pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 12.0], [1.0, 1.0, 1.0]])
    assert scene_extent(views, pts) == pytest.approx(0.1 * 13.0, rel=1e-6)
    assert scene_extent(views, pts * 1e-5) == 1e-3


def test_split_cameras(scene):
    assert split_cameras(scene, None) == (["cam00", "cam01", "cam02"], [])
    assert split_cameras(scene, 1) == (["cam00", "cam02"], ["cam01"])
    assert split_cameras(scene, 0) == (["cam01", "cam02"], ["cam00"])
    for bad in (3, -1, 5):
        with pytest.raises(ValueError, match=f"--holdout-camera: {bad} is not a camera index"):
            split_cameras(scene, bad)


def test_split_cameras_one_camera(tmp_path):
    one = load_scene(generate_scene(tmp_path, 0, 0, size=8, frames=1, cameras=1))
    assert split_cameras(one, None) == (["cam00"], [])
    with pytest.raises(ValueError, match="one camera"):
        split_cameras(one, 0)


def test_load_views(scene):
    views = load_views(scene, ["cam02", "cam00"])
    assert [(v.camera, v.frame) for v in views] == [("cam02", 0), ("cam02", 1), ("cam00", 0), ("cam00", 1)]
    path = scene.cameras("cam02")
    v = views[1]
    assert v.image.shape == (16, 16, 3) and v.image.dtype == torch.float32 and (v.width, v.height) == (16, 16)
    assert torch.equal(v.image, torch.from_numpy(scene.rgb("cam02", 1)))
    assert torch.equal(v.depth, torch.from_numpy(scene.depth("cam02", 1)))
    assert torch.equal(v.viewmat, path.viewmats[1].float()) and torch.equal(v.K, path.Ks[1].float())
    assert v.time == float(path.times[1]) == 1.0
    assert [(v.camera, v.frame) for v in load_views(scene, ["cam01"], frames=[1])] == [("cam01", 1)]


def test_covisible_masks_use_the_same_time_for_a_dynamic_scene():
    """A training view at frame 0 facing the surface, one at frame 1 facing away: a held-out view at frame 1
    sees nothing co-visible in a dynamic scene (only frame 1 counts) and everything in a static one."""
    depth = torch.full((9, 13), 3.0)
    away = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))
    train = [View(torch.zeros(9, 13, 3), depth, torch.eye(4), K, 0.0, "a", 0),
             View(torch.zeros(9, 13, 3), depth, away, K, 1.0, "a", 1)]
    held = [View(torch.zeros(9, 13, 3), depth, torch.eye(4), K, 1.0, "h", 1)]
    assert not bool(covisible_masks(held, train, static=False)[0].any())
    assert bool(covisible_masks(held, train, static=True)[0].all())
    assert covisible_masks(held, [View(torch.zeros(9, 13, 3), None, torch.eye(4), K, 0.0, "a", 0)], True) is None
    assert covisible_masks([], train, True) is None


def test_views_and_initial_points_on_each_device(scene, device):
    """Views on ``device``; the initial points made there from the same CPU draws as on the CPU."""
    views = load_views(scene, ["cam00", "cam01"], device=device)
    cpu = load_views(scene, ["cam00", "cam01"])
    assert {t.device.type for v in views for t in (v.image, v.depth, v.viewmat, v.K)} == {device.type}
    assert all(v.device.type == device.type and v.to("cpu").device.type == "cpu" for v in views)
    means, colors = depth_points(views, 10**6, torch.Generator().manual_seed(0))  # every point: no subsample
    ref_means, ref_colors = depth_points(cpu, 10**6, torch.Generator().manual_seed(0))
    assert means.device.type == device.type and colors.device.type == device.type
    torch.testing.assert_close(means.cpu(), ref_means, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(colors.cpu(), ref_colors, rtol=0, atol=0)
    keep = voxel_subsample(ref_means.to(device), 40, torch.Generator().manual_seed(3))
    assert keep.device.type == device.type
    assert torch.equal(keep.cpu(), voxel_subsample(ref_means, 40, torch.Generator().manual_seed(3)))
    box, box_colors = random_box_points(views, 50, torch.Generator().manual_seed(4))
    ref_box, ref_box_colors = random_box_points(cpu, 50, torch.Generator().manual_seed(4))
    assert box.device.type == device.type
    torch.testing.assert_close(box.cpu(), ref_box, rtol=1e-6, atol=1e-6)
    assert torch.equal(box_colors.cpu(), ref_box_colors)
    scales = knn_scales(ref_means[:200].to(device), chunk=64)
    assert scales.device.type == device.type
    torch.testing.assert_close(scales.cpu(), knn_scales(ref_means[:200]), rtol=1e-4, atol=1e-6)
    masks = covisible_masks(views[2:], views[:2], static=False)
    assert masks[0].device.type == device.type
    assert torch.equal(masks[0].cpu(), covisible_masks(cpu[2:], cpu[:2], static=False)[0])


def test_fit_data_makes_nothing_on_the_default_device(no_implicit_device):
    """With torch's default device "meta" (tests/conftest.py), CPU views give CPU points, scales and masks."""
    with torch.device("cpu"):
        views = _coded_views(3)
        held = [View(views[0].image, views[0].depth, views[0].viewmat, K, 0.0, "h", 5)]  # no training view at frame 5
    means, colors = depth_points(views, 30, torch.Generator().manual_seed(0))  # subsampled
    box, box_colors = random_box_points(views, 20, torch.Generator().manual_seed(1))
    scales, one = knn_scales(means, chunk=7), knn_scales(means[:1])
    masks = covisible_masks(held + views[1:2], views, static=False)
    out = [means, colors, box, box_colors, scales, one, *masks]
    assert {t.device.type for t in out} == {"cpu"}
    assert means.shape[0] <= 30 and torch.isfinite(scales).all() and not bool(masks[0].any())
    assert scene_extent(views, means) > 0
