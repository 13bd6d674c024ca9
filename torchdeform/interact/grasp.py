"""Grasping: nodes attached to a tool's frame follow its pose (Radetzky's forceps).

:class:`Attachment` holds nodes at fixed points of a tool's own frame: every step they are put
where those points are now (``x = c + R p``) and move with the tool's velocity there. A
:class:`Grasp` attaches the free nodes within its jaws (the tool's shape, plus ``margin``) when it
closes and releases them, moving with the tool, when it opens. Contact's anti-jitter option
(``ProjectionContact(hold=True)``) uses the same attachment for the nodes a tool touches.

Both keep the attached set in Python between steps: they run in the eager step (the compiled step
falls back to it with one warning line).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import Box, Grasp, Tool
    >>> grid = td.Grid((3, 3, 3), spacing=0.01)
    >>> jaws = Tool(Box((0.004, 0.004, 0.004)), path=[(0.0, (0.02, 0.01, 0.01)), (0.05, (0.02, 0.01, 0.01)),
    ...                                              (0.2, (0.03, 0.01, 0.01))], name="forceps")
    >>> grasp = Grasp(jaws, close=0.01, open=0.3)                # closes on the top centre node, lifts 1 cm
    >>> model = td.Model(grid, stiffness=20.0, damping=0.05, mass=1e-3, fixed=grid.face("bottom"),
    ...                  interactions=[grasp], dtype=torch.float64)
    >>> state, _ = td.simulate(model, model.rest_state(), dt=5e-4, steps=500)
    >>> round(float(state.x[0, 0, 2, 1, 1]), 6)                  # the top centre node lifted 1 cm
    0.03
    >>> state.readings["forceps.grasped"].tolist(), bool(state.readings["forceps.force"][0, 0] < 0)
    ([1.0], True)
"""

from __future__ import annotations

import math

import torch

from ..errors import ConfigError
from .reactions import report, report_momentum
from .tools import Tool, _rotate

__all__ = ["Attachment", "Grasp"]


class Attachment:
    """Nodes fixed at points of a tool's frame (positions ``p`` in the tool's own coordinates).

    Attributes:
        mask: bool ``(B, 1, ...)`` of the attached nodes, or None before the first attach.
        local: their positions in the tool's frame ``(B, 3, ...)``.
    """

    def __init__(self):
        self.mask, self.local = None, None

    def attach(self, tool: Tool, new: torch.Tensor, x: torch.Tensor, t) -> None:
        """Attach the nodes of the bool mask ``new`` ``(B, 1, ...)`` where they are now (``x`` at ``t``)."""
        c, R = tool.frame(t, x)
        local = x - c if R is None else _rotate(R, x - c, transpose=True)
        if self.mask is None or self.mask.shape[0] != x.shape[0] or self.mask.shape[2:] != x.shape[2:]:
            self.mask, self.local = torch.zeros_like(new), torch.zeros_like(local.expand_as(x))
        self.local = torch.where(new, local, self.local)
        self.mask = self.mask | new

    def release(self, *, which: torch.Tensor | None = None) -> None:
        """Let go of the nodes of ``which`` (all when None)."""
        if self.mask is not None:
            self.mask = torch.zeros_like(self.mask) if which is None else self.mask & ~which

    def count(self) -> int:
        """Attached nodes (all batch entries)."""
        return 0 if self.mask is None else int(self.mask.sum())

    def follow(self, tool: Tool, x: torch.Tensor, v: torch.Tensor, t):
        """Attached nodes put on their points of the tool at ``t``, with the tool's velocity there."""
        if self.mask is None:
            return x, v
        c, R = tool.frame(t, x)
        target = c + (self.local if R is None else _rotate(R, self.local))
        x = torch.where(self.mask, target, x)
        v = torch.where(self.mask, tool.point_velocity(target, t).expand_as(v), v)
        return x, v


def _time(value, key):
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, "a time in seconds", got=value) from None
    if math.isnan(v) or v < 0:
        raise ConfigError(key, "a time in seconds >= 0", got=value)
    return v


class Grasp:
    """A grasping tool (forceps): what is inside its jaws when it closes follows it until it opens.

    Pass it to a model with ``Model(..., interactions=[Grasp(...)])``. At the first step ending at
    or after ``close`` the free nodes within ``margin`` of the tool's shape (its jaws' volume) are
    attached; while closed they follow the tool's pose change every step exactly (translation and
    rotation); at the first step ending at or after ``open`` they are released, moving with the
    tool's velocity. Without times, a device loop sets :attr:`closed` itself.

    Reports ``<name>.force``, ``<name>.torque`` (what the held tissue pulls on the forceps) and
    ``<name>.grasped`` (the number of nodes held) every step.

    Args:
        tool: the :class:`~torchdeform.interact.tools.Tool` (its shape is the jaws' volume).
        close: time (s) the jaws close, or None (set :attr:`closed` from Python).
        open: time (s) they open again, after ``close``; required with ``close`` (``math.inf`` for never).
        margin: metres added around the shape when choosing the nodes, >= 0.

    Examples:
        >>> from torchdeform.interact import Sphere, Tool
        >>> g = Grasp(Tool(Sphere(0.003), position=(0.0, 0.0, 0.0)), close=0.1, open=0.5)
        >>> g.closed_at(0.05), g.closed_at(0.1), g.closed_at(0.5)
        (False, True, False)
    """

    def __init__(self, tool: Tool, *, close: float | None = None, open: float | None = None, margin: float = 0.0):
        if not isinstance(tool, Tool):
            raise ConfigError("grasp.tool", "a Tool", got=type(tool).__name__)
        self.tool, self.close, self.open = tool, _time(close, "grasp.close"), _time(open, "grasp.open")
        if (self.close is None) != (self.open is None):
            raise ConfigError(
                "grasp", "both a close and an open time (s), open = inf for never", got=f"close={close}, open={open}"
            )
        if self.close is not None and not self.open > self.close:
            raise ConfigError("grasp.open", f"a time after close = {self.close} s", got=open)
        try:
            self.margin = float(margin)
        except (TypeError, ValueError):
            raise ConfigError("grasp.margin", "metres >= 0", got=margin) from None
        if not math.isfinite(self.margin) or self.margin < 0:
            raise ConfigError("grasp.margin", "metres >= 0", got=margin)
        self.held, self._was_closed = Attachment(), False
        #: closed now (a device loop sets it when no times are given)
        self.closed = False

    #: keeps the grasped nodes in Python between steps: a compiled step falls back to the eager one
    eager_only = True

    def closed_at(self, t: float) -> bool:
        """Whether the jaws are closed at time ``t`` (s) by the schedule."""
        if self.close is None:
            return self.closed
        return self.close <= t < self.open

    def force(self, model, x, v, t):
        """A grasp adds no force."""
        return None

    def project(self, model, x, v, t, dt, *, readings=None):
        """Attach on closing, move the held nodes with the tool, release on opening.

        Args:
            model: the model (its ``free`` mask: only free nodes are grasped).
            x: positions ``(B, 3, ...)`` at the end of the step.
            v: velocities ``(B, 3, ...)``.
            t: the time at the end of the step (a float: the eager step).
            dt: the step (s).
            readings: the step's readings, or None.
        """
        if torch.is_tensor(t):
            raise ConfigError(
                "interactions",
                "a Grasp in the eager step (it keeps the grasped nodes in Python between steps)",
                got="a compiled step",
            )
        now = self.closed_at(float(t))
        if now and not self._was_closed:
            d, _ = self.tool.sdf(x, t)
            inside = d <= self.margin
            if model.free is not None:
                inside = inside & (model.free > 0)
            self.held.attach(self.tool, inside.expand(x.shape[0], *inside.shape[1:]), x, t)
        v0 = v
        x, v = self.held.follow(self.tool, x, v, t)
        if self.held.mask is not None:
            c, _ = self.tool.frame(t, x)
            report_momentum(readings, self.tool.name, model.mass, v - v0, x, c, dt)
        if not now:
            self.held.release()
        self._was_closed = now
        report(
            readings,
            self.tool.name,
            "grasped",
            x.new_zeros(()).expand(x.shape[0])
            if self.held.mask is None
            else self.held.mask.flatten(1).sum(1).to(x.dtype),
        )
        return x, v
