"""Strain-stiffening spring laws (torchdeform.sim.laws) against an edge list, finite differences and scipy.

Oracles: :class:`tests.oracles.edge_list.EdgeList` loops over every spring with the law written out
here in numpy (not the library's formulas); central finite differences of the forces; the static
equilibrium of a stretched bar found by scipy's trust-region Newton minimiser on that oracle energy.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.oracles.edge_list import EdgeList
from torchdeform.errors import ConfigError
from torchdeform.sim.model import State
from torchdeform.sim.packed import PackedLinearisation, PackedModel

SHAPE, SPACING = (3, 4, 3), (0.010, 0.012, 0.009)


# ------------------------------------------------------------------ numpy laws (independent)
def np_law(name, params):
    """(tension, slope, energy) of law ``name`` in numpy; ``params[s]`` are spring ``s``'s parameters."""

    def strain(l, l0):
        return l / l0 - 1.0

    if name == "exponential":

        def tension(l, l0, s, k):
            b = params[s][0]
            return k[s] * l0 * (np.exp(b * strain(l, l0)) - 1.0) / b

        def slope(l, l0, s, k):
            return k[s] * np.exp(params[s][0] * strain(l, l0))

        def energy(l, l0, s, k):
            b, e = params[s][0], strain(l, l0)
            return k[s] * l0 * l0 * (np.exp(b * e) - 1.0 - b * e) / b**2
    else:

        def tension(l, l0, s, k):
            c2, c3 = params[s]
            e = strain(l, l0)
            return k[s] * l0 * (e + c2 * e * abs(e) + c3 * e**3)

        def slope(l, l0, s, k):
            c2, c3 = params[s]
            e = strain(l, l0)
            return k[s] * (1.0 + 2.0 * c2 * abs(e) + 3.0 * c3 * e * e)

        def energy(l, l0, s, k):
            c2, c3 = params[s]
            e = strain(l, l0)
            return k[s] * l0 * l0 * (e * e / 2.0 + c2 * abs(e) ** 3 / 3.0 + c3 * e**4 / 4.0)

    return tension, slope, energy


def setup(name, seed=0, topology=26):
    """A model with per-spring stiffness and law parameters, a displaced state and the oracle."""
    rng = np.random.default_rng(seed)
    grid = td.Grid(SHAPE, spacing=SPACING, topology=topology)
    el = EdgeList(SHAPE, SPACING, topology)
    n = len(el.springs)
    k = rng.uniform(50.0, 150.0, n)
    params = rng.uniform(2.0, 20.0, (n, 1)) if name == "exponential" else rng.uniform(0.0, 30.0, (n, 2))
    field = lambda vals: torch.tensor(el.per_spring_tensor(vals, grid.directions))
    law = (
        td.Exponential(stiffening=field(params[:, 0]))
        if name == "exponential"
        else td.Polynomial(quadratic=field(params[:, 0]), cubic=field(params[:, 1]))
    )
    model = td.Model(grid, stiffness=field(k), mass=1e-3, law=law, dtype=torch.float64)
    x = model.X + torch.tensor(rng.normal(0, 0.15, (1, 3) + SHAPE)) * torch.tensor(SPACING).view(1, 3, 1, 1, 1)
    tension, slope, energy = np_law(name, params)
    return (
        model,
        x,
        el,
        (
            lambda l, l0, s: tension(l, l0, s, k),
            lambda l, l0, s: slope(l, l0, s, k),
            lambda l, l0, s: energy(l, l0, s, k),
        ),
    )


def packed_forces(model, x, form):
    pm = PackedModel(model)
    pm.force_form = form
    return pm.unpack(pm.spring_forces(pm.pack(x), None))


@pytest.mark.parametrize("name", ["exponential", "polynomial"])
def test_forces_equal_the_edge_list(name):
    """Strains up to about +-50 %, per-spring stiffness and parameters: the slice path, the conv3d
    reference and both packed sums equal the explicit loop over springs (float64, 1e-10)."""
    model, x, el, (tension, _, _) = setup(name)
    ref = el.law_forces(el.from_field(x[0]), tension)
    scale = np.abs(ref).max()
    for label, F in (
        ("slices", model.spring_forces(x, None)),
        ("conv", model.spring_forces(x, None, impl="conv")),
        ("gather", packed_forces(model, x, "gather")),
        ("reduction", packed_forces(model, x, "reduction")),
    ):
        err = np.abs(el.from_field(F[0]) - ref).max() / scale
        assert err < 1e-10, (label, err)


@pytest.mark.parametrize("name", ["exponential", "polynomial"])
def test_jacobian_equals_the_oracle_hessian_and_finite_differences(name):
    """K u of the linearisation (grid and packed layouts) equals the oracle Hessian times u, and
    -(F(x + eps u) - F(x - eps u)) / (2 eps); clamped, it equals the oracle's clamped Hessian."""
    model, x, el, (tension, slope, _) = setup(name, seed=1)
    u = torch.randn(x.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 0.01
    H = el.law_hessian(el.from_field(x[0]), tension, slope)
    ref = (H @ el.from_field(u[0]).ravel()).reshape(-1, 3)
    scale = np.abs(ref).max()
    Ku = model.linearise(x, clamp=False).apply(u)
    assert np.abs(el.from_field(Ku[0]) - ref).max() / scale < 1e-10
    eps = 1e-6
    fd = -(model.spring_forces(x + eps * u, None) - model.spring_forces(x - eps * u, None)) / (2 * eps)
    assert np.abs(el.from_field(fd[0]) - ref).max() / scale < 1e-8
    pm = PackedModel(model)
    Ku_packed = pm.unpack(PackedLinearisation(pm, x=pm.pack(x), clamp=False).apply(pm.pack(u)))
    assert np.abs(el.from_field(Ku_packed[0]) - ref).max() / scale < 1e-10
    Hc = el.law_hessian(el.from_field(x[0]), tension, slope, clamp=True)
    ref_c = (Hc @ el.from_field(u[0]).ravel()).reshape(-1, 3)
    for Kc in (model.linearise(x).apply(u), pm.unpack(pm.linearise(pm.pack(x)).apply(pm.pack(u)))):
        assert np.abs(el.from_field(Kc[0]) - ref_c).max() / scale < 1e-10


@pytest.mark.parametrize("name", ["exponential", "polynomial"])
def test_energy_equals_the_oracle_and_its_gradient_is_minus_the_force(name):
    model, x, el, (_tension, _, energy) = setup(name, seed=3)
    xe = el.from_field(x[0])
    d = xe[el.a] - xe[el.b]
    ref = sum(energy(float(np.linalg.norm(d[s])), el.l0[s], s) for s in range(len(el.springs)))
    xg = x.clone().requires_grad_()
    E = model.energy(State(xg, torch.zeros_like(xg)))["elastic"].sum()
    assert float(E.detach()) == pytest.approx(ref, rel=1e-10)
    (grad,) = torch.autograd.grad(E, xg)
    F = model.spring_forces(x, None)
    assert float((grad + F).abs().max()) < 1e-10 * float(F.abs().max())


def test_laws_reduce_to_hooke(make_model):
    """b -> 0 and c2 = c3 = 0 are Hooke's law."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=18)
    hooke = make_model(grid, stiffness=80.0, damping=0.05)
    gen = torch.Generator().manual_seed(0)
    x = hooke.X * (1 + 0.1 * torch.rand(hooke.X.shape, dtype=torch.float64, generator=gen).to(hooke.device))
    v = torch.randn_like(x)
    F = hooke.spring_forces(x, v)
    for law, tol in (
        (td.Exponential(stiffening=0.0), 1e-13),
        (td.Exponential(stiffening=1e-9), 1e-8),
        (td.Polynomial(), 1e-13),
    ):
        m = make_model(grid, stiffness=80.0, damping=0.05, law=law)
        assert float((m.spring_forces(x, v) - F).abs().max()) <= tol * float(F.abs().max()), law


def test_law_parameters_are_differentiable():
    """Gradients of forces w.r.t. the stiffness and the law parameters (per direction) pass
    torch.autograd.gradcheck (central differences, float64)."""
    grid = td.Grid((2, 3, 3), spacing=0.01, topology=26)
    x = grid.rest_positions(dtype=torch.float64) * 1.1
    x[0, 0, 1] += 0.002

    def forces(k, b, c3):
        m = td.Model(grid, stiffness=k, mass=1e-3, law=td.Exponential(stiffening=b), dtype=torch.float64)
        p = td.Model(grid, stiffness=k, mass=1e-3, law=td.Polynomial(quadratic=0.5, cubic=c3), dtype=torch.float64)
        return m.spring_forces(x, None) + p.spring_forces(x, None)

    S = grid.S
    args = (
        torch.full((S,), 100.0, dtype=torch.float64) + torch.arange(S),
        torch.linspace(1, 12, S, dtype=torch.float64),
        torch.linspace(1, 40, S, dtype=torch.float64),
    )
    assert torch.autograd.gradcheck(forces, tuple(a.requires_grad_() for a in args), eps=1e-6, atol=1e-7)


def bar_energy_oracle(el, tension_energy, fixed, load):
    """Energy, gradient, Hessian of a bar (oracle springs) with a point load, free nodes only."""
    tension, slope, energy = tension_energy
    free = np.flatnonzero(~fixed)

    def full(y):
        x = el.X.copy()
        x[free] = y.reshape(-1, 3)
        return x

    def f(y):
        x = full(y)
        d = x[el.a] - x[el.b]
        return sum(energy(float(np.linalg.norm(d[s])), el.l0[s], s) for s in range(len(el.springs))) - float(
            (load * x).sum()
        )

    def g(y):
        return -(el.law_forces(full(y), tension) + load)[free].ravel()

    def h(y):
        H = el.law_hessian(full(y), tension, slope)
        idx = (3 * free[:, None] + np.arange(3)).ravel()
        return H[np.ix_(idx, idx)]

    return f, g, h, free


@pytest.mark.parametrize("name", ["exponential", "polynomial"])
def test_implicit_euler_with_newton_reaches_the_static_solution_of_a_stretched_bar(name):
    """A 2 x 2 x 8 bar (26 neighbours) clamped at one end, its other end pulled to about 20 %
    strain. Implicit Euler at dt = 1000 s (10^6 x the explicit bound) with Newton iterations lands
    on the static equilibrium that scipy's trust-region Newton finds for the oracle energy; the
    Newton iterations converge (error falls by orders of magnitude), and Hooke's law gives a
    clearly different bar."""
    from scipy.optimize import minimize

    shape, h = (2, 2, 8), 0.01
    grid = td.Grid(shape, spacing=h, topology=26)
    el = EdgeList(shape, (h, h, h), 26)
    n = len(el.springs)
    params = np.full((n, 1), 8.0) if name == "exponential" else np.tile([2.0, 20.0], (n, 1))
    law = td.Exponential(stiffening=8.0) if name == "exponential" else td.Polynomial(quadratic=2.0, cubic=20.0)
    k = 100.0
    fixed_grid = grid.face("w-")
    pull = 2.5 if name == "exponential" else 2.0  # N on the far face, in total
    end = grid.face("w+")
    load = torch.zeros((1, 3) + shape, dtype=torch.float64)
    load[0, 2][end] = pull / int(end.sum())
    model = td.Model(grid, stiffness=k, mass=1e-4, law=law, fixed=fixed_grid, dtype=torch.float64)
    fixed = np.array([bool(fixed_grid[ijk]) for ijk in el.nodes])
    tension, slope, energy = np_law(name, params)
    kk = np.full(n, k)
    f, g, hess, free = bar_energy_oracle(
        el,
        (
            lambda l, l0, s: tension(l, l0, s, kk),
            lambda l, l0, s: slope(l, l0, s, kk),
            lambda l, l0, s: energy(l, l0, s, kk),
        ),
        fixed,
        el.from_field(load[0]),
    )
    res = minimize(f, el.X[free].ravel(), jac=g, hess=hess, method="trust-exact", options={"gtol": 1e-13})
    static = el.X.copy()
    static[free] = res.x.reshape(-1, 3)
    strain = (static[:, 2].max() - static[:, 2].min()) / (h * (shape[2] - 1)) - 1
    assert 0.1 < strain < 0.4, strain

    errors = []
    for newton in (0, 2, 5, 30):
        integ = td.ImplicitEuler(cg_iters=500, cg_tol=1e-13, newton_iters=newton)
        s = integ.step(model, model.rest_state(), dt=1000.0, loads=load)
        errors.append(np.abs(el.from_field(s.x[0]) - static).max() / (h * shape[2]))
    print(
        f"\n{name}: bar strain {strain:.3f}; error / bar length after 1, 3, 6, 31 Newton solves: "
        + ", ".join(f"{e:.1e}" for e in errors)
    )
    assert errors[-1] < 1e-8
    assert errors[0] > 1e3 * errors[-1] and errors[2] < errors[1] < errors[0]
    hooke = td.Model(grid, stiffness=k, mass=1e-4, fixed=fixed_grid, dtype=torch.float64)
    s = td.ImplicitEuler(cg_iters=500, cg_tol=1e-13, newton_iters=30).step(
        hooke, hooke.rest_state(), 1000.0, loads=load
    )
    assert np.abs(el.from_field(s.x[0]) - static).max() / (h * shape[2]) > 0.01  # the law matters


def test_scene_keys_make_the_law(tmp_path):
    from torchdeform.scene.run import load_scene

    base = """
[grid]
shape = [3, 3, 3]
spacing = 0.01
[material]
stiffness = 10.0
{law}
[mass]
density = 1000.0
[integrator]
dt = 1e-4
steps = 1
"""
    path = tmp_path / "s.toml"
    path.write_text(base.format(law='law = "exponential"\nstiffening = {axis = 4.0, face = 6.0, body = 8.0}'))
    model = load_scene(path).build()
    assert isinstance(model.law, td.Exponential)
    assert model.law_params[0].flatten().tolist() == [4.0] * 3 + [6.0] * 6 + [8.0] * 4
    path.write_text(base.format(law='law = "polynomial"\ncubic = 50.0'))
    m = load_scene(path).build()
    assert isinstance(m.law, td.Polynomial) and float(m.law_params[0].max()) == 0 and float(m.law_params[1].min()) == 50
    path.write_text(base.format(law='law = "exponential"\ncubic = 50.0'))
    with pytest.raises(ConfigError, match="cubic"):
        load_scene(path)
    path.write_text(base.format(law='law = "fung"'))
    with pytest.raises(ConfigError, match=r"s.toml:7: material.law"):
        load_scene(path)
    with pytest.raises(ConfigError, match=r"law\.stiffening"):
        td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=1.0, mass=1.0, law=td.Exponential(stiffening=-1.0))


@pytest.mark.slow
def test_compiled_step_runs_the_law():
    """The compiled fast path (packed layout, torch.compile) follows the law: 30 symplectic steps
    of a stretched, stiffening body agree with the eager grid-layout steps (float64)."""
    from torchdeform.sim.compiled import compiled_step

    grid = td.Grid((4, 4, 5), spacing=0.01, topology=26)
    model = td.Model(
        grid,
        stiffness=50.0,
        damping=0.02,
        mass=1e-3,
        law=td.Exponential(stiffening=12.0),
        fixed=grid.face("w-"),
        dtype=torch.float64,
    )
    s0 = model.rest_state()
    s0.x[0, 2] *= 1.25  # 25 % stretch along W
    dt = 0.5 * td.time_step_bound(model, integrator="symplectic", x=s0.x)  # the bound at the stretched state
    eager = s0
    for _ in range(30):
        eager = td.SymplecticEuler().step(model, eager, dt)
    step = compiled_step(td.SymplecticEuler(), model, dt, threads=1)
    fast = step.run(s0, 30)
    assert step.compiled
    assert float((fast.x - eager.x).abs().max()) < 1e-12
    assert float((eager.x - s0.x).abs().max()) > 1e-4  # it moved
