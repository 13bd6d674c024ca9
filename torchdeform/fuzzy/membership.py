"""Membership functions and hedges, as small learnable modules.

Every membership function (MF) maps a tensor of crisp values ``x`` of any shape to degrees
in ``[0, 1]`` of the same shape. Its parameters are one tensor ``raw`` (an
``nn.Parameter``, ``requires_grad=False`` until the system is made learnable with
``requires_grad_()``); :attr:`params` derives the effective parameters from it so that
constraints hold by construction:

- corner points of trapezoids and triangles are kept ordered with a running maximum
  (``a <= b <= c <= d`` always, also after any gradient step);
- widths (``sigma`` of a Gaussian, ``a`` of a bell) are kept positive with ``abs``;
- the other ordered kinds (zshape, sshape, pishape, lins, linz, rectangle, the x of discrete)
  use the same running maximum, and the other widths the same ``abs`` with a tiny floor.

=============  ========================  ==========================================  ======================
kind           parameters (our order)    membership                                  MATLAB .fis
=============  ========================  ==========================================  ======================
trapezoid      a, b, c, d                rises a..b, 1 on b..c, falls c..d           trapmf [a b c d]
triangle       a, b, c                   rises a..b, falls b..c                      trimf [a b c]
gaussian       mean, sigma               exp(-(x - mean)^2 / (2 sigma^2))            gaussmf [sigma c]
bell           width, slope, center      1 / (1 + |(x - center)/width|^(2 slope))    gbellmf [a b c]
sigmoid        center, slope             1 / (1 + exp(-slope (x - center)))          sigmf [a c]
singleton      value                     1 at x == value, else 0                     singletonmf [v]
zshape         a, b                      1 to a, spline fall a..b, 0 from b          zmf [a b]
sshape         a, b                      0 to a, spline rise a..b, 1 from b          smf [a b]
pishape        a, b, c, d                smf(a, b) * zmf(c, d)                       pimf [a b c d]
dsigmoid       a1, c1, a2, c2            |f1 - f2|, f_k = sigmoid(a_k (x - c_k))    dsigmf [a1 c1 a2 c2]
psigmoid       a1, c1, a2, c2            f1 * f2                                     psigmf [a1 c1 a2 c2]
gaussian2      sigma1, c1, sigma2, c2    left Gaussian below c1, right above c2      gauss2mf [s1 c1 s2 c2]
lins           a, b                      clamp((x - a)/(b - a), 0, 1)                linsmf [a b]
linz           a, b                      clamp((b - x)/(b - a), 0, 1)                linzmf [a b]
ramp           start, end                clamp((x - start)/(end - start), 0, 1)      rampmf [start end]
rectangle      start, end                1 on [start, end], else 0                   rectmf [start end]
concave        inflection, end           |d| / (|d| + relu(sign d (end - x)))        concavemf [i e]
cosine         center, width             0.5 (1 + cos(2 pi (x - center)/width))      cosinemf [c w]
spike          center, width             exp(-|10 (x - center)/width|)               spikemf [c w]
binary         start, direction          1 from start towards direction, else 0      binarymf [s d]
discrete       x1, y1, x2, y2, ...       piecewise linear through (xi, yi)           discretemf [x1 y1 ...]
=============  ========================  ==========================================  ======================

The last seven are fuzzylite's terms (``d = end - inflection`` for concave); their ``.fis``
names are those fuzzylite's FisExporter writes. For the new kinds our order is the ``.fis``
order, so a ``.fis`` line maps straight through.

A vertical side (``a == b`` or ``c == d``) is a shoulder: the degree is 1 from the corner
on, as in MATLAB and scikit-fuzzy. Gradients are finite everywhere (safe denominators and
square roots); at the corners themselves they are one-sided.

Example:
    >>> import torch
    >>> from torchdeform.fuzzy import Trapezoid
    >>> mf = Trapezoid(0.0, 2.0, 4.0, 6.0)
    >>> mf(torch.tensor([1.0, 3.0, 5.5]))
    tensor([0.5000, 1.0000, 0.2500])
    >>> from torchdeform.fuzzy.membership import make
    >>> make("zshape", 2.0, 6.0)(torch.tensor([1.0, 3.0, 5.0]))
    tensor([1.0000, 0.8750, 0.1250])
    >>> make("discrete", 0.0, 0.0, 1.0, 1.0, 3.0, 0.5)(torch.tensor([-1.0, 0.5, 2.0, 9.0]))
    tensor([0.0000, 0.5000, 0.7500, 0.5000])
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
    "ZShape",
    "SShape",
    "PiShape",
    "DiffSigmoid",
    "ProdSigmoid",
    "Gaussian2",
    "LinS",
    "LinZ",
    "Ramp",
    "Rectangle",
    "Concave",
    "Cosine",
    "Spike",
    "Binary",
    "Discrete",
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


def _signed_floor(d: torch.Tensor) -> torch.Tensor:
    """``d`` moved away from 0 to at least ``_TINY`` in magnitude, keeping its sign (0 counts as positive)."""
    return torch.where(d >= 0, d.clamp_min(_TINY), d.clamp_max(-_TINY))


def _s_curve(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """MATLAB's smf on ``a <= b``: 0 up to ``a``, ``2 u^2`` then ``1 - 2 v^2``, 1 from ``b``; a step at a == b.

    ``u = (x - a) / (b - a)`` and ``v = (b - x) / (b - a)``, both clamped to ``[0, 1]``. When
    ``a == b`` the degree is 1 from ``a`` on (MATLAB: ``x >= (a + b) / 2``).
    """
    wide = b > a
    den = torch.where(wide, b - a, torch.ones_like(b))
    u, v = ((x - a) / den).clamp(0.0, 1.0), ((b - x) / den).clamp(0.0, 1.0)
    return torch.where(wide, torch.where(u <= 0.5, 2.0 * u * u, 1.0 - 2.0 * v * v), (x >= a).to(x.dtype))


def _z_curve(x: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """MATLAB's zmf on ``a <= b``: 1 up to ``a``, ``1 - 2 u^2`` then ``2 v^2``, 0 from ``b``; a step at a == b.

    ``u``, ``v`` as in :func:`_s_curve`. When ``a == b`` the degree is 1 up to and including
    ``a`` and 0 after it (MATLAB: ``x <= (a + b) / 2``).
    """
    wide = b > a
    den = torch.where(wide, b - a, torch.ones_like(b))
    u, v = ((x - a) / den).clamp(0.0, 1.0), ((b - x) / den).clamp(0.0, 1.0)
    return torch.where(wide, torch.where(u < 0.5, 1.0 - 2.0 * u * u, 2.0 * v * v), (x <= a).to(x.dtype))


def _transition(s: float, c: float) -> tuple:
    """Where a sigmoid of slope ``s`` and center ``c`` changes: ``c +- 7 / |s|`` (``c +- 1`` for s == 0)."""
    r = 7.0 / abs(s) if s else 1.0
    return c - r, c + r


class _Ordered(MembershipFunction):
    """Base for kinds whose parameters are ordered points (MATLAB requires ``a <= b [<= c <= d]``)."""

    def check(self, values):
        """Raise :class:`ConfigError` unless the points are in ascending order."""
        if any(q < p for p, q in itertools.pairwise(values)):
            raise ConfigError(self.kind, f"points in order {' <= '.join(self.names)}", got=values)

    @property
    def params(self):
        """Points ``(len(names),)``, ordered by a running maximum of ``raw``."""
        return torch.cummax(self.raw, dim=0).values

    def support(self):
        """The transition interval ``(first point, last point)`` (constant degree outside)."""
        v = self.values()
        return v[0], v[-1]


class ZShape(_Ordered):
    """Z-shaped spline ``(a, b)``, MATLAB's ``zmf``: 1 up to ``a``, falls smoothly to 0 at ``b``.

    ``f = 1 - 2 ((x - a)/(b - a))^2`` on ``[a, (a+b)/2]``, ``2 ((b - x)/(b - a))^2`` on
    ``[(a+b)/2, b]``, 1 below and 0 above. ``a <= b`` (running maximum); ``a == b`` is a step,
    1 up to and including ``a`` (MATLAB's zmf for ``a >= b`` steps at ``(a + b)/2``; we refuse
    ``a > b``). Shape: ``x`` any shape -> same shape.
    """

    kind, names = "zshape", ("a", "b")

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return _z_curve(x, p[0], p[1])

    def peak(self):
        """The shoulder ``a`` (degree 1 from there down)."""
        return self.values()[0]


class SShape(_Ordered):
    """S-shaped spline ``(a, b)``, MATLAB's ``smf``: 0 up to ``a``, rises smoothly to 1 at ``b``.

    ``f = 2 ((x - a)/(b - a))^2`` on ``[a, (a+b)/2]``, ``1 - 2 ((b - x)/(b - a))^2`` on
    ``[(a+b)/2, b]``, 0 below and 1 above. ``a <= b`` (running maximum); ``a == b`` is a step,
    1 from ``a`` on (MATLAB's smf for ``a >= b`` steps at ``(a + b)/2``; we refuse ``a > b``).
    Shape: ``x`` any shape -> same shape.
    """

    kind, names = "sshape", ("a", "b")

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return _s_curve(x, p[0], p[1])

    def peak(self):
        """The shoulder ``b`` (degree 1 from there up)."""
        return self.values()[1]


class PiShape(_Ordered):
    """Pi-shaped spline ``(a, b, c, d)``, MATLAB's ``pimf``: ``smf(a, b) * zmf(c, d)``.

    Rises smoothly from 0 at ``a`` to 1 at ``b``, 1 on ``[b, c]``, falls smoothly to 0 at ``d``.
    ``a <= b <= c <= d`` by a running maximum (as the MATLAB documentation's formula and
    scikit-fuzzy require; MATLAB's code, a plain product, also takes ``b > c``: refused here).
    Shape: ``x`` any shape -> same shape.
    """

    kind, names = "pishape", ("a", "b", "c", "d")

    def forward(self, x):
        """Degrees ``smf(x; a, b) * zmf(x; c, d)`` of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return _s_curve(x, p[0], p[1]) * _z_curve(x, p[2], p[3])

    def peak(self):
        """The middle of the plateau, ``(b + c) / 2``."""
        v = self.values()
        return 0.5 * (v[1] + v[2])


class LinS(_Ordered):
    """Linear s-shaped saturation ``(a, b)``, MATLAB's ``linsmf``: 0 below ``a``, linear to 1 at ``b``.

    ``f = clamp((x - a)/(b - a), 0, 1)``; ``a <= b`` (running maximum); ``a == b`` is a step,
    1 from ``a`` on (MATLAB). Shape: ``x`` any shape -> same shape.
    """

    kind, names = "lins", ("a", "b")

    @property
    def is_piecewise_linear(self):
        """Always true."""
        return True

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return _rise(x, p[0], p[1])

    def peak(self):
        """The shoulder ``b``."""
        return self.values()[1]


class LinZ(_Ordered):
    """Linear z-shaped saturation ``(a, b)``, MATLAB's ``linzmf``: 1 below ``a``, linear to 0 at ``b``.

    ``f = clamp((b - x)/(b - a), 0, 1)``; ``a <= b`` (running maximum); ``a == b`` is a step,
    1 below ``a`` and 0 from ``a`` on (MATLAB). Shape: ``x`` any shape -> same shape.
    """

    kind, names = "linz", ("a", "b")

    @property
    def is_piecewise_linear(self):
        """Always true."""
        return True

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        a, b = p[0], p[1]
        wide = b > a
        den = torch.where(wide, b - a, torch.ones_like(b))
        return torch.where(wide, ((b - x) / den).clamp(0.0, 1.0), (x < a).to(x.dtype))

    def peak(self):
        """The shoulder ``a``."""
        return self.values()[0]


class _TwoSigmoids(MembershipFunction):
    """Base for MATLAB's two-sigmoid kinds ``(a1, c1, a2, c2)``: ``f_k = 1 / (1 + exp(-a_k (x - c_k)))``."""

    names = ("a1", "c1", "a2", "c2")

    def _both(self, x):
        p = self.params.to(x.dtype)
        return torch.sigmoid(p[0] * (x - p[1])), torch.sigmoid(p[2] * (x - p[3]))

    def support(self):
        """The union of both sigmoids' transitions ``c_k +- 7 / |a_k|`` (constant degree outside)."""
        a1, c1, a2, c2 = self.values()
        (l1, h1), (l2, h2) = _transition(a1, c1), _transition(a2, c2)
        return min(l1, l2), max(h1, h2)

    def peak(self):
        """The largest degree on 2001 points over :meth:`support` (its first point where several tie)."""
        return _grid_peak(self)


class DiffSigmoid(_TwoSigmoids):
    """Difference of sigmoids ``(a1, c1, a2, c2)``, MATLAB's ``dsigmf``: ``|f1(x) - f2(x)|``.

    ``f_k = 1 / (1 + exp(-a_k (x - c_k)))``. The absolute value is MATLAB's (``dsigmf.m``) and
    fuzzylite's (SigmoidDifference); scikit-fuzzy's dsigmf returns the signed ``f1 - f2``.
    A bump for ``a1, a2 > 0`` and ``c1 < c2``. Shape: ``x`` any shape -> same shape.
    """

    kind = "dsigmoid"

    def forward(self, x):
        """Degrees ``|f1 - f2|`` of ``x`` (any shape, same shape out)."""
        f1, f2 = self._both(x)
        return (f1 - f2).abs()


class ProdSigmoid(_TwoSigmoids):
    """Product of sigmoids ``(a1, c1, a2, c2)``, MATLAB's ``psigmf``: ``f1(x) * f2(x)``.

    ``f_k = 1 / (1 + exp(-a_k (x - c_k)))``; a bump for ``a1 > 0 > a2`` and ``c1 < c2``.
    Shape: ``x`` any shape -> same shape.
    """

    kind = "psigmoid"

    def forward(self, x):
        """Degrees ``f1 * f2`` of ``x`` (any shape, same shape out)."""
        f1, f2 = self._both(x)
        return f1 * f2


class Gaussian2(MembershipFunction):
    """Two-sided Gaussian ``(sigma1, c1, sigma2, c2)``, MATLAB's ``gauss2mf``.

    ``f = exp(-relu(c1 - x)^2 / (2 sigma1^2)) * exp(-relu(x - c2)^2 / (2 sigma2^2))``: the left
    Gaussian below ``c1``, the right one above ``c2``, 1 in between when ``c1 <= c2``. When
    ``c1 > c2`` both factors act on ``[c2, c1]`` and the maximum is below 1 (MATLAB's documented
    behaviour; scikit-fuzzy refuses ``c1 > c2``). Sigmas kept > 0 (``abs`` and a tiny floor).
    Shape: ``x`` any shape -> same shape.
    """

    kind, names = "gaussian2", ("sigma1", "c1", "sigma2", "c2")

    def check(self, values):
        """Raise :class:`ConfigError` for a zero sigma."""
        if values[0] == 0 or values[2] == 0:
            raise ConfigError(self.kind, "sigma1 != 0 and sigma2 != 0", got=values)

    @property
    def params(self):
        """``(|sigma1|, c1, |sigma2|, c2)`` with the sigmas kept above a tiny positive floor."""
        r = self.raw
        return torch.stack([r[0].abs().clamp_min(_TINY), r[1], r[2].abs().clamp_min(_TINY), r[3]])

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        left = torch.relu(p[1] - x) / p[0]
        right = torch.relu(x - p[3]) / p[2]
        return torch.exp(-0.5 * (left * left + right * right))

    def support(self):
        """``(min(c1, c2) - 4 sigma1, max(c1, c2) + 4 sigma2)``."""
        s1, c1, s2, c2 = self.values()
        return min(c1, c2) - 4 * s1, max(c1, c2) + 4 * s2

    def peak(self):
        """``(c1 + c2)/2`` for ``c1 <= c2``; else the maximiser ``(c1/s1^2 + c2/s2^2) / (1/s1^2 + 1/s2^2)``."""
        s1, c1, s2, c2 = self.values()
        if c1 <= c2:
            return 0.5 * (c1 + c2)
        w1, w2 = 1.0 / s1**2, 1.0 / s2**2
        return (w1 * c1 + w2 * c2) / (w1 + w2)


def _grid_peak(mf: MembershipFunction, n: int = 2001) -> float:
    """The first point of largest degree of ``mf`` on ``n`` points over its support."""
    lo, hi = mf.support()
    with torch.no_grad():
        x = torch.linspace(lo, hi, n, dtype=torch.float64)
        return float(x[torch.argmax(mf(x))])


class Ramp(MembershipFunction):
    """fuzzylite's Ramp ``(start, end)``: linear from 0 at ``start`` to 1 at ``end``.

    ``f = clamp((x - start)/(end - start), 0, 1)``: rising when ``start < end``, falling when
    ``start > end``. ``start == end`` is refused (fuzzylite returns NaN there); during learning
    ``end - start`` is kept at least ``1e-12`` away from 0. Shape: ``x`` any shape -> same shape.
    """

    kind, names = "ramp", ("start", "end")

    def check(self, values):
        """Raise :class:`ConfigError` for ``start == end``."""
        if values[0] == values[1]:
            raise ConfigError(self.kind, "start != end", got=values)

    @property
    def is_piecewise_linear(self):
        """Always true."""
        return True

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return ((x - p[0]) / _signed_floor(p[1] - p[0])).clamp(0.0, 1.0)

    def support(self):
        """The ramp ``(min(start, end), max(start, end))``."""
        s, e = self.values()
        return min(s, e), max(s, e)

    def peak(self):
        """``end``, where the degree reaches 1."""
        return self.values()[1]


class Rectangle(_Ordered):
    """fuzzylite's Rectangle ``(start, end)``: 1 on ``[start, end]``, 0 elsewhere.

    Both ends belong to the rectangle (fuzzylite's convention: degree 1 at ``x == start`` and at
    ``x == end``). ``start <= end`` by a running maximum (fuzzylite gives 0 everywhere for
    ``start > end``; refused here). No gradient with respect to ``x`` or the ends (a step).
    Shape: ``x`` any shape -> same shape.
    """

    kind, names = "rectangle", ("start", "end")

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return ((x >= p[0]) & (x <= p[1])).to(x.dtype)

    def peak(self):
        """The middle ``(start + end) / 2``."""
        s, e = self.values()
        return 0.5 * (s + e)


class Concave(MembershipFunction):
    """fuzzylite's Concave ``(inflection, end)``: a hyperbolic rise (or fall) to 1 at ``end``.

    Rising (``inflection < end``): ``f = (end - inflection) / (2 end - inflection - x)`` below
    ``end``, 1 from ``end`` on. Falling (``inflection > end``): ``f = (inflection - end) /
    (inflection - 2 end + x)`` above ``end``, 1 up to ``end``. The degree is 0.5 at the
    inflection and tends to 0 like ``1/|x|``. ``inflection == end`` is refused (a step in
    fuzzylite); during learning ``|end - inflection|`` is kept at least ``1e-12``.
    Shape: ``x`` any shape -> same shape.
    """

    kind, names = "concave", ("inflection", "end")

    def check(self, values):
        """Raise :class:`ConfigError` for ``inflection == end``."""
        if values[0] == values[1]:
            raise ConfigError(self.kind, "inflection != end", got=values)

    def forward(self, x):
        """Degrees ``|d| / (|d| + relu(sign(d) (end - x)))``, ``d = end - inflection`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        d = _signed_floor(p[1] - p[0])
        w = d.abs()
        return w / (w + torch.relu(torch.sign(d) * (p[1] - x)))

    def support(self):
        """From the end to where the degree drops to 0.01: ``end -+ 99 |end - inflection|``."""
        i, e = self.values()
        r = 99.0 * abs(e - i)
        return (e - r, e) if i < e else (e, e + r)

    def peak(self):
        """``end``, where the degree reaches 1."""
        return self.values()[1]


class Cosine(MembershipFunction):
    """fuzzylite's Cosine ``(center, width)``: ``0.5 (1 + cos(2 pi (x - center) / width))`` on the width.

    0 outside ``[center - width/2, center + width/2]``; smooth (value and slope 0) at the ends.
    ``width > 0`` required (fuzzylite gives 0 everywhere for a negative width); kept > 0 during
    learning by ``abs`` and a tiny floor. Shape: ``x`` any shape -> same shape.
    """

    kind, names = "cosine", ("center", "width")

    def check(self, values):
        """Raise :class:`ConfigError` unless ``width > 0``."""
        if not values[1] > 0:
            raise ConfigError(self.kind, "width > 0", got=values)

    @property
    def params(self):
        """``(center, |width|)`` with ``|width|`` kept above a tiny positive floor."""
        return torch.stack([self.raw[0], self.raw[1].abs().clamp_min(_TINY)])

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        z = (x - p[0]) / p[1]
        inside = z.abs() <= 0.5
        return torch.where(inside, 0.5 * (1.0 + torch.cos(2.0 * math.pi * z.clamp(-0.5, 0.5))), torch.zeros_like(z))

    def support(self):
        """``center +- width / 2``."""
        c, w = self.values()
        return c - 0.5 * w, c + 0.5 * w

    def peak(self):
        """The center."""
        return self.values()[0]


class Spike(MembershipFunction):
    """fuzzylite's Spike ``(center, width)``: ``exp(-|10 (x - center) / width|)``.

    ``width != 0`` (its sign does not matter); kept > 0 during learning by ``abs`` and a tiny
    floor. Shape: ``x`` any shape -> same shape.
    """

    kind, names = "spike", ("center", "width")

    def check(self, values):
        """Raise :class:`ConfigError` for ``width == 0``."""
        if values[1] == 0:
            raise ConfigError(self.kind, "width != 0", got=values)

    @property
    def params(self):
        """``(center, |width|)`` with ``|width|`` kept above a tiny positive floor."""
        return torch.stack([self.raw[0], self.raw[1].abs().clamp_min(_TINY)])

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        return torch.exp(-10.0 * (x - p[0]).abs() / p[1])

    def support(self):
        """``center +- width`` (degree below ``4.6e-5`` outside)."""
        c, w = self.values()
        return c - w, c + w

    def peak(self):
        """The center."""
        return self.values()[0]


class Binary(MembershipFunction):
    """fuzzylite's Binary ``(start, direction)``: 1 from ``start`` on towards ``direction``, else 0.

    ``direction > start``: 1 for ``x >= start``; ``direction < start``: 1 for ``x <= start``
    (fuzzylite's convention: ``start`` itself has degree 1). Only the side of ``direction``
    matters: fuzzylite writes it as ``inf`` or ``-inf``, stored here as ``start + 1`` or
    ``start - 1``. ``direction == start`` is refused (fuzzylite gives 0 everywhere). No gradient
    (a step). Shape: ``x`` any shape -> same shape.
    """

    kind, names = "binary", ("start", "direction")

    def __init__(self, *params):
        if len(params) == 2:
            start, direction = (float(p) if not torch.is_tensor(p) else float(p.detach()) for p in params)
            if math.isinf(direction) and math.isfinite(start):
                params = (start, start + math.copysign(1.0, direction))
        super().__init__(*params)

    def check(self, values):
        """Raise :class:`ConfigError` for ``direction == start``."""
        if values[0] == values[1]:
            raise ConfigError(self.kind, "direction != start", got=values)

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out)."""
        p = self.params.to(x.dtype)
        up = p[1] > p[0]
        return torch.where(up, x >= p[0], (x <= p[0]) & (p[1] < p[0])).to(x.dtype)

    def support(self):
        """The point ``(start, start)`` where the step is."""
        s = self.values()[0]
        return s, s

    def peak(self):
        """``start``."""
        return self.values()[0]


class Discrete(MembershipFunction):
    """fuzzylite's Discrete ``(x1, y1, x2, y2, ...)``: piecewise-linear through the points ``(xi, yi)``.

    Any even number (at least 2) of parameters, ``x1 <= x2 <= ...`` (running maximum) and every
    ``yi`` in ``[0, 1]`` (clamped). Below ``x1`` the degree is ``y1``, above the last ``xn`` it is
    ``yn`` (fuzzylite's convention); at a repeated ``x`` (a vertical jump) the first point's ``y``
    holds there, the last one's to the right. Shape: ``x`` any shape -> same shape.
    """

    kind = "discrete"

    def __init__(self, *params):
        if len(params) < 2 or len(params) % 2:
            raise ConfigError(self.kind, "an even number (>= 2) of parameters x1, y1, x2, y2, ...", got=list(params))
        self.names = tuple(f"{c}{i}" for i in range(1, len(params) // 2 + 1) for c in "xy")
        super().__init__(*params)

    def check(self, values):
        """Raise :class:`ConfigError` unless the x are ascending and every y is in ``[0, 1]``."""
        xs, ys = values[0::2], values[1::2]
        if any(q < p for p, q in itertools.pairwise(xs)):
            raise ConfigError(self.kind, "x values in ascending order x1 <= x2 <= ...", got=values)
        if not all(0.0 <= y <= 1.0 for y in ys):
            raise ConfigError(self.kind, "y values in [0, 1]", got=values)

    @property
    def is_piecewise_linear(self):
        """Always true."""
        return True

    @property
    def params(self):
        """``(x1, y1, x2, y2, ...)``: x ordered by a running maximum, y clamped to ``[0, 1]``."""
        xs = torch.cummax(self.raw[0::2], dim=0).values
        ys = self.raw[1::2].clamp(0.0, 1.0)
        return torch.stack([xs, ys], dim=1).reshape(-1)

    def forward(self, x):
        """Degrees of ``x`` (any shape, same shape out), interpolated linearly between the points."""
        p = self.params.to(x.dtype)
        xs, ys = p[0::2].contiguous(), p[1::2]
        n = xs.numel()
        i = torch.searchsorted(xs, x.detach().contiguous())  # first point with xs[i] >= x
        hi = i.clamp(1, n - 1) if n > 1 else torch.zeros_like(i)
        lo = (hi - 1).clamp_min(0)
        x0, x1, y0, y1 = xs[lo], xs[hi], ys[lo], ys[hi]
        between = x1 > x0
        t = torch.where(between, (x - x0) / torch.where(between, x1 - x0, torch.ones_like(x1)), torch.zeros_like(x))
        inner = y0 + (y1 - y0) * t.clamp(0.0, 1.0)
        exact = ys[i.clamp_max(n - 1)]
        out = torch.where(xs[i.clamp_max(n - 1)] == x, exact, inner)
        out = torch.where(x <= xs[0], ys[0], out)
        return torch.where(x >= xs[-1], ys[-1], out)

    def support(self):
        """The points' span ``(x1, xn)`` (constant degree outside)."""
        v = self.values()
        return v[0], v[-2]

    def peak(self):
        """The middle of the first run of points with the largest ``y``."""
        v = self.values()
        xs, ys = v[0::2], v[1::2]
        top = max(ys)
        first = ys.index(top)
        last = first
        while last + 1 < len(ys) and ys[last + 1] == top:
            last += 1
        return 0.5 * (xs[first] + xs[last])


#: kind -> class
KINDS = {
    cls.kind: cls
    for cls in (
        Trapezoid,
        Triangle,
        Gaussian,
        Bell,
        Sigmoid,
        Singleton,
        ZShape,
        SShape,
        PiShape,
        DiffSigmoid,
        ProdSigmoid,
        Gaussian2,
        LinS,
        LinZ,
        Ramp,
        Rectangle,
        Concave,
        Cosine,
        Spike,
        Binary,
        Discrete,
    )
}


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


#: hedge name -> function on degrees. The first six are fuzzylite's hedges (its definitions,
#: ``extremely`` being its contrast intensifier, not a power); ``cubed`` is Octave's "extremely".
#:
#: ==============  ============================================  ================================
#: name            degree ``m`` becomes                          Octave fuzzy-logic-toolkit code
#: ==============  ============================================  ================================
#: ``very``        ``m^2``                                       ``.2`` ("very")
#: ``somewhat``    ``sqrt(m)``                                   ``.05`` ("somewhat")
#: ``extremely``   ``2 m^2`` below 0.5, ``1 - 2 (1 - m)^2``      none (fuzzylite's Extremely)
#:                 above
#: ``seldom``      ``sqrt(m / 2)`` below 0.5,                    none (fuzzylite's Seldom)
#:                 ``1 - sqrt((1 - m) / 2)`` above
#: ``not``         ``1 - m``                                     a minus sign (applied after the
#:                                                               hedge: ``-k.2`` = not very)
#: ``any``         ``1``                                         none (fuzzylite's Any)
#: ``cubed``       ``m^3``                                       ``.3`` ("extremely")
#: ``very very``   ``m^4`` (two hedges)                          ``.4`` ("very very")
#: ==============  ============================================  ================================
#:
#: Octave raises the degree to the power ``dd / 10`` for any other two-digit fraction ``.dd``
#: (``.01`` is ``m^0.1``, ``.99`` is ``m^9.9``); those powers have no name here.
HEDGES = {
    "very": lambda m: m * m,
    "somewhat": _safe_sqrt,
    "extremely": _extremely,
    "seldom": _seldom,
    "not": lambda m: 1.0 - m,
    "any": torch.ones_like,
    "cubed": lambda m: m * m * m,
}

#: Octave's hedge codes: ``round(100 * fraction)`` of a rule entry -> hedges (a minus sign adds
#: ``"not"`` in front: ``-k.3`` is ``("not", "cubed")``, ``1 - m^3``)
OCTAVE_HEDGES = {5: ("somewhat",), 20: ("very",), 30: ("cubed",), 40: ("very", "very")}


def apply_hedges(mu: torch.Tensor, hedges) -> torch.Tensor:
    """Apply hedges to degrees, innermost first.

    ``("not", "very")`` reads "not very term" and computes ``not(very(mu))`` (Octave's ``-k.2``:
    its NOT comes after the hedge). See :data:`HEDGES` for the names and Octave's codes.

    Args:
        mu: degrees in ``[0, 1]``, any shape.
        hedges: hedge names (keys of :data:`HEDGES`), outermost first.

    Returns:
        The hedged degrees, same shape as ``mu``.
    """
    for h in reversed(tuple(hedges)):
        mu = HEDGES[h](mu)
    return mu
