"""The numba CPU kernel of :meth:`diff4splat.scene.dynamic.DynamicGaussians.at`: interpolation and composition in one
pass over the Gaussians. For each Gaussian i of ``index`` (w the weight of key k1, u = q/‖q‖):

    Δμ = (1 − w)·Δμ_k[i] + w·Δμ_k1[i]
    Δq = normalize((1 − w)·u(Δq_k[i]) + w·sign(u(Δq_k[i])·u(Δq_k1[i]))·u(Δq_k1[i]))
    Δs = (1 − w)·Δs_k[i] + w·Δs_k1[i]
    μ_t = μ[i] + Δμ,   q_t = Δq ⊗ u(q[i]),   s_t = s[i]·exp(Δs)

one parallel work item per Gaussian (thread-count independent). A Gaussian the reference would raise for is flagged
in ``bad`` and the caller runs the reference. Imported on first use (numba's import time).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import prange

from diff4splat.utils.jit import KERNEL, threads

__all__ = ["deform", "deform_kernel"]

_ZERO_NORM = 1e-12
"""The norm below which a quaternion has no orientation (as :func:`diff4splat.scene.quaternions.quat_norms`)."""


@KERNEL(parallel=True)
def deform_kernel(index: np.ndarray,  # (K,) int64 into the M Gaussians
                  means: np.ndarray, quats: np.ndarray, scales: np.ndarray,  # (M, 3), (M, 4), (M, 3) canonical
                  dm0: np.ndarray, dq0: np.ndarray, ds0: np.ndarray,  # key k: (M, 3), (M, 4), (M, 3)
                  dm1: np.ndarray, dq1: np.ndarray, ds1: np.ndarray,  # key k1
                  w: float,
                  out_means: np.ndarray, out_quats: np.ndarray, out_scales: np.ndarray,  # (K, 3), (K, 4), (K, 3)
                  bad: np.ndarray) -> None:  # (K,) bool, set where the reference would raise
    v = 1.0 - w
    for j in prange(index.shape[0]):
        i = index[j]
        n0 = math.sqrt(dq0[i, 0] ** 2 + dq0[i, 1] ** 2 + dq0[i, 2] ** 2 + dq0[i, 3] ** 2)
        n1 = math.sqrt(dq1[i, 0] ** 2 + dq1[i, 1] ** 2 + dq1[i, 2] ** 2 + dq1[i, 3] ** 2)
        nc = math.sqrt(quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2)
        if n0 < _ZERO_NORM or n1 < _ZERO_NORM or nc < _ZERO_NORM:
            bad[j] = True
            continue
        dot = dq0[i, 0] * dq1[i, 0] + dq0[i, 1] * dq1[i, 1] + dq0[i, 2] * dq1[i, 2] + dq0[i, 3] * dq1[i, 3]
        b = w / n1 if dot >= 0 else -w / n1
        a = v / n0
        q0 = a * dq0[i, 0] + b * dq1[i, 0]
        q1 = a * dq0[i, 1] + b * dq1[i, 1]
        q2 = a * dq0[i, 2] + b * dq1[i, 2]
        q3 = a * dq0[i, 3] + b * dq1[i, 3]
        nq = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)  # ≥ 1/√2: a blend of unit q on one hemisphere
        q0, q1, q2, q3 = q0 / nq, q1 / nq, q2 / nq, q3 / nq
        c0, c1, c2, c3 = quats[i, 0] / nc, quats[i, 1] / nc, quats[i, 2] / nc, quats[i, 3] / nc
        out_quats[j, 0] = q0 * c0 - q1 * c1 - q2 * c2 - q3 * c3  # Hamilton product Δq ⊗ u(q)
        out_quats[j, 1] = q0 * c1 + q1 * c0 + q2 * c3 - q3 * c2
        out_quats[j, 2] = q0 * c2 - q1 * c3 + q2 * c0 + q3 * c1
        out_quats[j, 3] = q0 * c3 + q1 * c2 - q2 * c1 + q3 * c0
        for c in range(3):
            out_means[j, c] = means[i, c] + (v * dm0[i, c] + w * dm1[i, c])
            s = scales[i, c] * math.exp(v * ds0[i, c] + w * ds1[i, c])
            out_scales[j, c] = s
            if not (s > 0 and s < math.inf):
                bad[j] = True


def deform(*arrays) -> None:
    """:func:`deform_kernel` on torch's thread count (:func:`diff4splat.utils.jit.threads`), same arguments."""
    with threads(torch.get_num_threads()):
        deform_kernel(*arrays)
