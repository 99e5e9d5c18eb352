"""The canonical container of activated 3D Gaussians (means, quats, scales, opacities, SH)."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

from torch import Tensor

from diff4splat.scene.quaternions import quat_normalize
from diff4splat.utils.checks import check_finite

__all__ = ["Gaussians", "SH_C0", "rgb_to_sh0", "sh0_to_rgb"]

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonic basis constant 1/(2√π) (INRIA 3DGS convention)."""


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC SH coefficient giving colour ``rgb`` (INRIA: colour = SH_C0·c0 + 0.5). (..., 3) → (..., 3)."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Colour of a DC SH coefficient before clamping: SH_C0·c0 + 0.5. (..., 3) → (..., 3)."""
    return sh0 * SH_C0 + 0.5


@dataclass
class Gaussians:
    """N activated 3D Gaussians, world frame (3DGS, Kerbl et al. 2023): ``means`` (N, 3) metres, ``quats`` (N, 4)
    wxyz (normalised on use), ``scales`` (N, 3) standard deviations along the local axes, metres, > 0, ``opacities``
    (N,) in [0, 1], ``sh`` (N, (degree+1)², 3), INRIA convention (colour = max(Σ_k sh_k·Y_k(dir) + 0.5, 0))."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor

    def __post_init__(self) -> None:
        self.validate()

    @property
    def num_gaussians(self) -> int:
        """N, the number of Gaussians."""
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """SH degree 0..3 of ``sh`` ((degree+1)² coefficients per colour)."""
        return int(math.isqrt(self.sh.shape[1])) - 1

    def validate(self) -> None:
        """Check shapes and values.

        Raises:
            ValueError: a wrong shape, non-finite values, scales ≤ 0, opacities outside [0, 1], an SH count that is not
                1, 4, 9 or 16, or a zero-norm quaternion.
        """
        n = self.means.shape[0] if self.means.dim() == 2 else -1
        expect = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in expect.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape or n < 0:
                raise ValueError(f"{name} must have shape {shape} (N = len(means)), got {tuple(t.shape)}")
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"sh must have shape (N, K, 3), got {tuple(self.sh.shape)}")
        k = self.sh.shape[1]
        if k < 1 or math.isqrt(k) ** 2 != k or k > 16:
            raise ValueError(f"sh must hold (degree+1)² ∈ {{1, 4, 9, 16}} coefficients per colour, got {k}")
        if any(getattr(self, f.name).is_meta for f in fields(self)):
            return  # meta tensors have shapes but no values (a model's size, sharding plans): nothing more to check
        for f in fields(self):
            check_finite(f.name, getattr(self, f.name))
        if n and bool((self.scales <= 0).any()):
            raise ValueError(f"scales must be > 0 metres, min is {float(self.scales.min())}")
        if n and bool(((self.opacities < 0) | (self.opacities > 1)).any()):
            raise ValueError("opacities must lie in [0, 1]")
        quat_normalize(self.quats, "quats")  # zero norm → ValueError naming quats

    def select(self, index: Tensor) -> Gaussians:
        """Subset by boolean mask (N,) or integer indices (M,); not validated again (every check is per Gaussian)."""
        return _unchecked(Gaussians, {f.name: getattr(self, f.name)[index] for f in fields(self)})

    def to(self, *args, **kwargs) -> Gaussians:
        """Move/cast every tensor (``Tensor.to`` arguments); validated again only if a dtype changed (a cast can
        overflow or underflow). ValueError as :meth:`validate`."""
        moved = {f.name: getattr(self, f.name).to(*args, **kwargs) for f in fields(self)}
        if all(moved[name].dtype == getattr(self, name).dtype for name in moved):
            return _unchecked(Gaussians, moved)  # the same values on another device
        return Gaussians(**moved)

    def detach(self) -> Gaussians:
        """Every tensor detached from autograd (the same storage and values: not validated again)."""
        return _unchecked(Gaussians, {f.name: getattr(self, f.name).detach() for f in fields(self)})


def _unchecked(cls, values: dict):
    """An instance of the dataclass ``cls`` holding ``values`` without running ``__post_init__``."""
    obj = object.__new__(cls)
    for f in fields(cls):
        setattr(obj, f.name, values.get(f.name))
    return obj
