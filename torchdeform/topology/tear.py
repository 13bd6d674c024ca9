"""Tearing and coagulation: springs that break past a strain, and a region whose shape sets.

:func:`tear` breaks every spring stretched beyond ``max_strain`` (``l / l0 - 1``; a number, or a
per-spring / per-tissue tensor ``(1|B, S, D, H, W)``), either all at once or only the most
strained one (ties: the lowest flat index, so the order is deterministic). Radetzky tore when the
spring force passed a limit; for a spring ``k (l - l0)`` that is a strain limit of
``F_max / (k l0)``, which :func:`strain_limit_from_force` gives per spring.

:func:`coagulate` (Radetzky, REFERENCE §6.2): in a region, rest length := current length (the
deformed shape becomes the new rest shape) and the viscosity (spring damping) rises by a factor.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.topology import components
    >>> grid = td.Grid((3, 1, 1), spacing=1.0, topology=6)              # two springs along D
    >>> model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=torch.float64)
    >>> x = model.X.clone()
    >>> x[0, 0, 2] = 2.5                                                 # strains 0 and 0.5
    >>> tear(model, x, max_strain=0.3), components(model)[1]
    (1, 2)
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from ..sim.springs import difference
from .masks import alive, assign, ends, full, remove

__all__ = ["spring_lengths", "spring_strain", "tear", "strain_limit_from_force", "coagulate", "coagulated_rest_length"]


def spring_lengths(grid, x: torch.Tensor) -> torch.Tensor:
    """Current length of every spring slot ``(B, S, D, H, W)`` (zero where the grid has no spring)."""
    d = difference(x, grid)  # (B, S, 3, D, H, W)
    return (d * d).sum(2).sqrt() * grid.spring_mask(device=x.device)


def spring_strain(model, x: torch.Tensor) -> torch.Tensor:
    """``l / l0 - 1`` of every existing spring ``(B, S, D, H, W)``; zero for removed springs and empty slots."""
    l0 = full(model, model.rest_length)
    strain = spring_lengths(model.grid, x) / l0.clamp_min(torch.finfo(x.dtype).tiny) - 1
    return torch.where(alive(model), strain, torch.zeros_like(strain))


def strain_limit_from_force(model, max_force) -> torch.Tensor:
    """Per-spring strain limit ``F_max / (k l0)`` ``(Bp, S, D, H, W)`` for a force limit (N)."""
    k, l0 = full(model, model.stiffness), full(model, model.rest_length)
    return torch.as_tensor(max_force, dtype=k.dtype, device=k.device) / (k * l0).clamp_min(torch.finfo(k.dtype).tiny)


def tear(
    model, x: torch.Tensor, max_strain, *, one_per_step: bool = False, as_tensor: bool = False
) -> int | torch.Tensor:
    """Break the springs strained beyond ``max_strain`` at positions ``x`` (in place); returns how many.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` (its stiffness and damping change; an
            Elastic body's cells around a torn spring die, see :func:`~torchdeform.topology.masks.remove`).
        x: positions ``(B, 3, D, H, W)`` (one tear per batch entry).
        max_strain: a number > 0 or a tensor broadcasting against ``(B, S, D, H, W)``.
        one_per_step: break only the most strained spring of each batch entry.
        as_tensor: return the count as a 0-d int64 tensor on the model's device (not an int):
            on an accelerator the host then reads nothing back and does not wait for the tear.
    """
    if not torch.is_tensor(max_strain) and (not isinstance(max_strain, (int, float)) or not max_strain > 0):
        raise ConfigError("tear.max_strain", "a positive strain (l / l0 - 1)", got=max_strain)
    strain = spring_strain(model, x)
    over = strain > max_strain
    if one_per_step:
        flat = torch.where(over, strain, torch.full_like(strain, -torch.inf)).flatten(1)
        top = flat.argmax(1)  # first of the largest
        # scatter, not an indexed assignment: index_put_ checks its indices on the host (a device wait)
        pick = torch.zeros_like(flat, dtype=torch.bool).scatter_(1, top.unsqueeze(1), True)
        over = over & pick.view_as(over)
    return remove(model, over, as_tensor=as_tensor)


def coagulate(model, x: torch.Tensor, region: torch.Tensor, *, viscosity_factor: float = 1.0) -> int:
    """Springs with both ends in ``region`` take their current length as rest length; damping x factor.

    Args:
        model: the model (its ``rest_length`` and ``damping`` change in place).
        x: positions ``(1, 3, D, H, W)`` (the shape that sets).
        region: bool ``(D, H, W)`` of the coagulated nodes.
        viscosity_factor: >= 1, the rise of the spring damping there.

    Returns:
        the number of springs changed.
    """
    grid = model.grid
    if x.shape[0] != 1:
        raise ConfigError("coagulate.x", "positions of one body (1, 3, D, H, W)", got=tuple(x.shape))
    if not isinstance(viscosity_factor, (int, float)) or not viscosity_factor >= 1:
        raise ConfigError("coagulate.viscosity_factor", "a factor >= 1", got=viscosity_factor)
    region = torch.as_tensor(region, dtype=torch.bool, device=x.device)
    if tuple(region.shape) != grid.shape:
        raise ConfigError("coagulate.region", f"a bool mask of shape {grid.shape}", got=tuple(region.shape))
    at_src, at_dst = ends(grid, region)
    both = at_src & at_dst & alive(model)
    assign(model, "rest_length", coagulated_rest_length(model, x, both))
    if model.damping is not None and viscosity_factor != 1:
        assign(
            model,
            "damping",
            torch.where(both, full(model, model.damping) * viscosity_factor, full(model, model.damping)),
        )
    return int(both.sum())


def coagulated_rest_length(model, x: torch.Tensor, springs: torch.Tensor) -> torch.Tensor:
    """Rest lengths ``(Bp, S, D, H, W)`` with the ``springs`` (bool, broadcasting) set to their lengths at ``x``.

    A function (differentiable in ``x`` and the model's rest lengths), the model is not changed.
    """
    return torch.where(springs, spring_lengths(model.grid, x), full(model, model.rest_length))
