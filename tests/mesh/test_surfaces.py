"""Surface extraction (marching tetrahedra) and export: analytic sphere, rigid moves, trimesh round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

trimesh = pytest.importorskip("trimesh")

from torchdeform.errors import ConfigError
from torchdeform.mesh import body_surface, marching_tetrahedra, save_surface, volume_surface


def sphere_field(n, R, centre=None):
    c = (n - 1) / 2 if centre is None else centre
    g = np.stack(np.meshgrid(*[np.arange(n, dtype=np.float64)] * 3, indexing="ij"))
    return R - np.sqrt(((g - np.reshape(c, (-1, 1, 1, 1))) ** 2).sum(0))


@pytest.mark.parametrize("R,n", [(6.0, 16), (10.0, 25)])
def test_sphere_is_watertight_with_analytic_volume_and_area(R, n):
    v, f = marching_tetrahedra(sphere_field(n, R), level=0.0)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # faces point outwards
    # linear interpolation on the tetrahedra: second-order error, < 1.5% at 6 voxels, < 0.6% at 10
    tol = 0.015 if R < 8 else 0.006
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * R**3, rel=tol)
    assert mesh.area == pytest.approx(4 * math.pi * R**2, rel=tol)
    r = np.linalg.norm(v - (n - 1) / 2, axis=1)
    assert np.abs(r - R).max() < 0.1  # vertices on the sphere


def test_border_is_closed_and_nodes_on_the_level_keep_it_manifold():
    m = np.ones((5, 6, 7))  # touches every face of the grid
    v, f = marching_tetrahedra(m)
    mesh = trimesh.Trimesh(v, f)  # process=True merges vertices
    assert mesh.is_watertight and mesh.volume > 0
    assert np.allclose(v.min(0), -0.5) and np.allclose(v.max(0), np.array(m.shape) - 0.5)
    # integer radius: grid nodes exactly on the level
    v, f = marching_tetrahedra(sphere_field(21, 8.0), level=0.0)
    assert trimesh.Trimesh(v, f).is_watertight


def test_uniform_displacement_moves_the_body_surface():
    spacing = torch.tensor([0.002, 0.003, 0.0025], dtype=torch.float64).view(3, 1, 1, 1)
    idx = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float64) for n in (6, 7, 5)], indexing="ij"))
    X = idx * spacing
    mask = torch.zeros(6, 7, 5, dtype=torch.bool)
    mask[1:5, 2:6, 1:4] = True
    mask[2, 3, 0] = True
    d = torch.tensor([0.01, -0.004, 0.007], dtype=torch.float64)
    v0, f0 = body_surface(X, node_mask=mask)
    v1, f1 = body_surface(X + d.view(3, 1, 1, 1), node_mask=mask)
    assert np.array_equal(f0, f1)
    assert np.abs(v1 - v0 - d.numpy()).max() < 1e-12
    assert trimesh.Trimesh(v0, f0).is_watertight
    # rest geometry: vertex = index * spacing (linear extrapolation half a cell beyond the grid)
    q, _ = marching_tetrahedra(mask.double())
    assert np.abs(v0 - q * spacing.view(1, 3).numpy()).max() < 1e-12


def test_warped_volume_surface_moves_by_the_offset():
    vol = torch.tensor(sphere_field(24, 6.3, centre=(10.0, 11.0, 12.0)))  # no node exactly on the level
    d = (2.0, -3.0, 1.0)
    offsets = torch.tensor(d, dtype=torch.float64).view(3, 1, 1, 1).expand(3, 4, 4, 4)
    v0, f0 = volume_surface(vol, 0.0)
    v1, f1 = volume_surface(vol, 0.0, offsets=offsets, check=False)
    assert len(f0) == len(f1)
    assert np.allclose(np.sort(v1 - np.array(d), axis=0), np.sort(v0, axis=0), atol=1e-6)


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_export_round_trips_through_trimesh(tmp_path, suffix):
    v, f = marching_tetrahedra(sphere_field(14, 5.0), level=0.0)
    ref = trimesh.Trimesh(v, f, process=False)
    save_surface(tmp_path / f"s{suffix}", v, f)
    back = trimesh.load(tmp_path / f"s{suffix}", force="mesh")
    assert back.is_watertight
    assert back.volume == pytest.approx(ref.volume, rel=1e-5)
    assert np.allclose(back.bounds, ref.bounds, atol=1e-5)


def test_surface_bad_input(tmp_path):
    v, f = marching_tetrahedra(sphere_field(8, 2.5), level=0.0)
    with pytest.raises(ConfigError, match=r"\.ply, \.stl or \.obj"):
        save_surface(tmp_path / "s.vtk", v, f)
    with pytest.raises(ConfigError, match="3-D"):
        marching_tetrahedra(np.zeros((4, 4)))
    with pytest.raises(ConfigError, match="finite"):
        marching_tetrahedra(np.full((3, 3, 3), np.nan))
    with pytest.raises(ConfigError, match="grid shape"):
        body_surface(torch.zeros(3, 4, 4, 4), node_mask=torch.ones(3, 3, 3, dtype=torch.bool))
