"""ChainMail unlinking (torchdeform.topology.unlink) against independent oracles.

Oracles written here, sharing no code with ``torchdeform.chainmail`` or ``torchdeform.topology``:

* :func:`lattice_links`: the explicit list of lattice links (node, neighbour, axis);
* :func:`brute_cut`: a plain numpy segment/rectangle test over that list (ends on opposite sides
  of the plane, a node on the plane on the side opposite the normal, the meeting point inside
  the rectangle);
* :func:`reference_move`: the least-motion ChainMail answer by a plain Bellman-Ford loop over the
  links that remain (an element must come within every remaining link's limits of the picked
  elements' targets; everything else stays).

Checked: (a) a full cut between two layers isolates the far side exactly (zero displacement),
while the uncut body moves it; (b) the unlinked set equals the brute-force set for an oblique,
partial blade through a deformed body; (c) across a partial cut the far side still follows
through the uncut links, and every solver (Gibson, Enhanced, tensor) equals the reference;
(d) no mask and an all-true mask give bit-identical results.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from tests.oracles.chainmail_moves import least_motion
from torchdeform.chainmail import ChainMail, Limits, limit_violation, link_mask, relax, tensor_chainmail
from torchdeform.errors import ConfigError
from torchdeform.topology import Blade, link_crossing, unlink

SPACING = (1.0, 0.9, 1.1)


# ------------------------------------------------------------------ independent oracles
def lattice_links(shape):
    """Every link of a box lattice as (node, neighbour, axis), neighbour = node + e_axis."""
    out = []
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                for a in range(3):
                    q = [i, j, k]
                    q[a] += 1
                    if q[a] < shape[a]:
                        out.append(((i, j, k), tuple(q), a))
    return out


def brute_cut(x, links, origin, u, v):
    """The links (from ``links``) whose segment crosses the rectangle ``origin + a u + b v``, as a set."""
    o, u, v = (np.asarray(t, dtype=np.float64) for t in (origin, u, v))
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    out = set()
    for p, q, a in links:
        xp, xq = x[(slice(None), *p)], x[(slice(None), *q)]
        hp, hq = float(n @ (xp - o)), float(n @ (xq - o))
        if (hp > 0) == (hq > 0):
            continue
        r = xp + hp / (hp - hq) * (xq - xp)
        s, t = float((r - o) @ u / (u @ u)), float((r - o) @ v / (v @ v))
        if 0 <= s <= 1 and 0 <= t <= 1:
            out.add((p, q, a))
    return out


def reference_move(u0, shape, lo, hi, sh, links, picks, delta):
    """Least-motion offsets after moving ``picks`` by ``delta`` with only ``links`` linked (Bellman-Ford).

    ``u0`` (3, D, H, W) offsets; ``lo, hi, sh`` per-axis offset-difference bounds (min - h, max - h,
    shear); per coordinate ``c`` the offset difference ``u_q[c] - u_p[c]`` of link (p, q, a) lies in
    ``[lo_a, hi_a]`` when ``c == a``, else in ``[-sh_a, sh_a]``.
    """

    def bounds(p, a, c):
        return (lo[a], hi[a]) if c == a else (-sh[a], sh[a])

    return least_motion(u0, shape, links, bounds, picks, delta)


def _mask_from(links, shape):
    m = torch.zeros((3,) + tuple(shape), dtype=torch.bool)
    for p, _, a in links:
        m[(a, *p)] = True
    return m


def _setup(shape=(6, 5, 4)):
    grid = td.Grid(shape, spacing=SPACING)
    lim = Limits.from_material(grid, compression=0.8, stretch=1.2, shear=0.2)
    return grid, lim


def _bounds(grid):
    h = np.asarray(grid.spacing)
    return 0.8 * h - h, 1.2 * h - h, 0.2 * h


# ------------------------------------------------------------------ (a) full cut
def _full_blade(grid, layer):
    """A blade between d-layers ``layer`` and ``layer + 1``, larger than the body."""
    _D, H, W = grid.shape
    h = grid.spacing
    return Blade(((layer + 0.5) * h[0], -h[1], -h[2]), (0.0, (H + 1) * h[1], 0.0), (0.0, 0.0, (W + 1) * h[2]))


@pytest.mark.parametrize("method", ["gibson", "enhanced"])
def test_full_cut_isolates_the_far_side_sequential(method):
    grid, lim = _setup()
    pick, delta = [(0, 2, 1)], (-2.5, 0.6, -0.4)
    whole = ChainMail(grid, lim, method=method)
    whole.move(pick, delta)
    assert float(whole.displacement(dtype=F64)[0, :, 3:].abs().max()) > 0.1  # uncut: the top is dragged

    cm = ChainMail(grid, lim, method=method)
    links = unlink(cm, None, _full_blade(grid, 2))
    assert int((link_mask(grid) & ~links).sum()) == grid.shape[1] * grid.shape[2]
    assert not bool(links[0, 2].any()) and bool(links[0, :2].all())
    r = cm.move(pick, delta)
    u = cm.displacement(dtype=F64)[0]
    assert float(u[:, 3:].abs().max()) == 0.0  # exactly: nothing moved
    assert r.fraction == 1.0 and r.moved > 1
    assert float(u[:, :3].abs().max()) > 0.1
    x = cm.positions()
    assert float(limit_violation(x, grid, lim, links=links)[0]) < 1e-12
    assert float(limit_violation(x, grid, lim)[0]) > 0.1  # the cut gapes
    assert bool((r.moved_nodes < 3 * 5 * 4).all())  # node indices: layers 0..2 only
    # relaxation respects the cut as well: the far side stays put
    cm.relax(steps=3)
    assert float(cm.displacement(dtype=F64)[0, :, 3:].abs().max()) == 0.0


def test_full_cut_isolates_the_far_side_tensor():
    grid, lim = _setup()
    x = grid.rest_positions(dtype=F64).repeat(2, 1, 1, 1, 1)
    pick = torch.zeros(grid.shape, dtype=torch.bool)
    pick[0, 2, 1] = True
    d = torch.tensor([[-2.5, 0.6, -0.4], [-1.0, -0.8, 0.5]], dtype=F64)
    full = tensor_chainmail(x, grid, lim, pick, d)
    assert bool(full.moved[:, 3:].flatten(1).any(1).all())
    links = unlink(link_mask(grid), x[:1], _full_blade(grid, 2))
    r = tensor_chainmail(x, grid, lim, pick, d, links=links)
    u = r.displacement(grid)
    assert float(u[:, :, 3:].abs().max()) == 0.0 and not bool(r.moved[:, 3:].any())
    assert bool((r.violation < 1e-12).all())
    near = (slice(None), slice(None), slice(0, 3))
    assert float((r.positions[near] - full.positions[near]).abs().max()) < 1e-12  # the near side as before
    # the relaxation of the result keeps the far side at rest and every remaining limit holds
    xr, e = relax(r.positions, grid, lim, steps=2, free=~pick, links=links)
    assert float((xr - x)[:, :, 3:].abs().max()) == 0.0
    assert float(limit_violation(xr, grid, lim, links=links).max()) < 1e-12
    assert e[-1] <= e[0]


# ------------------------------------------------------------------ (b) oblique partial blade
def test_oblique_partial_blade_matches_brute_force(device):
    grid, lim = _setup((7, 6, 5))
    shape = grid.shape
    x = grid.rest_positions(dtype=F64)
    g = torch.Generator().manual_seed(3)
    x = x + 0.05 * torch.rand(x.shape, generator=g, dtype=F64)  # a deformed body
    # an oblique rectangle: edges u, v at right angles, covering part of the body only
    u = np.array([1.5, 3.0, 0.4])
    v = np.cross(u, np.array([-1.0, 0.3, 0.9]))
    v *= 3.5 / np.linalg.norm(v)
    origin = (1.6, 0.4, 0.7)
    blade = Blade(origin, tuple(u), tuple(v))
    links = lattice_links(shape)
    expect = brute_cut(x[0].numpy(), links, origin, u, v)
    n = np.cross(u, v)
    planes = sum(
        1
        for p, q, a in links  # crossing the plane at all
        if (float(n @ (x[0][(slice(None), *p)].numpy() - origin)) > 0)
        != (float(n @ (x[0][(slice(None), *q)].numpy() - origin)) > 0)
    )
    assert 10 < len(expect) < planes  # partial: some pass by
    assert {a for *_, a in expect} == {0, 1, 2}  # oblique: links of every axis
    on_device = x.to(device)  # the link test on the device of the run; the ChainMail below on the CPU
    got = link_mask(grid) & ~unlink(link_mask(grid), on_device, blade).cpu()
    assert torch.equal(got, _mask_from(expect, shape))
    assert torch.equal(link_crossing(on_device, blade, grid=grid)[0].cpu(), got)
    cm = ChainMail(grid, lim, positions=x, method="enhanced")
    assert torch.equal(~unlink(cm, None, blade) & link_mask(grid), got)
    assert torch.equal(cm.links, link_mask(grid) & ~got)


def test_node_on_the_plane_counts_as_the_side_opposite_the_normal():
    grid, _ = _setup((5, 3, 3))
    x = grid.rest_positions(dtype=F64)
    h = grid.spacing
    blade = Blade((2 * h[0], -1.0, -1.0), (0.0, 5.0, 0.0), (0.0, 0.0, 5.0))  # through layer 2, normal +d
    cut_ = link_mask(grid) & ~unlink(link_mask(grid), x, blade)
    expect = brute_cut(x[0].numpy(), lattice_links(grid.shape), (2 * h[0], -1.0, -1.0), (0, 5.0, 0), (0, 0, 5.0))
    assert torch.equal(cut_, _mask_from(expect, grid.shape))
    assert bool(cut_[0, 2].all()) and int(cut_.sum()) == 9  # only 2 -> 3, never 1 -> 2


# ------------------------------------------------------------------ (c) partial cut
@pytest.mark.parametrize("method", ["gibson", "enhanced", "tensor"])
def test_far_side_follows_through_uncut_links(method):
    grid, lim = _setup()
    shape = grid.shape
    hs = grid.spacing
    # cut the d-links between layers 2 and 3 for h in {0, 1, 2}; h in {3, 4} stays linked
    blade = Blade((2.5 * hs[0], -hs[1], -hs[2]), (0.0, 3.0 * hs[1], 0.0), (0.0, 0.0, (shape[2] + 1) * hs[2]))
    x = grid.rest_positions(dtype=F64)
    links = unlink(link_mask(grid), x, blade)
    all_links = lattice_links(shape)
    cut_set = brute_cut(x[0].numpy(), all_links, blade.patches[0][0], blade.patches[0][1], blade.patches[0][2])
    assert len(cut_set) == 3 * shape[2]
    remaining = [lk for lk in all_links if lk not in cut_set]
    pick, delta = (0, 0, 1), (-3.0, 0.0, 0.5)
    lo, hi, sh = _bounds(grid)
    ref = reference_move(np.zeros((3,) + shape), shape, lo, hi, sh, remaining, [pick], delta)
    straight = reference_move(np.zeros((3,) + shape), shape, lo, hi, sh, all_links, [pick], delta)
    if method == "tensor":
        p = torch.zeros(shape, dtype=torch.bool)
        p[pick] = True
        r = tensor_chainmail(x, grid, lim, p, delta, links=links)
        u = r.displacement(grid)[0].numpy()
        assert float(r.violation[0]) < 1e-12
    else:
        cm = ChainMail(grid, lim, method=method, links=links)
        res = cm.move([pick], delta)
        assert res.fraction == 1.0
        u = cm.displacement(dtype=F64)[0].numpy()
        assert float(limit_violation(cm.positions(), grid, lim, links=links)[0]) < 1e-12
    assert np.abs(u - ref).max() < 1e-12
    far = u[:, 3:, :3]  # the far side behind the cut
    assert np.abs(far).max() > 0.1  # it follows, round the cut
    assert np.abs(far - straight[:, 3:, :3]).max() > 0.1  # but less than without the cut


# ------------------------------------------------------------------ (d) no mask == all-true mask
@pytest.mark.parametrize("method", ["gibson", "enhanced"])
def test_all_true_mask_is_bit_identical_sequential(method):
    grid, lim = _setup()
    full = torch.ones((3,) + grid.shape, dtype=torch.bool)  # also True on links leaving the box
    a = ChainMail(grid, lim, method=method, fixed=grid.face("top"))
    b = ChainMail(grid, lim, method=method, fixed=grid.face("top"), links=full)
    for pick, d in (([(0, 2, 1)], (-1.7, 0.4, 0.3)), ([(2, 4, 3), (2, 3, 3)], (0.2, 1.3, -0.9))):
        ra, rb = a.move(pick, d), b.move(pick, d)
        assert torch.equal(a.positions(), b.positions())
        assert (ra.fraction, ra.checked, ra.moved) == (rb.fraction, rb.checked, rb.moved)
        assert all(np.array_equal(p, q) for p, q in zip(ra.passes, rb.passes))
    assert a.relax(steps=2) == b.relax(steps=2)
    assert torch.equal(a.positions(), b.positions())
    assert torch.equal(a.links, b.links) and torch.equal(a.links, link_mask(grid))


def test_all_true_mask_is_bit_identical_tensor():
    grid, lim = _setup()
    x = grid.rest_positions(dtype=F64).repeat(2, 1, 1, 1, 1)
    pick = torch.zeros(grid.shape, dtype=torch.bool)
    pick[1, 2, 2] = True
    d = torch.tensor([[1.5, -0.5, 0.2], [-0.3, 0.9, 1.1]], dtype=F64)
    fixed = grid.face("bottom")
    ra = tensor_chainmail(x, grid, lim, pick, d, fixed=fixed)
    rb = tensor_chainmail(x, grid, lim, pick, d, fixed=fixed, links=link_mask(grid))
    assert torch.equal(ra.positions, rb.positions) and torch.equal(ra.moved, rb.moved)
    assert ra.sweeps == rb.sweeps and torch.equal(ra.depth, rb.depth) and torch.equal(ra.violation, rb.violation)
    xa, ea = relax(ra.positions, grid, lim, steps=2, free=~pick)
    xb, eb = relax(
        ra.positions, grid, lim, steps=2, free=~pick, links=torch.ones((2, 3) + grid.shape, dtype=torch.bool)
    )
    assert torch.equal(xa, xb) and ea == eb


# ------------------------------------------------------------------ errors
def test_bad_masks_and_relinking_are_refused():
    grid, lim = _setup()
    cm = ChainMail(grid, lim, method="enhanced")
    with pytest.raises(ConfigError):
        ChainMail(grid, lim, links=torch.ones(3, 2, 2, 2, dtype=torch.bool))
    with pytest.raises(ConfigError):
        tensor_chainmail(
            grid.rest_positions(dtype=F64), grid, lim, grid.face("top"), (1.0, 0, 0), links=torch.ones(2, 2, 2)
        )
    with pytest.raises(ConfigError):
        unlink(link_mask(grid), None, _full_blade(grid, 2))
    unlink(cm, None, _full_blade(grid, 2))
    cm.move([(0, 2, 2)], (-3.0, 0.0, 0.0))
    with pytest.raises(ConfigError):  # the sides drifted apart: no relinking
        cm.set_links(None)
    cm.reset()
    cm.set_links(None)  # at rest they may be linked again
    assert torch.equal(cm.links, link_mask(grid))
