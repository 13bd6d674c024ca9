"""Volume warping against independent oracles (scipy map_coordinates, a plain cell-centred lookup)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates

from torchdeform.errors import ConfigError
from torchdeform.volume import (
    DisplacementField,
    FoldingWarning,
    folding_fraction,
    inverse_points,
    inverse_residual,
    jacobian_determinant,
    offset_texture,
    warp,
)
from torchdeform.volume.io import load_volume, save_volume


def trilinear_nodes_np(nodes, shape):
    """Corner-aligned trilinear upsampling written out with numpy (independent of torch)."""
    out = np.zeros((3,) + tuple(shape))
    n = nodes.shape[1:]
    for c in range(3):
        coords = np.meshgrid(*[np.arange(N) * (k - 1) / (N - 1) for k, N in zip(n, shape)], indexing="ij")
        out[c] = map_coordinates(nodes[c], coords, order=1, mode="nearest")
    return out


@pytest.mark.parametrize("padding,scipy_mode", [("border", "nearest"), ("zeros", "grid-constant")])
def test_warp_equals_map_coordinates(padding, scipy_mode, device):
    rng = np.random.default_rng(0)
    shape = (9, 11, 13)
    vol = rng.normal(size=shape)
    nodes = rng.normal(scale=1.5, size=(3, 4, 5, 6))
    fill = 0.7 if padding == "zeros" else 0.0
    vol_t, nodes_t = torch.tensor(vol, device=device), torch.tensor(nodes, device=device)
    out = warp(vol_t, nodes_t, padding=padding, fill=fill, check=False).cpu().numpy()
    u = trilinear_nodes_np(nodes, shape)
    grid = np.stack(np.meshgrid(*[np.arange(N) for N in shape], indexing="ij"))
    ref = map_coordinates(vol, grid - u, order=1, mode=scipy_mode, cval=fill)
    assert np.abs(out - ref).max() < 1e-5


def test_identity_is_exact(device):
    vol = (torch.randn(7, 8, 9) * 1000).to(device)
    for mode in ("deform", "knoche", "carve"):
        assert torch.equal(warp(vol, torch.zeros(3, 3, 3, 3, device=device), mode=mode, inverse_iters=3), vol)


def test_uniform_offset_moves_content_from_a_to_b(device):
    vol = torch.zeros(12, 12, 12, dtype=torch.float64, device=device)
    A = (3, 4, 5)
    vol[A] = 1.0
    d = (2.0, -1.0, 3.0)
    offsets = torch.tensor(d, dtype=torch.float64, device=device).view(3, 1, 1, 1).expand(3, 3, 3, 3)
    out = warp(vol, offsets, check=False)
    B = tuple(a + int(x) for a, x in zip(A, d))
    assert float(out[B]) == pytest.approx(1.0, abs=1e-12)
    assert float(out.sum()) == pytest.approx(1.0, abs=1e-12)


def cell_centred_np(arr, pos):
    """Trilinear lookup of ``arr`` (D, H, W) at voxel positions ``pos`` (3,) with clamping to the edges."""
    p = [min(max(q, 0.0), n - 1) for q, n in zip(pos, arr.shape)]
    i0 = [min(int(np.floor(q)), n - 2) if n > 1 else 0 for q, n in zip(p, arr.shape)]
    f = [q - i for q, i in zip(p, i0)]
    val = 0.0
    for corner in np.ndindex(2, 2, 2):
        idx = tuple(min(i + c, n - 1) for i, c, n in zip(i0, corner, arr.shape))
        w = np.prod([fi if c else 1 - fi for fi, c in zip(f, corner)])
        val += w * arr[idx]
    return val


def test_knoche_mode_equals_cell_centred_lookup(device):
    rng = np.random.default_rng(1)
    shape, n = (6, 7, 8), (3, 4, 3)
    vol = rng.normal(size=shape)
    nodes = rng.normal(scale=1.2, size=(3,) + n)
    out = warp(torch.tensor(vol, device=device), torch.tensor(nodes, device=device), mode="knoche", check=False)
    out = out.cpu().numpy()
    ref = np.zeros(shape)
    for ijk in np.ndindex(*shape):
        uvw = [(i + 0.5) / N for i, N in zip(ijk, shape)]  # texture coordinates
        node_pos = [t * k - 0.5 for t, k in zip(uvw, n)]  # cell-centred node texels
        u = [cell_centred_np(nodes[c], node_pos) for c in range(3)]
        ref[ijk] = cell_centred_np(vol, [i - uc for i, uc in zip(ijk, u)])
    assert np.abs(out - ref).max() < 1e-10


def test_fixed_point_inverse_round_trip(device):
    rng = np.random.default_rng(2)
    shape = (33, 33, 33)
    # 30% of the node spacing (8 voxels)
    nodes = torch.tensor(rng.uniform(-1, 1, size=(3, 5, 5, 5)) * 0.3 * 8, device=device)
    field = DisplacementField(nodes, shape)
    p = torch.tensor(rng.uniform(2, 30, size=(1, 3, 500)), device=device)
    X0, _ = inverse_points(field, p, iters=0)
    X, info = inverse_points(field, p, iters=50, tol=1e-6)
    assert float(inverse_residual(field, X, p).max()) < 1e-3
    assert float(inverse_residual(field, X0, p).max()) > 1e-2  # first order is visibly worse
    assert info["iterations"] < 50


def test_jacobian_of_linear_field_and_folding(device):
    A = torch.tensor([[0.1, 0.05, 0.0], [0.0, -0.2, 0.02], [0.03, 0.0, 0.1]], dtype=torch.float64)
    ax = [torch.arange(6, dtype=torch.float64)] * 3
    p = torch.stack(torch.meshgrid(*ax, indexing="ij"))[None]
    u = torch.einsum("ij,bjdhw->bidhw", A, p).to(device)
    det = jacobian_determinant(u).cpu()
    assert torch.allclose(det, torch.linalg.det(torch.eye(3, dtype=torch.float64) + A).expand_as(det))
    g = torch.Generator().manual_seed(0)
    spacing = 63 / 8
    small = ((torch.rand(3, 9, 9, 9, generator=g) * 2 - 1) * 0.2 * spacing).to(device)
    big = ((torch.rand(3, 9, 9, 9, generator=g) * 2 - 1) * 1.0 * spacing).to(device)
    assert folding_fraction(small, (64, 64, 64), samples=(64, 64, 64)) == 0.0
    assert 0.05 < folding_fraction(big, (64, 64, 64), samples=(64, 64, 64)) < 0.3  # REFERENCE 5.3: 13.9%
    with pytest.warns(FoldingWarning, match="folds"):
        warp(torch.zeros(64, 64, 64, device=device), big)


def test_bspline_texture_is_smooth_and_reproduces_constants(device):
    c = offset_texture(torch.full((3, 4, 4, 4), 2.5, dtype=torch.float64, device=device), (10, 10, 10), order="bspline")
    assert torch.allclose(c, torch.full_like(c, 2.5))
    spike = torch.zeros(3, 5, 5, 5, dtype=torch.float64, device=device)
    spike[0, 2, 2, 2] = 1.0
    lin = offset_texture(spike, (17, 17, 17))
    bs = offset_texture(spike, (17, 17, 17), order="bspline")
    assert 0 < float(bs.max()) < float(lin.max())  # approximating, smoother


def test_carve_keeps_values_and_removes_material(device):
    vol = torch.arange(8 * 8 * 8, dtype=torch.float64, device=device).reshape(8, 8, 8)
    mask = torch.ones(8, 8, 8, dtype=torch.float64, device=device)
    mask[:, :, 6:] = 0
    zero = torch.zeros(3, 2, 2, 2, dtype=torch.float64, device=device)
    out = warp(vol, zero, mode="carve", material=mask, fill=-5.0)
    assert torch.equal(out[:, :, :6], vol[:, :, :6]) and bool((out[:, :, 6:] == -5.0).all())
    offsets = torch.zeros(3, 3, 3, 3, dtype=torch.float64, device=device)
    offsets[2] = -2.0  # body pushed 2 voxels towards w-
    out = warp(vol, offsets, mode="carve", fill=-5.0, check=False)
    assert torch.allclose(out[:, :, :5], vol[:, :, :5])  # values unchanged, not shifted
    assert bool((out[:, :, 7] == -5.0).all())  # uncovered material removed


def test_gradcheck_warp_wrt_offsets():
    torch.manual_seed(0)
    vol = torch.randn(5, 6, 7, dtype=torch.float64)
    nodes = (torch.rand(1, 3, 3, 3, 3, dtype=torch.float64) * 0.8 + 0.13).requires_grad_()  # fractional
    assert torch.autograd.gradcheck(lambda u: warp(vol, u, check=False), (nodes,))
    assert torch.autograd.gradcheck(lambda u: warp(vol, u, check=False, inverse_iters=2, tol=0), (nodes,))


@pytest.mark.parametrize(
    "bad,match",
    [
        (dict(volume=torch.zeros(4, 4)), "shape"),
        (dict(volume=torch.full((4, 4, 4), float("nan"))), "finite"),
        (dict(offsets=torch.zeros(2, 3, 3, 3)), "shape"),
        (dict(offsets=torch.zeros(3, 9, 3, 3)), "no finer"),
        (dict(offsets=torch.zeros(3, 3, 3, 3, dtype=torch.bool)), "real-valued"),
        (dict(mode="melt"), "one of"),
        (dict(volume=np.array([["a"]], dtype=object)), "numeric"),
    ],
)
def test_bad_input_is_one_line_config_error(bad, match):
    args = dict(volume=torch.zeros(4, 4, 4), offsets=torch.zeros(3, 2, 2, 2), mode="deform")
    args.update(bad)
    with pytest.raises(ConfigError, match=match) as e:
        warp(args["volume"], args["offsets"], mode=args["mode"])
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".nii.gz", ".nrrd"])
def test_volume_file_round_trip(tmp_path, suffix):
    vol = np.random.default_rng(3).normal(size=(4, 5, 6)).astype(np.float32)
    path = tmp_path / f"v{suffix}"
    save_volume(path, vol)
    assert np.array_equal(load_volume(path), vol)


def test_volume_files_bad(tmp_path):
    with pytest.raises(ConfigError, match=r"\.npy, \.npz"):
        load_volume(tmp_path / "v.tiff")
    np.save(tmp_path / "nan.npy", np.full((3, 3, 3), np.nan, np.float32))
    with pytest.raises(ConfigError, match="finite"):
        load_volume(tmp_path / "nan.npy")
    np.save(tmp_path / "flat.npy", np.zeros((3, 3), np.float32))
    with pytest.raises(ConfigError, match="3-D"):
        load_volume(tmp_path / "flat.npy")
    (tmp_path / "broken.nrrd").write_text("not nrrd")
    with pytest.raises(ConfigError, match="readable"):
        load_volume(tmp_path / "broken.nrrd")


def test_cli_warp_matches_library_and_rejects_bad_input(tmp_path, capsys):
    from torchdeform import cli

    rng = np.random.default_rng(4)
    vol = rng.normal(size=(9, 9, 9)).astype(np.float32)
    offs = rng.normal(scale=0.5, size=(3, 3, 3, 3)).astype(np.float32)
    np.save(tmp_path / "v.npy", vol)
    np.save(tmp_path / "o.npy", offs)
    assert (
        cli.main(
            argv=[
                "warp",
                str(tmp_path / "v.npy"),
                str(tmp_path / "o.npy"),
                "--out",
                str(tmp_path / "w.npy"),
                "--inverse-iters",
                "3",
            ]
        )
        == 0
    )
    ref = warp(torch.tensor(vol), torch.tensor(offs), inverse_iters=3).numpy()
    assert np.allclose(np.load(tmp_path / "w.npy"), ref, atol=1e-6)
    np.save(tmp_path / "bad.npy", offs[:2])
    capsys.readouterr()
    code = cli.main(argv=["warp", str(tmp_path / "v.npy"), str(tmp_path / "bad.npy"), "--out", str(tmp_path / "x.npy")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("torchdeform: ") and "Traceback" not in err and err.count("\n") == 1
