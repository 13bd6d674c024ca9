r"""Learning elastic parameters from static load cases: a loss on displacements and reactions, adjoint gradients.

A static load case holds some degrees of freedom (fixed, or moved to a prescribed displacement),
loads the others (node forces, gravity) and observes displacements at chosen nodes and/or the
reaction forces on constrained ones. :class:`StaticLoss` solves each case in the small-strain limit
of the model, as a linear finite-element code does:

.. math::

    P K P\, u_f = P\,(f - K u_b), \qquad u = u_f + u_b, \qquad R = (I - P)(K u - f),

with ``K`` the stiffness at rest (``model.linearise(model.X)``: springs and, for an
:class:`~torchdeform.sim.material.Elastic` material, the volume term), ``P`` the 0/1 filter of
the free degrees of freedom (per node and component), ``u_b`` the prescribed displacements and
``f`` the node loads plus ``m g``. ``R`` is the force the constraints apply to the body (N); it
includes loads put on constrained nodes. Conjugate gradients with a Jacobi preconditioner solve
the filtered system (:func:`~torchdeform.sim.integrators.conjugate_gradient`).

**Loss.** Dimensionless, summed over the cases: per case

.. math::

    J = \frac{\sum m_u (u - \hat u)^2}{\sum m_u \hat u^2}
      + w_R \frac{\sum m_R (R - \hat R)^2}{\sum m_R \hat R^2}

over the observed entries (``m_u``, ``m_R``: 0/1 masks per node and component; ``w_R`` the
``reaction_weight``); a case without displacement or without reaction observations drops that term.

**Gradient: the adjoint method.** With ``g_u = dJ/du`` and ``g_R = dJ/dR`` at the solution, one
more solve with the same operator

.. math::

    P K P\, \lambda = P\,(g_u + K (I - P)\, g_R), \qquad w = (I - P)\, g_R - P \lambda,

gives, for any parameter ``theta`` that ``K`` (and ``f``) depend on,
``dJ/dtheta = w^T (dK/dtheta\, u - df/dtheta)``: the product ``w . (K(theta) u - f(theta))``,
differentiated by autograd with ``w`` and ``u`` held constant, is the whole gradient. No CG
iteration is differentiated, so memory and time do not grow with the iteration count, and the
gradient is exact once both solves have converged (``tol``). The returned loss is the exact value
plus ``s - s.detach()`` for that product ``s``: its value is the loss, its gradient the adjoint
one (not twice differentiable).

The parameters are usually Young's modulus and Poisson ratio per region (:class:`ElasticRegions`),
but any model whose stiffness depends on tensors that require grad works (per-node ``E`` and
``nu`` of :class:`~torchdeform.sim.material.Elastic`, per-spring stiffness, masses through
gravity).

Shapes: node fields are ``(3, D, H, W)`` (or ``(1, 3, D, H, W)``), masks ``(D, H, W)`` (every
component) or ``(3, D, H, W)``; the model has a batch of 1. Units: m, N, Pa, m/s^2.

Example (a 2 x 2 x 4 mm bar pulled along ``w`` by 100 Pa, its data made by the lattice itself):

    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.learn import ElasticRegions, LoadCase, StaticLoss, face_traction, roller_faces
    >>> grid = td.Grid((3, 3, 5), spacing=1e-3, topology=26)
    >>> regions = torch.zeros(2, 2, 4, dtype=torch.long)
    >>> regions[..., 2:] = 1                                    # two regions, per cell
    >>> truth = ElasticRegions(grid, regions, E=[3e3, 8e3], nu=[0.45, 0.49], density=1000.0)
    >>> case = LoadCase(roller_faces(grid), loads=face_traction(grid, 2, (0.0, 0.0, 100.0)))
    >>> u, R = StaticLoss.solve_case(truth.model(), case)
    >>> loss = StaticLoss(grid, [LoadCase(case.fixed, loads=case.loads, observed=u, reactions=R)])
    >>> loss(truth).item() < 1e-18                              # zero at the truth
    True
    >>> guess = ElasticRegions(grid, regions, E=[4e3, 6e3], nu=[0.4, 0.45], density=1000.0)
    >>> value = loss(guess)
    >>> value.backward()
    >>> value.item() > 1e-3, guess.raw_E.grad.shape, guess.raw_nu.grad.shape
    (True, torch.Size([2]), torch.Size([2]))
"""

from __future__ import annotations

import math
from dataclasses import KW_ONLY, dataclass

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.integrators import conjugate_gradient
from ..sim.material import Elastic, cell_mask, spring_stiffness
from ..sim.model import Model

__all__ = ["LoadCase", "StaticLoss", "ElasticRegions", "face_traction", "roller_faces", "POISSON_LIMITS"]

#: The Poisson ratios :class:`ElasticRegions` learns in: ``nu = lo + (hi - lo) sigmoid(raw)``.
POISSON_LIMITS = (0.25, 0.5)


@dataclass
class LoadCase:
    """One static load case on a grid: constraints, loads and what was observed.

    Args:
        fixed: bool ``(D, H, W)`` (every component of those nodes) or ``(3, D, H, W)`` (per
            component: a roller holds one): the constrained degrees of freedom.
        displacement: prescribed displacement (m), ``(3, D, H, W)``, read on the constrained
            entries (zero elsewhere); None: every constrained entry stays at rest.
        loads: node forces (N), ``(3, D, H, W)`` (see :func:`face_traction`), or None.
        gravity: ``(gd, gh, gw)`` (m/s^2): the force ``m g`` with the model's masses, or None.
        observed: displacements (m) ``(3, D, H, W)`` to match, or None.
        observed_mask: bool ``(D, H, W)`` or ``(3, D, H, W)``: the entries of ``observed`` the loss
            reads (default: every free entry).
        reactions: reaction forces (N) ``(3, D, H, W)`` to match (the force the constraints apply
            to the body), or None.
        reaction_mask: bool ``(D, H, W)`` or ``(3, D, H, W)``: the entries of ``reactions`` the loss
            reads (default: every constrained entry); they must be constrained.
        name: shown in errors and reports.
    """

    fixed: torch.Tensor | np.ndarray
    _: KW_ONLY
    displacement: torch.Tensor | np.ndarray | None = None
    loads: torch.Tensor | np.ndarray | None = None
    gravity: tuple[float, float, float] | None = None
    observed: torch.Tensor | np.ndarray | None = None
    observed_mask: torch.Tensor | np.ndarray | None = None
    reactions: torch.Tensor | np.ndarray | None = None
    reaction_mask: torch.Tensor | np.ndarray | None = None
    name: str = "case"


def face_traction(grid: Grid, axis: int, traction, *, side: str = "+") -> torch.Tensor:
    """Node forces (N) ``(3, D, H, W)`` of a uniform traction (Pa) on one face of a box grid.

    ``traction``: the force per area ``(t0, t1, t2)`` (Pa) on the face ``axis`` at its last
    (``side="+"``) or first (``"-"``) node plane. Each face node gets ``t`` times its share of the
    face: ``h_a h_b`` inside, half on an edge of the face, a quarter at a corner (the bilinear hat
    functions integrated: the consistent load, under which a lattice of uniform material is in
    uniform stress).

    Example:
        >>> import torchdeform as td
        >>> from torchdeform.learn import face_traction
        >>> f = face_traction(td.Grid((3, 3, 5), spacing=1e-3), 2, (0.0, 0.0, 100.0))
        >>> [round(float(v), 12) for v in (f[2].sum(), f[2, 1, 1, -1], f[2, 0, 0, -1])]   # 100 Pa x 4 mm^2
        [0.0004, 0.0001, 2.5e-05]
    """
    if axis not in (0, 1, 2) or side not in ("+", "-"):
        raise ConfigError("face_traction", "axis 0, 1 or 2 and side '+' or '-'", got=(axis, side))
    t = torch.as_tensor(traction, dtype=torch.float64).reshape(-1)
    if t.numel() != 3 or not bool(torch.isfinite(t).all()):
        raise ConfigError("face_traction.traction", "three finite numbers (Pa)", got=traction)
    area = torch.ones(grid.shape, dtype=torch.float64)
    for a, (n, h) in enumerate(zip(grid.shape, grid.spacing)):
        if a == axis:
            continue
        w = torch.full((n,), float(h), dtype=torch.float64)
        if n > 1:
            w[0] = w[-1] = h / 2
        area = area * w.view([-1 if b == a else 1 for b in range(3)])
    face = torch.zeros(grid.shape, dtype=torch.bool)
    face.select(axis, -1 if side == "+" else 0).fill_(True)
    return t.view(3, 1, 1, 1) * (area * face)


def roller_faces(grid: Grid, *, axes=(0, 1, 2)) -> torch.Tensor:
    """Bool ``(3, D, H, W)``: component ``c`` held on the first node plane along ``c``, for ``c`` in ``axes``.

    Rollers on the three planes through the origin are mirror planes of a box: they remove the
    rigid motions and leave the body free to contract sideways (uniform uniaxial stress stays
    uniform).

    Example:
        >>> import torchdeform as td
        >>> from torchdeform.learn import roller_faces
        >>> m = roller_faces(td.Grid((3, 3, 5), spacing=1e-3))
        >>> int(m[0].sum()), int(m[2].sum()), bool(m[2, :, :, 0].all())
        (15, 9, True)
    """
    out = torch.zeros((3,) + tuple(grid.shape), dtype=torch.bool)
    for c in axes:
        out[c].select(c, 0).fill_(True)
    return out


# ------------------------------------------------------------------- the loss
def _field(value, shape, key, name, dtype, device) -> torch.Tensor | None:
    """A node field ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` as ``(1, 3, D, H, W)``; None stays None."""
    if value is None:
        return None
    t = torch.as_tensor(np.asarray(value) if not torch.is_tensor(value) else value).to(dtype=dtype, device=device)
    if tuple(t.shape) == (1, 3) + shape:
        t = t[0]
    if tuple(t.shape) != (3,) + shape:
        raise ConfigError(f"{name}.{key}", f"a node field (3, D, H, W) = {(3,) + shape}", got=tuple(t.shape))
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(f"{name}.{key}", "finite values (no NaN or inf)", got="non-finite values")
    return t.unsqueeze(0)


def _mask(value, shape, key, name, device) -> torch.Tensor | None:
    """A bool mask ``(D, H, W)`` or ``(3, D, H, W)`` as bool ``(1, 3, D, H, W)``; None stays None."""
    if value is None:
        return None
    t = torch.as_tensor(np.asarray(value) if not torch.is_tensor(value) else value, device=device)
    if t.dtype != torch.bool:
        raise ConfigError(f"{name}.{key}", "a bool mask", got=str(t.dtype))
    if tuple(t.shape) == shape:
        t = t.expand((3,) + shape)
    if tuple(t.shape) != (3,) + shape:
        raise ConfigError(
            f"{name}.{key}", f"a bool mask (D, H, W) or (3, D, H, W) with grid {shape}", got=tuple(t.shape)
        )
    return t.unsqueeze(0)


class _Case:
    """A :class:`LoadCase` checked against a grid, as tensors ``(1, 3, D, H, W)``."""

    def __init__(self, case: LoadCase, shape: tuple, dtype, device, reaction_weight: float):
        if not isinstance(case, LoadCase):
            raise ConfigError("cases", "LoadCase objects", got=type(case).__name__)
        name = case.name
        fixed = _mask(case.fixed, shape, "fixed", name, device)
        if fixed is None or not bool(fixed.any()):
            raise ConfigError(f"{name}.fixed", "at least one constrained degree of freedom", got="none", show_got=True)
        self.name = name
        self.free = (~fixed).to(dtype)
        self.fixed = fixed.to(dtype)
        disp = _field(case.displacement, shape, "displacement", name, dtype, device)
        self.u_b = None if disp is None else disp * self.fixed
        self.loads = _field(case.loads, shape, "loads", name, dtype, device)
        self.gravity = None
        if case.gravity is not None:
            g = torch.as_tensor(case.gravity, dtype=dtype).reshape(-1)
            if g.numel() != 3 or not bool(torch.isfinite(g).all()):
                raise ConfigError(f"{name}.gravity", "three finite numbers (m/s^2)", got=case.gravity)
            self.gravity = g.to(device).view(1, 3, 1, 1, 1)
        self.observed = _field(case.observed, shape, "observed", name, dtype, device)
        self.reactions = _field(case.reactions, shape, "reactions", name, dtype, device)
        if self.observed is None and self.reactions is None:
            raise ConfigError(f"{name}", "observed displacements or reactions (or both)", got="neither", show_got=True)
        self.terms = []  # (kind, data, weight mask (0/1 dtype), 1 / sum(m data^2))
        if self.observed is not None:
            m = _mask(case.observed_mask, shape, "observed_mask", name, device)
            m = (~fixed) if m is None else m
            self.terms.append(("u", self.observed, m.to(dtype), self._scale(self.observed, m, "observed", 1.0)))
        if self.reactions is not None:
            m = _mask(case.reaction_mask, shape, "reaction_mask", name, device)
            m = fixed if m is None else m
            if bool((m & ~fixed).any()):
                raise ConfigError(
                    f"{name}.reaction_mask",
                    "constrained entries only (free nodes carry no reaction)",
                    got="free entries",
                )
            self.terms.append(
                ("R", self.reactions, m.to(dtype), self._scale(self.reactions, m, "reactions", reaction_weight))
            )

    def _scale(self, data, mask, key, weight) -> float:
        if not bool(mask.any()):
            raise ConfigError(f"{self.name}.{key[:8]}_mask", "at least one observed entry", got="none", show_got=True)
        norm = float((data * data * mask).sum())
        if not norm > 0:
            raise ConfigError(
                f"{self.name}.{key}",
                "observations that are not all zero where observed (they set the loss's scale)",
                got=0.0,
            )
        return weight / norm

    def force(self, model: Model) -> torch.Tensor | int:
        """The applied node forces ``f`` (N), ``(1, 3, D, H, W)``, or 0."""
        f = 0
        if self.loads is not None:
            f = self.loads
        if self.gravity is not None:
            f = f + model.mass * self.gravity
        return f


class StaticLoss:
    """The loss of static load cases against a model's small-strain solution, with adjoint gradients.

    See the module docstring for the equations.

    Args:
        grid: the grid of every case (the model's).
        cases: :class:`LoadCase` objects (at least one).
        reaction_weight: ``w_R``, the weight of the reaction term against the displacement term.
        tol: relative residual of every conjugate-gradient solve (forward and adjoint).
        cg_iters: iterations per solve at most; more raise :class:`~torchdeform.errors.ConfigError`
            (the Trainer's line search treats it as a bad trial point).
        warm_start: start each solve from the previous call's solution of the same case (the same
            answer to ``tol``, in fewer iterations while a fit moves slowly).
        dtype: of the data (float64 recommended).

    Call with a model (batch 1) or with anything that has ``.model()`` (:class:`ElasticRegions`) to
    get a 0-d loss; ``windows`` (a LongTensor of case indices) takes a subset of the cases, as
    :class:`~torchdeform.learn.trainer.Trainer` passes for Adam subsets. :attr:`iterations` holds the
    CG iterations of the last call.
    """

    def __init__(
        self,
        grid: Grid,
        cases,
        *,
        reaction_weight: float = 1.0,
        tol: float = 1e-10,
        cg_iters: int = 20000,
        warm_start: bool = True,
        dtype=torch.float64,
        device=None,
    ):
        cases = list(cases) if not isinstance(cases, LoadCase) else [cases]
        if not cases:
            raise ConfigError("cases", "at least one LoadCase", got=[])
        if not (math.isfinite(float(reaction_weight)) and reaction_weight >= 0):
            raise ConfigError("reaction_weight", "a number >= 0", got=reaction_weight)
        if not (tol > 0) or int(cg_iters) < 1:
            raise ConfigError("StaticLoss", "tol > 0 and cg_iters >= 1", got=(tol, cg_iters))
        self.grid, self.shape, self.dtype = grid, tuple(grid.shape), dtype
        self.cases = [_Case(c, self.shape, dtype, device, float(reaction_weight)) for c in cases]
        self.tol, self.cg_iters, self.warm_start = float(tol), int(cg_iters), bool(warm_start)
        self._last: dict = {}
        #: CG iterations of the last call, ``{case name: (forward, adjoint)}``
        self.iterations: dict = {}
        #: calls so far
        self.calls = 0

    @property
    def num_windows(self) -> int:
        """The number of load cases (a Trainer's "windows")."""
        return len(self.cases)

    # ---------------------------------------------------------------- solves
    def _model(self, params) -> Model:
        model = params.model() if hasattr(params, "model") and not isinstance(params, Model) else params
        if not isinstance(model, Model):
            raise ConfigError("StaticLoss", "a Model or an object with .model()", got=type(params).__name__)
        if tuple(model.grid.shape) != self.shape:
            raise ConfigError("model.grid", f"the cases' grid {self.shape}", got=tuple(model.grid.shape))
        return model

    def _solve(self, apply, b, case: _Case, precond, dot, key):
        """``P K P x = P b`` by preconditioned CG, warm-started from the last solution stored under ``key``."""
        with torch.no_grad():
            b = b * case.free
            bnorm = float(b.norm())
            if bnorm == 0:
                return torch.zeros_like(b), 0
            x0 = self._last.get(key) if self.warm_start else None
            r = b if x0 is None else b - apply(x0) * case.free
            rnorm = float(r.norm())
            tol = self.tol * bnorm / max(rnorm, 1e-300)
            if tol >= 1:  # the last solution already solves it
                return x0, 0
            x, it, rel = conjugate_gradient(
                apply, r, precond=precond, mask=case.free, iters=self.cg_iters, tol=tol, dot=dot
            )
            if not rel <= tol:
                raise ConfigError(
                    "cg_iters",
                    f"enough conjugate-gradient iterations for load case {case.name!r} to reach tol {self.tol:g} "
                    "(or constraints that remove every rigid motion)",
                    got=f"{self.cg_iters} iterations, relative residual {rel * rnorm / bnorm:.3g}",
                )
            x = x if x0 is None else x0 + x
            self._last[key] = x
            return x, it

    @staticmethod
    def solve_case(model: Model, case: LoadCase, *, tol: float = 1e-10, cg_iters: int = 20000):
        """The small-strain solution of one case: displacements ``u`` (m) and reactions ``R`` (N), ``(1, 3, D, H, W)``.

        No gradient (see :class:`StaticLoss` for that); ``case`` needs no observations.
        """
        shape = tuple(model.grid.shape)
        probe = LoadCase(
            case.fixed,
            displacement=case.displacement,
            loads=case.loads,
            gravity=case.gravity,
            reactions=torch.ones((3,) + shape, dtype=model.dtype),
            name=case.name,
        )
        loss = StaticLoss(model.grid, [probe], tol=tol, cg_iters=cg_iters, warm_start=False, dtype=model.dtype)
        with torch.no_grad():
            lin = model.linearise(model.X)
            u, R, _ = loss._forward(model, lin, loss.cases[0])
        return u, R

    def _forward(self, model, lin, case: _Case):
        """``(u, R, iterations)`` of one case, without a graph."""
        diag = model.stiffness_row_sums().detach()
        precond = torch.where(diag > 0, 1.0 / diag, torch.zeros_like(diag))
        with torch.no_grad():
            f = case.force(model)
            f = torch.zeros_like(model.X) + (f.detach() if torch.is_tensor(f) else f)
            b = f if case.u_b is None else f - lin.apply(case.u_b)
            u, it = self._solve(lin.apply, b, case, precond, model.inner, (case.name, id(case), "u"))
            if case.u_b is not None:
                u = u + case.u_b
            R = (lin.apply(u) - f) * case.fixed
        return u, R, it

    def solve(self, params) -> list:
        """``[(u, R), ...]`` per case, ``(1, 3, D, H, W)`` each (m, N), without a graph."""
        model = self._model(params)
        with torch.no_grad():
            lin = model.linearise(model.X)
            return [self._forward(model, lin, c)[:2] for c in self.cases]

    # ---------------------------------------------------------------- the loss
    def __call__(self, params, windows=None) -> torch.Tensor:
        """The loss (0-d tensor) of the cases (or the subset ``windows``), with the adjoint gradient."""
        model = self._model(params)
        self.calls += 1
        cases = self.cases if windows is None else [self.cases[int(i)] for i in torch.as_tensor(windows).reshape(-1)]
        lin = model.linearise(model.X)  # with the parameters' graph; the solves run without it
        diag = model.stiffness_row_sums().detach()
        precond = torch.where(diag > 0, 1.0 / diag, torch.zeros_like(diag))
        total, surrogate = 0.0, None
        self.iterations = {}
        for case in cases:
            u, R, it = self._forward(model, lin, case)
            g_u = torch.zeros_like(u)
            g_R = torch.zeros_like(u)
            for kind, data, m, scale in case.terms:
                diff = (u if kind == "u" else R) - data
                total += scale * float((diff * diff * m).sum())
                if kind == "u":
                    g_u = g_u + 2 * scale * diff * m
                else:
                    g_R = g_R + 2 * scale * diff * m * case.fixed
            needs_grad = torch.is_grad_enabled() and any(
                t.requires_grad for t in (model.stiffness, *(model.volume or ())) if torch.is_tensor(t)
            )
            needs_grad = needs_grad or (
                torch.is_grad_enabled() and case.gravity is not None and model.mass.requires_grad
            )
            it_adj = 0
            if needs_grad:
                with torch.no_grad():
                    rhs = g_u + (lin.apply(g_R) if bool(g_R.any()) else 0)
                    lam, it_adj = self._solve(lin.apply, rhs, case, precond, model.inner, (case.name, id(case), "adj"))
                    w = g_R - lam * case.free
                # w . (K(theta) u - f(theta)): autograd of one product with w and u constant
                f = case.force(model)
                s = (w * (lin.apply(u) - f)).sum()
                surrogate = s if surrogate is None else surrogate + s
            self.iterations[case.name] = (it, it_adj)
        value = torch.tensor(total, dtype=self.dtype, device=model.X.device)
        if surrogate is None:
            return value
        return value + (surrogate - surrogate.detach())


# ------------------------------------------------------------------- parameters
def _cell_model(grid: Grid, material: Elastic, h: float, args: dict) -> Model:
    """The Elastic body whose cells have ``material``'s per-cell values ``(D-1, H-1, W-1)`` themselves.

    What :class:`~torchdeform.sim.model.Model` builds from an :class:`Elastic` material (springs
    assembled from the cells' shear moduli, the cell term's volume and shear moduli), with the cell
    values given instead of corner means of node values; the tests hold it equal to the Elastic
    model for a uniform material.
    """
    dtype = args["dtype"]
    inside = cell_mask(grid).to(dtype)
    mu = material.lame()[0] * inside
    model = Model(grid, spring_stiffness(grid, mu, h), **args)
    model.volume = (material.volume_modulus() * inside, h, material.cell_shear_modulus() * inside)
    model.mu_cells = mu
    return model


class ElasticRegions(nn.Module):
    """Young's modulus and Poisson ratio per region, learned, and the :class:`~torchdeform.sim.model.Model` they make.

    ``E_r = E0_r exp(raw_E_r)`` (positive; ``E0`` the initial values, so the raw values start at 0
    and are of order one) and ``nu_r = 0.25 + 0.25 sigmoid(raw_nu_r)``: every raw value is a Poisson
    ratio in ``(0.25, 0.5)`` (:data:`POISSON_LIMITS`, the range of
    :class:`~torchdeform.sim.material.Elastic`), incompressibility only in the limit.

    Args:
        grid: the grid (26, 18 or 14 neighbours, cubic cells).
        regions: int labels ``0 .. R-1``: per node ``(D, H, W)``, or per cell ``(D-1, H-1, W-1)``.
            Per node, the model is ``Elastic(E[labels], nu[labels])``, whose cells take the mean of
            their corners: an interface between regions becomes a layer one cell thick of mean
            properties. Per cell, each cell gets its region's ``mu`` and ``kappa`` (springs assembled
            from the cells by :func:`~torchdeform.sim.material.spring_stiffness`, the volume term
            per cell), the lattice counterpart of finite elements with the interface on element
            faces.
        E: initial Young's modulus per region (Pa), ``(R,)`` or a number.
        nu: initial Poisson ratio per region, in ``(0.25, 0.5)``, ``(R,)`` or a number.
        **model: the rest of the model (``density`` or ``mass``, ``gravity``, ``fixed``, ``dtype``;
            float64 by default), passed to :class:`~torchdeform.sim.model.Model`.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.learn import ElasticRegions
        >>> grid = td.Grid((3, 3, 5), spacing=1e-3)
        >>> p = ElasticRegions(grid, torch.zeros(3, 3, 5, dtype=torch.long), E=5e3, nu=0.45, density=1000.0)
        >>> p.summary()
        {'E': [5000.0], 'nu': [0.45]}
        >>> p.model().volume is not None
        True
    """

    def __init__(self, grid: Grid, regions, *, E, nu, **model):
        super().__init__()
        lab = torch.as_tensor(np.asarray(regions) if not torch.is_tensor(regions) else regions)
        cells = tuple(n - 1 for n in grid.shape)
        if lab.dtype in (torch.bool,) or lab.is_floating_point() or tuple(lab.shape) not in (tuple(grid.shape), cells):
            raise ConfigError(
                "regions",
                f"int labels per node {tuple(grid.shape)} or per cell {cells}",
                got=(str(lab.dtype), tuple(lab.shape)),
            )
        if int(lab.min()) < 0:
            raise ConfigError("regions", "labels >= 0", got=int(lab.min()))
        n = int(lab.max()) + 1
        self.grid, self.per_cell = grid, tuple(lab.shape) == cells
        self.register_buffer("regions", lab.long(), persistent=False)
        self.model_args = {"dtype": torch.float64, **model}
        dtype = self.model_args["dtype"]
        e0 = torch.as_tensor(E, dtype=dtype).reshape(-1).expand(n).clone()
        v0 = torch.as_tensor(nu, dtype=dtype).reshape(-1).expand(n).clone()
        if not bool(torch.isfinite(e0).all() & (e0 > 0).all()):
            raise ConfigError("E", f"{n} positive, finite values (Pa)", got=e0.tolist())
        lo, hi = POISSON_LIMITS
        if not bool(((v0 > lo) & (v0 < hi)).all()):
            raise ConfigError("nu", f"{n} values in ({lo}, {hi})", got=v0.tolist())
        self.register_buffer("E0", e0)
        self.raw_E = nn.Parameter(torch.zeros(n, dtype=dtype))
        self.raw_nu = nn.Parameter(torch.logit((v0 - lo) / (hi - lo)))
        self.material_check = Elastic(float(e0[0]), float(v0[0])).check_grid(grid)  # the cell side h (m)

    def E(self) -> torch.Tensor:
        """Young's modulus per region (Pa), ``(R,)``."""
        return self.E0 * torch.exp(self.raw_E)

    def nu(self) -> torch.Tensor:
        """Poisson ratio per region, ``(R,)``."""
        lo, hi = POISSON_LIMITS
        return lo + (hi - lo) * torch.sigmoid(self.raw_nu)

    def values(self) -> torch.Tensor:
        """``(2, R)``: E (Pa) and nu per region."""
        return torch.stack([self.E(), self.nu()])

    def model(self) -> Model:
        """The model with the current values (differentiable in ``raw_E`` and ``raw_nu``)."""
        E, nu = self.E()[self.regions], self.nu()[self.regions]
        if not self.per_cell:
            return Model(self.grid, Elastic(E, nu), **self.model_args)
        return _cell_model(self.grid, Elastic(E, nu), self.material_check, self.model_args)

    def summary(self) -> dict:
        """``{"E": [...], "nu": [...]}`` per region, plain floats."""
        return {"E": self.E().detach().cpu().tolist(), "nu": self.nu().detach().cpu().tolist()}
