"""Adaptive time steps: embedded Runge-Kutta pairs with error control.

A user asks for an accuracy, not a time step: ``simulate(model, state, dt, steps, rtol=1e-3)``
(or ``integrator=Adaptive(rtol=1e-3)``) still returns states every ``dt`` seconds, but each of
those intervals is covered by as many internal steps as the requested tolerance needs.

**Pairs** (``pair=``; the Butcher tableaux are the published ones):

=====================  ==================================  ===========  ==========================
name                   method                              orders       evaluations per try
=====================  ==================================  ===========  ==========================
``heun_euler``         Heun with Euler's error estimate    2 (1)        2
``bogacki_shampine``   Bogacki & Shampine 1989             3 (2)        4
``dormand_prince``     Dormand & Prince 1980 (RK5(4)7M)    5 (4)        7
=====================  ==================================  ===========  ==========================

The higher-order solution is propagated (local extrapolation). The first-same-as-last stage of
the last two pairs is evaluated again at the next step rather than reused: drags, contact
projections and global drag change the state between steps.

**Error control.** After a try of size ``h`` the embedded difference ``e`` of positions and of
velocities is measured on the free nodes in the max norm, each relative to
``atol + rtol * m``, where ``m`` is the largest displacement (for positions) or speed (for
velocities) anywhere in the body at the start or end of the try. The error ratio ``err`` is the
larger of the two. The try is accepted when ``err <= 1``; otherwise it is rejected and repeated
with a smaller ``h``. Either way the next ``h`` is ``h * clip(0.9 * err^(-1/(q+1)), 0.2, 5)``, with
``q`` the order of the error estimate. Default ``atol``: ``rtol * 1e-3`` grid spacings for
positions, and that times the highest natural frequency for velocities.

**Limits.** ``h`` never exceeds the pair's stability limit where one applies: the largest
``y`` with ``|R(iy)| <= 1`` over the highest frequency ``omega_max`` (power iteration; 1.73 for
Bogacki-Shampine, 0.997 for Dormand-Prince), and the real-axis limit over the dashpots' largest rate. Both limits come from the tableau's stability
function ``R(z)``, computed when the module is loaded. Heun's method has no stable stretch on
the imaginary axis, so for it the error control alone limits ``h``. A try that would need ``h``
below ``min_step`` (default ``1e-6 dt``) stops the run with :class:`StepSizeError`, one line
that says so.

Example:
    >>> import math
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)           # one spring, omega = 1 rad/s
    >>> model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]),
    ...                  dtype=torch.float64)
    >>> s = model.rest_state()
    >>> s.x[0, 2, 0, 0, 1] += 0.1                                   # stretched by 0.1 m
    >>> adaptive = td.Adaptive(rtol=1e-6)
    >>> s, _ = td.simulate(model, s, dt=1.0, steps=3, integrator=adaptive, warn=False)
    >>> abs(float(s.x[0, 2, 0, 0, 1]) - 1.0 - 0.1 * math.cos(3.0)) < 1e-6
    True
    >>> adaptive.stats["accepted"] > 3, adaptive.stats["rejected"] >= 0
    (True, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import ConfigError, DivergenceError
from .integrators import Integrator, positive_dt, rates, stage_time
from .model import Model, State
from .stability import damping_rate_bound, power_omega2

__all__ = ["Pair", "PAIRS", "Adaptive", "StepSizeError", "stability_limits"]


@dataclass(frozen=True)
class Pair:
    """An embedded explicit Runge-Kutta pair.

    Attributes:
        name: its key in :data:`PAIRS`.
        order: order of the propagated solution (weights ``b``).
        error_order: order of the embedded solution (weights ``b - e``).
        c: stage times (fractions of ``h``).
        a: the strictly lower-triangular stage weights, row by row.
        b: weights of the propagated solution.
        e: ``b`` minus the embedded solution's weights (the error estimate's weights).
    """

    name: str
    order: int
    error_order: int
    c: tuple
    a: tuple
    b: tuple
    e: tuple


def _pair(name, order, error_order, c, a, b, b_hat) -> Pair:
    return Pair(
        name, order, error_order, tuple(c), tuple(tuple(r) for r in a), tuple(b), tuple(x - y for x, y in zip(b, b_hat))
    )


#: the pairs by name
PAIRS = {
    p.name: p
    for p in (
        _pair("heun_euler", 2, 1, [0, 1], [[], [1]], [1 / 2, 1 / 2], [1, 0]),
        _pair(
            "bogacki_shampine",
            3,
            2,
            [0, 1 / 2, 3 / 4, 1],
            [[], [1 / 2], [0, 3 / 4], [2 / 9, 1 / 3, 4 / 9]],
            [2 / 9, 1 / 3, 4 / 9, 0],
            [7 / 24, 1 / 4, 1 / 3, 1 / 8],
        ),
        _pair(
            "dormand_prince",
            5,
            4,
            [0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1, 1],
            [
                [],
                [1 / 5],
                [3 / 40, 9 / 40],
                [44 / 45, -56 / 15, 32 / 9],
                [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
                [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
                [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
            ],
            [35 / 384, 0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0],
            [5179 / 57600, 0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40],
        ),
    )
}


def stability_limits(pair: Pair, *, resolution: float = 1e-4) -> tuple:
    """``(imaginary, real)``: how far the pair's stability region reaches along each axis.

    The largest ``y`` with ``|R(i s)| <= 1`` for all ``0 < s <= y`` and the largest ``r`` with
    ``|R(-s)| <= 1`` for all ``0 < s <= r``, where ``R(z) = 1 + z b^T (I - z A)^-1 1`` (scanned in
    steps of ``resolution``).

    Examples:
        >>> [round(v, 3) for v in stability_limits(PAIRS["bogacki_shampine"])]    # sqrt(3), 2.513
        [1.732, 2.513]
        >>> stability_limits(PAIRS["heun_euler"])[0]                              # none on the axis
        0.0
    """
    n = len(pair.c)
    A = np.zeros((n, n))
    for i, row in enumerate(pair.a):
        A[i, : len(row)] = row
    b, one = np.asarray(pair.b), np.ones(n)

    limits = []
    # |R(z)| along each ray at s = resolution, 2 resolution, ... below 10, a block of points per solve
    count = int(np.ceil(10 / resolution)) - 1
    for direction in (1j, -1.0):
        reach = count
        for start in range(0, count, 4096):
            z = direction * resolution * np.arange(start + 1, min(start + 4096, count) + 1)
            stages = np.linalg.solve(np.eye(n) - z[:, None, None] * A, np.broadcast_to(one, (len(z), n))[..., None])
            bad = np.flatnonzero(np.abs(1 + z * (stages[..., 0] @ b)) > 1 + 1e-12)
            if bad.size:
                reach = start + int(bad[0])
                break
        s = reach * resolution
        # a second-order method grows like 1 + s^4 / 8 on the imaginary axis: "stable" only within
        # rounding, for s < 0.002; that is no stretch of stability
        limits.append(round(s, 6) if s >= 0.01 else 0.0)
    return tuple(limits)


class StepSizeError(DivergenceError):
    """An adaptive run needed a step below its ``min_step`` to keep its error within the tolerance.

    Examples:
        >>> e = StepSizeError(t=0.05, h=1e-9, min_step=1e-8, rtol=1e-6, pair="bogacki_shampine")
        >>> str(e).split(":")[0]
        'adaptive step (bogacki_shampine, rtol 1e-06) fell to 1e-09 s at t = 0.05 s, below min_step 1e-08 s'
        >>> e.t, isinstance(e, DivergenceError)
        (0.05, True)
    """

    def __init__(self, t: float, h: float, min_step: float, rtol: float, pair: str):
        self.step, self.quantity, self.value, self.dt, self.safe_dt = None, "step size", h, h, None
        self.t, self.min_step = t, min_step
        Exception.__init__(
            self,
            f"adaptive step ({pair}, rtol {rtol:g}) fell to {h:.3g} s at t = {t:.6g} s, below min_step "
            f"{min_step:.3g} s: the motion is too stiff or too abrupt for an explicit pair at this "
            f"tolerance; loosen rtol, lower min_step, or use ImplicitEuler",
        )


class Adaptive(Integrator):
    """An embedded Runge-Kutta pair with error control (see the module docstring).

    Args:
        rtol: relative tolerance of each internal step (positions and velocities).
        atol: absolute tolerances ``(positions m, velocities m/s)``, or None (defaults above).
        pair: a key of :data:`PAIRS` (default ``"bogacki_shampine"``).
        min_step: smallest internal step (s); default ``1e-6`` times the ``dt`` of each call.
        max_step: largest internal step (s), or None (the ``dt`` of the call and the stability limit).

    Attributes:
        stats: ``{"accepted", "rejected", "evaluations", "min_h", "max_h"}`` since construction.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
        >>> model = td.Model(grid, stiffness=50.0, damping=0.02, mass=1e-3, fixed=grid.face("bottom"),
        ...                  loads=[td.PointForce((3, 1, 1), (-0.05, 0.0, 0.0), ramp=0.02)], dtype=torch.float64)
        >>> adaptive = td.Adaptive(rtol=1e-4)
        >>> state = adaptive.step(model, model.rest_state(), dt=0.01)    # 10 ms in as many steps as needed
        >>> round(state.t, 12), adaptive.stats["accepted"] > 1
        (0.01, True)
    """

    name = "adaptive"
    drag_in_rates = True  # the error control then sees the global drag too
    eager_reason = "adaptive steps run in the eager step"

    def __init__(
        self,
        *,
        rtol: float = 1e-3,
        atol=None,
        pair: str = "bogacki_shampine",
        min_step: float | None = None,
        max_step: float | None = None,
    ):
        rtol = float(rtol)
        if not (math.isfinite(rtol) and 0 < rtol < 1):
            raise ConfigError("rtol", "a relative tolerance between 0 and 1 (e.g. 1e-3)", got=rtol)
        if pair not in PAIRS:
            raise ConfigError("pair", f"one of {', '.join(PAIRS)}", got=pair)
        if atol is not None:
            atol = tuple(float(a) for a in atol)
            if len(atol) != 2 or not all(math.isfinite(a) and a > 0 for a in atol):
                raise ConfigError("atol", "two positive numbers (positions m, velocities m/s)", got=atol)
        for key, value in (("min_step", min_step), ("max_step", max_step)):
            if value is not None and not (math.isfinite(float(value)) and float(value) > 0):
                raise ConfigError(key, "a positive number of seconds", got=value)
        self.rtol, self.atol, self.pair = rtol, atol, PAIRS[pair]
        self.min_step, self.max_step = min_step, max_step
        self.imag_limit, self.real_limit = stability_limits(self.pair)
        self.stats = {"accepted": 0, "rejected": 0, "evaluations": 0, "min_h": math.inf, "max_h": 0.0}
        self._h = None
        self._model = None

    # ------------------------------------------------------------------ set-up per model
    def _prepare(self, model: Model) -> None:
        """The stability cap and default tolerances of ``model`` (once per model)."""
        if self._model is model:
            return
        self._model = model
        omega = math.sqrt(max(power_omega2(model), 0.0))
        gamma = damping_rate_bound(model)
        caps = [math.inf]
        if omega > 0 and self.imag_limit > 0:
            caps.append(0.9 * self.imag_limit / omega)
        if gamma > 0:
            caps.append(0.9 * self.real_limit / gamma)
        self.cap = min(caps)
        if self.atol is None:
            ax = self.rtol * 1e-3 * min(model.grid.spacing)
            self.tolerances = (ax, ax * (omega if omega > 0 else 1.0))
        else:
            self.tolerances = self.atol
        self.mask = None if model.free is None else model.free > 0

    # ------------------------------------------------------------------ one try
    def _try(self, f, t, x, v, h):
        """The propagated ``(x, v)`` after ``h`` and the embedded differences ``(ex, ev)``."""
        p, kx, kv = self.pair, [], []
        for i, ci in enumerate(p.c):
            xi, vi = x, v
            for aij, (dx, dv) in zip(p.a[i], zip(kx, kv)):
                if aij:
                    xi, vi = xi + h * aij * dx, vi + h * aij * dv
            rx, rv = f(stage_time(t, h, ci), xi, vi)
            kx.append(rx)
            kv.append(rv)
        self.stats["evaluations"] += len(p.c)

        def combine(w, ks):
            return sum(h * wi * k for wi, k in zip(w, ks) if wi)

        return x + combine(p.b, kx), v + combine(p.b, kv), combine(p.e, kx), combine(p.e, kv)

    def _ratio(self, model, x0, v0, x1, v1, ex, ev) -> float:
        """The error ratio ``err`` of a try (max over the batch; inf when non-finite)."""

        def largest(t):
            t = t.abs()
            if self.mask is not None:
                t = t * self.mask
            return t.flatten(1).amax(1)

        ax, av = self.tolerances
        sx = ax + self.rtol * torch.maximum(largest(x0 - model.X), largest(x1 - model.X))
        sv = av + self.rtol * torch.maximum(largest(v0), largest(v1))
        err = torch.maximum(largest(ex) / sx, largest(ev) / sv).max()
        err = float(err)
        return err if math.isfinite(err) else math.inf

    # ------------------------------------------------------------------ a call
    def step(self, model: Model, state: State, dt: float, *, loads=None) -> State:
        """Advance ``state`` by ``dt`` seconds in as many accepted internal steps as the tolerance needs."""
        dt = positive_dt(dt)
        self._prepare(model)
        f = rates(model, loads=loads)
        min_step = self.min_step or 1e-6 * dt
        cap = min(self.cap, dt, self.max_step or math.inf)
        h = min(self._h or cap, cap)
        t_end = state.t + dt
        q = self.pair.error_order
        while t_end - state.t > 1e-12 * dt:
            last = h >= t_end - state.t
            try_h = t_end - state.t if last else h
            x1, v1, ex, ev = self._try(f, state.t, state.x, state.v, try_h)
            err = self._ratio(model, state.x, state.v, x1, v1, ex, ev)
            factor = 5.0 if err == 0 else min(5.0, max(0.2, 0.9 * err ** (-1.0 / (q + 1))))
            if err <= 1.0:
                state = self.finish(model, state, x1, v1, try_h)
                if last:
                    state = State(state.x, state.v, t=t_end, readings=state.readings)  # no drift of the clock
                self.stats["accepted"] += 1
                self.stats["min_h"] = min(self.stats["min_h"], try_h)
                self.stats["max_h"] = max(self.stats["max_h"], try_h)
                if not last or try_h >= h:  # a shortened last try says nothing about h
                    h = try_h * factor
            else:
                self.stats["rejected"] += 1
                h = try_h * factor
            h = min(h, cap)
            if h < min_step:
                raise StepSizeError(state.t, h, min_step, self.rtol, self.pair.name)
        self._h = h
        return state
