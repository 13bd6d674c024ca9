"""ChainMail, Enhanced ChainMail, a batched tensor ChainMail and elastic relaxation.

ChainMail (Gibson 1997), Enhanced ChainMail (Schill 1998/2001), a batched tensor ChainMail and
elastic relaxation, on the face neighbours of a :class:`~torchdeform.sim.grid.Grid`.

ChainMail is geometric: every link between two face neighbours may stretch, compress and shear
within limits; moving an element drags, pushes or shears its neighbours only when a limit is
exceeded, so only the elements that must move are touched. The result is plastic; elastic
relaxation afterwards smooths it.

Limits (:class:`Limits`). For the link from element ``i`` to ``j = i + e_a`` along axis ``a``
(channel ``a`` moves along axis ``a`` of ``(D, H, W)``)::

    min_a <= x_j[a] - x_i[a] <= max_a,      |x_j[b] - x_i[b]| <= shear_a   (b != a)

per axis (homogeneous, Gibson) or per link (heterogeneous tissue, Enhanced ChainMail).
Every solver takes an optional link mask, bool ``(3, D, H, W)`` stored like per-link limits
(:func:`link_mask` gives the full one): a link that is False imposes no limit, which is how a cut
unlinks elements (:func:`torchdeform.topology.unlink`); no mask costs nothing.

=====================  ===========================================================================
:class:`ChainMail`     sequential, cost proportional to the elements that move:
  ``"gibson"``         six FIFO lists served in turn; an element is checked only against its
                       sponsor; the lists of a +/-d element feed d, h and w, those of a +/-h
                       element h and w, those of a +/-w element w only, so every element has one
                       sponsor path and is checked at most once per initiator. Needs per-axis
                       limits (one set for the whole body) and a box (no node mask).
  ``"enhanced"``       one priority queue per moving coordinate, largest violation first
                       (Schill); per-link limits for heterogeneous tissue; each element is
                       corrected at most once per coordinate.
:func:`tensor_chainmail`  sponsor-front Jacobi sweeps with torch ops on the active box only (the
                       moved elements plus one hop), batched over bodies, any device: an element
                       is bounded only by neighbours that have moved; about one sweep per hop.
:func:`relax`          red-black projected relaxation of the offsets towards the centroid of the
                       neighbours (Knoche) or towards Gibson's goal positions, within the limits.
:func:`limit_violation`  the independent vectorised checker.
=====================  ===========================================================================

Results are offsets ``u = x - X`` (a displacement field ``(B, 3, D, H, W)`` for the volume
pipeline, :meth:`ChainMail.displacement`) or a :class:`~torchdeform.sim.model.State` that the
mass-spring integrators continue from (:meth:`ChainMail.state`).

Why the variants agree, and where they differ. Every limit bounds the difference of one
coordinate between two neighbours, so each coordinate is a separate system of difference
constraints; in offsets all its bounds are >= 0 (the rest state satisfies the limits). When the
picked elements move by ``delta``, coordinate ``c`` only has to be pulled up (``delta_c > 0``)
or pushed down, and the least motion that satisfies every limit is
``u_i <- max(u_i, max_p (t_p - w(i, p)))`` (for a pull) with ``w`` the shortest-path bound from
``i`` to a picked element ``p``: a shortest-path problem with non-negative weights, pruned where
an element does not move (its neighbours then do not move either). Gibson's dimension-ordered
paths are shortest paths when the limits are homogeneous; largest-violation-first is a
label-setting (Dijkstra) order because a violation never grows along a propagation; the
sponsor-front sweeps are Bellman-Ford, which is why they need about one sweep per hop. So all
three give the same positions (tested to rounding against a plain Bellman-Ford reference).
They differ in cost
(the sequential order decides which elements are touched; Enhanced ChainMail's order has no
parallel equivalent, the sweeps touch the whole grid every time), in that Gibson needs
homogeneous limits, and when a move is blocked by a fixed element: :meth:`ChainMail.move`
scales the move down to what is possible, :func:`tensor_chainmail` leaves the fixed element and
reports the remaining excess.

Example:
    >>> import torchdeform as td
    >>> from torchdeform.chainmail import ChainMail, Limits, limit_violation
    >>> grid = td.Grid((20, 20, 20), spacing=0.001)
    >>> cm = ChainMail(grid, Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2))
    >>> r = cm.move([(19, 10, 10)], (0.003, 0.0, 0.0))      # pull the top centre up 3 mm
    >>> r.moved > 1, float(limit_violation(cm.positions(), grid, cm.limits)) < 1e-12
    (True, True)
    >>> u = cm.displacement()                                 # (1, 3, 20, 20, 20) metres
    >>> energies = cm.relax(steps=4)                          # smooth the straight-line artefacts
    >>> u.shape, len(energies), energies[-1] <= energies[0]
    (torch.Size([1, 3, 20, 20, 20]), 5, True)
"""

from .limits import (
    DIRECTIONS,
    GIBSON_SUCCESSORS,
    METHODS,
    RELAX_MODES,
    BlockedMoveError,
    Limits,
    limit_violation,
    link_mask,
    neighbour_boxes,
    tissue_limits,
)
from .relaxation import crease_measure, relax, relax_energy
from .sequential import ChainMail, MoveResult
from .tensor import SweepResult, tensor_chainmail

__all__ = [
    "Limits",
    "ChainMail",
    "MoveResult",
    "BlockedMoveError",
    "tissue_limits",
    "limit_violation",
    "link_mask",
    "tensor_chainmail",
    "SweepResult",
    "neighbour_boxes",
    "relax",
    "relax_energy",
    "crease_measure",
    "DIRECTIONS",
    "GIBSON_SUCCESSORS",
    "METHODS",
    "RELAX_MODES",
]
