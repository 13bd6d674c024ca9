"""The spring operator against a plain edge list.

Oracle: :class:`tests.oracles.edge_list.EdgeList`, which lists every spring of the grid from the node
coordinates (every node, every neighbour offset) and computes differences, forces (Hookean,
projected and unprojected damping), energies and stiffness matrices spring by spring in numpy.
The conv3d reference (``difference_conv`` / ``adjoint_conv`` / ``spring_forces_conv``) and the
shifted-slice fast path (``difference`` / ``adjoint`` / ``accumulate`` / ``spring_forces``) must
both equal it to 1e-12 (float64).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.oracles.edge_list import EdgeList
from torchdeform.sim import springs

TOPOLOGIES = (6, 14, 18, 26)
SHAPE = (4, 3, 5)  # non-cubic, so that axis mix-ups show
SPACING = (0.9, 1.15, 1.3)  # anisotropic
ATOL = 1e-12


def _node_mask(shape, seed=1):
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) < 0.8
    mask[0, 0, 0] = mask[1, 1, 1] = True
    return mask


def _deformed(grid, B=2, amp=0.25, seed=0):
    """Random deformed positions and velocities ``(B, 3, D, H, W)``, float64."""
    gen = torch.Generator().manual_seed(seed)
    X = grid.rest_positions(dtype=torch.float64)
    x = X + amp * torch.randn((B, 3) + grid.shape, generator=gen, dtype=torch.float64)
    v = torch.randn((B, 3) + grid.shape, generator=gen, dtype=torch.float64)
    return x, v


# ------------------------------------------------------------------- counting
@pytest.mark.parametrize("topology,expected", [(6, 54), (18, 126), (14, 86), (26, 158)])
def test_spring_counts_at_n3(topology, expected):
    """REFERENCE 1.1: 54 (axes), 126 (+ face diagonals), 86 (+ body diagonals), 158 (all)."""
    assert td.Grid((3, 3, 3), topology=topology).num_springs == expected
    assert len(EdgeList((3, 3, 3), (1, 1, 1), topology).springs) == expected


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_spring_count_formulas(n, topology):
    """3 n^2 (n-1) axes, + 6 n (n-1)^2 face diagonals, + 4 (n-1)^3 body diagonals."""
    axis, face, body = 3 * n * n * (n - 1), 6 * n * (n - 1) ** 2, 4 * (n - 1) ** 3
    expected = {6: axis, 14: axis + body, 18: axis + face, 26: axis + face + body}[topology]
    assert td.Grid((n, n, n), topology=topology).num_springs == expected


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_spring_count_with_node_mask_and_box(topology):
    for shape, mask in (((2, 3, 5), None), ((4, 3, 5), _node_mask((4, 3, 5)))):
        grid = td.Grid(
            shape, spacing=SPACING, topology=topology, node_mask=None if mask is None else torch.from_numpy(mask)
        )
        edges = EdgeList(shape, SPACING, topology, mask)
        assert grid.num_springs == len(edges.springs)
        assert int(grid.spring_mask().sum()) == len(edges.springs)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_rest_lengths_anisotropic(topology):
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    edges = EdgeList(SHAPE, SPACING, topology)
    l0 = grid.rest_lengths(dtype=torch.float64).numpy()
    for (s, _, _), ref in zip(edges.locate(grid.directions), edges.l0):
        assert abs(l0[s] - ref) < 1e-15


# ------------------------------------------------------------ D and D^T
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_difference_matches_edge_list(topology, device):
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    edges = EdgeList(SHAPE, SPACING, topology)
    x = torch.randn((2, 3) + SHAPE, dtype=torch.float64)
    ref = np.zeros((2, grid.S, 3) + SHAPE)
    for s, p, q in edges.locate(grid.directions):
        ref[(slice(None), s, slice(None)) + p] = (
            x.numpy()[(slice(None), slice(None)) + q] - x.numpy()[(slice(None), slice(None)) + p]
        )
    fast = springs.difference(x.to(device), grid).cpu().numpy()
    conv = springs.difference_conv(x.to(device), grid).cpu().numpy()
    np.testing.assert_allclose(fast, ref, rtol=0, atol=ATOL)
    np.testing.assert_allclose(conv, ref, rtol=0, atol=ATOL)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_adjoint_matches_edge_list(topology, device):
    """``D^T f``: each spring's value leaves its first endpoint and arrives at its second."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    edges = EdgeList(SHAPE, SPACING, topology)
    f = torch.randn((2, grid.S, 3) + SHAPE, dtype=torch.float64)
    ref = np.zeros((2, 3) + SHAPE)
    fn = f.numpy()
    for s, p, q in edges.locate(grid.directions):
        val = fn[(slice(None), s, slice(None)) + p]
        ref[(slice(None), slice(None)) + p] -= val
        ref[(slice(None), slice(None)) + q] += val
    fd = f.to(device)
    np.testing.assert_allclose(springs.adjoint(fd, grid).cpu().numpy(), ref, rtol=0, atol=ATOL)
    np.testing.assert_allclose(springs.adjoint_conv(fd, grid).cpu().numpy(), ref, rtol=0, atol=ATOL)
    # accumulate with b = -a is -D^T a
    acc = springs.accumulate(
        grid,
        lambda s, src, d: fd[(slice(None), s, slice(None), *src)],
        torch.zeros((2, 3) + SHAPE, dtype=torch.float64, device=device),
    )
    np.testing.assert_allclose(acc.cpu().numpy(), -ref, rtol=0, atol=ATOL)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_adjointness(topology, device):
    """<D x, f> = <x, D^T f> for both implementations (f only on springs inside the grid)."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    x = torch.randn((3, 2) + SHAPE, dtype=torch.float64).to(device)
    f = torch.randn((3, grid.S, 2) + SHAPE, dtype=torch.float64).to(device)
    f = f * grid.spring_mask(device=device)[None, :, None].to(torch.float64)
    for D, DT in ((springs.difference, springs.adjoint), (springs.difference_conv, springs.adjoint_conv)):
        lhs = (D(x, grid) * f).sum()
        rhs = (x * DT(f, grid)).sum()
        assert abs(float(lhs - rhs)) <= 1e-12 * float(f.abs().sum())


# --------------------------------------------------------------- forces
@pytest.mark.parametrize("projected", [True, False])
@pytest.mark.parametrize("use_mask", [False, True])
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_spring_forces_match_edge_list(topology, use_mask, projected, device):
    """conv3d reference = fast path = edge list, with per-spring random stiffness and damping,
    anisotropic spacing, a node mask, random deformed states and velocities (batch of 2)."""
    mask = _node_mask(SHAPE) if use_mask else None
    grid = td.Grid(
        SHAPE, spacing=SPACING, topology=topology, node_mask=None if mask is None else torch.from_numpy(mask)
    )
    edges = EdgeList(SHAPE, SPACING, topology, mask)
    rng = np.random.default_rng(topology)
    k_full = rng.uniform(0.5, 2.0, (grid.S,) + SHAPE)  # also on springs that do not exist
    c_full = rng.uniform(0.1, 0.7, (grid.S,) + SHAPE)
    loc = edges.locate(grid.directions)
    k_e = np.array([k_full[(s,) + p] for s, p, _ in loc])
    c_e = np.array([c_full[(s,) + p] for s, p, _ in loc])
    model = td.Model(
        grid,
        stiffness=torch.from_numpy(k_full),
        damping=torch.from_numpy(c_full),
        damping_mode="projected" if projected else "unprojected",
        mass=1.0,
        dtype=torch.float64,
        device=device,
    )
    x, v = _deformed(grid)
    xd, vd = x.to(device), v.to(device)
    f_fast = model.forces(xd, vd, impl="fast").cpu()
    f_conv = model.forces(xd, vd, impl="conv").cpu()
    f_direct = springs.spring_forces(
        xd, vd, grid, model.stiffness, model.rest_length, c=model.damping, projected=projected
    ).cpu()
    for b in range(x.shape[0]):
        ref = edges.to_field(edges.forces(edges.from_field(x[b]), edges.from_field(v[b]), k_e, c_e, projected))
        np.testing.assert_allclose(f_fast[b].numpy(), ref, rtol=0, atol=ATOL)
        np.testing.assert_allclose(f_conv[b].numpy(), ref, rtol=0, atol=ATOL)
        np.testing.assert_allclose(f_direct[b].numpy(), ref, rtol=0, atol=ATOL)
    # without damping
    und = td.Model(grid, stiffness=torch.from_numpy(k_full), mass=1.0, dtype=torch.float64, device=device)
    ref = edges.to_field(edges.forces(edges.from_field(x[0]), k=k_e))
    np.testing.assert_allclose(und.forces(xd, vd, impl="fast")[0].cpu().numpy(), ref, rtol=0, atol=ATOL)
    np.testing.assert_allclose(und.forces(xd, vd, impl="conv")[0].cpu().numpy(), ref, rtol=0, atol=ATOL)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_per_direction_class_stiffness(topology):
    """A dict by direction class gives every spring of a class its value."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    edges = EdgeList(SHAPE, SPACING, topology)
    values = {"axis": 1.3, "face": 0.7, "body": 0.4}
    classes = {1: "axis", 2: "face", 3: "body"}
    k_e = np.array([values[classes[sum(map(abs, off))]] for _, _, off in edges.springs])
    model = td.Model(grid, stiffness={c: values[c] for c in set(grid.direction_class())}, mass=1.0, dtype=torch.float64)
    x, _ = _deformed(grid, B=1)
    ref = edges.to_field(edges.forces(edges.from_field(x[0]), k=k_e))
    np.testing.assert_allclose(model.forces(x, torch.zeros_like(x))[0].numpy(), ref, rtol=0, atol=ATOL)


def test_edge_list_oracle_is_consistent():
    """Self-check of the oracle: its forces are minus the central-difference gradient of its
    energy, and its Hessian is the central-difference Jacobian of minus its forces."""
    edges = EdgeList((2, 2, 3), SPACING, 26)
    rng = np.random.default_rng(3)
    k = rng.uniform(0.5, 2, len(edges.springs))
    x = edges.X + 0.2 * rng.standard_normal(edges.X.shape)
    F = edges.forces(x, k=k)
    np.testing.assert_allclose(edges.forces_vec(x, k), F, atol=1e-13)
    H = edges.hessian(x, k)
    eps = 1e-6
    for a in range(edges.N):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[a, c] += eps
            xm[a, c] -= eps
            g = (edges.energy(xp, k) - edges.energy(xm, k)) / (2 * eps)
            assert abs(g + F[a, c]) < 1e-8
            col = -(edges.forces(xp, k=k) - edges.forces(xm, k=k)).ravel() / (2 * eps)
            np.testing.assert_allclose(H[:, 3 * a + c], col, atol=1e-7)


# --------------------------------------------------------------- energy
@pytest.mark.parametrize("use_mask", [False, True])
@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_spring_energy_matches_edge_list(topology, use_mask, device):
    mask = _node_mask(SHAPE) if use_mask else None
    grid = td.Grid(
        SHAPE, spacing=SPACING, topology=topology, node_mask=None if mask is None else torch.from_numpy(mask)
    )
    edges = EdgeList(SHAPE, SPACING, topology, mask)
    k_full = np.random.default_rng(5).uniform(0.5, 2.0, (grid.S,) + SHAPE)
    k_e = np.array([k_full[(s,) + p] for s, p, _ in edges.locate(grid.directions)])
    model = td.Model(grid, stiffness=torch.from_numpy(k_full), mass=1.0, dtype=torch.float64, device=device)
    x, v = _deformed(grid)
    e = model.energy(td.State(x.to(device), v.to(device)))["elastic"].cpu()
    for b in range(2):
        ref = edges.energy(edges.from_field(x[b]), k_e)
        assert abs(float(e[b]) - ref) <= 1e-12 * max(1.0, ref)


@pytest.mark.parametrize("topology", TOPOLOGIES)
def test_forces_are_minus_energy_gradient(topology):
    """The conservative part of ``model.forces`` (springs, home springs, gravity) equals
    ``-dE/dx`` of ``model.energy`` (autograd), at the nodes that exist."""
    mask = _node_mask(SHAPE)
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology, node_mask=torch.from_numpy(mask))
    k_full = torch.from_numpy(np.random.default_rng(7).uniform(0.5, 2.0, (grid.S,) + SHAPE))
    mass = torch.from_numpy(np.random.default_rng(8).uniform(0.5, 2.0, SHAPE))
    model = td.Model(grid, stiffness=k_full, mass=mass, gravity=(-9.81, 1.0, 0.5), home=0.3, dtype=torch.float64)
    x, v = _deformed(grid)
    x.requires_grad_(True)
    e = model.energy(td.State(x, torch.zeros_like(v)))
    (grad,) = torch.autograd.grad((e["elastic"] + e["gravity"]).sum(), x)
    F = model.forces(x.detach(), v)
    nodes = torch.from_numpy(mask)
    np.testing.assert_allclose(F[..., nodes].numpy(), -grad[..., nodes].numpy(), rtol=0, atol=1e-12)


# -------------------------------------------------------- stiffness products
@pytest.mark.parametrize("projected", [True, False])
@pytest.mark.parametrize("topology", (6, 26))
def test_linearisation_matches_assembled_matrices(topology, projected):
    """``Linearisation.apply`` = ``h^2 K u + h C u`` with ``K`` the edge-list Hessian (clamped
    and unclamped) and ``C`` the edge-list damping matrix."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    edges = EdgeList(SHAPE, SPACING, topology)
    rng = np.random.default_rng(11)
    k_full = rng.uniform(0.5, 2.0, (grid.S,) + SHAPE)
    c_full = rng.uniform(0.1, 0.7, (grid.S,) + SHAPE)
    loc = edges.locate(grid.directions)
    k_e = np.array([k_full[(s,) + p] for s, p, _ in loc])
    c_e = np.array([c_full[(s,) + p] for s, p, _ in loc])
    model = td.Model(
        grid,
        stiffness=torch.from_numpy(k_full),
        damping=torch.from_numpy(c_full),
        mass=1.0,
        damping_mode="projected" if projected else "unprojected",
        dtype=torch.float64,
    )
    x, u = _deformed(grid, B=1, amp=0.15)
    xe, ue = edges.from_field(x[0]), edges.from_field(u[0]).ravel()
    for clamp in (False, True):
        K = edges.hessian(xe, k_e, clamp=clamp)
        lin = model.linearise(x, clamp=clamp)
        np.testing.assert_allclose(edges.from_field(lin.apply(u)[0]).ravel(), K @ ue, rtol=0, atol=1e-11)
        h = 0.3
        C = edges.damping_matrix(xe, c_e, projected)
        got = lin.apply(u, alpha_scale=h * h, c=model.damping, projected=model.projected, c_scale=h)
        np.testing.assert_allclose(edges.from_field(got[0]).ravel(), (h * h * K + h * C) @ ue, rtol=0, atol=1e-11)
