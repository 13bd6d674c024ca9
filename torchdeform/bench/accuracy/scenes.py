"""The standard scenes of ``torchdeform bench accuracy``: scaled cubes and their loads.

Every scene is a cube of side :data:`SIDE` with ``n^3`` nodes and 26 neighbours, physically scaled
so that a finer grid is the same material (:func:`cube`, :func:`cell_share`); :data:`SCENES` names
them (the table in :mod:`torchdeform.bench.accuracy`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, field

import torch

from ...sim.forces import Drag, SurfaceForce
from ...sim.grid import Grid

__all__ = ["SIDE", "DENSITY", "cell_share", "cube", "AccuracyScene", "SCENES"]

SIDE = 0.04  # cube side (m)
DENSITY = 1000.0  # kg/m^3


def cell_share(grid: Grid) -> torch.Tensor:
    """Share of the grid cells bordering each spring, float64 ``(S, D, H, W)``.

    A spring along half-direction ``d`` lies in the cells spanned by ``[i_c, i_c + d_c]`` along
    every axis with ``d_c != 0`` and by either neighbouring cell along every axis with
    ``d_c == 0``; on the first or last node of such an axis only one of the two exists. So
    ``s = prod_{c: d_c = 0} w_c(i_c)`` with ``w_c = 1/2`` on the first and last node of axis
    ``c`` and 1 elsewhere (interior springs 1, springs in a face of the box 1/2, along an edge
    of the box 1/4): the weights that make a lattice with ``k = E h s`` the same material at
    every resolution, as :func:`~torchdeform.sim.model.lumped_mass` does for masses.
    Entries of springs that leave the grid are unused.
    """
    out = torch.ones((grid.S,) + grid.shape, dtype=torch.float64)
    for s, d in enumerate(grid.directions):
        for axis, (dc, n) in enumerate(zip(d, grid.shape)):
            if dc == 0 and n > 1:
                w = torch.ones(n, dtype=torch.float64)
                w[0] = w[-1] = 0.5
                out[s] = out[s] * w.view([-1 if a == axis else 1 for a in range(3)])
    return out


def cube(n: int, modulus: float, tau: float, decay: float | None, **terms) -> tuple[Grid, dict]:
    """A ``n^3`` cube of side :data:`SIDE`, 26 neighbours, scaled for a continuum limit.

    Springs ``k = modulus * h * cell_share`` (N/m) with ``h = SIDE / (n - 1)``, dashpots
    ``c = tau * k`` (N s/m), masses from :data:`DENSITY`, global drag ``decay`` (1/s), bottom
    face fixed unless ``terms`` gives ``fixed``.

    Returns:
        ``(grid, kwargs)``: ``Model(grid, **kwargs, dtype=..., device=...)`` builds the model.
    """
    h = SIDE / (n - 1)
    grid = Grid((n, n, n), spacing=h, topology=26)
    k = modulus * h * cell_share(grid)
    kwargs = dict(stiffness=k, damping=tau * k, density=DENSITY, decay=decay)
    kwargs["fixed"] = grid.face("bottom")
    kwargs.update(terms)
    return grid, kwargs


def _quarter_nodes(n: int) -> list[int]:
    return sorted({round((n - 1) / 4), round(3 * (n - 1) / 4)})


def _load(n, T):
    return cube(n, 5e3, 4e-4, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0))])


def _stiff(n, T):
    return cube(n, 5e5, 4e-5, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0), ramp=T)])


def _inclusion(n, T):
    """The load cube with a bone-like inclusion: springs inside a central ball 1000x stiffer.

    The ball (radius a quarter of the side, and at least the central nodes) has 1000x the modulus and the same relaxation time
    ``tau`` (so 1000x the dashpots); a spring between the ball and the tissue is the two in
    series (harmonic mean of its ends' factors).
    """
    from ...sim.springs import harmonic_mean_of_ends

    grid, kw = cube(n, 5e3, 4e-4, 20.0, loads=[SurfaceForce("top", (-100.0, 100.0, 0.0))])
    idx = torch.arange(n, dtype=torch.float64) - (n - 1) / 2
    r2 = idx.view(-1, 1, 1) ** 2 + idx.view(1, -1, 1) ** 2 + idx.view(1, 1, -1) ** 2
    radius2 = max(((n - 1) / 4) ** 2, 0.75)  # at least the central node(s)
    factor = torch.where(r2 <= radius2 + 1e-9, 1000.0, 1.0).to(torch.float64)
    per_spring = harmonic_mean_of_ends(factor[None], grid)[0]
    kw["stiffness"] = kw["stiffness"] * per_spring
    kw["damping"] = kw["damping"] * per_spring
    return grid, kw


def _drag(n, T):
    grid, kw = cube(n, 5e3, 4e-4, 20.0)
    c, r = (n - 1) / 2, (n - 1) / 4
    idx = torch.arange(n, dtype=torch.float64)
    near = (idx - c).abs() <= r + 1e-9
    patch = grid.face("top") & near.view(1, n, 1) & near.view(1, 1, n)
    kw["drags"] = [Drag(patch, path=[(0.0, (0.0, 0.0, 0.0)), (T / 2, (0.0, 0.004, 0.0))])]
    return grid, kw


def _supports(n, T):
    grid, kw = cube(n, 5e3, 4e-4, 20.0, gravity=(-9.81, 0.0, 0.0))
    q = _quarter_nodes(n)
    kw["fixed"] = grid.index_mask([(0, i, j) for i in q for j in q])
    return grid, kw


@dataclass(frozen=True)
class AccuracyScene:
    """One standard scene.

    Args:
        name, help: its name in the rows and one line for the report.
        build: ``(n, T) -> (grid, Model kwargs)``.
        duration, quick_duration: run length ``T`` (s), default and ``--quick``.
        static: True for an equilibrium scene (compared at ``T = inf``, no time steps).
        multiples: per-method overrides of the step multiples, ``{method: (default, quick)}``.
        ref_div: the reference step is the RK4 bound divided by this (``--ref-div`` overrides).
    """

    name: str
    help: str
    build: Callable
    _: KW_ONLY
    duration: float = 0.0
    quick_duration: float = 0.0
    static: bool = False
    multiples: dict = field(default_factory=dict)
    ref_div: float | None = None


# The stiff scene is the expensive one for explicit methods: fewer small steps there.
_STIFF = ((0.45, 0.9, 2), (0.9, 2))
_STIFF_EULER = ((0.9, 10), (0.9, 10))
_INCLUSION = ((0.9, 2), (0.9,))
SCENES = {
    "load": AccuracyScene(
        "load",
        "bottom fixed, top traction (-100, 100, 0) Pa from t=0, E 5 kPa, dashpots tau 0.4 ms, drag 20/s",
        _load,
        duration=0.045,
        quick_duration=0.03,
    ),
    "stiff": AccuracyScene(
        "stiff",
        "load scene 100x stiffer (E 500 kPa, tau 0.04 ms), traction ramped in over the whole run",
        _stiff,
        duration=0.03,
        quick_duration=0.003,
        multiples={
            "explicit": _STIFF_EULER,
            "symplectic": _STIFF,
            "verlet": _STIFF,
            "rk4": _STIFF,
            "implicit": ((5, 10, 20, 50), (4,)),
        },
        ref_div=5,
    ),
    "inclusion": AccuracyScene(
        "inclusion",
        "the load cube with a central bone-like ball (radius 1 cm) 1000x stiffer than the tissue around it",
        _inclusion,
        duration=0.015,
        quick_duration=0.0015,
        multiples={
            "explicit": _STIFF_EULER,
            "symplectic": _INCLUSION,
            "verlet": _INCLUSION,
            "rk4": _INCLUSION,
            "implicit": ((5, 20, 100, 300), (20,)),
            "adaptive": ((1e-2, 1e-4), (1e-2,)),
            "projective": (((20, 10), (100, 10), (300, 10), (100, 30)), ((100, 10),)),
        },
        ref_div=5,
    ),
    "drag": AccuracyScene(
        "drag",
        "bottom fixed, central top patch dragged 4 mm sideways over T/2, then held",
        _drag,
        duration=0.045,
        quick_duration=0.03,
    ),
    "supports": AccuracyScene(
        "supports",
        "released under gravity onto 4 fixed support nodes of its "
        "bottom face (fixed nodes from t=0: smooth, no contact)",
        _supports,
        duration=0.045,
        quick_duration=0.03,
    ),
    "load-static": AccuracyScene(
        "load-static", "the load cube at equilibrium, resolution sweep against a fine grid", _load, static=True
    ),
}
