"""Cuts, tears and cautery on an Elastic body (springs and a volume term assembled from its cells).

Oracles, each independent of the stencil code that re-assembles the springs:

* two Elastic blocks built separately (their own grids and cells): a plane between two node layers
  leaves the two sides of the cut body exactly as those blocks, in forces, energies, Gershgorin
  row sums and the time-step bound (a cell straddling the cut no longer ties the sides);
* a loop over cells (:func:`_cell_energy`): the energy as a sum over the live cells of each cell's
  28 corner pairs (its share of every spring) and its volume term, the live cells found from the
  geometry (the cells an oblique plane passes through, those with a burnt corner, those around a
  torn spring); forces are its autograd gradient;
* an Elastic body built on a node mask without the burnt nodes (cautery);
* energy linear in E at fixed nu (``dW/dE = W / E``) for the gradient kept through a cut.
"""

from __future__ import annotations

import itertools

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact import Sphere, Tool
from torchdeform.sim.material import CELL_SHARE, CLASS_WEIGHTS
from torchdeform.topology import Blade, cauterize, components, cut, tear
from torchdeform.topology.masks import editable

H = 0.01
E, NU = 5e3, 0.45


def _elastic(shape, *, topology=26, origin=(0.0, 0.0, 0.0), device=None, E=E, **kw):
    grid = td.Grid(shape, spacing=H, topology=topology, origin=origin, **kw.pop("grid", {}))
    if "density" not in kw:
        kw.setdefault("mass", 1e-3)
    return td.Model(grid, td.Elastic(E, NU), dtype=F64, device=device, **kw)


def _jiggle(model, seed=0, scale=1e-3):
    g = torch.Generator().manual_seed(seed)
    x = model.X + scale * torch.randn(model.X.shape, generator=g, dtype=F64).to(model.X.device)
    v = torch.randn(model.X.shape, generator=g, dtype=F64).to(model.X.device)
    return x, v


def _cell_energy(x, alive, topology):
    """Energy (J) of the live cells ``alive`` (bool ``(D-1, H-1, W-1)``) at positions ``x`` ``(1, 3, D, H, W)``.

    Per cell: each pair of its corners at grid distance 1, sqrt 2 or sqrt 3 is a spring of the
    cell's share ``w mu_s h / 4``, ``w mu_s h / 2``, ``w mu_s h`` (axis, face, body; ``mu_s`` the
    springs' share of ``mu``), Hooke's energy; plus ``h^3 (kappa (J - 1)^2 / 2 + mu' |E|^2)`` with
    ``F = sum_a x_a (x) s_a / (4 h)`` over the 8 corners and ``E = (F^T F - I) / 2``.
    """
    mu_total = E / (2 * (1 + NU))
    mu, mu_cell = (1 - CELL_SHARE) * mu_total, CELL_SHARE * mu_total
    kappa = E * NU / ((1 + NU) * (1 - 2 * NU)) - mu
    w = dict(zip((1, 2, 3), CLASS_WEIGHTS[topology]))
    share = {1: w[1] * mu * H / 4, 2: w[2] * mu * H / 2, 3: w[3] * mu * H}
    D, Hh, W = (n - 1 for n in x.shape[-3:])
    corners = list(itertools.product((0, 1), repeat=3))
    pos = {c: x[0, :, c[0] : c[0] + D, c[1] : c[1] + Hh, c[2] : c[2] + W] for c in corners}  # (3, cells)
    live = alive.to(x.dtype)
    total = x.new_zeros(())
    for a, b in itertools.combinations(corners, 2):
        n = sum(abs(p - q) for p, q in zip(a, b))
        if share[n] == 0:
            continue
        length = (pos[b] - pos[a]).norm(dim=0)
        total = total + (live * 0.5 * share[n] * (length - H * n**0.5) ** 2).sum()
    Fm = sum(
        pos[c].unsqueeze(1) * torch.tensor([2 * s - 1 for s in c], dtype=x.dtype).view(1, 3, 1, 1, 1) for c in corners
    ) / (4 * H)
    Fc = Fm.permute(2, 3, 4, 0, 1)  # (cells, 3, 3)
    J = torch.linalg.det(Fc)
    green = 0.5 * (Fc.transpose(-1, -2) @ Fc - torch.eye(3, dtype=x.dtype))
    return total + (live * H**3 * (0.5 * kappa * (J - 1) ** 2 + mu_cell * (green**2).sum((-1, -2)))).sum()


def _check_against_cells(model, alive, x):
    """The model's elastic energy and spring plus volume forces at ``x`` are those of the live cells (on the CPU)."""
    xg = x.detach().cpu().clone().requires_grad_()
    ref = _cell_energy(xg, alive.cpu(), model.grid.topology)
    (grad,) = torch.autograd.grad(ref, xg)
    got = model.energy(td.State(x, torch.zeros_like(x)))["elastic"]
    assert float(got) == pytest.approx(float(ref.detach()), rel=1e-11)
    f = model.forces(x, torch.zeros_like(x)).cpu()
    assert torch.allclose(f, -grad, rtol=1e-9, atol=1e-12 * float(grad.abs().max()))


@pytest.mark.parametrize(("topology", "axis"), [(26, 0), (18, 0), (14, 0), (26, 2)])
def test_a_plane_cut_leaves_the_two_blocks_built_alone(topology, axis):
    """Cut between layers 2 and 3: each side's forces, energy and row sums are the standalone block's."""
    shape = [6, 4, 5]
    shape[axis] = 6
    model = _elastic(tuple(shape), topology=topology, damping=0.05)
    o, u, v = [-0.01] * 3, [0.0] * 3, [0.0] * 3
    o[axis] = 0.025
    u[(axis + 1) % 3], v[(axis + 2) % 3] = 0.08, 0.08
    cut(model, model.X, Blade(o, u, v))
    lo_shape, origin = list(shape), [0.0] * 3
    lo_shape[axis], origin[axis] = 3, 0.03
    lo = _elastic(tuple(lo_shape), topology=topology, damping=0.05)
    hi = _elastic(tuple(lo_shape), topology=topology, damping=0.05, origin=tuple(origin))
    x, v = _jiggle(model)
    f = model.forces(x, v)
    rows = model.stiffness_row_sums()
    halves = [(lo, slice(0, 3)), (hi, slice(3, 6))]
    energy = 0.0
    for block, part in halves:
        idx = (slice(None), slice(None)) + tuple(part if a == axis else slice(None) for a in range(3))
        xb, vb = x[idx].clone(), v[idx].clone()
        assert torch.allclose(f[idx], block.forces(xb, vb), rtol=1e-13, atol=1e-16)
        assert torch.allclose(rows[idx], block.stiffness_row_sums(), rtol=1e-13, atol=0)
        energy += float(block.energy(td.State(xb, vb))["elastic"])
    assert float(model.energy(td.State(x, v))["elastic"]) == pytest.approx(energy, rel=1e-12)
    assert components(model)[1] == 2
    bound = td.time_step_bound(model, method="gershgorin")
    assert bound == pytest.approx(min(td.time_step_bound(b, method="gershgorin") for b, _ in halves), rel=1e-12)


def test_an_oblique_cut_kills_the_cells_it_passes_through(device):
    """Live cells: all 8 corners on one side of the plane; the rest of the body is untouched to the bit."""
    model = _elastic((6, 5, 5), device=device)
    x, _ = _jiggle(model, seed=3)
    before = model.forces(x, torch.zeros_like(x))
    blade = Blade((0.0237, -0.1, -0.1), (0.02, 0.3, 0.0), (-0.03, 0.0, 0.3))  # through no node
    cut(model, model.X, blade)
    side = blade.height(model.X)[0, 0] > 0  # (D, H, W)
    D, Hh, W = (n - 1 for n in side.shape)
    views = [side[a : a + D, b : b + Hh, c : c + W] for a, b, c in itertools.product((0, 1), repeat=3)]
    alive = torch.stack(views).all(0) | ~torch.stack(views).any(0)
    assert 0 < int((~alive).sum()) < alive.numel()
    kappa, mu = td.Elastic(E, NU).volume_modulus(), td.Elastic(E, NU).lame()[0]
    assert torch.equal(model.volume[0], kappa * alive.to(F64))
    assert torch.allclose(model.mu_cells, mu * alive.to(F64), rtol=1e-15, atol=0)
    _check_against_cells(model, alive, x)
    # nodes whose cells all live feel exactly the forces they felt before the cut
    pad = torch.nn.functional.pad((~alive).to(torch.uint8), (1, 1, 1, 1, 1, 1)).bool()
    near = torch.zeros_like(side)
    for a, b, c in itertools.product((0, 1), repeat=3):
        near |= pad[a : a + D + 1, b : b + Hh + 1, c : c + W + 1]
    after = model.forces(x, torch.zeros_like(x))
    assert bool((~near).any()) and torch.equal(after[0][:, ~near], before[0][:, ~near])


def test_a_burnt_region_stops_contributing(device):
    """The burnt body is the Elastic body built on a node mask without those nodes, and the live-cell sum."""
    model = _elastic((6, 5, 5), device=device, density=1000.0)
    out = cauterize(model, model.rest_state(), Tool(Sphere(0.012), position=(0.05, 0.02, 0.02)))
    assert out["nodes"] > 0
    burnt = model.removed
    reference = _elastic((6, 5, 5), device=device, density=1000.0, grid={"node_mask": ~burnt.cpu()})
    x, v = _jiggle(model, seed=1)
    x = torch.where(burnt, model.X, x)  # burnt nodes stay where they were
    assert torch.equal(model.forces(x, v), reference.forces(x, v))
    assert torch.equal(model.volume[0], reference.volume[0]) and torch.equal(model.stiffness, reference.stiffness)
    assert torch.equal(model.stiffness_row_sums(), reference.stiffness_row_sums())
    from torchdeform.sim.material import corner_cells

    alive = ~corner_cells(burnt)
    _check_against_cells(model, alive, x)


def test_a_torn_spring_takes_its_four_cells_with_it():
    """One node pulled along D: the axis spring below it tears; the 4 cells around that spring die."""
    model = _elastic((5, 5, 5))
    x = model.X.clone()
    x[0, 0, 2, 2, 2] += 0.004  # the spring (1, 2, 2) -> (2, 2, 2) stretched 40 %
    assert tear(model, x, 0.3, one_per_step=True) == 1
    alive = torch.ones((4, 4, 4), dtype=torch.bool)
    alive[1, 1:3, 1:3] = False
    assert torch.equal(model.volume[0] == 0, ~alive)
    xr, _ = _jiggle(model, seed=2)
    _check_against_cells(model, alive, xr)


def test_a_spring_left_without_cells_goes_but_the_body_keeps_its_mass():
    """Two cuts one layer apart: layer 2's in-plane springs lose both cells, so nothing ties its nodes."""
    model = _elastic((6, 4, 4), density=1000.0)
    mass = model.mass.clone()
    for at in (0.015, 0.025):
        cut(model, model.X, Blade((at, -0.01, -0.01), (0, 0.08, 0), (0, 0, 0.08)))
    alive = torch.ones((5, 3, 3), dtype=torch.bool)
    alive[1:3] = False
    assert torch.equal(model.volume[0] == 0, ~alive)
    _check_against_cells(model, alive, _jiggle(model, seed=4)[0])
    assert bool((model.spring_sums(model.stiffness)[0, 0, 2] == 0).all())  # layer 2: loose nodes
    assert torch.equal(model.mass, mass) and components(model)[1] == 2 + 16


def test_a_batch_of_cuts_gives_cells_per_batch_entry():
    """Two positions, the plane between different layers: each batch entry is its own single cut."""
    model = _elastic((6, 4, 4))
    x = model.X.expand(2, -1, -1, -1, -1).clone()
    x[1, 0] += 0.01  # the body moved up one layer: the same plane cuts one layer lower
    blade = Blade((0.035, -0.01, -0.01), (0, 0.08, 0), (0, 0, 0.08))
    cut(model, x, blade)
    assert model.volume[0].shape == (2, 5, 3, 3) and model.mu_cells.shape == (2, 5, 3, 3)
    xr, vr = _jiggle(model, seed=5)
    f = model.forces(x + (xr - model.X), vr)
    rows = model.stiffness_row_sums()
    assert rows.shape == (2, 1, 6, 4, 4)
    for b in range(2):
        one = _elastic((6, 4, 4))
        cut(one, x[b : b + 1], blade)
        assert torch.equal(f[b : b + 1], one.forces(x[b : b + 1] + (xr - model.X), vr))
        assert torch.equal(rows[b : b + 1], one.stiffness_row_sums())


def test_an_editable_body_is_cut_in_place_and_a_cut_keeps_the_graph_to_E():
    model = editable(_elastic((5, 4, 4)))
    kappa, k = model.volume[0], model.stiffness
    cut(model, model.X, Blade((0.015, -0.01, -0.01), (0, 0.08, 0), (0, 0, 0.08)))
    assert model.volume[0] is kappa and model.stiffness is k and bool((kappa == 0).any())
    # mu and kappa are proportional to E at a fixed nu: the energy of any x is W(E) = E w, dW/dE = W / E
    Et = torch.tensor(E, dtype=F64, requires_grad=True)
    model = _elastic((5, 4, 4), E=Et)
    cut(model, model.X, Blade((0.015, -0.01, -0.01), (0, 0.08, 0), (0, 0, 0.08)))
    assert model.stiffness.requires_grad and model.volume[0].requires_grad
    x, _ = _jiggle(model, seed=6)
    W = model.energy(td.State(x, torch.zeros_like(x)))["elastic"].sum()
    (g,) = torch.autograd.grad(W, Et)
    assert float(g) == pytest.approx(float(W.detach()) / E, rel=1e-12)
