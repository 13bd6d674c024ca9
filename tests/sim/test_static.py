"""Static equilibrium (torchdeform.sim.static.solve_static).

Oracles: scipy's L-BFGS minimising the potential energy of the edge-list springs plus gravity
(:mod:`tests.oracles.edge_list`: every spring listed one by one, no stencil); the forces of that
edge list at the solution; and the volume enclosed by the deformed body's boundary surface
(a closed triangulated surface, divergence theorem) for the nearly incompressible squeeze.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import minimize

import torchdeform as td
from tests.helpers import F64
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError


def test_springs_under_gravity_match_a_minimiser_of_the_edge_list_energy():
    """A 3 x 3 x 4 cantilever, 26 neighbours, soft enough to sag 15 % of its length (nonlinear)."""
    shape, h, k, m, g = (3, 3, 4), 0.01, 2.0, 1e-3, 9.81
    grid = td.Grid(shape, spacing=h, topology=26)
    fixed = grid.face("w-")
    model = td.Model(grid, stiffness=k, mass=m, gravity=(-g, 0, 0), fixed=fixed, dtype=F64)
    state, info = td.solve_static(model, tol=1e-12)
    assert info["converged"] and info["iterations"] >= 3  # nonlinear: several Newton steps

    edges = EdgeList(shape, (h, h, h), 26)
    free = np.array([not bool(fixed[ijk]) for ijk in edges.nodes])

    def potential(q):
        x = edges.X.copy()
        x[free] = q.reshape(-1, 3)
        return edges.energy(x, k) + m * g * float(np.sum(x[:, 0] - edges.X[:, 0]))

    def gradient(q):
        x = edges.X.copy()
        x[free] = q.reshape(-1, 3)
        G = -edges.forces(x, k=k)
        G[:, 0] += m * g
        return G[free].ravel()

    res = minimize(
        potential,
        edges.X[free].ravel(),
        jac=gradient,
        method="L-BFGS-B",
        options={"gtol": 1e-13, "ftol": 0.0, "maxiter": 20000},
    )
    ref = edges.X.copy()
    ref[free] = res.x.reshape(-1, 3)
    ours = state.x[0].permute(1, 2, 3, 0).numpy()[tuple(np.array(edges.nodes).T)]
    sag = float(edges.X[:, 0].max() - ref[:, 0].min())
    assert sag > 0.15 * 0.03
    np.testing.assert_allclose(ours, ref, atol=1e-7 * sag)
    F = edges.forces(ours, k=k)
    F[:, 0] -= m * g
    assert np.abs(F[free]).max() < 1e-9 * m * g * len(edges.nodes)


def _enclosed_volume(x: np.ndarray) -> float:
    """Volume inside the boundary of a deformed box of nodes ``x`` ``(D, H, W, 3)``: each boundary
    quad split in two triangles, ``sum det[a, b, c] / 6`` with outward orientation."""
    total = 0.0
    for axis in range(3):
        for end, sign in ((0, -1.0), (x.shape[axis] - 1, 1.0)):
            face = np.take(x, end, axis=axis)  # (n1, n2, 3) over the other two axes, in order
            a, b, c, d = face[:-1, :-1], face[1:, :-1], face[1:, 1:], face[:-1, 1:]
            tri = np.einsum("...i,...i->...", a, np.cross(b, c)) + np.einsum("...i,...i->...", a, np.cross(c, d))
            # the other two axes in increasing order: e_i x e_j is +e_axis for axes 0 and 2, -e_1 for axis 1
            cyc = -1.0 if axis == 1 else 1.0
            total += sign * cyc * tri.sum() / 6
    return total


@pytest.mark.parametrize(("nu", "limit"), [(0.49, 0.02), (0.3, None)])
def test_a_nearly_incompressible_block_squeezed_by_20_percent_keeps_its_volume(nu, limit):
    n, h = 6, 0.002
    grid = td.Grid((n, n, n), spacing=h, topology=26)
    squeeze = td.Drag(grid.face("top"), offset=(-0.2 * (n - 1) * h, 0.0, 0.0), ramp=0.0)
    model = td.Model(grid, td.Elastic(5e3, nu), mass=1.0, fixed=grid.face("bottom"), drags=[squeeze], dtype=F64)
    state, info = td.solve_static(model, state=td.State(model.X, torch.zeros_like(model.X), t=1.0), tol=1e-9)
    assert info["converged"], info
    x = state.x[0].permute(1, 2, 3, 0).numpy()
    v0, v1 = _enclosed_volume(model.X[0].permute(1, 2, 3, 0).numpy()), _enclosed_volume(x)
    assert v0 == pytest.approx(((n - 1) * h) ** 3, rel=1e-12)
    assert float(x[-1, :, :, 0].max() - x[0, :, :, 0].min()) == pytest.approx(0.8 * (n - 1) * h, rel=1e-9)
    change = abs(v1 / v0 - 1)
    if limit is not None:
        assert change < limit, change
    else:
        assert change > 0.05, change  # without a stiff volume term the volume goes


def test_bad_options_are_refused():
    model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=1.0, mass=1.0)
    with pytest.raises(ConfigError, match="solve_static"):
        td.solve_static(model, tol=0.0)
    with pytest.raises(ConfigError, match="solve_static"):
        td.solve_static(model, max_iter=0)
