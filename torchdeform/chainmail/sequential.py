"""Sequential ChainMail with persistent state.

Gibson's six FIFO lists (one sponsor path per element) and Schill's Enhanced ChainMail (one
priority queue per coordinate, largest violation first, per-link limits). Cost is proportional
to the elements that move, not to the grid.

Link masks (cut links, :func:`torchdeform.topology.unlink`). Per neighbour direction ``k`` a
padded array ``ok_k`` says whether the element ``n`` may be reached from ``n - offset_k``: the
element exists and so does the link. Without a mask every ``ok_k`` is the element flag array
itself, so the queues test exactly what they tested before, at the same cost. Gibson's one path
per element (d, then h, then w) may run through a cut link while a detour exists; with cut links
a Gibson move therefore checks the links of the elements it moved (cost proportional to them)
and, if a limit is left violated, redoes the move in Enhanced ChainMail's order.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import KW_ONLY, dataclass, field

import numpy as np
import torch

from ..errors import ConfigError
from ..sim.grid import Grid
from .limits import (
    _FIXED,
    _FREE,
    _OUTSIDE,
    DIRECTIONS,
    GIBSON_SUCCESSORS,
    METHODS,
    BlockedMoveError,
    Limits,
    _as_links,
    limit_violation,
    link_mask,
)
from .relaxation import relax

__all__ = ["ChainMail", "MoveResult"]


# --------------------------------------------------------------- move results
@dataclass
class MoveResult:
    """What one :meth:`ChainMail.move` did.

    Attributes:
        requested: the displacement asked for, ``(3,)`` metres.
        fraction: the fraction of it carried out (1 unless the move was blocked and scaled).
        blocked: the full move was blocked (by a fixed element or a conflict).
        moved: number of distinct elements that moved (picked elements included).
        checked: number of element checks (queue entries processed).
        passes: one array per propagation pass of the final attempt, each listing the node
            indices ``(i * H + j) * W + k`` processed in that pass, in order; an element appears
            at most once per pass (a pass is one initiator for Gibson, the whole move for
            Enhanced ChainMail).
        moved_nodes: the indices of the elements that moved, sorted.
        attempts: number of propagation attempts (more than 1 when a blocked move was scaled).
    """

    requested: tuple
    _: KW_ONLY
    fraction: float = 1.0
    blocked: bool = False
    moved: int = 0
    checked: int = 0
    passes: list = field(default_factory=list)
    moved_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    attempts: int = 1

    @property
    def max_touches(self) -> int:
        """The most times any element was processed within one pass (1 for a correct ChainMail)."""
        return max((int(np.bincount(p).max()) for p in self.passes if len(p)), default=0)


# ------------------------------------------------------------ sequential ChainMail
class ChainMail:
    """Sequential ChainMail with persistent state.

    Each :meth:`move` costs in proportion to the elements it moves, not to the grid.

    Positions are kept as float64 offsets ``u = x - X`` in flat arrays padded by one layer of
    "outside" elements, so a neighbour is a constant index offset and no bounds test is needed;
    scalar access goes through memoryviews (a torch scalar op costs microseconds).

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid` (its spacing and node mask; the spring
            topology is ignored: ChainMail links the six face neighbours).
        limits: :class:`Limits` (per-axis for ``"gibson"``, per-axis or per-link for ``"enhanced"``).
        fixed: optional bool ``(D, H, W)`` of elements that never move.
        positions: optional start positions ``(1, 3, D, H, W)`` or ``(3, D, H, W)`` (e.g. a
            mass-spring state's ``x``); default the rest positions. They must satisfy the limits.
        method: ``"gibson"`` or ``"enhanced"``.
        links: optional bool ``(3, D, H, W)`` link mask (entry ``[a, i, j, k]``: the link from
            ``(i, j, k)`` along ``+a`` exists); an unlinked pair imposes no limit on each other.
            Default: every link exists (and no cost). See :attr:`links`, :meth:`set_links` and
            :func:`torchdeform.topology.unlink`.

    Examples:
        >>> import torchdeform as td
        >>> g = td.Grid((16, 16, 16), spacing=0.001)
        >>> lim = td.Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
        >>> cm = td.ChainMail(g, lim, fixed=g.face("bottom"))
        >>> r = cm.move([(15, 8, 8)], (0.002, 0.0, 0.0))       # pull the top centre up 2 mm
        >>> r.fraction, r.max_touches, r.moved > 1
        (1.0, 1, True)
        >>> u = cm.displacement()
        >>> u.shape, round(float(u[0, 0, 15, 8, 8]), 6), float(u[0, 0, 0].abs().max())   # base fixed
        (torch.Size([1, 3, 16, 16, 16]), 0.002, 0.0)
    """

    def __init__(self, grid: Grid, limits: Limits, *, fixed=None, positions=None, method: str = "gibson", links=None):
        if not isinstance(grid, Grid):
            raise ConfigError("grid", "a torchdeform.Grid", got=type(grid).__name__)
        if not isinstance(limits, Limits) or limits.grid.shape != grid.shape:
            raise ConfigError("limits", f"a chainmail.Limits for the grid {grid.shape}", got=type(limits).__name__)
        if method not in METHODS:
            raise ConfigError("method", '"gibson" or "enhanced"', got=method)
        if method == "gibson" and not limits.uniform:
            raise ConfigError(
                "method",
                '"enhanced" for per-link (heterogeneous) limits: Gibson\'s six lists need one set of limits per axis',
                got=method,
            )
        if method == "gibson" and grid.node_mask is not None:
            raise ConfigError(
                "method",
                '"enhanced" for a body with a node mask: Gibson\'s one path per element '
                "(d, then h, then w) needs a box",
                got=method,
            )
        self.grid, self.limits, self.method = grid, limits, method
        #: Excess (m) below which an element that cannot move (fixed, or picked earlier in the
        #: same move) is taken to satisfy its limits: rounding of positions on a limit's edge.
        self.tol = 1e-9 * min(grid.spacing)
        D, H, W = grid.shape
        self._pshape = (D + 2, H + 2, W + 2)
        P = math.prod(self._pshape)
        self._off = ((H + 2) * (W + 2), W + 2, 1)
        self._doff = tuple(s * self._off[a] for a, s in DIRECTIONS)

        flag = np.zeros(self._pshape, dtype=np.uint8)
        flag[1:-1, 1:-1, 1:-1] = grid.nodes().numpy().astype(np.uint8) * _FREE
        if fixed is not None:
            fx = torch.as_tensor(fixed, dtype=torch.bool).cpu()
            if tuple(fx.shape) != grid.shape:
                raise ConfigError("fixed", f"a bool mask of shape {grid.shape}", got=tuple(fx.shape))
            inner = flag[1:-1, 1:-1, 1:-1]
            inner[fx.numpy() & (inner > 0)] = _FIXED
        self._flag = flag.reshape(-1)
        self._u = np.zeros((3, P), dtype=np.float64)
        self._stamp = np.zeros(P, dtype=np.int64)
        self._gen = 0
        self._moved = np.zeros(P, dtype=bool)
        self._held = np.zeros(0, dtype=np.int64)
        lo, hi, sh = limits.offset_bounds()
        if limits.uniform:
            self._bounds = tuple((float(lo[a]), float(hi[a]), float(sh[a])) for a in range(3))
            self._links = None
        else:  # per-link arrays, padded like _u
            self._bounds = None
            arrays = np.zeros((3, 3, P), dtype=np.float64)
            for k, t in enumerate((lo, hi, sh)):
                full = t.view(3, 1, 1, 1).expand(3, *grid.shape) if t.dim() == 1 else t
                view = arrays[k].reshape(3, *self._pshape)
                view[:, 1:-1, 1:-1, 1:-1] = full.numpy()
            self._links = arrays
        self._linkmask = None
        self._install_links(links)
        self.set_positions(grid.rest_positions(dtype=torch.float64) if positions is None else positions)
        self._views()

    # ------------------------------------------------------------------ links
    def _install_links(self, links) -> None:
        """Store the link mask and build the per-direction reachability arrays ``_ok``."""
        lk = _as_links(links, self.grid, "cpu")
        if lk is not None and lk.shape[0] != 1:
            raise ConfigError(
                "links", f"a bool (3, D, H, W) link mask with grid {self.grid.shape}", got=tuple(lk.shape)
            )
        if lk is None:
            self._linkmask, self._cut = None, False
            self._okarr = (self._flag,) * 6
        else:
            m = lk[0] & link_mask(self.grid)
            self._linkmask, self._cut = m, bool((m != link_mask(self.grid)).any())
            oks = []
            for _k, (a, sgn) in enumerate(DIRECTIONS):
                lp = np.zeros(self._pshape, dtype=np.uint8)
                lp[1:-1, 1:-1, 1:-1] = m[a].numpy()
                lp = lp.reshape(-1)
                off = self._off[a]
                ok = np.zeros_like(self._flag)
                if sgn > 0:  # n = e + off: the link is stored at e = n - off
                    ok[off:] = self._flag[off:] * lp[:-off]
                else:  # n = e - off: the link is stored at n
                    ok[:] = self._flag * lp
                oks.append(ok)
            self._okarr = tuple(oks)
        self._mok = tuple(memoryview(o) for o in self._okarr)

    @property
    def links(self) -> torch.Tensor:
        """Bool ``(3, D, H, W)``: the links that exist (all of the grid's unless some were cut).

        Entry ``[a, i, j, k]`` is the link from ``(i, j, k)`` to its neighbour along ``+a``
        (False also where that neighbour is outside the grid or the node mask).
        """
        return (link_mask(self.grid) if self._linkmask is None else self._linkmask).clone()

    def set_links(self, links) -> None:
        """Replace the link mask (bool ``(3, D, H, W)``, or ``None`` for every link).

        The current positions must satisfy the limits of the links that exist (always true when
        links are only removed; relinking two elements that drifted apart is refused).

        Example:
            >>> import torchdeform as td
            >>> g = td.Grid((4, 4, 4), spacing=1.0)
            >>> lim = td.Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
            >>> cm = td.ChainMail(g, lim, method="enhanced")
            >>> links = cm.links
            >>> links[0, 1] = False                       # unlink layer 1 from layer 2 (along d)
            >>> cm.set_links(links)
            >>> r = cm.move([(0, 2, 2)], (-3.0, 0.0, 0.0))
            >>> float(cm.displacement()[0, :, 2:].abs().max())   # layers 2 and 3 stay
            0.0
        """
        lk = _as_links(links, self.grid, "cpu")
        worst, excess = limit_violation(self.positions(), self.grid, self.limits, per_link=True, links=lk)
        if float(worst) > 1e-12:
            a, i, j, k = (int(v) for v in np.unravel_index(int(excess[0].flatten().argmax()), excess[0].shape))
            raise ConfigError(
                "links",
                "links whose limits the current positions satisfy; the link from "
                f"node {(i, j, k)} along {'dhw'[a]} exceeds them by {float(worst):.3g} m",
                show_got=False,
            )
        self._install_links(links)

    # ------------------------------------------------------------ state in/out
    def _views(self):
        self._mu = tuple(memoryview(self._u[c]) for c in range(3))
        self._mflag = memoryview(self._flag)
        self._mstamp = memoryview(self._stamp)
        if self._links is not None:
            self._mlinks = tuple(tuple(memoryview(self._links[k, a]) for a in range(3)) for k in range(3))

    def _interior(self, arr: np.ndarray) -> np.ndarray:
        return arr.reshape(arr.shape[:-1] + self._pshape)[..., 1:-1, 1:-1, 1:-1]

    def set_positions(self, positions) -> None:
        """Replace the positions (``(1, 3, D, H, W)`` or ``(3, D, H, W)``); they must satisfy the limits."""
        x = torch.as_tensor(positions).detach().to("cpu", torch.float64)
        x = x[0] if x.dim() == 5 else x
        if tuple(x.shape) != (3,) + self.grid.shape:
            raise ConfigError(
                "positions", f"(1, 3, D, H, W) or (3, D, H, W) with grid {self.grid.shape}", got=tuple(x.shape)
            )
        worst, excess = limit_violation(x, self.grid, self.limits, per_link=True, links=self._linkmask)
        if float(worst) > 1e-12:
            a, i, j, k = (int(v) for v in np.unravel_index(int(excess[0].flatten().argmax()), excess[0].shape))
            raise ConfigError(
                "positions",
                "positions that satisfy the ChainMail limits (repair a mass-spring "
                f"state first); the link from node {(i, j, k)} along {'dhw'[a]} "
                f"exceeds them by {float(worst):.3g} m",
                show_got=False,
            )
        u = (x - self.grid.rest_positions(dtype=torch.float64)[0]) * self.grid.nodes()
        self._interior(self._u)[...] = u.numpy()

    def reset(self) -> None:
        """Back to the rest positions; forgets the moved elements (cut links stay cut)."""
        self._u[...] = 0.0
        self._moved[:] = False
        self._held = np.zeros(0, dtype=np.int64)

    def offsets(self, *, dtype=torch.float32, device=None) -> torch.Tensor:
        """The displacement field ``u = x - X``, ``(1, 3, D, H, W)`` metres (0 outside the node mask)."""
        return torch.from_numpy(self._interior(self._u).copy()).unsqueeze(0).to(dtype=dtype, device=device)

    displacement = offsets

    def positions(self, *, dtype=torch.float64, device=None) -> torch.Tensor:
        """Positions ``x = X + u``, ``(1, 3, D, H, W)``."""
        return self.grid.rest_positions(dtype=dtype, device=device) + self.offsets(dtype=dtype, device=device)

    def state(self, *, dtype=torch.float32, device=None):
        """A :class:`~torchdeform.sim.model.State` (``x``, ``v = 0``) the mass-spring integrators continue from."""
        from ..sim.model import State

        x = self.positions(dtype=dtype, device=device)
        return State(x, torch.zeros_like(x), t=0.0)

    def moved_mask(self) -> torch.Tensor:
        """Bool ``(D, H, W)``: elements moved since construction or :meth:`clear_moved`."""
        return torch.from_numpy(self._interior(self._moved).copy())

    def clear_moved(self) -> None:
        """Forget which elements moved (see :meth:`moved_mask`)."""
        self._moved[:] = False

    @property
    def fixed(self) -> torch.Tensor:
        """Bool ``(D, H, W)`` of fixed elements."""
        return torch.from_numpy(self._interior(self._flag) == _FIXED)

    def _node_index(self, padded) -> np.ndarray:
        """Padded flat indices -> node indices ``(i * H + j) * W + k``."""
        p = np.asarray(padded, dtype=np.int64)
        i, j, k = np.unravel_index(p, self._pshape)
        _D, H, W = self.grid.shape
        return ((i - 1) * H + (j - 1)) * W + (k - 1)

    def _picked(self, nodes) -> list:
        shape = self.grid.shape
        if (torch.is_tensor(nodes) and nodes.dtype == torch.bool) or (
            isinstance(nodes, np.ndarray) and nodes.dtype == bool
        ):
            m = torch.as_tensor(nodes).cpu()
            if tuple(m.shape) != shape:
                raise ConfigError("nodes", f"a bool mask of shape {shape} or a list of [i, j, k]", got=tuple(m.shape))
            idx = [tuple(int(v) for v in r) for r in m.nonzero()]
        else:
            try:
                idx = [tuple(int(v) for v in ijk) for ijk in nodes]
            except (TypeError, ValueError):
                raise ConfigError("nodes", "a list of node indices [i, j, k] or a bool mask", got=nodes) from None
        if not idx:
            raise ConfigError(
                "nodes", "at least one element to move", got=nodes if not torch.is_tensor(nodes) else "[]"
            )
        out = []
        for ijk in idx:
            if len(ijk) != 3 or not all(0 <= v < n for v, n in zip(ijk, shape)):
                raise ConfigError(
                    "nodes", f"element indices inside the grid {shape} (a pull outside the grid)", got=list(ijk)
                )
            p = ((ijk[0] + 1) * self._pshape[1] + ijk[1] + 1) * self._pshape[2] + ijk[2] + 1
            if self._flag[p] == _OUTSIDE:
                raise ConfigError("nodes", "elements inside the body's node mask", got=list(ijk))
            if self._flag[p] == _FIXED:
                raise ConfigError("nodes", "free elements (this one is fixed and cannot be moved)", got=list(ijk))
            out.append(p)
        return list(dict.fromkeys(out))

    # ------------------------------------------------------------------ moving
    def move(self, nodes, displacement, *, on_blocked: str = "scale", bisections: int = 12) -> MoveResult:
        """Move the picked elements rigidly by ``displacement``; ChainMail drags, pushes and shears the rest.

        Args:
            nodes: picked elements: a list of ``(i, j, k)`` or a bool ``(D, H, W)`` mask.
            displacement: ``(dd, dh, dw)`` metres (a pull or a push in any direction).
            on_blocked: what to do when the move would have to move a fixed element:
                ``"scale"`` (default) carry out the largest fraction that can be done (bisection,
                ``bisections`` halvings), ``"error"`` raise :class:`BlockedMoveError` and change nothing.
            bisections: halvings for ``"scale"``.

        Returns:
            :class:`MoveResult`.

        Raises:
            ConfigError: picked elements outside the grid, outside the node mask or fixed; a bad
                displacement or option.
        """
        if on_blocked not in ("scale", "error"):
            raise ConfigError("on_blocked", '"scale" or "error"', got=on_blocked)
        try:
            d = tuple(float(v) for v in (displacement.tolist() if torch.is_tensor(displacement) else displacement))
        except (TypeError, ValueError):
            raise ConfigError("displacement", "three numbers (dd, dh, dw) in metres", got=displacement) from None
        if len(d) != 3 or not all(math.isfinite(v) for v in d):
            raise ConfigError("displacement", "three finite numbers (dd, dh, dw) in metres", got=displacement)
        picked = self._picked(nodes)
        start = [(p, self._u[0, p], self._u[1, p], self._u[2, p]) for p in picked]

        attempts = 1
        ok, log, passes, checked = self._attempt(start, d, 1.0)
        fraction = 1.0
        if not ok:
            self._undo(log)
            if on_blocked == "error":
                raise BlockedMoveError(
                    f"moving {len(picked)} element(s) by {d} m would have to move a fixed element; nothing was moved"
                )
            lo, hi = 0.0, 1.0
            for _ in range(bisections):
                mid = 0.5 * (lo + hi)
                attempts += 1
                good, log, _, _ = self._attempt(start, d, mid)
                self._undo(log)
                lo, hi = (mid, hi) if good else (lo, mid)
            fraction = lo
            attempts += 1
            ok, log, passes, checked = self._attempt(start, d, lo)
            if not ok:  # cannot happen for lo = 0 in a valid state
                self._undo(log)
                raise BlockedMoveError("a scaled move was blocked too; nothing was moved")
        moved = np.unique(np.asarray(log[0::4], dtype=np.int64))
        self._moved[moved] = True
        self._held = np.asarray(picked, dtype=np.int64)
        return MoveResult(
            requested=d,
            fraction=fraction,
            blocked=fraction < 1.0,
            moved=len(moved),
            checked=checked,
            passes=[self._node_index(p) for p in passes],
            moved_nodes=np.sort(self._node_index(moved)),
            attempts=attempts,
        )

    def _undo(self, log: list) -> None:
        u = self._u
        for n in range(len(log) - 4, -1, -4):
            p = log[n]
            u[0, p], u[1, p], u[2, p] = log[n + 1], log[n + 2], log[n + 3]

    def _attempt(self, start, d, scale):
        """One try at moving the picked elements by ``scale * d``.

        Returns ``(ok, undo log, processed indices per pass, checks)``. The log is flat: index,
        old u.
        """
        log, passes = [], []
        ux, uy, uz = self._mu
        targets = [(p, x0 + scale * d[0], y0 + scale * d[1], z0 + scale * d[2]) for p, x0, y0, z0 in start]
        self._gen += 1
        if self.method == "enhanced":
            ok = self._enhanced(targets, [scale * v for v in d], log, passes)
            return ok, log, passes, sum(len(p) for p in passes)
        pinned = set()
        checked = 0
        for p, tx, ty, tz in targets:
            log += (p, ux[p], uy[p], uz[p])
            ux[p], uy[p], uz[p] = tx, ty, tz
            pinned.add(p)
            touched = []
            ok = self._gibson(p, pinned, log, touched)
            passes.append(touched)
            checked += len(touched)
            if not ok:
                return False, log, passes, checked
        if self._cut and not self._links_hold(np.unique(np.asarray(log[0::4], dtype=np.int64))):
            self._undo(log)  # a sponsor path ran through a cut: redo in order
            log, passes = [], []
            self._gen += 1
            ok = self._enhanced(targets, [scale * v for v in d], log, passes)
            return ok, log, passes, checked + sum(len(p) for p in passes)
        return True, log, passes, checked

    def _links_hold(self, nodes: np.ndarray) -> bool:
        """Every existing link of the (padded) elements ``nodes`` is within its (uniform) limits."""
        u = self._u
        for k, (a, sgn) in enumerate(DIRECTIONS):
            n = nodes + self._doff[k]
            sel = self._okarr[k][n] != 0
            e, n = nodes[sel], n[sel]
            if not len(e):
                continue
            diff = u[:, n] - u[:, e]
            lo, hi, sh = self._bounds[a]
            la, ha = (lo, hi) if sgn > 0 else (-hi, -lo)
            excess = np.maximum(la - diff[a], diff[a] - ha)
            for b in range(3):
                if b != a:
                    excess = np.maximum(excess, np.abs(diff[b]) - sh)
            if float(excess.max()) > self.tol:
                return False
        return True

    def _gibson(self, e0: int, pinned: set, log: list, touched: list) -> bool:
        """Gibson's propagation from the initiator ``e0`` (already at its target)."""
        ux, uy, uz = self._mu
        flag = self._mflag
        oks = self._mok
        doff = self._doff
        queues = [[], [], [], [], [], []]
        for k in range(6):
            n = e0 + doff[k]
            if oks[k][n]:
                queues[k].append(n)
        # per list: offset of the sponsor and the offset-difference box of each coordinate
        boxes = []
        for k, (a, s) in enumerate(DIRECTIONS):
            lo, hi, sh = self._bounds[a]
            b = [(-sh, sh)] * 3
            b[a] = (lo, hi) if s > 0 else (-hi, -lo)
            boxes.append(
                (
                    doff[k],
                    b[0][0],
                    b[0][1],
                    b[1][0],
                    b[1][1],
                    b[2][0],
                    b[2][1],
                    [(queues[q], doff[q], oks[q]) for q in GIBSON_SUCCESSORS[k]],
                )
            )
        append = touched.append
        tol = self.tol
        busy = True
        while busy:
            busy = False
            for k in range(6):
                q = queues[k]
                if not q:
                    continue
                busy = True
                off, l0, h0, l1, h1, l2, h2, succ = boxes[k]
                for e in q:  # the list grows while it is served (same direction)
                    append(e)
                    s = e - off
                    changed = False
                    v = ux[e]
                    c = ux[s]
                    if v < c + l0:
                        v, changed = c + l0, True
                    elif v > c + h0:
                        v, changed = c + h0, True
                    w = uy[e]
                    c = uy[s]
                    if w < c + l1:
                        w, changed = c + l1, True
                    elif w > c + h1:
                        w, changed = c + h1, True
                    z = uz[e]
                    c = uz[s]
                    if z < c + l2:
                        z, changed = c + l2, True
                    elif z > c + h2:
                        z, changed = c + h2, True
                    if changed:
                        if flag[e] != _FREE or e in pinned:
                            if max(abs(v - ux[e]), abs(w - uy[e]), abs(z - uz[e])) > tol:
                                return False
                            continue  # off by rounding only: it stays, as it may
                        log += (e, ux[e], uy[e], uz[e])
                        ux[e] = v
                        uy[e] = w
                        uz[e] = z
                        for qq, o, ok in succ:
                            n = e + o
                            if ok[n]:
                                qq.append(n)
                q.clear()
        return True

    def _feed_table(self, c: int, sign: int) -> list:
        """The feeding rules of coordinate ``c`` pulled (``sign > 0``) or pushed (``sign < 0``).

        Per neighbour direction k of a final element e, ``(offset, limit array or None,
        constant, factor, link at e, reachable)`` such that the neighbour n = e + offset must satisfy
        ``u_n[c] >= u_e[c] + factor * limit`` (pull) or ``<=`` (push), the limit being that of the
        link (stored at e when ``link at e``, else at n); ``reachable[n]`` is 0 when n does not
        exist or the link is cut.
        """
        table = []
        for k, (a, s) in enumerate(DIRECTIONS):
            if c == a:
                which, factor = ((0, 1.0) if s > 0 else (1, -1.0)) if sign > 0 else ((1, 1.0) if s > 0 else (0, -1.0))
            else:
                which, factor = 2, (-1.0 if sign > 0 else 1.0)
            arr = None if self._links is None else self._mlinks[which][a]
            const = self._bounds[a][which] if self._links is None else 0.0
            table.append((self._doff[k], arr, const, factor, s > 0, self._mok[k]))
        return table

    def _enhanced(self, targets, delta, log: list, passes: list) -> bool:
        """Enhanced ChainMail: place the picked elements, then propagate each moving coordinate.

        Every coordinate that moves is propagated with one priority queue, largest violation
        first.

        The limits bound differences of one coordinate at a time, so the three coordinates are
        three independent systems; within one, a violation never grows along a propagation
        (the old positions satisfied the limits), so largest-violation-first is a label-setting
        order: an element popped is final, moved exactly onto the bound of its worst-violated
        link, and never touched again in that pass. Every limit holds afterwards; a fixed element
        that would have to move means the move is infeasible (blocked).
        """
        U = self._mu
        flag, stamp = self._mflag, self._mstamp
        push, pop = heapq.heappush, heapq.heappop
        tol = self.tol
        for p, *t in targets:
            log += (p, U[0][p], U[1][p], U[2][p])
            U[0][p], U[1][p], U[2][p] = t
        picks = [p for p, *_ in targets]
        for c in range(3):
            if delta[c] == 0.0:
                continue
            sign = 1 if delta[c] > 0 else -1
            self._gen += 1
            gen = self._gen
            for p in picks:
                stamp[p] = gen
            uc = U[c]
            table = self._feed_table(c, sign)
            processed = []
            passes.append(processed)
            heap = []
            todo = picks
            while True:
                for e in todo:  # queue e's violated, non-final neighbours
                    ue = uc[e]
                    for off, arr, const, factor, at_e, ok in table:
                        n = e + off
                        if not ok[n] or stamp[n] == gen:
                            continue
                        bound = ue + factor * (const if arr is None else arr[e if at_e else n])
                        v = bound - uc[n] if sign > 0 else uc[n] - bound
                        if v > 0.0:
                            if flag[n] == _FIXED:
                                if v > tol:
                                    return False
                                continue  # off by rounding only
                            push(heap, (-v, n, bound))
                e = -1
                while heap:
                    _, e, bound = pop(heap)
                    if stamp[e] != gen:
                        break
                    e = -1  # a stale entry: already final
                if e < 0:
                    break
                stamp[e] = gen
                processed.append(e)
                log += (e, U[0][e], U[1][e], U[2][e])
                uc[e] = bound
                todo = (e,)
        return True

    # --------------------------------------------------------------- relaxing
    def relax(
        self, *, steps: int = 1, mode: str = "centroid", only_moved: bool = False, omega: float = 1.0, hold=None
    ) -> list:
        """Elastic relaxation of the current deformation (see :func:`relax`).

        Fixed elements and the elements picked by the last :meth:`move` stay where they are
        (``hold``: a bool ``(D, H, W)`` mask to hold instead); with ``only_moved`` only the
        elements ChainMail moved since :meth:`clear_moved` are relaxed. Cut links (:attr:`links`)
        are left out: the two sides of a cut relax independently.

        Returns:
            the energy (:func:`relax_energy`) before and after every step, ``steps + 1`` floats.
        """
        free = (self._interior(self._flag) == _FREE).copy()
        if hold is None:
            held = np.zeros(self._flag.shape, dtype=bool)
            held[self._held] = True
            free &= ~self._interior(held)
        else:
            free &= ~torch.as_tensor(hold, dtype=torch.bool).cpu().numpy()
        if only_moved:
            free &= self._interior(self._moved)
        u = self.offsets(dtype=torch.float64)
        u, energies = relax(
            u,
            self.grid,
            self.limits,
            steps=steps,
            mode=mode,
            free=torch.from_numpy(free),
            omega=omega,
            offsets=True,
            links=self._linkmask,
        )
        self._interior(self._u)[...] = u[0].numpy()
        return energies
