"""Bridge to triangle meshes (trimesh): voxelise a closed mesh into a node mask; extract and save surfaces.

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

from ..checks import check_grid
from ..errors import ConfigError
from ..outputs import atomic_path
from ..sim.grid import Grid

#: Relative distance (in units of the smallest spacing) within which a node counts as on the
#: surface, and therefore inside.
SURFACE_TOL = 1e-6


def load_mesh(mesh_or_path, *, scale: float = 1.0, key: str = "mesh"):
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
            raise ConfigError(key, "an existing mesh file", got=f"{path} (not found)")
        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as e:  # trimesh raises many kinds for bad files
            raise ConfigError(
                key,
                "a triangle mesh file trimesh can read (.stl, .obj, .ply, .off, ...)",
                got=f"{path} ({type(e).__name__}: {e})",
            ) from None
    else:
        mesh = mesh_or_path
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ConfigError(key, "a triangle mesh with at least one triangle", got=f"{name} (no triangles)")
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ConfigError(
            key,
            "a closed (watertight) triangle mesh",
            got=f"{name} ({open_edges} open edges)" if open_edges else f"{name} (non-manifold edges)",
        )
    scale = float(scale)
    if not math.isfinite(scale) or scale <= 0:
        raise ConfigError("scale", "a positive number (metres per mesh unit)", got=scale)
    return np.asarray(mesh.vertices, dtype=np.float64) * scale, np.asarray(mesh.faces, dtype=np.int64)


def _crossings_above(tri: np.ndarray, xq: np.ndarray, yq: np.ndarray, zq: np.ndarray) -> np.ndarray:
    """Parity of surface crossings of the rays ``(xq[i], yq[j], zq[k]) + t (1, 0, 0)``, ``t > 0``.

    Args:
        tri: triangles ``(F, 3, 3)`` (vertex, coordinate).
        xq: sorted query coordinates ``(D,)`` along the rays.
        yq: sorted query coordinates ``(H,)``; the columns ``(yq[j], zq[k])`` must not lie on a
            projected edge (callers perturb them).
        zq: sorted query coordinates ``(W,)``.

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
    above = np.cumsum(hist[:, ::-1], axis=1)[:, ::-1][:, 1:]  # (H*W, D)
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


def voxelize(mesh_or_path, spacing, *, padding: int = 0, scale: float = 1.0):
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
        raise ConfigError("spacing", "one positive number or three (sd, sh, sw) in metres", got=spacing)
    if isinstance(padding, bool) or not isinstance(padding, (int, np.integer)) or padding < 0:
        raise ConfigError("padding", "an integer >= 0 (node layers)", got=padding)
    vertices, faces = load_mesh(mesh_or_path, scale=scale)
    lo, hi = vertices.min(0), vertices.max(0)
    shape = tuple(math.ceil((h - l) / s - 1e-9) + 1 + 2 * int(padding) for l, h, s in zip(lo, hi, sp))
    check_grid("spacing", shape)  # a spacing far too fine for the mesh: refused, not allocated
    origin = tuple(float((l + h) / 2 - (n - 1) * s / 2) for l, h, n, s in zip(lo, hi, shape, sp))
    axes = [o + s * np.arange(n) for o, s, n in zip(origin, sp, shape)]
    mask = inside_mask(vertices, faces, *axes, tol=SURFACE_TOL * min(sp))
    if not mask.any():
        raise ConfigError(
            "spacing",
            f"a spacing small enough that some node falls inside the mesh "
            f"(its bounding box is {tuple(float(e) for e in hi - lo)} m)",
            got=spacing,
        )
    return torch.from_numpy(mask), origin, shape


def grid_from_mesh(path, spacing, *, topology: int = 26, padding: int = 0, scale: float = 1.0) -> Grid:
    """A :class:`~torchdeform.sim.grid.Grid` whose node mask is a voxelised closed mesh.

    Args: as :func:`voxelize`, plus ``topology`` (6, 14, 18 or 26 neighbours).

    Example:
        >>> import trimesh
        >>> g = grid_from_mesh(trimesh.creation.icosphere(radius=0.01), 0.002, topology=6)
        >>> g.shape, g.num_nodes < 11 ** 3
        ((11, 11, 11), True)
    """
    mask, origin, shape = voxelize(path, spacing, padding=padding, scale=scale)
    return Grid(shape, spacing=spacing, topology=topology, node_mask=mask, origin=origin)


__all__ = ["voxelize", "grid_from_mesh", "load_mesh", "inside_mask"]


# ------------------------------------------------------------------ surfaces (marching tetrahedra)
#: The six tetrahedra of a cube (Kuhn / Freudenthal split along the main diagonal 0 -> 7), cube corner
#: ``c = 4 i + 2 j + k`` at offset ``(i, j, k)``. Every tetrahedron is a chain 0 -> ... -> 7 with one
#: axis stepped at a time, so neighbouring cubes split their shared faces the same way (no cracks).
_CUBE_TETS = np.array([[0, 4, 6, 7], [0, 4, 5, 7], [0, 2, 6, 7], [0, 2, 3, 7], [0, 1, 5, 7], [0, 1, 3, 7]])
_CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])


def _tet_cases() -> dict:
    """Case (4 inside bits) -> triangles as triples of tetrahedron edges ``(a, b)``."""
    cases = {}
    for case in range(1, 15):
        inside = [v for v in range(4) if case >> v & 1]
        outside = [v for v in range(4) if not case >> v & 1]
        if len(inside) in (1, 3):
            lone, rest = (inside[0], outside) if len(inside) == 1 else (outside[0], inside)
            cases[case] = [[(lone, r) for r in rest]]
        else:
            (i, j), (k, l) = inside, outside
            cases[case] = [[(i, k), (i, l), (j, l)], [(i, k), (j, l), (j, k)]]
    return cases


_TET_CASES = _tet_cases()


def _as_field(field, key):
    arr = field.detach().cpu().double().numpy() if torch.is_tensor(field) else np.asarray(field, dtype=np.float64)
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise ConfigError(key, "a 3-D array (D, H, W)", got=tuple(arr.shape))
    if not np.isfinite(arr).all():
        raise ConfigError(key, "finite values (no NaN or inf)", got="non-finite values", show_got=True)
    return arr


def marching_tetrahedra(field, *, level: float = 0.5, pad: bool = True):
    """Iso-surface ``field = level`` of a scalar grid, as a closed, consistently oriented triangle mesh.

    Each grid cube is split into six tetrahedra along its main diagonal (the split matches across
    shared faces); a tetrahedron crossed by the level gives one or two triangles whose vertices lie
    on its edges at the linearly interpolated crossing. Vertices on the same grid edge are shared,
    so the mesh is watertight when the surface is closed; ``pad`` surrounds the grid with one layer
    below ``level`` first, which closes surfaces that reach the border. "Inside" is
    ``field > level``; triangles face outwards (towards lower values). Fully vectorised (numpy),
    only the cubes the level crosses are processed.

    Args:
        field: ``(D, H, W)`` array or tensor (e.g. a node mask as 0/1, a warped volume).
        level: the iso-value.
        pad: close the surface at the grid border.

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)``; vertex coordinates are fractional grid
        indices ``(d, h, w)`` of ``field`` (``-0.5`` .. ``N - 0.5`` with ``pad`` and a 0/1 mask).

    Example:
        >>> m = np.zeros((4, 4, 4)); m[1:3, 1:3, 1:3] = 1
        >>> v, f = marching_tetrahedra(m)
        >>> float(v.min()), float(v.max())
        (0.5, 2.5)
    """
    arr = _as_field(field, "field")
    level = float(level)
    if not math.isfinite(level):
        raise ConfigError("level", "a finite iso-value", got=level)
    shift = 0
    if pad:
        # below the level; for a 0/1 mask at 0.5 the value 0, so the border crossing sits half-way
        arr = np.pad(arr, 1, constant_values=min(float(arr.min()), 2 * level - float(arr.max()), level - 1e-9))
        shift = 1
    D, H, W = arr.shape
    if min(arr.shape) < 2:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    inside = arr > level
    corner_in = [inside[i : D - 1 + i, j : H - 1 + j, k : W - 1 + k] for i, j, k in _CORNERS]
    n_in = sum(c.astype(np.int8) for c in corner_in)
    cubes = np.argwhere((n_in > 0) & (n_in < 8))  # (K, 3) lower corners
    flat = arr.reshape(-1)
    strides = np.array([H * W, W, 1])
    corner_ids = (cubes @ strides)[:, None] + (_CORNERS @ strides)[None, :]  # (K, 8) node ids
    tets = corner_ids[:, _CUBE_TETS].reshape(-1, 4)  # (6K, 4)
    vals = flat[tets]
    case = ((vals > level) * np.array([1, 2, 4, 8])).sum(1)
    edges_a, edges_b, inside_c = [], [], []
    for c, tris in _TET_CASES.items():
        sel = case == c
        if not sel.any():
            continue
        t = tets[sel]
        ins = [v for v in range(4) if c >> v & 1]
        for tri in tris:
            edges_a.append(np.stack([t[:, a] for a, _ in tri], 1))
            edges_b.append(np.stack([t[:, b] for _, b in tri], 1))
            inside_c.append(t[:, ins])
    if not edges_a:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    ea, eb = np.concatenate(edges_a), np.concatenate(edges_b)  # (F, 3) node ids
    lo, hi = np.minimum(ea, eb), np.maximum(ea, eb)
    keys = lo.astype(np.int64) * (D * H * W) + hi
    uniq, faces = np.unique(keys.reshape(-1), return_inverse=True)
    faces = faces.reshape(-1, 3).astype(np.int64)
    a, b = uniq // (D * H * W), uniq % (D * H * W)
    fa, fb = flat[a], flat[b]
    # a node exactly at the level would put the vertices of all its edges on one point; keeping them
    # 1e-6 of an edge apart keeps the mesh manifold after trimesh merges vertices by position
    t = np.clip((level - fa) / np.where(fb == fa, 1.0, fb - fa), 1e-6, 1.0 - 1e-6)
    pa = np.stack(np.unravel_index(a, (D, H, W)), 1).astype(np.float64)
    pb = np.stack(np.unravel_index(b, (D, H, W)), 1).astype(np.float64)
    verts = pa + t[:, None] * (pb - pa) - shift
    # orient outwards: the normal must point away from the inside corners of the tetrahedron
    tri = verts[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ins_pos = []
    for grp in inside_c:
        P = np.stack(np.unravel_index(grp, (D, H, W)), -1).astype(np.float64) - shift  # (n, k, 3)
        ins_pos.append(P.mean(1))
    ins_pos = np.concatenate(ins_pos)
    flip = (normal * (tri.mean(1) - ins_pos)).sum(1) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces


def trilinear_weights(q: np.ndarray, shape) -> tuple:
    """Trilinear interpolation at fractional node indices ``q`` ``(V, 3)`` as sparse weights.

    The cell index is clipped to the grid and the fraction is not, so points half a spacing
    outside the grid extrapolate linearly from the border cells.

    Args:
        q: ``(V, 3)`` fractional node indices along ``(D, H, W)``.
        shape: the grid's ``(D, H, W)``.

    Returns:
        ``(rows, cols, vals)``, COO entries of the ``(V, D H W)`` matrix (node index in C order),
        8 per point.

    Example:
        >>> r, c, v = trilinear_weights(np.array([[0.5, 0.0, 0.0]]), (2, 2, 2))
        >>> sorted(zip(c[v > 0].tolist(), v[v > 0].tolist()))
        [(0, 0.5), (4, 0.5)]
    """
    i0 = [np.clip(np.floor(q[:, c]), 0, max(n - 2, 0)).astype(np.int64) for c, n in enumerate(shape)]
    f = [q[:, c] - i0[c] if n > 1 else np.zeros(len(q)) for c, n in enumerate(shape)]
    i1 = [np.minimum(i0[c] + 1, n - 1) for c, n in enumerate(shape)]
    rows, cols, vals = [], [], []
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                vals.append((f[0] if a else 1 - f[0]) * (f[1] if b else 1 - f[1]) * (f[2] if c else 1 - f[2]))
                cols.append(((i1 if a else i0)[0] * shape[1] + (i1 if b else i0)[1]) * shape[2] + (i1 if c else i0)[2])
                rows.append(np.arange(len(q)))
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def _interp_positions(x: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Node positions ``x`` ``(3, D, H, W)`` interpolated at fractional node indices ``q`` (:func:`trilinear_weights`)."""
    _, cols, vals = trilinear_weights(q, x.shape[1:])  # 8 blocks of V entries, corner-major
    return (vals * x.reshape(3, -1)[:, cols]).reshape(3, 8, len(q)).sum(1).T


def body_surface(x, *, node_mask=None, level: float = 0.5):
    """Surface of a (deformed) grid body: marching tetrahedra over the node mask, moved with the nodes.

    The surface of ``node_mask`` (half a spacing outside the body's outer nodes, at ``level`` of the
    0/1 mask) is found in node-index coordinates, and every vertex is placed by trilinear
    interpolation of the node positions ``x`` (linear extrapolation half a cell beyond the grid),
    so the mesh follows the deformation.

    Args:
        x: node positions ``(3, D, H, W)`` or ``(1, 3, D, H, W)`` (metres), e.g. ``state.x``.
        node_mask: bool ``(D, H, W)`` (default: every node).
        level: iso-level of the mask (0.5: half-way between an inside and an outside node).

    Returns:
        ``(vertices (V, 3), faces (F, 3))``; vertices in the units of ``x``, coordinates ``(x, y, z)``
        = axes ``(D, H, W)`` (the convention of :func:`voxelize`).

    Example:
        >>> X = torch.stack(torch.meshgrid(*[torch.arange(3.0)] * 3, indexing="ij"))
        >>> v, f = body_surface(X + torch.tensor([1.0, 0, 0]).view(3, 1, 1, 1))
        >>> float(v[:, 0].min()), float(v[:, 0].max())
        (0.5, 3.5)
    """
    xs = x.detach().cpu().double().numpy() if torch.is_tensor(x) else np.asarray(x, dtype=np.float64)
    if xs.ndim == 5 and xs.shape[0] == 1:
        xs = xs[0]
    if xs.ndim != 4 or xs.shape[0] != 3:
        raise ConfigError("x", "node positions (3, D, H, W) or (1, 3, D, H, W)", got=tuple(xs.shape))
    mask = np.ones(xs.shape[1:]) if node_mask is None else _as_field(node_mask, "node_mask")
    if mask.shape != xs.shape[1:]:
        raise ConfigError("node_mask", f"a mask of the grid shape {tuple(xs.shape[1:])}", got=tuple(mask.shape))
    q, faces = marching_tetrahedra(mask.astype(np.float64), level=level)
    return _interp_positions(xs, q), faces


def volume_surface(volume, level: float, *, offsets=None, spacing=(1.0, 1.0, 1.0), **warp_kw):
    """Iso-surface of a volume (optionally warped by node offsets first, :func:`~torchdeform.volume.warp`).

    Args:
        volume: ``(D, H, W)``.
        level: iso-value in volume units (e.g. 300 HU for bone).
        offsets: node offsets in voxels ``(3, n_d, n_h, n_w)`` or None.
        spacing: voxel size ``(sd, sh, sw)``; vertices are ``index * spacing``.
        **warp_kw: keyword arguments of :func:`~torchdeform.volume.warp` (with ``offsets``).

    Returns:
        ``(vertices (V, 3), faces (F, 3))``.
    """
    from ..volume import as_volume, warp

    vol, _ = as_volume(volume)
    if vol.shape[:2] != (1, 1):
        raise ConfigError("volume", "a single volume (D, H, W)", got=tuple(vol.shape))
    if offsets is not None:
        vol = warp(vol, offsets, **warp_kw)
    v, f = marching_tetrahedra(vol.reshape(vol.shape[-3:]), level=level)
    return v * np.asarray(spacing, dtype=np.float64).reshape(1, 3), f


SURFACE_SUFFIXES = (".ply", ".stl", ".obj")


def save_surface(path, vertices, faces, *, vertex_attributes=None) -> None:
    """Write a triangle mesh with trimesh: ``.ply``, ``.stl`` or ``.obj`` (chosen by the suffix).

    ``vertex_attributes`` (name -> ``(V,)`` array) become extra per-vertex properties of a ``.ply``
    (float64 ``property double <name>``); ``.stl`` and ``.obj`` have no place for them and drop them.

    Raises:
        ConfigError: another suffix, or bad arrays.
    """
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise ConfigError("surface file", "a .ply, .stl or .obj path", got=str(path))
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
    if (
        v.ndim != 2
        or v.shape[1] != 3
        or f.ndim != 2
        or f.shape[1] != 3
        or (len(f) and (f.min() < 0 or f.max() >= len(v)))
    ):
        raise ConfigError("surface", "vertices (V, 3) and faces (F, 3) indexing them", got=(v.shape, f.shape))
    attrs = {k: np.asarray(a, dtype=np.float64) for k, a in (vertex_attributes or {}).items()}
    if any(a.shape != (len(v),) for a in attrs.values()):
        raise ConfigError(
            "vertex_attributes",
            f"one value per vertex ({len(v)},) for each name",
            got={k: a.shape for k, a in attrs.items()},
        )
    with atomic_path(path) as tmp:
        trimesh.Trimesh(vertices=v, faces=f, process=False, vertex_attributes=attrs).export(str(tmp))


__all__ += ["marching_tetrahedra", "trilinear_weights", "body_surface", "volume_surface", "save_surface"]
