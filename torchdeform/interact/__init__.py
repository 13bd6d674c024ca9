"""Touching tissue: rigid tools and their contact with the body.

=====================  ===========================================================================
:mod:`.tools`          shapes (sphere, capsule, box, half-space) with signed distances, and tools
                       whose pose (position, orientation) follows a path, a callable or Python
:mod:`.meshes`         any closed triangle mesh as a tool shape (a sampled signed distance field)
:mod:`.reactions`      forces back: each tool's force and torque, supports' reactions
:mod:`.contact`        projection after the step (normal or along the motion; inelastic, Coulomb
                       friction, hold against jitter) and a smooth penalty force; a model takes
                       them as ``Model(..., interactions=[...])``
:mod:`.grasp`          forceps: nodes in the jaws follow the tool while closed
:mod:`.haptic`         a haptic loop: tool pose in, force out at 1 kHz (a local linear contact
                       model between body steps for large bodies)
:mod:`.strain`         strain limiting: springs pulled back into ``[min, max]`` times their rest
                       length by averaged Jacobi corrections (Provot)
:mod:`.palpation`      reading a tool's force series: the direction it works in, block means, its
                       presses (force against indentation) and where the tissue is stiffest
=====================  ===========================================================================

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
from .grasp import Attachment, Grasp
from .haptic import HapticLoop
from .meshes import MeshShape
from .reactions import support_reaction
from .strain import StrainLimit
from .tools import SHAPES as _ANALYTIC
from .tools import Box, Capsule, HalfSpace, Shape, Sphere, Tool

#: shape names of scene files -> classes (the analytic shapes and ``mesh``)
SHAPES = {**_ANALYTIC, "mesh": MeshShape}

__all__ = [
    "Tool",
    "Shape",
    "Sphere",
    "Capsule",
    "Box",
    "HalfSpace",
    "MeshShape",
    "SHAPES",
    "ProjectionContact",
    "PenaltyContact",
    "Grasp",
    "Attachment",
    "StrainLimit",
    "support_reaction",
    "HapticLoop",
]
