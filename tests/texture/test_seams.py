"""Seam measure and Poisson seam blending of block-tiled solid textures (torchdeform.texture.seams).

Oracles: a tiled volume built here by plain numpy slicing from a smooth random exemplar; the
guided least-squares problem assembled edge by edge with scipy.sparse and solved by spsolve;
quadratic fields, which the face guidance reproduces exactly; hand-counted seam ratios.
"""

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy import ndimage
from scipy.sparse.linalg import spsolve

from torchdeform.errors import ConfigError
from torchdeform.texture.seams import (
    face_edges,
    histogram_distance,
    poisson_blend_3d,
    poisson_blend_slices,
    seam_band,
    seam_measure,
)

N, B = 48, 16  # exemplar and tiled volume 48^3, blocks of 16
STD = 0.15  # colour standard deviation of the exemplar (mean 0.5)


@pytest.fixture(scope="module")
def textures():
    """A smooth random RGB exemplar (Gaussian low-pass noise) and a tiling of 16^3 blocks of it."""
    rng = np.random.default_rng(7)
    ex = np.stack([ndimage.gaussian_filter(rng.standard_normal((N,) * 3), 4.0, mode="wrap") for _ in range(3)])
    ex = (ex - ex.mean()) / ex.std() * STD + 0.5
    vol = np.empty_like(ex)
    for i in range(N // B):
        for j in range(N // B):
            for k in range(N // B):
                o = rng.integers(0, N - B + 1, 3)
                vol[:, i * B : (i + 1) * B, j * B : (j + 1) * B, k * B : (k + 1) * B] = ex[
                    :, o[0] : o[0] + B, o[1] : o[1] + B, o[2] : o[2] + B
                ]
    return torch.tensor(ex, dtype=torch.float32), torch.tensor(vol, dtype=torch.float32)


# --------------------------------------------------------------------------- oracles
def edge_list(shape):
    """All 6-neighbour edges ``(i, j, axis)`` of a grid, as flat indices, by plain loops."""
    idx = np.arange(np.prod(shape)).reshape(shape)
    out = []
    for a in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[a], hi[a] = slice(0, shape[a] - 1), slice(1, shape[a])
        for i, j in zip(idx[tuple(lo)].ravel(), idx[tuple(hi)].ravel()):
            out.append((i, j, a))
    return out


def guidance_oracle(v, shape, block, guide):
    """Per-edge guidance, straight from the definition (numpy, one edge at a time)."""
    coords = np.stack(np.unravel_index(np.arange(np.prod(shape)), shape), 1)
    flat = {tuple(c): n for n, c in enumerate(coords)}

    def is_face(i, a):
        p = coords[i][a] + 1
        return p % block == 0 and p < shape[a]

    g = []
    for i, j, a in edge_list(shape):
        if not is_face(i, a):
            g.append(v[j] - v[i])
        elif guide == "zero":
            g.append(0.0)
        else:
            e = np.eye(3, dtype=int)[a]
            cands = []
            before = tuple(coords[i] - e)
            if before in flat and not is_face(flat[before], a):
                cands.append(v[i] - v[flat[before]])
            after = tuple(coords[j] + e)
            if after in flat and not is_face(j, a):
                cands.append(v[flat[after]] - v[j])
            g.append(np.mean(cands) if cands else 0.0)
    return np.array(g)


def scipy_blend(v, block, guide, unknown=None):
    """Minimise |D u - g|^2 with scipy: L = D^T D assembled from the edge list, spsolve.

    ``unknown``: bool mask of free voxels (others fixed); None: all free, mean of ``v`` kept.
    """
    shape = v.shape
    vf = v.ravel()
    edges = edge_list(shape)
    rows = np.repeat(np.arange(len(edges)), 2)
    cols = np.array([[i, j] for i, j, _ in edges]).ravel()
    vals = np.tile([-1.0, 1.0], len(edges))
    D = sp.csr_matrix((vals, (rows, cols)), shape=(len(edges), vf.size))
    L = (D.T @ D).tocsc()
    rhs = D.T @ (guidance_oracle(vf, shape, block, guide) - D @ vf)
    w = np.zeros_like(vf)
    if unknown is None:  # anchor voxel 0, then restore the mean
        w[1:] = spsolve(L[1:, 1:], rhs[1:])
        w -= w.mean()
    else:
        U = np.flatnonzero(unknown.ravel())
        w[U] = spsolve(L[U][:, U], rhs[U])
    return (vf + w).reshape(shape)


# --------------------------------------------------------------------------- (a) 3-D blend
@pytest.mark.parametrize("region", ["all", "seams"])
def test_3d_blend_removes_seams_and_keeps_colours(textures, region):
    ex, vol = textures
    before = seam_measure(vol, B)
    assert before > 6.0  # the tiling has clear seams (measured 8.18)
    u, iters, rel = poisson_blend_3d(vol, B, region=region, return_info=True)
    assert rel <= 1e-6 and iters < 2000
    after = seam_measure(u, B)
    assert after < before / 5  # measured 8.18 -> 1.16 (all), 1.21 (seams)
    assert 0.8 < after < 1.5  # about as rough as the inside of a block
    # colours: W1 per channel (STD = 0.15); the tiling itself is 0.024 from the exemplar (27 blocks of it)
    assert histogram_distance(u, vol) < 0.25 * STD  # measured 0.018 (all), 0.025 (seams)
    assert histogram_distance(u, ex) < 0.3 * STD  # measured 0.027 (all), 0.033 (seams)
    if region == "all":
        torch.testing.assert_close(u.mean((1, 2, 3)), vol.mean((1, 2, 3)), atol=1e-6, rtol=0)
    else:  # voxels outside the band are anchors
        outside = ~seam_band(vol.shape[1:], B, 4)
        assert torch.equal(u[:, outside], vol[:, outside])
        assert float((u.mean((1, 2, 3)) - vol.mean((1, 2, 3))).abs().max()) < 1e-3


def test_seam_measure_reference_and_axis(textures, device):
    ex, vol = (t.to(device) for t in textures)
    assert seam_measure(ex[:, :32, :32, :32], B) < 1.3  # a crop of the exemplar has no seams
    assert seam_measure(vol, B, reference=ex) == pytest.approx(seam_measure(vol, B), rel=0.1)
    per_axis = [seam_measure(vol, B, axis=a) for a in range(3)]
    assert min(per_axis) > 5.0


# --------------------------------------------------------------------------- (b) per-slice blend
@pytest.mark.parametrize("axis", [0, 2])
def test_slice_blend_cannot_fix_the_slicing_axis(textures, axis):
    _, vol = textures
    before = [seam_measure(vol, B, axis=a) for a in range(3)]
    u = poisson_blend_slices(vol, B, axis=axis)
    after = [seam_measure(u, B, axis=a) for a in range(3)]
    for a in range(3):
        if a == axis:
            assert after[a] > 0.8 * before[a]  # measured 7.8 -> 7.2 (axis 0), 8.4 -> 7.6 (axis 2)
        else:
            assert after[a] < before[a] / 5  # measured ~8.3 -> 1.07-1.15
    # each slice keeps its mean colour (region "seams": approximately)
    dims = tuple(d for d in (1, 2, 3) if d != axis + 1)
    assert float((u.mean(dims) - vol.mean(dims)).abs().max()) < 0.01


# --------------------------------------------------------------------------- (c) nothing to blend
@pytest.mark.parametrize("blend", [poisson_blend_3d, poisson_blend_slices])
def test_single_block_is_unchanged(textures, blend):
    ex, _ = textures
    one = ex[:, :16, :16, :16]
    u, iters, _ = blend(one, 16, return_info=True)
    assert iters == 0 and torch.equal(u, one)
    assert torch.equal(blend(ex[:, :20, :20, :20], 32), ex[:, :20, :20, :20])  # a block larger than the volume


@pytest.mark.parametrize("region", ["all", "seams"])
def test_quadratic_field_is_a_fixed_point(region):
    """The face guidance (mean of the differences either side) is exact for quadratics: no change."""
    i, j, k = np.meshgrid(*[np.arange(24.0)] * 3, indexing="ij")
    rng = np.random.default_rng(3)
    chans = []
    for _ in range(3):
        c = rng.normal(size=10) * np.array([1, 0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3])
        chans.append(
            c[0]
            + c[1] * i
            + c[2] * j
            + c[3] * k
            + c[4] * i * i
            + c[5] * j * j
            + c[6] * k * k
            + c[7] * i * j
            + c[8] * j * k
            + c[9] * i * k
        )
    v = torch.tensor(np.stack(chans))
    for blend in (poisson_blend_3d, poisson_blend_slices):
        u = blend(v, 8, region=region, tol=1e-10)
        torch.testing.assert_close(u, v, atol=1e-10, rtol=0)


# --------------------------------------------------------------------------- (d) normal equations
@pytest.mark.parametrize("guide", ["mean", "zero"])
@pytest.mark.parametrize("region", ["all", "seams"])
def test_cg_matches_scipy_spsolve(guide, region, device):
    rng = np.random.default_rng(11)
    v = rng.random((3, 6, 6, 6))
    u = poisson_blend_3d(torch.tensor(v, device=device), 3, region=region, margin=1, guide=guide, tol=1e-12)
    assert u.device == device
    u = u.cpu().numpy()
    unknown = seam_band((6, 6, 6), 3, 1).numpy() if region == "seams" else None
    for c in range(3):
        np.testing.assert_allclose(u[c], scipy_blend(v[c], 3, guide, unknown), atol=1e-9)


def test_slices_match_scipy_per_slice(device):
    rng = np.random.default_rng(12)
    v = rng.random((2, 6, 5, 6))
    u = poisson_blend_slices(torch.tensor(v, device=device), 3, axis=1, region="all", tol=1e-12).cpu().numpy()
    for c in range(2):
        for h in range(5):
            ref = scipy_blend(v[c][:, h : h + 1, :], 3, "mean")
            np.testing.assert_allclose(u[c][:, h : h + 1, :], ref, atol=1e-9)


# --------------------------------------------------------------------------- small pieces
def test_face_edges_and_band_by_hand():
    m = face_edges((7, 4, 1), (3, 2, None))
    assert m[0, :, 0, 0].tolist() == [False, False, True, False, False, True, False]
    assert m[1, 0, :, 0].tolist() == [False, True, False, False]
    assert not m[2].any()
    band = seam_band((7, 1, 1), 3, 1)[:, 0, 0].tolist()
    assert band == [False, False, True, True, False, True, True]


def test_histogram_distance_known_values():
    a = torch.linspace(0, 1, 1000).expand(3, 1000)
    assert histogram_distance(a, a) == 0.0
    assert histogram_distance(a, a + 0.25, bins=200) == pytest.approx(0.25, abs=0.01)
    assert histogram_distance(a, a + 10.0, metric="l1") == 2.0  # disjoint
    assert histogram_distance(a.double(), a.float()) == pytest.approx(0.0, abs=1e-12)


def test_bad_arguments_raise_one_clear_error(textures):
    _, vol = textures
    with pytest.raises(ConfigError, match="region"):
        poisson_blend_3d(vol, B, region="faces")
    with pytest.raises(ConfigError, match="block"):
        seam_measure(vol, 64)  # no interior face
    with pytest.raises(ConfigError, match="volume"):
        seam_measure(vol[0], B)
    with pytest.raises(ConfigError, match="axis"):
        poisson_blend_slices(vol, B, axis=3)


def test_seam_jump_equals_a_numpy_loop_over_face_edges(device):
    from torchdeform.texture.seams import seam_jump

    rng = np.random.default_rng(7)
    v = rng.random((2, 7, 6, 9))
    b = 3
    jumps, steps = [], []
    for a in range(3):
        n = v.shape[1 + a]
        for i in range(n - 1):
            d = np.take(v, i + 1, axis=1 + a) - np.take(v, i, axis=1 + a)
            if (i + 1) % b == 0:
                if i >= 1 and i + 2 <= n - 1:
                    before = np.take(v, i, axis=1 + a) - np.take(v, i - 1, axis=1 + a)
                    after = np.take(v, i + 2, axis=1 + a) - np.take(v, i + 1, axis=1 + a)
                    jumps.append(np.abs(d - (before + after) / 2).ravel())
            else:
                steps.append(np.abs(d).ravel())
    expect = np.concatenate(jumps).mean() / np.concatenate(steps).mean()
    assert abs(seam_jump(torch.from_numpy(v).to(device), b) - expect) < 1e-12


def test_poisson_blend_removes_most_of_the_gradient_jump_of_a_tiled_liver():
    """On the procedural liver the step measure cannot fall 5-fold (its floor is 1); the jump does."""
    from torchdeform.texture import SolidTexture, liver_exemplar
    from torchdeform.texture.seams import histogram_distance, poisson_blend_3d, seam_jump

    ex = liver_exemplar(size=48, seed=0)
    v = SolidTexture(ex, block=16, extent=(48, 48, 48), seed=1).materialise()
    u = poisson_blend_3d(v, 16)
    tiled, blended, seamless = (seam_jump(x, 16, reference=ex) for x in (v, u, ex))
    assert tiled > 5 * blended and blended < 3 * seamless
    assert histogram_distance(u, ex) < 1.5 * histogram_distance(v, ex) + 0.005


def test_solid_texture_blend_reads_the_blended_volume_from_then_on():
    """``SolidTexture.blend``: lookups = the Poisson-blended materialised texture (nearest: exactly;
    trilinear: one 3-D ``grid_sample`` of it), the report's measures = seam_jump / histogram_distance."""
    import torch.nn.functional as F

    from torchdeform.texture import SolidTexture, liver_exemplar
    from torchdeform.texture.seams import histogram_distance, poisson_blend_3d, poisson_blend_slices, seam_jump
    from torchdeform.volume import to_grid_sample

    ex = liver_exemplar(size=32, seed=2)
    tiled = SolidTexture(ex, block=16, extent=(40, 32, 24), seed=3).materialise()
    for method, blend in (("3d", poisson_blend_3d), ("slices", poisson_blend_slices)):
        tex = SolidTexture(ex, block=16, extent=(40, 32, 24), seed=3)
        report = tex.blend(method=method)
        want = blend(tiled, 16).clamp(0, 1)
        assert torch.equal(tex.materialise(), want)
        gen = torch.Generator().manual_seed(0)
        P = torch.rand(300, 3, generator=gen) * torch.tensor([42.0, 34, 26]) - 1
        grid = to_grid_sample(P.T.reshape(1, 3, -1, 1, 1), want.shape[1:], align_corners=True)
        ref = F.grid_sample(want[None], grid, mode="bilinear", padding_mode="border", align_corners=True)
        torch.testing.assert_close(tex.colour(P), ref.reshape(3, -1).T, atol=1e-4, rtol=0)
        assert report["seam_before"] == pytest.approx(seam_jump(tiled, 16, reference=ex))
        assert report["seam_after"] == pytest.approx(seam_jump(blend(tiled, 16), 16, reference=ex))
        assert report["histogram_after"] == pytest.approx(histogram_distance(blend(tiled, 16), ex))
    assert report["seam_after"] < report["seam_before"]
    tex = SolidTexture(ex, block=16, extent=(40, 32, 24), seed=3)
    assert tex.blend(method="none")["seam_after"] == tex.blend(method="none")["seam_before"] and tex.volume is None
    assert torch.equal(tex.materialise(), tiled)
    with pytest.raises(ConfigError, match=r"texture\.seams"):
        tex.blend(method="poisson")
