"""Topology as state: cutting, cautery, tearing and coagulation change the body during a run.

Every change is an edit of the model's spring and node fields (stiffness, damping, rest lengths,
masses, constraints), in place where the model is editable or shared with a compiled step
(``compiled_step(..., editable=True)``): a compiled step reads the same tensors, so a cut needs
no recompilation and costs nothing per step afterwards. An
:class:`~torchdeform.sim.material.Elastic` body also loses every cell a change touches (a removed
spring inside it, a removed corner): its volume term goes and the springs are re-assembled from the
cells left (:func:`.masks.remove`; the rule and why in :mod:`torchdeform.sim.material`).

=====================  ===========================================================================
:mod:`.cut`            blades (parallelograms, triangles, the surface a cutting edge sweeps), the
                       springs they cross (a search near the blade only), removing them, gaping
                       (pre-tension), :class:`Scalpel` for a tool's edge that cuts as it moves
:mod:`.tear`           tearing (springs past a strain or force limit break, all at once or the
                       most strained first) and coagulation (a region's deformed shape becomes its
                       rest shape, its viscosity rises)
:mod:`.cautery`        nodes inside a tool's volume burnt away with their springs; the removed mass
                       and momentum returned
:mod:`.split`          adding a node with Radetzky's mass rule (eq. 4.14: mass and momentum kept)
:mod:`.components`     connected components of the body through its remaining springs
:mod:`.surfaces`       one closed surface per side of a cut (rest coordinates per vertex, PLY), and
                       the pieces of a volume render that carves the gap
:mod:`.chainmail`      ChainMail links a blade crosses stop constraining each other
:mod:`.masks`          what they share: per-slot fields, in-place edits, node sets at spring ends
=====================  ===========================================================================

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.topology import Blade, components, cut
    >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    >>> blade = Blade((0.015, -0.01, -0.01), (0.0, 0.05, 0.0), (0.0, 0.0, 0.05))   # between layers 1 and 2
    >>> cut(model, model.X, blade)                          # (3n - 2)^2 springs for 26 neighbours
    100
    >>> labels, count = components(model)
    >>> count
    2
"""

from .cautery import cauterize
from .chainmail import link_crossing, unlink
from .components import components
from .cut import Blade, Scalpel, crossed_slots, crossing, cut, pretension, sides
from .split import add_node, share_mass
from .surfaces import CutSurface, cut_pieces, cut_surfaces, extend_displacement, save_cut_surfaces
from .tear import coagulate, coagulated_rest_length, spring_lengths, spring_strain, strain_limit_from_force, tear

__all__ = [
    "Blade",
    "Scalpel",
    "crossed_slots",
    "crossing",
    "cut",
    "pretension",
    "sides",
    "cauterize",
    "add_node",
    "share_mass",
    "components",
    "tear",
    "coagulate",
    "coagulated_rest_length",
    "spring_lengths",
    "spring_strain",
    "strain_limit_from_force",
    "link_crossing",
    "unlink",
    "CutSurface",
    "cut_surfaces",
    "save_cut_surfaces",
    "extend_displacement",
    "cut_pieces",
]
