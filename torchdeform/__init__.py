"""torchdeform: a tensor-based soft-tissue simulator on PyTorch.

Mass-spring bodies on regular 3-D grids whose springs are convolution stencils, with
integrators from explicit Euler to implicit Euler, stability bounds and scene files;
ChainMail (:mod:`torchdeform.chainmail`), fuzzy tissue parameters (:mod:`torchdeform.fuzzy`),
learning from time series (:mod:`torchdeform.data`, :mod:`torchdeform.learn`) and volume
deformation and rendering (:mod:`torchdeform.volume`, :mod:`torchdeform.render`).

    >>> import torchdeform as td
    >>> grid = td.Grid((8, 8, 8), spacing=0.005, topology=26)
    >>> model = td.Model(grid, stiffness=20.0, damping=0.05, density=1000.0,
    ...                  gravity=(-9.81, 0, 0), fixed=grid.face("bottom"))
    >>> state, record = td.simulate(model, model.rest_state(), dt=td.suggest_dt(model), steps=100)
"""
from . import chainmail, data, learn, render, volume
from .chainmail import ChainMail, Limits, limit_violation, tensor_chainmail
from .errors import ConfigError, DivergenceError, StabilityWarning, TorchdeformError
from .forces import Drag, PointForce, SurfaceForce
from .grid import Grid
from .integrators import (INTEGRATORS, RK4, DampedVerlet, ExplicitEuler, ImplicitEuler, Integrator,
                          KnocheRelaxation, SymplecticEuler, conjugate_gradient, simulate)
from .model import Model, State, lumped_mass
from .scene import Scene, demo_scene, load_scene, run_scene
from .volume import warp
from .stability import (DivergenceMonitor, gershgorin_omega2, power_omega2, suggest_dt, check_dt,
                        time_step_bound)

__version__ = "0.1.0"

__all__ = [
    "ConfigError", "DivergenceError", "StabilityWarning", "TorchdeformError", "Drag", "PointForce",
    "SurfaceForce", "Grid", "INTEGRATORS", "RK4", "DampedVerlet", "ExplicitEuler", "ImplicitEuler",
    "Integrator", "KnocheRelaxation", "SymplecticEuler", "conjugate_gradient", "simulate", "Model", "State",
    "lumped_mass", "DivergenceMonitor", "gershgorin_omega2", "power_omega2", "suggest_dt", "check_dt",
    "time_step_bound", "Scene", "demo_scene", "load_scene", "run_scene",
    "chainmail", "ChainMail", "Limits", "limit_violation", "tensor_chainmail", "data", "learn",
    "render", "volume", "warp",
]
