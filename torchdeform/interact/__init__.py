"""Touching tissue: rigid tools and their contact with the body.

=====================  ===========================================================================
:mod:`.tools`          shapes (sphere, capsule, box, half-space) with signed distances, and tools
                       that move them along a path, by a callable or from Python
:mod:`.contact`        projection after the step (inelastic, Coulomb friction) and a smooth
                       penalty force; a model takes them as ``Model(..., interactions=[...])``
:mod:`.strain`         strain limiting: springs pulled back into ``[min, max]`` times their rest
                       length by averaged Jacobi corrections (Provot)
=====================  ===========================================================================

This is the first part of the interaction issue: grasping, reaction and haptic forces, scene
sections and the benchmark come next.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import ProjectionContact, Sphere, Tool
    >>> grid = td.Grid((5, 5, 5), spacing=0.01)
    >>> probe = Tool(Sphere(0.01), path=[(0.0, (0.05, 0.02, 0.02)), (0.1, (0.045, 0.02, 0.02))])
    >>> model = td.Model(grid, stiffness=20.0, damping=0.01, mass=1e-3, fixed=grid.face("bottom"),
    ...                  interactions=[ProjectionContact(probe)], dtype=torch.float64)
    >>> state, _ = td.simulate(model, model.rest_state(), dt=1e-3, steps=100)
    >>> d, _ = probe.sdf(state.x, state.t)
    >>> bool(d.min() >= -1e-12)                                     # no node inside the probe
    True
"""
from .contact import PenaltyContact, ProjectionContact
from .strain import StrainLimit
from .tools import SHAPES, Box, Capsule, HalfSpace, Shape, Sphere, Tool

__all__ = ["Tool", "Shape", "Sphere", "Capsule", "Box", "HalfSpace", "SHAPES", "ProjectionContact",
           "PenaltyContact", "StrainLimit"]
