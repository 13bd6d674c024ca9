"""Cutting with a blade: every spring whose segment crosses the blade's surface is removed.

A :class:`Blade` is a rectangle (Punak's blade): the points ``o + a u + b v`` for ``a, b`` in
``[0, 1]``, with edges ``u`` and ``v`` at right angles. A spring from ``p`` to ``q`` crosses it when
its ends lie on opposite sides of the blade's plane (a node exactly on the plane counts as the
side the normal ``u x v`` points away from, so a plane through a layer of nodes cuts one set of
springs, never two) and the point where the segment meets the plane lies within the rectangle.

Removing a spring sets its stiffness (and damping) to zero in the model: the spring operator
already skips zero-stiffness springs, so the cut body steps like any other.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((2, 1, 1), spacing=1.0, topology=6)        # one spring along D
    >>> blade = Blade((0.5, -1.0, -1.0), (0.0, 2.0, 0.0), (0.0, 0.0, 2.0))
    >>> crossing(grid, grid.rest_positions(torch.float64), blade)[0, 0].flatten().tolist()   # along D, stored at node 0
    [True, False]
"""
from __future__ import annotations

import math

import torch

from ..errors import ConfigError
from ..sim.forces import as_vec3
from ..sim.model import Model
from .masks import remove

__all__ = ["Blade", "crossing", "cut", "sides"]


class Blade:
    """A rectangular blade ``o + a u + b v``, ``a, b`` in ``[0, 1]``.

    Args:
        origin: a corner ``(3,)`` m.
        u: one edge ``(3,)`` m.
        v: the other edge ``(3,)`` m, at right angles to ``u``.

    Examples:
        >>> Blade((0, 0, 0), (1, 0, 0), (0, 2, 0)).normal
        (0.0, 0.0, 1.0)
    """

    def __init__(self, origin, u, v):
        self.origin, self.u, self.v = as_vec3(origin, "blade.origin"), as_vec3(u, "blade.u"), as_vec3(v, "blade.v")
        uu, vv = sum(c * c for c in self.u), sum(c * c for c in self.v)
        if uu == 0 or vv == 0:
            raise ConfigError("blade", "two non-zero edges u and v", (self.u, self.v))
        if abs(sum(a * b for a, b in zip(self.u, self.v))) > 1e-9 * math.sqrt(uu * vv):
            raise ConfigError("blade", "edges u and v at right angles (a rectangle)", (self.u, self.v))
        u, v = self.u, self.v
        n = (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])
        s = math.sqrt(sum(c * c for c in n))
        self.normal = tuple(c / s for c in n)

    def _vec(self, value, like):
        return like.new_tensor(value).view(1, 3, *[1] * (like.dim() - 2))

    def height(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance ``(B, 1, ...)`` of points ``x`` ``(B, 3, ...)`` from the blade's plane (along the normal)."""
        return ((x - self._vec(self.origin, x)) * self._vec(self.normal, x)).sum(1, keepdim=True)

    def within(self, r: torch.Tensor) -> torch.Tensor:
        """Bool ``(B, 1, ...)``: points ``r`` on the plane lie within the rectangle."""
        d = r - self._vec(self.origin, r)
        a = (d * self._vec(self.u, r)).sum(1, keepdim=True) / sum(c * c for c in self.u)
        b = (d * self._vec(self.v, r)).sum(1, keepdim=True) / sum(c * c for c in self.v)
        return (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)


def crossing(grid, x: torch.Tensor, blade: Blade) -> torch.Tensor:
    """Bool ``(B, S, D, H, W)``: the spring stored at each node along each half-direction crosses the blade.

    Only springs the grid has (both ends inside the box and the node mask) are reported.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        x: node positions ``(B, 3, D, H, W)`` (rest or deformed: the cut follows the tissue).
        blade: the :class:`Blade`.
    """
    h = blade.height(x)
    side = h > 0
    out = torch.zeros((x.shape[0], grid.S) + grid.shape, dtype=torch.bool, device=x.device)
    exists = grid.spring_mask(x.device)
    for s, (src, dst) in enumerate(grid.stencil):
        p, q = x[(..., *src)], x[(..., *dst)]
        hp, hq = h[(..., *src)], h[(..., *dst)]
        opposite = side[(..., *src)] != side[(..., *dst)]
        t = (hp / (hp - hq).where(hp != hq, torch.ones_like(hp))).clamp(0, 1)
        hit = opposite & blade.within(p + t * (q - p))
        out[(slice(None), s, *src)] = hit[:, 0] & exists[(s, *src)]
    return out


def sides(x: torch.Tensor, blade: Blade) -> torch.Tensor:
    """Int8 ``(B, 1, D, H, W)``: +1 on the normal's side of the blade's plane, -1 on the other (Punak's tags)."""
    return (blade.height(x) > 0).to(torch.int8) * 2 - 1


def cut(model: Model, x: torch.Tensor, blade: Blade) -> int:
    """Remove the springs that cross ``blade`` from ``model`` (in place); returns how many.

    Springs stored per direction (``(Bp, S, 1, 1, 1)``) become a full per-spring field first.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` (its ``stiffness`` and ``damping`` change).
        x: node positions ``(B, 3, D, H, W)``; a batch of positions gives one cut per batch entry.
        blade: the :class:`Blade`.
    """
    return remove(model, crossing(model.grid, x, blade))
