"""Mass-spring scenes.

The ``[material]`` (a stiffness, a modulus, or tissue words through the fuzzy tissue library:
:func:`tissue_moduli`, :func:`lattice_modulus`), ``[[regions]]``, ``[mass]``, ``[boundary]``,
``[[loads]]``, ``[integrator]``, ``[output]`` and ``[volume]`` sections, the :class:`Scene` they
build, and a small dragged cube (:func:`cube_scene`). ``[[tools]]`` and ``[strain_limit]`` are read
by :mod:`.tools`, ``[[cuts]]``, ``[[cautery]]``, ``[tear]``, ``[[coagulate]]`` by :mod:`.topology`.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..checks import check_memory, usable_device
from ..errors import ConfigError, ConfigWarning, TorchdeformError
from ..fuzzy.presets import DEFAULT_POISSON_RATIO, TISSUE_EXPECTED, tissue_moduli, tissue_properties
from ..sim.adaptive import PAIRS
from ..sim.catalog import INTEGRATORS
from ..sim.engine import ENGINES
from ..sim.forces import Drag, PointForce, SurfaceForce
from ..sim.grid import FACES, Grid
from ..sim.integrators import Integrator, SymplecticEuler
from ..sim.laws import LAWS
from ..sim.material import Elastic, kelvin_voigt_damping
from ..sim.model import Model
from ..sim.projective import SOLVERS
from .reader import SECTIONS, Source, Table, drags_section, faces, grid_section, is_number, node_list, region_mask
from .tools import ToolSet, check_tool_reach, palpation_option, strain_limit_section
from .topology import TOPOLOGY, TopologySet, tools_with_cutters, topology_section

__all__ = [
    "Scene",
    "mass_spring_scene",
    "cube_scene",
    "lattice_modulus",
    "tissue_moduli",
    "tissue_properties",
    "kelvin_voigt_damping",
    "DEFAULT_POISSON_RATIO",
    "StaticSolve",
    "StaticSolveError",
    "full_load_time",
    "INTEGRATOR_OPTIONS",
    "EXPLICIT",
    "DTYPES",
    "MODEL_KEYS",
    "TISSUE_EXPECTED",
]

#: Options of each integrator (keyword arguments of its class): key -> what is expected.
INTEGRATOR_OPTIONS = {
    "explicit": {},
    "symplectic": {},
    "rk4": {},
    "verlet": {"kd": "a number in [0, 1)"},
    "implicit": {"cg_iters": "an integer >= 1", "cg_tol": "a positive number", "newton_iters": "an integer >= 0"},
    "knoche": {
        "material": "a number in [0, 1] or a [D][H][W] array of them",
        "eps": "a positive number",
        "gain": "a positive number",
    },
    "adaptive": {
        "rtol": "a positive number",
        "pair": "one of " + ", ".join(f'"{p}"' for p in PAIRS),
        "min_step": "a positive number of seconds",
        "max_step": "a positive number of seconds",
    },
    "projective": {
        "iterations": "an integer >= 1",
        "tol": "a number >= 0",
        "solver": "one of " + ", ".join(f'"{p}"' for p in SOLVERS),
        "rho": "a number in [0, 1)",
        "relaxation": "a number in (0, 1]",
        "delay": "an integer >= 0",
        "cg_iters": "an integer >= 1",
        "cg_tol": "a number >= 0",
    },
    "static": {
        "tol": "a positive number (relative residual)",
        "max_iter": "an integer >= 1 (Newton iterations)",
        "cg_iters": "an integer >= 1",
        "cg_tol": "a positive number",
        "time": "a time >= 0 (s)",
    },
}
#: integer options and their least values; text options and their choices
_INTEGER_OPTIONS = {"cg_iters": 1, "newton_iters": 0, "iterations": 1, "delay": 0, "max_iter": 1}
_TEXT_OPTIONS = {"pair": tuple(PAIRS), "solver": SOLVERS}
EXPLICIT = ("explicit", "symplectic", "verlet", "rk4")
#: the integrator names of ``[integrator] name``: the time integrators and the static solve
NAMES = (*INTEGRATORS, "static")
#: ``[integrator]`` keys of a time integration that a static solve has no use for
_DYNAMIC_ONLY = ("dt", "safety", "steps", "engine")
DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: Model keyword -> scene key, to locate errors raised by the core.
MODEL_KEYS = {
    "stiffness": "material.stiffness",
    "damping": "material.damping",
    "damping_mode": "material.damping_mode",
    "mass": "mass",
    "density": "mass.density",
    "gravity": "boundary.gravity",
    "home": "boundary.home",
    "anchors.stiffness": "boundary.anchors.stiffness",
    "anchors.every": "boundary.anchors.every",
    "decay": "boundary.decay",
    "fixed": "boundary.fixed",
}


# ------------------------------------------------------------------ the static solve
@dataclass(kw_only=True)
class StaticSolve:
    """``[integrator] name = "static"``: one :func:`~torchdeform.sim.static.solve_static` instead of time steps.

    :func:`~torchdeform.scene.run_scene` finds the equilibrium under the loads and drags at ``time``
    (Newton's method, CG inner solves) and writes it as the run's last frame (the first is the rest
    state); a solve that does not reach ``tol`` within ``max_iter`` iterations writes nothing and
    raises :class:`StaticSolveError`.

    Args:
        tol: relative residual to reach (``|F| <= tol |load|``); None: 1e-6 in float64 (a static
            solve's default dtype), 1e-3 in float32 (rounding stalls Newton near 5e-4 there).
        max_iter: Newton iterations at most.
        cg_iters: CG iterations per Newton step at most.
        cg_tol: relative tolerance of each CG solve.
        time: when the loads and drags are taken (s); None: the end of every ramp and drag path
            (:func:`full_load_time`, set by the scene reader).
    """

    tol: float | None = None
    max_iter: int = 50
    cg_iters: int = 500
    cg_tol: float = 1e-3
    time: float | None = None
    name: str = "static"

    def tolerance(self, dtype: torch.dtype) -> float:
        """``tol``, or its default for ``dtype``: 1e-6 in float64, 1e-3 in float32 (where Newton stalls near 5e-4)."""
        if self.tol is not None:
            return float(self.tol)
        return 1e-6 if dtype == torch.float64 else 1e-3


class StaticSolveError(TorchdeformError):
    """A static solve that did not reach its tolerance: one sentence naming the scene key to change."""


def full_load_time(loads, drags) -> float:
    """The time (s) by which every load has ramped up and every drag has reached its last waypoint (0 if none)."""
    ends = [0.0]
    for load in loads or []:
        ends.append(float(load.start) + float(load.ramp))
    for drag in drags or []:
        if drag.path is not None:
            ends.append(float(drag.path[-1][0]))
        else:
            ends.append(float(drag.start) + float(drag.ramp))
    return max(ends)


# ------------------------------------------------------------------ the scene
@dataclass(eq=False)
class Scene:
    """A scene: a grid, the keyword arguments of :class:`Model`, an integrator and run settings.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        model_args: keyword arguments of :class:`~torchdeform.sim.model.Model` besides ``grid``,
            ``dtype`` and ``device`` (``stiffness``, ``density``, ``fixed``, ``drags``, ...).
        integrator: an :class:`~torchdeform.sim.integrators.Integrator`.
        dt: seconds, or ``"auto"`` (``safety`` times the stability bound of ``integrator``).
        steps: number of steps.
        record_every: steps between saved frames (default: about 100 frames).
        name: title of the run.
        dtype: of the model.
        device: of the model (None = CPU).
        safety: fraction of the stability bound used by ``dt = "auto"``.
        threads: CPU threads ``run_scene`` simulates with (None: torch's setting). Small bodies run
            faster on one thread, and much faster than on two when another process holds a core.
        engine: ``"auto"`` (default: the C-kernel or compiled steps when the run is long enough to
            repay their start-up), ``"eager"``, ``"native"`` or ``"compiled"``
            (:class:`~torchdeform.sim.engine.Engine`).
        source: the scene file (:class:`Source`) for error messages, or None.

    Examples:
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01)
        >>> scene = td.Scene(grid, dict(stiffness=50.0, damping=0.1, density=1000.0, fixed=grid.face("bottom")),
        ...                  integrator=td.SymplecticEuler(), dt="auto", steps=200)
        >>> model = scene.build()                                  # built once per device
        >>> model is scene.build(device="cpu"), model.grid is grid, scene.frames_every
        (True, True, 2)
        >>> bound = td.time_step_bound(model)
        >>> scene.time_step(bound) == 0.9 * bound                  # dt = "auto": safety * bound
        True
    """

    grid: Grid
    model_args: dict
    _: KW_ONLY
    integrator: Integrator = field(default_factory=SymplecticEuler)
    dt: float | str = "auto"
    steps: int = 1000
    record_every: int | None = None
    name: str = "scene"
    dtype: torch.dtype = torch.float32
    device: str | None = None
    safety: float = 0.9
    threads: int | None = None
    engine: str = "auto"
    #: ``[integrator] settle``: settle the body under gravity before the run starts (``True``: the static
    #: solve, else damped steps for a default time; seconds: damped steps for that long where the static
    #: solve does not converge), or False
    settle: bool | float = False
    source: Source = field(default_factory=Source)
    #: optional ``{"file": .., "tf": .., "mode": .., "view": ..}``: a volume (file or ``"phantom:N"``)
    #: deformed by the final state; ``run_scene`` then writes before/after renders and the deformed volume
    volume: dict | None = None
    #: optional ``{"exemplar": .., "block": .., "seed": .., "voxel": ..}``: a solid texture on the body's
    #: material coordinates; ``run_scene`` then writes ``textured.png`` of the final surfaces
    texture: dict | None = None
    #: optional ``[camera]`` (:func:`~torchdeform.scene.camera.camera_section`): an endoscope riding a
    #: tool, looking through the deformed ``[volume]``; ``run_scene`` writes ``endoscope.gif``
    camera_view: dict | None = None
    #: optional :class:`~torchdeform.scene.tools.ToolSet` (``[[tools]]``, ``[strain_limit]``): ``run_scene``
    #: runs fresh interactions built from it and writes the tools' force series and plots
    tools: ToolSet | None = None
    #: optional :class:`~torchdeform.scene.topology.TopologySet` (``[[cuts]]``, ``[[cautery]]``, ``[tear]``,
    #: ``[[coagulate]]``, ``[output] surfaces``): ``run_scene`` applies them between steps on a copy of the model
    topology: TopologySet | None = None
    #: optional file name (``"animation.gif"`` for ``[output] animation = true``): ``run_scene`` then writes
    #: an animated GIF of the run there (:func:`torchdeform.scene.animation.animate`)
    animation: str | None = None
    #: the side (pixels) of each square panel of the animation (``[output] image_size``)
    image_size: int = 512
    #: where the animation's surface panel looks from, ``(3,)`` from the body's centre (``[output] camera``),
    #: and the direction upwards in it (``camera_up``); None: the animation's defaults
    camera: tuple | None = None
    camera_up: tuple | None = None
    #: smooth surfaces embedded in the lattice, ``{name: (rest vertices (V, 3) m, faces (F, 3))}``, or None;
    #: the animation shows them, and with ``write_surfaces`` the run writes them at every recorded frame
    embedded: dict | None = None
    #: ``"glb"`` or ``"ply"``: the format of the embedded surfaces' files
    surface_format: str = "glb"
    #: write ``surfaces/frame_NNNN.<format>`` (``[output] surfaces = "embedded"``)
    write_surfaces: bool = False
    _models: dict = field(default_factory=dict, init=False, repr=False)

    def build(self, *, device=None) -> Model:
        """The :class:`Model` on ``device`` (default: the scene's, else CPU); built once per device."""
        if device is None and self.device is not None:  # the scene's: its line in the file
            try:
                dev = usable_device(self.device, key="integrator.device")
            except ConfigError as e:
                raise self.source.error("integrator.device", e.expected, got=self.device) from None
        else:
            dev = usable_device(device, key="device")
        if str(dev) not in self._models:
            with self.source.located("material", keys=MODEL_KEYS):
                self._models[str(dev)] = Model(self.grid, **self.model_args, dtype=self.dtype, device=dev)
        return self._models[str(dev)]

    def time_step(self, bound: float) -> float:
        """The time step (s): ``dt``, or ``safety * bound`` for ``dt = "auto"``."""
        if self.dt != "auto":
            return float(self.dt)
        if not (0 < bound < math.inf):
            raise self.source.error(
                "integrator.dt",
                f'seconds: "auto" needs a finite, positive stability bound and '
                f"{self.integrator.name} has {bound:g} s here",
                got="auto",
            )
        return self.safety * bound

    @property
    def frames_every(self) -> int:
        """Steps between saved frames."""
        return self.record_every or max(1, self.steps // 100)


# ------------------------------------------------------------------ tissue words -> stiffness
def lattice_modulus(grid: Grid) -> float:
    """Young's modulus (Pa) of the grid's spring lattice per N/m of spring stiffness (all springs equal).

    The small-strain stiffness of a lattice of springs ``k`` (Cauchy-Born): per node, in Voigt
    notation, ``C = (k / V) sum_s l_s^2 a_s a_s^T`` over the ``S`` half-directions, with
    ``a = (n_d^2, n_h^2, n_w^2, n_h n_w, n_d n_w, n_d n_h)`` of the unit direction ``n``, rest length
    ``l_s`` and cell volume ``V``. Normal and shear parts decouple on a box lattice, so the Young's
    modulus along axis ``i`` is ``1 / (C_nn^-1)_ii`` of the normal 3 x 3 block; this is the mean over
    the three axes. For 26 neighbours and spacing ``h`` it is ``2.7 / h``: ``E = 2.7 k / h``
    (Poisson's ratio 0.35); for 6 neighbours ``1 / h`` (and no shear stiffness).

    Examples:
        >>> from torchdeform.sim.grid import Grid
        >>> round(lattice_modulus(Grid((2, 2, 2), spacing=0.001, topology=26)) * 0.001, 6)
        2.7
    """
    d = torch.tensor(grid.directions, dtype=torch.float64) * torch.tensor(grid.spacing, dtype=torch.float64)
    length = d.norm(dim=1, keepdim=True)
    n = d / length
    a = n * n  # the normal part of a_s
    C = (length**2 * a).T @ a / math.prod(grid.spacing)  # (3, 3) per unit k
    return float((1.0 / torch.linalg.inv(C).diagonal()).mean())


#: Young's moduli (Pa) outside which a spring lattice is no soft tissue: a unit is probably mixed up
PLAUSIBLE_E = (10.0, 1e7)


def _plausible(t: Table, which: str, grid: Grid) -> None:
    """Warn (one line, naming file, line and key) when springs give a lattice no soft tissue has."""
    value = t.data[which]
    if not is_number(value):
        return
    k = value / grid.spacing[0] if which in ("modulus", "spring_modulus") else value
    E = k * lattice_modulus(grid)
    if not PLAUSIBLE_E[0] <= E <= PLAUSIBLE_E[1]:
        import warnings

        line = t.src.line_of(t.key(which))
        where = f"{t.src.path}:{line}: " if t.src.path is not None and line else ""
        warnings.warn(
            f"{where}material.{which} = {value:g} makes a lattice of Young's modulus {E:.3g} Pa, outside "
            f"{PLAUSIBLE_E[0]:g}-{PLAUSIBLE_E[1]:g} Pa of soft tissue (for E in Pa use youngs_modulus)",
            ConfigWarning,
            stacklevel=2,
        )


#: the extent (m) of a body outside which it is no piece of soft tissue: a length unit is probably mixed up
PLAUSIBLE_EXTENT = (1e-3, 1.0)


def _plausible_size(t: Table, grid: Grid) -> None:
    """Warn (one line, naming file, line and key) when the body is smaller than 1 mm or larger than 1 m."""
    nodes = grid.nodes()
    if not bool(nodes.any()):
        return
    X = grid.rest_positions(dtype=torch.float64)[0].flatten(1)[:, nodes.flatten()]
    extent = float((X.amax(1) - X.amin(1)).max())
    if extent == 0 or PLAUSIBLE_EXTENT[0] <= extent <= PLAUSIBLE_EXTENT[1]:
        return
    import warnings

    which = "scale" if t.has("mesh") and t.has("scale") else "spacing"
    value = t.data.get(which)
    line = t.src.line_of(t.key(which))
    where = f"{t.src.path}:{line}: " if t.src.path is not None and line else ""
    warnings.warn(
        f"{where}grid.{which} = {value} makes a body {extent:.3g} metres across, outside "
        f"{PLAUSIBLE_EXTENT[0] * 1e3:g} mm - {PLAUSIBLE_EXTENT[1]:g} m of a piece of soft tissue: lengths are in "
        f"metres (2 mm is 0.002)",
        ConfigWarning,
        stacklevel=2,
    )


_E_EXPECTED = "Young's modulus E in Pa (> 0)"
_NU_EXPECTED = (
    "a Poisson ratio in [0.25, 0.5) (0.5 is incompressible, which the volume term never reaches; "
    "springs alone already give 0.25)"
)


@dataclass
class _Solid:
    """The elastic solid of ``[material]`` (``tissue`` or ``youngs_modulus``), and of its ``[[regions]]``.

    ``E`` (Pa), ``nu`` and ``tau`` (the Kelvin-Voigt retardation time eta / E in s, None: no automatic
    damping) and ``density`` (kg/m^3, None: none known) are numbers or per-node float64 fields
    ``(D, H, W)``; ``key`` is the scene key that made it.
    """

    E: float | torch.Tensor
    nu: float | torch.Tensor
    tau: float | torch.Tensor | None
    density: float | torch.Tensor | None
    key: str

    def model_args(self, grid: Grid) -> dict:
        """Model keywords: the :class:`Elastic` stiffness, its Kelvin-Voigt damping, the density if known."""
        args: dict = {"stiffness": Elastic(self.E, self.nu), "normalize": False}
        if self.tau is not None:
            args["damping"] = kelvin_voigt_damping(grid, self.E, self.nu, self.tau)
        return args

    def mass_args(self, grid: Grid) -> dict | None:
        """``{"density": rho}`` (one tissue) or ``{"mass": per node}`` (several), None with no density."""
        if self.density is None:
            return None
        if not torch.is_tensor(self.density):
            return {"density": float(self.density)}
        from ..sim.model import lumped_mass

        return {"mass": lumped_mass(grid, 1.0)[0, 0] * self.density}


def _field(value, grid: Grid) -> torch.Tensor:
    """A number or a field as a float64 field ``(D, H, W)`` (a copy)."""
    return torch.as_tensor(value, dtype=torch.float64).expand(grid.shape).clone()


def _material(t: Table, grid: Grid) -> tuple[dict, _Solid | None]:
    """The Model keywords of ``[material]`` and, for an elastic solid (``tissue``, ``youngs_modulus``), the solid.

    The solid's own keywords (stiffness, Kelvin-Voigt damping) come from :meth:`_Solid.model_args`
    once the regions are on it.
    """
    which = t.one_of("stiffness", "spring_modulus", "modulus", "tissue", "youngs_modulus")
    if which == "modulus":
        import warnings

        warnings.warn(
            "material.modulus (Y in N, each spring k = Y / l0) is now called material.spring_modulus; "
            "for Young's modulus in Pa use material.youngs_modulus",
            ConfigWarning,
            stacklevel=2,
        )
    solid = None
    if which not in ("youngs_modulus", "tissue"):
        t.only_with("poisson_ratio", "youngs_modulus")
    if which == "youngs_modulus":
        E = t.num("youngs_modulus", _E_EXPECTED, lo=0, lo_open=True)
        nu = t.num("poisson_ratio", _NU_EXPECTED, lo=0.25, hi=0.5, hi_open=True)
        solid = _Solid(E, nu, None, None, t.key("youngs_modulus"))
    elif which == "tissue":
        with t.src.located(t.key("tissue")):
            props = tissue_properties([t.data["tissue"]])[0]
        nu = t.num("poisson_ratio", _NU_EXPECTED, default=props["poisson_ratio"], lo=0.25, hi=0.5, hi_open=True)
        E = props["youngs_modulus"]
        tau = None if t.has("damping") else props["viscosity"] / E
        solid = _Solid(E, nu, tau, props["density"], t.key("tissue"))
    if solid is not None:
        args: dict = {"normalize": False}
        with t.src.located(solid.key, keys={"material": solid.key}):
            Elastic(solid.E, solid.nu).check_grid(grid)
    else:
        args = {
            "stiffness": t.per_class(which, "N/m" if which == "stiffness" else "N"),
            "normalize": which in ("modulus", "spring_modulus"),
        }
        _plausible(t, which, grid)  # a valid value, probably not what was meant
    if t.has("damping"):
        args["damping"] = t.per_class("damping", "N s/m")
    args["damping_mode"] = t.text(
        "damping_mode", '"projected" or "unprojected"', default="projected", choices=("projected", "unprojected")
    )
    laws = ("hooke",) + tuple(LAWS)
    name = t.text("law", "one of " + ", ".join(f'"{n}"' for n in laws), default="hooke", choices=laws)
    own = () if name == "hooke" else LAWS[name].params
    for key in ("stiffening", "quadratic", "cubic"):
        if key not in own:
            t.only_with(key, f'law = "{name}"')
    if name != "hooke":
        args["law"] = LAWS[name](**{key: t.per_class(key, "dimensionless") if t.has(key) else 0.0 for key in own})
    return args, solid


def _region_tables(src: Source, items) -> list:
    if not isinstance(items, list):
        raise src.error("regions", "[[regions]] tables", got=items)
    return [Table(src, f"regions[{n}]", item, SECTIONS["regions"]) for n, item in enumerate(items)]


def _regions(src: Source, items, grid: Grid, base_stiffness) -> torch.Tensor:
    """Per-spring stiffness ``(S, D, H, W)`` of ``[[regions]]``: each spring the harmonic mean of its ends' k."""
    from ..sim.springs import harmonic_mean_of_ends

    tables = _region_tables(src, items)
    if not is_number(base_stiffness):
        raise src.error(
            "material",
            "stiffness = a number or tissue = .. (or youngs_modulus = ..) with [[regions]] "
            "(not a class table or modulus)",
        )
    k = torch.full(grid.shape, float(base_stiffness), dtype=torch.float64)
    for t in tables:
        for key in ("youngs_modulus", "poisson_ratio"):
            if t.has(key):
                raise t.fail(
                    key,
                    "stiffness (N/m) or tissue in a region of a body of springs ([material] stiffness); "
                    f"{key} needs an elastic body ([material] youngs_modulus or tissue)",
                    got=t.data[key],
                )
        mask = region_mask(t, grid)
        if t.one_of("stiffness", "tissue") == "stiffness":
            value = t.num("stiffness", "a positive number (N/m)", lo=0, lo_open=True)
        else:
            with src.located(t.key("tissue")):
                value = tissue_moduli([t.data["tissue"]], key="tissue")[0] / lattice_modulus(grid)
        k[mask] = value
    return harmonic_mean_of_ends(k[None], grid)[0]


def _elastic_regions(src: Source, items, grid: Grid, solid: _Solid) -> _Solid:
    """The solid with the per-node E, nu (and Kelvin-Voigt tau, density) of ``[[regions]]``, later on top.

    A region's ``tissue`` sets E, nu (its own ``poisson_ratio`` wins), tau and density on its nodes;
    ``youngs_modulus`` and ``poisson_ratio`` set E and nu, the rest of the body's fields stay.
    """
    tables = _region_tables(src, items)
    E, nu = _field(solid.E, grid), _field(solid.nu, grid)
    tau = None if solid.tau is None else _field(solid.tau, grid)
    rho = None if solid.density is None else _field(solid.density, grid)
    for t in tables:
        if t.has("stiffness"):
            raise t.fail(
                "stiffness",
                "youngs_modulus (Pa), poisson_ratio or tissue in a region of an elastic body "
                f"({solid.key}); stiffness (N/m) is for a body of springs ([material] stiffness)",
                got=t.data["stiffness"],
            )
        present = [k for k in ("youngs_modulus", "poisson_ratio", "tissue") if t.has(k)]
        if not present:
            raise src.error(t.name, "at least one of the keys youngs_modulus, poisson_ratio or tissue")
        if t.has("tissue") and t.has("youngs_modulus"):
            raise t.fail("youngs_modulus", "exactly one of youngs_modulus or tissue", got=t.data["youngs_modulus"])
        mask = region_mask(t, grid)
        if t.has("tissue"):
            with src.located(t.key("tissue")):
                props = tissue_properties([t.data["tissue"]], key="tissue")[0]
            E[mask] = props["youngs_modulus"]
            nu[mask] = props["poisson_ratio"]
            if tau is not None:
                tau[mask] = props["viscosity"] / props["youngs_modulus"]
            if rho is not None and props["density"] is not None:
                rho[mask] = props["density"]
        if t.has("youngs_modulus"):
            E[mask] = t.num("youngs_modulus", _E_EXPECTED, lo=0, lo_open=True)
        if t.has("poisson_ratio"):
            nu[mask] = t.num("poisson_ratio", _NU_EXPECTED, lo=0.25, hi=0.5, hi_open=True)
    return _Solid(E, nu, tau, rho, solid.key)


def _mass(t: Table) -> dict:
    which = t.one_of("mass", "density")
    unit = "kg per node" if which == "mass" else "kg/m^3"
    return {which: t.num(which, f"a positive number ({unit})", lo=0, lo_open=True)}


def _fixed_patch(t: Table, grid: Grid) -> torch.Tensor:
    """``[boundary] fixed = {below = h}`` (the nodes within h of the body's lowest node along D) or a region.

    A face of a mesh body is every node seen from that side (the whole lower half-shell for
    ``"bottom"``); a base patch fixes only what the body stands on.
    """
    p = Table(t.src, t.key("fixed"), t.data["fixed"], ("below", "box", "sphere"))
    if p.has("below"):
        for k in ("box", "sphere"):
            if p.has(k):
                raise p.fail(k, "one of below, box or sphere", got=p.data[k])
        h = p.num("below", "a height in metres >= 0 above the body's lowest node (along D)", lo=0)
        nodes = grid.nodes()
        d = grid.rest_positions(dtype=torch.float64)[0, 0]
        lowest = float(d[nodes].min())
        return nodes & (d <= lowest + h + 1e-9 * max(grid.spacing))
    return region_mask(p, grid)


def _boundary(t: Table, grid: Grid) -> dict:
    args = {}
    fixed = None
    if t.has("fixed"):
        fixed = _fixed_patch(t, grid) if isinstance(t.data["fixed"], dict) else faces(t, "fixed", grid)
    if t.has("fixed_nodes"):
        nodes = node_list(t, "fixed_nodes", grid)
        fixed = nodes if fixed is None else fixed | nodes
    if fixed is not None:
        args["fixed"] = fixed
    if t.has("home"):
        args["home"] = t.num("home", "a number >= 0 (N/m)", lo=0)
    if t.has("anchors"):
        a = Table(t.src, t.key("anchors"), t.data["anchors"], ("stiffness", "every"))
        args["anchors"] = (
            a.num("stiffness", "a number >= 0 (N/m)", lo=0),
            a.integer("every", "an integer >= 1 (every k-th node)", lo=1),
        )
    if t.has("decay"):
        args["decay"] = t.num("decay", "a rate >= 0 (1/s)", lo=0)
    if t.has("gravity"):
        args["gravity"] = t.vec("gravity", "three numbers [gd, gh, gw] in m/s^2")
    return args


def _loads(src: Source, items, grid: Grid) -> list:
    if not isinstance(items, list):
        raise src.error("loads", "[[loads]] tables", got=items)
    loads = []
    for n, item in enumerate(items):
        t = Table(src, f"loads[{n}]", item, SECTIONS["loads"])
        timing = dict(
            start=t.num("start", "a time >= 0 (s)", default=0.0, lo=0),
            ramp=t.num("ramp", "a duration >= 0 (s)", default=0.0, lo=0),
        )
        if t.one_of("node", "face") == "node":
            t.only_with("traction", "node")
            node = t.index("node")
            with src.located(t.key("node")):
                grid.index_mask([node])
            loads.append(PointForce(node, t.vec("force", "three numbers [fd, fh, fw] in N"), **timing))
        else:
            t.only_with("force", "face")
            face = t.text("face", "a face name: " + ", ".join(f'"{f}"' for f in FACES), choices=FACES)
            loads.append(SurfaceForce(face, t.vec("traction", "three numbers [td, th, tw] in Pa"), **timing))
    return loads


def _device(t: Table):
    device = t.text("device", 'a device name such as "cpu" or "cuda"', default=None)
    if device is not None:  # tried once: torch accepts names it cannot use ("meta", "xpu")
        try:
            usable_device(device, key="device")
        except ConfigError as e:
            raise t.fail("device", e.expected, got=device) from None
    return device


def _static(t: Table) -> dict:
    """The run settings of ``[integrator] name = "static"`` (:class:`StaticSolve`)."""
    for k in _DYNAMIC_ONLY:
        if t.has(k):
            raise t.fail(k, f'no {k} with name = "static" (a static solve takes no time steps)', got=t.data[k])
    opts = INTEGRATOR_OPTIONS["static"]
    solve = StaticSolve(
        tol=t.num("tol", opts["tol"], default=None, lo=0, lo_open=True, hi=1, hi_open=True),
        max_iter=t.integer("max_iter", opts["max_iter"], default=50, lo=1),
        cg_iters=t.integer("cg_iters", opts["cg_iters"], default=500, lo=1),
        cg_tol=t.num("cg_tol", opts["cg_tol"], default=1e-3, lo=0, lo_open=True, hi=1, hi_open=True),
        time=t.num("time", opts["time"], default=None, lo=0),  # None: set from the loads and drags
    )
    return dict(
        integrator=solve,
        dt="auto",
        steps=0,
        dtype=DTYPES[t.text("dtype", '"float32" or "float64"', default="float64", choices=DTYPES)],
        device=_device(t),
        threads=t.integer("threads", "an integer >= 1 (CPU threads of the run)", default=None, lo=1),
    )


def _settle(t: Table) -> bool | float:
    """``[integrator] settle``: true, a positive number of seconds, or false (the default)."""
    settle = t.data.get("settle", False)
    if settle is not False and not (settle is True or (is_number(settle) and settle > 0)):
        raise t.fail("settle", "true or a positive number of seconds (settle under gravity before the run)", got=settle)
    return settle if isinstance(settle, bool) else float(settle)


def _knoche_needs(t: Table, grid: Grid) -> None:
    """The knoche integrator's ``material`` (also where a sweep edits a scene past the reader's check) and 6 neighbours."""
    if not t.has("material"):
        raise t.fail("material", INTEGRATOR_OPTIONS["knoche"]["material"] + " (the knoche integrator needs it)")
    if grid.topology != 6:
        raise t.src.error("grid.topology", "6 for the knoche integrator", got=grid.topology)


def _integrator(t: Table, grid: Grid) -> dict:
    name = t.text("name", "one of " + ", ".join(f'"{n}"' for n in NAMES), default="symplectic", choices=NAMES)
    options = INTEGRATOR_OPTIONS[name]
    for k in t.data:
        if k not in SECTIONS["integrator"] and k not in options:
            own = ", ".join(options) if options else "none"
            raise t.fail(k, f"one of the keys {', '.join(SECTIONS['integrator'])} (options of {name}: {own})", got=k)
    if name == "static":
        if t.has("settle"):
            raise t.fail(
                "settle", 'no settle with name = "static" (its solve already starts from rest)', got=t.data["settle"]
            )
        return _static(t)
    kwargs = {}
    for k, expected in options.items():
        if not t.has(k):
            continue
        if k in _INTEGER_OPTIONS:
            kwargs[k] = t.integer(k, expected, lo=_INTEGER_OPTIONS[k])
        elif k in _TEXT_OPTIONS:
            kwargs[k] = t.text(k, expected, choices=_TEXT_OPTIONS[k])
        elif k in ("kd", "rho"):
            kwargs[k] = t.num(k, expected, lo=0, hi=1, hi_open=True)
        elif k == "relaxation":
            kwargs[k] = t.num(k, expected, lo=0, lo_open=True, hi=1)
        elif k in ("tol", "cg_tol") and name == "projective":
            kwargs[k] = t.num(k, expected, lo=0)
        elif k == "material":
            v = t.data[k]
            try:
                w = torch.as_tensor(v, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                raise t.fail(k, expected, got=v) from None
            if (
                isinstance(v, bool)
                or not (w.dim() == 0 or tuple(w.shape) == grid.shape)
                or not bool(((w >= 0) & (w <= 1)).all())
            ):
                raise t.fail(k, expected + f" (grid {grid.shape})", got=v if w.dim() == 0 else tuple(w.shape))
            kwargs[k] = float(w) if w.dim() == 0 else w
        else:
            kwargs[k] = t.num(k, expected, lo=0, lo_open=True)
    if name == "knoche":
        _knoche_needs(t, grid)
    with t.src.located(t.name):
        integrator = INTEGRATORS[name](**kwargs)

    dt = t.raw("dt", 'a positive number of seconds or "auto"')
    if dt == "auto":
        if name not in EXPLICIT:
            raise t.fail(
                "dt", f'a positive number of seconds ("auto" needs an explicit integrator, not {name})', got=dt
            )
    elif not (is_number(dt) and dt > 0):
        raise t.fail("dt", 'a positive number of seconds or "auto"', got=dt)
    if t.has("safety") and dt != "auto":
        raise t.fail("safety", 'no safety unless dt = "auto"', got=t.data["safety"])
    device = _device(t)
    return dict(
        integrator=integrator,
        settle=_settle(t),
        dt=dt if dt == "auto" else float(dt),
        safety=t.num("safety", "a number in (0, 1]", default=0.9, lo=0, hi=1, lo_open=True),
        steps=t.integer("steps", "an integer >= 0 (number of steps)"),
        dtype=DTYPES[t.text("dtype", '"float32" or "float64"', default="float32", choices=DTYPES)],
        device=device,
        threads=t.integer("threads", "an integer >= 1 (CPU threads of the run)", default=None, lo=1),
        engine=t.text(
            "engine",
            f"one of {', '.join(ENGINES)} (auto: native or compiled when the run repays it)",
            default="auto",
            choices=ENGINES,
        ),
    )


def _body(src: Source, data: dict, section: dict, grid: Grid) -> dict:
    """Model keywords of ``[material]``, ``[[regions]]`` and ``[mass]`` (or the tissue's density)."""
    model_args, solid = _material(section["material"], grid)
    if "regions" in data:
        if solid is None:
            model_args["stiffness"] = _regions(src, data["regions"], grid, model_args["stiffness"])
        else:
            solid = _elastic_regions(src, data["regions"], grid, solid)
    if solid is not None:
        model_args.update(solid.model_args(grid))
    if "mass" in section:
        model_args.update(_mass(section["mass"]))
        return model_args
    mass = None if solid is None else solid.mass_args(grid)  # the density of the tissue
    if mass is None:
        raise src.error(
            "mass",
            "a [mass] section (required) unless [material] tissue names a tissue of the library "
            "(whose density it then takes)",
        )
    return {**model_args, **mass}


def _check_static(src: Source, data: dict, out: Table) -> None:
    """Refuse what a static solve cannot do: tools, topology changes, frames over time, an animation."""
    for name in ("tools", "strain_limit", *TOPOLOGY):
        if name in data:
            raise src.error(
                name,
                f'no [{name}] with [integrator] name = "static" (a static solve has no time steps for it to act in)',
            )
    for key in ("record_every", "surfaces", "animation", "palpation"):
        if out.has(key):
            raise out.fail(
                key,
                f'no {key} with [integrator] name = "static" (its run has two frames: rest and equilibrium)',
                got=out.data[key],
            )


#: ``up``: the mesh axis that becomes the lattice's axis D ("up"), with a sign
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


def _up_rotation(up: str) -> np.ndarray:
    """The rotation ``(3, 3)`` taking mesh ``(x, y, z)`` to lattice ``(D, H, W)`` with mesh axis ``up`` along +D.

    ``"x"``: D, H, W = x, y, z; ``"y"``: y, z, x; ``"z"``: z, x, y (cyclic, so a proper rotation that keeps
    the mesh's inside in); a minus sign turns D and H round.
    """
    axis = "xyz".index(up[-1])
    R = np.zeros((3, 3))
    for row in range(3):
        R[row, (axis + row) % 3] = 1.0
    if up.startswith("-"):
        R[:2] *= -1.0
    return R


def _up_value(src: Source, key: str, value) -> str:
    if value not in UP_AXES:
        raise src.error(
            key,
            'the mesh axis that points up (becomes the lattice axis D): "x" (default), "y", "z", "-x", "-y" or "-z"',
            got=value,
        )
    return value


def _surface_ups(src: Source, items) -> list | None:
    """The ``up`` of each ``[[surfaces]]`` table (``"x"`` where not given), or None when no table gives one."""
    if not isinstance(items, list) or not any(isinstance(i, dict) and "up" in i for i in items):
        return None
    return [
        _up_value(src, f"surfaces[{n}].up", i.get("up", "x")) if isinstance(i, dict) else "x"
        for n, i in enumerate(items)
    ]


@contextmanager
def _up_mesh(t: Table, base):
    """A ``[grid]`` table and folder whose ``mesh`` is turned so that its ``up`` axis is D (a context).

    Without ``up`` (or ``up = "x"``) the table (less ``up``) and the folder; else a copy of the table
    naming the turned mesh, written to a temporary folder that is removed afterwards.
    """
    if not t.has("up"):
        yield t, Path(base)
        return
    if not t.has("mesh"):
        raise t.fail("up", "no up without mesh (a box body has axis D up)", got=t.data["up"])
    up = _up_value(t.src, t.key("up"), t.data["up"])
    data = {k: v for k, v in t.data.items() if k != "up"}
    if up == "x":
        yield Table(t.src, t.name, data, tuple(data)), Path(base)
        return
    import tempfile

    import trimesh

    from ..mesh.surfaces import load_mesh

    mesh = t.text("mesh", "a mesh file name (relative to the scene file)")
    with t.src.located(t.key("mesh")):
        v, f = load_mesh(Path(base) / mesh)
    with tempfile.TemporaryDirectory(prefix="torchdeform-up-") as folder:
        turned = Path(folder) / (Path(mesh).stem + ".ply")
        trimesh.Trimesh(vertices=v @ _up_rotation(up).T, faces=f, process=False).export(turned)
        data["mesh"] = str(turned)
        yield Table(t.src, t.name, data, tuple(data)), Path(base)


def _grid_and_body(src: Source, data: dict, section: dict, base: Path, *, surfaces: bool = False) -> tuple:
    """``(grid, model keywords, embedded surfaces or None)`` of ``[grid]`` and the material sections."""
    if "tissues" in data and not section["grid"].has("labels"):
        raise src.error("tissues", "[[tissues]] only with [grid] labels (a label volume); else [[regions]]")
    embedded, user = None, None
    if "surfaces" in data:  # the user's meshes, embedded in the lattice (scene.anatomy)
        from .anatomy import surfaces_section

        ups = _surface_ups(src, data["surfaces"])
        items = [{k: v for k, v in item.items() if k != "up"} for item in data["surfaces"]] if ups else data["surfaces"]
        user = surfaces_section(src, items, base)
        for n, name in enumerate(list(user)):
            if ups and ups[n] != "x":
                v, f, key, file = user[name]
                user[name] = (np.ascontiguousarray(np.asarray(v) @ _up_rotation(ups[n]).T), f, key, file)
    if section["grid"].has("labels"):
        from .anatomy import label_body_section

        if section["grid"].has("up"):
            raise section["grid"].fail(
                "up", "no up with labels (a body of labels keeps its LPS frame)", got=section["grid"].data["up"]
            )

        grid, model_args, embedded = label_body_section(src, data, section, base, user=user, surfaces=surfaces)
    else:
        out_ = data.get("output")
        if isinstance(out_, dict) and out_.get("surfaces") == "embedded" and user is None:
            raise src.error(
                "output.surfaces",
                'times [t1, t2, ...]; "embedded" needs a body of labels ([grid] labels) or [[surfaces]]',
                got="embedded",
            )
        with _up_mesh(section["grid"], base) as (table, folder):
            grid = grid_section(table, folder)
        _plausible_size(section["grid"], grid)
        if user:
            from .anatomy import cover_surfaces

            grid = cover_surfaces(grid, user)
        model_args = _body(src, data, section, grid)
    if user:
        from .anatomy import check_surfaces

        embedded = {**(embedded or {}), **check_surfaces(src, grid, user)}
    return grid, model_args, embedded


def _embedded_outputs(scene: Scene, out: Table, embedded) -> None:
    """``[output] surfaces = "embedded"``, ``surface_format``: the scene's embedded surfaces and their files."""
    if embedded is not None:
        scene.embedded = embedded
        scene.surface_format = out.text("surface_format", '"glb" or "ply"', default="glb", choices=("glb", "ply"))
        scene.write_surfaces = out.data.get("surfaces") == "embedded"
        return
    for k in ("surface_format", "surface_faces"):
        out.only_with(k, 'surfaces = "embedded"')


def mass_spring_scene(src: Source, data: dict, base: Path, *, name: str = "scene", surfaces: bool = False) -> Scene:
    """Build a :class:`Scene` from a parsed scene file whose model is ``"mass-spring"``.

    The file is parsed by :func:`~torchdeform.scene.reader.read`; this is called by
    :func:`torchdeform.scene.load_scene`. The model is built once (on the CPU) to check every
    value.

    Args:
        src: the file (for located errors).
        data: its parsed TOML.
        base: the folder that relative paths (mesh, volume) start from.
        name: the default title of the run.
        surfaces: make a body of labels' smooth surfaces even when the scene neither writes nor
            animates them (:func:`~torchdeform.scene.load_scene`).
    """
    if "chainmail" in data:
        raise src.error("chainmail", 'model = "chainmail" (a top-level key) for a [chainmail] section')
    options = tuple(k for opts in INTEGRATOR_OPTIONS.values() for k in opts)
    section = {
        name_: Table(src, name_, data[name_], keys + (options if name_ == "integrator" else ()))
        for name_, keys in SECTIONS.items()
        if name_ in data
        and name_ not in ("loads", "drags", "regions", "tissues", "tools", "cuts", "cautery", "coagulate", "surfaces")
    }
    grid, model_args, embedded = _grid_and_body(src, data, section, base, surfaces=surfaces)
    if "boundary" in section:
        fixed = model_args.get("fixed")
        model_args.update(_boundary(section["boundary"], grid))
        if fixed is not None and "fixed" in model_args and model_args["fixed"] is not fixed:
            model_args["fixed"] = model_args["fixed"] | fixed  # the fixed labels stay fixed
    if "loads" in data:
        model_args["loads"] = _loads(src, data["loads"], grid)
    if "drags" in data:
        model_args["drags"] = drags_section(src, data["drags"], grid)
    tools = None
    if "tools" in data or "strain_limit" in data:
        tools = tools_with_cutters(src, data, base) if "tools" in data else ToolSet()
        if "strain_limit" in section:
            tools.strain_limit = strain_limit_section(section["strain_limit"])
        model_args["interactions"] = tools.interactions()
    run = _integrator(section["integrator"], grid)
    out = section.get("output") or Table(src, "output", {}, SECTIONS["output"])
    if isinstance(run["integrator"], StaticSolve):
        _check_static(src, data, out)
        if run["integrator"].time is None:
            run["integrator"].time = full_load_time(model_args.get("loads"), model_args.get("drags"))
    palpation = palpation_option(out, tools)
    if palpation is not None:
        assert tools is not None  # palpation names a tool
        tools.palpation = palpation
    topology = None
    timed_surfaces = out.has("surfaces") and out.data["surfaces"] != "embedded"
    if any(k in data for k in TOPOLOGY) or timed_surfaces:  # times checked now if dt is a number
        end = None if run["dt"] == "auto" else run["steps"] * run["dt"]
        topology = topology_section(src, data, grid, tools, out, end=end)
    scene = Scene(
        grid,
        model_args,
        **run,
        source=src,
        record_every=out.integer("record_every", "an integer >= 1 (steps between frames)", default=None, lo=1),
        name=out.text("name", "a string", default=name),
        tools=tools,
        topology=topology,
    )
    frames = scene.steps // scene.frames_every + 2  # recorded positions and velocities, kept on the CPU
    key = "output.record_every" if scene.record_every else "integrator.steps"
    with src.located(key, keys={key: key}):
        check_memory(
            key,
            6.0 * frames * grid.num_nodes * scene.dtype.itemsize,
            f"{frames} recorded frames of {grid.num_nodes} nodes",
            got=scene.record_every or scene.steps,
        )
    animation = out.flag("animation", expected="true or false (write animation.gif)", default=False)
    scene.animation = "animation.gif" if animation else None
    _embedded_outputs(scene, out, embedded)
    scene.image_size = out.integer("image_size", "an integer number of pixels in [64, 2048]", default=512, lo=64)
    if scene.image_size > 2048:
        raise out.fail("image_size", "an integer number of pixels in [64, 2048]", got=scene.image_size)
    _camera_keys(scene, out, patient=section["grid"].has("labels"))
    if "volume" in data:
        vt = Table(src, "volume", data["volume"], SECTIONS["volume"])
        scene.volume = {
            "file": vt.text("file", 'a volume file or "phantom:N"'),
            "tf": vt.text("tf", "a transfer-function preset or file", default="ct-soft"),
            "mode": vt.text("mode", '"dvr", "mip" or "average"', default="dvr", choices=("dvr", "mip", "average")),
            "view": vt.text(
                "view", "an axis view d, h, w, -d, -h, -w", default="h", choices=("d", "h", "w", "-d", "-h", "-w")
            ),
            "base": str(base),
        }
        from ..volume.io import check_volume_source
        from ..volume.transfer import get_tf

        name = scene.volume["file"]  # checked now, not after the simulation
        with src.located("volume.file", keys={"volume": "volume.file", "volume.file": "volume.file"}):
            if section["grid"].has("labels"):  # a CT in the labels' frame, onto the lattice's box
                from .anatomy import lattice_ct

                scene.volume["file"] = lattice_ct(name, Path(base), section["grid"], grid)
            else:
                check_volume_source(name if name.startswith("phantom") else Path(base) / name, "volume.file")
        with src.located("volume.tf", keys={"transfer function": "volume.tf", "control point": "volume.tf"}):
            get_tf(scene.volume["tf"])
    if "camera" in data:
        from .camera import camera_section

        scene.camera_view = camera_section(src, data, scene.tools, has_volume=scene.volume is not None)
    if "texture" in data:
        from ..texture.synthesis import SEAM_METHODS

        tt = Table(src, "texture", data["texture"], SECTIONS["texture"])
        exemplar = tt.text(
            "exemplar", "liver, liver:N or an exemplar file (.npy, .npz, a folder of slices)", default="liver:64"
        )
        if not exemplar.startswith("liver"):
            exemplar = str(Path(base) / exemplar)
        with src.located(tt.key("exemplar")):
            from ..texture.exemplar import exemplar_from

            ex = exemplar_from(exemplar, seed=tt.integer("seed", "an integer >= 0", default=0))
        block = tt.integer("block", "an integer block size >= 2 (voxels)", default=min(ex.shape[1:]) // 2, lo=2)
        if block > min(ex.shape[1:]):
            raise tt.fail(
                "block", f"a block no larger than the exemplar's smallest side ({min(ex.shape[1:])} voxels)", got=block
            )
        spacing = min(scene.grid.spacing)
        scene.texture = {
            "exemplar": ex,
            "block": block,
            "seed": tt.integer("seed", "an integer >= 0", default=0),
            "voxel": tt.num("voxel", "a positive voxel size (m)", default=spacing / 4, lo=0, lo_open=True),
            "seams": tt.text("seams", " or ".join(f'"{m}"' for m in SEAM_METHODS), default="3d", choices=SEAM_METHODS),
        }
    scene.build(device="cpu")
    if tools is not None:  # last: a scene with a mistake says that first, and only that
        check_tool_reach(src, tools, grid)
    return scene


#: the surface camera of a body of labels (LPS patient frame, lying on the back): from the patient's
#: right, in front and a little above the head end, anterior (-y) up in the image
PATIENT_CAMERA, PATIENT_UP = (-1.2, -0.9, 0.5), (0.0, -1.0, 0.0)


def _camera_keys(scene: Scene, out: Table, *, patient: bool) -> None:
    """``[output] camera`` and ``camera_up``: the animation's surface view (patient scenes: from the right)."""
    expected = "[x, y, z]: a direction from the body's centre, not zero"
    camera = out.vec("camera", expected, default=PATIENT_CAMERA if patient else None)
    up = out.vec("camera_up", "[x, y, z]: the direction upwards in the image, not zero", default=None)
    if up is None and patient:
        up = PATIENT_UP
    for k, v in (("camera", camera), ("camera_up", up)):
        if v is not None and not any(v):
            raise out.fail(k, expected if k == "camera" else "a direction [x, y, z], not zero", got=list(v))
    if camera is not None and up is not None:
        c, u = np.asarray(camera, float), np.asarray(up, float)
        if np.linalg.norm(np.cross(c, u)) < 1e-6 * np.linalg.norm(c) * np.linalg.norm(u):
            raise out.fail("camera_up", "a direction not parallel to camera", got=list(up))
    scene.camera, scene.camera_up = camera, up


# ------------------------------------------------------------------ a small cube
def cube_scene() -> Scene:
    """A small dragged cube (same as ``scenes/cube.toml``), built with the Python API.

    A 1 cm cube of liver-like tissue (11 x 11 x 11 nodes, 1 mm apart, 26 neighbours,
    density 1000 kg/m^3, k = 3 N/m, i.e. E of roughly 8 kPa), its base fixed, sagging under
    gravity (along -D), its top centre node dragged 2 mm up and 1 mm sideways within 50 ms
    and then held; symplectic Euler at dt = 0.1 ms (below the bound of about 0.12 ms) for
    0.15 s, with global drag so it settles. ``run_scene`` also writes ``animation.gif``, the animation of
    the run (the textured surface beside the deformed phantom, time and drag force written on it).

    Examples:
        >>> import torchdeform as td
        >>> scene = td.cube_scene()
        >>> scene.grid.shape, scene.integrator.name, scene.dt, scene.steps
        ((11, 11, 11), 'symplectic', 0.0001, 1500)
        >>> len(scene.model_args["drags"]), scene.volume["file"], scene.animation
        (1, 'phantom:64', 'animation.gif')
    """
    grid = Grid((11, 11, 11), spacing=(0.001, 0.001, 0.001), topology=26)
    top_centre = Drag(grid.index_mask([(10, 5, 5)]), path=[(0.0, (0.0, 0.0, 0.0)), (0.05, (0.002, 0.001, 0.0))])
    model_args = dict(
        stiffness=3.0,
        normalize=False,
        damping=1e-4,
        damping_mode="projected",
        density=1000.0,
        fixed=grid.face("bottom"),
        decay=100.0,
        gravity=(-9.81, 0.0, 0.0),
        drags=[top_centre],
    )
    # the procedural CT phantom fills the cube; run_scene also writes its before/after renders
    volume = {"file": "phantom:64", "tf": "ct-soft", "mode": "dvr", "view": "h"}
    return Scene(
        grid,
        model_args,
        integrator=SymplecticEuler(),
        dt=1e-4,
        steps=1500,
        record_every=15,
        name="cube",
        volume=volume,
        animation="animation.gif",
    )
