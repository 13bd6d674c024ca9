"""Adjoint gradients of implicit Euler (``ImplicitEuler(gradient="adjoint")``, :mod:`torchdeform.sim.adjoint`).

Oracles: the unrolled gradient (autograd through every CG iteration, CG run to convergence so
both are gradients of the same function), central finite differences, and the bytes autograd
holds for the backward (saved-tensor hooks).
"""

import weakref

import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.sim.adjoint import ImplicitSolve, adjoint_solve
from torchdeform.sim.integrators import conjugate_gradient


def _body(per_spring=False, damping=True, drag=False, home=False, shape=(4, 4, 5), seed=0, device=None):
    """A small 26-neighbour body with a fixed base, gravity, and parameters that require grad.

    Returns ``(loss, params)``: ``loss(integrator, steps)`` is a random projection of the final
    displacement and velocity; ``dt`` is 20 times the explicit (symplectic) bound.
    """
    grid = td.Grid(shape, spacing=0.01, topology=26)
    gen = torch.Generator().manual_seed(seed)
    kshape = (grid.S,) + grid.shape if per_spring else (grid.S,)

    def rand(shape, scale, normal=False):  # drawn on the CPU (same numbers on every device), then moved
        draw = torch.randn if normal else torch.rand
        return (scale * draw(shape, generator=gen, dtype=F64)).to(device)

    k = (50.0 * (1 + rand(kshape, 0.2))).requires_grad_()
    c = (0.05 * (1 + rand(kshape, 0.2))).requires_grad_() if damping else None
    m = (1e-3 * (1 + rand(shape, 0.2))).requires_grad_()
    X = grid.rest_positions(dtype=F64, device=device)
    x0 = (X + rand(X.shape, 1e-3, True)).requires_grad_()
    v0 = rand(X.shape, 0.01, True).requires_grad_()
    P, Q = (rand(X.shape, 1.0, True) for _ in range(2))
    drags = [td.Drag(grid.face("top"), offset=(0.002, 0.001, 0.0), ramp=0.05)] if drag else None

    def make(k, c, m):
        return td.Model(
            grid,
            stiffness=k,
            damping=c,
            mass=m,
            gravity=(-9.81, 0, 0),
            fixed=grid.face("bottom"),
            drags=drags,
            home=20.0 if home else None,
            dtype=F64,
            device=device,
        )

    with torch.no_grad():
        dt = 20 * td.time_step_bound(make(k, c, m), integrator="symplectic")

    def loss(integrator, steps, k=k, c=c, m=m, x0=x0, v0=v0):
        model = make(k, c, m)
        s = td.State(x0, v0)
        for _ in range(steps):
            s = integrator.step(model, s, dt)
        return 1e3 * (P * (s.x - X)).sum() + (Q * s.v).sum()

    params = {"k": k, "c": c, "m": m, "x0": x0, "v0": v0}
    return loss, {n: p for n, p in params.items() if p is not None}


def _implicit(gradient, newton_iters=0, **kw):
    kw = {"cg_iters": 1000, "cg_tol": 1e-13, **kw}
    return td.ImplicitEuler(newton_iters=newton_iters, gradient=gradient, **kw)


def test_gradient_option_is_validated():
    assert td.ImplicitEuler().gradient == "unrolled"
    with pytest.raises(td.ConfigError, match=r"implicit\.gradient"):
        td.ImplicitEuler(gradient="adjont")
    with pytest.raises(td.ConfigError, match=r"implicit\.adjoint_iters"):
        td.ImplicitEuler(gradient="adjoint", adjoint_iters=0)
    with pytest.raises(td.ConfigError, match=r"implicit\.adjoint_tol"):
        td.ImplicitEuler(gradient="adjoint", adjoint_tol=-1.0)


@pytest.mark.parametrize(
    "per_spring,damping,drag,home,newton_iters",
    [
        (False, True, False, False, 0),
        (False, False, True, False, 2),
        (True, True, True, False, 0),
        (True, True, False, True, 2),
    ],
    ids=["per-direction-damped", "undamped-drag-newton2", "per-spring-drag", "per-spring-home-newton2"],
)
def test_adjoint_equals_unrolled_gradients(per_spring, damping, drag, home, newton_iters, device):
    """Stiffness and damping (per direction or per spring), node masses, x0 and v0: the adjoint
    gradient of a 4-step rollout at 20 x the explicit bound equals the unrolled one to 1e-8."""
    loss, params = _body(per_spring, damping, drag, home, device=device)
    grads, values = {}, {}
    for gradient in ("unrolled", "adjoint"):
        integ = _implicit(gradient, newton_iters)
        L = loss(integ, 4)
        values[gradient] = L.detach()
        grads[gradient] = torch.autograd.grad(L, list(params.values()))
        assert integ.last_cg[1] <= 1e-13
        if gradient == "adjoint":
            assert integ.last_adjoint_cg[1] <= 1e-13
    assert torch.equal(values["unrolled"], values["adjoint"])
    for name, gu, ga in zip(params, grads["unrolled"], grads["adjoint"]):
        assert float(gu.norm()) > 0, name
        assert float((ga - gu).norm()) <= 1e-8 * float(gu.norm()), name


def test_adjoint_equals_central_differences():
    """Directional derivatives along random directions of each parameter (relative steps of 1e-4):
    the adjoint gradient equals central differences to 1e-6 (drag, damping, one Newton iteration)."""
    loss, params = _body(per_spring=False, damping=True, drag=True, shape=(3, 3, 4), seed=1)
    integ = _implicit("adjoint", newton_iters=1, cg_tol=1e-15, cg_iters=300)
    _check_central_differences(loss, params, integ, 3)


def _check_central_differences(loss, params, integ, steps):
    """The gradient of ``loss(integ, steps)`` against central differences along a random direction
    of each parameter (relative steps of 1e-4), to 1e-6."""
    L = loss(integ, steps)
    grads = dict(zip(params, torch.autograd.grad(L, list(params.values()))))
    gen = torch.Generator().manual_seed(2)
    scales = {"k": 50.0, "c": 0.05, "m": 1e-3, "x0": 1e-3, "v0": 0.01}
    eps = 1e-4
    with torch.no_grad():
        for name, p in params.items():
            d = scales[name] * torch.randn(p.shape, generator=gen, dtype=F64)
            plus = loss(integ, steps, **{name: p + eps * d})
            minus = loss(integ, steps, **{name: p - eps * d})
            fd = float(plus - minus) / (2 * eps)
            ad = float((grads[name] * d).sum())
            assert abs(fd - ad) <= 1e-6 * abs(ad), (name, fd, ad)


def test_forward_is_the_same_to_the_bit():
    """Under no_grad, with nothing requiring grad, and with gradients: the adjoint's states are
    exactly the unrolled ones (newton_iters=2, a drag, damping)."""
    loss, params = _body(damping=True, drag=True)
    grid = td.Grid((4, 4, 5), spacing=0.01, topology=26)
    model = td.Model(
        grid,
        stiffness=50.0,
        damping=0.05,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom"),
        drags=[td.Drag(grid.face("top"), offset=(0.002, 0, 0), ramp=0.05)],
        dtype=F64,
    )
    x0 = params["x0"].detach()

    def run(gradient, no_grad):
        integ = td.ImplicitEuler(cg_iters=30, cg_tol=1e-8, newton_iters=2, gradient=gradient)
        s = td.State(x0, torch.zeros_like(x0))
        with torch.no_grad() if no_grad else torch.enable_grad():
            for _ in range(3):
                s = integ.step(model, s, 0.01)
        return s

    for no_grad in (True, False):
        a, b = run("unrolled", no_grad), run("adjoint", no_grad)
        assert not b.x.requires_grad
        assert torch.equal(a.x, b.x) and torch.equal(a.v, b.v)
    with torch.no_grad():
        assert torch.equal(loss(_implicit("unrolled", 2), 2), loss(_implicit("adjoint", 2), 2))
    assert torch.equal(loss(_implicit("unrolled", 2), 2).detach(), loss(_implicit("adjoint", 2), 2).detach())


class _Box:
    __slots__ = ("__weakref__", "t")

    def __init__(self, t):
        self.t = t


def _held_for_backward(fn):
    """Run ``fn()`` and return ``(result, bytes, storages)``: the distinct storages of all tensors
    autograd saved for the backward and still holds when ``fn`` returns (saved-tensor hooks;
    tensors saved by graph parts that were freed meanwhile are not counted)."""
    boxes = weakref.WeakSet()

    def pack(t):
        box = _Box(t)
        boxes.add(box)
        return box

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda box: box.t):
        out = fn()
    storages = {}
    for box in list(boxes):
        st = box.t.untyped_storage()
        storages[st.data_ptr()] = st.nbytes()
    return out, sum(storages.values()), len(storages)


def _rollout(gradient, steps, cg_iters, shape=(6, 6, 6), topology=6, **kw):
    grid = td.Grid(shape, spacing=0.01, topology=topology)
    k = torch.tensor(50.0, dtype=F64, requires_grad=True)
    c = torch.tensor(0.05, dtype=F64, requires_grad=True)
    model = td.Model(
        grid, stiffness=k, damping=c, density=1000.0, gravity=(-9.81, 0, 0), fixed=grid.face("bottom"), dtype=F64
    )
    with torch.no_grad():
        dt = 20 * td.time_step_bound(model, integrator="symplectic")
    integ = td.ImplicitEuler(cg_iters=cg_iters, cg_tol=0.0, gradient=gradient, **kw)

    def run():
        s = model.rest_state()
        for _ in range(steps):
            s = integ.step(model, s, dt)
        return (s.x * s.x).sum()

    return integ, (k, c), run


def test_adjoint_memory_does_not_grow_with_cg_iterations():
    """What autograd keeps with the adjoint is the same for 10 and 100 CG iterations per solve;
    the backward runs ``adjoint_iters`` iterations."""
    held = []
    for cg_iters in (10, 100):
        integ, params, run = _rollout("adjoint", 2, cg_iters, shape=(4, 4, 4), topology=26, adjoint_iters=7)
        L, nbytes, _ = _held_for_backward(run)
        held.append(nbytes)
        torch.autograd.grad(L, params)
        assert integ.last_cg[0] == cg_iters and integ.last_adjoint_cg[0] == 7
    assert held[0] == held[1]


@pytest.mark.slow
def test_adjoint_holds_five_times_less_for_the_backward():
    """Rollouts of 25 and 50 steps (6 x 6 x 6, 6 neighbours, float64), exactly 50 CG iterations
    per solve: the bytes of the tensors saved for the backward, in all and per step, are at least
    5 x fewer with the adjoint. Both grow linearly with the steps, so the ratio holds for
    200-step rollouts too. (Only the forwards run; what they hold
    is what the backward would need.)"""
    held = {}
    for gradient in ("unrolled", "adjoint"):
        for steps in (25, 50):
            integ, _, run = _rollout(gradient, steps, 50)
            _, held[gradient, steps], count = _held_for_backward(run)
            assert integ.last_cg[0] == 50
        per_step = (held[gradient, 50] - held[gradient, 25]) / 25
        held[gradient] = per_step
        print(
            f"{gradient}: {held[gradient, 50] / 2**20:.1f} MiB saved for the backward of 50 steps "
            f"({count} storages), {per_step / 2**20:.2f} MiB per step"
        )
    print(f"ratio {held['unrolled', 50] / held['adjoint', 50]:.1f}, per step {held['unrolled'] / held['adjoint']:.1f}")
    assert held["unrolled", 50] >= 5 * held["adjoint", 50]
    assert held["unrolled"] >= 5 * held["adjoint"] > 0


def test_backward_uses_the_operator_of_the_forward():
    """A cut that replaces ``model.stiffness`` between the step and the backward does not change
    the gradient (the backward rebuilds the operator from the model as it was)."""
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    grads = []
    for cut in (False, True):
        k = torch.tensor(50.0, dtype=F64, requires_grad=True)
        model = td.Model(grid, stiffness=k, mass=1e-3, gravity=(-9.81, 0, 0), fixed=grid.face("bottom"), dtype=F64)
        s = _implicit("adjoint").step(model, model.rest_state(), 0.01)
        if cut:
            model.stiffness = torch.zeros_like(model.stiffness)
        grads.append(torch.autograd.grad(s.x.sum(), k)[0])
    assert torch.equal(grads[0], grads[1]) and float(grads[0].abs()) > 0


def test_implicit_solve_of_a_dense_system():
    """adjoint_solve on a dense SPD matrix: the gradients w.r.t. the matrix and the right-hand
    side are -lambda u^T and lambda with lambda = A^-1 g (numpy-free dense oracle)."""
    gen = torch.Generator().manual_seed(3)
    R = torch.randn(6, 6, generator=gen, dtype=F64)
    A = (R @ R.T + 6 * torch.eye(6, dtype=F64)).requires_grad_()
    b = torch.randn(1, 6, generator=gen, dtype=F64, requires_grad=True)
    g = torch.randn(1, 6, generator=gen, dtype=F64)
    u, _iters, _rel = adjoint_solve(lambda u: u @ A, b, conjugate_gradient, iters=50, tol=1e-14)
    (u * g).sum().backward()
    lam = torch.linalg.solve(A.detach(), g[0])
    u_ref = torch.linalg.solve(A.detach(), b.detach()[0])
    assert torch.allclose(u.detach()[0], u_ref, rtol=1e-12, atol=0)
    assert torch.allclose(b.grad[0], lam, rtol=1e-10, atol=1e-14)
    # u @ A reads A_ij as row i, column j of A^T u: dL/dA_ij = -u_i lambda_j
    assert torch.allclose(A.grad, -torch.outer(u_ref, lam), rtol=1e-10, atol=1e-14)
    assert not ImplicitSolve.apply(b.detach() - b.detach(), u.detach(), None).requires_grad


# ---------------------------------------------------------------- projective dynamics
def _projective(solver, gradient, **kw):
    """Projective dynamics run to convergence (so unrolled and adjoint differentiate the same step)."""
    kw = {
        "iterations": 3000,
        "tol": 1e-14,
        "adjoint_iters": 5000,
        "adjoint_tol": 1e-14,
        **({"cg_iters": 200, "cg_tol": 1e-9} if solver == "cg" else {}),
        **kw,
    }
    return td.ProjectiveDynamics(solver=solver, gradient=gradient, **kw)


@pytest.mark.slow
def test_projective_adjoint_equals_unrolled_gradients():
    """Per-spring stiffness and damping (projected dashpots: a non-symmetric Jacobian), masses,
    x0, v0, a drag and home springs: converged steps at 20 x the explicit bound. The adjoint
    gradients of every global-step solver (cholesky, cg, jacobi) equal the unrolled gradient
    (through jacobi's iterations) to 1e-8; jacobi's forward values are the same to the bit.
    (cg, slow in eager code on a small body, takes one step, the others two.)"""
    loss, params = _body(per_spring=True, damping=True, drag=True, home=True)
    reference = {}
    for steps in (1, 2):
        unrolled = _projective("jacobi", "unrolled")
        L = loss(unrolled, steps)
        reference[steps] = L.detach(), torch.autograd.grad(L, list(params.values()))
        assert unrolled.last_adjoint is None
    for solver, steps in (("jacobi", 2), ("cholesky", 2), ("cg", 1)):
        integ = _projective(solver, "adjoint")
        La = loss(integ, steps)
        grads = torch.autograd.grad(La, list(params.values()))
        L, ref = reference[steps]
        print(f"\n{solver}: {integ.last_iterations} iterations forward, {integ.last_adjoint[0]} adjoint")
        assert integ.last_residual <= 1e-14 and integ.last_adjoint[1] <= 1e-14
        if solver == "jacobi":
            assert torch.equal(La.detach(), L)
        assert abs(float(La.detach() - L)) <= 1e-12 * abs(float(L))
        for name, gu, ga in zip(params, ref, grads):
            assert float(gu.norm()) > 0, name
            assert float((ga - gu).norm()) <= 1e-8 * float(gu.norm()), (solver, name)


def test_projective_cholesky_adjoint_equals_central_differences():
    """The cholesky solver's steps (no unrolled gradient: ``gradient="auto"`` takes the adjoint)
    against central differences along random directions of each parameter, to 1e-6."""
    loss, params = _body(per_spring=False, damping=True, drag=True, shape=(3, 3, 4), seed=1)
    integ = _projective("cholesky", "auto", tol=1e-12, adjoint_tol=1e-12)
    _check_central_differences(loss, params, integ, 2)
    assert integ.last_adjoint[1] <= 1e-12


def test_projective_adjoint_memory_does_not_grow_with_iterations():
    """What autograd keeps for a projective step with the adjoint is the same for 5 and 40
    iterations (one residual's graph); the unrolled gradient keeps about one per iteration."""
    held = {}
    for gradient in ("adjoint", "unrolled"):
        for iterations in (5, 40):
            grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
            k = torch.tensor(50.0, dtype=F64, requires_grad=True)
            model = td.Model(
                grid,
                stiffness=k,
                damping=0.05,
                density=1000.0,
                gravity=(-9.81, 0, 0),
                fixed=grid.face("bottom"),
                dtype=F64,
            )
            integ = td.ProjectiveDynamics(
                iterations=iterations, solver="jacobi", gradient=gradient, adjoint_iters=7, adjoint_tol=0.0
            )

            def run(model=model, integ=integ):
                s = model.rest_state()
                for _ in range(2):
                    s = integ.step(model, s, 0.02)
                return (s.x * s.x).sum()

            L, held[gradient, iterations], _ = _held_for_backward(run)
            torch.autograd.grad(L, k)
            assert integ.last_iterations == iterations
            assert integ.last_adjoint == ((7, integ.last_adjoint[1]) if gradient == "adjoint" else None)
    print(f"\nbytes held: {held}")
    assert held["adjoint", 5] == held["adjoint", 40]
    assert held["unrolled", 40] >= 5 * held["unrolled", 5] > 5 * held["adjoint", 5]


def test_projective_gradient_options():
    assert td.ProjectiveDynamics().gradient == "auto"
    for kw in ({"gradient": "adjont"}, {"adjoint_iters": 0}, {"adjoint_tol": -1.0}):
        with pytest.raises(td.ConfigError, match="projective"):
            td.ProjectiveDynamics(**kw)
    pd = td.ProjectiveDynamics()
    assert [pd.gradient_for(s) for s in ("cholesky", "cg", "jacobi")] == ["adjoint", "unrolled", "unrolled"]
    loss, _ = _body(shape=(3, 3, 3))
    with pytest.raises(td.ConfigError, match=r"projective\.gradient"):  # a cholesky solve has no unrolled gradient
        loss(td.ProjectiveDynamics(solver="cholesky", gradient="unrolled"), 1)
    with torch.no_grad():  # nothing to differentiate: fine
        loss(td.ProjectiveDynamics(solver="cholesky", gradient="unrolled"), 1)
