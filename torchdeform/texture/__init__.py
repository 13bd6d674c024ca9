"""Solid texture (Chen & He 2015) on deforming and cut tissue.

=====================  ===========================================================================
:mod:`.exemplar`       3-D RGB exemplars: .npy/.npz files, folders of slice images, a procedural liver
:mod:`.synthesis`      the indirection texture: blocks of the exemplar at random offsets, looked up
                       with ``grid_sample`` at texture or material coordinates, never materialised
                       unless the seams are blended (``SolidTexture.blend``)
:mod:`.atlas`          Chen & He's triangle-interior sampling (about one sample per voxel), packed
                       into a texture atlas; textured export (.ply vertex colours, .glb/.obj atlas)
:mod:`.commands`       ``torchdeform texture EXEMPLAR --mesh MESH --out OUT``
:mod:`.mapping`        colours on (deformed, cut) surfaces at material coordinates, per vertex and
                       per pixel, rendered with the rasteriser of :mod:`torchdeform.mesh`
:mod:`.seams`          seam blending: Chen & He's per-slice 2-D Poisson editing and a 3-D Poisson
                       blend by CG on the one spring operator; a seam measure, histogram distances
=====================  ===========================================================================
"""

from .atlas import TextureAtlas, TriangleSamples, build_atlas, export_textured, sample_triangles
from .exemplar import as_exemplar, liver_exemplar, load_exemplar
from .mapping import render_textured, vertex_colours
from .seams import histogram_distance, poisson_blend_3d, poisson_blend_slices, seam_jump, seam_measure
from .synthesis import SEAM_METHODS, SolidTexture

__all__ = [
    "as_exemplar",
    "liver_exemplar",
    "load_exemplar",
    "SolidTexture",
    "seam_measure",
    "seam_jump",
    "poisson_blend_3d",
    "poisson_blend_slices",
    "histogram_distance",
    "vertex_colours",
    "render_textured",
    "TextureAtlas",
    "TriangleSamples",
    "build_atlas",
    "export_textured",
    "sample_triangles",
    "SEAM_METHODS",
]
