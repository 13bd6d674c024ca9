"""What every topology change shares: spring fields per slot, editing them, node sets at spring ends.

Spring parameters may be stored per direction (``(Bp, S, 1, 1, 1)``); a topology change makes them
per spring (``(Bp, S, D, H, W)``, one slot per node and half-direction, see
:attr:`~torchdeform.sim.grid.Grid.stencil`).

**Editing in place.** A model prepared by :func:`editable` (or shared with a compiled step, see
:meth:`~torchdeform.sim.packed.PackedModel.share`) holds every spring and node field at full size;
topology changes then write into those tensors (:func:`assign`, :func:`remove`) instead of
replacing them, so a compiled step that reads the same storage sees the change with no
recompilation, and a cut costs only the slots it touches. Fields that require grad are never
written in place: they are replaced (the functional path autograd needs).

Slots are given as a bool field ``(B|1, S, D, H, W)``, as a tuple of five index tensors
``(b, s, d, h, w)``, or as a list of :class:`Slab` masks (what the cut search returns: a cut
touches the few layers around the blade, and a mask over those layers is edited with two dense
operations, no index lists).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> grid = td.Grid((3, 1, 1), spacing=1.0, topology=6)
    >>> a, b = ends(grid, torch.tensor([True, False, False]).view(3, 1, 1))
    >>> (a | b)[0, 0].flatten().tolist()              # along D: only the spring 0-1 has node 0 at an end
    [True, False, False]
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ..errors import ConfigError
from ..sim.material import corner_cells, reassemble, spring_cells, surviving_cells

__all__ = ["Slab", "full", "alive", "remove", "drop_cells", "ends", "editable", "assign", "slot_index"]


class Slab(NamedTuple):
    """Slots of batch entry ``batch`` in the layers ``start ..`` along spatial ``axis``: ``mask`` ``(S, ...)``.

    ``mask`` has the grid's shape except along ``axis``, where it spans ``mask.shape[axis + 1]``
    layers from ``start``.
    """

    batch: int
    axis: int
    start: int
    mask: torch.Tensor

    def view(self, field: torch.Tensor) -> torch.Tensor:
        """The part ``(S, ...)`` of a per-slot field ``(B|1, S, D, H, W)`` this slab covers (a view)."""
        f = field[self.batch if field.shape[0] > 1 else 0]
        return f.narrow(self.axis + 1, self.start, self.mask.shape[self.axis + 1])


def full(model, p: torch.Tensor) -> torch.Tensor:
    """A spring parameter ``(Bp, S, 1|D, 1|H, 1|W)`` as one value per slot ``(Bp, S, D, H, W)`` (a view)."""
    return p.expand((p.shape[0], model.grid.S) + model.grid.shape)


def alive(model) -> torch.Tensor:
    """Bool ``(Bp, S, D, H, W)``: the slot holds a spring of the grid that still has stiffness."""
    return (full(model, model.stiffness) != 0) & model.grid.spring_mask(device=model.stiffness.device)


def editable(model):
    """Store ``model``'s spring fields per slot and its node fields per node, so that edits are in place.

    Returns the model (changed in place). A model stepped by a compiled step does not need this:
    ``compiled_step(..., editable=True)`` shares its fields with the step instead.

    Examples:
        >>> import torchdeform as td
        >>> model = editable(td.Model(td.Grid((3, 3, 3), spacing=0.01, topology=6), stiffness=1.0, mass=1e-3))
        >>> tuple(model.stiffness.shape), tuple(model.mass.shape), model.free is not None
        ((1, 3, 3, 3, 3), (1, 1, 3, 3, 3), True)
    """
    shape = model.grid.shape
    for name in ("stiffness", "rest_length", "damping"):
        p = getattr(model, name)
        if p is not None:
            setattr(model, name, full(model, p).clone())
    if model.free is None:
        model.free = (~model.constrained).to(model.dtype)[None, None]
    for name in ("mass", "inv_mass", "free", "k_home"):
        t = getattr(model, name)
        if t is not None:
            setattr(model, name, t.expand(t.shape[0], 1, *shape).clone())
    return model


def assign(model, name: str, value: torch.Tensor) -> None:
    """``model.<name> = value``, written into the existing tensor when the shapes allow it.

    In place when the current field has the full shape of ``value`` and neither requires grad;
    otherwise the attribute is replaced (a compiled step sharing the old tensor would not see it).
    """
    cur = getattr(model, name)
    if cur is not None and _in_place(cur, value):
        cur.copy_(value)
        return
    if model.shared and name in ("rest_length", "damping"):
        raise ConfigError(
            f"model.{name}",
            f"a per-spring {name} shared with the compiled step: "
            f"compiled_step(..., editable=({', '.join(repr(f) for f in model.shared + (name,))}))",
            got="a per-direction one",
            show_got=True,
        )
    setattr(model, name, value)


def slot_index(grid, springs) -> tuple:
    """Slots as five index tensors ``(b, s, d, h, w)``, from a bool field, slabs or such a tuple."""
    if isinstance(springs, tuple):
        return springs
    if isinstance(springs, list):
        springs = _union(grid, springs)
    return springs.nonzero(as_tuple=True)


def _dense(grid, idx: tuple, batch: int, device) -> torch.Tensor:
    out = torch.zeros((batch, grid.S) + grid.shape, dtype=torch.bool, device=device)
    if idx:
        out[idx] = True
    return out


def _union(grid, pieces: list, device=None) -> torch.Tensor:
    """The slots of a list of :class:`Slab` as one bool field ``(B, S, D, H, W)``."""
    device = pieces[0].mask.device if pieces else device
    out = _dense(grid, (), 1 + max((p.batch for p in pieces), default=0), device)
    for piece in pieces:
        piece.view(out).logical_or_(piece.mask)
    return out


def _dense_slots(grid, springs, device) -> torch.Tensor:
    """Slots given in any accepted form as one bool field ``(B, S, D, H, W)``."""
    if torch.is_tensor(springs):
        return springs.to(device=device, dtype=torch.bool)
    if isinstance(springs, tuple):
        n = int(springs[0].max()) + 1 if springs[0].numel() else 1
        return _dense(grid, springs, n, device)
    return _union(grid, springs, device)


def _full_slots(model, t) -> bool:
    """``t`` is a full per-slot field that may be written in place."""
    return (
        t is not None
        and t.dim() == 5
        and tuple(t.shape[1:]) == (model.grid.S,) + model.grid.shape
        and not t.requires_grad
    )


def _slabs(grid, springs) -> list:
    """Slots given in any accepted form as a list of :class:`Slab` (a bool field: one slab per batch entry)."""
    if isinstance(springs, list):
        return springs
    if isinstance(springs, tuple):
        springs = _dense(grid, springs, int(springs[0].max()) + 1 if springs[0].numel() else 1, springs[0].device)
    return [Slab(b, 0, 0, springs[b]) for b in range(springs.shape[0])]


def remove(model, springs, *, nodes: torch.Tensor | None = None, as_tensor: bool = False) -> int | torch.Tensor:
    """Zero the stiffness and damping of the given slots; how many of them held a spring.

    An :class:`~torchdeform.sim.material.Elastic` body (``model.mu_cells``) also loses the cells
    that contain a given slot or a corner in ``nodes``: their volume term goes and the springs are
    re-assembled from the cells left (:func:`drop_cells`), so springs whose cells all died lose
    their stiffness too (they are not counted).

    Args:
        model: the model (changed in place).
        springs: bool ``(B|1, S, D, H, W)``, index tensors ``(b, s, d, h, w)`` (no repeats) or a
            list of :class:`Slab` (they may overlap).
        nodes: bool ``(D, H, W)`` of nodes leaving the body (cautery), whose cells die with them;
            their springs must be among ``springs``.
        as_tensor: return the count as a 0-d int64 tensor on the model's device instead of an
            int: on an accelerator the host then does not wait for the edit.
    """
    count = _remove_springs(model, springs)
    if getattr(model, "mu_cells", None) is not None:
        grid = model.grid
        dead = spring_cells(grid, _dense_slots(grid, springs, model.mu_cells.device))
        if nodes is not None:
            dead = dead | corner_cells(torch.as_tensor(nodes, dtype=torch.bool, device=dead.device))
        if dead.device.type != "cpu" or bool(dead.any()):  # (an accelerator re-assembles without asking)
            drop_cells(model, dead)
    return count if as_tensor else int(count)


def _remove_springs(model, springs) -> torch.Tensor:
    """:func:`remove` of the slots alone: the count as a 0-d tensor."""
    # A spring with zero stiffness has no damping (spring_law): damping per direction stays as it
    # is; damping stored per spring is zeroed too (so the model reads the same either way).
    k, c = model.stiffness, model.damping
    c = c if _full_slots(model, c) and c.shape == k.shape else None
    pieces = _slabs(model.grid, springs)
    nb = 1 + max((p.batch for p in pieces), default=0)
    if _full_slots(model, k) and nb <= k.shape[0]:
        counts = []  # each taken before its slab is zeroed (slabs may overlap); read once at the end
        for piece in pieces:  # two dense operations over the slab's layers
            kv = piece.view(k)
            counts.append(torch.count_nonzero(kv * piece.mask))
            kv.masked_fill_(piece.mask, 0)
            if c is not None:
                piece.view(c).masked_fill_(piece.mask, 0)
        return sum(counts) if counts else torch.zeros((), dtype=torch.int64, device=k.device)
    if model.shared:
        raise ConfigError("remove.springs", f"one cut per batch entry of the model's {k.shape[0]}", got=nb)
    dense = _union(model.grid, pieces, k.device)
    count = (dense & alive(model)).sum()
    keep = (~dense).to(model.dtype)
    model.stiffness = full(model, model.stiffness) * keep
    if model.damping is not None:
        model.damping = full(model, model.damping) * keep
    return count


def drop_cells(model, dead: torch.Tensor) -> None:
    """Kill the ``dead`` cells of an :class:`~torchdeform.sim.material.Elastic` body (in place).

    Their shear and volume moduli become 0 (``model.mu_cells``, ``model.volume[0]`` and ``[2]``) and the
    springs are re-assembled from the live cells (:func:`~torchdeform.sim.material.reassemble`;
    springs left without a live cell lose their stiffness, and their damping where it is stored per
    spring). Written into the existing tensors where the shapes allow it (see :func:`assign`), so a
    step that shares them sees the change.

    Args:
        model: a model with ``mu_cells`` (an Elastic body).
        dead: bool ``(B|1, D-1, H-1, W-1)``: the cells to kill (per batch entry, or for all).
    """
    grid = model.grid
    assign(model, "mu_cells", surviving_cells(model.mu_cells, dead))
    if model.volume is not None:  # the cells' volume and shear moduli
        kappa, h, shear = model.volume
        kept = []
        for cur in (kappa, shear):
            value = surviving_cells(cur, dead)
            if _in_place(cur, value):
                cur.copy_(value)
                value = cur
            kept.append(value)
        model.volume = (kept[0], h, kept[1])
    k = reassemble(grid, full(model, model.stiffness), model.mu_cells, grid.spacing[0])
    assign(model, "stiffness", k)
    c = model.damping
    if _full_slots(model, c):
        assign(model, "damping", torch.where(k != 0, c, torch.zeros_like(c)))


def _in_place(cur: torch.Tensor, value: torch.Tensor) -> bool:
    """``value`` may be written into ``cur`` (same shape and dtype, neither requires grad)."""
    return (
        tuple(cur.shape) == tuple(value.shape)
        and cur.dtype == value.dtype
        and not cur.requires_grad
        and not value.requires_grad
    )


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
