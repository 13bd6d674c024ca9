"""A haptic loop: a tool pose in, a force out, at a fixed rate (1 kHz for a force-feedback device).

Punak and Radetzky name the rates: force feedback wants about 1 kHz (at least 300 Hz), the
picture 10-60 Hz. :class:`HapticLoop` takes the device's tool position at every tick and returns
the force the hand should feel (N, ``(3,)``, as reported by the tool's contact).

* ``mode="direct"``: every tick advances the body ``steps_per_tick`` steps with the tool at the
  new position and returns the force of the last step. The rate is what the body allows.
* ``mode="local"``: the body steps in a background thread at its own rate; each tick renders the
  force from a local linear model of the contact, refreshed whenever the body steps:
  ``F(p) = F_b - K (p - p_b)`` where ``F_b`` is the force at the body's last step with the tool at
  ``p_b``, and ``K = sum_i k_i n_i n_i^T`` over the touched nodes (``k_i`` the stiffness of the
  node's springs, ``n_i`` the tool's surface normal there): pressing deeper by ``dp`` pushes
  every touched node ``n_i . dp`` further in. So force output keeps the tick rate while a large
  body updates slower (Mark et al.'s "intermediate representation" for haptics).
* ``mode="auto"``: direct when one body step fits in a tick, local otherwise.

The body's step is compiled by default (:class:`~torchdeform.sim.compiled.CompiledStep` with
inductor's C++ wrapper, which releases the GIL while the step runs, so the device thread's ticks
keep their rate; the tool's position is a tensor updated in place, so moving it never
recompiles).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import HapticLoop, Sphere
    >>> grid = td.Grid((4, 4, 4), spacing=0.01)
    >>> model = td.Model(grid, stiffness=50.0, damping=0.1, mass=1e-3, fixed=grid.face("bottom"),
    ...                  dtype=torch.float64)
    >>> loop = HapticLoop(model, Sphere(0.01), start=(0.041, 0.01, 0.01), dt=2e-4, mode="direct",
    ...                   steps_per_tick=5, compiled=False)
    >>> with loop:                                           # the device presses 4 mm in 50 ticks
    ...     forces = [loop.tick((0.041 - 0.004 * k / 50, 0.01, 0.01)) for k in range(50)]
    >>> bool(forces[0][0] == 0 and forces[-1][0] > 0), loop.stats()["mode"]   # the tissue pushes up
    (True, 'direct')
"""

from __future__ import annotations

import copy
import threading
import time

import numpy as np
import torch

from ..errors import ConfigError, positive_number
from .contact import ProjectionContact
from .tools import Shape, Tool

__all__ = ["HapticLoop"]

MODES = ("auto", "direct", "local")


class HapticLoop:
    """Fixed-rate force output for a haptic device driving one tool (see the module docstring).

    Args:
        model: the body (its own interactions stay; the loop adds the tool's contact).
        shape: the tool's :class:`~torchdeform.interact.tools.Shape`.
        start: the tool's first position ``(3,)`` m.
        dt: the body's time step (s).
        rate: force output rate (Hz), default 1000.
        mode: ``"auto"``, ``"direct"`` or ``"local"``.
        steps_per_tick: body steps per tick in direct mode (default: ``1 / (rate dt)``, real time).
        integrator: default symplectic Euler.
        compiled: compile the body step.
        contact: keyword arguments of :class:`~torchdeform.interact.contact.ProjectionContact`.
        name: the tool's name.
    """

    def __init__(
        self,
        model,
        shape: Shape,
        start,
        dt: float,
        *,
        rate: float = 1000.0,
        mode: str = "auto",
        steps_per_tick: int | None = None,
        integrator=None,
        compiled: bool = True,
        contact: dict | None = None,
        name: str = "haptic",
    ):
        from .._compile import INDUCTOR_OPTIONS
        from ..sim.compiled import IMPLICIT_OPTIONS, CompiledStep
        from ..sim.integrators import SymplecticEuler
        from ..sim.model import Model

        if mode not in MODES:
            raise ConfigError("haptic.mode", " or ".join(MODES), got=mode)
        self.rate = positive_number(rate, "haptic.rate", expected="a positive rate in Hz")
        self.dt = positive_number(dt, "haptic.dt", expected="a positive time step (s)")
        if steps_per_tick is None:
            steps_per_tick = max(1, round(1.0 / (self.rate * self.dt)))
        if not isinstance(steps_per_tick, int) or steps_per_tick < 1:
            raise ConfigError("haptic.steps_per_tick", "an integer >= 1", got=steps_per_tick)
        self.steps_per_tick = steps_per_tick
        self.pose = torch.tensor(start, dtype=model.dtype, device=model.device).reshape(3)
        self.tool = Tool(shape, position=self.pose, name=name)
        self.contact = ProjectionContact(self.tool, **(contact or {}))
        if not isinstance(model, Model):
            raise ConfigError("haptic.model", "a torchdeform Model", got=type(model).__name__)
        self.model = body = copy.copy(model)  # the caller's model keeps its interactions
        body.interactions = list(model.interactions) + [self.contact]
        spacing = model.grid.spacing
        self._touch = 1e-6 * (min(spacing) if isinstance(spacing, (tuple, list)) else spacing)
        # inductor's C++ wrapper runs the whole step without the GIL: the ticks of the device thread
        # are not held up behind it (the Python wrapper's kernels keep the GIL: at 64^3 a
        # 0.5 ms sleep of the other thread then took 7.4 ms, with the C++ wrapper 0.58 ms)
        self.step = CompiledStep(
            integrator or SymplecticEuler(),
            body,
            self.dt,
            enable=compiled,
            options={**INDUCTOR_OPTIONS, **IMPLICIT_OPTIONS},
        )
        self.state = self.step.packed.pack_state(body.rest_state())
        self._k_node = self.step.packed.spring_sums(self.step.packed.stiffness)  # (1, 1, P)
        self.mode, self._requested = mode, mode
        self._lock = threading.Lock()
        self._thread, self._running = None, False
        self._body = (np.zeros(3), self.pose.cpu().numpy().astype(np.float64), np.zeros((3, 3)))
        self._ticks = self._body_steps = 0
        self._t_end = None
        self._t0 = self._next = time.perf_counter()
        self._target = self.pose.cpu().numpy().astype(np.float64)

    # ---------------------------------------------------------------- body
    def advance(self, *, read: bool = True) -> None:
        """One body step with the tool where the last tick put it; refreshes the force and :meth:`local_model`.

        The body thread runs this in a loop in local mode; direct mode runs it in every tick.

        Args:
            read: hand this step's force (and in local mode its contact stiffness) to the device
                side, :meth:`local_model`. That read is the one wait for an accelerator per step;
                direct mode reads after the last step of a tick only.
        """
        with self._lock:
            p = self._target.copy()
        # a fresh host array: the copy need not wait for the device's queued steps
        self.pose.copy_(torch.as_tensor(p, dtype=self.pose.dtype), non_blocking=True)
        self.state = self.step.step_packed(self.state)
        if not read:
            with self._lock:
                self._body_steps += 1
            return
        force = self.state.readings[f"{self.tool.name}.force"][0].reshape(3)
        K = torch.zeros((3, 3), dtype=force.dtype, device=force.device)
        if self.mode == "local":
            with torch.no_grad():
                d, n = self.tool.sdf(self.state.x, self.state.t)
                touched = (d <= self._touch) & (self.step.packed.free > 0)
                w = (self._k_node * touched)[0, 0]  # (P,)
                nn = n[0]  # (3, P)
                K = torch.einsum("p,ip,jp->ij", w, nn, nn)
        # the force the hand feels goes to the device driver: the host waits for the step here, once
        out = torch.cat([force.detach(), K.detach().reshape(9)]).double().cpu().numpy()
        with self._lock:
            self._body = (out[:3], p, out[3:].reshape(3, 3))
            self._body_steps += 1

    def local_model(self):
        """``(F_b, p_b, K)`` of the body's last step (zero ``K`` in direct mode).

        The force ``(3,)`` N, the tool position there ``(3,)`` m and the contact stiffness ``(3, 3)`` N/m.
        """
        with self._lock:
            return self._body

    def _run_body(self) -> None:
        while self._running:
            self.advance()

    # ---------------------------------------------------------------- device side
    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def start(self) -> None:
        """Compile and warm up the body step, choose the mode, start the body thread (local mode)."""
        t0 = time.perf_counter()
        self.advance()  # compiles on this first call
        self.compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(3):
            self.advance()
        per_step = (time.perf_counter() - t0) / 3
        if self._requested == "auto":
            self.mode = "direct" if per_step * self.steps_per_tick < 0.8 / self.rate else "local"
        self._ticks = self._body_steps = 0
        if self.mode == "local":
            self._running = True
            self._thread = threading.Thread(target=self._run_body, name="torchdeform-haptic-body", daemon=True)
            self._thread.start()
        self._t0 = self._next = time.perf_counter()

    def stop(self) -> None:
        """Stop the body thread."""
        self._running = False
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self._t_end = time.perf_counter()

    def tick(self, position) -> np.ndarray:
        """The force ``(3,)`` N the hand feels with the tool at ``position`` ``(3,)`` m; paced to :attr:`rate`."""
        p = np.asarray(position, dtype=np.float64).reshape(3)
        if not np.isfinite(p).all():
            raise ConfigError("haptic.position", "three finite numbers (m)", got=position)
        with self._lock:
            self._target = p
        if self.mode == "direct":
            for k in range(self.steps_per_tick):
                self.advance(read=k == self.steps_per_tick - 1)
            force = self._body[0]
        else:
            f_b, p_b, K = self.local_model()
            force = f_b - K @ (p - p_b)
        self._ticks += 1
        self._next += 1.0 / self.rate
        wait = self._next - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        elif wait < -10.0 / self.rate:  # more than 10 ticks behind: start again, no long burst
            self._next = time.perf_counter()
        self._last_tick = time.perf_counter()
        return force

    def stats(self) -> dict:
        """Measured rates from the start to the last tick.

        ``force_hz`` (ticks per second), ``body_hz`` (body steps per second), ``mode``, the counts.
        """
        end = self._last_tick if self._ticks else time.perf_counter()
        span = max(end - self._t0, 1e-12)
        return {
            "mode": self.mode,
            "force_hz": self._ticks / span,
            "body_hz": self._body_steps / span,
            "ticks": self._ticks,
            "body_steps": self._body_steps,
        }
