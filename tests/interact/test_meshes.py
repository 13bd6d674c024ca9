"""MeshShape (torchdeform.interact.meshes) against independent oracles.

* an icosphere against the analytic ball ``|p| - r`` (distance within 1.5 spacings everywhere, the
  faceting error of the exact icosphere geometry below 1% of r) and its normals ``p / |p|``;
* a box mesh against the analytic :class:`~torchdeform.interact.Box`: exact (1e-10) where the
  distance is linear around a point, within a spacing away from edges and corners, same normals;
* a torus (not convex) against trimesh's exact signed distance (opposite sign convention), and
  ``p - d n`` lands on the surface by trimesh's exact distance (within a spacing);
* packed ``(B, 3, P)`` and grid ``(B, 3, D, H, W)`` layouts give the same values; float32 works;
* bad meshes, paths and resolutions are one-line ConfigErrors; a grid too coarse for a thin mesh warns;
* as a tool in ProjectionContact: no node ends deeper than a spacing inside the mesh, and the
  packed model takes the same contact steps.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from torchdeform.errors import ConfigError
from torchdeform.interact import Box, ProjectionContact, Tool
from torchdeform.interact.meshes import MeshShape
from torchdeform.sim.packed import PackedModel

R = 0.01


@pytest.fixture(scope="module")
def icosphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=R)


@pytest.fixture(scope="module")
def ball(icosphere):
    return MeshShape(icosphere, resolution=32)


@pytest.fixture(scope="module")
def torus():
    mesh = trimesh.creation.torus(major_radius=0.01, minor_radius=0.004, major_sections=48, minor_sections=24)
    return mesh, MeshShape(mesh, resolution=40)


def _sdf(shape, p: np.ndarray, device="cpu"):
    """``shape.sdf`` at points ``(M, 3)`` (evaluated on ``device``), as numpy ``d`` ``(M,)`` and ``n`` ``(M, 3)``."""
    d, n = shape.sdf(torch.from_numpy(np.ascontiguousarray(p.T))[None].to(device))
    return d[0, 0].cpu().numpy(), n[0].cpu().numpy().T


def _points(n, scale, seed=0):
    return np.random.default_rng(seed).uniform(-scale, scale, size=(n, 3))


def test_icosphere_matches_the_analytic_ball(icosphere, ball, device):
    h = ball.spacing
    assert ball.shape == (32, 32, 32) and ball.field.dtype == torch.float64
    assert ball.field.shape == (1, 1, 32, 32, 32) and ball.gradient.shape == (1, 3, 32, 32, 32)
    # the exact icosphere lies between its inscribed ball (face planes) and the ball of radius r
    tri = icosphere.triangles
    inradius = np.abs(np.einsum("fi,fi->f", icosphere.face_normals, tri[:, 0])).min()
    assert R - inradius < 0.01 * R < h

    p = _points(4000, 1.5 * R)  # the box is +-1.2 r: some outside
    r = np.linalg.norm(p, axis=1)
    d, n = _sdf(ball, p, device)
    err = np.abs(d - (r - R))
    assert err.max() < 1.5 * h
    # away from the kink at the centre, only interpolation and faceting errors remain (measured:
    # 0.07 h near the surface, 0.09 h in the box, 0.24 h beyond it)
    in_box = (np.abs(p) < 1.2 * R).all(1)
    assert err[np.abs(r - R) < 2 * h].max() < 0.1 * h
    assert err[in_box & (r > 0.3 * R)].max() < 0.15 * h
    assert err[~in_box].max() < 0.5 * h
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    cos = np.einsum("mi,mi->m", n, p / r[:, None])
    assert cos[in_box & (r > 0.3 * R)].min() > 0.995 and cos[r > 0.3 * R].min() > 0.98
    # far outside the sampled box the distance keeps growing
    d_far, n_far = _sdf(ball, np.array([[0.1, 0.0, 0.0], [0.0, -0.05, 0.05]]), device)
    assert np.allclose(d_far, [0.1 - R, np.hypot(0.05, 0.05) - R], atol=1.5 * h)
    assert np.allclose(n_far[0], [1.0, 0.0, 0.0], atol=1e-6)


def test_box_mesh_matches_the_analytic_box(device):
    half = np.array([0.01, 0.006, 0.004])
    shape = MeshShape(trimesh.creation.box(extents=2 * half), resolution=32)
    h = shape.spacing
    assert shape.shape[0] == 32 and shape.shape[0] > shape.shape[1] > shape.shape[2]  # mesh x, y, z = D, H, W
    p = _points(6000, 1.0, seed=1) * 1.3 * half
    d, n = _sdf(shape, p, device)
    d_ref, n_ref = _sdf(Box(tuple(half)), p)  # the analytic box on the CPU
    q = np.abs(p) - half  # > 0 outside along that axis
    # a face's region, 3 spacings clear of every other face's: the distance is linear around it
    face = np.argmax(q, axis=1)
    others = np.sort(q, axis=1)[:, :2]
    slab = (others[:, 1] < -3 * h) & (q.max(1) - others[:, 1] > 3 * h)
    assert slab.sum() > 500
    assert np.abs(d - d_ref)[slab].max() < 1e-10
    assert np.abs(n - n_ref)[slab].max() < 1e-9
    assert np.all(np.abs(n[slab, face[slab]]) > 1 - 1e-12)
    # away from edges and corners (two axes both within 2 spacings of their faces)
    near_edge = (np.abs(q) < 2 * h).sum(1) >= 2
    assert np.abs(d - d_ref)[~near_edge].max() < h
    assert np.abs(d - d_ref).max() < 1.5 * h


def test_torus_matches_trimesh_and_projection_lands_on_the_surface(torus):
    mesh, shape = torus
    h = shape.spacing
    exact = trimesh.proximity.ProximityQuery(mesh)
    p = _points(600, 0.016, seed=2) * np.array([1.0, 1.0, 0.4])
    ref = -exact.signed_distance(p)  # trimesh: positive inside
    d, n = _sdf(shape, p)
    assert np.abs(d - ref).max() < h
    assert (np.sign(d) == np.sign(ref))[np.abs(ref) > h].all()
    near = np.abs(ref) < 0.5 * 0.004  # within half the tube radius
    assert near.sum() > 100
    on = p[near] - d[near, None] * n[near]
    assert np.abs(exact.signed_distance(on)).max() < h


def test_packed_and_grid_layouts_agree_and_float32_works(ball, device):
    x = torch.from_numpy(_points(2 * 4 * 5 * 6, 1.3 * R, seed=3)).T.reshape(3, 2, 4, 5, 6).transpose(0, 1)
    x = x.contiguous().to(device)  # (B, 3, D, H, W)
    d, n = ball.sdf(x)
    assert d.shape == (2, 1, 4, 5, 6) and n.shape == (2, 3, 4, 5, 6) and d.dtype == torch.float64
    dp, n_p = ball.sdf(x.reshape(2, 3, -1))
    assert torch.equal(dp, d.reshape(2, 1, -1)) and torch.equal(n_p, n.reshape(2, 3, -1))
    d1, _ = ball.sdf(x[1:])
    assert torch.equal(d1, d[1:])
    d32, n32 = ball.sdf(x.float())
    assert d32.dtype == n32.dtype == torch.float32
    assert torch.allclose(d32.double(), d, atol=1e-7) and torch.allclose(n32.double(), n, atol=1e-5)
    # differentiable in the points: the gradient of d (of the trilinear interpolant, its length
    # within about 10% of 1) points along the normal
    xg = x.reshape(2, 3, -1).clone().requires_grad_(True)
    dg, ng = ball.sdf(xg)
    (g,) = torch.autograd.grad(dg.sum(), xg)
    keep = xg.detach().norm(dim=1) > 0.3 * R
    assert ((g * ng).sum(1) / g.norm(dim=1))[keep].min() > 0.98
    assert ((g.norm(dim=1) - 1).abs()[keep] < 0.2).all()


def test_a_mesh_file_gives_the_same_field(tmp_path, icosphere, ball):
    path = tmp_path / "ball.stl"
    icosphere.export(str(path))
    for source in (path, str(path)):
        s = MeshShape(source, resolution=32)
        assert s.shape == ball.shape and np.allclose(s.origin, ball.origin, rtol=0, atol=1e-9)
        # STL keeps float32 vertices in another order: the same field, exactly so near the surface
        # (away from it the flooding may settle on another of the nearly equidistant triangles)
        near = ball.field.abs() < 2 * ball.spacing
        assert torch.allclose(s.field[near], ball.field[near], rtol=0, atol=1e-9)
        assert torch.allclose(s.field, ball.field, rtol=0, atol=0.25 * ball.spacing)


@pytest.mark.parametrize(
    "kwargs, key, words",
    [
        ({"resolution": 2}, "mesh_shape.resolution", "integer >= 4"),
        ({"resolution": 16.0}, "mesh_shape.resolution", "integer >= 4"),
        ({"resolution": True}, "mesh_shape.resolution", "integer >= 4"),
        ({"padding": -0.1}, "mesh_shape.padding", ">= 0"),
    ],
)
def test_bad_parameters_raise(icosphere, kwargs, key, words):
    with pytest.raises(ConfigError) as e:
        MeshShape(icosphere, **kwargs)
    assert e.value.key == key and words in str(e.value) and "\n" not in str(e.value)


def test_bad_meshes_raise(tmp_path, icosphere):
    holed = icosphere.copy()
    holed.update_faces(np.arange(len(holed.faces)) >= 3)  # three triangles removed
    with pytest.raises(ConfigError, match="closed") as e:
        MeshShape(holed)
    assert e.value.key == "mesh" and "open edges" in str(e.value)
    missing = tmp_path / "no" / "such.stl"
    with pytest.raises(ConfigError) as e:
        MeshShape(missing)
    assert str(missing) in str(e.value) and "\n" not in str(e.value)
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 not a mesh")
    with pytest.raises(ConfigError) as e:
        MeshShape(str(garbage))
    assert str(garbage) in str(e.value)
    with pytest.raises(ConfigError, match="triangle"):
        MeshShape(trimesh.Trimesh())


def test_a_grid_too_coarse_for_a_thin_mesh_warns():
    needle = trimesh.creation.cylinder(radius=0.0005, height=0.03, sections=16)  # along W
    with pytest.warns(UserWarning, match="raise resolution"):
        MeshShape(needle, resolution=16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fine = MeshShape(needle, resolution=160)
    assert fine.shape[2] == 160 and fine.shape[0] == fine.shape[1] < 160
    d, _ = _sdf(fine, np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], [0.0015, 0.0, 0.0], [0.0, 0.0015, 0.01]]))
    assert np.allclose(d[:2], -0.0005, atol=fine.spacing)  # the axis is a kink: within a spacing
    assert np.allclose(d[2:], 0.001, atol=0.1 * fine.spacing)


def test_mesh_tool_in_projection_contact(icosphere, ball, device):
    grid = td.Grid((5, 5, 5), spacing=0.01)
    path = [(0.0, (0.05, 0.02, 0.02)), (0.1, (0.045, 0.02, 0.02))]
    probe = Tool(ball, path=path)
    model = td.Model(
        grid,
        stiffness=20.0,
        damping=0.01,
        mass=1e-3,
        fixed=grid.face("bottom"),
        interactions=[ProjectionContact(probe)],
        dtype=torch.float64,
        device=device,
    )
    state, _ = td.simulate(model, model.rest_state(), dt=1e-3, steps=100)
    d, _ = probe.sdf(state.x, state.t)
    assert float(d.min()) > -0.1 * ball.spacing  # projected to the field's zero level
    centre = np.array(probe.position(state.t))
    x = state.x[0].reshape(3, -1).T.cpu().numpy() - centre
    depth = trimesh.proximity.ProximityQuery(icosphere).signed_distance(x)  # > 0 inside
    assert depth.max() < ball.spacing
    # the top layer was pushed: the probe went 5 mm below it
    assert float(state.x[0, 0, -1].min()) < 0.04 - 0.002

    # the packed layout (the compiled path's) takes the same contact steps
    pm = PackedModel(model)
    s, packed = model.rest_state(), pm.rest_state()
    integ = td.SymplecticEuler()
    for _ in range(30):
        s = integ.step(model, s, 2e-3)
        packed = integ.step(pm, packed, 2e-3)
    assert float(s.x[0, 0, -1].min()) < 0.04 - 0.001
    assert torch.allclose(pm.unpack_state(packed).x, s.x, atol=1e-14, rtol=0)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_tool_surfaces_are_the_tool_shapes_where_the_tools_are(axis):
    """Oracle: each shape's own signed distance is zero on its drawn surface (to the tessellation's
    chord error), the surface is closed and outward (positive volume), and it moves and turns with the tool."""
    import trimesh

    from torchdeform.interact import Box, Capsule, Sphere, Tool
    from torchdeform.interact.meshes import tool_surface

    rot = [0.0, 0.0, 0.0]
    rot[(axis + 1) % 3] = 0.4
    for shape in (Sphere(0.01), Capsule(0.005, 0.02, axis=axis), Box((0.01, 0.02, 0.005))):
        tool = Tool(shape, path=[(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), (1.0, [0.1, 0.2, 0.3], rot)])
        v, f = tool_surface(tool, 1.0, detail=4)
        mesh = trimesh.Trimesh(v, f, process=False)
        assert mesh.is_watertight and mesh.volume > 0
        R = torch.as_tensor(trimesh.transformations.rotation_matrix(0.4, np.eye(3)[(axis + 1) % 3])[:3, :3])
        local = (torch.as_tensor(v) - torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)) @ R  # R^T (p - c)
        d, _ = shape.sdf(local.T.reshape(1, 3, -1))
        assert float(d.abs().max()) < 2e-4  # chord error of the tessellation, metres
