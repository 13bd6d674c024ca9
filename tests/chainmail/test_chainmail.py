"""ChainMail, Enhanced ChainMail, tensor ChainMail and relaxation, against independent oracles.

Oracles written here, sharing no code with ``torchdeform.chainmail``:

* :func:`reference_move`: the least-motion solution of the limits, coordinate by coordinate, by
  a plain Bellman-Ford loop over the grid's links (an element must come within every link's
  limits of the picked elements' targets; everything else stays);
* :func:`plain_violation`: the limits checked link by link in Python loops;
* a single chain (1-D grid) pulled against a fixed end, solved by hand;
* :func:`whole_grid_sweeps`: the tensor version's Jacobi sponsor-front sweeps done the plain way,
  in numpy over the whole grid every sweep (and its depth by a breadth-first search in Python),
  the reference of the active-box sweeps of :func:`tensor_chainmail`.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from tests.oracles.chainmail_moves import least_motion
from torchdeform.chainmail import (
    BlockedMoveError,
    ChainMail,
    Limits,
    crease_measure,
    limit_violation,
    link_mask,
    relax,
    relax_energy,
    tensor_chainmail,
    tissue_limits,
)
from torchdeform.errors import ConfigError
from torchdeform.topology import Blade, unlink


# ------------------------------------------------------------------ independent oracles
def _links(shape):
    """Every link of a box grid as (node, neighbour, axis), neighbour = node + e_axis."""
    D, H, W = shape
    for i in range(D):
        for j in range(H):
            for k in range(W):
                for a in range(3):
                    q = [i, j, k]
                    q[a] += 1
                    if q[a] < shape[a]:
                        yield (i, j, k), tuple(q), a


def plain_violation(x, mn, mx, sh):
    """Largest excess over all links, loops only. ``x`` (3, D, H, W); limits per link (3, D, H, W)."""
    worst = 0.0
    for p, q, a in _links(x.shape[1:]):
        d = [x[c][q] - x[c][p] for c in range(3)]
        worst = max(worst, mn[a][p] - d[a], d[a] - mx[a][p], *[abs(d[c]) - sh[a][p] for c in range(3) if c != a])
    return worst


def reference_move(x, mn, mx, sh, picks, delta):
    """The positions after moving ``picks`` by ``delta`` (Bellman-Ford per coordinate, all links).

    A link along axis ``a`` allows ``[min, max]`` of ``x_q - x_p`` along ``a`` and the shear
    ``[-sh, sh]`` across it, per link."""

    def bounds(p, a, c):
        return (mn[a][p], mx[a][p]) if c == a else (-sh[a][p], sh[a][p])

    return least_motion(x, x.shape[1:], list(_links(x.shape[1:])), bounds, picks, delta)


def _side(a, part):
    """Index of the first (``part`` 0) or second (1) endpoints of the links along axis ``a``."""
    idx = [slice(None)] * 3
    idx[a] = slice(0, -1) if part == 0 else slice(1, None)
    return (slice(None), *idx)


def whole_grid_sweeps(x, grid, lim, pick, d, fixed=None, links=None):
    """Jacobi sponsor-front sweeps over the whole grid, numpy; returns what :class:`SweepResult` holds.

    ``x`` ``(B, 3, D, H, W)``, ``pick``/``fixed`` ``(B, D, H, W)``, ``d`` ``(B, 3)``, ``links``
    ``(B, 3, D, H, W)`` or None. Each sweep every free element takes the max (pull) or min (push)
    of its offset and the bounds its moved, linked face neighbours set, all from the previous
    sweep; until nothing changes. Depth: a breadth-first search through nodes and links.
    """
    B, shape = x.shape[0], grid.shape
    X = grid.rest_positions(dtype=F64).numpy()
    h = np.array(grid.spacing).reshape(3, 1, 1, 1)
    mn, mx, sh = (t.numpy() for t in lim.per_link())
    lo_l, hi_l = mn - h, mx - h  # bounds on u_q - u_p along the link
    nodes = grid.nodes().numpy()
    lk = np.ones((B, 3) + shape, bool) if links is None else np.broadcast_to(links.numpy(), (B, 3) + shape)
    pick = pick.numpy() & nodes
    fix = np.zeros_like(pick) if fixed is None else fixed.numpy() & nodes
    d = d.numpy()
    u = x.numpy() - X
    u = np.where(pick[:, None], u + d[:, :, None, None, None], u)
    moved, free = pick.copy(), nodes & ~pick & ~fix
    limit = 2 * sum(shape) if links is None else max(2 * sum(shape), int(nodes.sum()))
    sweeps = 0
    for _ in range(limit):
        lo = np.full(u.shape, -np.inf)
        hi = np.full(u.shape, np.inf)
        for a in range(3):
            if shape[a] < 2:
                continue
            p, q = _side(a, 0), _side(a, 1)
            link = lk[:, a][p]
            for c in range(3):
                l_, h_ = (lo_l[a][p[1:]], hi_l[a][p[1:]]) if c == a else (-sh[a][p[1:]], sh[a][p[1:]])
                up, uq = u[:, c][p], u[:, c][q]
                ok_p, ok_q = moved[p] & link, moved[q] & link  # p bounds q, q bounds p
                lo[:, c][q] = np.maximum(lo[:, c][q], np.where(ok_p, up + l_, -np.inf))
                hi[:, c][q] = np.minimum(hi[:, c][q], np.where(ok_p, up + h_, np.inf))
                lo[:, c][p] = np.maximum(lo[:, c][p], np.where(ok_q, uq - h_, -np.inf))
                hi[:, c][p] = np.minimum(hi[:, c][p], np.where(ok_q, uq - l_, np.inf))
        s = np.sign(d)[:, :, None, None, None]
        step = np.where(s > 0, np.maximum(u, lo), np.where(s < 0, np.minimum(u, hi), u))
        new = np.where(free[:, None], step, u)
        changed = (new != u).any(1)
        if not changed.any():
            break
        sweeps += 1
        moved |= changed
        u = new
    depth = []
    for b in range(B):  # breadth-first search, plain Python
        dist = {tuple(int(v) for v in ijk): 0 for ijk in np.argwhere(pick[b])}
        front = list(dist)
        while front:
            nxt = []
            for e in front:
                for a in range(3):
                    for step_ in (1, -1):
                        f = list(e)
                        f[a] += step_
                        f = tuple(f)
                        if not 0 <= f[a] < shape[a] or not nodes[f] or f in dist:
                            continue
                        if not lk[b, a][e if step_ > 0 else f]:
                            continue
                        dist[f] = dist[e] + 1
                        nxt.append(f)
            front = nxt
        depth.append(max(dist.get(tuple(int(v) for v in ijk), 0) for ijk in np.argwhere(moved[b])))
    return torch.from_numpy(X + u), torch.from_numpy(moved), sweeps, depth


def _np_limits(lim):
    return tuple(t.numpy() for t in lim.per_link())


def _random_moves(rng, shape, count, most=3, scale=1.5):
    out = []
    for _ in range(count):
        base = np.array([rng.integers(0, n) for n in shape])
        picks = {
            tuple(int(v) for v in np.minimum(base + rng.integers(0, 2, 3), np.array(shape) - 1))
            for _ in range(int(rng.integers(1, most + 1)))
        }
        out.append((sorted(picks), rng.normal(size=3) * scale))
    return out


def _hetero_limits(grid, rng):
    comp = torch.tensor(rng.uniform(0.6, 0.95, grid.shape))
    st = torch.tensor(rng.uniform(1.05, 1.4, grid.shape))
    sh = torch.tensor(rng.uniform(0.05, 0.3, grid.shape))
    return Limits.from_material(grid, compression=comp, stretch=st, shear=sh)


GRID = td.Grid((6, 5, 4), spacing=(1.0, 0.9, 1.1))


# ------------------------------------------------------------------ sequential versions
@pytest.mark.parametrize("method", ["gibson", "enhanced"])
def test_sequential_matches_reference_homogeneous(method):
    rng = np.random.default_rng(0)
    lim = Limits.from_material(GRID, compression=0.8, stretch=1.2, shear=0.15)
    mn, mx, sh = _np_limits(lim)
    for _trial in range(4):
        cm = ChainMail(GRID, lim, method=method)
        for picks, d in _random_moves(rng, GRID.shape, 3):
            before = cm.positions()[0].numpy()
            r = cm.move(picks, d)
            after = cm.positions()[0].numpy()
            assert not r.blocked and r.fraction == 1.0
            np.testing.assert_allclose(after, reference_move(before, mn, mx, sh, picks, d), rtol=0, atol=1e-12)
            assert plain_violation(after, mn, mx, sh) <= 1e-12
            assert float(limit_violation(cm.positions(), GRID, lim)[0]) <= 1e-12
            assert r.max_touches == 1  # each element at most once per pass
            for p in r.passes:
                assert np.bincount(p, minlength=1).max() <= 1
            moved = np.flatnonzero(np.abs(after - before).max(0).reshape(-1) > 0)
            assert set(moved) <= set(r.moved_nodes.tolist())
            for p in picks:  # picked elements move rigidly
                np.testing.assert_allclose(after[:, p[0], p[1], p[2]] - before[:, p[0], p[1], p[2]], d, atol=1e-12)


def test_gibson_single_pull_one_pass_touches_each_element_once():
    g = td.Grid((12, 12, 12), spacing=1.0)
    cm = ChainMail(g, Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2))
    r = cm.move([(6, 6, 6)], (2.0, -1.0, 0.5))
    assert len(r.passes) == 1 and r.checked == len(r.passes[0])
    assert np.bincount(r.passes[0]).max() == 1
    assert r.moved > 100 and r.checked < 6 * r.moved  # only the moved region and its rim


def test_enhanced_matches_reference_heterogeneous():
    rng = np.random.default_rng(1)
    lim = _hetero_limits(GRID, rng)
    assert not lim.uniform
    mn, mx, sh = _np_limits(lim)
    for _trial in range(3):
        cm = ChainMail(GRID, lim, method="enhanced")
        for picks, d in _random_moves(rng, GRID.shape, 3):
            before = cm.positions()[0].numpy()
            r = cm.move(picks, d)
            after = cm.positions()[0].numpy()
            assert r.fraction == 1.0 and r.max_touches == 1
            np.testing.assert_allclose(after, reference_move(before, mn, mx, sh, picks, d), rtol=0, atol=1e-12)
            assert plain_violation(after, mn, mx, sh) <= 1e-12


def test_single_chain_analytic_and_blocked_by_fixed_end():
    # a chain of 11 elements 1 m apart, stretch <= 1.2 m per link, its first element fixed
    g = td.Grid((11, 1, 1), spacing=1.0)
    lim = Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
    fixed = torch.zeros(g.shape, dtype=torch.bool)
    fixed[0] = True
    for method in ("gibson", "enhanced"):
        cm = ChainMail(g, lim, fixed=fixed, method=method)
        r = cm.move([(10, 0, 0)], (1.1, 0.3, 0.0))
        u = cm.displacement(dtype=F64)[0, 0, :, 0, 0].numpy()
        # element 10 - k follows by max(0, 1.1 - 0.2 k) along d; sideways by max(0, 0.3 - 0.2 k)
        k = np.arange(10, -1, -1)
        np.testing.assert_allclose(u, np.maximum(0, 1.1 - 0.2 * k), atol=1e-12)
        np.testing.assert_allclose(
            cm.displacement(dtype=F64)[0, 1, :, 0, 0].numpy(), np.maximum(0, 0.3 - 0.2 * k), atol=1e-12
        )
        assert r.moved == 6 and not r.blocked
        # 3 m more needs 4.1 m of stretch in all, the chain has 10 * 0.2 = 2 m: 0.9 / 3 is carried out
        r = cm.move([(10, 0, 0)], (3.0, 0.0, 0.0))
        assert r.blocked and r.fraction == pytest.approx(0.3, abs=2**-11)
        assert float(cm.displacement(dtype=F64)[0, 0, 0, 0, 0]) == 0.0  # the fixed end stays
        assert float(limit_violation(cm.positions(), g, lim)[0]) <= 1e-12
        before = cm.positions()
        with pytest.raises(BlockedMoveError):
            cm.move([(10, 0, 0)], (5.0, 0.0, 0.0), on_blocked="error")
        assert torch.equal(cm.positions(), before)  # nothing moved


def test_limits_hold_after_every_move_with_fixed_faces_and_node_mask():
    rng = np.random.default_rng(2)
    l_mask = torch.ones(7, 6, 6, dtype=torch.bool)
    l_mask[4:, :3, :3] = False  # an L-shaped body
    l_body = td.Grid((7, 6, 6), spacing=0.01, node_mask=l_mask)
    box = td.Grid(l_body.shape, spacing=0.01)
    for method, g, mask in (
        ("gibson", box, torch.ones_like(l_mask)),
        ("enhanced", box, torch.ones_like(l_mask)),
        ("enhanced", l_body, l_mask),
    ):
        lim = Limits.from_material(g, compression=0.85, stretch=1.15, shear=0.1)
        fixed = g.face("bottom")
        cm = ChainMail(g, lim, fixed=fixed, method=method)
        inside = [tuple(int(v) for v in ijk) for ijk in (mask & ~fixed).nonzero()]
        for _step in range(8):
            picks = [inside[int(rng.integers(len(inside)))]]
            before = cm.positions()
            r = cm.move(picks, rng.normal(size=3) * 0.02)
            after = cm.positions()
            assert float(limit_violation(after, g, lim)[0]) <= 1e-12
            assert torch.equal(after[0][:, fixed], before[0][:, fixed])  # fixed elements stay
            assert not cm.displacement(dtype=F64)[0][:, ~mask].any()  # outside the body: nothing
            assert 0.0 <= r.fraction <= 1.0


def test_checker_agrees_with_plain_loops():
    rng = np.random.default_rng(3)
    lim = _hetero_limits(GRID, rng)
    mn, mx, sh = _np_limits(lim)
    X = GRID.rest_positions(dtype=F64)
    for scale in (0.0, 0.05, 0.3):
        x = X + scale * torch.tensor(rng.normal(size=X.shape))
        worst, per_link = limit_violation(x, GRID, lim, per_link=True)
        assert float(worst[0]) == pytest.approx(max(0.0, plain_violation(x[0].numpy(), mn, mx, sh)), abs=1e-14)
        assert per_link.shape == (1, 3) + GRID.shape
    assert float(limit_violation(X, GRID, lim)[0]) == 0.0


def test_locality_same_work_on_small_and_large_grids():
    counts = []
    for n in (32, 64):
        g = td.Grid((n, n, n), spacing=0.001)
        cm = ChainMail(g, Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2))
        r = cm.move([(n // 2, n // 2, n // 2)], (0.002, 0.001, 0.0))
        counts.append((r.moved, r.checked))
    assert counts[0] == counts[1] and 1000 <= counts[0][0] <= 2000  # a ~1,300-element pull, same work


# ------------------------------------------------------------------ tensor version
def test_tensor_chainmail_matches_reference_batched(device):
    rng = np.random.default_rng(4)
    lim = _hetero_limits(GRID, rng)
    mn, mx, sh = _np_limits(lim)
    X = GRID.rest_positions(dtype=F64)
    picks = [[(2, 2, 1)], [(5, 0, 3), (5, 1, 3)], [(0, 4, 0)]]
    d = torch.tensor([[1.5, -0.5, 0.3], [-2.0, 0.0, 1.0], [0.5, 1.0, -1.0]], dtype=F64)
    mask = torch.zeros((3,) + GRID.shape, dtype=torch.bool)
    for b, ps in enumerate(picks):
        for p in ps:
            mask[(b,) + p] = True
    r = tensor_chainmail(X.repeat(3, 1, 1, 1, 1).to(device), GRID, lim, mask.to(device), d.to(device))
    assert r.positions.device == device
    for b in range(3):
        ref = reference_move(X[0].numpy(), mn, mx, sh, picks[b], d[b].numpy())
        np.testing.assert_allclose(r.positions[b].cpu().numpy(), ref, rtol=0, atol=1e-12)
        moved = np.abs(ref - X[0].numpy()).max(0) > 0
        assert torch.equal(r.moved[b].cpu(), torch.from_numpy(moved) | mask[b])
    assert float(r.violation.max()) <= 1e-12


def test_tensor_sweeps_follow_the_propagation_depth(device):
    g = td.Grid((24, 24, 24), spacing=1.0)
    lim = Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
    pick = torch.zeros(g.shape, dtype=torch.bool)
    pick[12, 12, 12] = True
    # d is pulled 0.2 m less per hop (stretch along d, shear across): moved within delta / 0.2 hops
    for delta, hops in (((1.1, 0.0, 0.0), 5), ((2.1, 0.0, 0.0), 10), ((2.1, -1.1, 0.5), 10)):
        x = g.rest_positions(dtype=F64, device=device)
        r = tensor_chainmail(x, g, lim, pick.to(device), torch.tensor(delta, dtype=F64, device=device))
        # shortest paths are monotone lattice paths here: one sweep per hop, nothing revised later
        assert int(r.depth[0]) == hops and r.sweeps == hops
        cm = ChainMail(g, lim)
        cm.move([(12, 12, 12)], delta)
        torch.testing.assert_close(r.positions.cpu(), cm.positions(), rtol=0, atol=1e-12)


def test_tensor_reports_a_blocked_move_and_keeps_fixed_elements(device):
    g = td.Grid((6, 1, 1), spacing=1.0)
    lim = Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
    fixed = torch.zeros(g.shape, dtype=torch.bool)
    fixed[0] = True
    pick = torch.zeros(g.shape, dtype=torch.bool)
    pick[5] = True
    x, d = g.rest_positions(dtype=F64, device=device), torch.tensor([2.0, 0, 0], dtype=F64, device=device)
    r = tensor_chainmail(x, g, lim, pick.to(device), d, fixed=fixed.to(device))
    assert float(r.positions[0, 0, 0, 0, 0]) == 0.0
    assert float(r.violation[0]) == pytest.approx(1.0)  # 2 m asked, 5 links x 0.2 m possible


def _bounding_box_of(moved, shape):
    """Bounding box of ``moved`` ``(B, D, H, W)`` over the batch dilated by one, clipped: by argwhere."""
    ijk = np.argwhere(moved.numpy().any(0))
    return tuple((max(int(ijk[:, a].min()) - 1, 0), min(int(ijk[:, a].max()) + 2, n)) for a, n in enumerate(shape))


def _box_case(name):
    """``(x, grid, lim, pick, d, kwargs)`` of one active-box comparison case."""
    rng = np.random.default_rng(sum(map(ord, name)))
    shape = (12, 11, 13)
    mask = None
    if name == "masked":  # an L-shaped body with a hole
        mask = torch.ones(shape, dtype=torch.bool)
        mask[6:, :5] = False
        mask[3:5, 3:6, 4:6] = False
    grid = td.Grid(shape, spacing=(1.0, 0.9, 1.1), node_mask=mask)
    lim = (
        _hetero_limits(grid, rng)
        if name in ("hetero", "cut")
        else Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2)
    )
    B = 2 if name in ("random", "cut") else 3
    nodes = grid.nodes()
    inside = nodes.nonzero().tolist()
    pick = torch.zeros((B,) + shape, dtype=torch.bool)
    # "random": picks anywhere (the box soon covers the grid); else near one element (a local box),
    # "border": near a corner (the box is clipped)
    middle = [ijk for ijk in inside if all(3 <= v <= n - 4 for v, n in zip(ijk, shape))]
    centre = np.array((1, 0, 1) if name == "border" else middle[int(rng.integers(len(middle)))])
    for b in range(B):
        for _ in range(int(rng.integers(1, 3))):
            ijk = (
                inside[int(rng.integers(len(inside)))]
                if name == "random"
                else np.clip(centre + rng.integers(-1, 2, 3), 0, np.array(shape) - 1).tolist()
            )
            pick[(b, *ijk)] = bool(nodes[tuple(ijk)])
        if not pick[b].any():
            pick[(b, *centre.tolist())] = True
    d = torch.tensor(rng.normal(size=(B, 3)) * (1.6 if name == "random" else 0.6), dtype=F64)  # random: all over
    kwargs = {}
    if name == "fixed":
        kwargs["fixed"] = (torch.from_numpy(rng.random(shape) < 0.05) | grid.face("bottom")) & ~pick.any(0)
    if name == "cut":  # one blade per body, plus random cuts
        x0 = grid.rest_positions(dtype=F64)
        links = torch.stack(
            [
                unlink(link_mask(grid), x0, Blade((5.5, -1.0, -1.0), (0.0, 7.0, 0.0), (0.0, 0.0, 15.0))),
                unlink(link_mask(grid), x0, Blade((-1.0, 4.5, -1.0), (14.0, 0.0, 0.0), (0.0, 0.0, 8.0))),
            ]
        )
        kwargs["links"] = links & torch.from_numpy(rng.random(links.shape) < 0.9)
    x = grid.rest_positions(dtype=F64).repeat(B, 1, 1, 1, 1)
    return x, grid, lim, pick, d, kwargs


@pytest.mark.parametrize("name", ["random", "hetero", "fixed", "cut", "border", "masked"])
def test_tensor_active_box_equals_whole_grid_sweeps(name, device):
    x, grid, lim, pick, d, kwargs = _box_case(name)
    on_device = {k: v.to(device) for k, v in kwargs.items()}
    r = tensor_chainmail(x.to(device), grid, lim, pick.to(device), d.to(device), **on_device)
    pos, moved, sweeps, depth = whole_grid_sweeps(x, grid, lim, pick, d, kwargs.get("fixed"), kwargs.get("links"))
    assert torch.equal(r.positions.cpu(), pos)  # bit for bit
    assert torch.equal(r.moved.cpu(), moved)
    assert r.sweeps == sweeps and r.depth.tolist() == depth
    # every link the pull changed lies in the box: the box's violation is the whole grid's
    assert torch.equal(r.violation, limit_violation(r.positions, grid, lim, links=on_device.get("links")))
    assert r.box == _bounding_box_of(r.moved.cpu(), grid.shape)
    assert len(set(d.flatten().tolist())) == d.numel()  # the bodies really differ


def test_whole_grid_reference_agrees_with_least_motion_oracle():
    x, grid, lim, pick, d, _ = _box_case("hetero")
    pos, *_ = whole_grid_sweeps(x, grid, lim, pick, d)
    mn, mx, sh = _np_limits(lim)
    for b in range(x.shape[0]):
        picks = [tuple(int(v) for v in p) for p in pick[b].nonzero()]
        ref = reference_move(x[b].numpy(), mn, mx, sh, picks, d[b].numpy())
        np.testing.assert_allclose(pos[b].numpy(), ref, rtol=0, atol=1e-12)


def test_tensor_second_pull_keeps_unmoved_elements_bit_for_bit():
    x, grid, lim, pick, d, _ = _box_case("random")
    first = tensor_chainmail(x, grid, lim, pick, d)
    pick2 = torch.zeros_like(pick)
    pick2[:, 2, 7, 1] = True
    d2 = torch.tensor([[-0.7, 0.4, 1.1], [0.9, -1.2, 0.3]], dtype=F64)
    r = tensor_chainmail(first.positions, grid, lim, pick2, d2)
    pos, moved, sweeps, depth = whole_grid_sweeps(first.positions, grid, lim, pick2, d2)
    m = r.moved.unsqueeze(1).expand_as(pos)
    assert torch.equal(r.moved, moved) and r.sweeps == sweeps and r.depth.tolist() == depth
    assert torch.equal(r.positions[m], pos[m])  # moved: as the whole-grid sweeps
    assert torch.equal(r.positions[~m], first.positions[~m])  # the rest: untouched, no X + (x - X)
    torch.testing.assert_close(r.violation, limit_violation(r.positions, grid, lim), rtol=0, atol=1e-14)


def test_tensor_sweeps_visit_only_the_active_box(device):
    n = 48
    g = td.Grid((n, n, n), spacing=1e-3)
    lim = Limits.from_material(g, compression=0.8, stretch=1.2, shear=0.2)
    pick = torch.zeros(g.shape, dtype=torch.bool)
    pick[30, 20, 24] = True
    x, d = g.rest_positions(dtype=F64, device=device), torch.tensor([2e-3, 1e-3, 0.0], dtype=F64, device=device)
    r = tensor_chainmail(x, g, lim, pick.to(device), d)
    moved = int(r.moved.sum())
    assert 1000 <= moved <= 2000
    assert r.box == _bounding_box_of(r.moved.cpu(), g.shape)
    volume = int(np.prod([hi - lo for lo, hi in r.box]))
    assert volume < n**3 / 8  # the box is the pull's, not the grid's
    # the box only grows: each sweep (the last, unchanged one included) visits at most its final volume
    assert 27 * (r.sweeps + 1) < r.checked <= (r.sweeps + 1) * volume
    assert r.checked < (r.sweeps + 1) * n**3 / 8


# ------------------------------------------------------------------ relaxation
def _pulled(method="gibson", n=16):
    g = td.Grid((n, n, n), spacing=1.0)
    lim = Limits.from_material(g, compression=0.7, stretch=1.3, shear=0.3)
    cm = ChainMail(g, lim, fixed=g.face("bottom"), method=method)
    cm.move([(n - 1, n // 2, n // 2)], (3.0, 1.0, 0.0))
    return g, lim, cm


def test_relaxation_lowers_energy_monotonically_and_removes_creases(device):
    g, lim, cm = _pulled()
    x0 = cm.positions(device=device)
    held = torch.zeros(g.shape, dtype=torch.bool)
    held[15, 8, 8] = True
    free = (~g.face("bottom") & ~held).to(device)
    c0 = float(crease_measure(x0, g, free=free))
    x1, _e1 = relax(x0, g, lim, steps=1, free=free)
    x4, e4 = relax(x0, g, lim, steps=4, free=free)
    _, e10 = relax(x0, g, lim, steps=10, free=free)
    assert all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(e10)) and e10[-1] < 0.9 * e10[0]
    # the energy is the Dirichlet energy of the offsets, computed here with plain numpy
    assert x4.device == device
    u = (x4 - g.rest_positions(dtype=F64, device=device))[0].cpu().numpy()
    dirichlet = sum(0.5 * ((np.diff(u, axis=1 + a)) ** 2).sum() for a in range(3))
    assert e4[-1] == pytest.approx(dirichlet, rel=1e-12)
    c1, c4 = float(crease_measure(x1, g, free=free)), float(crease_measure(x4, g, free=free))
    assert c1 < 0.7 * c0 and c4 < c1
    for x in (x1, x4):
        assert float(limit_violation(x, g, lim)[0]) <= 1e-12
        assert torch.equal(x[0][:, ~free], x0[0][:, ~free])  # fixed and held elements stay


def test_relaxation_goal_mode_and_only_moved():
    g = td.Grid((12, 12, 12), spacing=1.0)
    lim = Limits.from_material(g, compression=0.9, stretch=1.5, shear=0.3)  # goal distance 1.2 m, not the spacing
    cm = ChainMail(g, lim, method="enhanced")
    cm.move([(6, 6, 6)], (2.0, 0.0, 1.0))
    moved = cm.moved_mask()
    before = cm.positions()
    energies = cm.relax(steps=3, mode="goal", only_moved=True)
    after = cm.positions()
    assert all(b <= a * (1 + 1e-12) for a, b in itertools.pairwise(energies)) and energies[-1] < energies[0]
    assert energies[0] == pytest.approx(float(relax_energy(before, g, limits=lim, mode="goal")[0]))
    assert torch.equal(after[0][:, ~moved], before[0][:, ~moved])
    assert torch.equal(after[0][:, 6, 6, 6], before[0][:, 6, 6, 6])  # the picked element is held
    assert float(limit_violation(after, g, lim)[0]) <= 1e-12


# ------------------------------------------------------------------ outputs and materials
def test_displacement_field_and_mass_spring_state(device):
    g, lim, cm = _pulled(n=8)
    u = cm.displacement()
    assert u.shape == (1, 3, 8, 8, 8) and u.dtype == torch.float32
    state = cm.state(dtype=F64, device=device)
    assert state.x.device == device
    expect = g.rest_positions(dtype=F64, device=device) + cm.displacement(dtype=F64, device=device)
    torch.testing.assert_close(state.x, expect)
    model = td.Model(g, stiffness=10.0, mass=1e-3, fixed=g.face("bottom"), dtype=F64, device=device)
    nxt = td.SymplecticEuler().step(model, state, dt=1e-4)
    assert torch.isfinite(nxt.x).all() and float(nxt.v.abs().max()) > 0  # springs pull it back
    cm2 = ChainMail(g, lim, positions=state.x)  # and back into ChainMail
    torch.testing.assert_close(cm2.positions(), cm.positions(), rtol=0, atol=1e-12)


def test_limits_from_material_and_tissues():
    g = td.Grid((4, 3, 2), spacing=(0.001, 0.002, 0.003))
    lim = Limits.from_material(g, compression=0.8, stretch=1.25, shear=0.1)
    np.testing.assert_allclose(lim.min.numpy(), [0.0008, 0.0016, 0.0024])
    np.testing.assert_allclose(lim.max.numpy(), [0.00125, 0.0025, 0.00375])
    np.testing.assert_allclose(lim.shear.numpy(), [0.0001, 0.0002, 0.0003])
    from torchdeform.fuzzy.presets import tissue_parameters

    liver = tissue_limits(g, "liver")
    eps = 300.0 / tissue_parameters("liver")["youngs_modulus"]
    np.testing.assert_allclose(liver.max.numpy(), (1 + eps) * np.array(g.spacing), rtol=1e-9)
    labels = torch.zeros(g.shape, dtype=torch.long)
    labels[2:] = 1
    mixed = tissue_limits(g, ["brain", "liver_cirrhotic"], labels=labels)
    assert not mixed.uniform
    e_b = 300.0 / tissue_parameters("brain")["youngs_modulus"]
    e_c = 300.0 / tissue_parameters("liver_cirrhotic")["youngs_modulus"]
    assert mixed.shear[0, 0, 0, 0] == pytest.approx(e_b * 0.001)  # brain-brain link
    assert mixed.shear[0, 1, 0, 0] == pytest.approx(0.5 * (e_b + e_c) * 0.001)  # brain-cirrhotic: mean
    assert mixed.shear[0, 2, 0, 0] == pytest.approx(e_c * 0.001)
    assert e_b > e_c  # softer tissue, wider limits


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda g: Limits(g, min=1.2, max=0.8, shear=0.1), "min <= max"),
        (lambda g: Limits(g, min=0.8, max=1.2, shear=-0.1), "shear limits >= 0"),
        (lambda g: Limits.from_material(g, compression=0.9, stretch=1.1, shear=-0.2), "ratio >= 0"),
        (
            lambda g: ChainMail(
                g, Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1), fixed=g.face("top")
            ).move([(3, 1, 1)], (1, 0, 0)),
            "fixed and cannot be moved",
        ),
        (
            lambda g: ChainMail(g, Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1)).move(
                [(4, 1, 1)], (1, 0, 0)
            ),
            "outside the grid",
        ),
        (
            lambda g: ChainMail(g, Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1)).move(
                [(-1, 1, 1)], (1, 0, 0)
            ),
            "outside the grid",
        ),
        (
            lambda g: ChainMail(g, Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1)).move(
                [(1, 1, 1)], (1, 0)
            ),
            "displacement",
        ),
        (
            lambda g: ChainMail(
                g, Limits.from_material(g, compression=torch.full(g.shape, 0.9), stretch=1.1, shear=0.1)
            ),
            "enhanced",
        ),
        (
            lambda g: ChainMail(g, Limits.from_material(g, compression=1.05, stretch=1.2, shear=0.1)),
            "satisfy the ChainMail limits",
        ),
        (
            lambda g: ChainMail(g, Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1), method="fast"),
            "gibson",
        ),
        (
            lambda g: ChainMail(
                td.Grid(g.shape, spacing=1.0, node_mask=g.face("top")),
                Limits.from_material(g, compression=0.9, stretch=1.1, shear=0.1),
            ),
            "node mask",
        ),
    ],
)
def test_bad_input_gives_one_clear_error(make, message):
    g = td.Grid((4, 3, 3), spacing=1.0)
    with pytest.raises(ConfigError, match=message):
        make(g)
