"""The compiled fast path: an integrator step under ``torch.compile``, without gradients.

:func:`compiled_step` runs ``integrator.advance`` and ``finish`` on the packed layout of
:class:`~torchdeform.packed.PackedModel` (every node gathers its springs; forces and update fuse
into one vectorised loop) and compiles it, for one model and one time step. Every integrator of
:mod:`torchdeform.integrators` runs unchanged on the packed model; implicit Euler is compiled in
three pieces (:class:`_ImplicitParts`). Time enters as a 0-d tensor, so ramped loads and drag
paths never trigger a recompilation.

The eager :meth:`~torchdeform.integrators.Integrator.step` stays the default and the path for
autograd: the wrapper calls it whenever a gradient is needed, and it falls back to it for good,
with one warning line, when compilation is unavailable or fails.

Compilation happens on the first call and costs 20-60 s per grid shape on a 2-core CPU
(implicit Euler about 2 minutes); inductor caches it on disk.

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


def inductor_options(options: dict | None = None) -> dict:
    """``options`` plus the current torch thread count as inductor's ``cpp.threads``.

    Inductor chooses serial or OpenMP loops from the thread count at code generation, but its
    on-disk cache key does not include it: code compiled once under ``torch.set_num_threads(1)``
    would be handed, serial, to every later 2-thread run (measured: the implicit beam at 10.5 ms
    per step instead of 5.8). Naming the count makes it part of the key."""
    return dict(options or {}, **{"cpp.threads": torch.get_num_threads()})


@torch.library.custom_op("torchdeform::stored", mutates_args=())
def _realize(x: torch.Tensor) -> torch.Tensor:
    """Identity that inductor cannot see through: its input and output live in memory."""
    return x.clone()


@_realize.register_fake
def _(x):
    return torch.empty_like(x)


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

        self._fn = None
        self.compiled = bool(enable)
        if enable and callable(loads):
            self._fallback(TypeError("callable loads are not compiled"))
        elif enable:
            try:
                pm.realize = _realize
                compile_ = functools.partial(torch.compile, dynamic=False, mode=mode,
                                             options=None if mode else inductor_options(options or INDUCTOR_OPTIONS))
                if isinstance(integrator, ImplicitEuler):
                    self._fn = _ImplicitParts(integrator, pm, self.dt, loads_p, compile_)
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
                with torch.no_grad(), _no_autograd_cache():
                    t = torch.tensor(float(state.t), dtype=self.model.dtype, device=self.model.device)
                    x, v = self._fn(state.x, state.v, t)
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


class _ImplicitParts:
    """Implicit Euler in three compiled pieces: set-up of the system and the CG start, one CG
    iteration (compiled once, called ``cg_iters`` times), and the update. A compiled graph with
    all iterations unrolled would cost 20 copies of the spring kernel to compile (> 15 min for
    20 iterations on 2 cores); ``cg_unroll`` iterations per call (default 2) cost that many
    copies, and each call ~50-100 us of call overhead on these CPUs. With a tolerance
    (``cg_tol > 0``) every iteration is a call, followed by a residual check."""

    def __init__(self, integ, pm, dt, loads, compile_, cg_unroll: int = 2):
        self.integ, self.pm, self.dt, self.loads = integ, pm, dt, loads
        self.precond = integ.preconditioner(pm, dt)
        precond, mask = self.precond, pm.free

        def setup(x, v, vcur, t, it):
            pm.graph_inputs, pm.store_sums = (x, v, vcur), True
            _, apply_A, rhs, delta_c = integ.system(pm, State(x, v, t), vcur, it, dt, loads)
            u, r, p, rz = cg_start(rhs, precond, mask)
            return (apply_A.op.fields, u, r, p, rz, r.flatten(1).norm(dim=1).clamp_min(1e-300),
                    torch.zeros_like(v) if delta_c is None else delta_c)

        unroll = self.unroll = max(1, min(int(cg_unroll), integ.cg_iters)) if integ.cg_tol <= 0 else 1

        def iterate(fields, u, r, p, rz):
            pm.graph_inputs, pm.store_sums = (u, r, p, rz), True
            _, apply_A = integ.operator(pm, PackedLinearisation(pm, fields=fields, combined=True), dt)
            for _ in range(unroll):
                u, r, p, rz = cg_iteration(apply_A, u, r, p, rz, precond, mask)
            return u, r, p, rz

        def update(x, v, t, vcur, u, delta_c, r, bnorm):
            pm.graph_inputs, pm.store_sums = (), True
            vnew = vcur + u + delta_c
            out = integ.finish(pm, State(x, v, t), x + dt * vnew, vnew, dt)
            return out.x, out.v, (r.flatten(1).norm(dim=1) / bnorm).max()

        def setup_first(x, v, vcur, t):
            return setup(x, v, vcur, t, 0)

        def setup_newton(x, v, vcur, t):
            return setup(x, v, vcur, t, 1)

        self.setup = [compile_(_fresh(setup_first))]
        if integ.newton_iters:
            self.setup.append(compile_(_fresh(setup_newton)))
        self.iterate, self.update = compile_(_fresh(iterate)), compile_(_fresh(update))

    def __call__(self, x, v, t):
        integ, vcur = self.integ, v
        for it in range(1 + integ.newton_iters):
            fields, u, r, p, rz, bnorm, delta_c = self.setup[min(it, 1)](x, v, vcur, t)
            n_it = 0
            while n_it + self.unroll <= integ.cg_iters:
                u, r, p, rz = self.iterate(fields, u, r, p, rz)
                n_it += self.unroll
                if integ.cg_tol > 0 and float((r.flatten(1).norm(dim=1) / bnorm).max()) <= integ.cg_tol:
                    break
            if n_it < integ.cg_iters and integ.cg_tol <= 0:          # odd remainder of an unrolled count
                _, apply_A = integ.operator(self.pm, PackedLinearisation(self.pm, fields=fields, combined=True),
                                            self.dt)
                for _ in range(integ.cg_iters - n_it):
                    u, r, p, rz = cg_iteration(apply_A, u, r, p, rz, self.precond, self.pm.free)
                n_it = integ.cg_iters
            if it < integ.newton_iters:
                vcur = vcur + u + delta_c
        x, v, rel = self.update(x, v, t, vcur, u, delta_c, r, bnorm)
        integ.last_cg = (n_it, float(rel) if integ.cg_tol > 0 else rel)
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
