"""Property tests (hypothesis): the stencil spring forces equal the edge-list oracle.

Random small grids (1 to 4 nodes per axis, anisotropic spacing), every topology, a random node
mask, random per-spring stiffness and damping, positions near rest and random velocities, both
damping modes, float64. The oracle (:class:`tests.oracles.edge_list.EdgeList`) lists every spring
from the node coordinates and sums the forces in a Python loop.
"""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import torchdeform as td
from tests.oracles.edge_list import EdgeList
from torchdeform.sim import springs

ATOL = 1e-11


@st.composite
def spring_cases(draw):
    shape = tuple(draw(st.lists(st.integers(1, 4), min_size=3, max_size=3)))
    topology = draw(st.sampled_from([6, 14, 18, 26]))
    spacing = tuple(draw(st.lists(st.floats(0.8, 1.5), min_size=3, max_size=3)))
    mask = draw(hnp.arrays(bool, shape))
    mask[draw(st.tuples(*[st.integers(0, n - 1) for n in shape]))] = True  # at least one node
    batch = draw(st.integers(1, 2))
    # each node moves at most 0.2 * sqrt(3) < 0.4: two nodes never come closer than 0.8 - 0.7 > 0
    dx = draw(hnp.arrays(np.float64, (batch, 3) + shape, elements=st.floats(-0.2, 0.2)))
    v = draw(hnp.arrays(np.float64, (batch, 3) + shape, elements=st.floats(-1.0, 1.0)))
    S = topology // 2
    k = draw(hnp.arrays(np.float64, (S,) + shape, elements=st.floats(0.1, 5.0)))
    c = draw(st.none() | hnp.arrays(np.float64, (S,) + shape, elements=st.floats(0.01, 2.0)))
    projected = draw(st.booleans())
    return shape, topology, spacing, mask, dx, v, k, c, projected


@settings(max_examples=150, deadline=None)
@given(spring_cases())
def test_stencil_forces_equal_edge_list(case):
    shape, topology, spacing, mask, dx, v, k, c, projected = case
    grid = td.Grid(shape, spacing=spacing, topology=topology, node_mask=torch.from_numpy(mask))
    edges = EdgeList(shape, spacing, topology, mask)
    assert grid.num_springs == len(edges.springs)
    loc = edges.locate(grid.directions)  # which stencil entry holds each listed spring
    k_e = np.array([k[(s,) + p] for s, p, _ in loc])
    c_e = None if c is None else np.array([c[(s,) + p] for s, p, _ in loc])
    model = td.Model(
        grid,
        stiffness=torch.from_numpy(k),
        damping=None if c is None else torch.from_numpy(c),
        damping_mode="projected" if projected else "unprojected",
        mass=1.0,
        dtype=torch.float64,
    )
    X = np.stack(np.meshgrid(*[np.arange(n) * h for n, h in zip(shape, spacing)], indexing="ij"))
    x = torch.from_numpy(X[None] + dx)
    vt = torch.from_numpy(v)
    results = {
        "model fast": model.spring_forces(x, vt, impl="fast"),
        "model conv": model.spring_forces(x, vt, impl="conv"),
        "springs.spring_forces": springs.spring_forces(
            x, vt, grid, model.stiffness, model.rest_length, c=model.damping, projected=projected
        ),
    }
    for b in range(x.shape[0]):
        xb, vb = edges.from_field(X + dx[b]), edges.from_field(v[b])
        ref = edges.to_field(edges.forces(xb, vb, k_e, c_e, projected))
        for name, got in results.items():
            np.testing.assert_allclose(got[b].numpy(), ref, rtol=0, atol=ATOL, err_msg=name)
