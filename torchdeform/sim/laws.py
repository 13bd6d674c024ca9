"""Strain-stiffening spring laws: the force along a spring as a function of its strain.

Hooke's law ``f = k (l - l0)`` is the default and needs no law object. Soft tissue stiffens with
strain (collagen fibres straighten: the stress-strain curve of skin, liver or vessel wall is close
to exponential, Fung 1967), so a spring may instead follow

=====================  ==========================================================  ===================
law                    tension ``f(e)``, strain ``e = (l - l0) / l0``              ``df/dl``
=====================  ==========================================================  ===================
:class:`Exponential`   ``k l0 (exp(b e) - 1) / b``  (Hooke as ``b -> 0``)          ``k exp(b e)``
:class:`Polynomial`    ``k l0 (e + c2 e |e| + c3 e^3)``                            ``k (1 + 2 c2 |e| + 3 c3 e^2)``
=====================  ==========================================================  ===================

Both have the small-strain stiffness ``k`` at rest (so ``k``, stability bounds at rest and the
fuzzy tissue moduli keep their meaning) and a tangent stiffness ``df/dl > 0`` everywhere for
``b, c2, c3 >= 0``: the energy is convex along the spring. Their parameters (``b``;
``c2, c3``, dimensionless) are spring parameters like the stiffness: one number, one per
direction class or per spring, learnable, or computed (e.g. from a fuzzy system's output).

A :class:`~torchdeform.sim.model.Model` stores the law and its parameters normalised to spring
fields (``model.law``, ``model.law_params``); :func:`~torchdeform.sim.springs.spring_law` (forces),
:class:`~torchdeform.sim.springs.Linearisation` (exact Jacobians for implicit solves) and
:func:`~torchdeform.sim.springs.spring_energy` read them through the three methods every law has.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> law = td.Exponential(stiffening=10.0)
    >>> l, l0, k, b = torch.tensor([1.0, 1.1]), torch.tensor(1.0), torch.tensor(100.0), torch.tensor(10.0)
    >>> law.tension(l, l0, k, b)                     # at rest: 0; 10 % strain: k l0 (e - 1) / 10
    tensor([ 0.0000, 17.1828])
    >>> law.slope(l, l0, k, b)                       # tangent stiffness: k at rest, k e at 10 %
    tensor([100.0000, 271.8282])
"""

from __future__ import annotations

import torch

from ..errors import ConfigError

__all__ = ["SpringLaw", "Exponential", "Polynomial", "LAWS"]


class SpringLaw:
    """A force law of springs: tension, tangent stiffness and energy as functions of the length.

    Every method takes the length ``l``, rest length ``l0``, small-strain stiffness ``k`` and the
    law's parameters (:attr:`params`, in that order), all broadcastable tensors, and is
    differentiable in each of them.

    Attributes:
        name: the law's name in scene files (``[material] law``).
        params: names of the law's spring parameters.
        values: the parameter values given (numbers, class tables or tensors), in :attr:`params`
            order; a model normalises them to spring fields.
    """

    name = "base"
    params: tuple = ()

    def __init__(self, *values):
        self.values = values

    def tension(self, l, l0, k, *p) -> torch.Tensor:
        """Force along the spring (N), positive when it pulls its ends together."""
        raise NotImplementedError  # pragma: no cover

    def slope(self, l, l0, k, *p) -> torch.Tensor:
        """Tangent stiffness ``d tension / dl`` (N/m)."""
        raise NotImplementedError  # pragma: no cover

    def energy(self, l, l0, k, *p) -> torch.Tensor:
        """Elastic energy (J), the integral of the tension from ``l0`` to ``l``."""
        raise NotImplementedError  # pragma: no cover

    def __repr__(self) -> str:
        args = ", ".join(
            f"{n}={v!r}" if not torch.is_tensor(v) else f"{n}=tensor{tuple(v.shape)}"
            for n, v in zip(self.params, self.values)
        )
        return f"{type(self).__name__}({args})"


def _strain(l, l0):
    """``l / l0 - 1``, and 0 where ``l0 = 0`` (the halo of the packed layout, removed springs)."""
    ok = l0 > 0
    return torch.where(ok, l / torch.where(ok, l0, torch.ones_like(l0)) - 1.0, torch.zeros_like(l))


def _positive_part(b):
    """``(b > 0, b where positive else 1)``: a divisor that is never zero, with its mask."""
    pos = b > 0
    return pos, torch.where(pos, b, torch.ones_like(b))


class Exponential(SpringLaw):
    """Exponential stiffening: ``f = k l0 (exp(b e) - 1) / b`` with strain ``e = l / l0 - 1``.

    The tangent stiffness ``k exp(b e)`` grows by ``e^(b e)``: ``b = 10`` makes a spring 2.7 times
    stiffer at 10 % strain and 20 times at 30 %. ``b = 0`` is Hooke's law. In compression the spring
    softens (to ``k exp(-b)`` at zero length) but never loses its stiffness.

    Args:
        stiffening: ``b >= 0`` (dimensionless): a number, a class table ``{"axis": .., "face": ..,
            "body": ..}`` or a tensor of any spring-parameter shape
            (:func:`~torchdeform.sim.model.spring_param`).

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((1, 1, 2), spacing=0.01, topology=6)
        >>> model = td.Model(grid, stiffness=100.0, mass=1e-3, law=td.Exponential(stiffening=10.0), dtype=torch.float64)
        >>> x = model.X.clone()
        >>> x[0, 2, 0, 0, 1] += 0.002                       # 20 % strain
        >>> round(float(model.spring_forces(x, None)[0, 2, 0, 0, 0]), 6)   # k l0 (e^2 - 1) / 10
        0.638906
    """

    name = "exponential"
    params = ("stiffening",)

    def __init__(self, *, stiffening: float | dict | torch.Tensor = 0.0):
        super().__init__(stiffening)

    def tension(self, l, l0, k, b):
        """``k l0 expm1(b e) / b`` (``k l0 e`` where ``b = 0``)."""
        e = _strain(l, l0)
        pos, bs = _positive_part(b)
        return k * l0 * torch.where(pos, torch.expm1(b * e) / bs, e)

    def slope(self, l, l0, k, b):
        """``k exp(b e)``."""
        return k * torch.exp(b * _strain(l, l0))

    def energy(self, l, l0, k, b):
        """``k l0^2 (expm1(b e) - b e) / b^2`` (a series where ``|b e|`` is small)."""
        e = _strain(l, l0)
        pos, bs = _positive_part(b)
        be = b * e
        small = be.abs() < 1e-3
        series = e * e * (0.5 + be / 6.0 + be * be / 24.0)
        closed = (torch.expm1(be) - be) / (bs * bs)
        return k * l0 * l0 * torch.where(pos & ~small, closed, series)


class Polynomial(SpringLaw):
    """Polynomial stiffening: ``f = k l0 (e + c2 e |e| + c3 e^3)`` with strain ``e = l / l0 - 1``.

    An odd polynomial of the strain: tension and compression stiffen alike, the tangent stiffness
    ``k (1 + 2 c2 |e| + 3 c3 e^2)`` is at least ``k``.

    Args:
        quadratic: ``c2 >= 0`` (dimensionless), any spring-parameter shape.
        cubic: ``c3 >= 0`` (dimensionless), any spring-parameter shape.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> law = td.Polynomial(quadratic=0.0, cubic=100.0)
        >>> one = torch.tensor(1.0)
        >>> law.tension(torch.tensor([0.9, 1.1]), one, one, torch.tensor(0.0), torch.tensor(100.0))
        tensor([-0.2000,  0.2000])
    """

    name = "polynomial"
    params = ("quadratic", "cubic")

    def __init__(self, *, quadratic: float | dict | torch.Tensor = 0.0, cubic: float | dict | torch.Tensor = 0.0):
        super().__init__(quadratic, cubic)

    def tension(self, l, l0, k, c2, c3):
        """``k l0 (e + c2 e |e| + c3 e^3)``."""
        e = _strain(l, l0)
        return k * l0 * e * (1.0 + c2 * e.abs() + c3 * e * e)

    def slope(self, l, l0, k, c2, c3):
        """``k (1 + 2 c2 |e| + 3 c3 e^2)``."""
        e = _strain(l, l0)
        return k * (1.0 + 2.0 * c2 * e.abs() + 3.0 * c3 * e * e)

    def energy(self, l, l0, k, c2, c3):
        """``k l0^2 (e^2 / 2 + c2 |e|^3 / 3 + c3 e^4 / 4)``."""
        e = _strain(l, l0)
        e2 = e * e
        return k * l0 * l0 * e2 * (0.5 + c2 * e.abs() / 3.0 + c3 * e2 / 4.0)


#: The laws by scene-file name (``[material] law``).
LAWS = {cls.name: cls for cls in (Exponential, Polynomial)}


def as_law(law) -> SpringLaw | None:
    """A law object from ``None`` (Hooke), a law or a law's name; a ConfigError otherwise."""
    if law is None or isinstance(law, SpringLaw):
        return law
    if isinstance(law, str) and law in LAWS:
        return LAWS[law]()
    raise ConfigError(
        "law",
        "None (Hooke), " + ", ".join(f'"{n}"' for n in LAWS) + " or a SpringLaw (td.Exponential, td.Polynomial)",
        got=law,
    )
