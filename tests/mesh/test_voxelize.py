"""Voxelising closed triangle meshes: node counts against analytic inside tests."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from torchdeform import ConfigError, Grid
from torchdeform.mesh import grid_from_mesh, voxelize


def _nodes(origin, shape, spacing):
    """Node positions ``(D, H, W, 3)`` of a grid (independent of the library)."""
    spacing = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))
    axes = [o + s * np.arange(n) for o, s, n in zip(origin, spacing, shape)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def _in_box(P, lo, hi, tol=1e-12):
    return np.all((np.asarray(lo) - tol <= P) & (np.asarray(hi) + tol >= P), axis=-1)


def test_box_with_nodes_on_its_faces_keeps_them():
    """A 1 cm box on a 1 mm grid: the grid spans the box, every node is inside or on it."""
    mask, origin, shape = voxelize(trimesh.creation.box((0.01, 0.01, 0.01)), 0.001)
    assert shape == (11, 11, 11)
    assert np.allclose(origin, (-0.005,) * 3)
    assert mask.dtype == torch.bool and tuple(mask.shape) == shape
    assert int(mask.sum()) == 11**3


def test_translated_anisotropic_box_matches_analytic_count():
    lo, hi = np.array([0.02, -0.01, 0.003]), np.array([0.0305, 0.0023, 0.0111])
    box = trimesh.creation.box(hi - lo)
    box.apply_translation((lo + hi) / 2)
    spacing = (0.001, 0.0015, 0.0007)
    mask, origin, shape = voxelize(box, spacing)
    P = _nodes(origin, shape, spacing)
    expected = _in_box(P, lo, hi)
    assert P[..., 0].min() <= lo[0] + 1e-12 and P[..., 0].max() >= hi[0] - 1e-12  # covers the box
    assert np.array_equal(mask.numpy(), expected)


def test_icosphere_matches_convex_halfspace_test():
    """Inside a convex polyhedron iff on the inner side of every face plane."""
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.01)
    ico.apply_translation((0.001, -0.002, 0.0005))
    spacing = 0.0007
    mask, origin, shape = voxelize(ico, spacing)
    P = _nodes(origin, shape, spacing).reshape(-1, 3)
    n = ico.face_normals
    offset = np.einsum("fc,fc->f", ico.triangles[:, 0], n)
    expected = np.all(P @ n.T - offset <= 1e-12, axis=1).reshape(shape)
    assert 5000 < expected.sum() < np.prod(shape)
    assert np.array_equal(mask.numpy(), expected)


def test_hollow_box_two_shells():
    """A box with a closed cavity (outer shell + inverted inner shell): parity handles it."""
    outer = trimesh.creation.box((0.0105,) * 3)
    inner = trimesh.creation.box((0.0051,) * 3)
    inner.invert()
    hollow = trimesh.util.concatenate([outer, inner])
    assert hollow.is_watertight
    mask, origin, shape = voxelize(hollow, 0.001)
    P = _nodes(origin, shape, 0.001)
    expected = _in_box(P, [-0.00525] * 3, [0.00525] * 3) & ~_in_box(P, [-0.00255] * 3, [0.00255] * 3)
    assert shape == (12, 12, 12)
    assert int(mask.sum()) == int(expected.sum()) == 10**3 - 6**3
    assert np.array_equal(mask.numpy(), expected)


def test_padding_and_scale():
    box = trimesh.creation.box((10.0, 10.0, 10.0))  # millimetres
    mask, origin, shape = voxelize(box, 0.001, padding=2, scale=1e-3)
    assert shape == (15, 15, 15)
    assert np.allclose(origin, (-0.007,) * 3)
    assert int(mask.sum()) == 11**3
    assert not bool(mask[:2].any()) and not bool(mask[-2:].any())


def test_axis_convention_x_to_d():
    """Mesh x, y, z map to grid axes D, H, W."""
    _mask, _origin, shape = voxelize(trimesh.creation.box((0.004, 0.002, 0.001)), 0.001)
    assert shape == (5, 3, 2)


def test_grid_from_stl_file(tmp_path):
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.005).export(path)
    grid = grid_from_mesh(path, 0.001, topology=6)
    assert isinstance(grid, Grid) and grid.topology == 6
    mask, origin, shape = voxelize(path, 0.001)
    assert grid.shape == shape and grid.origin == pytest.approx(origin)
    assert torch.equal(grid.nodes(), mask)
    assert 0 < grid.num_nodes < np.prod(shape)
    # a node on the centre axis is inside; the corners of the bounding box are not
    assert bool(grid.nodes()[5, 5, 5]) and not bool(grid.nodes()[0, 0, 0])


def test_voxelised_body_gets_positive_masses_from_a_density():
    """The poles of a sphere are lone inside nodes; they still get mass and move."""
    grid = grid_from_mesh(trimesh.creation.icosphere(subdivisions=2, radius=0.005), 0.001, topology=26)
    assert bool(grid.nodes()[0, 5, 5]) and not bool(grid.nodes()[0, 4:7, 4:7].all())
    model = td.Model(grid, 1.0, density=1000.0)
    assert bool((model.mass[0, 0][grid.nodes()] > 0).all())


def test_missing_file_is_config_error(tmp_path):
    with pytest.raises(ConfigError, match=r"mesh: expected an existing mesh file.*nope\.stl"):
        voxelize(tmp_path / "nope.stl", 0.001)


def test_open_mesh_is_config_error(tmp_path):
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])  # one side missing
    with pytest.raises(ConfigError, match=r"closed \(watertight\) triangle mesh.*4 open edges"):
        voxelize(open_box, 0.001)
    path = tmp_path / "open.stl"
    open_box.export(path)
    with pytest.raises(ConfigError, match="closed"):
        grid_from_mesh(path, 0.001, topology=26)


def test_unreadable_file_and_bad_arguments(tmp_path):
    bad = tmp_path / "junk.stl"
    bad.write_bytes(b"\x00\x01 not a mesh")
    with pytest.raises(ConfigError, match="mesh"):
        voxelize(bad, 0.001)
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    with pytest.raises(ConfigError, match="spacing"):
        voxelize(box, -1.0)
    with pytest.raises(ConfigError, match="padding"):
        voxelize(box, 0.001, padding=-1)
    with pytest.raises(ConfigError, match="spacing small enough"):
        voxelize(trimesh.creation.icosphere(radius=0.001), 0.05)  # no node falls inside


def test_agrees_with_trimesh_signed_distance():
    import rtree  # noqa: F401  (in the test extra; trimesh.contains needs it)

    mesh = trimesh.creation.annulus(r_min=0.003, r_max=0.008, height=0.004)
    mask, origin, shape = voxelize(mesh, 0.0007)
    P = _nodes(origin, shape, 0.0007).reshape(-1, 3)
    d = trimesh.proximity.signed_distance(mesh, P)
    clear = np.abs(d) > 1e-9  # not on the surface
    assert np.array_equal(mask.numpy().reshape(-1)[clear], mesh.contains(P)[clear])


def test_trimesh_not_imported_with_the_package():
    code = "import sys, torchdeform, torchdeform.scene; assert 'trimesh' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
