"""Several deformable bodies in one scene, touching each other.

Each :class:`Body` is a :class:`~torchdeform.sim.model.Model` on its own grid (its own shape,
spacing, origin, material, loads, fixed nodes, tools); :class:`Bodies` steps them with one
integrator and then resolves the contacts between them (:class:`BodyContact`).

**Where a node is inside another body.** A body's solid is the union of its cells whose eight
corners belong to it. At rest, every node of the body holds ``phi``, minus its distance (m) to the
nearest node on the body's surface (0 on the surface). A point ``p`` of another body is located in
this body's deformed lattice by Newton's method on the trilinear map of the cell it falls in
(``x(s) = sum_k b_k(s) x_k``, ``s`` the cell coordinates, started from the body's least-squares
affine map); it is inside where its cell is solid and ``phi(s) < 0``. The depth and the outward
normal are the first-order ones, ``d = phi / |grad_x phi|``, ``n = grad_x phi / |grad_x phi|``
with ``grad_x phi = J^-T grad_s phi`` (``J = dx/ds``): exact across a flat face.

**The response** is a projection after the step, as for tools
(:class:`~torchdeform.interact.contact.ProjectionContact`), but between a node ``a`` and the point
of the other body it fell in, whose velocity and position are the trilinear blend of the cell's
corners. With inverse masses ``w_a`` and ``w_k`` (0 for fixed nodes) and
``W = w_a + sum_k b_k^2 w_k``, the normal impulse ``j_n = -d / (W dt)`` changes the velocities,
``v_a += w_a j``, ``v_k -= b_k w_k j``, and the positions as the step would have moved them with
those velocities (``x += dt dv``): the penetration is gone, positions and velocities stay
consistent (a body at rest on another stays at rest; the contact force is the weight it
carries), and the impulses are equal and opposite (momentum conserved to rounding). Coulomb
friction adds a tangential impulse of at most ``mu j_n`` against the relative tangential velocity
(all of it: sticking), so a block on a slope tilted by ``theta`` sticks for ``tan(theta) <= mu``.
Contacts that share corners of the other body are resolved colour by colour (cells of one parity
along the three axes, then the contacts within one cell in turn: Gauss-Seidel), each seeing how
far the earlier ones moved the corners, so that together they do not overshoot.

Nodes of ``a`` in ``b`` are resolved, then nodes of ``b`` in ``a``. The order of the error is that
of tool contact: first order in ``dt`` (the contact acts at the end of the step, after the
integrator, implicit Euler included, and before the global drag). A folded body touching itself
is not detected (no self-contact), nor are two edges crossing where no node is inside the other
body (two equal blocks stacked with their edges exactly aligned). Without friction a block on
another is held sideways only by the dent it makes, and drifts slowly.

**Cost.** Only the nodes inside the other body's deformed bounding box are located: in a stack,
about one layer of each body.

**Readings** per pair ``"<a>/<b>"`` (keys of :attr:`~torchdeform.sim.model.State.readings` of the
step, on both bodies' states): ``force`` ``(B, 3)`` N, the force ``a`` exerts on ``b`` (the
momentum the response gave ``b``, over ``dt``); ``contacts`` ``(B,)`` the nodes of either body
found inside the other; ``penetration`` ``(B,)`` m, the deepest of them before the projection.

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.interact.bodies import Bodies, Body
    >>> from torchdeform.interact.reactions import support_reaction
    >>> lower = td.Model(td.Grid((4, 4, 4), spacing=0.01), stiffness=50.0, mass=1e-3, fixed="bottom",
    ...                  gravity=(-9.81, 0, 0), decay=50.0, dtype=torch.float64)
    >>> upper = td.Model(td.Grid((3, 3, 3), spacing=0.01, origin=(0.0305, 0.005, 0.005)), stiffness=50.0,
    ...                  mass=1e-3, gravity=(-9.81, 0, 0), decay=50.0, dtype=torch.float64)
    >>> scene = Bodies([Body("lower", lower), Body("upper", upper)], friction=0.5)
    >>> states = scene.simulate(scene.rest_states(), dt=1e-3, steps=600)
    >>> round(float(states[1].readings["lower/upper.force"][0, 0]), 5)     # carries the upper block: 27 g
    0.26487
    >>> round(float(support_reaction(lower, states[0])[0, 0]), 5)          # the base carries both: 91 g
    0.89271
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import torch
from tqdm import tqdm

from ..errors import ConfigError, DivergenceError
from ..sim.integrators import Integrator, SymplecticEuler
from ..sim.model import Model, State
from ..sim.stability import DivergenceMonitor
from .reactions import report
from .stacking import stack_key, stack_models

__all__ = ["Body", "BodyContact", "Bodies", "rest_distance", "rest_member"]

#: Newton iterations that locate a point in a deformed cell (quadratic convergence: 5 are plenty)
NEWTON = 5

#: the corners of a cell as offsets (d, h, w), in the order of the trilinear weights
_CORNERS = torch.tensor(list(itertools.product((0, 1), repeat=3)))


def rest_distance(model: Model) -> tuple:
    """The body's solid at rest: ``(phi (D, H, W), solid cells (D-1, H-1, W-1))``.

    ``phi`` is minus the distance (m) from each node to the nearest surface node of the body (0
    on the surface, one spacing at nodes that are not part of it); a cell is solid where its eight
    corners are part of the body (the grid's ``node_mask``, less nodes a topology change removed).

    Example:
        >>> import torchdeform as td
        >>> phi, solid = rest_distance(td.Model(td.Grid((5, 5, 5), spacing=0.01), stiffness=1.0, mass=1.0))
        >>> round(float(phi[2, 2, 2]), 6), float(phi[0, 2, 2]), bool(solid.all())
        (-0.02, 0.0, True)
    """
    from scipy.ndimage import distance_transform_edt

    grid = model.grid
    shape = grid.shape
    m = member = rest_member(model).reshape(shape)
    solid = m[:-1, :-1, :-1] & m[1:, :-1, :-1] & m[:-1, 1:, :-1] & m[:-1, :-1, 1:]
    solid = solid & m[1:, 1:, :-1] & m[1:, :-1, 1:] & m[:-1, 1:, 1:] & m[1:, 1:, 1:]
    # an interior node has all eight cells around it solid (a node on the grid's border has not)
    padded = torch.nn.functional.pad(solid.float()[None, None], (1, 1, 1, 1, 1, 1))[0, 0] > 0
    interior = torch.ones(shape, dtype=torch.bool)
    for dd, dh, dw in _CORNERS.tolist():
        interior &= padded[dd : dd + shape[0], dh : dh + shape[1], dw : dw + shape[2]]
    dist = distance_transform_edt(interior.numpy(), sampling=model.grid.spacing)
    phi = torch.from_numpy(-dist) + 0.0  # -0.0 on the surface becomes 0.0
    phi[~member] = max(grid.spacing)  # outside (only solid cells are tested)
    return phi.to(model.dtype), solid


def rest_member(model: Model) -> torch.Tensor:
    """Flat bool ``(D*H*W,)``: the nodes that belong to the body (its grid's ``node_mask``, less removed nodes)."""
    grid = model.grid
    member = torch.ones(grid.shape, dtype=torch.bool) if grid.node_mask is None else grid.node_mask.cpu().bool()
    if model.removed is not None:
        member = member & ~model.removed.cpu()
    return member.reshape(-1)


@dataclass(eq=False)
class Body:
    """One deformable body of a scene: a name and its model.

    Args:
        name: the body's name (readings and errors use it).
        model: the :class:`~torchdeform.sim.model.Model`, on a grid placed in the world by its
            ``origin`` (m).
    """

    name: str
    model: Model
    phi: torch.Tensor = field(init=False, repr=False)
    solid: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError("bodies.name", "a non-empty name for every body", got=self.name)
        if not isinstance(self.model, Model):
            raise ConfigError(f"bodies.{self.name}", "a torchdeform Model", got=type(self.model).__name__)
        phi, solid = rest_distance(self.model)
        self.phi = phi.to(self.model.device).reshape(-1)
        self.solid = solid.to(self.model.device)
        grid, dev, dt = self.model.grid, self.model.device, self.model.dtype
        self._shape = torch.tensor(grid.shape, device=dev)
        self._h = torch.tensor(grid.spacing, dtype=dt, device=dev)
        self._origin = torch.tensor(grid.origin, dtype=dt, device=dev)
        self._strides = torch.tensor([grid.shape[1] * grid.shape[2], grid.shape[2], 1], device=dev)
        self._corner_offsets = (_CORNERS.to(dev) * self._strides).sum(1)  # (8,) flat offsets
        # the least-squares affine map x = X A + b over the body's nodes, solved once at rest
        X = self.model.X[0].reshape(3, -1).T.to(torch.float64)  # (N, 3)
        member = rest_member(self.model)
        Xh = torch.cat([X, torch.ones(len(X), 1, dtype=torch.float64, device=X.device)], 1)[member.to(X.device)]
        self._member = member.to(dev)
        self._whole = bool(member.all())
        self._fit = torch.linalg.pinv(Xh).to(dt)  # (4, M)
        self._inv_mass = self.model.inv_mass.expand(1, 1, *grid.shape).reshape(-1).contiguous()
        self._member_u8 = self._member.to(torch.uint8).contiguous()  # for the C kernel
        self._solid_u8 = self.solid.to(torch.uint8).contiguous()

    def affine(self, x: torch.Tensor) -> tuple:
        """The least-squares affine map of the deformed lattice ``x`` ``(3, D, H, W)`` (or ``(3, N)``) as ``x = X A + b``.

        Returns ``(A^-1 (3, 3), b (3,))``: a rest point's first guess is ``X = (p - b) A^-1``.
        """
        nodes = x.reshape(3, -1).T
        P = self._fit @ (nodes if self._whole else nodes[self._member])  # (4, 3)
        return torch.linalg.inv_ex(P[:3])[0].contiguous(), P[3].contiguous()  # NaN in, NaN out: the monitor reports it

    def locate(self, x: torch.Tensor, p: torch.Tensor) -> tuple:
        """Points ``p`` ``(M, 3)`` in this body's deformed lattice ``x`` ``(3, D, H, W)``.

        Returns ``(inside (M,), depth (M,) m <= 0, normal (M, 3), corners (M, 8) flat node
        indices, weights (M, 8))``.
        """
        nodes = x.reshape(3, -1).T  # (N, 3)
        A_inv, b = self.affine(x)
        X = (p - b) @ A_inv  # (M, 3) rest positions, first guess
        top = (self._shape - 2).to(p.dtype)
        tol = 1e-4 if p.dtype == torch.float32 else 1e-9  # cells: rounding of the positions
        for _ in range(NEWTON):
            cell, s = self._cell(X, top)
            xs, J, corners, w, _ = self._trilinear(nodes, cell, s)
            step, _ = torch.linalg.solve_ex(J, (p - xs).unsqueeze(-1))
            step = torch.nan_to_num(step.squeeze(-1)).clamp(-4.0, 4.0)  # a collapsed cell: no step
            X = X + step * self._h
            if float(step.abs().max()) < tol:  # converged (quadratically) everywhere
                break
        cell, s = self._cell(X, top)
        xs, J, corners, w, dw = self._trilinear(nodes, cell, s)
        c = cell.long()
        solid = self.solid[c[:, 0], c[:, 1], c[:, 2]]
        within = ((s >= -1e-9) & (s <= 1 + 1e-9)).all(1)
        close = (xs - p).norm(dim=1) <= 1e-3 * float(self._h.min())
        phi_c = self.phi[corners]  # (M, 8)
        phi = (w * phi_c).sum(1)
        grad_s = (dw * phi_c.unsqueeze(-1)).sum(1)  # (M, 3)
        grad_x, info = torch.linalg.solve_ex(J.transpose(1, 2), grad_s.unsqueeze(-1))
        grad_x = grad_x.squeeze(-1)
        size = grad_x.norm(dim=1)
        inside = solid & within & close & (phi < 0) & (info == 0) & torch.isfinite(size) & (size > 0)
        size = torch.where(inside, size, torch.ones_like(size))
        return inside, phi / size, grad_x / size.unsqueeze(1), corners, w

    def _cell(self, X, top):
        """The cell ``(M, 3)`` (clamped into the grid) and the cell coordinates ``s`` ``(M, 3)`` of rest points ``X``."""
        g = (X - self._origin) / self._h
        cell = g.floor().clamp(torch.zeros_like(top), top)
        return cell, g - cell

    def _trilinear(self, nodes, cell, s):
        """``x(s)`` ``(M, 3)``, ``J = dx/ds`` ``(M, 3, 3)``, corners ``(M, 8)``, weights ``(M, 8)`` and their gradients ``(M, 8, 3)``."""
        c = cell.long()
        corners = (c * self._strides).sum(1, keepdim=True) + self._corner_offsets  # (M, 8)
        xc = nodes[corners]  # (M, 8, 3)
        f = torch.stack([1 - s, s], 1)  # (M, 2, 3): the two linear factors along each axis
        o = _CORNERS.to(s.device)
        fd, fh, fw = f[:, o[:, 0], 0], f[:, o[:, 1], 1], f[:, o[:, 2], 2]  # (M, 8) each
        sign = (2 * o - 1).to(s.dtype)
        wd = torch.stack([fd * fh * fw, sign[:, 0] * fh * fw, sign[:, 1] * fd * fw, sign[:, 2] * fd * fh], 2)
        out = torch.bmm(xc.transpose(1, 2), wd)  # (M, 3, 4): x(s) and the three columns of J
        return out[:, :, 0], out[:, :, 1:], corners, wd[:, :, 0], wd[:, :, 1:]

    def near(self, x: torch.Tensor, p: torch.Tensor, member: torch.Tensor) -> torch.Tensor:
        """Indices ``(M,)`` of the points ``p`` ``(N, 3)`` (where ``member``) inside this body's deformed bounding box.

        Only these can be inside the body: the others are not located (:meth:`locate`).
        """
        lo, hi = self.boxes(x[None])
        return (((p > lo[0]) & (p < hi[0])).all(1) & member).nonzero().squeeze(1)

    def boxes(self, x: torch.Tensor, *, pad: float = 0.0) -> tuple:
        """The deformed lattice's bounding boxes ``(lo, hi)``, ``(B, 3)`` each, of positions ``x`` ``(B, 3, D, H, W)``.

        ``pad`` (m) widens them on every side.
        """
        pts = x.reshape(x.shape[0], 3, -1)
        if not self._whole:
            pts = pts[:, :, self._member]
        lo, hi = torch.aminmax(pts, dim=2)
        return lo - pad, hi + pad


def _padded_boxes(body: Body, x: torch.Tensor) -> tuple:
    """:meth:`Body.boxes` widened by one spacing of the body.

    The contacts resolved before a pair is looked at move nodes by less than that, so two bodies
    whose boxes stay apart cannot touch.
    """
    return body.boxes(x, pad=float(body._h.max()))


def _colours(corners: torch.Tensor, strides: torch.Tensor) -> list:
    """Masks ``(M,)`` of constraints that share no corner, in order: one colour after another.

    Constraints in cells of the same parity along the three axes share no corner unless they are
    in the same cell; those in one cell are numbered and go into successive colours.
    """
    cell = corners[:, 0]  # the first corner names the cell
    coords = [(cell // strides[k]) % (strides[k - 1] // strides[k] if k else cell.max() + 1) for k in range(3)]
    parity = (coords[0] % 2) * 4 + (coords[1] % 2) * 2 + coords[2] % 2
    order = torch.argsort(cell, stable=True)
    ranked = cell[order]
    pos = torch.arange(len(cell), device=cell.device)
    first = torch.ones_like(ranked, dtype=torch.bool)
    first[1:] = ranked[1:] != ranked[:-1]
    start = torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
    rank = torch.empty_like(pos)
    rank[order] = pos - start
    colour = rank * 8 + parity
    return [colour == c for c in torch.unique(colour).tolist()]


class BodyContact:
    """Contact between deformable bodies, resolved after every step (module docstring).

    Args:
        friction: Coulomb coefficient ``mu >= 0`` between every pair (0: frictionless).
        engine: ``"native"`` (the C kernel of :mod:`~torchdeform.interact.native_contact`:
            constraints resolved one after another), ``"torch"`` (tensor code, constraints that share
            no corner resolved together, colour by colour; any device) or ``"auto"`` (the kernel
            where it can run: CPU, float32/float64, a C compiler).
    """

    def __init__(self, *, friction: float = 0.0, engine: str = "auto"):
        if (
            not isinstance(friction, (int, float))
            or isinstance(friction, bool)
            or not math.isfinite(friction)
            or friction < 0
        ):
            raise ConfigError("contact.friction", "a Coulomb coefficient >= 0", got=friction)
        if engine not in ("auto", "native", "torch"):
            raise ConfigError("contact.engine", "one of auto, native, torch", got=engine)
        self.friction = float(friction)
        self.engine = engine

    def engine_for(self, x: torch.Tensor) -> str:
        """The engine that resolves bodies with positions like ``x``: ``"native"`` or ``"torch"``."""
        if self.engine == "torch":
            return "torch"
        from . import native_contact

        why = native_contact.supports(x.dtype, x.device)
        if why is None:
            return "native"
        if self.engine == "native":
            raise ConfigError("contact.engine", "a body the C contact kernel can resolve", got=why, show_got=True)
        return "torch"

    def resolve(self, bodies: list, xs: list, vs: list, dt: float, *, readings: list | None = None) -> None:
        """Project every pair's penetrations: replaces the entries of the lists ``xs``, ``vs`` (``(B, 3, D, H, W)`` each)."""
        for k in range(len(xs)):  # corrected in place below: copies, the integrator's tensors stay as they were
            xs[k], vs[k] = xs[k].clone(), vs[k].clone()
        boxes = [_padded_boxes(b, x) for b, x in zip(bodies, xs)]  # the broad phase: (B, 3) each
        for i, j in itertools.combinations(range(len(bodies)), 2):
            a, b = bodies[i], bodies[j]
            key = f"{a.name}/{b.name}"
            force = torch.zeros(xs[i].shape[0], 3, dtype=xs[i].dtype, device=xs[i].device)
            count = torch.zeros(xs[i].shape[0], dtype=xs[i].dtype, device=xs[i].device)
            depth = torch.zeros_like(count)
            pair = self._pair
            if self.engine_for(xs[i]) == "native":
                pair = self._native_pair
            (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
            near = ((lo_i < hi_j) & (lo_j < hi_i)).all(1).tolist()  # per batch entry: the boxes overlap
            for q, r, sign in ((i, j, 1.0), (j, i, -1.0)):  # nodes of q in r, then of r in q
                for n in range(xs[q].shape[0]):
                    if not near[n if len(near) > 1 else 0]:
                        continue
                    f, c, d = pair(bodies[q], bodies[r], xs, vs, q, r, n, dt)
                    force[n] += sign * f
                    count[n] += c
                    depth[n] = torch.maximum(depth[n], d)
            if readings is not None:
                for k in (i, j):
                    report(readings[k], key, "force", force)
                    report(readings[k], key, "contacts", count)
                    report(readings[k], key, "penetration", depth)

    def _native_pair(self, a: Body, b: Body, xs, vs, ia: int, ib: int, n: int, dt: float):
        """:meth:`_pair` by the C kernel (:mod:`~torchdeform.interact.native_contact`)."""
        from .native_contact import resolve_pair

        xa, va, xb, vb = (t[n].reshape(3, -1) for t in (xs[ia], vs[ia], xs[ib], vs[ib]))  # contiguous views
        return resolve_pair(a, b, xa, va, xb, vb, dt, self.friction)

    def _pair(self, a: Body, b: Body, xs, vs, ia: int, ib: int, n: int, dt: float):
        """Nodes of ``a`` inside ``b``, batch entry ``n``; returns (force of a on b (3,), count, depth)."""
        xa, va, xb, vb = (t[n].reshape(3, -1) for t in (xs[ia], vs[ia], xs[ib], vs[ib]))  # views (3, N)
        pa = xa.T  # (N, 3)
        zero = torch.zeros(3, dtype=xa.dtype, device=xa.device)
        idx = b.near(xb, pa, a._member)
        if idx.numel() == 0:
            return zero, 0.0, torch.zeros((), dtype=xa.dtype, device=xa.device)
        inside, d, nrm, corners, w = b.locate(xb, pa[idx])
        if not bool(inside.any()):
            return zero, 0.0, torch.zeros((), dtype=xa.dtype, device=xa.device)
        idx, d, nrm, corners, w = idx[inside], d[inside], nrm[inside], corners[inside], w[inside]
        wa = a._inv_mass[idx]  # (M,)
        wk = b._inv_mass[corners]  # (M, 8)
        W = wa + (w * w * wk).sum(1)
        ok = W > 0
        idx, d, nrm, corners, w, wa, wk, W = (t[ok] for t in (idx, d, nrm, corners, w, wa, wk, W))
        if idx.numel() == 0:
            return zero, 0.0, torch.zeros((), dtype=xa.dtype, device=xa.device)
        # the penetration removed by equal and opposite impulses j_n n, split by inverse mass, that
        # move the nodes as the step would have with them (x = x0 + dt v): positions and
        # velocities stay consistent, so a body at rest on another stays at rest. Constraints
        # that share corners of b are resolved one colour after another (Gauss-Seidel), each seeing
        # how far the earlier ones moved b, so that together they do not overshoot
        moved = torch.zeros_like(xb)  # (3, N) what the constraints resolved so far moved b's nodes
        impulse = torch.zeros(3, dtype=xa.dtype, device=xa.device)
        for sel in _colours(corners, b._strides):
            i_, n_, c_, w_, wa_, wk_, W_ = idx[sel], nrm[sel], corners[sel], w[sel], wa[sel], wk[sel], W[sel]
            f_ = c_.reshape(-1)
            shift = torch.bmm(w_.unsqueeze(1), moved[:, f_].T.reshape(-1, 8, 3)).squeeze(1)
            depth = d[sel] - (n_ * shift).sum(1)  # the depth now: b's point moved by shift
            jn = (-depth).clamp_min(0) / (W_ * dt)  # (m,) kg m/s
            vrel = va[:, i_].T - torch.bmm(w_.unsqueeze(1), vb[:, f_].T.reshape(-1, 8, 3)).squeeze(1)
            tang = vrel - (vrel * n_).sum(1, keepdim=True) * n_  # (m, 3)
            speed = tang.norm(dim=1)
            jt = torch.minimum(speed / W_, self.friction * jn) if self.friction > 0 else torch.zeros_like(jn)
            tdir = tang / speed.clamp_min(torch.finfo(xa.dtype).tiny).unsqueeze(1)
            j = jn.unsqueeze(1) * n_ - jt.unsqueeze(1) * tdir  # (m, 3) impulse on a's nodes
            dva = wa_.unsqueeze(1) * j
            dvb = (-(w_ * wk_).unsqueeze(-1) * j.unsqueeze(1)).reshape(-1, 3).T  # (3, m*8)
            va.index_add_(1, i_, dva.T)  # in place on the copies made by resolve
            xa.index_add_(1, i_, dt * dva.T)
            vb.index_add_(1, f_, dvb)
            xb.index_add_(1, f_, dt * dvb)
            moved.index_add_(1, f_, dt * dvb)
            impulse = impulse + j.sum(0)

        # the impulses on a's nodes came from b: a pushes b with minus their sum, over the step
        return -impulse / dt, float(idx.numel()), (-d).max()


def _groups(models: list, integrator) -> list:
    """Lists of the indices of models that can be stepped in one batch (:func:`~torchdeform.interact.stacking.stack_key`)."""
    groups: dict = {}
    for k, m in enumerate(models):
        key = stack_key(m, integrator)
        groups.setdefault(("alone", k) if key is None else key, []).append(k)
    return sorted(groups.values())


class Bodies:
    """Several bodies stepped by one integrator, with the contacts between them.

    Args:
        bodies: a list of :class:`Body` (names distinct).
        integrator: the :class:`~torchdeform.sim.integrators.Integrator` of every body
            (default symplectic Euler).
        friction: Coulomb coefficient between bodies (:class:`BodyContact`).
        engine: how the contacts are resolved, ``"auto"``, ``"native"`` or ``"torch"`` (:class:`BodyContact`).
        batch: step bodies whose grids share a shape in one batch (:mod:`~torchdeform.interact.stacking`:
            the same arithmetic per body, one integrator call for all of them); False: one after the other.
    """

    def __init__(
        self,
        bodies,
        *,
        integrator: Integrator | None = None,
        friction: float = 0.0,
        engine: str = "auto",
        batch: bool = True,
    ):
        bodies = list(bodies)
        if not bodies or not all(isinstance(b, Body) for b in bodies):
            raise ConfigError("bodies", "a list of Body", got=bodies)
        names = [b.name for b in bodies]
        for k, name in enumerate(names):
            if name in names[:k]:
                raise ConfigError("bodies.name", "a name no other body has", got=name)
        self.bodies = bodies
        self.integrator = integrator or SymplecticEuler()
        self.contact = BodyContact(friction=friction, engine=engine)
        #: lists of body indices stepped together (one integrator call each), in body order
        self.groups = (
            _groups([b.model for b in bodies], self.integrator) if batch else [[k] for k in range(len(bodies))]
        )
        self._stacked: dict = {}

    def rest_states(self, *, batch: int = 1) -> list:
        """Every body at rest, ``[State]``."""
        return [b.model.rest_state(batch=batch) for b in self.bodies]

    def check_apart(self, states: list) -> None:
        """Raise :class:`ConfigError` where a body starts inside another (naming both)."""
        for a, b in itertools.permutations(range(len(self.bodies)), 2):
            A, B = self.bodies[a], self.bodies[b]
            for n in range(states[a].x.shape[0]):
                pa, xb = states[a].x[n].reshape(3, -1).T, states[b].x[n]
                idx = B.near(xb, pa, A._member)
                if idx.numel() and bool(B.locate(xb, pa[idx])[0].any()):
                    raise ConfigError(
                        f"bodies.{A.name}",
                        f"bodies that start apart ({A.name} starts inside {B.name})",
                        got=None,
                        show_got=False,
                    )

    def step(self, states: list, dt: float) -> list:
        """Advance every body by ``dt`` (s), then resolve their contacts; returns the new states."""
        integ = self.integrator
        new = self._advance(states, dt)
        xs, vs = [s.x for s in new], [s.v for s in new]
        readings = [dict(s.readings or {}) for s in new]
        self.contact.resolve(self.bodies, xs, vs, dt, readings=readings)  # before the global drag, as tool contact
        return [
            State(x, integ.drag(b.model, v, dt), t=s.t, readings=r or None)
            for b, x, v, s, r in zip(self.bodies, xs, vs, new, readings)
        ]

    def _advance(self, states: list, dt: float) -> list:
        """Every body's state after the integrator's step (before contact), one call per group."""
        integ = self.integrator
        new: list = [None] * len(states)
        for group in self.groups:
            if len(group) == 1:
                (k,) = group
                m, s = self.bodies[k].model, states[k]
                new[k] = integ.respond(m, s, *integ.advance(m, s, dt, None), dt)
                continue
            sizes = [states[k].x.shape[0] for k in group]
            model = self._stacked_model(group, sizes)
            s = State(
                torch.cat([states[k].x for k in group]), torch.cat([states[k].v for k in group]), t=states[group[0]].t
            )
            out = integ.respond(model, s, *integ.advance(model, s, dt, None), dt)
            for k, x, v in zip(group, out.x.split(sizes), out.v.split(sizes)):
                new[k] = State(x, v, t=out.t)
        return new

    def _stacked_model(self, group: list, sizes: list) -> Model:
        """The group's models stacked for batches of ``sizes`` (built once; again if a model's fields change)."""
        models = [self.bodies[k].model for k in group]
        key = (
            tuple(group),
            tuple(sizes),
            tuple(id(t) for m in models for t in (m.stiffness, m.mass, m.damping, m.volume)),
        )
        if key not in self._stacked:
            self._stacked = {key: stack_models(models, sizes)}
        return self._stacked[key]

    def simulate(
        self, states: list, *, dt: float, steps: int, callback=None, progress: bool = False, check_every: int = 10
    ) -> list:
        """``steps`` steps of ``dt`` (s) from ``states``; ``callback(step, states)`` after each.

        Every ``check_every`` steps and at the last, each body's state is checked
        (:class:`~torchdeform.sim.stability.DivergenceMonitor`): a non-finite or runaway body stops
        the run with :class:`~torchdeform.errors.DivergenceError` naming it.

        Raises:
            ConfigError: a start state that is not finite, or bodies that start inside each other.
        """
        for body, s in zip(self.bodies, states):
            for name, value in (("x", s.x), ("v", s.v)):
                bad = int((~torch.isfinite(value.detach())).sum())
                if bad:
                    raise ConfigError(
                        f"bodies.{body.name}.state.{name}", "a finite start state", got=f"{bad} non-finite values"
                    )
        self.check_apart(states)
        monitors = [DivergenceMonitor(b.model, dt, self.integrator) for b in self.bodies]
        for k in tqdm(range(1, steps + 1), disable=not progress, desc="simulate", unit="step"):
            states = self.step(states, dt)
            if k % check_every == 0 or k == steps:
                self.check(monitors, states, k)
            if callback is not None:
                callback(k, states)
        return states

    def check(self, monitors: list, states: list, step: int) -> None:
        """Raise :class:`~torchdeform.errors.DivergenceError` naming the first body whose state diverged."""
        for body, monitor, s in zip(self.bodies, monitors, states):
            try:
                monitor.check(s, step)
            except DivergenceError as e:
                raise DivergenceError(
                    e.step, f"body {body.name!r}: {e.quantity}", e.value, e.dt, e.safe_dt, cause=e.cause
                ) from None
