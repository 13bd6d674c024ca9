"""The spring operator: the difference stencil ``D`` over a grid and its adjoint.

For a node field ``x`` of shape ``(B, C, D, H, W)``, ``D x`` is the per-spring difference
``x[i + d] - x[i]`` of shape ``(B, S, C, D, H, W)`` (zero where the spring leaves the grid),
and ``D^T f`` maps a per-spring field back to nodes. Every spring computation in torchdeform
(forces, energy, stiffness products for implicit solves, stability bounds, Knoche relaxation,
learning) goes through :func:`accumulate` (the fast path, shifted slices) or the readable
reference :func:`difference_conv` / :func:`adjoint_conv` (``conv3d`` / ``conv_transpose3d``).
Both are tested equal to a plain edge list.

Sign convention: a spring from ``i`` to ``j = i + d`` with tension vector ``f`` (pointing
from ``i`` towards ``j`` when the spring pulls) adds ``+f`` to node ``i`` and ``-f`` to
node ``j``; summed over springs that is ``-D^T f``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from .grid import Grid

__all__ = [
    "stencil_weights",
    "difference_conv",
    "adjoint_conv",
    "take",
    "accumulate",
    "difference",
    "harmonic_mean_of_ends",
    "adjoint",
    "spring_law",
    "tension",
    "spring_forces",
    "spring_forces_conv",
    "spring_energy",
    "node_sums",
    "Linearisation",
    "combine_coefficients",
    "gate_damping",
    "gated_damping",
]


# ------------------------------------------------------------------ reference path
def stencil_weights(grid: Grid, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Convolution weights ``(S, 1, 3, 3, 3)``: ``+1`` at the neighbour, ``-1`` at the centre."""
    w = torch.zeros(grid.S, 1, 3, 3, 3, dtype=dtype, device=device)
    for s, (dd, dh, dw) in enumerate(grid.directions):
        w[s, 0, 1 + dd, 1 + dh, 1 + dw] = 1.0
        w[s, 0, 1, 1, 1] = -1.0
    return w


def difference_conv(x: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Reference ``D x`` with ``conv3d``.

    Args:
        x: node field ``(B, C, D, H, W)``.
        grid: the grid.

    Returns:
        ``(B, S, C, D, H, W)`` with ``[b, s, c, i] = x[b, c, i + d_s] - x[b, c, i]``, zero where
        ``i + d_s`` is outside the grid.
    """
    B, C = x.shape[:2]
    w = stencil_weights(grid, dtype=x.dtype, device=x.device)
    y = F.conv3d(x.reshape(B * C, 1, *grid.shape), w, padding=1)
    y = y.reshape(B, C, grid.S, *grid.shape).transpose(1, 2)
    return y * grid.in_grid_mask(device=x.device)[:, None]


def adjoint_conv(f: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Reference ``D^T f`` with ``conv_transpose3d``.

    Args:
        f: per-spring field ``(B, S, C, D, H, W)``; entries of springs outside the grid are ignored.
        grid: the grid.

    Returns:
        node field ``(B, C, D, H, W)``.
    """
    B, S, C = f.shape[:3]
    f = f * grid.in_grid_mask(device=f.device)[:, None]
    w = stencil_weights(grid, dtype=f.dtype, device=f.device)
    y = F.conv_transpose3d(f.transpose(1, 2).reshape(B * C, S, *grid.shape), w, padding=1)
    return y.reshape(B, C, *grid.shape)


# ------------------------------------------------------------------- fast path
def take(p: torch.Tensor, s: int, src) -> torch.Tensor:
    """Per-spring parameter of half-direction ``s`` over the region ``src``.

    ``p`` has shape ``(Bp, S, 1, 1, 1)`` (one value per direction) or ``(Bp, S, D, H, W)``
    (one per spring); the result broadcasts against ``(B, C, *region)``.
    """
    q = p[:, s : s + 1]
    return q if q.shape[-1] == 1 and q.shape[-3:] == (1, 1, 1) else q[(..., *src)]


def accumulate(grid: Grid, fn: Callable, *fields: torch.Tensor, channels: int | None = None) -> torch.Tensor:
    """Sum a per-spring quantity onto the nodes, one shifted slice per half-direction.

    For each half-direction ``s``, ``fn(s, src, *deltas)`` receives the differences
    ``field[i + d] - field[i]`` over the region ``src`` (shape ``(B, C, *region)``) and returns
    either ``a`` or a pair ``(a, b)``; ``a`` is added at the first endpoint ``i`` and ``b``
    (default ``-a``) at the second endpoint ``i + d``. With ``b = -a`` this is ``-D^T a``.

    Args:
        grid: the grid.
        fn: per-direction function, see above.
        fields: node fields ``(B, C, D, H, W)`` whose differences ``fn`` needs (at least one).
        channels: channel count of the result, default that of ``fields[0]``.

    Returns:
        node field ``(B, channels, D, H, W)``.
    """
    ref = fields[0]
    shape = (ref.shape[0], channels or ref.shape[1]) + grid.shape
    out = torch.zeros(shape, dtype=ref.dtype, device=ref.device)
    traced = torch.compiler.is_compiling()
    for s, (src, dst) in enumerate(grid.stencil):
        deltas = [f[(..., *dst)] - f[(..., *src)] for f in fields]
        res = fn(s, src, *deltas)
        a, b = res if isinstance(res, tuple) else (res, None)
        if traced:
            # Under torch.compile, sums of zero-padded terms: in-place slice updates become a chain of
            # full-field copies (slice_scatter) that takes minutes to compile with their backward.
            # The additions happen in the same order, so the result is the same to the bit.
            out = out + _padded(a, src, grid.shape)
            out = out - _padded(a, dst, grid.shape) if b is None else out + _padded(b, dst, grid.shape)
            continue
        # add_ / sub_ on the slice's view: ``out[i] += a`` would also copy the view back onto itself
        out[(..., *src)].add_(a)
        if b is None:
            out[(..., *dst)].sub_(a)
        else:
            out[(..., *dst)].add_(b)
    return out


def _padded(t: torch.Tensor, region, shape) -> torch.Tensor:
    """``t`` over ``region`` (three slices) of a ``shape`` grid, zero elsewhere."""
    t = t.expand(*t.shape[:-3], *[r.stop - r.start for r in region])
    pad = []
    for r, n in zip(reversed(region), reversed(shape)):
        pad += [r.start, n - r.stop]
    return torch.nn.functional.pad(t, pad)


def difference(x: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Fast ``D x`` with shifted slices; same result as :func:`difference_conv`."""
    out = torch.zeros((x.shape[0], grid.S) + x.shape[1:], dtype=x.dtype, device=x.device)
    for s, (src, dst) in enumerate(grid.stencil):
        out[(slice(None), s, slice(None), *src)] = x[(..., *dst)] - x[(..., *src)]
    return out


def harmonic_mean_of_ends(values: torch.Tensor, grid: Grid, *, spring_mask=None) -> torch.Tensor:
    """Per-node values ``(B, D, H, W)`` to per-spring values ``(B, S, D, H, W)``.

    Each spring gets the harmonic mean ``2 a b / (a + b)`` of its two end nodes (springs in
    series), zero where no spring exists (``spring_mask``, default the grid's) or both ends are
    zero. Differentiable.
    """
    nodes = values.unsqueeze(1)  # (B, 1, D, H, W)
    ends = nodes + difference(nodes, grid)[:, :, 0]  # value at the far end
    here = nodes.expand_as(ends)
    total = here + ends
    safe = torch.where(total > 0, total, torch.ones_like(total))
    out = torch.where(total > 0, 2.0 * here * ends / safe, torch.zeros_like(total))
    mask = grid.spring_mask(device=values.device) if spring_mask is None else spring_mask.to(values.device)
    return out * mask


def adjoint(f: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Fast ``D^T f`` with shifted slices; same result as :func:`adjoint_conv`."""
    out = torch.zeros((f.shape[0],) + f.shape[2:], dtype=f.dtype, device=f.device)
    for s, (src, dst) in enumerate(grid.stencil):
        fs = f[(slice(None), s, slice(None), *src)]
        out[(..., *src)].sub_(fs)  # in place on the views (see accumulate)
        out[(..., *dst)].add_(fs)
    return out


# ------------------------------------------------------------- spring physics
def _length(delta: torch.Tensor) -> torch.Tensor:
    """``|delta|`` over the channel axis, kept ``>= tiny``.

    Coincident nodes then give a zero direction (and zero force direction) instead of NaN, in
    values and gradients.
    """
    sq = (delta * delta).sum(1, keepdim=True)
    return sq.clamp_min(torch.finfo(delta.dtype).tiny).sqrt()


def spring_law(sq, dxdv, k, l0, c, projected: bool, *, law=None, lp=()):
    """The spring law, as coefficients.

    The force on a spring's endpoint ``i`` is ``alpha (x_j - x_i) + beta (v_j - v_i)``, with
    ``alpha = f(l) / l + c ((v_j - v_i) . delta) / l^2`` for projected damping (a dashpot
    along the spring), ``beta = c`` for Radetzky's unprojected damping. The tension ``f`` is Hooke's
    ``k (l - l0)`` or that of a strain-stiffening ``law`` (:mod:`torchdeform.sim.laws`). ``l`` is kept
    ``>= sqrt(tiny)`` so coincident nodes give finite values. Every spring force in torchdeform
    (the slice path, the packed fast path) comes from here.

    Args:
        sq: ``|x_j - x_i|^2``.
        dxdv: ``(x_j - x_i) . (v_j - v_i)`` (ignored when ``c`` is None).
        k: stiffness, broadcastable.
        l0: rest length, broadcastable.
        c: damping, broadcastable, or None.
        projected: damping along the spring (in ``alpha``) if True, else Radetzky's unprojected
            damping (``beta = c``).
        law: a :class:`~torchdeform.sim.laws.SpringLaw`, or None for Hooke's law.
        lp: the law's parameters, broadcastable like ``k``.

    Returns:
        ``(alpha, beta)``; ``beta`` is None unless the damping is unprojected.
    """
    l = sq.clamp_min(torch.finfo(sq.dtype).tiny).sqrt()
    inv_l = 1.0 / l
    # exactly 0 at rest length
    alpha = k * (l - l0) * inv_l if law is None else law.tension(l, l0, k, *lp) * inv_l
    if c is None:
        return alpha, None
    c = gated_damping(c, k)
    if projected:
        return alpha + c * dxdv * (inv_l * inv_l), None
    return alpha, c


def tension(delta, dv, k, l0, c, projected: bool, *, law=None, lp=()) -> torch.Tensor:
    """Tension vector of springs: ``k (l - l0) n`` (or a ``law``'s) plus damping (:func:`spring_law`).

    Args:
        delta: ``x_j - x_i``, ``(B, 3, ...)``.
        dv: ``v_j - v_i`` or ``None``.
        k: stiffness, broadcastable to ``(B, 1, ...)``.
        l0: rest length, broadcastable to ``(B, 1, ...)``.
        c: damping, broadcastable to ``(B, 1, ...)``, or ``None`` (no damping, no cost).
        projected: damping along the spring ``c ((dv . n) n)`` if True, else Radetzky's
            unprojected relative-velocity damping ``c dv``.
        law: a strain-stiffening law (:func:`spring_law`), or None.
        lp: the law's parameters, broadcastable like ``k``.

    Returns:
        ``(B, 3, ...)``: the force on ``i`` (its negative acts on ``j``).
    """
    sq = (delta * delta).sum(1, keepdim=True)
    dxdv = (delta * dv).sum(1, keepdim=True) if c is not None and projected else None
    alpha, beta = spring_law(sq, dxdv, k, l0, c, projected, law=law, lp=lp)
    f = alpha * delta
    return f if beta is None else f + beta * dv


def spring_forces(x, v, grid, k, l0, *, c=None, projected=True, law=None, lp=()) -> torch.Tensor:
    """Node forces of all springs (fast path).

    Args:
        x: positions ``(B, 3, D, H, W)``.
        v: velocities ``(B, 3, D, H, W)`` (unused when ``c`` is None).
        grid: the grid.
        k: stiffness ``(Bk, S, 1|D, 1|H, 1|W)``.
        l0: rest length, same convention.
        c: damping like ``k`` or ``None``.
        projected: damping along the spring if True, else unprojected (see :func:`tension`).
        law: a strain-stiffening law (:mod:`torchdeform.sim.laws`) or None (Hooke).
        lp: the law's parameters, each like ``k``.

    Returns:
        forces ``(B, 3, D, H, W)``.
    """

    def lps(s, src):
        return tuple(take(p, s, src) for p in lp)

    if c is None:
        return accumulate(
            grid,
            lambda s, src, dx: tension(
                dx, None, take(k, s, src), take(l0, s, src), None, projected, law=law, lp=lps(s, src)
            ),
            x,
        )
    return accumulate(
        grid,
        lambda s, src, dx, dv: tension(
            dx, dv, take(k, s, src), take(l0, s, src), take(c, s, src), projected, law=law, lp=lps(s, src)
        ),
        x,
        v,
    )


def spring_forces_conv(x, v, grid, k, l0, *, c=None, projected=True, law=None, lp=()) -> torch.Tensor:
    """Node forces of all springs through the ``conv3d`` reference.

    Same arguments as :func:`spring_forces`.
    """
    delta = difference_conv(x, grid).movedim(2, 1)  # (B, 3, S, D, H, W)
    dv = difference_conv(v, grid).movedim(2, 1) if c is not None else None
    unsq = lambda p: None if p is None else p.unsqueeze(1)  # (Bk, 1, S, ...)
    f = tension(delta, dv, unsq(k), unsq(l0), unsq(c), projected, law=law, lp=tuple(map(unsq, lp)))
    return -adjoint_conv(f.movedim(1, 2), grid)


def spring_energy(x, grid, k, l0, *, law=None, lp=()) -> torch.Tensor:
    """Elastic energy ``sum 1/2 k (l - l0)^2`` (or a ``law``'s) per batch entry, ``(B,)``."""
    B = x.shape[0]
    total = x.new_zeros(B)
    for s, (src, dst) in enumerate(grid.stencil):
        l = _length(x[(..., *dst)] - x[(..., *src)])
        ks, l0s = take(k, s, src), take(l0, s, src)
        e = 0.5 * ks * (l - l0s) ** 2 if law is None else law.energy(l, l0s, ks, *(take(p, s, src) for p in lp))
        total = total + e.expand(B, *e.shape[1:]).reshape(B, -1).sum(1)
    return total


def node_sums(grid, p) -> torch.Tensor:
    """Sum of a per-spring quantity over the springs touching each node, ``(Bp, 1, D, H, W)``.

    Used for Gershgorin bounds (``sum_j k_ij`` per node).
    """
    zeros = torch.zeros((p.shape[0], 1) + grid.shape, dtype=p.dtype, device=p.device)

    def both_ends(s, src, _):
        q = take(p, s, src).expand(p.shape[0], 1, *[sl.stop - sl.start for sl in src])
        return q, q

    return accumulate(grid, both_ends, zeros)


class Linearisation:
    """Springs linearised at a state, for stiffness products ``K u`` without a matrix.

    Per spring, ``-dF/dx`` acts as ``D^T [a Du + (f' - a) n (n . Du)]`` with ``a = max(f / l, 0)``
    and ``f' = df/dl`` (Hooke: ``a = k max(1 - l0 / l, 0)``, ``f' = k``): the exact Jacobian, except
    that the compressive part is clamped to zero (only in this matrix, never in the force) so the
    operator stays positive semi-definite.

    Args:
        x: positions ``(B, 3, D, H, W)`` to linearise at.
        grid, k, l0: as in :func:`spring_forces`.
        clamp: clamp the compressive term (default True).
        law: a strain-stiffening law (:func:`spring_forces`), or None.
        lp: the law's parameters, broadcastable like ``k``.
    """

    def __init__(self, x, grid, k, l0, *, clamp=True, law=None, lp=()):
        self.grid = grid
        self.parts = []
        #: stiffness per spring: damping given per direction is gated by it (see :func:`gate_damping`)
        self.gated = k.shape[-3:] != (1, 1, 1)
        for s, (src, dst) in enumerate(grid.stencil):
            delta = x[(..., *dst)] - x[(..., *src)]
            l = _length(delta)
            ks, l0s = take(k, s, src), take(l0, s, src)
            if law is None:
                a, slope = ks * (1 - l0s / l), ks
            else:
                ps = tuple(take(p, s, src) for p in lp)
                a, slope = law.tension(l, l0s, ks, *ps) / l, law.slope(l, l0s, ks, *ps)
            if clamp:
                a = a.clamp_min(0)
            self.parts.append((delta / l, a, slope - a))

    #: True for the operator of :meth:`scaled` (coefficients already combined).
    combined = False

    def scaled(self, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> Linearisation:
        """The operator ``u -> apply(u, alpha_scale, c, projected, c_scale)``, combined once.

        Its per-spring coefficients are combined once, for many products with the same scales,
        as in CG.
        """
        out = object.__new__(type(self))
        out.grid, out.combined, out.parts, out.gated = self.grid, True, [], self.gated
        for s, (src, _) in enumerate(self.grid.stencil):
            n, a, b = self.parts[s]
            out.parts.append(
                (
                    n,
                    *combine_coefficients(
                        a,
                        b,
                        alpha_scale=alpha_scale,
                        c=self._damping(c, s, src, a, b),
                        projected=projected,
                        c_scale=c_scale,
                    ),
                )
            )
        return out

    def _damping(self, c, s, src, a, b):
        """The damping of half-direction ``s`` (gated where the stiffness is per spring), or None."""
        if c is None:
            return None
        cs = take(c, s, src)
        return gate_damping(cs, a + b) if self.gated and cs.shape[-3:] == (1, 1, 1) else cs  # a + b = f' = 0 iff k = 0

    def apply(self, u: torch.Tensor, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> torch.Tensor:
        """``(h2 K + h C) u`` as a node field ``(B, 3, D, H, W)``.

        ``h2 = alpha_scale`` and ``h = c_scale``; ``K = -dF/dx`` (clamped) and ``C = -dF/dv``
        (damping ``c`` or none).
        """

        def fn(s, src, du):
            n, a, b = self.parts[s]
            alpha, beta = combine_coefficients(
                a, b, alpha_scale=alpha_scale, c=self._damping(c, s, src, a, b), projected=projected, c_scale=c_scale
            )
            return alpha * du + beta * (n * du).sum(1, keepdim=True) * n

        return -accumulate(self.grid, fn, u)


def _times(scale, t):
    return t if isinstance(scale, (int, float)) and scale == 1 else scale * t


def _needs_gate(k, c) -> bool:
    """Stiffness per spring, damping not: a removed spring's damping must be gated out."""
    return torch.is_tensor(k) and torch.is_tensor(c) and k.numel() > c.numel()


def gated_damping(c, k):
    """The damping ``c`` that springs of stiffness ``k`` apply (``c`` may be None).

    Gated (:func:`gate_damping`) where the stiffness is per spring and the damping is not, else
    ``c`` itself.
    """
    return gate_damping(c, k) if c is not None and _needs_gate(k, c) else c


def gate_damping(c, k):
    """Damping ``c`` where the stiffness ``k`` is not zero: a removed spring (cut, torn) damps nothing.

    So a cut needs to zero only the stiffness, and damping stored per direction stays as it is
    (:meth:`~torchdeform.sim.packed.PackedModel.share`). Applied only where the stiffness is per
    spring and the damping is not (elsewhere it changes nothing and would cost a select per spring).
    """
    return torch.where(k != 0, c, torch.zeros((), dtype=c.dtype, device=c.device))


def combine_coefficients(a, b, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0):
    """``(alpha, beta)`` of one linearised spring in ``h2 K + h C``.

    ``K``'s coefficients ``a, b`` scaled by ``h2 = alpha_scale``, plus the damping ``h c``
    (``h = c_scale``) on the projected (``beta``) or the full (``alpha``) term. Scales of exactly
    1 and no damping cost nothing.
    """
    alpha, beta = _times(alpha_scale, a), _times(alpha_scale, b)
    if c is not None:
        cs = _times(c_scale, c)
        if projected:
            beta = beta + cs
        else:
            alpha = alpha + cs
    return alpha, beta
