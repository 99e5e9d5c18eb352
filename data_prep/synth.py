"""Synthetic dynamic scenes made of 3D Gaussians, rendered with diff4splat's renderer (``data_prep synth``).

A spec (:func:`data_prep.synth_world.sample_scene_spec`) becomes a :class:`~diff4splat.scene.dynamic.DynamicGaussians`
of flat Gaussians on a ground disk, a cylindrical wall and 1–4 objects, textured (:mod:`data_prep.textures`) and shaded
``ambient + (1 − ambient)·max(0, n·l)`` into the degree-0 SH, deformed at the frame times t_i = i/(T−1). Depth is the
rendered z-depth (metres) where opacity ≥ 0.5, else +inf; tracks are exact object Gaussian means. Scene ``index`` of
run ``seed`` draws everything from ``default_rng([seed, index])`` and renders on one thread: the same bytes serially,
in parallel or on resume.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diff4splat.cameras import CameraPath, intrinsics_from_fov, look_at
from diff4splat.render.sequence import render_path
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat, rotmat_to_quat

from .format import SceneWriter
from .scene_files import NO_SURFACE
from .synth_world import MOTIONS, SYNTH, caption_for, check_motions, sample_scene_spec
from .textures import image_albedo

__all__ = ["generate_scene", "render_spec", "write_synth_scene", "SynthScene", "build_scene", "build_gaussians",
           "object_transform", "object_poses", "render_camera",
           "camera_path", "track_visibility", "scene_name", "MAX_TRACKS", "VISIBILITY_TOL_M",
           "VISIBILITY_TOL_REL"]

MAX_TRACKS = 256
"""Tracked object points per scene (fewer if the objects have fewer Gaussians)."""
VISIBILITY_TOL_M = 0.05
VISIBILITY_TOL_REL = 0.03
"""Occlusion tolerance VISIBILITY_TOL_M + VISIBILITY_TOL_REL·z, metres (FORMAT.md, tracks): the rendered depth
averages Gaussian-centre depths, so it lies up to about 0.1 m in front of a slanted surface at 3 m."""
IMAGE_SPACING = 0.5
"""Spacing factor of image-textured ground and wall Gaussians (4× as many), so a photograph's detail survives."""
_WALL_HEIGHT = 4.0
_UP = np.array([0.0, -1.0, 0.0])  # world up (y points down)


def scene_name(index: int) -> str:
    """Folder name of scene ``index``: ``scene_00007``."""
    return f"scene_{index:05d}"


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations whose columns are (t1, t2, n): local → world frames of flat Gaussians."""
    a = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(normals, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=-1)


def _texture_rgb(rng: np.random.Generator, tex: dict, base: list[float], uv: np.ndarray, extent: np.ndarray,
                 spacing: float) -> np.ndarray:
    """Albedo (N, 3) of a texture at surface coordinates ``uv`` (N, 2) metres plus grey jitter ``noise``·N(0, 1)."""
    if tex["kind"] == "image":
        return image_albedo(tex, uv, spacing) + tex["noise"] * rng.standard_normal((len(uv), 1))
    c1, c2 = np.asarray(base), np.asarray(tex["color2"])
    ca, sa = math.cos(tex["angle"]), math.sin(tex["angle"])
    u, v = uv[:, 0] * ca + uv[:, 1] * sa, -uv[:, 0] * sa + uv[:, 1] * ca
    f = tex["freq"]
    if tex["kind"] == "checker":
        mix = ((np.floor(u * f) + np.floor(v * f)) % 2)[:, None]
    elif tex["kind"] == "stripes":
        mix = (np.floor(u * f) % 2)[:, None]
    else:
        mix = np.zeros((len(uv), 1))
    rgb = c1 * (1 - mix) + c2 * mix
    if tex["kind"] == "noise":
        rel = uv / np.maximum(extent, 1e-6)
        for c, r, col in zip(tex["blobs"]["centers"], tex["blobs"]["radii"], tex["blobs"]["colors"], strict=True):
            w = np.exp(-((rel - np.asarray(c)) ** 2).sum(1) / (2 * r * r))[:, None]
            rgb = rgb * (1 - w) + np.asarray(col) * w
    return rgb + tex["noise"] * rng.standard_normal((len(uv), 1))


def _shade(albedo: np.ndarray, normals: np.ndarray, light: dict) -> np.ndarray:
    """Lambertian shading: albedo·tint·(ambient + (1 − ambient)·max(0, n·l)), clipped to [0, 1]."""
    lam = np.clip(normals @ np.asarray(light["direction"]), 0, None)[:, None]
    return np.clip(albedo * np.asarray(light["tint"]) * (light["ambient"] + (1 - light["ambient"]) * lam), 0, 1)


def _fibonacci(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    y = 1 - 2 * i / n
    r, phi = np.sqrt(1 - y * y), math.pi * (3 - math.sqrt(5)) * i
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], 1)


def _object_surface(obj: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Object-local surface samples: points (N, 3), normals (N, 3), uv (N, 2) m, extent (2,) m, spacing m."""
    h = np.asarray(obj["half"])
    if obj["shape"] == "box":
        area = 8 * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2])
        sp = max(math.sqrt(area / 600), 0.04)
        pts, nrm, uv = [], [], []
        for ax in range(3):
            a, b = [k for k in range(3) if k != ax]
            ga, gb = (np.arange(-h[k] + sp / 2, h[k], sp) for k in (a, b))
            A, B = (g.reshape(-1) for g in np.meshgrid(ga, gb, indexing="ij"))
            for sign in (-1.0, 1.0):
                p = np.zeros((len(A), 3))
                p[:, a], p[:, b], p[:, ax] = A, B, sign * h[ax]
                n = np.zeros_like(p)
                n[:, ax] = sign
                pts.append(p), nrm.append(n), uv.append(np.stack([A, B], 1))
        return np.concatenate(pts), np.concatenate(nrm), np.concatenate(uv), 2 * h[:2], sp
    r = float(h.max())
    area = 4 * math.pi * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2]) / 3  # ellipsoid area (Thomsen, p=1)
    n = int(np.clip(area / 0.05 ** 2, 200, 700))
    d = _fibonacci(n)
    if obj["shape"] == "blob":  # a sphere with low-order radial lumps: r(d) = r·(1 + Σ c_k·d_{k mod 3}·d_{(k+1) mod 3})
        c = np.asarray(obj["lumps"])
        bump = sum(c[k] * d[:, k % 3] * d[:, (k + 1) % 3] * (1 + k // 3) for k in range(len(c)))
        pts = d * (r * (1 + bump))[:, None]
        nrm = d
    else:
        pts = d * h
        nrm = d / h
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = np.stack([np.arctan2(d[:, 2], d[:, 0]) * r, np.arccos(np.clip(d[:, 1], -1, 1)) * r], 1)
    return pts, nrm, uv, np.array([2 * math.pi * r, math.pi * r]), math.sqrt(area / n)


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _density(tex: dict) -> float:
    """Spacing factor of ground/wall Gaussians: :data:`IMAGE_SPACING` for an image texture, else 1."""
    return IMAGE_SPACING if tex["kind"] == "image" else 1.0


def build_gaussians(spec: dict[str, Any], rng: np.random.Generator) -> tuple[Gaussians, np.ndarray]:
    """Canonical (t = 0) float32 Gaussians of a scene spec (ground, wall, then objects; flat discs of in-plane
    σ = 0.7·spacing) and the object id (M,) int64 of each: −1 for ground/wall, k for ``spec["objects"][k]``."""
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float, int]] = []  # pts, nrm, rgb, sigma, opacity, id
    R, gy, light = spec["room_radius"], spec["ground_y"], spec["light"]
    sp = 0.25 * min(1.0, 64 / spec["size"]) ** 0.5
    sg = sp * _density(spec["ground"]["texture"])
    g = np.arange(-R, R + 1e-9, sg)
    X, Z = (a.reshape(-1) for a in np.meshgrid(g, g, indexing="ij"))
    keep = X ** 2 + Z ** 2 <= R * R
    X, Z = X[keep], Z[keep]
    pts = np.stack([X, np.full_like(X, gy), Z], 1)
    nrm = np.tile(_UP, (len(X), 1))
    tex = spec["ground"]
    albedo = _texture_rgb(rng, tex["texture"], tex["color"], pts[:, [0, 2]], np.array([2 * R, 2 * R]), sg)
    parts.append((pts, nrm, _shade(albedo, nrm, light), sg, 0.97, -1))
    f = _density(spec["wall"]["texture"])
    n_arc = int(math.ceil(2 * math.pi * R / (sp * 1.2 * f)))
    th = np.arange(n_arc) * 2 * math.pi / n_arc
    ys = gy - np.arange(sp * 0.6 * f, _WALL_HEIGHT, sp * 1.2 * f)
    TH, Y = (a.reshape(-1) for a in np.meshgrid(th, ys, indexing="ij"))
    pts = np.stack([R * np.cos(TH), Y, R * np.sin(TH)], 1)
    nrm = -pts * np.array([1.0, 0.0, 1.0]) / R
    tex = spec["wall"]
    uv = np.stack([TH * R, gy - Y], 1)
    extent = np.array([2 * math.pi * R, _WALL_HEIGHT])
    albedo = _texture_rgb(rng, tex["texture"], tex["color"], uv, extent, sp * 1.2 * f)
    parts.append((pts, nrm, _shade(albedo, nrm, light), sp * 1.2 * f, 0.97, -1))
    for k, obj in enumerate(spec["objects"]):
        p, n, uv, extent, osp = _object_surface(obj)
        Ry = _rot_y(obj["yaw"])
        p, n = p @ Ry.T + np.asarray(obj["center"]), n @ Ry.T
        albedo = _texture_rgb(rng, obj["texture"], obj["color"], uv, extent, osp)
        parts.append((p, n, _shade(albedo, n, light), osp, obj["opacity"], k))
    means = np.concatenate([q[0] for q in parts])
    frames = _tangent_frames(np.concatenate([q[1] for q in parts]))
    rgb = np.concatenate([q[2] for q in parts])
    sig = np.concatenate([np.full(len(q[0]), 0.7 * q[3]) for q in parts])
    scales = np.stack([sig, sig, 0.1 * sig], 1)
    opac = np.concatenate([np.full(len(q[0]), q[4]) for q in parts])
    ids = np.concatenate([np.full(len(q[0]), q[5], dtype=np.int64) for q in parts])
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32, device="cpu")  # noqa: E731
    quats = rotmat_to_quat(torch.as_tensor(frames, dtype=torch.float64, device="cpu")).float()
    return Gaussians(f32(means), quats, f32(scales), f32(opac), rgb_to_sh0(f32(rgb))[:, None, :]), ids


def object_transform(obj: dict[str, Any], t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pose of an object at clip time t ∈ [0, 1], p(t) = p0 + d + R·(S ⊙ (p − p0)) (motions:
    :mod:`data_prep.synth_world`): float64 pivot p0 (3,), displacement d (3,) metres, R (3, 3), scales S (3,)."""
    m, c = obj["motion"], np.asarray(obj["center"], dtype=np.float64)
    d, R, S = np.zeros(3), np.eye(3), np.ones(3)
    if m is None:
        return c, d, R, S
    if m["kind"] in ("translate", "bounce"):
        d = t * np.asarray(m["velocity"])
    if m["kind"] == "translate" and m["roll"] and np.linalg.norm(d) > 0:
        axis = np.cross(_UP, d / np.linalg.norm(d))
        R = _axis_angle(axis, np.linalg.norm(d) / obj["half"][0])
    elif m["kind"] == "rotate":
        R = _axis_angle(np.asarray(m["axis"]), m["omega"] * t)
    elif m["kind"] == "bounce":
        tau = (m["hops"] * t) % 1.0
        d = d + _UP * 4 * m["height"] * tau * (1 - tau)
    elif m["kind"] == "deform":
        s = m["amplitude"] * math.sin(2 * math.pi * m["freq"] * t)
        S = np.full(3, 1 + s) if m["mode"] == "pulse" else np.array([1 + s / 2, 1 - s, 1 + s / 2])
        c = c + np.array([0.0, obj["half"][1], 0.0])  # pivot at the bottom: the object stays on the ground
    return c, d, R, S


def object_poses(spec: dict[str, Any]) -> np.ndarray:
    """(O, T, 3, 4) float64 affine world maps [A | b] of the spec's O objects at the T frame times (objects.npz,
    FORMAT.md): x = A·p + b with A = R·diag(S), b = p0 + d − A·p0 (:func:`object_transform`)."""
    T = spec["num_frames"]
    times = np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1)
    poses = np.zeros((len(spec["objects"]), T, 3, 4))
    for k, obj in enumerate(spec["objects"]):
        for i, t in enumerate(times):
            p0, d, R, S = object_transform(obj, float(t))
            A = R * S[None, :]
            poses[k, i, :, :3], poses[k, i, :, 3] = A, p0 + d - A @ p0
    return poses


def render_camera(scene: DynamicGaussians, object_ids: np.ndarray, num_objects: int, cameras: CameraPath,
                  background: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame i of ``cameras`` with the scene at ``cameras.times[i]``, on the scene's device, in one render: colour
    (T, H, W, 3) float32 in [0, 1] over ``background``, z-depth (T, H, W) float32 metres where the alpha is ≥ 0.5
    (+inf elsewhere), and the object id map (T, H, W) uint8 (objects.npz, FORMAT.md: 0 background, k + 1 object k,
    :data:`~data_prep.scene_files.NO_SURFACE` where the depth is +inf; the id whose Gaussians weigh most in the
    pixel, ``object_ids`` (M,) as :func:`build_gaussians`): the one-hot ids composited beside the colours by
    :func:`~diff4splat.render.sequence.render_path` (``features``)."""
    device, dtype = scene.canonical.means.device, scene.canonical.means.dtype
    onehot = torch.eye(num_objects + 1, dtype=dtype, device=device)[torch.as_tensor(object_ids + 1, device=device)]
    out, expected, alpha = render_path(scene, cameras, background=background, features=onehot)
    surface = alpha >= 0.5
    rgb = out[..., :3].cpu().numpy().astype(np.float32)
    depth = torch.where(surface, expected, torch.inf).cpu().numpy().astype(np.float32)
    ids = torch.where(surface, out[..., 3:].argmax(-1), NO_SURFACE).to(torch.uint8).cpu().numpy()
    return rgb, depth, ids


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    q = axis_angle_to_quat(torch.as_tensor(axis, dtype=torch.float64, device="cpu"),
                           torch.tensor(float(angle), dtype=torch.float64, device="cpu"))
    return quat_to_rotmat(q).cpu().numpy()


def build_scene(spec: dict[str, Any], rng: np.random.Generator) -> tuple[DynamicGaussians, np.ndarray]:
    """The :class:`DynamicGaussians` of a spec (deformation at the T frame times; none if nothing moves)
    and the object id (M,) of every Gaussian (−1 = background)."""
    canon, ids = build_gaussians(spec, rng)
    T = spec["num_frames"]
    times = np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1)
    movers = [k for k, o in enumerate(spec["objects"]) if o["motion"] is not None]
    if not movers:
        return DynamicGaussians(canon), ids
    M = canon.num_gaussians
    d_means = np.zeros((T, M, 3))
    d_quats = np.tile(np.array([1.0, 0, 0, 0]), (T, M, 1))
    d_scales = np.zeros((T, M, 3))
    means = canon.means.double().cpu().numpy()
    for k in movers:
        sel = ids == k
        for i, t in enumerate(times):
            p0, d, R, S = object_transform(spec["objects"][k], float(t))
            d_means[i, sel] = p0 + d + ((means[sel] - p0) * S) @ R.T - means[sel]
            d_quats[i, sel] = rotmat_to_quat(torch.as_tensor(R, device="cpu")).numpy()  # device: made on the CPU
            d_scales[i, sel] = np.log(S).mean()  # isotropic approximation of the Gaussian's shape; means exact
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32, device="cpu")  # noqa: E731
    return DynamicGaussians(canon, f32(times), f32(d_means), f32(d_quats), f32(d_scales)), ids


def camera_path(spec: dict[str, Any], cam: dict[str, Any]) -> CameraPath:
    """T cameras of one sampled camera (square images of ``spec["size"]`` pixels): eye at azimuth θ and distance d,
    (d·sin θ, ground_y − height, −d·cos θ), looking ``target_height`` above the centre; over t ∈ [0, 1] orbit
    θ += δ·t, dolly / truck move eye and target by δ·t along forward / right, pan turns by δ·t towards right."""
    T, size = spec["num_frames"], spec["size"]
    t = np.linspace(0.0, 1.0, T) if T > 1 else np.zeros(1)
    gy, d = spec["ground_y"], cam["distance"]
    theta = cam["azimuth"] + (cam["delta"] * t if cam["kind"] == "orbit" else 0.0 * t)
    eyes = np.stack([d * np.sin(theta), np.full(T, gy - cam["height"]), -d * np.cos(theta)], 1)
    targets = np.tile(np.array([0.0, gy - cam["target_height"], 0.0]), (T, 1))
    f = -eyes[0] * np.array([1.0, 0.0, 1.0])
    f /= np.linalg.norm(f)
    r = np.array([f[2], 0.0, -f[0]])  # down × f: the camera's x axis in look_at
    if cam["kind"] == "dolly":
        eyes, targets = eyes + cam["delta"] * t[:, None] * f, targets + cam["delta"] * t[:, None] * f
    elif cam["kind"] == "truck":
        eyes, targets = eyes + cam["delta"] * t[:, None] * r, targets + cam["delta"] * t[:, None] * r
    elif cam["kind"] == "pan":
        to = targets - eyes
        a = cam["delta"] * t[:, None]
        fwd, side = (to * f).sum(1, keepdims=True), (to * r).sum(1, keepdims=True)
        rest = to - fwd * f - side * r
        targets = eyes + rest + (fwd * np.cos(a) - side * np.sin(a)) * f + (fwd * np.sin(a) + side * np.cos(a)) * r
    cpu = lambda a: torch.as_tensor(a, device="cpu")  # noqa: E731
    viewmats = look_at(cpu(eyes), cpu(targets), up=tuple(_UP)).float()
    K = intrinsics_from_fov(size, size, fov_x_deg=cam["fov_x_deg"])
    return CameraPath(viewmats, K.expand(T, 3, 3).clone(), size, size)


def track_visibility(points: np.ndarray, cameras: CameraPath, depth: np.ndarray) -> np.ndarray:
    """Visibility (P, T) bool of world points (P, T, 3) metres in the reference camera's T ``cameras`` with rendered
    ``depth`` (T, H, W) metres (FORMAT.md, tracks.npz; tolerance :data:`VISIBILITY_TOL_M` + VISIBILITY_TOL_REL·z)."""
    V = cameras.viewmats.double().cpu().numpy()
    K = cameras.Ks.double().cpu().numpy()
    cam = np.einsum("tij,ptj->pti", V[:, :3, :3], points.astype(np.float64)) + V[None, :, :3, 3]
    z = cam[..., 2]
    zs = np.where(z > 1e-9, z, 1.0)
    u = K[None, :, 0, 0] * cam[..., 0] / zs + K[None, :, 0, 2]
    v = K[None, :, 1, 1] * cam[..., 1] / zs + K[None, :, 1, 2]
    inside = (z > 1e-9) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
    ui = np.clip(np.floor(u), 0, cameras.width - 1).astype(np.int64)
    vi = np.clip(np.floor(v), 0, cameras.height - 1).astype(np.int64)
    frame = np.broadcast_to(np.arange(points.shape[1]), z.shape)
    tol = VISIBILITY_TOL_M + VISIBILITY_TOL_REL * z
    return inside & (depth[frame, vi, ui] >= z - tol)


@dataclass
class SynthScene:
    """A rendered synthetic scene, before writing: per camera (reference first) a path, rgb (T, H, W, 3) float32 in
    [0, 1], depth (T, H, W) float32 metres and object id maps (T, H, W) uint8 (:func:`render_camera`);
    ``object_ids`` (M,) as :func:`build_gaussians`; the tracked Gaussians ``track_ids`` (P,), their ``points``
    (P, T, 3) float32 metres and ``visibility`` (P, T) bool; the objects' ``poses`` (:func:`object_poses`)."""

    spec: dict[str, Any]
    scene: DynamicGaussians
    object_ids: np.ndarray
    cameras: list[CameraPath]
    rgb: list[np.ndarray]
    depth: list[np.ndarray]
    track_ids: np.ndarray
    points: np.ndarray
    visibility: np.ndarray
    caption: str
    id_maps: list[np.ndarray]
    poses: np.ndarray


def render_spec(spec: dict[str, Any], rng: np.random.Generator, device: str | torch.device = "cpu") -> SynthScene:
    """Build, render (on ``device``; one torch thread) and track a scene spec; the result is on the CPU. ``rng``
    draws the texture jitter and the tracked points. CUDA renders with gsplat when installed (float rounding and
    its 0.999 alpha clamp differ from the CPU renderer)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene, ids = build_scene(spec, rng)
        paths = [camera_path(spec, c) for c in spec["cameras"]]
        rendered = scene.to(device)
        rgbs, depths, id_maps = [], [], []
        for p in paths:
            rgb, depth, id_map = render_camera(rendered, ids, len(spec["objects"]), p, tuple(spec["background"]))
            rgbs.append(rgb)
            depths.append(depth)
            id_maps.append(id_map)
    finally:
        torch.set_num_threads(threads)
    obj = np.flatnonzero(ids >= 0)
    pick = np.sort(rng.choice(obj, size=min(MAX_TRACKS, len(obj)), replace=False))
    base = scene.canonical.means.cpu().numpy()[pick]  # (P, 3)
    if scene.is_static:
        points = np.repeat(base[:, None], spec["num_frames"], axis=1)
    else:  # exactly the means scene.at(t_i) renders (key times are the frame times)
        points = base[:, None] + scene.d_means.cpu().numpy()[:, pick].transpose(1, 0, 2)
    points = points.astype(np.float32)
    visibility = track_visibility(points, paths[0], depths[0])
    caption = caption_for(spec, paths[0].viewmats[0, :3, :3].double().cpu().numpy())
    return SynthScene(spec, scene, ids, paths, rgbs, depths, pick, points, visibility, caption, id_maps,
                      object_poses(spec))


def write_synth_scene(path: str | os.PathLike, result: SynthScene, extra: dict[str, Any] | None = None,
                      replace: bool = False) -> Path:
    """Write a :class:`SynthScene` as a scene folder atomically (cameras ``cam00``, …; meta ``"synth"``: the spec
    plus ``extra``) and return it."""
    spec, T = result.spec, result.spec["num_frames"]
    with SceneWriter(path, source="synthetic", dynamic=spec["dynamic"], depth_source="ground_truth", num_frames=T,
                     fps=spec["fps"], extra={"synth": {**(extra or {}), "spec": spec}}, replace=replace) as w:
        for c, (p, rgb, depth) in enumerate(zip(result.cameras, result.rgb, result.depth, strict=True)):
            name = f"cam{c:02d}"
            w.add_camera(name, p)
            for i in range(T):
                w.write_frame(name, i, rgb[i], depth[i])
        w.write_tracks(result.points, result.visibility)
        w.write_objects(result.poses, {f"cam{c:02d}": m for c, m in enumerate(result.id_maps)})
        w.write_caption(result.caption)
    return Path(path)


def generate_scene(out_dir: str | os.PathLike, index: int, seed: int, *, size: int = SYNTH.size,
                   frames: int = SYNTH.frames, cameras: int = SYNTH.cameras,
                   static_ratio: float = SYNTH.static_ratio, texture_ratio: float = SYNTH.texture_ratio,
                   motions: tuple[str, ...] = SYNTH.motions, max_movers: int | None = None,
                   replace: bool = False, device: str | torch.device = "cpu") -> Path:
    """Sample, render (on ``device``) and write scene ``index`` of run ``seed`` to ``out_dir/scene_{index:05d}``;
    static with probability ``static_ratio``, each surface image-textured with probability ``texture_ratio``, its
    moving objects' kinds from ``motions``, at most ``max_movers`` of them (:func:`sample_scene_spec`; meta.json's
    ``synth`` records the two when they restrict the draw). Returns the folder. Raises FileExistsError: the
    scene exists and ``replace`` is false; ValueError: bad ``motions`` or ``max_movers``."""
    kinds, max_movers = check_motions(motions, max_movers)
    rng = np.random.default_rng([seed, index])
    dynamic = bool(rng.random() >= static_ratio)
    spec = sample_scene_spec(rng, dynamic=dynamic, num_cameras=cameras, size=size, num_frames=frames,
                             texture_ratio=texture_ratio, motions=kinds, max_movers=max_movers)
    result = render_spec(spec, rng, device)
    extra = {"seed": seed, "index": index}
    if kinds != MOTIONS:
        extra["motions"] = list(kinds)
    if max_movers is not None:
        extra["max_movers"] = max_movers
    return write_synth_scene(Path(out_dir) / scene_name(index), result, extra, replace)
