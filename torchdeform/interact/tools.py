"""Rigid tools: a shape and a pose that changes over time, and their signed distance.

A tool is a :class:`Shape` (sphere, capsule, box, half-space) placed at a position that follows a
piecewise-linear path of waypoints, a callable ``t -> (3,)``, or a value set from Python before
each step (:meth:`Tool.move_to`, a device loop). Positions are in metres, channel order
``(D, H, W)`` as everywhere in torchdeform. This first version translates tools only (no
orientation); capsules and boxes are aligned with the grid axes.

Every shape answers :meth:`Shape.sdf`: for points ``p`` ``(B, 3, ...)`` in the tool's frame, the
signed distance ``d`` ``(B, 1, ...)`` (negative inside) and the outward unit normal ``n``
``(B, 3, ...)`` of the nearest surface point, so that ``p - d n`` lies on the surface. The node
layout does not matter (grid ``(B, 3, D, H, W)`` or packed ``(B, 3, P)``): everything is
elementwise over the trailing axes, so the same code runs in the compiled step.

Examples:
    >>> import torch
    >>> from torchdeform.interact import Sphere, Tool
    >>> tool = Tool(Sphere(0.01), path=[(0.0, (0.03, 0.0, 0.0)), (1.0, (0.02, 0.0, 0.0))])
    >>> tool.position(0.5)
    (0.025, 0.0, 0.0)
    >>> d, n = tool.sdf(torch.zeros(1, 3, 1), 0.5)          # a node at the origin
    >>> round(d.item(), 6), n[0, :, 0].tolist()
    (0.015, [-1.0, 0.0, 0.0])
"""
from __future__ import annotations

import math

import torch

from ..errors import ConfigError, positive_number
from ..sim.forces import Waypoints, as_vec3

__all__ = ["Shape", "Sphere", "Capsule", "Box", "HalfSpace", "Tool", "SHAPES"]


def _unit(p: torch.Tensor, fallback: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(|p|, p / |p|)`` over the channel axis 1; a zero vector gets the unit vector of axis ``fallback``."""
    r = p.norm(dim=1, keepdim=True)
    e = torch.zeros_like(p)
    e[:, fallback] = 1.0
    return r, torch.where(r > 0, p / r.clamp_min(torch.finfo(p.dtype).tiny), e)


class Shape:
    """A rigid shape in its own frame (centred on the tool's position)."""

    def sdf(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance ``(B, 1, ...)`` and outward unit normal ``(B, 3, ...)`` at points ``p`` ``(B, 3, ...)``."""
        raise NotImplementedError                                   # pragma: no cover


class Sphere(Shape):
    """A ball of ``radius`` metres (Punak's sphere tool).

    Args:
        radius: metres, > 0.

    Examples:
        >>> import torch
        >>> d, n = Sphere(1.0).sdf(torch.tensor([[[2.0], [0.0], [0.0]]]))
        >>> d.item(), n[0, :, 0].tolist()
        (1.0, [1.0, 0.0, 0.0])
    """

    def __init__(self, radius: float):
        self.radius = positive_number(radius, "sphere.radius", "a positive number of metres")

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        r, n = _unit(p)
        return r - self.radius, n


class Capsule(Shape):
    """A capsule (an instrument shaft) aligned with a grid axis.

    The points within ``radius`` of a segment of half-length ``half_length`` along grid ``axis``
    (0 = D, 1 = H, 2 = W) through the tool's position.

    Args:
        radius: metres, > 0.
        half_length: metres, >= 0 (0 is a sphere).
        axis: 0, 1 or 2.

    Examples:
        >>> import torch
        >>> d, n = Capsule(0.5, 2.0, axis=2).sdf(torch.tensor([[[1.0], [0.0], [1.5]]]))
        >>> d.item(), n[0, :, 0].tolist()
        (0.5, [1.0, 0.0, 0.0])
    """

    def __init__(self, radius: float, half_length: float, axis: int = 2):
        self.radius = positive_number(radius, "capsule.radius", "a positive number of metres")
        try:
            self.half_length = float(half_length)
        except (TypeError, ValueError):
            raise ConfigError("capsule.half_length", "a number of metres >= 0", half_length) from None
        if not math.isfinite(self.half_length) or self.half_length < 0:
            raise ConfigError("capsule.half_length", "a number of metres >= 0", half_length)
        if axis not in (0, 1, 2):
            raise ConfigError("capsule.axis", "0 (D), 1 (H) or 2 (W)", axis)
        self.axis = axis

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        a = self.axis
        on_axis = p[:, a:a + 1].clamp(-self.half_length, self.half_length)
        q = torch.cat([on_axis if c == a else torch.zeros_like(on_axis) for c in range(3)], 1)
        r, n = _unit(p - q, fallback=(a + 1) % 3)
        return r - self.radius, n


class Box(Shape):
    """An axis-aligned box with half extents ``(hd, hh, hw)`` metres.

    Outside, the normal points from the nearest box point; inside, it is the normal of the nearest
    face (so projection pushes a node out through that face).

    Args:
        half_extents: three positive numbers (metres), channel order ``(D, H, W)``.

    Examples:
        >>> import torch
        >>> d, n = Box((1.0, 1.0, 1.0)).sdf(torch.tensor([[[0.0], [0.0], [0.75]]]))
        >>> d.item(), n[0, :, 0].tolist()
        (-0.25, [0.0, 0.0, 1.0])
    """

    def __init__(self, half_extents):
        h = as_vec3(half_extents, "box.half_extents")
        if min(h) <= 0:
            raise ConfigError("box.half_extents", "three positive numbers (metres)", half_extents)
        self.half_extents = h

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        h = p.new_tensor(self.half_extents).view(1, 3, *[1] * (p.dim() - 2))
        q = p.abs() - h                                             # > 0 outside along that axis
        outside = q.clamp_min(0)
        r_out, n_out = _unit(outside * p.sign())
        inside_d, face = q.max(dim=1, keepdim=True)                 # nearest face from inside (<= 0)
        n_in = torch.zeros_like(p).scatter(1, face, 1.0) * p.sign().where(p != 0, torch.ones_like(p))
        is_out = (q > 0).any(dim=1, keepdim=True)
        return torch.where(is_out, r_out, inside_d), torch.where(is_out, n_out, n_in)


class HalfSpace(Shape):
    """The half-space behind a plane through the tool's position: a floor, a support, a wall.

    With outward ``normal``, ``d = (p - position) . normal``.

    Args:
        normal: three numbers, the outward direction (normalised here).

    Examples:
        >>> import torch
        >>> d, n = HalfSpace((1.0, 0.0, 0.0)).sdf(torch.tensor([[[-0.5], [3.0], [0.0]]]))
        >>> d.item(), n[0, :, 0].tolist()
        (-0.5, [1.0, 0.0, 0.0])
    """

    def __init__(self, normal=(1.0, 0.0, 0.0)):
        v = as_vec3(normal, "half_space.normal")
        s = math.sqrt(sum(c * c for c in v))
        if s == 0:
            raise ConfigError("half_space.normal", "a non-zero direction", normal)
        self.normal = tuple(c / s for c in v)

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        n = p.new_tensor(self.normal).view(1, 3, *[1] * (p.dim() - 2))
        return (p * n).sum(1, keepdim=True), n.expand_as(p)


#: shape names of scene files -> classes
SHAPES = {"sphere": Sphere, "capsule": Capsule, "box": Box, "half_space": HalfSpace}


class Tool:
    """A shape whose position follows a path, a callable, or values set from Python.

    Args:
        shape: a :class:`Shape`.
        path: waypoints ``[(t, (pd, ph, pw)), ...]``: positions (m) at strictly increasing times
            (s), linear in between, held before the first and after the last.
        position: instead of ``path``: a fixed position ``(3,)`` or a callable ``t -> (3,)``.
        name: for reports.

    Examples:
        >>> tool = Tool(Sphere(0.005), position=(0.0, 0.0, 0.01))
        >>> tool.move_to((0.001, 0.0, 0.01))                    # a device loop sets the pose each tick
        >>> tool.position(0.0), tool.velocity(0.0)
        ((0.001, 0.0, 0.01), (0.0, 0.0, 0.0))
    """

    def __init__(self, shape: Shape, path=None, *, position=None, name: str = "tool"):
        if not isinstance(shape, Shape):
            raise ConfigError("tool.shape", "a Sphere, Capsule, Box or HalfSpace", type(shape).__name__)
        if (path is None) == (position is None):
            raise ConfigError("tool", "exactly one of path (waypoints) or position (fixed or callable)",
                              "both" if path is not None else "neither")
        self.shape, self.name, self._fn, self._path = shape, name, None, None
        if path is not None:
            self._path = Waypoints(path, "tool.path")
        elif callable(position):
            self._fn = position
        else:
            self.move_to(position)

    def move_to(self, position) -> None:
        """Set a fixed position ``(3,)`` m (a device loop calls this before each step)."""
        self._path, self._fn = Waypoints([(0.0, as_vec3(position, "tool.position"))], "tool.position"), None

    def position(self, t):
        """Position at time ``t``: a tuple for a float ``t``, a tensor ``(3,)`` for a 0-d tensor."""
        if self._fn is not None:
            p = self._fn(t)
            return p if torch.is_tensor(p) or not torch.is_tensor(t) else t.new_tensor(p)
        return self._path.at(t)

    def velocity(self, t, dt: float = 1e-6):
        """Velocity ``(3,)`` m/s at ``t``.

        The path segment entered at ``t``; a central difference of step ``dt`` for a callable.
        """
        if self._fn is not None:
            a, b = self.position(t - dt), self.position(t + dt)
            if torch.is_tensor(a):
                return (b - a) / (2 * dt)
            return tuple((q - p) / (2 * dt) for p, q in zip(a, b))
        return self._path.rate(t)

    def sdf(self, x: torch.Tensor, t) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance ``(B, 1, ...)`` and outward normal ``(B, 3, ...)`` of nodes ``x`` at time ``t``.

        Args:
            x: node positions ``(B, 3, ...)`` (m).
            t: time (s), a float or a 0-d tensor.
        """
        c = torch.as_tensor(self.position(t), dtype=x.dtype, device=x.device).view(1, 3, *[1] * (x.dim() - 2))
        return self.shape.sdf(x - c)
