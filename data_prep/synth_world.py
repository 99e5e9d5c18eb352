"""Random specifications of synthetic scenes (layout, objects, motions, cameras, lighting) and their captions:
numpy sampling from one generator into JSON-serialisable dicts (stored in ``meta.json["synth"]``).

World frame (metres): x right, **y down**, z forward; the ground is the plane y = ``ground_y`` > 0 with the scene
centre (0, ground_y, 0), inside a cylindrical wall of radius ``room_radius``. Object motion over t ∈ [0, 1] is
``p(t) = p0 + d(t) + R(t)·(S(t) ⊙ (p − p0))`` (:func:`data_prep.synth.object_transform`):
- ``translate``: d(t) = t·v (v horizontal); spheres roll without slipping: R about up × v̂ by |d|/r;
- ``rotate``: R(t) about a unit axis by ω·t (vertical axis → "spins", other → "tumbles");
- ``bounce``: d(t) = t·v + (0, −4H·τ(1−τ), 0), τ = frac(n·t): n parabolic hops of height H;
- ``deform``: S(t) = 1 + a·s·(1, 1, 1) ("pulses") or (1 + a/2·s, 1 − a·s, 1 + a/2·s), s = sin(2πft), about the
  object's bottom.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from diff4splat.utils.checks import check_int, check_number

from .textures import IMAGE_TEXTURES, load_texture, texture_names

__all__ = ["COLORS", "SHAPES", "MOTIONS", "CAMERA_MOTIONS", "TEXTURES", "sample_scene_spec", "caption_for",
           "direction_word", "check_motions", "DIRECTION_PHRASES", "SynthDefaults", "SYNTH"]

COLORS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.12, 0.10), "orange": (0.95, 0.50, 0.08), "yellow": (0.95, 0.85, 0.15),
    "green": (0.20, 0.70, 0.20), "teal": (0.10, 0.60, 0.60), "blue": (0.15, 0.30, 0.90),
    "purple": (0.55, 0.20, 0.75), "pink": (0.95, 0.50, 0.70), "white": (0.92, 0.92, 0.90),
    "black": (0.08, 0.08, 0.09), "grey": (0.50, 0.50, 0.52), "brown": (0.50, 0.30, 0.15),
}
"""Named base colours (linear-ish RGB in [0, 1]); sampled colours jitter these by ±0.06."""

SHAPES: dict[str, str] = {"sphere": "ball", "box": "box", "ellipsoid": "egg", "blob": "blob"}
"""Object shapes and the noun used in captions."""

MOTIONS: tuple[str, ...] = ("translate", "rotate", "bounce", "deform")
"""Object motion kinds (module docstring); a scene draws each moving object's kind uniformly from these."""
CAMERA_MOTIONS: tuple[str, ...] = ("orbit", "dolly", "pan", "truck", "static")
TEXTURES: dict[str, str] = {"plain": "", "checker": "checkered", "stripes": "striped", "noise": "spotted"}
"""Procedural textures and their caption adjective (kind ``"image"``: :data:`data_prep.textures.IMAGE_TEXTURES`)."""


@dataclass(frozen=True)
class SynthDefaults:
    """What a synthetic scene is made with when the caller names nothing: the one home of the defaults of
    ``data_prep synth``, :func:`data_prep.synth_dataset.synthesize` and :func:`data_prep.synth.generate_scene`.

    Attributes:
        size: image width = height, pixels (the ``base`` model's resolution).
        frames: frames per camera (the ``base`` model's clip length, 1 + 4·4).
        cameras: synchronised cameras per scene (one to train on, one to supervise novel views).
        static_ratio: probability of a static scene.
        texture_ratio: probability that a surface gets a crop of a bundled photograph as texture.
        motions: the kinds a moving object draws from (all of :data:`MOTIONS`).
    """

    size: int = 64
    frames: int = 17
    cameras: int = 2
    static_ratio: float = 0.3
    texture_ratio: float = 0.5
    motions: tuple[str, ...] = MOTIONS


SYNTH = SynthDefaults()
"""The defaults of a synthetic scene (:class:`SynthDefaults`)."""

_MATERIALS = ("wooden", "tiled", "concrete", "carpeted", "grassy", "sandy")


def _color(rng: np.random.Generator, exclude: tuple[str, ...] = ()) -> tuple[str, list[float]]:
    names = [n for n in COLORS if n not in exclude]
    name = names[int(rng.integers(len(names)))]
    rgb = np.clip(np.asarray(COLORS[name]) + rng.uniform(-0.06, 0.06, 3), 0.02, 0.98)
    return name, rgb.round(4).tolist()


def _texture(rng: np.random.Generator, kinds: tuple[str, ...], base: list[float], scale: float) -> dict[str, Any]:
    """A procedural texture: kind, two colours, spatial frequency (cycles per metre), angle, blobs."""
    kind = kinds[int(rng.integers(len(kinds)))]
    second = np.clip(np.asarray(base) * rng.uniform(0.3, 0.7) + rng.uniform(0.0, 0.35, 3), 0.02, 0.98)
    if rng.random() < 0.35:  # a contrasting second colour instead of a shade of the first
        second = np.asarray(_color(rng)[1])
    tex = {"kind": kind, "color2": second.round(4).tolist(), "freq": float(rng.uniform(0.6, 1.6) / scale),
           "angle": float(rng.uniform(0, math.pi)), "noise": float(rng.uniform(0.0, 0.08))}
    if kind == "noise":
        n = int(rng.integers(4, 12))
        tex["blobs"] = {"centers": rng.uniform(0, 1, (n, 2)).round(4).tolist(),
                        "radii": rng.uniform(0.05, 0.2, n).round(4).tolist(),
                        "colors": np.clip(rng.uniform(0, 1, (n, 3)), 0.02, 0.98).round(4).tolist()}
    return tex


def _image_texture(rng: np.random.Generator, base: list[float]) -> dict[str, Any]:
    """An image texture (fields: :mod:`data_prep.textures`): a random square crop of a bundled image, tinted."""
    names = texture_names()
    name = names[int(rng.integers(len(names)))]
    img = load_texture(name)
    h, w = img.shape[:2]
    c = float(rng.uniform(0.4, 1.0) * min(h, w))
    crop = [float(rng.uniform(0, w - c)), float(rng.uniform(0, h - c)), c]
    grey = img.ndim == 2
    bright = np.clip(0.2 + 1.5 * np.asarray(base), 0.0, 1.0)
    tint = bright if grey else 1 - rng.uniform(0.0, 0.25) * (1 - bright)
    return {"kind": "image", "file": name, "grey": grey, "crop": np.round(crop, 3).tolist(),
            "metres": float(rng.uniform(0.5, 3.0)),
            "angle": float(rng.uniform(0, 2 * math.pi)) if rng.random() < 0.5 else 0.0,
            "tint": tint.round(4).tolist(), "noise": float(rng.uniform(0.0, 0.04))}


def _apply_image_textures(rng: np.random.Generator, spec: dict[str, Any], ratio: float) -> None:
    """Give each surface an image texture with probability ``ratio``, in place; draws nothing when ``ratio`` is 0."""
    if ratio <= 0:
        return
    for surface in (spec["ground"], spec["wall"], *spec["objects"]):
        if rng.random() < ratio:
            surface["texture"] = _image_texture(rng, surface["color"])
            if surface is spec["ground"]:
                surface["material"] = IMAGE_TEXTURES[surface["texture"]["file"]]


DIRECTION_PHRASES: tuple[tuple[str, str], ...] = (("to the right", "to the left"), ("downwards", "upwards"),
                                                  ("away from the camera", "towards the camera"))
"""Caption phrases of the camera frame's axes x, y, z (x right, y down, z forward): (positive, negative)."""


def direction_word(v_cam: np.ndarray) -> str:
    """Dominant direction of a camera-frame vector (x right, y down, z forward) as a caption phrase
    (:data:`DIRECTION_PHRASES`)."""
    axis = int(np.argmax(np.abs(v_cam)))
    return DIRECTION_PHRASES[axis][0 if v_cam[axis] > 0 else 1]


def check_motions(motions: object, max_movers: object, names: tuple[str, str] = ("motions", "max_movers")
                  ) -> tuple[tuple[str, ...], int | None]:
    """``motions`` as a tuple: a non-empty sequence of distinct :data:`MOTIONS` kinds (in :data:`MOTIONS`' order, so
    the same set draws the same scenes); ``max_movers`` None or an int ≥ 1. ``names``: how messages call the two.
    Raises ValueError: an unknown, repeated or missing kind, or a bad ``max_movers`` (named)."""
    kinds = (motions,) if isinstance(motions, str) else tuple(motions) if isinstance(motions, (list, tuple)) else None
    if not kinds or len(set(kinds)) != len(kinds) or any(k not in MOTIONS for k in kinds):
        raise ValueError(f"{names[0]} must be distinct kinds among {', '.join(MOTIONS)}, got {motions!r}")
    if max_movers is not None:
        check_int(names[1], max_movers, 1)
    return tuple(k for k in MOTIONS if k in kinds), None if max_movers is None else int(max_movers)


def _sample_motion(rng: np.random.Generator, shape: str, center: np.ndarray, room: float,
                   kinds: tuple[str, ...]) -> dict[str, Any]:
    kind = kinds[int(rng.integers(len(kinds)))]
    heading = rng.uniform(0, 2 * math.pi)
    direction = np.array([math.cos(heading), 0.0, math.sin(heading)])
    # keep the end point within 55% of the room radius from the centre
    reach = max(0.0, 0.55 * room - float(np.linalg.norm(center[[0, 2]])))
    if kind == "translate":
        dist = float(min(rng.uniform(0.5, 1.6), reach + 0.3))
        return {"kind": "translate", "velocity": (direction * dist).round(5).tolist(), "roll": shape == "sphere"}
    if kind == "rotate":
        vertical = rng.random() < 0.7
        axis = np.array([0.0, 1.0, 0.0]) if vertical else rng.normal(size=3)
        axis = axis / np.linalg.norm(axis)
        omega = float(rng.choice([-1, 1]) * rng.uniform(0.5, 2.0) * math.pi)
        return {"kind": "rotate", "axis": axis.round(6).tolist(), "omega": omega}
    if kind == "bounce":
        drift = float(rng.uniform(0.0, min(1.0, reach + 0.2)))
        return {"kind": "bounce", "velocity": (direction * drift).round(5).tolist(),
                "height": float(rng.uniform(0.3, 1.0)), "hops": int(rng.integers(1, 4))}
    return {"kind": "deform", "mode": "pulse" if rng.random() < 0.5 else "squash",
            "amplitude": float(rng.uniform(0.15, 0.35)), "freq": float(rng.choice([1.0, 1.5, 2.0]))}


def _sample_object(rng: np.random.Generator, others: list[dict]) -> dict[str, Any] | None:
    shape = list(SHAPES)[int(rng.integers(len(SHAPES)))]
    r = float(rng.uniform(0.2, 0.55))
    if shape == "sphere" or shape == "blob":
        half = [r, r, r]
    elif shape == "box":
        half = rng.uniform(0.15, 0.5, 3).round(4).tolist()
    else:
        half = np.maximum(r * rng.uniform(0.6, 1.3, 3), 0.15).round(4).tolist()
    for _ in range(20):  # rejection sampling of a free spot on the ground
        rho, phi = 1.4 * math.sqrt(rng.random()), rng.uniform(0, 2 * math.pi)
        xz = np.array([rho * math.cos(phi), rho * math.sin(phi)])
        ok = all(np.linalg.norm(xz - np.asarray(o["center"])[[0, 2]]) > max(half) + max(o["half"]) + 0.1
                 for o in others)
        if ok:
            break
    else:
        return None
    name, rgb = _color(rng)
    obj = {"shape": shape, "half": [float(h) for h in half], "color_name": name, "color": rgb,
           "texture": _texture(rng, tuple(TEXTURES), rgb, 0.3), "opacity": float(rng.uniform(0.9, 0.99)),
           "lumps": rng.normal(0, 0.12, 6).round(4).tolist() if shape == "blob" else [],
           "yaw": float(rng.uniform(0, 2 * math.pi))}
    obj["center"] = [float(xz[0]), 0.0, float(xz[1])]  # y is set relative to the ground by the caller
    obj["motion"] = None
    return obj


def _sample_camera(rng: np.random.Generator, fov: float, kind: str) -> dict[str, Any]:
    cam = {"kind": kind, "fov_x_deg": fov, "azimuth": float(rng.uniform(-math.pi, math.pi)),
           "distance": float(rng.uniform(2.6, 4.0)), "height": float(rng.uniform(0.5, 1.6)),
           "target_height": float(rng.uniform(0.2, 0.6))}
    sign = float(rng.choice([-1.0, 1.0]))
    if kind == "orbit":
        cam["delta"] = sign * float(rng.uniform(math.radians(20), math.radians(70)))  # radians of azimuth
    elif kind == "dolly":
        cam["delta"] = sign * float(rng.uniform(0.4, 0.35 * cam["distance"] if sign > 0 else 1.0))  # metres forward
    elif kind == "pan":
        cam["delta"] = sign * float(rng.uniform(math.radians(10), math.radians(30)))  # radians of yaw
    elif kind == "truck":
        cam["delta"] = sign * float(rng.uniform(0.4, 1.2))  # metres to the right
    else:
        cam["delta"] = 0.0
    return cam


def sample_scene_spec(rng: np.random.Generator, *, dynamic: bool, num_cameras: int, size: int,
                      num_frames: int, fps: float = 8.0, texture_ratio: float = SYNTH.texture_ratio,
                      motions: tuple[str, ...] = MOTIONS, max_movers: int | None = None) -> dict[str, Any]:
    """Sample a complete scene description from the scene's own generator ``rng``. ``dynamic``: at least one object
    moves (else none); ``num_cameras`` ≥ 1 (camera 0 the reference); ``size``: image width = height, pixels; ``fps``:
    Hz; ``texture_ratio`` in [0, 1]: probability that a surface gets an image texture, drawn after the procedural scene
    so that nothing else depends on it; ``motions``: the kinds a moving object draws from (:func:`check_motions`);
    ``max_movers``: at most this many objects move (None: each object moves with probability 0.7, at least one). Returns
    a JSON-serialisable dict: ``dynamic``, ``size``, ``num_frames``, ``fps``, ``ground_y``, ``room_radius``, ``light``
    {direction (3,), ambient, tint (3,)}, ``background`` (3,), ``ground`` / ``wall`` {material, color_name, color,
    texture}, ``objects`` (1–4 dicts: shape, half extents (3,) and center (3,) metres, colour, texture, motion or None)
    and ``cameras`` (kind, fov_x_deg, azimuth, distance, height, target_height, delta). Raises ValueError:
    ``texture_ratio`` is not a number in [0, 1]; bad ``motions`` or ``max_movers``."""
    check_number("texture_ratio", texture_ratio, lo=0, hi=1)
    kinds, max_movers = check_motions(motions, max_movers)
    room = float(rng.uniform(5.0, 6.0))
    ground_y = float(rng.uniform(0.8, 1.5))
    light = rng.normal(size=3)
    light[1] = -abs(light[1]) - 0.5  # from above (y down)
    ground_name, ground_rgb = _color(rng, exclude=("black",))
    wall_name, wall_rgb = _color(rng, exclude=(ground_name,))
    spec: dict[str, Any] = {
        "dynamic": bool(dynamic), "size": int(size), "num_frames": int(num_frames), "fps": float(fps),
        "room_radius": room, "ground_y": ground_y,
        "light": {"direction": (light / np.linalg.norm(light)).round(6).tolist(),
                  "ambient": float(rng.uniform(0.35, 0.6)),
                  "tint": np.clip(1 + rng.normal(0, 0.06, 3), 0.85, 1.15).round(4).tolist()},
        "background": np.clip(rng.uniform(0.3, 0.95, 3), 0, 1).round(4).tolist(),
        "ground": {"material": _MATERIALS[int(rng.integers(len(_MATERIALS)))], "color_name": ground_name,
                   "color": ground_rgb, "texture": _texture(rng, ("checker", "stripes", "noise"), ground_rgb, 1.2)},
        "wall": {"color_name": wall_name, "color": wall_rgb,
                 "texture": _texture(rng, ("plain", "checker", "stripes", "noise"), wall_rgb, 1.5)},
    }
    objects: list[dict] = []
    for _ in range(int(rng.integers(1, 5))):
        obj = _sample_object(rng, objects)
        if obj is not None:
            obj["center"][1] = ground_y - obj["half"][1]  # resting on the ground (y down)
            objects.append(obj)
    if dynamic:
        movers = [i for i in range(len(objects)) if rng.random() < 0.7] or [int(rng.integers(len(objects)))]
        for i in movers[:max_movers]:
            o = objects[i]
            o["motion"] = _sample_motion(rng, o["shape"], np.asarray(o["center"]), room, kinds)
    spec["objects"] = objects
    fov = float(rng.uniform(45, 70))
    spec["cameras"] = [_sample_camera(rng, fov, CAMERA_MOTIONS[int(rng.integers(len(CAMERA_MOTIONS)))])
                       for _ in range(num_cameras)]
    _apply_image_textures(rng, spec, float(texture_ratio))
    return spec


def _object_phrase(o: dict[str, Any]) -> str:
    """"a red striped ball"; an RGB image texture shows its own colours, so it gets no colour word."""
    tex = o["texture"]
    image = tex["kind"] == "image"
    colour = "" if image and not tex["grey"] else o["color_name"]
    texture = IMAGE_TEXTURES[tex["file"]] if image else TEXTURES[tex["kind"]]
    words = " ".join(w for w in (colour, texture, SHAPES[o["shape"]]) if w)
    return ("an " if words[0] in "aeiou" else "a ") + words


def _motion_phrase(m: dict[str, Any], shape: str, cam_R: np.ndarray) -> str:
    if m["kind"] == "translate":
        verb = "rolls" if m.get("roll") else "slides"
        return f"{verb} {direction_word(cam_R @ np.asarray(m['velocity']))}"
    if m["kind"] == "rotate":
        axis = np.asarray(m["axis"])
        if abs(axis[1]) > 0.99:  # a positive angle about +y (down) looks clockwise from above
            clockwise = (m["omega"] > 0) == (axis[1] > 0)
            return "spins " + ("clockwise" if clockwise else "counter-clockwise")
        return "tumbles"
    if m["kind"] == "bounce":
        hops = {1: "once", 2: "twice"}.get(m["hops"], f"{m['hops']} times")
        v = np.asarray(m["velocity"])
        where = f" {direction_word(cam_R @ v)}" if np.linalg.norm(v) > 0.3 else " in place"
        return f"bounces {hops}{where}"
    return "pulses in size" if m["mode"] == "pulse" else "squashes and stretches"


def _camera_phrase(cam: dict[str, Any], static_scene: bool = False) -> str:
    """"the camera orbits right around the scene"; with ``static_scene`` it ends in a preposition ("… around")."""
    d, kind = cam["delta"], cam["kind"]
    if kind == "orbit":  # azimuth grows → the eye moves to the camera's right (synth.camera_path)
        return f"the camera orbits {'right' if d > 0 else 'left'} around" + ("" if static_scene else " the scene")
    if kind == "dolly":
        return f"the camera dollies {'forward' if d > 0 else 'backward'}" + (" through" if static_scene else "")
    if kind in ("pan", "truck"):
        return f"the camera {kind}s {'right' if d > 0 else 'left'}" + (" across" if static_scene else "")
    return "the camera stays still" + (" in front of" if static_scene else "")


def caption_for(spec: dict[str, Any], ref_rotation: np.ndarray) -> str:
    """One-line caption of what moves and how (objects, then the reference camera), directions in the frame of
    ``ref_rotation`` (3, 3), the reference camera's world-to-camera rotation at frame 0: e.g. "a red striped ball rolls
    to the left and a blue box stays still on a wooden floor, while the camera orbits left around the scene"."""
    floor = f"on a {spec['ground']['material']} floor"
    objs = spec["objects"]
    if not spec["dynamic"] or all(o["motion"] is None for o in objs):
        things = _join([_object_phrase(o) for o in objs])
        return f"{_camera_phrase(spec['cameras'][0], True)} a static scene with {things} {floor}"
    clauses = [f"{_object_phrase(o)} {_motion_phrase(o['motion'], o['shape'], ref_rotation)}"
               for o in objs if o["motion"]]
    still = [_object_phrase(o) for o in objs if o["motion"] is None]
    if still:
        clauses.append(f"{_join(still)} {'stays' if len(still) == 1 else 'stay'} still")
    return f"{_join(clauses)} {floor}, while {_camera_phrase(spec['cameras'][0])}"


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]
