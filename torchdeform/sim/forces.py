"""Force terms other than the grid springs, and prescribed motion.

The one load vocabulary of :class:`~torchdeform.sim.model.Model`, scene files and learning series.

Each term exists in a :class:`~torchdeform.sim.model.Model` only when the scene names it:

* :class:`PointForce`: a force on one node (N).
* :class:`SurfaceForce`: a traction (Pa) on a face of the box, lumped onto its nodes.
* :class:`FieldForce`: a dense force field ``(3, D, H, W)`` (N per node), e.g. a pressure along
  surface normals.
* :class:`Drag`: a group of nodes moved rigidly, along a piecewise-linear path of waypoints or by
  an offset times a time profile.
* home springs (Punak) and anchors (Radetzky): zero-length springs to the rest position,
  :func:`home_force`.
* gravity and global drag (velocity decay) are plain numbers on the model.

Time profile, shared by the loads and by offset drags (:func:`profile_factor`): zero before
``start``; then a linear ramp from 0 to 1 over ``ramp`` seconds (``ramp = 0``: full at once);
with a ``period`` the ramp multiplies ``sin(2 pi (t - start) / period)``. A profile is evaluated
at a float (Python numbers), a 0-d tensor (inside compiled code, without branches) or an array
of times (numpy: the per-step tables of :class:`~torchdeform.learn.series.Series`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import KW_ONLY, dataclass

import numpy as np
import torch

from ..errors import ConfigError
from .grid import FACES, Grid

__all__ = [
    "PointForce",
    "SurfaceForce",
    "FieldForce",
    "Drag",
    "Waypoints",
    "home_force",
    "profile_factor",
    "as_vec3",
    "constant",
]


def constant(value, like: torch.Tensor) -> torch.Tensor:
    """``value`` (numbers, nested sequences or a tensor) as a tensor of ``like``'s dtype and device.

    Numbers reach an accelerator by a non-blocking copy of a fresh host tensor: the host does not
    wait for the device's queued work, as ``like.new_tensor(value)`` does on every call.
    """
    if torch.is_tensor(value):
        return value.to(dtype=like.dtype, device=like.device)
    t = torch.tensor(value, dtype=like.dtype)
    return t if t.device == like.device else t.to(like.device, non_blocking=True)


def as_vec3(value, key) -> tuple:
    """Three finite floats, or a :class:`~torchdeform.errors.ConfigError` naming ``key``."""
    try:
        v = tuple(float(c) for c in value)
    except (TypeError, ValueError):
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise ConfigError(key, "three finite numbers in channel order (D, H, W)", got=value)
    return v


def _timing(start, ramp, period, key) -> None:
    for name, v in (("start", start), ("ramp", ramp)):
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ConfigError(f"{key}.{name}", "a finite number >= 0 (s)", got=v)
    if period is not None and (not isinstance(period, (int, float)) or not math.isfinite(period) or period <= 0):
        raise ConfigError(f"{key}.period", "a positive number of seconds (or None: no oscillation)", got=period)


def profile_factor(t, *, start: float = 0.0, ramp: float = 0.0, period: float | None = None):
    """The time profile of a load or offset drag at ``t`` (see the module docstring).

    Args:
        t: seconds: a float, a 0-d tensor, or an array / list of times.
        start: s, before which the factor is 0.
        ramp: s to rise linearly from 0 to 1.
        period: s of a sine oscillation, or None.

    Returns:
        a float for a float ``t``, a tensor for a tensor, a numpy array of ``t``'s shape otherwise.

    Examples:
        >>> from torchdeform.sim.forces import profile_factor
        >>> profile_factor(0.5, start=0.0, ramp=1.0)
        0.5
        >>> profile_factor([0.0, 0.1, 0.2, 0.3], start=0.1, ramp=0.1).tolist()
        [0.0, 0.0, 1.0, 1.0]
    """
    if torch.is_tensor(t):
        a = torch.ones_like(t) if ramp <= 0 else ((t - start) / ramp).clamp(max=1.0)
        if period is not None:
            a = a * torch.sin(2 * math.pi * (t - start) / period)
        return torch.where(t < start, torch.zeros_like(t), a)
    if isinstance(t, (int, float)):
        if t < start:
            return 0.0
        a = 1.0 if ramp <= 0 else min(1.0, (t - start) / ramp)
        return a if period is None else a * math.sin(2 * math.pi * (t - start) / period)
    t = np.asarray(t, dtype=np.float64)
    a = np.ones_like(t) if ramp <= 0 else np.clip((t - start) / ramp, 0.0, 1.0)
    if period is not None:
        a = a * np.sin(2 * math.pi * (t - start) / period)
    return np.where(t >= start, a, 0.0)


class _Timed:
    """The time profile every load shares (fields ``start``, ``ramp``, ``period``)."""

    start: float
    ramp: float
    period: float | None

    def factor(self, t):
        """Load factor at time ``t`` (see :func:`profile_factor`)."""
        return profile_factor(t, start=self.start, ramp=self.ramp, period=self.period)


@dataclass
class PointForce(_Timed):
    """A force on one node, at full strength from ``start`` on (after an optional ramp).

    Args:
        node: ``(i, j, k)`` node index.
        force: ``(fd, fh, fw)`` newtons.
        start: time (s) at which the force appears.
        ramp: seconds to ramp it linearly to full.
        period: seconds of a sinusoidal oscillation ``sin(2 pi (t - start) / period)``, or None.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> f = td.PointForce((2, 1, 1), (-0.05, 0.0, 0.0), ramp=0.2)
        >>> f.factor(0.1), f.dense(td.Grid((3, 3, 3), spacing=0.01), torch.float64, "cpu")[0, 0, 2, 1, 1].item()
        (0.5, -0.05)
    """

    node: tuple
    force: tuple
    _: KW_ONLY
    start: float = 0.0
    ramp: float = 0.0
    period: float | None = None

    def __post_init__(self):
        _timing(self.start, self.ramp, self.period, "point_force")

    def dense(self, grid: Grid, dtype, device) -> torch.Tensor:
        """The force as a node field ``(1, 3, D, H, W)`` at full strength."""
        mask = grid.index_mask([self.node])
        f = torch.tensor(as_vec3(self.force, "point_force.force"), dtype=dtype, device=device)
        return mask.to(dtype=dtype, device=device) * f.view(1, 3, 1, 1, 1)


@dataclass
class SurfaceForce(_Timed):
    """A traction (force per area, Pa) on one face of the box.

    The traction is lumped onto the face's nodes by their share of the face area (half on
    edges, a quarter on corners), so the total force is ``traction * face area``.

    Args:
        face: ``"d-"``, ``"d+"``, ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``, ``"bottom"``, ``"top"``.
        traction: ``(td, th, tw)`` pascals.
        start, ramp, period: the time profile, as for :class:`PointForce`.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> g = td.Grid((3, 3, 3), spacing=0.01)
        >>> top = td.SurfaceForce("top", (-100.0, 0.0, 0.0)).dense(g, torch.float64, "cpu")
        >>> round(top.sum().item(), 6)                # -100 Pa over a 2 cm x 2 cm face
        -0.04
    """

    face: str
    traction: tuple
    _: KW_ONLY
    start: float = 0.0
    ramp: float = 0.0
    period: float | None = None

    def __post_init__(self):
        _timing(self.start, self.ramp, self.period, "surface_force")

    def dense(self, grid: Grid, dtype, device) -> torch.Tensor:
        """The lumped traction as a node field ``(1, 3, D, H, W)`` at full strength."""
        mask = grid.face(self.face).to(torch.float64)
        axis = FACES[self.face][0]
        area = torch.ones(grid.shape, dtype=torch.float64)
        for b in range(3):
            if b == axis:
                continue
            area *= grid.spacing[b]
            n = grid.shape[b]
            if n > 1:
                w = torch.ones(n, dtype=torch.float64)
                w[0] = w[-1] = 0.5
                area *= w.view([-1 if a == b else 1 for a in range(3)])
        t = torch.tensor(as_vec3(self.traction, "surface_force.traction"), dtype=torch.float64)
        return (mask * area * t.view(3, 1, 1, 1)).unsqueeze(0).to(dtype=dtype, device=device)


@dataclass
class FieldForce(_Timed):
    """A dense force field on the nodes (N per node), e.g. a pressure along surface normals.

    Args:
        field: ``(3, D, H, W)`` newtons (numpy array or tensor).
        start, ramp, period: the time profile, as for :class:`PointForce`.

    Examples:
        >>> import numpy as np
        >>> import torch
        >>> import torchdeform as td
        >>> f = td.FieldForce(np.ones((3, 2, 2, 2)), ramp=1.0)
        >>> f.dense(td.Grid((2, 2, 2), spacing=0.01), torch.float32, "cpu").shape, f.factor(0.25)
        (torch.Size([1, 3, 2, 2, 2]), 0.25)
    """

    field: np.ndarray
    _: KW_ONLY
    start: float = 0.0
    ramp: float = 0.0
    period: float | None = None

    def __post_init__(self):
        _timing(self.start, self.ramp, self.period, "field_force")

    def dense(self, grid: Grid, dtype, device) -> torch.Tensor:
        """The field as ``(1, 3, D, H, W)`` at full strength."""
        f = torch.as_tensor(np.asarray(self.field) if not torch.is_tensor(self.field) else self.field)
        if tuple(f.shape) != (3,) + grid.shape:
            raise ConfigError("field_force.field", f"shape (3, {', '.join(map(str, grid.shape))})", got=tuple(f.shape))
        return f.to(dtype=dtype, device=device).unsqueeze(0)


class Waypoints:
    """A piecewise-linear path of 3-vectors through waypoints ``[(t, (a, b, c)), ...]``.

    Held at the first value before the first time and at the last after the last; evaluated at a
    float (tuples), a 0-d tensor (tensors, without branches: the form compiled code uses) or an
    array of times (``(T, 3)`` numpy). Drags (offsets) and tools (positions) share it.

    Args:
        path: waypoints with strictly increasing times (s).
        key: the name errors use (``"drag.path"``, ``"tool.path"``).

    Examples:
        >>> w = Waypoints([(0.0, (0.0, 0.0, 0.0)), (2.0, (2.0, 0.0, -4.0))])
        >>> w.at(0.5), w.rate(0.5), w.at(3.0)
        ((0.5, 0.0, -1.0), (1.0, 0.0, -2.0), (2.0, 0.0, -4.0))
    """

    def __init__(self, path, *, key: str = "path"):
        if not path:
            raise ConfigError(key, "at least one waypoint [t, [a, b, c]]", got=path)
        try:
            times = [float(p[0]) for p in path]
        except (TypeError, ValueError, IndexError):
            raise ConfigError(key, "waypoints [t, [a, b, c]] with a number t (s)", got=path) from None
        if not all(math.isfinite(t) for t in times):
            raise ConfigError(key, "finite waypoint times (s)", got=times)
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ConfigError(key, "waypoint times strictly increasing", got=times)
        self.times, self.values = times, [as_vec3(p[1], f"{key} value") for p in path]

    def at(self, t):
        """The value at time ``t`` (a tuple, a tensor ``(3,)`` or an array ``(T, 3)``)."""
        ts, os_ = self.times, self.values
        if torch.is_tensor(t):
            o = constant(os_[0], t)
            for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
                o = o + ((t - t0) / (t1 - t0)).clamp(0.0, 1.0) * constant([q - p for p, q in zip(o0, o1)], t)
            return o
        if not isinstance(t, (int, float)):
            t = np.asarray(t, dtype=np.float64)
            return np.stack([np.interp(t, ts, [o[c] for o in os_]) for c in range(3)], -1)
        if t <= ts[0]:
            return os_[0]
        for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
            if t <= t1:
                a = (t - t0) / (t1 - t0)
                return tuple(p + a * (q - p) for p, q in zip(o0, o1))
        return os_[-1]

    def rate(self, t):
        """The rate of change at ``t`` (of the segment entered at ``t``; zero outside the path)."""
        ts, os_ = self.times, self.values
        if torch.is_tensor(t):
            vel = t.new_zeros(3)
            for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
                inside = ((t >= t0) & (t < t1)).to(t.dtype)
                vel = vel + inside * constant([(q - p) / (t1 - t0) for p, q in zip(o0, o1)], t)
            return vel
        for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
            if t0 <= t < t1:
                return tuple((q - p) / (t1 - t0) for p, q in zip(o0, o1))
        return (0.0, 0.0, 0.0)


@dataclass
class Drag(_Timed):
    """Prescribed rigid translation of a group of nodes.

    Either along a piecewise-linear ``path`` of waypoints, or by a fixed ``offset`` times the time
    profile (``start``, ``ramp``, ``period``: a ramp, an indentation, a sinusoidal drag).

    Args:
        nodes: bool mask ``(D, H, W)`` of the dragged nodes.
        path: waypoints ``[(t, (od, oh, ow)), ...]``: offsets (m) from the rest position at
            increasing times (s). Before the first waypoint the offset is that of the first;
            after the last it stays at the last.
        offset: instead of ``path``: ``(od, oh, ow)`` metres, scaled by the profile.
        start, ramp, period: the time profile of ``offset`` (see :func:`profile_factor`).

    The dragged nodes are constrained: they ignore forces and follow the path exactly.

    Examples:
        >>> import torchdeform as td
        >>> g = td.Grid((3, 3, 3), spacing=0.01)
        >>> d = td.Drag(g.face("top"), path=[(0.0, (0, 0, 0)), (1.0, (0.002, 0, 0))])
        >>> d.offset(0.5), d.velocity(0.5)
        ((0.001, 0.0, 0.0), (0.002, 0.0, 0.0))
        >>> td.Drag(g.face("top"), offset=(0.002, 0, 0), ramp=1.0).offset(0.5)
        (0.001, 0.0, 0.0)
    """

    nodes: torch.Tensor
    path: list | None = None
    offset_vector: tuple | None = None
    start: float = 0.0
    ramp: float = 0.0
    period: float | None = None

    def __init__(
        self, nodes, *, path=None, offset=None, start: float = 0.0, ramp: float = 0.0, period: float | None = None
    ):
        self.nodes, self.path, self.start, self.ramp, self.period = nodes, path, start, ramp, period
        self.offset_vector = None if offset is None else as_vec3(offset, "drag.offset")
        if (path is None) == (offset is None):
            raise ConfigError(
                "drag",
                "exactly one of path (waypoints) or offset (with a time profile)",
                got="both" if path is not None else "neither",
            )
        _timing(start, ramp, period, "drag")
        self._path = None if path is None else Waypoints(path, key="drag.path")

    def mask(self) -> torch.Tensor:
        """The dragged nodes as a bool tensor ``(D, H, W)``."""
        return torch.as_tensor(self.nodes, dtype=torch.bool)

    def offset(self, t):
        """Offset (m) from the rest position at time ``t``.

        A tuple ``(3,)`` for a float ``t``, a tensor ``(3,)`` for a 0-d tensor (the form compiled
        code uses, without branches), an array ``(T, 3)`` for an array of ``T`` times.
        """
        if self.path is None:
            f, o = self.factor(t), self.offset_vector
            assert o is not None  # an offset is given when there is no path
            if torch.is_tensor(t):
                return constant(o, t) * f
            if isinstance(t, (int, float)):
                return tuple(c * f for c in o)
            return np.asarray(f)[:, None] * np.asarray(o)[None]
        assert self._path is not None  # the waypoints of the path
        return self._path.at(t)

    def velocity(self, t):
        """Velocity ``(3,)`` at time ``t`` (for a path: of the segment entered at ``t``).

        A tensor for a 0-d tensor ``t``, as :meth:`offset`.
        """
        if self.path is None:
            return self._profile_velocity(t)
        assert self._path is not None  # the waypoints of the path
        return self._path.rate(t)

    def _profile_velocity(self, t):
        """Time derivative of ``offset * factor(t)`` (the ramp's slope on ``[start, start + ramp)``)."""
        s, r, p, o = self.start, self.ramp, self.period, self.offset_vector
        assert o is not None  # an offset is given when there is no path
        tensor = torch.is_tensor(t)
        if tensor:
            tt = t
            on_ramp = ((t >= s) & (t < s + r)).to(t.dtype) if r > 0 else torch.zeros_like(t)
            ramp_v = 1.0 if r <= 0 else ((t - s) / r).clamp(0.0, 1.0)
            after = (t >= s).to(t.dtype)
        else:
            tt = float(t)
            on_ramp = 1.0 if r > 0 and s <= tt < s + r else 0.0
            ramp_v = 1.0 if r <= 0 else min(1.0, max(0.0, (tt - s) / r))
            after = 1.0 if tt >= s else 0.0
        slope = on_ramp / r if r > 0 else on_ramp
        if p is None:
            rate = slope * after
        else:
            w = 2 * math.pi / p
            if tensor:
                rate = after * (slope * torch.sin(w * (t - s)) + ramp_v * w * torch.cos(w * (t - s)))
            else:
                rate = after * (slope * math.sin(w * (tt - s)) + ramp_v * w * math.cos(w * (tt - s)))
        if tensor:
            return constant(o, t) * rate
        return tuple(c * rate for c in o)


def home_force(x: torch.Tensor, X: torch.Tensor, k_home: torch.Tensor) -> torch.Tensor:
    """Zero-length springs to the rest positions: ``k_home (X - x)``.

    Args:
        x: positions ``(B, 3, D, H, W)``.
        X: rest positions ``(1, 3, D, H, W)``.
        k_home: stiffness per node, broadcastable to ``(B, 1, D, H, W)`` (zero where absent).
    """
    return k_home * (X - x)
