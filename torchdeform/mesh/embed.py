r"""Surfaces embedded in the lattice (SOFA's barycentric mapping), and smooth surfaces of label volumes.

An **embedded surface** is a fine triangle mesh (a segmented organ at image resolution, say)
carried by the coarse lattice of a body. At rest each vertex ``v`` (metres) lies in one lattice
cell, its *rest cell*, with lower corner node ``n`` and fractional position ``f = (v - o) / s - n``
in ``[0, 1]^3`` (``o`` the grid origin, ``s`` its spacing, per axis). Its 8 trilinear weights

.. math::

    w_{abc} = (a f_0 + (1 - a)(1 - f_0)) (b f_1 + (1 - b)(1 - f_1)) (c f_2 + (1 - c)(1 - f_2)),
    \quad a, b, c \in \{0, 1\}

sum to 1 and reproduce every affine map exactly, so the vertex follows the deformed lattice as

.. math:: p(v) = \sum_{abc} w_{abc} \, x_{n + (a, b, c)},

a sparse ``(V, N)`` matrix with 8 entries per row times the node positions ``(N, 3)``. The cell
is the one that contains the vertex, clipped to the grid so that a vertex at most one spacing
outside extrapolates linearly from the border cell. A vertex on a cell face, edge or corner (within
:data:`~torchdeform.mesh.surfaces.SURFACE_TOL` of a cell) may use any cell that shares it; with a
node mask the cell chosen is one whose 8 corners are all nodes of the body, and a vertex without
such a cell is an error: the body must cover the surface.

Vertex normals are recomputed every frame: the area-weighted sum of the face normals around the
vertex (the cross product ``(p_b - p_a) x (p_c - p_a)`` is twice the face's area times its unit
normal, so summing cross products weights by area), normalised; they point to the side the faces'
winding (counter-clockwise seen from outside) makes the outside. A vertex whose triangles have
zero total area (an unused vertex, a collapsed fan) gets the zero vector, never NaN.

The rest positions are the surface's texture coordinates: a solid texture is looked up at the
material point a vertex came from, so the texture moves with the tissue.

**Cuts.** :meth:`EmbeddedSurface.cut` splits the surface along a whole plane;
:meth:`EmbeddedSurface.cut_patches` along a blade of flat patches ``o + a u + b v`` (a
parallelogram, ``0 <= a, b <= 1``, or a triangle, ``a, b >= 0``, ``a + b <= 1``; the sheet of the
lattice's cut), and :meth:`EmbeddedSurface.cut_swept` along the sheet a straight edge sweeps. A
triangle whose trace on a patch's plane (the segment ``p(s) = A + s (B - A)`` where the plane meets
it) overlaps the patch is split along the overlap ``[s0, s1]``: the patch coordinates are affine in
the point, so ``s0`` and ``s1`` follow from the trace's two ends, and a point on an edge is inside
for both triangles that share the edge or for neither (no T-junction). The surface then opens
along the new edges (a copy of each vertex per fan of triangles they separate), and a vertex whose
cell has a spring the sheet cuts takes its weights from a cell of its own side's nodes.

The per-frame path is two sparse products (CSR on CPU and CUDA, deterministic, no atomics): the
``(V, N)`` weight matrix times the node positions, and the ``(V, F)`` vertex-face incidence matrix
times the face cross products. On 2 CPU cores a surface of 100k triangles (50k vertices) is
updated, positions and normals, float32, in about 2-3 ms (the numbers of the variants tried are in
``docs/guide/embedded-surfaces.md``).

:func:`label_surfaces` makes such surfaces from a label volume: marching cubes at image resolution
(scikit-image), mapped through the image's affine to metres (LPS), Taubin smoothing and quadric
decimation (trimesh, fast-simplification).

Example:
    >>> import torch, trimesh
    >>> import torchdeform as td
    >>> from torchdeform.mesh import EmbeddedSurface
    >>> grid = td.Grid((5, 5, 5), spacing=0.005, origin=(-0.01, -0.01, -0.01))
    >>> ball = trimesh.creation.icosphere(subdivisions=2, radius=0.008)
    >>> surf = EmbeddedSurface(ball.vertices, ball.faces, grid)
    >>> surf.corners.shape, surf.weights.shape
    (torch.Size([162, 8]), torch.Size([162, 8]))
    >>> x = 2.0 * grid.rest_positions()                  # (1, 3, D, H, W): the lattice scaled by 2
    >>> p, n = surf.update(x)                             # a batch in, a batch out
    >>> torch.allclose(p[0], 2.0 * surf.rest_vertices, atol=1e-6), p.shape, n.shape
    (True, torch.Size([1, 162, 3]), torch.Size([1, 162, 3]))
    >>> surf.positions(x[0]).shape                         # one body (3, D, H, W)
    torch.Size([162, 3])
"""

from __future__ import annotations

import itertools
import math
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ConfigError
from ..outputs import atomic_path
from ..sim.grid import Grid
from .surfaces import SURFACE_TOL, load_mesh, trilinear_weights

__all__ = ["EmbeddedSurface", "label_surfaces", "save_surfaces", "EMBEDDED_SUFFIXES"]

#: The file types :meth:`EmbeddedSurface.save` writes (chosen by the suffix).
EMBEDDED_SUFFIXES = (".ply", ".glb")

#: Taubin's filter: shrink by ``lamb``, then dilate by ``nu = 1 / (1 / lamb - k_PB)`` (Taubin 1995, ``k_PB = 0.1``).
_TAUBIN_LAMB = 0.5
_TAUBIN_NU = 1.0 / (1.0 / _TAUBIN_LAMB - 0.1)
#: fast-simplification aggressions tried in turn (7 is its default and fastest).
_AGGRESSION = (7, 5, 3)


# --------------------------------------------------------------------------------- rest cells
def _full_cells(mask: np.ndarray) -> np.ndarray:
    """Bool ``(D-1, H-1, W-1)`` (an axis of one node keeps its 1): all 8 corners of the cell are nodes."""
    full = mask
    for axis, n in enumerate(mask.shape):
        if n > 1:
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(0, -1), slice(1, None)
            full = full[tuple(lo)] & full[tuple(hi)]
    return full


def _rest_cells(q: np.ndarray, shape: tuple, full: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Lower corners ``(V, 3)`` of the rest cells of fractional node indices ``q`` ``(V, 3)``, and bool ``(V,)`` ok.

    The cell containing the point, clipped to the grid; where ``full`` (the cells whose corners are
    all nodes) rejects it, a neighbouring cell that shares the point (within ``SURFACE_TOL``) is tried.
    """
    top = np.maximum(np.asarray(shape) - 2, 0)
    base = np.clip(np.floor(q), 0, top).astype(np.int64)
    if full is None:
        return base, np.ones(len(q), dtype=bool)
    ok = full[tuple(base.T)]
    bad = np.flatnonzero(~ok)
    if len(bad) == 0:
        return base, ok
    frac = q[bad] - base[bad]
    can_down = (frac < SURFACE_TOL) & (base[bad] > 0)
    can_up = (frac > 1.0 - SURFACE_TOL) & (base[bad] < top)
    steps = sorted((s for s in itertools.product((0, -1, 1), repeat=3) if any(s)), key=lambda s: sum(map(abs, s)))
    found = np.zeros(len(bad), dtype=bool)
    for step in steps:
        allowed = ~found
        for axis, s in enumerate(step):
            if s:
                allowed &= can_down[:, axis] if s < 0 else can_up[:, axis]
        if not allowed.any():
            continue
        cand = base[bad[allowed]] + np.asarray(step)
        good = full[tuple(cand.T)]
        rows = np.flatnonzero(allowed)[good]
        base[bad[rows]] = cand[good]
        found[rows] = True
    ok[bad[found]] = True
    return base, ok


def _as_array(values, key: str, *, dtype, what: str) -> np.ndarray:
    arr = values.detach().cpu().numpy() if torch.is_tensor(values) else np.asarray(values)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise ConfigError(key, what, got=tuple(arr.shape))
    if dtype is np.int64:
        if arr.dtype.kind not in "iu":
            raise ConfigError(key, what + " of integers", got=f"dtype {arr.dtype}")
        return arr.astype(np.int64)
    if arr.dtype.kind not in "biuf":
        raise ConfigError(key, what + " of numbers", got=f"dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ConfigError(key, "finite vertex coordinates (no NaN or inf)", got="non-finite values")
    return arr


def _csr(crow: np.ndarray, col: np.ndarray, values: np.ndarray, size: tuple, *, dtype, device) -> torch.Tensor:
    """A CSR matrix (torch's sparse CSR layout is marked beta; its one-time notice is not the user's business)."""
    # int32 indices where they fit: the CPU kernel (MKL) takes int32 and would convert int64 on every call
    index = np.int32 if max(len(col), *size) < 2**31 else np.int64
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        m = torch.sparse_csr_tensor(
            torch.from_numpy(crow.astype(index)),
            torch.from_numpy(col.astype(index)),
            torch.from_numpy(values).to(dtype),
            size,
            check_invariants=False,
        )
        return m.to(device)


# ------------------------------------------------------------------------- cutting sheets
#: the corner offsets of a cell, corner ``4 a + 2 b + c`` at ``(a, b, c)``
_OFFSETS = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=np.int64)
#: tolerance of the patch coordinates (dimensionless: a patch spans [0, 1] along u and v)
_PATCH_TOL = 1e-9
#: heights within this fraction of the surface's extent count as on the plane
_HEIGHT_TOL = 1e-9
#: a triangle whose trace on the plane meets the sheet over less than this fraction of the trace is not opened
_SPAN_MIN = 1e-6
_PATCHES = "flat patches (origin (3,), u (3,), v (3,), triangle) in metres, or a blade holding such patches"

# The triangles that replace a crossed triangle, per case, over its named points: a, b, c its corners
# (counter-clockwise; type I: a alone on its side, type II: a on the plane), S and E the ends of its
# trace on the plane (type I: on edges ab and ca, type II: a itself and a point of bc), T0 and T1 the
# tips where the sheet begins and ends inside the triangle, M half-way between them. Each case also
# names the new edges along which the surface opens.
_CASES = {
    # type I (a alone): S on ab, E on ca
    ("I", "full"): ([("a", "S", "E"), ("S", "b", "c"), ("S", "c", "E")], [("S", "E")]),
    ("I", "start"): ([("a", "S", "T1"), ("S", "b", "T1"), ("b", "c", "T1"), ("c", "a", "T1")], [("S", "T1")]),
    ("I", "end"): ([("a", "b", "T0"), ("b", "c", "T0"), ("c", "E", "T0"), ("E", "a", "T0")], [("T0", "E")]),
    ("I", "slit"): (
        [
            ("a", "b", "T0"),
            ("a", "T0", "M"),
            ("a", "M", "T1"),
            ("a", "T1", "c"),
            ("b", "M", "T0"),
            ("b", "T1", "M"),
            ("b", "c", "T1"),
        ],
        [("T0", "M"), ("M", "T1")],
    ),
    ("I", "split start"): ([("a", "S", "c"), ("S", "b", "c")], []),
    ("I", "split end"): ([("a", "b", "E"), ("b", "c", "E")], []),
    # type II (a on the plane): S = a, E on bc
    ("II", "full"): ([("a", "b", "E"), ("a", "E", "c")], [("a", "E")]),
    ("II", "start"): ([("a", "b", "T1"), ("b", "c", "T1"), ("c", "a", "T1")], [("a", "T1")]),
    ("II", "end"): ([("a", "b", "T0"), ("b", "E", "T0"), ("E", "c", "T0"), ("c", "a", "T0")], [("T0", "E")]),
    ("II", "slit"): (
        [
            ("a", "b", "T0"),
            ("c", "a", "T0"),
            ("b", "M", "T0"),
            ("b", "T1", "M"),
            ("b", "c", "T1"),
            ("c", "T0", "M"),
            ("c", "M", "T1"),
        ],
        [("T0", "M"), ("M", "T1")],
    ),
    ("II", "split end"): ([("a", "b", "E"), ("a", "E", "c")], []),
}


def _as_patches(patches) -> list:
    """``[(origin, u, v, triangle, unit normal)]`` float64 of patches given as tuples or a blade's ``patches``."""
    items = getattr(patches, "patches", patches)
    if isinstance(items, (str, bytes)) or not hasattr(items, "__iter__"):
        raise ConfigError("patches", _PATCHES, got=type(patches).__name__)
    out = []
    for item in items:
        if not isinstance(item, (tuple, list)) or len(item) not in (3, 4):
            raise ConfigError("patches", _PATCHES, got=item)
        try:
            o, u, v = (
                (a.detach().cpu().double().numpy() if torch.is_tensor(a) else np.asarray(a, dtype=np.float64)).reshape(
                    -1
                )
                for a in item[:3]
            )
        except (TypeError, ValueError, RuntimeError):
            raise ConfigError("patches", _PATCHES, got=item) from None
        if any(a.shape != (3,) or not np.isfinite(a).all() for a in (o, u, v)):
            raise ConfigError("patches", _PATCHES, got=item)
        n = np.cross(u, v)
        area, scale = float(np.linalg.norm(n)), float(np.linalg.norm(u) * np.linalg.norm(v))
        if scale == 0 or not area > 1e-12 * scale:
            raise ConfigError("patches", "non-degenerate patches (edges u and v non-zero, not parallel)", got=item)
        out.append((o, u, v, bool(item[3]) if len(item) == 4 else False, n / area))
    if not out:
        raise ConfigError("patches", _PATCHES, got="none")
    return out


def _swept_patches(edges) -> list:
    """The patches a straight edge sweeps through poses ``(K, 2, 3)`` (m).

    Per interval the quadrilateral of the four ends as two triangles, or one parallelogram where the
    edge translates: the patches of the lattice's swept blade (:meth:`torchdeform.topology.Blade.swept`).
    """
    try:
        e = edges.detach().cpu().double().numpy() if torch.is_tensor(edges) else np.asarray(edges, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(
            "edges", "the edge's two ends at two or more poses, shape (K, 2, 3) in metres", got=edges
        ) from None
    if e.ndim != 3 or e.shape[1:] != (2, 3) or e.shape[0] < 2 or not np.isfinite(e).all():
        raise ConfigError("edges", "the edge's two ends at two or more poses, shape (K, 2, 3) in metres", got=e.shape)
    out = []
    for k in range(len(e) - 1):
        a0, b0, a1, b1 = e[k, 0], e[k, 1], e[k + 1, 0], e[k + 1, 1]
        u, v, w = b0 - a0, a1 - a0, b1 - b0
        if not np.cross(u, v).any():  # the edge moved along itself: nothing swept
            continue
        if np.all(np.abs(v - w) <= 1e-12 * (1 + np.abs(v))):  # a translation: one parallelogram
            out.append((a0, u, v, False))
        else:
            out += [(a0, u, b1 - a0, True), (a0, b1 - a0, v, True)]
    if not out:
        raise ConfigError("edges", "an edge that sweeps a surface (it only moved along itself)", got=e.shape)
    return out


def _plane_groups(patches: list) -> list:
    """Patches grouped by plane, ``[(unit normal, offset, [patch, ...])]``.

    Normal and offset are compared to 12 digits, as :meth:`torchdeform.topology.Blade.planes` groups
    them for the lattice.
    """
    groups: dict = {}
    for o, u, v, tri, n in patches:
        c = float(n @ o)
        key = tuple(np.round(n, 12).tolist()) + (round(c, 12),)
        groups.setdefault(key, (n, c, []))[2].append((o, u, v, tri))
    return list(groups.values())


class _Region:
    """The union of coplanar flat patches: which points lie in it, and which stretch of a segment does.

    A point's *values* are, per patch, the four numbers ``(a, b, 1 - a, 1 - b)`` of a parallelogram
    or ``(a, b, 1 - a - b, 1)`` of a triangle (``a, b`` its patch coordinates); it lies in a patch when
    all four are ``>= -_PATCH_TOL``. The values are affine in the point, so the stretch of a segment
    within a patch follows from its two ends' values alone: a point and the segments ending there
    always agree on whether it is inside.
    """

    def __init__(self, patches: list):
        self.o, self.u, self.v = (np.stack([p[k] for p in patches]) for k in range(3))  # (P, 3)
        self.tri = np.array([p[3] for p in patches])
        self.uu, self.uv = (self.u * self.u).sum(1), (self.u * self.v).sum(1)
        self.vv = (self.v * self.v).sum(1)
        self.det = self.uu * self.vv - self.uv**2

    def values(self, p: np.ndarray) -> np.ndarray:
        """``(k, 3)`` points -> ``(k, P, 4)`` values."""
        d = p[:, None, :] - self.o
        du, dv = (d * self.u).sum(-1), (d * self.v).sum(-1)
        a = (self.vv * du - self.uv * dv) / self.det
        b = (self.uu * dv - self.uv * du) / self.det
        return np.stack([a, b, np.where(self.tri, 1 - a - b, 1 - a), np.where(self.tri, 1.0, 1 - b)], -1)

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The region's axis-aligned box ``(low (3,), high (3,))``."""
        far = np.where(self.tri[:, None], self.o, self.o + self.u + self.v)  # a triangle has three corners
        pts = np.concatenate([self.o, self.o + self.u, self.o + self.v, far])
        return pts.min(0), pts.max(0)

    @staticmethod
    def inside(g: np.ndarray) -> np.ndarray:
        """Bool ``(k,)`` of values ``(k, P, 4)``: in one of the patches (closed)."""
        return np.asarray((g >= -_PATCH_TOL).all(-1).any(-1))

    @staticmethod
    def span(ga: np.ndarray, gb: np.ndarray) -> tuple:
        """``(s0, s1, hit)`` ``(k,)``: the stretch ``[s0, s1]`` of the segments ``a + s (b - a)`` in the region.

        Per patch the stretch within it (``s0 = 0`` exactly when ``a`` is inside); over several
        patches the span from the first stretch's start to the last one's end.
        """
        dg = gb - ga
        rise, fall = dg > 0, dg < 0
        bound = np.divide(-_PATCH_TOL - ga, dg, out=np.zeros_like(ga), where=rise | fall)
        lo = np.maximum(np.where(rise, bound, -np.inf).max(-1), 0.0)
        hi = np.minimum(np.where(fall, bound, np.inf).min(-1), 1.0)
        ok = (hi >= lo) & ~(~rise & ~fall & (ga < -_PATCH_TOL)).any(-1)
        return np.where(ok, lo, np.inf).min(-1), np.where(ok, hi, -np.inf).max(-1), ok.any(-1)


def _cut_plane(R: np.ndarray, P: np.ndarray, F: np.ndarray, n: np.ndarray, c: float, region: _Region) -> tuple:
    """Split the triangles that coplanar patches cross and open the surface along the crossings.

    Args:
        R: rest vertex positions ``(V, 3)`` (m).
        P: vertex positions ``(V, 3)`` where the sheet cuts (m).
        F: triangles ``(F, 3)``.
        n: the unit normal ``(3,)`` of the patches' plane ``n . p = c``.
        c: its offset (m).
        region: the patches.

    Returns:
        ``(R, P, F, side, parent, points)``: the vertices (the old ones first, unchanged; then the new
        points on edges and traces; then, from index ``points`` on, the copies made to open the
        surface), the triangles, int8 ``side`` ``(V',)`` (+1 / -1: the side of the plane the vertex's
        triangles are on; 0 for a vertex on the plane shared by both sides) and ``parent`` ``(V',)``
        (the old vertex next to a new point; the vertex a copy copies).
    """
    V = len(R)
    h = P @ n - c
    tol = _HEIGHT_TOL * max(float(np.ptp(P, axis=0).max()), 1e-300)
    sg = np.where(h > tol, 1, np.where(h < -tol, -1, 0)).astype(np.int8)
    h = np.where(sg == 0, 0.0, h)
    pairs = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1)
    keys, inv = np.unique(pairs[:, 0] * V + pairs[:, 1], return_inverse=True)  # 1-D keys: far faster than axis=0
    E, inv = np.stack([keys // V, keys % V], 1), inv.reshape(-1)
    fe = inv.reshape(-1, 3)  # edge k of a triangle joins its corners k and k + 1
    # where each edge that crosses the plane meets it, and whether that point is in the sheet
    ce = np.flatnonzero(sg[E[:, 0]].astype(np.int64) * sg[E[:, 1]] < 0)
    ea, eb = E[ce, 0], E[ce, 1]
    t = (h[ea] / (h[ea] - h[eb]))[:, None]
    Pe, Re = P[ea] + t * (P[eb] - P[ea]), R[ea] + t * (R[eb] - R[ea])
    ge = region.values(Pe)
    e_in = region.inside(ge)
    row = np.full(len(E), -1)
    row[ce] = np.arange(len(ce))
    ev = np.full(len(ce), -1)
    ev[e_in] = V + np.arange(int(e_in.sum()))
    new_R, new_P, parent = [Re[e_in]], [Pe[e_in]], [ea[e_in]]
    nv = V + int(e_in.sum())

    # the triangles with corners on both sides, turned so that corner a is alone (I) or on the plane (II)
    fs = sg[F]
    sf = np.flatnonzero((fs > 0).any(1) & (fs < 0).any(1))
    s = fs[sf]
    two = (s == 0).any(1)
    lone = np.where(s[:, 1] == s[:, 2], 0, np.where(s[:, 0] == s[:, 2], 1, 2))
    k = np.where(two, (s == 0).argmax(1), lone)
    rot = (k[:, None] + np.arange(3)) % 3
    at = np.arange(len(sf))[:, None]
    tri, edges = F[sf][at, rot], fe[sf][at, rot]  # edges: ab, bc, ca
    start, end = row[edges[:, 0]], row[np.where(two, edges[:, 1], edges[:, 2])]
    gS = np.empty((len(sf),) + ge.shape[1:])
    PS, RS, iS = np.empty((len(sf), 3)), np.empty((len(sf), 3)), np.empty(len(sf), dtype=np.int64)
    one = ~two
    gS[one], PS[one], RS[one], iS[one] = ge[start[one]], Pe[start[one]], Re[start[one]], ev[start[one]]
    z = tri[two, 0]
    gS[two], PS[two], RS[two], iS[two] = region.values(P[z]), P[z], R[z], z
    s_in = region.inside(gS)
    gE, PE, RE, iE, e_end = ge[end], Pe[end], Re[end], ev[end], e_in[end]
    s0, s1, hit = region.span(gS, gE)
    s0, s1 = np.where(hit, s0, 0.0), np.where(hit, s1, 0.0)
    short = ~hit | (s1 - s0 <= _SPAN_MIN)
    cases = {
        "full": s_in & e_end,
        "start": s_in & ~e_end & ~short,
        "end": ~s_in & e_end & ~short,
        "slit": ~s_in & ~e_end & ~short,
        "split start": s_in & ~e_end & short & one,
        "split end": ~s_in & e_end & short,
    }

    def points(mask, at_s):
        nonlocal nv
        ids = np.full(len(sf), -1)
        m = np.flatnonzero(mask)
        ids[m] = nv + np.arange(len(m))
        nv += len(m)
        w = at_s[m][:, None]
        new_P.append(PS[m] + w * (PE[m] - PS[m]))
        new_R.append(RS[m] + w * (RE[m] - RS[m]))
        parent.append(tri[m, 0])
        return ids

    tips = cases["end"] | cases["slit"]
    names = {"a": tri[:, 0], "b": tri[:, 1], "c": tri[:, 2], "S": iS, "E": iE}
    names["T0"] = points(tips, s0)
    names["T1"] = points(cases["start"] | cases["slit"], s1)
    names["M"] = points(cases["slit"], (s0 + s1) / 2)
    keep = np.ones(len(F), dtype=bool)
    faces, opens = [F], []
    for (kind, case), (tris, cracks) in _CASES.items():
        mask = cases[case] & (two if kind == "II" else one)
        if not mask.any():
            continue
        keep[sf[mask]] = False
        faces += [np.stack([names[q][mask] for q in t_], 1) for t_ in tris]
        opens += [np.stack([names[q][mask] for q in e_], 1) for e_ in cracks]
    faces[0] = F[keep]
    NF = np.concatenate(faces)
    R2, P2 = np.concatenate([R, *new_R]), np.concatenate([P, *new_P])
    par = np.concatenate([np.arange(V), *parent])
    side = np.concatenate([sg, np.zeros(nv - V, dtype=np.int8)])

    # edges already on the plane, in the sheet, between a triangle on each side: they open too
    count = np.bincount(inv, minlength=len(E))
    flat = (sg[E[:, 0]] == 0) & (sg[E[:, 1]] == 0) & (count == 2)
    if flat.any():
        order = np.argsort(inv, kind="stable")
        first = np.searchsorted(inv[order], np.flatnonzero(flat))
        third = F[:, [2, 0, 1]].reshape(-1)  # the corner opposite each triangle edge
        t1, t2 = sg[third[order[first]]], sg[third[order[first + 1]]]
        e = E[flat][(t1.astype(np.int64) * t2) < 0]
        if len(e):
            e = e[region.inside(region.values((P[e[:, 0]] + P[e[:, 1]]) / 2))]
            opens.append(e)
    if opens:
        R2, P2, NF, side, par = _unzip(R2, P2, NF, side, par, np.sort(np.concatenate(opens), 1))
    return R2, P2, NF, side, par, nv


def _unzip(R, P, F, side, parent, crack: np.ndarray) -> tuple:
    """Open the surface along the ``crack`` edges ``(m, 2)``.

    Each vertex on them gets one copy per fan of triangles that the crack (or the surface's border)
    separates around it; a crack's end keeps one vertex.
    """
    F = F.copy()
    cracked = {(int(a), int(b)) for a, b in crack.tolist()}
    flat = F.reshape(-1)
    order = np.argsort(flat, kind="stable")
    sorted_ = flat[order]
    sides, copied = side.tolist(), []  # copied: the vertex each copy copies
    for v in np.unique(crack).tolist():
        lo, hi = np.searchsorted(sorted_, v), np.searchsorted(sorted_, v, side="right")
        around = (order[lo:hi] // 3).tolist()
        root = list(range(len(around)))

        def find(i, root=root):
            while root[i] != i:
                root[i] = root[root[i]]
                i = root[i]
            return i

        seen: dict = {}
        for i, f in enumerate(around):
            for w in F[f].tolist():
                if w == v or (min(v, w), max(v, w)) in cracked:
                    continue
                if w in seen:
                    root[find(i)] = find(seen[w])
                else:
                    seen[w] = i
        fans: dict = {}
        for i, f in enumerate(around):
            fans.setdefault(find(i), []).append(f)
        if len(fans) < 2:
            continue  # a crack's end: the surface goes on around it
        for g, tris in enumerate(fans.values()):
            sign = int(np.sign(sum(sides[w] for w in F[tris].reshape(-1).tolist() if w != v)))
            if g == 0:
                sides[v] = sign
                continue
            copy = len(sides)
            tris = np.asarray(tris)
            F[tris] = np.where(F[tris] == v, copy, F[tris])
            sides.append(sign)
            copied.append(v)
    if copied:
        R, P = np.concatenate([R, R[copied]]), np.concatenate([P, P[copied]])
        parent = np.concatenate([parent, np.asarray(copied, dtype=np.int64)])
    return R, P, F, np.asarray(sides, dtype=np.int8), parent


def _spring_pairs(grid: Grid) -> list:
    """The corner pairs ``(i, j)`` of a cell joined by a spring of the grid's topology."""
    dirs = {tuple(d) for d in grid.directions}
    pairs = []
    for i, j in itertools.combinations(range(8), 2):
        d = tuple(int(a) for a in _OFFSETS[j] - _OFFSETS[i])
        if d in dirs or tuple(-a for a in d) in dirs:
            pairs.append((i, j))
    return pairs


def _cells_cut(cells: np.ndarray, grid: Grid, xn: np.ndarray, hn: np.ndarray, mask: np.ndarray, region) -> np.ndarray:
    """Bool ``(V,)``: a spring between two corners of the cell ``cells`` ``(V, 3)`` crosses the sheet.

    The lattice's own test (:func:`torchdeform.topology.crossing`): the spring's ends on either side
    of the plane (a node on it counts as the negative side) and the point where it meets the plane in
    the sheet. ``xn`` ``(N, 3)`` node positions, ``hn`` ``(N,)`` their heights, ``mask`` ``(N,)`` body nodes.
    """
    if not len(cells):
        return np.zeros(0, dtype=bool)
    shape = np.asarray(grid.shape)
    keys, back = np.unique(np.ravel_multi_index(tuple(cells.T), grid.shape), return_inverse=True)
    U = np.stack(np.unravel_index(keys, grid.shape), 1)
    idx = np.minimum(U[:, None, :] + _OFFSETS, shape - 1)  # (M, 8, 3): a flat axis repeats its node
    node = np.asarray(np.ravel_multi_index(tuple(np.moveaxis(idx, -1, 0)), grid.shape), dtype=np.int64)
    hc, ok = hn[node], mask[node]
    up = hc > 0
    cut = np.zeros(len(U), dtype=bool)
    across = up.any(1) & (~up).any(1)
    for i, j in _spring_pairs(grid):
        m = np.flatnonzero(across & ~cut & (up[:, i] != up[:, j]) & ok[:, i] & ok[:, j])
        if len(m):
            a, b = hc[m, i], hc[m, j]
            xa, xb = xn[node[m, i]], xn[node[m, j]]
            hit = region.inside(region.values(xa + (a / (a - b))[:, None] * (xb - xa)))
            cut[m[hit]] = True
    return cut[back.reshape(-1)]


def _nearest_cells(p, full, shape, spacing_, origin_) -> tuple[np.ndarray, np.ndarray]:
    """Per point ``(V, 3)``: the nearest cell within one of its own whose corners are all in ``full``.

    Returns its lower corner ``(V, 3)`` and bool ``(V,)`` whether there is one (else the point's own cell).
    """
    q = (p - origin_) / spacing_
    top = np.maximum(shape - 2, 0)
    base = np.clip(np.floor(q), 0, top).astype(np.int64)
    best = np.full(len(p), np.inf)
    out = base.copy()
    for step in itertools.product((0, -1, 1), repeat=3):
        cand = base + np.asarray(step)
        inside = ((cand >= 0) & (cand <= top)).all(1)
        good = np.zeros(len(p), dtype=bool)
        good[inside] = full[tuple(cand[inside].T)]
        dist = np.linalg.norm(q - (cand + 0.5), axis=1)
        better = good & (dist < best)
        out[better], best[better] = cand[better], dist[better]
    return out, np.isfinite(best)


# ---------------------------------------------------------------------------- the surface
class EmbeddedSurface:
    """A triangle surface carried by a lattice: rest cells, trilinear weights, deformed positions and normals.

    Args:
        vertices: rest vertex positions ``(V, 3)`` in metres (patient frame LPS = lattice axes
            ``(D, H, W)``), array or tensor; kept in float64 for the weights.
        faces: triangles ``(F, 3)`` of vertex indices; counter-clockwise seen from outside.
        grid: the body's :class:`~torchdeform.sim.grid.Grid`, or its shape ``(D, H, W)`` with
            ``spacing`` and ``origin`` given here.
        spacing: node spacing in metres (one number or ``(sd, sh, sw)``), only with a shape.
        origin: position of node ``(0, 0, 0)`` in metres, only with a shape.
        dtype: dtype of the weights and of what :meth:`update` returns.
        device: device of every tensor the surface holds.
        cells: optional ``(V, 3)`` lower corners of the cells the vertices take their weights from
            (default: the cell holding each vertex); a vertex outside its given cell extrapolates
            (trilinear weights outside ``[0, 1]`` still reproduce affine maps). :meth:`cut` uses it.

    Raises:
        ConfigError: bad arrays; a vertex more than one spacing outside the lattice box (key
            ``"surface"``: a mesh in millimetres needs ``scale=1e-3``); with a node mask, vertices
            in cells that have a corner outside the body (key ``"surface"``, with their count).

    Attributes:
        grid: the lattice.
        corners: int64 ``(V, 8)``, flat node indices (C order over ``(D, H, W)``) of each vertex's
            rest cell, corner ``4 a + 2 b + c`` at offset ``(a, b, c)``.
        weights: ``(V, 8)`` trilinear weights of those corners (each row sums to 1).

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=(0.01, 0.02, 0.01), origin=(0.1, 0.0, 0.0))
        >>> tri = torch.tensor([[0.105, 0.01, 0.0], [0.115, 0.01, 0.0], [0.105, 0.03, 0.0]], dtype=torch.float64)
        >>> surf = EmbeddedSurface(tri, [[0, 1, 2]], grid, dtype=torch.float64)
        >>> [round(w, 6) for w in surf.weights[0].tolist()]  # half-way along D and along H, on a W node
        [0.25, 0.0, 0.25, 0.0, 0.25, 0.0, 0.25, 0.0]
        >>> surf.normals(surf.rest_vertices)[0].tolist()    # the triangle faces +W
        [0.0, 0.0, 1.0]
    """

    def __init__(
        self,
        vertices,
        faces,
        grid,
        *,
        spacing=None,
        origin=None,
        dtype: torch.dtype = torch.float32,
        device=None,
        cells=None,
    ):
        if isinstance(grid, Grid):
            if spacing is not None or origin is not None:
                raise ConfigError("spacing", "no spacing or origin beside a Grid (the Grid has its own)", got=spacing)
        else:
            grid = Grid(
                grid,
                spacing=(1.0, 1.0, 1.0) if spacing is None else spacing,
                origin=(0.0, 0.0, 0.0) if origin is None else origin,
            )
        self.grid = grid
        self.dtype, self.device = dtype, torch.device(device) if device is not None else torch.device("cpu")
        v = _as_array(vertices, "vertices", dtype=np.float64, what="rest vertex positions (V, 3)")
        f = _as_array(faces, "faces", dtype=np.int64, what="triangles (F, 3)")
        V, nf = len(v), len(f)
        if f.min() < 0 or f.max() >= V:
            raise ConfigError("faces", f"vertex indices in [0, {V})", got=f"[{f.min()}, {f.max()}]")
        shape = np.asarray(grid.shape)
        spacing_, origin_ = np.asarray(grid.spacing), np.asarray(grid.origin)
        q = (v - origin_) / spacing_  # fractional node indices (V, 3)
        span = shape > 1
        far = ((q < -1.0 - SURFACE_TOL) | (q > shape + SURFACE_TOL)) & span
        if far.any():
            gap = np.where(span, np.maximum(-1.0 - q, q - shape) * spacing_, 0.0)[far.any(1)].max()
            raise ConfigError(
                "surface",
                "vertices within one spacing of the lattice box (a mesh in millimetres needs scale=1e-3)",
                got=f"{int(far.any(1).sum())} of {V} vertices farther out, by up to {gap:.3g} m",
            )
        mask = None if grid.node_mask is None else grid.node_mask.cpu().numpy()
        if cells is None:
            cells, ok = _rest_cells(q, grid.shape, None if mask is None else _full_cells(mask))
        else:  # given cells (a cut: each side's own); the weights extrapolate beyond them
            cells = np.asarray(cells, dtype=np.int64).reshape(V, 3)
            ok = np.ones(V, dtype=bool)
        if not ok.all():
            raise ConfigError(
                "surface",
                "every vertex in a lattice cell whose 8 corners are nodes of the body (the body must cover the surface)",
                got=f"{int((~ok).sum())} of {V} vertices in cells with missing corners",
            )
        # the weights of each vertex in its own cell: trilinear_weights in a one-cell grid (unclipped fraction)
        local = tuple(min(int(n), 2) for n in grid.shape)
        _, cols, vals = trilinear_weights(q - cells, local)
        offsets = np.stack(np.unravel_index(cols.reshape(8, V).T, local), -1)  # (V, 8, 3)
        corners = np.ravel_multi_index(tuple(np.moveaxis(cells[:, None, :] + offsets, -1, 0)), grid.shape)
        weights = vals.reshape(8, V).T
        N = math.prod(grid.shape)
        self._v = v
        self._cells = cells  # (V, 3) lower corners of the cells the weights come from
        self._w64 = weights  # (V, 8) float64: the cuts locate vertices with these
        self._corner_np = corners
        self.corners = torch.from_numpy(np.ascontiguousarray(corners)).to(self.device)
        self.weights = torch.from_numpy(np.ascontiguousarray(weights)).to(dtype=dtype, device=self.device)
        self._faces = torch.from_numpy(f).to(self.device)
        self._rest = torch.from_numpy(v).to(dtype=dtype, device=self.device)
        self._fa, self._fb, self._fc = (self._faces[:, k].contiguous() for k in range(3))
        #: after :meth:`cut`: int8 ``(V,)``, the side of the plane each vertex is on (+1 or -1); else None
        self.side: torch.Tensor | None = None
        # (V, N): 8 entries a row, column indices ascending (corner order); (V, F): the faces around each vertex
        crow = np.arange(0, 8 * V + 1, 8, dtype=np.int64)
        self._interp = _csr(crow, corners.reshape(-1), weights.reshape(-1), (V, N), dtype=dtype, device=self.device)
        owner = f.reshape(-1)
        order = np.argsort(owner, kind="stable")  # by vertex, faces ascending within a vertex
        crow = np.zeros(V + 1, dtype=np.int64)
        np.cumsum(np.bincount(owner, minlength=V), out=crow[1:])
        face_of = np.repeat(np.arange(nf, dtype=np.int64), 3)[order]
        self._incidence = _csr(crow, face_of, np.ones(3 * nf), (V, nf), dtype=dtype, device=self.device)

    # ------------------------------------------------------------------ static data
    @property
    def rest_vertices(self) -> torch.Tensor:
        """Rest vertex positions ``(V, 3)`` in metres (``dtype``, ``device``)."""
        return self._rest

    @property
    def rest(self) -> torch.Tensor:
        """The rest positions ``(V, 3)`` (m) under the name texture lookups read (``vertex_colours``)."""
        return self._rest

    @property
    def texcoords(self) -> torch.Tensor:
        """3-D texture coordinates ``(V, 3)``: the rest positions in metres (a solid texture's material points)."""
        return self._rest

    @property
    def faces(self) -> torch.Tensor:
        """Triangles ``(F, 3)`` int64 (``device``)."""
        return self._faces

    @property
    def num_vertices(self) -> int:
        """Number of vertices ``V``."""
        return len(self._rest)

    @property
    def num_faces(self) -> int:
        """Number of triangles ``F``."""
        return len(self._faces)

    def __repr__(self) -> str:
        return (
            f"EmbeddedSurface({self.num_vertices} vertices, {self.num_faces} faces, "
            f"grid {self.grid.shape}, {self.dtype}, {self.device})"
        )

    # ------------------------------------------------------------------ per frame
    def _batch(self, x) -> tuple[torch.Tensor, bool]:
        """``x`` as ``(B, 3, N)`` in the surface's dtype and device, and whether it had a batch dimension."""
        x = torch.as_tensor(x)
        shape = tuple(self.grid.shape)
        if x.dim() == 4 and tuple(x.shape) == (3,) + shape:
            batched = False
            x = x.unsqueeze(0)
        elif x.dim() == 5 and tuple(x.shape[1:]) == (3,) + shape:
            batched = True
        else:
            raise ConfigError("x", f"node positions (3, *{shape}) or (B, 3, *{shape})", got=tuple(x.shape))
        return x.to(device=self.device, dtype=self.dtype).reshape(x.shape[0], 3, -1), batched

    def _positions(self, xb: torch.Tensor) -> torch.Tensor:
        """``(B, 3, N)`` -> ``(V, B, 3)``: one sparse product with the columns of all bodies at once."""
        B = xb.shape[0]
        return torch.sparse.mm(self._interp, xb.reshape(B * 3, -1).t()).view(-1, B, 3)

    def _normals(self, p: torch.Tensor) -> torch.Tensor:
        """``(V, B, 3)`` -> unit normals ``(V, B, 3)``."""
        pa = p.index_select(0, self._fa)
        area2 = torch.linalg.cross(p.index_select(0, self._fb) - pa, p.index_select(0, self._fc) - pa, dim=-1)
        summed = torch.sparse.mm(self._incidence, area2.reshape(len(area2), -1)).view(p.shape)
        return F.normalize(summed, dim=-1, eps=torch.finfo(summed.dtype).tiny)

    def positions(self, x) -> torch.Tensor:
        """Vertex positions (m) on the deformed lattice.

        Args:
            x: node positions ``(3, D, H, W)``, ``(1, 3, D, H, W)`` or ``(B, 3, D, H, W)`` in
                metres (``state.x``); converted to the surface's dtype and device.

        Returns:
            ``(V, 3)`` for ``(3, D, H, W)``, else ``(B, V, 3)``; differentiable with respect to ``x``.
        """
        xb, batched = self._batch(x)
        p = self._positions(xb)
        return p.permute(1, 0, 2).contiguous() if batched else p.view(-1, 3)

    def normals(self, positions: torch.Tensor) -> torch.Tensor:
        """Unit vertex normals ``(V, 3)`` or ``(B, V, 3)`` of vertex positions of the same shape.

        The area-weighted sum of the face normals around each vertex, normalised; outwards for
        counter-clockwise faces; ``(0, 0, 0)`` where the faces around a vertex have no area.
        """
        p = torch.as_tensor(positions).to(device=self.device, dtype=self.dtype)
        V = self.num_vertices
        if p.dim() == 2 and tuple(p.shape) == (V, 3):
            return self._normals(p.unsqueeze(1)).view(V, 3)
        if p.dim() == 3 and tuple(p.shape[1:]) == (V, 3):
            return self._normals(p.permute(1, 0, 2)).permute(1, 0, 2).contiguous()
        raise ConfigError("positions", f"vertex positions ({V}, 3) or (B, {V}, 3)", got=tuple(p.shape))

    def update(self, x) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions and unit normals of the surface on the deformed lattice: the per-frame call.

        Args:
            x: node positions ``(3, D, H, W)``, ``(1, 3, D, H, W)`` or ``(B, 3, D, H, W)`` (m).

        Returns:
            ``(positions, normals)``, each ``(V, 3)`` for ``(3, D, H, W)``, else ``(B, V, 3)``.
        """
        xb, batched = self._batch(x)
        p = self._positions(xb)
        n = self._normals(p)
        if batched:
            return p.permute(1, 0, 2).contiguous(), n.permute(1, 0, 2).contiguous()
        return p.view(-1, 3), n.view(-1, 3)

    # ------------------------------------------------------------------ cuts
    def cut(self, origin, normal) -> EmbeddedSurface:
        """The surface cut by a plane: triangles split along it, each side following only its own nodes.

        Triangles the plane crosses are split along it (``trimesh.intersections.slice_faces_plane``,
        once per side), so no triangle straddles the plane and the two sides share no vertex. Each
        side's vertices take their weights from a cell whose 8 corners are all nodes on that side
        (the nearest such cell to the vertex, within one cell of its own; the weights extrapolate
        linearly when the vertex lies outside it), so when the lattice is cut along the same plane
        (:func:`~torchdeform.topology.cut`) the opening shows on the surface. At rest the cut surface
        lies where the uncut one did (trilinear weights reproduce the rest positions, an affine map).

        Args:
            origin: a point of the plane ``(3,)`` (m, LPS).
            normal: its normal ``(3,)`` (need not be unit).

        Returns:
            a new :class:`EmbeddedSurface` (the same lattice, dtype and device), the positive side's
            vertices first; its ``side`` is int8 ``(V,)``, +1 or -1 per vertex.

        :meth:`cut_patches` cuts with a blade of finite extent (the lattice's), leaving the surface
        whole beyond it.

        Raises:
            ConfigError: a zero normal; a vertex with no cell of its own side's nodes within reach.

        Example:
            >>> import torch, trimesh
            >>> import torchdeform as td
            >>> grid = td.Grid((6, 6, 6), spacing=0.01)
            >>> ball = trimesh.creation.icosphere(3, radius=0.018)
            >>> s = EmbeddedSurface(ball.vertices + 0.025, ball.faces, grid, dtype=torch.float64)
            >>> c = s.cut((0.0245, 0.0, 0.0), (1.0, 0.0, 0.0))
            >>> side = (c.rest_vertices[:, 0] - 0.0245)[c.faces]       # (F, 3) signed distances
            >>> bool(((side >= -1e-12).all(1) | (side <= 1e-12).all(1)).all())    # no triangle straddles
            True
        """
        from trimesh import Trimesh
        from trimesh.intersections import slice_faces_plane

        o = np.asarray(origin, dtype=np.float64).reshape(3)
        n = np.asarray(normal, dtype=np.float64).reshape(3)
        if not np.isfinite(n).all() or np.linalg.norm(n) == 0:
            raise ConfigError("normal", "a non-zero plane normal (3,)", got=normal)
        n = n / np.linalg.norm(n)
        v, f = self._v, self._faces.cpu().numpy()
        grid = self.grid
        shape, spacing_, origin_ = np.asarray(grid.shape), np.asarray(grid.spacing), np.asarray(grid.origin)
        nodes = np.stack(np.meshgrid(*[np.arange(k) for k in grid.shape], indexing="ij"), -1)
        signed = ((origin_ + nodes * spacing_ - o) @ n).reshape(grid.shape)
        mask = np.ones(grid.shape, dtype=bool) if grid.node_mask is None else grid.node_mask.cpu().numpy()
        parts, cells = [], []
        for sgn in (1.0, -1.0):
            sv, sf = slice_faces_plane(v, f, plane_normal=sgn * n, plane_origin=o)[:2]
            mesh = Trimesh(sv, sf, process=False)
            mesh.merge_vertices()  # the split triangles' new vertices, one per crossing edge
            mesh.remove_unreferenced_vertices()
            pv, pf = np.asarray(mesh.vertices), np.asarray(mesh.faces)
            full = _full_cells(mask & (sgn * signed > 0))
            cells.append(self._own_cells(pv, full, shape, spacing_, origin_))
            parts.append((pv, pf))
        (pv, pf), (mv, mf) = parts
        out = EmbeddedSurface(
            np.concatenate([pv, mv]),
            np.concatenate([pf, mf + len(pv)]),
            grid,
            dtype=self.dtype,
            device=self.device,
            cells=np.concatenate(cells),
        )
        out.side = torch.cat([torch.ones(len(pv), dtype=torch.int8), -torch.ones(len(mv), dtype=torch.int8)])
        return out

    def cut_patches(self, patches, *, x=None) -> EmbeddedSurface:
        r"""The surface cut by a sheet of flat patches (a blade), each splitting only the triangles it crosses.

        The sheet is the one the lattice's cut uses (:class:`~torchdeform.topology.Blade`): flat patches
        ``o + a u + b v`` with ``a, b >= 0`` and ``a, b <= 1`` (a parallelogram) or ``a + b <= 1`` (a
        triangle). Coplanar patches act together (grouped by plane as the lattice's cut groups them),
        one plane after another. For each plane, at the vertex positions the lattice ``x`` gives:

        1. A triangle with corners on both sides of the plane meets it along a segment, its *trace*;
           where the trace lies in the sheet the triangle is split along it: new vertices where the
           trace leaves the triangle's edges inside the sheet, and where the sheet's border crosses
           the trace inside the triangle (a *tip*, plus one half-way between two tips). A triangle
           whose trace misses the sheet is left as it is, and so is every edge whose crossing lies
           outside it: the surface stays whole beyond the sheet's end, with no T-junction.
        2. The surface opens along the split: every vertex on it gets one copy per side (the fans of
           triangles around it that the split separates), a tip keeps one. A partial cut leaves the
           surface one piece; a full one makes two.
        3. A vertex whose cell has a spring that the sheet cuts (the lattice's own test: ends on either
           side, crossing point in the sheet) takes its weights from the nearest cell whose 8
           corners are body nodes on its side of the plane (within one cell of its own; it keeps its
           cell if there is none), so it follows only its own side when the lattice opens.

        New vertices get their rest positions by interpolating along the edges and traces they lie
        on: at rest they are where the surface was; in the deformed lattice a split triangle may
        move by the (second-order) difference between the trilinear map and its own flatness. A
        vertex near two cuts with different planes takes its cell from the side of the latest.

        Args:
            patches: ``[(origin (3,), u (3,), v (3,), triangle), ...]`` (m; ``triangle`` a bool, left
                out for a parallelogram), or an object holding them as ``patches`` (a
                :class:`~torchdeform.topology.Blade`).
            x: node positions where the sheet cuts, ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` (m; the
                deformed lattice at the moment of the cut), or None for the rest positions.

        Returns:
            a new :class:`EmbeddedSurface` (the same lattice, dtype and device; old vertices first),
            or this surface itself when the sheet neither crosses a triangle nor cuts a vertex's cell.
            Its ``side`` is int8 ``(V,)``: +1 / -1 for the vertices that the last plane puts on its
            positive / negative side, 0 for the others.

        Raises:
            ConfigError: bad patches or positions.

        Example:
            >>> import numpy as np, torch, trimesh
            >>> import torchdeform as td
            >>> grid = td.Grid((6, 6, 6), spacing=0.01)
            >>> ball = trimesh.creation.icosphere(3, radius=0.018)
            >>> s = EmbeddedSurface(ball.vertices + 0.025, ball.faces, grid, dtype=torch.float64)
            >>> # a square blade in the plane d = 24.5 mm reaching half-way across the ball (w < 25 mm)
            >>> c = s.cut_patches([((0.0245, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 0.025), False)])
            >>> c.num_faces > s.num_faces, len(trimesh.Trimesh(c.rest_vertices, c.faces, process=False).split(only_watertight=False))
            (True, 1)
        """
        groups = _plane_groups(_as_patches(patches))
        grid = self.grid
        shape, spacing_, origin_ = np.asarray(grid.shape), np.asarray(grid.spacing), np.asarray(grid.origin)
        xn = self._nodes(x)
        mask = np.ones(grid.shape, dtype=bool) if grid.node_mask is None else grid.node_mask.cpu().numpy()
        R, F, cells = self._v, self._faces.cpu().numpy(), self._cells
        P = np.einsum("vk,vkc->vc", self._w64, xn[self._corner_np])
        side = np.zeros(len(R), dtype=np.int8)
        changed = False
        reach = 3.0 * float(np.linalg.norm(spacing_))  # a vertex's cell lies within about one cell of it
        for n, c, group in groups:
            region = _Region(group)
            lo, hi = region.box()
            # only the triangles whose boxes meet the sheet's can be split, only vertices near it moved
            slack = 1e-6 * float(np.linalg.norm(hi - lo))  # far wider than the patches' own tolerance
            near = ((P[F].min(1) <= hi + slack) & (P[F].max(1) >= lo - slack)).all(1)
            before, kept = len(R), F[~near]
            R, P, Fn, side, parent, points = _cut_plane(R, P, F[near], n, c, region)
            F = np.concatenate([kept, Fn])
            cells = np.concatenate([cells, np.empty((len(R) - before, 3), dtype=np.int64)])
            new = np.arange(before, points)  # points on edges and traces: the cell holding them (the body's)
            cells[new] = cells[parent[new]]
            if len(new):
                q = (R[new] - origin_) / spacing_
                own, ok = _rest_cells(q, grid.shape, None if grid.node_mask is None else _full_cells(mask))
                cells[new[ok]] = own[ok]
            for v in range(points, len(R)):  # copies of vertices on the opening: their vertex's cell
                cells[v] = cells[parent[v]]
            hn = xn @ n - c
            moved = np.zeros(len(R), dtype=bool)
            close = (np.abs(P - (lo + hi) / 2) <= (hi - lo) / 2 + reach).all(1)
            cand = np.flatnonzero((side != 0) & close)
            moved[cand] = _cells_cut(cells[cand], grid, xn, hn, mask.reshape(-1), region)
            for sgn in (1, -1):
                sel = np.flatnonzero(moved & (side == sgn))
                if len(sel):
                    mine = (hn > 0).reshape(grid.shape) if sgn > 0 else (hn <= 0).reshape(grid.shape)
                    own, ok = _nearest_cells(R[sel], _full_cells(mask & mine), shape, spacing_, origin_)
                    cells[sel[ok]] = own[ok]
            changed |= len(R) != before or len(Fn) != int(near.sum()) or bool(moved.any())
        if not changed:
            return self
        out = EmbeddedSurface(R, F, grid, dtype=self.dtype, device=self.device, cells=cells)
        out.side = torch.from_numpy(side.astype(np.int8))
        return out

    def cut_swept(self, edges, *, x=None) -> EmbeddedSurface:
        r"""The surface cut by a straight edge swept through poses (a scalpel's path), sheet patch by patch.

        Between poses ``k`` and ``k + 1`` the edge sweeps the quadrilateral of its four ends, taken as
        two triangles (one parallelogram where the edge translates): the swept blade of
        :meth:`torchdeform.topology.Blade.swept`, the same sheet the lattice's cut uses. The triangles
        each patch crosses are split along it, only within the patch (see :meth:`cut_patches`): a
        path that stops inside the surface leaves it one piece, opened up to the edge's last pose.

        Args:
            edges: the edge's two ends at each pose, ``(K, 2, 3)`` (m), ``K >= 2``.
            x: node positions where the sheet cuts, ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` (m), or
                None for the rest positions.

        Returns:
            as :meth:`cut_patches`.

        Raises:
            ConfigError: bad edges (a shape other than ``(K, 2, 3)``, an edge that only moves along
                itself) or positions.

        Example:
            >>> import numpy as np, torch, trimesh
            >>> import torchdeform as td
            >>> grid = td.Grid((6, 6, 6), spacing=0.01)
            >>> ball = trimesh.creation.icosphere(3, radius=0.018)
            >>> s = EmbeddedSurface(ball.vertices + 0.025, ball.faces, grid, dtype=torch.float64)
            >>> # an edge along d through the whole ball at h = 24.5 mm, drawn along w from 0 to 30 mm
            >>> edge = np.array([[0.0, 0.0245, 0.0], [0.05, 0.0245, 0.0]])
            >>> path = np.stack([edge, edge + [0.0, 0.0, 0.015], edge + [0.0, 0.0, 0.03]])   # (3, 2, 3) m
            >>> c = s.cut_swept(path)
            >>> h = (c.rest_vertices[:, 1] - 0.0245)[c.faces]                       # (F, 3) heights
            >>> w = c.rest_vertices[:, 2][c.faces].mean(1)
            >>> straddle = (h.max(1).values > 1e-12) & (h.min(1).values < -1e-12)
            >>> bool(straddle[w < 0.029].any()), bool(straddle.any())    # split within the path, not beyond
            (False, True)
            >>> len(trimesh.Trimesh(c.rest_vertices, c.faces, process=False).split(only_watertight=False))  # the far side holds it together
            1
        """
        return self.cut_patches(_swept_patches(edges), x=x)

    def _nodes(self, x) -> np.ndarray:
        """Node positions ``(N, 3)`` float64 of ``x`` (one body), or the rest positions for None."""
        grid = self.grid
        if x is None:
            x = grid.rest_positions(dtype=torch.float64)
        x = torch.as_tensor(x).detach()
        if x.dim() == 5 and x.shape[0] == 1:
            x = x[0]
        if tuple(x.shape) != (3,) + tuple(grid.shape):
            raise ConfigError(
                "x", f"node positions of one body (3, *{grid.shape}) or (1, 3, *{grid.shape})", got=tuple(x.shape)
            )
        return x.to(device="cpu", dtype=torch.float64).reshape(3, -1).t().numpy()

    @staticmethod
    def _own_cells(p, full, shape, spacing_, origin_) -> np.ndarray:
        """Per point ``(V, 3)``: the lower corner of the nearest cell within one of its own whose corners are all in ``full``."""
        out, found = _nearest_cells(p, full, shape, spacing_, origin_)
        if not found.all():
            raise ConfigError(
                "cut",
                "a cell of the cut's own side near every vertex (a plane through the body, not along its skin)",
                got=f"{int((~found).sum())} vertices without one",
            )
        return out

    # ------------------------------------------------------------------ files
    def save(self, path, x) -> None:
        """Write the surface on the deformed lattice with its vertex normals: ``.ply`` or ``.glb`` (trimesh).

        The file appears whole or not at all (written beside it, then renamed). Both formats store
        float32 positions and normals; glTF readers expect unit normals (vertices with zero area get
        trimesh's fallback there).

        Args:
            path: a ``.ply`` or ``.glb`` path in an existing folder.
            x: node positions of one body, ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` (m).

        Raises:
            ConfigError: another suffix, a batch of several bodies, a missing folder.
        """
        import trimesh

        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in EMBEDDED_SUFFIXES:
            raise ConfigError("surface file", "a .ply or .glb path", got=str(path))
        xb, _ = self._batch(x)
        if xb.shape[0] != 1:
            raise ConfigError("x", "the node positions of one body (3, D, H, W) or (1, 3, D, H, W)", got=tuple(x.shape))
        with torch.no_grad():
            p = self._positions(xb)
            n = self._normals(p)
        v = p.view(-1, 3).double().cpu().numpy()
        normals = n.view(-1, 3).double().cpu().numpy()
        mesh = trimesh.Trimesh(vertices=v, faces=self._faces.cpu().numpy(), vertex_normals=normals, process=False)
        with atomic_path(path, key="surface file") as tmp:
            if suffix == ".ply":
                mesh.export(str(tmp), file_type="ply", vertex_normal=True)
            else:
                mesh.export(str(tmp), file_type="glb", include_normals=True)

    @classmethod
    def from_file(
        cls, path, grid, *, scale: float = 1.0, dtype: torch.dtype = torch.float32, device=None
    ) -> EmbeddedSurface:
        """An embedded surface from a closed mesh file (``.stl``, ``.obj``, ``.ply``, ...), read by :func:`load_mesh`.

        Args:
            path: the mesh file; its coordinates times ``scale`` are metres in the lattice's frame.
            grid: the body's :class:`~torchdeform.sim.grid.Grid`.
            scale: multiplies the mesh coordinates (``1e-3`` for millimetres).
            dtype: as :class:`EmbeddedSurface`.
            device: as :class:`EmbeddedSurface`.

        Raises:
            ConfigError: the file is missing, unreadable or not closed (key ``"surface"``), or as
                :class:`EmbeddedSurface`.
        """
        vertices, faces = load_mesh(path, scale=scale, key="surface")
        return cls(vertices, faces, grid, dtype=dtype, device=device)


def save_surfaces(path, surfaces: dict, x) -> None:
    """Write several embedded surfaces on one deformed lattice into one file, with vertex normals.

    A ``.glb`` holds one named mesh per surface; a ``.ply`` holds them as one mesh whose vertices
    carry a ``surface`` property (the index of their surface in ``surfaces``' order). The file
    appears whole or not at all.

    Args:
        path: a ``.ply`` or ``.glb`` path in an existing folder.
        surfaces: ``{name: EmbeddedSurface}`` on the same lattice.
        x: node positions of one body, ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` (m).

    Example:
        >>> import torch, trimesh
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01)
        >>> ball = trimesh.creation.icosphere(2, radius=0.01)
        >>> s = EmbeddedSurface(ball.vertices + 0.015, ball.faces, grid)
        >>> path = getfixture("tmp_path") / "frame.glb"
        >>> save_surfaces(path, {"liver": s}, grid.rest_positions())
        >>> list(trimesh.load(path).geometry)
        ['liver']
    """
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EMBEDDED_SUFFIXES:
        raise ConfigError("surface file", "a .ply or .glb path", got=str(path))
    meshes = {}
    with torch.no_grad():
        for name, surface in surfaces.items():
            p, n = surface.update(x)
            p, n = p.reshape(-1, 3), n.reshape(-1, 3)
            meshes[str(name)] = (p.double().cpu().numpy(), surface.faces.cpu().numpy(), n.double().cpu().numpy())
    with atomic_path(path, key="surface file") as tmp:
        if suffix == ".glb":
            scene = trimesh.Scene()
            for name, (v, f, n) in meshes.items():
                scene.add_geometry(
                    trimesh.Trimesh(v, f, vertex_normals=n, process=False), geom_name=name, node_name=name
                )
            scene.export(str(tmp), file_type="glb", include_normals=True)
            return
        vs, fs, ns, ids, base = [], [], [], [], 0
        for k, (v, f, n) in enumerate(meshes.values()):
            vs.append(v)
            fs.append(f + base)
            ns.append(n)
            ids.append(np.full(len(v), float(k)))
            base += len(v)
        mesh = trimesh.Trimesh(
            np.concatenate(vs),
            np.concatenate(fs),
            vertex_normals=np.concatenate(ns),
            vertex_attributes={"surface": np.concatenate(ids)},
            process=False,
        )
        mesh.export(str(tmp), file_type="ply", vertex_normal=True)


# ------------------------------------------------------------------------- label surfaces
_ANATOMY = "pip install torchdeform[anatomy]"


def _need(module: str, package: str, what: str):
    try:
        return __import__(module)
    except ImportError:
        raise ConfigError(
            "label_surfaces", f"the optional package {package} for {what} ({_ANATOMY})", got="not installed"
        ) from None


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed mesh (positive when its faces wind counter-clockwise seen from outside)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _label_values(labels: np.ndarray, which) -> list:
    present = np.unique(labels)
    present = present[present != 0]
    if which is None:
        return present.tolist()
    wanted = [which] if np.ndim(which) == 0 else list(np.asarray(which).reshape(-1).tolist())
    missing = [w for w in wanted if w not in set(present.tolist())]
    if missing or not wanted:
        shown = present.tolist()[:20]
        raise ConfigError("which", f"label values present in the volume ({shown})", got=missing or which)
    return wanted


def _decimate(mesh, faces: int):
    """Quadric decimation to at most ``faces`` triangles that keeps the surface closed.

    fast-simplification's most aggressive setting (7) sometimes pinches two sheets onto one edge
    (an edge of four faces); the gentler settings are tried then, which may stop above the target.
    The first closed result within the target wins, else the closed one with the fewest faces
    (else, none being closed, the gentlest setting's).
    """
    best = None
    for aggression in _AGGRESSION:
        out = mesh.simplify_quadric_decimation(face_count=faces, aggression=aggression)
        if out.is_watertight:
            if len(out.faces) <= faces:
                return out
            if best is None or len(out.faces) < len(best.faces):
                best = out
    return best if best is not None else out


def label_surfaces(labels, affine, *, which=None, smooth: int = 10, faces=None, spacing_min=None) -> dict:
    """Smooth closed surfaces of the labels of a label volume, in metres, at image resolution.

    For each label: marching cubes (scikit-image, Lewiner) at level 0.5 on the label's binary mask
    padded with background; the vertices mapped through ``affine`` (voxel index ``(i, j, k, 1)`` ->
    metres, LPS, the lattice's frame); faces wound so that normals point outwards whatever the sign
    of the affine's determinant (the signed volume of each result is positive); Taubin smoothing
    (``smooth`` passes alternating ``lambda = 0.5`` and ``mu = -1 / (1 / lambda - 0.1)``, which keeps
    the volume); quadric decimation to ``faces`` triangles (fast-simplification through trimesh).
    The surfaces feed :class:`EmbeddedSurface`.

    Args:
        labels: integer label volume ``(D, H, W)`` (array or tensor); 0 is background.
        affine: ``(4, 4)`` voxel-to-metres matrix (LPS), as read with the volume.
        which: a label value or a sequence of them (default: every non-zero value present).
        smooth: Taubin passes (0: the raw marching-cubes surface, terraced at voxel scale).
        faces: target triangle count per label (decimation), or None to keep them all; a
            surface with fewer faces is left as it is. Decimation keeps the surface closed: where
            the fastest setting pinches an edge, gentler ones are tried, and if none reaches the
            target while closed, the closed result with the fewest faces is returned.
        spacing_min: coarsest detail kept, in metres: marching cubes steps over
            ``max(1, round(spacing_min / smallest voxel size))`` voxels (fewer, larger triangles
            from a fine image); None steps over every voxel.

    Returns:
        ``{label: (vertices (V, 3) float64 metres, faces (F, 3) int64)}``, closed meshes.

    Raises:
        ConfigError: a bad array, affine or option; a label value not in the volume; scikit-image
            (or, with ``faces``, fast-simplification) missing, naming ``pip install torchdeform[anatomy]``.

    Example:
        >>> import numpy as np
        >>> lab = np.zeros((12, 12, 12), dtype=np.int16)
        >>> lab[3:9, 3:9, 3:9] = 2
        >>> affine = np.diag([0.001, 0.001, 0.002, 1.0])             # 1 mm x 1 mm x 2 mm voxels
        >>> v, f = label_surfaces(lab, affine, smooth=0)[2]
        >>> [round(float(a), 4) for a in v.min(0)], [round(float(a), 4) for a in v.max(0)]
        ([0.0025, 0.0025, 0.005], [0.0085, 0.0085, 0.017])
    """
    arr = labels.detach().cpu().numpy() if torch.is_tensor(labels) else np.asarray(labels)
    if arr.ndim != 3 or min(arr.shape) < 1 or arr.dtype.kind not in "biu":
        raise ConfigError("labels", "an integer label volume (D, H, W)", got=f"shape {arr.shape}, dtype {arr.dtype}")
    A = np.asarray(affine, dtype=np.float64)
    if A.shape != (4, 4) or not np.isfinite(A).all() or abs(np.linalg.det(A[:3, :3])) < 1e-300:
        raise ConfigError("affine", "a finite, invertible (4, 4) voxel-to-metres matrix", got=A.shape)
    if isinstance(smooth, bool) or not isinstance(smooth, (int, np.integer)) or smooth < 0:
        raise ConfigError("smooth", "an integer >= 0 (Taubin passes)", got=smooth)
    if faces is not None and (isinstance(faces, bool) or not isinstance(faces, (int, np.integer)) or faces < 4):
        raise ConfigError("faces", "an integer >= 4 (triangles per surface) or None", got=faces)
    voxel = np.linalg.norm(A[:3, :3], axis=0)  # voxel size along i, j, k (m)
    step = 1
    if spacing_min is not None:
        if isinstance(spacing_min, bool) or not isinstance(spacing_min, (int, float)) or not spacing_min > 0:
            raise ConfigError("spacing_min", "a positive length in metres, or None", got=spacing_min)
        step = max(1, round(float(spacing_min) / float(voxel.min())))
    values = _label_values(arr, which)
    measure = _need("skimage.measure", "scikit-image", "marching cubes").measure
    if faces is not None:
        _need("fast_simplification", "fast-simplification", "decimation")
    import trimesh

    flip = np.linalg.det(A[:3, :3]) < 0
    out = {}
    for value in values:
        mask = np.pad((arr == value).astype(np.float32), step)
        vi, fi, _, _ = measure.marching_cubes(mask, level=0.5, step_size=step, allow_degenerate=False)
        vi = vi.astype(np.float64) - step  # voxel indices of the unpadded volume
        fi = fi.astype(np.int64)
        if _signed_volume(vi, fi) < 0:
            fi = fi[:, ::-1]
        if flip:  # a mirroring affine turns the winding inside out
            fi = fi[:, ::-1]
        v = vi @ A[:3, :3].T + A[:3, 3]
        mesh = trimesh.Trimesh(vertices=v, faces=np.ascontiguousarray(fi), process=False)
        if smooth:
            trimesh.smoothing.filter_taubin(mesh, lamb=_TAUBIN_LAMB, nu=_TAUBIN_NU, iterations=int(smooth))
        if faces is not None and len(mesh.faces) > faces:
            mesh = _decimate(mesh, int(faces))
        v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        if _signed_volume(v, f) < 0:  # never expected; kept so the promise holds
            f = f[:, ::-1]
        out[int(value)] = (v, np.ascontiguousarray(f))
    return out
