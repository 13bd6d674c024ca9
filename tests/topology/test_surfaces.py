"""Surfaces and carved renders of a cut body (torchdeform.topology.surfaces) against independent oracles.

* after a full axis-aligned cut each side's surface is watertight (trimesh), its bounding box is the
  side's node layers plus half a spacing all round, and it encloses the analytic volume of the
  level-1/2 surface of that box of nodes (the half-cell box less the chamfers of the tetrahedral
  split, a closed form checked against a per-tetrahedron count); pulled apart, the two surfaces lie on either side of a plane (so they cannot
  intersect) and are still watertight boxes of the same volume;
* a different affine map per side: every vertex equals ``A_L rest + t_L`` (an affine map is an
  exact oracle for the extension), rest coordinates equal the undeformed surface, and each volume
  is ``det(A_L)`` times the box;
* the PLY files read back with the same vertices and float64 rest coordinates;
* carved render: a ramp volume, cut between node layers, one side moved 4 voxels along the cut
  normal; a MIP and a DVR along a direction in the cut plane equal the analytic image (empty gap
  rows, each side showing its own translated content), while one interpolated field smears tissue
  into the gap; without motion the carved render equals the plain one (axis view and orbit camera).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.topology import (
    Blade,
    CutSurface,
    components,
    cut,
    cut_pieces,
    cut_surfaces,
    extend_displacement,
    save_cut_surfaces,
    sides,
)
from torchdeform.volume import OrbitCamera, TransferFunction, node_offsets, render

SPACING = (0.01, 0.012, 0.008)  # anisotropic, so the axes cannot be mixed up unnoticed
ORIGIN = (0.1, -0.2, 0.05)


def _cut_body(n, k, spacing=SPACING, device=None):
    """An n^3 body cut between node layers k and k + 1 along D; returns (grid, model, labels)."""
    grid = td.Grid((n, n, n), spacing=spacing, topology=26, origin=ORIGIN)
    model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=F64, device=device)
    sd, sh, sw = spacing
    blade = Blade(
        (ORIGIN[0] + (k + 0.5) * sd, ORIGIN[1] - sh, ORIGIN[2] - sw), (0.0, (n + 1) * sh, 0.0), (0.0, 0.0, (n + 1) * sw)
    )
    assert cut(model, model.X, blade) == (3 * n - 2) ** 2
    labels, count = components(model)
    assert count == 2
    return grid, model, labels


def _mesh(s: CutSurface) -> trimesh.Trimesh:
    return trimesh.Trimesh(s.vertices, s.faces, process=True)


#: Volume (in unit cubes) of {f >= 1/2} inside one Kuhn tetrahedron (1/6 of the cube) with k of its four
#: corners inside, f the piecewise-linear interpolant of the 0/1 node mask: 0; the corner's tetrahedron
#: scaled by 1/2, (1/2)^3 / 6 = 1/48; half of it by the symmetry f <-> 1 - f, 1/12; 1/6 - 1/48 = 7/48; 1/6.
KUHN_PART = np.array([0, 1, 4, 7, 8]) / 48.0


def _kuhn_volume(mask: np.ndarray) -> float:
    """Volume (unit cells) of the level-1/2 set of a 0/1 node mask, counted per tetrahedron.

    Every cube is split into the six chains 0 -> 7 that step one axis at a time (one per axis order)."""
    m = np.pad(mask.astype(np.int64), 1)
    D, H, W = m.shape
    total = 0.0
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        c, k = [0, 0, 0], m[:-1, :-1, :-1].copy()
        for axis in order:
            c[axis] = 1
            k += m[c[0] : D - 1 + c[0], c[1] : H - 1 + c[1], c[2] : W - 1 + c[2]]
        total += KUHN_PART[k].sum()
    return total


def _box(n, layers, spacing=SPACING):
    """Analytic volume enclosed by the surface of `layers` node layers along D of an n x n cross-section.

    The level-1/2 surface of a 0/1 node mask lies half a spacing outside the outer nodes, so its bounding
    box has (count) spacings per axis: p q r cells for p x q x r nodes. Across the six box edges whose two
    faces the cube diagonal (1, 1, 1) of the tetrahedral split meets with opposite signs, the surface is
    chamfered: the edge cubes there hold 1/8 of a cell instead of 1/4 (three of the six tetrahedra reach
    it, two with one corner inside, 2/48, one with two, 1/12), so the box loses (p + q + r) / 4 cells; the
    corners give 1/4 back: V = p q r - (p + q + r - 1) / 4 (checked against the per-tetrahedron count)."""
    p, q, r = layers, n, n
    return (p * q * r - (p + q + r - 1) / 4) * spacing[0] * spacing[1] * spacing[2]


@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 4, 4), (3, 2, 5), (4, 4, 4)])
def test_box_volume_formula_matches_the_tetrahedron_count(shape):
    p, q, r = shape
    assert _kuhn_volume(np.ones(shape)) == pytest.approx(p * q * r - (p + q + r - 1) / 4, rel=1e-12)


@pytest.mark.parametrize("n, k", [(4, 1), (5, 2)])
def test_full_cut_sides_are_closed_boxes_and_part_when_pulled_apart(n, k, device):
    grid, model, labels = _cut_body(n, k, device=device)
    lower, upper = cut_surfaces(grid, model.X, labels)
    assert (lower.label, upper.label) == (0, (k + 1) * n * n)  # smallest flat index per side
    for s, layers in ((lower, k + 1), (upper, n - 1 - k)):
        mesh = _mesh(s)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume == pytest.approx(_box(n, layers), rel=1e-9)  # > 0: faces point outwards
        lo = np.array(ORIGIN) - 0.5 * np.array(SPACING)  # the half-cell offset
        np.testing.assert_allclose(mesh.bounds[1, 1:] - mesh.bounds[0, 1:], [n * SPACING[1], n * SPACING[2]])
        np.testing.assert_allclose(mesh.bounds[0, 1:], lo[1:], atol=1e-12)
    # at rest the two cut faces coincide, on the plane half-way between layers k and k + 1
    plane = ORIGIN[0] + (k + 0.5) * SPACING[0]
    assert lower.vertices[:, 0].max() == pytest.approx(plane, abs=1e-12)
    assert upper.vertices[:, 0].min() == pytest.approx(plane, abs=1e-12)

    # pull the upper side away along the normal (and sideways): a rigid translation
    t = torch.tensor([0.4 * SPACING[0], 0.3 * SPACING[1], -0.2 * SPACING[2]], dtype=F64)
    x = model.X.clone()
    up = labels == upper.label
    x[0] = torch.where(up, x[0] + t.to(device).view(3, 1, 1, 1), x[0])
    lower2, upper2 = cut_surfaces(grid, x, labels)
    for s, layers in ((lower2, k + 1), (upper2, n - 1 - k)):
        mesh = _mesh(s)
        assert mesh.is_watertight
        assert mesh.volume == pytest.approx(_box(n, layers), rel=1e-9)
    # a separating plane: no triangle of one surface can meet a triangle of the other
    assert lower2.vertices[:, 0].max() == pytest.approx(plane, abs=1e-12)
    assert upper2.vertices[:, 0].min() == pytest.approx(plane + float(t[0]), abs=1e-12)
    np.testing.assert_allclose(upper2.vertices, upper.vertices + t.numpy(), atol=1e-12)
    np.testing.assert_allclose(upper2.rest, upper.vertices, atol=1e-12)


def test_affine_map_per_side_is_reproduced_exactly():
    n, k = 5, 1
    grid, model, labels = _cut_body(n, k)
    gen = torch.Generator().manual_seed(3)
    maps = {}
    x = model.X.clone()
    X = model.X[0]
    for label in torch.unique(labels).tolist():
        A = torch.eye(3, dtype=F64) + 0.2 * (torch.rand(3, 3, generator=gen, dtype=F64) - 0.5)
        b = 0.01 * torch.randn(3, generator=gen, dtype=F64)
        maps[label] = (A.numpy(), b.numpy())
        mapped = torch.einsum("ij,jdhw->idhw", A, X) + b.view(3, 1, 1, 1)
        x[0] = torch.where(labels == label, mapped, x[0])
    at_rest = {s.label: s for s in cut_surfaces(grid, model.X, labels)}
    for s in cut_surfaces(grid, x, labels):
        A, b = maps[s.label]
        np.testing.assert_allclose(s.vertices, s.rest @ A.T + b, atol=1e-12)
        np.testing.assert_allclose(s.rest, at_rest[s.label].vertices, atol=1e-12)
        layers = k + 1 if s.label == 0 else n - 1 - k
        mesh = _mesh(s)
        assert mesh.is_watertight
        assert mesh.volume == pytest.approx(np.linalg.det(A) * _box(n, layers), rel=1e-9)


def test_sides_as_labels_and_a_batch_of_one():
    n, k = 4, 1
    grid, model, labels = _cut_body(n, k)
    blade_side = sides(model.X, Blade((ORIGIN[0] + 1.5 * SPACING[0], -1, -1), (0, 3, 0), (0, 0, 3)))
    side_labels = torch.where(grid.nodes(), (blade_side[0, 0] > 0).long(), -1)
    by_side = cut_surfaces(grid, model.X[0], side_labels, X=model.X)
    by_component = cut_surfaces(grid, model.X, labels)
    assert [s.label for s in by_side] == [0, 1]
    for a, b in zip(by_side, by_component):
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-15)


def test_extension_is_linear_one_layer_out_and_nearest_beyond(device):
    mask = torch.zeros(6, 3, 3, dtype=torch.bool, device=device)
    mask[:2] = True
    X = td.Grid((6, 3, 3), spacing=1.0).rest_positions(dtype=F64, device=device)[0]
    A = torch.tensor([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.0]], dtype=F64, device=device)
    u = torch.einsum("ij,jdhw->idhw", A - torch.eye(3, dtype=F64, device=device), X) * mask
    out = extend_displacement(u, mask)
    exact = torch.einsum("ij,jdhw->idhw", A - torch.eye(3, dtype=F64, device=device), X)
    torch.testing.assert_close(out[:, :3], exact[:, :3], rtol=0, atol=1e-14)  # the piece + one layer out
    for d in range(3, 6):  # nearest filled: layer 2
        torch.testing.assert_close(out[:, d], exact[:, 2], rtol=0, atol=1e-14)


def test_ply_files_keep_rest_coordinates(tmp_path):
    grid, model, labels = _cut_body(4, 1)
    x = model.X.clone()
    x[0, 0] += 0.003 * (labels >= 32)
    surfaces = cut_surfaces(grid, x, labels)
    paths = save_cut_surfaces(tmp_path / "out", surfaces, stem="side")
    assert [p.name for p in paths] == ["side_0.ply", "side_32.ply"]
    for s, path in zip(surfaces, paths):
        mesh = trimesh.load(str(path), process=False)
        raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
        np.testing.assert_allclose(mesh.vertices, s.vertices, rtol=1e-6)  # float32 positions
        np.testing.assert_array_equal(np.stack([raw["rest_x"], raw["rest_y"], raw["rest_z"]], 1), s.rest)
        np.testing.assert_array_equal(mesh.faces, s.faces)
        assert trimesh.Trimesh(mesh.vertices, mesh.faces).is_watertight


# ------------------------------------------------------------------ carved render
N_VOX, N_NODES, SHIFT = 13, 5, 4  # 3 voxels per node spacing; the cut half-way between nodes 1 and 2
H = 0.01


def _ramp_volume():
    d, _, w = torch.meshgrid(*[torch.arange(N_VOX, dtype=F64)] * 3, indexing="ij")
    return 1.0 + d + 0.1 * w  # constant along H


def _moved_apart():
    grid, model, labels = _cut_body(N_NODES, 1, spacing=(H, H, H))
    x = model.X.clone()
    metres_per_voxel = H * (N_NODES - 1) / (N_VOX - 1)
    x[0, 0] = torch.where(labels > 0, x[0, 0] + SHIFT * metres_per_voxel, x[0, 0])
    return grid, model, labels, x


def _expected_mip():
    """The analytic image (rows D, columns W) of a view along H: voxel centres d <= 4 lie in the lower side
    (the cut is at voxel 4.5), d >= 4.5 + SHIFT show the upper side's content from d - SHIFT, between them
    nothing (0)."""
    d = np.arange(N_VOX, dtype=np.float64)[:, None]
    w = np.arange(N_VOX, dtype=np.float64)[None, :]
    img = np.zeros((N_VOX, N_VOX))
    lower, upper = d[:, 0] <= 4.5, d[:, 0] >= 4.5 + SHIFT
    img[lower] = (1.0 + d + 0.1 * w)[lower]
    img[upper] = (1.0 + d - SHIFT + 0.1 * w)[upper]
    return img, ~(lower | upper)


@pytest.mark.parametrize("view", ["h", "-w"])
def test_carved_render_shows_the_gap(view):
    grid, model, labels, x = _moved_apart()
    vol = _ramp_volume()
    pieces = cut_pieces(grid, x, labels, vol.shape)
    img = render(vol, mode="mip", view=view, pieces=pieces)[0, 0].numpy()
    expected, gap = _expected_mip()
    assert gap.sum() == 4
    if view == "-w":  # rays along W: a MIP picks the largest w (= N_VOX - 1)
        expected = expected.max(1)[:, None] * np.ones((1, N_VOX))
    np.testing.assert_allclose(img, expected, atol=1e-12)
    # one interpolated field smears the tissue across the gap
    offsets = node_offsets(x, model.X, grid.spacing, vol.shape)
    smeared = render(vol, mode="mip", view=view, offsets=offsets)[0, 0].numpy()
    assert (smeared[gap] > 1.0).all()


def test_carved_dvr_is_transparent_in_the_gap():
    grid, _model, labels, x = _moved_apart()
    vol = _ramp_volume()
    tf = TransferFunction([0.0, 0.5, 20.0], [[1, 1, 1]] * 3, [0.0, 0.2, 0.2])
    img = render(vol, tf=tf, mode="dvr", view="h", pieces=cut_pieces(grid, x, labels, vol.shape), stop=0)
    alpha = img[0, 3].numpy()
    _, gap = _expected_mip()
    assert (alpha[gap] == 0).all()
    np.testing.assert_allclose(alpha[~gap], 1 - np.exp(-0.2 * N_VOX), rtol=1e-6)


@pytest.mark.parametrize("view", ["d", OrbitCamera(azimuth=30.0, elevation=20.0, size=(12, 12))])
def test_carved_render_without_motion_is_the_plain_render(view):
    grid, model, labels = _cut_body(N_NODES, 1, spacing=(H, H, H))
    vol = _ramp_volume()
    pieces = cut_pieces(grid, model.X, labels, vol.shape)
    for mode in ("mip", "average"):
        torch.testing.assert_close(
            render(vol, mode=mode, view=view, pieces=pieces), render(vol, mode=mode, view=view), rtol=0, atol=1e-12
        )


def test_bad_inputs_are_config_errors():
    grid, model, labels = _cut_body(4, 1)
    with pytest.raises(ConfigError, match="x"):
        cut_surfaces(grid, model.X.expand(2, -1, -1, -1, -1), labels)
    with pytest.raises(ConfigError, match="labels"):
        cut_surfaces(grid, model.X, labels[:3])
    with pytest.raises(ConfigError, match="labels"):
        cut_surfaces(grid, model.X, labels.double())
    with pytest.raises(ConfigError, match="X"):
        cut_surfaces(grid, model.X, labels, X=model.X[:, :2])
    with pytest.raises(ConfigError, match="volume_shape"):
        cut_pieces(grid, model.X, labels, (3, 8, 8))
    vol = torch.zeros(7, 7, 7)
    pieces = cut_pieces(grid, model.X.float(), labels, vol.shape)
    with pytest.raises(ConfigError, match="pieces"):
        render(vol, mode="mip", pieces=pieces, offsets=pieces[0][0])
    with pytest.raises(ConfigError, match="pieces material"):
        render(vol, mode="mip", pieces=[(pieces[0][0], torch.ones(3, 3, 3))])
    with pytest.raises(ConfigError, match="pieces"):
        render(vol, mode="mip", pieces=[pieces[0][0]])
    with pytest.raises(ConfigError, match="directory"):
        save_cut_surfaces(__file__, cut_surfaces(grid, model.X, labels))
