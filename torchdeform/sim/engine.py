"""Running many steps: :func:`simulate` and the :class:`Engine` that chooses eager or compiled steps.

An engine runs a simulation's steps as

* ``"eager"``: :meth:`~torchdeform.sim.integrators.Integrator.step` on the grid layout, the path
  for autograd and the tested reference;
* ``"compiled"``: :func:`~torchdeform.sim.compiled.compiled_step` on the packed layout (about 5-10x
  faster per step on a CPU, after a compile of 15-60 s per grid shape that inductor caches on
  disk); the state is unpacked only where someone looks at it (records, divergence checks,
  callbacks that read positions);
* ``"auto"``: eager steps first; after :attr:`Engine.probe_steps` of them it switches to compiled
  steps when the eager time still to come is worth more than :attr:`Engine.payback` times the
  expected compile time, and when the compiled step can run the simulation at all (no gradient
  needed, no callable loads, no interaction that runs eagerly, no topology change between steps).

After a run, :attr:`Engine.ran` says which engine ran, :attr:`Engine.reason` why, and
:meth:`Engine.summary` gives both with the measured eager step time and the compile time.

Example:
    >>> import torchdeform as td
    >>> grid = td.Grid((4, 4, 4), spacing=0.01)
    >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0, gravity=(-9.81, 0, 0),
    ...                  fixed=grid.face("bottom"))
    >>> engine = td.Engine("auto")
    >>> state, record = td.simulate(model, model.rest_state(), td.suggest_dt(model), 50, engine=engine)
    >>> engine.ran, engine.reason.split(":")[0]        # a short run does not repay a compile
    ('eager', 'auto')
"""
from __future__ import annotations

import statistics
import time

import torch
from tqdm.auto import tqdm

from ..errors import ConfigError
from .integrators import ImplicitEuler, Integrator, SymplecticEuler, positive_dt
from .model import Model, State
from .stability import DivergenceMonitor, check_dt

__all__ = ["ENGINES", "Engine", "simulate", "gradient_needed"]

#: the engine names of ``[integrator] engine`` and ``--engine``
ENGINES = ("auto", "eager", "compiled")


def gradient_needed(model: Model, state: State) -> bool:
    """Whether a step of ``model`` from ``state`` must record a gradient (grad mode on and a tensor needs it)."""
    if not torch.is_grad_enabled():
        return False
    return any(t is not None and t.requires_grad
               for t in (state.x, state.v, model.stiffness, model.damping, model.mass, model.inv_mass,
                         model.rest_length))


class Engine:
    """Which step runs a simulation: ``"eager"``, ``"compiled"`` or ``"auto"`` (see the module docstring).

    Args:
        mode: ``"auto"`` (default), ``"eager"`` or ``"compiled"``.
        probe_steps: eager steps timed by ``"auto"`` before it decides (the first is a warm-up).
        payback: ``"auto"`` compiles when the eager time still to come exceeds ``payback`` times
            the expected compile time.
        compile_s: expected cold compile time (s) per integrator kind, ``{"explicit": .., "implicit": ..}``
            (default :attr:`COMPILE_S`: measured on 2 cores).
        editable: passed to :func:`~torchdeform.sim.compiled.compiled_step` (a model edited in
            place between steps).
        blocked: a reason the compiled step cannot run this simulation, known to the caller (for
            example topology changes between steps), or None.
        compile: False runs the compiled engine's packed loop with the uncompiled packed step
            (``compiled_step(..., enable=False)``): the same code path without the compile, for
            tests and debugging.

    Attributes:
        ran: ``"eager"`` or ``"compiled"`` once a run has decided (None before).
        reason: one line: why.
        eager_ms: the median eager step time measured by ``"auto"`` (ms), or None.
        compile_s: the time of the first compiled step less one step (s), or None.
        step: the :class:`~torchdeform.sim.compiled.CompiledStep` of a compiled run, or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), 0.01), stiffness=10.0, mass=1e-3)
        >>> k = torch.tensor(10.0, requires_grad=True)
        >>> model.stiffness = model.stiffness * k / 10.0            # a learned parameter
        >>> engine = td.Engine("auto")
        >>> _ = td.simulate(model, model.rest_state(), 1e-4, 5, engine=engine, warn=False)
        >>> engine.ran, engine.reason
        ('eager', 'auto: a gradient is needed (the compiled step runs without autograd)')
    """

    #: expected cold compile time (s) on 2 cores: the explicit steps in their reduction form
    #: (64^3, 26 neighbours: 7 s, 13 s on a machine's first compile, which also builds inductor's
    #: precompiled header), in their unrolled gather form (24-37 s), and the implicit step's one
    #: graph with its CG loop
    COMPILE_S = {"explicit": 15.0, "gather": 40.0, "implicit": 60.0}
    #: what the gather form saves per step against the reduction form, as a fraction of an eager
    #: step, when compiled for several threads (64^3, 26 neighbours, 2 cores: eager 27 ms,
    #: reduction 3.6 ms, gather 2.45 ms)
    GATHER_SAVES = 1 / 20

    def __init__(self, mode: str = "auto", probe_steps: int = 3, payback: float = 2.0,
                 compile_s: dict | None = None, editable=False, blocked: str | None = None,
                 compile: bool = True):
        if mode not in ENGINES:
            raise ConfigError("engine", f"one of {', '.join(ENGINES)}", mode)
        self.mode, self.probe_steps, self.payback = mode, max(2, int(probe_steps)), float(payback)
        self.expected = dict(self.COMPILE_S, **(compile_s or {}))
        self.editable, self.blocked, self.enable = editable, blocked, bool(compile)
        self.ran: str | None = None
        self.reason = ""
        self.eager_ms: float | None = None
        self.compile_s: float | None = None
        self.step = None
        #: the spring sum ``"auto"`` chose for an explicit compiled step (``"gather"`` or
        #: ``"reduction"``), or None (the compiled step's own default)
        self.force_form: str | None = None

    # -------------------------------------------------------------- deciding
    def blocker(self, model: Model, integrator: Integrator, state: State, loads) -> str | None:
        """Why the compiled step cannot run this simulation, or None."""
        if self.blocked:
            return self.blocked
        if gradient_needed(model, state):
            return "a gradient is needed (the compiled step runs without autograd)"
        if callable(loads):
            return "callable loads run in the eager step"
        eager_only = [type(c).__name__ for c in model.interactions if getattr(c, "eager_only", False)]
        if eager_only:
            return f"{', '.join(eager_only)} runs in the eager step"
        return getattr(integrator, "eager_reason", None)

    def expected_compile_s(self, integrator: Integrator) -> float:
        """The compile time :meth:`decide` expects for ``integrator`` (s)."""
        return self.expected["implicit" if isinstance(integrator, ImplicitEuler) else "explicit"]

    def decide(self, integrator: Integrator, eager_s: list, remaining: int, threads: int = 1) -> bool:
        """``"auto"`` after its probe: compile for the ``remaining`` steps? Sets :attr:`reason`.

        An explicit step compiled for several ``threads`` also gets its spring sum: the unrolled
        gather form, faster per step but slower to compile, only when the steps to come repay its
        extra compile (:attr:`GATHER_SAVES`); otherwise the reduction form (:attr:`force_form`).
        """
        self.eager_ms = 1e3 * statistics.median(eager_s[1:] if len(eager_s) > 1 else eager_s)
        to_come = remaining * self.eager_ms / 1e3
        expected = self.expected_compile_s(integrator)
        worth = to_come > self.payback * expected
        self.reason = (f"auto: {remaining:,} steps x {self.eager_ms:.3g} ms eager = {to_come:.3g} s "
                       f"{'>' if worth else '<='} {self.payback:g} x ~{expected:g} s compile")
        if worth and threads > 1 and not isinstance(integrator, ImplicitEuler):
            extra = self.expected["gather"] - self.expected["explicit"]
            gather = to_come * self.GATHER_SAVES > self.payback * extra
            self.force_form = "gather" if gather else "reduction"
            self.reason += (f"; {self.force_form} form ({to_come * self.GATHER_SAVES:.3g} s saved "
                            f"{'>' if gather else '<='} {self.payback:g} x ~{extra:g} s more compile)")
        return worth

    def summary(self) -> dict:
        """``{"requested", "ran", "why", "eager_ms_per_step", "compile_s", "force_form", "threads"}`` for a run's summary.

        ``threads``: the compiled step's thread governor (:meth:`~torchdeform.sim.threads.ThreadGovernor.summary`:
        the count it ended on, steps per count, switches), or None.
        """
        compiled = self.step is not None and self.ran == "compiled"
        gov = self.step.governor if compiled else None
        return {"requested": self.mode, "ran": self.ran, "why": self.reason,
                "eager_ms_per_step": self.eager_ms, "compile_s": self.compile_s,
                "force_form": self.step.force_form if compiled else None,
                "threads": gov.summary() if gov is not None else None}

    def _compile(self, model, integrator, dt, loads):
        from .compiled import compiled_step
        self.step = compiled_step(integrator, model, dt, loads, editable=self.editable, enable=self.enable,
                                  force_form=self.force_form)
        return self.step


def _reads_positions(callback) -> bool:
    return callback is not None and getattr(callback, "reads_positions", True)


def simulate(model: Model, state: State, dt: float, steps: int, integrator: Integrator | None = None,
             loads=None, record_every: int | None = None, check_every: int = 10, progress: bool = False,
             warn: bool = True, callback=None, engine: Engine | str = "eager", rtol: float | None = None):
    """Run ``steps`` steps with divergence detection.

    Args:
        model: the :class:`~torchdeform.sim.model.Model`.
        state: the start state, positions and velocities ``(B, 3, D, H, W)``.
        dt: time step (s), > 0.
        steps: number of steps (>= 0).
        integrator: default :class:`~torchdeform.sim.integrators.SymplecticEuler`.
        loads: extra node forces as for :meth:`Integrator.step`, or None.
        record_every: keep every k-th state (positions and velocities) on the CPU, or None.
        check_every: check for non-finite values and runaway energy every k steps (and at the end).
        progress: show a tqdm progress bar.
        warn: warn when an explicit ``dt`` exceeds the stability bound.
        callback: ``callback(step, state)`` after every step, or None. A callback with the
            attribute ``reads_positions = False`` (it reads only ``t`` and ``readings``) is handed
            the compiled engine's packed state as it is, without unpacking positions every step.
        engine: an :class:`Engine` (read its :attr:`~Engine.ran` and :attr:`~Engine.reason`
            afterwards) or its mode, ``"eager"`` (default), ``"compiled"`` or ``"auto"``.
        rtol: ask for an accuracy instead of a step: ``dt`` becomes the interval between the
            returned states, each covered by the internal steps of
            :class:`~torchdeform.sim.adaptive.Adaptive` (``rtol``, default pair) that the
            tolerance needs. Give no ``integrator`` with it (or an ``Adaptive``, which then keeps
            its own tolerance).

    Returns:
        ``(final state, record)`` where record is a dict with ``t`` ``(T,)``, ``x`` and ``v``
        ``(T, B, 3, D, H, W)`` (empty if nothing was recorded).

    Raises:
        DivergenceError: naming the step, the quantity and a safe dt.
        ConfigError: ``engine = "compiled"`` for a simulation the compiled step cannot run.

    Examples:
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01)
        >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0, gravity=(-9.81, 0, 0),
        ...                  fixed=grid.face("bottom"))
        >>> dt = td.suggest_dt(model)
        >>> state, record = td.simulate(model, model.rest_state(), dt, steps=50, record_every=10)
        >>> record["x"].shape, len(record["t"]), round(state.t / dt)
        (torch.Size([6, 1, 3, 4, 4, 4]), 6, 50)
        >>> bool(state.x[0, 0, -1].mean() < model.X[0, 0, -1].mean())        # the top sags
        True
    """
    if rtol is not None:
        from .adaptive import Adaptive
        if integrator is None:
            integrator = Adaptive(rtol=rtol)
        elif not isinstance(integrator, Adaptive):
            raise ConfigError("rtol", f"no integrator, or an Adaptive one (the {integrator.name} integrator "
                                      f"takes a fixed dt)", rtol)
    integrator = integrator or SymplecticEuler()
    engine = engine if isinstance(engine, Engine) else Engine(engine)
    dt = positive_dt(dt)
    steps = int(steps)
    if steps < 0:
        raise ConfigError("steps", "an integer >= 0", steps)
    if warn and integrator.name not in ("implicit", "knoche", "adaptive", "projective"):
        check_dt(model, dt, integrator)
    monitor = DivergenceMonitor(model, dt, integrator)
    state = model.start(state)                        # fixed nodes at rest, dragged nodes on their path
    ts, xs, vs = [], [], []

    def record(st):
        ts.append(st.t)
        xs.append(st.x.detach().cpu())
        vs.append(st.v.detach().cpu())

    blocker = engine.blocker(model, integrator, state, loads) if engine.mode != "eager" else None
    if engine.mode == "compiled" and blocker:
        raise ConfigError("engine", f"a simulation the compiled step can run; here {blocker}", "compiled")
    engine.ran, engine.reason = "eager", ("asked for" if engine.mode == "eager" else f"auto: {blocker}")
    probing = engine.mode == "auto" and blocker is None
    if engine.mode == "compiled":
        engine.ran, engine.reason = "compiled", "asked for"
    compiled = engine._compile(model, integrator, dt, loads) if engine.mode == "compiled" else None
    if probing and steps <= engine.probe_steps:
        probing, engine.reason = False, f"auto: {steps} steps are too few to repay a compile"
    packed, eager_s, timing = None, [], 0
    if record_every:
        record(state)
    for i in tqdm(range(1, steps + 1), disable=not progress, desc="simulate", unit="step"):
        if compiled is None:
            t0 = time.perf_counter()
            state = integrator.step(model, state, dt, loads)
            if probing:
                eager_s.append(time.perf_counter() - t0)
                if len(eager_s) == engine.probe_steps:
                    probing = False
                    from .compiled import step_threads
                    if engine.decide(integrator, eager_s, steps - i, step_threads(model, integrator)):
                        engine.ran = "compiled"
                        compiled = engine._compile(model, integrator, dt, loads)
        else:
            if packed is None:
                packed = compiled.packed.pack_state(state)
            t0 = time.perf_counter()
            packed = compiled.step_packed(packed)
            if timing < 2:                                  # compile time: first call less the second
                spent, timing = time.perf_counter() - t0, timing + 1
                if not compiled.compiled and engine.enable:  # compilation failed: eager from now on
                    engine.ran, engine.reason = "eager", f"{engine.reason}; compile failed: {compiled.compile_error}"
                    timing = 2
                elif timing == 1:
                    engine.compile_s = spent
                else:
                    engine.compile_s = max(0.0, engine.compile_s - spent)
            look = i == steps or (record_every and i % record_every == 0) or _reads_positions(callback)
            state = compiled.packed.unpack_state(packed) if look else packed
        if i % check_every == 0 or i == steps:
            # a packed state is checked as it is (its halo has no mass), not unpacked for it
            monitor.check(state, i, mass=compiled.packed.mass if state is packed else None)
        if record_every and i % record_every == 0:
            record(state)
        if callback is not None:
            callback(i, state)
    rec = {}
    if xs:
        rec = {"t": torch.tensor(ts, dtype=torch.float64), "x": torch.stack(xs), "v": torch.stack(vs)}
    return state, rec
