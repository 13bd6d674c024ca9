"""Elastic materials on the lattice (torchdeform.sim.material): springs from cells plus a volume term.

Oracles: the analytic solution of uniaxial stress (a uniform strain with ``eps = sigma / E`` along
the pull and ``-nu eps`` across it), autograd of the volume energy for its forces, forward-mode
differentiation of the forces for the stiffness product, and the dynamics themselves for the
time-step bound (bounded below it, growing above it).
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64, cg_solve
from torchdeform.errors import ConfigError
from torchdeform.sim.material import CELL_SHARE, CLASS_WEIGHTS, spring_stiffness, volume_energy, volume_forces


def _face_mean(u, channel, axis, end):
    idx = [slice(None)] * 3
    idx[axis] = end
    return float(u[(0, channel, *idx)].mean())


def uniaxial(n, nu, topology, *, E=5e3, axis=2, side=0.02, device=None):
    """Effective ``(E, nu)`` of a free ``n^3`` cube pulled by equal and opposite tractions on the
    faces normal to ``axis`` (consistent nodal forces), in the small-strain limit."""
    h = side / (n - 1)
    grid = td.Grid((n, n, n), spacing=h, topology=topology)
    model = td.Model(grid, td.Elastic(E, nu), mass=1.0, dtype=F64, device=device)
    lin = model.linearise(model.X)
    sigma = 50.0
    w = torch.ones(n, dtype=F64)
    w[0] = w[-1] = 0.5
    area = (w[:, None] * w[None, :]) * h * h
    f = torch.zeros((1, 3, n, n, n), dtype=F64)
    hi, lo = [slice(None)] * 3, [slice(None)] * 3
    hi[axis], lo[axis] = -1, 0
    f[(0, axis, *hi)] = sigma * area
    f[(0, axis, *lo)] = -sigma * area
    u = cg_solve(lin.apply, f.to(model.device)).cpu()
    axial = (_face_mean(u, axis, axis, -1) - _face_mean(u, axis, axis, 0)) / side
    lat = (axis + 1) % 3
    lateral = (_face_mean(u, lat, lat, -1) - _face_mean(u, lat, lat, 0)) / side
    return sigma / axial, -lateral / axial


@pytest.mark.parametrize("topology", [14, 18, 26])
@pytest.mark.parametrize("nu", [0.25, 0.3, 0.45, 0.49])
def test_uniaxial_stress_gives_the_asked_modulus_and_ratio(topology, nu, device):
    """A free cube pulled along W: E to 1e-6 and nu to 1e-6 at 5^3 and 9^3 nodes, on every topology."""
    for n in (5, 9):
        modulus, ratio = uniaxial(n, nu, topology, device=device)
        assert modulus == pytest.approx(5e3, rel=1e-6), (n, modulus)
        assert ratio == pytest.approx(nu, abs=1e-6), (n, ratio)


@pytest.mark.parametrize("axis", [0, 1])
def test_the_pull_along_every_axis_is_the_same(axis):
    modulus, ratio = uniaxial(6, 0.45, 26, axis=axis)
    assert modulus == pytest.approx(5e3, rel=1e-6) and ratio == pytest.approx(0.45, abs=1e-6)


def test_interior_springs_get_the_class_weights_and_surface_springs_their_cells_share():
    h, E, nu = 0.01, 6e3, 0.3
    grid = td.Grid((4, 4, 4), spacing=h, topology=26)
    model = td.Model(grid, td.Elastic(E, nu), mass=1.0, dtype=F64)
    mu = (1 - CELL_SHARE) * E / (2 * (1 + nu))  # the springs' share
    k = model.stiffness[0]
    wa, wf, wb = CLASS_WEIGHTS[26]
    dirs = list(grid.directions)
    axis_d, face_d, body_d = dirs.index((1, 0, 0)), dirs.index((1, 1, 0)), dirs.index((1, 1, 1))
    assert float(k[axis_d, 1, 1, 1]) == pytest.approx(wa * mu * h, rel=1e-12)  # 4 cells
    assert float(k[face_d, 1, 1, 1]) == pytest.approx(wf * mu * h, rel=1e-12)  # 2 cells
    assert float(k[body_d, 1, 1, 1]) == pytest.approx(wb * mu * h, rel=1e-12)  # 1 cell
    assert float(k[axis_d, 1, 0, 0]) == pytest.approx(wa * mu * h / 4, rel=1e-12)  # on an edge: 1 of 4 cells
    assert float(k[axis_d, 1, 0, 1]) == pytest.approx(wa * mu * h / 2, rel=1e-12)  # on a face: 2 of 4
    assert float(k[face_d, 1, 1, 0]) == pytest.approx(wf * mu * h / 2, rel=1e-12)  # on a face: 1 of 2
    assert float(k[axis_d, 3, 1, 1]) == 0.0  # leaves the grid


def test_a_node_mask_removes_the_cells_of_its_missing_nodes():
    """Removing one corner node takes its 8 cells (and their share of every spring) away."""
    mask = torch.ones(5, 5, 5, dtype=torch.bool)
    mask[2, 2, 2] = False
    grid = td.Grid((5, 5, 5), spacing=0.01, topology=18, node_mask=mask)
    mu_cells = torch.ones(4, 4, 4, dtype=F64)
    from torchdeform.sim.material import cell_mask

    cells = cell_mask(grid)
    assert int((~cells).sum()) == 8 and not bool(cells[1:3, 1:3, 1:3].any())
    k = spring_stiffness(grid, mu_cells * cells, 0.01)
    dirs = list(grid.directions)
    # the axis spring (1,2,1) -> (2,2,1) has cells (1, 1..2, 0..1): two of them are gone
    assert float(k[dirs.index((1, 0, 0)), 1, 2, 1]) == pytest.approx((1 - CELL_SHARE) * 0.5 * 1.0 * 0.01, rel=1e-12)


def test_volume_forces_are_minus_the_gradient_of_the_energy():
    gen = torch.Generator().manual_seed(3)
    X = td.Grid((3, 4, 5), spacing=0.01).rest_positions(dtype=F64)
    x = (X + 2e-3 * torch.randn(X.shape, generator=gen, dtype=F64)).requires_grad_()
    kappa = 1e4 * torch.rand((2, 3, 4), generator=gen, dtype=F64)
    shear = 2e3 * torch.rand((2, 3, 4), generator=gen, dtype=F64)
    for mu in (None, shear):
        (g,) = torch.autograd.grad(volume_energy(x, kappa, 0.01, mu).sum(), x)
        f = volume_forces(x, kappa, 0.01, mu)
        assert torch.allclose(f, -g, rtol=1e-12, atol=1e-12 * float(g.abs().max()))


def test_the_stiffness_product_is_the_jacobian_at_rest_and_semi_definite_away_from_it():
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    model = td.Model(grid, td.Elastic(5e3, 0.49), mass=1.0, dtype=F64)
    gen = torch.Generator().manual_seed(1)
    u = torch.randn(model.X.shape, generator=gen, dtype=F64)
    _, jvp = torch.func.jvp(lambda y: model.forces(y, torch.zeros_like(y)), (model.X,), (u,))
    Ku = model.linearise(model.X).apply(u)
    assert torch.allclose(Ku, -jvp, rtol=1e-10, atol=1e-10 * float(jvp.abs().max()))
    x = model.X + 2e-3 * torch.randn(model.X.shape, generator=gen, dtype=F64)
    lin = model.linearise(x)
    for _ in range(5):
        w = torch.randn(model.X.shape, generator=gen, dtype=F64)
        assert float((w * lin.apply(w)).sum()) >= 0.0


def test_explicit_steps_stay_bounded_just_below_the_reported_bound_and_grow_just_above():
    """nu = 0.49 makes the body stiff in volume: the bound must include the volume term."""
    grid = td.Grid((5, 4, 4), spacing=0.005, topology=26)
    model = td.Model(grid, td.Elastic(5e3, 0.49), density=1000.0, fixed=grid.face("bottom"), dtype=F64)
    bound = td.time_step_bound(model, integrator="symplectic")
    gen = torch.Generator().manual_seed(0)
    x0 = model.X + 1e-6 * torch.randn(model.X.shape, generator=gen, dtype=F64) * model.free
    for factor, grows in ((0.97, False), (1.03, True)):
        s = td.State(x0, torch.zeros_like(x0))
        for _ in range(1000):
            s = td.SymplecticEuler().step(model, s, factor * bound)
        amp = float((s.x - model.X).abs().max())
        assert (not amp < 1e-3) if grows else amp < 1e-5, (factor, amp)


def test_implicit_euler_converges_far_beyond_the_explicit_bound():
    grid = td.Grid((5, 4, 4), spacing=0.005, topology=26)
    model = td.Model(
        grid,
        td.Elastic(5e3, 0.49),
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
    )
    dt = 50 * td.time_step_bound(model, integrator="symplectic")
    integ = td.ImplicitEuler(cg_iters=200, cg_tol=1e-10)
    s = model.rest_state()
    for _ in range(40):
        s = integ.step(model, s, dt)
    assert integ.last_cg[1] <= 1e-10
    assert bool(torch.isfinite(s.x).all()) and float(s.x[0, 0, -1].mean() - model.X[0, 0, -1].mean()) < 0


def test_the_lowest_ratio_needs_no_volume_modulus_and_springs_given_as_stiffness_have_no_cell_term():
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    kappa, _, shear = td.Model(grid, td.Elastic(5e3, 1 / 6), mass=1.0, dtype=F64).volume
    mu = 5e3 / (2 * (1 + 1 / 6))
    assert float(kappa.abs().max()) < 1e-9 * mu and float(shear.min()) == pytest.approx(CELL_SHARE * mu, rel=1e-12)
    assert td.Model(grid, stiffness=50.0, mass=1.0).volume is None


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"youngs_modulus": 5e3, "poisson_ratio": 0.5}, "material.poisson_ratio"),
        ({"youngs_modulus": 5e3, "poisson_ratio": 0.16}, "material.poisson_ratio"),
        ({"youngs_modulus": 0.0, "poisson_ratio": 0.3}, "material.youngs_modulus"),
        ({"youngs_modulus": float("nan"), "poisson_ratio": 0.3}, "material.youngs_modulus"),
        ({"youngs_modulus": "soft", "poisson_ratio": 0.3}, "material.youngs_modulus"),
        ({"youngs_modulus": 5e3, "poisson_ratio": True}, "material.poisson_ratio"),
    ],
)
def test_bad_materials_name_their_key(kwargs, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        td.Elastic(**kwargs)


def test_grids_the_material_cannot_describe_are_refused():
    with pytest.raises(ConfigError, match="14, 18 or 26"):
        td.Model(td.Grid((3, 3, 3), spacing=0.01, topology=6), td.Elastic(5e3, 0.3), mass=1.0)
    with pytest.raises(ConfigError, match="cubic cells"):
        td.Model(td.Grid((3, 3, 3), spacing=(0.01, 0.01, 0.02)), td.Elastic(5e3, 0.3), mass=1.0)
    with pytest.raises(ConfigError, match="normalize"):
        td.Model(td.Grid((3, 3, 3), spacing=0.01), td.Elastic(5e3, 0.3), normalize=True, mass=1.0)


def test_projective_dynamics_refuses_the_volume_term():
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    model = td.Model(grid, td.Elastic(5e3, 0.45), density=1000.0, fixed=grid.face("bottom"), dtype=F64)
    with pytest.raises(ConfigError, match="integrator"):
        td.ProjectiveDynamics().step(model, model.rest_state(), 1e-3)


def _voigt_stiffness(model, eps=1e-6):
    """The body's small-strain stiffness ``C`` (6 x 6 Voigt, Pa) from the energies of affine strains.

    For an Elastic body every cell carries its share exactly, so the energy of ``x = (I + e) X``
    is ``V e:C:e / 2`` with ``V`` the volume of the cells (here all of the box).
    """
    V = float(torch.tensor([(n - 1) * s for n, s in zip(model.grid.shape, model.grid.spacing)]).prod())
    pairs = [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]

    def energy(gamma):
        e = torch.zeros(3, 3, dtype=F64)
        for (i, j), g in zip(pairs, gamma):
            if i == j:
                e[i, i] += g
            else:
                e[i, j] += g / 2
                e[j, i] += g / 2
        x = model.X + torch.einsum("ij,bjdhw->bidhw", e, model.X)
        return float(model.energy(td.State(x, torch.zeros_like(x)))["elastic"][0]) / V

    unit = torch.eye(6, dtype=F64) * eps
    diag = [2 * energy(unit[i]) / eps**2 for i in range(6)]
    C = torch.zeros(6, 6, dtype=F64)
    for i in range(6):
        for j in range(6):
            C[i, j] = diag[i] if i == j else energy(unit[i] + unit[j]) / eps**2 - (diag[i] + diag[j]) / 2
    return C


def _modulus_along(C, n):
    n = torch.tensor(n, dtype=F64)
    n = n / n.norm()
    s = torch.stack([n[0] ** 2, n[1] ** 2, n[2] ** 2, n[1] * n[2], n[0] * n[2], n[0] * n[1]])
    return float(1 / (s @ torch.linalg.solve(C, s)))


@pytest.mark.parametrize("topology", [14, 18, 26])
def test_youngs_modulus_is_the_same_along_axes_face_and_body_diagonals(topology):
    """Isotropy. Springs alone (26 equal springs, ``C11 = 13 k / 3 h``, ``C12 = C44 = 7 k / 3 h``)
    are 1.63x as stiff along a face diagonal and 2.06x along a body diagonal as along an axis."""
    model = td.Model(td.Grid((3, 3, 3), spacing=0.01, topology=topology), td.Elastic(5e3, 0.45), mass=1.0, dtype=F64)
    C = _voigt_stiffness(model)
    axis, face, body = (_modulus_along(C, n) for n in ((1, 0, 0), (1, 1, 0), (1, 1, 1)))
    assert axis == pytest.approx(5e3, rel=1e-4)
    assert face == pytest.approx(axis, rel=1e-4) and body == pytest.approx(axis, rel=1e-4)


def test_gradients_with_respect_to_youngs_modulus_and_poisson_ratio():
    """gradcheck (central differences) of three explicit steps and the energy with respect to E and nu."""
    grid = td.Grid((3, 3, 4), spacing=0.01, topology=26)
    gen = torch.Generator().manual_seed(5)
    X = grid.rest_positions(dtype=F64)
    x0 = X + 1e-3 * torch.randn(X.shape, generator=gen, dtype=F64)

    def rollout(E, nu):
        model = td.Model(grid, td.Elastic(E, nu), density=1000.0, fixed=grid.face("bottom"), dtype=F64)
        s = td.State(x0, torch.zeros_like(x0))
        for _ in range(3):
            s = td.SymplecticEuler().step(model, s, 1e-4)
        return s.x, model.energy(s)["elastic"]

    E = torch.tensor(5e3, dtype=F64, requires_grad=True)
    nu = torch.tensor(0.45, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda e, n: rollout(e * 1e3, n), (E / 1e3, nu), eps=1e-6, atol=1e-8, rtol=1e-5)
