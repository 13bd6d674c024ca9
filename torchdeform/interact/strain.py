"""Strain limiting (Provot 1995; Punak's relaxation constraint, REFERENCE §6.3).

After a step, every spring whose length ``l`` left ``[min_ratio l0, max_ratio l0]`` asks for the
correction that brings it back to the nearest bound: its excess ``e = l - clamp(l)`` split
between its two endpoints along the spring (all of it to the free end when the other is fixed or
dragged, nothing when both are). Each node then moves by the **average** of the corrections its
violating springs ask for (a Jacobi pass). ``passes`` passes per step; velocities follow the
positions (``v += dx / dt``) unless ``update_velocity=False``.

A spring counts as violated only when ``|e| > tol l0`` with ``tol = 64 eps`` of the dtype: a
spring that sits on its bound (after an earlier pass, say) is then neither corrected nor counted
in its nodes' averages according to rounding noise.

The rule itself (:meth:`StrainLimit.rule`) is written once; each layout only sums it onto the nodes
with its own spring operator: the grid layout through :func:`torchdeform.sim.springs.accumulate`
(every spring evaluated once per pass, scattered to both ends), the packed layout of the compiled
step as one sum over the ``2 S`` directions of every core node (:meth:`PackedModel.ends
<torchdeform.sim.packed.PackedModel.ends>`, as :class:`~torchdeform.sim.packed.PackedLinearisation`:
each spring is evaluated from both ends and there is no scatter; under ``torch.compile`` the sum is
one loop over the nodes with the directions as its inner reduction, not ``2 S`` unrolled terms).

A body whose springs are all within bounds is left exactly as it is.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import StrainLimit
    >>> grid = td.Grid((2, 1, 1), spacing=1.0, topology=6)             # one spring along D
    >>> model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=torch.float64)
    >>> x = torch.tensor([0.0, 2.0], dtype=torch.float64).view(1, 1, 2, 1, 1) * torch.tensor(
    ...     [1.0, 0.0, 0.0], dtype=torch.float64).view(1, 3, 1, 1, 1)     # stretched to 2 x rest
    >>> x1, _ = StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=1).project(model, x, torch.zeros_like(x), 0.0, 0.01)
    >>> [round(c, 12) for c in x1[0, 0, :, 0, 0].tolist()]            # both ends move 0.45 in
    [0.45, 1.55]
"""

from __future__ import annotations

import math

import torch

from ..errors import ConfigError
from ..sim.packed import PackedModel
from ..sim.springs import accumulate, take

__all__ = ["StrainLimit"]


class StrainLimit:
    """Keep every spring's length within ``[min_ratio, max_ratio]`` times its rest length.

    Pass it to a model with ``Model(..., interactions=[StrainLimit(...)])``; it runs at the end of
    every step, eager (grid layout) or compiled (:func:`torchdeform.sim.compiled.compiled_step`,
    packed layout), with the same result.

    Args:
        min_ratio: smallest length / rest length, in ``(0, 1]``.
        max_ratio: largest length / rest length, ``>= 1``.
        passes: Jacobi passes per step, ``>= 1``.
        update_velocity: add ``dx / dt`` of the correction to the velocities.

    Examples:
        >>> StrainLimit(min_ratio=0.9, max_ratio=1.1, passes=4).passes
        4
    """

    def __init__(
        self, *, min_ratio: float = 0.9, max_ratio: float = 1.1, passes: int = 4, update_velocity: bool = True
    ):
        for key, v in (("strain_limit.min_ratio", min_ratio), ("strain_limit.max_ratio", max_ratio)):
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(key, "a positive ratio of the rest length", got=v)
        if not min_ratio <= 1 <= max_ratio:
            raise ConfigError("strain_limit", "min_ratio <= 1 <= max_ratio", got=(min_ratio, max_ratio))
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise ConfigError("strain_limit.passes", "an integer >= 1", got=passes)
        self.min_ratio, self.max_ratio, self.passes = float(min_ratio), float(max_ratio), passes
        self.update_velocity = bool(update_velocity)

    def force(self, model, x, v, t):
        """Strain limiting adds no force."""
        return None

    def rule(self, sq, l0, exists, wa, wb):
        """The rule for springs from ``a`` to ``b``, the one both layouts use.

        Endpoint ``a`` asks to move by ``wa * alpha * (x_b - x_a)`` and ``b`` by
        ``wb * alpha * (x_a - x_b)``, each counting ``violated`` towards its average: the excess
        ``e = l - clamp(l, min_ratio l0, max_ratio l0)`` is shared in proportion to the ends'
        free-ness ``wa, wb`` (1 free, 0 fixed or dragged), all of it to the free end when the other
        is constrained and nothing when both are. The spring is violated only when
        ``|e| > tol l0``, ``tol = 64 eps`` of the dtype (on its bound within rounding it asks for
        nothing and is not counted). ``l`` is kept ``>= sqrt(tiny)``, so coincident nodes ask for
        no (finite, zero) move.

        Args:
            sq: ``|x_b - x_a|^2``.
            l0: rest length, broadcastable.
            exists: bool, the spring exists, broadcastable.
            wa: free-ness of ``a``, broadcastable.
            wb: free-ness of ``b``, broadcastable.

        Returns:
            ``(alpha, violated)``, ``violated`` 1 where the spring exists and is out of bounds by
            more than ``tol l0``, else 0.

        Examples:
            >>> import torch
            >>> one = torch.ones(1, dtype=torch.float64)
            >>> limit = StrainLimit(min_ratio=0.9, max_ratio=1.1)
            >>> alpha, n = limit.rule(4 * one, one, one > 0, one, 0 * one)   # l = 2 l0
            >>> round(alpha.item(), 12), n.item()    # the free end a moves 0.45 * 2 = 0.9 towards b
            (0.45, 1.0)
        """
        l = sq.clamp_min(torch.finfo(sq.dtype).tiny).sqrt()
        excess = l - l.clamp(self.min_ratio * l0, self.max_ratio * l0)
        tol = 64 * torch.finfo(sq.dtype).eps
        violated = (exists & (excess.abs() > tol * l0)).to(sq.dtype)
        return excess / l * violated / (wa + wb).clamp_min(1), violated

    def corrections(self, model, x: torch.Tensor) -> torch.Tensor:
        """One Jacobi pass: the average correction each node's violating springs ask for.

        Args:
            model: the model (grid, rest lengths, stiffness as the spring-exists mask, free nodes),
                in the grid layout or packed (:class:`~torchdeform.sim.packed.PackedModel`).
            x: positions ``(B, 3, D, H, W)``, or ``(B, 3, P)`` on a packed model.

        Returns:
            the corrections, shaped like ``x``.
        """
        total = self._packed_sums(model, x) if isinstance(model, PackedModel) else self._grid_sums(model, x)
        # read once per channel: under torch.compile stored, not recomputed by every read
        total = model.keep(total)
        return total[:, :3] / total[:, 3:].clamp_min(1)

    def _grid_sums(self, model, x):
        """Per node, the sum of its corrections and its count of violated springs, ``(B, 4, D, H, W)``."""
        grid = model.grid
        free = torch.ones_like(x[:, :1]) if model.free is None else model.free.expand_as(x[:, :1])

        def fn(s, src, dx):
            wa, wb = free[(..., *src)], free[(..., *grid.stencil[s][1])]
            alpha, violated = self.rule(
                (dx * dx).sum(1, keepdim=True),
                take(model.rest_length, s, src),
                take(model.stiffness, s, src) > 0,
                wa,
                wb,
            )
            step = alpha * dx  # moves a towards b when too long
            return torch.cat([step * wa, violated * wa], 1), torch.cat([-step * wb, violated * wb], 1)

        return accumulate(grid, fn, x, channels=4)

    def _packed_sums(self, pm: PackedModel, x):
        """As :meth:`_grid_sums` on a packed model: one sum over the ``2 S`` directions, ``(B, 4, P)``."""
        x = pm.trace.operand(x)
        dx = pm.ends(x) - pm.blocks(x).unsqueeze(2)  # (B, 3, 2S, N, L)
        sq = dx[:, 0] * dx[:, 0] + dx[:, 1] * dx[:, 1] + dx[:, 2] * dx[:, 2]  # (B, 2S, N, L)
        wa = pm.blocks(pm.free)[:, 0]  # (1, 1, N, L), 0 in the halo
        wb = pm.ends(pm.free)[:, 0]  # (1, 2S, N, L)
        exists = (pm.directed(pm.stiffness) > 0) & (pm.spring_exists > 0)
        alpha, violated = self.rule(sq, pm.directed(pm.rest_length), exists, wa, wb)
        # Channels kept apart (four sums, one loop over the nodes), as PackedLinearisation.apply.
        sums = [(alpha * dx[:, a]).sum(1, keepdim=True) for a in range(3)] + [violated.sum(1, keepdim=True)]
        return pm.spread((torch.cat(sums, 1) * wa).flatten(-2))

    def project(self, model, x, v, t, dt, *, readings=None):
        """``passes`` Jacobi passes on the positions at the end of a step (velocities follow).

        Args:
            model: the model, grid layout or packed.
            x: positions ``(B, 3, D, H, W)`` (``(B, 3, P)`` packed).
            v: velocities, like ``x``.
            t: time (s), unused.
            dt: the step (s), for the velocity update.
            readings: the step's readings, unused (strain limiting measures nothing).
        """
        # read again by the velocity update: under torch.compile stored once, not recomputed
        x0 = x = model.keep(x) if self.update_velocity else x
        for _ in range(self.passes):
            x = x + self.corrections(model, x)
        if self.update_velocity:
            v = v + (x - x0) / dt
        return x, v
