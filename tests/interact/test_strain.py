"""Strain limiting (torchdeform.interact.StrainLimit) against a plain edge-list Jacobi pass.

The oracle lists every spring from the node coordinates (tests.oracles.edge_list), computes each
violating spring's correction in numpy and averages per node, so it shares nothing with the
stencil code but the rule itself (Provot's averaged corrections, REFERENCE §6.3; a spring is
violated only when its excess is above ``64 eps`` times its rest length). The packed layout of the
compiled step (one sum over the ``2 S`` directions of every node) is held to the grid layout.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.interact import StrainLimit
from torchdeform.sim.compiled import compiled_step
from torchdeform.sim.packed import PackedModel


def oracle_pass(edges: EdgeList, x: np.ndarray, free: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """One averaged Jacobi pass over the listed springs; ``x`` ``(N, 3)``, ``free`` ``(N,)`` bool.

    A spring is violated only when ``|excess| > 64 eps l0`` (on its bound within rounding it is skipped).
    """
    tol = 64 * np.finfo(x.dtype).eps
    total, count = np.zeros_like(x), np.zeros(len(x))
    for (a, b, _), l0 in zip(edges.springs, edges.l0):
        d = x[b] - x[a]
        length = np.linalg.norm(d)
        excess = length - min(max(length, lo * l0), hi * l0)
        if abs(excess) <= tol * l0:
            continue
        wa, wb = float(free[a]), float(free[b])
        if wa + wb == 0:
            continue
        step = excess * d / length / (wa + wb)
        total[a] += wa * step
        total[b] -= wb * step
        count[a] += wa
        count[b] += wb
    return x + total / np.maximum(count, 1)[:, None]


def _stretched(shape=(3, 4, 3), topology=18, seed=0, device=None):
    grid = td.Grid(shape, spacing=(0.01, 0.012, 0.01), topology=topology)
    model = td.Model(grid, stiffness=1.0, mass=1e-3, fixed=grid.face("bottom"), dtype=torch.float64, device=device)
    g = torch.Generator().manual_seed(seed)
    stretch = torch.tensor([1.6, 1.0, 0.7], dtype=torch.float64, device=device)  # stretch D, squeeze W
    x = model.X * stretch.view(1, 3, 1, 1, 1)
    x = x + 1e-3 * torch.randn(x.shape, generator=g, dtype=torch.float64).to(device)
    x = torch.where(model.constrained[None, None], model.X, x)  # fixed nodes at rest
    return grid, model, x


@pytest.mark.parametrize("topology", [6, 18, 26])
def test_one_pass_equals_the_edge_list_oracle(topology, device):
    grid, model, x = _stretched(topology=topology, device=device)
    edges = EdgeList(grid.shape, grid.spacing, topology)
    free = ~edges.from_field(model.constrained[None].expand(3, *grid.shape))[:, 0].astype(bool)
    want = oracle_pass(edges, edges.from_field(x[0]), free, 0.9, 1.1)
    got, _ = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=1, update_velocity=False).project(
        model, x, torch.zeros_like(x), 0.0, 1e-3
    )
    assert np.abs(edges.from_field(got[0]) - want).max() < 1e-15


def test_passes_bring_every_spring_within_its_bounds(device):
    grid, model, x = _stretched(topology=26, device=device)
    edges = EdgeList(grid.shape, grid.spacing, 26)

    def worst(xx):
        p = edges.from_field(xx[0])
        ratio = np.linalg.norm(p[edges.b] - p[edges.a], axis=1) / edges.l0
        return max(ratio.max() - 1.1, 0.9 - ratio.min(), 0.0)

    assert worst(x) > 0.4
    limit = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=300, update_velocity=False)
    x1, _ = limit.project(model, x, torch.zeros_like(x), 0.0, 1e-3)
    assert worst(x1) < 1e-6
    assert torch.equal(x1[:, :, 0], x[:, :, 0])  # fixed nodes stay


def test_no_op_within_bounds_and_velocity_follows(device):
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    model = td.Model(grid, stiffness=1.0, mass=1e-3, dtype=torch.float64, device=device)
    g = torch.Generator().manual_seed(1)
    x = model.X + 2e-4 * torch.randn(model.X.shape, generator=g, dtype=torch.float64).to(device)  # < 4 % strain
    v = torch.randn(x.shape, generator=g, dtype=torch.float64).to(device)
    x1, v1 = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=3).project(model, x, v, 0.0, 1e-3)
    assert torch.equal(x1, x) and torch.equal(v1, v)
    _, model2, xs = _stretched(device=device)
    x2, v2 = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=2).project(model2, xs, torch.zeros_like(xs), 0.0, 1e-3)
    assert torch.allclose(v2, (x2 - xs) / 1e-3, rtol=0, atol=1e-12)


def test_in_a_simulation_and_bad_input():
    grid = td.Grid((4, 3, 3), spacing=0.01, topology=26)
    pull = td.Drag(grid.face("top"), path=[(0.0, (0, 0, 0)), (0.01, (0.004, 0, 0))])  # 4 mm up in 10 ms
    edges = EdgeList(grid.shape, grid.spacing, 26)

    def largest_ratio(interactions):
        model = td.Model(
            grid,
            stiffness=0.5,
            mass=1e-3,
            fixed=grid.face("bottom"),
            drags=[pull],
            interactions=interactions,
            dtype=torch.float64,
        )
        state, _ = td.simulate(model, model.rest_state(), dt=1e-3, steps=10)
        p = edges.from_field(state.x[0])
        return (np.linalg.norm(p[edges.b] - p[edges.a], axis=1) / edges.l0).max(), model

    free_ratio, _ = largest_ratio(None)
    limited_ratio, _model = largest_ratio([StrainLimit(min_ratio=0.9, max_ratio=1.2, passes=200)])
    assert free_ratio > 1.3 and limited_ratio < 1.2 + 1e-6  # the soft springs would stretch far more
    for kwargs, key in (
        ({"min_ratio": 1.2}, "strain_limit"),
        ({"passes": 0}, "strain_limit.passes"),
        ({"max_ratio": -1.0}, "strain_limit.max_ratio"),
    ):
        with pytest.raises(ConfigError) as e:
            StrainLimit(**kwargs)
        assert e.value.key == key


@pytest.mark.parametrize("ratio", [0.9, 1.1])
def test_springs_on_their_bound_within_rounding_are_left_alone(ratio, device):
    """A body scaled onto a bound and a few ulps beyond it (rounding noise) is left exactly as it is."""
    grid = td.Grid((3, 4, 3), spacing=(0.01, 0.012, 0.007), topology=26)
    model = td.Model(grid, stiffness=1.0, mass=1e-3, fixed=grid.face("bottom"), dtype=torch.float64, device=device)
    x = model.X * (ratio * (1 + np.sign(ratio - 1) * 2e-15))  # ~ 10 ulps outside the bound
    edges = EdgeList(grid.shape, grid.spacing, 26)
    p = edges.from_field(x[0])
    length = np.linalg.norm(p[edges.b] - p[edges.a], axis=1)
    excess = length - np.clip(length, 0.9 * edges.l0, 1.1 * edges.l0)
    assert (np.abs(excess) > 0).all() and (np.abs(excess) < 64 * np.finfo(float).eps * edges.l0).all()
    free = ~edges.from_field(model.constrained[None].expand(3, *grid.shape))[:, 0].astype(bool)
    assert np.array_equal(oracle_pass(edges, p, free, 0.9, 1.1), p)
    v = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(device)
    limit = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=3)
    x1, v1 = limit.project(model, x, v, 0.0, 1e-3)
    assert torch.equal(x1, x) and torch.equal(v1, v)
    pm = PackedModel(model)
    ps = pm.pack_state(td.State(x, v))
    px, pv = limit.project(pm, ps.x, ps.v, 0.0, 1e-3)
    assert torch.equal(px, ps.x) and torch.equal(pv, ps.v)


@pytest.mark.parametrize("topology", [6, 18, 26])
def test_packed_layout_gives_the_same_projection(topology, device):
    """One ``project`` call on the packed layout (summed over all directions) equals the grid layout's."""
    nodes = torch.ones(4, 5, 3, dtype=torch.bool)
    nodes[3, 4, :] = False  # a body that is not a box
    grid = td.Grid((4, 5, 3), spacing=(0.01, 0.012, 0.01), topology=topology, node_mask=nodes)
    g = torch.Generator().manual_seed(topology)
    springs = torch.rand((grid.S,) + grid.shape, generator=g) > 0.25  # cut a quarter of them
    fixed = torch.zeros(grid.shape, dtype=torch.bool)
    fixed[0, :2] = True
    limit = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=2)

    def project(spring_mask):
        model = td.Model(
            grid,
            stiffness=torch.rand(grid.S, generator=g, dtype=torch.float64) + 0.5,
            mass=1e-3,
            fixed=fixed,
            spring_mask=spring_mask,
            dtype=torch.float64,
            device=device,
        )
        x = model.X * torch.tensor([1.5, 1.0, 0.75], dtype=torch.float64, device=device).view(1, 3, 1, 1, 1)
        x = x + 2e-3 * torch.randn((2,) + x.shape[1:], generator=g, dtype=torch.float64).to(device)  # batch of 2
        x = torch.where(model.constrained[None, None], model.X, x)
        v = torch.randn(x.shape, generator=g, dtype=torch.float64).to(device)
        grid_out = limit.project(model, x, v, 0.0, 1e-3)
        pm = PackedModel(model)
        ps = pm.pack_state(td.State(x, v))
        packed_out = limit.project(pm, ps.x, ps.v, 0.0, 1e-3)
        for a in packed_out:  # halo and padding stay 0
            assert torch.equal(pm.pack(pm.unpack(a)), a)
        return x, grid_out, pm.unpack_state(td.State(*packed_out))

    x, (xg, vg), packed = project(springs)
    assert (xg - x).abs().max() > 1e-3  # it did correct
    assert (packed.x - xg).abs().max() < 1e-12 and (packed.v - vg).abs().max() < 1e-12
    xg, x = xg.cpu(), x.cpu()
    assert torch.equal(xg[..., ~nodes], x[..., ~nodes]) and torch.equal(xg[:, :, fixed], x[:, :, fixed])
    _, (x_uncut, _), _ = project(None)  # the cut springs mattered
    assert (x_uncut.cpu() - xg).abs().max() > 1e-4


def test_compiled_step_wrapper_runs_strain_limits_like_simulate(device):
    """The eager packed path behind ``compiled_step`` (``enable=False``) equals ``td.simulate``."""
    grid = td.Grid((4, 3, 3), spacing=0.01, topology=26)
    pull = td.Drag(grid.face("top"), path=[(0.0, (0, 0, 0)), (0.01, (0.004, 0.001, 0))])
    model = td.Model(
        grid,
        stiffness=0.5,
        damping=0.002,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        drags=[pull],
        interactions=[StrainLimit(min_ratio=0.9, max_ratio=1.15, passes=5)],
        dtype=torch.float64,
        device=device,
    )
    dt, steps = 5e-4, 20
    rest = model.rest_state(batch=2)
    start = td.State(*model.constrain(rest.x, rest.v, 0.0), t=0.0)  # dragged nodes on their path, as simulate
    step = compiled_step(td.SymplecticEuler(), model, dt, enable=False)
    assert not step.compiled
    got = step.run(start, steps)
    want, _ = td.simulate(model, start, dt=dt, steps=steps, warn=False)
    free, _ = td.simulate(
        td.Model(
            grid,
            stiffness=0.5,
            damping=0.002,
            mass=1e-3,
            gravity=(-9.81, 0, 0),
            fixed=grid.face("bottom"),
            drags=[pull],
            dtype=torch.float64,
            device=device,
        ),
        start,
        dt=dt,
        steps=steps,
        warn=False,
    )
    assert (free.x - want.x).abs().max() > 1e-4  # the limit was active
    assert (got.x - want.x).abs().max() < 1e-10 and (got.v - want.v).abs().max() < 1e-10
    assert got.t == pytest.approx(want.t)
