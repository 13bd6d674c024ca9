"""``torchdeform bench accuracy``: error against run time of every integrator.

Each *case* is one scene x one method x one parameter; it gives one row with the common
columns ``scene, method, param, dt, steps, error, wall_s, status`` (and a few more). Methods
are entries of :data:`METHODS`; a new method (ChainMail against mass-spring, inverse-warp
iterations ...) is one more entry that says which scenes it applies to, which parameters it
sweeps and how one run is computed and compared with the scene's reference.

Scenes (:data:`SCENES`; cubes of side 4 cm, ``n^3`` nodes, 26 neighbours, 1000 kg/m^3, float64):

=============  ==============================================================================
load           bottom face fixed, a traction of (-100, 100, 0) Pa on the top face from t = 0
               (a step load), damped; run to about the first peak of the response
stiff          the same cube 100x stiffer, the load ramped in over the whole run: slow loading
               of a stiff body, where the explicit stability bound is tiny and implicit Euler
               can take steps far above it
drag           bottom face fixed, the central top patch dragged sideways 4 mm along a path
               (:class:`~torchdeform.sim.forces.Drag`), then held
supports       "falling onto fixed supports": the cube is released from rest under gravity held
               only by four fixed support nodes on its bottom face (posts fixed from t = 0); it
               drops and sags onto them. The supports stay fixed nodes, a smooth problem whose
               errors show each integrator's order; a contact with static obstacles
               (:mod:`torchdeform.interact`, a fixed tool) is not smooth and is tested there
load-static    the ``load`` cube at equilibrium, at several resolutions (the resolution sweep)
=============  ==============================================================================

Reference and error. A dynamic scene's reference is RK4 at a step of ``rk4 bound / ref_div``
(default 20), checked by halving: RK4 at twice that step is also run and their difference is
reported (RK4 is 4th order, so the reference's own error is about 1/15 of it). The error of
a run is the largest node position error over the output times ``T/4, T/2, 3T/4, T``,
divided by the largest node displacement of the reference over the same times:
``max_{t, node} |x - x_ref| / max_{t, node} |x_ref - X|``. Every time step is a multiple of a
stability bound from :func:`~torchdeform.sim.stability.time_step_bound` (power iteration): each
explicit integrator's own bound, the symplectic Euler bound for implicit Euler (whose own bound
is infinite). The step is then shrunk so that a whole number of steps lands on every output
time; ``dt_bound`` is the step actually used over the bound.

Wall time: ``time.perf_counter`` around the run (:func:`~torchdeform.sim.engine.simulate`
with its divergence checks), after one untimed warm-up step; the median of ``--repeats`` runs
(default 3; runs slower than 0.5 s are timed once), 1 with ``--quick``. A run that raises
:class:`~torchdeform.errors.DivergenceError`, ends non-finite, or ends with an error above 10 or
a kinetic energy above 100x the reference's largest (it is blowing up but the monitor has not
caught it yet) is a ``diverged`` row.

The scenes have global drag (``decay``), which every integrator applies after its step
(:meth:`~torchdeform.sim.integrators.Integrator.finish`, a splitting): at small steps that splitting
error, not RK4's own, limits RK4's observed order (about 2 instead of 4).

Resolution sweep (``load-static``). The continuum limit needs physically scaled parameters:
masses from ``density=`` (``rho h^3`` per node), and spring constants ``k = E h s`` with the
node spacing ``h``, a lattice modulus ``E`` (Pa) and ``s`` the share of the grid cells that
border the spring (1 inside; for a spring lying in the body's surface 1/2, on an edge of the
box 1/4), the spring counterpart of lumped masses. In 3-D a lattice's elastic modulus is
``~ k / h``, so ``k ~ E h`` keeps it fixed; the 1-D rule ``k = Y / l0`` (``normalize=True``)
does not. Dashpots scale the same way (``c = tau k``). The static equilibrium is solved with
implicit Euler at ``dt = 1e4 s``, which is Newton's method on ``F(x) = 0`` (``M / dt^2 -> 0``),
until the largest node move is below 1e-8 (1e-10 for the reference) of the displacement; the
coarse grids (default n = 3, 5, 9) are compared with the fine one (n = 17) at the coarse nodes,
which coincide with fine nodes because ``n - 1`` divides ``n_ref - 1``.

Knoche relaxation is left out: it is a first-order relaxation of offsets towards a harmonic
interpolation of fixed nodes (no masses, forces or loads), not a time integrator of these
dynamics nor a solver of this equilibrium.

Example:
    torchdeform bench accuracy --quick
    torchdeform bench accuracy --out accuracy-out            # about 2 minutes on 2 cores
    torchdeform bench accuracy --scenes load,stiff --methods rk4,implicit --json
"""

from __future__ import annotations

import contextlib
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import ConfigError, DivergenceError
from ..options import integer, number
from ..outputs import save_figure
from ..sim.adaptive import PAIRS, Adaptive
from ..sim.catalog import INTEGRATORS
from ..sim.engine import simulate
from ..sim.forces import Drag, SurfaceForce
from ..sim.grid import Grid
from ..sim.integrators import RK4, DampedVerlet, ImplicitEuler
from ..sim.model import Model, State
from ..sim.projective import ProjectiveDynamics
from ..sim.stability import time_step_bound
from .common import add_common, device_sync, emit, machine_info, progress

HELP = (
    "error against wall time of every integrator on standard scenes (load, stiff, drag, "
    "supports) and a resolution sweep; Pareto front and a computed recommendation"
)

#: Columns every row has (``None`` where a column does not apply).
COLUMNS = (
    "scene",
    "method",
    "param",
    "n",
    "dt",
    "bound_s",
    "bound_of",
    "dt_bound",
    "steps",
    "error",
    "wall_s",
    "repeats",
    "status",
    "pareto",
    "note",
)

TABLE = [
    ("scene", "scene", None),
    ("method", "method", None),
    ("param", "param", None),
    ("dt", "dt [s]", "{:.2e}"),
    ("dt_bound", "dt/bound", "{:.3g}"),
    ("steps", "steps", None),
    ("error", "error", "{:.2e}"),
    ("wall_s", "wall [s]", "{:.3g}"),
    ("status", "status", None),
    ("pareto", "pareto", None),
    ("note", "note", None),
]

TARGETS = (1e-1, 1e-2, 1e-4)
REPEAT_LIMIT_S = 0.5  # runs slower than this are timed once
BLOWUP_ERROR = 10.0  # a finished run with a larger error has blown up ...
N_OUT = 4  # output times T/4, T/2, 3T/4, T
MAX_DT_CHANGE = 0.3  # a multiple is not run if landing on the output times changes dt more
BLOWUP_ENERGY = 100.0  # ... or a kinetic energy above this many times the reference's largest
STATIC_DT = 1e4  # implicit Euler step that makes it Newton's method on F(x) = 0
SIDE = 0.04  # cube side (m)
DENSITY = 1000.0  # kg/m^3


# ------------------------------------------------------------------------ scenes


def cell_share(grid: Grid) -> torch.Tensor:
    """Share of the grid cells bordering each spring, float64 ``(S, D, H, W)``.

    A spring along half-direction ``d`` lies in the cells spanned by ``[i_c, i_c + d_c]`` along
    every axis with ``d_c != 0`` and by either neighbouring cell along every axis with
    ``d_c == 0``; on the first or last node of such an axis only one of the two exists. So
    ``s = prod_{c: d_c = 0} w_c(i_c)`` with ``w_c = 1/2`` on the first and last node of axis
    ``c`` and 1 elsewhere (interior springs 1, springs in a face of the box 1/2, along an edge
    of the box 1/4): the weights that make a lattice with ``k = E h s`` the same material at
    every resolution, as :func:`~torchdeform.sim.model.lumped_mass` does for masses.
    Entries of springs that leave the grid are unused.
    """
    out = torch.ones((grid.S,) + grid.shape, dtype=torch.float64)
    for s, d in enumerate(grid.directions):
        for axis, (dc, n) in enumerate(zip(d, grid.shape)):
            if dc == 0 and n > 1:
                w = torch.ones(n, dtype=torch.float64)
                w[0] = w[-1] = 0.5
                out[s] = out[s] * w.view([-1 if a == axis else 1 for a in range(3)])
    return out


def cube(n: int, modulus: float, tau: float, decay: float | None, **terms) -> tuple[Grid, dict]:
    """A ``n^3`` cube of side :data:`SIDE`, 26 neighbours, scaled for a continuum limit.

    Springs ``k = modulus * h * cell_share`` (N/m) with ``h = SIDE / (n - 1)``, dashpots
    ``c = tau * k`` (N s/m), masses from :data:`DENSITY`, global drag ``decay`` (1/s), bottom
    face fixed unless ``terms`` gives ``fixed``.

    Returns:
        ``(grid, kwargs)``: ``Model(grid, **kwargs, dtype=..., device=...)`` builds the model.
    """
    h = SIDE / (n - 1)
    grid = Grid((n, n, n), spacing=h, topology=26)
    k = modulus * h * cell_share(grid)
    kwargs = dict(stiffness=k, damping=tau * k, density=DENSITY, decay=decay)
    kwargs["fixed"] = grid.face("bottom")
    kwargs.update(terms)
    return grid, kwargs


def _quarter_nodes(n: int) -> list[int]:
    return sorted({round((n - 1) / 4), round(3 * (n - 1) / 4)})


def _load(n, T):
    return cube(n, 5e3, 4e-4, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0))])


def _stiff(n, T):
    return cube(n, 5e5, 4e-5, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0), ramp=T)])


def _inclusion(n, T):
    """The load cube with a bone-like inclusion: springs inside a central ball 1000x stiffer.

    The ball (radius a quarter of the side, and at least the central nodes) has 1000x the modulus and the same relaxation time
    ``tau`` (so 1000x the dashpots); a spring between the ball and the tissue is the two in
    series (harmonic mean of its ends' factors).
    """
    from ..sim.springs import harmonic_mean_of_ends

    grid, kw = cube(n, 5e3, 4e-4, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0))])
    idx = torch.arange(n, dtype=torch.float64) - (n - 1) / 2
    r2 = idx.view(-1, 1, 1) ** 2 + idx.view(1, -1, 1) ** 2 + idx.view(1, 1, -1) ** 2
    radius2 = max(((n - 1) / 4) ** 2, 0.75)  # at least the central node(s)
    factor = torch.where(r2 <= radius2 + 1e-9, 1000.0, 1.0).to(torch.float64)
    per_spring = harmonic_mean_of_ends(factor[None], grid)[0]
    kw["stiffness"] = kw["stiffness"] * per_spring
    kw["damping"] = kw["damping"] * per_spring
    return grid, kw


def _drag(n, T):
    grid, kw = cube(n, 5e3, 4e-4, 20.0)
    c, r = (n - 1) / 2, (n - 1) / 4
    idx = torch.arange(n, dtype=torch.float64)
    near = (idx - c).abs() <= r + 1e-9
    patch = grid.face("top") & near.view(1, n, 1) & near.view(1, 1, n)
    kw["drags"] = [Drag(patch, [(0.0, (0.0, 0.0, 0.0)), (T / 2, (0.0, 0.004, 0.0))])]
    return grid, kw


def _supports(n, T):
    grid, kw = cube(n, 5e3, 4e-4, 20.0, gravity=(-9.81, 0.0, 0.0))
    q = _quarter_nodes(n)
    kw["fixed"] = grid.index_mask([(0, i, j) for i in q for j in q])
    return grid, kw


@dataclass(frozen=True)
class AccuracyScene:
    """One standard scene.

    Args:
        name, help: its name in the rows and one line for the report.
        build: ``(n, T) -> (grid, Model kwargs)``.
        duration, quick_duration: run length ``T`` (s), default and ``--quick``.
        static: True for an equilibrium scene (compared at ``T = inf``, no time steps).
        multiples: per-method overrides of the step multiples, ``{method: (default, quick)}``.
        ref_div: the reference step is the RK4 bound divided by this (``--ref-div`` overrides).
    """

    name: str
    help: str
    build: Callable
    duration: float = 0.0
    quick_duration: float = 0.0
    static: bool = False
    multiples: dict = field(default_factory=dict)
    ref_div: float | None = None


# The stiff scene is the expensive one for explicit methods: fewer small steps there.
_STIFF = ((0.45, 0.9, 2), (0.9, 2))
_STIFF_EULER = ((0.9, 10), (0.9, 10))
_INCLUSION = ((0.9, 2), (0.9,))
SCENES = {
    "load": AccuracyScene(
        "load",
        "bottom fixed, top traction (-100, 100, 0) Pa from t=0, E 5 kPa, dashpots tau 0.4 ms, drag 20/s",
        _load,
        0.045,
        0.03,
    ),
    "stiff": AccuracyScene(
        "stiff",
        "load scene 100x stiffer (E 500 kPa, tau 0.04 ms), traction ramped in over the whole run",
        _stiff,
        0.03,
        0.003,
        multiples={
            "explicit": _STIFF_EULER,
            "symplectic": _STIFF,
            "verlet": _STIFF,
            "rk4": _STIFF,
            "implicit": ((5, 10, 20, 50), (4,)),
        },
        ref_div=5,
    ),
    "inclusion": AccuracyScene(
        "inclusion",
        "the load cube with a central bone-like ball (radius 1 cm) 1000x stiffer than the tissue around it",
        _inclusion,
        0.015,
        0.0015,
        multiples={
            "explicit": _STIFF_EULER,
            "symplectic": _INCLUSION,
            "verlet": _INCLUSION,
            "rk4": _INCLUSION,
            "implicit": ((5, 20, 100, 300), (20,)),
            "adaptive": ((1e-2, 1e-4), (1e-2,)),
            "projective": (((20, 10), (100, 10), (300, 10), (100, 30)), ((100, 10),)),
        },
        ref_div=5,
    ),
    "drag": AccuracyScene(
        "drag", "bottom fixed, central top patch dragged 4 mm sideways over T/2, then held", _drag, 0.045, 0.03
    ),
    "supports": AccuracyScene(
        "supports",
        "released under gravity onto 4 fixed support nodes of its "
        "bottom face (fixed nodes from t=0: smooth, no contact)",
        _supports,
        0.045,
        0.03,
    ),
    "load-static": AccuracyScene(
        "load-static", "the load cube at equilibrium, resolution sweep against a fine grid", _load, static=True
    ),
}


@dataclass
class Reference:
    """Reference solution of a scene: node positions at the output times.

    Attributes:
        x: ``(N_OUT, B, 3, D, H, W)`` (dynamic) or ``(1, B, 3, D, H, W)`` of the fine grid (static).
        scale: largest node displacement ``|x - X|`` of the reference (m).
        info: a JSON-able description (method, dt, steps, self-check).
        kinetic: largest kinetic energy at the output times (J), None for a static reference.
    """

    x: torch.Tensor
    scale: float
    info: dict
    kinetic: float | None = None


class Context:
    """One scene, built once: the model, its start state, duration and (cached) bounds.

    Args:
        scene: the :class:`AccuracyScene`; n: grid size; quick: shorter run.
        dtype, device: of the model.
    """

    def __init__(self, scene: AccuracyScene, n: int, quick: bool, dtype, device):
        self.scene, self.n, self.quick, self.dtype, self.device = scene, n, quick, dtype, device
        self.duration = scene.quick_duration if quick else scene.duration
        self.grid, self.kwargs = scene.build(n, self.duration)
        self.model = self.make_model()
        self._bounds: dict = {}
        self.reference: Reference | None = None

    def make_model(self, **override) -> Model:
        """``Model`` of this scene, with some keyword arguments replaced."""
        return Model(self.grid, **{**self.kwargs, **override}, dtype=self.dtype, device=self.device)

    def bound(self, name: str) -> float:
        """``time_step_bound(model, name)`` (power iteration), computed once per name.

        Explicit Euler's bound with dashpots is ``min(c / k, 2 / Lc)`` and does not use
        ``omega_max``, so it is asked for with ``method="gershgorin"``, which skips the power
        iteration and gives the same number.
        """
        if name not in self._bounds:
            damped = self.model.damping is not None
            method = "gershgorin" if name == "explicit" and damped else "power"
            self._bounds[name] = time_step_bound(self.model, name, method=method)
        return self._bounds[name]

    def steps_for(self, dt: float, multiple_of: int = N_OUT, at_most: bool = True) -> tuple[int, float]:
        """Steps that land on every output time: ``(steps, dt used)``.

        ``at_most``: the step used is at most ``dt`` (for steps that must stay below a
        stability bound); otherwise the nearest step count (at least one per output interval).
        """
        per = self.duration / (multiple_of * dt)
        m = math.ceil(per - 1e-9) if at_most else round(per)
        steps = multiple_of * max(1, m)
        return steps, self.duration / steps


def relative_error(x: torch.Tensor, ref: torch.Tensor, scale: float) -> float:
    """``max |x - ref| / scale`` over everything but the channel axis.

    Args:
        x: positions ``(..., 3, D, H, W)`` with the channel at dim -4.
        ref: reference positions, the same shape (or broadcastable).
        scale: the reference's largest displacement (m).
    """
    diff = (x.double() - ref.double()).norm(dim=-4)
    return float(diff.max()) / scale


def _displacement(x: torch.Tensor, X: torch.Tensor) -> float:
    return float((x.double() - X.double().cpu()).norm(dim=-4).max())


def kinetic_energy(mass: torch.Tensor, v: torch.Tensor) -> float:
    """Largest kinetic energy (J) over the leading axes of ``v`` ``(..., 3, D, H, W)``.

    ``mass`` broadcasts as ``(1, 1, D, H, W)``.
    """
    e = 0.5 * (mass.double().cpu() * v.double() ** 2).sum(dim=(-4, -3, -2, -1))
    return float(e.max())


# ---------------------------------------------------------------------- methods


@dataclass
class Job:
    """A prepared run.

    Attributes:
        run: what is timed; returns the positions at the output times ``(T_out, B, 3, D, H, W)``
            (CPU), or ``(positions, velocities)`` of that shape; raises ``DivergenceError``.
        warmup: runs untimed before it.
        info: the row's ``n``, ``dt``, ``bound_s``, ``bound_of``, ``dt_bound``, ``steps``, ``note``.
        iters: iteration counts that ``run`` appends (they replace ``steps`` in the row), if any.
    """

    run: Callable
    warmup: Callable
    info: dict
    iters: list = field(default_factory=list)


class Method:
    """One family of rows.

    Subclasses set :attr:`name` and :attr:`description` and implement :meth:`applies`,
    :meth:`params` and :meth:`prepare`.
    """

    name = "method"
    description = ""

    def applies(self, scene: AccuracyScene) -> bool:  # pragma: no cover
        """Whether this method runs on ``scene`` (dynamic or static scenes)."""
        raise NotImplementedError

    def params(self, ctx: Context) -> list:  # pragma: no cover
        """The parameters swept on this scene (``ctx.quick`` for the short list)."""
        raise NotImplementedError

    def skip(self, ctx: Context, param) -> str | None:
        """Why a parameter is not run on this scene, or None."""
        return None

    def label(self, param) -> str:
        """The row label of a parameter."""
        return str(param)

    def prepare(self, ctx: Context, param) -> Job:  # pragma: no cover
        """The :class:`Job` that runs ``param`` on ``ctx``'s scene."""
        raise NotImplementedError

    def compare(self, ctx: Context, x: torch.Tensor) -> float:
        """Error of the run's output against the scene's reference."""
        return relative_error(x, ctx.reference.x, ctx.reference.scale)


class TimeStepping(Method):
    """An integrator of :data:`~torchdeform.sim.integrators.INTEGRATORS` at multiples of a stability bound.

    The time steps are multiples of the bound of ``bound_of``.

    Args:
        name: the integrator's name.
        make: ``(ctx, dt) -> (integrator, model)`` (the model may be a variant of the scene's).
        bound_of: whose :func:`time_step_bound` the multiples refer to.
        multiples, quick_multiples: default and ``--quick`` multiples.
        note: text for every row.
    """

    def __init__(self, name, make, bound_of, multiples, quick_multiples, description="", note=""):
        self.name, self.make, self.bound_of = name, make, bound_of
        self.multiples, self.quick_multiples, self.note = tuple(multiples), tuple(quick_multiples), note
        self.description = description

    def applies(self, scene):
        """Dynamic scenes only."""
        return not scene.static

    def params(self, ctx):
        """The bound multiples of this integrator on the scene (``ctx.quick``: the short list)."""
        default, fast = ctx.scene.multiples.get(self.name, (self.multiples, self.quick_multiples))
        return list(fast if ctx.quick else default)

    def steps(self, ctx, param) -> tuple[int, float]:
        """``(steps, dt)`` for a multiple.

        At most the requested step below the bound (so "0.9x" stays stable), the nearest step
        count that lands on the output times above it.
        """
        return ctx.steps_for(param * ctx.bound(self.bound_of), at_most=param <= 1)

    def skip(self, ctx, param):
        """Why a multiple is not run: no whole number of steps per output interval near its ``dt``; or None."""
        want = param * ctx.bound(self.bound_of)
        dt = self.steps(ctx, param)[1]
        if abs(dt / want - 1) > MAX_DT_CHANGE:
            return (
                f"no whole number of steps near dt = {want:.2g} s per output interval "
                f"T/{N_OUT} = {ctx.duration / N_OUT:.2g} s"
            )
        return None

    def label(self, param):
        """``"0.9x"``: the multiple of the stability bound."""
        return f"{param:g}x"

    def prepare(self, ctx, param):
        """A :class:`Job` simulating the scene at the multiple's ``dt``, recording the output times."""
        bound = ctx.bound(self.bound_of)
        steps, dt = self.steps(ctx, param)
        integ, model = self.make(ctx, dt)
        state0 = model.rest_state()

        def run():
            _, rec = simulate(model, state0, dt, steps, integ, record_every=steps // N_OUT, warn=False)
            return rec["x"][1:], rec["v"][1:]

        def warmup():
            integ.step(model, state0, dt)

        note = self.note(ctx, dt) if callable(self.note) else (self.note or None)
        info = dict(n=ctx.n, dt=dt, bound_s=bound, bound_of=self.bound_of, dt_bound=dt / bound, steps=steps, note=note)
        return Job(run, warmup, info)


def _plain(cls):
    return lambda ctx, dt: (cls(), ctx.model)


def _verlet(ctx, dt):
    """Damped Verlet solving the same equations.

    The model's global drag ``c`` is replaced by Verlet's per-step damping
    ``kd = 1 - exp(-c dt)`` (so ``v' = exp(-c dt) v + dt a``).
    """
    decay = ctx.model.decay or 0.0
    return DampedVerlet(kd=1.0 - math.exp(-decay * dt)), ctx.make_model(decay=None)


def _verlet_note(ctx, dt):
    decay = ctx.model.decay or 0.0
    return f"kd {1.0 - math.exp(-decay * dt):.2g}" if decay else "kd 0 (= symplectic Euler)"


class ProjectiveIterations(TimeStepping):
    """Projective dynamics at a multiple of the symplectic Euler bound and an iteration count.

    The parameter is ``(multiple, iterations)``; the solver is ``"auto"`` (a pre-factored
    Cholesky on these small grids).
    """

    def __init__(self, multiples, quick_multiples):
        super().__init__(
            "projective",
            None,
            "symplectic",
            multiples,
            quick_multiples,
            "projective dynamics (Liu et al. 2013: local/global iterations, constant matrix "
            "pre-factored); param = multiple of the symplectic Euler bound / iterations per step",
        )
        self._iterations = 10
        self.make = lambda ctx, dt: (ProjectiveDynamics(iterations=self._iterations), ctx.model)

    def steps(self, ctx, param):
        """``(steps, dt)`` for the multiple (``param`` or ``param[0]``)."""
        return super().steps(ctx, param[0] if isinstance(param, tuple) else param)

    def skip(self, ctx, param):
        """As :meth:`TimeStepping.skip`, for the multiple."""
        return super().skip(ctx, param[0])

    def label(self, param):
        """``"20x/10it"``."""
        return f"{param[0]:g}x/{param[1]}it"

    def prepare(self, ctx, param):
        """A :class:`Job` at the multiple's ``dt`` with ``param[1]`` iterations per step."""
        self._iterations = param[1]
        return super().prepare(ctx, param)


class AdaptiveTolerance(Method):
    """:class:`~torchdeform.sim.adaptive.Adaptive` steps at a requested tolerance ``rtol`` (the parameter).

    The run asks for the output times only (``dt = T / 4``, four intervals) and the error control
    chooses the steps. The row's ``dt`` is the mean step taken, ``dt_bound`` that over the RK4
    bound, ``steps`` the tries (accepted and rejected); its note gives both counts and the
    smallest step.

    Args:
        pair: the embedded pair (:data:`~torchdeform.sim.adaptive.PAIRS`).
        tolerances, quick_tolerances: the ``rtol`` values of the default and ``--quick`` runs.
    """

    def __init__(
        self, pair="bogacki_shampine", tolerances=(1e-2, 1e-3, 1e-4, 1e-5, 1e-6), quick_tolerances=(1e-2, 1e-4)
    ):
        self.pair, self.tolerances, self.quick_tolerances = pair, tolerances, quick_tolerances
        self.name = "adaptive" if pair == "bogacki_shampine" else f"adaptive-{pair}"
        p = PAIRS[pair]
        self.description = (
            f"embedded Runge-Kutta pair {pair} (order {p.order}, error estimate of order "
            f"{p.error_order}) at a requested tolerance rtol; it chooses its own steps"
        )

    def applies(self, scene):
        """Dynamic scenes only."""
        return not scene.static

    def params(self, ctx):
        """The tolerances (``ctx.quick``: the short list; a scene may set its own)."""
        default, fast = ctx.scene.multiples.get(self.name, (self.tolerances, self.quick_tolerances))
        return list(fast if ctx.quick else default)

    def label(self, param):
        """``"rtol 1e-03"``."""
        return f"rtol {param:.0e}"

    def prepare(self, ctx, param):
        """A :class:`Job` running the scene with ``Adaptive(rtol=param)`` between the output times."""
        model, bound = ctx.model, ctx.bound("rk4")
        interval = ctx.duration / N_OUT
        state0 = model.rest_state()
        info = dict(n=ctx.n, dt=None, bound_s=bound, bound_of="rk4", dt_bound=None, steps=None, note=None)

        def run():
            adaptive = Adaptive(rtol=param, pair=self.pair)
            _, rec = simulate(model, state0, interval, N_OUT, adaptive, record_every=1, warn=False)
            st = adaptive.stats
            mean = ctx.duration / max(st["accepted"], 1)
            info.update(
                dt=mean,
                dt_bound=mean / bound,
                steps=st["accepted"] + st["rejected"],
                note=f"{st['accepted']} accepted, {st['rejected']} rejected, smallest step "
                f"{st['min_h'] / bound:.2g}x the bound",
            )
            return rec["x"][1:], rec["v"][1:]

        def warmup():
            Adaptive(rtol=param, pair=self.pair).step(model, state0, interval / 1000)

        return Job(run, warmup, info)


class StaticResolution(Method):
    """Static equilibrium of a ``static`` scene at grid size ``n`` (the parameter).

    Compared against the scene's reference at ``ref_n``, at the coarse nodes. Solved by implicit
    Euler at ``dt = STATIC_DT`` (Newton's method on ``F(x) = 0``) until the largest node move is
    below ``tol`` times the displacement.
    """

    name = "static"
    description = (
        "static equilibrium at grid size n (implicit Euler at dt = 1e4 s = Newton, to 1e-8), "
        "against a fine grid at the coarse nodes; wall time of the solve"
    )

    def __init__(self, resolutions=(3, 5, 9), quick_resolutions=(2, 3), tol: float = 1e-8, max_iters: int = 60):
        self.resolutions, self.quick_resolutions = tuple(resolutions), tuple(quick_resolutions)
        self.tol, self.max_iters = tol, max_iters

    def applies(self, scene):
        """Static scenes only."""
        return scene.static

    def params(self, ctx):
        """The grid sizes ``n`` (``ctx.quick``: the short list)."""
        return list(self.quick_resolutions if ctx.quick else self.resolutions)

    def label(self, param):
        """``"n=5"``."""
        return f"n={param}"

    @staticmethod
    def tolerance(tol: float, dtype) -> float:
        """``tol`` raised to ``1000 eps`` of ``dtype``."""
        return max(tol, 1e3 * torch.finfo(dtype).eps)

    def solve(self, model: Model, tol: float):
        """Newton iterations via implicit Euler; returns ``(x (B, 3, D, H, W), iterations)``.

        ``tol`` is raised to ``1000 eps`` of the model's dtype (float32 cannot reach 1e-8).

        Raises:
            DivergenceError: if it does not converge within ``max_iters`` or goes non-finite.
        """
        tol = self.tolerance(tol, model.dtype)
        integ = ImplicitEuler(cg_iters=4000, cg_tol=max(1e-10, 10 * torch.finfo(model.dtype).eps))
        state = model.rest_state()
        zero = torch.zeros_like(state.v)
        with torch.no_grad():
            for it in range(1, self.max_iters + 1):
                new = integ.step(model, State(state.x, zero, 0.0), STATIC_DT)
                move = float((new.x - state.x).norm(dim=1).max())
                state = new
                if not math.isfinite(move):
                    raise DivergenceError(it, "position", move, STATIC_DT, None)
                if move <= tol * _displacement(state.x, model.X):
                    return state.x, it
        raise DivergenceError(self.max_iters, "Newton update (not converged)", move, STATIC_DT, None)

    def prepare(self, ctx, param):
        """A :class:`Job` solving the static equilibrium at grid size ``n = param``."""
        n = int(param)
        grid, kwargs = ctx.scene.build(n, 0.0)
        model = Model(grid, **kwargs, dtype=ctx.dtype, device=ctx.device)
        iters = []

        def run():
            x, it = self.solve(model, self.tol)
            iters.append(it)
            return x.detach().cpu()[None]

        def warmup():
            model.forces(model.X, torch.zeros_like(model.X))

        info = dict(n=n, dt=None, bound_s=None, bound_of=None, dt_bound=None, steps=None, note=None)
        return Job(run, warmup, info, iters)

    def compare(self, ctx, x):
        """Error at the coarse nodes against the fine reference (every ``(ref_n - 1) / (n - 1)``-th node)."""
        ref_n = ctx.n
        n = x.shape[-1]
        stride = (ref_n - 1) // (n - 1)
        sub = ctx.reference.x[..., ::stride, ::stride, ::stride]
        return relative_error(x, sub, ctx.reference.scale)


_EXPLICIT = (0.1, 0.2, 0.45, 0.9, 2)
_QUICK = (0.45, 0.9, 2)
#: integrator name -> (whose bound the multiples refer to, (multiples, quick multiples), description).
#: Explicit Euler's instability above its bound grows slowly (|1 + h lambda| only a little above 1),
#: so its "well above" multiple is 10x.
_SPECS = {
    "explicit": (
        "explicit",
        ((0.1, 0.2, 0.45, 0.9, 10), (0.9, 10)),
        "explicit Euler; dt in multiples of its own bound (c/k of the dashpots)",
    ),
    "symplectic": ("symplectic", (_EXPLICIT, _QUICK), "symplectic Euler; multiples of its own bound"),
    "verlet": (
        "symplectic",
        (_EXPLICIT, (0.9, 2)),
        "damped Verlet with kd = 1 - exp(-drag dt) in place of the model's global drag (the same "
        "equations); multiples of the symplectic Euler bound (the same as its own)",
    ),
    "rk4": ("rk4", (_EXPLICIT, _QUICK), "classic RK4; multiples of its own bound (2 sqrt 2 / omega_max)"),
    "implicit": (
        "symplectic",
        ((0.5, 1, 2, 5, 10), (4,)),
        "implicit Euler (Baraff-Witkin, CG 100 iterations to 1e-6: the defaults); multiples of the "
        "symplectic Euler bound (its own is infinite)",
    ),
}

#: Integrators of INTEGRATORS that have no rows, with the reason printed in the report.
SKIPPED = {
    "knoche": "left out: Knoche relaxation is a first-order relaxation of offsets towards a harmonic "
    "interpolation of fixed nodes (no masses, forces or loads), not a time integrator of these "
    "dynamics nor a solver of this equilibrium"
}


def _methods() -> dict:
    out = {}
    for name, cls in INTEGRATORS.items():
        if name in _SPECS:
            bound_of, (mult, quick), description = _SPECS[name]
            make = _verlet if name == "verlet" else _plain(cls)
            note = _verlet_note if name == "verlet" else None
            out[name] = TimeStepping(name, make, bound_of, mult, quick, description, note)
    out["projective"] = ProjectiveIterations(((5, 3), (5, 10), (5, 30), (20, 10), (50, 10)), ((5, 10),))
    out["adaptive"] = AdaptiveTolerance()
    out["static"] = StaticResolution()
    return out


#: name -> :class:`Method`. A new row family is one more entry.
METHODS = _methods()
for _name in INTEGRATORS:
    if _name not in METHODS and _name not in SKIPPED:  # a new integrator without a spec yet
        SKIPPED[_name] = "left out: no accuracy settings for this integrator yet (add it to _SPECS)"


# -------------------------------------------------------------------- references


def dynamic_reference(ctx: Context, ref_div: float) -> Reference:
    """RK4 at ``rk4 bound / ref_div``, checked against RK4 at twice that step."""
    bound = ctx.bound("rk4")
    steps, dt = ctx.steps_for(bound / ref_div, 2 * N_OUT)
    model, state0 = ctx.model, ctx.model.rest_state()
    t0 = time.perf_counter()
    _, rec = simulate(model, state0, dt, steps, RK4(), record_every=steps // N_OUT, warn=False)
    wall = time.perf_counter() - t0
    _, rec2 = simulate(model, state0, 2 * dt, steps // 2, RK4(), record_every=steps // (2 * N_OUT), warn=False)
    x = rec["x"][1:]
    scale = _displacement(x, model.X)
    kinetic = kinetic_energy(model.mass, rec["v"][1:])
    check = relative_error(rec2["x"][1:], x, scale)
    info = dict(
        method="rk4",
        dt=dt,
        dt_bound=dt / bound,
        steps=steps,
        wall_s=wall,
        max_displacement_m=scale,
        halving_diff=check,
        error_estimate=check / 15,
        text=(
            f"RK4 at dt = {dt:.3g} s (rk4 bound / {bound / dt:.3g}), {steps} steps; halving check: "
            f"RK4 at 2 dt differs by {check:.2e} (relative), so the reference is good to about "
            f"{check / 15:.1e}; max displacement {scale * 1e3:.3g} mm"
        ),
    )
    return Reference(x, scale, info, kinetic)


def static_reference(ctx: Context, method: StaticResolution) -> Reference:
    """Equilibrium on the fine grid (``ctx.n``), Newton to 1e-10."""
    t0 = time.perf_counter()
    tol = method.tolerance(1e-10, ctx.model.dtype)
    x, it = method.solve(ctx.model, tol)
    wall = time.perf_counter() - t0
    x = x.detach().cpu()[None]
    scale = _displacement(x, ctx.model.X)
    info = dict(
        method="static",
        n=ctx.n,
        newton_iterations=it,
        wall_s=wall,
        max_displacement_m=scale,
        text=(
            f"static equilibrium at n = {ctx.n} ({ctx.n**3} nodes), implicit Euler at dt = "
            f"{STATIC_DT:g} s = Newton, {it} iterations to {tol:.1g}; compared at the coarse nodes; "
            f"max displacement {scale * 1e3:.3g} mm"
        ),
    )
    return Reference(x, scale, info)


# ----------------------------------------------------------------- run and rows


def _row(scene: str, method: Method, param, info: dict, **values) -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(scene=scene, method=method.name, param=method.label(param), pareto=False)
    row.update({k: info.get(k) for k in ("n", "dt", "bound_s", "bound_of", "dt_bound", "steps", "note")})
    row.update(values)
    return row


def run_case(ctx: Context, method: Method, param, repeats: int, sync=lambda: None) -> dict:
    """Run one case; returns its row (see :data:`COLUMNS`)."""
    job = method.prepare(ctx, param)
    with torch.no_grad():
        job.warmup()
        times, x = [], None
        try:
            while len(times) < repeats:
                sync()
                t0 = time.perf_counter()
                out = job.run()
                sync()
                times.append(time.perf_counter() - t0)
                x = out if x is None else x
                if times[0] > REPEAT_LIMIT_S:
                    break
        except DivergenceError as e:
            sync()
            wall = time.perf_counter() - t0
            info = dict(job.info)
            if info.get("steps") is not None:
                info["steps"] = e.step
            return _row(
                ctx.scene.name,
                method,
                param,
                info,
                wall_s=wall,
                repeats=1,
                status="diverged",
                note=f"DivergenceError at step {e.step}: {e.quantity}",
            )
    info = dict(job.info)
    if job.iters:
        info["steps"] = job.iters[0]
    wall = statistics.median(times)
    x, v = x if isinstance(x, tuple) else (x, None)
    common = dict(wall_s=wall, repeats=len(times))
    if not bool(torch.isfinite(x).all()) or (v is not None and not bool(torch.isfinite(v).all())):
        return _row(ctx.scene.name, method, param, info, status="diverged", note="non-finite positions", **common)
    err = method.compare(ctx, x)
    why = None
    if err > BLOWUP_ERROR:
        why = f"error {err:.2g} > {BLOWUP_ERROR:g}"
    elif v is not None and ctx.reference.kinetic:
        ratio = kinetic_energy(ctx.model.mass, v) / ctx.reference.kinetic
        if ratio > BLOWUP_ENERGY:
            why = f"kinetic energy {ratio:.2g}x the reference's"
    if why:
        return _row(
            ctx.scene.name,
            method,
            param,
            info,
            error=err,
            status="diverged",
            note=why + ": blowing up, not yet caught by the monitor",
            **common,
        )
    return _row(ctx.scene.name, method, param, info, error=err, status="ok", **common)


def pareto_front(points) -> list[bool]:
    """Which points no other point beats on both coordinates.

    ``q`` dominates ``p`` when ``q <= p`` in both coordinates and ``q < p`` in at least one;
    points with a ``None`` or non-finite coordinate are never on the front and dominate nothing.

    Args:
        points: sequence of ``(error, time)`` pairs (any two "smaller is better" numbers).

    Returns:
        one bool per point, True on the front. ``O(P log P)``: sweep in order of time.
    """
    pts = [
        (i, p[0], p[1])
        for i, p in enumerate(points)
        if p[0] is not None and p[1] is not None and math.isfinite(p[0]) and math.isfinite(p[1])
    ]
    pts.sort(key=lambda q: (q[2], q[1]))
    front = [False] * len(points)
    best = math.inf  # smallest error among strictly faster points
    i = 0
    while i < len(pts):
        j = i
        while j < len(pts) and pts[j][2] == pts[i][2]:
            j += 1
        group_min = pts[i][1]  # the group is sorted by error
        if group_min < best:
            for idx, err, _ in pts[i:j]:
                front[idx] = err == group_min
        best = min(best, group_min)
        i = j
    return front


def mark_pareto(rows: list) -> None:
    """Set ``row["pareto"]`` per scene over the ``ok`` rows."""
    for scene in dict.fromkeys(r["scene"] for r in rows):
        sub = [r for r in rows if r["scene"] == scene and r["status"] == "ok"]
        for r, on in zip(sub, pareto_front([(r["error"], r["wall_s"]) for r in sub])):
            r["pareto"] = on


def recommend(rows: list, targets=TARGETS) -> list[dict]:
    """For each scene and error target, the fastest ``ok`` row whose error reaches it."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for target in targets:
            ok = [r for r in rows if r["scene"] == scene and r["status"] == "ok" and r["error"] <= target]
            best = min(ok, key=lambda r: r["wall_s"]) if ok else None
            out.append(
                dict(
                    scene=scene,
                    target=target,
                    method=best and best["method"],
                    param=best and best["param"],
                    dt=best and best["dt"],
                    steps=best and best["steps"],
                    error=best and best["error"],
                    wall_s=best and best["wall_s"],
                )
            )
    return out


def _fmt(x: float) -> str:
    """``1e-4`` rather than ``0.0001``."""
    m, e = f"{x:.0e}".split("e")
    return f"{x:g}" if 1e-2 <= x < 1e3 and float(m) != 1 else f"{m}e{int(e)}"


def recommendation_text(recs: list, targets=TARGETS) -> str:
    """The recommendation as printed: one line per scene, then the overall winner per target."""
    lines = ["recommendation (computed from the rows: fastest run reaching each error target):"]
    width = max(len(r["scene"]) for r in recs) if recs else 0
    for scene in dict.fromkeys(r["scene"] for r in recs):
        parts = []
        for r in (r for r in recs if r["scene"] == scene):
            if r["method"] is None:
                parts.append(f"<= {_fmt(r['target'])}: none reached")
            else:
                dt = "" if r["dt"] is None else f", dt {r['dt']:.2g} s"
                parts.append(f"<= {_fmt(r['target'])}: {r['method']} {r['param']}{dt} ({r['wall_s']:.2g} s)")
        lines.append(f"  {scene.ljust(width)}  " + "; ".join(parts))
    dyn = [r for r in recs if r["method"] not in (None, "static")]
    for target in targets:
        wins = {}
        for r in dyn:
            if r["target"] == target:
                wins[r["method"]] = wins.get(r["method"], 0) + 1
        if wins:
            ranked = ", ".join(
                f"{m} ({k} scene{'s' if k > 1 else ''})" for m, k in sorted(wins.items(), key=lambda kv: -kv[1])
            )
            lines.append(f"  error <= {_fmt(target)}: fastest is {ranked}")
    return "\n".join(lines)


# ---------------------------------------------------------------------- command


def _list(value, key, kind, allowed=None):
    """``"a,b"`` (or a list) -> list of ``kind``; None stays None. Raises ConfigError."""
    if value is None:
        return None
    items = value if isinstance(value, (list, tuple)) else [v.strip() for v in str(value).split(",") if v.strip()]
    try:
        values = [kind(v) for v in items]
    except ValueError:
        raise ConfigError(key, f"comma-separated values of type {kind.__name__}", value) from None
    if not values:
        raise ConfigError(key, "at least one value", value)
    if allowed is not None:
        bad = [v for v in values if v not in allowed]
        if bad:
            raise ConfigError(key, "some of " + ", ".join(allowed), ",".join(map(str, bad)))
    return values


def add_arguments(p) -> None:
    """Options of ``torchdeform bench accuracy`` (the common ones from :func:`bench.add_common`)."""
    add_common(p)
    p.set_defaults(dtype="float64", threads=1)
    p.description = (
        HELP + ". Defaults differ from bench speed: float64 and 1 thread (the scenes are "
        "tiny; one thread is fastest). Knoche relaxation is left out (it does not integrate "
        "these dynamics); 'supports' stands for falling onto supports, with the supports as "
        "fixed nodes (smooth; contact with obstacles is torchdeform.interact's)."
    )
    p.add_argument("--scenes", default=None, help="comma-separated subset of " + ",".join(SCENES) + " (default all)")
    p.add_argument("--methods", default=None, help="comma-separated subset of " + ",".join(METHODS) + " (default all)")
    p.add_argument(
        "--n", type=integer(lo=2), default=None, help="grid size of the dynamic scenes, n^3 nodes (default 5; quick 4)"
    )
    p.add_argument("--resolutions", default=None, help="grid sizes of the resolution sweep (default 3,5,9; quick 2,3)")
    p.add_argument(
        "--ref-n",
        type=integer(lo=2),
        default=None,
        help="grid size of the sweep's reference (default 17; quick 5); n-1 must divide ref-n - 1",
    )
    p.add_argument(
        "--ref-div",
        type=number(lo=1),
        default=None,
        help="reference step = RK4 bound / REF_DIV (default 20, 5 for the stiff scene; quick 5)",
    )
    p.add_argument(
        "--repeats",
        type=integer(lo=1),
        default=None,
        help=f"timed repeats, the median is kept (default 3; quick 1); runs slower than "
        f"{REPEAT_LIMIT_S:g} s are timed once",
    )
    p.add_argument("--targets", default=None, help="error targets of the recommendation (default 1e-1,1e-2,1e-4)")
    p.add_argument(
        "--inverse-warp",
        action="store_true",
        help="also rows of the fixed-point inverse warp (torchdeform.volume): round-trip error "
        "|X + u(X) - p| in voxels against iterations and wall time (scene 'inverse-warp')",
    )


def _check_args(args):
    """Validate the options; lists are parsed here so that a mistake is one ConfigError line.

    Returns ``(device, n, resolutions, ref_n)`` and sets ``args.scenes``, ``args.methods``,
    ``args.targets`` to lists (or None).
    """
    args.scenes = _list(args.scenes, "--scenes", str, list(SCENES))
    args.methods = _list(args.methods, "--methods", str, list(METHODS))
    args.targets = _list(args.targets, "--targets", float) or list(TARGETS)
    if args.threads is not None and args.threads < 1:
        raise ConfigError("--threads", "an integer >= 1", args.threads)
    device = str(torch.device(args.device))
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device", "cpu, or cuda on a machine with CUDA", args.device)
    n = args.n or (4 if args.quick else 5)
    if n < 3:
        raise ConfigError("--n", "an integer >= 3", n)
    res = _list(args.resolutions, "--resolutions", int) or list(
        StaticResolution().quick_resolutions if args.quick else StaticResolution().resolutions
    )
    ref_n = args.ref_n or (5 if args.quick else 17)
    if min(res) < 2 or ref_n < 3:
        raise ConfigError("--resolutions", "grid sizes >= 2 (and --ref-n >= 3)", res)
    for r in res:
        if r >= ref_n or (ref_n - 1) % (r - 1):
            raise ConfigError(
                "--resolutions", f"sizes n < ref-n = {ref_n} with n - 1 dividing {ref_n - 1} (e.g. 3, 5, 9 for 17)", r
            )
    if args.ref_div is not None and not (math.isfinite(args.ref_div) and args.ref_div >= 2):
        raise ConfigError("--ref-div", "a number >= 2", args.ref_div)
    if args.repeats is not None and args.repeats < 1:
        raise ConfigError("--repeats", "an integer >= 1", args.repeats)
    if any(not (0 < t < math.inf) for t in args.targets):  # also rejects NaN
        raise ConfigError("--targets", "positive error targets", args.targets)
    return device, n, res, ref_n


def run(args) -> int:
    """``torchdeform bench accuracy``: compute the rows, print/write them; returns 0."""
    device, n, resolutions, ref_n = _check_args(args)
    old_threads = torch.get_num_threads()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    try:
        return _run(args, device, n, resolutions, ref_n)
    finally:
        torch.set_num_threads(old_threads)


def _plan(args, device, dtype, n, resolutions, ref_n):
    """Build each scene's :class:`Context` and its cases.

    Returns ``(plan, not_run)`` with ``plan = [(ctx, [(method, param), ...]), ...]``.
    """
    methods = [m for k, m in METHODS.items() if args.methods is None or k in args.methods]
    methods = [StaticResolution(resolutions, resolutions) if m.name == "static" else m for m in methods]
    plan, not_run = [], []
    for sc in (SCENES[s] for s in (args.scenes or SCENES)):
        ms = [m for m in methods if m.applies(sc)]
        if not ms:
            continue
        ctx = Context(sc, ref_n if sc.static else n, args.quick, dtype, device)
        cases = []
        for m in ms:
            for p in m.params(ctx):
                why = m.skip(ctx, p)
                if why:
                    not_run.append(dict(scene=sc.name, method=m.name, param=m.label(p), reason=why))
                else:
                    cases.append((m, p))
        if cases:
            plan.append((ctx, cases))
    if not plan:
        raise ConfigError(
            "--methods",
            "at least one method that applies to the chosen scenes",
            ",".join(args.methods or []) + " on " + ",".join(args.scenes or []),
        )
    return plan, not_run


def _run(args, device, n, resolutions, ref_n) -> int:
    dtype = getattr(torch, args.dtype)
    repeats = args.repeats or (1 if args.quick else 3)
    sync = device_sync(device)
    rows, references = [], {}
    redirect = contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext()
    with redirect:
        plan, not_run = _plan(args, device, dtype, n, resolutions, ref_n)
        with progress(sum(1 + len(cases) for _, cases in plan), "bench accuracy") as bar:
            for ctx, cases in plan:
                sc = ctx.scene
                bar.set_postfix_str(f"{sc.name} reference")
                if sc.static:
                    ctx.reference = static_reference(ctx, next(m for m, _ in cases))
                else:
                    div = args.ref_div or min(sc.ref_div or 20, 5 if args.quick else math.inf)
                    ctx.reference = dynamic_reference(ctx, div)
                references[sc.name] = dict(
                    ctx.reference.info, duration_s=None if sc.static else ctx.duration, description=sc.help
                )
                bar.update(1)
                for m, p in cases:
                    bar.set_postfix_str(f"{sc.name} {m.name} {m.label(p)}")
                    rows.append(run_case(ctx, m, p, repeats, sync))
                    bar.update(1)
    _static_orders(rows)
    mark_pareto(rows)
    recs = recommend(rows, args.targets)
    used = list(dict.fromkeys(r["method"] for r in rows))
    if getattr(args, "inverse_warp", False):  # after the recommendation: not an integrator
        inv_rows, references["inverse-warp"] = inverse_warp_rows(args.quick, dtype, repeats)
        rows += inv_rows
        mark_pareto(rows)
    machine = machine_info(device)
    extra = {
        "machine": machine,
        "dtype": args.dtype,
        "quick": bool(args.quick),
        "references": references,
        "methods": {k: METHODS[k].description for k in used},
        "skipped": dict(SKIPPED),
        "not_run": not_run,
        "error": (
            "max over the output times T/4, T/2, 3T/4, T and the nodes of |x - x_ref|, over the "
            "reference's max displacement; static rows: at the coarse nodes, against the fine grid"
        ),
        "wall_time": (
            f"perf_counter around the run after an untimed warm-up step; median of {repeats} "
            f"repeat(s), runs over {REPEAT_LIMIT_S:g} s timed once"
        ),
        "scaling": (
            "k = E h s (h spacing, s = share of the grid cells bordering the spring), c = tau k, masses from density"
        ),
        "targets": list(args.targets),
        "recommendations": recs,
    }
    out = Path(args.out) if args.out else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        plot(rows, out / "accuracy.png", references)
    if not args.json:
        print(
            f"accuracy against wall time, {args.dtype}, {device}, {machine['threads']} thread(s), "
            f"torch {machine['torch']}, median of {repeats} repeat(s) (runs over {REPEAT_LIMIT_S:g} s: 1)"
        )
    display = [dict(r, pareto="*" if r["pareto"] else "", note=r["note"] or "") for r in rows]
    emit("accuracy", args, rows, TABLE, extra, display)
    if not args.json:
        print(report(extra))
        if out is not None:
            print(f"wrote {out / 'accuracy.csv'} and {out / 'accuracy.png'}")
    return 0


def report(extra: dict) -> str:
    """The text after the table: references, methods, what was left out, the recommendation."""
    lines = [
        "",
        "error: " + extra["error"] + ".",
        "pareto *: no other run of the scene is both faster and more accurate.",
        "scaling: " + extra["scaling"] + ".",
        "",
        "references:",
    ]
    lines += [f"  {name}: {ref['text']}" for name, ref in extra["references"].items()]
    lines.append("methods:")
    lines += [f"  {name}: {text}" for name, text in extra["methods"].items()]
    for name, why in extra["skipped"].items():
        lines.append(f"  {name}: {why}")
    groups = {}
    for d in extra["not_run"]:
        groups.setdefault((d["scene"], d["reason"]), []).append(f"{d['method']} {d['param']}")
    if groups:
        lines.append("not run:")
        lines += [f"  {scene}: {', '.join(cases)} ({why})" for (scene, why), cases in groups.items()]
    lines += ["", recommendation_text(extra["recommendations"], extra["targets"])]
    return "\n".join(lines)


def _static_orders(rows: list) -> None:
    """Note the observed convergence order between successive resolutions of a static scene."""
    for scene in dict.fromkeys(r["scene"] for r in rows if r["method"] == "static"):
        sub = sorted(
            (r for r in rows if r["scene"] == scene and r["method"] == "static" and r["status"] == "ok"),
            key=lambda r: r["n"],
        )
        for a, b in zip(sub, sub[1:]):
            if a["error"] > 0 and b["error"] > 0:
                order = math.log(a["error"] / b["error"]) / math.log((b["n"] - 1) / (a["n"] - 1))
                b["note"] = f"order {order:.2f} from n={a['n']}"


# ------------------------------------------------------------- inverse warp rows


def inverse_warp_rows(quick: bool, dtype=torch.float64, repeats: int = 3, seed: int = 0):
    """Rows of the fixed-point inverse warp (:func:`torchdeform.volume.inverse_points`).

    A ``64^3`` volume (quick ``32^3``) under ``9^3`` node offsets (quick ``5^3``), uniform random
    up to 0.15 node spacings (neighbouring nodes differ by at most 0.3 spacings per component, so
    ``|grad u|_F <= 0.9 < 1``: a contraction, well below the folding limit). At every voxel centre
    ``p``, ``X_k`` after ``k`` iterations of ``X <- p - u(X)`` (``k = 0``: first order
    ``p - u(p)``); the error is the largest round-trip residual ``|X_k + u(X_k) - p|`` in voxels
    (not relative, unlike the mechanical scenes) and the wall time that of ``inverse_points``.

    Returns:
        ``(rows, reference)``: rows with :data:`COLUMNS` (scene ``inverse-warp``, method
        ``fixed-point``, ``steps`` = iterations, ``n`` = nodes per axis) and a reference dict.
    """
    from ..volume import DisplacementField, identity_points, inverse_points, inverse_residual

    size, nodes = (32, 5) if quick else (64, 9)
    AMP = 0.15
    iters = (0, 1, 2, 4, 8) if quick else (0, 1, 2, 3, 4, 6, 8, 12, 16, 24)
    g = torch.Generator().manual_seed(seed)
    spacing = (size - 1) / (nodes - 1)
    offsets = (torch.rand(3, nodes, nodes, nodes, generator=g, dtype=torch.float64) * 2 - 1) * AMP * spacing
    field = DisplacementField(offsets.to(dtype), (size,) * 3)
    p = identity_points((size,) * 3, dtype)
    rows = []
    info = dict(n=nodes, dt=None, bound_s=None, bound_of=None, dt_bound=None)
    with torch.no_grad():
        for k in iters:
            times = []
            for _ in range(max(1, repeats)):
                t0 = time.perf_counter()
                X, _ = inverse_points(field, p, k, tol=0.0)
                times.append(time.perf_counter() - t0)
            err = float(inverse_residual(field, X, p).max())
            rows.append(
                _row(
                    "inverse-warp",
                    _InverseWarp,
                    k,
                    dict(info, steps=k),
                    error=err,
                    wall_s=statistics.median(times),
                    repeats=len(times),
                    status="ok",
                    note="max |X + u(X) - p| [voxels]",
                )
            )
    reached = [r["steps"] for r in rows if r["error"] < 1e-3]
    ref = dict(
        method="exact",
        n=nodes,
        max_displacement_m=None,
        text=(
            f"fixed-point inverse warp X <- p - u(X) at all {size}^3 voxel centres, {nodes}^3 node offsets "
            f"up to {AMP:g} node spacings ({AMP * spacing:.2g} voxels), {str(dtype).replace('torch.', '')}; "
            f"error = max round-trip residual |X + u(X) - p| in voxels (exact inverse: 0); below 1e-3 "
            f"voxel from {min(reached) if reached else 'no'} iteration(s)"
        ),
    )
    return rows, ref


class _InverseWarpMethod(Method):
    name = "fixed-point"
    description = "fixed-point inverse warp X <- p - u(X) (torchdeform.volume.inverse_points)"

    def label(self, param):
        return f"{param} it"


_InverseWarp = _InverseWarpMethod()


# -------------------------------------------------------------------------- plot


def plot(rows: list, path: Path, references: dict | None = None) -> None:
    """Log-log error against wall time.

    One panel per scene, one colour per method (points joined in order of dt, or n), the Pareto
    front as a black step line with ringed points, diverged runs as crosses along the top. ``rows``
    as returned by the bench; ``references`` names the reference in each panel's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colours = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
    cols = min(3, max(1, len(scenes)))
    nrows = math.ceil(len(scenes) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.7 * nrows), squeeze=False)
    for ax in axes.flat[len(scenes) :]:
        ax.set_visible(False)
    handles = {}
    for ax, scene in zip(axes.flat, scenes):
        sub = [r for r in rows if r["scene"] == scene]
        ok = [r for r in sub if r["status"] == "ok" and r["error"] > 0]
        for m in methods:
            series = sorted((r for r in ok if r["method"] == m), key=lambda r: (r["dt"] or 0, r["n"] or 0))
            if series:
                (h,) = ax.plot(
                    [r["wall_s"] for r in series],
                    [r["error"] for r in series],
                    marker="o",
                    ms=4,
                    lw=1,
                    color=colours[m],
                    label=m,
                )
                handles[m] = h
        front = sorted((r["wall_s"], r["error"]) for r in ok if r["pareto"])
        if front:
            (h,) = ax.step(*zip(*front), where="post", color="k", lw=1, ls="--", label="Pareto front")
            ax.scatter(*zip(*front), s=70, facecolors="none", edgecolors="k", zorder=3)
            handles["Pareto front"] = h
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_minor_formatter(NullFormatter())
        bad = [r for r in sub if r["status"] != "ok" and r["wall_s"]]
        if bad:
            top = ax.get_ylim()[1]
            for r in bad:
                ax.scatter([r["wall_s"]], [top], marker="x", color=colours[r["method"]], zorder=3)
            handles["diverged (drawn at the top)"] = ax.scatter([], [], marker="x", color="0.4")
            ax.set_ylim(top=top * 1.5)
        ref = (references or {}).get(scene, {})
        title = (
            scene
            if "method" not in ref
            else f"{scene}  (ref: {ref['method']}" + (f", n={ref['n']})" if ref.get("n") else ")")
        )
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("max position error / max displacement")
        ax.grid(True, which="major", alpha=0.3)
    fig.legend(
        list(handles.values()),
        list(handles),
        loc="lower right" if len(scenes) % cols else "upper right",
        fontsize=9,
        frameon=True,
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)


__all__ = [
    "HELP",
    "add_arguments",
    "run",
    "SCENES",
    "METHODS",
    "SKIPPED",
    "AccuracyScene",
    "Method",
    "TimeStepping",
    "StaticResolution",
    "Context",
    "Reference",
    "cube",
    "cell_share",
    "pareto_front",
    "mark_pareto",
    "recommend",
    "relative_error",
    "run_case",
    "plot",
]
