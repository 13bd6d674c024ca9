"""Cutting ChainMail: links crossed by a blade stop constraining their two elements (Knoche's unlinking).

ChainMail has no springs to remove; its links are the face-neighbour pairs that bound each
other's motion. A cut keeps every element and removes links: a link mask, bool ``(3, D, H, W)``
(entry ``[a, i, j, k]`` for the link from ``(i, j, k)`` to its neighbour along ``+a``, the layout
of per-link limits), which every ChainMail solver takes (``links=``, see
:mod:`torchdeform.chainmail`). An unlinked pair imposes no min/max/shear limit on each other, so
elements on the far side of a full cut never move, and across a partial cut motion follows the
links that remain.

Which links a blade cuts is decided by :func:`torchdeform.topology.cut.crossing` itself, on a
6-neighbour grid, whose springs are exactly the ChainMail links (half-direction ``s`` is axis
``s``): the link's two elements lie on opposite sides of a blade patch's plane (an element
exactly on the plane counts as the side the normal points away from) and the point where the
segment meets the plane lies within the patch. So rectangles, triangles and swept blades cut
ChainMail links and springs alike. The test runs on the given positions, rest or deformed, so
the cut follows the tissue. This module imports :mod:`torchdeform.chainmail`, never
the other way round.

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.topology import Blade, unlink
    >>> g = td.Grid((6, 6, 6), spacing=1.0)
    >>> cm = td.ChainMail(g, td.Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2), method="enhanced")
    >>> blade = Blade((2.5, -1.0, -1.0), (0.0, 7.0, 0.0), (0.0, 0.0, 7.0))   # between layers 2 and 3
    >>> links = unlink(cm, None, blade)
    >>> int((~links[0]).sum() - (~td.chainmail.link_mask(g)[0]).sum())     # 6 x 6 links along d cut
    36
    >>> r = cm.move([(0, 3, 3)], (-4.0, 0.0, 0.0))      # drag the bottom away: the top stays
    >>> float(cm.displacement()[0, :, 3:].abs().max()), r.moved > 1
    (0.0, True)
"""

from __future__ import annotations

import functools

import torch

from ..chainmail import ChainMail, link_mask
from ..errors import ConfigError
from ..sim.grid import Grid
from .cut import Blade, crossing

__all__ = ["link_crossing", "unlink"]


@functools.lru_cache(maxsize=8)
def _box6(shape: tuple) -> Grid:
    """A box grid of ``shape`` with the 6-neighbour stencil: its springs are the ChainMail links."""
    return Grid(shape, spacing=1.0, topology=6)


def _positions(x) -> torch.Tensor:
    x = torch.as_tensor(x)
    x = x.unsqueeze(0) if x.dim() == 4 else x
    if x.dim() != 5 or x.shape[1] != 3:
        raise ConfigError("positions", "element positions (B, 3, D, H, W) or (3, D, H, W)", got=tuple(x.shape))
    return x


def link_crossing(positions: torch.Tensor, blade: Blade, *, grid=None) -> torch.Tensor:
    """Bool ``(B, 3, D, H, W)``: the ChainMail link stored at each element along each axis crosses the blade.

    Entry ``[b, a, i, j, k]`` is the link from ``(i, j, k)`` to ``(i, j, k) + e_a``; links leaving
    the box are False, and so are links the grid lacks (node mask) when ``grid`` is given.

    Args:
        positions: element positions ``(B, 3, D, H, W)`` or ``(3, D, H, W)`` (rest or deformed).
        blade: the :class:`~torchdeform.topology.cut.Blade`.
        grid: optional :class:`~torchdeform.sim.grid.Grid` whose missing links are masked out.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.topology import Blade, link_crossing
        >>> g = td.Grid((3, 2, 2), spacing=1.0)
        >>> blade = Blade((0.5, -1.0, -1.0), (0.0, 3.0, 0.0), (0.0, 0.0, 3.0))   # between layers 0 and 1
        >>> c = link_crossing(g.rest_positions(dtype=torch.float64), blade, grid=g)
        >>> c.shape, int(c.sum()), c[0, 0, 0].all().item()
        (torch.Size([1, 3, 3, 2, 2]), 4, True)
    """
    if not isinstance(blade, Blade):
        raise ConfigError("blade", "a torchdeform.topology.Blade", got=type(blade).__name__)
    x = _positions(positions)
    shape = tuple(x.shape[2:])
    if grid is not None and tuple(grid.shape) != shape:
        raise ConfigError("positions", f"(B, 3, D, H, W) with grid {grid.shape}", got=tuple(x.shape))
    out = crossing(_box6(shape), x, blade)  # 6 neighbours: half-direction s is axis s
    if grid is not None:
        out &= link_mask(grid, device=x.device)
    return out


def unlink(target, positions, blade: Blade) -> torch.Tensor:
    """Cut the ChainMail links that cross ``blade``: they no longer constrain their two elements.

    Args:
        target: a :class:`~torchdeform.chainmail.ChainMail` (its links change in place), or a
            link mask, bool ``(3, D, H, W)`` or ``(B, 3, D, H, W)`` (left unchanged; pass the
            result as ``links=`` to :func:`~torchdeform.chainmail.tensor_chainmail` or
            :func:`~torchdeform.chainmail.relax`).
        positions: element positions ``(B, 3, D, H, W)`` or ``(3, D, H, W)`` to test the links at
            (rest or deformed); for a ChainMail ``None`` means its current positions (and ``B``
            must be 1). For a mask, ``B`` positions give ``B`` cuts.
        blade: the :class:`~torchdeform.topology.cut.Blade`.

    Returns:
        The new link mask: ``(3, D, H, W)`` for a ChainMail or a 4-D mask with one set of
        positions, else ``(B, 3, D, H, W)``; the old mask with every crossing link set to False.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.chainmail import link_mask, tensor_chainmail
        >>> from torchdeform.topology import Blade, unlink
        >>> g = td.Grid((6, 6, 6), spacing=1.0)
        >>> x = g.rest_positions(dtype=torch.float64)
        >>> half = Blade((2.5, -1.0, -1.0), (0.0, 2.5, 0.0), (0.0, 0.0, 7.0))   # h in 0..1 only
        >>> links = unlink(link_mask(g), x, half)
        >>> int((~links).sum() - (~link_mask(g)).sum())      # links 2 -> 3 along d with h in 0..1
        12
        >>> pick = torch.zeros(6, 6, 6, dtype=torch.bool); pick[0, 0, 0] = True
        >>> lim = td.Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
        >>> r = tensor_chainmail(x, g, lim, pick, (-4.0, 0.0, 0.0), links=links)
        >>> bool(r.moved[0, 5].any()), float(r.violation[0]) < 1e-12   # the far side follows round the cut
        (True, True)
    """
    if isinstance(target, ChainMail):
        x = target.positions() if positions is None else _positions(positions)
        if x.shape[0] != 1:
            raise ConfigError("positions", "one set of positions (1, 3, D, H, W) for a ChainMail", got=tuple(x.shape))
        cut_ = link_crossing(x, blade, grid=target.grid)[0].cpu()
        new = target.links & ~cut_
        target.set_links(new)
        return new
    if positions is None:
        raise ConfigError("positions", "element positions (B, 3, D, H, W) to cut a link mask at", got=None)
    try:
        mask = target.to(torch.bool) if torch.is_tensor(target) else torch.as_tensor(target, dtype=torch.bool)
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError("target", "a ChainMail or a bool (3, D, H, W) link mask", got=type(target).__name__) from None
    x = _positions(positions)
    if (
        mask.dim() not in (4, 5)
        or tuple(mask.shape[-4:]) != (3,) + tuple(x.shape[2:])
        or (mask.dim() == 5 and mask.shape[0] not in (1, x.shape[0]))
    ):
        raise ConfigError(
            "target",
            f"a bool (3, D, H, W) or (B, 3, D, H, W) link mask matching positions {tuple(x.shape)}",
            got=tuple(mask.shape),
        )
    new = mask.to(x.device) & ~link_crossing(x, blade)
    return new[0] if mask.dim() == 4 and x.shape[0] == 1 else new
