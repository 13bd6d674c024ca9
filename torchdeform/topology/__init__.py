"""Topology as state: cutting and connected components (the first part of the topology issue).

=====================  ===========================================================================
:mod:`.cut`            a rectangular blade: which springs its surface crosses, removing them from a
                       model (stiffness and damping set to zero), which side each node lies on
:mod:`.tear`           tearing (springs past a strain or force limit break, all at once or the
                       most strained first) and coagulation (a region's deformed shape becomes its
                       rest shape, its viscosity rises)
:mod:`.cautery`        nodes inside a tool's volume burnt away with their springs; the removed mass
                       and momentum returned
:mod:`.masks`          what they share: spring fields per slot, removing springs, node sets at
                       spring ends
:mod:`.components`     connected components of the body through its remaining springs (label
                       propagation on the stencil)
=====================  ===========================================================================

Swept and progressive blades, mass-conserving node splits (Radetzky's eq. 4.14), the compiled path without recompiling and ChainMail
unlinking come next.

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
from .tear import coagulate, coagulated_rest_length, spring_lengths, spring_strain, strain_limit_from_force, tear

__all__ = ["Blade", "Scalpel", "crossed_slots", "crossing", "cut", "pretension", "sides", "cauterize", "components",
           "tear", "coagulate", "coagulated_rest_length", "spring_lengths", "spring_strain", "strain_limit_from_force"]
__all__ += ["link_crossing", "unlink"]
from .surfaces import CutSurface, cut_pieces, cut_surfaces, extend_displacement, save_cut_surfaces

__all__ += ["CutSurface", "cut_surfaces", "save_cut_surfaces", "extend_displacement", "cut_pieces"]
