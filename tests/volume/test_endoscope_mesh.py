"""Triangle meshes (embedded organ surfaces) in the endoscope's view: :class:`~torchdeform.volume.Mesh`.

Oracles: the analytic sphere a fine triangulated sphere approximates (trimesh's icosphere), a flat
square's plane, and the analytic depth compositing of a surface in front of a slab.
"""

from __future__ import annotations

import pytest
import torch
import trimesh

from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.volume import EndoscopeCamera, Mesh, Sphere, TransferFunction, render_endoscope


def _icosphere(centre, radius, subdivisions=4):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(torch.tensor(ico.vertices) + torch.tensor(centre), torch.tensor(ico.faces), (0.8, 0.3, 0.3))


def test_a_triangulated_sphere_is_hit_where_the_sphere_is():
    cam = EndoscopeCamera(position=(10.0, 10.0, 1.0), direction=(0, 0, 1), fov=60.0, size=(21, 21), mask=False)
    eye, d, _ = cam.rays((20, 20, 20), dtype=F64)
    d = d.reshape(3, -1)
    centre, radius = (10.3, 9.8, 12.0), 4.0
    mesh = _icosphere(centre, radius)
    t_mesh, n_mesh = mesh.hit(eye, d)
    t_ball, n_ball = Sphere(centre, radius, (1, 1, 1)).hit(eye, d)
    both = torch.isfinite(t_ball) & torch.isfinite(t_mesh)
    assert int(both.sum()) > 100 and bool((torch.isfinite(t_mesh) <= torch.isfinite(t_ball)).all())
    # the triangles lie inside the sphere by at most the sag of their planes: along a ray meeting the
    # surface at incidence cos, the hit comes at most sag / cos later
    a = mesh.vertices[mesh.faces[:, 0]] - torch.tensor(centre, dtype=F64)
    e1 = mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]]
    e2 = mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]]
    n = torch.linalg.cross(e1, e2)
    sag = radius - float(((a * n).sum(1).abs() / n.norm(dim=1)).min())
    incidence = (n_ball[:, both] * d[:, both]).sum(0).abs()
    steep = incidence > 0.3
    err = (t_mesh[both] - t_ball[both])[steep]
    assert 0 < sag < 0.01 * radius and bool((err >= -1e-9).all())
    assert bool((err <= sag / incidence[steep] + 1e-9).all()), float((err * incidence[steep]).max() / sag)
    cos = (n_mesh[:, both] * n_ball[:, both]).sum(0).abs()
    assert float(cos.min()) > 0.99


def test_a_square_is_hit_on_its_plane_and_missed_beside_it():
    sq = Mesh(
        [[-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [1.0, 1.0, 5.0], [-1.0, 1.0, 5.0]], [[0, 1, 2], [0, 2, 3]], (1, 1, 1)
    )
    g = torch.linspace(-0.5, 0.5, 7, dtype=F64)
    dirs = torch.stack([g.repeat(7), g.repeat_interleave(7), torch.ones(49, dtype=F64)])
    dirs = dirs / dirs.norm(dim=0)
    t, n = sq.hit(torch.zeros(3, dtype=F64), dirs)
    inside = (5.0 * dirs[0] / dirs[2]).abs().le(1) & (5.0 * dirs[1] / dirs[2]).abs().le(1)
    assert torch.allclose(t[inside], 5.0 / dirs[2][inside], rtol=0, atol=1e-12)
    assert bool(torch.isinf(t[~inside]).all()) and bool((n[2, inside].abs() == 1).all())
    t_behind, _ = sq.hit(torch.tensor([0.0, 0.0, 6.0], dtype=F64), dirs)  # the square is behind this eye
    assert bool(torch.isinf(t_behind).all())


def test_a_mesh_hides_the_slab_behind_it():
    vol = torch.zeros(16, 16, 24, dtype=F64)
    vol[:, :, 16:] = 100.0  # a bright slab far along W
    tf = TransferFunction([0.0, 100.0], [[0, 0, 0], [0.2, 0.9, 0.2]], [0.0, 5.0])
    cam = EndoscopeCamera(position=(7.5, 7.5, 2.0), direction=(0, 0, 1), fov=40.0, size=(9, 9), mask=False)
    plate = Mesh([[3.0, 3.0, 8.0], [12.0, 3.0, 8.0], [12.0, 12.0, 8.0], [3.0, 12.0, 8.0]], [[0, 1, 2], [0, 2, 3]],
                 (1.0, 0.0, 0.0))  # fmt: skip
    bare, depth_bare = render_endoscope(vol, cam, tf=tf, light=None, return_depth=True)
    img, depth = render_endoscope(vol, cam, tf=tf, light=None, surfaces=[plate], return_depth=True, engine="torch")
    centre = img[0, :, 4, 4]
    assert torch.allclose(centre, torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=F64), atol=1e-9)  # the plate, opaque
    assert abs(float(depth[0, 4, 4]) - 6.0) < 1e-9 and float(depth_bare[0, 4, 4]) > 13.5  # the slab was behind
    assert float(bare[0, 1, 4, 4]) > 4 * float(bare[0, 0, 4, 4]) > 0  # without the plate: the slab's green


def test_bad_meshes_are_refused():
    with pytest.raises(ConfigError, match=r"mesh\.faces"):
        Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], (1, 1, 1))
    with pytest.raises(ConfigError, match=r"mesh\.vertices"):
        Mesh([[0.0, 0], [1, 0]], [[0, 1, 1]], (1, 1, 1))
