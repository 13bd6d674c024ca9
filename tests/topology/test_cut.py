"""Cutting and connected components (torchdeform.topology) against independent oracles.

* a full cut between two adjacent layers removes the analytic counts of REFERENCE.md §6.2
  (6: n^2, 14: n^2 + 4(n-1)^2, 18: n^2 + 4n(n-1), 26: (3n-2)^2) and leaves 2 components;
* a tilted, partial blade through a deformed body cuts exactly the springs a plain numpy
  segment-rectangle test over an explicit edge list finds;
* components equal scipy.sparse.csgraph.connected_components of the remaining edge list;
* after a full cut the upper piece falls freely (acceleration g exactly, nothing holds it);
* the dense search (every slot tested, nothing read back to the host: the accelerator's) finds
  exactly the slots of the layer search, on the device of the run against the CPU;
* cuts, gaping, a scalpel's sweep and tears counted on the device never wait for it (on CUDA,
  torch's sync debug mode raises on any wait) and edit the model as on the CPU.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

import torchdeform as td
from tests.helpers import F64, make_grid, make_model, no_host_wait
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.interact import Sphere, Tool
from torchdeform.topology import Blade, Scalpel, components, crossing, cut, tear
from torchdeform.topology.masks import editable

H = 0.01


def _model(n, topology, shape=None, device=None):
    grid = make_grid(shape or n, spacing=H, topology=topology)
    return grid, make_model(grid, stiffness=10.0, damping=0.01, device=device)


@pytest.mark.parametrize(
    "topology, count",
    [
        (6, lambda n: n * n),
        (14, lambda n: n * n + 4 * (n - 1) ** 2),
        (18, lambda n: n * n + 4 * n * (n - 1)),
        (26, lambda n: (3 * n - 2) ** 2),
    ],
)
@pytest.mark.parametrize("n", [3, 5])
def test_full_layer_cut_removes_the_analytic_count(topology, count, n, device):
    grid, model = _model(n, topology, device=device)
    blade = Blade((1.5 * H, -H, -H), (0.0, (n + 1) * H, 0.0), (0.0, 0.0, (n + 1) * H))
    assert cut(model, model.X, blade) == count(n)
    assert int(((model.stiffness != 0) & grid.spring_mask(device=device)).sum()) == grid.num_springs - count(n)
    assert components(model)[1] == 2
    assert cut(model, model.X, blade) == 0  # nothing left to cut there


def _numpy_crossings(el, x, o, u, v):
    """Springs (a, b) of the edge list whose segment meets the rectangle o + a u + b v."""
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    out = set()
    for a, b, _ in el.springs:
        p, q = x[a], x[b]
        hp, hq = (p - o) @ n, (q - o) @ n
        if (hp > 0) == (hq > 0):
            continue
        r = p + hp / (hp - hq) * (q - p)
        s, t = (r - o) @ u / (u @ u), (r - o) @ v / (v @ v)
        if 0 <= s <= 1 and 0 <= t <= 1:
            out.add((a, b))
    return out


@pytest.mark.parametrize("topology", [6, 18, 26])
def test_partial_tilted_blade_on_a_deformed_body_matches_numpy(topology, device):
    grid, model = _model(0, topology, shape=(5, 6, 4), device=device)
    gen = torch.Generator().manual_seed(1)
    x = model.X + 0.2 * H * torch.randn(model.X.shape, generator=gen, dtype=F64).to(device)
    rng = np.random.default_rng(2)
    axis = rng.normal(size=3)
    u = np.cross(axis, [0.3, 1.0, 0.2])
    u *= 0.035 / np.linalg.norm(u)
    v = np.cross(axis, u)
    v *= 0.03 / np.linalg.norm(v)
    o = np.array([0.02, 0.025, 0.015]) - 0.5 * u - 0.4 * v
    blade = Blade(tuple(o), tuple(u), tuple(v))
    hit = crossing(grid, x, blade)[0].cpu()
    el = EdgeList(grid.shape, (H,) * 3, topology)
    expect = _numpy_crossings(el, el.from_field(x[0]), o, u, v)
    assert len(expect) > 5 and el.slot_pairs(grid.directions, hit) == expect


def test_components_equal_scipy_on_random_removals(device):
    grid, model = _model(0, 18, shape=(4, 5, 6), device=device)
    gen = torch.Generator().manual_seed(3)
    keep = (torch.rand((1, grid.S) + grid.shape, generator=gen, dtype=F64) > 0.8).to(device)
    model.stiffness = model.stiffness.expand_as(keep) * keep
    labels, count = components(model)
    el = EdgeList(grid.shape, (H,) * 3, 18)
    alive = []
    stiffness = model.stiffness.cpu()
    for s, d in enumerate(grid.directions):
        for ijk in zip(*torch.nonzero((stiffness[0, s] != 0) & grid.spring_mask()[s], as_tuple=True)):
            alive.append((el.index[tuple(int(i) for i in ijk)], el.index[tuple(int(i) + c for i, c in zip(ijk, d))]))
    a, b = np.array(alive).T
    ref_count, ref = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(el.N, el.N)), directed=False)
    assert count == ref_count > 3
    flat = labels.flatten().cpu().numpy()
    same_ref = ref[:, None] == ref[None, :]
    same = flat[:, None] == flat[None, :]
    order = [np.ravel_multi_index(ijk, grid.shape) for ijk in el.nodes]
    assert np.array_equal(same[np.ix_(order, order)], same_ref)


def test_cut_piece_falls_freely(device):
    grid = td.Grid((4, 3, 3), spacing=H, topology=26)
    model = td.Model(
        grid,
        stiffness=20.0,
        damping=0.02,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
    )
    blade = Blade((1.5 * H, -H, -H), (0.0, 5 * H, 0.0), (0.0, 0.0, 5 * H))
    cut(model, model.X, blade)
    state, _ = td.simulate(model, model.rest_state(), dt=1e-4, steps=200)
    top = state.x[0, 0, 2:] - model.X[0, 0, 2:]
    t = state.t
    # symplectic Euler: x_n = x_0 - g h^2 n (n + 1) / 2 exactly for a free particle
    n = 200
    assert torch.allclose(top, torch.full_like(top, -9.81 * 1e-8 * n * (n + 1) / 2), atol=1e-13)
    assert abs(t - 0.02) < 1e-12


@pytest.mark.parametrize("topology", [6, 14, 18, 26])
def test_dense_search_finds_the_slots_of_the_layer_search(topology, device):
    """Full, oblique partial and swept blades through a batch of two deformed bodies with a node mask."""
    nodes = torch.ones(5, 6, 4, dtype=torch.bool)
    nodes[4, 5], nodes[0, 0, 0] = False, False  # a body that is not a box
    grid = make_grid((5, 6, 4), spacing=H, topology=topology, node_mask=nodes)
    gen = torch.Generator().manual_seed(topology)
    x = grid.rest_positions(dtype=F64).repeat(2, 1, 1, 1, 1)
    x = x + 0.2 * H * torch.randn(x.shape, generator=gen, dtype=F64)
    blades = [
        Blade((2.5 * H, -H, -H), (0.0, 8 * H, 0.0), (0.0, 0.0, 6 * H)),  # full, axis-aligned
        Blade((0.02, 0.0, 0.01), (0.012, 0.03, 0.004), (-0.02, 0.006, 0.025)),  # oblique, partial
        Blade.swept([[(0.0, 0.01, -0.01), (0.05, 0.02, 0.05)], [(0.01, 0.04, -0.01), (0.04, 0.05, 0.05)]]),
    ]
    for blade in blades:
        layers = crossing(grid, x, blade, dense=False)
        assert int(layers.sum()) > 5
        assert torch.equal(crossing(grid, x, blade, dense=True), layers)
        assert torch.equal(crossing(grid, x.to(device), blade).cpu(), layers)  # dense on an accelerator
    # the count of a cut, read at once or kept on the device
    box, model = _model(0, topology, shape=(5, 6, 4), device=device)
    n = cut(model, model.X, blades[0], as_tensor=True)
    assert torch.is_tensor(n) and n.device == model.stiffness.device and n.dtype == torch.int64
    assert int(n) == int(crossing(box, model.X.cpu(), blades[0], dense=False).sum()) > 0
    assert int(cut(model, model.X, blades[0], as_tensor=True)) == 0 and cut(model, model.X, blades[0]) == 0


def _cuts_and_tears(device, in_place):
    """A cut, a gaping cut, a scalpel's sweep and two tears of one body, counted on its device."""
    grid = make_grid((6, 5, 4), spacing=H, topology=26)
    model = make_model(grid, stiffness=10.0, damping=0.01, device=device)
    if in_place:
        editable(model)
    gen = torch.Generator().manual_seed(7)
    x = model.X + 0.15 * H * torch.randn(model.X.shape, generator=gen, dtype=F64).to(device)
    across = Blade((1.5 * H, -H, -H), (0.0, 3 * H, 0.0), (0.0, 0.0, 6 * H))  # partial
    oblique = Blade((0.03, 0.0, 0.0), (0.01, 0.05, 0.0), (-0.005, 0.0, 0.04))
    tool = Tool(Sphere(0.001), path=[(0.0, (0.045, -0.01, 0.0)), (1.0, (0.045, 0.06, 0.0))])
    knife = Scalpel(tool, edge=((0.0, 0.0, -0.01), (0.0, 0.0, 0.05)))
    crossing(grid, x, across)  # the grid's tables on the device are built (and copied there) once, before
    counts = []
    with no_host_wait(device):
        counts.append(cut(model, x, across, as_tensor=True))
        counts.append(cut(model, x, oblique, gape=0.1, as_tensor=True))
        for i in range(5):
            counts.append(knife.update(model, td.State(x, torch.zeros_like(x), t=i / 4), as_tensor=True))
        counts.append(tear(model, x, 0.15, as_tensor=True))
        counts.append(tear(model, x, 1e-3, one_per_step=True, as_tensor=True))
    return [int(n) for n in counts], model


@pytest.mark.parametrize("in_place", [False, True], ids=["replaced", "editable"])
def test_cuts_and_tears_queue_on_the_device_without_waiting_for_it(in_place, device):
    counts, model = _cuts_and_tears(device, in_place)
    ref, ref_model = _cuts_and_tears(torch.device("cpu"), in_place)  # the oracle: the same edits on the CPU
    assert counts == ref and all(n > 0 for n in ref[:2] + ref[-2:]) and sum(ref[2:-2]) > 0
    assert torch.equal(model.stiffness.cpu(), ref_model.stiffness)
    assert torch.allclose(model.rest_length.cpu(), ref_model.rest_length, rtol=1e-15, atol=0)
    assert torch.equal(model.cut_nodes.cpu(), ref_model.cut_nodes)


def test_degenerate_blades_are_refused():
    with pytest.raises(ConfigError, match="not parallel"):
        Blade((0, 0, 0), (1, 0, 0), (2, 0, 0))
    with pytest.raises(ConfigError, match="blade"):
        Blade((0, 0, 0), (0, 0, 0), (0, 1, 0))
    with pytest.raises(ConfigError, match="not on one line"):
        Blade.triangle((0, 0, 0), (1, 1, 1), (2, 2, 2))
    with pytest.raises(ConfigError, match="sweeps a surface"):
        Blade.swept([[(0, 0, 0), (0, 0, 1)], [(0, 0, 1), (0, 0, 2)]])
