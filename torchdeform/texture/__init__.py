"""Solid texture (Chen & He 2015) on deforming and cut tissue (work in progress: the texture issue).

=====================  ===========================================================================
:mod:`.exemplar`       3-D RGB exemplars: .npy/.npz files, folders of slice images, a procedural liver
:mod:`.synthesis`      the indirection texture: blocks of the exemplar at random offsets, looked up
                       with ``grid_sample`` at texture or material coordinates, never materialised
=====================  ===========================================================================
"""
from .exemplar import as_exemplar, liver_exemplar, load_exemplar
from .synthesis import SolidTexture

__all__ = ["as_exemplar", "liver_exemplar", "load_exemplar", "SolidTexture"]
