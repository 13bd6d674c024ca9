"""Triangle meshes: voxelise closed meshes, extract surfaces, rasterise them, save them.

=====================  ===========================================================================
:mod:`.surfaces`       closed meshes voxelised into node masks (:func:`voxelize`,
                       :func:`grid_from_mesh`, the ray-parity :func:`inside_mask`), surfaces of
                       bodies and volumes by marching tetrahedra, :func:`save_surface` (trimesh)
:mod:`.embed`          surfaces carried by the lattice (:class:`EmbeddedSurface`: rest cells, trilinear
                       weights, deformed positions and normals per frame, .ply/.glb export) and
                       smooth surfaces of label volumes (:func:`label_surfaces`, scikit-image)
:mod:`.raster`         a z-buffer rasteriser on torch: :class:`Camera` (orthographic or
                       perspective), :func:`rasterize` (vertex colours or a solid texture, Lambert
                       shading), :func:`save_png`
=====================  ===========================================================================

trimesh is imported only by the functions that read or write mesh files (scikit-image only by
:func:`label_surfaces`); the rasteriser needs torch alone (PIL for :func:`save_png`).

Example:
    >>> import torch
    >>> from torchdeform.mesh import Camera, body_surface, rasterize
    >>> X = torch.stack(torch.meshgrid(*[torch.arange(4.0)] * 3, indexing="ij"))   # a 4^3 block
    >>> v, f = body_surface(X)
    >>> cam = Camera((1.5, 1.5, 20.0), (1.5, 1.5, 1.5), ortho_height=8.0, size=(32, 32))
    >>> out = rasterize(torch.as_tensor(v), torch.as_tensor(f), cam)
    >>> int((out["face"] >= 0).sum())     # 16 x 16 pixels less two corners marching tetrahedra chamfer
    254
"""

from .embed import EMBEDDED_SUFFIXES, EmbeddedSurface, label_surfaces
from .raster import Camera, rasterize, save_png
from .surfaces import (
    SURFACE_SUFFIXES,
    SURFACE_TOL,
    body_surface,
    grid_from_mesh,
    inside_mask,
    load_mesh,
    marching_tetrahedra,
    save_surface,
    trilinear_weights,
    volume_surface,
    voxelize,
)

__all__ = [
    "voxelize",
    "grid_from_mesh",
    "load_mesh",
    "inside_mask",
    "marching_tetrahedra",
    "body_surface",
    "trilinear_weights",
    "volume_surface",
    "save_surface",
    "SURFACE_TOL",
    "SURFACE_SUFFIXES",
    "EmbeddedSurface",
    "label_surfaces",
    "EMBEDDED_SUFFIXES",
    "Camera",
    "rasterize",
    "save_png",
]
