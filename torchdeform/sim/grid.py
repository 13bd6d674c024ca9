"""Regular 3-D grids of nodes and their spring stencils.

A grid has ``D x H x W`` nodes with spacing ``(sd, sh, sw)`` metres along the axes
``(D, H, W)``. Springs join a node to neighbours along *half-directions*: each unordered
neighbour direction is stored once, with a first non-zero component of ``+1``, so every
spring is stored exactly once, at its first endpoint.

========  =================================  ======
topology  half-directions                    S
========  =================================  ======
6         3 axes                             3
14        3 axes + 4 body diagonals          7
18        3 axes + 6 face diagonals          9
26        axes + face + body diagonals       13
========  =================================  ======

Per-spring tensors have shape ``(S, D, H, W)``; entry ``[s, i, j, k]`` is the spring from
node ``(i, j, k)`` to node ``(i, j, k) + direction[s]``.
"""

from __future__ import annotations

import math
from dataclasses import KW_ONLY, dataclass, field
from functools import cached_property

import torch

from ..errors import ConfigError

__all__ = ["Grid", "AXES", "FACE_DIAGONALS", "BODY_DIAGONALS", "TOPOLOGIES", "CLASSES", "FACES"]

AXES = ((1, 0, 0), (0, 1, 0), (0, 0, 1))
FACE_DIAGONALS = ((1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1))
BODY_DIAGONALS = ((1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1))
TOPOLOGIES = {
    6: AXES,
    14: AXES + BODY_DIAGONALS,
    18: AXES + FACE_DIAGONALS,
    26: AXES + FACE_DIAGONALS + BODY_DIAGONALS,
}
#: Direction classes, for stiffness "per direction class".
CLASSES = ("axis", "face", "body")

FACES = {
    "d-": (0, 0),
    "d+": (0, 1),
    "h-": (1, 0),
    "h+": (1, 1),
    "w-": (2, 0),
    "w+": (2, 1),
    "bottom": (0, 0),
    "top": (0, 1),
}


def _slices(step: int, n: int) -> tuple[slice, slice]:
    """Source and destination slices along one axis for a neighbour offset ``step``."""
    if step == 1:
        return slice(0, n - 1), slice(1, n)
    if step == -1:
        return slice(1, n), slice(0, n - 1)
    return slice(0, n), slice(0, n)


def _numbers(values, kind) -> tuple | None:
    """``values`` as a tuple of ``kind`` (int or float, no bools or strings), or None."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
        return None
    try:
        out = []
        for v in values:
            if isinstance(v, (bool, str, bytes)):
                return None
            if kind is int and float(v) != int(v):
                return None
            out.append(kind(v))
        return tuple(out)
    except (TypeError, ValueError, OverflowError):
        return None


@dataclass(frozen=True, eq=False)
class Grid:
    """A regular grid of nodes with a spring topology.

    Args:
        shape: ``(D, H, W)`` node counts, each >= 1.
        spacing: node spacing in metres, one number or one per axis ``(sd, sh, sw)``.
        topology: 6, 14, 18 or 26 neighbours.
        node_mask: optional bool tensor ``(D, H, W)``; nodes outside it do not exist
            (no springs, no mass, never move), so a body need not be a box.
        origin: position of node ``(0, 0, 0)`` in metres.

    Examples:
        >>> import torchdeform as td
        >>> g = td.Grid((3, 3, 3), spacing=0.01, topology=6)
        >>> g.num_nodes, g.S, g.num_springs
        (27, 3, 54)
        >>> g.rest_positions().shape, int(g.face("top").sum())
        (torch.Size([1, 3, 3, 3, 3]), 9)
    """

    shape: tuple
    _: KW_ONLY
    spacing: tuple = (1.0, 1.0, 1.0)
    topology: int = 26
    node_mask: torch.Tensor | None = None
    origin: tuple = (0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        shape = _numbers(self.shape, int)
        if shape is None or len(shape) != 3 or min(shape) < 1:
            raise ConfigError("grid.shape", "three node counts D, H, W, each >= 1", got=self.shape)
        spacing = (self.spacing,) * 3 if isinstance(self.spacing, (int, float)) else self.spacing
        spacing = _numbers(spacing, float)
        if spacing is None or len(spacing) != 3 or not all(math.isfinite(s) and s > 0 for s in spacing):
            raise ConfigError("grid.spacing", "one positive number or three (sd, sh, sw)", got=self.spacing)
        if isinstance(self.topology, bool) or self.topology not in TOPOLOGIES:
            raise ConfigError("grid.topology", "6, 14, 18 or 26", got=self.topology)
        origin = _numbers(self.origin, float)
        if origin is None or len(origin) != 3 or not all(math.isfinite(o) for o in origin):
            raise ConfigError("grid.origin", "three finite numbers (od, oh, ow) in metres", got=self.origin)
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "spacing", spacing)
        object.__setattr__(self, "origin", origin)
        if self.node_mask is not None:
            mask = torch.as_tensor(self.node_mask, dtype=torch.bool, device="cpu")
            if tuple(mask.shape) != shape:
                raise ConfigError("grid.node_mask", f"a bool array of shape {shape}", got=tuple(mask.shape))
            if not bool(mask.any()):
                raise ConfigError(
                    "grid.node_mask", "at least one node inside the body", got="an empty mask", show_got=True
                )
            object.__setattr__(self, "node_mask", None if bool(mask.all()) else mask)

    # ----------------------------------------------------------------- stencil
    @property
    def directions(self) -> tuple:
        """The ``S`` half-directions as integer triples ``(dd, dh, dw)``."""
        return TOPOLOGIES[self.topology]

    @property
    def S(self) -> int:
        """Number of half-directions."""
        return len(self.directions)

    @property
    def num_nodes(self) -> int:
        """Number of existing nodes (those in the node mask, or all ``D H W``)."""
        return int(self.node_mask.sum()) if self.node_mask is not None else math.prod(self.shape)

    @cached_property
    def stencil(self) -> tuple:
        """Per half-direction ``(src, dst)`` index tuples over ``(D, H, W)``.

        ``x[..., *dst] - x[..., *src]`` is ``x[i + d] - x[i]`` for every spring ``i -> i + d``
        that lies inside the grid; ``src`` is where the spring is stored.
        """
        out = []
        for d in self.directions:
            pairs = [_slices(step, n) for step, n in zip(d, self.shape)]
            out.append((tuple(p[0] for p in pairs), tuple(p[1] for p in pairs)))
        return tuple(out)

    def direction_class(self) -> list[str]:
        """Class (``"axis"``, ``"face"`` or ``"body"``) of each half-direction."""
        return [CLASSES[sum(abs(c) for c in d) - 1] for d in self.directions]

    def rest_lengths(self, *, dtype=torch.float32, device=None) -> torch.Tensor:
        """Rest length of each half-direction, ``(S,)``: ``|(dd*sd, dh*sh, dw*sw)|``."""
        d = torch.tensor(self.directions, dtype=torch.float64)
        return (d * torch.tensor(self.spacing, dtype=torch.float64)).norm(dim=1).to(dtype=dtype, device=device)

    def spring_mask(self, *, device=None) -> torch.Tensor:
        """Bool ``(S, D, H, W)``: spring exists (both ends in the grid and in the node mask)."""
        key = ("spring_mask", str(device))
        if key not in self._cache:
            mask = self.in_grid_mask()
            if self.node_mask is not None:
                mask = mask.clone()
                for s, (src, dst) in enumerate(self.stencil):
                    mask[(s, *src)] &= self.node_mask[src] & self.node_mask[dst]
            self._cache[key] = mask.to(device)
        return self._cache[key]

    def in_grid_mask(self, *, device=None) -> torch.Tensor:
        """Bool ``(S, D, H, W)``: the spring's far end lies inside the box (ignores the node mask)."""
        key = ("in_grid", str(device))
        if key not in self._cache:
            mask = torch.zeros((self.S,) + self.shape, dtype=torch.bool)
            for s, (src, _) in enumerate(self.stencil):
                mask[(s, *src)] = True
            self._cache[key] = mask.to(device)
        return self._cache[key]

    @property
    def num_springs(self) -> int:
        """Number of springs (each counted once)."""
        return int(self.spring_mask().sum())

    # ------------------------------------------------------------------ nodes
    def rest_positions(self, *, dtype=torch.float32, device=None, box=None) -> torch.Tensor:
        """Rest positions ``X``, shape ``(1, 3, D, H, W)``; channel c varies along axis c.

        ``box``: ``((d0, d1), (h0, h1), (w0, w1))`` (ends exclusive) gives only those nodes, the
        same values as slicing the whole grid's, without building it.
        """
        box = box or tuple((0, n) for n in self.shape)
        axes = [
            torch.arange(lo, hi, dtype=torch.float64) * s + o for (lo, hi), s, o in zip(box, self.spacing, self.origin)
        ]
        X = torch.stack(torch.meshgrid(*axes, indexing="ij"))
        return X.unsqueeze(0).to(dtype=dtype, device=device)

    def nodes(self) -> torch.Tensor:
        """Bool ``(D, H, W)`` of existing nodes (all True without a node mask)."""
        return self.node_mask if self.node_mask is not None else torch.ones(self.shape, dtype=torch.bool)

    def face(self, name: str) -> torch.Tensor:
        """Bool ``(D, H, W)`` mask of the nodes on a face of the box.

        ``name`` is ``"d-"``, ``"d+"``, ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``, or ``"bottom"``
        (= ``"d-"``) / ``"top"`` (= ``"d+"``): axis D is "up" in the built-in scenes. With a
        node mask, the face is the first/last existing node along that axis in each column.
        """
        if name not in FACES:
            raise ConfigError("face", "one of " + ", ".join(FACES), got=name)
        axis, side = FACES[name]
        nodes = self.nodes()
        idx = torch.arange(self.shape[axis]).view([-1 if a == axis else 1 for a in range(3)])
        idx = idx.expand(self.shape)
        big = self.shape[axis]
        if side == 0:
            first = torch.where(nodes, idx, big).amin(dim=axis, keepdim=True)
        else:
            first = torch.where(nodes, idx, -1).amax(dim=axis, keepdim=True)
        return nodes & (idx == first)

    def index_mask(self, indices) -> torch.Tensor:
        """Bool ``(D, H, W)`` mask from a list of node indices ``[(i, j, k), ...]``."""
        mask = torch.zeros(self.shape, dtype=torch.bool)
        for ijk in indices:
            ijk = tuple(int(v) for v in ijk)
            if len(ijk) != 3 or not all(0 <= v < n for v, n in zip(ijk, self.shape)):
                raise ConfigError("node index", f"three indices inside the grid {self.shape}", got=list(ijk))
            if not bool(self.nodes()[ijk]):
                raise ConfigError("node index", "a node inside the body's node mask", got=list(ijk))
            mask[ijk] = True
        return mask

    def box_mask(self, lo, hi) -> torch.Tensor:
        """Bool ``(D, H, W)`` mask of existing nodes whose rest position lies in ``[lo, hi]`` (metres)."""
        X = self.rest_positions(dtype=torch.float64)[0]
        lo = torch.tensor(lo, dtype=torch.float64).view(3, 1, 1, 1)
        hi = torch.tensor(hi, dtype=torch.float64).view(3, 1, 1, 1)
        return self.nodes() & ((lo - 1e-12 <= X) & (hi + 1e-12 >= X)).all(0)

    def every_kth(self, k: int) -> torch.Tensor:
        """Bool ``(D, H, W)``: existing nodes with ``(i + j + l) % k == 0`` (Radetzky's anchors).

        The diagonal pattern spreads the anchors evenly along all three axes.
        """
        if int(k) < 1:
            raise ConfigError("anchors.every", "an integer >= 1", got=k)
        i, j, l = torch.meshgrid(*[torch.arange(n) for n in self.shape], indexing="ij")
        return self.nodes() & ((i + j + l) % int(k) == 0)

    def missing_neighbours(self, *, device=None) -> torch.Tensor:
        """Number of the 6 face neighbours of each node that lie outside the grid, ``(D, H, W)``."""
        counts = torch.zeros(self.shape)
        for axis, n in enumerate(self.shape):
            sl: list[slice | int] = [slice(None)] * 3
            sl[axis] = 0
            counts[tuple(sl)] += 1
            sl[axis] = n - 1
            counts[tuple(sl)] += 1
        return counts.to(device)
