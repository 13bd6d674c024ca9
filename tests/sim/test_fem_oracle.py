"""Checks of the finite-element oracle :mod:`torchdeform.bench.accuracy.fem` (scikit-fem, quadratic hexahedra).

Independent oracle: closed forms. The uniaxial pull against Hooke's law (``E`` and ``nu`` back);
simple shear against ``G = E / (2 (1 + nu))``; the cantilever against Timoshenko beam theory,
``w = q L^4 / (8 E I) + q L^2 / (2 kappa G A)``, ``q = rho g A``, ``I = h^4 / 12`` and
``A = h^2`` for the square section, ``kappa = 5/6``; the bonded punch against itself (mesh
convergence) and the linearity of the problem in the depth and in ``E``.
"""

import math

import pytest

pytest.importorskip("skfem")

from torchdeform.bench.accuracy import fem

YOUNG = 5e3  # Pa


def _shear_modulus(E, nu):
    return E / (2 * (1 + nu))


def _timoshenko(E, nu, rho, size=(0.01, 0.01, 0.06), g=9.81, kappa=5 / 6):
    h, b, L = size
    A, I = h * b, b * h**3 / 12
    q = rho * g * A
    return q * L**4 / (8 * E * I) + q * L**2 / (2 * kappa * _shear_modulus(E, nu) * A)


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.45, 0.49])
@pytest.mark.parametrize("size", [(0.01, 0.01, 0.01), (0.004, 0.02, 0.03)])
def test_uniaxial_gives_E_and_nu_back(nu, size):
    r = fem.uniaxial_pull(YOUNG, nu, size, 250.0)
    young = r.E
    assert young == pytest.approx(YOUNG, rel=1e-6)
    assert r.nu == pytest.approx(nu, rel=1e-6, abs=1e-9)
    assert r.strain_axial == pytest.approx(250.0 / YOUNG, rel=1e-6)
    for lateral in r.strain_lateral:
        assert lateral == pytest.approx(-nu * 250.0 / YOUNG, rel=1e-6, abs=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.49])
def test_simple_shear_close_to_G(nu):
    # L0 / L2 = 0.1: the free ends x2 = 0, L2 carry no shear stress over a layer ~L0 wide, so the
    # apparent modulus is a few % low (3.2 % at nu = 0.3, 2.2 % at 0.49); never above G.
    r = fem.simple_shear(YOUNG, nu)
    ratio = r.G / _shear_modulus(YOUNG, nu)
    assert 0.95 < ratio < 1.0
    assert r.force == pytest.approx(r.G * 0.01 * 0.05 * 0.05, rel=1e-12)


@pytest.mark.parametrize(
    ("nu", "rel"),
    [
        pytest.param(0.0, 0.002, marks=pytest.mark.slow),
        (0.3, 0.02),
        pytest.param(0.45, 0.05, marks=pytest.mark.slow),
        pytest.param(0.49, 0.05, marks=pytest.mark.slow),
    ],
)
def test_cantilever_matches_timoshenko(nu, rel):
    # the full clamp also stops the Poisson contraction of the root section, which stiffens the
    # 3D beam as nu grows (1.5 % at nu = 0.3, 4.4 % at 0.49); at nu = 0 only end effects remain.
    tip = fem.cantilever_tip(YOUNG, nu, 1000.0)
    w = _timoshenko(YOUNG, nu, 1000.0)
    assert -tip.mean == pytest.approx(w, rel=rel)
    assert -tip.mean < w  # the clamp's restraint stiffens, never softens
    assert tip.centre == pytest.approx(tip.mean, rel=1e-3)


def test_cantilever_linear_in_load_over_stiffness():
    a = fem.cantilever_tip(YOUNG, 0.3, 1000.0)
    b = fem.cantilever_tip(2 * YOUNG, 0.3, 500.0, g=2 * 9.81)  # the same rho g, twice as stiff
    assert b.mean == pytest.approx(a.mean / 2, rel=1e-9)


@pytest.mark.slow
def test_punch_force_linear_in_depth_and_E():
    h = 3 * fem.PUNCH_HMIN  # linearity holds on any mesh: a coarse one keeps this fast
    f = fem.bonded_punch_force(YOUNG, 0.3, depth=5e-4, hmin=h)
    assert fem.bonded_punch_force(YOUNG, 0.3, depth=1e-3, hmin=h) == pytest.approx(2 * f, rel=1e-9)
    assert fem.bonded_punch_force(3 * YOUNG, 0.3, depth=5e-4, hmin=h) == pytest.approx(3 * f, rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.3])
def test_punch_stiffer_than_a_half_space(nu):
    # a rigid flat circular punch of the same area on a half-space: F = 2 E d a / (1 - nu^2),
    # a = sqrt(A / pi) (Sneddon); the 20 mm block on a fixed base, pressed by a bonded punch, is
    # stiffer, but not by orders of magnitude
    f = fem.bonded_punch_force(YOUNG, nu)
    half_space = 2 * YOUNG * 5e-4 * math.sqrt(1e-4 / math.pi) / (1 - nu**2)
    assert half_space < f < 3 * half_space


def test_the_oracles_stiffness_matrix_is_scikit_fems_linear_elasticity():
    """The oracle assembles isotropic elasticity by its own form (faster): the matrix of
    ``skfem.models.elasticity.linear_elasticity`` on a graded box of 27-node hexahedra, to 1e-13."""
    import numpy as np
    from skfem import asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    coords = [np.array([0.0, 0.002, 0.005]), np.array([0.0, 0.003, 0.004, 0.01]), np.array([0.0, 0.001, 0.004])]
    p = fem._Problem(coords, 4.2e3, 0.45)
    ref = asm(linear_elasticity(*lame_parameters(4.2e3, 0.45)), p.basis).tocsr()
    assert abs(p.K - ref).max() <= 1e-13 * abs(ref).max()
