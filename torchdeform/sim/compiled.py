"""The compiled fast path: an integrator step under ``torch.compile``, without gradients.

:func:`compiled_step` runs ``integrator.advance`` and ``finish`` on the packed layout of
:class:`~torchdeform.sim.packed.PackedModel` and compiles it, for one model and one time step. An
explicit step sums its springs with the C kernel of :mod:`~torchdeform.sim.native` where that
kernel can run (one external call in the graph), else with inductor's unrolled gather form (every
node gathers its springs; forces and update fuse into one vectorised loop) or its reduction form
(:attr:`~torchdeform.sim.packed.PackedModel.force_form`). Every integrator of
:mod:`torchdeform.sim.integrators` runs unchanged on the packed model; implicit Euler's CG
iterations run as a loop inside the one compiled graph (:class:`ImplicitGraph`). Time enters as a
0-d tensor, so ramped loads and drag paths never trigger a recompilation.

The eager :meth:`~torchdeform.sim.integrators.Integrator.step` stays the default and the path for
autograd: the wrapper calls it whenever a gradient is needed, and it falls back to it for good,
with one warning line, when compilation is unavailable or fails. ``enable=False`` gives the same
packed step uncompiled (with ``force_form="native"``: the ``"native"`` engine of
:mod:`~torchdeform.sim.engine`).

Compilation happens on the first call. Measured on a 2-core CPU, 64^3, 26 neighbours: around the
C kernel 3 s per grid shape once the kernel is built (6.7 s with empty caches: the kernel's build
1.3 s, inductor's C++ header); without it 10-60 s per grid shape. Inductor caches it on disk for
later processes, the implicit step's loop graph too (:func:`~torchdeform._compile.loop_cache_options`
marks the ``while_loop`` cacheable): the 40 x 10 x 10 beam compiles in 27-34 s, then loads in
2-7 s. Unrolling its CG iterations instead took over 14 minutes to compile for 20 iterations.

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.sim.compiled import compiled_step
    >>> model = td.Model(td.Grid((8, 8, 8), spacing=0.01, topology=26), stiffness=50.0, damping=0.1, mass=1e-3,
    ...                  gravity=(-9.81, 0, 0))
    >>> step = compiled_step(td.SymplecticEuler(), model, dt=1e-4)
    >>> state = step.run(model.rest_state(), 10)      # compiles on this first call  # doctest: +SKIP
    >>> eager = compiled_step(td.SymplecticEuler(), model, dt=1e-4, enable=False)   # same interface
    >>> state = eager.run(model.rest_state(), 10)
    >>> state.x.shape, eager.compiled, round(state.t, 6)
    (torch.Size([1, 3, 8, 8, 8]), False, 0.001)
    >>> bool(state.v[0, 0].mean() < 0)                  # falling under gravity
    True
"""

from __future__ import annotations

import functools
import time

import torch

from .._compile import (
    INDUCTOR_OPTIONS,
    CompileFallbackWarning,
    fresh,
    inductor_options,
    loop_cache_options,
    no_autograd_cache,
    realize,
    skip_guards,
    warn_fallback,
    while_loop,
)
from ..errors import ConfigError
from . import native
from .integrators import ImplicitEuler, cg_iteration, cg_start, positive_dt
from .model import State
from .packed import PackedLinearisation, PackedModel, TraceContext
from .threads import ThreadGovernor, omp_threads

__all__ = [
    "CompileFallbackWarning",
    "CompiledStep",
    "ImplicitGraph",
    "compiled_step",
    "step_threads",
    "SERIAL_NODES",
    "IMPLICIT_OPTIONS",
    "STEP_OPTIONS",
]


#: Extra options for the implicit step, whose CG loop body runs ``cg_iters`` times per step:
#: inductor's C++ wrapper runs that loop without Python (each pass otherwise allocates its
#: buffers and checks its inputs' strides from Python), and the stride checks are dropped
#: (dynamo's guards already check the step's own inputs). Measured on the beam of ``bench speed``
#: with the earlier per-direction spring kernel, variants interleaved in one process: 5.09 ms per
#: step with both, 5.55 without the C++ wrapper, 5.63 with neither (medians of 30). On a GPU the
#: C++ wrapper is left out (it failed to build on a CUDA machine without the toolkit's headers).
IMPLICIT_OPTIONS = {"cpp_wrapper": True, "size_asserts": False, "alignment_asserts": False}

#: Options of every compiled spring step, under the caller's. Inductor unrolls a reduction of at
#: most 8 terms into one expression; the reduction form's sum over the ``2 S = 6`` directions of a
#: 6-neighbour grid, unrolled, gave kernels so large that generating them took minutes. Measured
#: on 2 idle cores, one process per figure: the 6-neighbour 40 x 10 x 10 implicit beam compiled in
#: 199 s and stepped in 4.4 ms unrolled, in 32 s and 2.1 ms as a loop; the explicit 32^3 step (one
#: thread) in 69 s and 0.77 ms against 11 s and 0.51 ms. Other grids sum 14 to 26 terms: unchanged.
STEP_OPTIONS = {"unroll_reductions_threshold": 1}


class CompiledStep:
    """One step of ``integrator`` on ``model`` with time step ``dt``, compiled (see :func:`compiled_step`).

    The compiled function works in the packed layout of :class:`~torchdeform.sim.packed.PackedModel`:
    ``__call__`` packs and unpacks a grid-layout :class:`State` around one step, :meth:`run`
    packs once and advances many steps, and :meth:`step_packed` is the bare packed step.

    Attributes:
        packed: the :class:`~torchdeform.sim.packed.PackedModel`.
        compiled: False once the wrapper has fallen back to the eager step.
        compile_error: the reason of the fall-back, or None.
    """

    def __init__(
        self,
        integrator,
        model,
        dt: float,
        *,
        loads=None,
        mode: str | None = None,
        enable: bool = True,
        options: dict | None = None,
        editable: bool | tuple[str, ...] = False,
        threads: int | None = None,
        force_form: str | None = None,
    ):
        if force_form not in (None, "native", "gather", "reduction"):
            raise ConfigError("force_form", "None, 'native', 'gather' or 'reduction'", got=force_form)
        self.integrator, self.model, self.loads = integrator, model, loads
        self.dt = positive_dt(dt)
        #: the OpenMP threads the code is compiled for (see :func:`step_threads`)
        self.threads = int(threads) if threads else step_threads(model, integrator)
        self.compile_error = None
        implicit = isinstance(integrator, ImplicitEuler)
        #: picks the threads of each step from the step times (:mod:`~torchdeform.sim.threads`):
        #: an explicit step on several threads on a CPU, compiled or with the C spring kernel, else None
        self.governor = (
            ThreadGovernor(self.threads)
            if (enable or force_form == "native")
            and not implicit
            and self.threads > 1
            and model.device.type == "cpu"
            and mode is None
            else None
        )
        self.packed = pm = PackedModel(model, share=editable)
        pm.force_form = force_form
        self._loads = (
            None
            if loads is None or callable(loads)
            else pm.pack(
                torch.as_tensor(loads, dtype=model.dtype, device=model.device).expand(-1, 3, *model.grid.shape)
            )
        )
        dt_, loads_p = self.dt, self._loads

        #: the compile-time context of this step's graph; its packed kernels see it through a view
        #: of the packed model (the model itself carries no compile flags)
        self.trace = ctx = TraceContext(store=realize)
        pmc = pm.traced(ctx, threads=self.threads, native_ok=not implicit, build=enable)
        #: how this step sums the springs, ``"native"``, ``"gather"`` or ``"reduction"`` (decided by the traced view)
        self.force_form = pmc.force_form
        if pm.force_form == "native":  # the uncompiled step makes an Elastic body's cell term in C too
            pm.native_kernel, pm.volume_kernel = pmc.native_kernel, pmc.volume_kernel
        #: uncompiled with the C kernel, a symplectic step that one kernel makes whole
        #: (:func:`~torchdeform.sim.native.symplectic_step`): that kernel's name, else None
        self.fused = None
        if not enable and self.force_form == "native" and native.fused_blocker(pm, integrator, loads=loads) is None:
            self.fused = native.kernel(native.fused_variant(pm))  # springs, an Elastic body's cell term, update

        # t enters as a 0-d tensor: ramps and drag paths are evaluated inside the compiled code
        # without branches, and a new t never triggers a recompilation.
        def step(x, v, t):
            ctx.set(graph_inputs=(x, v))
            state = State(x, v, t=t)
            out = integrator.finish(pmc, state, *integrator.advance(pmc, state, dt_, loads_p), dt_)
            return out.x, out.v, out.readings or {}

        self._fn, self._compiled_for = None, set()
        self.compiled = bool(enable)
        eager_only = [type(c).__name__ for c in model.interactions if getattr(c, "eager_only", False)]
        if enable and callable(loads):
            self._fallback(TypeError("callable loads are not compiled"))
        elif enable and eager_only:
            self._fallback(TypeError(f"{', '.join(eager_only)} runs in the eager step"))
        elif enable:
            try:
                opts = dict(STEP_OPTIONS, **(options or INDUCTOR_OPTIONS))
                if implicit:  # its while_loop graph kept in the on-disk cache too
                    opts.update(IMPLICIT_OPTIONS, **loop_cache_options())
                if model.device.type != "cpu":  # inductor's C++ wrapper of a GPU graph needs the CUDA toolkit's headers
                    opts.pop("cpp_wrapper", None)
                if self.governor is not None:  # the thread count is read when the code runs
                    opts["cpp.dynamic_threads"] = True
                compile_ = functools.partial(
                    torch.compile,
                    dynamic=False,
                    mode=mode,
                    fullgraph=implicit,
                    options=None if mode else inductor_options(options=opts, threads=self.threads),
                )
                if implicit:
                    self._fn = ImplicitGraph(integrator, pm, self.dt, loads_p, compile_=compile_, threads=self.threads)
                else:
                    self._fn = compile_(fresh(step))
            except Exception as e:
                self._fallback(e)

    def _fallback(self, e: Exception) -> None:
        self.compiled, self._fn = False, None
        first = (str(e).strip().splitlines() or [""])[0][:160]
        self.compile_error = f"{type(e).__name__}: {first}"
        warn_fallback(self.compile_error)

    def _needs_grad(self, state) -> bool:
        if not torch.is_grad_enabled():
            return False
        m = self.model
        return any(
            t is not None and t.requires_grad for t in (state.x, state.v, m.stiffness, m.damping, m.mass, m.inv_mass)
        )

    def step_packed(self, state: State) -> State:
        """One step on a packed state (``x``, ``v``: ``(B, 3, P)``), no gradient."""
        if self._fn is not None:
            try:
                x, v = state.x, state.v
                t = torch.scalar_tensor(float(state.t), dtype=self.model.dtype, device=self.model.device)
                x, v, readings = self._governed(lambda n: self._compiled_call(x, v, t, n))
                return State(x, v, t=state.t + self.dt, readings=readings or None)
            except Exception as e:
                self._fallback(e)
        with torch.no_grad():
            return self._governed(lambda n: self._eager_step(state))

    def _governed(self, run):
        """``run(n)`` on the ``n`` threads the governor picks (torch's setting without one), timed for it."""
        if self.governor is None:
            return run(torch.get_num_threads())
        n = self.governor.choose()
        t0 = time.perf_counter()
        with omp_threads(n):
            out = run(n)
        self.governor.record(n, time.perf_counter() - t0)
        return out

    def _compiled_call(self, x, v, t, n: int):
        fn = self._fn
        assert fn is not None  # called on the compiled path only
        signature = (tuple((a.shape, a.stride(), a.dtype, a.device) for a in (x, v)), n)
        if signature in self._compiled_for:
            # Shapes and threads of a compiled call, and the model is baked in: dynamo's guards
            # (one check per model tensor, ~0.15 ms per call on the beam) cannot fail.
            with torch.no_grad(), skip_guards():
                return fn(x, v, t)
        with torch.no_grad(), no_autograd_cache():  # compiles; on another thread count, traces again
            out = fn(x, v, t)
        self._compiled_for.add(signature)
        return out

    def _eager_step(self, state: State) -> State:
        if self.fused is not None:
            x, v = native.symplectic_step(self.packed, state.x, state.v, self.dt, name=self.fused)
            return State(x, v, t=state.t + self.dt, readings=None)
        return self.integrator.step(
            self.packed, state, self.dt, loads=self._loads if self._loads is not None else self.loads
        )

    def __call__(self, state: State) -> State:
        """One step on a grid-layout state (``(B, 3, D, H, W)``); eager when a gradient is needed."""
        if self._fn is None or self._needs_grad(state):
            return self.integrator.step(self.model, state, self.dt, loads=self.loads)
        return self.packed.unpack_state(self.step_packed(self.packed.pack_state(state)))

    def run(self, state: State, steps: int, *, callback=None) -> State:
        """``steps`` steps from a grid-layout state, packed once; returns a grid-layout state.

        ``callback(i, packed_state)`` (optional) is called after every step; unpack with
        ``self.packed.unpack_state``. Fixed nodes start at rest and dragged nodes on their path, as in
        :func:`~torchdeform.sim.engine.simulate`.
        """
        state = self.model.start(state)
        ps = self.packed.pack_state(state)
        for i in range(int(steps)):
            ps = self.step_packed(ps)
            if callback is not None:
                callback(i, ps)
        return self.packed.unpack_state(ps)


class ImplicitGraph:
    """Implicit Euler as one compiled graph.

    Set-up of the system, the CG iterations as a ``while_loop`` (one iteration's code, compiled
    once and looped inside the graph, so the spring kernel is not copied ``cg_iters`` times and
    no iteration pays a Python call), and the update.

    Called as ``(x, v, t) -> (x, v, readings)`` on packed fields; sets ``integrator.last_cg``. With a
    tolerance (``cg_tol > 0``) the loop condition reads the residual, as the eager solver does
    after every iteration; without one it runs exactly ``cg_iters`` iterations.

    Args:
        integ: the :class:`~torchdeform.sim.integrators.ImplicitEuler`.
        pm: the :class:`~torchdeform.sim.packed.PackedModel`.
        dt: time step (s).
        loads: packed extra forces ``(B, 3, P)`` or None.
        compile_: ``fn -> compiled fn`` (``torch.compile`` with options), or None to run the graph
            eagerly (``while_loop`` then runs as a Python loop: the tested reference of the graph).
        threads: the thread count the graph is compiled for (default torch's).
    """

    def __init__(self, integ, pm, dt, loads, *, compile_=None, threads: int | None = None):
        loop = while_loop()
        if loop is None:  # pragma: no cover
            raise RuntimeError("this torch has no while_loop for the compiled implicit solve")
        precond, mask, iters, tol = integ.preconditioner(pm, dt), pm.free, integ.cg_iters, integ.cg_tol
        self.integ = integ
        #: the compile-time context of this graph (see :class:`~torchdeform.sim.packed.TraceContext`)
        self.trace = ctx = TraceContext(store=realize if compile_ is not None else None)
        pm = pm.traced(ctx, threads=threads, native_ok=False)

        def cg_loop(bnorm, fields):
            """The ``while_loop`` condition and body of one Newton iteration's CG solve."""

            def cond(i, u, r, p, rz):
                if tol <= 0:
                    return i < iters
                return (i < 1) | ((i < iters) & ((r.flatten(1).norm(dim=1) / bnorm).max() > tol))

            def body(i, u, r, p, rz):
                _, A = integ.operator(pm, PackedLinearisation(pm, fields=fields, combined=True), dt)
                return (i + 1, *cg_iteration(A, u, r, p, rz, precond=precond, mask=mask))

            return cond, body

        def step(x, v, t):
            vcur = v
            for it in range(1 + integ.newton_iters):
                ctx.set(graph_inputs=(x, v), store_sums=True)
                _, apply_A, rhs, delta_c = integ.system(pm, State(x, v, t=t), vcur, it, dt, loads)
                u, r, p, rz = cg_start(rhs, precond=precond, mask=mask)
                bnorm = r.flatten(1).norm(dim=1).clamp_min(1e-300)
                cond, body = cg_loop(bnorm, apply_A.op.fields)
                # Inside the loop body every field is a body input, already in memory.
                ctx.set(graph_inputs=(x, v), store_sums=True, inputs_stored=True)
                start = torch.zeros((), dtype=torch.int64, device=x.device)
                n_it, u, r, p, rz = loop(cond, body, (start, u, r, p, rz))
                vcur = vcur + u if delta_c is None else vcur + u + delta_c
            ctx.set(store_sums=True)
            out = integ.finish(pm, State(x, v, t=t), x + dt * vcur, vcur, dt)
            return out.x, out.v, n_it, (r.flatten(1).norm(dim=1) / bnorm).max(), out.readings or {}

        self.fn = step if compile_ is None else compile_(fresh(step))

    def __call__(self, x, v, t):
        """One step on packed fields: ``(x, v, t) -> (x, v, readings)``; sets ``integrator.last_cg``."""
        x, v, n_it, rel, readings = self.fn(x, v, t)
        self.integ.last_cg = (int(n_it), float(rel)) if self.integ.cg_tol > 0 else (self.integ.cg_iters, rel)
        return x, v, readings


#: Below these node counts a compiled step runs on one thread (:func:`step_threads`). An explicit
#: step has one or two parallel loops: two threads already pay at 8^3. The implicit step's graph
#: (CG iterations in a while loop, about 5 parallel loops each) is slower on two threads at every
#: size measured (2 idle cores, 20 CG iterations): the 40 x 10 x 10 beam 3.1 ms per step on one
#: thread, 13.7 ms on two; 32^3 25.5 ms against 137 ms. So it is always compiled serial.
SERIAL_NODES = {"explicit": 512, "implicit": None}


def step_threads(model, integrator, *, available: int | None = None) -> int:
    """The threads a compiled step of ``integrator`` on ``model`` is compiled for.

    One below :data:`SERIAL_NODES` (None: always; small problems: thread barriers cost more than
    they share, and a busy core beside does not stall the step), else ``available`` (default
    torch's setting).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> beam = td.Model(td.Grid((10, 10, 40), spacing=0.1, topology=26), stiffness=1.0, mass=1.0)
        >>> step_threads(beam, td.ImplicitEuler(), available=2), step_threads(beam, td.SymplecticEuler(), available=2)
        (1, 2)
    """
    available = int(available or torch.get_num_threads())
    below = SERIAL_NODES["implicit" if isinstance(integrator, ImplicitEuler) else "explicit"]
    return 1 if below is None or model.grid.num_nodes < below else available


def compiled_step(
    integrator,
    model,
    dt: float,
    *,
    loads=None,
    mode: str | None = None,
    enable: bool = True,
    editable: bool | tuple[str, ...] = False,
    threads: int | None = None,
    force_form: str | None = None,
) -> CompiledStep:
    """Wrap one integrator step on one model in ``torch.compile`` (the no-grad fast path).

    Args:
        integrator: an :class:`~torchdeform.sim.integrators.Integrator` whose ``advance`` is plain
            tensor code (symplectic, explicit Euler, Verlet, RK4).
        model: the :class:`~torchdeform.sim.model.Model`; its tensors are baked into the compiled code.
        dt: time step (s), fixed for the wrapper.
        loads: extra forces as for :meth:`Integrator.step` (a tensor; a callable must not depend
            on ``t`` in ways that force recompilation).
        mode: ``torch.compile`` mode (default None).
        enable: False gives the eager step behind the same interface.
        editable: the model's fields and the packed model's become one storage
            (:meth:`~torchdeform.sim.packed.PackedModel.share`): topology changes made to
            ``model`` in place between steps (:mod:`torchdeform.topology`) reach the compiled code
            without a recompilation, and a step costs the same after them. True shares the
            stiffness per spring (cuts, tears, cautery); a tuple of spring fields adds
            ``"rest_length"`` (coagulation, gaping cuts) and ``"damping"`` (coagulation's
            viscosity rise); each per-spring field costs memory traffic in every step.
        threads: OpenMP threads of the compiled code (default :func:`step_threads`: one for small
            problems, else torch's setting).
        force_form: how the springs are summed (:attr:`~torchdeform.sim.packed.PackedModel.force_form`):
            ``"native"`` (the C kernel; :class:`~torchdeform.sim.native.NativeBuildError` where it
            cannot run), ``"gather"``, ``"reduction"`` or None (for an explicit step the C kernel
            where it can run, else gather on several threads, else reduction; an implicit step
            reduction).

    Returns:
        a :class:`CompiledStep`, ``step(state) -> State``. It runs the compiled code under
        ``torch.no_grad``; when a gradient is needed (grad mode on and the state or the model's
        parameters require grad) it calls the eager step. If compilation fails it warns once
        (:class:`CompileFallbackWarning`) and uses the eager step from then on.
    """
    return CompiledStep(
        integrator,
        model,
        dt,
        loads=loads,
        mode=mode,
        enable=enable,
        editable=editable,
        threads=threads,
        force_form=force_form,
    )
