"""What every topology change shares: spring fields per slot, removing springs, node sets at spring ends.

Spring parameters may be stored per direction (``(Bp, S, 1, 1, 1)``); a topology change makes them
per spring (``(Bp, S, D, H, W)``, one slot per node and half-direction, see
:attr:`~torchdeform.sim.grid.Grid.stencil`).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((3, 1, 1), spacing=1.0, topology=6)
    >>> a, b = ends(grid, torch.tensor([True, False, False]).view(3, 1, 1))
    >>> (a | b)[0, 0].flatten().tolist()              # along D: only the spring 0-1 has node 0 at an end
    [True, False, False]
"""
from __future__ import annotations

import torch

__all__ = ["full", "alive", "remove", "ends"]


def full(model, p: torch.Tensor) -> torch.Tensor:
    """A spring parameter ``(Bp, S, 1|D, 1|H, 1|W)`` as one value per slot ``(Bp, S, D, H, W)`` (a view)."""
    return p.expand((p.shape[0], model.grid.S) + model.grid.shape)


def alive(model) -> torch.Tensor:
    """Bool ``(Bp, S, D, H, W)``: the slot holds a spring of the grid that still has stiffness."""
    return (full(model, model.stiffness) != 0) & model.grid.spring_mask(model.stiffness.device)


def remove(model, springs: torch.Tensor) -> int:
    """Zero the stiffness and damping of the slots in bool ``springs`` ``(B|1, S, D, H, W)``; how many were alive."""
    count = int((springs & alive(model)).sum())
    keep = (~springs).to(model.dtype)
    model.stiffness = full(model, model.stiffness) * keep
    if model.damping is not None:
        model.damping = full(model, model.damping) * keep
    return count


def ends(grid, nodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A bool node set ``(D, H, W)`` at the two ends of every slot: ``(at_src, at_dst)``, each ``(1, S, D, H, W)``.

    Slots without a spring (the far end outside the box) are False.
    """
    a = torch.zeros((1, grid.S) + grid.shape, dtype=torch.bool, device=nodes.device)
    b = torch.zeros_like(a)
    for s, (src, dst) in enumerate(grid.stencil):
        a[(0, s, *src)] = nodes[src]
        b[(0, s, *src)] = nodes[dst]
    return a, b
