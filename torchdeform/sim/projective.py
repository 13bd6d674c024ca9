"""Projective dynamics (Liu, Bargteil, O'Brien and Kavan 2013): implicit Euler with a constant matrix.

Implicit (backward) Euler of a mass-spring body is the minimisation of

    g(x) = 1/(2 h^2) (x - y)^T M (x - y) + E(x),      y = x_n + h v_n + h^2 M^-1 f_ext

over the new positions ``x`` (``v = (x - x_n) / h``). Liu et al. write each spring's energy
``k/2 |x_j - x_i|^2 - ...`` with an auxiliary direction ``d = l0 (x_j - x_i) / |x_j - x_i|``
(the *local step*, one projection per spring) and minimise over ``x`` with the directions held
(the *global step*): ``(M + h^2 L) x = h^2 J d + M y``, where ``L`` is the graph Laplacian of the
spring stiffnesses, the same for the three channels and for every step. Since for Hooke springs
``J d(x) - L x`` is exactly the spring force ``F_s(x)``, one local/global iteration is

    x  <-  x + A^-1 r(x),      r(x) = M (x_n + h v_n - x) + h^2 F(x, (x - x_n) / h, t + h)     (*)

with ``A = M + h^2 L`` and ``F`` every force of the model (:meth:`~torchdeform.sim.model.Model.forces`:
springs, home springs, gravity, loads). This module iterates (*) in that residual form: the
same iterates as the local/global form, written with the model's own force code, so the packed
model of the compiled fast path runs it unchanged. ``r(x) = 0`` is the implicit-Euler equation, so
the iterates converge to the implicit-Euler step (:class:`~torchdeform.sim.integrators.ImplicitEuler`
with Newton iterations) as their number grows; a few iterations give a stable, more damped step.

**The matrix** ``A`` (one scalar ``N x N`` matrix shared by the three channels; ``L (x) I_3``):

    A = M + h^2 (L_k + K_home) + h L_c

``L_k`` the Laplacian of the stiffnesses (per spring ``k`` on the diagonal at both ends, ``-k``
off it); ``K_home`` the diagonal of the home and anchor springs (zero-length springs, quadratic);
``L_c`` the Laplacian of the damping coefficients. Rows and columns of constrained nodes
(``model.free == 0``: fixed, dragged, outside the node mask) are removed: those nodes do not
move in the solve. A spring to a constrained node keeps its diagonal term.

**Damping.** Unprojected damping (``damping_mode="unprojected"``, force ``-c (v_i - v_j)``) is
linear in ``v = (x - x_n) / h``: ``h L_c`` in ``A`` and the force in ``r`` make it exact.
Projected dashpots (``-c ((v_i - v_j) . n) n``, the default mode) are not a quadratic energy:
they are evaluated in ``r`` with the current iterate's velocity, and ``A`` keeps the unprojected
``h L_c``, an upper bound of their Jacobian ``h sum c n n^T``. The fixed point is still the
implicit-Euler step with projected dashpots (tested against Newton's solution); the bound keeps
the iteration from overshooting. Contact forces of interactions are treated the same way
(explicitly in ``r``, not in ``A``). Global drag (``decay``) is applied by
:meth:`~torchdeform.sim.integrators.Integrator.finish`.

**Constrained nodes.** Fixed nodes stay at ``x_n + h v_n`` (as in every integrator: a fixed
node normally has ``v = 0``); dragged nodes are put on their path at ``t + h`` before the first
iteration, so the free nodes see them where they will be, and ``finish`` sets their path velocity.

**Global-step solvers** (``solver=``):

===========  ===================================================================================
cholesky     ``A`` assembled once per (model, dt) as a scipy sparse matrix and factored with
             cholespy (CHOLMOD; CPU, and CUDA for CUDA models); one solve with ``3 B`` right-hand
             sides per iteration. The factor is cached on the integrator and made again when the
             model, ``dt`` or the shapes or in-place versions of its fields change (a cut then
             costs a new factorisation). Needs ``pip install cholespy``.
cg           matrix-free Jacobi-preconditioned conjugate gradients on the spring stencil (a product
             with ``L`` is the linearisation of springs of rest length zero), warm-started at the
             previous iterate (``(*)`` solves for the change, from zero). Reads the stiffness every
             step: the solver for topology changes (cuts zero stiffness per spring).
jacobi       one Jacobi sweep ``x <- x + gamma D^-1 r(x)`` per iteration, ``D = M + h^2 diag(L_k +
             K_home) + h diag(L_c)``, with Chebyshev acceleration (Wang 2015, "A Chebyshev
             semi-iterative approach for accelerating projective and position-based dynamics"):
             ``x_{k+1} = w_{k+1} (x~_{k+1} - x_{k-1}) + x_{k-1}``, ``x~`` the relaxed sweep,
             ``w = 1`` for the first ``delay`` iterations, then ``2 / (2 - rho^2)``, then
             ``4 / (4 - rho^2 w)``. Plain tensor code with ``model.forces``, ``model.spring_sums``
             and ``model.mass``: runs on the packed model of :func:`~torchdeform.sim.compiled.compiled_step`
             (with ``tol = 0``) and with any spring law.
===========  ===================================================================================

``rho`` is the spectral radius of the (relaxed) Jacobi iteration that the Chebyshev weights
assume. Too small a value loses the acceleration, too large (close to 1) makes the weights
approach 2 and the iteration oscillate. Measured on a 5 x 4 x 4 body (26 neighbours, stretched,
float64), error against Newton's implicit Euler: at 3x the explicit bound 0.95 converged fastest
of ``0.9, 0.95, 0.99``; at 10x-100x, 0.99 was better after 20 or more iterations (the same after
10), but at 1e8 N/m its energy grew and with a stiffening law it diverged. The default is 0.95
(weights up to 1.52), with ``relaxation = 0.9`` (Wang's under-relaxation ``gamma``) and
``delay = 1``: Wang waits longer before accelerating, but a frame here has about 10 iterations.

Spring laws (``model.law``): their energy is not quadratic in the spring length, so ``A`` is no
bound of their Hessian and the constant-matrix solvers may not converge: ``cholesky`` and ``cg``
raise a :class:`~torchdeform.errors.ConfigError`; ``jacobi`` runs (its ``D`` uses the small-strain
stiffness; a strongly stiffening law may need more iterations or a smaller step).

**Gradients** (``gradient=``). ``"unrolled"``: autograd through every iteration (and every CG
iteration of the cg solver); its memory grows with ``iterations``, and it is the gradient of the
iterates actually computed. ``"adjoint"``: the implicit function theorem at the converged step
(DiffPD, Du et al. 2021, does the same): the forward iterates without a graph, and the backward
solves ``J^T lambda = g`` with ``J = -dr/dx`` at the step's result, by the forward's own
iteration run on the transposed system, ``lambda <- lambda + S (g - J^T lambda)`` (``S`` the
global-step solve or the Jacobi sweep; the products ``J^T lambda`` by autograd of ``r``, so
projected dashpots, laws and loads are exact). It converges as the forward does and keeps one
residual's graph per step, whatever ``iterations``. It is the gradient of the *converged* step:
it equals the unrolled gradient when the forward runs to convergence (``tol``), and is the
better gradient of implicit Euler when it does not. The cholesky solves have no unrolled
gradient (cholespy is not differentiable): ``"auto"`` (the default) takes the adjoint there.
In compiled code the step is unrolled.

Shapes: positions and velocities ``(B, 3, D, H, W)`` (packed ``(B, 3, P)`` on the fast path).
"""

from __future__ import annotations

import copy
import math

import torch

from ..errors import ConfigError
from .adjoint import ImplicitSolve
from .integrators import Integrator, conjugate_gradient, inverse_diagonal
from .springs import gated_damping

__all__ = ["ProjectiveDynamics", "SOLVERS", "GRADIENTS", "CHOLESKY_NODES"]

#: the global-step solvers, by name
SOLVERS = ("auto", "cholesky", "cg", "jacobi")
#: the values of ``gradient``
GRADIENTS = ("auto", "unrolled", "adjoint")
#: ``solver="auto"`` factors bodies up to this many free nodes (about 32^3): the factor of a 3-D
#: 27-point stencil fills in like ``N^(4/3)``: at 64^3 (262,144 nodes) it took 274 s and 2.9 GB.
CHOLESKY_NODES = 32768


def _number(value, key: str, expected: str, ok) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, expected, got=value) from None
    if not math.isfinite(v) or not ok(v):
        raise ConfigError(key, expected, got=value)
    return v


def _count(value, key: str, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(key, f"a whole number >= {least}", got=value)
    return value


def _is_packed(model) -> bool:
    """True for the packed model of the compiled fast path (:class:`~torchdeform.sim.packed.PackedModel`)."""
    return hasattr(model, "source") and hasattr(model, "unpack_state")


class ProjectiveDynamics(Integrator):
    """Projective dynamics: implicit Euler by local/global iterations with a constant matrix.

    See the module docstring for the equations, the damping and the constrained nodes.

    Args:
        iterations: local/global iterations per step (the most, with ``tol``), >= 1.
        tol: stop when the relative change of an iteration, ``|x_{k+1} - x_k| / |x_{k+1} - x_n|``
            over the free nodes (largest over the batch), is ``<= tol``; 0 (default) runs exactly
            ``iterations`` without reading values on the host (what compiled code needs).
        solver: ``"cholesky"`` (a pre-factored sparse Cholesky, exact global steps),
            ``"cg"`` (matrix-free conjugate gradients: topology changes), ``"jacobi"``
            (Chebyshev-accelerated Jacobi: the compiled fast path, large grids, spring laws) or
            ``"auto"`` (default, :meth:`solver_for`: cholesky for bodies up to
            :data:`CHOLESKY_NODES` free nodes when cholespy is installed, else jacobi).
        rho: spectral-radius estimate of the Jacobi iteration for the Chebyshev weights, in
            ``[0, 1)`` (jacobi only; 0: no acceleration).
        relaxation: under-relaxation ``gamma`` of each Jacobi sweep, in ``(0, 1]`` (jacobi only).
        delay: plain (relaxed) Jacobi iterations before the Chebyshev weights start (jacobi only).
        cg_iters: maximum CG iterations per global step (cg only).
        cg_tol: relative residual at which a global CG solve stops (cg only; 0: always ``cg_iters``).
        gradient: how autograd differentiates a step (see "Gradients" in the module docstring):
            ``"unrolled"`` (through every iteration), ``"adjoint"`` (implicit function theorem at
            the converged step: memory independent of ``iterations``) or ``"auto"`` (default:
            adjoint for the cholesky solver, whose solves have no unrolled gradient, else unrolled).
        adjoint_iters: the most adjoint iterations per step (backward), >= 1.
        adjoint_tol: the adjoint iteration stops at this relative change (0: always ``adjoint_iters``).

    Attributes:
        last_iterations: iterations done in the last step.
        last_residual: relative change of the last iteration (see ``tol``); a 0-d tensor when
            ``tol = 0``, a float otherwise.
        last_cg: ``(iterations, relative residual)`` of the last CG solve (cg only).
        last_adjoint: ``(iterations, relative change)`` of the last adjoint solve (backward), or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.sim.projective import ProjectiveDynamics
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)     # two nodes, one spring along W
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                   # explicit bound: dt < 2 s
        >>> s = model.rest_state()
        >>> s.x[0, 2, 0, 0, 1] += 0.1                               # stretch the spring by 0.1 m
        >>> pd = ProjectiveDynamics(iterations=200, tol=1e-12, solver="jacobi")
        >>> s1 = pd.step(model, s, dt=1.0)            # implicit Euler: x' = (x + h v + h^2 k l0) / (1 + h^2 k)
        >>> round(float(s1.x[0, 2, 0, 0, 1]) - 1.0, 9), round(float(s1.v[0, 2, 0, 0, 1]), 9)
        (0.05, -0.05)
        >>> s2 = pd.step(model, s, dt=100.0)                        # stable far beyond the bound
        >>> abs(float(s2.x[0, 2, 0, 0, 1]) - 1.0) < 1e-4, pd.last_iterations < 200
        (True, True)
    """

    name = "projective"

    def __init__(
        self,
        *,
        iterations: int = 10,
        tol: float = 0.0,
        solver: str = "auto",
        rho: float = 0.95,
        relaxation: float = 0.9,
        delay: int = 1,
        cg_iters: int = 50,
        cg_tol: float = 1e-6,
        gradient: str = "auto",
        adjoint_iters: int = 500,
        adjoint_tol: float = 1e-10,
    ):
        self.iterations = _count(iterations, "projective.iterations", 1)
        self.tol = _number(tol, "projective.tol", "a number >= 0", lambda v: v >= 0)
        if solver not in SOLVERS:
            raise ConfigError("projective.solver", " or ".join(map(repr, SOLVERS)), got=solver)
        self.solver = solver
        self.rho = _number(rho, "projective.rho", "a number in [0, 1)", lambda v: 0 <= v < 1)
        self.relaxation = _number(relaxation, "projective.relaxation", "a number in (0, 1]", lambda v: 0 < v <= 1)
        self.delay = _count(delay, "projective.delay", 0)
        self.cg_iters = _count(cg_iters, "projective.cg_iters", 1)
        self.cg_tol = _number(cg_tol, "projective.cg_tol", "a number >= 0", lambda v: v >= 0)
        if gradient not in GRADIENTS:
            raise ConfigError("projective.gradient", " or ".join(map(repr, GRADIENTS)), got=gradient)
        self.gradient = gradient
        self.adjoint_iters = _count(adjoint_iters, "projective.adjoint_iters", 1)
        self.adjoint_tol = _number(adjoint_tol, "projective.adjoint_tol", "a number >= 0", lambda v: v >= 0)
        self.last_iterations, self.last_residual, self.last_cg, self.last_adjoint = 0, 0.0, (0, 0.0), None
        self._cache = None  # (key, value): the factor (cholesky) or the operator (cg)

    def solver_for(self, model) -> str:
        """The global-step solver used for ``model`` (``"auto"`` resolved: see ``solver``).

        ``"auto"`` takes jacobi for a spring law and in compiled code (the packed model), else
        cholesky up to :data:`CHOLESKY_NODES` free nodes if cholespy is installed.
        """
        if getattr(model, "volume", None) is not None:
            raise ConfigError(
                "integrator",
                "symplectic, rk4, verlet or implicit for an Elastic material's volume term",
                got="projective",
            )
        if self.solver != "auto":
            return self.solver
        if getattr(model, "law", None) is not None or _is_packed(model):
            return "jacobi"
        free = model.grid.num_nodes if model.free is None else int((model.free > 0).sum())
        if free > CHOLESKY_NODES:
            return "jacobi"
        try:
            import cholespy  # noqa: F401
        except ImportError:
            return "jacobi"
        return "cholesky"

    @property
    def eager_reason(self) -> str | None:
        """Why this integrator runs in the eager step (cholesky and cg solvers), or None."""
        if self.solver in ("cholesky", "cg"):
            return f"projective dynamics with solver={self.solver!r} runs in the eager step (only jacobi compiles)"
        return None

    # ------------------------------------------------------------------ the step
    def advance(self, model, state, dt, loads):
        """Iterate (*) from the inertial prediction; ``v' = (x' - x_n) / h``.

        Args:
            model: a :class:`~torchdeform.sim.model.Model` (or the packed model of the fast path).
            state: positions and velocities ``(B, 3, D, H, W)`` (packed ``(B, 3, P)``).
            dt: time step ``h`` (s).
            loads: extra node forces, as for :meth:`~torchdeform.sim.integrators.Integrator.step`.

        Returns:
            ``(x, v)`` at ``t + h``, each like ``state.x``.
        """
        solver = self.solver_for(model)
        if solver != "jacobi" and getattr(model, "law", None) is not None:
            raise ConfigError(
                "projective.solver",
                "'jacobi' for a model with a spring law (projective dynamics' constant matrix needs Hooke springs)",
                got=self.solver,
            )
        if solver == "cholesky" and _is_packed(model):
            return self._advance_unpacked(model, state, dt, loads)
        h = dt
        x0, v0, t1 = state.x, state.v, state.t + h
        free = model.free
        xp = x0 + h * v0  # where inertia alone takes the body
        x = xp
        if model.drags:
            x, _ = model.constrain(x, v0, t1)  # dragged nodes on their path at t + h
        if model.gravity is not None:  # y, as far as gravity goes
            g = (h * h) * model.gravity
            x = x + (g if free is None else g * free)

        def residual(x):
            r = model.mass * (xp - x) + (h * h) * model.forces(x, (x - x0) / h, t=t1, loads=loads)
            return r if free is None else r * free

        if self.gradient_for(solver) == "adjoint" and torch.is_grad_enabled() and not torch.compiler.is_compiling():
            with torch.no_grad():  # no graph through the iterations
                x_star, n_it, rel = self._solve(solver, model, x.detach(), x0, h, residual, self.iterations, self.tol)
            x = self._adjoint(model, solver, h, x, x_star, residual)
        else:
            x, n_it, rel = self._solve(solver, model, x, x0, h, residual, self.iterations, self.tol)
        self.last_iterations, self.last_residual = n_it, rel
        return x, (x - x0) / h

    def gradient_for(self, solver: str) -> str:
        """The gradient used with the global-step ``solver`` (``"auto"`` resolved: see ``gradient``)."""
        if self.gradient != "auto":
            return self.gradient
        return "adjoint" if solver == "cholesky" else "unrolled"

    def _solve(self, solver, model, x, x0, h, residual, iterations, tol):
        """Iterate ``x <- x + S residual(x)`` from ``x`` with the global-step ``solver``: ``(x, iterations, change)``.

        ``S`` approximates the inverse of the residual's Jacobian: ``A^-1`` (cholesky, cg) or the
        Chebyshev-accelerated Jacobi sweeps. The adjoint solve runs the same iteration.
        """
        if solver == "jacobi":
            return self._jacobi(model, x, x0, h, residual, iterations, tol)
        solve = self._cholesky_solve(model, h) if solver == "cholesky" else self._cg_solve(model, h)
        return self._iterate(x, x0, lambda x: solve(residual(x)), iterations, tol)

    def _adjoint(self, model, solver, h, x_init, x_star, residual):
        """The converged step ``x_star`` made differentiable by the implicit function theorem.

        ``x_star`` solves ``r(x, theta) = 0`` at the free nodes (``theta``: the model's parameters,
        the state, the loads); the constrained nodes are ``x_init``'s, with its graph. With
        ``J = -dr/dx`` (for Hooke springs and unprojected damping, ``M + h^2 K + h C``) and a loss
        gradient ``g``, ``dL/dtheta = lambda^T dr/dtheta`` where ``J^T lambda = g``. The backward
        finds ``lambda`` with the forward's own iteration, ``lambda <- lambda + S (g - J^T lambda)``
        (products ``J^T lambda`` by autograd of ``r``): it converges as the forward does. What it
        keeps per step is the graph of one residual ``r(x_star)``.
        """
        free = model.free

        def mixed(x):  # free nodes from x, constrained ones from x_init
            return x if free is None else x * free + x_init * (1 - free)

        x_star = x_star.detach()
        if not residual(mixed(x_star)).requires_grad:
            return mixed(x_star)  # nothing to differentiate
        x_var = x_star.clone().requires_grad_()  # the graph's handle for J^T lambda
        r = residual(mixed(x_var))
        zero = torch.zeros_like(x_star)

        def adjoint(g):
            def rhs(lam):  # g - J^T lambda = g + (dr/dx)^T lambda
                return g + torch.autograd.grad(r, x_var, lam, retain_graph=True)[0]

            g = g if free is None else g * free
            lam, n_it, rel = self._solve(solver, model, zero, zero, h, rhs, self.adjoint_iters, self.adjoint_tol)
            self.last_adjoint = (n_it, float(rel))
            return lam

        return mixed(ImplicitSolve.apply(r, x_star, adjoint))

    def _advance_unpacked(self, model, state, dt, loads):
        """The Cholesky step of a packed model, done on its grid-layout source model (eager)."""
        src = model.source
        if loads is not None and not callable(loads):
            loads = model.unpack(loads)
        x, v = self.advance(src, model.unpack_state(state), dt, loads)
        return model.pack(x), model.pack(v)

    @staticmethod
    def _iterate(x, x0, step, iterations, tol):
        """``x <- x + step(x)`` up to ``iterations`` times: ``(x, iterations, relative change)``."""
        rel = x.new_zeros(())
        for it in range(1, iterations + 1):
            dx = step(x)
            x = x + dx
            rel = _relative(dx, x - x0)
            if tol > 0:
                rel = float(rel)
                if rel <= tol:
                    return x, it, rel
        return x, iterations, rel

    # ------------------------------------------------------------------ jacobi
    def _jacobi(self, model, x, x0, h, residual, iterations, tol):
        """Chebyshev-accelerated Jacobi sweeps (Wang 2015): ``(x, iterations, relative change)``.

        One iteration is one function of tensors, run by a Python loop, or, while ``torch.compile``
        traces a fixed count (``tol = 0``), by ``while_loop``: the compiled graph then holds one
        iteration (one spring kernel) instead of ``iterations`` copies (unrolled, 10 iterations
        took over 10 minutes to compile on 2 cores).
        """
        step_scale = self.relaxation * jacobi_inverse_diagonal(model, h)
        rho2, delay = self.rho * self.rho, self.delay
        first, accelerate = 2.0 / (2.0 - rho2), rho2 > 0

        def body(i, x, x_prev, omega, rel):
            step = step_scale * residual(x)
            x_sweep = x + step
            i = i + 1
            if accelerate:
                cheb = i > delay
                omega = torch.where(i == delay + 1, first, torch.where(cheb, 4.0 / (4.0 - rho2 * omega), 1.0))
                x_new = torch.where(cheb, omega * (x_sweep - x_prev) + x_prev, x_sweep)
            else:
                x_new = x_sweep
            # the sweep's own step: zero only at the solution (a Chebyshev step can be small at a
            # turning point of its oscillation)
            return i, x_new, x, omega, _relative(step, x - x0)

        carry = (
            torch.zeros((), dtype=torch.int64, device=x.device),
            x,
            x,
            torch.ones((), dtype=x.dtype, device=x.device),
            x.new_zeros(()),
        )
        loop = None
        if tol <= 0 and torch.compiler.is_compiling():
            from .._compile import while_loop  # (lazy: importing it loads inductor, ~1.7 s)

            loop = while_loop()
        if loop is not None:
            n = iterations

            def looped(*c):  # a loop body may not return its inputs
                i, x_new, x_prev, omega, rel = body(*c)
                return i, x_new, x_prev.clone(), omega if accelerate else omega.clone(), rel

            carry = (carry[0], carry[1], carry[2].clone(), *carry[3:])  # nor alias each other
            _, x, _, _, rel = loop(lambda i, *_: i < n, looped, carry)
            return x, iterations, rel
        for it in range(1, iterations + 1):
            carry = body(*carry)
            if tol > 0:
                rel = float(carry[4])
                if rel <= tol:
                    return carry[1], it, rel
        return carry[1], iterations, (float(carry[4]) if tol > 0 else carry[4])

    # ------------------------------------------------------------------ cholesky
    def _cached(self, model, h, make):
        """``make()`` cached for this model and ``dt``, made again when a field changes (see the key)."""
        key = _fingerprint(model, h)
        if self._cache is not None and self._cache[0] == key and self._cache[1] is model:
            return self._cache[2]
        value = make()
        self._cache = (key, model, value)
        return value

    def _cholesky_solve(self, model, h):
        """``r -> A^-1 r`` on the free nodes (zero elsewhere) with the cached cholespy factors."""
        try:
            import cholespy
        except ImportError:
            raise ConfigError(
                "projective.solver",
                "the cholespy package for solver='cholesky' (pip install cholespy), or solver='cg' or 'jacobi'",
                got="cholesky",
            ) from None
        factors, index = self._cached(model, h, lambda: self._factor(model, h, cholespy))

        def solve(r):
            if r.requires_grad:
                raise ConfigError(
                    "projective.gradient",
                    "'adjoint' or 'auto' with solver='cholesky' (its solves have no unrolled gradient)",
                    got=self.gradient,
                )
            B = r.shape[0]
            flat = r.reshape(B, 3, -1)
            out = torch.zeros_like(flat)
            for b in range(B):
                solver = factors[b if len(factors) > 1 else 0]
                rhs = flat[b][:, index].T.contiguous().to(solver[1])  # (n_free, 3)
                sol = torch.zeros_like(rhs)
                solver[0].solve(rhs, sol)
                out[b][:, index] = sol.T.to(r.dtype)
            return out.view_as(r)

        return solve

    def _factor(self, model, h, cholespy):
        """The factors of ``A`` (one per parameter batch entry) and the flat indices of the free nodes."""
        mats, index = self.matrix(model, h)
        use64 = model.dtype == torch.float64
        cls, dtype = (cholespy.CholeskySolverD, torch.float64) if use64 else (cholespy.CholeskySolverF, torch.float32)
        factors = []
        for A in mats:
            dev = model.device
            factors.append(
                (
                    cls(
                        A.shape[0],
                        torch.as_tensor(A.indptr, dtype=torch.int32, device=dev),
                        torch.as_tensor(A.indices, dtype=torch.int32, device=dev),
                        torch.as_tensor(A.data, dtype=torch.float64, device=dev),
                        cholespy.MatrixType.CSR,
                    ),
                    dtype,
                )
            )
        return factors, torch.as_tensor(index, device=model.device)

    # ------------------------------------------------------------------ cg
    def _cg_solve(self, model, h):
        """``r -> A^-1 r`` by preconditioned CG on the stencil (masked to the free nodes)."""
        apply_A, precond = self._cached(
            model, h, lambda: (laplacian_operator(model, h), jacobi_inverse_diagonal(model, h))
        )

        def solve(r):
            u, n_it, rel = conjugate_gradient(
                apply_A, r, precond=precond, mask=model.free, iters=self.cg_iters, tol=self.cg_tol
            )
            self.last_cg = (n_it, rel)
            return u

        return solve

    @staticmethod
    def matrix(model, dt: float):
        """The global-step matrix ``A`` of ``model`` and ``dt`` (see the module docstring).

        Returns:
            ``(matrices, index)``: one ``scipy.sparse`` CSR matrix ``(n_free, n_free)`` per entry of
            the parameters' batch axis (one when they are shared), and the flat ``(D H W)`` indices
            ``(n_free,)`` of the free nodes, in the matrices' order.
        """
        mats, index = system_matrices(model, float(dt))
        return [A.tocsr() for A in mats], index


def _relative(dx, ref):
    """``max_b |dx_b| / |ref_b|``, a 0-d tensor."""
    num = dx.detach().flatten(1).norm(dim=1)
    den = ref.detach().flatten(1).norm(dim=1)
    return (num / den.clamp_min(torch.finfo(dx.dtype).tiny)).max()


def _fingerprint(model, h):
    """What the cached factor depends on: ``dt``, and shape, storage and in-place version of each field."""
    fields = []
    for name in ("stiffness", "damping", "mass", "k_home", "free"):
        t = getattr(model, name, None)
        fields.append(None if t is None else (name, tuple(t.shape), t.data_ptr(), t._version))
    return (float(h), bool(getattr(model, "projected", True)), tuple(fields))


def jacobi_inverse_diagonal(model, h: float) -> torch.Tensor:
    """``1 / diag(A)``, ``A = M + h^2 (L_k + K_home) + h L_c``, zero at constrained nodes.

    Args:
        model: a model (grid or packed layout).
        h: time step (s).

    Returns:
        ``(Bp, 1, D, H, W)`` (packed ``(Bp, 1, P)``): :func:`~torchdeform.sim.integrators.inverse_diagonal`
        (the same diagonal as implicit Euler's preconditioner), masked to the free nodes.
    """
    inv = inverse_diagonal(model, h)
    return inv if model.free is None else inv * model.free


def laplacian_operator(model, h: float):
    """``u -> A u``, ``A = M + h^2 (L_k + K_home) + h L_c``, matrix-free on the spring stencil.

    A product with the Laplacian ``L_k`` is the stiffness product of springs of rest length zero
    (their tangent stiffness is ``k I`` whatever their direction), made with the model's own
    linearisation; the damping enters as unprojected (``h L_c``), gated by the stiffness.

    Args:
        model: a model (grid or packed layout).
        h: time step (s).

    Returns:
        a function ``(B, 3, ...) -> (B, 3, ...)``.
    """
    zero = copy.copy(model)
    zero.rest_length = torch.zeros_like(model.rest_length)
    zero.law, zero.law_params = None, ()
    op = zero.linearise(model.X, clamp=False).scaled(alpha_scale=h * h, c=model.damping, projected=False, c_scale=h)
    mass, k_home = model.mass, model.k_home

    def apply_A(u):
        y = mass * u + op.apply(u)
        return y if k_home is None else y + (h * h) * k_home * u

    return apply_A


def system_matrices(model, h: float):
    """``A`` per parameter batch entry as ``scipy.sparse`` COO matrices over the free nodes.

    Assembled from the spring stencil: per half-direction ``s`` the springs ``i -> i + d_s`` stored
    at ``i`` (weight ``h^2 k + h c``, zero for a missing or cut spring) add the weight to both
    diagonal entries and subtract it from both off-diagonal ones.

    Returns:
        ``(matrices, index)``: the list of matrices ``(n_free, n_free)`` and the flat indices of the
        free nodes (numpy ``int64``).
    """
    import numpy as np
    import scipy.sparse as sp

    grid = model.grid
    N = math.prod(grid.shape)
    ids = torch.arange(N).view(grid.shape)
    free = (
        torch.ones(grid.shape, dtype=torch.bool)
        if model.free is None
        else (model.free.detach().cpu().reshape(-1, *grid.shape)[0] > 0)
    )
    index = ids[free].numpy()
    pos = np.full(N, -1, dtype=np.int64)
    pos[index] = np.arange(len(index))
    k, c = model.stiffness.detach(), gated_damping(model.damping, model.stiffness)
    c = None if c is None else c.detach()
    mass = model.mass.detach()
    k_home = None if model.k_home is None else model.k_home.detach()
    batch = max(t.shape[0] for t in (k, c, mass, k_home) if t is not None)

    def entry(t, b):
        return t[b if t.shape[0] > 1 else 0]

    mats = []
    for b in range(batch):
        diag = entry(mass, b)[0].expand(grid.shape).to(torch.float64).cpu().clone()
        if k_home is not None:
            diag += (h * h) * entry(k_home, b)[0].expand(grid.shape).to(torch.float64).cpu()
        rows, cols, vals = [], [], []
        for s, (src, dst) in enumerate(grid.stencil):
            w = (h * h) * entry(k, b)[s].to(torch.float64).cpu()
            if c is not None:
                w = w + h * entry(c, b)[s].to(torch.float64).cpu()
            w = w.expand(grid.shape)[src]
            diag[src] += w
            diag[dst] += w
            i, j, w = pos[ids[src].reshape(-1).numpy()], pos[ids[dst].reshape(-1).numpy()], w.reshape(-1).numpy()
            both = (i >= 0) & (j >= 0) & (w != 0)
            i, j, w = i[both], j[both], w[both]
            rows += [i, j]
            cols += [j, i]
            vals += [-w, -w]
        n = len(index)
        rows.append(np.arange(n))
        cols.append(np.arange(n))
        vals.append(diag.reshape(-1).numpy()[index])
        mats.append(sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)))
    return mats, index
