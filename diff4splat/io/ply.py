"""Gaussians as binary PLY in the INRIA 3DGS layout (Kerbl et al. 2023, ``GaussianModel.save_ply``).

Vertex properties, all float32, binary little-endian, in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 … f_rest_{3(K−1)−1}
    opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

f_dc_c = sh[:, 0, c]; f_rest is channel-major, f_rest_{c·(K−1)+k−1} = sh[:, k, c] (INRIA transposes features_rest
to (N, 3, K−1)); opacity = logit(clamp(o, 1e-6, 1 − 1e-6)); scale_i = log(s_i); rot = the quaternion wxyz as stored;
normals are zero. The reader accepts any binary little-endian PLY whose vertex element has scalar properties with
these names (others ignored, f_rest_* ordered by index as INRIA's loader does).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from diff4splat.io.atomic import atomic_output_path
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.constants import OPACITY_EPS

__all__ = ["save_ply", "ply_bytes", "load_ply", "ply_property_names"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def ply_property_names(sh_coeffs: int) -> list[str]:
    """INRIA vertex property names, in file order, for K = ``sh_coeffs`` SH coefficients per colour."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (sh_coeffs - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def _ply_parts(gaussians: Gaussians) -> tuple[bytes, np.ndarray]:
    """The PLY header and the (N, P) little-endian float32 vertex records in file order (logit and log in float64)."""
    gaussians.validate()
    g = gaussians.detach().to("cpu")  # device: the records are a CPU array
    n, k = g.num_gaussians, g.sh.shape[1]
    names = ply_property_names(k)
    values = torch.empty(n, len(names), dtype=torch.float32, device="cpu")  # device: the records are host bytes
    o = 9 + 3 * (k - 1)  # the opacity column
    values[:, 0:3] = g.means
    values[:, 3:6] = 0  # the normals
    values[:, 6:9] = g.sh[:, 0, :]
    values[:, 9:o] = g.sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1))  # channel-major rest coefficients
    opac = g.opacities.double().clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    values[:, o] = torch.log(opac / (1.0 - opac))
    values[:, o + 1:o + 4] = torch.log(g.scales.double())
    values[:, o + 4:o + 8] = g.quats
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    records = np.asarray(values.numpy(), dtype="<f4")  # device: a CPU tensor; no copy on little-endian hosts
    return ("\n".join(header) + "\n").encode("ascii"), records


def ply_bytes(gaussians: Gaussians) -> bytes:
    """The binary PLY file :func:`save_ply` writes, as bytes; ValueError if ``gaussians`` fails validation."""
    header, values = _ply_parts(gaussians)
    return header + values.tobytes()


def save_ply(path: str | os.PathLike, gaussians: Gaussians) -> None:
    """Write N activated Gaussians (scales > 0 metres, opacities in [0, 1], SH (N, K, 3); any device) as an INRIA
    binary PLY (module docstring) of float32, atomically; ValueError if they fail :meth:`Gaussians.validate`."""
    header, values = _ply_parts(gaussians)
    with atomic_output_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(values.data)  # the records' own buffer: no bytes copy of the file


_MAX_HEADER_LINE = 1024
"""Bytes a PLY header line may take, so a binary file is not read whole looking for a line break."""
_MAX_HEADER_LINES = 4096
"""Lines a PLY header may take (the INRIA layout at SH degree 3 has 65)."""


def _read_header(f, path: Path) -> tuple[int, np.dtype]:
    if f.readline(_MAX_HEADER_LINE).strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
    n_vertex, props, current, fmt = None, [], None, None
    for _ in range(_MAX_HEADER_LINES):
        line = f.readline(_MAX_HEADER_LINE)
        if not line:
            raise ValueError(f"{path}: PLY header has no end_header (truncated file?)")
        if not line.endswith(b"\n"):
            raise ValueError(f"{path}: PLY header line longer than {_MAX_HEADER_LINE - 1} bytes (not a PLY header)")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element":
            if len(words) != 3:
                raise ValueError(f"{path}: malformed PLY element line {line!r}")
            if n_vertex is not None:
                raise ValueError(f"{path}: only a single 'vertex' element is supported, found {words[1]!r} after it")
            if words[1] != "vertex":
                raise ValueError(f"{path}: expected element 'vertex', found {words[1]!r}")
            if not words[2].isdigit():
                raise ValueError(f"{path}: PLY vertex count must be a non-negative integer, got {words[2]!r}")
            n_vertex, current = int(words[2]), words[1]
        elif words[0] == "property":
            if current != "vertex" or len(words) != 3 or words[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported PLY property line {line.decode(errors='replace')!r} "
                                 "(list properties are not supported)")
            props.append((words[2], "<" + _PLY_TYPES[words[1]]))
    else:
        raise ValueError(f"{path}: PLY header has no end_header within {_MAX_HEADER_LINES} lines")
    if fmt != "binary_little_endian":
        raise ValueError(f"{path}: only binary_little_endian PLY is supported, got format {fmt!r}")
    if n_vertex is None:
        raise ValueError(f"{path}: PLY has no vertex element")
    names = [name for name, _ in props]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: PLY vertex properties repeat a name: {names}")
    return n_vertex, np.dtype(props)


def load_ply(path: str | os.PathLike) -> Gaussians:
    """Read Gaussians from a binary PLY in the INRIA layout (inverse of :func:`save_ply`; properties of any scalar
    type, others ignored) as float32 :class:`Gaussians`: means (N, 3) metres, quats (N, 4) wxyz as stored,
    scales = exp(scale_*), opacities = sigmoid(opacity), sh (N, K, 3), K = 1 + (number of f_rest_*)/3.

    Raises:
        FileNotFoundError: ``path`` is not an existing file.
        ValueError: starting with ``path``: not a binary little-endian PLY (a header line over 1 KB, no
            ``end_header``), a required property missing, f_rest_* not 3·(K−1) for K ∈ {1, 4, 9, 16}, truncated
            data, or values failing :meth:`Gaussians.validate`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        n, dtype = _read_header(f, path)
        names = set(dtype.names or ())
        required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
        required += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
        missing = [r for r in required if r not in names]
        if missing:
            raise ValueError(f"{path}: missing PLY vertex properties {missing}")
        found = {p for p in names if p.startswith("f_rest_")}
        rest = [f"f_rest_{i}" for i in range(len(found))]  # INRIA's order: by index
        k = 1 + len(rest) // 3
        if len(rest) % 3 or math.isqrt(k) ** 2 != k or k > 16 or set(rest) != found:
            raise ValueError(f"{path}: {len(rest)} f_rest_* properties do not form f_rest_0 … f_rest_{{3·(K−1)−1}} "
                             "with K a square ≤ 16")
        size = n * dtype.itemsize
        left = path.stat().st_size - f.tell()
        data = f.read(size) if size <= left else b""  # a corrupt count must not allocate its bytes
    if len(data) < size:
        raise ValueError(f"{path}: truncated PLY, expected {n} vertices of {dtype.itemsize} bytes")
    v = np.frombuffer(data, dtype=dtype, count=n)

    def cols(keys: list[str]) -> torch.Tensor:
        if not keys:
            return torch.zeros(n, 0, dtype=torch.float64, device="cpu")  # files load onto the CPU
        return torch.from_numpy(np.stack([v[key].astype(np.float64) for key in keys], axis=1))

    sh = torch.empty(n, k, 3, dtype=torch.float64, device="cpu")
    sh[:, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    sh[:, 1:, :] = cols(rest).reshape(n, 3, k - 1).transpose(1, 2)
    try:  # validated in float64, then again in float32 (a log-scale of 100 overflows float32)
        return Gaussians(
            means=cols(["x", "y", "z"]),
            quats=cols([f"rot_{i}" for i in range(4)]),
            scales=torch.exp(cols([f"scale_{i}" for i in range(3)])),
            opacities=torch.sigmoid(cols(["opacity"])[:, 0]),
            sh=sh,
        ).to(torch.float32)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
