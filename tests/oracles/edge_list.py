"""Independent edge-list oracle for the spring tests.

Nothing here calls the spring code of torchdeform: springs are listed one by one from the
node coordinates (every node, every neighbour offset of the topology), and forces, energies
and stiffness matrices are computed in plain numpy. The tests import these helpers with
``from tests.oracles.edge_list import EdgeList, OFFSETS``.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

#: Full neighbour offsets (both signs) of each topology, written out independently of
#: ``torchdeform.sim.grid``: 6 = faces, 14 = faces + corners, 18 = faces + edges, 26 = all.
_ALL = [o for o in itertools.product((-1, 0, 1), repeat=3) if o != (0, 0, 0)]
OFFSETS = {
    6: [o for o in _ALL if sum(map(abs, o)) == 1],
    14: [o for o in _ALL if sum(map(abs, o)) in (1, 3)],
    18: [o for o in _ALL if sum(map(abs, o)) in (1, 2)],
    26: _ALL,
}


class EdgeList:
    """Every spring of a grid, listed explicitly.

    Args:
        shape: ``(D, H, W)``; spacing: three spacings; topology: 6, 14, 18 or 26;
        node_mask: optional bool array ``(D, H, W)``.

    Attributes:
        nodes: list of ``(i, j, k)`` of existing nodes (index ``a`` into this list);
        index: dict ``(i, j, k) -> a``;
        springs: list of ``(a, b, offset)`` with ``a < b`` (each unordered pair once);
        l0: rest length of each spring, from the rest coordinates.
        X: rest positions ``(N, 3)``.
    """

    def __init__(self, shape, spacing, topology, node_mask=None):
        self.shape = tuple(shape)
        self.spacing = np.asarray(spacing, dtype=np.float64)
        if node_mask is None:
            node_mask = np.ones(self.shape, dtype=bool)
        self.node_mask = np.asarray(node_mask, dtype=bool)
        self.nodes = [ijk for ijk in itertools.product(*map(range, self.shape)) if self.node_mask[ijk]]
        self.index = {ijk: a for a, ijk in enumerate(self.nodes)}
        self.X = np.array([np.array(ijk) * self.spacing for ijk in self.nodes], dtype=np.float64)
        springs = []
        for ijk in self.nodes:  # loop over every node ...
            a = self.index[ijk]
            for off in OFFSETS[topology]:  # ... and every neighbour offset
                nb = tuple(p + o for p, o in zip(ijk, off))
                if nb in self.index and self.index[nb] > a:  # list each unordered pair once
                    springs.append((a, self.index[nb], off))
        self.springs = springs
        self.a = np.array([s[0] for s in springs], dtype=np.int64)
        self.b = np.array([s[1] for s in springs], dtype=np.int64)
        self.l0 = np.linalg.norm(self.X[self.b] - self.X[self.a], axis=1)

    @property
    def N(self):
        return len(self.nodes)

    # ---------------------------------------------------------- conversions
    def from_field(self, f):
        """``(3, D, H, W)`` (numpy or torch, batch squeezed) -> ``(N, 3)`` over listed nodes."""
        f = f.detach().cpu().numpy() if torch.is_tensor(f) else np.asarray(f)
        return np.stack([f[(slice(None),) + ijk] for ijk in self.nodes])

    def to_field(self, y):
        """``(N, 3)`` -> ``(3, D, H, W)`` numpy, zero at nodes not in the list."""
        out = np.zeros((3,) + self.shape)
        for a, ijk in enumerate(self.nodes):
            out[(slice(None),) + ijk] = y[a]
        return out

    def locate(self, directions):
        """For each listed spring, ``(s, p, q)``: the half-direction index ``s`` in
        ``directions`` with ``q - p = directions[s]`` and the two node triples ``p``, ``q``."""
        out = []
        for a, b, _ in self.springs:
            pa, pb = self.nodes[a], self.nodes[b]
            for s, d in enumerate(directions):
                if tuple(np.subtract(pb, pa)) == tuple(d):
                    out.append((s, pa, pb))
                    break
                if tuple(np.subtract(pa, pb)) == tuple(d):
                    out.append((s, pb, pa))
                    break
            else:  # pragma: no cover
                raise AssertionError("spring direction not in the stencil")
        return out

    def slot_pairs(self, directions, slots):
        """The springs ``(a, b)``, ``a < b``, of bool slots ``(S, D, H, W)`` stored per half-direction.

        ``directions``: the ``S`` offsets ``(dd, dh, dw)`` of the slots (slot ``(s, i, j, k)`` is
        the spring from node ``(i, j, k)`` to ``(i, j, k) + directions[s]``).
        """
        out = set()
        for s, d in enumerate(directions):
            for ijk in zip(*np.nonzero(np.asarray(slots[s]))):
                a = self.index[tuple(int(i) for i in ijk)]
                b = self.index[tuple(int(i) + c for i, c in zip(ijk, d))]
                out.add((min(a, b), max(a, b)))
        return out

    def damping_matrix(self, x, c=1.0, projected=True):
        """``C = -dF/dv`` ``(3N, 3N)``: blocks ``c n n^T`` (projected) or ``c I``."""
        c = np.broadcast_to(np.asarray(c, dtype=np.float64), (len(self.springs),))
        C = np.zeros((3 * self.N, 3 * self.N))
        for s, (a, b, _) in enumerate(self.springs):
            d = x[a] - x[b]
            n = d / np.sqrt(d @ d)
            blk = c[s] * (np.outer(n, n) if projected else np.eye(3))
            for p, q, sg in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                C[3 * p : 3 * p + 3, 3 * q : 3 * q + 3] += sg * blk
        return C

    def per_spring_tensor(self, values, directions):
        """Store per-spring ``values`` (one per listed spring) in torchdeform's ``(S, D, H, W)``
        layout for the half-directions ``directions``: the spring between ``p`` and ``p + d``
        goes to ``[s, p]``. Only the layout comes from the library; the pairing is checked by
        identity of the two endpoints."""
        out = np.zeros((len(directions),) + self.shape)
        for (a, b, _), val in zip(self.springs, values):
            pa, pb = np.array(self.nodes[a]), np.array(self.nodes[b])
            for s, d in enumerate(directions):
                if tuple(pb - pa) == tuple(d):
                    out[(s,) + tuple(pa)] = val
                    break
                if tuple(pa - pb) == tuple(d):
                    out[(s,) + tuple(pb)] = val
                    break
            else:  # pragma: no cover
                raise AssertionError("spring direction not in the stencil")
        return out

    # -------------------------------------------------------------- physics
    def forces(self, x, v=None, k=1.0, c=None, projected=True):
        """Spring forces ``(N, 3)`` at positions ``x`` ``(N, 3)`` (explicit loop over springs).

        On endpoint ``a`` of a spring ``(a, b)``, with ``n = (x_a - x_b) / l``: Hookean
        ``-k (l - l0) n`` (pulls ``a`` towards ``b`` when stretched), damping
        ``-c ((v_a - v_b) . n) n`` (projected) or ``-c (v_a - v_b)`` (unprojected); the
        opposite force acts on ``b``.
        """
        k = np.broadcast_to(np.asarray(k, dtype=np.float64), (len(self.springs),))
        cc = None if c is None else np.broadcast_to(np.asarray(c, dtype=np.float64), (len(self.springs),))
        F = np.zeros_like(x)
        for s, (a, b, _) in enumerate(self.springs):
            d = x[a] - x[b]
            l = np.sqrt(d @ d)
            n = d / l
            f = -k[s] * (l - self.l0[s]) * n
            if cc is not None:
                dv = v[a] - v[b]
                f = f - cc[s] * ((dv @ n) * n if projected else dv)
            F[a] += f
            F[b] -= f
        return F

    def forces_vec(self, x, k=1.0, v=None, c=None, projected=True):
        """Vectorised spring forces ``(N, 3)`` (same formulas as :meth:`forces`, for ODE
        references)."""
        d = x[self.a] - x[self.b]
        l = np.linalg.norm(d, axis=1)
        n = d / l[:, None]
        f = -(np.asarray(k) * (l - self.l0))[:, None] * n
        if c is not None:
            dv = v[self.a] - v[self.b]
            c = np.broadcast_to(np.asarray(c, dtype=np.float64), l.shape)[:, None]
            f = f - c * ((dv * n).sum(1, keepdims=True) * n if projected else dv)
        F = np.zeros_like(x)
        np.add.at(F, self.a, f)
        np.add.at(F, self.b, -f)
        return F

    def law_forces(self, x, tension):
        """Spring forces ``(N, 3)`` of a nonlinear law (explicit loop over springs).

        ``tension(l, l0, s)`` is the force magnitude of spring ``s`` at length ``l`` (positive when
        stretched); on endpoint ``a`` the force is ``-tension n`` with ``n = (x_a - x_b) / l``.
        """
        F = np.zeros_like(x)
        for s, (a, b, _) in enumerate(self.springs):
            d = x[a] - x[b]
            l = np.sqrt(d @ d)
            f = -tension(l, self.l0[s], s) * d / l
            F[a] += f
            F[b] -= f
        return F

    def law_hessian(self, x, tension, slope, clamp=False):
        """Hessian ``(3N, 3N)`` of a nonlinear law's energy: blocks ``(f / l)(I - n n^T) + f' n n^T``.

        ``tension(l, l0, s)`` and ``slope(l, l0, s)`` (its derivative in ``l``) per spring; with
        ``clamp`` the factor ``f / l`` is replaced by ``max(f / l, 0)``.
        """
        H = np.zeros((3 * self.N, 3 * self.N))
        I = np.eye(3)
        for s, (a, b, _) in enumerate(self.springs):
            d = x[a] - x[b]
            l = np.sqrt(d @ d)
            n = d / l
            t = tension(l, self.l0[s], s) / l
            t = max(t, 0.0) if clamp else t
            blk = t * (I - np.outer(n, n)) + slope(l, self.l0[s], s) * np.outer(n, n)
            for p, q, sg in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                H[3 * p : 3 * p + 3, 3 * q : 3 * q + 3] += sg * blk
        return H

    def energy(self, x, k=1.0):
        d = x[self.a] - x[self.b]
        l = np.linalg.norm(d, axis=1)
        return float(np.sum(0.5 * np.asarray(k) * (l - self.l0) ** 2))

    def hessian(self, x, k=1.0, clamp=False):
        """Exact Hessian of the elastic energy ``(3N, 3N)``, assembled from ``3 x 3`` spring
        blocks ``k [(1 - l0/l)(I - n n^T) + n n^T]``; with ``clamp`` the factor ``1 - l0/l``
        is replaced by ``max(1 - l0/l, 0)``. Hooke's law in :meth:`law_hessian`."""
        k = np.broadcast_to(np.asarray(k, dtype=np.float64), (len(self.springs),))
        return self.law_hessian(x, lambda l, l0, s: k[s] * (l - l0), lambda l, l0, s: k[s], clamp)
