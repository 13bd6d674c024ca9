"""Static equilibrium: the shape a body takes under its loads, without running dynamics to rest.

:func:`solve_static` finds ``x`` with ``F(x) = 0`` on the free nodes (springs, the volume term of an
:class:`~torchdeform.sim.material.Elastic` material, home springs, gravity, loads), the constrained
nodes where the state (fixed nodes) or their drag paths at ``t`` (dragged nodes) put them.
Newton's method: each iteration solves ``K(x) dx = F(x)`` by conjugate gradients with a Jacobi
preconditioner, ``K`` the stiffness product of :meth:`~torchdeform.sim.model.Model.linearise`: the
exact spring Jacobian, or where that gives no descent direction (compressed springs make it
indefinite) its clamped, positive semi-definite form; the volume term enters as Gauss-Newton.
A backtracking line search then halves the step until the potential energy (elastic, gravity,
minus the loads' work) decreases enough (Armijo) or the residual ``|F|`` does.
The residual is reported relative to the load (gravity, loads and what the constrained nodes
push in at the start), so a ``tol`` means the same at any stiffness.

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((3, 3, 5), spacing=0.01, topology=26)
    >>> model = td.Model(grid, td.Elastic(5e3, 0.45), density=1000.0, gravity=(-9.81, 0, 0),
    ...                  fixed=grid.face("w-"), dtype=torch.float64)
    >>> state, info = td.solve_static(model, tol=1e-10)
    >>> info["converged"], info["residual"] <= 1e-10, float((state.x - model.X)[0, 0, :, :, -1].mean()) < 0
    (True, True, True)
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from .integrators import conjugate_gradient
from .model import Loads, Model, State

__all__ = ["solve_static"]


def _residual(model: Model, x: torch.Tensor, t, loads) -> torch.Tensor:
    """The force on the free nodes, ``(B, 3, D, H, W)`` (zero at constrained nodes)."""
    F = model.forces(x, torch.zeros_like(x), t=t, loads=loads)
    return F if model.free is None else F * model.free


def _potential(model: Model, x: torch.Tensor, t, loads) -> torch.Tensor:
    """Potential energy per batch entry (J): elastic, gravity, minus the work of the loads."""
    e = model.energy(State(x, torch.zeros_like(x), t=t))
    total = e["elastic"] + e.get("gravity", 0.0)
    ext = model.external(t)
    if loads is not None:
        extra = torch.as_tensor(loads(t) if callable(loads) else loads)
        ext = extra if ext is None else ext + extra
    if ext is not None:
        total = total - (ext * (x - model.X)).flatten(1).sum(1)
    return total


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).flatten(1).sum(1)


def _norm(r: torch.Tensor) -> torch.Tensor:
    return r.flatten(1).norm(dim=1)


def solve_static(
    model: Model,
    *,
    state: State | None = None,
    loads: Loads = None,
    tol: float = 1e-8,
    max_iter: int = 50,
    cg_iters: int = 500,
    cg_tol: float = 1e-3,
) -> tuple[State, dict]:
    """Static equilibrium of ``model`` from ``state`` (default: rest), by Newton with a line search.

    Args:
        model: the body; callable loads are evaluated at ``state.t``.
        state: the start ``(B, 3, D, H, W)`` positions and the time ``t`` of the loads and drags
            (default ``model.rest_state()``); velocities are ignored.
        loads: extra force ``(B|1, 3, D, H, W)`` (N) or a callable ``t -> force``, or None.
        tol: stop when ``|F| <= tol * |load|`` for every batch entry (relative residual).
        max_iter: Newton iterations at most.
        cg_iters: CG iterations per Newton step at most.
        cg_tol: relative tolerance of each inner CG solve (inexact Newton).

    Returns:
        ``(state, info)``: the equilibrium (velocities zero, the same ``t``) and ``info`` with
        ``residual`` (the largest relative residual over the batch), ``iterations``,
        ``cg_iterations`` (all inner iterations), ``converged``.

    Raises:
        ConfigError: a tolerance or iteration count out of range, or a model whose free nodes
            carry no stiffness.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
        >>> model = td.Model(grid, stiffness=5.0, mass=1e-3, gravity=(-9.81, 0, 0), fixed=grid.face("bottom"),
        ...                  dtype=torch.float64)
        >>> state, info = td.solve_static(model, tol=1e-10)
        >>> info["converged"], bool((state.x - model.X)[0, 0, -1].mean() < 0)   # the top settles down
        (True, True)
    """
    if not tol > 0 or int(max_iter) < 1 or int(cg_iters) < 1 or not cg_tol > 0:
        raise ConfigError(
            "solve_static",
            "tol > 0, cg_tol > 0, max_iter >= 1 and cg_iters >= 1",
            got=(tol, cg_tol, max_iter, cg_iters),
        )
    state = model.rest_state() if state is None else state
    t = state.t
    x = state.x.detach()
    if model.drags:
        x, _ = model.constrain(x, torch.zeros_like(x), t)
    with torch.no_grad():
        r = _residual(model, x, t, loads)
        scale = _norm(r).clamp_min(torch.finfo(x.dtype).tiny)  # the load the body must carry
        rel = _norm(r) / scale
        diag = model.stiffness_row_sums()  # Jacobi preconditioner
        if not bool((diag > 0).any()):
            raise ConfigError("solve_static", "a body with stiffness (its free nodes carry no springs)")
        precond = torch.where(diag > 0, 1.0 / diag, torch.zeros_like(diag))
        mask = model.free  # CG holds the constrained nodes at zero
        cg_total, it = 0, 0
        energy = _potential(model, x, t, loads)
        while float(rel.max()) > tol and it < int(max_iter):
            it += 1
            dx = None
            for clamp in (False, True):  # the exact Jacobian, or its clamped (semi-definite) form
                lin = model.linearise(x, clamp=clamp)
                dx, n_cg, _ = conjugate_gradient(
                    lin.apply, r, precond=precond, mask=mask, iters=int(cg_iters), tol=float(cg_tol), dot=model.inner
                )
                cg_total += int(n_cg)
                slope = _dot(r, dx)  # -dPi/dstep at 0: positive for a descent direction
                if bool(torch.isfinite(dx).all()) and bool((slope > 0).all()):
                    break
            assert dx is not None
            step, norm0 = 1.0, _norm(r)
            trial, r_trial, e_trial = x + dx, r, energy
            for _ in range(40):  # backtracking (Armijo on the potential energy, or a smaller residual)
                trial = x + step * dx
                r_trial = _residual(model, trial, t, loads)
                e_trial = _potential(model, trial, t, loads)
                armijo = e_trial <= energy - 1e-4 * step * slope
                if bool((armijo | (_norm(r_trial) < norm0)).all()) or step < 1e-10:
                    break
                step *= 0.5
            x, r, energy = trial, r_trial, e_trial
            rel = _norm(r) / scale
    residual = float(rel.max())
    info = {"residual": residual, "iterations": it, "cg_iterations": cg_total, "converged": residual <= tol}
    return State(x, torch.zeros_like(x), t=t), info
