"""The mass-spring core.

Grids, the one spring operator, force terms, models and states, integrators, stability bounds
and the compiled fast path.

=====================  ===========================================================================
:mod:`.grid`           :class:`Grid`: node counts, spacing, topology (6/14/18/26 neighbours), masks
:mod:`.springs`        the one spring operator: stencil differences and their adjoint (slices and
                       ``conv3d`` reference), the spring law, energies, linearisations
:mod:`.laws`           strain-stiffening spring laws (:class:`Exponential`, :class:`Polynomial`)
:mod:`.forces`         loads (point, surface, field), drags, home springs: the one load vocabulary
:mod:`.model`          :class:`Model` (what a step reads) and :class:`State` (``x``, ``v``, ``t``)
:mod:`.adjoint`        adjoint (implicit-function) gradients of linear solves, for implicit Euler
:mod:`.integrators`    explicit/symplectic Euler, damped Verlet, RK4, implicit Euler, Knoche
                       relaxation; :func:`simulate`
:mod:`.stability`      time-step bounds, :func:`suggest_dt`, divergence monitoring
:mod:`.adaptive`       :class:`Adaptive`: embedded Runge-Kutta pairs with error control (``rtol``)
:mod:`.projective`     :class:`ProjectiveDynamics`: implicit Euler by local/global iterations
:mod:`.catalog`        :data:`INTEGRATORS`: every integrator by its scene-file name
:mod:`.native`         the packed spring forces (and a whole symplectic step) as a C kernel
:mod:`.packed`         the padded, flattened layout of the fast path
:mod:`.threads`        the governor that picks a packed step's thread count from its step times
:mod:`.compiled`       :func:`compiled_step`: one integrator step under ``torch.compile``
:mod:`.engine`         :func:`simulate` and its :class:`Engine`: eager, native, compiled or chosen
                       per run
=====================  ===========================================================================

Imports point downwards in that order; :mod:`.compiled` is imported only when a compiled step
is asked for.

Examples:
    >>> import torch
    >>> from torchdeform import sim
    >>> grid = sim.Grid((4, 4, 4), spacing=0.01, topology=18)
    >>> model = sim.Model(grid, stiffness=10.0, damping=0.01, mass=1e-3, fixed=grid.face("bottom"),
    ...                   loads=[sim.PointForce((3, 1, 1), (-0.01, 0.0, 0.0), ramp=0.05)])
    >>> state = sim.SymplecticEuler().step(model, model.rest_state(), dt=1e-3)
    >>> state.x.shape, state.t
    (torch.Size([1, 3, 4, 4, 4]), 0.001)
"""

from .adaptive import PAIRS, Adaptive, StepSizeError
from .catalog import INTEGRATORS
from .engine import ENGINES, Engine, simulate
from .forces import Drag, FieldForce, PointForce, SurfaceForce
from .grid import Grid
from .integrators import (
    RK4,
    DampedVerlet,
    ExplicitEuler,
    ImplicitEuler,
    Integrator,
    KnocheRelaxation,
    SymplecticEuler,
    conjugate_gradient,
)
from .laws import LAWS, Exponential, Polynomial, SpringLaw
from .material import Elastic
from .model import Model, State, lumped_mass
from .projective import ProjectiveDynamics
from .stability import DivergenceMonitor, check_dt, gershgorin_omega2, power_omega2, suggest_dt, time_step_bound
from .static import solve_static

__all__ = [
    "Grid",
    "Model",
    "State",
    "Elastic",
    "lumped_mass",
    "Drag",
    "PointForce",
    "SurfaceForce",
    "FieldForce",
    "INTEGRATORS",
    "Integrator",
    "ExplicitEuler",
    "SymplecticEuler",
    "DampedVerlet",
    "RK4",
    "ImplicitEuler",
    "KnocheRelaxation",
    "conjugate_gradient",
    "simulate",
    "Engine",
    "ENGINES",
    "DivergenceMonitor",
    "check_dt",
    "gershgorin_omega2",
    "power_omega2",
    "suggest_dt",
    "time_step_bound",
    "Adaptive",
    "PAIRS",
    "StepSizeError",
    "SpringLaw",
    "Exponential",
    "Polynomial",
    "LAWS",
    "ProjectiveDynamics",
    "solve_static",
]
