"""Embedded surfaces and label surfaces.

Oracles, each independent of the code under test:

- the input vertices themselves (the lattice at rest carries them where they were);
- affine maps, which trilinear weights reproduce exactly (``x -> A x + b`` moves every vertex by
  ``A v + b``), and rigid rotations, which turn the normals by the same rotation;
- ``scipy.interpolate.RegularGridInterpolator`` (linear) for positions on a random lattice;
- a plain numpy loop over faces for area-weighted normals;
- the analytic sphere: an icosphere's normals are radial; a ball of radius ``r`` voxels seen through
  a rotated, anisotropic, mirrored affine has its surface on the mapped sphere, volume
  ``4/3 pi r^3 |det A|``, outward normals; trimesh for watertightness and file round trips;
- for cuts by a sheet of patches: the lattice's own blade (:class:`torchdeform.topology.Blade`) for
  the sheet's geometry, points sampled along each triangle's trace on a patch's plane (a split
  triangle has none strictly inside the patch), ``scipy.sparse.csgraph.connected_components`` for
  the pieces, the original triangles for what lies beyond the sheet, and the rest surface's area.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

trimesh = pytest.importorskip("trimesh")

import torchdeform as td
from torchdeform.errors import ConfigError
from torchdeform.mesh import EmbeddedSurface, grid_from_mesh, label_surfaces

F64 = torch.float64
SHAPE, SPACING, ORIGIN = (5, 6, 7), (0.004, 0.006, 0.003), (-0.01, 0.02, 0.005)


def lattice(**kw) -> td.Grid:
    return td.Grid(SHAPE, spacing=SPACING, origin=ORIGIN, **kw)


def random_points(rng, n, *, outside=0.5):
    """Points in the lattice box widened by ``outside`` spacings on every side (metres)."""
    lo = np.asarray(ORIGIN) - outside * np.asarray(SPACING)
    hi = np.asarray(ORIGIN) + (np.asarray(SHAPE) - 1 + outside) * np.asarray(SPACING)
    return lo + rng.random((n, 3)) * (hi - lo)


def icosphere_in(grid: td.Grid, *, subdivisions=3, fill=0.4):
    """An icosphere centred in the lattice box, radius ``fill`` of its smallest half-extent."""
    extent = (np.asarray(grid.shape) - 1) * np.asarray(grid.spacing)
    centre = np.asarray(grid.origin) + extent / 2
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=fill * extent.min())
    return np.asarray(ball.vertices) + centre, np.asarray(ball.faces), centre


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def map_lattice(grid, A, b, *, device=None) -> torch.Tensor:
    """Node positions ``A X + b`` of the whole lattice, ``(1, 3, D, H, W)`` float64."""
    X = grid.rest_positions(dtype=F64, device=device)
    A_ = torch.as_tensor(A, dtype=F64, device=device)
    b_ = torch.as_tensor(b, dtype=F64, device=device)
    return torch.einsum("ij,bjdhw->bidhw", A_, X) + b_.view(1, 3, 1, 1, 1)


def numpy_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, one face at a time."""
    out = np.zeros_like(p)
    for a, b, c in faces:
        n = np.cross(p[b] - p[a], p[c] - p[a])
        out[a] += n
        out[b] += n
        out[c] += n
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


# ------------------------------------------------------------------------- at rest
def test_rest_lattice_carries_random_points_exactly():
    rng = np.random.default_rng(1)
    v = random_points(rng, 400)
    surf = EmbeddedSurface(v, [[0, 1, 2]], lattice(), dtype=F64)
    p = surf.positions(lattice().rest_positions(dtype=F64))
    assert p.shape == (1, 400, 3)
    assert np.abs(p[0].numpy() - v).max() < 1e-9
    w = surf.weights.numpy()
    assert np.allclose(w.sum(1), 1.0, atol=1e-12)
    assert surf.corners.dtype == torch.int64 and surf.corners.shape == (400, 8)
    assert int(surf.corners.min()) >= 0 and int(surf.corners.max()) < math.prod(SHAPE)


def test_rest_lattice_carries_an_icosphere():
    grid = lattice()
    v, f, _ = icosphere_in(grid)
    surf = EmbeddedSurface(v, f, grid, dtype=F64)
    p = surf.positions(grid.rest_positions(dtype=F64)[0])  # one body (3, D, H, W) -> (V, 3)
    assert p.shape == (len(v), 3)
    assert np.abs(p.numpy() - v).max() < 1e-9
    assert torch.equal(surf.texcoords, surf.rest_vertices) and torch.equal(surf.faces, torch.as_tensor(f))


def test_positions_match_scipy_linear_interpolation_on_a_random_lattice():
    from scipy.interpolate import RegularGridInterpolator

    rng = np.random.default_rng(2)
    grid = lattice()
    v = random_points(rng, 300, outside=0.0)
    surf = EmbeddedSurface(v, [[0, 1, 2]], grid, dtype=F64)
    x = grid.rest_positions(dtype=F64) + 1e-3 * torch.randn((1, 3, *SHAPE), dtype=F64)
    axes = [o + s * np.arange(n) for o, s, n in zip(ORIGIN, SPACING, SHAPE)]
    want = np.stack([RegularGridInterpolator(axes, x[0, c].numpy())(v) for c in range(3)], 1)
    assert np.abs(surf.positions(x)[0].numpy() - want).max() < 1e-12


# --------------------------------------------------------------------- deformations
def test_affine_maps_of_the_lattice_move_vertices_by_the_same_map(device):
    rng = np.random.default_rng(3)
    grid = lattice()
    A = np.eye(3) + 0.4 * rng.normal(size=(3, 3))
    if np.linalg.det(A) < 0:
        A[:, 0] *= -1
    b = rng.normal(size=3) * 0.01
    v = np.concatenate([random_points(rng, 200), icosphere_in(grid, subdivisions=2)[0]])
    surf = EmbeddedSurface(v, [[0, 1, 2]], grid, dtype=F64, device=device)
    p = surf.positions(map_lattice(grid, A, b, device=device))[0].cpu().numpy()
    assert np.abs(p - (v @ A.T + b)).max() < 1e-9


def test_rotation_turns_the_normals_and_icosphere_normals_point_outwards():
    rng = np.random.default_rng(4)
    grid = lattice()
    v, f, centre = icosphere_in(grid)
    surf = EmbeddedSurface(v, f, grid, dtype=F64)
    _, n0 = surf.update(grid.rest_positions(dtype=F64)[0])
    radial = (v - centre) / np.linalg.norm(v - centre, axis=1, keepdims=True)
    assert ((n0.numpy() * radial).sum(1) > 0.9).all()
    R = random_rotation(rng)
    b = np.array([0.01, -0.02, 0.003])
    p, n = surf.update(map_lattice(grid, R, b)[0])
    assert np.abs(p.numpy() - (v @ R.T + b)).max() < 1e-9
    assert np.abs(n.numpy() - n0.numpy() @ R.T).max() < 1e-9
    assert np.allclose(np.linalg.norm(n.numpy(), axis=1), 1.0, atol=1e-12)


def test_normals_match_a_face_loop_on_a_random_deformation():
    grid = lattice()
    v, f, _ = icosphere_in(grid, subdivisions=2)
    surf = EmbeddedSurface(v, f, grid, dtype=F64)
    x = grid.rest_positions(dtype=F64) + 5e-4 * torch.randn((1, 3, *SHAPE), dtype=F64)
    p, n = surf.update(x)
    assert np.abs(n[0].numpy() - numpy_normals(p[0].numpy(), f)).max() < 1e-12
    assert torch.equal(surf.normals(p), n) and torch.equal(surf.normals(p[0]), n[0])


def test_a_vertex_without_area_gets_a_zero_normal():
    grid = lattice()
    v = np.asarray(ORIGIN) + np.array(
        [[0.001, 0.001, 0.001], [0.002, 0.001, 0.001], [0.001, 0.002, 0.001], [0.003] * 3]
    )
    surf = EmbeddedSurface(v, [[0, 1, 2], [0, 0, 1]], grid, dtype=F64)  # vertex 3 unused, one degenerate face
    n = surf.normals(surf.rest_vertices)
    assert torch.equal(n[3], torch.zeros(3, dtype=F64)) and torch.isfinite(n).all()
    assert torch.allclose(n[:3], torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(3, 3))


def test_batches_equal_single_bodies_and_float32_agrees(dtype):
    grid = lattice()
    v, f, _ = icosphere_in(grid, subdivisions=2)
    x = grid.rest_positions(dtype=F64) + 5e-4 * torch.randn((3, 3, *SHAPE), dtype=F64)
    surf = EmbeddedSurface(v, f, grid, dtype=dtype)
    ref = EmbeddedSurface(v, f, grid, dtype=F64)
    p, n = surf.update(x)
    assert p.dtype == dtype and p.shape == n.shape == (3, len(v), 3)
    tol_p, tol_n = (5e-8, 1e-5) if dtype == torch.float32 else (1e-15, 1e-12)  # metres, unit vectors
    for k in range(3):
        pk, nk = ref.update(x[k])
        assert (p[k].double() - pk).abs().max() < tol_p and (n[k].double() - nk).abs().max() < tol_n


def test_positions_and_normals_are_differentiable():
    grid = td.Grid((2, 2, 3), spacing=0.01)
    v = np.array([[0.002, 0.003, 0.004], [0.007, 0.002, 0.013], [0.004, 0.008, 0.018]])
    surf = EmbeddedSurface(v, [[0, 1, 2]], grid, dtype=F64)
    x = (grid.rest_positions(dtype=F64) + 1e-3 * torch.randn((1, 3, 2, 2, 3), dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: surf.update(x)[0], (x,))
    assert torch.autograd.gradcheck(lambda x: surf.update(x)[1], (x,))


# ----------------------------------------------------------------------- node masks
def test_a_vertex_in_a_cell_with_a_missing_corner_is_an_error():
    mask = torch.ones(SHAPE, dtype=torch.bool)
    mask[4, 5, 6] = False  # the far corner node
    grid = lattice(node_mask=mask)
    rng = np.random.default_rng(5)
    inside = np.asarray(ORIGIN) + rng.random((20, 3)) * 2 * np.asarray(SPACING)  # the first cells
    far_cell = np.asarray(ORIGIN) + (np.asarray(SHAPE) - 1.5) * np.asarray(SPACING)
    v = np.concatenate([inside, far_cell[None], far_cell[None] - 1e-4])
    with pytest.raises(ConfigError, match=r"surface: .*body must cover the surface.*2 of 22 vertices"):
        EmbeddedSurface(v, [[0, 1, 2]], grid)
    EmbeddedSurface(inside, [[0, 1, 2]], grid)  # away from the missing node: fine


def test_a_mesh_on_the_outer_nodes_of_its_voxelised_body_embeds():
    box = trimesh.creation.box((0.01, 0.008, 0.006))
    grid = grid_from_mesh(box, 0.002, padding=1)
    assert grid.node_mask is not None
    surf = EmbeddedSurface(box.vertices, box.faces, grid, dtype=F64)  # vertices on the outermost nodes
    p = surf.positions(grid.rest_positions(dtype=F64))[0].numpy()
    assert np.abs(p - box.vertices).max() < 1e-9
    nodes = grid.node_mask.reshape(-1)[surf.corners.reshape(-1)]
    assert bool(nodes.all())


def test_bad_inputs_are_one_sentence_errors():
    grid = lattice()
    v, f, _ = icosphere_in(grid, subdivisions=1)
    with pytest.raises(ConfigError, match=r"within one spacing of the lattice box.*scale=1e-3"):
        EmbeddedSurface(v * 1000, f, grid)
    with pytest.raises(ConfigError, match="faces: expected vertex indices"):
        EmbeddedSurface(v, f + len(v), grid)
    surf = EmbeddedSurface(v, f, grid)
    with pytest.raises(ConfigError, match="x: expected node positions"):
        surf.positions(torch.zeros(3, 4, 4, 4))
    # a shape with spacing and origin builds the same lattice
    other = EmbeddedSurface(v, f, SHAPE, spacing=SPACING, origin=ORIGIN)
    assert torch.equal(other.corners, surf.corners)


# ----------------------------------------------------------------------------- files
def read_raw(path) -> dict:
    """Vertices, faces and vertex normals as stored in a .ply or .glb file."""
    from trimesh.exchange.gltf import load_glb
    from trimesh.exchange.ply import load_ply

    with open(path, "rb") as fh:
        if path.suffix == ".ply":
            return load_ply(fh)
        return next(iter(load_glb(fh)["geometry"].values()))


@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_save_writes_positions_and_normals(tmp_path, suffix):
    grid = lattice()
    v, f, _ = icosphere_in(grid, subdivisions=2)
    surf = EmbeddedSurface(v, f, grid)
    x = grid.rest_positions() * 1.1
    p, n = surf.update(x)
    out = tmp_path / f"organ{suffix}"
    surf.save(out, x)
    assert sorted(q.name for q in tmp_path.iterdir()) == [out.name]
    back = read_raw(out)  # what the file holds (trimesh.load recomputes the normals)
    assert np.abs(back["vertices"] - p[0].numpy()).max() < 1e-8
    assert np.abs(back["vertex_normals"] - n[0].numpy()).max() < 1e-6
    assert np.array_equal(np.asarray(back["faces"]), f)
    assert trimesh.load(out, force="mesh").is_watertight
    with pytest.raises(ConfigError, match=r"\.ply or \.glb"):
        surf.save(tmp_path / "organ.stl", x)


def test_from_file_reads_a_mesh_in_millimetres(tmp_path):
    grid = lattice()
    v, f, _ = icosphere_in(grid, subdivisions=2)
    path = tmp_path / "ball.stl"
    trimesh.Trimesh(v * 1000, f).export(path)
    surf = EmbeddedSurface.from_file(path, grid, scale=1e-3, dtype=F64)
    p = surf.positions(grid.rest_positions(dtype=F64))[0].numpy()
    assert np.abs(p - surf.rest_vertices.numpy()).max() < 1e-9
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(v).query(surf.rest_vertices.numpy())  # STL keeps float32 millimetres, not the order
    assert gap.max() < 1e-8 and surf.num_faces == len(f)


# -------------------------------------------------------------------- label surfaces
def needs_anatomy_extra():
    """scikit-image and fast-simplification are optional (``torchdeform[anatomy]``): skip without them."""
    pytest.importorskip("skimage.measure")
    pytest.importorskip("fast_simplification")


def ball_labels(n=30, r=9.0, label=3):
    c = np.array([14.3, 15.1, 13.7])
    d = np.sqrt(((np.indices((n, n, n)) - c[:, None, None, None]) ** 2).sum(0))
    return np.where(d <= r, label, 0).astype(np.int16), c, r


def rotated_flipped_affine():
    rng = np.random.default_rng(6)
    M = random_rotation(rng) @ np.diag([0.8e-3, 1.1e-3, 1.5e-3]) @ np.diag([1.0, -1.0, 1.0])
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = M, [0.01, -0.02, 0.03]
    assert np.linalg.det(M) < 0
    return A


def test_label_surface_of_a_ball_through_a_rotated_mirrored_affine():
    needs_anatomy_extra()
    labels, c, r = ball_labels()
    A = rotated_flipped_affine()
    M, t = A[:3, :3], A[:3, 3]
    surfaces = label_surfaces(labels, A)
    assert list(surfaces) == [3]
    v, f = surfaces[3]
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    u = (v - t) @ np.linalg.inv(M).T  # back to voxel indices
    assert np.abs(np.linalg.norm(u - c, axis=1) - r).max() < 1.0  # within a voxel of the true sphere
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * r**3 * abs(np.linalg.det(M)), rel=0.05)
    # outwards: each face normal against the gradient of |M^-1 (p - t) - c| at the face centre
    centre = (mesh.triangles_center - t) @ np.linalg.inv(M).T - c
    outward = centre @ np.linalg.inv(M)  # M^-T (u - c), as rows
    assert ((mesh.face_normals * outward).sum(1) > 0).all()


def test_label_surface_decimation_and_no_smoothing():
    needs_anatomy_extra()
    labels, _, _ = ball_labels(n=24, r=7.0)
    A = rotated_flipped_affine()
    raw_v, raw_f = label_surfaces(labels, A, smooth=0)[3]
    v, f = label_surfaces(labels, A, faces=500)[3]
    assert len(raw_f) > 500 >= len(f) > 400
    for vv, ff in ((raw_v, raw_f), (v, f)):
        mesh = trimesh.Trimesh(vv, ff, process=False)
        assert mesh.is_watertight and mesh.volume > 0


def test_label_surfaces_choose_labels_and_check_inputs(monkeypatch):
    needs_anatomy_extra()
    labels = np.zeros((10, 10, 10), dtype=np.int32)
    labels[2:5, 2:5, 2:5] = 1
    labels[6:9, 6:9, 6:9] = 7
    eye = np.eye(4) * 1e-3
    eye[3, 3] = 1.0
    assert sorted(label_surfaces(labels, eye, smooth=0)) == [1, 7]
    assert list(label_surfaces(labels, eye, which=7, smooth=0)) == [7]
    with pytest.raises(ConfigError, match=r"which: expected label values present in the volume \(\[1, 7\]\)"):
        label_surfaces(labels, eye, which=[1, 4])
    with pytest.raises(ConfigError, match="affine"):
        label_surfaces(labels, np.eye(3))
    monkeypatch.setitem(sys.modules, "skimage", None)
    monkeypatch.setitem(sys.modules, "skimage.measure", None)
    with pytest.raises(ConfigError, match=r"scikit-image .*pip install torchdeform\[anatomy\]"):
        label_surfaces(labels, eye)


def test_a_full_planar_cut_splits_the_embedded_surface_into_two_pieces_that_separate():
    """Oracles: the plane itself (no triangle has vertices on both sides); trimesh's connected
    components; the rest surface (the cut one lies where it was, to 1e-9); after the lattice is cut
    along the same plane and its ends are pulled apart, the sides' vertex sets are apart by more
    than the pull's opening minus the lattice's own stretch."""
    import trimesh

    import torchdeform as td
    from torchdeform.topology import Blade, cut

    h = 0.005
    grid = td.Grid((12, 7, 7), spacing=h, topology=26)
    ell = trimesh.creation.icosphere(4, radius=1.0)
    rest = ell.vertices * np.array([0.024, 0.013, 0.013]) + np.array([0.0275, 0.015, 0.015])
    surf = EmbeddedSurface(rest, ell.faces, grid, dtype=torch.float64)
    x0 = 0.0275 + 0.3 * h  # between node planes 5 and 6
    c = surf.cut((x0, 0.0, 0.0), (1.0, 0.0, 0.0))
    d = (c.rest_vertices[:, 0] - x0)[c.faces]
    assert bool(((d >= -1e-12).all(1) | (d <= 1e-12).all(1)).all())  # nothing straddles the plane
    at_rest = c.positions(grid.rest_positions(dtype=torch.float64))
    assert float((at_rest - c.rest_vertices).abs().max()) < 1e-9
    pieces = trimesh.Trimesh(c.rest_vertices.numpy(), c.faces.numpy(), process=False).split(only_watertight=False)
    assert len(pieces) == 2
    # cut the lattice on the same plane, then pull its two ends 4 mm apart, statically
    model = td.Model(grid, td.Elastic(3e3, 0.45), density=1000.0, dtype=torch.float64)
    blade = Blade((x0, -0.01, -0.01), (0.0, 0.06, 0.0), (0.0, 0.0, 0.06))
    assert cut(model, model.X, blade) > 0
    X = model.X[0]
    x = X.clone()
    x[0] = torch.where(X[0] > x0, X[0] + 0.002, X[0] - 0.002)  # each side moved rigidly
    p = c.positions(x)
    assert c.side is not None
    plus = c.side > 0
    assert bool((c.rest_vertices[plus, 0] >= x0 - 1e-12).all() & (c.rest_vertices[~plus, 0] <= x0 + 1e-12).all())
    gap = float(p[plus][:, 0].min() - p[~plus][:, 0].max())
    assert gap == pytest.approx(0.004, abs=1e-9)  # each side follows only its own nodes
    uncut = surf.positions(x)  # the uncut surface is stretched across the opening instead
    assert float(uncut[:, 0].max() - uncut[:, 0].min()) > float(rest[:, 0].max() - rest[:, 0].min()) + 0.0039


# ------------------------------------------------------------------ cuts by sheets of patches
def pieces(faces: np.ndarray, n_vertices: int) -> int:
    """Connected pieces of a triangle mesh (vertices joined by its edges), scipy's oracle."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    labels = connected_components(graph, directed=False)[1]
    return len(np.unique(labels[np.unique(faces)]))


def straddling_inside(v: np.ndarray, faces: np.ndarray, patch, *, margin=1e-6, samples=64) -> np.ndarray:
    """Bool ``(F,)``: the triangle has corners on both sides of the patch's plane and a point of its trace
    on that plane strictly inside the patch (``margin`` in patch coordinates), found by sampling the trace."""
    o, u, w = (np.asarray(a, dtype=np.float64) for a in patch[:3])
    tri = bool(patch[3])
    n = np.cross(u, w)
    n /= np.linalg.norm(n)
    h = (v - o) @ n
    scale = 1e-9 * np.ptp(v, axis=0).max()
    out = np.zeros(len(faces), dtype=bool)
    G = np.linalg.inv(np.array([[u @ u, u @ w], [u @ w, w @ w]]))
    for k, f in enumerate(faces):
        hf = h[f]
        if not (hf.max() > scale and hf.min() < -scale):
            continue
        ends = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            if (hf[i] > scale) != (hf[j] > scale) and (hf[i] < -scale) != (hf[j] < -scale):
                ends.append(v[f[i]] + hf[i] / (hf[i] - hf[j]) * (v[f[j]] - v[f[i]]))
            elif abs(hf[i]) <= scale:
                ends.append(v[f[i]])
        a, b = ends[0], ends[-1]
        pts = a + np.linspace(0, 1, samples)[:, None] * (b - a)
        ab = (pts - o) @ np.stack([u, w], 1) @ G
        inside = (ab > margin).all(1) & ((ab.sum(1) < 1 - margin) if tri else (ab < 1 - margin).all(1))
        out[k] = inside.any()
    return out


def area(v, f) -> float:
    return 0.5 * float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())


def test_a_swept_cut_across_part_of_the_surface_splits_only_within_its_patches():
    """An edge through the whole ball along D, at h = h0, drawn along W over two intervals from before
    the ball to past its middle: the lattice's swept blade of the same poses gives the patches."""
    from torchdeform.topology import Blade

    grid = td.Grid((7, 7, 7), spacing=0.005)
    ball = trimesh.creation.icosphere(3, radius=0.012)
    rest = ball.vertices + 0.015
    surf = EmbeddedSurface(rest, ball.faces, grid, dtype=F64)
    h0, w_end = 0.0153, 0.0187  # the plane between vertices; the sweep ends 3.7 mm past the middle
    edge = np.array([[-0.001, h0, 0.0], [0.031, h0, 0.0]])
    poses = np.stack([edge, edge + [0.0, 0.0, 0.01], edge + [0.0, 0.0, w_end]])
    cut = surf.cut_swept(poses)
    v, f = cut.rest_vertices.numpy(), cut.faces.numpy()
    patches = Blade.swept(poses).patches
    assert len(patches) == 2 and not any(tri for *_, tri in patches)
    # no triangle straddles the sheet inside a patch ...
    for patch in patches:
        assert not straddling_inside(v, f, patch).any()
    # ... while the uncut surface had triangles there, and those are gone (split)
    f0 = ball.faces
    crossed = np.zeros(len(f0), dtype=bool)
    for patch in patches:
        crossed |= straddling_inside(rest, f0, patch)
    assert crossed.sum() > 10
    kept = {tuple(t) for t in f.tolist()}
    assert not any(tuple(t) in kept for t in f0[crossed].tolist())
    # beyond the sheet's end the triangles are the original ones (old vertices keep their indices),
    # among them triangles that straddle the plane: the surface goes on, uncut
    beyond = rest[f0][:, :, 2].min(1) > w_end + 1e-4
    assert beyond.sum() > 100 and all(tuple(t) in kept for t in f0[beyond].tolist())
    hb = rest[f0[beyond]][:, :, 1] - h0
    assert ((hb.max(1) > 0) & (hb.min(1) < 0)).sum() >= 2
    # a partial cut: one piece, opened (new vertices, copies along the split), the same surface at rest
    assert pieces(f, len(v)) == 1 and cut.num_vertices > surf.num_vertices and cut.num_faces > surf.num_faces
    assert area(v, f) == pytest.approx(area(rest, f0), rel=1e-12)
    X = grid.rest_positions(dtype=F64)
    assert float((cut.positions(X)[0] - cut.rest_vertices).abs().max()) < 1e-12
    # the same edge drawn across the whole ball cuts it in two
    through = surf.cut_swept(np.stack([edge, edge + [0.0, 0.0, 0.04]]))
    assert pieces(through.faces.numpy(), through.num_vertices) == 2


def test_a_partial_swept_cut_opens_where_the_lattice_cut_of_the_same_blade_opens():
    """Cut the lattice with the same blade (torchdeform.topology.cut), then move the nodes on either
    side of the plane apart only where the sheet reached (w below its end): the split's two lips follow
    their sides; beyond the sheet's end the surface stays closed."""
    from torchdeform.topology import Blade, crossing

    grid = td.Grid((7, 7, 7), spacing=0.005)
    ball = trimesh.creation.icosphere(3, radius=0.012)
    surf = EmbeddedSurface(ball.vertices + 0.015, ball.faces, grid, dtype=F64)
    edge = np.array([[-0.001, 0.0163, 0.0], [0.031, 0.0163, 0.0]])
    poses = np.stack([edge, edge + [0.0, 0.0, 0.0175]])  # the sheet ends at w = 17.5 mm (a node plane is 15)
    cut = surf.cut_swept(poses)
    X = grid.rest_positions(dtype=F64)
    assert bool(crossing(grid, X, Blade.swept(poses)).any())
    x = X.clone()[0]
    opened = x[2] < 0.0151  # nodes whose springs across the plane the sheet cut: open them by 2 mm
    x[1] = torch.where(opened & (x[1] > 0.0163), x[1] + 0.001, torch.where(opened, x[1] - 0.001, x[1]))
    p = cut.positions(x).numpy()
    side = cut.side.numpy()
    lips = (np.abs(cut.rest_vertices[:, 1].numpy() - 0.0163) < 1e-12) & (cut.rest_vertices[:, 2].numpy() < 0.0149)
    v = cut.rest_vertices.numpy()
    up_side = 1 if v[(side > 0) & ~lips, 1].mean() > 0.0163 else -1  # the side the patches' normal points to
    upper, lower = lips & (side == up_side), lips & (side == -up_side)
    assert upper.sum() >= 4 and lower.sum() >= 4
    assert np.abs(p[upper, 1] - (0.0163 + 0.001)).max() < 1e-12  # each lip follows its own side
    assert np.abs(p[lower, 1] - (0.0163 - 0.001)).max() < 1e-12
    assert pieces(cut.faces.numpy(), cut.num_vertices) == 1


def test_cuts_by_patches_check_their_input_and_leave_a_missed_surface_alone():
    grid = td.Grid((6, 6, 6), spacing=0.01)
    ball = trimesh.creation.icosphere(2, radius=0.015)
    surf = EmbeddedSurface(ball.vertices + 0.025, ball.faces, grid, dtype=F64)
    far = [((0.0, 0.0, 0.0), (0.0, 0.001, 0.0), (0.0, 0.0, 0.001), True)]  # a corner of the box: misses
    assert surf.cut_patches(far) is surf
    for bad, match in [
        ([((0, 0, 0), (1, 0, 0), (2, 0, 0))], "non-degenerate"),
        ([((0, 0), (1, 0, 0), (0, 1, 0))], "flat patches"),
        ([], "flat patches"),
        (3.0, "flat patches"),
    ]:
        with pytest.raises(ConfigError, match=match):
            surf.cut_patches(bad)
    with pytest.raises(ConfigError, match=r"edges: .*\(K, 2, 3\)"):
        surf.cut_swept(np.zeros((1, 2, 3)))
    with pytest.raises(ConfigError, match="only moved along itself"):
        surf.cut_swept([[(0, 0, 0), (0, 0, 1)], [(0, 0, 0.5), (0, 0, 1.5)]])
    with pytest.raises(ConfigError, match="node positions of one body"):
        surf.cut_patches(far, x=torch.zeros(2, 3, 6, 6, 6))


def test_a_turning_edge_cuts_patch_by_patch_and_leaves_a_valid_surface():
    """The edge turns about D while it moves: its triangles lie in different planes. Oracles: the
    straddle test per patch, every edge of the result in at most two triangles and each directed
    edge in at most one (a consistently wound 2-manifold with a border), the area at rest."""
    from torchdeform.topology import Blade

    grid = td.Grid((7, 7, 7), spacing=0.005)
    ball = trimesh.creation.icosphere(3, radius=0.012)
    rest = ball.vertices + 0.015
    surf = EmbeddedSurface(rest, ball.faces, grid, dtype=F64)
    poses = []
    for k, angle in enumerate(np.linspace(0.0, 0.6, 5)):
        centre = np.array([0.015, 0.0153, 0.002 + 0.0045 * k])
        d = np.array([1.0, 0.0, 0.0]) * 0.016
        tilt = np.array([0.0, np.sin(angle), 0.0]) * 0.016
        poses.append([centre - d - tilt, centre + d + tilt])
    poses = np.array(poses)
    cut = surf.cut_swept(poses)
    v, f = cut.rest_vertices.numpy(), cut.faces.numpy()
    patches = Blade.swept(poses).patches
    assert len({tuple(np.round(np.cross(u, w) / np.linalg.norm(np.cross(u, w)), 9)) for _, u, w, _ in patches}) > 2
    assert cut.num_faces > surf.num_faces
    for patch in patches:
        assert not straddling_inside(v, f, patch).any()
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1)
    assert np.unique(e, axis=0, return_counts=True)[1].max() <= 2
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert np.unique(d, axis=0, return_counts=True)[1].max() == 1
    assert area(v, f) == pytest.approx(area(rest, ball.faces), rel=1e-12)
    assert pieces(f, len(v)) == 1
