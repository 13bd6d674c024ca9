"""Integrators: pure functions of ``(model, state, dt, loads)`` that return a new ``State``.

=====================  ==========================================================  =====
class                  update                                                      order
=====================  ==========================================================  =====
ExplicitEuler          ``x' = x + h v``;  ``v' = v + h a(x, v)``                    1
SymplecticEuler        ``v' = v + h a(x, v)``;  ``x' = x + h v'``                  1
DampedVerlet           ``x' = x + (1 - kd)(x - x_prev) + h^2 a`` (Punak eq. 4-1)    1-2
RK4                    classic Runge-Kutta, 4 force evaluations                    4
ImplicitEuler          Baraff-Witkin linearised step, CG on stencil products,     1
                       optional Newton iterations
KnocheRelaxation       Knoche's first-order offset relaxation (his Cg shader)      -
=====================  ==========================================================  =====

``DampedVerlet`` keeps ``v = (x - x_prev) / h`` in the state, which makes eq. 4-1 read
``v' = (1 - kd) v + h a``, ``x' = x + h v'``.

Dragged nodes follow their path exactly (they are put on it after every step and before every
force evaluation); global drag (``model.decay``) is applied after the step as
``v <- v exp(-c h)``: exact for the drag alone, but after a symplectic or Verlet update it lowers
the stable step (to ``1/sqrt(2)`` of the undamped bound for a strong drag), which
:func:`~torchdeform.sim.stability.time_step_bound` accounts for. That splitting is first order,
so the higher-order methods (:class:`RK4`, :class:`~torchdeform.sim.adaptive.Adaptive`) take the
drag as the force ``-c m v`` inside their stages instead (:attr:`Integrator.drag_in_rates`,
:func:`rates`) and keep their order.

:data:`~torchdeform.sim.catalog.INTEGRATORS` maps each class's ``name`` (the ``[integrator] name``
of scene files) to the class, these and the adaptive and projective integrators.

Examples:
    >>> import torchdeform as td
    >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=1.0, mass=1e-3, gravity=(-9.81, 0, 0))
    >>> s = td.RK4().step(model, model.rest_state(), dt=1e-3)
    >>> round(float(s.v[0, 0].mean()), 5)                    # free fall: g dt
    -0.00981
"""

from __future__ import annotations

import contextlib
import copy
import math

import torch

from ..errors import ConfigError
from .adjoint import adjoint_solve
from .model import Model, State
from .springs import accumulate, gated_damping
from .stability import time_step_bound


def positive_dt(dt) -> float:
    """``dt`` as a float.

    Raises:
        ConfigError: unless ``dt`` is a positive, finite number of seconds.
    """
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise ConfigError("dt", "a positive number of seconds", got=dt) from None
    if not math.isfinite(dt) or dt <= 0:
        raise ConfigError("dt", "a positive, finite number of seconds", got=dt)
    return dt


class Integrator:
    """Base class of the integrators.

    Subclasses implement :meth:`advance`; :meth:`step` adds the checks, the constraints and the
    global drag.

    Examples:
        >>> import torchdeform as td
        >>> class Still(td.Integrator):                     # x and v unchanged by the update
        ...     name = "still"
        ...     def advance(self, model, state, dt, loads):
        ...         return state.x, state.v
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3, decay=100.0)
        >>> s = model.rest_state()
        >>> s.v += 1.0
        >>> s = Still().step(model, s, dt=0.01)              # step adds the clock and the global drag
        >>> s.t, round(float(s.v.mean()), 4)                 # v exp(-100 * 0.01)
        (0.01, 0.3679)
    """

    name = "base"

    def step(self, model: Model, state: State, dt: float, *, loads=None) -> State:
        """Advance ``state`` by ``dt`` seconds.

        Args:
            model: the :class:`~torchdeform.sim.model.Model`.
            state: positions and velocities ``(B, 3, D, H, W)``.
            dt: time step (s), > 0.
            loads: extra node forces ``(B|1, 3, D, H, W)`` or a callable ``t -> forces``.

        Returns:
            the new :class:`~torchdeform.sim.model.State` at ``t + dt``.
        """
        dt = positive_dt(dt)
        x, v = self.advance(model, state, dt, loads)
        return self.finish(model, state, x, v, dt)

    #: why the compiled fast path cannot run this integrator (it then runs eagerly), or None
    eager_reason: str | None = None

    #: True where :meth:`advance` integrates the global drag itself (:func:`rates`), so that
    #: :meth:`finish` does not apply it again
    drag_in_rates = False

    def finish(self, model: Model, state: State, x, v, dt: float) -> State:
        """End of a step: dragged nodes onto their path, interactions, then global drag.

        Interactions (tool contact, grasp, strain limits) see the time ``t + dt``; what they
        measure is the new state's ``readings`` (None without interactions). The global drag is
        left out where the integrator's stages included it (:attr:`drag_in_rates`).
        """
        state = self.respond(model, state, x, v, dt)
        return State(state.x, self.drag(model, state.v, dt), t=state.t, readings=state.readings)

    def respond(self, model: Model, state: State, x, v, dt: float) -> State:
        """The first part of :meth:`finish`: dragged nodes onto their path, then the interactions.

        Returns the state at ``t + dt`` before the global drag (:meth:`drag`); contact between
        bodies (:mod:`torchdeform.interact.bodies`) acts between the two.
        """
        t1 = state.t + dt
        if model.drags:
            x, v = model.constrain(x, v, t1)
        readings = {} if model.interactions else None
        for interaction in model.interactions:
            x, v = interaction.project(model, x, v, t1, dt, readings=readings)
        return State(x, v, t=t1, readings=readings or None)

    def drag(self, model: Model, v, dt: float):
        """The last part of :meth:`finish`: the global drag ``v exp(-c dt)`` (unless the stages had it)."""
        if model.decay is not None and not self.drag_in_rates:
            v = v * math.exp(-model.decay * dt)
        return v

    def advance(self, model, state, dt, loads):  # pragma: no cover
        """The update of one step: ``(x, v)`` at ``t + dt``, before constraints and global drag."""
        raise NotImplementedError


class ExplicitEuler(Integrator):
    """Forward Euler; unstable without damping for every dt (use it for comparisons).

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3, gravity=(-9.81, 0, 0))
        >>> s = td.ExplicitEuler().step(model, model.rest_state(), dt=1e-3)
        >>> float((s.x - model.X).abs().max()), round(float(s.v[0, 0].mean()), 5)   # x' = x + h v, v' = h g
        (0.0, -0.00981)
    """

    name = "explicit"

    def advance(self, model, state, dt, loads):
        """``x' = x + h v``, ``v' = v + h a(x, v)``."""
        a = model.acceleration(state.x, state.v, t=state.t, loads=loads)
        return state.x + dt * state.v, state.v + dt * a


class SymplecticEuler(Integrator):
    """Semi-implicit (symplectic) Euler: velocities first, then positions with the new velocity.

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3, gravity=(-9.81, 0, 0))
        >>> s = td.SymplecticEuler().step(model, model.rest_state(), dt=1e-3)
        >>> round(float((s.x - model.X)[0, 0].mean()), 8)        # x' = x + h v' = h^2 g
        -9.81e-06
    """

    name = "symplectic"

    def advance(self, model, state, dt, loads):
        """``v' = v + h a(x, v)``, ``x' = x + h v'``."""
        v = state.v + dt * model.acceleration(state.x, state.v, t=state.t, loads=loads)
        return state.x + dt * v, v


class DampedVerlet(Integrator):
    """Punak's damped Verlet (eq. 4-1): ``x' = x + (1 - kd)(x - x_prev) + h^2 F / m``.

    Args:
        kd: dimensionless per-step damping in ``[0, 1)``; roughly a viscous ``c = kd m / h``.

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3)
        >>> s = model.rest_state()
        >>> s.v += 1.0                                           # a rigid translation: no spring force
        >>> s = td.DampedVerlet(kd=0.1).step(model, s, dt=1e-3)
        >>> round(float(s.v.mean()), 6)                          # v' = (1 - kd) v + h a
        0.9
    """

    name = "verlet"

    def __init__(self, *, kd: float = 0.0):
        if not 0 <= kd < 1:
            raise ConfigError("verlet.kd", "a number in [0, 1)", got=kd)
        self.kd = float(kd)

    def advance(self, model, state, dt, loads):
        """``v' = (1 - kd) v + h a(x, v)``, ``x' = x + h v'``."""
        v = (1 - self.kd) * state.v + dt * model.acceleration(state.x, state.v, t=state.t, loads=loads)
        return state.x + dt * v, v


def just_before(t1):
    """A time a hair before ``t1`` (a float or a 0-d tensor), where a step ending at ``t1`` reads drags.

    See :func:`stage_time`.
    """
    return t1 - 1e-12 * (1.0 + abs(t1))


def stage_time(t0, h, c):
    """The time of a Runge-Kutta stage at ``t0 + c h``, seen from inside the step.

    A drag's velocity at a waypoint is that of the segment that starts there, and a step's clock
    drifts from the waypoint by rounding (after many steps ``t0`` is a hair below or above it). So
    the first stage (``c = 0``) reads drags a hair after ``t0`` and the last (``c = 1``) a hair
    before ``t0 + h``: every stage sees the path segment of its own step, and a kink on a step
    boundary costs no order of accuracy.
    """
    if c == 0:
        return t0 + 1e-12 * (1.0 + abs(t0))
    if c == 1:
        return just_before(t0 + h)
    return t0 + c * h


def rates(model: Model, *, loads=None):
    """The state's time derivative as a function ``f(t, x, v) -> (dx/dt, dv/dt) = (v, a)``.

    Dragged nodes are put on their path at time ``t`` first (Runge-Kutta stages of :class:`RK4`
    and :mod:`torchdeform.sim.adaptive`). The global drag is part of ``a`` (``-c v`` at free
    nodes), so the stages integrate it to their own order.
    """

    def f(t, x, v):
        if model.drags:
            x, v = model.constrain(x, v, t)
        a = model.acceleration(x, v, t=t, loads=loads)
        if model.decay is not None:
            drag = model.decay * v
            a = a - (drag if model.free is None else model.free * drag)
        return v, a

    return f


class RK4(Integrator):
    """Classic fourth-order Runge-Kutta on ``(x, v)``.

    Dragged nodes are put on their path at every stage time.

    Examples:
        >>> import math
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)     # two nodes, one spring along W
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                   # omega = sqrt(k / m) = 1 rad/s
        >>> s = model.rest_state()
        >>> s.x[0, 2, 0, 0, 1] += 0.1                               # stretch the spring by 0.1 m
        >>> for _ in range(10):
        ...     s = td.RK4().step(model, s, dt=0.1)
        >>> round(float(s.x[0, 2, 0, 0, 1]) - 1.0, 6), round(0.1 * math.cos(s.t), 6)
        (0.05403, 0.05403)
    """

    name = "rk4"
    drag_in_rates = True

    def advance(self, model, state, dt, loads):
        """Four force evaluations at ``t``, ``t + h/2`` (twice) and ``t + h``."""
        t0, x0, v0 = state.t, state.x, state.v
        f = rates(model, loads=loads)
        k1x, k1v = f(stage_time(t0, dt, 0), x0, v0)
        k2x, k2v = f(t0 + dt / 2, x0 + dt / 2 * k1x, v0 + dt / 2 * k1v)
        k3x, k3v = f(t0 + dt / 2, x0 + dt / 2 * k2x, v0 + dt / 2 * k2v)
        k4x, k4v = f(stage_time(t0, dt, 1), x0 + dt * k3x, v0 + dt * k3v)
        return (x0 + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x), v0 + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))


def _dot(a, b):
    """Per-batch-entry inner product, shaped to broadcast against ``a`` (:meth:`Model.inner`)."""
    return (a * b).sum(tuple(range(1, a.dim())), keepdim=True)


def cg_start(b, *, precond=None, mask=None, dot=_dot):
    """Initial conjugate-gradient state ``(u, r, p, rz)`` for ``A u = b``.

    See :func:`conjugate_gradient`; ``u = 0``, ``r`` the filtered ``b``.
    """
    r = b if mask is None else b * mask
    z = r if precond is None else precond * r
    return torch.zeros_like(r), r, z, dot(r, z)


def cg_iteration(apply_A, u, r, p, rz, *, precond=None, mask=None, dot=_dot):
    """One preconditioned conjugate-gradient iteration: ``(u, r, p, rz) -> (u, r, p, rz)``.

    Guarded so that an exactly solved system (``p^T A p = 0`` or ``r^T z = 0``) stays put
    instead of dividing by zero.
    """
    Ap = apply_A(p)
    if mask is not None:
        Ap = Ap * mask
    pAp = dot(p, Ap)
    alpha = torch.where(pAp > 0, rz / torch.where(pAp > 0, pAp, 1.0), 0.0)
    u = u + alpha * p
    r = r - alpha * Ap
    z = r if precond is None else precond * r
    rz_new = dot(r, z)
    p = z + torch.where(rz > 0, rz_new / torch.where(rz > 0, rz, 1.0), 0.0) * p
    return u, r, p, rz_new


def conjugate_gradient(apply_A, b, *, precond=None, mask=None, iters: int = 100, tol: float = 1e-8, dot=None):
    """Solve ``A u = b`` for symmetric positive definite ``A`` given as a function.

    Batched over the leading dimension; entries where ``mask`` is 0 are held at 0 (Baraff-Witkin
    filtering of constrained nodes).

    Args:
        apply_A: ``u -> A u`` on node fields (``(B, 3, D, H, W)`` or packed ``(B, 3, P)``).
        b: right-hand side, same shape.
        precond: diagonal preconditioner (multiplies the residual), broadcastable, or None.
        mask: broadcastable 0/1 filter or None.
        iters: maximum iterations.
        tol: stop when ``|r| <= tol |b|`` for every batch entry. ``tol <= 0`` runs exactly
            ``iters`` iterations without reading the residual on the host (no synchronisation).
        dot: the inner product ``(a, b) -> (B, 1, ...)`` of the iterations and the residual norms
            (a model's :meth:`~torchdeform.sim.model.Model.inner`; a domain-decomposed model sums
            over ranks), or None for the plain per-entry sum.

    Returns:
        ``(u, iterations used, relative residual)`` (the residual is a 0-d tensor when ``tol <= 0``).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> b = torch.ones(1, 3, 2, 2, 2, dtype=torch.float64)
        >>> u, iters, rel = td.conjugate_gradient(lambda u: 4.0 * u, b)        # A = 4 I
        >>> float(u.mean()), iters, rel <= 1e-8
        (0.25, 1, True)
        >>> mask = torch.ones(1, 1, 2, 2, 2, dtype=torch.float64)
        >>> mask[..., 0, 0, 0] = 0                                            # a constrained node
        >>> u, _, _ = td.conjugate_gradient(lambda u: 4.0 * u, b, mask=mask)
        >>> float(u[..., 0, 0, 0].abs().max()), float(u[..., 1, 1, 1].min())
        (0.0, 0.25)
    """
    if dot is None:
        dot, norm = _dot, (lambda r: r.detach().flatten(1).norm(dim=1))
    else:

        def norm(r):
            r = r.detach()
            return dot(r, r).flatten(1)[:, 0].sqrt()

    u, r, p, rz = cg_start(b, precond=precond, mask=mask, dot=dot)
    bnorm = norm(r).clamp_min(1e-300)
    for it in range(1, iters + 1):
        u, r, p, rz = cg_iteration(apply_A, u, r, p, rz, precond=precond, mask=mask, dot=dot)
        if tol > 0:
            rel = float((norm(r) / bnorm).max())
            if rel <= tol:
                return u, it, rel
    rel = (norm(r) / bnorm).max()
    return u, iters, (float(rel) if tol > 0 else rel)


def inverse_diagonal(model, h: float) -> torch.Tensor:
    """``1 / (m + h^2 (sum_j k_ij + k_home) + h sum_j c_ij)`` per node, ``(Bp, 1, D, H, W)`` (packed ``(Bp, 1, P)``).

    The Jacobi preconditioner of implicit Euler's ``M + h C + h^2 K`` (``K``'s diagonal bounded by
    the spring sums) and the exact inverse diagonal of projective dynamics' ``M + h^2 L + h L_c``;
    zero on empty rows (nodes outside a node mask, the packed halo). A removed spring's damping
    does not count (:func:`~torchdeform.sim.springs.gated_damping`).
    """
    diag = model.mass + h * h * model.spring_sums(model.stiffness)
    if model.k_home is not None:
        diag = diag + h * h * model.k_home
    volume = model.volume_diagonal()
    if volume is not None:
        diag = diag + h * h * volume
    c = gated_damping(model.damping, model.stiffness)
    if c is not None:
        diag = diag + h * model.spring_sums(c)
    ok = diag > 0
    return torch.where(ok, 1.0 / torch.where(ok, diag, torch.ones_like(diag)), torch.zeros_like(diag))


class ImplicitEuler(Integrator):
    """Implicit (backward) Euler, Baraff-Witkin style, matrix-free.

    The first iteration is Baraff and Witkin's linearised step
    ``(M - h dF/dv - h^2 dF/dx) dv = h (F0 + h dF/dx v0)``; each of ``newton_iters`` further
    iterations re-linearises at ``x0 + h v`` and solves
    ``(M - h dF/dv - h^2 dF/dx) delta = h F(x0 + h v, v) - M (v - v0)``. The systems are solved by
    Jacobi-preconditioned conjugate gradients on the spring stencil's stiffness products; the
    compressive term is clamped in the matrix so it stays positive definite.

    Args:
        cg_iters: maximum CG iterations per solve.
        cg_tol: relative residual to stop at (``0``: always exactly ``cg_iters``, as SOFA's
            fixed-count benchmarks and compiled code do).
        newton_iters: extra Newton iterations (0 = one linearised step).
        gradient: how autograd differentiates the solves: ``"unrolled"`` (through every CG
            iteration; memory grows with ``cg_iters``) or ``"adjoint"`` (implicit function
            theorem, :mod:`~torchdeform.sim.adjoint`: the forward CG runs without a graph, the
            backward solves ``A lambda = dL/du`` with CG; memory of one operator product per
            solve, exact when both solves converge). The forward values are the same to the bit.
        adjoint_iters: maximum CG iterations of each backward solve (default ``cg_iters``).
        adjoint_tol: relative residual of each backward solve (default ``cg_tol``).

    Attributes:
        last_cg: ``(iterations, relative residual)`` of the last solve (the residual is a 0-d
            tensor when ``cg_tol = 0``).
        last_adjoint_cg: the same for the last backward solve (``gradient="adjoint"``), or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)     # two nodes, one spring along W
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                   # explicit bound: dt < 2 s
        >>> s = model.rest_state()
        >>> s.x[0, 2, 0, 0, 1] += 0.1
        >>> implicit = td.ImplicitEuler(cg_tol=1e-10)
        >>> s = implicit.step(model, s, dt=100.0)                   # stable far beyond the bound
        >>> abs(float(s.x[0, 2, 0, 0, 1]) - 1.0) < 1e-3, implicit.last_cg[0]
        (True, 1)

        Adjoint gradients (one operator product kept per solve, whatever ``cg_iters``):

        >>> k = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
        >>> model = td.Model(grid, stiffness=k, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)
        >>> s = model.rest_state()
        >>> s.x[0, 2, 0, 0, 1] += 0.1
        >>> adjoint = td.ImplicitEuler(cg_tol=1e-12, gradient="adjoint")
        >>> s = adjoint.step(model, s, dt=1.0)              # x' = 1 + 0.1 / (1 + k) (linear here)
        >>> s.x[0, 2, 0, 0, 1].backward()                   # dx'/dk = -0.1 / (1 + k)^2
        >>> round(float(k.grad), 12), adjoint.last_adjoint_cg[0]
        (-0.025, 1)
    """

    name = "implicit"
    #: the values of ``gradient``
    GRADIENTS = ("unrolled", "adjoint")

    def __init__(
        self,
        *,
        cg_iters: int = 100,
        cg_tol: float = 1e-6,
        newton_iters: int = 0,
        gradient: str = "unrolled",
        adjoint_iters: int | None = None,
        adjoint_tol: float | None = None,
    ):
        self.cg_iters, self.cg_tol, self.newton_iters = int(cg_iters), float(cg_tol), int(newton_iters)
        if gradient not in self.GRADIENTS:
            raise ConfigError("implicit.gradient", '"unrolled" or "adjoint"', got=gradient)
        if adjoint_iters is not None and (
            isinstance(adjoint_iters, bool) or not isinstance(adjoint_iters, int) or adjoint_iters < 1
        ):
            raise ConfigError("implicit.adjoint_iters", "a whole number >= 1", got=adjoint_iters)
        if adjoint_tol is not None and not (isinstance(adjoint_tol, (int, float)) and 0 <= adjoint_tol < math.inf):
            raise ConfigError("implicit.adjoint_tol", "a number >= 0", got=adjoint_tol)
        self.gradient, self.adjoint_iters = gradient, adjoint_iters
        self.adjoint_tol = None if adjoint_tol is None else float(adjoint_tol)
        self.last_cg = (0, 0.0)
        self.last_adjoint_cg = None

    def preconditioner(self, model, h: float) -> torch.Tensor:
        """Jacobi preconditioner ``1 / diag(M + h C + h^2 K)`` (:func:`inverse_diagonal`)."""
        return inverse_diagonal(model, h)

    def operator(self, model, x_lin, h: float):
        """``(linearisation, apply_A)`` with ``A u = M u + h C u + h^2 K(x_lin) u``.

        ``x_lin`` is a position field, a linearisation already made, or the combined operator of
        an earlier call (``apply_A.op``: ``h^2 K + h C`` with its coefficients merged once per
        solve, so CG products skip the scaling); ``apply_A.lin`` is the linearisation.
        """
        lin = model.linearise(x_lin) if torch.is_tensor(x_lin) else x_lin
        op = (
            lin
            if lin.combined
            else lin.scaled(alpha_scale=h * h, c=model.damping, projected=model.projected, c_scale=h)
        )

        def apply_A(u):
            y = model.mass * u + op.apply(u)
            return y if model.k_home is None else y + (h * h) * model.k_home * u

        apply_A.lin, apply_A.op = lin, op
        return lin, apply_A

    def system(self, model, state, v, it: int, h: float, loads):
        """The linear system of Newton iteration ``it`` from ``state`` with current velocity ``v``.

        Returns:
            ``(x_lin, apply_A, rhs, delta_c)``: the linearisation point, the operator, the
            right-hand side and the prescribed velocity change of dragged nodes (or None); the
            new velocity is ``v + solution + delta_c``.
        """
        x0, v0, t1 = state.x, state.v, state.t + h
        x_lin = x0 if it == 0 else x0 + h * v
        lin, apply_A = self.operator(model, x_lin, h)
        F = model.forces(x_lin, v, t=t1, loads=loads)
        if it == 0:
            k_v = lin.apply(v0) + (0 if model.k_home is None else model.k_home * v0)
            rhs = h * (F - h * k_v)
        else:
            rhs = h * F - model.mass * (v - v0)
        delta_c = None
        if model.drags:  # prescribed velocities of dragged nodes over the step
            _, v_target = model.constrain(x0, v0, just_before(t1))
            delta_c = torch.where(model.constrained[None, None], v_target - v, torch.zeros_like(v))
            rhs = rhs - apply_A(delta_c)
        return x_lin, apply_A, rhs, delta_c

    def advance(self, model, state, dt, loads):
        """``1 + newton_iters`` linear solves for the new velocity; ``x' = x + h v'``."""
        adjoint = self.gradient == "adjoint" and torch.is_grad_enabled()
        with torch.no_grad() if adjoint else contextlib.nullcontext():
            precond = self.preconditioner(model, dt)
        v = state.v
        for it in range(1 + self.newton_iters):
            x_lin, apply_A, rhs, delta_c = self.system(model, state, v, it, dt, loads)
            if adjoint:  # (the state's x is the caller's: the backward keeps a copy)
                x_keep = x_lin.detach().clone() if x_lin is state.x else x_lin
                delta, n_it, rel = self._adjoint_solve(model, x_keep, apply_A, rhs, precond, dt)
            else:
                delta, n_it, rel = conjugate_gradient(
                    apply_A,
                    rhs,
                    precond=precond,
                    mask=model.free,
                    iters=self.cg_iters,
                    tol=self.cg_tol,
                    dot=model.inner,
                )
            self.last_cg = (n_it, rel)
            v = v + delta if delta_c is None else v + delta + delta_c
        return state.x + dt * v, v

    def _adjoint_solve(self, model, x_lin, apply_A, rhs, precond, h):
        """One solve with the adjoint gradient (:func:`~torchdeform.sim.adjoint.adjoint_solve`).

        The backward rebuilds the operator from ``x_lin`` and the model's tensors as they are
        now (a shallow copy: a later cut that replaces ``model.stiffness`` does not change it).
        """
        frozen = copy.copy(model)

        def operator(x_lin, precond):
            return self.operator(frozen, x_lin, h)[1], precond

        def record(n_it, rel):
            self.last_adjoint_cg = (n_it, rel)

        return adjoint_solve(
            apply_A,
            rhs,
            conjugate_gradient,
            precond=precond,
            mask=model.free,
            iters=self.cg_iters,
            tol=self.cg_tol,
            adjoint_iters=self.adjoint_iters,
            adjoint_tol=self.adjoint_tol,
            adjoint_operator=operator,
            saved=(x_lin, precond),
            on_backward=record,
        )


class KnocheRelaxation(Integrator):
    """Knoche's first-order offset relaxation (2008, Code Example 2), reproduced exactly.

    Offsets ``u = x - X``; per node a material value ``w`` in ``[0, 1]``. A node with
    ``w > 1 - eps`` is fixed; every other node moves by ``gain (1 - w_c) F`` with
    ``F = sum_k (u_k - u_c) s(w_k) (w_k + w_c) / 2`` over its 6 face neighbours, ``s = 0.5`` for a
    neighbour with ``w < eps`` and 1 otherwise; neighbours outside the grid are ghosts with
    ``u = 0``, ``w = 0``. Updates are Jacobi (all nodes from the previous offsets).

    ``dt`` only advances the clock: one step is one shader pass. Velocities stay zero.

    Args:
        material: ``w``, a number or ``(D, H, W)``.
        eps: threshold of "fixed" and "free" (Knoche does not state it; default 1e-3).
        gain: step factor, default ``3 / n`` with ``n = D`` (the shader's ``3.0 / dim``).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((4, 4, 4), spacing=0.01, topology=6), stiffness=1.0, mass=1.0,
        ...                  dtype=torch.float64)
        >>> s = model.rest_state()
        >>> s.x[0, 0, 2, 2, 2] += 0.001                            # a 1 mm bump at one node
        >>> s = td.KnocheRelaxation(material=0.8).step(model, s, dt=1.0)
        >>> u = s.x - model.X           # u' = u + gain (1 - w) F, F = -6 w u at the bump: 28% left
        >>> round(float(u[0, 0, 2, 2, 2]), 7), round(float(u[0, 0, 1, 2, 2]), 7), bool((s.v == 0).all())
        (0.00028, 0.00012, True)
    """

    name = "knoche"
    eager_reason = "Knoche's relaxation runs in the eager step"

    def __init__(self, material, *, eps: float = 1e-3, gain: float | None = None):
        self.material, self.eps, self.gain = material, float(eps), gain

    def advance(self, model, state, dt, loads):
        """One Jacobi pass of the offsets; velocities are zero."""
        grid = model.grid
        if grid.topology != 6:
            raise ConfigError("integrator", "a 6-neighbour grid for Knoche relaxation", got=grid.topology)
        w = torch.as_tensor(self.material, dtype=model.dtype, device=model.device)
        w = w.expand(grid.shape).reshape(1, 1, *grid.shape)
        eps = self.eps
        gain = 3.0 / grid.shape[0] if self.gain is None else self.gain
        half = torch.where(w < eps, 0.5, 1.0)
        u = state.x - model.X

        # asymmetric edge weights: node i sees s(w_j)(w_i+w_j)/2, node j sees s(w_i)(w_i+w_j)/2
        def edge(s, src, du, dw, dhalf):
            wi = w[(..., *src)]
            mean = wi + 0.5 * dw
            s_i = half[(..., *src)]
            s_j = s_i + dhalf
            return s_j * mean * du, -s_i * mean * du

        F = accumulate(grid, edge, u, w, half, channels=3)
        ghosts = grid.missing_neighbours(device=model.device).to(model.dtype)[None, None]
        F = F - ghosts * 0.5 * (0.5 * w) * u
        moving = (w <= 1 - eps).to(model.dtype)
        if model.free is not None:
            moving = moving * model.free
        u = u + gain * (1 - w) * moving * F
        return model.X + u, torch.zeros_like(state.v)


__all__ = [
    "Integrator",
    "rates",
    "ExplicitEuler",
    "SymplecticEuler",
    "DampedVerlet",
    "RK4",
    "ImplicitEuler",
    "KnocheRelaxation",
    "conjugate_gradient",
    "cg_start",
    "cg_iteration",
    "just_before",
    "stage_time",
    "inverse_diagonal",
    "time_step_bound",
    "positive_dt",
]
