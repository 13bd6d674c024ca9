"""Projective dynamics against independent oracles (float64): Newton's implicit Euler, a dense edge-list matrix."""

import itertools
import sys

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.sim.projective import ProjectiveDynamics, jacobi_inverse_diagonal, laplacian_operator

SOLVERS = ["cholesky", "cg", "jacobi"]
#: cg takes cholesky's exact global steps, each one up to 200 CG iterations: in the slow tier where steps add up
SOLVERS_CG_SLOW = ["cholesky", pytest.param("cg", marks=pytest.mark.slow), "jacobi"]
EXACT = {"cholesky": {}, "cg": {"cg_tol": 1e-10, "cg_iters": 200}}  # exact global steps


def body(k=1e3, **kw):
    """A 5 x 4 x 4 body, 26 neighbours, gravity, fixed base (``device=`` as :class:`td.Model`)."""
    grid = td.Grid((5, 4, 4), spacing=0.01, topology=26)
    kw.setdefault("fixed", grid.face("bottom"))
    return td.Model(grid, stiffness=k, density=1000.0, gravity=(-9.81, 0, 0), dtype=F64, **kw)


def stretched(model, seed=1):
    """10 % stretch along D plus millimetre noise on the free nodes."""
    g = torch.Generator().manual_seed(seed)
    x = model.X + 1e-3 * torch.randn(model.X.shape, generator=g, dtype=F64).to(model.device) * model.free
    x[:, 0] = x[:, 0] * 1.1
    x = torch.where(model.free > 0, x, model.X)
    return td.State(x, torch.zeros_like(x), t=0.0)


def newton(model, state, dt):
    """Converged implicit Euler: the oracle."""
    return td.ImplicitEuler(cg_tol=1e-12, cg_iters=500, newton_iters=20).step(model, state, dt)


def rel_error(out, ref, state):
    return float((out.x - ref.x).norm() / (ref.x - state.x).norm())


@pytest.mark.parametrize("solver", SOLVERS_CG_SLOW)
def test_converges_to_implicit_euler(solver, device):
    model = body(device=device)
    s = stretched(model)
    dt = 10 * td.time_step_bound(model, integrator="symplectic")  # well beyond the explicit bound
    ref = newton(model, s, dt)
    counts = {"jacobi": (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000), "cg": (1, 5, 50, 500)}.get(
        solver, (1, 2, 5, 10, 20, 50, 100, 200, 500)
    )  # (cg: cholesky's, slower)
    kw = EXACT.get(solver, {})
    errs = [rel_error(ProjectiveDynamics(iterations=n, solver=solver, **kw).step(model, s, dt), ref, s) for n in counts]
    print(f"\n{solver}: relative error vs Newton implicit Euler, dt = 10x explicit bound")
    for n, e in zip(counts, errs):
        print(f"  {n:4d} iterations  {e:.2e}")
    assert errs[-1] < 1e-8
    tail = [e for n, e in zip(counts, errs) if n >= 5]
    assert all(b < a for a, b in itertools.pairwise(tail))  # decreasing from 5 iterations on
    assert errs[0] < 1.0 if solver != "jacobi" else errs[0] <= 1.0


@pytest.mark.parametrize("solver", SOLVERS_CG_SLOW)
def test_solvers_agree_with_tolerance_stop(solver):
    model = body(home=50.0)
    s = stretched(model, seed=3)
    dt = 30 * td.time_step_bound(model, integrator="symplectic")
    ref = newton(model, s, dt)
    pd = ProjectiveDynamics(iterations=5000, tol=1e-12, solver=solver, **EXACT.get(solver, {}))
    out = pd.step(model, s, dt)
    assert pd.last_iterations < 5000 and isinstance(pd.last_residual, float)
    assert rel_error(out, ref, s) < 1e-8, solver


def _edge_list(grid):
    """Every spring ``(i, j, s)`` by a plain loop over nodes and directions."""
    D, H, W = grid.shape
    out = []
    for d in range(D):
        for h in range(H):
            for w in range(W):
                for s, (a, b, c) in enumerate(grid.directions):
                    if 0 <= d + a < D and 0 <= h + b < H and 0 <= w + c < W:
                        out.append(((d, h, w), (d + a, h + b, w + c), s))
    return out


def test_matrix_equals_dense_edge_list_oracle():
    grid = td.Grid((3, 3, 2), spacing=(0.01, 0.02, 0.015), topology=26)
    g = torch.Generator().manual_seed(0)
    k = 100 + 900 * torch.rand((grid.S,) + grid.shape, generator=g, dtype=F64)
    cut = torch.ones((grid.S,) + grid.shape, dtype=torch.bool)
    cut[4, 1, 1, 0] = False  # one spring removed
    fixed = grid.index_mask([(0, 0, 0), (0, 1, 1)])
    home = 5 * torch.rand(grid.shape, generator=g, dtype=F64)
    mass = 1e-3 * (1 + torch.rand(grid.shape, generator=g, dtype=F64))
    model = td.Model(
        grid,
        stiffness=k,
        damping=0.3,
        damping_mode="unprojected",
        mass=mass,
        home=home,
        fixed=fixed,
        spring_mask=cut,
        dtype=F64,
    )
    h = 2e-3
    N = grid.num_nodes
    flat = {idx: n for n, idx in enumerate(np.ndindex(*grid.shape))}
    A = np.diag(mass.numpy().ravel() + h * h * home.numpy().ravel())
    for i, j, s in _edge_list(grid):
        if not cut[(s,) + i]:
            continue
        w = h * h * float(k[(s,) + i]) + h * 0.3
        a, b = flat[i], flat[j]
        A[a, a] += w
        A[b, b] += w
        A[a, b] -= w
        A[b, a] -= w
    keep = [n for n, idx in enumerate(np.ndindex(*grid.shape)) if not fixed[idx]]
    oracle = A[np.ix_(keep, keep)]
    mats, index = ProjectiveDynamics.matrix(model, h)
    assert len(mats) == 1 and list(index) == keep
    np.testing.assert_allclose(mats[0].toarray(), oracle, rtol=1e-13, atol=0)
    # the matrix-free product and the Jacobi diagonal are the same matrix
    u = torch.randn(1, 3, *grid.shape, generator=g, dtype=F64) * model.free
    Au = laplacian_operator(model, h)(u).reshape(3, N)[:, keep].numpy()
    np.testing.assert_allclose(Au, (A[keep] @ u.reshape(3, N).numpy().T).T, rtol=1e-10, atol=1e-15)
    inv_d = jacobi_inverse_diagonal(model, h).reshape(N)
    np.testing.assert_allclose(inv_d[keep].numpy(), 1 / np.diag(oracle), rtol=1e-13)
    assert float(inv_d[[n for n in range(N) if n not in keep]].abs().max()) == 0.0


@pytest.mark.parametrize("solver", SOLVERS_CG_SLOW)
def test_stable_at_100x_explicit_bound(solver):
    model = body(k=1e8)
    s = stretched(model)
    dt = 100 * td.time_step_bound(model, integrator="symplectic")
    pd = ProjectiveDynamics(solver=solver)
    e0 = float(model.energy(s)["total"][0])
    energies = []
    for _ in range(50):
        s = pd.step(model, s, dt)
        assert bool(torch.isfinite(s.x).all() and torch.isfinite(s.v).all())
        energies.append(float(model.energy(s)["total"][0]))
    assert max(energies) <= e0 * (1 + 1e-9)
    assert energies[-1] < 0.5 * e0  # and it does not ring forever
    assert bool((s.x[:, :, 0] == model.X[:, :, 0]).all())  # the base stays fixed exactly


@pytest.mark.parametrize("solver", SOLVERS_CG_SLOW)
def test_fixed_nodes_stay_and_drag_moves_its_nodes(solver):
    grid = td.Grid((5, 4, 4), spacing=0.01, topology=26)
    top = grid.face("top")
    drag = td.Drag(top, path=[(0.0, (0.0, 0.0, 0.0)), (1.0, (0.0, 0.05, 0.0))])  # 5 cm/s along H
    model = body(drags=[drag])
    s = model.rest_state()
    dt = 10 * td.time_step_bound(model, integrator="symplectic")
    pd = ProjectiveDynamics(iterations=3000, tol=1e-13, solver=solver, **EXACT.get(solver, {}))
    out = pd.step(model, s, dt)
    ref = newton(model, s, dt)
    assert bool((out.x[:, :, 0] == model.X[:, :, 0]).all()) and float(out.v[:, :, 0].abs().max()) == 0.0
    np.testing.assert_allclose(out.x[0, 1][top].numpy(), model.X[0, 1][top].numpy() + 0.05 * dt, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out.v[0, 1][top].numpy(), 0.05, rtol=1e-12)
    assert float(out.x[0, 1, 2].mean() - model.X[0, 1, 2].mean()) > 0  # the middle follows
    assert rel_error(out, ref, s) < 1e-8
    for _ in range(3):  # and keeps following
        out = ProjectiveDynamics(solver=solver).step(model, out, dt)
    np.testing.assert_allclose(out.x[0, 1][top].numpy(), model.X[0, 1][top].numpy() + 0.05 * 4 * dt, atol=1e-15)


@pytest.mark.parametrize("mode", ["unprojected", "projected"])
@pytest.mark.parametrize("solver", SOLVERS_CG_SLOW)
def test_damping_matches_implicit_euler(mode, solver):
    """Unprojected: linear, in the matrix; projected: in the residual. Both converge to Newton's step."""
    model = body(damping=2.0, damping_mode=mode, home=20.0)
    s = stretched(model, seed=2)
    g = torch.Generator().manual_seed(5)
    s.v = 0.3 * torch.randn(s.x.shape, generator=g, dtype=F64) * model.free
    dt = 10 * td.time_step_bound(model, integrator="symplectic")
    ref = newton(model, s, dt)
    pd = ProjectiveDynamics(iterations=3000, tol=1e-13, solver=solver, **EXACT.get(solver, {}))
    out = pd.step(model, s, dt)
    assert rel_error(out, ref, s) < 1e-8
    plain = ProjectiveDynamics(iterations=3000, tol=1e-13, solver=solver, **EXACT.get(solver, {}))
    undamped = plain.step(body(home=20.0), s, dt)
    assert rel_error(undamped, ref, s) > 1e-3  # damping did something


def test_unprojected_damping_is_exact_in_one_cholesky_iteration_of_a_linear_system():
    """Springs at rest length with velocities along them only: unprojected damping enters ``A`` exactly."""
    grid = td.Grid((1, 1, 3), spacing=1.0, topology=6)
    model = td.Model(
        grid,
        stiffness=0.0,
        damping=0.5,
        damping_mode="unprojected",
        mass=1.0,
        home=2.0,
        fixed=grid.index_mask([(0, 0, 0)]),
        dtype=F64,
    )
    s = model.rest_state()
    s.v[0, 2, 0, 0, 1:] = torch.tensor([1.0, -1.0], dtype=F64)
    pd = ProjectiveDynamics(iterations=1, solver="cholesky")
    out = pd.step(model, s, 0.1)
    ref = newton(model, s, 0.1)
    np.testing.assert_allclose(out.x.numpy(), ref.x.numpy(), rtol=0, atol=1e-14)


def test_spring_law_needs_jacobi():
    grid = td.Grid((5, 4, 4), spacing=0.01, topology=26)
    model = td.Model(
        grid,
        stiffness=1e3,
        law=td.Exponential(stiffening=5.0),
        density=1000.0,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        dtype=F64,
    )
    s = stretched(model)
    dt = 3 * td.time_step_bound(model, integrator="symplectic")
    for solver in ("cholesky", "cg"):
        with pytest.raises(ConfigError, match="law"):
            ProjectiveDynamics(solver=solver).step(model, s, dt)
    out = ProjectiveDynamics(iterations=3000, tol=1e-13, solver="jacobi").step(model, s, dt)
    assert rel_error(out, newton(model, s, dt), s) < 1e-8


def test_options_and_missing_cholespy(monkeypatch):
    for kw in ({"solver": "lu"}, {"iterations": 0}, {"rho": 1.0}, {"relaxation": 0.0}, {"tol": -1.0}):
        with pytest.raises(ConfigError):
            ProjectiveDynamics(**kw)
    model = body()
    assert ProjectiveDynamics().solver_for(model) == "cholesky"  # auto: a small body, cholespy here
    monkeypatch.setitem(sys.modules, "cholespy", None)
    with pytest.raises(ConfigError, match="pip install cholespy"):
        ProjectiveDynamics(solver="cholesky").step(model, model.rest_state(), 1e-3)
    assert ProjectiveDynamics().solver_for(model) == "jacobi"  # auto without cholespy
    assert (
        ProjectiveDynamics().solver_for(td.Model(td.Grid((40, 40, 40), spacing=0.01), stiffness=1.0, mass=1.0))
        == "jacobi"
    )


def test_cholesky_refactors_after_an_in_place_cut_and_per_batch_parameters():
    model = body()
    s = stretched(model)
    dt = 10 * td.time_step_bound(model, integrator="symplectic")
    pd = ProjectiveDynamics(solver="cholesky")
    pd.step(model, s, dt)
    with torch.no_grad():
        model.stiffness[:, 3] = 0.0  # a direction cut in place
    np.testing.assert_array_equal(
        pd.step(model, s, dt).x.numpy(), ProjectiveDynamics(solver="cholesky").step(model, s, dt).x.numpy()
    )
    # per-batch stiffness: one factor per entry, each equal to its own single-entry model
    ks = torch.tensor([[1e3] * 13, [4e3] * 13], dtype=F64)
    batched = body(k=ks)
    s2 = td.State(s.x.expand(2, -1, -1, -1, -1).clone(), torch.zeros_like(s.x).expand(2, -1, -1, -1, -1).clone())
    out = ProjectiveDynamics(solver="cholesky").step(batched, s2, dt)
    for b, k in enumerate((1e3, 4e3)):
        one = ProjectiveDynamics(solver="cholesky").step(body(k=k), s, dt)
        np.testing.assert_allclose(out.x[b].numpy(), one.x[0].numpy(), rtol=0, atol=1e-14)


@pytest.mark.parametrize("solver", SOLVERS)
def test_packed_model_equals_grid_model(solver, device):
    from torchdeform.sim.packed import PackedModel

    model = body(damping=1.0, device=device)
    pm = PackedModel(model)
    s = stretched(model)
    dt = 30 * td.time_step_bound(model, integrator="symplectic")
    out = ProjectiveDynamics(solver=solver).step(model, s, dt)
    packed = pm.unpack_state(ProjectiveDynamics(solver=solver).step(pm, pm.pack_state(s), dt))
    assert packed.x.device == model.device
    np.testing.assert_allclose(packed.x.cpu().numpy(), out.x.cpu().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(packed.v.cpu().numpy(), out.v.cpu().numpy(), rtol=0, atol=1e-9)


@pytest.mark.slow
def test_compiled_jacobi_equals_eager():
    from torchdeform.sim.compiled import compiled_step

    grid = td.Grid((6, 5, 5), spacing=0.01, topology=26)
    model = td.Model(grid, stiffness=1e3, damping=0.5, density=1000.0, gravity=(-9.81, 0, 0), fixed=grid.face("bottom"))
    dt = 100 * td.time_step_bound(model, integrator="symplectic")
    pd = ProjectiveDynamics(solver="jacobi")
    step = compiled_step(pd, model, dt)
    s = model.rest_state()
    s.x = s.x * 1.05
    fast, eager = s, s
    for _ in range(3):
        fast, eager = step(fast), pd.step(model, eager, dt)
    assert step.compiled, step.compile_error
    scale = float((eager.x - s.x).abs().max())
    assert float((fast.x - eager.x).abs().max()) <= 1e-5 * scale
    # v = (x - x_n) / h: float32 rounding of positions (a few ulps, fused differently) divided by h
    ulp = torch.finfo(torch.float32).eps * float(eager.x.abs().max())
    assert float((fast.v - eager.v).abs().max()) <= 100 * ulp / dt
