"""Tests of diff4splat.render.sh: INRIA real SH basis, DC colour, SH colours inside the renderer."""
import math

import pytest
import torch

from diff4splat.render import rasterize, sh_basis, sh_to_color, spherical_harmonics
from diff4splat.render.sh import num_sh_bases, rotate_sh, sh_rotation
from diff4splat.scene.gaussians import SH_C0, rgb_to_sh0
from diff4splat.scene.quaternions import axis_angle_to_quat, quat_to_rotmat


def _legendre(deg: int, m: int, x: torch.Tensor) -> torch.Tensor:
    """Associated Legendre P_l^m(x), m ≥ 0, with the Condon–Shortley phase (standard recurrences)."""
    pmm = torch.ones_like(x)
    somx2 = torch.sqrt((1 - x) * (1 + x))
    for i in range(1, m + 1):
        pmm = -(2 * i - 1) * somx2 * pmm
    if deg == m:
        return pmm
    pmmp1 = x * (2 * m + 1) * pmm
    for ll in range(m + 2, deg + 1):
        pmm, pmmp1 = pmmp1, ((2 * ll - 1) * x * pmmp1 - (ll + m - 1) * pmm) / (ll - m)
    return pmmp1


def _real_sh_direct(deg: int, m: int, dirs: torch.Tensor) -> torch.Tensor:
    """Orthonormal real SH from spherical coordinates (Sloan 2008 / INRIA sign convention)."""
    x, y, z = dirs.unbind(-1)
    phi = torch.atan2(y, x)
    am = abs(m)
    norm = math.sqrt((2 * deg + 1) / (4 * math.pi) * math.factorial(deg - am) / math.factorial(deg + am))
    p = _legendre(deg, am, z)
    if m > 0:
        return math.sqrt(2) * norm * p * torch.cos(m * phi)
    if m < 0:
        return math.sqrt(2) * norm * p * torch.sin(am * phi)
    return norm * p


def _fibonacci_sphere(n: int) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt(1 - z * z)
    phi = i * math.pi * (3 - math.sqrt(5))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def test_basis_matches_direct_legendre_formula():
    dirs = torch.nn.functional.normalize(torch.randn(500, 3, dtype=torch.float64,
                                                     generator=torch.Generator().manual_seed(0)), dim=-1)
    basis = sh_basis(3, dirs)
    k = 0
    for deg in range(4):
        for m in range(-deg, deg + 1):
            torch.testing.assert_close(basis[:, k], _real_sh_direct(deg, m, dirs), rtol=1e-12, atol=1e-12)
            k += 1
    assert k == basis.shape[-1] == 16


def test_basis_is_orthonormal_on_the_sphere():
    dirs = _fibonacci_sphere(20000)
    b = sh_basis(3, dirs)
    gram = b.T @ b * (4 * math.pi / len(dirs))
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_degree_zero_is_the_dc_colour_in_every_direction():
    rgb = torch.rand(7, 3, dtype=torch.float64)
    coeffs = rgb_to_sh0(rgb)[:, None, :]  # (7, 1, 3)
    dirs = torch.randn(7, 3, dtype=torch.float64)
    assert SH_C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)))
    torch.testing.assert_close(sh_to_color(spherical_harmonics(0, dirs, coeffs)), rgb)


def test_higher_coefficients_ignored_below_their_degree_and_direction_normalised():
    coeffs = torch.randn(5, 16, 3, dtype=torch.float64)
    dirs = torch.randn(5, 3, dtype=torch.float64)
    for deg in range(4):
        k = (deg + 1) ** 2
        want = torch.einsum("nk,nkc->nc", sh_basis(deg, dirs / dirs.norm(dim=-1, keepdim=True)), coeffs[:, :k])
        torch.testing.assert_close(spherical_harmonics(deg, 3.7 * dirs, coeffs), want)


def test_color_clamped_at_zero():
    assert float(sh_to_color(torch.tensor(-0.9))) == 0.0
    assert float(sh_to_color(torch.tensor(0.2))) == pytest.approx(0.7)


@pytest.mark.parametrize("bad", [-1, 4, 1.0])
def test_bad_degree_raises(bad):
    with pytest.raises(ValueError, match="sh_degree"):
        num_sh_bases(bad)


def test_too_few_coefficients_raises():
    with pytest.raises(ValueError, match="coeffs"):
        spherical_harmonics(2, torch.randn(3, 3), torch.randn(3, 4, 3))


def test_renderer_uses_direction_from_camera_centre():
    """Rendering SH equals rendering the colours computed by hand along (mean − camera centre)."""
    g = torch.Generator().manual_seed(3)
    n = 30
    means = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) - 0.5,
                         2 + torch.rand(n, generator=g)], -1).double()
    quats = torch.randn(n, 4, generator=g).double()
    scales = (0.05 + 0.1 * torch.rand(n, 3, generator=g)).double()
    opac = (0.2 + 0.7 * torch.rand(n, generator=g)).double()
    sh = 0.4 * torch.randn(n, 16, 3, generator=g).double()
    angle = 0.3
    R = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                      [-math.sin(angle), 0, math.cos(angle)]]).double()
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = R
    vm[:3, 3] = torch.tensor([0.3, -0.1, 0.2]).double()
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]).double()
    campos = -R.T @ vm[:3, 3]
    for deg in range(4):
        cols = sh_to_color(spherical_harmonics(deg, means - campos, sh))
        a, _, _ = rasterize(means, quats, scales, opac, sh, vm[None], K[None], 32, 24, sh_degree=deg, render_mode="RGB")
        b, _, _ = rasterize(means, quats, scales, opac, cols, vm[None], K[None], 32, 24, render_mode="RGB")
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_coefficients_give_the_rotated_colours(degree):
    """Gaussians rotated by R show towards R·d the colour they showed towards d (brute force over directions and
    rotations), in float64 to rounding and in float32 to its rounding; the matrix is orthogonal and block-diagonal
    (a rotation keeps each degree's functions among themselves) and the identity for R = I."""
    g = torch.Generator().manual_seed(degree)
    k = num_sh_bases(degree)
    sh = torch.randn(20, k, 3, generator=g, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=torch.float64), dim=-1)
    for axis, angle in (([0.3, 1.0, -0.5], 1.1), ([0.0, 0.0, 1.0], math.pi), ([1.0, -2.0, 0.5], 2.9)):
        R = quat_to_rotmat(axis_angle_to_quat(torch.tensor(axis, dtype=torch.float64),
                                              torch.tensor(angle, dtype=torch.float64)))
        want = spherical_harmonics(degree, dirs, sh)
        torch.testing.assert_close(spherical_harmonics(degree, dirs @ R.T, rotate_sh(sh, R)), want, rtol=0,
                                   atol=1e-12)
        got32 = spherical_harmonics(degree, (dirs @ R.T).float(), rotate_sh(sh.float(), R.float()))
        torch.testing.assert_close(got32, want.float(), rtol=0, atol=2e-5)
        M = sh_rotation(degree, R)
        torch.testing.assert_close(M @ M.T, torch.eye(k, dtype=torch.float64), rtol=0, atol=1e-12)
        for band in range(degree + 1):
            block = torch.zeros(k, dtype=torch.bool)
            block[band * band:(band + 1) ** 2] = True
            assert float(M[block][:, ~block].abs().sum()) < 1e-11
    torch.testing.assert_close(sh_rotation(degree, torch.eye(3)), torch.eye(k, dtype=torch.float64), rtol=0,
                               atol=1e-12)


def test_rotating_the_dc_term_changes_nothing_and_bad_shapes_raise():
    sh = torch.randn(4, 1, 3)
    assert rotate_sh(sh, torch.eye(3)) is sh
    with pytest.raises(ValueError, match="K in"):
        rotate_sh(torch.zeros(4, 5, 3), torch.eye(3))
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        rotate_sh(torch.zeros(4, 4, 3), torch.eye(4))
