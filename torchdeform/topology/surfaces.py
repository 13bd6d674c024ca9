"""Surfaces that show a cut: one closed surface per side, and a volume render that carves the gap.

Punak ran marching cubes once per side of a cut, so that the cut faces are closed. Here each label
``L >= 0`` (a side, or a component from :func:`~torchdeform.topology.components`) is one piece:

Surfaces
    The node mask ``labels == L`` goes through :func:`torchdeform.mesh.body_surface` (marching
    tetrahedra at level 1/2, vertices half-way between a node of the piece and a node outside it,
    placed by trilinear interpolation of node positions). Interpolating the body's own positions
    ``x`` would put the cut face of one side half-way towards the *other* side's nodes, so both
    sides would share one face in the middle of the gap. Instead each piece reads its own
    positions ``x_L = X + u_L``, the piece's displacement ``u_L = x - X`` extended beyond it:

    * one layer out (the nodes a vertex can read): linear extrapolation
      ``u_b = 2 u_a - u_c`` along every stencil direction ``e`` with ``a = b - e`` and
      ``c = b - 2e`` both in the piece, averaged over the directions (exact for an affine
      deformation ``x = A X + t``); where no such pair exists, the mean of ``u_a`` over the
      piece's neighbours ``a`` (a rigid shift);
    * further out (only the render reads them): the value of the nearest filled node in rest
      space (``scipy.ndimage.distance_transform_edt`` with the grid spacing).

    Every vertex also carries its rest (material) coordinates, the same interpolation of the rest
    positions ``X``: texture coordinates for a solid texture, exact where the mask's level-1/2
    surface lies. For an affine deformation of a piece, ``vertex = A rest + t`` holds exactly.

Carved render
    :func:`cut_pieces` turns the same extended displacements into node offsets in voxels
    (:func:`~torchdeform.volume.node_offsets`) with each piece's material (its 0/1 node mask) for
    ``render(volume, ..., pieces=...)`` (:mod:`torchdeform.volume.rendering`, "Through a cut"):
    every sample is mapped back through every piece and shows the piece whose rest point lies in
    its own material (trilinear node mask >= 1/2, the same level as the surfaces), or nothing.
    The gap between two sides that moved apart renders empty, where one interpolated field smears
    tissue across it.

Shapes: node positions ``(1, 3, D, H, W)`` or ``(3, D, H, W)`` (metres, channel ``c`` along axis
``c``); labels ``(D, H, W)`` int, negative outside every piece; vertex coordinates ``(x, y, z)`` =
axes ``(D, H, W)`` (the convention of :mod:`torchdeform.mesh`).

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.topology import Blade, components, cut, cut_surfaces
    >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    >>> _ = cut(model, model.X, Blade((0.015, -0.01, -0.01), (0.0, 0.05, 0.0), (0.0, 0.0, 0.05)))
    >>> labels, count = components(model)
    >>> surfaces = cut_surfaces(grid, model.X, labels)
    >>> [(s.label, s.vertices.shape == s.rest.shape) for s in surfaces]     # one closed surface per side
    [(0, True), (32, True)]
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..errors import ConfigError
from ..mesh import body_surface, save_surface
from ..volume.deform import node_offsets

__all__ = [
    "CutSurface",
    "cut_surfaces",
    "surface_map",
    "FrameSurface",
    "save_cut_surfaces",
    "extend_displacement",
    "extension_weights",
    "cut_pieces",
]


class CutSurface(NamedTuple):
    """The closed surface of one piece of a cut body.

    Attributes:
        label: the piece's label (``labels == label``).
        vertices: ``(V, 3)`` float64, deformed positions (units of ``x``).
        faces: ``(F, 3)`` int64, outward-facing triangles.
        rest: ``(V, 3)`` float64, the rest (material) coordinates of each vertex.
    """

    label: int
    vertices: np.ndarray
    faces: np.ndarray
    rest: np.ndarray


# ------------------------------------------------------------------ checks
def _positions(x, shape, key) -> torch.Tensor:
    """``x`` as a floating ``(3, D, H, W)`` tensor (a batch of one allowed)."""
    if not torch.is_tensor(x):
        x = torch.as_tensor(np.asarray(x, dtype=np.float64))
    if x.dim() == 5 and x.shape[0] == 1:
        x = x[0]
    if x.dim() != 4 or tuple(x.shape) != (3, *shape):
        raise ConfigError(
            key,
            f"node positions (3, {', '.join(map(str, shape))}) or a batch of one (1, 3, ...) of the grid",
            got=tuple(x.shape),
        )
    if not x.is_floating_point():
        x = x.double()
    if not bool(torch.isfinite(x).all()):
        raise ConfigError(key, "finite node positions (no NaN or inf)", got="non-finite values", show_got=True)
    return x


def _labels(labels, shape) -> torch.Tensor:
    """``labels`` as an int64 ``(D, H, W)`` tensor."""
    t = labels if torch.is_tensor(labels) else torch.as_tensor(np.asarray(labels))
    if t.dim() == 5 and tuple(t.shape[:2]) == (1, 1):
        t = t[0, 0]
    if tuple(t.shape) != tuple(shape) or t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ConfigError(
            "labels",
            f"integer labels of the grid's nodes {tuple(shape)} (negative: no piece)",
            got=(tuple(t.shape), str(t.dtype)),
        )
    return t.long()


def _inputs(grid, x, labels, X):
    shape = tuple(grid.shape)
    x = _positions(x, shape, "x")
    X = grid.rest_positions(dtype=x.dtype, device=x.device)[0] if X is None else _positions(X, shape, "X").to(x)
    return x, X, _labels(labels, shape).to(x.device)


# ------------------------------------------------------------------ extension
def extension_weights(mask: np.ndarray) -> tuple:
    """The first-layer rule of :func:`extend_displacement` as a sparse ``(N, N)`` matrix (module docstring).

    Rows of the piece's nodes are the identity. A node of the first layer outside the piece takes
    ``mean over e of (2 u[b - e] - u[b - 2e])`` over the 26 directions ``e`` with both nodes in the
    piece, or, where there is no such pair, the mean of its neighbours in the piece. Nodes further
    out get no row.

    Args:
        mask: bool ``(D, H, W)``, the piece's nodes.

    Returns:
        ``(rows, cols, vals)``: COO entries over node indices in C order (``N = D H W``).

    Example:
        >>> r, c, v = extension_weights(np.array([True, True, False]).reshape(3, 1, 1))
        >>> sorted(zip(r.tolist(), c.tolist(), v.tolist()))      # node 2 = 2 u_1 - u_0
        [(0, 0, 1.0), (1, 1, 1.0), (2, 0, -1.0), (2, 1, 2.0)]
    """
    D, H, W = mask.shape
    mp = np.pad(mask, 2)

    def at(e):  # the mask at index - e, (D, H, W)
        return mp[2 - e[0] : 2 - e[0] + D, 2 - e[1] : 2 - e[1] + H, 2 - e[2] : 2 - e[2] + W]

    dirs = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)]
    lin_n, near_n = np.zeros(mask.shape), np.zeros(mask.shape)
    for e in dirs:
        ma, mc = at(e), at(tuple(2 * c for c in e))
        lin_n += ma & mc
        near_n += ma
    first = ~mask & (near_n > 0)
    lin, near = first & (lin_n > 0), first & (lin_n == 0)
    own = np.flatnonzero(mask)
    rows, cols, vals = [own], [own], [np.ones(len(own))]
    for e in dirs:
        off = (e[0] * H + e[1]) * W + e[2]
        ma, mc = at(e), at(tuple(2 * c for c in e))
        b = np.flatnonzero(lin & ma & mc)
        n = lin_n.reshape(-1)[b]
        rows += [b, b]
        cols += [b - off, b - 2 * off]
        vals += [2 / n, -1 / n]
        b = np.flatnonzero(near & ma)
        rows.append(b)
        cols.append(b - off)
        vals.append(1 / near_n.reshape(-1)[b])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def extend_displacement(u: torch.Tensor, mask: torch.Tensor, *, spacing=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """A piece's node displacements extended over the whole grid (module docstring, "Surfaces").

    The first layer around the piece is linearly extrapolated along the 26 lattice directions
    (exact for an affine ``u``; a rigid shift where the piece is one node thin;
    :func:`extension_weights`), every node further out takes the value of the nearest node filled
    so far (distances in rest space).

    Args:
        u: displacements ``(C, D, H, W)`` (e.g. ``x - X``, C = 3).
        mask: bool ``(D, H, W)``, the piece's nodes (at least one).
        spacing: node spacing ``(sd, sh, sw)`` for the nearest-node distances.

    Returns:
        ``(C, D, H, W)``, equal to ``u`` on ``mask``.

    Example:
        >>> u = torch.arange(4.0).view(1, 4, 1, 1)                   # u = index along D
        >>> mask = torch.tensor([True, True, False, False]).view(4, 1, 1)
        >>> extend_displacement(u * mask, mask).flatten().tolist()   # 2 extrapolated, 3 nearest
        [0.0, 1.0, 2.0, 2.0]
    """
    mask = mask.to(torch.bool)
    if mask.dim() != 3 or u.dim() != 4 or tuple(u.shape[1:]) != tuple(mask.shape):
        raise ConfigError(
            "u", "displacements (C, D, H, W) and a mask (D, H, W)", got=(tuple(u.shape), tuple(mask.shape))
        )
    if not bool(mask.any()):
        raise ConfigError("mask", "a piece with at least one node", got="an empty mask", show_got=True)
    C, N = u.shape[0], mask.numel()
    rows, cols, vals = (torch.as_tensor(a, device=u.device) for a in extension_weights(mask.cpu().numpy()))
    E = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals.to(u.dtype), (N, N), check_invariants=False)
    out = (E @ u.reshape(C, N).T).T.reshape(u.shape)
    out = torch.where(mask, u, out)  # the piece exactly as it is
    filled = torch.zeros(N, dtype=torch.bool, device=u.device)
    filled[rows] = True
    filled = filled.view(mask.shape)
    if not bool(filled.all()):
        from scipy.ndimage import distance_transform_edt

        idx = distance_transform_edt(
            ~filled.cpu().numpy(),
            sampling=tuple(float(s) for s in spacing),
            return_distances=False,
            return_indices=True,
        )
        idx = torch.as_tensor(idx, device=u.device)
        out = out[:, idx[0], idx[1], idx[2]]
    return out


def cut_surfaces(grid, x, labels, *, X=None) -> list[CutSurface]:
    """The closed surface of every piece ``labels == L``, ``L >= 0``, on the deformed lattice.

    Each piece's surface follows its own nodes only (its displacement extended beyond it, module
    docstring), so the two faces of a cut part when the sides move apart, and each surface is
    closed (watertight) over the cut face. Vertices lie half a node spacing outside the piece's
    outer nodes (half-way to the next node in rest space).

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid` (shape; default rest positions).
        x: node positions ``(1, 3, D, H, W)`` or ``(3, D, H, W)`` (m), e.g. ``state.x``.
        labels: int ``(D, H, W)`` (or ``(1, 1, D, H, W)``): a piece per value ``>= 0``, e.g.
            ``components(model)[0]``, or the sides of a blade as 0/1:
            ``torch.where(grid.nodes(), (sides(model.X, blade)[0, 0] > 0).long(), -1)``.
        X: rest positions of the same shape (default: the grid's).

    Returns:
        one :class:`CutSurface` per label, in increasing label order: ``vertices (V, 3)``,
        ``faces (F, 3)``, ``rest (V, 3)`` (numpy float64 / int64; coordinates ``(x, y, z)`` =
        axes ``(D, H, W)``).

    Raises:
        ConfigError: positions or labels not of the grid's shape, a batch larger than one,
            non-finite positions.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 3, 3), spacing=1.0, topology=26)
        >>> labels = (torch.arange(4) >= 2).long().view(4, 1, 1).expand(4, 3, 3)   # two sides along D
        >>> x = grid.rest_positions(dtype=torch.float64).clone()
        >>> x[:, 0, 2:] += 1.0                                                     # side 1 moves 1 m along D
        >>> lo, hi = cut_surfaces(grid, x, labels)
        >>> float(lo.vertices[:, 0].max()), float(hi.vertices[:, 0].min()), float(hi.rest[:, 0].min())
        (1.5, 2.5, 1.5)
    """
    x, X, labels = _inputs(grid, x, labels, X)
    out = []
    for label in torch.unique(labels[labels >= 0]).tolist():
        mask = labels == label
        xl = X + extend_displacement(x - X, mask, spacing=grid.spacing)
        vertices, faces = body_surface(xl, node_mask=mask)
        rest, _ = body_surface(X, node_mask=mask)
        out.append(CutSurface(int(label), vertices, faces, rest))
    return out


def surface_map(grid, labels: np.ndarray) -> dict:
    """The surfaces of :func:`cut_surfaces` as one linear map of the node positions.

    Each vertex is the trilinear interpolation (:func:`~torchdeform.mesh.trilinear_weights`) of its
    piece's extended positions (:func:`extension_weights`), so a whole frame is one sparse product.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        labels: int ``(D, H, W)``, a piece per value ``>= 0`` (as :func:`cut_surfaces`).

    Returns:
        dict: ``weights`` (scipy CSR ``(V, N)``, N = D H W in C order), ``rest`` ``(V, 3)`` float64
        (the vertices at rest, m), ``faces`` ``(F, 3)`` int64 (pieces in increasing label order, as
        :func:`cut_surfaces` returns them, indices into the stacked vertices), ``label`` ``(V,)``
        (each vertex's piece). The vertices at positions ``x`` are ``rest + weights @ (x - X)``
        (node-major ``(N, 3)``).

    Example:
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=1.0, topology=26)
        >>> m = surface_map(grid, np.zeros((3, 3, 3), dtype=np.int64))
        >>> m["weights"].shape[1], float(m["rest"][:, 0].min()), float(m["rest"][:, 0].max())
        (27, -0.5, 2.5)
    """
    from scipy.sparse import coo_matrix, csr_matrix, vstack

    from ..mesh import marching_tetrahedra, trilinear_weights

    shape = tuple(grid.shape)
    N = int(np.prod(shape))
    X = grid.rest_positions(dtype=torch.float64)[0].reshape(3, N).T.numpy()
    blocks, rests, faces, owner, count = [], [], [], [], 0
    for label in np.unique(labels[labels >= 0]):
        mask = labels == label
        q, f = marching_tetrahedra(mask.astype(np.float64), level=0.5)
        r, c, v = trilinear_weights(q, shape)
        T = csr_matrix(coo_matrix((v, (r, c)), shape=(len(q), N)))
        r, c, v = extension_weights(mask)
        blocks.append(T @ csr_matrix(coo_matrix((v, (r, c)), shape=(N, N))))
        rests.append(T @ X)
        faces.append(f + count)
        owner.append(np.full(len(q), int(label)))
        count += len(q)
    if not blocks:
        return {
            "weights": csr_matrix((0, N)),
            "rest": np.zeros((0, 3)),
            "faces": np.zeros((0, 3), np.int64),
            "label": np.zeros(0, np.int64),
        }
    return {
        "weights": vstack(blocks).tocsr(),
        "rest": np.concatenate(rests),
        "faces": np.concatenate(faces),
        "label": np.concatenate(owner),
    }


def save_cut_surfaces(directory, surfaces, *, stem: str = "piece") -> list[Path]:
    """Write every surface as ``<directory>/<stem>_<label>.ply`` (created if missing), via trimesh.

    Vertex positions are stored as float32 (``x``, ``y``, ``z``, trimesh's PLY writer); the rest
    coordinates as float64 vertex properties ``rest_x``, ``rest_y``, ``rest_z`` (trimesh reads them
    back in ``mesh.metadata["_ply_raw"]["vertex"]["data"]``; other PLY readers list them as named
    properties).

    Args:
        directory: the folder.
        surfaces: a list of :class:`CutSurface` (from :func:`cut_surfaces`).
        stem: the file name before ``_<label>``.

    Returns:
        the written paths, in the order of ``surfaces``.

    Example:
        >>> import tempfile
        >>> import torchdeform as td
        >>> grid = td.Grid((2, 2, 2), spacing=1.0)
        >>> surfaces = cut_surfaces(grid, grid.rest_positions(), torch.zeros(2, 2, 2, dtype=torch.long))
        >>> [p.name for p in save_cut_surfaces(tempfile.mkdtemp(), surfaces)]
        ['piece_0.ply']
    """
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise ConfigError("directory", "a folder for the surface files", got=str(directory))
    if not all(isinstance(s, CutSurface) for s in surfaces):
        raise ConfigError("surfaces", "a list of CutSurface (from cut_surfaces)", got=type(surfaces).__name__)
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for s in surfaces:
        path = directory / f"{stem}_{s.label}.ply"
        rest = np.asarray(s.rest, dtype=np.float64)
        save_surface(
            path, s.vertices, s.faces, vertex_attributes={f"rest_{c}": rest[:, i] for i, c in enumerate("xyz")}
        )
        paths.append(path)
    return paths


# ------------------------------------------------------------------ carved render
def cut_pieces(grid, x, labels, volume_shape, *, X=None) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The pieces of a cut body for ``render(volume, ..., pieces=...)`` (a carved render of the gap).

    Per label ``L >= 0``: the piece's displacement extended over the grid (module docstring) as
    node offsets in voxels of a volume that fills the node grid's box
    (:func:`~torchdeform.volume.node_offsets`: node ``(0, 0, 0)`` at voxel ``(0, 0, 0)``, the last
    node at the last voxel), and its material, the 0/1 node mask ``labels == L``.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        x: node positions ``(1, 3, D, H, W)`` or ``(3, D, H, W)`` (m).
        labels: int ``(D, H, W)``, a piece per value ``>= 0`` (as :func:`cut_surfaces`).
        volume_shape: the volume's ``(D_v, H_v, W_v)`` voxels (at least the node counts).
        X: rest positions (default: the grid's).

    Returns:
        ``[(offsets (1, 3, D, H, W), material (D, H, W)), ...]`` in increasing label order, in the
        dtype of ``x``.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.volume import render
        >>> grid = td.Grid((5, 2, 2), spacing=1.0)
        >>> labels = (torch.arange(5) >= 2).long().view(5, 1, 1).expand(5, 2, 2)  # cut between nodes 1 and 2
        >>> x = grid.rest_positions(dtype=torch.float64).clone()
        >>> x[:, 0, 2:] += 1.0                                    # side 1 moves 1 node spacing = 3 voxels
        >>> vol = torch.ones(13, 3, 3, dtype=torch.float64)     # nodes at voxels 0, 3, ..., 12; cut at 4.5
        >>> img = render(vol, mode="mip", view="h", pieces=cut_pieces(grid, x, labels, vol.shape))
        >>> img[0, 0, :, 1].tolist()                              # the gap: voxels 4.5 .. 7.5
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    """
    x, X, labels = _inputs(grid, x, labels, X)
    volume_shape = tuple(int(n) for n in volume_shape)
    if len(volume_shape) != 3 or any(n > N for N, n in zip(volume_shape, grid.shape)):
        raise ConfigError(
            "volume_shape", f"three voxel counts, each at least the node count {tuple(grid.shape)}", got=volume_shape
        )
    out = []
    for label in torch.unique(labels[labels >= 0]).tolist():
        mask = labels == label
        xl = X + extend_displacement(x - X, mask, spacing=grid.spacing)
        offsets = node_offsets(xl[None], X[None], grid.spacing, volume_shape)
        out.append((offsets, mask.to(x.dtype)))
    return out


class FrameSurface:
    """The deformed surface of a grid body, per frame: vertices and normals from the node positions.

    Built once at rest from :func:`~torchdeform.topology.surfaces.surface_map`: its ``(V, N)``
    weights are restricted to the nodes they read (the body's outer layers) and their columns
    point straight into the positions' storage, so a frame gathers only those nodes from the
    (packed or grid-layout) state, with no unpacking.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        labels: int ``(D, H, W)`` pieces (as :func:`~torchdeform.topology.cut_surfaces`; default: the
            whole body, one piece).
        packed: a :class:`~torchdeform.sim.packed.PackedModel` of the body: positions come packed
            ``(1, 3, P)``; None: grid layout ``(1, 3, D, H, W)`` (or ``(3, D, H, W)``).
        dtype, device: of the positions and of the results.

    Attributes:
        faces: ``(F, 3)`` int64 triangles (outward), fixed over the run.
        rest: ``(V, 3)`` rest (texture) coordinates of the vertices.
        source: the :func:`surface_map` it was built from (float64 ``rest``, vertex ``label`` ...).
    """

    def __init__(self, grid, *, labels=None, packed=None, dtype=torch.float32, device="cpu", compile: bool = False):
        shape = tuple(grid.shape)
        labels = np.zeros(shape, np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
        self.source = m = surface_map(grid, labels)
        W = m["weights"].tocsr()
        W.sum_duplicates()
        used, cols = np.unique(W.indices, return_inverse=True)  # the nodes the surface reads
        _D, H, W_ = shape
        d, h, w = np.unravel_index(used, shape)
        if packed is None:
            where, stride = used, int(np.prod(shape))
        else:
            where = (d + 1) * (H + 2) * (W_ + 2) + (h + 1) * (W_ + 2) + (w + 1)
            stride = int(packed.P)
        self.stride = stride
        #: (M, 3) flat index of each used node's three coordinates in the positions' storage
        self.index = torch.as_tensor(where[:, None] + stride * np.arange(3)[None, :], device=device)
        X = grid.rest_positions(dtype=torch.float64)[0].reshape(3, -1).T.numpy()[used]  # (M, 3)
        self.X = torch.as_tensor(X, dtype=dtype, device=device)
        V, M = W.shape[0], len(used)
        with warnings.catch_warnings():  # "sparse CSR support is in beta"
            warnings.simplefilter("ignore", UserWarning)
            self.weights = torch.sparse_csr_tensor(
                torch.as_tensor(W.indptr, dtype=torch.int64),
                torch.as_tensor(cols.reshape(-1), dtype=torch.int64),
                torch.as_tensor(W.data),
                (V, M),
                dtype=dtype,
                device=device,
                check_invariants=False,
            )
        self.rest = torch.as_tensor(m["rest"], dtype=dtype, device=device)
        self.faces = torch.as_tensor(m["faces"], dtype=torch.int64, device=device)
        self._corners = self.faces.T.contiguous()  # (3, F)
        self._flat = self.faces.reshape(-1)
        # the faces around each vertex, padded with face F (a zero row): (V, K), K = the largest valence
        F_ = int(self.faces.shape[0])
        owner = self._flat.cpu()
        count = torch.bincount(owner, minlength=V)
        order = torch.argsort(owner, stable=True)
        start = torch.cumsum(count, 0) - count
        slot = torch.arange(int(count.max()) if V else 0)[None]
        face_of = torch.arange(F_).repeat_interleave(3)[order]
        self._incident = torch.where(
            slot < count[:, None], face_of[(start[:, None] + slot).clamp_max(max(3 * F_ - 1, 0))], F_
        ).to(device)
        self.compile_error = None
        self._compiled = None
        if compile:
            from .._compile import INDUCTOR_OPTIONS, inductor_options

            self._compiled = torch.compile(
                self._gather_normals, dynamic=False, options=inductor_options(options=INDUCTOR_OPTIONS)
            )

    @property
    def num_vertices(self) -> int:
        """V, the number of surface vertices."""
        return int(self.rest.shape[0])

    def vertices(self, x: torch.Tensor) -> torch.Tensor:
        """``(V, 3)`` deformed vertices from node positions (packed ``(1, 3, P)`` or grid layout)."""
        u = x.reshape(-1)[self.index] - self.X  # (M, 3): only the surface nodes
        return torch.addmm(self.rest, self.weights, u)

    def normals(self, v: torch.Tensor) -> torch.Tensor:
        """``(V, 3)`` unit vertex normals: area-weighted face normals summed per vertex.

        Compiled (``compile=True``): :meth:`_gather_normals` under ``torch.compile``; otherwise (or
        after a failed compilation, with one warning) :meth:`_scatter_normals`, the faster of the
        two eagerly. Both give the same sums up to rounding.
        """
        if self._compiled is not None:
            try:
                with torch.no_grad():
                    return self._compiled(v)
            except Exception as e:
                from .._compile import warn_fallback

                self._compiled = None
                self.compile_error = f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0][:160]}"
                warn_fallback(self.compile_error, what="the eager surface normals")
        return self._scatter_normals(v)

    def _face_normals(self, v):
        p = v[self._flat].view(-1, 3, 3)  # (F, corner, xyz)
        return torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=1)  # 2 x area x unit normal

    @staticmethod
    def _unit(n):
        return n / n.norm(dim=1, keepdim=True).clamp_min(torch.finfo(n.dtype).tiny)

    def _scatter_normals(self, v):
        """Face normals added into their three corners (``index_add_``): the eager path."""
        fn = self._face_normals(v)
        n = torch.zeros_like(v)
        for c in range(3):
            n.index_add_(0, self._corners[c], fn)
        return self._unit(n)

    def _gather_normals(self, v):
        """Each vertex sums the face normals of its incident faces (no scatter): the compiled path."""
        fn = self._face_normals(v)
        fn = torch.cat([fn, fn.new_zeros(1, 3)])  # face F: the padding
        return self._unit(fn[self._incident].sum(1))

    def __call__(self, x: torch.Tensor):
        """``(vertices, normals)``, each ``(V, 3)``."""
        v = self.vertices(x)
        return v, self.normals(v)
