"""Bridge to triangle meshes (trimesh): voxelise a closed mesh into the node mask of a grid.

Axis convention: mesh coordinates ``(x, y, z)`` map to grid axes ``(D, H, W)`` in that order,
so channel 0 of positions (axis D) is the mesh's x, channel 1 (H) its y and channel 2 (W)
its z. Mesh coordinates are metres unless a ``scale`` is given (``scale=1e-3`` for a mesh in
millimetres).

trimesh is imported here only, lazily, by the functions that need it; the inside test is
our own (a ray-parity scanline in numpy), so neither ``rtree`` nor ``embree`` is needed.

Example:
    >>> import trimesh
    >>> from torchdeform.mesh import voxelize
    >>> mask, origin, shape = voxelize(trimesh.creation.icosphere(radius=0.01), spacing=0.002)
    >>> shape
    (11, 11, 11)
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .errors import ConfigError
from .grid import Grid

#: Relative distance (in units of the smallest spacing) within which a node counts as on the
#: surface, and therefore inside.
SURFACE_TOL = 1e-6


def load_mesh(mesh_or_path, scale: float = 1.0, key: str = "mesh"):
    """A closed triangle mesh as ``(vertices (V, 3) float64 metres, faces (F, 3) int64)``.

    Args:
        mesh_or_path: a ``trimesh.Trimesh`` or the path of a mesh file trimesh can read
            (``.stl``, ``.obj``, ``.ply``, ``.off``, ...).
        scale: multiplies the mesh coordinates (``1e-3`` for millimetres).
        key: the parameter name used in error messages.
    Raises:
        ConfigError: the file is missing or unreadable, has no triangles, or the mesh is not
            closed (every edge must be shared by exactly two triangles).
    """
    import trimesh

    name = "the mesh"
    if isinstance(mesh_or_path, (str, Path)):
        path = Path(mesh_or_path)
        name = str(path)
        if not path.is_file():
            raise ConfigError(key, "an existing mesh file", f"{path} (not found)")
        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as e:                       # trimesh raises many kinds for bad files
            raise ConfigError(key, "a triangle mesh file trimesh can read (.stl, .obj, .ply, .off, ...)",
                              f"{path} ({type(e).__name__}: {e})") from None
    else:
        mesh = mesh_or_path
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(key, "a triangle mesh with at least one triangle", f"{name} (no triangles)")
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ConfigError(key, "a closed (watertight) triangle mesh",
                          f"{name} ({open_edges} open edges)" if open_edges else f"{name} (non-manifold edges)")
    scale = float(scale)
    if not math.isfinite(scale) or scale <= 0:
        raise ConfigError("scale", "a positive number (metres per mesh unit)", scale)
    return np.asarray(mesh.vertices, dtype=np.float64) * scale, np.asarray(mesh.faces, dtype=np.int64)


def _crossings_above(tri: np.ndarray, xq: np.ndarray, yq: np.ndarray, zq: np.ndarray) -> np.ndarray:
    """Parity of surface crossings of the rays ``(xq[i], yq[j], zq[k]) + t (1, 0, 0)``, ``t > 0``.

    Args:
        tri: triangles ``(F, 3, 3)`` (vertex, coordinate).
        xq, yq, zq: sorted query coordinates ``(D,)``, ``(H,)``, ``(W,)``; the columns
            ``(yq[j], zq[k])`` must not lie on a projected edge (callers perturb them).
    Returns:
        bool ``(D, H, W)``: odd number of crossings, i.e. inside a closed mesh.
    """
    D, H, W = len(xq), len(yq), len(zq)
    y, z = tri[:, :, 1], tri[:, :, 2]
    # candidate columns: those inside each triangle's projected bounding box
    j0 = np.searchsorted(yq, y.min(1), "left")
    j1 = np.searchsorted(yq, y.max(1), "right")
    k0 = np.searchsorted(zq, z.min(1), "left")
    k1 = np.searchsorted(zq, z.max(1), "right")
    nj, nk = np.maximum(j1 - j0, 0), np.maximum(k1 - k0, 0)
    counts = nj * nk
    f = np.repeat(np.arange(len(tri)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    j = j0[f] + local // np.maximum(nk[f], 1)
    k = k0[f] + local % np.maximum(nk[f], 1)
    py, pz = yq[j], zq[k]

    # 2-D edge functions = barycentric weights (times twice the signed projected area)
    def edge(a, b):
        return (y[f, b] - y[f, a]) * (pz - z[f, a]) - (z[f, b] - z[f, a]) * (py - y[f, a])
    w0, w1, w2 = edge(1, 2), edge(2, 0), edge(0, 1)
    hit = ((w0 > 0) & (w1 > 0) & (w2 > 0)) | ((w0 < 0) & (w1 < 0) & (w2 < 0))
    w0, w1, w2, f, j, k = w0[hit], w1[hit], w2[hit], f[hit], j[hit], k[hit]
    x_hit = (w0 * tri[f, 0, 0] + w1 * tri[f, 1, 0] + w2 * tri[f, 2, 0]) / (w0 + w1 + w2)

    # a crossing at x_hit lies above the nodes i < n, with n = #{i: xq[i] < x_hit}
    hist = np.zeros((H * W, D + 1), dtype=np.int64)
    np.add.at(hist, (j * W + k, np.searchsorted(xq, x_hit, "left")), 1)
    above = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]            # (H*W, D)
    return (above % 2 == 1).T.reshape(D, H, W)


def inside_mask(vertices: np.ndarray, faces: np.ndarray, xs, ys, zs, tol: float) -> np.ndarray:
    """Bool ``(D, H, W)``: grid point ``(xs[i], ys[j], zs[k])`` lies inside or on a closed mesh.

    A point counts as inside when it or a point at most ``~1.6 tol`` away is strictly inside
    (eight slightly shifted copies of the grid are tested), so nodes on the surface are part of
    the body and rays never graze an edge or a vertex.
    """
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    xs, ys, zs = (np.asarray(a, dtype=np.float64) for a in (xs, ys, zs))
    out = np.zeros((len(xs), len(ys), len(zs)), dtype=bool)
    for sy in (-1.0, 1.0):
        for sz in (-1.0, 1.0):
            for sx in (-1.0, 1.0):
                # irrational-ish ratios keep the shifted columns off edges of axis-aligned meshes
                out |= _crossings_above(tri, xs + sx * tol, ys + sy * 0.9 * tol, zs + sz * 0.6180339887 * tol)
    return out


def voxelize(mesh_or_path, spacing, padding: int = 0, scale: float = 1.0):
    """Voxelise a closed triangle mesh: which nodes of a regular grid lie inside it.

    The grid covers the mesh's bounding box (centred on it, ``ceil(extent / spacing) + 1``
    nodes per axis) plus ``padding`` extra node layers on every side. Mesh ``(x, y, z)`` maps
    to grid axes ``(D, H, W)``. Nodes on the surface (within ``1e-6`` spacing) count as inside.

    Args:
        mesh_or_path: ``trimesh.Trimesh`` or a mesh file path (``.stl``, ``.obj``, ``.ply``, ...).
        spacing: node spacing in metres, one number or ``(sd, sh, sw)``.
        padding: extra node layers around the bounding box (>= 0).
        scale: multiplies the mesh coordinates first (``1e-3`` for a mesh in millimetres).
    Returns:
        ``(node_mask, origin, shape)``: bool tensor ``(D, H, W)``, the position (m) of node
        ``(0, 0, 0)`` as a tuple ``(3,)``, and ``(D, H, W)``.
    Raises:
        ConfigError: missing/unreadable file, a mesh that is not closed, a bad spacing or
            padding, or a spacing so coarse that no node falls inside.

    Example:
        >>> import trimesh
        >>> mask, origin, shape = voxelize(trimesh.creation.box((0.01, 0.01, 0.01)), 0.001)
        >>> shape, int(mask.sum())
        ((11, 11, 11), 1331)
    """
    sp = (spacing,) * 3 if isinstance(spacing, (int, float)) else tuple(spacing)
    try:
        sp = tuple(float(s) for s in sp)
    except (TypeError, ValueError):
        sp = ()
    if len(sp) != 3 or not all(math.isfinite(s) and s > 0 for s in sp):
        raise ConfigError("spacing", "one positive number or three (sd, sh, sw) in metres", spacing)
    if isinstance(padding, bool) or not isinstance(padding, (int, np.integer)) or padding < 0:
        raise ConfigError("padding", "an integer >= 0 (node layers)", padding)
    vertices, faces = load_mesh(mesh_or_path, scale)
    lo, hi = vertices.min(0), vertices.max(0)
    shape = tuple(int(math.ceil((h - l) / s - 1e-9)) + 1 + 2 * int(padding) for l, h, s in zip(lo, hi, sp))
    origin = tuple(float((l + h) / 2 - (n - 1) * s / 2) for l, h, n, s in zip(lo, hi, shape, sp))
    axes = [o + s * np.arange(n) for o, s, n in zip(origin, sp, shape)]
    mask = inside_mask(vertices, faces, *axes, tol=SURFACE_TOL * min(sp))
    if not mask.any():
        raise ConfigError("spacing", f"a spacing small enough that some node falls inside the mesh "
                                     f"(its bounding box is {tuple(float(e) for e in hi - lo)} m)", spacing)
    return torch.from_numpy(mask), origin, shape


def grid_from_mesh(path, spacing, topology: int = 26, padding: int = 0, scale: float = 1.0) -> Grid:
    """A :class:`~torchdeform.grid.Grid` whose node mask is a voxelised closed mesh.

    Args: as :func:`voxelize`, plus ``topology`` (6, 14, 18 or 26 neighbours).

    Example:
        >>> import trimesh
        >>> g = grid_from_mesh(trimesh.creation.icosphere(radius=0.01), 0.002, topology=6)
        >>> g.shape, g.num_nodes < 11 ** 3
        ((11, 11, 11), True)
    """
    mask, origin, shape = voxelize(path, spacing, padding, scale)
    return Grid(shape, spacing, topology, node_mask=mask, origin=origin)


__all__ = ["voxelize", "grid_from_mesh", "load_mesh", "inside_mask"]
