"""Connected components of the body through its remaining springs.

Label propagation on the stencil: every node starts with its own index; each sweep gives both ends
of every spring the smaller of their labels, then every node the label of the node its label
names (pointer jumping: a label is always a node of the same component), until nothing changes. A spring exists where the model's stiffness is not zero.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> model = td.Model(td.Grid((3, 1, 1), spacing=1.0, topology=6), stiffness=1.0, mass=1.0)
    >>> components(model)[1]
    1
"""

from __future__ import annotations

import torch

from .masks import alive

__all__ = ["components"]


def components(model, *, batch: int = 0) -> tuple[torch.Tensor, int]:
    """``(labels, count)``: the component of every node ``(D, H, W)`` (int64, -1 outside the body).

    Outside the body: outside the grid's node mask, or removed by cautery.

    Labels are the smallest flat node index in each component.

    Args:
        model: the :class:`~torchdeform.sim.model.Model`.
        batch: which batch entry of a batched stiffness.
    """
    grid = model.grid
    shape = grid.shape
    live = alive(model)
    exists = live[min(batch, live.shape[0] - 1)]
    dev = exists.device
    inside = grid.nodes().to(dev)
    if model.removed is not None:  # burnt away (cautery)
        inside = inside & ~model.removed.to(dev)
    big = torch.iinfo(torch.int64).max
    labels = torch.arange(inside.numel(), device=dev).view(shape)
    labels = torch.where(inside, labels, torch.full_like(labels, big))
    flat_inside = inside.view(-1)
    while True:
        new = labels.clone()
        for s, (src, dst) in enumerate(grid.stencil):
            m = exists[(s, *src)]
            a, b = labels[src], labels[dst]
            low = torch.minimum(a, b)
            new[src] = torch.minimum(new[src], torch.where(m, low, a))
            new[dst] = torch.minimum(new[dst], torch.where(m, low, b))
        # pointer jumping: a label is a node of the same component, so take that node's label too
        # (labels spread by doubling strides, not one node per sweep)
        flat = new.view(-1)
        jump = flat[torch.where(flat_inside, flat, torch.zeros_like(flat))]
        new = torch.where(inside, torch.minimum(new, jump.view(shape)), new)
        if torch.equal(new, labels):
            break
        labels = new
    labels = torch.where(inside, labels, torch.full_like(labels, -1))
    return labels, int(torch.unique(labels[inside]).numel())
