"""The compiled fast path: an integrator step under ``torch.compile``, without gradients.

:func:`compiled_step` wraps ``integrator.advance`` (plain tensor code: symplectic Euler,
explicit Euler, damped Verlet, RK4, ...) for one model and one time step in ``torch.compile``.
The eager :meth:`~torchdeform.integrators.Integrator.step` stays the default and the path for
autograd: the wrapper calls it whenever a gradient is needed, and it falls back to it for good,
with one warning line, when compilation is unavailable or fails.

Compilation happens on the first call and costs 20-60 s per grid shape on a 2-core CPU.

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

import types
import warnings

import torch

from .integrators import _check_dt
from .model import State

__all__ = ["CompileFallbackWarning", "CompiledStep", "compiled_step"]


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


#: Inductor options for the spring step. The shifted-slice accumulation is a chain of 2 S in-place
#: slice updates of one buffer; left to its defaults, inductor inlines the whole chain into one
#: expression whose size doubles with each update, so 18 or 26 neighbours never finish compiling
#: (> 10 min for an 8^3 grid, torch 2.13 CPU). Realising intermediate buffers early fixes that
#: (8^3: 26 neighbours ~30 s) and also gives faster code (32^3, 6 neighbours: 3x).
INDUCTOR_OPTIONS = {"realize_opcount_threshold": 8, "realize_acc_reads_threshold": 4}


def _fresh(fn):
    """A copy of ``fn`` with its own code object: dynamo keeps its cache (and its limit of
    recompilations) per code object, so every wrapper gets its own instead of sharing one."""
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__,
                              fn.__closure__)


class CompiledStep:
    """``state -> State``: one step of ``integrator`` on ``model`` with time step ``dt``.

    Same result as ``integrator.step(model, state, dt, loads)`` (up to float rounding); see
    :func:`compiled_step`.

    Attributes:
        compiled: False once the wrapper has fallen back to the eager step.
        compile_error: the reason of the fall-back, or None.
    """

    def __init__(self, integrator, model, dt: float, loads=None, *, mode: str | None = None,
                 enable: bool = True):
        self.integrator, self.model, self.loads = integrator, model, loads
        self.dt = _check_dt(dt)
        self.compile_error = None

        # The step must not depend on t: dynamo specialises on Python floats, so a changing t
        # would recompile at every step (and give up after 8). Time-dependent loads stay eager.
        time_dependent = bool(model.loads) or callable(loads)
        dt_ = self.dt

        def advance(x, v):
            return integrator.advance(model, State(x, v, 0.0), dt_, loads)

        self._fn = None
        self.compiled = bool(enable) and not time_dependent
        if enable and time_dependent:
            self.compile_error = "time-dependent loads are not compiled"
            _warn_once(self.compile_error)
        elif enable:
            try:
                self._fn = torch.compile(_fresh(advance), dynamic=False, mode=mode,
                                         options=None if mode else dict(INDUCTOR_OPTIONS))
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

    def __call__(self, state: State) -> State:
        if self._fn is None or self._needs_grad(state):
            return self.integrator.step(self.model, state, self.dt, self.loads)
        try:
            with torch.no_grad():
                x, v = self._fn(state.x, state.v)
        except Exception as e:                              # noqa: BLE001 (any failure -> eager)
            self._fallback(e)
            return self.integrator.step(self.model, state, self.dt, self.loads)
        return self.integrator.finish(self.model, state, x, v, self.dt)


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
