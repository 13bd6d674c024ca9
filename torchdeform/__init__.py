"""torchdeform: a tensor-based soft-tissue simulator on PyTorch.

Mass-spring bodies on regular 3-D grids whose springs are convolution stencils, with
integrators from explicit Euler to implicit Euler, stability bounds and scene files
(:mod:`torchdeform.sim`, :mod:`torchdeform.scene`); ChainMail (:mod:`torchdeform.chainmail`),
fuzzy tissue parameters (:mod:`torchdeform.fuzzy`), learning from time series
(:mod:`torchdeform.learn`), volume deformation and rendering (:mod:`torchdeform.volume`) and tools
in contact with the tissue (:mod:`torchdeform.interact`), and topology changes: cutting, tearing,
coagulation (:mod:`torchdeform.topology`).
Benchmarks (:mod:`torchdeform.bench`) are a command, ``torchdeform bench``.

Examples:
    >>> import torchdeform as td
    >>> grid = td.Grid((8, 8, 8), spacing=0.005, topology=26)
    >>> model = td.Model(grid, stiffness=20.0, damping=0.05, density=1000.0,
    ...                  gravity=(-9.81, 0, 0), fixed=grid.face("bottom"))
    >>> state, record = td.simulate(model, model.rest_state(), dt=td.suggest_dt(model), steps=100)
    >>> bool(state.x[0, 0, -1].mean() < model.X[0, 0, -1].mean())        # it sags under gravity
    True
"""

import gc as _gc

# importing torch and this package leaves about a million long-lived objects, which the cyclic
# collector would rescan several times on the way (0.2 s of a 1.3 s import): paused for the imports
_gc_was_enabled = _gc.isenabled()
_gc.disable()
from . import cpu_load  # noqa: F401  # first: the machine's load is sampled over torch's import

try:
    from . import chainmail, interact, learn, scene, sim, topology, volume
    from .chainmail import ChainMail, Limits, limit_violation, tensor_chainmail
    from .errors import ConfigError, ConfigWarning, DivergenceError, StabilityWarning, TorchdeformError
    from .scene import Scene, cube_scene, demo_scene, load_scene, run_scene
    from .sim import (
        INTEGRATORS,
        RK4,
        Adaptive,
        DampedVerlet,
        DivergenceMonitor,
        Drag,
        Elastic,
        Engine,
        ExplicitEuler,
        Exponential,
        FieldForce,
        Grid,
        ImplicitEuler,
        Integrator,
        KnocheRelaxation,
        Model,
        PointForce,
        Polynomial,
        ProjectiveDynamics,
        State,
        StepSizeError,
        SurfaceForce,
        SymplecticEuler,
        check_dt,
        conjugate_gradient,
        gershgorin_omega2,
        lumped_mass,
        power_omega2,
        simulate,
        solve_static,
        suggest_dt,
        time_step_bound,
    )
    from .volume import render, warp
finally:
    if _gc_was_enabled:
        _gc.enable()
    del _gc, _gc_was_enabled

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "DivergenceError",
    "StabilityWarning",
    "ConfigWarning",
    "TorchdeformError",
    "Drag",
    "PointForce",
    "SurfaceForce",
    "FieldForce",
    "Grid",
    "INTEGRATORS",
    "RK4",
    "DampedVerlet",
    "ExplicitEuler",
    "ImplicitEuler",
    "Integrator",
    "KnocheRelaxation",
    "SymplecticEuler",
    "conjugate_gradient",
    "simulate",
    "solve_static",
    "Engine",
    "Model",
    "State",
    "Elastic",
    "lumped_mass",
    "DivergenceMonitor",
    "gershgorin_omega2",
    "power_omega2",
    "suggest_dt",
    "check_dt",
    "time_step_bound",
    "Adaptive",
    "StepSizeError",
    "Exponential",
    "Polynomial",
    "ProjectiveDynamics",
    "Scene",
    "demo_scene",
    "cube_scene",
    "load_scene",
    "run_scene",
    "ChainMail",
    "Limits",
    "limit_violation",
    "tensor_chainmail",
    "warp",
    "render",
    "sim",
    "chainmail",
    "learn",
    "volume",
    "scene",
    "interact",
    "topology",
]
