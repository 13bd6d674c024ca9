"""An Elastic lattice body against finite elements: the FEM is the oracle (:mod:`torchdeform.bench.accuracy.fem`,
scikit-fem, quadratic hexahedra on graded meshes converged to about 1 %, see its docstring).

The lattice is solved in the small-strain limit (its stiffness at rest, conjugate gradients), as
the linear FEM is. Measured here (E = 5 kPa; ratio lattice / FEM, 26 neighbours):

=============================  ==========  ==========  ==========
case                           nu = 0.3    nu = 0.45   nu = 0.49
=============================  ==========  ==========  ==========
simple shear, h = 2.5 mm       1.017       1.017       1.018
simple shear, h = 1.25 mm      1.006       1.007       1.007
bonded punch, h = 2.5 mm       1.172       1.153       1.146
bonded punch, h = 1.25 mm      -           1.067       -
cantilever, 12 / 24 / 48 cells -           0.777 / 0.925 / 0.978
=============================  ==========  ==========  ==========

(cantilever at 24 cells: 0.944 on 18 neighbours, 0.909 on 14). The lattice converges to the FEM
under refinement; a coarse lattice is too stiff in bending and near a punch's edge.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64, cg_solve

pytest.importorskip("skfem")
from torchdeform.bench.accuracy import fem

E = 5e3


def _prescribed(model, fixed, ub):
    """Small-strain solution with the nodes of ``fixed`` at displacement ``ub``; ``(u, K u)``."""
    free = (~fixed).to(F64)[None, None]
    lin = model.linearise(model.X)
    u = cg_solve(lambda p: lin.apply(p * free) * free, -lin.apply(ub) * free) + ub
    return u, lin.apply(u)


def lattice_shear(nu, h, *, topology=26, gamma=0.01):
    """Shear force (N) of the 5 x 50 x 50 mm box between bonded plates (as :func:`fem.simple_shear`)."""
    nd, nh = round(0.005 / h) + 1, round(0.05 / h) + 1
    grid = td.Grid((nd, nh, nh), spacing=h, topology=topology)
    model = td.Model(grid, td.Elastic(E, nu), mass=1.0, dtype=F64)
    ub = torch.zeros_like(model.X)
    ub[0, 2, -1] = gamma * 0.005
    _, R = _prescribed(model, grid.face("bottom") | grid.face("top"), ub)
    return float(R[0, 2, -1].sum())


def lattice_punch(nu, h, *, topology=26, depth=5e-4):
    """Force (N) on a bonded 10 x 10 mm punch pressed ``depth`` into a 20 x 40 x 40 mm block (as :func:`fem.bonded_punch_force`)."""
    nd, nh = round(0.02 / h) + 1, round(0.04 / h) + 1
    grid = td.Grid((nd, nh, nh), spacing=h, topology=topology)
    model = td.Model(grid, td.Elastic(E, nu), mass=1.0, dtype=F64)
    x1, x2 = model.X[0, 1, -1], model.X[0, 2, -1]
    lo, hi = 0.015 - 1e-9, 0.025 + 1e-9
    punch = torch.zeros(grid.shape, dtype=torch.bool)
    punch[-1] = (x1 >= lo) & (x1 <= hi) & (x2 >= lo) & (x2 <= hi)
    ub = torch.zeros_like(model.X)
    ub[0, 0][punch] = -depth
    _, R = _prescribed(model, grid.face("bottom") | punch, ub)
    return float(-R[0, 0][punch].sum())


def lattice_cantilever(nu, cells, *, topology=26, rho=1000.0):
    """Mean tip deflection (m) of the 10 x 10 x 60 mm beam clamped at w = 0 under gravity (as :func:`fem.cantilever_tip`)."""
    h = 0.06 / cells
    n = round(0.01 / h) + 1
    grid = td.Grid((n, n, cells + 1), spacing=h, topology=topology)
    model = td.Model(grid, td.Elastic(E, nu), density=rho, fixed=grid.face("w-"), dtype=F64)
    f = model.mass * torch.tensor([-9.81, 0.0, 0.0], dtype=F64).view(1, 3, 1, 1, 1) * model.free
    lin = model.linearise(model.X)
    u = cg_solve(lambda p: lin.apply(p * model.free) * model.free, f)
    return float(u[0, 0, :, :, -1].mean())


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.49])
def test_simple_shear_within_5_percent_of_the_fem(nu):
    ref = fem.simple_shear(E, nu).force
    coarse, fine = lattice_shear(nu, 0.0025), lattice_shear(nu, 0.00125)
    assert abs(coarse / ref - 1) < 0.05 and abs(fine / ref - 1) < 0.02
    assert abs(fine / ref - 1) < abs(coarse / ref - 1)


@pytest.mark.slow
def test_bonded_punch_within_10_percent_of_the_fem_at_1_25_mm():
    ref = fem.bonded_punch_force(E, 0.45)
    coarse, fine = lattice_punch(0.45, 0.0025), lattice_punch(0.45, 0.00125)
    assert abs(fine / ref - 1) < 0.10, fine / ref
    assert 1 < fine / ref < coarse / ref  # too stiff, less so when finer


@pytest.mark.slow
def test_cantilever_converges_to_the_fem_tip_deflection():
    ref = fem.cantilever_tip(E, 0.45, 1000.0).mean
    ratios = [lattice_cantilever(0.45, cells) / ref for cells in (12, 24, 48)]
    assert ratios[0] < ratios[1] < ratios[2] < 1.0, ratios
    assert ratios[2] > 0.97, ratios
