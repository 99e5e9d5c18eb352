"""benchmarks/stereo_views.py: the camera path reproduces the stereo pair's geometry (a sign or offset error in the
baseline, the crop or ``doffs`` would score every model against the wrong view)."""
import torch
from helpers import benchmark_module

stereo_views = benchmark_module("stereo_views")


def test_a_point_at_its_disparitys_depth_lands_on_its_right_image_pixel():
    """A left pixel (x, y) of disparity d, placed at z = f·B/(d + doffs) on its ray, projects in the right camera
    (s = 1) to (x − d, y) in the original image: both scaled by the crop-and-resize to the output size."""
    calib = stereo_views.MOTORCYCLE
    H, W = 500, 741
    path = stereo_views.stereo_path((H, W), calib)
    right = stereo_views.SCALES.index(1.0) + 1
    s, x0 = stereo_views.SIZE / H, (W - H) / 2
    g = torch.Generator().manual_seed(0)
    x = x0 + torch.rand(50, generator=g, dtype=torch.float64) * H
    y = torch.rand(50, generator=g, dtype=torch.float64) * H
    d = 7 + torch.rand(50, generator=g, dtype=torch.float64) * 53  # the pair's disparity range, pixels
    z = calib["focal"] * calib["baseline"] / (d + calib["doffs"])
    pix = torch.stack([(x - x0) * s, y * s, torch.ones_like(x)], 1)
    X = z[:, None] * (torch.linalg.inv(path.Ks[0]) @ pix.T).T  # camera 0 is the world frame
    assert torch.equal(path.viewmats[0], torch.eye(4, dtype=torch.float64))
    cam = (path.viewmats[right, :3, :3] @ X.T).T + path.viewmats[right, :3, 3]
    proj = (path.Ks[right] @ cam.T).T
    torch.testing.assert_close(proj[:, 0] / proj[:, 2], (x - d - x0) * s)
    torch.testing.assert_close(proj[:, 1] / proj[:, 2], y * s)
    assert bool((path.times == 0).all()) and len(path) == len(stereo_views.SCALES) + 1
