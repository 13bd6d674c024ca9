r"""An elastic material on the lattice: Young's modulus and Poisson ratio from springs plus a volume term.

A lattice of central springs alone obeys the Cauchy relation: its stiffness tensor is fully
symmetric, so at best it is isotropic with :math:`\lambda = \mu`, a Poisson ratio of 1/4.
:class:`Elastic` reaches any :math:`\nu \in [1/4, 1/2)` by adding a volume term per cell, and
assembles each spring's stiffness from the cells that contain it, so that the springs of a surface
layer are not stiffer than those inside.

**Springs.** With cubic cells of side ``h``, a spring of stiffness ``k`` along the half-direction
``d`` (length ``L = h |d|``, unit vector ``n``) adds :math:`k L^2 n_i n_j n_k n_l / h^3` to the
small-strain stiffness tensor of an infinite lattice (one spring per half-direction per node).
Summing the three classes (axis ``k_a``, face diagonal ``k_f``, body diagonal ``k_b``):

.. math::

    C_{11} = (k_a + 2 k_f + \tfrac43 k_b) / h, \qquad C_{12} = C_{44} = (k_f + \tfrac43 k_b) / h .

Cubic symmetry becomes isotropy when :math:`C_{11} - C_{12} = 2 C_{44}`, i.e.
:math:`k_a = k_f + \tfrac83 k_b`, and then :math:`\mu = C_{44}`, :math:`\lambda_{springs} = \mu`.
One ratio is free; this module takes (interior springs, :data:`CLASS_WEIGHTS`, ``k = w mu h``):

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
``w_a mu_c h / 4``, its face diagonals ``w_f mu_c h / 2`` and its body diagonals ``w_b mu_c h``;
a spring's stiffness is the sum over the cells that exist around it (:func:`spring_stiffness`).
Inside a uniform body that is the table above; on a face or an edge a spring gets the share of the
cells it has, so every cell carries exactly the energy of the continuum's deviatoric part.

**Volume term.** Per cell, :math:`W_c = \tfrac12 \kappa_c V (J_c - 1)^2` with :math:`V = h^3`,
:math:`J_c = \det F_c` and :math:`F_c` the deformation gradient at the cell's centre (the
trilinear cell: column ``j`` is the mean of the four edge vectors along axis ``j`` over ``h``). It
is invariant under rotation and, for small strain, :math:`\tfrac12 \kappa_c V
(\operatorname{tr}\varepsilon)^2`: it adds :math:`\kappa` to :math:`\lambda`. With

.. math::

    \mu = \frac{E}{2 (1 + \nu)}, \qquad \lambda = \frac{E \nu}{(1 + \nu)(1 - 2 \nu)}, \qquad
    \kappa = \lambda - \mu \ \ge 0 \iff \nu \ge \tfrac14,

springs and term together are the isotropic solid of modulus ``E`` and ratio ``nu`` in the
small-strain limit of a uniform strain. The force on corner ``a`` is
:math:`f_a = -\kappa V (J - 1)\, \operatorname{cof}(F)\, \nabla N_a` with
:math:`\nabla N_a = s_a / (4 h)`, :math:`s_a \in \{-1, 1\}^3` (:func:`volume_forces`). At
:math:`\nu = 1/4` the term vanishes and costs nothing.

Example:
    >>> import torchdeform as td
    >>> m = td.Elastic(youngs_modulus=5e3, poisson_ratio=0.45)
    >>> mu, lam = m.lame()
    >>> round(mu, 2), round(lam, 1), round(m.volume_modulus(), 1)
    (1724.14, 15517.2, 13793.1)
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
    "cell_mask",
    "spring_stiffness",
    "deformation_gradient",
    "volume_energy",
    "volume_forces",
    "volume_product",
    "volume_row_sums",
    "VolumeLinearisation",
]

#: Interior spring stiffness per class as a multiple of ``mu h`` (axis, face, body), per topology.
CLASS_WEIGHTS = {26: (1.5, 0.5, 0.375), 18: (1.0, 1.0, 0.0), 14: (2.0, 0.0, 0.75)}

#: The Poisson ratios :class:`Elastic` reaches on each topology: ``[lo, hi)``.
POISSON_RANGE = dict.fromkeys(CLASS_WEIGHTS, (0.25, 0.5))


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
    stiffness of :func:`spring_stiffness` and, for ``poisson_ratio > 1/4``, the model gets the
    per-cell volume term (:func:`volume_forces`). See the module docstring for the calibration.

    Args:
        youngs_modulus: E (Pa), a number or a per-node tensor ``(D, H, W)`` (a cell takes the
            mean of its 8 corners).
        poisson_ratio: nu, in ``[0.25, 0.5)`` (:data:`POISSON_RANGE`), a number or per node.

    Example:
        >>> import torchdeform as td
        >>> grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
        >>> model = td.Model(grid, td.Elastic(5e3, 0.3), density=1000.0)
        >>> model.volume is not None, round(float(model.stiffness[0, 0, 1, 1, 1]), 2)   # axis spring inside
        (True, 28.85)
    """

    youngs_modulus: float | torch.Tensor
    poisson_ratio: float | torch.Tensor

    def __post_init__(self):
        E = _number(self.youngs_modulus, "material.youngs_modulus")
        nu = _number(self.poisson_ratio, "material.poisson_ratio")
        e_bad = not bool((torch.as_tensor(E) > 0).all() & torch.isfinite(torch.as_tensor(E)).all())
        if e_bad:
            raise ConfigError("material.youngs_modulus", "a positive, finite Young's modulus (Pa)", got=E)
        lo, hi = 0.25, 0.5
        t = torch.as_tensor(nu)
        if not bool(((t >= lo) & (t < hi)).all()):
            raise ConfigError(
                "material.poisson_ratio",
                f"a Poisson ratio in [{lo}, {hi}) (springs plus a volume term reach no lower ratio)",
                got=nu,
            )
        object.__setattr__(self, "youngs_modulus", E)
        object.__setattr__(self, "poisson_ratio", nu)

    def lame(self):
        """``(mu, lambda)`` in Pa (numbers or per-node tensors)."""
        E, nu = self.youngs_modulus, self.poisson_ratio
        return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    def volume_modulus(self):
        """``kappa = lambda - mu`` (Pa): the volume term's modulus, 0 at ``nu = 1/4``."""
        mu, lam = self.lame()
        return lam - mu

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
    """A number or a per-node field ``(D, H, W)`` as a per-cell field ``(D-1, H-1, W-1)`` (corner mean)."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    if t.dim() == 0:
        return t.expand(tuple(n - 1 for n in grid.shape))
    if tuple(t.shape) != grid.shape:
        raise ConfigError("material", f"numbers or per-node fields of shape {grid.shape}", got=tuple(t.shape))
    for axis in range(3):
        t = _mean2(t, axis)
    return t


def cell_mask(grid, *, device=None) -> torch.Tensor:
    """Bool ``(D-1, H-1, W-1)``: the cell's 8 corners are all nodes of the body."""
    nodes = grid.nodes().to(device)
    D, H, W = (n - 1 for n in nodes.shape)
    m = torch.ones((D, H, W), dtype=torch.bool, device=nodes.device)
    for a, b, c in itertools.product((0, 1), repeat=3):
        m &= nodes[a : a + D, b : b + H, c : c + W]
    return m


def spring_stiffness(grid, mu_cells: torch.Tensor, h: float) -> torch.Tensor:
    """Each spring's stiffness (N/m), ``(S, D, H, W)``, assembled from the cells that contain it.

    ``mu_cells``: the shear modulus of each cell (Pa), ``(D-1, H-1, W-1)``, 0 where a cell is
    missing. A spring along ``d`` stored at node ``p`` lies in the cells ``c`` with
    ``c_j = min(p_j, p_j + d_j)`` where ``d_j != 0`` and ``c_j in {p_j - 1, p_j}`` where
    ``d_j = 0``: ``2^z`` cells for ``z`` zero components, each giving ``w mu_c h / 2^z``.
    """
    weights = dict(zip(("axis", "face", "body"), CLASS_WEIGHTS[grid.topology]))
    M = F.pad(mu_cells, (1, 1, 1, 1, 1, 1))  # M[c + 1] = mu_c; zero outside the grid
    D, H, W = grid.shape
    out = []
    for d, cls in zip(grid.directions, grid.direction_class()):
        starts = [(0, 1) if c == 0 else (1,) if c > 0 else (0,) for c in d]  # of the cells, in M
        total = sum(M[a : a + D, b : b + H, e : e + W] for a, b, e in itertools.product(*starts))
        out.append(total * (weights[cls] * h / 2 ** d.count(0)))
    return torch.stack(out)


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


def volume_energy(x: torch.Tensor, kappa_cells: torch.Tensor, h: float) -> torch.Tensor:
    """The volume term's energy (J) per batch entry, ``(B,)``: ``sum_c kappa_c h^3 (J_c - 1)^2 / 2``.

    ``kappa_cells``: ``(D-1, H-1, W-1)`` or ``(B|1, D-1, H-1, W-1)`` (Pa), 0 where a cell is missing.
    """
    J, _ = _det_cof(deformation_gradient(x, h))
    return (0.5 * h**3 * kappa_cells * (J - 1) ** 2).flatten(1).sum(1)


def volume_forces(x: torch.Tensor, kappa_cells: torch.Tensor, h: float) -> torch.Tensor:
    """The volume term's force on every node (N), ``(B, 3, D, H, W)``: minus the gradient of :func:`volume_energy`.

    Per cell ``P = kappa h^3 (J - 1) cof(F)``; corner ``a`` gets ``-P grad N_a`` with
    ``grad N_a = s_a / (4 h)``, gathered to the nodes by the adjoints of the edge differences and
    means that made ``F`` (:func:`deformation_gradient`).

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.sim.material import volume_energy, volume_forces
        >>> X = td.Grid((3, 3, 3), spacing=0.01).rest_positions(dtype=torch.float64)
        >>> x = (X * torch.tensor([1.02, 0.99, 1.0], dtype=torch.float64).view(1, 3, 1, 1, 1)).requires_grad_()
        >>> kappa = torch.full((2, 2, 2), 1e4, dtype=torch.float64)
        >>> f = volume_forces(x, kappa, 0.01)
        >>> g, = torch.autograd.grad(volume_energy(x, kappa, 0.01).sum(), x)
        >>> bool(torch.allclose(f, -g, rtol=1e-12, atol=1e-18))
        True
    """
    J, cof = _det_cof(deformation_gradient(x, h))
    return -_gather((h**3 * kappa_cells * (J - 1)).unsqueeze(1).unsqueeze(1) * cof, h)


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


def volume_product(cof: torch.Tensor, u: torch.Tensor, kappa_cells: torch.Tensor, h: float) -> torch.Tensor:
    """The volume term's stiffness product ``K u`` (N), ``(B, 3, D, H, W)``, Gauss-Newton.

    ``cof``: ``cof(F)`` at the state linearised at, ``(B, 3, 3, cells)``. Per cell
    ``K u = kappa h^3 (cof : dF(u)) cof grad N`` gathered to the nodes: the exact Hessian at rest
    (``J = 1``) and positive semi-definite everywhere (the ``(J - 1) d cof`` part is left out, as
    the compressive part of a spring's Jacobian is clamped).
    """
    dJ = (cof * deformation_gradient(u, h)).sum((1, 2))
    return _gather((h**3 * kappa_cells * dJ).unsqueeze(1).unsqueeze(1) * cof, h)


def volume_row_sums(kappa_cells: torch.Tensor, h: float, shape) -> torch.Tensor:
    """Gershgorin row sums of the volume term's stiffness at rest per node (N/m), ``(1, 1, D, H, W)``.

    One cell's matrix is ``kappa h^3 g g^T`` with ``|g_ai| = 1 / (4 h)`` over 24 entries: a row
    sums to ``1.5 kappa h``; a node adds its cells' sums.
    """
    c = (1.5 * h * kappa_cells).expand(1, 1, *[n - 1 for n in shape])
    for axis in (2, 3, 4):
        c = _pad_axis(c, axis, 1, 0) + _pad_axis(c, axis, 0, 1)
    return c


class VolumeLinearisation:
    """Springs and the volume term linearised at a state, for stiffness products.

    :class:`~torchdeform.sim.springs.Linearisation` plus :func:`volume_product`, with the same
    ``apply`` and ``scaled``.

    Args:
        springs: the springs' linearisation at ``x``.
        x: positions ``(B, 3, D, H, W)`` (or None with ``cof``).
        kappa_cells: the volume modulus per cell (Pa).
        h: the cell side (m).
        alpha: the scale of the volume term's product (``h2`` of :meth:`scaled`).
        cof: ``cof(F)`` per cell, when already known (instead of ``x``).
    """

    def __init__(self, springs, x, kappa_cells, h, *, alpha: float = 1.0, cof: torch.Tensor | None = None):
        self.springs, self.kappa, self.h, self.alpha = springs, kappa_cells, h, alpha
        self.grid = springs.grid
        #: ``cof(F)`` at the state linearised at, per cell ``(B, 3, 3, D-1, H-1, W-1)``
        self.cof: torch.Tensor = _det_cof(deformation_gradient(x, h))[1] if cof is None else cof

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
            alpha=self.alpha * alpha_scale,
            cof=self.cof,
        )

    def apply(self, u: torch.Tensor, *, alpha_scale=1.0, c=None, projected=True, c_scale=1.0) -> torch.Tensor:
        """``(h2 K + h C) u`` as a node field ``(B, 3, D, H, W)`` (the volume term has no damping)."""
        y = self.springs.apply(u, alpha_scale=alpha_scale, c=c, projected=projected, c_scale=c_scale)
        return y + (self.alpha * alpha_scale) * volume_product(self.cof, u, self.kappa, self.h)
