"""Triangle-interior samples of the solid texture (Chen & He, REFERENCE §7.1), a 2-D atlas, textured files.

**Sampling.** Each triangle ``ABC`` is taken at its material (rest) coordinates, in texture voxels
``(X - texture.origin) / texture.voxel``. With ``n_a = density |AB|`` and ``n_b = density |AC|``
(lengths in voxels), the samples are the points ``A + a AB + b AC`` with ``a = i / n_a``,
``b = j / n_b`` (Chen & He's steps ``L_a = 1/|AB|``, ``L_b = 1/|AC|`` at ``density = 1``: about
one sample per voxel), integers ``i, j >= 0`` and ``a + b <= 1`` (with a 1e-9 slack so that the
far corners of integer legs count). Row ``i`` has ``J_i = floor(n_b (1 - i / n_a)) + 1`` samples;
triangle ``f`` has ``I_f = floor(n_a) + 1`` rows. Everything is vectorised over all triangles with
two ragged expansions (``repeat_interleave``), no loop per triangle.

**Atlas.** Each triangle gets a square cell of ``s = m + 2`` texels, ``m = max(I_f, J_0)`` the
sample count along its longer leg (so no fixed size: a triangle keeps about one texel per sample).
Sample ``(i, j)`` sits at texel ``(x, y) = (x0 + 1 + i, y0 + 1 + j)`` (``a`` along x, ``b`` along y,
right-triangle layout); texel column/row 0 and everything past the hypotenuse is the gutter,
filled with the texture at the same affine map extended past the triangle (``i = -1`` or
``a + b > 1``), so bilinear filtering at a triangle's edge reads the triangle's own colour field
and never a neighbour cell. The corners' UVs point at ``A``: texel centre ``(x0 + 1.5, y0 + 1.5)``,
``B``: ``A + (n_a, 0)``, ``C``: ``A + (0, n_b)`` (pixels), so the renderer's affine interpolation
of UVs reproduces ``(a, b)`` exactly. UVs follow the OpenGL/trimesh convention
``u = x / W``, ``v = 1 - y / H`` (image row 0 on top). Cells are packed per size class (one loop
over the few distinct sizes), row by row in an atlas ``ceil(sqrt(sum s^2))`` texels wide.

**Files.** :func:`export_textured` writes the deformed mesh with the texture of its rest
coordinates: ``.ply`` with per-vertex colours (Chen & He's node colouring), ``.glb`` or ``.obj``
(+ ``.mtl`` + ``.png``) with the atlas (vertices split per face corner).

Examples:
    >>> import torch
    >>> from torchdeform.texture import SolidTexture, liver_exemplar
    >>> tex = SolidTexture(liver_exemplar(size=16), block=8, extent=(16, 16, 16), voxel=0.001)
    >>> rest = torch.tensor([[0.001, 0.001, 0.001], [0.005, 0.001, 0.001], [0.001, 0.005, 0.001]], dtype=torch.float64)
    >>> s = sample_triangles(rest, torch.tensor([[0, 1, 2]]), tex)
    >>> s.count                                     # legs of 4 voxels: 5 + 4 + 3 + 2 + 1 grid points
    15
    >>> atlas = build_atlas(rest, torch.tensor([[0, 1, 2]]), tex, samples=s)
    >>> atlas.image.shape, atlas.cell.tolist()      # one cell of 5 + 2 texels
    (torch.Size([7, 7, 3]), [7])
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from ..outputs import atomic_path

__all__ = ["TriangleSamples", "TextureAtlas", "sample_triangles", "build_atlas", "export_textured", "TEXTURED_SUFFIXES"]

TEXTURED_SUFFIXES = (".ply", ".glb", ".obj")
_SLACK = 1e-9  # a + b <= 1 + slack: integer legs keep their far corners


def _ragged(counts: torch.Tensor):
    """``(owner, k)`` for ragged lists: element ``n`` of the output is item ``k`` of list ``owner``."""
    owner = torch.repeat_interleave(torch.arange(len(counts)), counts)
    start = torch.cumsum(counts, 0) - counts
    return owner, torch.arange(len(owner)) - start[owner]


def _triangles(vertices_rest, faces, texture, density):
    """Corners ``A`` and legs ``AB``, ``AC`` in texture voxels (float64, ``(F, 3)`` each), ``n_a``, ``n_b``."""
    X = torch.as_tensor(vertices_rest, dtype=torch.float64)
    f = torch.as_tensor(faces, dtype=torch.int64)
    if (
        X.dim() != 2
        or X.shape[1] != 3
        or f.dim() != 2
        or f.shape[1] != 3
        or (len(f) and (int(f.min()) < 0 or int(f.max()) >= len(X)))
    ):
        raise ConfigError(
            "surface", "rest vertices (V, 3) and faces (F, 3) indexing them", got=(tuple(X.shape), tuple(f.shape))
        )
    if not (isinstance(density, (int, float)) and math.isfinite(density) and density > 0):
        raise ConfigError("density", "a positive number (samples per voxel along each leg)", got=density)
    Xv = (X - texture.origin.to(torch.float64)) / texture.voxel
    A, B, C = Xv[f[:, 0]], Xv[f[:, 1]], Xv[f[:, 2]]
    AB, AC = B - A, C - A
    return A, AB, AC, AB.norm(dim=1) * density, AC.norm(dim=1) * density


def _params(i, j, n_a, n_b):
    """``a = i / n_a``, ``b = j / n_b`` (0 where a leg has zero length)."""
    a = torch.where(n_a > 0, i / n_a.clamp_min(1e-300), torch.zeros_like(n_a))
    b = torch.where(n_b > 0, j / n_b.clamp_min(1e-300), torch.zeros_like(n_b))
    return a, b


def _colour_at(texture, P):
    """Texture colours at voxel points ``P`` ``(N, 3)`` (float64), looked up in the exemplar's dtype."""
    return texture.colour(P.to(texture.exemplar.dtype))


@dataclass
class TriangleSamples:
    """Chen & He's triangle-interior samples in compact form (``N`` samples, ``F`` triangles).

    Attributes:
        face: int64 ``(N,)``: the triangle of each sample (samples of a triangle are contiguous).
        i, j: int32 ``(N,)``: grid indices; ``a = i / n_a``, ``b = j / n_b``.
        colour: ``(N, 3)`` texture colours (the exemplar's dtype) at ``A + a AB + b AC``.
        n_a, n_b: float64 ``(F,)``: ``density |AB|``, ``density |AC|`` in texture voxels (steps ``1/n``).
        per_face: int64 ``(F,)``: samples per triangle.
        count: ``N``.
    """

    face: torch.Tensor
    i: torch.Tensor
    j: torch.Tensor
    colour: torch.Tensor
    n_a: torch.Tensor
    n_b: torch.Tensor
    per_face: torch.Tensor
    count: int

    @property
    def a(self) -> torch.Tensor:
        """float64 ``(N,)``: ``a = i / n_a`` of each sample (``i`` steps of ``L_a`` along ``AB``)."""
        return _params(self.i.double(), self.j.double(), self.n_a[self.face], self.n_b[self.face])[0]

    @property
    def b(self) -> torch.Tensor:
        """float64 ``(N,)``: ``b = j / n_b`` of each sample (``j`` steps of ``L_b`` along ``AC``)."""
        return _params(self.i.double(), self.j.double(), self.n_a[self.face], self.n_b[self.face])[1]

    def __len__(self) -> int:
        return self.count


def sample_triangles(vertices_rest, faces, texture, *, density: float = 1.0) -> TriangleSamples:
    """Sample every triangle's interior on Chen & He's grid and colour the samples (see the module docstring).

    Args:
        vertices_rest: ``(V, 3)`` material (rest) coordinates, metres.
        faces: ``(F, 3)`` vertex indices; corner 0 is ``A``, 1 is ``B``, 2 is ``C``.
        texture: a :class:`~torchdeform.texture.synthesis.SolidTexture`.
        density: samples per texture voxel along each leg (steps ``1 / (density |AB|)``); 1 is Chen & He's.

    Returns:
        :class:`TriangleSamples` (``.count`` samples in all, ``.per_face`` per triangle).

    Raises:
        ConfigError: bad arrays or density.

    Examples:
        >>> import torch
        >>> from torchdeform.texture import SolidTexture, liver_exemplar
        >>> tex = SolidTexture(liver_exemplar(size=16), block=8, extent=(16, 16, 16), voxel=0.001)
        >>> rest = torch.tensor([[0.0, 0, 0], [0.002, 0, 0], [0, 0.003, 0]], dtype=torch.float64)
        >>> s = sample_triangles(rest, [[0, 1, 2]], tex)
        >>> s.count, s.a.tolist()[:4], s.b.tolist()[:4]        # row i = 0 holds b = 0, 1/3, 2/3, 1
        (7, [0.0, 0.0, 0.0, 0.0], [0.0, 0.3333333333333333, 0.6666666666666666, 1.0])
    """
    A, AB, AC, n_a, n_b = _triangles(vertices_rest, faces, texture, density)
    rows = torch.floor(n_a + _SLACK).long() + 1  # i = 0 .. floor(n_a)
    row_face, row_i = _ragged(rows)
    a_row, _ = _params(row_i.double(), torch.zeros(len(row_i), dtype=torch.float64), n_a[row_face], n_b[row_face])
    per_row = torch.floor(n_b[row_face] * (1.0 - a_row) + _SLACK).clamp_min(0).long() + 1
    row, j = _ragged(per_row)
    # per row: its first point A + a AB and the step AC / n_b; per sample only start + j step (the
    # samples outnumber the rows about 10 to 1)
    start = A.index_select(0, row_face) + a_row[:, None] * AB.index_select(0, row_face)
    step = torch.where(n_b[:, None] > 0, AC / n_b.clamp_min(1e-300)[:, None], torch.zeros_like(AC))
    P = torch.addcmul(
        start.index_select(0, row), j[:, None].double(), step.index_select(0, row_face).index_select(0, row)
    )
    per_face = torch.zeros(len(n_a), dtype=torch.int64).index_add_(0, row_face, per_row)
    face, i = row_face.index_select(0, row), row_i.index_select(0, row)
    return TriangleSamples(face, i.int(), j.int(), _colour_at(texture, P), n_a, n_b, per_face, len(face))


@dataclass
class TextureAtlas:
    """A 2-D RGB atlas of triangle samples with per-face-corner UVs (see the module docstring).

    Attributes:
        image: ``(H, W, 3)`` colours in ``[0, 1]``; row 0 is the image's top.
        uv: float64 ``(F, 3, 2)``: ``(u, v)`` of each face corner, ``v`` upwards (OpenGL, trimesh).
        corner: int64 ``(F, 2)``: each cell's top-left texel ``(x0, y0)``.
        cell: int64 ``(F,)``: each cell's side ``s`` in texels (samples along the longer leg + 2).
        samples: the :class:`TriangleSamples` it packs; sample ``k`` is texel
            ``(y0 + 1 + j, x0 + 1 + i)`` of its face.
    """

    image: torch.Tensor
    uv: torch.Tensor
    corner: torch.Tensor
    cell: torch.Tensor
    samples: TriangleSamples

    def to_pil(self):
        """The atlas as an 8-bit RGB ``PIL.Image``."""
        from PIL import Image

        arr = (self.image.double().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        return Image.fromarray(np.ascontiguousarray(arr))  # (H, W, 3) uint8: RGB


def _pack(cell: torch.Tensor):
    """Top-left corners ``(F, 2)`` of square cells of sides ``cell`` and the atlas size ``(H, W)``."""
    W = max(int(cell.max()), math.ceil(math.sqrt(float((cell.double() ** 2).sum()))))
    corner = torch.zeros(len(cell), 2, dtype=torch.int64)
    y0 = 0
    for s in torch.unique(cell).flip(0).tolist():  # largest cells first
        idx = torch.nonzero(cell == s).flatten()
        k, cols = torch.arange(len(idx)), W // s
        corner[idx, 0] = (k % cols) * s
        corner[idx, 1] = y0 + (k // cols) * s
        y0 += math.ceil(len(idx) / cols) * s
    return corner, (y0, W)


def build_atlas(
    vertices_rest, faces, texture, *, density: float = 1.0, samples: TriangleSamples | None = None
) -> TextureAtlas:
    """Pack each triangle's samples into a square cell of an RGB atlas, with a 1-texel gutter and corner UVs.

    Args:
        vertices_rest: ``(V, 3)`` material (rest) coordinates, metres.
        faces: ``(F, 3)`` vertex indices.
        texture: a :class:`~torchdeform.texture.synthesis.SolidTexture`.
        density: as in :func:`sample_triangles`.
        samples: the samples of these arguments, when already computed.

    Returns:
        :class:`TextureAtlas` (``image`` ``(H, W, 3)``, ``uv`` ``(F, 3, 2)``).

    Examples:
        >>> import torch
        >>> from torchdeform.texture import SolidTexture, liver_exemplar
        >>> tex = SolidTexture(liver_exemplar(size=16), block=8, extent=(16, 16, 16), voxel=0.001)
        >>> rest = torch.tensor([[0.0, 0, 0], [0.002, 0, 0], [0, 0.003, 0], [0, 0, 0.003]], dtype=torch.float64)
        >>> atlas = build_atlas(rest, [[0, 1, 2], [0, 2, 3]], tex)
        >>> atlas.cell.tolist(), atlas.uv.shape, bool(((atlas.uv > 0) & (atlas.uv < 1)).all())
        ([6, 6], torch.Size([2, 3, 2]), True)
    """
    A, AB, AC, n_a, n_b = _triangles(vertices_rest, faces, texture, density)
    s = sample_triangles(vertices_rest, faces, texture, density=density) if samples is None else samples
    m = torch.maximum(torch.floor(n_a + _SLACK), torch.floor(n_b + _SLACK)).long() + 1
    cell = m + 2
    corner, (H, W) = _pack(cell)
    image = torch.zeros(H * W, 3, dtype=s.colour.dtype)
    filled = torch.zeros(H * W, dtype=torch.bool)
    # the samples, at their texels
    flat = (corner[s.face, 1] + 1 + s.j.long()) * W + corner[s.face, 0] + 1 + s.i.long()
    image[flat] = s.colour
    filled[flat] = True
    # the gutter and the rest of each cell: the triangle's affine map extended past its edges
    face, k = _ragged(cell**2)
    side = cell[face]
    x, y = k % side, torch.div(k, side, rounding_mode="floor")
    tflat = (corner[face, 1] + y) * W + corner[face, 0] + x
    keep = ~filled[tflat]
    face, x, y, tflat = face[keep], x[keep], y[keep], tflat[keep]
    a, b = _params((x - 1).double(), (y - 1).double(), n_a[face], n_b[face])
    image[tflat] = _colour_at(texture, A[face] + a[:, None] * AB[face] + b[:, None] * AC[face])
    # corner UVs: A at texel centre (x0 + 1.5, y0 + 1.5), B = A + (n_a, 0), C = A + (0, n_b)
    pa = corner.double() + 1.5
    px = torch.stack(
        [pa, pa + torch.stack([n_a, torch.zeros_like(n_a)], 1), pa + torch.stack([torch.zeros_like(n_b), n_b], 1)], 1
    )  # (F, 3, 2) pixels
    uv = torch.stack([px[..., 0] / W, 1.0 - px[..., 1] / H], -1)
    return TextureAtlas(image.reshape(H, W, 3), uv, corner, cell, s)


def export_textured(path, vertices, faces, rest, texture, *, kind: str | None = None, density: float = 1.0):
    """Write a deformed mesh coloured by the solid texture at its rest coordinates.

    ``.ply``: per-vertex 8-bit colours ``texture.at_material(rest)`` (node colouring). ``.glb``:
    the atlas of :func:`build_atlas` embedded as the base-colour texture. ``.obj``: the same
    atlas as ``<name>.png`` beside a ``.mtl``. Atlas files split the vertices per face corner
    (``3 F`` vertices), since each corner has its own UV.

    Args:
        path: the output file.
        vertices: ``(V, 3)`` deformed positions (m).
        faces: ``(F, 3)`` vertex indices.
        rest: ``(V, 3)`` material coordinates (m) of the same vertices.
        texture: a :class:`~torchdeform.texture.synthesis.SolidTexture`.
        kind: ``"ply"``, ``"glb"`` or ``"obj"``; default: the path's suffix.
        density: atlas samples per voxel (see :func:`sample_triangles`).

    Returns:
        the :class:`TextureAtlas` written (``None`` for ``.ply``).

    Raises:
        ConfigError: an unknown suffix or kind, or bad arrays.

    Examples:
        >>> import tempfile, torch, trimesh
        >>> from torchdeform.texture import SolidTexture, liver_exemplar
        >>> tex = SolidTexture(liver_exemplar(size=16), block=8, extent=(24, 24, 24), voxel=0.001)
        >>> sphere = trimesh.creation.icosphere(1, radius=0.005)
        >>> rest = torch.from_numpy(sphere.vertices) + 0.006
        >>> with tempfile.TemporaryDirectory() as d:
        ...     atlas = export_textured(d + "/s.glb", rest * 1.1, sphere.faces, rest, tex)
        ...     loaded = trimesh.load(d + "/s.glb", force="mesh")
        >>> loaded.visual.material.baseColorTexture.size == atlas.to_pil().size
        True
    """
    import trimesh

    path = Path(path)
    k = (kind if kind is not None else path.suffix.lstrip(".")).lower()
    if "." + k not in TEXTURED_SUFFIXES:
        raise ConfigError(
            "textured file",
            "a .ply, .glb or .obj path (or kind 'ply', 'glb', 'obj')",
            got=kind if kind is not None else str(path),
        )
    v = np.asarray(torch.as_tensor(vertices, dtype=torch.float64))
    X = torch.as_tensor(rest, dtype=torch.float64)
    f = np.asarray(torch.as_tensor(faces, dtype=torch.int64))
    if v.ndim != 2 or v.shape[1] != 3 or tuple(X.shape) != v.shape:
        raise ConfigError(
            "surface", "deformed and rest vertices of the same shape (V, 3)", got=(v.shape, tuple(X.shape))
        )
    if k == "ply":
        _, _, _, _, _ = _triangles(X, f, texture, density)  # validates faces
        rgb = (texture.at_material(X).double().clamp(0, 1) * 255).round().to(torch.uint8).numpy()
        colours = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)
        with atomic_path(path) as tmp:
            trimesh.Trimesh(vertices=v, faces=f, vertex_colors=colours, process=False).export(str(tmp), file_type="ply")
        return None
    atlas = build_atlas(X, f, texture, density=density)
    corners = np.arange(3 * len(f)).reshape(-1, 3)
    visual = trimesh.visual.TextureVisuals(uv=atlas.uv.reshape(-1, 2).numpy(), image=atlas.to_pil())
    mesh = trimesh.Trimesh(vertices=v[f.reshape(-1)], faces=corners, visual=visual, process=False)
    if k == "obj":  # the .mtl and texture image it names are written beside it
        mesh.export(str(path), file_type=k)
    else:
        with atomic_path(path) as tmp:
            mesh.export(str(tmp), file_type=k)
    return atlas
