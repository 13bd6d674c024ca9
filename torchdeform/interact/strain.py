"""Strain limiting (Provot 1995; Punak's relaxation constraint, REFERENCE §6.3).

After a step, every spring whose length ``l`` left ``[min_ratio l0, max_ratio l0]`` asks for the
correction that brings it back to the nearest bound: its excess ``e = l - clamp(l)`` split
between its two endpoints along the spring (all of it to the free end when the other is fixed or
dragged). Each node then moves by the **average** of the corrections its violating springs ask
for (a Jacobi pass: no scatter, every spring evaluated once per pass through the one spring
operator, :func:`torchdeform.sim.springs.accumulate`). ``passes`` passes per step; velocities
follow the positions (``v += dx / dt``) unless ``update_velocity=False``.

A body whose springs are all within bounds is left exactly as it is.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact import StrainLimit
    >>> grid = td.Grid((2, 1, 1), spacing=1.0, topology=6)             # one spring along D
    >>> model = td.Model(grid, stiffness=1.0, mass=1.0, dtype=torch.float64)
    >>> x = torch.tensor([0.0, 2.0], dtype=torch.float64).view(1, 1, 2, 1, 1) * torch.tensor(
    ...     [1.0, 0.0, 0.0], dtype=torch.float64).view(1, 3, 1, 1, 1)     # stretched to 2 x rest
    >>> x1, _ = StrainLimit(0.9, 1.1, passes=1).project(model, x, torch.zeros_like(x), 0.0, 0.01)
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
    every eager step (the compiled step does not support it yet and falls back to the eager one).

    Args:
        min_ratio: smallest length / rest length, in ``(0, 1]``.
        max_ratio: largest length / rest length, ``>= 1``.
        passes: Jacobi passes per step, ``>= 1``.
        update_velocity: add ``dx / dt`` of the correction to the velocities.

    Examples:
        >>> StrainLimit(0.9, 1.1, passes=4).passes
        4
    """

    def __init__(self, min_ratio: float = 0.9, max_ratio: float = 1.1, passes: int = 4,
                 update_velocity: bool = True):
        for key, v in (("strain_limit.min_ratio", min_ratio), ("strain_limit.max_ratio", max_ratio)):
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(key, "a positive ratio of the rest length", v)
        if not min_ratio <= 1 <= max_ratio:
            raise ConfigError("strain_limit", "min_ratio <= 1 <= max_ratio", (min_ratio, max_ratio))
        if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
            raise ConfigError("strain_limit.passes", "an integer >= 1", passes)
        self.min_ratio, self.max_ratio, self.passes = float(min_ratio), float(max_ratio), passes
        self.update_velocity = bool(update_velocity)

    def force(self, model, x, v, t):
        """Strain limiting adds no force."""
        return None

    def corrections(self, model, x: torch.Tensor) -> torch.Tensor:
        """One Jacobi pass: the average correction ``(B, 3, D, H, W)`` each node's violating springs ask for.

        Args:
            model: the model (grid, rest lengths, stiffness as the spring-exists mask, free nodes).
            x: positions ``(B, 3, D, H, W)``.
        """
        grid = model.grid
        free = torch.ones_like(x[:, :1]) if model.free is None else model.free.expand_as(x[:, :1])

        def fn(s, src, dx):
            dst = grid.stencil[s][1]
            l = dx.norm(dim=1, keepdim=True)
            l0 = take(model.rest_length, s, src)
            exists = take(model.stiffness, s, src) > 0
            excess = l - l.clamp(self.min_ratio * l0, self.max_ratio * l0)
            violated = (exists & (excess != 0)).to(x.dtype)
            wa, wb = free[(..., *src)], free[(..., *dst)]
            share = violated / (wa + wb).clamp_min(1)
            unit = dx / l.clamp_min(torch.finfo(x.dtype).tiny)
            step = excess * unit * share                               # moves a towards b when too long
            return (torch.cat([step * wa, violated * wa], 1), torch.cat([-step * wb, violated * wb], 1))

        total = accumulate(grid, fn, x, channels=4)
        return total[:, :3] / total[:, 3:].clamp_min(1)

    def project(self, model, x, v, t, dt):
        """``passes`` Jacobi passes on the positions at the end of a step (velocities follow).

        Args:
            model: the model (grid layout).
            x: positions ``(B, 3, D, H, W)``.
            v: velocities ``(B, 3, D, H, W)``.
            t: time (s), unused.
            dt: the step (s), for the velocity update.
        """
        if isinstance(model, PackedModel):
            raise ConfigError("interactions", "strain limiting on the grid layout (the eager step); the compiled "
                                              "step does not support it yet", "a packed model")
        x0 = x
        for _ in range(self.passes):
            x = x + self.corrections(model, x)
        if self.update_velocity:
            v = v + (x - x0) / dt
        return x, v
