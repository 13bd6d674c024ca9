"""Cautery: the nodes inside a tool's volume are burnt away with all their springs (Punak).

A removed node keeps its place in the grid but no longer belongs to the body: its springs (and
anchor spring) are gone, its mass is zero and it is constrained, so it neither moves nor pulls on
anything, and gravity no longer acts on it. The mass and momentum that left the body are
returned, so that they can be accounted for: the body's mass after plus the removed mass is the
mass before, and likewise for momentum. ``model.removed`` (bool ``(D, H, W)``) collects the
removed nodes. In an :class:`~torchdeform.sim.material.Elastic` body every cell with a removed
corner dies (no volume term; its springs' shares go, see :mod:`torchdeform.sim.material`), so the
body left is the one built on a node mask without the burnt nodes.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import Sphere, Tool
    >>> grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    >>> burnt = cauterize(model, model.rest_state(), Tool(Sphere(0.005), position=(0.02, 0.01, 0.01)))
    >>> burnt["nodes"], round(burnt["mass_kg"], 9)                 # the top centre node
    (1, 0.001)
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from .masks import assign, ends, remove

__all__ = ["cauterize"]


def cauterize(model, state, tool) -> dict:
    """Remove the nodes inside ``tool`` at the state's positions and time (in place).

    Args:
        model: the :class:`~torchdeform.sim.model.Model` (one body: batch 1).
        state: the current state (positions ``(1, 3, D, H, W)``; the removed nodes' velocities
            are set to zero in place).
        tool: a :class:`~torchdeform.interact.tools.Tool` (anything with ``sdf(x, t) -> (d, n)``).

    Returns:
        ``{"nodes": int, "mass_kg": float, "momentum": (3,) tuple (kg m/s)}`` of what was removed.
    """
    grid = model.grid
    if state.x.shape[0] != 1:
        raise ConfigError("cauterize.state", "one body (batch 1)", got=tuple(state.x.shape))
    dev = state.x.device
    d, _ = tool.sdf(state.x, state.t)
    removed = model.removed
    if removed is None:
        removed = torch.zeros(grid.shape, dtype=torch.bool, device=dev)
    burn = (d[0, 0] < 0) & grid.nodes().to(dev, non_blocking=True) & ~removed
    mass = model.mass.expand(1, 1, *grid.shape)
    b = burn[None, None].to(model.dtype)
    # what leaves the body is reported in numbers: read back in one transfer (one wait for a device)
    nodes, mass_kg, *momentum = torch.cat(
        [
            burn.sum().reshape(1).double(),
            (mass * b).sum().reshape(1).double(),
            (mass * b * state.v).flatten(2).sum(2)[0].double(),
        ]
    ).tolist()
    if nodes == 0:
        return {"nodes": 0, "mass_kg": 0.0, "momentum": (0.0, 0.0, 0.0)}
    out = {"nodes": int(nodes), "mass_kg": mass_kg, "momentum": tuple(momentum)}
    at_src, at_dst = ends(grid, burn)  # springs with an end burnt
    remove(model, at_src | at_dst, nodes=burn)  # an Elastic body's cells with a burnt corner die too
    if model.k_home is not None:
        assign(model, "k_home", model.k_home.expand(1, 1, *grid.shape) * (1 - b))
    # the node leaves the body: no mass, constrained, at rest (written in place where the model is
    # editable, so a compiled step sharing its fields sees it)
    assign(model, "mass", mass * (1 - b))
    model.removed = removed | burn
    assign(model, "constrained", model.constrained | burn)
    free = (~model.constrained).to(model.dtype)[None, None]
    assign(model, "free", free)
    safe = torch.where(model.mass > 0, model.mass, torch.ones_like(model.mass))
    assign(model, "inv_mass", free / safe)
    state.v.mul_(1 - b)
    return out
