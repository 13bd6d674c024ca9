"""Rigid tools: a shape and a pose that changes over time, and their signed distance.

A tool is a :class:`Shape` (sphere, capsule, box, half-space, or a closed triangle mesh through
:class:`~torchdeform.interact.meshes.MeshShape`) with a pose (position and orientation) that
follows a piecewise-linear path of waypoints, a callable ``t -> (3,)``, or values set from Python
before each step (:meth:`Tool.move_to`, a device loop). Positions are in metres, channel order
``(D, H, W)`` as everywhere in torchdeform; orientations are rotation vectors (radians). A pose may
differ per batch entry (``(B, 3)``).

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
from ..sim.forces import Waypoints, as_vec3, constant

__all__ = ["Shape", "Sphere", "Capsule", "Box", "HalfSpace", "Tool", "SHAPES"]


def length(p: torch.Tensor) -> torch.Tensor:
    """``|p|`` over the channel axis 1, ``(B, 1, ...)``.

    A plain sum of squares: ``Tensor.norm(dim=1)`` over a small channel axis took about 30x longer
    on one CPU thread (540 us against 16 us on ``(1, 3, 8, 23, 23)``, torch 2.13).
    """
    return (p * p).sum(1, keepdim=True).sqrt()


def _unit(p: torch.Tensor, fallback: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(|p|, p / |p|)`` over the channel axis 1; a zero vector gets the unit vector of axis ``fallback``."""
    r = length(p)
    e = torch.zeros_like(p)
    e[:, fallback] = 1.0
    return r, torch.where(r > 0, p / r.clamp_min(torch.finfo(p.dtype).tiny), e)


class Shape:
    """A rigid shape in its own frame (centred on the tool's position)."""

    def sdf(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance ``(B, 1, ...)`` and outward unit normal ``(B, 3, ...)`` at points ``p`` ``(B, 3, ...)``."""
        raise NotImplementedError  # pragma: no cover


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
        self.radius = positive_number(radius, "sphere.radius", expected="a positive number of metres")

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

    def __init__(self, radius: float, half_length: float, *, axis: int = 2):
        self.radius = positive_number(radius, "capsule.radius", expected="a positive number of metres")
        try:
            self.half_length = float(half_length)
        except (TypeError, ValueError):
            raise ConfigError("capsule.half_length", "a number of metres >= 0", got=half_length) from None
        if not math.isfinite(self.half_length) or self.half_length < 0:
            raise ConfigError("capsule.half_length", "a number of metres >= 0", got=half_length)
        if axis not in (0, 1, 2):
            raise ConfigError("capsule.axis", "0 (D), 1 (H) or 2 (W)", got=axis)
        self.axis = axis

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        a = self.axis
        on_axis = p[:, a : a + 1].clamp(-self.half_length, self.half_length)
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
            raise ConfigError("box.half_extents", "three positive numbers (metres)", got=half_extents)
        self.half_extents = h

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        h = constant(self.half_extents, p).view(1, 3, *[1] * (p.dim() - 2))
        q = p.abs() - h  # > 0 outside along that axis
        outside = q.clamp_min(0)
        r_out, n_out = _unit(outside * p.sign())
        inside_d, face = q.max(dim=1, keepdim=True)  # nearest face from inside (<= 0)
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
        >>> d, n = HalfSpace(normal=(1.0, 0.0, 0.0)).sdf(torch.tensor([[[-0.5], [3.0], [0.0]]]))
        >>> d.item(), n[0, :, 0].tolist()
        (-0.5, [1.0, 0.0, 0.0])
    """

    def __init__(self, *, normal=(1.0, 0.0, 0.0)):
        v = as_vec3(normal, "half_space.normal")
        s = math.sqrt(sum(c * c for c in v))
        if s == 0:
            raise ConfigError("half_space.normal", "a non-zero direction", got=normal)
        self.normal = tuple(c / s for c in v)

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`)."""
        n = constant(self.normal, p).view(1, 3, *[1] * (p.dim() - 2))
        return (p * n).sum(1, keepdim=True), n.expand_as(p)


#: analytic shape names of scene files -> classes (``torchdeform.interact.SHAPES`` adds ``mesh``)
SHAPES = {"sphere": Sphere, "capsule": Capsule, "box": Box, "half_space": HalfSpace}


def _rotation_matrix(r: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation vectors ``(..., 3)`` (axis times angle, radians) -> matrices ``(..., 3, 3)``."""
    theta = r.norm(dim=-1, keepdim=True)[..., None]  # (..., 1, 1)
    k = r / theta[..., 0].clamp_min(torch.finfo(r.dtype).tiny)
    z = torch.zeros_like(k[..., 0])
    K = torch.stack([z, -k[..., 2], k[..., 1], k[..., 2], z, -k[..., 0], -k[..., 1], k[..., 0], z], -1)
    K = K.view(*k.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(K)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def _field(value, like: torch.Tensor) -> torch.Tensor:
    """A 3-vector ``(3,)`` or one per batch entry ``(B, 3)`` as ``(B|1, 3, 1, ...)`` against fields like ``like``."""
    return constant(value, like).reshape(-1, 3, *[1] * (like.dim() - 2))


def _rotate(R: torch.Tensor, p: torch.Tensor, transpose: bool = False) -> torch.Tensor:
    """``R p`` (or ``R^T p``) for matrices ``(B|1, 3, 3)`` and fields ``(B|1, 3, ...)``."""
    q = (R.transpose(-1, -2) if transpose else R) @ p.flatten(2)
    return q.view(q.shape[0], 3, *p.shape[2:])


class Tool:
    """A shape whose pose follows a path, a callable, or values set from Python.

    The pose is a position ``c`` and an orientation ``R``: a point ``p`` of the shape's own frame
    is at ``c + R p``. Orientations are rotation vectors (axis times angle, radians); along a path
    they are interpolated linearly, which is exact for rotations about a fixed axis. Positions and
    rotation vectors may be ``(3,)`` (all batch entries) or ``(B, 3)`` (one pose per batch entry).

    Args:
        shape: a :class:`Shape`.
        path: waypoints ``[(t, (pd, ph, pw)), ...]`` or ``[(t, (pd, ph, pw), (rd, rh, rw)), ...]``:
            positions (m) and optional rotation vectors (rad) at strictly increasing times (s),
            linear in between, held before the first and after the last.
        position: instead of ``path``: a fixed position ``(3,)`` / ``(B, 3)`` or a callable ``t -> (3,)``.
        orientation: with ``position``: a fixed rotation vector or a callable ``t -> (3,)``; None
            is the identity.
        name: for reports (the keys of the force readings).

    Examples:
        >>> import math
        >>> tool = Tool(Sphere(0.005), position=(0.0, 0.0, 0.01))
        >>> tool.move_to((0.001, 0.0, 0.01))                    # a device loop sets the pose each tick
        >>> tool.position(0.0), tool.velocity(0.0)
        ((0.001, 0.0, 0.01), (0.0, 0.0, 0.0))
        >>> shaft = Tool(Capsule(0.002, 0.02, axis=0), position=(0.0, 0.0, 0.0),
        ...              orientation=(0.0, 0.0, math.pi / 2))   # the D-axis shaft turned onto H
        >>> d, n = shaft.sdf(torch.tensor([[[0.0], [0.015], [0.005]]]), 0.0)
        >>> round(d.item(), 6), [round(c, 6) for c in n[0, :, 0].tolist()]
        (0.003, [0.0, 0.0, 1.0])
    """

    def __init__(self, shape: Shape, *, path=None, position=None, orientation=None, name: str = "tool"):
        if not isinstance(shape, Shape):
            raise ConfigError(
                "tool.shape", "a Shape (Sphere, Capsule, Box, HalfSpace, MeshShape)", got=type(shape).__name__
            )
        if (path is None) == (position is None):
            raise ConfigError(
                "tool",
                "exactly one of path (waypoints) or position (fixed or callable)",
                got="both" if path is not None else "neither",
            )
        if path is not None and orientation is not None:
            raise ConfigError(
                "tool.orientation", "orientations inside the path waypoints (t, position, rotation)", got=orientation
            )
        self.shape, self.name = shape, str(name)
        self._fn = self._path = self._rot_fn = self._rot = None
        if path is not None:
            try:
                rows = [tuple(w) for w in path]
            except TypeError:
                raise ConfigError(
                    "tool.path", "waypoints [t, [d, h, w]] or [t, [d, h, w], [rd, rh, rw]]", got=path
                ) from None
            sizes = {len(w) for w in rows}
            if not rows or not sizes <= {2, 3} or len(sizes) != 1:
                raise ConfigError("tool.path", "waypoints all [t, position] or all [t, position, rotation]", got=path)
            self._path = Waypoints([w[:2] for w in rows], key="tool.path")
            if sizes == {3}:
                self._rot = Waypoints([(w[0], w[2]) for w in rows], key="tool.path rotation")
        else:
            self.move_to(position, orientation=orientation)

    def move_to(self, position, *, orientation=None) -> None:
        """Set the pose: a position ``(3,)`` / ``(B, 3)`` m or a callable ``t -> (3,)``, and a rotation vector.

        A device loop calls this before each step; the tool's velocity is then zero (give it a
        callable or a path for a moving contact's friction and grasp release velocity). A tensor
        is read at every step: update it in place (``copy_``) to move a tool inside a compiled
        step without recompiling it.
        """
        self._path = self._rot = None
        if callable(position):
            self._fn = position
        elif torch.is_tensor(position) and position.shape[-1:] == (3,) and position.dim() <= 2:
            self._fn = _constant(position)
        else:
            self._fn = None
            self._path = Waypoints([(0.0, as_vec3(position, "tool.position"))], key="tool.position")
        self._rot_fn = None
        if callable(orientation):
            self._rot_fn = orientation
        elif torch.is_tensor(orientation) and orientation.shape[-1:] == (3,) and orientation.dim() <= 2:
            self._rot_fn = _constant(orientation)
        elif orientation is not None:
            self._rot = Waypoints([(0.0, as_vec3(orientation, "tool.orientation"))], key="tool.orientation")

    def position(self, t):
        """Position at time ``t``: a tuple for a float ``t``, a tensor ``(3,)`` / ``(B, 3)`` for a 0-d tensor."""
        if self._fn is not None:
            p = self._fn(t)
            return p if torch.is_tensor(p) or not torch.is_tensor(t) else constant(p, t)
        return self._path.at(t)

    def rotation(self, t):
        """Rotation vector (rad) at time ``t`` as :meth:`position` gives positions, or None (identity)."""
        if self._rot_fn is not None:
            r = self._rot_fn(t)
            return r if torch.is_tensor(r) or not torch.is_tensor(t) else constant(r, t)
        return None if self._rot is None else self._rot.at(t)

    @staticmethod
    def _rate(fn, t, dt):
        a, b = fn(t - dt), fn(t + dt)
        if torch.is_tensor(a) or torch.is_tensor(b):
            return (torch.as_tensor(b) - torch.as_tensor(a)) / (2 * dt)
        return tuple((q - p) / (2 * dt) for p, q in zip(a, b))

    def velocity(self, t, *, dt: float = 1e-6):
        """Velocity ``(3,)`` m/s of the tool's origin at ``t``.

        The path segment entered at ``t``; a central difference of step ``dt`` for a callable.
        """
        if self._fn is not None:
            return self._rate(self._fn, t, dt)
        return self._path.rate(t)

    def angular_velocity(self, t, *, dt: float = 1e-6):
        """Angular velocity ``(3,)`` rad/s: the rate of the rotation vector (exact about a fixed axis)."""
        if self._rot_fn is not None:
            return self._rate(self._rot_fn, t, dt)
        return None if self._rot is None else self._rot.rate(t)

    def frame(self, t, like: torch.Tensor):
        """``(c, R)``: the position ``(B|1, 3, 1, ...)`` against fields like ``like``, and ``R`` ``(B|1, 3, 3)`` or None."""
        r = self.rotation(t)
        R = None if r is None else _rotation_matrix(constant(r, like).reshape(-1, 3))
        return _field(self.position(t), like), R

    def sdf(self, x: torch.Tensor, t) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance ``(B, 1, ...)`` and outward normal ``(B, 3, ...)`` of nodes ``x`` at time ``t``.

        Args:
            x: node positions ``(B, 3, ...)`` (m).
            t: time (s), a float or a 0-d tensor.
        """
        c, R = self.frame(t, x)
        if R is None:
            return self.shape.sdf(x - c)
        d, n = self.shape.sdf(_rotate(R, x - c, transpose=True))
        return d, _rotate(R, n)

    def point_velocity(self, x: torch.Tensor, t) -> torch.Tensor:
        """Velocity ``(B|1, 3, ...)`` of the tool's material point at positions ``x`` ``(B, 3, ...)``: ``v + w x (x - c)``."""
        v = _field(self.velocity(t), x)
        w = self.angular_velocity(t)
        if w is None:
            return v
        c = _field(self.position(t), x)
        return v + torch.cross(_field(w, x).expand_as(x), x - c, dim=1)


def _constant(value: torch.Tensor):
    """A callable ``t -> value`` (a pose per batch entry, set from Python)."""

    def fn(t):
        return value

    return fn
