"""A tool shape for any closed triangle mesh, through a signed distance field sampled on a grid.

:class:`MeshShape` samples the signed distance ``phi`` of a closed triangle mesh (negative inside,
metres) once, on a regular grid with the same spacing ``h`` on every axis that covers the mesh's
bounding box enlarged by ``padding`` times its largest extent on each side, and its gradient
``grad phi`` by central differences (``torch.gradient``, one-sided on the border). A query is one
trilinear ``grid_sample`` of the four channels ``(phi, grad phi)``:

* inside the box, ``d(p) = phi(p)`` and ``n(p) = grad phi(p) / |grad phi(p)|`` (the unit vector of
  axis 0 where the gradient is zero: on the medial axis, e.g. the centre of a ball);
* outside it, with ``c`` the nearest point of the box and ``s = c - phi(c) n(c)`` (about the surface
  point nearest to ``c``): ``d(p) = |p - s|`` and ``n(p) = (p - s) / |p - s|``, so a point far
  away still gets a positive distance that grows with its distance (never more than
  ``phi(c) + |p - c|``, and exact for a ball).

The error of ``d`` near the surface is that of trilinear interpolation of a distance (below ``h``;
``O(h^2 / R)`` on a surface of curvature radius ``R``, more at sharp edges and corners), so
``p - d n`` lies on the surface to within about a spacing.

Building the field (once per shape, numpy, float64, one CPU thread):

1. exact point-triangle distances (to the plane where the foot of the perpendicular falls inside
   the triangle, else to the nearest of its three edges) from every triangle to the grid points in
   its bounding box grown by one spacing: a narrow band in which every point within ``h`` of the
   surface has its exact distance, nearest triangle and nearest surface point (its *site*);
2. the sites spread to the rest of the grid by jump flooding (Rong & Tan 2006), separably:
   steps ``2^k, ..., 2, 1``, each a pass along D, then H, then W in which a point takes a
   neighbour's site ``+-step`` away when it is nearer;
3. for the points off the band, the exact distance to their site's triangle and to the triangles
   of their six neighbours' sites, the least kept. The result is an exact distance to some
   triangle, so never below the true distance; in our tests it is exact within ``2 h`` of the
   surface and within ``0.2 h`` farther away (where a neighbouring triangle was taken);
4. the sign from the ray-parity inside test of :func:`torchdeform.mesh.inside_mask`.

About 0.3-0.7 s of CPU at ``resolution=32`` and 1.5-2.5 s at 64 for meshes of 1,000-5,000
triangles (trimesh's ``signed_distance`` takes about 6 s at 32 without embree).

Mesh ``(x, y, z)`` are the channels ``(D, H, W)`` in that order, in metres, in the tool's own frame
(the tool's position moves the mesh's origin), as in :mod:`torchdeform.mesh`.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ConfigError
from ..mesh import inside_mask, load_mesh
from ..sim.forces import constant
from .tools import Shape, _unit

__all__ = ["MeshShape", "tool_surface"]

#: (point, triangle) pairs evaluated at once while building (memory: ~0.5 kB each, ~130 MB)
_CHUNK = 1 << 18


class _Triangles:
    """Per-triangle constants for exact point-triangle distances, float64 ``(35, F)``.

    numpy, one thread: the build is a one-off and torch's thread pool only adds overhead to these
    short elementwise loops (and stalls badly on a loaded machine).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        tri = np.asarray(vertices, dtype=np.float64)[faces]  # (F, 3, 3)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, bc, ca = b - a, c - b, a - c
        n = np.cross(ab, c - a)
        nn = (n * n).sum(-1)
        # (ab x ap) . n = ap . (n x ab): the three edge tests are dot products with these
        e0, e1, e2 = (np.cross(n, e) for e in (ab, bc, ca))
        lengths = np.stack([(e * e).sum(-1) for e in (ab, bc, ca)], 0)
        # a triangle of area below 1e-12 of its longest edge squared is degenerate (a sliver, a point)
        flat = nn <= 1e-24 * lengths.max(0) ** 2
        self.table = np.ascontiguousarray(
            np.concatenate(
                [
                    np.concatenate([a, b, c, ab, bc, ca, e0, e1, e2, n], 1).T,
                    np.maximum(nn, 1e-300)[None],
                    np.maximum(lengths, 1e-300),
                    flat[None].astype(np.float64),
                ],
                0,
            )
        )

    def closest(self, p: np.ndarray, idx: np.ndarray, point: bool = False):
        """Squared distance ``(M,)`` from points ``p`` ``(3, M)`` to triangles ``idx`` ``(M,)``.

        With ``point``, also the nearest point of each triangle ``(3, M)``.
        """
        if len(idx) > _CHUNK:
            parts = [self.closest(p[:, i : i + _CHUNK], idx[i : i + _CHUNK], point) for i in range(0, len(idx), _CHUNK)]
            if not point:
                return np.concatenate(parts)
            return np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts], 1)
        t = self.table[:, idx]

        def dot(x, y):
            return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]

        a, b, c, ab, bc, ca, e0, e1, e2, n = (t[3 * i : 3 * i + 3] for i in range(10))
        nn, lengths, flat = t[30], t[31:34], t[34]
        ap, bp, cp = p - a, p - b, p - c
        inside = (dot(ap, e0) >= 0) & (dot(bp, e1) >= 0) & (dot(cp, e2) >= 0) & (flat == 0)
        above = dot(ap, n)
        d2, offset = None, None
        for q, e, k in ((ap, ab, 0), (bp, bc, 1), (cp, ca, 2)):
            s = np.clip(dot(q, e) / lengths[k], 0.0, 1.0)
            r = q - s * e  # p minus the edge's nearest point
            r2 = dot(r, r)
            if d2 is None:
                d2, offset = r2, r
            else:
                if point:
                    offset = np.where(r2 < d2, r, offset)
                d2 = np.minimum(d2, r2)
        d2 = np.where(inside, above**2 / nn, d2)
        if not point:
            return d2
        return d2, p - np.where(inside, above / nn * n, offset)


def _unsigned_distance(
    tris: _Triangles, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, h: float, shape: tuple[int, int, int]
) -> np.ndarray:
    """Distance ``(D, H, W)`` float64 from the grid points to the surface (steps 1 to 3 above)."""
    D, H, W = shape
    N = D * H * W
    axes = [origin[i] + h * np.arange(shape[i]) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), 0).reshape(3, N)
    best = np.full(N, np.inf)  # squared distance to the site
    nearest = np.full(N, -1, dtype=np.int64)  # the site's triangle
    site = np.zeros((3, N))  # a surface point [m]

    # 1. the band: every triangle against the grid points of its bounding box grown by one spacing
    tri = vertices[faces]
    dims = np.array(shape)
    i0 = np.clip(np.floor((tri.min(1) - origin) / h).astype(np.int64) - 1, 0, dims - 1)
    i1 = np.clip(np.ceil((tri.max(1) - origin) / h).astype(np.int64) + 1, 0, dims - 1)
    size = i1 - i0 + 1  # (F, 3) points per axis
    counts = size.prod(1)
    start = 0
    while start < len(faces):  # chunks of about _CHUNK pairs
        stop = start + max(1, int(np.searchsorted(np.cumsum(counts[start:]), _CHUNK, "right")))
        c = counts[start:stop]
        f = np.repeat(np.arange(start, stop), c)
        local = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        sz = size[f]
        k = i0[f, 2] + local % sz[:, 2]
        j = i0[f, 1] + (local // sz[:, 2]) % sz[:, 1]
        i = i0[f, 0] + local // (sz[:, 2] * sz[:, 1])
        pt = (i * H + j) * W + k
        d2, q = tris.closest(points[:, pt], f, point=True)
        order = np.lexsort((d2, pt))  # by point, then distance
        first = order[np.r_[True, pt[order][1:] != pt[order][:-1]]]  # each point's nearest triangle
        pt, d2, f, q = pt[first], d2[first], f[first], q[:, first]
        better = d2 < best[pt]
        pt = pt[better]
        best[pt], nearest[pt], site[:, pt] = d2[better], f[better], q[:, better]
        start = stop
    # points within h of the surface are exact now: their nearest triangle was among those tried
    exact = best <= h * h

    # 2. jump flooding of the sites (surface points), separably: +-step along D, then H, then W
    def shifted(offset):
        """Index of every point's neighbour at ``offset`` (grid steps), -1 outside the grid."""
        idx = np.full(shape, -1, dtype=np.int64)
        src, dst = [], []
        for o, n in zip(offset, shape):
            if abs(o) >= n:
                return idx.reshape(-1)
            src.append(slice(o, None) if o > 0 else slice(None, o if o < 0 else None))
            dst.append(slice(None, -o) if o > 0 else slice(-o, None))
        idx[tuple(dst)] = np.arange(N).reshape(shape)[tuple(src)]
        return idx.reshape(-1)

    step = 1 << max(0, (max(shape) - 1).bit_length() - 1)
    while step >= 1:
        for axis in range(3):
            for sign in (1, -1):
                nb = shifted(tuple(sign * step if a == axis else 0 for a in range(3)))
                todo = np.nonzero((nb >= 0) & ~exact)[0]
                todo = todo[nearest[nb[todo]] >= 0]
                q = site[:, nb[todo]]
                r = points[:, todo] - q
                d2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
                better = d2 < best[todo]
                pt = todo[better]
                best[pt], nearest[pt], site[:, pt] = d2[better], nearest[nb[pt]], q[:, better]
        step //= 2

    # 3. exact distances from the other points to their site's triangle and those of their neighbours
    far = np.nonzero(~exact)[0]
    best[far] = tris.closest(points[:, far], nearest[far])
    tried = nearest.copy()
    for axis in range(3):
        for sign in (1, -1):
            nb = shifted(tuple(sign if a == axis else 0 for a in range(3)))[far]
            cand = np.where(nb >= 0, tried[np.maximum(nb, 0)], -1)
            keep = (cand >= 0) & (cand != tried[far])
            pt, ct = far[keep], cand[keep]
            d2 = tris.closest(points[:, pt], ct)
            better = d2 < best[pt]
            best[pt[better]], nearest[pt[better]] = d2[better], ct[better]
    return np.sqrt(best).reshape(shape)


class MeshShape(Shape):
    """A closed triangle mesh as a tool shape, through a signed distance field sampled on a grid.

    The field is built once (see the module notes); :meth:`sdf` is then a single trilinear
    ``grid_sample``, elementwise over any node layout, differentiable in ``p`` and usable in the
    compiled step.

    Args:
        mesh: a ``trimesh.Trimesh`` or the path of a mesh file trimesh can read (``.stl``,
            ``.obj``, ``.ply``, ``.off``, ...), closed (watertight). Vertices in metres in the
            tool's own frame, mesh ``(x, y, z)`` = channels ``(D, H, W)``.
        resolution: grid points along the longest axis of the padded box, an integer >= 4
            (memory and build time grow as its cube; 32 to 64 suits most tools). Thin parts need
            a few spacings across: a needle of radius ``r`` and length ``L`` wants a resolution
            above ``2.4 L / r``; a warning says when no grid point is a spacing deep inside.
        padding: margin added on each side of the mesh's bounding box, as a fraction (>= 0) of its
            largest extent.

    Attributes:
        field: signed distance [m], float64, shape ``(1, 1, D, H, W)``, negative inside.
        gradient: ``grad field`` (dimensionless), float64, shape ``(1, 3, D, H, W)``.
        origin: position [m] of grid point ``(0, 0, 0)``, a tuple ``(3,)``.
        spacing: the grid spacing [m], the same on every axis.
        shape: the grid ``(D, H, W)``.
        vertices: mesh vertices [m], float64 numpy ``(V, 3)``; ``faces``: int64 numpy ``(F, 3)``.

    Raises:
        ConfigError: the file is missing or unreadable, the mesh has no triangles or is not
            closed, ``resolution`` is not an integer >= 4, or ``padding`` is not a number >= 0.

    Warns:
        UserWarning: no grid point lies a spacing or more inside the mesh (too coarse a grid).

    Examples:
        >>> import torch
        >>> import trimesh
        >>> ball = MeshShape(trimesh.creation.icosphere(subdivisions=3, radius=0.01))
        >>> ball.shape
        (32, 32, 32)
        >>> p = torch.tensor([[[0.0, 0.005, 0.02], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])   # (B, 3, P)
        >>> d, n = ball.sdf(p)
        >>> [round(v, 3) for v in d[0, 0].tolist()]       # the centre, 5 mm deep, 1 cm outside
        [-0.009, -0.005, 0.01]
        >>> bool(abs(d[0, 0, 0] + 0.01) < ball.spacing)   # the centre is a kink: within a spacing
        True
        >>> [round(c, 3) for c in n[0, :, 2].tolist()]
        [1.0, 0.0, 0.0]
    """

    def __init__(self, mesh, *, resolution: int = 32, padding: float = 0.1):
        if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or resolution < 4:
            raise ConfigError(
                "mesh_shape.resolution", "an integer >= 4 (grid points along the longest axis)", got=resolution
            )
        try:
            pad = float(padding)
        except (TypeError, ValueError):
            pad = math.nan
        if not math.isfinite(pad) or pad < 0:
            raise ConfigError("mesh_shape.padding", "a number >= 0 (fraction of the largest extent)", got=padding)
        if isinstance(mesh, Path):
            mesh = str(mesh)
        vertices, faces = load_mesh(mesh, key="mesh")
        lo, hi = vertices.min(0), vertices.max(0)
        extent = float((hi - lo).max())
        if not extent > 0:
            raise ConfigError("mesh", "a triangle mesh with a non-zero extent", got="all vertices at one point")
        h = extent * (1 + 2 * pad) / (int(resolution) - 1)
        shape = tuple(max(2, math.ceil((e + 2 * pad * extent) / h - 1e-9) + 1) for e in hi - lo)
        origin = (lo + hi) / 2 - (np.array(shape) - 1) * h / 2
        self.vertices, self.faces = vertices, faces
        self.spacing, self.shape = float(h), shape
        self.origin = tuple(float(o) for o in origin)

        dist = _unsigned_distance(_Triangles(vertices, faces), vertices, faces, origin, h, shape)
        axes = [origin[i] + h * np.arange(shape[i]) for i in range(3)]
        inside = inside_mask(vertices, faces, *axes, tol=1e-6 * h)
        phi = torch.from_numpy(np.where(inside, -dist, dist))
        depth = -float(phi.min())  # the deepest grid point inside [m]
        if depth < h:
            warnings.warn(
                f"MeshShape: no grid point lies more than {max(depth, 0.0):.3g} m inside the mesh, under one "
                f"spacing ({h:.3g} m): thin parts will be missed by contact; raise resolution "
                f"(now {int(resolution)})",
                UserWarning,
                stacklevel=2,
            )
        self.field = phi[None, None].contiguous()
        self.gradient = torch.stack(torch.gradient(phi, spacing=h), 0)[None].contiguous()
        self._stacked = {}  # (dtype, device) -> (1, 4, D, H, W)

    def _tables(self, like: torch.Tensor):
        key = (like.dtype, like.device)
        if key not in self._stacked:
            self._stacked[key] = torch.cat([self.field, self.gradient], 1).to(dtype=like.dtype, device=like.device)
        return self._stacked[key]

    def sdf(self, p):
        """Signed distance and outward normal (see :meth:`Shape.sdf`).

        Args:
            p: points ``(B, 3, ...)`` [m] in the tool's frame, any trailing layout.

        Returns:
            ``d`` ``(B, 1, ...)`` [m] (negative inside) and ``n`` ``(B, 3, ...)``, unit, outward;
            the dtype and device of ``p``.
        """
        B, trailing = p.shape[0], p.shape[2:]
        q = p.reshape(B, 3, -1)  # (B, 3, M)
        M = q.shape[2]
        lo = constant(self.origin, q).view(1, 3, 1)
        hi = lo + constant([(s - 1) * self.spacing for s in self.shape], q).view(1, 3, 1)
        inner = torch.minimum(torch.maximum(q, lo), hi)  # nearest point of the box
        u = 2 * (inner - lo) / (hi - lo) - 1  # [-1, 1] per channel (D, H, W)
        grid = u.flip(1).permute(0, 2, 1).reshape(1, B * M, 1, 1, 3)  # grid_sample's (x=W, y=H, z=D)
        s = F.grid_sample(
            self._tables(q),
            grid,
            mode="bilinear",
            padding_mode="border",  # trilinear in 3-D
            align_corners=True,
        )
        s = s.reshape(4, B, M).permute(1, 0, 2)  # (B, 4, M)
        d, (_, n) = s[:, :1], _unit(s[:, 1:])
        # outside the box: from the surface point nearest to the box point, inner - d n
        r, m = _unit(q - inner + d * n)
        out = (q != inner).any(1, keepdim=True)  # (B, 1, M)
        d, n = torch.where(out, r, d), torch.where(out, m, n)
        return d.reshape(B, 1, *trailing), n.reshape(B, 3, *trailing)


def tool_surface(tool, t: float, *, detail: int = 3) -> tuple[np.ndarray, np.ndarray] | None:
    """The triangles of a tool at time ``t``, in world coordinates: for drawing it beside the body.

    A sphere is an icosphere (``detail`` subdivisions), a capsule trimesh's capsule along its
    axis, a box its 12 triangles, a mesh shape its own mesh; each is turned by the tool's
    orientation and moved to its position at ``t`` (batch entry 0). A half-space has no finite
    surface: None.

    Args:
        tool: a :class:`~torchdeform.interact.tools.Tool`.
        t: the time (s).
        detail: subdivisions of a sphere's icosphere (and a capsule's count of rings, ``8 * detail``).

    Returns:
        ``(vertices (V, 3) float64 metres, faces (F, 3) int64)``, outward winding, or None.

    Example:
        >>> from torchdeform.interact import Sphere, Tool
        >>> v, f = tool_surface(Tool(Sphere(0.01), position=(0.1, 0.0, 0.0)), 0.0)
        >>> round(float(np.linalg.norm(v - [0.1, 0.0, 0.0], axis=1).max()), 6), len(f)
        (0.01, 1280)
    """
    import trimesh

    from .tools import Box, Capsule, Sphere, _rotation_matrix

    shape = tool.shape
    if isinstance(shape, Sphere):
        m = trimesh.creation.icosphere(subdivisions=detail, radius=shape.radius)
    elif isinstance(shape, Capsule):
        m = trimesh.creation.capsule(height=2 * shape.half_length, radius=shape.radius, count=[8 * detail, 8 * detail])
        if shape.axis != 2:  # trimesh's capsule lies along its z: our channel 2
            perm = [2, 0, 1] if shape.axis == 0 else [0, 2, 1]  # a cycle keeps the winding, a swap flips it
            m = trimesh.Trimesh(m.vertices[:, perm], m.faces if shape.axis == 0 else m.faces[:, ::-1], process=False)
    elif isinstance(shape, Box):
        m = trimesh.creation.box(extents=[2 * h for h in shape.half_extents])
    elif isinstance(shape, MeshShape):
        m = trimesh.Trimesh(np.asarray(shape.vertices), np.asarray(shape.faces), process=False)
    else:
        return None
    v = np.asarray(m.vertices, dtype=np.float64)
    rot = tool.rotation(float(t))
    if rot is not None:
        R = _rotation_matrix(torch.as_tensor(np.asarray(rot, dtype=np.float64).reshape(-1, 3)[0])).numpy()
        v = v @ R.T
    pos = tool.position(float(t))
    pos = np.asarray(pos.detach().cpu() if torch.is_tensor(pos) else pos, dtype=np.float64).reshape(-1, 3)[0]
    return v + pos, np.asarray(m.faces, dtype=np.int64)
