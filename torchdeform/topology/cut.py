"""Cutting with a blade: every spring whose segment crosses the blade's surface is removed.

**Blades.** A :class:`Blade` is a surface made of flat patches, each the points
``o + a u + b v`` with ``a, b >= 0`` and either ``a, b <= 1`` (a parallelogram, Punak's rectangular
blade) or ``a + b <= 1`` (a triangle). ``Blade(o, u, v)`` is one parallelogram,
:meth:`Blade.triangle` one triangle, :meth:`Blade.swept` the ruled surface a straight cutting edge
sweeps through a sequence of poses (two triangles per interval: curved when the edge turns), and
:class:`Scalpel` takes those poses from a :class:`~torchdeform.interact.tools.Tool`, so that a
blade moving over many steps cuts as it goes (:meth:`Scalpel.update`).

**Crossing.** A spring from ``p`` to ``q`` crosses a patch when its ends lie on opposite sides of
the patch's plane (a node exactly on the plane counts as the side the normal ``u x v`` points
away from, so a plane through a layer of nodes cuts one set of springs, never two) and the point
where the segment meets the plane lies within the patch (closed, to a relative ``16 eps``, so a
spring through the edge shared by two triangles is caught by one of them at least).

**Search.** Only springs near the blade are tested: per plane the nodes' heights ``h = n . x - c``
(one matrix-vector product), the range of layers along the axis closest to the normal that holds
nodes of both signs within one layer of each other, and, in that range, the springs whose ends'
heights differ in sign; only those get the in-patch test. The search returns the crossed slots as
indices; :func:`cut` zeroes them in place on an editable model (see :mod:`.masks`), so a full
cut of a ``64^3`` body costs well under a millisecond and a compiled step that shares the model's
fields runs on without recompiling. On an accelerator, where every value read back makes the host
wait for the device, the search is dense instead: every slot gets both tests at once, the same
slots are found, and a cut counted as a tensor (``as_tensor=True``) reads nothing back.

**Gaping** (pre-tension, Radetzky): with ``gape > 0`` the springs left at the nodes of the cut
(the ends of the springs it removed) get their rest lengths multiplied by ``1 - gape``; they
contract, and the cut opens. :func:`pretension` is the same as a function of the rest lengths
(differentiable: the gape can be learned).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((2, 1, 1), spacing=1.0, topology=6)        # one spring along D
    >>> blade = Blade((0.5, -1.0, -1.0), (0.0, 2.0, 0.0), (0.0, 0.0, 2.0))
    >>> crossing(grid, grid.rest_positions(dtype=torch.float64), blade)[0, 0].flatten().tolist()   # along D, stored at node 0
    [True, False]
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from ..sim.forces import as_vec3
from ..sim.model import Model
from .masks import Slab, _union, alive, assign, ends, full, remove, slot_index

__all__ = ["Blade", "Scalpel", "crossing", "crossed_pieces", "crossed_slots", "cut", "sides", "pretension"]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return sum(p * q for p, q in zip(a, b))


class Blade:
    """A blade surface: flat patches ``o + a u + b v`` (parallelograms and triangles).

    ``Blade(origin, u, v)`` is one parallelogram (a rectangle when ``u`` and ``v`` are at right
    angles). See the module docstring for the other forms.

    Args:
        origin: a corner ``(3,)`` m.
        u: one edge ``(3,)`` m.
        v: the other edge ``(3,)`` m, not parallel to ``u``.

    Attributes:
        patches: list of ``(origin, u, v, triangle)`` (3-tuples of floats, bool).
        normal: the unit normal ``u x v / |u x v|`` of the first patch.

    Examples:
        >>> Blade((0, 0, 0), (1, 0, 0), (0, 2, 0)).normal
        (0.0, 0.0, 1.0)
        >>> swept = Blade.swept([[(0, 0, 0), (0, 0, 1)], [(1, 0, 0), (1, 0, 1)], [(2, 0, 0), (2, 1, 1)]])
        >>> [tri for *_, tri in swept.patches]       # a translation, then a turn: two triangles
        [False, True, True]
    """

    def __init__(self, origin, u, v, *, triangle: bool = False, key: str = "blade"):
        self.patches = []
        self._add(origin, u, v, triangle, key)

    def _add(self, origin, u, v, triangle, key):
        o, u, v = as_vec3(origin, f"{key}.origin"), as_vec3(u, f"{key}.u"), as_vec3(v, f"{key}.v")
        n = _cross(u, v)
        area, scale = _dot(n, n) ** 0.5, (_dot(u, u) * _dot(v, v)) ** 0.5
        if not area > 1e-12 * scale or scale == 0:
            what = "three corners not on one line" if triangle else "two non-zero edges u and v, not parallel"
            raise ConfigError(key, f"a non-degenerate {'triangle' if triangle else 'blade'}: {what}", got=(o, u, v))
        self.patches.append((o, u, v, bool(triangle)))
        if len(self.patches) == 1:
            self.normal = tuple(c / area for c in n)

    @classmethod
    def triangle(cls, a, b, c, *, key: str = "blade") -> Blade:
        """The triangle with corners ``a``, ``b``, ``c`` ``(3,)`` m."""
        a, b, c = (as_vec3(p, f"{key}.corner") for p in (a, b, c))
        return cls(a, [q - p for p, q in zip(a, b)], [q - p for p, q in zip(a, c)], triangle=True, key=key)

    @classmethod
    def swept(cls, edges, *, key: str = "blade") -> Blade:
        """The surface a straight cutting edge sweeps through ``K >= 2`` poses.

        Args:
            edges: the edge's two ends at each pose, ``(K, 2, 3)`` m (nested lists or a tensor).
                Between poses ``k`` and ``k + 1`` the quadrilateral of the four ends becomes two
                triangles (a planar parallelogram stays one patch).
            key: the name in error messages.
        """
        e = torch.as_tensor(edges, dtype=torch.float64)
        if e.dim() != 3 or e.shape[1:] != (2, 3) or e.shape[0] < 2:
            raise ConfigError(key, "the edge's ends at two or more poses, shape (K, 2, 3)", got=tuple(e.shape))
        blade = None
        for k in range(e.shape[0] - 1):
            a0, b0, a1, b1 = (tuple(float(c) for c in p) for p in (e[k, 0], e[k, 1], e[k + 1, 0], e[k + 1, 1]))
            u, v, w = [q - p for p, q in zip(a0, b0)], [q - p for p, q in zip(a0, a1)], [q - p for p, q in zip(b0, b1)]
            if _dot(_cross(u, v), _cross(u, v)) == 0:  # the edge moved along itself: nothing swept
                continue
            if all(abs(p - q) <= 1e-12 * (1 + abs(p)) for p, q in zip(v, w)):  # a translation: one parallelogram
                parts = [(a0, u, v, False)]
            else:
                parts = [(a0, u, [q - p for p, q in zip(a0, b1)], True), (a0, [q - p for p, q in zip(a0, b1)], v, True)]
            for o, p, q, tri in parts:
                if blade is None:
                    blade = cls(o, p, q, triangle=tri, key=key)
                else:
                    blade._add(o, p, q, tri, key)
        if blade is None:
            raise ConfigError(key, "an edge that sweeps a surface (it only moved along itself)", got=tuple(e.shape))
        return blade

    # --------------------------------------------------------------- geometry
    def _vec(self, value, like):
        return like.new_tensor(value).view(1, 3, *[1] * (like.dim() - 2))

    def height(self, x: torch.Tensor) -> torch.Tensor:
        """Signed distance ``(B, 1, ...)`` of points ``x`` ``(B, 3, ...)`` from the first patch's plane."""
        o = self.patches[0][0]
        return ((x - self._vec(o, x)) * self._vec(self.normal, x)).sum(1, keepdim=True)

    def bounds(self) -> tuple[tuple, tuple]:
        """The axis-aligned box ``(low, high)`` of the blade (m)."""
        pts = []
        for o, u, v, tri in self.patches:
            pts += [o, tuple(a + b for a, b in zip(o, u)), tuple(a + b for a, b in zip(o, v))]
            if not tri:
                pts.append(tuple(a + b + c for a, b, c in zip(o, u, v)))
        return tuple(min(p[i] for p in pts) for i in range(3)), tuple(max(p[i] for p in pts) for i in range(3))

    def planes(self) -> list:
        """The patches grouped by plane: ``[(normal, offset, [patch, ...]), ...]`` (computed once)."""
        if getattr(self, "_planes", None) is not None and self._planes[0] == len(self.patches):
            return self._planes[1]
        groups = {}
        for o, u, v, tri in self.patches:
            n = _cross(u, v)
            s = _dot(n, n) ** 0.5
            n = tuple(c / s for c in n)
            key = tuple(round(c, 12) for c in n) + (round(_dot(n, o), 12),)
            groups.setdefault(key, (n, _dot(n, o), []))[2].append((o, u, v, tri))
        self._planes = (len(self.patches), list(groups.values()))
        return self._planes[1]


def _patch_coordinates(point, patch) -> tuple:
    """``(a, b)`` of a point in a patch's frame ``o + a u + b v`` (normal part ignored).

    ``point``: three components, floats or tensors of any shape (``r`` ``(3, ...)`` works as is).
    """
    o, u, v, _ = patch
    uu, uv, vv = _dot(u, u), _dot(u, v), _dot(v, v)
    det = uu * vv - uv * uv
    d = [point[i] - o[i] for i in range(3)]
    du, dv = _dot(d, u), _dot(d, v)
    return (vv * du - uv * dv) / det, (uu * dv - uv * du) / det


def _inside(a, b, triangle: bool, tol: float):
    """Coordinates within the patch, widened by ``tol`` (narrowed when negative); floats or tensors."""
    return (a >= -tol) & (b >= -tol) & ((a + b <= 1 + tol) if triangle else ((a <= 1 + tol) & (b <= 1 + tol)))


def _covers(box, patches) -> bool:
    """One of the patches holds the projection of the box ``[low (3,), high (3,)]`` onto their plane.

    The patch coordinates are linear in the point, so testing the 8 corners suffices (plain floats:
    a handful of numbers, no tensor calls), strictly inside by a margin of 1e-12.
    """
    corners = [
        (x, y, z) for x in (box[0][0], box[1][0]) for y in (box[0][1], box[1][1]) for z in (box[0][2], box[1][2])
    ]
    return any(all(_inside(*_patch_coordinates(c, patch), patch[3], -1e-12) for c in corners) for patch in patches)


def _patch_hits(r: torch.Tensor, patches) -> torch.Tensor:
    """Bool ``(E,)``: points ``r`` ``(3, E)`` on the patches' common plane lie within one of them."""
    tol = 16 * torch.finfo(r.dtype).eps
    hit = None
    for patch in patches:
        inside = _inside(*_patch_coordinates(r, patch), patch[3], tol)
        hit = inside if hit is None else hit | inside
    return hit


def _layer_range(top: list, bottom: list, steps: set):
    """Layers that may hold the first end of a spring crossing a plane, from per-layer height bounds.

    ``top``, ``bottom``: the largest and smallest height in each layer (lists: a few dozen numbers,
    plain Python is faster than tensor calls); ``steps``: the layer steps (-1, 0, +1) of the
    half-directions along this axis (a spring is stored at its first end, so along D, where every
    half-direction steps 0 or +1, only the layer below a crossing holds it). Returns ``(lo, hi)``
    or None.
    """
    pos, neg = [t > 0 for t in top], [b <= 0 for b in bottom]
    n = len(pos)
    found = [
        k
        for k in range(n)
        if (pos[k] and neg[k])
        or (1 in steps and k + 1 < n and ((pos[k] and neg[k + 1]) or (neg[k] and pos[k + 1])))
        or (-1 in steps and k > 0 and ((pos[k] and neg[k - 1]) or (neg[k] and pos[k - 1])))
    ]
    return (found[0], found[-1]) if found else None


def _direction_index(grid, device) -> tuple:
    """``(dd + 1, dh + 1, dw + 1)`` of the ``S`` half-directions, three ``(S,)`` index tensors."""
    key = ("direction_index", str(device))
    if key not in grid._cache:
        grid._cache[key] = tuple(torch.tensor([d[a] + 1 for d in grid.directions], device=device) for a in range(3))
    return grid._cache[key]


def _steps(grid, axis: int) -> set:
    """The layer steps ``{-1, 0, 1}`` of the grid's half-directions along ``axis``."""
    key = ("layer_steps", axis)
    if key not in grid._cache:
        grid._cache[key] = {d[axis] for d in grid.directions}
    return grid._cache[key]


def _far_ends(sub: torch.Tensor, axis: int, before: int, after: int, index: tuple) -> tuple:
    """Which side of the plane the nodes of a slab and the far ends of their springs lie on.

    ``sub``: heights of the slab's layers plus ``before`` (0 or 1) layers before and ``after``
    after it; returns bool ``(near (n0, n1, n2), far (S, n0, n1, n2))`` (height > 0); far ends
    outside the grid read False (their springs do not exist). One padded copy of the layers and
    one strided gather of bytes.
    """
    pad = [1, 1, 1, 1, 1, 1]
    pad[2 * (2 - axis)], pad[2 * (2 - axis) + 1] = 1 - before, 1 - after
    up = torch.nn.functional.pad(sub[None], pad)[0] > 0  # (n0+2, n1+2, n2+2)
    box = tuple(m - 2 for m in up.shape)
    st = up.stride()
    cube = up.as_strided((3, 3, 3) + box, st + st)
    return up[1:-1, 1:-1, 1:-1], cube[index[0], index[1], index[2]]


def _heights(x: torch.Tensor, n, c):
    """``h = n . x - c`` of positions ``(3, ...)``; a signed view for an axis-aligned ``n``."""
    axis = max(range(3), key=lambda a: abs(n[a]))
    if abs(n[axis]) == 1.0:
        return x[axis] - c if n[axis] > 0 else -x[axis] - c
    return n[0] * x[0] + n[1] * x[1] + n[2] * x[2] - c


def _dense_pieces(grid, x: torch.Tensor, blade: Blade) -> list:
    """:func:`crossed_pieces` without the layer search: every slot tested, one piece per batch entry.

    The same slots, found with no value read back to the host (no layer bounds, no index lists):
    the form for an accelerator, where each read waits for the device.
    """
    D, H, W = grid.shape
    exists = grid.spring_mask(device=x.device)  # (S, D, H, W)
    index = _direction_index(grid, x.device)
    out = []
    for b in range(x.shape[0]):
        xb = x[b]
        # the far end of every slot: the positions padded by one node all round, one strided gather
        # (far ends outside the grid read zeros; their springs do not exist)
        pad = torch.nn.functional.pad(xb, (1, 1, 1, 1, 1, 1))  # (3, D+2, H+2, W+2)
        st = pad.stride()
        cube = pad.as_strided((3, 3, 3, 3, D, H, W), st + st[1:])
        q = cube[:, index[0], index[1], index[2]]  # (3, S, D, H, W)
        p = xb.unsqueeze(1)  # (3, 1, D, H, W)
        hit = torch.zeros_like(exists)
        for n, c, patches in blade.planes():
            hp, hq = _heights(p, n, c), _heights(q, n, c)  # (1, D, H, W), (S, D, H, W)
            across = ((hp > 0) != (hq > 0)) & exists
            # where the segment meets the plane (hp != hq on every slot across it)
            r = p + (hp / torch.where(across, hp - hq, torch.ones_like(hq))) * (q - p)
            hit = hit | (across & _patch_hits(r, patches))
        out.append(Slab(b, 0, 0, hit))
    return out


def crossed_pieces(grid, x: torch.Tensor, blade: Blade, *, dense: bool | None = None) -> list:
    """The slots whose springs cross ``blade``, as :class:`~torchdeform.topology.masks.Slab` masks.

    Each piece covers the layers of one plane's search (see the module docstring); a slot that
    crosses two planes of the blade may appear in two pieces. Only springs the grid has are
    reported.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        x: node positions ``(B, 3, D, H, W)`` (rest or deformed: the cut follows the tissue).
        blade: the :class:`Blade`.
        dense: test every slot, one piece ``(S, D, H, W)`` per batch entry, with no value read
            back to the host (the same slots); None: dense on an accelerator, the layer search
            on the CPU.
    """
    if dense is None:
        dense = x.device.type != "cpu"
    if dense:
        return _dense_pieces(grid, x, blade)
    D, H, W = grid.shape
    N, dev = D * H * W, x.device
    exists = grid.spring_mask(device=dev)
    index = _direction_index(grid, dev)
    offs = ((index[0] - 1) * H + index[1] - 1) * W + index[2] - 1  # (S,) flat offsets
    out = []
    for b in range(x.shape[0]):
        xb = x[b]
        for n, c, patches in blade.planes():
            axis = max(range(3), key=lambda a: abs(n[a]))
            other = tuple(a for a in range(3) if a != axis)
            if abs(n[axis]) == 1.0:  # axis-aligned: the layer bounds from x itself
                top, bottom = torch.stack([xb[axis].amax(other), xb[axis].amin(other)]).tolist()
                if n[axis] > 0:
                    top, bottom = [t - c for t in top], [b - c for b in bottom]
                else:
                    top, bottom = [-b - c for b in bottom], [-t - c for t in top]
            else:
                h = _heights(xb, n, c)
                top, bottom = torch.stack([h.amax(other), h.amin(other)]).tolist()
            steps = _steps(grid, axis)
            rng = _layer_range(top, bottom, steps)
            if rng is None:
                continue
            lo, hi = rng
            lo2, hi2 = max(lo - (-1 in steps), 0), min(hi + (1 in steps), grid.shape[axis] - 1)
            slab = xb.narrow(axis + 1, lo2, hi2 - lo2 + 1)  # (3, ...) layers lo-1..hi+1
            near, far = _far_ends(_heights(slab, n, c), axis, lo - lo2, hi2 - hi, index)
            mask = (near.unsqueeze(0) != far) & exists.narrow(axis + 1, lo, hi - lo + 1)
            # The slab's positions bound every candidate segment: when a patch covers that box,
            # every candidate crosses it and none needs its own test.
            flat = slab.reshape(3, -1)
            box = torch.stack([flat.amin(1), flat.amax(1)]).tolist()
            if not _covers(box, patches):
                slot = list(mask.nonzero(as_tuple=True))  # s, then the layers
                slot[axis + 1] = slot[axis + 1] + lo
                p_i = (slot[1] * H + slot[2]) * W + slot[3]
                q_i = p_i + offs[slot[0]]
                xf = xb.reshape(3, N)
                p, q = xf.index_select(1, p_i), xf.index_select(1, q_i)
                hp, hq = _heights(p, n, c), _heights(q, n, c)
                mask = torch.zeros_like(mask)
                slot[axis + 1] = slot[axis + 1] - lo
                mask[tuple(slot)] = _patch_hits(p + (hp / (hp - hq)) * (q - p), patches)
            out.append(Slab(b, axis, lo, mask))
    return out


def crossed_slots(grid, x: torch.Tensor, blade: Blade, *, dense: bool | None = None) -> tuple:
    """The slots whose springs cross ``blade``, as index tensors ``(b, s, d, h, w)`` (each slot once).

    The index form of :func:`crossed_pieces` (arguments as there).
    """
    return slot_index(grid, crossing(grid, x, blade, dense=dense))


def crossing(grid, x: torch.Tensor, blade: Blade, *, dense: bool | None = None) -> torch.Tensor:
    """Bool ``(B, S, D, H, W)``: the spring stored at each node along each half-direction crosses the blade.

    The dense form of :func:`crossed_pieces` (arguments as there).
    """
    out = torch.zeros((x.shape[0], grid.S) + grid.shape, dtype=torch.bool, device=x.device)
    for piece in crossed_pieces(grid, x, blade, dense=dense):
        piece.view(out).logical_or_(piece.mask)
    return out


def sides(x: torch.Tensor, blade: Blade) -> torch.Tensor:
    """Int8 ``(B, 1, D, H, W)``: +1 on the normal's side of the first patch's plane, -1 on the other (Punak's tags)."""
    return (blade.height(x) > 0).to(torch.int8) * 2 - 1


def pretension(model: Model, nodes: torch.Tensor, gape, *, springs: torch.Tensor | None = None) -> torch.Tensor:
    """Rest lengths ``(Bp, S, D, H, W)`` with the springs at ``nodes`` shortened by the factor ``1 - gape``.

    A function of the model's rest lengths and ``gape`` (differentiable in both), the model is not
    changed.

    Args:
        model: the model.
        nodes: bool ``(D, H, W)`` (on any device): the springs (still alive) with an end here are shortened.
        gape: a number or 0-d tensor in ``[0, 1)``.
        springs: optional bool ``(1, S, D, H, W)`` restricting which of them (default: all).
    """
    if not torch.is_tensor(gape) and not 0 <= float(gape) < 1:
        raise ConfigError("cut.gape", "a fraction in [0, 1) of the rest length", got=gape)
    dev = model.rest_length.device
    at_src, at_dst = ends(model.grid, torch.as_tensor(nodes, dtype=torch.bool, device=dev))
    touch = (at_src | at_dst) & alive(model)
    if springs is not None:
        touch = touch & springs.to(dev)
    l0 = full(model, model.rest_length)
    return torch.where(touch, l0 * (1 - gape), l0)


def cut(
    model: Model, x: torch.Tensor, blade: Blade, *, gape: float = 0.0, as_tensor: bool = False
) -> int | torch.Tensor:
    """Remove the springs that cross ``blade`` from ``model`` (in place); returns how many.

    On an accelerator the search is dense (:func:`crossed_pieces`) and, with ``as_tensor``, the
    whole cut is queued on the device: the host reads nothing back and does not wait for it.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` (its ``stiffness`` and ``damping`` change;
            in place when it is editable or shared with a compiled step, see :mod:`.masks`; an
            Elastic body's crossed cells die, see :func:`~torchdeform.topology.masks.remove`).
        x: node positions ``(B, 3, D, H, W)``; a batch of positions gives one cut per batch entry.
        blade: the :class:`Blade`.
        gape: pre-tension: the springs left at the nodes of the cut get their rest lengths
            multiplied by ``1 - gape`` (once: nodes of earlier cuts are not shortened again;
            ``model.cut_nodes`` collects them).
        as_tensor: return the count as a 0-d int64 tensor on the model's device (not an int).

    Examples:
        >>> import torchdeform as td
        >>> model = td.Model(td.Grid((3, 3, 3), spacing=0.01, topology=6), stiffness=10.0, mass=1e-3)
        >>> cut(model, model.X, Blade((0.005, -0.01, -0.01), (0, 0.04, 0), (0, 0, 0.04)))     # n^2
        9
    """
    pieces = crossed_pieces(model.grid, x, blade)
    count = remove(model, pieces, as_tensor=as_tensor)
    if gape or torch.is_tensor(gape):
        grid = model.grid
        hit = _union(grid, pieces, x.device).any(0)  # (S, D, H, W): the slots the blade crossed
        nodes = hit.any(0)  # their first ends
        for s, (src, dst) in enumerate(grid.stencil):  # and their far ends
            nodes[dst] |= hit[(s, *src)]
        old = model.cut_nodes
        fresh = nodes if old is None else nodes & ~old
        springs = None
        if old is not None:  # a spring shortened once only
            a, b = ends(grid, old)
            springs = ~(a | b)
        assign(model, "rest_length", pretension(model, fresh, gape, springs=springs))
        model.cut_nodes = nodes if old is None else old | nodes
    return count


class Scalpel:
    """A blade's straight cutting edge carried by a tool: it cuts what it sweeps (progressive cutting).

    Args:
        tool: the :class:`~torchdeform.interact.tools.Tool` (its path, callable or ``move_to``).
        edge: the edge's two ends in the tool's frame, ``((3,), (3,))`` m.
        pieces: triangles per update along the sweep (more follow a turning edge more closely).
        gape: pre-tension of every cut (see :func:`cut`).

    Examples:
        >>> import torchdeform as td
        >>> from torchdeform.interact import Sphere, Tool
        >>> model = td.Model(td.Grid((4, 4, 4), spacing=0.01, topology=6), stiffness=10.0, mass=1e-3)
        >>> tool = Tool(Sphere(0.001), path=[(0.0, (0.015, -0.01, -0.01)), (1.0, (0.015, 0.05, -0.01))])
        >>> knife = Scalpel(tool, edge=((0, 0, 0), (0, 0, 0.05)))
        >>> state = model.rest_state()
        >>> knife.update(model, state)                   # the first call only marks where it starts
        0
        >>> state.t = 0.5                                # the edge has swept y <= 0.02: 3 of 4 columns
        >>> knife.update(model, state)
        12
    """

    def __init__(self, tool, edge, *, pieces: int = 1, gape: float = 0.0):
        self.tool = tool
        self.edge = (as_vec3(edge[0], "scalpel.edge"), as_vec3(edge[1], "scalpel.edge"))
        if self.edge[0] == self.edge[1]:
            raise ConfigError("scalpel.edge", "two different ends", got=self.edge)
        if int(pieces) < 1:
            raise ConfigError("scalpel.pieces", "an integer >= 1", got=pieces)
        self.pieces, self.gape = int(pieces), gape
        self._last = None

    def edge_at(self, t: float) -> torch.Tensor:
        """The edge's two ends at time ``t``, ``(2, 3)`` float64 (batch entry 0 of the tool's pose)."""
        like = torch.zeros(1, 3, dtype=torch.float64)
        c, R = self.tool.frame(t, like)
        e = torch.tensor(self.edge, dtype=torch.float64)  # (2, 3)
        if R is not None:
            e = e @ R[0].T
        return e + c.reshape(-1, 3)[0]

    def swept(self, t0: float, t1: float) -> Blade | None:
        """The surface the edge sweeps from ``t0`` to ``t1`` (None if it did not move)."""
        ts = [t0 + (t1 - t0) * i / self.pieces for i in range(self.pieces + 1)]
        edges = torch.stack([self.edge_at(t) for t in ts])
        if bool((edges[1:] == edges[:-1]).all()):
            return None
        try:
            return Blade.swept(edges, key="scalpel")
        except ConfigError:  # moved only along its own line
            return None

    def update(self, model: Model, state, *, as_tensor: bool = False) -> int | torch.Tensor:
        """Cut what the edge swept since the previous call (at the state's positions and time).

        The blade is built on the host from the tool's pose (``state.t`` a float, or a 0-d tensor
        read once); with ``as_tensor`` the count comes back as a 0-d int64 tensor on the model's
        device and, on an accelerator, the cut is queued without waiting for the device (see :func:`cut`).
        """
        t = float(state.t)
        if self._last is None or t == self._last:
            self._last = t
            blade = None
        else:
            blade, self._last = self.swept(self._last, t), t
        if blade is not None:
            return cut(model, state.x, blade, gape=self.gape, as_tensor=as_tensor)
        return torch.zeros((), dtype=torch.int64, device=state.x.device) if as_tensor else 0
