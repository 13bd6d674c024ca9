"""Bodies of one grid shape stepped as one batch: their models stacked along the batch axis.

A scene of several bodies (:class:`~torchdeform.interact.bodies.Bodies`) steps each body's model
with the integrator, then resolves the contacts. Bodies whose grids share a shape, spacing,
topology and node mask, and whose models differ only in what is stored per batch entry (spring
stiffness and damping, node masses, an Elastic material's cell moduli), are stepped together: one
model holds their parameters stacked along the batch axis (:func:`stack_models`) and one call of
the integrator advances all of them, where a call per body would pay the eager step's fixed cost
(a few hundred small tensor operations) once per body.

What must be shared (:func:`stack_key`): the grid, the dtype and device, the fixed nodes, gravity,
the global decay, the damping mode, Hooke's law; what a stacked model cannot hold refuses it: drags,
loads, home springs, interactions (tools), topology changes, and integrators that read the rest
positions or factor one system for the whole batch (``knoche``, ``projective``, ``adaptive``).
Such bodies are stepped one after the other, as before.

The stacked step is the same arithmetic per batch entry as the separate steps (the integrators act
per entry; implicit Euler's conjugate gradients take per-entry step lengths, so with a fixed number
of iterations the result is the same to rounding, and with a tolerance each entry stops no earlier
than alone).

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> a = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=50.0, mass=1e-3, dtype=torch.float64)
    >>> b = td.Model(td.Grid((3, 3, 3), spacing=0.01, origin=(0.1, 0, 0)), stiffness=80.0, mass=2e-3,
    ...              dtype=torch.float64)
    >>> stack_key(a, "symplectic") == stack_key(b, "symplectic")
    True
    >>> both = stack_models([a, b], [1, 1])
    >>> tuple(both.stiffness.shape[:2]), [float(m) for m in both.mass[:, 0, 0, 0, 0]]
    ((2, 13), [0.001, 0.002])
"""

from __future__ import annotations

import copy

import torch

from ..sim.model import Model

__all__ = ["stack_key", "stack_models", "STACKABLE_INTEGRATORS"]

#: integrators that act on every batch entry on its own (no rest positions, no shared factorisation)
STACKABLE_INTEGRATORS = ("explicit", "symplectic", "verlet", "rk4", "implicit")


def _bytes(t: torch.Tensor | None):
    return None if t is None else (tuple(t.shape), t.detach().cpu().numpy().tobytes())


def stack_key(model: Model, integrator) -> tuple | None:
    """What bodies stepped in one batch must share, or None where ``model`` cannot be stacked.

    ``integrator``: the integrator or its name.
    """
    name = integrator if isinstance(integrator, str) else getattr(integrator, "name", None)
    if name not in STACKABLE_INTEGRATORS:
        return None
    if (
        model.drags
        or model.loads
        or model.interactions
        or model.k_home is not None
        or model.law is not None
        or model.removed is not None
        or model.cut_nodes is not None
        or model.shared
    ):
        return None
    grid = model.grid
    return (
        tuple(grid.shape),
        tuple(grid.spacing),
        grid.topology,
        _bytes(grid.node_mask),
        model.dtype,
        str(model.device),
        model.projected,
        _bytes(model.constrained),
        _bytes(model.rest_length),
        None if model.gravity is None else tuple(model.gravity.flatten().tolist()),
        model.decay,
        None if model.volume is None else float(model.volume[1]),
        model.damping is None,
    )


def _entries(t: torch.Tensor, batch: int, shape: tuple) -> torch.Tensor:
    """``t`` ``(1 or batch, ...)`` broadcast to ``(batch, *shape)``."""
    return t.expand(batch, *shape)


def stack_models(models: list, batches: list) -> Model:
    """One model stepping ``models`` (equal :func:`stack_key`) with ``batches[i]`` entries each, in order.

    The result is a shallow copy of the first model whose per-entry parameters (stiffness, damping,
    masses, inverse masses, an Elastic material's cell moduli) are the models' own, stacked along
    the batch axis: entries ``sum(batches[:i])`` to ``sum(batches[:i + 1])`` are model ``i``'s.
    """
    first = models[0]
    S, shape = first.grid.S, tuple(first.grid.shape)
    stacked = copy.copy(first)

    def cat(get, tail):
        return torch.cat([_entries(get(m), n, tail) for m, n in zip(models, batches)])

    stacked.stiffness = cat(lambda m: m.stiffness, (S, *shape))
    if first.damping is not None:
        stacked.damping = cat(lambda m: m.damping, (S, *shape))
    stacked.mass = cat(lambda m: m.mass, (1, *shape))
    stacked.inv_mass = cat(lambda m: m.inv_mass, (1, *shape))
    if first.volume is not None:
        cells = tuple(n - 1 for n in shape)

        def cell(m, k):
            t = m.volume[k]
            return t if t.dim() == 4 else t.unsqueeze(0)

        kappa = cat(lambda m: cell(m, 0), cells)
        shear = cat(lambda m: cell(m, 2), cells)
        stacked.volume = (kappa, first.volume[1], shear)
        if first.mu_cells is not None and all(m.mu_cells is not None for m in models):
            stacked.mu_cells = cat(lambda m: m.mu_cells if m.mu_cells.dim() == 4 else m.mu_cells.unsqueeze(0), cells)
    return stacked
