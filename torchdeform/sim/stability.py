"""Time-step bounds and divergence detection.

The linearised body is ``M x'' = -K x - C x'``. With ``Lk = lambda_max(M^-1 K)`` (``omega_max^2``)
and ``Lc`` a bound on ``lambda_max(M^-1 C)``, the explicit schemes are stable for

=====================  =====================================================
integrator             bound on dt
=====================  =====================================================
symplectic Euler,      ``h^2 Lk + 2 h Lc < 4``; undamped ``h < 2 / omega_max``
damped Verlet
RK4                    ``h < 2 sqrt(2) / omega_max`` (and ``h Lc < 2.78``)
explicit Euler         ``h < gamma / omega^2`` of the top mode; 0 without damping
implicit Euler         none (A-stable)
=====================  =====================================================

``Lk`` comes from Gershgorin (a guaranteed upper bound: ``max_i (2 sum_j k_ij + k_home) / m_i``)
or from power iteration on the stencil's stiffness products (tight; the default).
"""

from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING

import torch

from ..errors import DivergenceError, StabilityWarning

if TYPE_CHECKING:
    from .integrators import Integrator

__all__ = [
    "gershgorin_omega2",
    "damping_rate_bound",
    "power_omega2",
    "time_step_bound",
    "suggest_dt",
    "check_dt",
    "DivergenceMonitor",
    "likely_causes",
]


@torch.no_grad()
def gershgorin_omega2(model) -> float:
    """Upper bound on ``omega_max^2 = lambda_max(M^-1 K)`` at rest (Gershgorin).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)       # two nodes, one spring
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                     # omega^2 = k / m = 1
        >>> td.gershgorin_omega2(model), round(td.power_omega2(model), 9)   # bound and exact value
        (2.0, 1.0)
    """
    ksum = model.stiffness_row_sums()
    return float((model.inv_mass * ksum).max())


@torch.no_grad()
def damping_rate_bound(model) -> float:
    """Upper bound on ``lambda_max(M^-1 C)`` of the spring dashpots (Gershgorin); 0 if undamped."""
    if model.damping is None:
        return 0.0
    return float((model.inv_mass * 2 * model.spring_sums(model.damping)).max())


def _stiffness_product(model, lin, u):
    y = lin.apply(u)
    return y if model.k_home is None else y + model.k_home * u


@torch.no_grad()
def power_omega2(model, *, x=None, iters: int = 60, seed: int = 0) -> float:
    """``lambda_max(M^-1 K)`` by power iteration on ``M^-1/2 K M^-1/2`` (free nodes only).

    Args:
        model: the :class:`~torchdeform.sim.model.Model`.
        x: state ``(B, 3, D, H, W)`` to linearise at (default: rest).
        iters: power iterations; each costs one stiffness product.
        seed: seed of the random start vector.

    Returns:
        the largest eigenvalue found over the batch (a lower bound that is tight once converged).

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((4, 4, 4), spacing=0.01), stiffness=50.0, mass=1e-3)
        >>> lk = td.power_omega2(model)                   # (rad/s)^2
        >>> 0 < lk <= td.gershgorin_omega2(model)
        True
    """
    x = model.X if x is None else x.detach()
    lin = model.linearise(x)
    s = model.inv_mass.sqrt()
    B = max(x.shape[0], s.shape[0], model.stiffness.shape[0])
    gen = torch.Generator().manual_seed(seed)
    u = torch.randn((B, 3) + model.grid.shape, generator=gen, dtype=torch.float64).to(model.dtype)
    u = u.to(model.device) * s
    lam = torch.zeros(B, dtype=model.dtype, device=model.device)
    with torch.no_grad():
        for _ in range(iters):
            # (the dtype's tiny, not 1e-300, which is 0 in float32: no springs or no free node gives
            # u = 0 and lambda = 0, hence no bound, instead of 0 / 0)
            norm = u.flatten(1).norm(dim=1).clamp_min(torch.finfo(u.dtype).tiny).view(-1, 1, 1, 1, 1)
            u = u / norm
            y = s * _stiffness_product(model, lin, s * u)
            lam = (u * y).flatten(1).sum(1)
            u = y
    return float(lam.max())


def _name(integrator) -> str:
    return integrator if isinstance(integrator, str) else integrator.name


@torch.no_grad()
def time_step_bound(model, *, integrator: str | Integrator = "symplectic", method: str = "power", x=None) -> float:
    """Largest stable time step (s) of an explicit integrator for this model.

    Args:
        model: the :class:`~torchdeform.sim.model.Model`.
        integrator: an integrator or its name (``"explicit"``, ``"symplectic"``, ``"verlet"``,
            ``"rk4"``, ``"implicit"``, ``"knoche"``).
        method: ``"power"`` (tight) or ``"gershgorin"`` (guaranteed, up to ~3x smaller).
        x: state ``(B, 3, D, H, W)`` to linearise at (default: rest; ``"power"`` only).

    Returns:
        the bound in seconds; ``inf`` for implicit Euler and Knoche relaxation (no time step).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)       # two nodes, one spring
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                     # omega^2 = k / m = 1
        >>> round(td.time_step_bound(model), 6), round(td.time_step_bound(model, integrator="rk4"), 6)
        (2.0, 2.828427)
        >>> round(td.time_step_bound(model, method="gershgorin"), 6), td.time_step_bound(model, integrator="implicit")
        (1.414214, inf)
    """
    name = _name(integrator)
    if name in ("implicit", "knoche", "projective"):
        return math.inf
    lk = power_omega2(model, x=x) if method == "power" else gershgorin_omega2(model)
    lc = damping_rate_bound(model)
    if name == "explicit":
        if lc == 0 or lk == 0:
            return 0.0 if lk > 0 else (2 / lc if lc else math.inf)
        # stiffness-proportional dashpots: gamma / omega^2 = c / k for every mode
        # (over the springs that exist: a removed or masked spring has k = 0)
        k, c = torch.broadcast_tensors(model.stiffness, model.damping)
        ratio = float(torch.where(k > 0, c / k.clamp_min(1e-300), torch.full_like(k, math.inf)).min())
        return min(ratio, 2 / lc)
    if name == "rk4":
        h = 2 * math.sqrt(2) / math.sqrt(lk) if lk > 0 else math.inf
        return min(h, 2.78 / lc) if lc > 0 else h
    if lk == 0:
        return 2 / lc if lc > 0 else math.inf
    h = (-lc + math.sqrt(lc * lc + 4 * lk)) / lk
    c = float(model.decay or 0.0)
    if c > 0:
        # global drag after the step, v <- e^{-c h} v, scales the update's determinant: stable while
        # h^2 w^2 <= 2 + 2 e^{-c h} (1 - h g) (Jury), down to 1/sqrt(2) of the bound for a strong drag
        def stable(t):
            return t * t * lk <= 2 + 2 * math.exp(-c * t) * (1 - t * lc)

        lo, hi = 0.0, h
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if stable(mid) else (lo, mid)
        h = lo
    return h


def suggest_dt(
    model, *, integrator: str | Integrator = "symplectic", safety: float = 0.9, method: str = "power"
) -> float:
    """A stable time step: ``safety`` times :func:`time_step_bound` (s).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)       # two nodes, one spring
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                     # omega^2 = k / m = 1
        >>> round(td.suggest_dt(model), 6), round(td.suggest_dt(model, integrator="rk4", safety=0.5), 6)
        (1.8, 1.414214)
    """
    return safety * time_step_bound(model, integrator=integrator, method=method)


def check_dt(model, dt: float, integrator, *, bound: float | None = None) -> float:
    """Warn with :class:`StabilityWarning` when ``dt`` exceeds the bound; returns the bound.

    Examples:
        >>> import warnings
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)       # two nodes, one spring
        >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
        ...                  dtype=torch.float64)                     # omega^2 = k / m = 1
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     bound = td.check_dt(model, 3.0, "symplectic")          # 3 s > 2 s
        >>> round(bound, 6), [w.category.__name__ for w in caught]
        (2.0, ['StabilityWarning'])
    """
    bound = time_step_bound(model, integrator=integrator) if bound is None else bound
    if dt > bound and bound == 0:
        warnings.warn(
            f"dt = {dt:.3g} s: {_name(integrator)} is unstable at every time step for this model (springs "
            "without damping); add damping, or use the symplectic, verlet, rk4 or an implicit integrator",
            StabilityWarning,
            stacklevel=3,
        )
    elif dt > bound:
        warnings.warn(
            f"dt = {dt:.3g} s exceeds the stability bound of {_name(integrator)}: the bound is "
            f"{bound:.3g} s; use dt <= {0.9 * bound:.3g} s or an implicit integrator",
            StabilityWarning,
            stacklevel=3,
        )
    return bound


class DivergenceMonitor:
    """Stops a run with :class:`DivergenceError` on non-finite values or runaway energy.

    Runaway energy: kinetic energy above ``factor`` times a scale of the model, the energy of
    every spring stretched to twice its rest length plus ``M |g|`` times the body's size.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` of the run.
        dt: the time step of the run (s).
        integrator: the integrator of the run, or its name (names the safe dt in the message).
        factor: runaway threshold (default ``1e4``).

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3)
        >>> monitor = td.DivergenceMonitor(model, dt=1e-4, integrator="symplectic")
        >>> state = model.rest_state()
        >>> monitor.check(state, step=1)                    # finite and calm: nothing happens
        >>> state.v[0, 0, 1, 1, 1] = float("nan")
        >>> try:
        ...     monitor.check(state, step=2)
        ... except td.DivergenceError as e:
        ...     print(e.step, e.quantity, e.dt)
        2 velocity 0.0001
    """

    def __init__(self, model, dt, integrator, *, factor: float = 1e4):
        self.model, self.dt, self.integrator = model, dt, integrator
        with torch.no_grad():
            l0 = model.rest_length
            e_springs = float((0.5 * model.stiffness * l0 * l0 * model.grid.spring_mask(device=model.device)).sum())
            size = max(n * s for n, s in zip(model.grid.shape, model.grid.spacing))
            g = 0.0 if model.gravity is None else float(model.gravity.norm())
            e_grav = float(model.mass.expand(-1, -1, *model.grid.shape).sum()) * g * size
        self.limit = factor * max(e_springs + e_grav, 1e-30)

    def fail(self, step: int, quantity: str, value: float, *, state=None):
        """Raise the :class:`DivergenceError` of ``quantity`` at ``step`` (runners that check their own way).

        Above the stability bound it names a safe dt; within it, the likely cause among the model's terms
        (:func:`likely_causes`: tools, damping, strain limits, loads, drags, gravity), read at ``state``
        (the diverged state, or None).
        """
        name = _name(self.integrator)
        implicit = name in ("implicit", "knoche", "projective")
        try:
            bound = math.inf if implicit else time_step_bound(self.model, integrator=name)
        except Exception:  # pragma: no cover
            bound = math.nan
        safe = 0.9 * bound if math.isfinite(bound) and bound > 0 else None
        cause = None
        if implicit or (math.isfinite(bound) and self.dt <= bound) or bound == math.inf:
            # the linear stability bound holds (or there is none): the time step is not what diverged
            within = "an implicit integrator" if implicit else f"dt within the stability bound ({bound:.3g} s)"
            try:
                likely = likely_causes(self.model, step * self.dt if state is None else state.t, self.dt, state=state)
            except Exception:  # pragma: no cover - a diagnosis never hides the divergence itself
                likely = ""
            cause = f"with {within} the time step is not the cause: " + (
                likely
                or "look for a load, drag, gravity or start state too large for this body, or a spring law "
                "that stiffens without limit"
            )
            safe = None
        raise DivergenceError(step, quantity, value, self.dt, safe, cause=cause)

    def check(self, state, step: int, *, mass: torch.Tensor | None = None):
        """Raise :class:`DivergenceError` if ``state`` is non-finite or runaway.

        ``mass``: node masses laid out like ``state`` (a packed state, ``(B, 3, P)``, takes the packed
        model's masses, zero in the halo), default the model's. One pass over the velocities and one
        over the positions: their sums are finite unless a value is not (then each is searched).
        """
        with torch.no_grad():
            m = self.model.mass if mass is None else mass
            ke_all = (0.5 * m * state.v * state.v).flatten(1).sum(1)
            probe = float(ke_all.max() + 0.0 * state.x.sum())
            if not math.isfinite(probe):
                for quantity, t in (("position", state.x), ("velocity", state.v)):
                    if not bool(torch.isfinite(t).all()):
                        bad = t[~torch.isfinite(t)]
                        self.fail(step, quantity, float(bad[0]), state=_plain(state))
            ke = float(ke_all.max())
            if ke > self.limit:
                self.fail(step, "kinetic energy (runaway)", ke, state=_plain(state))


def _plain(state):
    """``state`` if its positions are laid out as the grid's ``(B, 3, D, H, W)``, else None (a packed state)."""
    return state if getattr(state, "x", None) is not None and state.x.dim() == 5 else None


def _speed(fn, t: float, dt: float) -> float:
    """|d fn / dt| (m/s) at ``t`` of a position function ``t -> (3,)``, by a difference over one step."""
    a, b = (torch.as_tensor(fn(s), dtype=torch.float64).reshape(-1, 3)[0] for s in (t, t + dt))
    return float((b - a).norm()) / dt


@torch.no_grad()
def likely_causes(model, t: float, dt: float, *, state=None) -> str:
    """One sentence naming the model's terms that most likely made a run diverge, the likeliest first.

    Every term the model has is weighed: tools in contact (how deep they are in the body, how far they
    move per step against the spacing, whether they swallow the body), grasps, strain limits, damping
    (none: said so), loads, drags and gravity. A term the model does not have is not named.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` of the run (its ``interactions`` read by duck
            typing: contacts have ``tools``, grasps a ``tool``).
        t: the time of the divergence (s).
        dt: the time step (s).
        state: the state that diverged, or None (then the rest positions are used).

    Returns:
        ``"likely cause: ...; also in this scene: ..."``, or ``""`` for a model with no term to name.

    Examples:
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=0.01)
        >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, gravity=(-9.81, 0, 0))
        >>> likely_causes(model, 0.0, 1e-4)
        'likely cause: no damping (add [material] damping or [boundary] decay), with gravity'
    """
    h = min(model.grid.spacing)
    X = model.X
    x = X
    if state is not None and bool(torch.isfinite(state.x).all()):
        x = state.x
    nodes = model.grid.nodes().to(X.device)
    n_nodes = max(int(nodes.sum()), 1)
    undamped = model.damping is None and not model.decay
    strong, weak = [], []
    for obj in model.interactions:
        kind = type(obj).__name__
        tools = list(getattr(obj, "tools", None) or ([obj.tool] if getattr(obj, "tool", None) is not None else []))
        if not tools:
            if kind == "StrainLimit":
                weak.append("strain limiting (its projections add energy when a step stretches springs far)")
            continue
        for tool in tools:
            what = f'grasp of tool "{tool.name}"' if kind == "Grasp" else f'tool "{tool.name}"'
            d_rest, _ = tool.sdf(X, t)
            inside = float(((d_rest[:, 0] < 0) & nodes).sum()) / n_nodes
            if inside > 0.5 and kind != "Grasp":
                strong.insert(
                    0,
                    f"{what} swallows the body ({inside:.0%} of its rest nodes are inside the tool at "
                    f"t = {t:.3g} s): move the tool out of the body (its position or path, its size)",
                )
                continue
            k_pen = getattr(obj, "stiffness", None) if kind == "PenaltyContact" else None
            if k_pen is not None:
                m = float(model.mass.expand(1, 1, *model.grid.shape)[0, 0][nodes].min())
                limit = 2.0 * math.sqrt(m / float(k_pen))  # symplectic Euler on one node against the tool
                if dt > limit:
                    strong.append(
                        f"{what}'s penalty stiffness {float(k_pen):.3g} N/m, which needs dt < {limit:.3g} s on "
                        f"nodes of {m:.3g} kg: lower the tool's stiffness or the time step"
                    )
                    continue
            d, _ = tool.sdf(x, t)
            depth = max(0.0, -float(torch.where(nodes, d[:, 0], torch.zeros_like(d[:, 0])).min()))
            step = _speed(tool.position, t, dt) * dt
            if kind != "Grasp" and (depth > h or step > 0.5 * h):
                strong.append(
                    f"{what}, {depth * 1e3:.3g} mm deep in the body, moving {step * 1e3:.3g} mm per step "
                    f"({step / h:.2g} x the spacing {h * 1e3:.3g} mm): slow it down or take smaller steps"
                )
            else:
                (strong if undamped else weak).append(f"{what} pressing the body")
    for drag in model.drags:
        step = _speed(drag.at, t, dt) * dt
        text = f"a drag moving {step * 1e3:.3g} mm per step ({step / h:.2g} x the spacing)"
        (strong if step > 0.5 * h else weak).append(text)
    if model.loads:
        peak = max(float(dense.norm(dim=1).max()) for _, dense in model.loads)
        weak.append(f"loads (up to {peak:.3g} N on a node)")
    if model.gravity is not None and bool((model.gravity != 0).any()):
        weak.append("gravity")
    if undamped:
        fix = "no damping (add [material] damping or [boundary] decay)"
        if strong:
            strong.append(fix)
        else:
            strong.insert(0, fix)
    if not strong and not weak:
        return ""
    if not strong:
        return "likely cause, among " + ", ".join(weak) + ": one of them too large for this body"
    text = "likely cause: " + "; ".join(strong)
    if weak:
        text += ", with " if len(strong) == 1 and strong[0].startswith("no damping") else "; also in this scene: "
        text += ", ".join(weak)
    return text
