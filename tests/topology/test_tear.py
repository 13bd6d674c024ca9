"""Tearing and coagulation (torchdeform.topology.tear).

* strains against a numpy edge list (|x_b - x_a| / l0 - 1 per listed spring); all-at-once tears
  exactly the springs above the limit, one-per-step the most strained;
* a force limit is the strain limit F / (k l0);
* a chain pulled by its end tears at its softest spring (the highest strain under one tension)
  and falls into two pieces;
* a coagulated body keeps its deformed shape at rest (it is the new rest shape: 200 steps
  without loads leave it to 1e-15), springs outside the region keep their rest lengths, and the
  damping there rises by the factor.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.topology import coagulate, components, spring_strain, strain_limit_from_force, tear

H = 0.01


def _deformed(topology=18, shape=(4, 3, 5), seed=0, amp=0.15, device=None):
    grid = td.Grid(shape, spacing=H, topology=topology)
    model = td.Model(grid, stiffness=10.0, damping=0.02, mass=1e-3, dtype=F64, device=device)
    gen = torch.Generator().manual_seed(seed)
    return grid, model, model.X + amp * H * torch.randn(model.X.shape, generator=gen, dtype=F64).to(device)


def _edge_strains(grid, x, topology):
    el = EdgeList(grid.shape, (H,) * 3, topology)
    p = el.from_field(x[0])
    return el, np.linalg.norm(p[el.b] - p[el.a], axis=1) / el.l0 - 1


@pytest.mark.parametrize("topology", [6, 26])
def test_all_at_once_tears_exactly_the_springs_beyond_the_limit(topology, device):
    grid, model, x = _deformed(topology, device=device)
    _, ref = _edge_strains(grid, x, topology)
    got = spring_strain(model, x).cpu()
    assert np.allclose(np.sort(got[got != 0].numpy()), np.sort(ref), atol=1e-14)
    limit = float(np.quantile(ref, 0.8))
    assert tear(model, x, limit) == int((ref > limit).sum())
    assert float(spring_strain(model, x).max()) <= limit


def test_one_per_step_breaks_the_most_strained_spring_first(device):
    grid, model, x = _deformed(18, device=device)
    _, ref = _edge_strains(grid, x, 18)
    order = np.sort(ref)[::-1]
    for k in range(3):
        before = spring_strain(model, x)
        assert tear(model, x, 0.0 + 1e-12, one_per_step=True) == 1
        gone = (before != 0) & (spring_strain(model, x) == 0)
        assert float(before[gone].item()) == pytest.approx(order[k], abs=1e-14)


def test_force_limit_is_strain_limit_over_k_l0(device):
    grid = td.Grid((2, 2, 2), spacing=H, topology=26)
    model = td.Model(grid, stiffness={"axis": 10.0, "face": 5.0, "body": 2.0}, mass=1e-3, dtype=F64, device=device)
    lim = strain_limit_from_force(model, 0.01).cpu()
    l0 = grid.rest_lengths(dtype=F64)
    k = torch.tensor([{"axis": 10.0, "face": 5.0, "body": 2.0}[c] for c in grid.direction_class()], dtype=F64)
    assert torch.allclose(lim[0, :, 0, 0, 0], 0.01 / (k * l0))


def test_pulled_chain_tears_at_its_softest_spring(device):
    grid = td.Grid((6, 1, 1), spacing=H, topology=6)
    k = torch.full((1, grid.S) + grid.shape, 50.0, dtype=F64)
    k[0, 0, 3] = 20.0  # the spring between nodes 3 and 4
    top = torch.zeros(grid.shape, dtype=torch.bool)
    top[-1] = True
    model = td.Model(
        grid,
        stiffness=k,
        damping=0.05,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
        drags=[td.Drag(top, path=[(0.0, (0.0, 0.0, 0.0)), (0.5, (0.02, 0.0, 0.0))])],
    )
    state, torn = model.rest_state(), 0
    for _ in range(400):
        state, _ = td.simulate(model, state, dt=2e-4, steps=5)
        torn += tear(model, state.x, 0.3, one_per_step=True)
        if torn:
            break
    assert torn == 1 and float(model.stiffness[0, 0, 3, 0, 0]) == 0
    labels, count = components(model)
    assert count == 2 and labels[:4].unique().numel() == 1 and labels[4:].unique().numel() == 1


def test_chain_tears_when_the_spring_force_reaches_k_l0_limit_and_not_before():
    """Quasi-static pull of a chain of unequal springs: the soft spring breaks at F = k l0 s_lim.

    Oracle: spring forces k (l - l0) computed in numpy from the node positions at every check,
    and the series-spring formula for the pull at which it happens, delta* = k_s l0 s_lim sum 1/k_i.
    """
    n, lim, l0 = 6, 0.3, H
    grid = td.Grid((n, 1, 1), spacing=H, topology=6)
    ks = np.array([50.0, 50.0, 50.0, 20.0, 50.0])  # spring i joins nodes i, i+1
    k = torch.zeros((1, grid.S) + grid.shape, dtype=F64)
    k[0, 0, : n - 1, 0, 0] = torch.tensor(ks)
    top = torch.zeros(grid.shape, dtype=torch.bool)
    top[-1] = True
    speed = 0.01  # m/s: slow against the chain's ~14 Hz
    model = td.Model(
        grid,
        stiffness=k,
        damping=0.02,
        mass=1e-3,
        fixed=grid.face("bottom"),
        dtype=F64,
        drags=[td.Drag(top, path=[(0.0, (0.0, 0.0, 0.0)), (10.0, (10 * speed, 0.0, 0.0))])],
    )
    state = model.rest_state()
    limit = ks * l0 * lim  # N, per spring
    for _ in range(2000):
        x = state.x[0, 0, :, 0, 0].numpy()
        force = ks * (np.diff(x) - l0)
        torn = tear(model, state.x, lim)
        if torn:
            break
        assert (force <= limit * (1 + 1e-12)).all()  # not before
        state, _ = td.simulate(model, state, dt=5e-4, steps=4)
    assert torn == 1 and float(model.stiffness[0, 0, 3, 0, 0]) == 0  # the soft spring
    assert force[3] >= limit[3] and (force[[0, 1, 2, 4]] < limit[[0, 1, 2, 4]]).all()
    delta = float(state.x[0, 0, -1, 0, 0] - model.X[0, 0, -1, 0, 0])
    expect = 20.0 * l0 * lim * float((1 / ks).sum())
    assert abs(delta - expect) < 0.01 * expect  # quasi-static (a check every 0.26 %)


def test_coagulated_shape_is_the_new_rest_shape(device):
    grid, model, x = _deformed(26, amp=0.2, device=device)
    region = torch.zeros(grid.shape, dtype=torch.bool)
    region[:2] = True
    model = td.Model(grid, stiffness=10.0, damping=0.02, mass=1e-3, dtype=F64, device=device)
    changed = coagulate(model, x, torch.ones(grid.shape, dtype=torch.bool), viscosity_factor=3.0)
    assert changed == grid.num_springs
    assert torch.allclose(model.damping[0].cpu()[grid.spring_mask()].unique(), torch.tensor([0.06], dtype=F64))
    state, _ = td.simulate(model, td.State(x.clone(), torch.zeros_like(x)), dt=2e-4, steps=200)
    assert (state.x - x).abs().max() < 1e-15
    # only a region: springs with an end outside keep the grid's rest lengths
    part = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=F64, device=device)
    n = coagulate(part, x, region)
    p = x[0].cpu().numpy()
    rest_length = part.rest_length.cpu()
    count = 0
    for si, d in enumerate(grid.directions):  # every spring slot, checked one by one in numpy
        for ijk in zip(*np.nonzero(grid.spring_mask()[si].numpy())):
            far = tuple(int(i) + c for i, c in zip(ijk, d))
            both = bool(region[ijk]) and bool(region[far])
            expect = (
                np.linalg.norm(p[(slice(None),) + far] - p[(slice(None),) + tuple(ijk)])
                if both
                else H * np.linalg.norm(d)
            )
            assert abs(float(rest_length[0, si][tuple(ijk)]) - expect) < 1e-15
            count += both
    assert n == count > 0


def test_bad_limits():
    grid, model, x = _deformed(6)
    with pytest.raises(ConfigError, match=r"tear\.max_strain"):
        tear(model, x, -0.1)
    with pytest.raises(ConfigError, match="viscosity_factor"):
        coagulate(model, x, torch.ones(grid.shape, dtype=torch.bool), viscosity_factor=0.5)
    with pytest.raises(ConfigError, match=r"coagulate\.region"):
        coagulate(model, x, torch.ones((2, 2, 2), dtype=torch.bool))
