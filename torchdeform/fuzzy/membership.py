"""Membership functions and hedges, as small learnable modules.

Every membership function (MF) maps a tensor of crisp values ``x`` of any shape to degrees
in ``[0, 1]`` of the same shape. Its parameters are one tensor ``raw`` (an
``nn.Parameter``, ``requires_grad=False`` until the system is made learnable with
``requires_grad_()``); :attr:`params` derives the effective parameters from it so that
constraints hold by construction:

- corner points of trapezoids and triangles are kept ordered with a running maximum
  (``a <= b <= c <= d`` always, also after any gradient step);
- widths (``sigma`` of a Gaussian, ``a`` of a bell) are kept positive with ``abs``.

=============  ======================  ======================================  ===============
kind           parameters (our order)  membership                               MATLAB .fis
=============  ======================  ======================================  ===============
trapezoid      a, b, c, d              rises a..b, 1 on b..c, falls c..d       trapmf [a b c d]
triangle       a, b, c                 rises a..b, falls b..c                  trimf [a b c]
gaussian       mean, sigma             exp(-(x - mean)^2 / (2 sigma^2))        gaussmf [sigma c]
bell           width, slope, center    1 / (1 + |(x - center)/width|^(2 slope))  gbellmf [a b c]
sigmoid        center, slope           1 / (1 + exp(-slope (x - center)))      sigmf [a c]
singleton      value                   1 at x == value, else 0                 singletonmf [v]
=============  ======================  ======================================  ===============

A vertical side (``a == b`` or ``c == d``) is a shoulder: the degree is 1 from the corner
on, as in MATLAB and scikit-fuzzy. Gradients are finite everywhere (safe denominators and
square roots); at the corners themselves they are one-sided.

Example:
    >>> import torch
    >>> from torchdeform.fuzzy import Trapezoid
    >>> mf = Trapezoid(0.0, 2.0, 4.0, 6.0)
    >>> mf(torch.tensor([1.0, 3.0, 5.5]))
    tensor([0.5000, 1.0000, 0.2500])
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import nn

from ..errors import ConfigError

__all__ = [
    "MembershipFunction",
    "Trapezoid",
    "Triangle",
    "Gaussian",
    "Bell",
    "Sigmoid",
    "Singleton",
    "KINDS",
    "make",
    "HEDGES",
    "apply_hedges",
]

_TINY = 1e-12


def _safe_sqrt(t: torch.Tensor) -> torch.Tensor:
    """Sqrt with a finite gradient at 0 (where the gradient is set to 0)."""
    pos = t > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, t, torch.ones_like(t))), torch.zeros_like(t))


def _rise(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """0 below ``lo``, 1 from ``hi`` on, linear in between; a step to 1 at ``lo`` when lo == hi."""
    wide = hi > lo
    den = torch.where(wide, hi - lo, torch.ones_like(hi))
    return torch.where(wide, ((x - lo) / den).clamp(0.0, 1.0), (x >= lo).to(x.dtype))


def _fall(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """1 up to ``lo``, 0 from ``hi`` on, linear in between.

    When lo == hi: 1 up to and including ``lo``, 0 after it.
    """
    wide = hi > lo
    den = torch.where(wide, hi - lo, torch.ones_like(hi))
    return torch.where(wide, ((hi - x) / den).clamp(0.0, 1.0), (x <= lo).to(x.dtype))


class MembershipFunction(nn.Module):
    """Base class: ``kind``, parameter ``names`` in our order, ``raw`` tensor, :meth:`forward`."""

    kind: str = ""
    names: tuple = ()

    def __init__(self, *params):
        super().__init__()
        if len(params) != len(self.names):
            raise ConfigError(self.kind, f"{len(self.names)} parameters ({', '.join(self.names)})", got=list(params))
        values = [float(p) if not torch.is_tensor(p) else float(p.detach()) for p in params]
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(self.kind, "finite parameters", got=values)
        self.check(values)
        self.raw = nn.Parameter(torch.tensor(values, dtype=torch.get_default_dtype()), requires_grad=False)

    def check(self, values: list) -> None:
        """Raise :class:`ConfigError` for parameters that make no sense (overridden)."""

    @property
    def params(self) -> torch.Tensor:
        """Effective parameters ``(len(names),)`` with the constraints applied."""
        return self.raw

    def values(self) -> list:
        """Effective parameters as plain floats (our order)."""
        return [float(v) for v in self.params.detach()]

    @property
    def is_singleton(self) -> bool:
        """Whether this is a point mass (:class:`Singleton`): defuzzified over the positions."""
        return False

    @property
    def is_piecewise_linear(self) -> bool:
        """Whether the membership is piecewise linear (trapezoids and triangles)."""
        return False

    def support(self) -> tuple:
        """An interval outside which the degree is (numerically) zero: used to bound plots."""
        raise NotImplementedError

    def peak(self) -> float:
        """A point where the degree is largest: used for plots and rule summaries."""
        raise NotImplementedError

    def extra_repr(self) -> str:
        """The parameters as ``name=value`` for :meth:`__repr__`."""
        return ", ".join(f"{n}={v:.6g}" for n, v in zip(self.names, self.values()))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.extra_repr()})"


class Trapezoid(MembershipFunction):
    """Trapezoid ``(a, b, c, d)``: 0 up to ``a``, rises to 1 at ``b``, 1 until ``c``, 0 from ``d``.

    Shape: ``x`` any shape -> same shape. Corner points are ordered by a running maximum of
    ``raw`` (so ``a <= b <= c <= d`` holds during learning too).
    """

    kind, names = "trapezoid", ("a", "b", "c", "d")

    def check(self, values):
        """Raise :class:`ConfigError` unless the corner points are in order ``a <= b <= c <= d``."""
        if any(q < p for p, q in itertools.pairwise(values)):
            raise ConfigError(self.kind, "corner points in order a <= b <= c <= d", got=values)

    @property
    def params(self):
        """Corner points ``(4,)`` (``(3,)`` for a triangle), ordered by a running maximum of ``raw``."""
        return torch.cummax(self.raw, dim=0).values

    @property
    def is_piecewise_linear(self):
        """Always true: trapezoids and triangles are piecewise linear."""
        return True

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out): ``min(rise(a, b), fall(c, d))``."""
        p = self.params.to(x.dtype)
        return torch.minimum(_rise(x, p[0], p[1]), _fall(x, p[2], p[3]))

    def support(self):
        """The interval ``(a, d)`` (``(a, c)`` for a triangle)."""
        v = self.values()
        return v[0], v[-1]

    def peak(self):
        """The middle of the plateau, ``(b + c) / 2`` (``b`` for a triangle)."""
        v = self.values()
        return 0.5 * (v[1] + v[-2])


class Triangle(Trapezoid):
    """Triangle ``(a, b, c)``: rises from ``a`` to 1 at ``b`` and falls to 0 at ``c``."""

    kind, names = "triangle", ("a", "b", "c")

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out): ``min(rise(a, b), fall(b, c))``."""
        p = self.params.to(x.dtype)
        return torch.minimum(_rise(x, p[0], p[1]), _fall(x, p[1], p[2]))


class Gaussian(MembershipFunction):
    """Gaussian ``(mean, sigma)``: ``exp(-(x - mean)^2 / (2 sigma^2))``; ``sigma`` kept > 0."""

    kind, names = "gaussian", ("mean", "sigma")

    def check(self, values):
        """Raise :class:`ConfigError` for ``sigma == 0``."""
        if values[1] == 0:
            raise ConfigError(self.kind, "sigma != 0", got=values)

    @property
    def params(self):
        """``(mean, |sigma|)`` with ``|sigma|`` kept above a tiny positive floor."""
        return torch.stack([self.raw[0], self.raw[1].abs().clamp_min(_TINY)])

    def forward(self, x):
        """Degrees ``exp(-(x - mean)^2 / (2 sigma^2))`` of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return torch.exp(-0.5 * ((x - p[0]) / p[1]) ** 2)

    def support(self):
        """``mean +- 4 sigma`` (degree below ``3.4e-4`` outside)."""
        m, s = self.values()
        return m - 4 * s, m + 4 * s

    def peak(self):
        """The mean."""
        return self.values()[0]


class Bell(MembershipFunction):
    """Generalised bell ``(width, slope, center)``: ``1 / (1 + |(x - center)/width|^(2 slope))``."""

    kind, names = "bell", ("width", "slope", "center")

    def check(self, values):
        """Raise :class:`ConfigError` for ``width == 0``."""
        if values[0] == 0:
            raise ConfigError(self.kind, "width != 0", got=values)

    @property
    def params(self):
        """``(|width|, slope, center)`` with ``|width|`` kept above a tiny positive floor."""
        return torch.stack([self.raw[0].abs().clamp_min(_TINY), self.raw[1], self.raw[2]])

    def forward(self, x):
        """Degrees ``1 / (1 + |(x - center)/width|^(2 slope))`` of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        z2 = ((x - p[2]) / p[0]) ** 2
        return 1.0 / (1.0 + torch.exp(p[1] * torch.log(z2.clamp_min(1e-300 if x.dtype == torch.float64 else 1e-38))))

    def support(self):
        """``center +- width 100^(1 / (2 |slope|))`` (degree below about 0.01 outside)."""
        w, s, c = self.values()
        r = w * 100.0 ** (1.0 / (2.0 * abs(s))) if s else w
        return c - r, c + r

    def peak(self):
        """The center."""
        return self.values()[2]


class Sigmoid(MembershipFunction):
    """Sigmoid ``(center, slope)``: ``1 / (1 + exp(-slope (x - center)))``; rises for slope > 0."""

    kind, names = "sigmoid", ("center", "slope")

    def forward(self, x):
        """Degrees ``1 / (1 + exp(-slope (x - center)))`` of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return torch.sigmoid(p[1] * (x - p[0]))

    def support(self):
        """``center +- 7 / |slope|`` (degree below about 0.001 or above 0.999 outside)."""
        c, s = self.values()
        r = 7.0 / abs(s) if s else 1.0
        return c - r, c + r

    def peak(self):
        """``+inf`` for a rising sigmoid (slope > 0), ``-inf`` otherwise."""
        _c, s = self.values()
        return math.inf if s > 0 else -math.inf


class Singleton(MembershipFunction):
    """Singleton ``(value,)``: degree 1 at ``x == value`` and 0 elsewhere.

    As an input term it tests equality (no gradient with respect to ``x``). As an output term
    it is a point mass: an output whose terms are all singletons is defuzzified over the
    singleton positions (centroid = weighted mean of the positions).
    """

    kind, names = "singleton", ("value",)

    @property
    def is_singleton(self):
        """Always true: a singleton is a point mass."""
        return True

    def forward(self, x):
        """Degree 1 where ``x == value`` and 0 elsewhere (any shape, same shape out)."""
        return (x == self.params[0].to(x.dtype)).to(x.dtype)

    def support(self):
        """The point ``(value, value)``."""
        v = self.values()[0]
        return v, v

    def peak(self):
        """The value."""
        return self.values()[0]


#: kind -> class
KINDS = {cls.kind: cls for cls in (Trapezoid, Triangle, Gaussian, Bell, Sigmoid, Singleton)}


def make(kind: str, *params) -> MembershipFunction:
    """A membership function by kind name (see :data:`KINDS`) and parameters in our order."""
    try:
        cls = KINDS[kind]
    except KeyError:
        raise ConfigError("membership function", f"one of {', '.join(KINDS)}", got=kind) from None
    return cls(*params)


# ------------------------------------------------------------------ hedges


def _extremely(m):
    return torch.where(m <= 0.5, 2.0 * m * m, 1.0 - 2.0 * (1.0 - m) ** 2)


def _seldom(m):
    return torch.where(m <= 0.5, _safe_sqrt(0.5 * m), 1.0 - _safe_sqrt(0.5 * (1.0 - m)))


#: hedge name -> function on degrees (fuzzylite's definitions)
HEDGES = {
    "very": lambda m: m * m,
    "somewhat": _safe_sqrt,
    "extremely": _extremely,
    "seldom": _seldom,
    "not": lambda m: 1.0 - m,
    "any": torch.ones_like,
}


def apply_hedges(mu: torch.Tensor, hedges) -> torch.Tensor:
    """Apply hedges to degrees, innermost first.

    ``("not", "very")`` reads "not very term" and computes ``not(very(mu))``.

    Args:
        mu: degrees in ``[0, 1]``, any shape.
        hedges: hedge names (keys of :data:`HEDGES`), outermost first.

    Returns:
        The hedged degrees, same shape as ``mu``.
    """
    for h in reversed(tuple(hedges)):
        mu = HEDGES[h](mu)
    return mu
