"""Limits of ChainMail links, the independent limit checker and the neighbour boxes.

For the link from element ``i`` to ``j = i + e_a`` along axis ``a`` (channel ``a`` moves along
axis ``a`` of ``(D, H, W)``)::

    min_a <= x_j[a] - x_i[a] <= max_a,      |x_j[b] - x_i[b]| <= shear_a   (b != a)

per axis (homogeneous, Gibson) or per link (heterogeneous tissue, Enhanced ChainMail). The links
are the six face neighbours: the 6-neighbour stencil of :mod:`torchdeform.sim.springs`.

Link masks. Every function that applies the limits takes an optional ``links``: bool
``(3, D, H, W)`` (or ``(B, 3, D, H, W)`` per body), entry ``[a, i, j, k]`` for the link from node
``(i, j, k)`` to its neighbour along ``+a`` (the layout of per-link limits and of the 6-neighbour
per-spring tensors ``(S, D, H, W)``); a link whose entry is False does not exist and imposes no
limit (Knoche's unlinked elements after a cut, :func:`torchdeform.topology.unlink`). ``None``
(the default) means every link exists and costs nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import ConfigError, TorchdeformError
from ..sim.grid import Grid

__all__ = [
    "Limits",
    "BlockedMoveError",
    "tissue_limits",
    "limit_violation",
    "neighbour_boxes",
    "link_mask",
    "DIRECTIONS",
    "GIBSON_SUCCESSORS",
    "METHODS",
    "RELAX_MODES",
]

#: Directions of the six neighbour lists: (axis, sign) for +d, -d, +h, -h, +w, -w.
DIRECTIONS = ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1))
#: Gibson's successor lists: an element reached through list k feeds these lists.
GIBSON_SUCCESSORS = ((0, 2, 3, 4, 5), (1, 2, 3, 4, 5), (2, 4, 5), (3, 4, 5), (4,), (5,))
METHODS = ("gibson", "enhanced")
RELAX_MODES = ("centroid", "goal")
_OUTSIDE, _FREE, _FIXED = 0, 1, 2


class BlockedMoveError(TorchdeformError):
    """A move cannot be carried out.

    It would have to move a fixed element (or, in Enhanced ChainMail, two neighbours demand
    incompatible positions). Raised with ``on_blocked="error"``.
    """


# ------------------------------------------------------------------------- limits
def _limit_tensor(value, key, shape) -> torch.Tensor:
    try:
        t = (
            torch.as_tensor(value, dtype=torch.float64).detach().cpu()
            if not torch.is_tensor(value)
            else value.detach().to("cpu", torch.float64)
        )
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(key, "a number, three numbers (d, h, w) or a (3, D, H, W) array", got=value) from None
    if t.dim() == 0:
        t = t.expand(3).clone()
    if tuple(t.shape) not in ((3,), (3,) + tuple(shape)):
        raise ConfigError(
            key,
            f"a number, three numbers (d, h, w) or a (3, D, H, W) = {(3,) + tuple(shape)} array",
            got=tuple(t.shape),
        )
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(key, "finite values", got="non-finite values", show_got=True)
    return t


@dataclass(frozen=True, eq=False)
class Limits:
    """ChainMail limits of a grid's links, in metres.

    Each of ``min``, ``max``, ``shear`` is a number, three numbers ``(d, h, w)`` (one per axis:
    homogeneous, as Gibson) or a ``(3, D, H, W)`` array (per link: entry ``[a, i, j, k]`` is the
    link from node ``(i, j, k)`` to its neighbour along ``+a``; entries of links that leave the
    grid are ignored). ``min`` and ``max`` bound the distance along the link's axis, ``shear``
    the offset across it.

    Args:
        grid: the grid the limits belong to.
        min: smallest distance along a link's axis (m), ``0 <= min <= max``.
        max: largest distance along a link's axis (m).
        shear: largest offset across a link's axis (m), ``>= 0``.

    Examples:
        >>> import torchdeform as td
        >>> g = td.Grid((4, 4, 4), spacing=0.01)
        >>> lim = td.Limits(g, min=0.008, max=0.012, shear=0.002)
        >>> lim.uniform, [round(float(v), 6) for v in lim.offset_bounds()[1]]    # max - spacing
        (True, [0.002, 0.002, 0.002])
        >>> td.Limits(g, min=0.008, max=0.012, shear=[0.001, 0.002, 0.003]).shear.tolist()
        [0.001, 0.002, 0.003]
    """

    grid: Grid
    min: torch.Tensor
    max: torch.Tensor
    shear: torch.Tensor

    def __post_init__(self):
        shape = self.grid.shape
        lo = _limit_tensor(self.min, "limits.min", shape)
        hi = _limit_tensor(self.max, "limits.max", shape)
        sh = _limit_tensor(self.shear, "limits.shear", shape)
        if bool((lo < 0).any()):
            raise ConfigError("limits.min", "distances >= 0 (no element may pass its neighbour)", got=float(lo.min()))
        if bool((sh < 0).any()):
            raise ConfigError("limits.shear", "shear limits >= 0", got=float(sh.min()))
        per = lambda t: t.view(3, 1, 1, 1) if t.dim() == 1 else t
        bad = per(lo) > per(hi)
        if bool(bad.any()):
            where = [int(v) for v in bad.nonzero()[0]]
            node = f" at node {tuple(where[1:])}" if lo.dim() > 1 or hi.dim() > 1 else ""
            raise ConfigError(
                "limits",
                f"min <= max on every link; axis {'dhw'[where[0]]}{node} has "
                f"min {float(per(lo).expand_as(bad)[tuple(where)]):.4g} > "
                f"max {float(per(hi).expand_as(bad)[tuple(where)]):.4g}",
                show_got=False,
            )
        for name, t in (("min", lo), ("max", hi), ("shear", sh)):
            object.__setattr__(self, name, t)

    @property
    def uniform(self) -> bool:
        """True when every limit is one number per axis (Gibson's homogeneous case)."""
        return all(t.dim() == 1 for t in (self.min, self.max, self.shear))

    def per_link(self) -> tuple:
        """``(min, max, shear)`` each as ``(3, D, H, W)`` float64."""
        shape = (3,) + self.grid.shape
        return tuple(t.view(3, 1, 1, 1).expand(shape) if t.dim() == 1 else t for t in (self.min, self.max, self.shear))

    def offset_bounds(self, *, dtype=torch.float64, device=None) -> tuple:
        """Limits on offset differences ``u_j - u_i`` (``u = x - X``), as ``(lo, hi, shear)``.

        ``lo_a = min_a - spacing_a``, ``hi_a = max_a - spacing_a``. Each ``(3,)`` when
        :attr:`uniform` allows it, else ``(3, D, H, W)``.
        """
        h = torch.tensor(self.grid.spacing, dtype=torch.float64)
        out = []
        for t, shift in ((self.min, True), (self.max, True), (self.shear, False)):
            s = h.view(3, *[1] * (t.dim() - 1)) if shift else 0.0
            out.append((t - s).to(dtype=dtype, device=device))
        return tuple(out)

    @classmethod
    def from_material(cls, grid: Grid, *, compression=0.9, stretch=1.1, shear=0.1) -> Limits:
        """Limits as ratios of the rest spacing.

        ``min_a = compression * h_a``, ``max_a = stretch * h_a``, ``shear_a = shear * h_a``.

        Each ratio is a number, three numbers ``(d, h, w)`` (anisotropic, e.g. muscle fibres) or
        a ``(D, H, W)`` array per element; a link then gets the mean of its two elements' values
        (Schill's rule for heterogeneous tissue).

        Example:
            >>> from torchdeform.chainmail import Limits
            >>> from torchdeform.sim.grid import Grid
            >>> g = Grid((8, 8, 8), spacing=0.001)
            >>> lim = Limits.from_material(g, compression=0.8, stretch=1.25, shear=0.15)
            >>> [round(float(v), 6) for v in lim.max]
            [0.00125, 0.00125, 0.00125]
        """
        h = torch.tensor(grid.spacing, dtype=torch.float64)
        shape = grid.shape

        def ratio(value, key):
            try:
                t = (
                    value.detach().to("cpu", torch.float64)
                    if torch.is_tensor(value)
                    else torch.as_tensor(value, dtype=torch.float64)
                )
            except (TypeError, ValueError, RuntimeError):
                raise ConfigError(key, "a number, three numbers (d, h, w) or a (D, H, W) array", got=value) from None
            if not bool(torch.isfinite(t).all()):
                raise ConfigError(key, "finite values", got="non-finite values", show_got=True)
            if t.dim() == 0:
                return t * h
            if tuple(t.shape) == (3,):
                return t * h
            if tuple(t.shape) == shape:  # per element -> per link
                links = t.expand(3, *shape).clone()
                for a in range(3):
                    n = shape[a]
                    if n > 1:
                        lo = [slice(None)] * 3
                        hi = [slice(None)] * 3
                        lo[a], hi[a] = slice(0, n - 1), slice(1, n)
                        links[(a, *lo)] = 0.5 * (t[tuple(lo)] + t[tuple(hi)])
                return links * h.view(3, 1, 1, 1)
            raise ConfigError(
                key, f"a number, three numbers (d, h, w) or a (D, H, W) = {shape} array", got=tuple(t.shape)
            )

        if bool((torch.as_tensor(shear, dtype=torch.float64) < 0).any()):
            raise ConfigError("shear", "a ratio >= 0", got=shear if not torch.is_tensor(shear) else float(shear.min()))
        return cls(grid, ratio(compression, "compression"), ratio(stretch, "stretch"), ratio(shear, "shear"))


def tissue_limits(
    grid: Grid, tissue, *, labels=None, reference_stress: float = 300.0, slack_range=(0.005, 0.5)
) -> Limits:
    """Limits from the fuzzy tissue library (:mod:`torchdeform.fuzzy.presets`).

    Each tissue's Young's modulus ``E`` (the ``tissue_si`` Mamdani system evaluated at its
    consistency) gives a strain slack ``eps = reference_stress / E`` (the strain a probe
    stress causes), clipped to ``slack_range``; the link ratios are then
    ``compression = 1 - eps``, ``stretch = 1 + eps``, ``shear = eps``: softer tissue, wider limits.
    With ``reference_stress = 300`` Pa: brain 0.20, liver 0.08, muscle 0.027, cirrhotic liver 0.007.

    Args:
        grid: the grid.
        tissue: a tissue name (``"liver"``, see ``torchdeform.fuzzy.presets.tissues()``), a
            consistency value on the system's 0..10 scale, or a list of them indexed by ``labels``.
        labels: optional integer ``(D, H, W)`` array choosing an entry of ``tissue`` per element
            (heterogeneous tissue: per-link limits, use ``method="enhanced"``).
        reference_stress: Pa.
        slack_range: ``(lo, hi)`` clip of ``eps``.

    Returns:
        :class:`Limits`.

    Example:
        >>> from torchdeform.chainmail import tissue_limits
        >>> from torchdeform.sim.grid import Grid
        >>> lim = tissue_limits(Grid((8, 8, 8), spacing=0.001), "liver")
        >>> lim.uniform
        True
    """
    from ..fuzzy.presets import load_preset, tissue_parameters

    if not (isinstance(reference_stress, (int, float)) and reference_stress > 0):
        raise ConfigError("reference_stress", "a positive stress in Pa", got=reference_stress)
    items = list(tissue) if isinstance(tissue, (list, tuple)) else [tissue]
    if not items:
        raise ConfigError("tissue", "at least one tissue name or consistency value", got=tissue)
    eps = []
    system = None
    for item in items:
        if isinstance(item, str):
            E = tissue_parameters(item)["youngs_modulus"]
        elif isinstance(item, (int, float)) and not isinstance(item, bool) and 0 <= item <= 10:
            system = system or load_preset("tissue_si")
            E = float(system.evaluate(consistency=float(item))["youngs_modulus"])
        else:
            raise ConfigError("tissue", "a tissue name or a consistency value in [0, 10]", got=item)
        eps.append(min(max(reference_stress / E, slack_range[0]), slack_range[1]))
    if labels is None:
        if len(eps) != 1:
            raise ConfigError("labels", "a (D, H, W) integer array to choose among several tissues", got=None)
        e = torch.tensor(eps[0], dtype=torch.float64)
    else:
        lab = torch.as_tensor(labels)
        if tuple(lab.shape) != grid.shape or lab.is_floating_point() or bool(((lab < 0) | (lab >= len(eps))).any()):
            raise ConfigError(
                "labels",
                f"integers in [0, {len(eps) - 1}] of shape {grid.shape}",
                got=tuple(lab.shape) if tuple(lab.shape) != grid.shape else "values out of range",
            )
        e = torch.tensor(eps, dtype=torch.float64)[lab.long()]
    return Limits.from_material(grid, compression=1 - e, stretch=1 + e, shear=e)


# ---------------------------------------------------------------- the checker
def _exists(grid: Grid, device) -> torch.Tensor:
    return grid.nodes().to(device)


def link_mask(grid: Grid, *, device=None) -> torch.Tensor:
    """Bool ``(3, D, H, W)``: the links the grid has (both ends inside the box and the node mask).

    Entry ``[a, i, j, k]`` is the link from node ``(i, j, k)`` to its neighbour along ``+a``; the
    full mask of a ``links`` argument before any link is cut.

    Example:
        >>> from torchdeform.chainmail import link_mask
        >>> from torchdeform.sim.grid import Grid
        >>> m = link_mask(Grid((2, 3, 4), spacing=1.0))
        >>> m.shape, int(m.sum())                     # 1*3*4 + 2*2*4 + 2*3*3 links
        (torch.Size([3, 2, 3, 4]), 46)
    """
    return _grid6(grid).spring_mask(device=device)


def _as_links(links, grid: Grid, device, batch: int | None = None, key: str = "links"):
    """``None``, or the link mask as bool ``(1|B, 3, D, H, W)`` on ``device`` (validated)."""
    if links is None:
        return None
    try:
        m = (
            links.to(device=device, dtype=torch.bool)
            if torch.is_tensor(links)
            else torch.as_tensor(links, dtype=torch.bool, device=device)
        )
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(key, "a bool (3, D, H, W) or (B, 3, D, H, W) link mask", got=type(links).__name__) from None
    if m.dim() == 4:
        m = m.unsqueeze(0)
    if m.dim() != 5 or tuple(m.shape[1:]) != (3,) + grid.shape or (batch is not None and m.shape[0] not in (1, batch)):
        raise ConfigError(
            key, f"a bool (3, D, H, W) or (B, 3, D, H, W) link mask with grid {grid.shape}", got=tuple(m.shape)
        )
    return m


def limit_violation(positions: torch.Tensor, grid: Grid, limits: Limits, *, per_link: bool = False, links=None):
    """Largest amount (m) by which any link exceeds its ChainMail limits.

    An independent, vectorised check written on absolute positions (not on the offsets the
    algorithms use).

    Args:
        positions: ``(B, 3, D, H, W)`` or ``(3, D, H, W)``.
        grid: the grid (its node mask decides which links exist).
        limits: the :class:`Limits`.
        per_link: also return the excess of every link, ``(B, 3, D, H, W)`` (axis ``a`` at the
            link's first endpoint; 0 where the link does not exist).
        links: optional bool link mask ``(3, D, H, W)`` or ``(B, 3, D, H, W)``; links that are
            False are not checked (see the module docstring).

    Returns:
        ``(B,)`` largest excess, 0 where every limit holds (and the field with ``per_link``).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> g = td.Grid((3, 3, 3), spacing=1.0)
        >>> lim = td.Limits(g, 0.9, 1.1, 0.1)
        >>> x = g.rest_positions(dtype=torch.float64)
        >>> float(td.limit_violation(x, g, lim)[0])
        0.0
        >>> x[0, 0, 2] += 0.5                            # lift the top layer: its links stretch to 1.5
        >>> worst, per_link = td.limit_violation(x, g, lim, per_link=True)
        >>> round(float(worst[0]), 6), per_link.shape
        (0.4, torch.Size([1, 3, 3, 3, 3]))
    """
    x = positions if positions.dim() == 5 else positions.unsqueeze(0)
    dev, dt = x.device, x.dtype
    mn, mx, sh = (t.to(device=dev, dtype=dt) for t in limits.per_link())
    nodes = _exists(grid, dev)
    lk = _as_links(links, grid, dev, x.shape[0])
    field_ = torch.zeros((x.shape[0], 3) + grid.shape, dtype=dt, device=dev)
    for a in range(3):
        n = grid.shape[a]
        if n < 2:
            continue
        first = [slice(None)] * 3
        second = [slice(None)] * 3
        first[a], second[a] = slice(0, n - 1), slice(1, n)
        first, second = tuple(first), tuple(second)
        diff = x[(..., *second)] - x[(..., *first)]  # (B, 3, region)
        along = diff[:, a]
        excess = torch.maximum(mn[a][first] - along, along - mx[a][first])
        for b in range(3):
            if b != a:
                excess = torch.maximum(excess, diff[:, b].abs() - sh[a][first])
        excess = excess.clamp_min(0) * (nodes[first] & nodes[second])
        if lk is not None:
            excess = excess * lk[(slice(None), a, *first)]
        field_[(slice(None), a, *first)] = excess
    worst = field_.flatten(1).amax(1)
    return (worst, field_) if per_link else worst


def _grid6(grid: Grid) -> Grid:
    if grid.topology == 6:
        return grid
    key = ("chainmail_grid6",)
    if key not in grid._cache:
        grid._cache[key] = Grid(
            grid.shape, spacing=grid.spacing, topology=6, node_mask=grid.node_mask, origin=grid.origin
        )
    return grid._cache[key]


# ---------------------------------------------------------------- neighbour boxes (tensor)
def _axis_slices(grid: Grid, a: int):
    """``(first, second)`` index tuples of the links along axis ``a``: the 6-neighbour stencil."""
    return _grid6(grid).stencil[a]


def _link_values(t: torch.Tensor, a: int, region) -> torch.Tensor:
    return t[a] if t.dim() == 1 else t[a][region]


def neighbour_boxes(u: torch.Tensor, grid: Grid, bounds: tuple, source: torch.Tensor, *, links=None):
    """The box each element's offset must lie in relative to its face neighbours in ``source``.

    Args:
        u: offsets ``(B, 3, D, H, W)``.
        grid: the grid.
        bounds: ``(lo, hi, shear)`` from :meth:`Limits.offset_bounds` (same dtype and device as ``u``).
        source: bool ``(B|1, 1, D, H, W)``: neighbours that constrain (moved, fixed, or all).
        links: optional link mask, ``None`` or bool ``(B|1, 3, D, H, W)`` (as from ``_as_links``):
            a neighbour constrains only through a link that exists.

    Returns:
        ``(lo, hi)``, each ``(B, 3, D, H, W)``: the intersection of the boxes, ``-inf``/``+inf``
        where no neighbour in ``source`` constrains.
    """
    L, Hh, S = bounds
    lo = torch.full_like(u, -math.inf)
    hi = torch.full_like(u, math.inf)
    for a in range(3):
        if grid.shape[a] < 2:
            continue
        first, second = _axis_slices(grid, a)
        la, ha, sa = (_link_values(t, a, first) for t in (L, Hh, S))
        linked = None if links is None else links[(slice(None), slice(a, a + 1), *first)]
        for elem, nbr, sgn in ((second, first, 1), (first, second, -1)):
            centre = u[(..., *nbr)]
            rel_lo = [-sa, -sa, -sa]
            rel_hi = [sa, sa, sa]
            rel_lo[a], rel_hi[a] = (la, ha) if sgn > 0 else (-ha, -la)
            blo = torch.stack([centre[:, c] + rel_lo[c] for c in range(3)], 1)
            bhi = torch.stack([centre[:, c] + rel_hi[c] for c in range(3)], 1)
            ok = source[(..., *nbr)]
            if linked is not None:
                ok = ok & linked
            blo = torch.where(ok, blo, -math.inf)
            bhi = torch.where(ok, bhi, math.inf)
            lo[(..., *elem)] = torch.maximum(lo[(..., *elem)], blo)
            hi[(..., *elem)] = torch.minimum(hi[(..., *elem)], bhi)
    return lo, hi
