"""Adjoint gradients of linear solves (implicit function theorem), independent of the iteration count.

An implicit step solves ``A(theta) u = b(theta)`` with an iterative solver (conjugate
gradients). Differentiating through the solver's iterations (the "unrolled" gradient) keeps
every iteration's graph: memory grows with the iteration count. The solution instead satisfies
``A du = db - dA u``, so for a loss gradient ``g = dL/du``

    lambda = A^-T g,        dL/db = lambda,        dL/dA = -lambda u^T,

exact at the converged solve (Griewank & Walther, *Evaluating Derivatives*, ch. 15; the same
idea as the implicit differentiation of DiffPD, torchdeq and jaxopt).

:func:`adjoint_solve` implements it with autograd:

1. solve ``A u* = b`` without a graph (``torch.no_grad``);
2. build the residual ``r = b - A u*`` with the graph (one operator product; ``u*`` is a
   constant and ``r`` is about zero);
3. return ``u = ImplicitSolve.apply(r, u*)``: its value is ``u*``, and its backward solves
   ``A^T lambda = g`` (for symmetric ``A``, the same operator and preconditioner) and passes
   ``lambda`` to ``r``. Autograd carries it through ``r``'s graph to every tensor ``A`` and ``b``
   depend on: ``dL/dtheta = lambda^T (db/dtheta - dA/dtheta u*)``.

What the backward keeps per solve is the graph of one operator product and of ``b``, whatever the
number of iterations. The forward value is ``u*`` itself: the same, to the bit, as the solver's
result without autograd.

Filtered systems (Baraff-Witkin): with a 0/1 ``mask`` the solver solves ``P A P u = P b`` with
``u = P u``; the adjoint solve uses the same mask, so ``lambda`` is zero where ``mask`` is.

This module knows no integrator: the solver, the operator and the preconditioner are arguments
(:class:`~torchdeform.sim.integrators.ImplicitEuler` passes its conjugate gradients).

Examples:
    >>> import torch
    >>> from torchdeform.sim.adjoint import adjoint_solve
    >>> from torchdeform.sim.integrators import conjugate_gradient
    >>> k = torch.tensor(4.0, dtype=torch.float64, requires_grad=True)
    >>> b = torch.ones(1, 3, 2, 2, 2, dtype=torch.float64)
    >>> u, iters, rel = adjoint_solve(lambda u: k * u, b, conjugate_gradient, tol=1e-12)   # u = b / k
    >>> u.sum().backward()                                                          # d/dk sum(b / k) = -24 / k^2
    >>> float(u.detach().mean()), float(k.grad)
    (0.25, -1.5)
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["ImplicitSolve", "adjoint_solve"]


class ImplicitSolve(torch.autograd.Function):
    """The solution of a linear system as a function of its residual.

    ``ImplicitSolve.apply(residual, solution, adjoint, *saved)`` returns (a copy of) ``solution``;
    its backward returns ``adjoint(grad, *saved)``, i.e. ``A^-T grad``, as the gradient of
    ``residual`` (nothing for ``solution``, a constant). With ``residual = b - A u*`` built with
    autograd, this makes ``u*`` differentiable with respect to everything ``A`` and ``b`` depend on.

    ``apply`` takes:

    - ``residual``: ``b - A u*`` with its graph, ``(B, C, ...)``;
    - ``solution``: ``u*``, same shape, no graph;
    - ``adjoint``: ``(grad, *saved) -> A^-T grad``, run under ``torch.no_grad``;
    - ``saved``: detached tensors ``adjoint`` needs, kept like any tensor saved for backward
      (saved-tensor hooks see them; a later in-place change is an error).

    Not twice differentiable.

    Examples:
        >>> import torch
        >>> from torchdeform.sim.adjoint import ImplicitSolve
        >>> a = torch.tensor(2.0, requires_grad=True)               # 1 x 1 system a u = 3
        >>> u_star = torch.tensor(1.5)
        >>> u = ImplicitSolve.apply(3.0 - a * u_star, u_star, lambda g, a: g / a, a.detach())
        >>> u.backward()                                            # du/da = -u / a
        >>> float(u.detach()), float(a.grad)
        (1.5, -0.75)
    """

    @staticmethod
    def forward(ctx, residual, solution, adjoint, *saved):
        """The value: ``solution``."""
        ctx.adjoint = adjoint
        ctx.save_for_backward(*saved)
        return solution.clone()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        """``A^-T grad`` for the residual; nothing for the other arguments."""
        saved = ctx.saved_tensors
        with torch.no_grad():
            lam = ctx.adjoint(grad, *saved)
        return (lam, None, None) + (None,) * len(saved)


def adjoint_solve(
    apply_A: Callable,
    b: torch.Tensor,
    solver: Callable,
    *,
    precond=None,
    mask=None,
    iters: int = 100,
    tol: float = 1e-8,
    adjoint_iters: int | None = None,
    adjoint_tol: float | None = None,
    adjoint_operator: Callable | None = None,
    saved: tuple = (),
    on_backward: Callable | None = None,
):
    """Solve ``A u = b`` (``A`` symmetric positive definite) with the adjoint gradient.

    Args:
        apply_A: ``u -> A u`` on fields shaped like ``b``; differentiable in ``A``'s coefficients.
        b: right-hand side ``(B, C, ...)``, possibly with a graph.
        solver: ``(apply_A, b, *, precond, mask, iters, tol) -> (u, iterations, relative residual)``,
            e.g. :func:`~torchdeform.sim.integrators.conjugate_gradient`.
        precond: preconditioner for ``solver`` (a diagonal, broadcastable), or None.
        mask: 0/1 filter of ``solver`` (broadcastable), or None.
        iters: maximum iterations of the forward solve.
        tol: relative residual of the forward solve (``0``: exactly ``iters`` iterations).
        adjoint_iters: maximum iterations of the backward solve (default ``iters``).
        adjoint_tol: its relative residual (default ``tol``).
        adjoint_operator: ``(*saved) -> (apply_A, precond)`` building the operator again for the
            backward solve from the tensors ``saved`` (so the backward keeps only those, not the
            operator's coefficients); default: the forward's ``apply_A`` and ``precond``, which
            the backward then keeps alive.
        saved: tensors ``adjoint_operator`` needs; kept detached, as autograd keeps saved tensors.
        on_backward: called as ``on_backward(iterations, relative residual)`` after each
            backward solve, or None.

    Returns:
        ``(u, iterations, relative residual)`` of the forward solve. ``u`` has the solver's value;
        when grad mode is on and ``A`` or ``b`` requires grad it is differentiable (adjoint),
        otherwise it is the solver's tensor itself.

    Examples:
        >>> import torch
        >>> from torchdeform.sim.adjoint import adjoint_solve
        >>> from torchdeform.sim.integrators import conjugate_gradient
        >>> b = torch.tensor([[1.0, 2.0]], dtype=torch.float64, requires_grad=True)
        >>> d = torch.tensor([[2.0, 4.0]], dtype=torch.float64)              # A = diag(2, 4)
        >>> u, _, _ = adjoint_solve(lambda u: d * u, b, conjugate_gradient, tol=1e-12)
        >>> u.sum().backward()                                                # du/db = A^-1
        >>> u.detach().tolist(), b.grad.tolist()
        ([[0.5, 0.5]], [[0.5, 0.25]])
    """
    with torch.no_grad():  # no graph through the iterations
        u, n_it, rel = solver(apply_A, b, precond=precond, mask=mask, iters=iters, tol=tol)
    if not torch.is_grad_enabled():
        return u, n_it, rel
    residual = b - apply_A(u)
    if not residual.requires_grad:  # nothing to differentiate: the solver's result
        return u, n_it, rel
    a_iters = iters if adjoint_iters is None else adjoint_iters
    a_tol = tol if adjoint_tol is None else adjoint_tol

    def same_operator():
        return apply_A, precond

    if adjoint_operator is None:
        saved = ()
    operator = same_operator if adjoint_operator is None else adjoint_operator

    def adjoint(grad, *tensors):
        op, pre = operator(*tensors)
        lam, n, r = solver(op, grad, precond=pre, mask=mask, iters=a_iters, tol=a_tol)
        if on_backward is not None:
            on_backward(n, r)
        return lam

    return ImplicitSolve.apply(residual, u, adjoint, *(t.detach() for t in saved)), n_it, rel
