r"""The finite-element reference's load cases on an :class:`~torchdeform.sim.material.Elastic` lattice body.

Each function builds the body of one problem of :mod:`.fem` on a lattice of cubic cells of side
``h`` and solves it in the small-strain limit, as the linear finite elements do: the stiffness at
rest ``K`` (:meth:`~torchdeform.sim.model.Model.linearise` at the rest positions: springs and the
volume term), conjugate gradients (:func:`~torchdeform.sim.integrators.conjugate_gradient`, Jacobi
preconditioner, relative residual :data:`CG_TOL`) on the free nodes with the constrained nodes at
their prescribed displacement ``u_b``:

.. math::

    K_{ff} u_f = f_f - K_{fb} u_b, \qquad R_b = (K u)_b - f_b ,

``R_b`` the force the constraints apply. Shapes: displacements ``(1, 3, D, H, W)`` in metres,
float64, on the CPU; the conventions are the lattice's and :mod:`.fem`'s (axes ``(D, H, W)`` =
``(x0, x1, x2)``, ``x0`` up, every box from the origin). Sizes must be whole multiples of ``h``
(5 mm divided by a whole number fits them all).

=======================  ==============================  ===========================================
function                 body                            answer (the :mod:`.fem` function)
=======================  ==============================  ===========================================
:func:`lattice_uniaxial`         free 10 mm cube, normal         mean strains, ``E`` and ``nu`` they imply
                         tractions +-t on the W faces    (:func:`.fem.uniaxial_pull`)
:func:`lattice_shear`            5 x 50 x 50 mm between bonded   the force on the top plate, N
                         plates, top moved ``gamma L0``  (:func:`.fem.simple_shear`)
:func:`lattice_punch`            20 x 40 x 40 mm block, bonded   the force on the punch, N
                         10 x 10 mm punch, ``depth``     (:func:`.fem.bonded_punch_force`)
:func:`lattice_cantilever`       10 x 10 x 60 mm beam clamped    mean deflection of the free end, m
                         at w = 0, gravity along -x0     (:func:`.fem.cantilever_tip`)
=======================  ==============================  ===========================================

The free cube has no constrained node: its tractions sum to zero force and torque, so the
singular system is consistent and conjugate gradients from zero stay clear of the rigid modes
(the strains read are differences of face means, which a rigid motion leaves unchanged). Its
tractions are the consistent nodal forces of a uniform traction on bilinear faces (``t h^2``
per face node, half on an edge, a quarter at a corner). Every cell of an ``Elastic`` body carries
the continuum's energy for a uniform strain, so the lattice reproduces ``E`` and ``nu`` to the
solver's tolerance at any ``h``: :func:`lattice_uniaxial` checks the calibration, the other three measure
the discretisation.

Example:
    >>> from torchdeform.bench.accuracy import lattice
    >>> pull = lattice.lattice_uniaxial(0.45, 0.005)                 # 3 x 3 x 3 nodes
    >>> round(pull.E / lattice.YOUNGS, 6), round(pull.nu, 6)
    (1.0, 0.45)
"""

from __future__ import annotations

import torch

from ...errors import ConfigError
from ...sim.grid import Grid
from ...sim.integrators import conjugate_gradient
from ...sim.material import Elastic
from ...sim.model import Model
from .fem import Uniaxial

__all__ = [
    "YOUNGS",
    "CG_TOL",
    "small_strain",
    "lattice_uniaxial",
    "lattice_shear",
    "lattice_punch",
    "lattice_cantilever",
    "shear_fits",
]

#: Young's modulus of every case (Pa), as in the tests and the bench
YOUNGS = 5e3
#: relative residual ``|r| / |b|`` at which the conjugate gradients of :func:`small_strain` stop
CG_TOL = 1e-11

F64 = torch.float64


def _nodes(length: float, h: float, key: str) -> int:
    """Nodes along a side of ``length`` (m) at spacing ``h``; refuses a side that is not a whole number of cells."""
    cells = length / h
    if abs(cells - round(cells)) > 1e-6 or round(cells) < 1:
        raise ConfigError(key, f"a spacing that divides {length * 1e3:g} mm into whole cells", got=h)
    return round(cells) + 1


def small_strain(model: Model, *, loads=None, fixed=None, ub=None, tol: float = CG_TOL, iters: int = 50_000):
    """Small-strain displacements ``u`` and the forces ``K u - f``, both ``(1, 3, D, H, W)``.

    ``loads``: node loads ``f`` (N) or None; ``fixed``: bool ``(D, H, W)``, the nodes held at ``ub`` (m, the
    same shape as ``u``; zero if None), or None for a free body (then ``f`` must balance).
    ``K u - f`` is the constraints' reaction at the fixed nodes (zero elsewhere, up to ``tol``).
    """
    X = model.X
    f = torch.zeros_like(X) if loads is None else loads
    ub = torch.zeros_like(X) if ub is None else ub
    lin = model.linearise(X)
    free = torch.ones_like(X[:, :1]) if fixed is None else (~fixed).to(X.dtype)[None, None]
    diag = model.stiffness_row_sums()  # Gershgorin row sums: a Jacobi preconditioner
    precond = free / diag.clamp_min(float(diag.max()) * 1e-12)
    b = (f - lin.apply(ub)) * free
    if float(b.abs().max()) == 0.0:
        u = ub
    else:
        du, _, _ = conjugate_gradient(lin.apply, b, precond=precond, mask=free, iters=iters, tol=tol)
        u = du + ub
    return u, lin.apply(u) - f


def _elastic(shape, h: float, nu: float, topology: int, E: float, **kw) -> Model:
    grid = Grid(shape, spacing=h, topology=topology)
    return Model(grid, Elastic(E, nu), dtype=F64, **kw)


def _face_weights(n1: int, n2: int, h: float) -> torch.Tensor:
    """The area (m^2) each node of an ``n1 x n2`` face of cells ``h`` stands for (bilinear faces)."""
    w1, w2 = torch.full((n1,), h, dtype=F64), torch.full((n2,), h, dtype=F64)
    w1[[0, -1]] *= 0.5
    w2[[0, -1]] *= 0.5
    return w1[:, None] * w2[None, :]


def lattice_uniaxial(
    nu: float, h: float, *, topology: int = 26, youngs_modulus: float = YOUNGS, size: float = 0.01, traction=100.0
) -> Uniaxial:
    """A free cube of side ``size`` pulled by normal tractions ``+-traction`` (Pa) on its two W faces.

    Returns the mean strains (differences of the opposite faces' mean displacements over the side)
    and ``E = traction / strain_axial``, ``nu = -mean(lateral) / strain_axial``, as
    :func:`.fem.uniaxial_pull` (which models the octant of the same cube).
    """
    n = _nodes(size, h, "h")
    model = _elastic((n, n, n), h, nu, topology, youngs_modulus, mass=1.0)
    f = torch.zeros_like(model.X)
    area = _face_weights(n, n, h) * traction
    f[0, 2, :, :, -1] = area
    f[0, 2, :, :, 0] = -area
    u, _ = small_strain(model, loads=f)
    u = u[0]
    axial = float(u[2, :, :, -1].mean() - u[2, :, :, 0].mean()) / size
    lat = (float(u[0, -1].mean() - u[0, 0].mean()) / size, float(u[1, :, -1].mean() - u[1, :, 0].mean()) / size)
    return Uniaxial(axial, lat, traction / axial, -0.5 * (lat[0] + lat[1]) / axial)


def shear_fits(h: float, *, thickness: float = 0.005) -> bool:
    """Whether the shear box ``thickness`` thick leaves a free layer of nodes between its plates at spacing ``h``."""
    return thickness / h > 1.5


def lattice_shear(
    nu: float, h: float, *, topology: int = 26, youngs_modulus: float = YOUNGS, gamma: float = 0.01
) -> float:
    """Shear force (N) of the 5 x 50 x 50 mm box between bonded plates, as :func:`.fem.simple_shear`.

    Base ``x0 = 0`` fixed; the top ``x0 = 5 mm`` moved by ``gamma * 5 mm`` along ``x2``; the force
    is the top nodes' reaction along ``x2``. Needs ``h <= 2.5 mm`` (:func:`shear_fits`).
    """
    if not shear_fits(h):
        raise ConfigError("h", "a spacing of at most 2.5 mm (a free layer between the plates)", got=h)
    nd, nh = _nodes(0.005, h, "h"), _nodes(0.05, h, "h")
    model = _elastic((nd, nh, nh), h, nu, topology, youngs_modulus, mass=1.0)
    grid = model.grid
    ub = torch.zeros_like(model.X)
    ub[0, 2, -1] = gamma * 0.005
    _, R = small_strain(model, fixed=grid.face("bottom") | grid.face("top"), ub=ub)
    return float(R[0, 2, -1].sum())


def lattice_punch(
    nu: float, h: float, *, topology: int = 26, youngs_modulus: float = YOUNGS, depth: float = 5e-4
) -> float:
    """Force (N) on a bonded 10 x 10 mm punch pressed ``depth`` into a 20 x 40 x 40 mm block, as :func:`.fem.bonded_punch_force`.

    Base fixed; the top nodes inside the centred footprint (edges included) moved by ``-depth``
    along ``x0`` and held in ``x1``, ``x2``; the force is minus their reaction along ``x0``.
    """
    nd, nh = _nodes(0.02, h, "h"), _nodes(0.04, h, "h")
    model = _elastic((nd, nh, nh), h, nu, topology, youngs_modulus, mass=1.0)
    x1, x2 = model.X[0, 1, -1], model.X[0, 2, -1]
    lo, hi = 0.015 - 1e-9, 0.025 + 1e-9
    pressed = torch.zeros(model.grid.shape, dtype=torch.bool)
    pressed[-1] = (x1 >= lo) & (x1 <= hi) & (x2 >= lo) & (x2 <= hi)
    ub = torch.zeros_like(model.X)
    ub[0, 0][pressed] = -depth
    _, R = small_strain(model, fixed=model.grid.face("bottom") | pressed, ub=ub)
    return float(-R[0, 0][pressed].sum())


def cantilever_model(
    cells: int,
    *,
    nu: float = 0.45,
    topology: int = 26,
    youngs_modulus: float = YOUNGS,
    rho=1000.0,
    dtype=F64,
    device=None,
) -> Model:
    """The 10 x 10 x 60 mm beam, ``cells`` cells along its length, clamped at w = 0, under gravity ``-9.81`` along ``x0``."""
    h = 0.06 / cells
    n = _nodes(0.01, h, "cells")
    grid = Grid((n, n, cells + 1), spacing=h, topology=topology)
    return Model(
        grid,
        Elastic(youngs_modulus, nu),
        density=rho,
        gravity=(-9.81, 0.0, 0.0),
        fixed=grid.face("w-"),
        dtype=dtype,
        device=device,
    )


def lattice_cantilever(
    nu: float, cells: int, *, topology: int = 26, youngs_modulus: float = YOUNGS, rho: float = 1000.0
) -> float:
    """Mean deflection (m, negative: it sags) of the free end of :func:`cantilever_model`, as :func:`.fem.cantilever_tip` ``.mean``."""
    model = cantilever_model(cells, nu=nu, topology=topology, youngs_modulus=youngs_modulus, rho=rho)
    f = model.mass * torch.tensor([-9.81, 0.0, 0.0], dtype=F64).view(1, 3, 1, 1, 1)
    u, _ = small_strain(model, loads=f, fixed=model.grid.face("w-"))
    return float(u[0, 0, :, :, -1].mean())
