"""``diff4splat reconstruct`` (diff4splat/reconstruct.py, diff4splat/io/video_input.py): a video's clip is read as
asked, its scene moves as the video does (in-between frames rendered from it beat holding the previous frame), a
still video gives a static scene, and the command writes generate's folder or fails in one line."""
import json
import math
from unittest import mock

import numpy as np
import pytest
import torch
from helpers import TEXTURES, moving_patch_video

from data_prep.synth import generate_scene
from diff4splat.assembly.layers import LAYER_ORDER_OFFSET, carried_depth, layer_spans
from diff4splat.cli import main
from diff4splat.geometry.scene_flow import consecutive_flows
from diff4splat.io import OutputDirError, load_cameras_json, load_image, save_cameras_json, save_image, save_video
from diff4splat.io.video_input import read_video_clip
from diff4splat.pipeline import Diff4SplatPipeline
from diff4splat.reconstruct import memory_estimate, reconstruct, still_cameras
from diff4splat.render.sequence import render_path
from diff4splat.request import load_pipeline

SIZE = 64


@pytest.fixture(scope="module")
def videos(tmp_path_factory):
    root = tmp_path_factory.mktemp("videos")
    moving = moving_patch_video(17)
    (root / "moving").mkdir()
    for i, frame in enumerate(moving):
        save_image(root / "moving" / f"{i:04d}.png", frame)
    save_video(root / "moving.mp4", moving)
    (root / "still").mkdir()
    for i in range(9):
        save_image(root / "still" / f"{i:04d}.png", moving[0])
    return root, moving


@pytest.fixture(scope="module")
def base_pipeline():
    return load_pipeline(device="cpu")


@pytest.fixture(scope="module")
def moving_every_other(videos, base_pipeline):
    """``reconstruct`` of every other frame of the moving video (9 frames, stride 2, every frame a layer): the same
    call in each test that reads it, so it is made once for the module (the tests only read the result)."""
    root, _ = videos
    return reconstruct(root / "moving", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE)


def test_a_clip_is_the_frames_asked_for(videos):
    root, moving = videos
    clip = read_video_clip(root / "moving", 5, stride=3, start=2)
    assert clip.indices == [2, 5, 8, 11, 14] and clip.fps is None and clip.total == 17
    for frame, i in zip(clip.frames, clip.indices, strict=True):
        assert np.array_equal(frame, moving[i])  # PNG is lossless
    video = read_video_clip(root / "moving.mp4", 5, stride=3, start=2)
    assert video.indices == clip.indices and video.fps == pytest.approx(8.0) and video.total == 17  # the header's
    for frame, i in zip(video.frames, video.indices, strict=True):  # MPEG-4 is lossy: close, and the right frame
        err = np.abs(frame.astype(float) - moving[i]).mean()
        assert err < 12 and all(err < np.abs(frame.astype(float) - moving[j]).mean() for j in (i - 1, i + 1))


@pytest.mark.parametrize("source", ["moving", "moving.mp4"])
def test_a_clip_longer_than_the_video_is_refused_with_the_numbers(videos, source):
    root, _ = videos
    with pytest.raises(ValueError, match=r"17 frame\(s\), but --start 10 --stride 2 --frames 5 needs 19"):
        read_video_clip(root / source, 5, stride=2, start=10)


def test_bad_clip_requests_are_refused(videos, tmp_path):
    root, _ = videos
    with pytest.raises(FileNotFoundError):
        read_video_clip(tmp_path / "none.mp4", 5)
    with pytest.raises(ValueError, match="--start"):
        read_video_clip(root / "moving", 5, start=-1)
    with pytest.raises(ValueError, match="--stride"):
        read_video_clip(root / "moving", 5, stride=0)
    with pytest.raises(ValueError, match="no image file"):
        read_video_clip(tmp_path, 5)
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(ValueError, match="junk.mp4"):
        read_video_clip(tmp_path / "junk.mp4", 5)


def test_the_output_folder_and_frame_rate_are_checked_before_the_model_loads(videos, tmp_path):
    """``reconstruct`` checks the folder it is told of and the frame rate first (its command checks neither)."""
    root, _ = videos

    def never():
        raise AssertionError("the model was loaded before the request was checked")

    with pytest.raises(OutputDirError, match="holds input"):
        reconstruct(root / "moving", pipeline=never, out=root, overwrite=True)
    with pytest.raises(OutputDirError, match="holds input"):
        reconstruct(root / "moving", pipeline=never, out=tmp_path, inputs=[tmp_path / "model"], overwrite=True)
    with pytest.raises(ValueError, match="--fps"):
        reconstruct(root / "moving", pipeline=never, out=tmp_path / "out", fps=-1)
    assert not (tmp_path / "out").exists()


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean()))


@pytest.mark.slow
def test_the_scene_moves_as_the_video_does(videos, base_pipeline, moving_every_other):
    """Every other frame of a patch moving 1 px per frame: the scene at its own frames shows them, and rendered at
    the held-out frames between them it beats holding the previous given frame (the patch is where it was)."""
    _, moving = videos
    gen = moving_every_other
    scene = gen.result.scene
    assert not scene.is_static and gen.kind == "reconstruct" and gen.meta["video_frames"] == list(range(0, 17, 2))
    truth = torch.from_numpy(moving).float() / 255
    for f in gen.result.source_frames.tolist():  # at its own time a frame's layer is shown alone: the frame itself
        assert _psnr(gen.colors[f], truth[2 * f]) > 60, f
    times = (torch.arange(8, dtype=torch.float32) + 0.5) / 8
    mid = still_cameras(base_pipeline.pipeline, 8, SIZE, SIZE)
    mid = type(mid)(mid.viewmats, mid.Ks, SIZE, SIZE, times)
    between = render_path(scene, mid, eps2d=gen.result.eps2d, background=gen.result.background)[0]
    target, held = truth[1::2], truth[0:-1:2]
    assert _psnr(between, target) > _psnr(held, target) + 1.0



@pytest.mark.slow
def test_the_two_layers_around_a_time_cross_fade(videos, base_pipeline):
    """layer_support on the scene of a moving video: at a layer's time only it is shown (with the backdrop); at
    α of the way to the next layer exactly the two are, the even one in front (pushed back by nothing, the odd one
    by LAYER_ORDER_OFFSET along its rays) at 1 − α of its opacity when it is the earlier, α when the later, the
    odd one at full opacity."""
    root, _ = videos
    gen = reconstruct(root / "moving", pipeline=base_pipeline, frames=13, resolution=SIZE)  # times i/12: rounded
    scene, index, n0 = gen.result.scene, gen.result.gaussian_index, gen.result.photo_gaussians
    backdrop = gen.result.num_slots - 13 * n0
    unpruned = torch.where(index < n0, 0, torch.where(index < n0 + backdrop, -1, 1 + (index - n0 - backdrop) // n0))
    for k in range(13):  # what the renderer draws (o·p(t) ≥ 1/255): a rounded triangle's 1e-7 at its end is not
        shown = scene.active_indices(float(gen.result.cameras.times[k]))
        assert set(unpruned[shown].tolist()) == {-1, k}, k
    for k, alpha in ((0, 0.25), (1, 0.5), (2, 0.75), (3, 0.3), (11, 0.9)):
        p = scene.temporal_opacity((k + alpha) / 12)
        assert set(unpruned[p > 1e-6].tolist()) == {-1, k, k + 1}
        even, odd = (k, k + 1) if k % 2 == 0 else (k + 1, k)
        torch.testing.assert_close(p[unpruned == even], torch.full_like(p[unpruned == even],
                                                                        1 - alpha if even == k else alpha),
                                   rtol=0, atol=1e-5)
        assert bool((p[unpruned == odd] == 1).all())
    z = scene.canonical.means[:, 2]
    front = lambda layer: z[(unpruned == layer) & (index % n0 < SIZE * SIZE)]  # noqa: E731  the front disks
    ratio = front(1) / front(0)[: front(1).numel()]
    assert float(ratio.median()) == pytest.approx(1 + LAYER_ORDER_OFFSET, rel=2e-3)


@pytest.mark.slow
def test_a_layer_is_tracked_only_where_it_is_shown_and_frame_0_s_over_the_clip(moving_every_other):
    """layer_spans: a layer k ≥ 1 is shown only between its neighbours' times (the test above), so its motion is
    measured there and is exactly zero at every other key time; frame 0's layer is tracked over the whole clip (the
    patch's pixels have moved 16 px by the last frame)."""
    gen = moving_every_other
    scene, index, n0 = gen.result.scene, gen.result.gaussian_index, gen.result.photo_gaussians
    backdrop = gen.result.num_slots - 9 * n0
    unpruned = torch.where(index < n0, 0, torch.where(index < n0 + backdrop, -1, 1 + (index - n0 - backdrop) // n0))
    moved = scene.d_means.norm(dim=-1) > 0  # (T, N)
    for k in range(1, 9):
        outside = [t for t in range(9) if abs(t - k) > 1]
        assert not bool(moved[outside][:, unpruned == k].any()), k
        assert bool(moved[min(k + 1, 8)][unpruned == k].any() | moved[k - 1][unpruned == k].any()), k
    assert bool(moved[8][unpruned == 0].any())
    assert layer_spans([0, 1, 2, 3]) == [(0, 3), (0, 2), (1, 3), (2, 3)]
    assert layer_spans([0, 4, 8]) == [(0, 8), (0, 8), (4, 8)]


def test_the_layers_knobs_reach_the_scene_and_bad_ones_fail_first(videos, base_pipeline):
    """``order_offset`` is the odd layers' push (0.05: their front disks 1.05× as deep as the even ones'); a bad
    ``order_offset`` or ``unchecked`` fails before any network runs (the pipeline is never loaded)."""
    root, _ = videos
    gen = reconstruct(root / "moving", pipeline=base_pipeline, frames=5, resolution=SIZE, order_offset=0.05)
    scene, index, n0 = gen.result.scene, gen.result.gaussian_index, gen.result.photo_gaussians
    backdrop = gen.result.num_slots - 5 * n0
    unpruned = torch.where(index < n0, 0, torch.where(index < n0 + backdrop, -1, 1 + (index - n0 - backdrop) // n0))
    z = scene.canonical.means[:, 2]
    front = lambda layer: z[(unpruned == layer) & (index % n0 < SIZE * SIZE)]  # noqa: E731  the front disks
    assert float((front(1) / front(0)[: front(1).numel()]).median()) == pytest.approx(1.05, rel=2e-3)
    never = lambda: pytest.fail("the pipeline was loaded")  # noqa: E731
    for kwargs, match in (({"order_offset": -0.01}, "order_offset"), ({"order_offset": math.inf}, "order_offset"),
                          ({"unchecked": -1}, "unchecked"), ({"unchecked": 1.5}, "unchecked")):
        with pytest.raises(ValueError, match=match):
            reconstruct(root / "moving", pipeline=never, frames=5, resolution=SIZE, **kwargs)


def test_a_frame_s_depth_is_carried_from_the_nearest_source_frame_along_the_flow():
    """Content moving 2 px right per frame: frame 1's pixel u was at u − 2 in source frame 0, so it takes the depth
    there (a depth ramp along x makes that visible); frame 3 takes source frame 4's depth at u + 2."""
    back = load_image(TEXTURES / "coins.png", (96, 96))
    frames = torch.stack([back[10:10 + SIZE, 20 - 2 * t:20 - 2 * t + SIZE].permute(2, 0, 1) for t in range(5)])
    ramp = 1.0 + 0.01 * (torch.arange(SIZE, dtype=torch.float32) + 0.5)
    depths = torch.stack([ramp.expand(SIZE, SIZE), 2 * ramp.expand(SIZE, SIZE)])  # sources 0 and 4
    flows = consecutive_flows(frames)
    inner = (slice(8, -8), slice(8, -8))
    z1 = carried_depth(depths, [0, 4], 1, flows)
    assert abs(float((z1 - (ramp - 0.02).expand(SIZE, SIZE))[inner].median())) < 0.003
    z3 = carried_depth(depths, [0, 4], 3, flows)
    assert abs(float((z3 - 2 * (ramp + 0.02).expand(SIZE, SIZE))[inner].median())) < 0.006
    assert torch.equal(carried_depth(depths, [0, 4], 4, flows), depths[1])


@pytest.mark.slow
def test_source_layers_are_fewer_and_still_move(videos, base_pipeline, moving_every_other):
    root, _ = videos
    every = moving_every_other
    source = reconstruct(root / "moving", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE, layers="source")
    assert source.result.source_frames.tolist() == [0, 4, 8] and every.result.source_frames.tolist() == list(range(9))
    assert source.result.num_slots < every.result.num_slots / 2 and not source.result.scene.is_static
    with pytest.raises(ValueError, match="--layers"):
        reconstruct(root / "moving", pipeline=base_pipeline, frames=9, layers="all")


def test_a_request_beyond_the_memory_limit_is_refused_before_the_networks_run(videos, base_pipeline, monkeypatch):
    root, _ = videos
    every = memory_estimate(base_pipeline.pipeline, SIZE, SIZE, 9, 9)
    assert memory_estimate(base_pipeline.pipeline, SIZE, SIZE, 9, 3) < every
    monkeypatch.setenv("DIFF4SPLAT_MAX_MEMORY_BYTES", str(every - 1))
    with mock.patch.object(Diff4SplatPipeline, "reconstruct", side_effect=AssertionError("ran")):
        with pytest.raises(ValueError, match="--layers source"):
            reconstruct(root / "moving", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE)
        with pytest.raises(AssertionError, match="ran"):  # a quarter of the layers fits
            reconstruct(root / "moving", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE, layers="source")


@pytest.mark.slow
def test_a_still_video_gives_a_static_scene(videos, base_pipeline):
    root, _ = videos
    gen = reconstruct(root / "still", pipeline=base_pipeline, frames=9, resolution=SIZE)
    assert gen.result.scene.is_static and not gen.result.scene.changes_with_time
    assert gen.result.prune_stats["duplicates"] > 0  # the later frames' copies of frame 0 are settled away
    assert _psnr(gen.colors[4], gen.colors[0]) > 60


@pytest.mark.slow  # two whole runs of the command (video, viewer, PLYs written)
def test_the_command_writes_generate_s_folder(videos, tmp_path, capsys):
    root, _ = videos
    out = tmp_path / "out"
    args = ["reconstruct", str(root / "moving.mp4"), "--frames", "9", "--stride", "2", "--resolution", str(SIZE),
            "--device", "cpu", "--quiet", "--no-frame-plys", "--out", str(out)]
    assert main(args) == 0
    meta = json.loads((out / "meta.json").read_text())
    marker = json.loads((out / ".diff4splat-output.json").read_text())
    assert marker["kind"] == meta["kind"] == "reconstruct" and meta["video_frames"] == list(range(0, 17, 2))
    assert meta["frames"] == 9 and not meta["static"] and (out / "deformation.npz").is_file()
    assert (out / "scene.ply").is_file() and (out / "video.mp4").is_file() and (out / "viewer.html").is_file()
    cams = json.loads((out / "cameras.json").read_text())
    assert np.allclose(cams["times"], np.arange(9) / 8)
    assert main(args) == 0  # its own earlier output is replaced
    assert "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_a_camera_file_of_every_video_frame_gives_the_clip_s_cameras(tmp_path, base_pipeline):
    """A synthetic scene's first camera (a moving one): its 17 frames and the cameras.json of all 17; the clip every
    other frame takes the cameras of frames 0, 2, …, 16, relative to the first, at the clip's times. A file with
    neither the clip's nor the video's count (fewer, or more than the video's frames) is refused, naming both."""
    scene = generate_scene(tmp_path, 0, seed=3)
    video, cams_file = scene / "cam00" / "rgb", scene / "cam00" / "cameras.json"
    gen = reconstruct(video, cams_file, pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE)
    truth = load_cameras_json(cams_file).viewmats.double()
    expected = truth[0::2] @ torch.linalg.inv(truth[0])
    assert torch.allclose(gen.result.cameras.viewmats.double(), expected, atol=1e-5)
    assert torch.allclose(gen.result.cameras.times.double(), torch.arange(9, dtype=torch.float64) / 8)
    short = load_cameras_json(cams_file)
    save_cameras_json(tmp_path / "five.json", type(short)(short.viewmats[:5], short.Ks[:5], short.width,
                                                          short.height))
    with pytest.raises(ValueError, match=r"5 cameras, but the clip needs 9 .*or 17 \(one per video frame\)"):
        reconstruct(video, tmp_path / "five.json", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE)
    # issue 81, case 12: 40 cameras for a 17-frame video were used silently (cameras 0–16 of 40)
    many = torch.cat([short.viewmats] * 3)[:40], torch.cat([short.Ks] * 3)[:40]
    save_cameras_json(tmp_path / "forty.json", type(short)(*many, short.width, short.height))
    with pytest.raises(ValueError, match=r"40 cameras, but the clip needs 9 .*or 17 \(one per video frame\)"):
        reconstruct(video, tmp_path / "forty.json", pipeline=base_pipeline, frames=9, stride=2, resolution=SIZE)


@pytest.mark.parametrize("case", ["missing", "frames_not_1_plus_4k", "one_frame", "too_short", "zero_stride",
                                  "generate_folder"])
def test_bad_input_is_one_line_exit_2_and_no_output(videos, tmp_path, capsys, case):
    root, _ = videos
    out = tmp_path / "out"
    args = ["reconstruct", str(root / "moving"), "--frames", "9", "--resolution", str(SIZE), "--device", "cpu",
            "--quiet", "--out", str(out)]
    if case == "missing":
        args[1] = str(tmp_path / "none.mp4")
    elif case == "frames_not_1_plus_4k":
        args[3] = "8"
    elif case == "one_frame":  # a one-frame clip: was the optical flow's "(T, 3, H, W) with T ≥ 2"
        args[3] = "1"
    elif case == "too_short":
        args += ["--start", "10"]
    elif case == "zero_stride":
        args += ["--stride", "0"]
    else:  # an earlier generate output is another kind: not replaced
        out.mkdir()
        (out / ".diff4splat-output.json").write_text(json.dumps({"tool": "diff4splat", "kind": "generate",
                                                                 "format": 2, "files": []}))
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("diff4splat: error:"), err
    assert not out.exists() or case == "generate_folder"
    if case == "one_frame":
        assert err[0] == "diff4splat: error: --frames 1: a clip needs at least 2 frames (a frame count the VAE " \
                         "takes: 5, 9, 13, …)"


def test_a_one_frame_clip_is_refused_before_the_networks_run(base_pipeline):
    frames = torch.rand(1, SIZE, SIZE, 3)
    with pytest.raises(ValueError, match=r"^frames: a clip needs at least 2 frames .*got 1$"):
        base_pipeline.pipeline.reconstruct(frames, still_cameras(base_pipeline.pipeline, 1, SIZE, SIZE))
