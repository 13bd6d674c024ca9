"""Finite-element reference for small-strain linear isotropic elasticity, built on scikit-fem.

The reference of ``torchdeform bench elasticity`` and ``training/fit_fem.py`` and the tests'
oracle of :class:`~torchdeform.sim.material.Elastic`; it needs the ``fem`` extra
(``pip install torchdeform[fem]``). Nothing here calls the rest of torchdeform. It solves ``-div sigma(u) = rho b`` with
``sigma = lambda tr(eps) I + 2 mu eps``, ``eps = sym grad u`` (skfem.models.elasticity:
``linear_elasticity``, ``lame_parameters``) on boxes, in SI units (m, Pa, N, kg/m^3). The
conventions are the lattice's: coordinates ``(x0, x1, x2)`` are the axes ``(D, H, W)``, ``x0`` is up,
gravity acts along ``-x0`` and every box starts at the origin.

Discretisation: ``MeshHex.init_tensor`` tensor-product hexahedra, triquadratic 27-node Lagrange
elements (``ElementVector(ElementHex2())``), 3x3x3 Gauss points (``intorder=4``, exact for the
stiffness of box elements; the default order, 7x7x7 points, is 13 times slower and no more exact).
Where the solution is singular (the edges where a clamp or a bonded punch meets a free face), the
cells are graded geometrically toward the singular edges: the smallest cell is ``hmin``, each
next one ``ratio`` times larger, up to ``hmax``. Mirror symmetry planes (roller conditions) cut
the symmetric problems to a half or a quarter. Dirichlet values are eliminated (a condensed
system, as ``skfem.condense`` does), the SPD system is factored by CHOLMOD (cholespy, a dependency
of torchdeform, CPU), and reaction forces are the consistent nodal reactions ``K u - f`` summed
over the constrained degrees of freedom (their sum is the traction resultant, which converges
faster than an integral of the stress).

Locking: quadratic hexahedra do not lock at ``nu = 0.3, 0.45, 0.49`` in these problems (the
results converge to limits that agree with beam theory and scale as they must); the convergence
is slower as ``nu -> 0.5`` because the edge singularities get stronger, which the graded meshes
absorb. ``nu = 0.5`` itself is not supported (``lambda`` is infinite).

Measured convergence (E = 5 kPa; relative change between the two finest meshes tried; times on
two busy CPU cores of the development machine, the first call of a process included):

* :func:`uniaxial_pull`: the exact solution is homogeneous and lies in the element space; one
  mesh of 2x2x2 elements reproduces ``E`` and ``nu`` to round-off (< 1e-12); 0.3 s.
* :func:`simple_shear`: default (``hmin`` 0.5 mm, ``hmax`` 5 mm) vs. ``hmin`` 0.2 mm, ``hmax``
  2.5 mm: 0.02 % at ``nu = 0.3``, 0.12 % at 0.49; 2-5 s. For the default 5 x 50 x 50 mm box the
  apparent modulus ``F / (gamma A)`` is 0.968 G at ``nu = 0.3``, 0.975 G at 0.45, 0.978 G at 0.49.
* :func:`cantilever_tip` (rho = 1000): default (4 x 2 cells on the half section, ``hmin`` 0.2 mm
  at the clamp, 7425 dofs) vs. 14 x 7 cells with ``hmin`` 0.05 mm (77k dofs): 0.4 % at
  ``nu = 0.49``, 0.1 % at 0.45, < 0.05 % at 0.3; 1.5-3 s. At ``nu = 0`` it matches Timoshenko
  beam theory to 0.01 %; as ``nu`` grows the clamp, which also stops the Poisson contraction of the
  root section, makes it stiffer than beam theory (1.5 % at 0.3, 3.7 % at 0.45, 4.5 % at 0.49).
* :func:`bonded_punch_force` (depth 0.5 mm): ``hmin`` 0.3 mm (default, 19845 dofs) vs. 0.1 mm
  (47937 dofs): 0.44 % at ``nu = 0.3``, 0.60 % at 0.45, 1.04 % at 0.49; the extrapolated limit
  (geometric, from hmin = 1, 0.3, 0.1 mm) is 0.5 % below the default at 0.3, 1.0 % at 0.45 and
  1.0-1.8 % at 0.49 (the last spread: two element families, 27- and 20-node, extrapolate apart),
  so the default is converged to ~1 % for ``nu <= 0.45`` and to ~2 % at 0.49 (the forces fall
  monotonically with refinement: they are upper bounds). 6-8 s; ``hmin = 1e-4`` (1 % at 0.49) takes about a minute.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

#: the resolution of :func:`bonded_punch_force` by default (m): smallest cell at the punch edge
PUNCH_HMIN = 3e-4


class Uniaxial(NamedTuple):
    """Mean strains of a uniaxial pull and the moduli they imply."""

    strain_axial: float  # mean eps_22
    strain_lateral: tuple[float, float]  # mean eps_00, eps_11
    E: float  # traction / strain_axial
    nu: float  # -mean(lateral) / strain_axial


class Shear(NamedTuple):
    """Simple shear between bonded plates: the tangential force on the top and ``F / (gamma A)``."""

    force: float  # N, along +x2, the force the top plate applies
    G: float  # Pa, apparent shear modulus F / (gamma L1 L2)


class Tip(NamedTuple):
    """Deflection of a cantilever's free end along ``x0`` (negative: it sags)."""

    mean: float  # m, mean of u0 over the end face x2 = L2
    centre: float  # m, u0 at the centre of the end face


def _side(a: float, b: float, hmin: float, ratio: float, hmax: float) -> np.ndarray:
    """Coordinates from ``a`` (fine end) to ``b``: cells ``hmin * ratio**k`` capped at ``hmax``, rescaled to fit."""
    length = b - a
    sizes: list[float] = []
    h = min(hmin, hmax)
    while sum(sizes) + h < length * (1 - 1e-9):
        sizes.append(h)
        h = min(h * ratio, hmax)
    rest = length - sum(sizes)
    if sizes and rest < 0.5 * sizes[-1]:
        sizes[-1] += rest
    else:
        sizes.append(rest)
    s = np.concatenate([[0.0], np.cumsum(sizes)])
    return a + s * (length / s[-1])


def _segment(a: float, b: float, fine_a: bool, fine_b: bool, hmin: float, ratio: float, hmax: float) -> np.ndarray:
    """Coordinates on ``[a, b]`` graded toward the ends marked fine (uniform, at most ``hmax``, if none)."""
    if fine_a and fine_b:
        mid = 0.5 * (a + b)
        left = _side(a, mid, hmin, ratio, hmax)
        return np.concatenate([left, (a + b - left[::-1])[1:]])
    if fine_a:
        return _side(a, b, hmin, ratio, hmax)
    if fine_b:
        return a + b - _side(a, b, hmin, ratio, hmax)[::-1]
    return np.linspace(a, b, max(1, int(np.ceil((b - a) / hmax - 1e-9))) + 1)


class _Problem:
    """A tensor-product box of 27-node hexahedra with its stiffness matrix."""

    def __init__(self, coords, E: float, nu: float):
        from skfem import Basis, BilinearForm, ElementHex2, ElementVector, MeshHex, asm
        from skfem.helpers import ddot, div, grad, transpose
        from skfem.models.elasticity import lame_parameters

        if not (E > 0 and -1 < nu < 0.5):
            raise ValueError(f"need E > 0 and -1 < nu < 0.5, got E={E}, nu={nu}")
        self.mesh = MeshHex.init_tensor(*(np.asarray(c, dtype=float) for c in coords))
        self.basis = Basis(self.mesh, ElementVector(ElementHex2()), intorder=4)
        lam, mu = lame_parameters(E, nu)

        # isotropic linear elasticity, 2 mu e(u):e(v) + lam div u div v with 2 e(u):e(v) =
        # grad u : grad v + grad u : (grad v)^T: the matrix of skfem.models.elasticity's
        # linear_elasticity (to 1e-15) several times faster (it builds a stress tensor, an
        # identity and two symmetric gradients per pair of basis functions)
        @BilinearForm
        def elasticity(u, v, w):
            gu, gv = grad(u), grad(v)
            return mu * (ddot(gu, gv) + ddot(gu, transpose(gv))) + lam * div(u) * div(v)

        self.K = asm(elasticity, self.basis).tocsr()
        self.f = np.zeros(self.basis.N)

    def dofs(self, where, comp: int) -> np.ndarray:
        """Degrees of freedom of displacement component ``comp`` on the boundary facets ``where(x)``."""
        return np.asarray(self.basis.get_dofs(where).all(f"u^{comp + 1}"))

    def body_force(self, b) -> None:
        """Add a uniform body force density ``b`` (N/m^3) to the load."""
        from skfem import LinearForm

        @LinearForm
        def load(v, w):
            return b[0] * v[0] + b[1] * v[1] + b[2] * v[2]

        self.f += load.assemble(self.basis)

    def traction(self, where, t) -> None:
        """Add a uniform traction ``t`` (Pa) on the boundary facets ``where(x)``."""
        from skfem import FacetBasis, LinearForm

        fb = FacetBasis(self.mesh, self.basis.elem, facets=self.mesh.facets_satisfying(where), intorder=4)

        @LinearForm
        def load(v, w):
            return t[0] * v[0] + t[1] * v[1] + t[2] * v[2]

        self.f += load.assemble(fb)

    def face_mean(self, u: np.ndarray, where, comp: int, area: float) -> float:
        """Mean of displacement component ``comp`` over the boundary facets ``where(x)`` of total ``area``."""
        from skfem import FacetBasis, LinearForm

        fb = FacetBasis(self.mesh, self.basis.elem, facets=self.mesh.facets_satisfying(where), intorder=4)

        @LinearForm
        def one(v, w):
            return v[comp]

        return float(one.assemble(fb) @ u) / area

    def solve(self, fixed: np.ndarray, values: np.ndarray | None = None) -> np.ndarray:
        """Displacements with ``u[fixed] = values[fixed]`` (zero by default), by a sparse Cholesky factor."""
        from cholespy import CholeskySolverD, MatrixType

        n = self.basis.N
        x = np.zeros(n) if values is None else np.asarray(values, dtype=float).copy()
        fixed = np.unique(fixed)
        free = np.setdiff1d(np.arange(n), fixed)
        A = self.K[free][:, free].tocsr()
        A.sort_indices()
        rhs = np.ascontiguousarray(self.f[free] - self.K[free][:, fixed] @ x[fixed])
        chol = CholeskySolverD(
            len(free), A.indptr.astype(np.int32), A.indices.astype(np.int32), A.data.astype(np.float64), MatrixType.CSR
        )
        y = np.zeros_like(rhs)
        chol.solve(rhs, y)
        x[free] = y
        return x

    def reaction(self, u: np.ndarray, dofs: np.ndarray) -> float:
        """Sum of the consistent reactions ``K u - f`` on ``dofs``: the force the constraint applies (N)."""
        r = self.K @ u - self.f
        return float(r[np.unique(dofs)].sum())


def _plane(axis: int, value: float):
    return lambda x: np.isclose(x[axis], value, rtol=0.0, atol=1e-12)


@functools.lru_cache(maxsize=64)
def uniaxial_pull(E: float, nu: float, size=(0.01, 0.01, 0.01), traction: float = 100.0) -> Uniaxial:
    """A free box pulled by normal tractions ``+-traction`` (Pa) on its two ``x2`` faces.

    The octant ``[0, L0/2] x [0, L1/2] x [0, L2/2]`` of the box centred on the origin corner is
    modelled, with rollers on the planes ``x0 = 0``, ``x1 = 0``, ``x2 = 0`` (the mirror planes, which
    also remove the rigid modes) and the traction on ``x2 = L2/2``. The answer is homogeneous, so the
    mean strains are those of the whole box.
    """
    L0, L1, L2 = (0.5 * s for s in size)
    p = _Problem([np.linspace(0, L, 3) for L in (L0, L1, L2)], E, nu)
    p.traction(_plane(2, L2), (0.0, 0.0, traction))
    fixed = np.concatenate([p.dofs(_plane(a, 0.0), a) for a in range(3)])
    u = p.solve(fixed)
    e2 = p.face_mean(u, _plane(2, L2), 2, L0 * L1) / L2
    e0 = p.face_mean(u, _plane(0, L0), 0, L1 * L2) / L0
    e1 = p.face_mean(u, _plane(1, L1), 1, L0 * L2) / L1
    return Uniaxial(e2, (e0, e1), traction / e2, -0.5 * (e0 + e1) / e2)


@functools.lru_cache(maxsize=64)
def simple_shear(
    E: float,
    nu: float,
    size=(0.005, 0.05, 0.05),
    gamma: float = 0.01,
    hmin: float = 5e-4,
    ratio: float = 2.0,
    hmax: float = 5e-3,
) -> Shear:
    """A box between bonded plates: base ``x0 = 0`` fixed, top ``x0 = L0`` moved by ``gamma L0`` along ``x2``.

    The top is held in ``x0`` and ``x1``; the four sides are free. Half the box (``x1 <= L1/2``, a
    roller on ``x1 = L1/2``) is modelled, graded toward the edges of the plates. ``G`` is the force
    over ``gamma L1 L2``: below the shear modulus by the free ends ``x2 = 0, L2``, where the shear
    stress must vanish over a boundary layer about ``L0`` wide (the plates there also resist the
    Poisson contraction, a smaller effect that stiffens). For ``L0 / L2 = 0.1`` it is 2-3 % below ``G``.
    """
    L0, L1, L2 = size
    h = min(hmax, L0 / 4)
    coords = [
        _segment(0.0, L0, True, True, hmin, ratio, h),
        _segment(0.0, L1 / 2, True, False, hmin, ratio, hmax),
        _segment(0.0, L2, True, True, hmin, ratio, hmax),
    ]
    p = _Problem(coords, E, nu)
    bottom, top = _plane(0, 0.0), _plane(0, L0)
    fixed = [p.dofs(bottom, c) for c in range(3)] + [p.dofs(top, c) for c in range(3)]
    fixed.append(p.dofs(_plane(1, L1 / 2), 1))
    x = np.zeros(p.basis.N)
    top2 = p.dofs(top, 2)
    x[top2] = gamma * L0
    u = p.solve(np.concatenate(fixed), x)
    force = 2.0 * p.reaction(u, top2)
    return Shear(force, force / (gamma * L1 * L2))


@functools.lru_cache(maxsize=64)
def cantilever_tip(
    E: float,
    nu: float,
    rho: float,
    size=(0.01, 0.01, 0.06),
    g: float = 9.81,
    cells: int = 2,
    hmin: float = 2e-4,
    ratio: float = 2.0,
) -> Tip:
    """A cantilever clamped on ``x2 = 0`` (all components zero), sagging under gravity ``-g`` along ``x0``.

    Half the box (``x1 <= L1/2``, a roller on ``x1 = L1/2``) is modelled with ``2 cells x cells``
    uniform cells on the half section and cells along ``x2`` graded toward the clamp (smallest
    ``hmin``, at most a quarter of the section height). Linear theory: the deflection is
    proportional to ``rho g / E`` whatever its size.
    """
    L0, L1, L2 = size
    coords = [
        np.linspace(0.0, L0, 2 * cells + 1),
        np.linspace(0.0, L1 / 2, cells + 1),
        _side(0.0, L2, hmin, ratio, L0 / 4),
    ]
    p = _Problem(coords, E, nu)
    p.body_force((-rho * g, 0.0, 0.0))
    fixed = [p.dofs(_plane(2, 0.0), c) for c in range(3)] + [p.dofs(_plane(1, L1 / 2), 1)]
    u = p.solve(np.concatenate(fixed))
    mean = p.face_mean(u, _plane(2, L2), 0, L0 * L1 / 2)
    centre = float((p.basis.probes(np.array([[L0 / 2], [L1 / 2], [L2]])) @ u)[0])
    return Tip(mean, centre)


@functools.lru_cache(maxsize=64)
def bonded_punch_force(
    E: float,
    nu: float,
    block=(0.02, 0.04, 0.04),
    punch=(0.01, 0.01),
    depth: float = 5e-4,
    hmin: float = PUNCH_HMIN,
    ratio: float = 2.0,
    hmax: float = 5e-3,
) -> float:
    """Force (N, positive when pressing) to push a bonded rigid punch ``depth`` (m) into a block.

    Block ``[0, H] x [0, W1] x [0, W2]`` with its base ``x0 = 0`` fixed; on the top ``x0 = H`` the
    centred footprint ``punch = (P1, P2)`` moves by ``-depth`` along ``x0`` with zero tangential
    displacement; the rest of the top and the sides are free. The quarter ``x1 <= W1/2``,
    ``x2 <= W2/2`` is modelled (rollers on the two mirror planes), graded toward the top and the
    footprint's edges, where the stress is singular (the force converges nonetheless).
    """
    H, W1, W2 = block
    c1, c2 = W1 / 2, W2 / 2
    e1, e2 = c1 - punch[0] / 2, c2 - punch[1] / 2
    coords = [
        _segment(0.0, H, False, True, hmin, ratio, hmax),
        np.concatenate([_segment(0.0, e1, False, True, hmin, ratio, hmax), _side(e1, c1, hmin, ratio, hmax)[1:]]),
        np.concatenate([_segment(0.0, e2, False, True, hmin, ratio, hmax), _side(e2, c2, hmin, ratio, hmax)[1:]]),
    ]
    p = _Problem(coords, E, nu)
    tol = 1e-12

    def footprint(x):
        return np.isclose(x[0], H, rtol=0.0, atol=tol) & (x[1] > e1 - tol) & (x[2] > e2 - tol)

    pressed = [p.dofs(footprint, c) for c in range(3)]
    fixed = [p.dofs(_plane(0, 0.0), c) for c in range(3)] + pressed
    fixed += [p.dofs(_plane(1, c1), 1), p.dofs(_plane(2, c2), 2)]
    x = np.zeros(p.basis.N)
    x[pressed[0]] = -depth
    u = p.solve(np.concatenate(fixed), x)
    return -4.0 * p.reaction(u, pressed[0])


# ------------------------------------------------------------------ two regions, lattice-aligned
class BlockLoad(NamedTuple):
    """One load case of :func:`two_region_block`, on the face ``x_face = L_face`` (the others are rollers or free).

    ``kind``: ``"traction"``, a uniform normal traction ``value`` (Pa, positive pulls) on that face;
    ``"plate"``, a frictionless rigid plate: the normal displacement ``u_face = value`` (m) on the
    face, the tangential components free.
    """

    face: int
    kind: str
    value: float


class TwoRegion(NamedTuple):
    """The answer of :func:`two_region_block` at the nodes of a lattice of spacing ``h``.

    ``displacement`` and ``reaction`` are ``(3, D, H, W)`` arrays (channel ``c`` is component
    ``c``; node ``(i, j, k)`` sits at ``(i h, j h, k h)``), in m and N.
    """

    displacement: np.ndarray  # m, the FEM displacement at the lattice nodes (mesh vertices)
    reaction: np.ndarray  # N, the constraints' reactions tested with the lattice's hat functions
    dofs: int  # degrees of freedom of the FEM problem


class _TwoRegionProblem(_Problem):
    """A uniform box mesh of 27-node hexahedra whose Lame parameters jump across the plane ``x_axis = position``.

    Every element is the same cube, so its stiffness is ``lam A + mu B`` with ``A`` and ``B``
    integrated once on one element (3x3x3 Gauss points, exact) and scattered to the global matrix
    by the elements' dofs: ten times faster than assembling element by element, and the same matrix
    (to round-off).
    """

    def __init__(self, coords, E, nu, axis: int, position: float):
        import scipy.sparse as sp
        from skfem import Basis, BilinearForm, ElementHex2, ElementVector, MeshHex, asm
        from skfem.helpers import ddot, sym_grad, trace
        from skfem.models.elasticity import lame_parameters

        for e, n in zip(E, nu):
            if not (e > 0 and -1 < n < 0.5):
                raise ValueError(f"need E > 0 and -1 < nu < 0.5 in each region, got E={E}, nu={nu}")
        self.mesh = MeshHex.init_tensor(*(np.asarray(c, dtype=float) for c in coords))
        self.basis = Basis(self.mesh, ElementVector(ElementHex2()), intorder=4)
        one = Basis(self.mesh, self.basis.elem, intorder=4, elements=np.array([0]))  # the first element alone
        local = one.element_dofs[:, 0]

        @BilinearForm
        def volumetric(u, v, w):
            return trace(sym_grad(u)) * trace(sym_grad(v))

        @BilinearForm
        def deviatoric(u, v, w):
            return 2.0 * ddot(sym_grad(u), sym_grad(v))

        A, B = (asm(f, one)[local][:, local].toarray() for f in (volumetric, deviatoric))
        (lam1, mu1), (lam2, mu2) = (lame_parameters(e, n) for e, n in zip(E, nu))
        first = self.mesh.p[axis][self.mesh.t].mean(axis=0) < position
        lam, mu = np.where(first, lam1, lam2), np.where(first, mu1, mu2)
        dofs = self.basis.element_dofs  # (81, elements)
        n, K = self.basis.N, None
        for s in range(0, dofs.shape[1], 2000):  # in chunks: 81^2 entries per element
            d, la, m = dofs[:, s : s + 2000], lam[s : s + 2000], mu[s : s + 2000]
            data = la[:, None, None] * A + m[:, None, None] * B  # (chunk, 81, 81)
            rows = np.broadcast_to(d.T[:, :, None], data.shape)
            cols = np.broadcast_to(d.T[:, None, :], data.shape)
            part = sp.coo_matrix((data.ravel(), (rows.ravel(), cols.ravel())), shape=(n, n)).tocsr()
            K = part if K is None else K + part
        self.K = K
        self.f = np.zeros(n)


def _divides(step: float, length: float) -> bool:
    n = round(length / step)
    return n >= 1 and abs(n * step - length) <= 1e-9 * length


@functools.lru_cache(maxsize=32)
def two_region_block(
    E: tuple[float, float],
    nu: tuple[float, float],
    load: BlockLoad,
    *,
    size=(0.01, 0.01, 0.02),
    interface: tuple[int, float] = (2, 0.01),
    spacing: float = 1e-3,
    element: float = 2e-3,
) -> TwoRegion:
    """A box ``[0, L0] x [0, L1] x [0, L2]`` of two materials, sampled at the nodes of a lattice of side ``spacing``.

    Region 1 (``E[0]``, ``nu[0]``) is ``x_a < p``, region 2 (``E[1]``, ``nu[1]``) is ``x_a > p`` for
    ``interface = (a, p)``: piecewise constant Lame parameters per element, the interface a plane of
    the mesh. The box has rollers on its three planes through the origin (``u_c = 0`` on
    ``x_c = 0``: mirror planes, which also remove the rigid motions); ``load`` acts on the face
    ``x_f = L_f`` (a uniform normal traction, or a frictionless plate with a prescribed normal
    displacement); the other faces are free.

    The mesh is uniform: cubes of side ``element`` (dividing the sides and ``p``), quadratic as in
    this module's other problems. The lattice nodes must be Lagrange nodes of the mesh
    (``element = 2 spacing``, or ``spacing`` a multiple of ``element``), so ``displacement`` is read
    there, not interpolated. ``reaction`` at lattice node ``a`` is ``sum_j psi_a(x_j) (K u - f)_j``
    over the constrained degrees of freedom ``j``, with ``psi_a`` the node's trilinear hat
    function (two lattice cells wide per axis): the consistent reaction tested with the hat (exact
    when the hat lies in the element space, ``spacing`` a multiple of ``element``; its Lagrange
    interpolant otherwise; summed over a face, the resultant either way), which is what a lattice's
    nodal reaction ``K u - f`` approximates.

    Convergence (E = 3 / 8 kPa, nu = 0.45 / 0.49, the default 10 x 10 x 20 mm box with the interface
    across the middle of the long axis, sampled on a 1 mm lattice; ``element`` 2 mm against 1 mm):
    the displacements at the lattice nodes agree to 0.40 % of the largest displacement under a
    100 Pa pull along ``x2`` and to 0.05 % under a 0.1 mm plate along ``x0`` (the largest
    differences sit where the interface meets a free face, where the stress is weakly singular);
    E and nu fitted by ``training/fit_fem.py`` to either mesh's displacements agree to 0.09 %
    (errors against the true values: worst 0.13 % with 2 mm elements, 0.22 % with 1 mm). The
    per-node reactions are not converged at 2 mm next to the singular edges (up to 78 % of the
    largest nodal reaction there between the two meshes; the resultants agree to round-off): use
    ``element = spacing`` or finer where reactions are fitted node by node. The default 2 mm elements
    (7.6k dofs) take about 3 s on two busy cores; 1 mm elements (54k dofs) about 160 s, nearly all
    of it the sparse Cholesky factor.
    """
    axis, position = interface
    if load.kind not in ("traction", "plate") or load.face not in (0, 1, 2):
        raise ValueError(f"need a load on face 0, 1 or 2 of kind 'traction' or 'plate', got {load}")
    if not all(_divides(element, L) and _divides(spacing, L) for L in size):
        raise ValueError(f"the element {element} m and the spacing {spacing} m must divide the sides {size}")
    if not (_divides(spacing, element) or abs(element - 2 * spacing) <= 1e-12 * element):
        raise ValueError(f"the lattice nodes must be mesh nodes: element {element} m = 2 x spacing, or divides it")
    if not 0 < position < size[axis] or not _divides(element, position):
        raise ValueError(f"the interface {interface} must be a plane of the mesh inside the box")
    coords = [np.linspace(0.0, L, round(L / element) + 1) for L in size]
    p = _TwoRegionProblem(coords, tuple(E), tuple(nu), axis, position)
    far = _plane(load.face, size[load.face])
    fixed = [p.dofs(_plane(c, 0.0), c) for c in range(3)]
    x = np.zeros(p.basis.N)
    if load.kind == "traction":
        t = [0.0, 0.0, 0.0]
        t[load.face] = load.value
        p.traction(far, t)
    else:
        plate = p.dofs(far, load.face)
        fixed.append(plate)
        x[plate] = load.value
    fixed_dofs = np.unique(np.concatenate(fixed))
    u = p.solve(fixed_dofs, x)
    r = p.K @ u - p.f
    shape = tuple(round(s / spacing) + 1 for s in size)
    disp, reac = np.zeros((3,) + shape), np.zeros((3,) + shape)
    for c, comp in enumerate(p.basis.split_indices()):
        s = p.basis.doflocs[:, comp] / spacing
        on = np.all(np.abs(s - np.round(s)) < 1e-6, axis=0)  # the dofs at lattice nodes
        disp[c][tuple(np.round(s[:, on]).astype(int))] = u[comp[on]]
        # reactions tested with the lattice's hat functions: trilinear weights of each constrained dof
        dofs = np.intersect1d(comp, fixed_dofs)
        s = p.basis.doflocs[:, dofs] / spacing
        base = np.minimum(np.floor(s + 1e-9).astype(int), np.array(shape)[:, None] - 2)
        frac = np.clip(s - base, 0.0, 1.0)
        for corner in np.ndindex(2, 2, 2):
            o = np.array(corner)[:, None]
            w = np.prod(np.where(o == 1, frac, 1.0 - frac), axis=0)
            np.add.at(reac[c], tuple(base + o), w * r[dofs])
    return TwoRegion(disp, reac, int(p.basis.N))
