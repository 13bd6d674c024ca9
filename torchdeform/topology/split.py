"""Adding a node to the body with Radetzky's mass rule (eq. 4.14): total mass is conserved exactly.

When a topology change adds a node ``n`` joined to a neighbour set ``N``, the new node takes a
share of each neighbour's mass (REFERENCE §6.2)::

    m_n = sum_{i in N} m_i / (|N| + 1),        m_i <- m_i |N| / (|N| + 1)   (i in N)

so ``m_n + sum m_i`` after equals ``sum m_i`` before. The share carries its momentum: the new
node's velocity is ``sum m_i v_i / (|N| + 1) / m_n`` and the neighbours keep theirs, so the
momentum is conserved too. The new springs copy their neighbours' parameters (the mean stiffness
and damping of the body's remaining springs along the same half-direction) with a rest length
shortened by ``1 - gape`` from the current distance, so the new material is under tension, as
Radetzky's springs along a cut were.

On the lattice a node can only be added where the body has a free slot: a node removed earlier
(cautery, :attr:`Model.removed <torchdeform.sim.model.Model>`). Removing a node
(:func:`~torchdeform.topology.cautery.cauterize`) and adding it back are exact inverses in mass
and momentum.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import Sphere, Tool
    >>> from torchdeform.topology import cauterize
    >>> grid = td.Grid((3, 3, 3), spacing=0.01, topology=6)
    >>> model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    >>> state = model.rest_state()
    >>> _ = cauterize(model, state, Tool(Sphere(0.005), position=(0.01, 0.01, 0.01)))   # the centre node
    >>> added = add_node(model, state, (1, 1, 1))
    >>> added["neighbours"], round(added["mass_kg"], 12), round(float(model.mass.sum()), 12)
    (6, 0.000857142857, 0.026)
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from .masks import alive, assign, full

__all__ = ["add_node", "share_mass"]


def share_mass(masses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4.14 for neighbour masses ``(|N|,)``: ``(new node's mass (), neighbours' new masses (|N|,))``.

    Examples:
        >>> m_new, m = share_mass(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
        >>> float(m_new), m.tolist()
        (1.5, [0.75, 1.5, 2.25])
    """
    k = masses.shape[0]
    return masses.sum() / (k + 1), masses * (k / (k + 1))


def add_node(model, state, node, *, neighbours=None, position=None, gape: float = 0.0) -> dict:
    """Add the removed lattice node ``node`` back to the body, joined to ``neighbours`` (in place).

    Args:
        model: the model (one body; masses, springs and constraints change in place).
        state: the state (batch 1); the new node's position and velocity are set in place.
        node: ``(d, h, w)`` of a node in ``model.removed``.
        neighbours: bool ``(D, H, W)`` of the nodes to join, or None for all its stencil neighbours
            that belong to the body.
        position: ``(3,)`` m, or None for the mean of the neighbours' positions.
        gape: the new springs' rest lengths are their current lengths times ``1 - gape``.

    Returns:
        ``{"neighbours": |N|, "mass_kg": m_n, "springs": number of new springs}``.
    """
    grid = model.grid
    node = tuple(int(i) for i in node)
    if len(node) != 3 or not all(0 <= i < n for i, n in zip(node, grid.shape)):
        raise ConfigError("add_node.node", f"a node index (d, h, w) inside the grid {grid.shape}", got=node)
    if model.removed is None or not bool(model.removed[node]):
        raise ConfigError("add_node.node", "a node removed from the body earlier (cautery)", got=node)
    if state.x.shape[0] != 1:
        raise ConfigError("add_node.state", "one body (batch 1)", got=tuple(state.x.shape))
    if not 0 <= float(gape) < 1:
        raise ConfigError("add_node.gape", "a fraction in [0, 1)", got=gape)
    # looked up node by node below: on the host (each look-up on a device would wait for it)
    body = grid.nodes() & ~model.removed.cpu()
    if torch.is_tensor(neighbours):
        neighbours = neighbours.cpu()
    # the stencil neighbours: slot (s, node) joins node -> node + d_s; slot (s, node - d_s) joins the other way
    links = []  # (slot index, neighbour)
    for s, d in enumerate(grid.directions):
        for sign in (1, -1):
            j = tuple(a + sign * b for a, b in zip(node, d))
            if not all(0 <= i < n for i, n in zip(j, grid.shape)) or not bool(body[j]):
                continue
            if neighbours is not None and not bool(neighbours[j]):
                continue
            links.append(((s,) + (node if sign > 0 else j), j))
    if not links:
        raise ConfigError("add_node.neighbours", "at least one neighbour in the body", got=node)
    js = [j for _, j in links]
    mass = full_node(model, "mass")
    m_nb = torch.stack([mass[(0, 0) + j] for j in js])
    v_nb = torch.stack([state.v[(0, slice(None)) + j] for j in js])  # (|N|, 3)
    m_new, m_left = share_mass(m_nb)
    new_mass = mass.clone()
    for j, m in zip(js, m_left):
        new_mass[(0, 0) + j] = m
    new_mass[(0, 0) + node] = m_new
    x_new = (
        torch.stack([state.x[(0, slice(None)) + j] for j in js]).mean(0)
        if position is None
        else state.x.new_tensor(position)
    )
    state.x[(0, slice(None)) + node] = x_new
    state.v[(0, slice(None)) + node] = (m_nb[:, None] * v_nb).sum(0) / (len(js) + 1) / m_new
    # springs: the mean parameters of the body's remaining springs along the same half-direction
    live = alive(model)[0]  # (S, D, H, W)
    k, c, l0 = (
        None if p is None else full(model, p).clone() for p in (model.stiffness, model.damping, model.rest_length)
    )
    for (s, *src), j in links:
        at = (0, s, *src)
        n_s = live[s].sum().clamp_min(1)
        k[at] = (k[0, s] * live[s]).sum() / n_s
        if c is not None:
            c[at] = (c[0, s] * live[s]).sum() / n_s
        l0[at] = (x_new - state.x[(0, slice(None)) + j]).norm() * (1 - gape)
    assign(model, "stiffness", k)
    if c is not None:
        assign(model, "damping", c)
    assign(model, "rest_length", l0)
    # the node rejoins the body: mass, free (unless fixed some other way), not removed
    assign(model, "mass", new_mass)
    removed = model.removed.clone()
    removed[node] = False
    model.removed = removed
    constrained = model.constrained.clone()
    constrained[node] = False
    assign(model, "constrained", constrained)
    free = (~constrained).to(model.dtype)[None, None]
    assign(model, "free", free)
    safe = torch.where(new_mass > 0, new_mass, torch.ones_like(new_mass))
    assign(model, "inv_mass", free / safe)
    return {"neighbours": len(js), "mass_kg": float(m_new), "springs": len(links)}


def full_node(model, name: str) -> torch.Tensor:
    """A node field ``(Bp, 1, 1|D, 1|H, 1|W)`` as ``(Bp, 1, D, H, W)`` (a view)."""
    t = getattr(model, name)
    return t.expand(t.shape[0], 1, *model.grid.shape)
