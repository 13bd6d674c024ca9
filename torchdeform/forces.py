"""Force terms other than the grid springs, and prescribed motion.

Each term exists in a :class:`~torchdeform.model.Model` only when the scene names it:

* :class:`PointForce`: a force on one node (N), optionally ramped in over time.
* :class:`SurfaceForce`: a traction (Pa) on a face of the box, lumped onto its nodes.
* :class:`Drag`: a group of nodes moved rigidly along a piecewise-linear path.
* home springs (Punak) and anchors (Radetzky): zero-length springs to the rest position,
  :func:`home_force`.
* gravity and global drag (velocity decay) are plain numbers on the model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .errors import ConfigError
from .grid import FACES, Grid


def _vec3(value, key) -> tuple:
    try:
        v = tuple(float(c) for c in value)
    except TypeError:
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise ConfigError(key, "three finite numbers in channel order (D, H, W)", value)
    return v


def _ramp(t, start: float, ramp: float):
    """Load factor in ``[0, 1]`` at time ``t`` (a float, or a 0-d tensor inside compiled code)."""
    if torch.is_tensor(t):
        a = torch.ones_like(t) if ramp <= 0 else ((t - start) / ramp).clamp(max=1.0)
        return torch.where(t < start, torch.zeros_like(t), a)
    if t < start:
        return 0.0
    return 1.0 if ramp <= 0 else min(1.0, (t - start) / ramp)


@dataclass
class PointForce:
    """A constant force on one node.

    Args:
        node: ``(i, j, k)`` node index.
        force: ``(fd, fh, fw)`` newtons.
        start: time (s) at which the force appears; ramp: seconds to ramp it linearly to full.
    """
    node: tuple
    force: tuple
    start: float = 0.0
    ramp: float = 0.0

    def dense(self, grid: Grid, dtype, device) -> torch.Tensor:
        """The force as a node field ``(1, 3, D, H, W)`` at full strength."""
        mask = grid.index_mask([self.node])
        f = torch.tensor(_vec3(self.force, "point_force.force"), dtype=dtype, device=device)
        return mask.to(dtype=dtype, device=device) * f.view(1, 3, 1, 1, 1)

    def factor(self, t: float) -> float:
        return _ramp(t, self.start, self.ramp)


@dataclass
class SurfaceForce:
    """A traction (force per area, Pa) on one face of the box.

    The traction is lumped onto the face's nodes by their share of the face area (half on
    edges, a quarter on corners), so the total force is ``traction * face area``.

    Args:
        face: ``"d-"``, ``"d+"``, ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``, ``"bottom"``, ``"top"``.
        traction: ``(td, th, tw)`` pascals.
    """
    face: str
    traction: tuple
    start: float = 0.0
    ramp: float = 0.0

    def dense(self, grid: Grid, dtype, device) -> torch.Tensor:
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
        t = torch.tensor(_vec3(self.traction, "surface_force.traction"), dtype=torch.float64)
        return (mask * area * t.view(3, 1, 1, 1)).unsqueeze(0).to(dtype=dtype, device=device)

    def factor(self, t: float) -> float:
        return _ramp(t, self.start, self.ramp)


@dataclass
class Drag:
    """Prescribed rigid translation of a group of nodes along a piecewise-linear path.

    Args:
        nodes: bool mask ``(D, H, W)`` of the dragged nodes.
        path: waypoints ``[(t, (od, oh, ow)), ...]``: offsets (m) from the rest position at
            increasing times (s). Before the first waypoint the offset is that of the first;
            after the last it stays at the last.

    The dragged nodes are constrained: they ignore forces and follow the path exactly.
    """
    nodes: torch.Tensor
    path: list

    def __post_init__(self):
        if not self.path:
            raise ConfigError("drag.path", "at least one waypoint [t, [od, oh, ow]]", self.path)
        times = [float(p[0]) for p in self.path]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ConfigError("drag.path", "waypoint times strictly increasing", times)
        self._t = times
        self._o = [_vec3(p[1], "drag.path offset") for p in self.path]

    def offset(self, t):
        """Offset ``(3,)`` at time ``t``: a tuple for a float ``t``, a tensor for a 0-d tensor
        (the form compiled code uses, without branches)."""
        ts, os_ = self._t, self._o
        if torch.is_tensor(t):
            o = t.new_tensor(os_[0])
            for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
                o = o + ((t - t0) / (t1 - t0)).clamp(0.0, 1.0) * t.new_tensor([q - p for p, q in zip(o0, o1)])
            return o
        if t <= ts[0]:
            return os_[0]
        for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
            if t <= t1:
                a = (t - t0) / (t1 - t0)
                return tuple(p + a * (q - p) for p, q in zip(o0, o1))
        return os_[-1]

    def velocity(self, t):
        """Velocity ``(3,)`` of the path at time ``t`` (the segment entered at ``t``); a tensor
        for a 0-d tensor ``t``, as :meth:`offset`."""
        ts, os_ = self._t, self._o
        if torch.is_tensor(t):
            vel = t.new_zeros(3)
            for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
                inside = ((t >= t0) & (t < t1)).to(t.dtype)
                vel = vel + inside * t.new_tensor([(q - p) / (t1 - t0) for p, q in zip(o0, o1)])
            return vel
        for (t0, o0), (t1, o1) in zip(zip(ts, os_), zip(ts[1:], os_[1:])):
            if t0 <= t < t1:
                return tuple((q - p) / (t1 - t0) for p, q in zip(o0, o1))
        return (0.0, 0.0, 0.0)


def home_force(x: torch.Tensor, X: torch.Tensor, k_home: torch.Tensor) -> torch.Tensor:
    """Zero-length springs to the rest positions: ``k_home (X - x)``.

    Args:
        x: positions ``(B, 3, D, H, W)``; X: rest positions ``(1, 3, D, H, W)``;
        k_home: stiffness per node, broadcastable to ``(B, 1, D, H, W)`` (zero where absent).
    """
    return k_home * (X - x)
