"""Every integrator by its scene-file name: :data:`INTEGRATORS`.

The one place that knows them all: the fixed-step integrators of :mod:`.integrators`, the
adaptive steps of :mod:`.adaptive` and projective dynamics of :mod:`.projective`. Scene files
(``[integrator] name``), time series and the accuracy benchmark look integrators up here.

Examples:
    >>> import torchdeform as td
    >>> sorted(td.INTEGRATORS)
    ['adaptive', 'explicit', 'implicit', 'knoche', 'projective', 'rk4', 'symplectic', 'verlet']
    >>> td.INTEGRATORS["rk4"] is td.RK4, td.INTEGRATORS["implicit"](cg_iters=20).cg_iters
    (True, 20)
"""

from __future__ import annotations

from .adaptive import Adaptive
from .integrators import RK4, DampedVerlet, ExplicitEuler, ImplicitEuler, KnocheRelaxation, SymplecticEuler
from .projective import ProjectiveDynamics

__all__ = ["INTEGRATORS"]

#: integrator name (``[integrator] name`` of scene files) -> class
INTEGRATORS = {
    cls.name: cls
    for cls in (
        ExplicitEuler,
        SymplecticEuler,
        DampedVerlet,
        RK4,
        ImplicitEuler,
        KnocheRelaxation,
        Adaptive,
        ProjectiveDynamics,
    )
}
