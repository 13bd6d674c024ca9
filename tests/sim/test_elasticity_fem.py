"""An Elastic lattice body against finite elements: the FEM is the oracle (:mod:`torchdeform.bench.accuracy.fem`,
scikit-fem, quadratic hexahedra on graded meshes converged to about 1 %, see its docstring).

The lattice load cases are those of ``torchdeform bench elasticity``
(:mod:`torchdeform.bench.accuracy.lattice`), solved in the small-strain limit (the stiffness at
rest, conjugate gradients), as the linear FEM is. Measured here (E = 5 kPa; ratio lattice / FEM,
26 neighbours):

=============================  ==========  ==========  ==========
case                           nu = 0.3    nu = 0.45   nu = 0.49
=============================  ==========  ==========  ==========
simple shear, h = 2.5 mm       1.013       1.015       1.017
simple shear, h = 1.25 mm      1.004       1.005       1.004
bonded punch, h = 2.5 mm       -           1.104       -
bonded punch, h = 1.25 mm      -           1.044       -
cantilever, 12 / 24 / 48 cells 0.967 /     0.972 /     0.967 /
                               0.990 /     0.988 /     0.987 /
                               0.997       0.997       0.997
=============================  ==========  ==========  ==========

(cantilever at 12 / 24 / 48 cells on 18 neighbours: 1.019 / 0.999 / 0.999 at nu = 0.45). The
lattice converges to the FEM under refinement; a coarse lattice is too stiff near a punch's edge.
"""

from __future__ import annotations

import pytest

pytest.importorskip("skfem")
from torchdeform.bench.accuracy import fem
from torchdeform.bench.accuracy.lattice import lattice_cantilever, lattice_punch, lattice_shear

E = 5e3


@pytest.mark.slow
@pytest.mark.parametrize("nu", [0.49])
def test_simple_shear_within_5_percent_of_the_fem(nu):
    ref = fem.simple_shear(E, nu).force
    assert abs(lattice_shear(nu, 0.0025) / ref - 1) < 0.05  # 1.017 (1.004 at h = 1.25 mm: the table above)


@pytest.mark.slow
def test_bonded_punch_within_10_percent_of_the_fem_at_1_25_mm():
    ref = fem.bonded_punch_force(E, 0.45)
    coarse, fine = lattice_punch(0.45, 0.0025), lattice_punch(0.45, 0.00125)
    assert abs(fine / ref - 1) < 0.10, fine / ref
    assert 1 < fine / ref < coarse / ref  # too stiff, less so when finer


@pytest.mark.slow
def test_cantilever_at_24_cells_within_5_percent_of_the_fem_tip_deflection():
    ref = fem.cantilever_tip(E, 0.45, 1000.0).mean
    ratios = [lattice_cantilever(0.45, cells) / ref for cells in (12, 24, 48)]
    assert abs(ratios[1] - 1) < 0.05, ratios
    assert abs(ratios[0] - 1) > abs(ratios[1] - 1) > abs(ratios[2] - 1), ratios  # it converges
    assert abs(lattice_cantilever(0.45, 24, topology=18) / ref - 1) < 0.05
