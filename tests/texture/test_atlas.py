"""Triangle-interior samples, the 2-D atlas and textured files (texture.atlas) against independent oracles."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torchdeform.errors import ConfigError
from torchdeform.texture import SolidTexture, liver_exemplar
from torchdeform.texture.atlas import build_atlas, export_textured, sample_triangles

VOXEL = 0.001


def _liver_texture():
    return SolidTexture(liver_exemplar(size=16, seed=3), block=8, extent=(32, 32, 32), voxel=VOXEL, seed=1)


def _affine_texture(E=32):
    """One block, offset 0: channel c = 0.1 + 0.8 P_c / (E - 1), affine, so trilinear lookups are exact."""
    axes = torch.meshgrid(*[torch.arange(E, dtype=torch.float32)] * 3, indexing="ij")
    ex = torch.stack([0.1 + 0.8 * a / (E - 1) for a in axes])
    return SolidTexture(ex, block=E, extent=(E, E, E), voxel=VOXEL), 0.8 / (E - 1)


def _sphere(subdivisions=2, radius=0.012, centre=0.016):
    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return torch.from_numpy(s.vertices + centre), torch.from_numpy(s.faces)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("legs", ["axes", "rotated"])
def test_a_right_triangle_with_legs_of_n_voxels_has_the_hand_counted_grid_points(n, legs):
    hand = sum(1 for i in range(n + 1) for j in range(n + 1) if i + j <= n)  # (i/n, j/n), i + j <= n
    if legs == "axes":
        u, w = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    else:  # 3-4-5 legs: |AB| = |AC| = n
        u, w = np.array([0.6, 0.8, 0]), np.array([-0.8, 0.6, 0])
    A = np.array([2.3, 4.1, 5.7])
    rest = torch.from_numpy(np.stack([A, A + n * u, A + n * w]) * VOXEL)
    s = sample_triangles(rest, [[0, 1, 2]], _liver_texture())
    assert s.count == hand and s.per_face.tolist() == [hand]
    assert sorted(zip(s.i.tolist(), s.j.tolist())) == sorted(
        (i, j) for i in range(n + 1) for j in range(n + 1) if i + j <= n
    )
    s2 = sample_triangles(rest, [[0, 1, 2]], _liver_texture(), density=2.0)  # steps of half a voxel
    assert s2.count == sum(1 for i in range(2 * n + 1) for j in range(2 * n + 1) if i + j <= 2 * n)


def test_sample_grid_matches_a_brute_force_enumeration_per_triangle():
    rest, faces = _sphere(1, radius=0.009)
    s = sample_triangles(rest, faces, _liver_texture(), density=1.3)
    X = rest.numpy() / VOXEL
    for f in range(0, len(faces), 7):
        A, B, C = X[faces[f].numpy()]
        na, nb = 1.3 * np.linalg.norm(B - A), 1.3 * np.linalg.norm(C - A)
        want = {(i, j) for i in range(int(na) + 2) for j in range(int(nb) + 2) if i / na + j / nb <= 1 + 1e-9}
        mine = s.face == f
        assert set(zip(s.i[mine].tolist(), s.j[mine].tolist())) == want
    assert int(s.per_face.sum()) == s.count == len(s.face)
    assert bool((torch.diff(s.face) >= 0).all())  # contiguous per triangle


def test_every_sample_colour_is_the_texture_at_its_point():
    tex = _liver_texture()
    rest, faces = _sphere(1, radius=0.009)
    s = sample_triangles(rest, faces, tex)
    X = rest.numpy() / VOXEL
    A, B, C = (X[faces[:, k].numpy()] for k in range(3))
    f = s.face.numpy()
    a = s.i.numpy() / np.linalg.norm(B - A, axis=1)[f]
    b = s.j.numpy() / np.linalg.norm(C - A, axis=1)[f]
    assert (a >= 0).all() and (b >= 0).all() and (a + b <= 1 + 1e-9).all()
    P = A[f] + a[:, None] * (B - A)[f] + b[:, None] * (C - A)[f]
    want = tex.colour(torch.from_numpy(P).float())
    torch.testing.assert_close(s.colour, want, atol=1e-5, rtol=0)


@pytest.mark.parametrize("w", [(1 / 3, 1 / 3, 1 / 3), (0.6, 0.25, 0.15)])
def test_atlas_at_the_centroid_uv_shows_the_texture_at_the_centroid(w):
    """The centroid as asked, and a point with unequal weights (which catches corner UVs in the wrong order)."""
    tex, g = _affine_texture()
    rest, faces = _sphere(2)
    atlas = build_atlas(rest, faces, tex)
    H, W, _ = atlas.image.shape
    wt = torch.tensor(w, dtype=torch.float64)
    uv = (atlas.uv * wt[None, :, None]).sum(1)  # UVs are affine in the barycentrics
    col = torch.floor(uv[:, 0] * W).long()
    row = torch.floor((1 - uv[:, 1]) * H).long()
    got = atlas.image[row, col].double()  # nearest read
    X = rest / VOXEL
    A, B, C = (X[faces[:, k]] for k in range(3))
    want = tex.colour((w[0] * A + w[1] * B + w[2] * C).float()).double()
    # nearest rounds (a, b) = (w1, w2) to the sample grid: at most half a step L_a = 1/|AB| along AB and
    # L_b = 1/|AC| along AC, i.e. half a voxel along each leg; for the affine texture with gradient g along
    # each axis that bounds channel c by g (|AB_c| / |AB| + |AC_c| / |AC|) / 2 (+ float32 rounding)
    tol = (
        0.5
        * g
        * ((B - A).abs() / (B - A).norm(dim=1, keepdim=True) + (C - A).abs() / (C - A).norm(dim=1, keepdim=True))
    )
    assert bool(((got - want).abs() <= tol + 1e-5).all())
    assert float((got - want).abs().max()) > 0  # the bound is not vacuous


def test_atlas_cells_hold_their_samples_do_not_overlap_and_filter_inside_their_gutter():
    tex = _liver_texture()
    rest, faces = _sphere(2)
    atlas = build_atlas(rest, faces, tex)
    H, W, _ = atlas.image.shape
    s = atlas.samples
    x0, y0 = atlas.corner[s.face, 0], atlas.corner[s.face, 1]
    assert torch.equal(atlas.image[y0 + 1 + s.j.long(), x0 + 1 + s.i.long()], s.colour)
    owner = np.zeros((H, W), int)
    for (x, y), c in zip(atlas.corner.tolist(), atlas.cell.tolist()):
        owner[y : y + c, x : x + c] += 1
    assert owner.max() == 1
    assert bool(((atlas.uv > 0) & (atlas.uv < 1)).all())
    # bilinear footprint of every corner (hence of the whole convex triangle) stays in its own cell
    px = torch.stack([atlas.uv[..., 0] * W, (1 - atlas.uv[..., 1]) * H], -1)  # (F, 3, 2) pixels
    lo, hi = torch.floor(px - 0.5), torch.floor(px - 0.5) + 1
    corner = atlas.corner[:, None, :].double()
    assert bool((lo >= corner).all()) and bool((hi < corner + atlas.cell[:, None, None]).all())


def test_ply_round_trip_gives_the_rest_colours(tmp_path):
    tex = _liver_texture()
    rest, faces = _sphere(1)
    deformed = rest * 1.2 + 0.003
    export_textured(tmp_path / "s.ply", deformed, faces, rest, tex)
    m = trimesh.load(tmp_path / "s.ply", process=False)
    np.testing.assert_allclose(m.vertices, deformed.numpy(), atol=1e-12)
    got = m.visual.vertex_colors[:, :3] / 255.0
    np.testing.assert_allclose(got, tex.at_material(rest).double().numpy(), atol=1 / 255)


def test_glb_and_obj_round_trips_carry_the_atlas(tmp_path):
    tex = _liver_texture()
    rest, faces = _sphere(1)
    atlas = export_textured(tmp_path / "s.glb", rest * 0.9, faces, rest, tex)
    H, W, _ = atlas.image.shape
    m = trimesh.load(tmp_path / "s.glb", force="mesh")
    img = m.visual.material.baseColorTexture
    assert img.size == (W, H)
    assert np.array_equal(np.asarray(img.convert("RGB")), np.asarray(atlas.to_pil()))
    assert len(m.faces) == len(faces)
    export_textured(tmp_path / "o.obj", rest, faces, rest, tex)
    assert (tmp_path / "o.obj").exists() and any(tmp_path.glob("*.mtl")) and any(tmp_path.glob("*.png"))
    mo = trimesh.load(tmp_path / "o.obj", force="mesh")
    assert mo.visual.material.image.size == (W, H)


def test_unknown_suffix_is_a_config_error(tmp_path):
    rest, faces = _sphere(0)
    with pytest.raises(ConfigError, match=r"ply, \.glb or \.obj"):
        export_textured(tmp_path / "s.stl", rest, faces, rest, _liver_texture())
    with pytest.raises(ConfigError):
        sample_triangles(rest, faces, _liver_texture(), density=0)
