"""Elastic relaxation of a ChainMail deformation.

Red-black projected Jacobi steps of the offsets towards the centroid of the neighbours' offsets
(Knoche) or towards Gibson's goal positions, within the limits; never raises
:func:`relax_energy`, the Dirichlet energy ``1/2 sum |u_j - u_i - b_ij|^2`` of the offsets.

With a link mask (``links``, see :mod:`.limits`) an unlinked neighbour is no neighbour: it is left
out of the centroid, the limits' box and the energy, so the two sides of a cut relax apart.
"""

from __future__ import annotations

import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from ..sim.springs import accumulate
from .limits import RELAX_MODES, Limits, _as_links, _exists, _grid6, _link_values, neighbour_boxes

__all__ = ["relax", "relax_energy", "crease_measure"]


def _goal_shift(grid: Grid, limits: Limits | None, mode: str, dtype, device):
    """Per axis, the goal offset difference along the link.

    0 (centroid) or the middle of ``[min, max]`` minus the spacing (Gibson's goal), ``(3,)`` or
    ``(3, D, H, W)``.
    """
    if mode == "centroid" or limits is None:
        return None
    lo, hi, _ = limits.offset_bounds(dtype=dtype, device=device)
    g = 0.5 * (lo + hi)
    return None if not bool((g != 0).any()) else g


def _goal_vector(goal, s: int, src, like: torch.Tensor) -> torch.Tensor:
    """The goal offset difference of the links of half-direction ``s`` as a vector field.

    It broadcasts against ``like`` ``(B, 3, *region)``: ``goal_s`` on channel ``s``, 0 elsewhere.
    """
    g = _link_values(goal, s, src)
    g = g.expand(like.shape[2:]) if g.dim() else g.expand(like.shape[2:]).clone()
    vec = torch.zeros(like.shape[1:], dtype=like.dtype, device=like.device)
    vec[s] = g
    return vec.unsqueeze(0)


def _residual(u, grid6: Grid, goal, links=None):
    """``sum_j (u_j - u_i - b_ij)`` over existing face neighbours ``(B, 3, D, H, W)``.

    Returned with the neighbour counts ``(1|B, 1, D, H, W)``; ``links``: ``None`` or bool
    ``(1|B, 3, D, H, W)``, the links that exist.
    """
    masks = grid6.spring_mask(device=u.device)
    if links is None:

        def weight(s, src):
            return masks[s][src].to(u.dtype).view(1, 1, *masks[s][src].shape)
    else:

        def weight(s, src):
            return (masks[s][src] & links[(slice(None), s, *src)]).to(u.dtype).unsqueeze(1)

    def fn(s, src, du):
        if goal is not None:
            du = du - _goal_vector(goal, s, src, du)
        return du * (masks[s][src].to(u.dtype) if links is None else weight(s, src))

    r = accumulate(grid6, fn, u)
    ones = torch.ones((1 if links is None else links.shape[0], 1) + grid6.shape, dtype=u.dtype, device=u.device)

    def count(s, src, _):
        m = weight(s, src)
        return m, m

    return r, accumulate(grid6, count, ones)


def relax_energy(
    positions: torch.Tensor,
    grid: Grid,
    *,
    limits: Limits | None = None,
    mode: str = "centroid",
    offsets: bool = False,
    links=None,
) -> torch.Tensor:
    """The energy relaxation lowers, ``(B,)``.

    ``E(u) = 1/2 sum_links |u_j - u_i - b_ij|^2`` over the face-neighbour links, with
    ``u = x - X``. ``b = 0`` for ``mode="centroid"`` (the Dirichlet energy of the offsets,
    REFERENCE 2.4), ``b_ij = (goal_a - h_a) e_a`` for ``mode="goal"`` (zero-length springs to
    Gibson's goal distance ``goal_a = (min_a + max_a) / 2``). ``links``: optional bool link mask
    ``(3, D, H, W)`` or ``(B, 3, D, H, W)``; unlinked pairs add nothing.
    """
    if mode not in RELAX_MODES:
        raise ConfigError("mode", '"centroid" or "goal"', got=mode)
    u = positions if offsets else positions - grid.rest_positions(dtype=positions.dtype, device=positions.device)
    u = u if u.dim() == 5 else u.unsqueeze(0)
    lk = _as_links(links, grid, u.device, u.shape[0])
    return _energy(u, _grid6(grid), _goal_shift(grid, limits, mode, u.dtype, u.device), lk)


def _energy(u: torch.Tensor, g6: Grid, goal, lk) -> torch.Tensor:
    """:func:`relax_energy` ``(B,)`` of offsets ``u`` ``(B, 3, D, H, W)`` with the goal and links resolved."""
    total = u.new_zeros(u.shape[0])
    for s, (src, dst) in enumerate(g6.stencil):
        du = u[(..., *dst)] - u[(..., *src)]
        if goal is not None:
            du = du - _goal_vector(goal, s, src, du)
        e = (du * du).sum(1) * g6.spring_mask(device=u.device)[s][src]
        if lk is not None:
            e = e * lk[(slice(None), s, *src)]
        total = total + 0.5 * e.flatten(1).sum(1)
    return total


def crease_measure(
    positions: torch.Tensor, grid: Grid, *, free=None, offsets: bool = False, links=None
) -> torch.Tensor:
    """Straight-line artefact measure, ``(B,)`` in m^2.

    ``sum_i |c_i - u_i|^2`` over the free elements, where ``c_i`` is the centroid of the offsets
    of ``i``'s face neighbours.

    ChainMail leaves piecewise-linear offsets whose straight segments meet at creases (the
    straight lines running out from the pulled element); along a straight segment the offset
    equals its neighbours' centroid, at a crease it does not, so this sum collects the creases
    and is zero for a smooth (harmonic) field.

    Args:
        positions: ``(B, 3, D, H, W)`` positions (or offsets with ``offsets=True``).
        grid: the grid.
        free: bool ``(D, H, W)`` elements to include (default: all existing elements).
        offsets: ``positions`` are offsets ``u = x - X``.
        links: optional bool link mask ``(3, D, H, W)`` or ``(B, 3, D, H, W)`` (unlinked
            neighbours are not neighbours).
    """
    u = positions if offsets else positions - grid.rest_positions(dtype=positions.dtype, device=positions.device)
    u = u if u.dim() == 5 else u.unsqueeze(0)
    r, deg = _residual(u, _grid6(grid), None, _as_links(links, grid, u.device, u.shape[0]))
    dev = (r / deg.clamp_min(1)) ** 2
    m = _exists(grid, u.device) if free is None else torch.as_tensor(free, dtype=torch.bool).to(u.device)
    return (dev.sum(1) * m).flatten(1).sum(1)


def relax(
    positions: torch.Tensor,
    grid: Grid,
    limits: Limits,
    *,
    steps: int = 1,
    mode: str = "centroid",
    free=None,
    omega: float = 1.0,
    offsets: bool = False,
    links=None,
):
    """Elastic relaxation within the ChainMail limits.

    Each step updates every free element once, red-black (the elements with even ``i + j + k``,
    then the odd ones; all face neighbours of an element have the other colour): the element's
    offset moves by ``omega`` towards its target (the centroid of its face neighbours' offsets,
    Knoche, or the mean of the goal positions its neighbours give it, Gibson) and is clamped into
    the box its neighbours' limits allow.

    Energy: :func:`relax_energy` never increases. For one colour the energy splits into one
    isotropic quadratic per element (neighbours are held), minimised at the target; the limits of
    that element form a box containing its current offset, and moving towards the minimiser by
    ``0 < omega < 2`` and clamping into that box cannot move it further from the minimiser in
    any coordinate. Every limit holds after every half-step (the box is exact while the
    neighbours are held). Knoche's shader updates all elements at once (Jacobi, ping-pong); the
    red-black order is what keeps both properties.

    Args:
        positions: ``(B, 3, D, H, W)`` positions (or offsets with ``offsets=True``), inside the limits.
        grid: the grid.
        limits: the :class:`Limits`.
        steps: relaxation steps (>= 0).
        mode: ``"centroid"`` (Knoche) or ``"goal"`` (Gibson's goal positions: the middle of each
            link's ``[min, max]``; the same as the centroid when that middle is the spacing).
        free: bool ``(D, H, W)`` or ``(B, D, H, W)`` of elements that may move (default all;
            exclude fixed and picked elements, or pass the elements ChainMail moved).
        omega: relaxation factor in ``(0, 2)`` (1: straight to the target).
        offsets: ``positions`` are offsets ``u = x - X`` (and so is the result).
        links: optional bool link mask ``(3, D, H, W)`` or ``(B, 3, D, H, W)``: an unlinked
            neighbour is left out of the centroid, the box and the energy (default all linked).

    Returns:
        ``(positions, energies)``: the relaxed positions (offsets with ``offsets=True``), same
        shape as the input, and the energy (summed over the batch) before and after every step,
        ``steps + 1`` floats.

    Example:
        >>> import torch
        >>> from torchdeform.chainmail import ChainMail, Limits, relax
        >>> from torchdeform.sim.grid import Grid
        >>> g = Grid((9, 9, 9), spacing=1.0)
        >>> cm = ChainMail(g, Limits.from_material(g, compression=0.7, stretch=1.3, shear=0.3))
        >>> r = cm.move([(4, 4, 4)], (2.0, 0.0, 0.0))
        >>> free = torch.ones(9, 9, 9, dtype=torch.bool); free[4, 4, 4] = False   # hold the pick
        >>> x, e = relax(cm.positions(), g, cm.limits, steps=4, free=free)
        >>> all(b <= a for a, b in zip(e, e[1:]))
        True
    """
    if mode not in RELAX_MODES:
        raise ConfigError("mode", '"centroid" or "goal"', got=mode)
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ConfigError("steps", "an integer >= 0", got=steps)
    if not (0 < float(omega) < 2):
        raise ConfigError("omega", "a relaxation factor in (0, 2)", got=omega)
    squeeze = positions.dim() == 4
    x = positions.unsqueeze(0) if squeeze else positions
    dt, dev = x.dtype, x.device
    X = grid.rest_positions(dtype=dt, device=dev)
    u = x if offsets else x - X
    g6 = _grid6(grid)
    lk = _as_links(links, grid, dev, u.shape[0])
    nodes = _exists(grid, dev)
    m = nodes if free is None else torch.as_tensor(free, dtype=torch.bool).to(dev) & nodes
    m = m.view(-1, 1, *grid.shape)
    idx = [torch.arange(n, device=dev) for n in grid.shape]
    parity = (idx[0].view(-1, 1, 1) + idx[1].view(1, -1, 1) + idx[2].view(1, 1, -1)) % 2
    colours = [m & (parity == c).view(1, 1, *grid.shape) for c in (0, 1)]
    bounds = limits.offset_bounds(dtype=dt, device=dev)
    goal = _goal_shift(grid, limits, mode, dt, dev)
    source = nodes.view(1, 1, *grid.shape)
    # the energies stay on the device until the end: one host sync, not one per step
    energies = [_energy(u, g6, goal, lk).sum()]
    for _ in range(steps):
        for colour in colours:
            r, deg = _residual(u, g6, goal, lk)
            target = u + omega * r / deg.clamp_min(1)
            lo, hi = neighbour_boxes(u, grid, bounds, source, links=lk)
            u = torch.where(colour, torch.minimum(torch.maximum(target, lo), hi), u)
        energies.append(_energy(u, g6, goal, lk).sum())
    out = u if offsets else X + u
    return (out[0] if squeeze else out), torch.stack(energies).tolist()
