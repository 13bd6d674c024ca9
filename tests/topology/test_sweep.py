"""Triangle and swept blades, progressive cutting and gaping, against a numpy brute force.

The oracle lists every spring of the grid explicitly (tests.oracles.edge_list) and intersects
each segment with each triangle by Moller-Trumbore (its own triangulation of the swept surface:
two triangles per interval), independently of torchdeform's plane-grouped search.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from tests.oracles.edge_list import EdgeList
from torchdeform.interact import Sphere, Tool
from torchdeform.topology import Blade, Scalpel, components, crossing, cut

H = 0.01


def _segment_hits_triangle(p, q, a, b, c):
    """Moller-Trumbore: the closed segment p-q meets the triangle abc (no ties in these tests)."""
    d, e1, e2 = q - p, b - a, c - a
    h = np.cross(d, e2)
    det = e1 @ h
    if abs(det) < 1e-300:
        return False
    s = p - a
    u = (s @ h) / det
    qv = np.cross(s, e1)
    v = (d @ qv) / det
    t = (e2 @ qv) / det
    return u >= 0 and v >= 0 and u + v <= 1 and 0 <= t <= 1


def _oracle(el, x, triangles):
    out = set()
    for a, b, _ in el.springs:
        if any(_segment_hits_triangle(x[a], x[b], *tri) for tri in triangles):
            out.add((a, b))
    return out


def _body(topology, seed=1, device=None):
    grid = td.Grid((6, 6, 5), spacing=H, topology=topology)
    model = td.Model(grid, stiffness=10.0, damping=0.01, mass=1e-3, dtype=F64, device=device)
    gen = torch.Generator().manual_seed(seed)
    x = model.X + 0.2 * H * torch.randn(model.X.shape, generator=gen, dtype=F64).to(device)
    return grid, model, x, EdgeList(grid.shape, (H,) * 3, topology)


def _curved_edges(k=7):
    """A cutting edge that descends into the body while it turns about the vertical (a curved cut)."""
    out = []
    for i in range(k):
        phi = 0.9 * i / (k - 1)
        centre = np.array([0.035 - 0.004 * i / (k - 1), 0.012 + 0.03 * i / (k - 1), 0.021])
        half = 0.03 * np.array([0.55, np.sin(phi) * 0.3, np.cos(phi)])
        out.append([centre - half, centre + half])
    return np.array(out)


@pytest.mark.parametrize("topology", [6, 18, 26])
def test_triangle_blade_matches_brute_force(topology, device):
    grid, _model, x, el = _body(topology, device=device)
    a, b, c = np.array([0.005, -0.004, 0.01]), np.array([0.05, 0.02, 0.002]), np.array([0.02, 0.055, 0.045])
    hit = crossing(grid, x, Blade.triangle(tuple(a), tuple(b), tuple(c)))[0].cpu()
    expect = _oracle(el, el.from_field(x[0]), [(a, b, c)])
    assert len(expect) > 10 and el.slot_pairs(grid.directions, hit) == expect


@pytest.mark.parametrize("topology", [6, 18, 26])
def test_curved_swept_blade_matches_brute_force(topology, device):
    grid, model, x, el = _body(topology, seed=2, device=device)
    edges = _curved_edges()
    blade = Blade.swept(edges)
    assert sum(tri for *_, tri in blade.patches) >= 2 and len(blade.planes()) > 2  # curved: many planes
    triangles = []
    for k in range(len(edges) - 1):
        a0, b0, a1, b1 = edges[k, 0], edges[k, 1], edges[k + 1, 0], edges[k + 1, 1]
        triangles += [(a0, b0, b1), (a0, b1, a1)]
    hit = crossing(grid, x, blade)[0].cpu()
    expect = _oracle(el, el.from_field(x[0]), triangles)
    assert len(expect) > 20 and el.slot_pairs(grid.directions, hit) == expect
    assert cut(model, x, blade) == len(expect)


def test_progressive_cut_equals_one_cut_of_the_whole_sweep(device):
    """A scalpel updated every step cuts exactly what the whole path's swept surface crosses."""
    grid, model, x, el = _body(26, seed=3, device=device)
    start, end = (0.025, -0.012, 0.0), (0.028, 0.075, 0.0)
    tool = Tool(Sphere(0.001), path=[(0.0, start), (1.0, end)])
    knife = Scalpel(tool, edge=((0.0, 0.0, -0.012), (0.0, 0.0, 0.03)))
    state = td.State(x.clone(), torch.zeros_like(x), t=0.0)
    total = 0
    for i in range(41):
        state.t = i / 40
        total = total + knife.update(model, state, as_tensor=True)  # counted on the device, read once
    ref = td.Model(grid, stiffness=10.0, damping=0.01, mass=1e-3, dtype=F64, device=device)
    edges = [[(s[0], s[1], s[2] - 0.012), (s[0], s[1], s[2] + 0.03)] for s in (start, end)]
    assert int(total) == cut(ref, x, Blade.swept(edges)) > 30
    assert torch.equal(model.stiffness != 0, ref.stiffness != 0)
    # a turning edge: the progressive cut follows the curved surface, matching the oracle
    grid, model, x, el = _body(18, seed=4, device=device)
    tool = Tool(
        Sphere(0.001), path=[(0.0, (0.025, 0.0, 0.02), (0.0, 0.0, 0.0)), (1.0, (0.025, 0.05, 0.02), (0.0, 0.8, 0.0))]
    )
    knife = Scalpel(tool, edge=((0.0, 0.0, -0.03), (0.0, 0.0, 0.03)), pieces=4)
    state = td.State(x.clone(), torch.zeros_like(x), t=0.0)
    for i in range(11):
        state.t = i / 10
        knife.update(model, state)
    triangles = []
    ts = np.linspace(0, 1, 41)
    ends = np.stack([knife.edge_at(float(t)).numpy() for t in ts])
    for k in range(len(ts) - 1):
        triangles += [(ends[k, 0], ends[k, 1], ends[k + 1, 1]), (ends[k, 0], ends[k + 1, 1], ends[k + 1, 0])]
    expect = _oracle(el, el.from_field(x[0]), triangles)
    got = el.slot_pairs(grid.directions, (model.stiffness[0].cpu() == 0) & grid.spring_mask())
    assert len(expect) > 20 and got == expect


def test_gape_shortens_the_springs_at_the_cut_once_and_opens_it(device):
    n = 6
    grid = td.Grid((n, n, n), spacing=H, topology=26)
    blade = Blade((2.5 * H, -H, -H), (0.0, (n + 1) * H, 0.0), (0.0, 0.0, (n + 1) * H))

    def opened(gape):
        model = td.Model(
            grid, stiffness=20.0, damping=0.05, mass=1e-3, fixed=grid.face("bottom"), dtype=F64, device=device
        )
        cut(model, model.X, blade, gape=gape)
        state, _ = td.simulate(model, model.rest_state(), dt=2e-4, steps=1500)
        return model, float((state.x[0, 0, 3] - state.x[0, 0, 2]).mean())  # distance across the cut

    model, gap = opened(0.2)
    _, gap0 = opened(0.0)
    assert abs(gap0 - H) < 1e-9 and gap > H * 1.05  # the cut gapes open
    # exactly the springs left at the two layers of the cut are shortened, by 20 %
    l0 = grid.rest_lengths(dtype=F64).view(-1, 1, 1, 1).expand(-1, *grid.shape)
    ratio = model.rest_length[0].cpu() / l0
    live = (model.stiffness[0].cpu() != 0) & grid.spring_mask()
    at_cut = torch.zeros((grid.S,) + grid.shape, dtype=torch.bool)
    for s, d in enumerate(grid.directions):
        for ijk in zip(*torch.nonzero(grid.spring_mask()[s], as_tuple=True)):
            ends = (int(ijk[0]), int(ijk[0]) + d[0])
            at_cut[(s,) + tuple(int(i) for i in ijk)] = 2 in ends or 3 in ends
    assert torch.allclose(ratio[live & at_cut], torch.tensor(0.8, dtype=F64))
    assert torch.allclose(ratio[live & ~at_cut], torch.tensor(1.0, dtype=F64))
    # a second cut through the same nodes shortens nothing again
    before = model.rest_length.clone()
    cut(model, model.X, Blade((2.5 * H, -H, -H), (0.0, (n + 1) * H, 0.0), (0.0, 0.0, (n + 1) * H)), gape=0.2)
    assert torch.equal(model.rest_length, before)
    assert components(model)[1] == 2
