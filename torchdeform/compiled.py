"""The compiled fast path: an integrator step under ``torch.compile``, without gradients.

:func:`compiled_step` runs ``integrator.advance`` and ``finish`` on the packed layout of
:class:`~torchdeform.packed.PackedModel` (every node gathers its springs; forces and update fuse
into one vectorised loop) and compiles it, for one model and one time step. Every integrator of
:mod:`torchdeform.integrators` runs unchanged on the packed model; implicit Euler's CG iterations
run as a loop inside the one compiled graph (:class:`_ImplicitStep`). Time enters as a 0-d
tensor, so ramped loads and drag paths never trigger a recompilation.

The eager :meth:`~torchdeform.integrators.Integrator.step` stays the default and the path for
autograd: the wrapper calls it whenever a gradient is needed, and it falls back to it for good,
with one warning line, when compilation is unavailable or fails.

Compilation happens on the first call and costs 20-60 s per grid shape on a 2-core CPU;
inductor caches it on disk, except the implicit step, whose loop graph inductor will not cache
("Can't cache HigherOrderOperator: while_loop") and compiles again in every new process (45-60 s
on the 40 x 10 x 10 beam). Unrolling its CG iterations instead would be cacheable but took over
14 minutes to compile for 20 iterations.

Example:
    >>> import torch, torchdeform as td
    >>> from torchdeform.compiled import compiled_step
    >>> model = td.Model(td.Grid((8, 8, 8), 0.01, 26), stiffness=50.0, damping=0.1, mass=1e-3)
    >>> step = compiled_step(td.SymplecticEuler(), model, dt=1e-4)
    >>> state = model.rest_state()
    >>> with torch.no_grad():
    ...     for _ in range(10):
    ...         state = step(state)       # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
import functools
import types
import warnings

import torch

from .integrators import ImplicitEuler, _check_dt, cg_iteration, cg_start
from .model import State
from .packed import PackedLinearisation, PackedModel

__all__ = ["CompileFallbackWarning", "CompiledStep", "compiled_step", "inductor_options"]


class CompileFallbackWarning(UserWarning):
    """``torch.compile`` is unavailable or failed; the eager step is used instead."""


_warned: set = set()


def _warn_once(reason: str) -> None:
    key = reason.split(":")[0]
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(f"torchdeform: torch.compile unavailable ({reason}); using the eager step",
                  CompileFallbackWarning, stacklevel=3)


#: Inductor options for the packed step. By default inductor stores ("realises") every
#: intermediate that is read more than a few times or costs more than 30 operations; for the
#: gather loop that means one buffer per spring direction, written and read back by serial loops
#: (64^3, 26 neighbours: ~100 Msprings/s). Raising the thresholds keeps the whole force sum and
#: the update in registers, one parallel vectorised loop (~600 Msprings/s, same machine). Fields
#: that really must be stored (RK4 stages, CG directions) go through :func:`_realize`.
INDUCTOR_OPTIONS = {"realize_opcount_threshold": 10_000, "realize_reads_threshold": 1_000,
                    "realize_acc_reads_threshold": 1_000}


#: Extra options for the implicit step, whose CG loop body runs ``cg_iters`` times per step:
#: inductor's C++ wrapper runs that loop without Python (each pass otherwise allocates its
#: buffers and checks its inputs' strides from Python), and the stride checks are dropped
#: (dynamo's guards already check the step's own inputs). Measured on the beam of ``bench speed``
#: with the earlier per-direction spring kernel, variants interleaved in one process: 5.09 ms per
#: step with both, 5.55 without the C++ wrapper, 5.63 with neither (medians of 30).
IMPLICIT_OPTIONS = {"cpp_wrapper": True, "size_asserts": False, "alignment_asserts": False}


def inductor_options(options: dict | None = None) -> dict:
    """``options`` plus the current torch thread count as inductor's ``cpp.threads``.

    Inductor chooses serial or OpenMP loops from the thread count at code generation, but its
    on-disk cache key does not include it: code compiled once under ``torch.set_num_threads(1)``
    would be handed, serial, to every later 2-thread run (measured: the implicit beam at 10.5 ms
    per step instead of 5.8). Naming the count makes it part of the key."""
    return dict(options or {}, **{"cpp.threads": torch.get_num_threads()})


@torch.library.custom_op("torchdeform::stored", mutates_args=())
def _realize(x: torch.Tensor) -> torch.Tensor:
    """Identity that inductor cannot see through: its input and output live in memory, the output
    contiguous in the input's axis order (so a permuted view is stored in that order)."""
    return x.clone(memory_format=torch.contiguous_format)


@_realize.register_fake
def _(x):
    return x.new_empty(x.shape)


def _register_realize_lowering() -> None:
    """Lower :func:`_realize` inside inductor as a stored buffer (computed by the fused loop that
    produces it) instead of an external ``clone`` call: each external call costs ~50-90 us of
    dispatch on these CPUs, several times per CG iteration. Without the private lowering API
    the op still works, as the external call."""
    try:
        from torch._inductor import lowering
    except ImportError:                                                 # pragma: no cover
        return

    @lowering.register_lowering(torch.ops.torchdeform.stored.default, type_promotion_kind=None)
    def _lower(x):
        y = lowering.clone(x)
        y.realize()
        return y


_register_realize_lowering()


def _no_autograd_cache():
    """Compile without AOTAutograd's on-disk cache (inductor's own FX-graph cache still applies).

    Measured on the implicit beam (torch 2.13 CPU): the set-up piece loaded through that cache
    runs in 3.7 ms per call, the same inductor code compiled or loaded from the FX-graph cache in
    1.1-1.2 ms (one step: ~10 ms against ~5 ms). Without the cache a warm start costs ~10 s more.
    """
    try:
        from torch._functorch import config
        if hasattr(config, "enable_autograd_cache"):
            return config.patch(enable_autograd_cache=False)
    except ImportError:                                             # pragma: no cover
        pass
    return contextlib.nullcontext()


def _skip_guards():
    """Run compiled code without evaluating dynamo's guards (``skip_guard_eval_unsafe``), for calls
    whose inputs match the call that compiled it; a no-op where this torch lacks the stance."""
    try:
        return torch.compiler.set_stance(skip_guard_eval_unsafe=True)
    except (AttributeError, TypeError):                                 # pragma: no cover
        return contextlib.nullcontext()


def _fresh(fn):
    """A copy of ``fn`` with its own code object: dynamo keeps its cache (and its limit of
    recompilations) per code object, so every wrapper gets its own instead of sharing one."""
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__,
                              fn.__closure__)


class CompiledStep:
    """One step of ``integrator`` on ``model`` with time step ``dt``, compiled (see
    :func:`compiled_step`).

    The compiled function works in the packed layout of :class:`~torchdeform.packed.PackedModel`:
    ``__call__`` packs and unpacks a grid-layout :class:`State` around one step, :meth:`run`
    packs once and advances many steps, and :meth:`step_packed` is the bare packed step.

    Attributes:
        packed: the :class:`~torchdeform.packed.PackedModel`.
        compiled: False once the wrapper has fallen back to the eager step.
        compile_error: the reason of the fall-back, or None.
    """

    def __init__(self, integrator, model, dt: float, loads=None, *, mode: str | None = None,
                 enable: bool = True, options: dict | None = None):
        self.integrator, self.model, self.loads = integrator, model, loads
        self.dt = _check_dt(dt)
        self.compile_error = None
        self.packed = pm = PackedModel(model)
        self._loads = None if loads is None or callable(loads) else pm.pack(torch.as_tensor(
            loads, dtype=model.dtype, device=model.device).expand(-1, 3, *model.grid.shape))
        dt_, loads_p = self.dt, self._loads

        # t enters as a 0-d tensor: ramps and drag paths are evaluated inside the compiled code
        # without branches, and a new t never triggers a recompilation.
        def step(x, v, t):
            pm.graph_inputs, pm.store_sums = (x, v), False
            state = State(x, v, t)
            out = integrator.finish(pm, state, *integrator.advance(pm, state, dt_, loads_p), dt_)
            return out.x, out.v

        self._fn, self._compiled_for = None, None
        self.compiled = bool(enable)
        if enable and callable(loads):
            self._fallback(TypeError("callable loads are not compiled"))
        elif enable:
            try:
                pm.realize = _realize
                implicit = isinstance(integrator, ImplicitEuler)
                opts = dict(options or INDUCTOR_OPTIONS, **(IMPLICIT_OPTIONS if implicit else {}))
                compile_ = functools.partial(torch.compile, dynamic=False, mode=mode, fullgraph=implicit,
                                             options=None if mode else inductor_options(opts))
                if implicit:
                    self._fn = _ImplicitStep(integrator, pm, self.dt, loads_p, compile_)
                else:
                    self._fn = compile_(_fresh(step))
            except Exception as e:                          # noqa: BLE001 (any failure -> eager)
                self._fallback(e)

    def _fallback(self, e: Exception) -> None:
        self.compiled, self._fn = False, None
        first = (str(e).strip().splitlines() or [""])[0][:160]
        self.compile_error = f"{type(e).__name__}: {first}"
        _warn_once(self.compile_error)

    def _needs_grad(self, state) -> bool:
        if not torch.is_grad_enabled():
            return False
        m = self.model
        return any(t is not None and t.requires_grad
                   for t in (state.x, state.v, m.stiffness, m.damping, m.mass, m.inv_mass))

    def step_packed(self, state: State) -> State:
        """One step on a packed state (``x``, ``v``: ``(B, 3, P)``), no gradient."""
        if self._fn is not None:
            try:
                x, v = state.x, state.v
                t = torch.scalar_tensor(float(state.t), dtype=self.model.dtype, device=self.model.device)
                signature = [(a.shape, a.stride(), a.dtype, a.device) for a in (x, v)]
                if signature == self._compiled_for:
                    # Same shapes as the compiled call, and the model is baked in: dynamo's guards
                    # (one check per model tensor, ~0.15 ms per call on the beam) cannot fail.
                    with torch.no_grad(), _skip_guards():
                        x, v = self._fn(x, v, t)
                else:
                    with torch.no_grad(), _no_autograd_cache():
                        x, v = self._fn(x, v, t)
                    self._compiled_for = signature
                return State(x, v, state.t + self.dt)
            except Exception as e:                          # noqa: BLE001 (any failure -> eager)
                self._fallback(e)
        with torch.no_grad():
            return self.integrator.step(self.packed, state, self.dt, self._loads if self._loads is not None
                                        else self.loads)

    def __call__(self, state: State) -> State:
        """One step on a grid-layout state (``(B, 3, D, H, W)``); eager when a gradient is needed."""
        if self._fn is None or self._needs_grad(state):
            return self.integrator.step(self.model, state, self.dt, self.loads)
        return self.packed.unpack_state(self.step_packed(self.packed.pack_state(state)))

    def run(self, state: State, steps: int, callback=None) -> State:
        """``steps`` steps from a grid-layout state, packed once; returns a grid-layout state.

        ``callback(i, packed_state)`` (optional) is called after every step; unpack with
        ``self.packed.unpack_state``.
        """
        ps = self.packed.pack_state(state)
        for i in range(int(steps)):
            ps = self.step_packed(ps)
            if callback is not None:
                callback(i, ps)
        return self.packed.unpack_state(ps)


def _while_loop():
    """``torch._higher_order_ops.while_loop`` (a loop that stays one loop in the compiled graph),
    or None where this torch lacks it."""
    try:
        from torch._higher_order_ops.while_loop import while_loop
    except ImportError:                                                 # pragma: no cover
        return None
    return while_loop


class _ImplicitStep:
    """Implicit Euler as one compiled graph: set-up of the system, the CG iterations as a
    ``while_loop`` (one iteration's code, compiled once and looped inside the graph, so the spring
    kernel is not copied ``cg_iters`` times and no iteration pays a Python call), and the update.

    Called as ``(x, v, t) -> (x, v)`` on packed fields; sets ``integrator.last_cg``. With a
    tolerance (``cg_tol > 0``) the loop condition reads the residual, as the eager solver does
    after every iteration; without one it runs exactly ``cg_iters`` iterations.
    """

    def __init__(self, integ, pm, dt, loads, compile_=None):
        while_loop = _while_loop()
        if while_loop is None:                                          # pragma: no cover
            raise RuntimeError("this torch has no while_loop for the compiled implicit solve")
        precond, mask, iters, tol = integ.preconditioner(pm, dt), pm.free, integ.cg_iters, integ.cg_tol
        self.integ = integ

        def step(x, v, t):
            vcur = v
            for it in range(1 + integ.newton_iters):
                pm.graph_inputs, pm.store_sums, pm.inputs_stored = (x, v), True, False
                _, apply_A, rhs, delta_c = integ.system(pm, State(x, v, t), vcur, it, dt, loads)
                u, r, p, rz = cg_start(rhs, precond, mask)
                bnorm = r.flatten(1).norm(dim=1).clamp_min(1e-300)
                fields = apply_A.op.fields

                def cond(i, u, r, p, rz):
                    if tol <= 0:
                        return i < iters
                    return (i < 1) | ((i < iters) & ((r.flatten(1).norm(dim=1) / bnorm).max() > tol))

                def body(i, u, r, p, rz):
                    _, A = integ.operator(pm, PackedLinearisation(pm, fields=fields, combined=True), dt)
                    return (i + 1, *cg_iteration(A, u, r, p, rz, precond, mask))

                # Inside the loop body every field is a body input, already in memory.
                pm.inputs_stored = True
                start = torch.zeros((), dtype=torch.int64, device=x.device)
                n_it, u, r, p, rz = while_loop(cond, body, (start, u, r, p, rz))
                vcur = vcur + u if delta_c is None else vcur + u + delta_c
            pm.graph_inputs, pm.inputs_stored = (), False
            out = integ.finish(pm, State(x, v, t), x + dt * vcur, vcur, dt)
            return out.x, out.v, n_it, (r.flatten(1).norm(dim=1) / bnorm).max()

        self.fn = step if compile_ is None else compile_(_fresh(step))

    def __call__(self, x, v, t):
        x, v, n_it, rel = self.fn(x, v, t)
        self.integ.last_cg = (int(n_it), float(rel)) if self.integ.cg_tol > 0 else (self.integ.cg_iters, rel)
        return x, v


def compiled_step(integrator, model, dt: float, loads=None, *, mode: str | None = None,
                  enable: bool = True) -> CompiledStep:
    """Wrap one integrator step on one model in ``torch.compile`` (the no-grad fast path).

    Args:
        integrator: an :class:`~torchdeform.integrators.Integrator` whose ``advance`` is plain
            tensor code (symplectic, explicit Euler, Verlet, RK4).
        model: the :class:`~torchdeform.model.Model`; its tensors are baked into the compiled code.
        dt: time step (s), fixed for the wrapper.
        loads: extra forces as for :meth:`Integrator.step` (a tensor; a callable must not depend
            on ``t`` in ways that force recompilation).
        mode: ``torch.compile`` mode (default None).
        enable: False gives the eager step behind the same interface.
    Returns:
        a :class:`CompiledStep`, ``step(state) -> State``. It runs the compiled code under
        ``torch.no_grad``; when a gradient is needed (grad mode on and the state or the model's
        parameters require grad) it calls the eager step. If compilation fails it warns once
        (:class:`CompileFallbackWarning`) and uses the eager step from then on.
    """
    return CompiledStep(integrator, model, dt, loads, mode=mode, enable=enable)
