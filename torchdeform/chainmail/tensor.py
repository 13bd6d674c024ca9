"""Tensor ChainMail: sponsor-front Jacobi sweeps over the whole grid with torch ops.

Batched over bodies, on any device. An element is bounded only by neighbours that have moved;
about one sweep per lattice hop of propagation (Bellman-Ford on each coordinate's difference
constraints).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from .limits import Limits, _as_links, _axis_slices, _exists, limit_violation, neighbour_boxes

__all__ = ["tensor_chainmail", "SweepResult"]


# ------------------------------------------------------------------ tensor ChainMail
@dataclass
class SweepResult:
    """What :func:`tensor_chainmail` did.

    Attributes:
        positions: ``(B, 3, D, H, W)``.
        moved: bool ``(B, D, H, W)`` elements that moved (picked included).
        sweeps: sweeps that changed something (the last, unchanged sweep not counted).
        depth: ``(B,)`` propagation depth: the largest number of lattice hops (6-neighbour path
            length) from a picked element to a moved element.
        violation: ``(B,)`` largest limit excess after the sweeps (:func:`limit_violation`);
            above 0 only when a fixed element blocked the move or bounds conflicted.
    """
    positions: torch.Tensor
    moved: torch.Tensor
    sweeps: int
    depth: torch.Tensor
    violation: torch.Tensor

    def displacement(self, grid: Grid) -> torch.Tensor:
        """Offsets ``x - X``, ``(B, 3, D, H, W)``."""
        return self.positions - grid.rest_positions(self.positions.dtype, self.positions.device)


def _dilate(m: torch.Tensor, grid: Grid, links=None) -> torch.Tensor:
    """Grow ``m`` ``(B, D, H, W)`` by one face-neighbour hop (through existing ``links`` ``(1|B, 3, D, H, W)``)."""
    out = m.clone()
    for a in range(3):
        if grid.shape[a] < 2:
            continue
        first, second = _axis_slices(grid, a)
        if links is None:
            out[(..., *second)] |= m[(..., *first)]
            out[(..., *first)] |= m[(..., *second)]
        else:
            lk = links[(slice(None), a, *first)]
            out[(..., *second)] |= m[(..., *first)] & lk
            out[(..., *first)] |= m[(..., *second)] & lk
    return out


def _hops(picked: torch.Tensor, grid: Grid, moved: torch.Tensor, links=None) -> torch.Tensor:
    """Largest 6-neighbour hop distance (through the body) from ``picked`` to an element of ``moved``.

    Returns ``(B,)``; ``picked`` and ``moved`` are both ``(B, D, H, W)`` bool.
    """
    nodes = _exists(grid, picked.device)
    reach = picked.clone()
    depth = torch.zeros(picked.shape[0], dtype=torch.long, device=picked.device)
    hop = 0
    while bool((moved & ~reach).any()):
        grown = _dilate(reach, grid, links) & nodes
        if bool((grown == reach).all()):
            break
        hop += 1
        new = (grown & ~reach & moved).flatten(1).any(1)
        depth = torch.where(new, torch.full_like(depth, hop), depth)
        reach = grown
    return depth


def tensor_chainmail(positions: torch.Tensor, grid: Grid, limits: Limits, picked, displacement,
                     fixed=None, max_sweeps: int | None = None, links=None) -> SweepResult:
    """Batched ChainMail by sponsor-front Jacobi sweeps (torch ops only, any device).

    The picked elements move rigidly by their body's displacement. Each sweep, every free
    element that has a moved face neighbour is clamped against the bounds those neighbours set
    (all at once, from the previous sweep's positions); elements that
    change join the moved set. Elements bounded by nothing that moved are never touched, so the
    moved set advances as a front, about one lattice hop per sweep; sweeps stop when nothing
    changes.

    Each coordinate is only pulled up or pushed down (the sign of the body's displacement), so
    an element takes ``max(u, lo)`` or ``min(u, hi)`` of its moved neighbours' bounds: a
    Bellman-Ford iteration, which ends at the same positions as the sequential versions (see the
    module docstring); a sweep count above the depth means later sweeps raised bounds again.
    A fixed element that would have to move is not moved and the remaining excess is reported
    in ``violation`` (no scaling, unlike :meth:`ChainMail.move`).

    Args:
        positions: ``(B, 3, D, H, W)`` start positions satisfying the limits.
        grid: the grid (node mask respected).
        limits: the :class:`Limits`.
        picked: bool ``(D, H, W)`` or ``(B, D, H, W)``: the elements moved rigidly.
        displacement: ``(3,)`` or ``(B, 3)`` metres.
        fixed: optional bool ``(D, H, W)`` or ``(B, D, H, W)``.
        max_sweeps: default ``2 (D + H + W)`` (enough for any propagation), or the number of
            elements when ``links`` is given (a path around a cut may be that long); sweeps stop
            as soon as nothing changes.
        links: optional bool link mask ``(3, D, H, W)`` or ``(B, 3, D, H, W)``: a link that is
            False imposes no limit, so nothing propagates through it (unlinked by a cut,
            :func:`torchdeform.topology.unlink`); default every link exists.

    Returns:
        :class:`SweepResult` (positions, moved, sweeps, depth, violation).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> g = td.Grid((16, 16, 16), spacing=1.0)
        >>> lim = td.Limits.from_material(g, 0.8, 1.2, 0.2)
        >>> pick = torch.zeros(16, 16, 16, dtype=torch.bool)
        >>> pick[15, 8, 8] = True                                   # the top centre
        >>> r = td.tensor_chainmail(g.rest_positions(torch.float64).repeat(2, 1, 1, 1, 1), g, lim, pick,
        ...                         torch.tensor([[2.0, 0, 0], [-1.0, 0.5, 0]], dtype=torch.float64))
        >>> r.sweeps, r.depth.tolist(), r.moved.flatten(1).sum(1).tolist(), bool((r.violation < 1e-12).all())
        (10, [10, 5], [853, 146], True)
        >>> cm = td.ChainMail(g, lim)                               # the sequential version agrees
        >>> _ = cm.move([(15, 8, 8)], (2.0, 0.0, 0.0))
        >>> float((cm.positions() - r.positions[:1]).abs().max()) < 1e-12
        True
    """
    x = positions
    if x.dim() != 5 or x.shape[1] != 3 or tuple(x.shape[2:]) != grid.shape:
        raise ConfigError("positions", f"(B, 3, D, H, W) with grid {grid.shape}", tuple(x.shape))
    dev, dt, B = x.device, x.dtype, x.shape[0]

    def mask(value, key):
        m = torch.as_tensor(value, dtype=torch.bool, device=dev) if not torch.is_tensor(value) \
            else value.to(device=dev, dtype=torch.bool)
        if tuple(m.shape) == grid.shape:
            m = m.unsqueeze(0)
        if m.dim() != 4 or tuple(m.shape[1:]) != grid.shape or m.shape[0] not in (1, B):
            raise ConfigError(key, f"a bool (D, H, W) or (B, D, H, W) mask with grid {grid.shape}", tuple(m.shape))
        return m.expand(B, *grid.shape).unsqueeze(1)            # (B, 1, D, H, W)

    nodes = _exists(grid, dev).view(1, 1, *grid.shape)
    pick = mask(picked, "picked") & nodes
    if not bool(pick.flatten(1).any(1).all()):
        raise ConfigError("picked", "at least one element inside the body for every batch entry", "none")
    fix = mask(fixed, "fixed") & nodes if fixed is not None else torch.zeros_like(pick)
    if bool((pick & fix).any()):
        raise ConfigError("picked", "free elements (a picked element is fixed and cannot be moved)", "fixed element")
    d = torch.as_tensor(displacement, dtype=dt, device=dev)
    if d.dim() == 1:
        d = d.unsqueeze(0)
    if tuple(d.shape) not in ((1, 3), (B, 3)) or not bool(torch.isfinite(d).all()):
        raise ConfigError("displacement", "(3,) or (B, 3) finite numbers in metres", tuple(d.shape))
    lk = _as_links(links, grid, dev, B)
    bounds = limits.offset_bounds(dt, dev)
    X = grid.rest_positions(dt, dev)
    u = torch.where(pick, x - X + d.view(-1, 3, 1, 1, 1), x - X)
    moved = pick.clone()
    free = nodes & ~pick & ~fix
    sign = torch.sign(d).view(-1, 3, 1, 1, 1)
    pull, push = sign > 0, sign < 0
    if max_sweeps is not None:
        limit = max_sweeps
    else:                               # a path around a cut may be as long as the body has elements
        limit = 2 * sum(grid.shape) if lk is None else max(2 * sum(grid.shape), grid.num_nodes)
    sweeps = 0
    for _ in range(limit):
        lo, hi = neighbour_boxes(u, grid, bounds, moved, lk)
        step = torch.where(pull, torch.maximum(u, lo), torch.where(push, torch.minimum(u, hi), u))
        new = torch.where(free, step, u)
        changed = (new != u).any(1, keepdim=True)
        if not bool(changed.any()):
            break
        sweeps += 1
        moved |= changed
        u = new
    xn = X + u
    moved4 = moved[:, 0]
    depth = _hops(pick[:, 0], grid, moved4, lk)
    return SweepResult(xn, moved4, sweeps, depth, limit_violation(xn, grid, limits, links=lk))
