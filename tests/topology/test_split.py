"""Adding a node with Radetzky's eq. 4.14: mass and momentum conserved, against hand sums."""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.interact import Sphere, Tool
from torchdeform.topology import add_node, cauterize, share_mass

H = 0.01


def _moving_body(topology=26, device=None):
    grid = td.Grid((4, 4, 4), spacing=H, topology=topology)
    gen = torch.Generator().manual_seed(0)
    mass = 1e-3 * (1 + torch.rand(grid.shape, generator=gen, dtype=F64))
    model = td.Model(grid, stiffness=15.0, damping=0.02, mass=mass, dtype=F64, device=device)
    state = model.rest_state()
    state.v = torch.randn(state.x.shape, generator=gen, dtype=F64).to(device) * 0.1
    return grid, model, state


def _totals(model, state):
    m = model.mass.expand(1, 1, *model.grid.shape)
    return float(m.sum()), (m * state.v).flatten(2).sum(2)[0]


def test_share_mass_is_eq_4_14(device):
    m = torch.tensor([2e-3, 1e-3, 4e-3, 3e-3], dtype=F64, device=device)
    m_new, left = share_mass(m)
    assert float(m_new) == pytest.approx(10e-3 / 5, rel=1e-15)
    assert torch.allclose(left, m * 4 / 5, rtol=1e-15)
    assert abs(float(m_new + left.sum()) - float(m.sum())) <= 2 * torch.finfo(F64).eps * float(m.sum())


@pytest.mark.parametrize("topology", [6, 26])
def test_burn_then_add_keeps_mass_and_momentum(topology, device):
    grid, model, state = _moving_body(topology, device)
    mass0, p0 = _totals(model, state)
    burnt = cauterize(model, state, Tool(Sphere(0.7 * H), position=(H, 2 * H, H)))
    mass1, p1 = _totals(model, state)
    assert burnt["nodes"] == 1
    assert mass1 + burnt["mass_kg"] == pytest.approx(mass0, rel=1e-15, abs=0)
    assert torch.allclose(p1 + torch.tensor(burnt["momentum"], dtype=F64, device=device), p0, rtol=0, atol=1e-18)
    # neighbours before adding, by hand: the node's stencil neighbours in the body
    node = (1, 2, 1)
    nbrs = [tuple(a + b for a, b in zip(node, o)) for d in grid.directions for o in (d, tuple(-c for c in d))]
    nbrs = [j for j in nbrs if all(0 <= i < 4 for i in j)]
    m_before = {j: float(model.mass[(0, 0) + j]) for j in nbrs}
    added = add_node(model, state, node)
    mass2, p2 = _totals(model, state)
    k = len(nbrs)
    assert added["neighbours"] == k == {6: 6, 26: 26}[topology]
    assert added["mass_kg"] == pytest.approx(sum(m_before.values()) / (k + 1), rel=1e-15)
    for j in nbrs:
        assert float(model.mass[(0, 0) + j]) == pytest.approx(m_before[j] * k / (k + 1), rel=1e-15)
    assert mass2 == pytest.approx(mass1, rel=1e-15, abs=0)  # eq. 4.14: exact
    assert torch.allclose(p2, p1, rtol=0, atol=1e-18)  # the share carries its momentum
    assert not bool(model.removed[node]) and not bool(model.constrained[node])


def test_added_node_springs_copy_the_neighbours_and_are_shortened(device):
    grid, model, state = _moving_body(6, device)
    cauterize(model, state, Tool(Sphere(0.7 * H), position=(2 * H, 2 * H, 2 * H)))
    add_node(model, state, (2, 2, 2), gape=0.1)
    # springs into the node: stiffness 15 (all springs are 15), rest length 0.9 x the distance
    x = state.x[0]
    for s, d in enumerate(grid.directions):
        for src in ((2, 2, 2), tuple(2 - c for c in d)):
            dst = tuple(a + b for a, b in zip(src, d))
            dist = float((x[(slice(None),) + dst] - x[(slice(None),) + src]).norm())
            assert float(model.stiffness[(0, s) + src]) == pytest.approx(15.0)
            assert float(model.rest_length[(0, s) + src]) == pytest.approx(0.9 * dist, rel=1e-14)
    # the body then moves like any other: finite, and total mass unchanged by stepping
    state, _ = td.simulate(model, state, dt=1e-4, steps=50)
    assert bool(torch.isfinite(state.x).all())


def test_add_node_refuses_nodes_of_the_body():
    _grid, model, state = _moving_body(6)
    with pytest.raises(ConfigError, match=r"add_node\.node"):
        add_node(model, state, (1, 1, 1))
    with pytest.raises(ConfigError, match=r"add_node\.node"):
        add_node(model, state, (9, 0, 0))
