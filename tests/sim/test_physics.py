"""Physics of the mass-spring core against independent oracles (float64).

Oracles used here (none of them produced by torchdeform):

* analytic normal modes of a 1-D chain, and the exact discrete frequency of symplectic Euler;
* a dense Newton solve (numpy/scipy) of the edge-list energy for static equilibria, and the
  dense linear solve ``K u = f`` of the assembled stiffness for small loads;
* exact invariants (linear and angular momentum of central pair forces);
* a DOP853 ``scipy.integrate.solve_ivp`` reference of the edge-list equations of motion at
  tolerance 1e-13 for convergence orders;
* dense generalised eigenvalues of ``(K, M)`` for the stability bound;
* Knoche's Cg shader transcribed literally (loop over nodes) and REFERENCE.md section 1.3;
* finite differences (``torch.autograd.gradcheck``) for gradients.

The edge-list helpers live in ``tests/oracles/edge_list.py``.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.linalg as sla
import torch
from scipy.integrate import solve_ivp

import torchdeform as td
from tests.helpers import F64
from tests.oracles.edge_list import EdgeList


def _field_mask(edges, mask):
    """Bool ``(N,)`` over the edge list's nodes from a ``(D, H, W)`` mask."""
    mask = mask.numpy() if torch.is_tensor(mask) else np.asarray(mask)
    return np.array([bool(mask[ijk]) for ijk in edges.nodes])


def _node_values(edges, field):
    """``(N,)`` over the edge list's nodes from a ``(1, 1, D|1, H|1, W|1)`` model tensor."""
    f = field.detach().expand(1, 1, *edges.shape)[0, 0].numpy()
    return np.array([f[ijk] for ijk in edges.nodes])


# ====================================================================== 1-D chain
def _chain(n_free, k, m, spacing, both_ends=True):
    grid = td.Grid((n_free + (2 if both_ends else 1), 1, 1), spacing=spacing, topology=6)
    fixed = torch.zeros(grid.shape, dtype=torch.bool)
    fixed[0] = True
    if both_ends:
        fixed[-1] = True
    return td.Model(grid, stiffness=k, mass=m, fixed=fixed, dtype=F64)


def _period_from_zero_crossings(t, q):
    idx = np.nonzero(np.sign(q[:-1]) != np.sign(q[1:]))[0]
    tc = t[idx] - q[idx] * (t[idx + 1] - t[idx]) / (q[idx + 1] - q[idx])
    assert len(tc) >= 4
    return 2 * np.mean(np.diff(tc))


@pytest.mark.parametrize("mode", [1, 2, 5])
def test_chain_oscillation_frequency_rk4(mode):
    """A fixed-fixed chain of N masses started in mode n oscillates at
    omega_n = 2 sqrt(k/m) sin(n pi / (2 (N + 1))); measured from zero crossings of the modal
    coordinate in an RK4 run (dt = T/100, 3 periods) and the mode stays pure."""
    N, k, m, h = 8, 3.0, 0.5, 0.1
    model = _chain(N, k, m, h)
    omega = 2 * math.sqrt(k / m) * math.sin(mode * math.pi / (2 * (N + 1)))
    period = 2 * math.pi / omega
    dt = period / 100
    j = torch.arange(N + 2, dtype=F64)
    shape = torch.sin(mode * math.pi * j / (N + 1))
    state = model.rest_state()
    state.x[0, 0, :, 0, 0] += 1e-6 * h * shape
    ts, qs, purity = [], [], 0.0
    integ = td.RK4()
    for _ in range(300):
        u = (state.x - model.X)[0, 0, :, 0, 0]
        q = float(u @ shape / (shape @ shape))
        ts.append(state.t)
        qs.append(q)
        purity = max(purity, float((u - q * shape).abs().max()) / (1e-6 * h))
        state = integ.step(model, state, dt)
    measured = 2 * math.pi / _period_from_zero_crossings(np.array(ts), np.array(qs))
    assert abs(measured / omega - 1) < 1e-5
    assert purity < 1e-6
    # no lateral motion
    assert float((state.x - model.X)[0, 1:].abs().max()) == 0.0


def test_chain_symplectic_euler_discrete_frequency():
    """Symplectic Euler on the (exactly linear) longitudinal chain rotates each mode with the
    discrete frequency 2/dt arcsin(omega dt / 2)."""
    N, k, m, h, mode = 6, 2.0, 0.3, 0.05, 2
    model = _chain(N, k, m, h)
    omega = 2 * math.sqrt(k / m) * math.sin(mode * math.pi / (2 * (N + 1)))
    dt = 0.6 / omega
    discrete = 2 / dt * math.asin(omega * dt / 2)
    j = torch.arange(N + 2, dtype=F64)
    shape = torch.sin(mode * math.pi * j / (N + 1))
    state = model.rest_state()
    state.x[0, 0, :, 0, 0] += 1e-6 * h * shape
    ts, qs = [], []
    for _ in range(200):
        ts.append(state.t)
        qs.append(float((state.x - model.X)[0, 0, :, 0, 0] @ shape))
        state = td.SymplecticEuler().step(model, state, dt)
    # the modal coordinate obeys q_{n+1} + q_{n-1} = (2 - omega^2 dt^2) q_n exactly: fit omega
    q = np.array(qs)
    lhs, rhs = q[2:] + q[:-2], q[1:-1]
    w2 = (2 - (lhs @ rhs) / (rhs @ rhs)) / dt**2
    assert abs(math.sqrt(w2) / omega - 1) < 1e-9
    measured = 2 * math.pi / _period_from_zero_crossings(np.array(ts), q)
    assert abs(measured / discrete - 1) < 5e-3  # zero-crossing interpolation at ~10 steps/period


@pytest.mark.parametrize("both_ends", [True, False])
def test_chain_linearised_spectrum(both_ends):
    """Eigenvalues of M^-1 K from ``Model.linearise`` (longitudinal channel, free nodes) equal
    the analytic chain spectrum: fixed-fixed 4k/m sin^2(n pi / (2(N+1))), fixed-free
    4k/m sin^2((2n-1) pi / (2(2N+1)))."""
    N, k, m = 7, 5.0, 0.2
    model = _chain(N, k, m, 0.02, both_ends)
    lin = model.linearise(model.X)
    free = (~model.constrained).flatten().nonzero().flatten().tolist()
    K = np.zeros((len(free), len(free)))
    for col, node in enumerate(free):
        u = torch.zeros_like(model.X)
        u[0, 0].view(-1)[node] = 1.0
        K[:, col] = lin.apply(u)[0, 0].flatten()[free].numpy()
    lam = np.sort(np.linalg.eigvalsh(K / m))
    n = np.arange(1, N + 1)
    if both_ends:
        ref = 4 * k / m * np.sin(n * np.pi / (2 * (N + 1))) ** 2
    else:
        ref = 4 * k / m * np.sin((2 * n - 1) * np.pi / (2 * (2 * N + 1))) ** 2
    np.testing.assert_allclose(lam, np.sort(ref), rtol=1e-12)
    # and the stability bound of the chain is 2 / omega_max (tight within 1e-6)
    bound = td.time_step_bound(model, integrator="symplectic")
    assert abs(bound / (2 / math.sqrt(ref.max())) - 1) < 1e-6


# ============================================================== static equilibria
def _static_problem():
    """A 4x3x3 body (axis 0 up), 26 neighbours, bottom fixed, gravity and a point load."""
    shape, spacing = (4, 3, 3), (0.01, 0.012, 0.011)
    grid = td.Grid(shape, spacing=spacing, topology=26)
    k = {"axis": 50.0, "face": 35.0, "body": 20.0}
    return grid, k


def _static_model(grid, k, load_scale):
    return td.Model(
        grid,
        stiffness=k,
        density=1000.0,
        gravity=(-9.81 * load_scale, 0.0, 0.0),
        fixed=grid.face("bottom"),
        dtype=F64,
        loads=[td.PointForce((3, 1, 1), (0.0, 0.02 * load_scale, -0.01 * load_scale))],
    )


def _edge_static(grid, k, model, load_scale):
    """Edge list, per-spring stiffness, free flags and external forces of the static problem."""
    edges = EdgeList(grid.shape, grid.spacing, grid.topology)
    cls = {1: "axis", 2: "face", 3: "body"}
    ke = np.array([k[cls[sum(map(abs, off))]] for _, _, off in edges.springs])
    mass = _node_values(edges, model.mass)
    free = ~_field_mask(edges, grid.face("bottom"))
    fext = mass[:, None] * np.array([-9.81 * load_scale, 0.0, 0.0])
    fext[edges.index[(3, 1, 1)]] += np.array([0.0, 0.02, -0.01]) * load_scale
    return edges, ke, free, fext


def _torchdeform_equilibrium(model, steps=60, dt=1e3):
    """Implicit Euler with a very large step is a (quasi-)Newton iteration on F(x) = 0; velocities
    are reset between steps. Stops when the largest free-node force is below 1e-15 N."""
    integ = td.ImplicitEuler(cg_iters=2000, cg_tol=1e-14)
    state = model.rest_state()
    for _ in range(steps):
        state = integ.step(model, state, dt)
        state = td.State(state.x, torch.zeros_like(state.v), t=state.t)
        if float((model.forces(state.x, state.v) * model.free).abs().max()) < 1e-15:
            break
    return state


def test_static_equilibrium_vs_dense_newton():
    """Gravity + point load: torchdeform's converged equilibrium equals a dense Newton solve
    (exact edge-list Hessian, scipy.linalg.solve) of the nonlinear edge-list energy, relative
    error < 1e-6 (measured ~1e-12)."""
    grid, k = _static_problem()
    model = _static_model(grid, k, 1.0)
    edges, ke, free, fext = _edge_static(grid, k, model, 1.0)
    dof = np.repeat(free, 3)
    x = edges.X.copy()
    for _ in range(30):
        r = edges.forces_vec(x, ke) + fext
        if np.abs(r[free]).max() < 1e-15:
            break
        H = edges.hessian(x, ke)
        step = sla.solve(H[np.ix_(dof, dof)], r.ravel()[dof], assume_a="pos")
        x = x.ravel()
        x[dof] += step
        x = x.reshape(-1, 3)
    assert np.abs(edges.forces_vec(x, ke) + fext)[free].max() < 1e-13
    u_ref = x - edges.X
    assert np.abs(u_ref).max() > 1e-4  # a visibly nonlinear sag (~5 % strain)
    state = _torchdeform_equilibrium(model)
    u_td = edges.from_field((state.x - model.X)[0])
    rel = np.abs(u_td - u_ref).max() / np.abs(u_ref).max()
    assert rel < 1e-6, rel
    assert np.abs(u_td[~free]).max() == 0.0


def test_static_equilibrium_small_load_vs_linear_stiffness_solve():
    """With a small load the equilibrium equals the dense linear solve K u = f of the stiffness
    matrix assembled from k n n^T spring blocks (nonlinear terms are O(strain) ~ 1e-8)."""
    grid, k = _static_problem()
    scale = 1e-6
    model = _static_model(grid, k, scale)
    edges, ke, free, fext = _edge_static(grid, k, model, scale)
    dof = np.repeat(free, 3)
    K = np.zeros((3 * edges.N, 3 * edges.N))
    for s, (a, b, _) in enumerate(edges.springs):
        n = edges.X[a] - edges.X[b]
        n /= np.linalg.norm(n)
        blk = ke[s] * np.outer(n, n)
        K[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] += blk
        K[3 * b : 3 * b + 3, 3 * b : 3 * b + 3] += blk
        K[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] -= blk
        K[3 * b : 3 * b + 3, 3 * a : 3 * a + 3] -= blk
    u_lin = np.zeros(3 * edges.N)
    u_lin[dof] = sla.solve(K[np.ix_(dof, dof)], fext.ravel()[dof], assume_a="pos")
    state = _torchdeform_equilibrium(model)
    u_td = edges.from_field((state.x - model.X)[0]).ravel()
    rel = np.abs(u_td - u_lin).max() / np.abs(u_lin).max()
    assert rel < 1e-6, rel


def test_normalized_stiffness_gives_resolution_independent_stretch():
    """k = Y / l0: a chain of length L fixed at one end, pulled by F at the tip, stretches by
    F L / Y (springs in series) at every resolution."""
    L, Y, F = 0.1, 40.0, 0.3
    stretches = []
    for n_nodes in (5, 17):
        grid = td.Grid((n_nodes, 1, 1), spacing=L / (n_nodes - 1), topology=6)
        fixed = torch.zeros(grid.shape, dtype=torch.bool)
        fixed[0] = True
        model = td.Model(
            grid,
            stiffness=Y,
            normalize=True,
            mass=1e-3,
            fixed=fixed,
            dtype=F64,
            loads=[td.PointForce((n_nodes - 1, 0, 0), (F, 0.0, 0.0))],
        )
        state = _torchdeform_equilibrium(model)
        stretches.append(float(state.x[0, 0, -1, 0, 0] - model.X[0, 0, -1, 0, 0]))
    assert stretches[0] == pytest.approx(F * L / Y, rel=1e-9)
    assert stretches[1] == pytest.approx(F * L / Y, rel=1e-9)


# ============================================================== invariants
def _free_body(topology=26, damping=None, mode="projected", seed=2, device=None):
    grid = td.Grid((3, 3, 3), spacing=(0.01, 0.011, 0.012), topology=topology)
    model = td.Model(grid, stiffness=50.0, damping=damping, damping_mode=mode, density=1000.0, dtype=F64, device=device)
    gen = torch.Generator().manual_seed(seed)
    x = model.X + 5e-4 * torch.randn((1, 3) + grid.shape, generator=gen, dtype=F64).to(model.device)
    v = 0.05 * torch.randn((1, 3) + grid.shape, generator=gen, dtype=F64).to(model.device)
    return model, td.State(x, v)


def _momenta(model, state):
    mv = model.mass * state.v
    p = mv.flatten(2).sum(2)[0]
    L = torch.linalg.cross(state.x.flatten(2)[0].T, mv.flatten(2)[0].T).sum(0)
    return p, L


@pytest.mark.slow
def test_symplectic_euler_energy_band_10000_steps():
    """Undamped symplectic Euler: the total energy (kinetic + springs + home springs) stays in a
    narrow band for 10,000 steps at dt = 0.2 x bound, without drift (symplectic schemes conserve
    a shadow energy). A 6-neighbour body (3 stencil directions, cheap) with home springs so that
    its shear mechanisms cannot fold it up over the long run."""
    grid = td.Grid((3, 3, 3), spacing=(0.01, 0.011, 0.012), topology=6)
    model = td.Model(grid, stiffness=50.0, home=10.0, density=1000.0, dtype=F64)
    gen = torch.Generator().manual_seed(6)
    x = model.X + 1e-3 * torch.randn(model.X.shape, generator=gen, dtype=F64)
    state = td.State(x, 0.05 * torch.randn(model.X.shape, generator=gen, dtype=F64))
    dt = 0.2 * td.time_step_bound(model, integrator="symplectic")
    E0 = float(model.energy(state)["total"])
    energies = []

    def cb(i, st):
        if i % 10 == 0:
            energies.append(float(model.energy(st)["total"]))

    td.simulate(model, state, dt, 10_000, callback=cb)
    E = np.array(energies)
    assert np.all(np.isfinite(E))
    assert np.abs(E - E0).max() / E0 < 0.15
    assert abs(E[-100:].mean() - E[:100].mean()) / E0 < 0.01


@pytest.mark.parametrize("damping", [None, 0.2])
def test_symplectic_euler_conserves_momenta(damping, device):
    """No fixed nodes, no gravity, random velocities: central pair forces (springs and projected
    dashpots) conserve linear and angular momentum under symplectic Euler (exactly, up to
    rounding)."""
    model, state = _free_body(damping=damping, device=device)
    p0, L0 = _momenta(model, state)
    dt = 0.5 * td.time_step_bound(model, integrator="symplectic")
    state, _ = td.simulate(model, state, dt, 500)
    p1, L1 = _momenta(model, state)
    assert float((p1 - p0).norm()) <= 1e-10 * float(p0.norm())
    assert float((L1 - L0).norm()) <= 1e-10 * float(L0.norm())
    assert float((state.x - model.X).abs().max()) > 1e-3  # the body did move


@pytest.mark.parametrize(
    "integrator",
    [td.ExplicitEuler(), td.DampedVerlet(kd=0.0), td.RK4(), td.ImplicitEuler(cg_tol=1e-14, cg_iters=500)],
    ids=["explicit", "verlet", "rk4", "implicit"],
)
def test_linear_momentum_conserved_by_all_integrators(integrator, device):
    model, state = _free_body(damping=0.2, device=device)
    p0, _ = _momenta(model, state)
    dt = 0.3 * td.time_step_bound(model, integrator="symplectic")
    for _ in range(20):
        state = integrator.step(model, state, dt)
    p1, _ = _momenta(model, state)
    assert float((p1 - p0).norm()) <= 1e-10 * float(p0.norm())


def test_rigid_rotation_damped_only_by_unprojected_damping():
    """For a rigid rotation v = w x X every spring keeps its length: projected dashpots give no
    force, Radetzky's unprojected damping gives -c (v_i - v_j) on every spring (REFERENCE 1.2)."""
    grid = td.Grid((3, 3, 3), spacing=(0.01, 0.011, 0.012), topology=26)
    w = torch.tensor([0.3, -1.2, 0.7], dtype=F64)
    X = grid.rest_positions(dtype=F64)
    v = torch.linalg.cross(w.view(1, 3, 1, 1, 1).expand_as(X), X, dim=1)
    proj = td.Model(grid, stiffness=50.0, damping=0.2, mass=1.0, dtype=F64)
    unproj = td.Model(grid, stiffness=50.0, damping=0.2, damping_mode="unprojected", mass=1.0, dtype=F64)
    assert float(proj.forces(X, v).abs().max()) < 1e-16
    edges = EdgeList(grid.shape, grid.spacing, 26)
    ref = edges.to_field(edges.forces(edges.from_field(X[0]), edges.from_field(v[0]), 50.0, 0.2, projected=False))
    np.testing.assert_allclose(unproj.forces(X, v)[0].numpy(), ref, atol=1e-14)
    assert np.abs(ref).max() > 1e-4


# ============================================================ convergence orders
def _order_problem():
    shape, spacing = (2, 2, 3), (1.0, 0.9, 1.1)
    grid = td.Grid(shape, spacing=spacing, topology=14)
    fixed = torch.zeros(shape, dtype=torch.bool)
    fixed[0, 0, :] = True
    rng = np.random.default_rng(0)
    mass = torch.from_numpy(rng.uniform(0.8, 1.5, shape))
    k, c, g = 1.0, 0.05, (-1.0, 0.2, 0.0)
    model = td.Model(grid, stiffness=k, damping=c, mass=mass, gravity=g, fixed=fixed, dtype=F64)
    gen = torch.Generator().manual_seed(0)
    free = model.free
    x0 = model.X + 0.1 * torch.randn((1, 3) + shape, generator=gen, dtype=F64) * free
    v0 = 0.3 * torch.randn((1, 3) + shape, generator=gen, dtype=F64) * free
    return model, td.State(x0, v0), (k, c, np.array(g), fixed)


@pytest.fixture(scope="module")
def order_reference():
    """x(T = 1) of the edge-list equations of motion, DOP853 at rtol = atol = 1e-13."""
    model, s0, (k, c, g, fixed) = _order_problem()
    edges = EdgeList(model.grid.shape, model.grid.spacing, model.grid.topology)
    m = _node_values(edges, model.mass)
    free = (~_field_mask(edges, fixed)).astype(np.float64)[:, None]

    def rhs(t, y):
        x, v = y[: y.size // 2].reshape(-1, 3), y[y.size // 2 :].reshape(-1, 3)
        a = (edges.forces_vec(x, k, v, c) / m[:, None] + g) * free
        return np.concatenate([(v * free).ravel(), a.ravel()])

    y0 = np.concatenate([edges.from_field(s0.x[0]).ravel(), edges.from_field(s0.v[0]).ravel()])
    sol = solve_ivp(rhs, (0.0, 1.0), y0, method="DOP853", rtol=1e-13, atol=1e-13)
    assert sol.success
    return edges, sol.y[: y0.size // 2, -1].reshape(-1, 3)


@pytest.mark.parametrize(
    "integrator,steps,lo,hi",
    [
        (td.ExplicitEuler(), (20, 40, 80, 160), 0.8, 1.3),
        (td.SymplecticEuler(), (20, 40, 80, 160), 0.8, 1.3),
        (td.DampedVerlet(kd=0.0), (20, 40, 80, 160), 0.8, 1.3),
        (td.ImplicitEuler(cg_iters=300, cg_tol=1e-12), (16, 32, 64, 128), 0.8, 1.3),
        (td.RK4(), (10, 20, 40, 80), 3.5, 4.6),
    ],
    ids=["explicit", "symplectic", "verlet", "implicit", "rk4"],
)
def test_convergence_order(order_reference, integrator, steps, lo, hi):
    """Errors at T = 1 against the DOP853 edge-list reference over 4 step sizes: log-log slopes
    about 1 for the Euler variants and implicit Euler, about 4 for RK4 (damping, gravity and a
    fixed edge included; the state is large-amplitude, i.e. nonlinear)."""
    edges, x_ref = order_reference
    model, s0, _ = _order_problem()
    errors = []
    for n in steps:
        state, dt = s0, 1.0 / n
        for _ in range(n):
            state = integrator.step(model, state, dt)
        errors.append(np.abs(edges.from_field(state.x[0]) - x_ref).max())
    slopes = np.diff(np.log(errors)) / np.diff(np.log(1.0 / np.array(steps)))
    assert np.all((slopes > lo) & (slopes < hi)), (errors, slopes)


# ============================================================== stability
def _stability_model(topology=26, k=None):
    grid = td.Grid((3, 3, 3), spacing=(0.01, 0.011, 0.009), topology=topology)
    k = k or {"axis": 60.0, "face": 40.0, "body": 30.0}
    k = {c: k[c] for c in set(grid.direction_class())}
    return td.Model(grid, stiffness=k, density=1000.0, fixed=grid.face("bottom"), dtype=F64), k


def _dense_omega2(model, k):
    """lambda_max of the generalised problem K u = lambda M u over free nodes (scipy eigh)."""
    edges = EdgeList(model.grid.shape, model.grid.spacing, model.grid.topology)
    cls = {1: "axis", 2: "face", 3: "body"}
    ke = np.array([k[cls[sum(map(abs, off))]] for _, _, off in edges.springs])
    dof = np.repeat(~_field_mask(edges, model.constrained), 3)
    m = np.repeat(_node_values(edges, model.mass), 3)
    K = edges.hessian(edges.X, ke)
    lam = sla.eigh(K[np.ix_(dof, dof)], np.diag(m[dof]), eigvals_only=True)
    return lam.max()


@pytest.mark.parametrize("topology", [6, 14, 18, 26])
def test_time_step_bound_vs_dense_eigenvalue(topology):
    model, k = _stability_model(topology)
    w2 = _dense_omega2(model, k)
    dense = 2 / math.sqrt(w2)
    bound = td.time_step_bound(model, integrator="symplectic")
    assert abs(bound / dense - 1) < 0.01
    # Gershgorin is a guaranteed (smaller) bound; the RK4 bound is sqrt(2) larger
    assert td.time_step_bound(model, integrator="symplectic", method="gershgorin") <= dense * (1 + 1e-12)
    assert td.gershgorin_omega2(model) >= w2 * (1 - 1e-12)
    assert abs(td.time_step_bound(model, integrator="rk4") / (2 * math.sqrt(2) / math.sqrt(w2)) - 1) < 0.01


def _perturbed(model, amp=1e-7, seed=3):
    gen = torch.Generator().manual_seed(seed)
    h = min(model.grid.spacing)
    x = model.X + amp * h * torch.randn(model.X.shape, generator=gen, dtype=F64) * model.free
    return td.State(x, torch.zeros_like(x))


def test_symplectic_stable_just_below_bound():
    """At 0.95 x the computed bound symplectic Euler runs 2,000 steps with bounded energy
    (perturbation 1e-7 of the spacing, so the linear analysis applies), no warning."""
    model, _ = _stability_model(topology=14)
    dt = 0.95 * td.time_step_bound(model, integrator="symplectic")
    state = _perturbed(model)
    E0 = float(model.energy(state)["total"])
    energies = []

    def cb(i, st):
        if i % 5 == 0:
            energies.append(float(model.energy(st)["total"]))

    with warnings.catch_warnings():
        warnings.simplefilter("error", td.StabilityWarning)
        state, _ = td.simulate(model, state, dt, 2000, callback=cb)
    E = np.array(energies)
    assert np.all(np.isfinite(E))
    # near the bound the energy of the top mode oscillates by up to 1/(1 - (h w / 2)^2) ~ 10x;
    # an unstable run grows by > 40x per step
    assert E.max() < 30 * E0
    assert E[-50:].max() < 2 * E[:50].max()


def test_divergence_detected_above_bound():
    """At 1.5 x a tight bound symplectic Euler diverges; ``simulate`` warns first, then stops
    with a DivergenceError naming the step, the quantity and a safe dt below the dense bound."""
    model, k = _stability_model()
    dense = 2 / math.sqrt(_dense_omega2(model, k))
    bound = td.time_step_bound(model, integrator="symplectic")
    with (
        pytest.warns(td.StabilityWarning, match="exceeds the stability bound"),
        pytest.raises(td.DivergenceError) as info,
    ):
        td.simulate(model, _perturbed(model), 1.5 * bound, 2000)
    err = info.value
    msg = str(err)
    assert 0 < err.step <= 2000 and f"step {err.step}" in msg
    assert err.quantity in ("position", "velocity", "kinetic energy (runaway)") and err.quantity in msg
    assert err.safe_dt is not None and 0 < err.safe_dt < dense
    assert f"{err.safe_dt:.3g}" in msg
    assert err.dt == pytest.approx(1.5 * bound)


def test_check_dt_warns_only_above_bound():
    model, _ = _stability_model()
    bound = td.time_step_bound(model, integrator="symplectic")
    with pytest.warns(td.StabilityWarning):
        td.check_dt(model, 1.1 * bound, "symplectic")
    with pytest.warns(td.StabilityWarning):
        td.check_dt(model, 1e-6, "explicit")  # undamped explicit Euler: always unstable
    with warnings.catch_warnings():
        warnings.simplefilter("error", td.StabilityWarning)
        td.check_dt(model, 0.9 * bound, "symplectic")
        td.check_dt(model, 1.2 * bound, "rk4")  # RK4 allows 2 sqrt 2 / omega
        td.check_dt(model, 1e3 * bound, "implicit")


@pytest.mark.parametrize("stiffness", [1e2, 1e4, 1e6, 1e8])
def test_implicit_euler_at_100x_bound(stiffness, device):
    """Implicit Euler at 100 x the explicit bound, fixed base, gravity, an initial random
    deformation: finite, the total energy (kinetic + elastic + gravity) never exceeds its initial
    value, oscillations die out, and the sag approaches the static one (mg / k scale)."""
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    model = td.Model(
        grid,
        stiffness=stiffness,
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
        device=device,
    )
    dt = 100 * td.time_step_bound(model, integrator="symplectic")
    gen = torch.Generator().manual_seed(4)
    sag = float(model.mass.sum()) * 9.81 / stiffness  # a displacement scale
    x0 = model.X + 0.3 * sag * torch.randn(model.X.shape, generator=gen, dtype=F64).to(device) * model.free
    state = td.State(x0, torch.zeros_like(x0))
    E0 = float(model.energy(state)["total"])
    scale = abs(E0) + float(model.mass.sum()) * 9.81 * sag
    energies, kinetic = [], []

    def cb(i, st):
        e = model.energy(st)
        energies.append(float(e["total"]))
        kinetic.append(float(e["kinetic"]))

    state, _ = td.simulate(model, state, dt, 20, integrator=td.ImplicitEuler(), callback=cb)
    assert bool(torch.isfinite(state.x).all() and torch.isfinite(state.v).all())
    assert max(energies) <= E0 + 1e-9 * scale
    assert kinetic[-1] < 1e-6 * max(kinetic)
    assert float((state.x - model.X).abs().max()) < 3 * sag


# ============================================================== Knoche mode
def _knoche_setup(n=16):
    grid = td.Grid((n, n, n), spacing=1.0, topology=6)
    model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=F64)
    w = torch.full((n, n, n), 0.5, dtype=F64)
    for i in (0, n - 1):
        for j in (0, n - 1):
            for k in (0, n - 1):
                w[i, j, k] = 1.0
    c = n // 2
    w[c, c, c] = 1.0
    state = model.rest_state()
    state.x[0, 0, c, c, c] += 0.1
    return model, td.KnocheRelaxation(w, eps=1e-3), state


def test_knoche_single_step():
    """REFERENCE 1.3: after one step the 6 face neighbours of the centre have 0.00703125 =
    (3/16)(0.5)(0.1)(0.75); every other node stays 0."""
    model, relax, state = _knoche_setup()
    u = (relax.step(model, state, 1.0).x - model.X)[0]
    expected = torch.zeros_like(u)
    expected[0, 8, 8, 8] = 0.1
    for off in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
        expected[0, 8 + off[0], 8 + off[1], 8 + off[2]] = 0.00703125
    assert float((u - expected).abs().max()) < 1e-12


@pytest.mark.slow
def test_knoche_converged_x_line():
    """REFERENCE 1.3: iterate until the largest change is < 1e-11 (about 5,000 iterations); the
    x-offsets along [:, 8, 8] match the listed 5-decimal values, (9,8,8) and (8,9,8) are 0.041959,
    y and z stay exactly 0."""
    model, relax, state = _knoche_setup()
    it = 0
    while True:
        for _ in range(100):
            prev = state.x
            state = relax.step(model, state, 1.0)
            it += 1
        if float((state.x - prev).abs().max()) < 1e-11:
            break
        assert it < 20_000
    assert 3_000 < it < 8_000
    u = (state.x - model.X)[0]
    ref = [
        0.00228,
        0.00303,
        0.00403,
        0.00545,
        0.00763,
        0.01142,
        0.01943,
        0.04197,
        0.1,
        0.04196,
        0.01940,
        0.01138,
        0.00758,
        0.00539,
        0.00396,
        0.00295,
    ]
    np.testing.assert_allclose(u[0, :, 8, 8].numpy(), ref, rtol=0, atol=6e-6)
    assert float(u[0, 9, 8, 8]) == pytest.approx(0.041959, abs=1e-6)
    assert float(u[0, 8, 9, 8]) == pytest.approx(0.041959, abs=1e-6)
    assert float(u[1:].abs().max()) == 0.0


def _knoche_shader(u, w, eps):
    """Knoche 2008, Code Example 2, transcribed literally: for every node (one fragment), read
    the 6 neighbours (out of the texture: offset 0, w 0), halve a spring whose neighbour has
    w < eps, weight by (w_k + w_c)/2, scale by (1 - w_c), add 3/dim of it (Jacobi)."""
    n = u.shape[1]
    out = u.copy()
    for i in range(n):
        for j in range(n):
            for k in range(n):
                wc = w[i, j, k]
                if wc > 1.0 - eps:
                    continue  # fixed: output = input
                force = np.zeros(3)
                for di, dj, dk in ((-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)):
                    a, b, c = i + di, j + dj, k + dk
                    if 0 <= a < n and 0 <= b < n and 0 <= c < n:
                        un, wn = u[:, a, b, c], w[a, b, c]
                    else:
                        un, wn = np.zeros(3), 0.0
                    spring = (un - u[:, i, j, k]) / 2.0 if wn < eps else un - u[:, i, j, k]
                    force += spring * (wn + wc) / 2.0
                force *= 1.0 - wc
                out[:, i, j, k] = u[:, i, j, k] + 3.0 / n * force
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_knoche_step_matches_shader_transcription(seed):
    n, eps = 6, 1e-3
    rng = np.random.default_rng(seed)
    w = rng.uniform(0, 1, (n, n, n))
    w[rng.random((n, n, n)) < 0.15] = 0.0  # "free" (w < eps) nodes
    w[rng.random((n, n, n)) < 0.1] = 1.0  # fixed nodes
    w[0, 0, 0], w[1, 2, 3] = 5e-4, 1 - 5e-4  # just inside the eps bands
    u = rng.standard_normal((3, n, n, n))
    grid = td.Grid((n, n, n), spacing=(1.0, 0.5, 2.0), topology=6)
    model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=F64)
    state = td.State(model.X + torch.from_numpy(u)[None], torch.zeros(1, 3, n, n, n, dtype=F64))
    got = (td.KnocheRelaxation(torch.from_numpy(w), eps=eps).step(model, state, 1.0).x - model.X)[0]
    np.testing.assert_allclose(got.numpy(), _knoche_shader(u, w, eps), rtol=0, atol=1e-12)
    ref2 = _knoche_shader(_knoche_shader(u, w, eps), w, eps)
    s2 = td.KnocheRelaxation(torch.from_numpy(w), eps=eps)
    st = s2.step(model, s2.step(model, state, 1.0), 1.0)
    np.testing.assert_allclose((st.x - model.X)[0].numpy(), ref2, rtol=0, atol=1e-12)


# ============================================================== gradients
def _rollout(integrator, steps, dt, per_direction=False):
    grid = td.Grid((3, 3, 3), spacing=0.1, topology=26)
    gen = torch.Generator().manual_seed(0)
    x0 = grid.rest_positions(dtype=F64) + 0.01 * torch.randn((1, 3, 3, 3, 3), generator=gen, dtype=F64)
    v0 = 0.05 * torch.randn((1, 3, 3, 3, 3), generator=gen, dtype=F64)
    P = torch.randn(3, 81, generator=gen, dtype=F64)
    fixed = grid.face("bottom")

    def f(k, c, m):
        model = td.Model(grid, stiffness=k, damping=c, mass=m, gravity=(-9.81, 0, 0), fixed=fixed, dtype=F64)
        s = td.State(x0, v0)
        for _ in range(steps):
            s = integrator.step(model, s, dt)
        return torch.cat([P @ s.x.flatten(), P @ s.v.flatten()])

    return f


def _scalars():
    return tuple(torch.tensor(v, dtype=F64, requires_grad=True) for v in (20.0, 0.3, 0.05))


@pytest.mark.parametrize(
    "integrator,steps,dt", [(td.SymplecticEuler(), 8, 0.005), (td.RK4(), 3, 0.005)], ids=["symplectic", "rk4"]
)
def test_gradcheck_rollout_scalar_parameters(integrator, steps, dt):
    assert torch.autograd.gradcheck(_rollout(integrator, steps, dt), _scalars())


def test_gradcheck_rollout_per_direction_parameters():
    """Stiffness and damping per half-direction ``(S,)``, mass per node ``(D, H, W)``."""
    gen = torch.Generator().manual_seed(5)
    k = (20.0 + torch.rand(13, generator=gen, dtype=F64)).requires_grad_()
    c = (0.3 + 0.1 * torch.rand(13, generator=gen, dtype=F64)).requires_grad_()
    m = (0.05 + 0.01 * torch.rand(3, 3, 3, generator=gen, dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(_rollout(td.SymplecticEuler(), 3, 0.005), (k, c, m))


def test_gradcheck_implicit_euler():
    """Through the CG solves of implicit Euler (tight tolerance)."""
    integ = td.ImplicitEuler(cg_iters=300, cg_tol=1e-13)
    assert torch.autograd.gradcheck(_rollout(integ, 1, 0.02), _scalars())


@pytest.mark.parametrize("decay", [0.0, 200.0, 5000.0])
def test_bound_with_global_drag_is_the_edge_of_stability(decay):
    """Global drag after a symplectic step (v <- e^{-c h} v) lowers the stable step. Oracle: the
    spectral radius of the 2 x 2 update matrix of one spring, [[1 - h^2 w^2, h], [-d h w^2, d]]
    with d = e^{-c h}, computed by numpy: < 1 just below the bound, > 1 just above it."""
    grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)
    model = td.Model(grid, stiffness=1e4, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]), decay=decay or None, dtype=F64)
    w2 = 1e4
    h = td.time_step_bound(model)

    def radius(t):
        d = math.exp(-decay * t)
        return max(abs(np.linalg.eigvals([[1 - t * t * w2, t], [-d * t * w2, d]])))

    assert radius(0.999 * h) <= 1 + 1e-12 < 1.001 < radius(1.001 * h)  # undamped: on the unit circle below
    if decay >= 5000:  # a strong drag: down to 1/sqrt(2) of 2/w
        assert h < 0.75 * 2 / math.sqrt(w2)
