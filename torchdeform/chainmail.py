"""ChainMail (Gibson 1997), Enhanced ChainMail (Schill 1998/2001), a batched tensor ChainMail
and elastic relaxation, on the face neighbours of a :class:`~torchdeform.grid.Grid`.

ChainMail is geometric: every link between two face neighbours may stretch, compress and shear
within limits; moving an element drags, pushes or shears its neighbours only when a limit is
exceeded, so only the elements that must move are touched. The result is plastic; elastic
relaxation afterwards smooths it.

Limits (:class:`Limits`). For the link from element ``i`` to ``j = i + e_a`` along axis ``a``
(channel ``a`` moves along axis ``a`` of ``(D, H, W)``)::

    min_a <= x_j[a] - x_i[a] <= max_a,      |x_j[b] - x_i[b]| <= shear_a   (b != a)

per axis (homogeneous, Gibson) or per link (heterogeneous tissue, Enhanced ChainMail).

=====================  ===========================================================================
:class:`ChainMail`     sequential, cost proportional to the elements that move:
  ``"gibson"``         six FIFO lists served in turn; an element is checked only against its
                       sponsor; the lists of a +/-d element feed d, h and w, those of a +/-h
                       element h and w, those of a +/-w element w only, so every element has one
                       sponsor path and is checked at most once per initiator. Needs per-axis
                       limits (one set for the whole body) and a box (no node mask).
  ``"enhanced"``       one priority queue per moving coordinate, largest violation first
                       (Schill); per-link limits for heterogeneous tissue; each element is
                       corrected at most once per coordinate.
:func:`tensor_chainmail`  sponsor-front Jacobi sweeps over the whole grid with torch ops, batched
                       over bodies, any device: an element is bounded only by neighbours that
                       have moved; about one sweep per lattice hop.
:func:`relax`          red-black projected relaxation of the offsets towards the centroid of the
                       neighbours (Knoche) or towards Gibson's goal positions, within the limits.
:func:`limit_violation`  the independent vectorised checker.
=====================  ===========================================================================

Results are offsets ``u = x - X`` (a displacement field ``(B, 3, D, H, W)`` for the volume
pipeline, :meth:`ChainMail.displacement`) or a :class:`~torchdeform.model.State` that the
mass-spring integrators continue from (:meth:`ChainMail.state`).

Why the variants agree, and where they differ. Every limit bounds the difference of one
coordinate between two neighbours, so each coordinate is a separate system of difference
constraints; in offsets all its bounds are >= 0 (the rest state satisfies the limits). When the
picked elements move by ``delta``, coordinate ``c`` only has to be pulled up (``delta_c > 0``)
or pushed down, and the least motion that satisfies every limit is
``u_i <- max(u_i, max_p (t_p - w(i, p)))`` (for a pull) with ``w`` the shortest-path bound from
``i`` to a picked element ``p``: a shortest-path problem with non-negative weights, pruned where
an element does not move (its neighbours then do not move either). Gibson's dimension-ordered
paths are shortest paths when the limits are homogeneous; largest-violation-first is a
label-setting (Dijkstra) order because a violation never grows along a propagation; the
sponsor-front sweeps are Bellman-Ford, which is why they need about one sweep per hop. So all
three give the same positions (tested to rounding against a plain Bellman-Ford reference),
They differ in cost
(the sequential order decides which elements are touched; Enhanced ChainMail's order has no
parallel equivalent, the sweeps touch the whole grid every time), in that Gibson needs
homogeneous limits, and when a move is blocked by a fixed element: :meth:`ChainMail.move`
scales the move down to what is possible, :func:`tensor_chainmail` leaves the fixed element and
reports the remaining excess.

Example:
    >>> import torchdeform as td
    >>> from torchdeform.chainmail import ChainMail, Limits
    >>> grid = td.Grid((20, 20, 20), spacing=0.001)
    >>> cm = ChainMail(grid, Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2))
    >>> r = cm.move([(19, 10, 10)], (0.003, 0.0, 0.0))      # pull the top centre up 3 mm
    >>> r.moved > 1, float(limit_violation(cm.positions(), grid, cm.limits)) < 1e-12
    (True, True)
    >>> u = cm.displacement()                                 # (1, 3, 20, 20, 20) metres
    >>> energies = cm.relax(steps=4)                          # smooth the straight-line artefacts
"""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import ConfigError, TorchdeformError
from .grid import Grid
from .springs import accumulate

#: Directions of the six neighbour lists: (axis, sign) for +d, -d, +h, -h, +w, -w.
DIRECTIONS = ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1))
#: Gibson's successor lists: an element reached through list k feeds these lists.
GIBSON_SUCCESSORS = ((0, 2, 3, 4, 5), (1, 2, 3, 4, 5), (2, 4, 5), (3, 4, 5), (4,), (5,))
METHODS = ("gibson", "enhanced")
RELAX_MODES = ("centroid", "goal")
_OUTSIDE, _FREE, _FIXED = 0, 1, 2


class BlockedMoveError(TorchdeformError):
    """A move cannot be carried out: it would have to move a fixed element (or, in Enhanced
    ChainMail, two neighbours demand incompatible positions). Raised with ``on_blocked="error"``."""


# ------------------------------------------------------------------------- limits
def _limit_tensor(value, key, shape) -> torch.Tensor:
    try:
        t = torch.as_tensor(value, dtype=torch.float64).detach().cpu() if not torch.is_tensor(value) \
            else value.detach().to("cpu", torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(key, "a number, three numbers (d, h, w) or a (3, D, H, W) array", value) from None
    if t.dim() == 0:
        t = t.expand(3).clone()
    if tuple(t.shape) not in ((3,), (3,) + tuple(shape)):
        raise ConfigError(key, f"a number, three numbers (d, h, w) or a (3, D, H, W) = {(3,) + tuple(shape)} "
                               "array", tuple(t.shape))
    if not bool(torch.isfinite(t).all()):
        raise ConfigError(key, "finite values", "non-finite values", show_got=True)
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
        min, max, shear: see above; ``0 <= min <= max``, ``shear >= 0``.

    Example:
        >>> g = Grid((4, 4, 4), spacing=0.01)
        >>> Limits(g, min=0.008, max=0.012, shear=0.002).uniform
        True
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
            raise ConfigError("limits.min", "distances >= 0 (no element may pass its neighbour)", float(lo.min()))
        if bool((sh < 0).any()):
            raise ConfigError("limits.shear", "shear limits >= 0", float(sh.min()))
        per = (lambda t: t.view(3, 1, 1, 1) if t.dim() == 1 else t)
        bad = per(lo) > per(hi)
        if bool(bad.any()):
            where = [int(v) for v in bad.nonzero()[0]]
            node = f" at node {tuple(where[1:])}" if lo.dim() > 1 or hi.dim() > 1 else ""
            raise ConfigError("limits", f"min <= max on every link; axis {'dhw'[where[0]]}{node} has "
                                        f"min {float(per(lo).expand_as(bad)[tuple(where)]):.4g} > "
                                        f"max {float(per(hi).expand_as(bad)[tuple(where)]):.4g}", show_got=False)
        for name, t in (("min", lo), ("max", hi), ("shear", sh)):
            object.__setattr__(self, name, t)

    @property
    def uniform(self) -> bool:
        """True when every limit is one number per axis (Gibson's homogeneous case)."""
        return all(t.dim() == 1 for t in (self.min, self.max, self.shear))

    def per_link(self) -> tuple:
        """``(min, max, shear)`` each as ``(3, D, H, W)`` float64."""
        shape = (3,) + self.grid.shape
        return tuple(t.view(3, 1, 1, 1).expand(shape) if t.dim() == 1 else t
                     for t in (self.min, self.max, self.shear))

    def offset_bounds(self, dtype=torch.float64, device=None) -> tuple:
        """Limits on offset differences ``u_j - u_i`` (``u = x - X``), as ``(lo, hi, shear)``:
        ``lo_a = min_a - spacing_a``, ``hi_a = max_a - spacing_a``. Each ``(3,)`` when
        :attr:`uniform` allows it, else ``(3, D, H, W)``."""
        h = torch.tensor(self.grid.spacing, dtype=torch.float64)
        out = []
        for t, shift in ((self.min, True), (self.max, True), (self.shear, False)):
            s = h.view(3, *[1] * (t.dim() - 1)) if shift else 0.0
            out.append((t - s).to(dtype=dtype, device=device))
        return tuple(out)

    @classmethod
    def from_material(cls, grid: Grid, compression=0.9, stretch=1.1, shear=0.1) -> "Limits":
        """Limits as ratios of the rest spacing: ``min_a = compression * h_a``,
        ``max_a = stretch * h_a``, ``shear_a = shear * h_a``.

        Each ratio is a number, three numbers ``(d, h, w)`` (anisotropic, e.g. muscle fibres) or
        a ``(D, H, W)`` array per element; a link then gets the mean of its two elements' values
        (Schill's rule for heterogeneous tissue).

        Example:
            >>> g = Grid((8, 8, 8), spacing=0.001)
            >>> lim = Limits.from_material(g, compression=0.8, stretch=1.25, shear=0.15)
            >>> [round(float(v), 6) for v in lim.max]
            [0.00125, 0.00125, 0.00125]
        """
        h = torch.tensor(grid.spacing, dtype=torch.float64)
        shape = grid.shape

        def ratio(value, key):
            try:
                t = value.detach().to("cpu", torch.float64) if torch.is_tensor(value) \
                    else torch.as_tensor(value, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                raise ConfigError(key, "a number, three numbers (d, h, w) or a (D, H, W) array", value) from None
            if not bool(torch.isfinite(t).all()):
                raise ConfigError(key, "finite values", "non-finite values", show_got=True)
            if t.dim() == 0:
                return t * h
            if tuple(t.shape) == (3,):
                return t * h
            if tuple(t.shape) == shape:                                     # per element -> per link
                links = t.expand(3, *shape).clone()
                for a in range(3):
                    n = shape[a]
                    if n > 1:
                        lo = [slice(None)] * 3
                        hi = [slice(None)] * 3
                        lo[a], hi[a] = slice(0, n - 1), slice(1, n)
                        links[(a, *lo)] = 0.5 * (t[tuple(lo)] + t[tuple(hi)])
                return links * h.view(3, 1, 1, 1)
            raise ConfigError(key, f"a number, three numbers (d, h, w) or a (D, H, W) = {shape} array",
                              tuple(t.shape))
        if bool((torch.as_tensor(shear, dtype=torch.float64) < 0).any()):
            raise ConfigError("shear", "a ratio >= 0", shear if not torch.is_tensor(shear) else float(shear.min()))
        return cls(grid, ratio(compression, "compression"), ratio(stretch, "stretch"), ratio(shear, "shear"))


def tissue_limits(grid: Grid, tissue, labels=None, reference_stress: float = 300.0,
                  slack_range=(0.005, 0.5)) -> Limits:
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
        >>> lim = tissue_limits(Grid((8, 8, 8), spacing=0.001), "liver")
    """
    from .fuzzy.presets import load_preset, tissue_parameters
    if not (isinstance(reference_stress, (int, float)) and reference_stress > 0):
        raise ConfigError("reference_stress", "a positive stress in Pa", reference_stress)
    items = list(tissue) if isinstance(tissue, (list, tuple)) else [tissue]
    if not items:
        raise ConfigError("tissue", "at least one tissue name or consistency value", tissue)
    eps = []
    system = None
    for item in items:
        if isinstance(item, str):
            E = tissue_parameters(item)["youngs_modulus"]
        elif isinstance(item, (int, float)) and not isinstance(item, bool) and 0 <= item <= 10:
            system = system or load_preset("tissue_si")
            E = float(system.evaluate(consistency=float(item))["youngs_modulus"])
        else:
            raise ConfigError("tissue", "a tissue name or a consistency value in [0, 10]", item)
        eps.append(min(max(reference_stress / E, slack_range[0]), slack_range[1]))
    if labels is None:
        if len(eps) != 1:
            raise ConfigError("labels", "a (D, H, W) integer array to choose among several tissues", None)
        e = torch.tensor(eps[0], dtype=torch.float64)
    else:
        lab = torch.as_tensor(labels)
        if tuple(lab.shape) != grid.shape or lab.is_floating_point() or \
                bool(((lab < 0) | (lab >= len(eps))).any()):
            raise ConfigError("labels", f"integers in [0, {len(eps) - 1}] of shape {grid.shape}",
                              tuple(lab.shape) if tuple(lab.shape) != grid.shape else "values out of range")
        e = torch.tensor(eps, dtype=torch.float64)[lab.long()]
    return Limits.from_material(grid, 1 - e, 1 + e, e)


# ---------------------------------------------------------------- the checker
def _exists(grid: Grid, device) -> torch.Tensor:
    return grid.nodes().to(device)


def limit_violation(positions: torch.Tensor, grid: Grid, limits: Limits, per_link: bool = False):
    """Largest amount (m) by which any link exceeds its ChainMail limits: an independent,
    vectorised check written on absolute positions (not on the offsets the algorithms use).

    Args:
        positions: ``(B, 3, D, H, W)`` or ``(3, D, H, W)``.
        grid, limits: the grid (its node mask decides which links exist) and the limits.
        per_link: also return the excess of every link, ``(B, 3, D, H, W)`` (axis ``a`` at the
            link's first endpoint; 0 where the link does not exist).
    Returns:
        ``(B,)`` largest excess, 0 where every limit holds (and the field with ``per_link``).

    Example:
        >>> g = Grid((3, 3, 3), spacing=1.0)
        >>> float(limit_violation(g.rest_positions(), g, Limits(g, 0.9, 1.1, 0.1))[0])
        0.0
    """
    x = positions if positions.dim() == 5 else positions.unsqueeze(0)
    dev, dt = x.device, x.dtype
    mn, mx, sh = (t.to(device=dev, dtype=dt) for t in limits.per_link())
    nodes = _exists(grid, dev)
    field_ = torch.zeros((x.shape[0], 3) + grid.shape, dtype=dt, device=dev)
    for a in range(3):
        n = grid.shape[a]
        if n < 2:
            continue
        first = [slice(None)] * 3
        second = [slice(None)] * 3
        first[a], second[a] = slice(0, n - 1), slice(1, n)
        first, second = tuple(first), tuple(second)
        diff = x[(..., *second)] - x[(..., *first)]                   # (B, 3, region)
        along = diff[:, a]
        excess = torch.maximum(mn[a][first] - along, along - mx[a][first])
        for b in range(3):
            if b != a:
                excess = torch.maximum(excess, diff[:, b].abs() - sh[a][first])
        excess = excess.clamp_min(0) * (nodes[first] & nodes[second])
        field_[(slice(None), a, *first)] = excess
    worst = field_.flatten(1).amax(1)
    return (worst, field_) if per_link else worst


# --------------------------------------------------------------- move results
@dataclass
class MoveResult:
    """What one :meth:`ChainMail.move` did.

    Attributes:
        requested: the displacement asked for, ``(3,)`` metres.
        fraction: the fraction of it carried out (1 unless the move was blocked and scaled).
        blocked: the full move was blocked (by a fixed element or a conflict).
        moved: number of distinct elements that moved (picked elements included).
        checked: number of element checks (queue entries processed).
        passes: one array per propagation pass of the final attempt, each listing the node
            indices ``(i * H + j) * W + k`` processed in that pass, in order; an element appears
            at most once per pass (a pass is one initiator for Gibson, the whole move for
            Enhanced ChainMail).
        moved_nodes: the indices of the elements that moved, sorted.
        attempts: number of propagation attempts (more than 1 when a blocked move was scaled).
    """
    requested: tuple
    fraction: float = 1.0
    blocked: bool = False
    moved: int = 0
    checked: int = 0
    passes: list = field(default_factory=list)
    moved_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    attempts: int = 1

    @property
    def max_touches(self) -> int:
        """The most times any element was processed within one pass (1 for a correct ChainMail)."""
        return max((int(np.bincount(p).max()) for p in self.passes if len(p)), default=0)


# ------------------------------------------------------------ sequential ChainMail
class ChainMail:
    """Sequential ChainMail with persistent state: each :meth:`move` costs in proportion to
    the elements it moves, not to the grid.

    Positions are kept as float64 offsets ``u = x - X`` in flat arrays padded by one layer of
    "outside" elements, so a neighbour is a constant index offset and no bounds test is needed;
    scalar access goes through memoryviews (a torch scalar op costs microseconds).

    Args:
        grid: the :class:`~torchdeform.grid.Grid` (its spacing and node mask; the spring
            topology is ignored: ChainMail links the six face neighbours).
        limits: :class:`Limits` (per-axis for ``"gibson"``, per-axis or per-link for ``"enhanced"``).
        fixed: optional bool ``(D, H, W)`` of elements that never move.
        positions: optional start positions ``(1, 3, D, H, W)`` or ``(3, D, H, W)`` (e.g. a
            mass-spring state's ``x``); default the rest positions. They must satisfy the limits.
        method: ``"gibson"`` or ``"enhanced"``.

    Example:
        >>> g = Grid((16, 16, 16), spacing=0.001)
        >>> cm = ChainMail(g, Limits.from_material(g, 0.8, 1.2, 0.2), fixed=g.face("bottom"))
        >>> r = cm.move([(15, 8, 8)], (0.002, 0.0, 0.0))
        >>> r.fraction, r.max_touches
        (1.0, 1)
    """

    def __init__(self, grid: Grid, limits: Limits, fixed=None, positions=None, method: str = "gibson"):
        if not isinstance(grid, Grid):
            raise ConfigError("grid", "a torchdeform.Grid", type(grid).__name__)
        if not isinstance(limits, Limits) or limits.grid.shape != grid.shape:
            raise ConfigError("limits", f"a chainmail.Limits for the grid {grid.shape}", type(limits).__name__)
        if method not in METHODS:
            raise ConfigError("method", '"gibson" or "enhanced"', method)
        if method == "gibson" and not limits.uniform:
            raise ConfigError("method", '"enhanced" for per-link (heterogeneous) limits: Gibson\'s six lists '
                                        "need one set of limits per axis", method)
        if method == "gibson" and grid.node_mask is not None:
            raise ConfigError("method", '"enhanced" for a body with a node mask: Gibson\'s one path per element '
                                        "(d, then h, then w) needs a box", method)
        self.grid, self.limits, self.method = grid, limits, method
        #: Excess (m) below which an element that cannot move (fixed, or picked earlier in the
        #: same move) is taken to satisfy its limits: rounding of positions on a limit's edge.
        self.tol = 1e-9 * min(grid.spacing)
        D, H, W = grid.shape
        self._pshape = (D + 2, H + 2, W + 2)
        P = math.prod(self._pshape)
        self._off = ((H + 2) * (W + 2), W + 2, 1)
        self._doff = tuple(s * self._off[a] for a, s in DIRECTIONS)

        flag = np.zeros(self._pshape, dtype=np.uint8)
        flag[1:-1, 1:-1, 1:-1] = grid.nodes().numpy().astype(np.uint8) * _FREE
        if fixed is not None:
            fx = torch.as_tensor(fixed, dtype=torch.bool).cpu()
            if tuple(fx.shape) != grid.shape:
                raise ConfigError("fixed", f"a bool mask of shape {grid.shape}", tuple(fx.shape))
            inner = flag[1:-1, 1:-1, 1:-1]
            inner[fx.numpy() & (inner > 0)] = _FIXED
        self._flag = flag.reshape(-1)
        self._u = np.zeros((3, P), dtype=np.float64)
        self._stamp = np.zeros(P, dtype=np.int64)
        self._gen = 0
        self._moved = np.zeros(P, dtype=bool)
        self._held = np.zeros(0, dtype=np.int64)
        lo, hi, sh = limits.offset_bounds()
        if limits.uniform:
            self._bounds = tuple((float(lo[a]), float(hi[a]), float(sh[a])) for a in range(3))
            self._links = None
        else:                                                   # per-link arrays, padded like _u
            self._bounds = None
            arrays = np.zeros((3, 3, P), dtype=np.float64)
            for k, t in enumerate((lo, hi, sh)):
                full = t.view(3, 1, 1, 1).expand(3, *grid.shape) if t.dim() == 1 else t
                view = arrays[k].reshape(3, *self._pshape)
                view[:, 1:-1, 1:-1, 1:-1] = full.numpy()
            self._links = arrays
        self.set_positions(grid.rest_positions(torch.float64) if positions is None else positions)
        self._views()

    # ------------------------------------------------------------ state in/out
    def _views(self):
        self._mu = tuple(memoryview(self._u[c]) for c in range(3))
        self._mflag = memoryview(self._flag)
        self._mstamp = memoryview(self._stamp)
        if self._links is not None:
            self._mlinks = tuple(tuple(memoryview(self._links[k, a]) for a in range(3)) for k in range(3))

    def _interior(self, arr: np.ndarray) -> np.ndarray:
        return arr.reshape(arr.shape[:-1] + self._pshape)[..., 1:-1, 1:-1, 1:-1]

    def set_positions(self, positions) -> None:
        """Replace the positions (``(1, 3, D, H, W)`` or ``(3, D, H, W)``); they must satisfy the limits."""
        x = torch.as_tensor(positions).detach().to("cpu", torch.float64)
        x = x[0] if x.dim() == 5 else x
        if tuple(x.shape) != (3,) + self.grid.shape:
            raise ConfigError("positions", f"(1, 3, D, H, W) or (3, D, H, W) with grid {self.grid.shape}",
                              tuple(x.shape))
        worst, excess = limit_violation(x, self.grid, self.limits, per_link=True)
        if float(worst) > 1e-12:
            a, i, j, k = (int(v) for v in np.unravel_index(int(excess[0].flatten().argmax()), excess[0].shape))
            raise ConfigError("positions", "positions that satisfy the ChainMail limits (repair a mass-spring "
                                           f"state first); the link from node {(i, j, k)} along {'dhw'[a]} "
                                           f"exceeds them by {float(worst):.3g} m", show_got=False)
        u = (x - self.grid.rest_positions(torch.float64)[0]) * self.grid.nodes()
        self._interior(self._u)[...] = u.numpy()

    def reset(self) -> None:
        """Back to the rest positions; forgets the moved elements."""
        self._u[...] = 0.0
        self._moved[:] = False
        self._held = np.zeros(0, dtype=np.int64)

    def offsets(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """The displacement field ``u = x - X``, ``(1, 3, D, H, W)`` metres (0 outside the node mask)."""
        return torch.from_numpy(self._interior(self._u).copy()).unsqueeze(0).to(dtype=dtype, device=device)

    displacement = offsets

    def positions(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """Positions ``x = X + u``, ``(1, 3, D, H, W)``."""
        return self.grid.rest_positions(dtype, device) + self.offsets(dtype, device)

    def state(self, dtype=torch.float32, device=None):
        """A :class:`~torchdeform.model.State` (``x``, ``v = 0``) the mass-spring integrators continue from."""
        from .model import State
        x = self.positions(dtype, device)
        return State(x, torch.zeros_like(x), 0.0)

    def moved_mask(self) -> torch.Tensor:
        """Bool ``(D, H, W)``: elements moved since construction or :meth:`clear_moved`."""
        return torch.from_numpy(self._interior(self._moved).copy())

    def clear_moved(self) -> None:
        self._moved[:] = False

    @property
    def fixed(self) -> torch.Tensor:
        """Bool ``(D, H, W)`` of fixed elements."""
        return torch.from_numpy(self._interior(self._flag) == _FIXED)

    def _node_index(self, padded) -> np.ndarray:
        """Padded flat indices -> node indices ``(i * H + j) * W + k``."""
        p = np.asarray(padded, dtype=np.int64)
        i, j, k = np.unravel_index(p, self._pshape)
        D, H, W = self.grid.shape
        return ((i - 1) * H + (j - 1)) * W + (k - 1)

    def _picked(self, nodes) -> list:
        shape = self.grid.shape
        if torch.is_tensor(nodes) and nodes.dtype == torch.bool or isinstance(nodes, np.ndarray) and nodes.dtype == bool:
            m = torch.as_tensor(nodes).cpu()
            if tuple(m.shape) != shape:
                raise ConfigError("nodes", f"a bool mask of shape {shape} or a list of [i, j, k]", tuple(m.shape))
            idx = [tuple(int(v) for v in r) for r in m.nonzero()]
        else:
            try:
                idx = [tuple(int(v) for v in ijk) for ijk in nodes]
            except (TypeError, ValueError):
                raise ConfigError("nodes", "a list of node indices [i, j, k] or a bool mask", nodes) from None
        if not idx:
            raise ConfigError("nodes", "at least one element to move", nodes if not torch.is_tensor(nodes) else "[]")
        out = []
        for ijk in idx:
            if len(ijk) != 3 or not all(0 <= v < n for v, n in zip(ijk, shape)):
                raise ConfigError("nodes", f"element indices inside the grid {shape} (a pull outside the grid)",
                                  list(ijk))
            p = ((ijk[0] + 1) * self._pshape[1] + ijk[1] + 1) * self._pshape[2] + ijk[2] + 1
            if self._flag[p] == _OUTSIDE:
                raise ConfigError("nodes", "elements inside the body's node mask", list(ijk))
            if self._flag[p] == _FIXED:
                raise ConfigError("nodes", "free elements (this one is fixed and cannot be moved)", list(ijk))
            out.append(p)
        return list(dict.fromkeys(out))

    # ------------------------------------------------------------------ moving
    def move(self, nodes, displacement, on_blocked: str = "scale", bisections: int = 12) -> MoveResult:
        """Move the picked elements rigidly by ``displacement`` and let ChainMail drag, push and
        shear the rest.

        Args:
            nodes: picked elements: a list of ``(i, j, k)`` or a bool ``(D, H, W)`` mask.
            displacement: ``(dd, dh, dw)`` metres (a pull or a push in any direction).
            on_blocked: what to do when the move would have to move a fixed element:
                ``"scale"`` (default) carry out the largest fraction that can be done (bisection,
                ``bisections`` halvings), ``"error"`` raise :class:`BlockedMoveError` and change nothing.
            bisections: halvings for ``"scale"``.
        Returns:
            :class:`MoveResult`.
        Raises:
            ConfigError: picked elements outside the grid, outside the node mask or fixed; a bad
                displacement or option.
        """
        if on_blocked not in ("scale", "error"):
            raise ConfigError("on_blocked", '"scale" or "error"', on_blocked)
        try:
            d = tuple(float(v) for v in (displacement.tolist() if torch.is_tensor(displacement) else displacement))
        except (TypeError, ValueError):
            raise ConfigError("displacement", "three numbers (dd, dh, dw) in metres", displacement) from None
        if len(d) != 3 or not all(math.isfinite(v) for v in d):
            raise ConfigError("displacement", "three finite numbers (dd, dh, dw) in metres", displacement)
        picked = self._picked(nodes)
        start = [(p, self._u[0, p], self._u[1, p], self._u[2, p]) for p in picked]

        attempts = 1
        ok, log, passes, checked = self._attempt(start, d, 1.0)
        fraction = 1.0
        if not ok:
            self._undo(log)
            if on_blocked == "error":
                raise BlockedMoveError(f"moving {len(picked)} element(s) by {d} m would have to move a fixed "
                                       "element; nothing was moved")
            lo, hi = 0.0, 1.0
            for _ in range(bisections):
                mid = 0.5 * (lo + hi)
                attempts += 1
                good, log, _, _ = self._attempt(start, d, mid)
                self._undo(log)
                lo, hi = (mid, hi) if good else (lo, mid)
            fraction = lo
            attempts += 1
            ok, log, passes, checked = self._attempt(start, d, lo)
            if not ok:                                  # cannot happen for lo = 0 in a valid state
                self._undo(log)
                raise BlockedMoveError("a scaled move was blocked too; nothing was moved")
        moved = np.unique(np.asarray(log[0::4], dtype=np.int64))
        self._moved[moved] = True
        self._held = np.asarray(picked, dtype=np.int64)
        return MoveResult(requested=d, fraction=fraction, blocked=fraction < 1.0, moved=len(moved),
                          checked=checked, passes=[self._node_index(p) for p in passes],
                          moved_nodes=np.sort(self._node_index(moved)), attempts=attempts)

    def _undo(self, log: list) -> None:
        u = self._u
        for n in range(len(log) - 4, -1, -4):
            p = log[n]
            u[0, p], u[1, p], u[2, p] = log[n + 1], log[n + 2], log[n + 3]

    def _attempt(self, start, d, scale):
        """One try at moving the picked elements by ``scale * d``; returns
        ``(ok, undo log, processed indices per pass, checks)``. The log is flat: index, old u."""
        log, passes = [], []
        ux, uy, uz = self._mu
        targets = [(p, x0 + scale * d[0], y0 + scale * d[1], z0 + scale * d[2]) for p, x0, y0, z0 in start]
        self._gen += 1
        gen = self._gen
        if self.method == "enhanced":
            ok = self._enhanced(targets, [scale * v for v in d], log, passes)
            return ok, log, passes, sum(len(p) for p in passes)
        pinned = set()
        checked = 0
        for p, tx, ty, tz in targets:
            log += (p, ux[p], uy[p], uz[p])
            ux[p], uy[p], uz[p] = tx, ty, tz
            pinned.add(p)
            touched = []
            ok = self._gibson(p, pinned, log, touched)
            passes.append(touched)
            checked += len(touched)
            if not ok:
                return False, log, passes, checked
        return True, log, passes, checked

    def _gibson(self, e0: int, pinned: set, log: list, touched: list) -> bool:
        """Gibson's propagation from the initiator ``e0`` (already at its target)."""
        ux, uy, uz = self._mu
        flag = self._mflag
        doff = self._doff
        queues = [[], [], [], [], [], []]
        for k in range(6):
            n = e0 + doff[k]
            if flag[n]:
                queues[k].append(n)
        # per list: offset of the sponsor and the offset-difference box of each coordinate
        boxes = []
        for k, (a, s) in enumerate(DIRECTIONS):
            lo, hi, sh = self._bounds[a]
            b = [(-sh, sh)] * 3
            b[a] = (lo, hi) if s > 0 else (-hi, -lo)
            boxes.append((doff[k], b[0][0], b[0][1], b[1][0], b[1][1], b[2][0], b[2][1],
                          [(queues[q], doff[q]) for q in GIBSON_SUCCESSORS[k]]))
        append = touched.append
        tol = self.tol
        busy = True
        while busy:
            busy = False
            for k in range(6):
                q = queues[k]
                if not q:
                    continue
                busy = True
                off, l0, h0, l1, h1, l2, h2, succ = boxes[k]
                for e in q:                      # the list grows while it is served (same direction)
                    append(e)
                    s = e - off
                    changed = False
                    v = ux[e]
                    c = ux[s]
                    if v < c + l0:
                        v, changed = c + l0, True
                    elif v > c + h0:
                        v, changed = c + h0, True
                    w = uy[e]
                    c = uy[s]
                    if w < c + l1:
                        w, changed = c + l1, True
                    elif w > c + h1:
                        w, changed = c + h1, True
                    z = uz[e]
                    c = uz[s]
                    if z < c + l2:
                        z, changed = c + l2, True
                    elif z > c + h2:
                        z, changed = c + h2, True
                    if changed:
                        if flag[e] != _FREE or e in pinned:
                            if max(abs(v - ux[e]), abs(w - uy[e]), abs(z - uz[e])) > tol:
                                return False
                            continue                  # off by rounding only: it stays, as it may
                        log += (e, ux[e], uy[e], uz[e])
                        ux[e] = v
                        uy[e] = w
                        uz[e] = z
                        for qq, o in succ:
                            n = e + o
                            if flag[n]:
                                qq.append(n)
                q.clear()
        return True

    def _feed_table(self, c: int, sign: int) -> list:
        """For coordinate ``c`` pulled (``sign > 0``) or pushed (``sign < 0``): per neighbour
        direction k of a final element e, ``(offset, limit array or None, constant, factor,
        link at e)`` such that the neighbour n = e + offset must satisfy
        ``u_n[c] >= u_e[c] + factor * limit`` (pull) or ``<=`` (push), the limit being that of the
        link (stored at e when ``link at e``, else at n)."""
        table = []
        for k, (a, s) in enumerate(DIRECTIONS):
            if c == a:
                which, factor = ((0, 1.0) if s > 0 else (1, -1.0)) if sign > 0 else ((1, 1.0) if s > 0 else (0, -1.0))
            else:
                which, factor = 2, (-1.0 if sign > 0 else 1.0)
            arr = None if self._links is None else self._mlinks[which][a]
            const = self._bounds[a][which] if self._links is None else 0.0
            table.append((self._doff[k], arr, const, factor, s > 0))
        return table

    def _enhanced(self, targets, delta, log: list, passes: list) -> bool:
        """Enhanced ChainMail: the picked elements are placed, then every coordinate that moves is
        propagated with one priority queue, largest violation first.

        The limits bound differences of one coordinate at a time, so the three coordinates are
        three independent systems; within one, a violation never grows along a propagation
        (the old positions satisfied the limits), so largest-violation-first is a label-setting
        order: an element popped is final, moved exactly onto the bound of its worst-violated
        link, and never touched again in that pass. Every limit holds afterwards; a fixed element
        that would have to move means the move is infeasible (blocked)."""
        U = self._mu
        flag, stamp = self._mflag, self._mstamp
        push, pop = heapq.heappush, heapq.heappop
        tol = self.tol
        for p, *t in targets:
            log += (p, U[0][p], U[1][p], U[2][p])
            U[0][p], U[1][p], U[2][p] = t
        picks = [p for p, *_ in targets]
        for c in range(3):
            if delta[c] == 0.0:
                continue
            sign = 1 if delta[c] > 0 else -1
            self._gen += 1
            gen = self._gen
            for p in picks:
                stamp[p] = gen
            uc = U[c]
            table = self._feed_table(c, sign)
            processed = []
            passes.append(processed)
            heap = []
            todo = picks
            while True:
                for e in todo:                               # queue e's violated, non-final neighbours
                    ue = uc[e]
                    for off, arr, const, factor, at_e in table:
                        n = e + off
                        if not flag[n] or stamp[n] == gen:
                            continue
                        bound = ue + factor * (const if arr is None else arr[e if at_e else n])
                        v = bound - uc[n] if sign > 0 else uc[n] - bound
                        if v > 0.0:
                            if flag[n] == _FIXED:
                                if v > tol:
                                    return False
                                continue                     # off by rounding only
                            push(heap, (-v, n, bound))
                e = -1
                while heap:
                    _, e, bound = pop(heap)
                    if stamp[e] != gen:
                        break
                    e = -1                                   # a stale entry: already final
                if e < 0:
                    break
                stamp[e] = gen
                processed.append(e)
                log += (e, U[0][e], U[1][e], U[2][e])
                uc[e] = bound
                todo = (e,)
        return True

    # --------------------------------------------------------------- relaxing
    def relax(self, steps: int = 1, mode: str = "centroid", only_moved: bool = False, omega: float = 1.0,
              hold=None) -> list:
        """Elastic relaxation of the current deformation (see :func:`relax`).

        Fixed elements and the elements picked by the last :meth:`move` stay where they are
        (``hold``: a bool ``(D, H, W)`` mask to hold instead); with ``only_moved`` only the
        elements ChainMail moved since :meth:`clear_moved` are relaxed.

        Returns:
            the energy (:func:`relax_energy`) before and after every step, ``steps + 1`` floats.
        """
        free = (self._interior(self._flag) == _FREE).copy()
        if hold is None:
            held = np.zeros(self._flag.shape, dtype=bool)
            held[self._held] = True
            free &= ~self._interior(held)
        else:
            free &= ~torch.as_tensor(hold, dtype=torch.bool).cpu().numpy()
        if only_moved:
            free &= self._interior(self._moved)
        u = self.offsets(torch.float64)
        u, energies = relax(u, self.grid, self.limits, steps, mode, torch.from_numpy(free), omega, offsets=True)
        self._interior(self._u)[...] = u[0].numpy()
        return energies


# ---------------------------------------------------------------- neighbour boxes (tensor)
def _axis_slices(grid: Grid, a: int):
    """``(first, second)`` index tuples of the links along axis ``a``: the 6-neighbour stencil."""
    return _grid6(grid).stencil[a]


def _link_values(t: torch.Tensor, a: int, region) -> torch.Tensor:
    return t[a] if t.dim() == 1 else t[a][region]


def neighbour_boxes(u: torch.Tensor, grid: Grid, bounds: tuple, source: torch.Tensor):
    """The box each element's offset must lie in relative to its face neighbours in ``source``.

    Args:
        u: offsets ``(B, 3, D, H, W)``.
        grid: the grid.
        bounds: ``(lo, hi, shear)`` from :meth:`Limits.offset_bounds` (same dtype and device as ``u``).
        source: bool ``(B|1, 1, D, H, W)``: neighbours that constrain (moved, fixed, or all).
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
        for elem, nbr, sgn in ((second, first, 1), (first, second, -1)):
            centre = u[(..., *nbr)]
            rel_lo = [-sa, -sa, -sa]
            rel_hi = [sa, sa, sa]
            rel_lo[a], rel_hi[a] = (la, ha) if sgn > 0 else (-ha, -la)
            blo = torch.stack([centre[:, c] + rel_lo[c] for c in range(3)], 1)
            bhi = torch.stack([centre[:, c] + rel_hi[c] for c in range(3)], 1)
            ok = source[(..., *nbr)]
            blo = torch.where(ok, blo, -math.inf)
            bhi = torch.where(ok, bhi, math.inf)
            lo[(..., *elem)] = torch.maximum(lo[(..., *elem)], blo)
            hi[(..., *elem)] = torch.minimum(hi[(..., *elem)], bhi)
    return lo, hi


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


def _dilate(m: torch.Tensor, grid: Grid) -> torch.Tensor:
    out = m.clone()
    for a in range(3):
        if grid.shape[a] < 2:
            continue
        first, second = _axis_slices(grid, a)
        out[(..., *second)] |= m[(..., *first)]
        out[(..., *first)] |= m[(..., *second)]
    return out


def _hops(picked: torch.Tensor, grid: Grid, moved: torch.Tensor) -> torch.Tensor:
    """Largest 6-neighbour hop distance (through the body) from ``picked`` to an element of
    ``moved``, ``(B,)``; both ``(B, D, H, W)`` bool."""
    nodes = _exists(grid, picked.device)
    reach = picked.clone()
    depth = torch.zeros(picked.shape[0], dtype=torch.long, device=picked.device)
    hop = 0
    while bool((moved & ~reach).any()):
        grown = _dilate(reach, grid) & nodes
        if bool((grown == reach).all()):
            break
        hop += 1
        new = (grown & ~reach & moved).flatten(1).any(1)
        depth = torch.where(new, torch.full_like(depth, hop), depth)
        reach = grown
    return depth


def tensor_chainmail(positions: torch.Tensor, grid: Grid, limits: Limits, picked, displacement,
                     fixed=None, max_sweeps: int | None = None) -> SweepResult:
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
        grid, limits: grid (node mask respected) and :class:`Limits`.
        picked: bool ``(D, H, W)`` or ``(B, D, H, W)``: the elements moved rigidly.
        displacement: ``(3,)`` or ``(B, 3)`` metres.
        fixed: optional bool ``(D, H, W)`` or ``(B, D, H, W)``.
        max_sweeps: default ``D + H + W`` (enough for any propagation).
    Returns:
        :class:`SweepResult` (positions, moved, sweeps, depth, violation).

    Example:
        >>> g = Grid((16, 16, 16), spacing=1.0)
        >>> pick = torch.zeros(16, 16, 16, dtype=torch.bool); pick[15, 8, 8] = True
        >>> r = tensor_chainmail(g.rest_positions(torch.float64).repeat(2, 1, 1, 1, 1), g,
        ...                      Limits.from_material(g, 0.8, 1.2, 0.2), pick,
        ...                      torch.tensor([[2.0, 0, 0], [-1.0, 0.5, 0]], dtype=torch.float64))
        >>> r.sweeps, r.violation.tolist()                       # doctest: +SKIP
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
    bounds = limits.offset_bounds(dt, dev)
    X = grid.rest_positions(dt, dev)
    u = torch.where(pick, x - X + d.view(-1, 3, 1, 1, 1), x - X)
    moved = pick.clone()
    free = nodes & ~pick & ~fix
    sign = torch.sign(d).view(-1, 3, 1, 1, 1)
    pull, push = sign > 0, sign < 0
    limit = max_sweeps if max_sweeps is not None else 2 * sum(grid.shape)
    sweeps = 0
    for _ in range(limit):
        lo, hi = neighbour_boxes(u, grid, bounds, moved)
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
    depth = _hops(pick[:, 0], grid, moved4)
    return SweepResult(xn, moved4, sweeps, depth, limit_violation(xn, grid, limits))


# ------------------------------------------------------------------- relaxation
def _grid6(grid: Grid) -> Grid:
    if grid.topology == 6:
        return grid
    key = ("chainmail_grid6",)
    if key not in grid._cache:
        grid._cache[key] = Grid(grid.shape, grid.spacing, 6, node_mask=grid.node_mask, origin=grid.origin)
    return grid._cache[key]


def _goal_shift(grid: Grid, limits: Limits | None, mode: str, dtype, device):
    """Per axis, the goal offset difference along the link: 0 (centroid) or the middle of
    ``[min, max]`` minus the spacing (Gibson's goal), ``(3,)`` or ``(3, D, H, W)``."""
    if mode == "centroid" or limits is None:
        return None
    lo, hi, _ = limits.offset_bounds(dtype, device)
    g = 0.5 * (lo + hi)
    return None if not bool((g != 0).any()) else g


def _goal_vector(goal, s: int, src, like: torch.Tensor) -> torch.Tensor:
    """The goal offset difference of the links of half-direction ``s`` as a vector field
    broadcasting against ``like`` ``(B, 3, *region)``: ``goal_s`` on channel ``s``, 0 elsewhere."""
    g = _link_values(goal, s, src)
    g = g.expand(like.shape[2:]) if g.dim() else g.expand(like.shape[2:]).clone()
    vec = torch.zeros(like.shape[1:], dtype=like.dtype, device=like.device)
    vec[s] = g
    return vec.unsqueeze(0)


def _residual(u, grid6: Grid, goal):
    """``sum_j (u_j - u_i - b_ij)`` over existing face neighbours ``(B, 3, D, H, W)``, and the
    neighbour counts ``(1, 1, D, H, W)``."""
    masks = grid6.spring_mask(u.device)

    def fn(s, src, du):
        if goal is not None:
            du = du - _goal_vector(goal, s, src, du)
        return du * masks[s][src].to(u.dtype)
    r = accumulate(grid6, fn, u)
    ones = torch.ones((1, 1) + grid6.shape, dtype=u.dtype, device=u.device)

    def count(s, src, _):
        m = masks[s][src].to(u.dtype).view(1, 1, *masks[s][src].shape)
        return m, m
    return r, accumulate(grid6, count, ones)


def relax_energy(positions: torch.Tensor, grid: Grid, limits: Limits | None = None, mode: str = "centroid",
                 offsets: bool = False) -> torch.Tensor:
    """The energy relaxation lowers, ``(B,)``: ``E(u) = 1/2 sum_links |u_j - u_i - b_ij|^2`` over
    the face-neighbour links, with ``u = x - X``. ``b = 0`` for ``mode="centroid"`` (the
    Dirichlet energy of the offsets, REFERENCE 2.4), ``b_ij = (goal_a - h_a) e_a`` for
    ``mode="goal"`` (zero-length springs to Gibson's goal distance ``goal_a = (min_a + max_a) / 2``).
    """
    if mode not in RELAX_MODES:
        raise ConfigError("mode", '"centroid" or "goal"', mode)
    u = positions if offsets else positions - grid.rest_positions(positions.dtype, positions.device)
    u = u if u.dim() == 5 else u.unsqueeze(0)
    g6 = _grid6(grid)
    goal = _goal_shift(grid, limits, mode, u.dtype, u.device)
    total = u.new_zeros(u.shape[0])
    for s, (src, dst) in enumerate(g6.stencil):
        du = u[(..., *dst)] - u[(..., *src)]
        if goal is not None:
            du = du - _goal_vector(goal, s, src, du)
        e = (du * du).sum(1) * g6.spring_mask(u.device)[s][src]
        total = total + 0.5 * e.flatten(1).sum(1)
    return total


def crease_measure(positions: torch.Tensor, grid: Grid, free=None, offsets: bool = False) -> torch.Tensor:
    """Straight-line artefact measure, ``(B,)`` in m^2: ``sum_i |c_i - u_i|^2`` over the free
    elements, where ``c_i`` is the centroid of the offsets of ``i``'s face neighbours.

    ChainMail leaves piecewise-linear offsets whose straight segments meet at creases (the
    straight lines running out from the pulled element); along a straight segment the offset
    equals its neighbours' centroid, at a crease it does not, so this sum collects the creases
    and is zero for a smooth (harmonic) field.

    Args:
        positions: ``(B, 3, D, H, W)`` positions (or offsets with ``offsets=True``).
        free: bool ``(D, H, W)`` elements to include (default: all existing elements).
    """
    u = positions if offsets else positions - grid.rest_positions(positions.dtype, positions.device)
    u = u if u.dim() == 5 else u.unsqueeze(0)
    r, deg = _residual(u, _grid6(grid), None)
    dev = (r / deg.clamp_min(1)) ** 2
    m = _exists(grid, u.device) if free is None else torch.as_tensor(free, dtype=torch.bool).to(u.device)
    return (dev.sum(1) * m).flatten(1).sum(1)


def relax(positions: torch.Tensor, grid: Grid, limits: Limits, steps: int = 1, mode: str = "centroid",
          free=None, omega: float = 1.0, offsets: bool = False):
    """Elastic relaxation within the ChainMail limits.

    Each step updates every free element once, red-black (the elements with even ``i + j + k``,
    then the odd ones; all face neighbours of an element have the other colour): the element's
    offset moves by ``omega`` towards its target (the centroid of its face neighbours' offsets,
    Knoche, or the mean of the goal positions its neighbours give it, Gibson) and is clamped into
    the box its neighbours' limits allow.

    Energy: :func:`relax_energy` never increases. For one colour the energy splits into one
    isotropic quadratic per element (neighbours are held), minimised at the target; the limits of
    that element form a box containing its current offset, and moving towards the minimiser by
    ``0 < omega < 2`` and clamping into that box cannot move it further from the minimiser in
    any coordinate. Every limit holds after every half-step (the box is exact while the
    neighbours are held). Knoche's shader updates all elements at once (Jacobi, ping-pong); the
    red-black order is what keeps both properties.

    Args:
        positions: ``(B, 3, D, H, W)`` positions (or offsets with ``offsets=True``), inside the limits.
        grid, limits: grid and :class:`Limits`.
        steps: relaxation steps (>= 0).
        mode: ``"centroid"`` (Knoche) or ``"goal"`` (Gibson's goal positions: the middle of each
            link's ``[min, max]``; the same as the centroid when that middle is the spacing).
        free: bool ``(D, H, W)`` or ``(B, D, H, W)`` of elements that may move (default all;
            exclude fixed and picked elements, or pass the elements ChainMail moved).
        omega: relaxation factor in ``(0, 2)`` (1: straight to the target).
    Returns:
        ``(positions, energies)``: the relaxed positions (offsets with ``offsets=True``), same
        shape as the input, and the energy (summed over the batch) before and after every step,
        ``steps + 1`` floats.

    Example:
        >>> g = Grid((9, 9, 9), spacing=1.0)
        >>> cm = ChainMail(g, Limits.from_material(g, 0.7, 1.3, 0.3))
        >>> r = cm.move([(4, 4, 4)], (2.0, 0.0, 0.0))
        >>> free = torch.ones(9, 9, 9, dtype=torch.bool); free[4, 4, 4] = False   # hold the pick
        >>> x, e = relax(cm.positions(), g, cm.limits, steps=4, free=free)
        >>> all(b <= a for a, b in zip(e, e[1:]))
        True
    """
    if mode not in RELAX_MODES:
        raise ConfigError("mode", '"centroid" or "goal"', mode)
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ConfigError("steps", "an integer >= 0", steps)
    if not (0 < float(omega) < 2):
        raise ConfigError("omega", "a relaxation factor in (0, 2)", omega)
    squeeze = positions.dim() == 4
    x = positions.unsqueeze(0) if squeeze else positions
    dt, dev = x.dtype, x.device
    X = grid.rest_positions(dt, dev)
    u = x if offsets else x - X
    g6 = _grid6(grid)
    nodes = _exists(grid, dev)
    m = nodes if free is None else torch.as_tensor(free, dtype=torch.bool).to(dev) & nodes
    m = m.view(-1, 1, *grid.shape)
    idx = [torch.arange(n, device=dev) for n in grid.shape]
    parity = (idx[0].view(-1, 1, 1) + idx[1].view(1, -1, 1) + idx[2].view(1, 1, -1)) % 2
    colours = [m & (parity == c).view(1, 1, *grid.shape) for c in (0, 1)]
    bounds = limits.offset_bounds(dt, dev)
    goal = _goal_shift(grid, limits, mode, dt, dev)
    source = nodes.view(1, 1, *grid.shape)
    energies = [float(relax_energy(u, grid, limits, mode, offsets=True).sum())]
    for _ in range(steps):
        for colour in colours:
            r, deg = _residual(u, g6, goal)
            target = u + omega * r / deg.clamp_min(1)
            lo, hi = neighbour_boxes(u, grid, bounds, source)
            u = torch.where(colour, torch.minimum(torch.maximum(target, lo), hi), u)
        energies.append(float(relax_energy(u, grid, limits, mode, offsets=True).sum()))
    out = u if offsets else X + u
    return (out[0] if squeeze else out), energies


# ------------------------------------------------------------------------ scenes
@dataclass(eq=False)
class ChainMailScene:
    """A ChainMail scene (``model = "chainmail"`` in a scene file, see :func:`chainmail_scene`).

    Each of ``frames`` frames moves every drag group rigidly to its path's offset at the frame's
    time (``t`` from 0 to the last waypoint), then relaxes ``relax_steps`` times (drag groups and
    fixed elements held). :meth:`run` writes ``trajectory.npz``, ``summary.json`` and ``energy.png``.
    """
    grid: Grid
    limits: Limits
    method: str = "gibson"
    fixed: torch.Tensor | None = None
    drags: list = field(default_factory=list)
    frames: int = 20
    relax_steps: int = 0
    relax_mode: str = "centroid"
    relax_moved_only: bool = False
    on_blocked: str = "scale"
    name: str = "chainmail"
    source: object = None

    def run(self, out_dir, progress: bool = True, device=None) -> dict:
        """Run the scene; returns the summary (also written to ``summary.json``). ``device`` is
        not used (the sequential ChainMail runs on the CPU)."""
        import json
        import time as _time
        from pathlib import Path
        out = Path(out_dir)
        cm = ChainMail(self.grid, self.limits, fixed=self.fixed, method=self.method)
        end = max((float(d.path[-1][0]) for d in self.drags), default=0.0)
        times = np.linspace(0.0, end, self.frames + 1)
        hold = torch.zeros(self.grid.shape, dtype=torch.bool)
        groups = []
        for d in self.drags:
            m = torch.as_tensor(d.nodes, dtype=torch.bool)
            hold |= m
            idx = [tuple(int(v) for v in r) for r in m.nonzero()]
            groups.append((d, idx))
        X = self.grid.rest_positions(torch.float64)
        frames = [X[0].float().numpy()]
        energy, violation, moved, fraction = [0.0], [0.0], [0], [1.0]
        from tqdm.auto import tqdm
        start = _time.perf_counter()
        for t in tqdm(times[1:], desc=self.name, unit="frame", disable=not progress, leave=False):
            n_moved, frac = 0, 1.0
            for d, idx in groups:
                target = np.asarray(d.offset(float(t)), dtype=np.float64)
                current = cm.displacement(torch.float64)[0][(slice(None),) + idx[0]].numpy()
                delta = target - current
                if np.any(delta != 0):
                    r = cm.move(idx, delta, on_blocked=self.on_blocked)
                    n_moved, frac = n_moved + r.moved, min(frac, r.fraction)
            if self.relax_steps:
                cm.relax(self.relax_steps, self.relax_mode, self.relax_moved_only, hold=hold)
            x = cm.positions()
            frames.append(x[0].float().numpy())
            energy.append(float(relax_energy(x, self.grid, self.limits, self.relax_mode)[0]))
            violation.append(float(limit_violation(x, self.grid, self.limits)[0]))
            moved.append(n_moved)
            fraction.append(frac)
        wall = _time.perf_counter() - start
        x = np.stack(frames)
        disp = np.linalg.norm(x - X[0].float().numpy()[None], axis=1).reshape(len(x), -1).max(1)
        g = self.grid
        np.savez(out / "trajectory.npz", t=times, x=x, X=X[0].float().numpy(), node_mask=g.nodes().numpy(),
                 shape=np.array(g.shape), spacing=np.array(g.spacing), origin=np.array(g.origin),
                 model="chainmail", method=self.method, energy=np.array(energy), max_displacement=disp,
                 max_violation=np.array(violation), moved=np.array(moved), fraction=np.array(fraction))
        dt = float(times[1] - times[0]) if len(times) > 1 else 0.0
        summary = {
            "name": self.name, "scene": getattr(self.source, "path", None), "model": "chainmail",
            "integrator": {"name": f"chainmail-{self.method}", "relax_steps": self.relax_steps,
                           "relax_mode": self.relax_mode},
            "steps": self.frames, "dt_s": dt, "dt_auto": False, "simulated_time_s": float(times[-1]),
            "time_step_bound_s": None, "stability_bound_method": "none: ChainMail is geometric",
            "wall_time_s": wall, "steps_per_s": self.frames / wall if wall > 0 else None,
            "nodes": g.num_nodes, "grid": {"shape": list(g.shape), "spacing": list(g.spacing),
                                           "origin": list(g.origin), "topology": 6},
            "frames": len(times), "max_displacement_m": float(disp[-1]), "peak_displacement_m": float(disp.max()),
            "max_violation_m": float(max(violation)), "blocked_frames": int(sum(f < 1.0 for f in fraction)),
            "final_relax_energy_m2": energy[-1],
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        _plot_scene(out / "energy.png", times, energy, disp, f"{self.name}: ChainMail ({self.method})")
        return summary


def _plot_scene(path, t, energy, disp, title):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7, 5), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(t, energy, marker=".")
    top.set_ylabel("relaxation energy (m^2)")
    top.set_title(title)
    top.grid(alpha=0.3)
    bottom.plot(t, np.asarray(disp) * 1e3, color="k", marker=".")
    bottom.set_ylabel("max displacement (mm)")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    fig.savefig(path, dpi=100)


def chainmail_scene(src, data: dict, base, name: str = "chainmail") -> ChainMailScene:
    """Build a :class:`ChainMailScene` from a parsed scene file with ``model = "chainmail"``
    (called by :func:`torchdeform.scene.load_scene`).

    ``[chainmail]`` keys: ``method`` (``"gibson"`` default, or ``"enhanced"``); the limits as
    ratios of the spacing ``compression`` (0.9), ``stretch`` (1.1), ``shear`` (0.1), or
    ``tissue`` (a name of the fuzzy tissue library or a consistency 0..10) with
    ``reference_stress`` (Pa, 300); ``frames`` (20); ``relax_steps`` (0), ``relax_mode``
    (``"centroid"`` or ``"goal"``), ``relax_moved_only`` (false); ``on_blocked`` (``"scale"``
    or ``"error"``). ``[grid]`` as for mass-spring scenes (the topology is ignored: ChainMail
    links face neighbours); ``[boundary]`` ``fixed`` and ``fixed_nodes``; ``[[drags]]`` the
    picked groups and their paths; ``[output]`` ``name``.
    """
    from . import scene as sc
    unused = [k for k in data if k not in ("model", "grid", "chainmail", "boundary", "drags", "output")]
    if unused:
        raise src.error(unused[0], 'no such section in a scene with model = "chainmail"', unused[0])
    grid = sc._grid(sc._Table(src, "grid", data["grid"], sc.SECTIONS["grid"]), base)
    t = sc._Table(src, "chainmail", data["chainmail"], sc.SECTIONS["chainmail"])
    method = t.text("method", '"gibson" or "enhanced"', "gibson", METHODS)
    if t.has("tissue"):
        for k in ("compression", "stretch", "shear"):
            t.only_with(k, "tissue")
        tissue = t.raw("tissue", "a tissue name or a consistency value in [0, 10]")
        with src.located(t.key("tissue")):
            limits = tissue_limits(grid, tissue, reference_stress=t.num(
                "reference_stress", "a positive stress in Pa", 300.0, lo=0, lo_open=True))
    else:
        t.only_with("reference_stress", "compression")
        comp = t.num("compression", "a ratio in (0, 1] (minimum distance / spacing)", 0.9, lo=0, hi=1, lo_open=True)
        stretch = t.num("stretch", "a ratio >= 1 (maximum distance / spacing)", 1.1, lo=1)
        shear = t.num("shear", "a ratio >= 0 (shear limit / spacing)", 0.1, lo=0)
        with src.located(t.name):
            limits = Limits.from_material(grid, comp, stretch, shear)
    fixed = None
    if "boundary" in data:
        b = sc._Table(src, "boundary", data["boundary"], ("fixed", "fixed_nodes"))
        if b.has("fixed"):
            fixed = sc._faces(b, "fixed", grid)
        if b.has("fixed_nodes"):
            nodes = sc._node_list(b, "fixed_nodes", grid)
            fixed = nodes if fixed is None else fixed | nodes
    drags = sc._drags(src, data["drags"], grid) if "drags" in data else []
    out = sc._Table(src, "output", data.get("output", {}), ("name",))
    scene = ChainMailScene(
        grid, limits, method, fixed, drags,
        frames=t.integer("frames", "an integer >= 1 (moves along the drag paths)", 20, lo=1),
        relax_steps=t.integer("relax_steps", "an integer >= 0", 0),
        relax_mode=t.text("relax_mode", '"centroid" or "goal"', "centroid", RELAX_MODES),
        relax_moved_only=bool(t.raw("relax_moved_only", "true or false", False)),
        on_blocked=t.text("on_blocked", '"scale" or "error"', "scale", ("scale", "error")),
        name=out.text("name", "a string", name), source=src)
    if fixed is not None:
        for n, d in enumerate(drags):
            if bool((torch.as_tensor(d.nodes, dtype=torch.bool) & fixed).any()):
                raise src.error(f"drags[{n}].nodes", "free elements (a dragged element is fixed)")
    with src.located(t.name):
        ChainMail(grid, limits, fixed=fixed, method=method)           # checks method, node mask, rest state
    return scene


__all__ = ["Limits", "ChainMail", "MoveResult", "BlockedMoveError", "tissue_limits", "limit_violation",
           "tensor_chainmail", "SweepResult", "neighbour_boxes", "relax", "relax_energy", "crease_measure",
           "ChainMailScene", "chainmail_scene", "DIRECTIONS", "GIBSON_SUCCESSORS"]
