r"""An elastic material on the lattice: Young's modulus and Poisson ratio from springs plus a cell term.

A lattice of central springs alone obeys the Cauchy relation: its stiffness tensor is fully
symmetric, so at best it is isotropic with :math:`\lambda = \mu`, a Poisson ratio of 1/4.
:class:`Elastic` gives half of the shear modulus to the springs and the rest, with a volume
modulus, to a term per cell evaluated at the cell's centre; together they are the isotropic solid
of any :math:`\nu \in [1/6, 1/2)`. Each spring's stiffness is assembled from the cells that
contain it, so that the springs of a surface layer are not stiffer than those inside.

**Springs.** With cubic cells of side ``h``, a spring of stiffness ``k`` along the half-direction
``d`` (length ``L = h |d|``, unit vector ``n``) adds :math:`k L^2 n_i n_j n_k n_l / h^3` to the
small-strain stiffness tensor of an infinite lattice (one spring per half-direction per node).
Summing the three classes (axis ``k_a``, face diagonal ``k_f``, body diagonal ``k_b``):

.. math::

    C_{11} = (k_a + 2 k_f + \tfrac43 k_b) / h, \qquad C_{12} = C_{44} = (k_f + \tfrac43 k_b) / h .

Cubic symmetry becomes isotropy when :math:`C_{11} - C_{12} = 2 C_{44}`, i.e.
:math:`k_a = k_f + \tfrac83 k_b`, and then :math:`\mu_s = C_{44}`, :math:`\lambda_s = \mu_s`.
One ratio is free; this module takes (interior springs, :data:`CLASS_WEIGHTS`,
``k = w mu_s h`` with ``mu_s = (1 - CELL_SHARE) mu``, :func:`spring_factors`):

========  ====================  ==========  ===========
topology  axis                  face        body
========  ====================  ==========  ===========
26        3/2                   1/2         3/8
18        1                     1           -
14        2                     -           3/4
========  ====================  ==========  ===========

(26: face and body diagonals carry equal shares of :math:`C_{44}`.) Six neighbours have no shear
stiffness and cannot be made isotropic: :class:`Elastic` refuses them.

**Cells.** A cell (its 8 corner nodes) holds 12 axis springs, each shared by 4 cells, 12 face
diagonals, each shared by 2, and 4 body diagonals of its own. Each cell gives its axis springs
``w_a mu_s h / 4``, its face diagonals ``w_f mu_s h / 2`` and its body diagonals ``w_b mu_s h``;
a spring's stiffness is the sum over the cells that exist around it (:func:`spring_stiffness`).
Inside a uniform body that is the table above; on a face or an edge a spring gets the share of the
cells it has, so every cell carries exactly its share of the continuum's energy.

**Cell term.** Per cell, with :math:`V = h^3`, :math:`F_c` the deformation gradient at the cell's
centre (the trilinear cell: column ``j`` is the mean of the four edge vectors along axis ``j``
over ``h``), :math:`J_c = \det F_c` and :math:`E_c = (F_c^T F_c - I) / 2`,

.. math::

    W_c = V \left( \tfrac12 \kappa_c (J_c - 1)^2 + \mu'_c\, E_c : E_c \right).

Both parts are invariant under rotation; for small strain they are
:math:`V (\tfrac12 \kappa (\operatorname{tr}\varepsilon)^2 + \mu' \varepsilon : \varepsilon)`:
the volume part adds :math:`\kappa` to :math:`\lambda`, the shear part (a Saint Venant-Kirchhoff
solid with :math:`\lambda' = 0`) adds :math:`\mu'` to :math:`\mu`. With

.. math::

    \mu = \frac{E}{2 (1 + \nu)}, \qquad \lambda = \frac{E \nu}{(1 + \nu)(1 - 2 \nu)}, \qquad
    \mu' = s \mu, \qquad \kappa = \lambda - (1 - s) \mu \ \ge 0 \iff \nu \ge \frac{1 - s}{2 (2 - s)},

(``s`` = :data:`CELL_SHARE` = 1/2: :math:`\nu \ge 1/6`), springs and cell term together are the
isotropic solid of modulus ``E`` and ratio ``nu`` in the small-strain limit of a uniform strain, on
every topology. The force on corner ``a`` is :math:`f_a = -V P \nabla N_a` with the first Piola
stress :math:`P = \kappa (J - 1) \operatorname{cof}(F) + 2 \mu' F E` and
:math:`\nabla N_a = s_a / (4 h)`, :math:`s_a \in \{-1, 1\}^3` (:func:`volume_forces`).

**Why half the shear modulus in the cells.** A uniform strain does not tell springs and cells
apart; a bending strain does. Springs lie on the node layers and see the strain there, so through
a bent body's thickness they integrate the axial energy like the trapezoid rule (too stiff by
about :math:`1/n^2` with ``n`` cells through the thickness); the cell term sees the strain at the
cell centres, the midpoint rule (too soft by about :math:`1/(2 n^2)`). Springs alone made a
10 x 10 x 60 mm cantilever (26 neighbours, ``nu`` = 0.45, 4 cells through its thickness) 7.5 %
too stiff against converged finite elements, 22 % with 2 cells; half and half (``s`` = 1/2) gives
1.2 % and 2.9 % (``torchdeform bench elasticity``; ``s`` = 0.6 overshoots to 2 % too soft with
2 cells). One-point cells alone would have zero-energy (hourglass) modes: the springs keep every
mode stiff.

**Topology changes.** The body is the union of its live cells; springs and volume term are both
made from them. A cut, a tear or a cautery burn (:mod:`torchdeform.topology`) kills every cell that
contains a removed spring (any of its 12 edges, 12 face and 4 body diagonals the topology has)
or a removed corner node (:func:`spring_cells`, :func:`corner_cells`): its cell-term moduli
become 0 (:func:`surviving_cells`) and the springs are re-assembled from the cells left
(:func:`reassemble`). A spring shared by a live and a dead cell keeps the live cell's share, just
as a spring on a block's face has only the cells inside the block. A spring with no live cell left
gets no stiffness, though the blade may not have touched it: a real cut is a surface with
material on both sides, and on the lattice that material is the cells; a spring whose cells all
lie in the kerf has no material behind it, and keeping it would leave a strut spanning the gap
(with its full stiffness, stiffer than the face it sits in). So after any sequence of changes the
body is exactly the :class:`Elastic` body built on the cells that remain: a plane cut between
two node layers gives the two blocks on either side, each as if built alone (the layer of cells
the plane crosses is the cut's kerf). Masses do not change: a node whose cells all died (a sliver
between two cuts, a corner the blade clipped) keeps its mass and moves freely.

Example:
    >>> import torchdeform as td
    >>> m = td.Elastic(youngs_modulus=5e3, poisson_ratio=0.45)
    >>> mu, lam = m.lame()
    >>> round(mu, 2), round(lam, 1), round(m.volume_modulus(), 1), round(m.cell_shear_modulus(), 2)
    (1724.14, 15517.2, 14655.2, 862.07)
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..errors import ConfigError

__all__ = [
    "Elastic",
    "CLASS_WEIGHTS",
    "POISSON_RANGE",
    "cell_field",
    "kelvin_voigt_damping",
    "cell_mask",
    "corner_cells",
    "spring_cells",
    "spring_stiffness",
    "reassemble",
    "surviving_cells",
    "deformation_gradient",
    "volume_energy",
    "volume_forces",
    "volume_product",
    "volume_cofactors",
    "volume_state",
    "spring_factors",
    "CELL_SHARE",
    "volume_row_sums",
    "VolumeLinearisation",
]

#: The isotropic split of ``mu h`` among the spring classes (axis, face, body), per topology: the
#: interior springs' stiffness is ``(1 - CELL_SHARE)`` times these multiples of ``mu h``.
CLASS_WEIGHTS = {26: (1.5, 0.5, 0.375), 18: (1.0, 1.0, 0.0), 14: (2.0, 0.0, 0.75)}

#: The share of the shear modulus the cells carry (their shear part, at the cell centre); the
#: springs carry the rest.
CELL_SHARE = 0.5

#: The Poisson ratios :class:`Elastic` reaches on each topology: ``[lo, hi)`` (``kappa >= 0``).
POISSON_RANGE = dict.fromkeys(CLASS_WEIGHTS, ((1 - CELL_SHARE) / (2 * (2 - CELL_SHARE)), 0.5))


def _number(value, key: str):
    """A float or a tensor of floats (per node ``(D, H, W)``); refuses what is neither."""
    if torch.is_tensor(value):
        return value
    if isinstance(value, bool):
        raise ConfigError(key, "a number", got=value)
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(key, "a number", got=value) from None


@dataclass(frozen=True)
class Elastic:
    """Isotropic linear elasticity for a lattice body: Young's modulus and Poisson ratio.

    Give it to :class:`~torchdeform.sim.model.Model` as its stiffness: the springs get the
    stiffness of :func:`spring_stiffness` and the model gets the per-cell term
    (:func:`volume_forces`: ``Model.volume = (kappa_cells, h, shear_cells)``). See the module
    docstring for the calibration.

    Args:
        youngs_modulus: E (Pa), a number, a per-node tensor ``(D, H, W)`` (a cell takes the
            mean of its 8 corners) or a per-cell tensor ``(D-1, H-1, W-1)`` (cell ``(i, j, k)``
            between nodes ``(i, j, k)`` and ``(i+1, j+1, k+1)``).
        poisson_ratio: nu, in ``[1/6, 0.5)`` (:data:`POISSON_RANGE`), a number, per node or per cell.

    Example:
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
        >>> model = td.Model(grid, td.Elastic(5e3, 0.3), density=1000.0)
        >>> model.volume is not None, round(float(model.stiffness[0, 0, 1, 1, 1]), 3)   # axis spring inside
        (True, 14.423)
    """

    youngs_modulus: float | torch.Tensor
    poisson_ratio: float | torch.Tensor

    def __post_init__(self):
        E = _number(self.youngs_modulus, "material.youngs_modulus")
        nu = _number(self.poisson_ratio, "material.poisson_ratio")
        e_bad = not bool((torch.as_tensor(E) > 0).all() & torch.isfinite(torch.as_tensor(E)).all())
        if e_bad:
            raise ConfigError("material.youngs_modulus", "a positive, finite Young's modulus (Pa)", got=E)
        lo, hi = POISSON_RANGE[26]
        t = torch.as_tensor(nu)
        if not bool(((t >= lo - 1e-12) & (t < hi)).all()):
            raise ConfigError(
                "material.poisson_ratio",
                "a Poisson ratio in [1/6, 1/2) (the lattice's springs and cells reach no lower ratio)",
                got=nu,
            )
        object.__setattr__(self, "youngs_modulus", E)
        object.__setattr__(self, "poisson_ratio", nu)

    def lame(self):
        """``(mu, lambda)`` in Pa (numbers or per-node tensors)."""
        E, nu = self.youngs_modulus, self.poisson_ratio
        return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    def volume_modulus(self):
        """``kappa = lambda - (1 - CELL_SHARE) mu`` (Pa): the cells' volume modulus, 0 at ``nu = 1/6``."""
        mu, lam = self.lame()
        return lam - (1 - CELL_SHARE) * mu

    def cell_shear_modulus(self):
        """``mu' = CELL_SHARE mu`` (Pa): the share of the shear modulus the cells carry."""
        return CELL_SHARE * self.lame()[0]

    def check_grid(self, grid) -> float:
        """The cell side ``h`` (m); refuses a topology without shear springs and non-cubic cells."""
        if grid.topology not in CLASS_WEIGHTS:
            raise ConfigError(
                "material",
                "a grid of 14, 18 or 26 neighbours (6 neighbours have no shear stiffness)",
                got=f"topology {grid.topology}",
            )
        h = grid.spacing[0]
        if any(abs(s - h) > 1e-9 * h for s in grid.spacing):
            raise ConfigError("material", "cubic cells (equal spacing along D, H and W)", got=grid.spacing)
        return float(h)


def cell_field(value, grid, *, dtype, device) -> torch.Tensor:
    """A number, a per-node field ``(D, H, W)`` (corner mean) or a per-cell field as a per-cell field ``(D-1, H-1, W-1)``."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    cells = tuple(n - 1 for n in grid.shape)
    if t.dim() == 0:
        return t.expand(cells)
    if tuple(t.shape) == cells:
        return t
    if tuple(t.shape) != grid.shape:
        raise ConfigError(
            "material", f"numbers, per-node fields {grid.shape} or per-cell fields {cells}", got=tuple(t.shape)
        )
    for axis in range(3):
        t = _mean2(t, axis)
    return t


def cell_mask(grid, *, device=None) -> torch.Tensor:
    """Bool ``(D-1, H-1, W-1)``: the cell's 8 corners are all nodes of the body."""
    return ~corner_cells(~grid.nodes().to(device))


def corner_cells(nodes: torch.Tensor) -> torch.Tensor:
    """Bool ``(..., D-1, H-1, W-1)``: the cells with a corner in the node set ``nodes`` (bool ``(..., D, H, W)``)."""
    D, H, W = (n - 1 for n in nodes.shape[-3:])
    m = torch.zeros(nodes.shape[:-3] + (D, H, W), dtype=torch.bool, device=nodes.device)
    for a, b, c in itertools.product((0, 1), repeat=3):
        m |= nodes[..., a : a + D, b : b + H, c : c + W]
    return m


def _cells_of(d) -> list:
    """The cells holding a spring along half-direction ``d``, as offsets from its first node plus one.

    Cell ``c`` (of the cell field padded by one all round, where it sits at ``c + 1``) with
    ``c_j = min(p_j, p_j + d_j)`` where ``d_j != 0`` and ``c_j in {p_j - 1, p_j}`` where ``d_j = 0``.
    """
    return list(itertools.product(*[(0, 1) if c == 0 else (1,) if c > 0 else (0,) for c in d]))


def spring_factors(grid, h: float) -> list:
    """Per half-direction, the factor ``(1 - CELL_SHARE) w h / 2^z`` (m) of the sum of its cells' shear moduli.

    A spring along ``d`` (``z`` zero components, class weight ``w``) has the stiffness
    ``factor * sum_cells mu_c`` (:func:`spring_stiffness`).
    """
    weights = dict(zip(("axis", "face", "body"), CLASS_WEIGHTS[grid.topology]))
    return [
        (1 - CELL_SHARE) * weights[cls] * h / 2 ** d.count(0) for d, cls in zip(grid.directions, grid.direction_class())
    ]


def spring_stiffness(grid, mu_cells: torch.Tensor, h: float) -> torch.Tensor:
    """Each spring's stiffness (N/m), ``(S, D, H, W)`` (``(B, S, D, H, W)`` for cells per batch entry).

    ``mu_cells``: the shear modulus of each cell (Pa), ``(D-1, H-1, W-1)`` or
    ``(B, D-1, H-1, W-1)``, 0 where a cell is missing. A spring along ``d`` stored at node ``p``
    lies in the cells ``c`` with ``c_j = min(p_j, p_j + d_j)`` where ``d_j != 0`` and
    ``c_j in {p_j - 1, p_j}`` where ``d_j = 0``: ``2^z`` cells for ``z`` zero components, each
    giving ``(1 - CELL_SHARE) w mu_c h / 2^z`` (:func:`spring_factors`).
    """
    M = F.pad(mu_cells, (1, 1, 1, 1, 1, 1))  # M[c + 1] = mu_c; zero outside the grid
    D, H, W = grid.shape
    out = []
    for d, factor in zip(grid.directions, spring_factors(grid, h)):
        total = sum(M[..., a : a + D, b : b + H, e : e + W] for a, b, e in _cells_of(d))
        out.append(total * factor)
    return torch.stack(out, dim=-4)


def spring_cells(grid, springs: torch.Tensor) -> torch.Tensor:
    """Bool ``(B, D-1, H-1, W-1)``: the cells that contain one of the ``springs`` (bool ``(B, S, D, H, W)``).

    The adjoint of :func:`spring_stiffness`'s gather (the same cells per spring); slots whose
    spring leaves the grid have no cell there.
    """
    D, H, W = grid.shape
    hit = torch.zeros((springs.shape[0], D + 1, H + 1, W + 1), dtype=torch.bool, device=springs.device)
    for s, d in enumerate(grid.directions):
        for a, b, e in _cells_of(d):
            hit[:, a : a + D, b : b + H, e : e + W] |= springs[:, s]
    return hit[:, 1:-1, 1:-1, 1:-1]


def surviving_cells(cells: torch.Tensor, dead: torch.Tensor) -> torch.Tensor:
    """A per-cell field ``cells`` (``(D-1, H-1, W-1)`` or ``(B, ...)``, Pa) with the ``dead`` cells set to 0.

    ``dead``: bool ``(B|1, D-1, H-1, W-1)``. The result keeps ``cells``' shape where one ``dead``
    set serves every batch entry (``B = 1``) and becomes per batch entry ``(B, ...)`` otherwise.
    A function (differentiable in ``cells``).
    """
    keep = (~dead).to(cells.dtype)
    if cells.dim() == 3 and keep.shape[0] == 1:
        keep = keep[0]
    return cells * keep


def reassemble(grid, stiffness: torch.Tensor, mu_cells: torch.Tensor, h: float) -> torch.Tensor:
    """The springs ``stiffness`` ``(Bp, S, D, H, W)`` (N/m) re-assembled from the cells ``mu_cells`` (Pa).

    A spring with zero stiffness (severed, masked, or never there) stays at zero; every other spring
    gets :func:`spring_stiffness` of the cells, so a body whose cells died is the body built from
    the cells that remain, to the bit. A function (differentiable in ``mu_cells``).
    """
    k = spring_stiffness(grid, mu_cells, h)
    return torch.where(stiffness != 0, k, torch.zeros_like(k))


def kelvin_voigt_damping(grid, youngs_modulus, poisson_ratio, retardation) -> torch.Tensor:
    r"""Each spring's dashpot (N s/m), ``(S, D, H, W)`` float64: Kelvin-Voigt damping of an elastic body.

    A Kelvin-Voigt solid has stress :math:`\sigma = C \varepsilon + \tau C \dot\varepsilon`:
    every spring of stiffness ``k`` (N/m) gets a dashpot ``c = k tau`` (N s/m) with the retardation
    time :math:`\tau = \eta / E` (s) of the tissue (viscosity eta in Pa s, Young's modulus E in Pa).
    Assembled from the cells as :class:`~torchdeform.sim.material.Elastic` assembles the springs,
    with the shear modulus ``mu`` of each cell replaced by ``mu tau`` (the corner mean): for one
    ``tau`` everywhere exactly ``c = k tau``; a body of several tissues gives each cell its own.
    The volume term gets no dashpot.

    Args:
        grid: the grid (14, 18 or 26 neighbours, cubic cells).
        youngs_modulus: E (Pa), a number, per node ``(D, H, W)`` or per cell ``(D-1, H-1, W-1)``.
        poisson_ratio: nu, a number, per node or per cell.
        retardation: tau = eta / E (s), a number, per node or per cell.

    Examples:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=0.01)
        >>> c = kelvin_voigt_damping(grid, 3700.0, 0.49, 4e-4)
        >>> k = td.Model(grid, td.Elastic(3700.0, 0.49), density=1000.0, dtype=torch.float64).stiffness[0]
        >>> bool(torch.allclose(c, 4e-4 * k, rtol=1e-12, atol=0))
        True
    """
    h = Elastic(youngs_modulus, poisson_ratio).check_grid(grid)
    E, nu, tau = (torch.as_tensor(v, dtype=torch.float64) for v in (youngs_modulus, poisson_ratio, retardation))
    viscous = E / (2 * (1 + nu)) * tau  # mu tau (Pa s) per node
    cells = cell_field(viscous, grid, dtype=torch.float64, device=None) * cell_mask(grid).to(torch.float64)
    return spring_stiffness(grid, cells, h)


def _diff(x: torch.Tensor, axis: int) -> torch.Tensor:
    n = x.shape[axis]
    return x.narrow(axis, 1, n - 1) - x.narrow(axis, 0, n - 1)


def _mean2(x: torch.Tensor, axis: int) -> torch.Tensor:
    n = x.shape[axis]
    return 0.5 * (x.narrow(axis, 0, n - 1) + x.narrow(axis, 1, n - 1))


def _pad_axis(x: torch.Tensor, axis: int, lo: int, hi: int) -> torch.Tensor:
    pads = [0, 0] * (x.dim() - axis)
    k = 2 * (x.dim() - 1 - axis)
    pads[k], pads[k + 1] = lo, hi
    return F.pad(x, pads)


def deformation_gradient(x: torch.Tensor, h: float) -> torch.Tensor:
    """``F`` at every cell centre, ``(B, 3, 3, D-1, H-1, W-1)`` (``F[:, i, j]`` = d x_i / d X_j).

    ``x``: positions ``(B, 3, D, H, W)``; column ``j`` is the mean of the cell's four edge
    vectors along axis ``j``, over ``h``.
    """
    cols = []
    for j in range(3):
        g = _diff(x, 2 + j)
        for k in range(3):
            if k != j:
                g = _mean2(g, 2 + k)
        cols.append(g / h)
    return torch.stack(cols, dim=2)


def _det_cof(Fm: torch.Tensor):
    """``det F`` ``(B, ...)`` and the cofactor matrix ``(B, 3, 3, ...)`` of ``F`` ``(B, 3, 3, ...)``."""
    a = [[Fm[:, i, j] for j in range(3)] for i in range(3)]
    cof = [
        [
            a[(i + 1) % 3][(j + 1) % 3] * a[(i + 2) % 3][(j + 2) % 3]
            - a[(i + 1) % 3][(j + 2) % 3] * a[(i + 2) % 3][(j + 1) % 3]
            for j in range(3)
        ]
        for i in range(3)
    ]
    det = a[0][0] * cof[0][0] + a[0][1] * cof[0][1] + a[0][2] * cof[0][2]
    return det, torch.stack([torch.stack(row, dim=1) for row in cof], dim=1)


def _per_cell(A: torch.Tensor, B: torch.Tensor, *, transpose_a: bool = False) -> torch.Tensor:
    """The matrix product ``A B`` (``A^T B`` with ``transpose_a``) in every cell, ``(B, 3, 3, cells)``.

    Three broadcast products over the cells: as an einsum this becomes a batched 3x3 matmul,
    3 times slower on a 48,000-cell lattice (one CPU thread).
    """
    out = None
    for k in range(3):
        a = A[:, k, :, None] if transpose_a else A[:, :, k, None]
        term = a * B[:, k, None, :]
        out = term if out is None else out + term
    assert out is not None
    return out


def _green(Fm: torch.Tensor) -> torch.Tensor:
    """The Green-Lagrange strain ``E = (F^T F - I) / 2`` per cell, ``(B, 3, 3, cells)``."""
    E = 0.5 * _per_cell(Fm, Fm, transpose_a=True)
    eye = torch.eye(3, dtype=Fm.dtype, device=Fm.device).view(1, 3, 3, 1, 1, 1)
    return E - 0.5 * eye


def _cells(t: torch.Tensor) -> torch.Tensor:
    """A per-cell modulus ``(cells)`` or ``(B|1, cells)`` as ``(B|1, 1, 1, cells)`` against ``(B, 3, 3, cells)``."""
    return t.reshape(-1, 1, 1, *t.shape[-3:])


def volume_energy(x: torch.Tensor, kappa_cells: torch.Tensor, h: float, shear_cells) -> torch.Tensor:
    """The cell term's energy (J) per batch entry, ``(B,)``: ``sum_c h^3 (kappa_c (J_c - 1)^2 / 2 + mu'_c |E_c|^2)``.

    ``kappa_cells``, ``shear_cells`` (the cell share ``mu'`` of the shear modulus, or None):
    ``(D-1, H-1, W-1)`` or ``(B|1, D-1, H-1, W-1)`` (Pa), 0 where a cell is missing.
    """
    Fm = deformation_gradient(x, h)
    J, _ = _det_cof(Fm)
    w = 0.5 * kappa_cells * (J - 1) ** 2
    if shear_cells is not None:
        w = w + shear_cells * (_green(Fm) ** 2).sum((1, 2))
    return (h**3 * w).flatten(1).sum(1)


def volume_forces(x: torch.Tensor, kappa_cells: torch.Tensor, h: float, shear_cells) -> torch.Tensor:
    """The cell term's force on every node (N), ``(B, 3, D, H, W)``: minus the gradient of :func:`volume_energy`.

    Per cell the first Piola stress ``P = kappa (J - 1) cof(F) + 2 mu' F E``; corner ``a`` gets
    ``-h^3 P grad N_a`` with ``grad N_a = s_a / (4 h)``, gathered to the nodes by the adjoints of
    the edge differences and means that made ``F`` (:func:`deformation_gradient`).

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.sim.material import volume_energy, volume_forces
        >>> X = td.Grid((3, 3, 3), spacing=0.01).rest_positions(dtype=torch.float64)
        >>> x = (X * torch.tensor([1.02, 0.99, 1.0], dtype=torch.float64).view(1, 3, 1, 1, 1)).requires_grad_()
        >>> kappa, shear = torch.full((2, 2, 2), 1e4, dtype=torch.float64), torch.full((2, 2, 2), 2e3, dtype=torch.float64)
        >>> f = volume_forces(x, kappa, 0.01, shear)
        >>> g, = torch.autograd.grad(volume_energy(x, kappa, 0.01, shear).sum(), x)
        >>> bool(torch.allclose(f, -g, rtol=1e-12, atol=1e-18))
        True
    """
    Fm = deformation_gradient(x, h)
    J, cof = _det_cof(Fm)
    P = _cells(kappa_cells) * (J - 1).unsqueeze(1).unsqueeze(1) * cof
    if shear_cells is not None:
        P = P + 2 * _cells(shear_cells) * _per_cell(Fm, _green(Fm))
    return -_gather(h**3 * P, h)


def _gather(P: torch.Tensor, h: float) -> torch.Tensor:
    """``sum_c P_c grad N_a`` at every node ``a``, ``(B, 3, D, H, W)``, for per-cell ``P`` ``(B, 3, 3, cells)``.

    The adjoint of :func:`deformation_gradient`: the means along the other axes give each node
    half of each cell beside it, the difference along ``j`` gives the far corner ``+`` and the
    near corner ``-``.
    """
    f = None
    for j in range(3):
        g = P[:, :, j] / h
        for k in range(3):
            if k != j:
                g = 0.5 * (_pad_axis(g, 2 + k, 1, 0) + _pad_axis(g, 2 + k, 0, 1))
        g = _pad_axis(g, 2 + j, 1, 0) - _pad_axis(g, 2 + j, 0, 1)
        f = g if f is None else f + g
    assert f is not None
    return f


def volume_cofactors(x: torch.Tensor, h: float) -> torch.Tensor:
    """``cof(F)`` at every cell centre, ``(B, 3, 3, D-1, H-1, W-1)``."""
    return _det_cof(deformation_gradient(x, h))[1]


def volume_state(x: torch.Tensor, h: float, *, shear: bool = True) -> tuple:
    """What :func:`volume_product` linearises at: ``(cof(F), F)`` per cell (``F`` None without a shear part)."""
    Fm = deformation_gradient(x, h)
    return _det_cof(Fm)[1], (Fm if shear else None)


def volume_product(at: tuple, u: torch.Tensor, kappa_cells: torch.Tensor, h: float, shear_cells) -> torch.Tensor:
    """The cell term's stiffness product ``K u`` (N), ``(B, 3, D, H, W)``, Gauss-Newton.

    ``at``: ``(cof(F), F)`` at the state linearised at (:func:`volume_state`), each
    ``(B, 3, 3, cells)``. Per cell ``dP = kappa (cof : dF) cof + 2 mu' F sym(F^T dF)``, ``dF = dF(u)``,
    gathered to the nodes: the exact Hessian at rest (``J = 1``, ``E = 0``) and positive
    semi-definite everywhere (the ``(J - 1) d cof`` and ``dF E`` parts are left out, as the
    compressive part of a spring's Jacobian is clamped).
    """
    cof, Fm = at
    dF = deformation_gradient(u, h)
    dJ = (cof * dF).sum((1, 2))
    P = _cells(kappa_cells) * dJ.unsqueeze(1).unsqueeze(1) * cof
    if shear_cells is not None:
        assert Fm is not None
        FtdF = _per_cell(Fm, dF, transpose_a=True)
        dE = 0.5 * (FtdF + FtdF.transpose(1, 2))
        P = P + 2 * _cells(shear_cells) * _per_cell(Fm, dE)
    return _gather(h**3 * P, h)


def volume_row_sums(kappa_cells: torch.Tensor, h: float, shape, shear_cells, *, diagonal: bool = False):
    """Gershgorin row sums (or the diagonal) of the cell term's stiffness at rest per node (N/m), ``(1|B, 1, D, H, W)``.

    With ``g_a = grad N_a``, ``|g_ai| = 1 / (4 h)``, one cell's volume part is ``kappa h^3 g g^T``
    (24 entries per row: a row sums to ``1.5 kappa h``, its diagonal entry ``kappa h / 16``) and
    its shear part ``mu' h^3 (delta_ij g_a . g_b + g_aj g_bi)`` (a row sums to ``2.25 mu' h``, its
    diagonal ``mu' h / 4``); a node adds its cells'.
    """
    a, b = (1 / 16, 1 / 4) if diagonal else (1.5, 2.25)
    c = a * h * kappa_cells
    if shear_cells is not None:
        c = c + b * h * shear_cells
    c = c.reshape(-1, 1, *[n - 1 for n in shape])  # (1|B, 1, cells)
    for axis in (2, 3, 4):
        c = _pad_axis(c, axis, 1, 0) + _pad_axis(c, axis, 0, 1)
    return c


class VolumeLinearisation:
    """Springs and the cell term linearised at a state, for stiffness products.

    :class:`~torchdeform.sim.springs.Linearisation` plus :func:`volume_product`, with the same
    ``apply`` and ``scaled``.

    Args:
        springs: the springs' linearisation at ``x``.
        x: positions ``(B, 3, D, H, W)`` (or None with ``at``).
        kappa_cells: the volume modulus per cell (Pa).
        h: the cell side (m).
        shear_cells: the cell share of the shear modulus per cell (Pa), or None.
        alpha: the scale of the cell term's product (``h2`` of :meth:`scaled`).
        at: :func:`volume_state` at ``x``, when already known (instead of ``x``).
    """

    def __init__(self, springs, x, kappa_cells, h, shear_cells, *, alpha: float = 1.0, at: tuple | None = None):
        self.springs, self.kappa, self.h, self.shear, self.alpha = springs, kappa_cells, h, shear_cells, alpha
        self.grid = springs.grid
        #: ``(cof(F), F)`` at the state linearised at, per cell ``(B, 3, 3, D-1, H-1, W-1)``
        self.at: tuple = volume_state(x, h, shear=shear_cells is not None) if at is None else at

    @property
    def combined(self) -> bool:
        """True for the operator of :meth:`scaled` (the springs' coefficients combined)."""
        return self.springs.combined

    def scaled(self, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> VolumeLinearisation:
        """The operator ``u -> apply(u, alpha_scale, c, projected, c_scale)``, combined once."""
        return VolumeLinearisation(
            self.springs.scaled(alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale),
            None,
            self.kappa,
            self.h,
            self.shear,
            alpha=self.alpha * alpha_scale,
            at=self.at,
        )

    def apply(self, u: torch.Tensor, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> torch.Tensor:
        """``(h2 K + h C) u`` as a node field ``(B, 3, D, H, W)`` (the cell term has no damping)."""
        y = self.springs.apply(u, alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale)
        return y + (self.alpha * alpha_scale) * volume_product(self.at, u, self.kappa, self.h, self.shear)
