"""Running many steps: :func:`simulate` and the :class:`Engine` that chooses how each step runs.

An engine runs a simulation's steps as

* ``"eager"``: :meth:`~torchdeform.sim.integrators.Integrator.step` on the grid layout, the path
  for autograd and the tested reference;
* ``"native"``: the same integrator, eagerly, on the packed layout with the spring forces from a
  small C kernel (:mod:`~torchdeform.sim.native`; built in 1-3 s once per kind of model and cached
  on disk): about 5x faster than eager at 64^3 with nothing to compile per grid shape; explicit
  integrators, Hooke springs on a CPU with a C compiler, or on CUDA with Triton
  (:mod:`~torchdeform.sim.native_cuda`, compiled by Triton on first use);
* ``"compiled"``: :func:`~torchdeform.sim.compiled.compiled_step` on the packed layout, the whole
  step under ``torch.compile`` (for explicit steps around the C kernel: about 3 s per grid shape
  plus ~3 s to load inductor; an implicit step 27-34 s, 2-7 s once inductor's disk cache holds
  it; without the kernel 10-60 s); a quarter
  faster than ``"native"`` per explicit step whose update ``"native"`` leaves to torch;
* ``"auto"``: eager steps first; after :attr:`Engine.probe_steps` of them it moves on when the
  eager time still to come is worth more than :attr:`Engine.payback` times the expected cost of
  the next engine: to ``"native"`` where it can run, and from there, after timing as many native
  steps (and waiting, up to :attr:`Engine.SETTLE_STEPS`, for the thread governor to settle on a
  thread count: beside a busy process the first steps on two threads are many times slower than
  the run's), to ``"compiled"`` when what compiling saves repays its compile (never for a native step
  that one fused kernel makes whole: symplectic Euler with Hooke springs, gravity, fixed nodes and
  the global drag, faster than its compiled form); straight to
  ``"compiled"`` where the kernel cannot run. It stays eager when no faster engine can run the
  simulation at all (a gradient needed, callable loads, an interaction that runs eagerly, a
  topology change between steps).

In the packed engines the state is unpacked only where someone looks at it (records, callbacks
that read positions). After a run, :attr:`Engine.ran` says which engine ran last,
:attr:`Engine.reason` why, and :meth:`Engine.summary` gives both with the measured step times
and the compile time.

Example:
    >>> import torchdeform as td
    >>> grid = td.Grid((4, 4, 4), spacing=0.01)
    >>> model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0, gravity=(-9.81, 0, 0),
    ...                  fixed=grid.face("bottom"))
    >>> engine = td.Engine(mode="auto")
    >>> state, record = td.simulate(model, model.rest_state(), td.suggest_dt(model), 50, engine=engine)
    >>> engine.ran, engine.reason.split(":")[0]        # a short run does not repay a compile
    ('eager', 'auto')
"""

from __future__ import annotations

import functools
import math
import statistics
import time
from typing import ClassVar

import torch
from tqdm.auto import tqdm

from ..errors import ConfigError
from . import native
from .integrators import ImplicitEuler, Integrator, SymplecticEuler, positive_dt
from .model import Loads, Model, State
from .stability import DivergenceMonitor, check_dt

__all__ = ["ENGINES", "Engine", "simulate", "gradient_needed"]

#: the engine names of ``[integrator] engine`` and ``--engine``
ENGINES = ("auto", "eager", "native", "compiled")


def gradient_needed(model: Model, state: State) -> bool:
    """Whether a step of ``model`` from ``state`` must record a gradient (grad mode on and a tensor needs it)."""
    if not torch.is_grad_enabled():
        return False
    return any(
        t is not None and t.requires_grad
        for t in (state.x, state.v, model.stiffness, model.damping, model.mass, model.inv_mass, model.rest_length)
    )


class Engine:
    """How a simulation's steps run: ``"eager"``, ``"native"``, ``"compiled"`` or ``"auto"`` (module docstring).

    :func:`simulate` steps, records and asks the engine: :meth:`begin` before the first step says
    which step the run starts on; :meth:`after_eager` and :meth:`after_packed`, given each step's
    time, say which step it goes on with (``"auto"`` probes, decides and switches there).

    Args:
        mode: ``"auto"`` (default), ``"eager"``, ``"native"`` or ``"compiled"``.
        probe_steps: steps timed by ``"auto"`` on each engine before it decides (the first is a warm-up).
        payback: ``"auto"`` moves to a faster engine when what it saves exceeds ``payback``
            times its expected start-up cost (:attr:`COMPILE_S`).
        compile_s: expected start-up costs (s), updating :attr:`COMPILE_S`.
        editable: passed to :func:`~torchdeform.sim.compiled.compiled_step` (a model edited in
            place between steps).
        blocked: a reason the packed engines cannot run this simulation, known to the caller (for
            example topology changes between steps), or None.
        compile: False runs the compiled engine's packed loop with the uncompiled packed step
            (``compiled_step(..., enable=False)``): the same code path without the compile, for
            tests and debugging.

    Attributes:
        ran: ``"eager"``, ``"native"`` or ``"compiled"`` once a run has decided (None before): the
            engine of the run's last steps.
        reason: one line: why.
        eager_ms, native_ms: the median step times measured by ``"auto"`` (ms), or None.
        compile_s: the start-up of the engine that ran: the C kernel's build or load for
            ``"native"``, the first compiled step less one step for ``"compiled"`` (s), or None.
        step: the :class:`~torchdeform.sim.compiled.CompiledStep` of a packed run, or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3)
        >>> k = torch.tensor(10.0, requires_grad=True)
        >>> model.stiffness = model.stiffness * k / 10.0            # a learned parameter
        >>> engine = td.Engine(mode="auto")
        >>> _ = td.simulate(model, model.rest_state(), 1e-4, 5, engine=engine, warn=False)
        >>> engine.ran, engine.reason
        ('eager', 'auto: a gradient is needed (the packed engines run without autograd)')
    """

    #: expected start-up costs (s) on 2 cores: ``"native"``, building the C spring kernel (1-3 s);
    #: ``"native_built"``, loading it from the disk cache and packing the model; ``"explicit"``, compiling an explicit step around
    #: that kernel (64^3, 26 neighbours: 3 s per grid shape, 6.7 s with empty caches, plus ~3 s
    #: to import inductor); where the kernel cannot run, ``"reduction"`` and ``"gather"``, the
    #: explicit step in inductor's two spring sums (7-14 s and 24-60 s); ``"implicit"``, the
    #: implicit step's one graph with its CG loop (the 40 x 10 x 10 beam: 27-34 s to build, 2-7 s
    #: when inductor's disk cache holds it from an earlier process; a Newton iteration doubles the
    #: graph, and this cost has no way to know beforehand which case it is); ``"native_cuda"``, the
    #: Triton kernel's compile on first use (about 10 s per launch shape on a 16-core GPU host,
    #: three shapes timed for a large body; Triton's own disk cache is not looked into)
    COMPILE_S: ClassVar[dict] = {
        "native": 2.0,
        "native_cuda": 12.0,
        "native_built": 0.05,
        "explicit": 8.0,
        "reduction": 15.0,
        "gather": 40.0,
        "implicit": 60.0,
    }
    #: what the gather form saves per step against the reduction form, as a fraction of an eager
    #: step, when compiled for several threads (64^3, 26 neighbours, 2 cores: eager 27 ms,
    #: reduction 3.6 ms, gather 2.45 ms)
    GATHER_SAVES = 1 / 20
    #: what the compiled step saves per step against a native one whose update runs in torch (drags,
    #: loads, other integrators), as a fraction of the native step (64^3, 26 neighbours, float32,
    #: 2 cores: native 6.3 ms, compiled 4.7 ms; the eager update is ~8 passes over the nodes, the
    #: compiled one a single loop). A native step that one fused kernel makes whole is not compiled.
    COMPILED_SAVES = 1 / 4
    #: native steps ``"auto"`` waits at most for the thread governor to settle before its compile
    #: decision. Beside a busy process the first steps run on two threads, 20-40 times slower than
    #: on the one the governor moves to after its first look at the machine's load (0.1 s of steps:
    #: 20-300 steps of the 11^3 cube); decided on those, a 2 s run of the cube compiled for 7 s
    SETTLE_STEPS = 512

    def __init__(
        self,
        *,
        mode: str = "auto",
        probe_steps: int = 3,
        payback: float = 2.0,
        compile_s: dict | None = None,
        editable: bool | tuple[str, ...] = False,
        blocked: str | None = None,
        compile: bool = True,
    ):
        if mode not in ENGINES:
            raise ConfigError("engine", f"one of {', '.join(ENGINES)}", got=mode)
        self.mode, self.probe_steps, self.payback = mode, max(2, int(probe_steps)), float(payback)
        self.expected = dict(self.COMPILE_S, **(compile_s or {}))
        self.editable, self.blocked, self.enable = editable, blocked, bool(compile)
        self.ran: str | None = None
        self.reason = ""
        self.eager_ms: float | None = None
        self.native_ms: float | None = None
        #: the engine ``"auto"`` chose after its eager probe (``"native"`` or ``"compiled"``), or None
        self.choice: str | None = None
        self.compile_s: float | None = None
        self.step = None
        #: the spring sum ``"auto"`` chose for an explicit compiled step (``"gather"`` or
        #: ``"reduction"``), or None (the compiled step's own default)
        self.force_form: str | None = None
        # the run under way (begin): (model, integrator, dt, loads), the engine being probed, its step
        # times, compiled steps timed for the compile time
        self._run: tuple[Model, Integrator, float, Loads] | None = None
        self._probing: str | None = None
        self._samples: list = []
        self._timed = 0

    # -------------------------------------------------------------- deciding
    def blocker(self, model: Model, integrator: Integrator, state: State, loads) -> str | None:
        """Why the packed engines cannot run this simulation, or None."""
        if self.blocked:
            return self.blocked
        if gradient_needed(model, state):
            return "a gradient is needed (the packed engines run without autograd)"
        if callable(loads):
            return "callable loads run in the eager step"
        eager_only = [type(c).__name__ for c in model.interactions if getattr(c, "eager_only", False)]
        if eager_only:
            return f"{', '.join(eager_only)} runs in the eager step"
        return getattr(integrator, "eager_reason", None)

    @staticmethod
    def native_blocker(model: Model, integrator: Integrator) -> str | None:
        """Why the ``"native"`` engine cannot run this step (beyond :meth:`blocker`), or None."""
        if isinstance(integrator, ImplicitEuler):
            return "an implicit step is compiled as one graph (its CG products have no C kernel)"
        return native.supports(model)

    def expected_compile_s(self, integrator: Integrator, *, model: Model | None = None) -> float:
        """The compile time :meth:`decide` expects for ``integrator`` on ``model`` (s).

        An explicit step around the C kernel (:func:`.native.supports`; unknown without ``model``)
        expects :attr:`COMPILE_S` ``["explicit"]``, one without it ``["reduction"]``.
        """
        if isinstance(integrator, ImplicitEuler):
            return self.expected["implicit"]
        return self.expected["explicit" if model is not None and native.supports(model) is None else "reduction"]

    def decide(
        self, integrator: Integrator, eager_s: list, remaining: int, *, threads: int = 1, model: Model | None = None
    ) -> bool:
        """``"auto"`` after its eager probe: leave the eager step for the ``remaining`` steps?

        Sets :attr:`choice` (``"native"`` where :meth:`native_blocker` allows it and the eager time to
        come repays the kernel's build, else ``"compiled"`` where it repays the compile) and
        :attr:`reason`. An explicit step compiled without the C kernel for several ``threads`` also
        gets its spring sum: the unrolled gather form, faster per step but slower to compile, only
        when the steps to come repay its extra compile (:attr:`GATHER_SAVES`); otherwise the
        reduction form (:attr:`force_form`).
        """
        self.eager_ms = _median_ms(eager_s)
        to_come = remaining * self.eager_ms / 1e3
        why_not = "no model given" if model is None else self.native_blocker(model, integrator)
        self.choice = "native" if why_not is None else "compiled"
        built = why_not is None and model is not None and _kernel_built(model)  # cached: nothing to wait for
        cuda = model is not None and model.device.type == "cuda"
        native_s = self.expected["native_cuda" if cuda else "native"]
        expected = native_s if why_not is None else self.expected_compile_s(integrator, model=model)
        expected = min(expected, self.expected["native_built"]) if built else expected
        worth = to_come > self.payback * expected
        self.reason = (
            f"auto: {remaining:,} steps x {self.eager_ms:.3g} ms eager = {to_come:.3g} s "
            f"{'>' if worth else '<='} {self.payback:g} x ~{expected:g} s "
            f"{('Triton kernel compile' if cuda else 'C kernel build') if why_not is None else 'compile'}"
            f"{' (built before)' if built else ''}"
        )
        if not worth:
            self.choice = None
        elif why_not is None:
            self.reason += "; native"
        elif (
            threads > 1 and not isinstance(integrator, ImplicitEuler) and (model is None or model.device.type == "cpu")
        ):
            extra = self.expected["gather"] - self.expected["reduction"]
            gather = to_come * self.GATHER_SAVES > self.payback * extra
            self.force_form = "gather" if gather else "reduction"
            self.reason += (
                f"; compiled, {self.force_form} form ({to_come * self.GATHER_SAVES:.3g} s saved "
                f"{'>' if gather else '<='} {self.payback:g} x ~{extra:g} s more compile)"
            )
        else:
            self.reason += "; compiled"
        return worth

    def decide_compiled(self, native_s: list, remaining: int, *, fused: bool = False, warm_up: bool = True) -> bool:
        """``"auto"`` after its native probe: compile for the ``remaining`` steps? Extends :attr:`reason`.

        ``native_s``: native step times (s), the first a warm-up left out unless ``warm_up`` is False.

        Never when the native step is ``fused`` (one C kernel makes the whole step: the compiled
        step, the force kernel plus a fused update, is slower). Otherwise compiles when the time
        the compiled step saves (:attr:`COMPILED_SAVES` of a native step) over the steps to come
        exceeds :attr:`payback` times the expected compile (:attr:`COMPILE_S` ``["explicit"]``).
        """
        self.native_ms = _median_ms(native_s, warm_up=warm_up)
        if fused:
            self.reason += f"; {self.native_ms:.3g} ms per native step, one fused kernel (nothing to compile)"
            return False
        saved = remaining * self.native_ms / 1e3 * self.COMPILED_SAVES
        expected = self.expected["explicit"]
        worth = saved > self.payback * expected
        self.reason += (
            f"; {self.native_ms:.3g} ms per native step, compiling would save ~{saved:.3g} s "
            f"{'>' if worth else '<='} {self.payback:g} x ~{expected:g} s compile"
            f"{': compiled' if worth else ''}"
        )
        return worth

    def summary(self) -> dict:
        """A run's summary: ``{"requested", "ran", "why", "eager_ms_per_step", "native_ms_per_step", "compile_s", "force_form", "threads"}``.

        ``threads``: the compiled step's thread governor (:meth:`~torchdeform.sim.threads.ThreadGovernor.summary`:
        the count it ended on, steps per count, switches), or None.
        """
        step = self.step if self.ran in ("native", "compiled") else None
        gov = step.governor if step is not None else None
        return {
            "requested": self.mode,
            "ran": self.ran,
            "why": self.reason,
            "eager_ms_per_step": self.eager_ms,
            "native_ms_per_step": self.native_ms,
            "compile_s": self.compile_s,
            "force_form": step.force_form if step is not None else None,
            "threads": gov.summary() if gov is not None else None,
        }

    # -------------------------------------------------------------- running
    def begin(self, model: Model, integrator: Integrator, state: State, dt: float, steps: int, loads):
        """Before a run's first step (``state`` already :meth:`~torchdeform.sim.model.Model.start` ed).

        Checks that the engine can run the simulation, sets :attr:`ran` and :attr:`reason`, starts
        a packed engine that was asked for, and plans ``"auto"``'s eager probe (none for a run of
        at most :attr:`probe_steps` steps).

        Returns:
            the packed step (:class:`~torchdeform.sim.compiled.CompiledStep`) the run starts on, or
            None: eager steps.

        Raises:
            ConfigError: ``"native"`` or ``"compiled"`` for a simulation that engine cannot run.
        """
        blocker = self.blocker(model, integrator, state, loads) if self.mode != "eager" else None
        if self.mode == "native" and blocker is None:
            blocker = self.native_blocker(model, integrator)
        if self.mode in ("native", "compiled") and blocker:
            raise ConfigError("engine", f"a simulation the {self.mode} engine can run; here {blocker}", got=self.mode)
        self.ran, self.reason = "eager", ("asked for" if self.mode == "eager" else f"auto: {blocker}")
        self._run = (model, integrator, dt, loads)
        # the engine "auto" is timing ("eager", then "native"), or None; the step times so far;
        # the compiled steps timed for the compile time (two: the first less the second)
        self._probing = "eager" if self.mode == "auto" and blocker is None else None
        self._samples, self._timed = [], 0
        packed = None
        if self.mode in ("native", "compiled"):
            self.ran, self.reason = self.mode, "asked for"
            packed = self._start(self.mode)
        if self._probing and steps <= self.probe_steps:
            self._probing, self.reason = None, f"auto: {steps} steps are too few to repay a compile"
        return packed

    def after_eager(self, seconds: float, remaining: int):
        """After an eager step that took ``seconds``, with ``remaining`` steps to come: the packed step to go on with.

        While ``"auto"`` probes the eager step it keeps the time; after :attr:`probe_steps` steps it
        asks :meth:`decide` and starts the engine chosen (then probes ``"native"`` in turn).

        Returns:
            the :class:`~torchdeform.sim.compiled.CompiledStep` to run the remaining steps on, or
            None: stay eager.
        """
        if self._probing != "eager":
            return None
        self._samples.append(seconds)
        if len(self._samples) < self.probe_steps:
            return None
        self._probing = None
        from .compiled import step_threads

        assert self._run is not None  # set by begin
        model, integrator = self._run[:2]
        if not self.decide(integrator, self._samples, remaining, threads=step_threads(model, integrator), model=model):
            return None
        assert self.choice is not None  # set by decide
        self.ran = self.choice
        if self.choice == "native":
            self._probing, self._samples = "native", []
        return self._start(self.choice)

    def after_packed(self, step, seconds: float, remaining: int):
        """After a step of the packed ``step`` that took ``seconds``, with ``remaining`` to come: the one to go on with.

        Measures the compile time of a compiled step (its first call less its second; a compile
        that failed leaves the uncompiled packed step running and says so in :attr:`reason`), and
        while ``"auto"`` probes the native step, asks :meth:`decide_compiled` after
        :attr:`probe_steps` steps and compiles when it repays: the same packed layout, so the
        state carries over.
        """
        if self.ran == "compiled" and self._timed < 2:
            self._timed += 1
            if not step.compiled and self.enable:  # compilation failed: eager from now on
                self.ran, self.reason = "eager", f"{self.reason}; compile failed: {step.compile_error}"
                self._timed = 2
            elif self._timed == 1:
                self.compile_s = seconds
            else:
                assert self.compile_s is not None  # the first compiled step's time
                self.compile_s = max(0.0, self.compile_s - seconds)
        if self._probing != "native":
            return step
        self._samples.append(seconds)
        gov = getattr(step, "governor", None)
        waiting = gov is not None and not gov.settled and len(self._samples) < self.SETTLE_STEPS
        if len(self._samples) < self.probe_steps or waiting:
            return step
        self._probing = None
        # the steps on the count the governor settled on (its first steps may be on a count it left)
        if gov is not None and gov.settled:
            samples, warm_up = list(gov.recent), False
        else:
            samples, warm_up = self._samples, True
        if not self.decide_compiled(samples, remaining, fused=step.fused is not None, warm_up=warm_up):
            return step
        self.ran, self._timed = "compiled", 0
        return self._start("compiled")

    def _start(self, how: str):
        """Build the packed step of engine ``how`` for the run; the C kernel's build (or load) is ``compile_s``."""
        assert self._run is not None  # set by begin
        t0 = time.perf_counter()
        step = self._compile(*self._run, how)
        if how == "native":  # the C kernel's build (or load from the disk cache)
            self.compile_s = time.perf_counter() - t0
        return step

    def _compile(self, model, integrator, dt, loads, how: str = "compiled"):
        """The packed step of engine ``how`` (``"native"``: uncompiled, with the C kernel)."""
        from .compiled import compiled_step

        native_only = how == "native"
        self.step = compiled_step(
            integrator,
            model,
            dt,
            loads=loads,
            editable=self.editable,
            enable=self.enable and not native_only,
            force_form="native" if native_only else self.force_form,
        )
        return self.step


def _kernel_built(model: Model) -> bool:
    """Whether ``model``'s C spring kernel is already built (loaded, or in the disk cache)."""
    from .packed import PackedModel

    try:
        return native.is_built(model if isinstance(model, PackedModel) else PackedModel(model, share=True))
    except (ValueError, TypeError, NotImplementedError):  # a model the packed layout does not take
        return False


def _median_ms(samples: list, *, warm_up: bool = True) -> float:
    """Median step time (ms) of a probe, its first step (a warm-up) left out unless ``warm_up`` is False."""
    return 1e3 * statistics.median(samples[1:] if warm_up and len(samples) > 1 else samples)


def _reads_positions(callback) -> bool:
    return callback is not None and getattr(callback, "reads_positions", True)


def _steps_of(steps, duration, dt: float) -> int:
    """The number of steps of :func:`simulate`: ``steps``, or those that cover ``duration`` seconds."""
    if (steps is None) == (duration is None):
        raise ConfigError(
            "steps",
            "exactly one of steps (a number of steps) or duration (seconds)",
            got="both" if steps else "neither",
        )
    if duration is None:
        return int(steps)
    if (
        isinstance(duration, bool)
        or not isinstance(duration, (int, float))
        or not math.isfinite(duration)
        or duration < 0
    ):
        raise ConfigError("duration", "a simulated time in seconds >= 0", got=duration)
    n = duration / dt
    return max(0, round(n) if abs(n - round(n)) < 1e-6 else math.ceil(n))


def _steps_or_duration(fn):
    """``fn(model, state, dt, steps, *, duration=None, ...)`` callable without ``steps`` when ``duration`` is given.

    ``steps`` stays the one positional run length (the public signature shows it so); a call without
    it passes ``steps=None`` (then ``duration`` must be given).
    """

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if len(args) < 4 and "steps" not in kwargs:  # duration alone (neither: one clear error)
            kwargs["steps"] = None
        return fn(*args, **kwargs)

    return call


@_steps_or_duration
def simulate(
    model: Model,
    state: State,
    dt: float,
    steps: int | None,
    *,
    duration: float | None = None,
    integrator: Integrator | None = None,
    loads=None,
    record_every: int | None = None,
    check_every: int = 10,
    progress: bool = False,
    warn: bool = True,
    callback=None,
    engine: Engine | str = "eager",
    rtol: float | None = None,
):
    """Run ``steps`` steps with divergence detection.

    Args:
        model: the :class:`~torchdeform.sim.model.Model`.
        state: the start state, positions and velocities ``(B, 3, D, H, W)``.
        dt: time step (s), > 0.
        steps: number of steps (>= 0); may be left out (or None) when ``duration`` is given.
        duration: instead of ``steps``: the simulated time (s, >= 0), ``ceil(duration / dt)`` steps (a
            duration within a millionth of a step of a whole number of steps takes that number):
            ``simulate(model, state, dt, duration=0.5)``.
        integrator: default :class:`~torchdeform.sim.integrators.SymplecticEuler`.
        loads: extra node forces as for :meth:`Integrator.step`, or None.
        record_every: keep every k-th state (positions and velocities) on the CPU, or None.
        check_every: check for non-finite values and runaway energy every k steps (and at the end).
        progress: show a tqdm progress bar.
        warn: warn when an explicit ``dt`` exceeds the stability bound.
        callback: ``callback(step, state)`` after every step, or None. A callback with the
            attribute ``reads_positions = False`` (it reads only ``t`` and ``readings``) is handed
            the compiled engine's packed state as it is, without unpacking positions every step.
            A callback may change the state in place (cautery stops the nodes it burns): the packed
            engines take the change into their layout.
        engine: an :class:`Engine` (read its :attr:`~Engine.ran` and :attr:`~Engine.reason`
            afterwards) or its mode, ``"eager"`` (default), ``"native"``, ``"compiled"`` or ``"auto"``.
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
        ConfigError: ``engine = "native"`` or ``"compiled"`` for a simulation that engine cannot run.

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
            raise ConfigError(
                "rtol",
                f"no integrator, or an Adaptive one (the {integrator.name} integrator takes a fixed dt)",
                got=rtol,
            )
    integrator = integrator or SymplecticEuler()
    engine = engine if isinstance(engine, Engine) else Engine(mode=engine)
    dt = positive_dt(dt)
    steps = _steps_of(steps, duration, dt)
    if steps < 0:
        raise ConfigError("steps", "an integer >= 0", got=steps)
    if warn and integrator.name not in ("implicit", "knoche", "adaptive", "projective"):
        check_dt(model, dt, integrator)
    monitor = DivergenceMonitor(model, dt, integrator)
    state = model.start(state)  # fixed nodes at rest, dragged nodes on their path
    for name, value in (("state.x", state.x), ("state.v", state.v)):  # even 0 steps return no NaN
        bad = int((~torch.isfinite(value.detach())).sum())
        if bad:
            raise ConfigError(name, "a finite start state", got=f"{bad} non-finite values")
    ts, xs, vs = [], [], []

    def record(st):
        ts.append(st.t)
        xs.append(st.x.detach().cpu())
        vs.append(st.v.detach().cpu())

    compiled = engine.begin(model, integrator, state, dt, steps, loads)
    packed = None
    if record_every:
        record(state)
    for i in tqdm(range(1, steps + 1), disable=not progress, desc="simulate", unit="step"):
        if compiled is None:
            t0 = time.perf_counter()
            state = integrator.step(model, state, dt, loads=loads)
            compiled = engine.after_eager(time.perf_counter() - t0, steps - i)
        else:
            if packed is None:
                packed = compiled.packed.pack_state(state)
            t0 = time.perf_counter()
            packed = compiled.step_packed(packed)
            compiled = engine.after_packed(compiled, time.perf_counter() - t0, steps - i)
            look = i == steps or (record_every and i % record_every == 0) or _reads_positions(callback)
            state = compiled.packed.unpack_state(packed) if look else packed
        if i % check_every == 0 or i == steps:
            # a packed state is checked as it is (its halo has no mass), not unpacked for it
            monitor.check(state, i, mass=compiled.packed.mass if compiled is not None and state is packed else None)
        if record_every and i % record_every == 0:
            record(state)
        if callback is not None:
            seen = (state.x._version, state.v._version)
            callback(i, state)
            if compiled is not None and state is not packed and (state.x._version, state.v._version) != seen:
                packed = compiled.packed.pack_state(state)  # the callback changed the unpacked state in place
    rec = {}
    if xs:
        rec = {"t": torch.tensor(ts, dtype=torch.float64), "x": torch.stack(xs), "v": torch.stack(vs)}
    return state, rec
