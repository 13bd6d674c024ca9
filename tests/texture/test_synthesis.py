"""Exemplars and the indirection texture against plain indexing (REFERENCE §7.3 tests).

* every block of a materialised texture equals ``exemplar[o:o + b]`` at its offset (numpy slicing);
* the block count is the product of ceil(extent / b);
* nearest-mode lookup at integer points equals integer indexing bit for bit;
* trilinear lookup inside a block equals a hand-written trilinear interpolation of the exemplar;
* colours at material coordinates do not change when the body moves rigidly (1e-6);
* exemplars load from .npy, .npz and folders of PNG slices; bad input is one clear error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform.errors import ConfigError
from torchdeform.texture import SolidTexture, as_exemplar, liver_exemplar, load_exemplar


@pytest.fixture(scope="module")
def exemplar():
    return liver_exemplar(size=32, seed=3)


@pytest.mark.parametrize("extent, block", [((40, 20, 33), 16), ((16, 16, 16), 16), ((7, 50, 9), 8)])
def test_blocks_are_exemplar_copies_at_their_offsets(exemplar, extent, block):
    tex = SolidTexture(exemplar, block=block, extent=extent, seed=5)
    assert tex.blocks == tuple(math.ceil(e / block) for e in extent)
    assert tex.offsets.shape == (*tex.blocks, 3)
    assert int(tex.offsets.min()) >= 0 and int(tex.offsets.max()) <= 32 - block
    vol = tex.materialise().numpy()
    ex = exemplar.numpy()
    for i in range(tex.blocks[0]):
        for j in range(tex.blocks[1]):
            for k in range(tex.blocks[2]):
                o = tex.offsets[i, j, k].tolist()
                lo = (i * block, j * block, k * block)
                hi = tuple(min(a + block, e) for a, e in zip(lo, extent))
                part = vol[:, lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
                ref = ex[:, o[0] : o[0] + hi[0] - lo[0], o[1] : o[1] + hi[1] - lo[1], o[2] : o[2] + hi[2] - lo[2]]
                assert np.array_equal(part, ref)


def test_nearest_lookup_is_integer_indexing_and_trilinear_interpolates(exemplar, device):
    tex = SolidTexture(exemplar, block=16, extent=(48, 48, 48), seed=1)
    gen = torch.Generator().manual_seed(0)
    P = torch.randint(0, 48, (500, 3), generator=gen)
    got = tex.colour(P.float().to(device), mode="nearest")
    assert got.device == device
    o = tex.offsets[P[:, 0] // 16, P[:, 1] // 16, P[:, 2] // 16] + P % 16
    assert torch.equal(got.cpu(), exemplar[:, o[:, 0], o[:, 1], o[:, 2]].T)
    # trilinear inside a block (away from its far face): a hand-written interpolation
    Q = (P // 16 * 16).double() + torch.rand(500, 3, generator=gen, dtype=torch.float64) * 14.9
    tex64 = SolidTexture(exemplar.double(), block=16, extent=(48, 48, 48), seed=1)
    got = tex64.colour(Q.to(device)).cpu()
    e = exemplar.double().numpy()
    for n in range(0, 500, 25):
        q = Q[n].numpy()
        base = tex64.offsets[tuple(int(c) // 16 for c in q)].numpy() + (q - np.floor(q / 16) * 16)
        i0 = np.floor(base).astype(int)
        f = base - i0
        ref = np.zeros(3)
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([f[a] if corner[a] else 1 - f[a] for a in range(3)])
            ref += w * e[:, i0[0] + corner[0], i0[1] + corner[1], i0[2] + corner[2]]
        assert np.allclose(got[n].numpy(), ref, atol=1e-12)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-4)])
def test_trilinear_slice_lookup_equals_3d_grid_sample(dtype, tol, device):
    """The slice-atlas lookup against one 3-D ``grid_sample`` (border padding, on the CPU), points inside
    and outside a non-cubic exemplar; 20,001 points on 3 threads exercise the split into batch elements
    (on the CPU)."""
    import torch.nn.functional as F

    from torchdeform.volume import to_grid_sample

    ex = liver_exemplar(size=24, seed=4)[:, :19, :, :21].to(dtype)  # 19 slices: 5 x 4 tiles
    tex = SolidTexture(ex, block=8, extent=(16, 16, 16))
    gen = torch.Generator().manual_seed(1)
    q = torch.rand(20001, 3, generator=gen, dtype=dtype) * torch.tensor([23.0, 28, 25], dtype=dtype) - 2
    grid = to_grid_sample(q.T.reshape(1, 3, -1, 1, 1), ex.shape[1:], align_corners=True)
    ref = F.grid_sample(ex[None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    threads = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        got = tex._trilinear(q.to(device)).cpu()
    finally:
        torch.set_num_threads(threads)
    assert torch.allclose(got, ref.reshape(3, -1).T, rtol=0, atol=tol)


def test_colours_of_a_surface_ignore_rigid_motion(exemplar, device):
    """The surface of a body moved rigidly carries the same rest coordinates, hence the same colours."""
    from torchdeform.topology import cut_surfaces

    grid = td.Grid((6, 5, 4), spacing=0.002, topology=26)
    X = grid.rest_positions(dtype=torch.float64)
    labels = torch.zeros(grid.shape, dtype=torch.int64)
    tex = SolidTexture(exemplar, block=8, extent=(30, 30, 30), seed=2, voxel=0.0005, origin=(-0.0013, -0.0021, -0.0017))
    angle = 0.7
    R = torch.tensor(
        [[1, 0, 0], [0, math.cos(angle), -math.sin(angle)], [0, math.sin(angle), math.cos(angle)]], dtype=torch.float64
    )
    t = torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64)
    moved = torch.einsum("ij,bjdhw->bidhw", R, X) + t.view(1, 3, 1, 1, 1)
    (a,), (b,) = cut_surfaces(grid, X, labels), cut_surfaces(grid, moved, labels)
    assert np.allclose(b.vertices, a.vertices @ R.numpy().T + t.numpy(), atol=1e-12)  # the surface moved
    ca = tex.at_material(torch.from_numpy(a.rest).to(device))
    cb = tex.at_material(torch.from_numpy(b.rest).to(device))
    assert ca.device == device and torch.allclose(ca, cb, atol=1e-6)
    assert torch.allclose(ca.cpu(), tex.at_material(torch.from_numpy(a.rest)), atol=1e-6)  # as on the CPU
    assert float(ca.std(0).min()) > 0.005  # it is textured


def test_liver_exemplar_is_seeded_and_rgb():
    a, b, c = liver_exemplar(size=16, seed=0), liver_exemplar(size=16, seed=0), liver_exemplar(size=16, seed=1)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert a.shape == (3, 16, 16, 16) and float(a.min()) >= 0 and float(a.max()) <= 1
    assert float(a[0].mean()) > float(a[1].mean())  # reddish


def test_exemplar_files(tmp_path):
    import matplotlib.image as mpimg

    vol = (np.random.default_rng(0).random((4, 6, 5, 3)) * 255).astype(np.uint8)
    np.save(tmp_path / "ex.npy", vol)
    np.savez(tmp_path / "ex.npz", exemplar=vol)
    folder = tmp_path / "slices"
    folder.mkdir()
    for i in range(4):
        mpimg.imsave(folder / f"slice_{i:03d}.png", vol[i])
    ref = torch.from_numpy(vol).permute(3, 0, 1, 2).float() / 255
    assert torch.equal(load_exemplar(tmp_path / "ex.npy"), ref)
    assert torch.equal(load_exemplar(tmp_path / "ex.npz"), ref)
    assert torch.allclose(load_exemplar(folder), ref, atol=1 / 255)
    mpimg.imsave(folder / "slice_999.png", np.zeros((3, 3, 3), dtype=np.uint8))
    with pytest.raises(ConfigError, match=r"slice_999.png.*6 x 5"):
        load_exemplar(folder)


def test_bad_exemplars_and_blocks(exemplar):
    with pytest.raises(ConfigError, match="RGB"):
        as_exemplar(np.zeros((4, 4, 4)))
    with pytest.raises(ConfigError, match="RGB"):
        as_exemplar(np.zeros((4, 4, 4, 2)))
    with pytest.raises(ConfigError, match="block"):
        SolidTexture(exemplar, block=64, extent=(10, 10, 10))
    with pytest.raises(ConfigError, match="extent"):
        SolidTexture(exemplar, block=8, extent=(10, 0, 10))
