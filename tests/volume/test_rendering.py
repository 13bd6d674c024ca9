"""Renderer: analytic slab transmittance, MIP of one voxel, rendering through offsets against the
warped volume, gradients, transfer-function files, images and the CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.volume import warp
from torchdeform.volume.cameras import OrbitCamera
from torchdeform.volume.images import to_image
from torchdeform.volume.rendering import render
from torchdeform.volume.transfer import TransferFunction, load_tf, preset


def flat_tf(sigma, dtype=F64):
    return TransferFunction([-1e4, 1e4], torch.ones(2, 3, dtype=dtype), torch.full((2,), sigma, dtype=dtype))


@pytest.mark.parametrize("view", ["d", "-h", "w"])
@pytest.mark.parametrize("step", [1.0, 0.5, 0.37, 3.0])
def test_homogeneous_slab_transmittance(view, step, device):
    shape = (12, 9, 7)
    sigma = 0.13
    vol = torch.full(shape, 5.0, dtype=F64, device=device)
    img = render(vol, tf=flat_tf(sigma), mode="dvr", view=view, step=step, stop=0)
    assert img.device == device
    L = shape["dhw".index(view[-1])]
    expected = torch.tensor(math.exp(-sigma * L), dtype=F64, device=device)
    assert torch.allclose(1 - img[0, 3], expected, atol=1e-4, rtol=0)
    assert torch.allclose(img[0, :3], img[0, 3:4].expand(3, -1, -1), atol=1e-12)  # white emission


@pytest.mark.parametrize("steps", [0.5, 1.0, 2.0])
def test_orbit_slab_transmittance_follows_path_length(steps, device):
    vol = torch.full((10, 10, 10), 5.0, dtype=F64, device=device)
    sigma = 0.05
    cam = OrbitCamera(azimuth=0.0, elevation=0.0, size=(9, 9), fov=10.0)
    img = render(vol, tf=flat_tf(sigma), mode="dvr", view=cam, step=steps, stop=0)
    # the central ray crosses the volume along H: path length 10 voxels
    assert float(1 - img[0, 3, 4, 4]) == pytest.approx(math.exp(-sigma * 10), abs=1e-4)


def test_mip_of_a_single_bright_voxel(device):
    vol = torch.zeros(9, 10, 11, dtype=F64, device=device)
    vol[4, 6, 3] = 7.0
    img = render(vol, mode="mip", view="d")[0, 0]
    assert float(img[6, 3]) == 7.0 and float(img.sum()) == 7.0
    img = render(vol, mode="mip", view="-w")[0, 0]
    assert float(img[4, 6]) == 7.0 and float(img.sum()) == 7.0
    cam = OrbitCamera(azimuth=0.0, elevation=0.0, size=(33, 33), fov=30.0)
    vol2 = torch.zeros(9, 9, 9, dtype=F64, device=device)
    vol2[4, 4, 4] = 7.0
    img = render(vol2, mode="mip", view=cam, step=0.25)[0, 0]
    # the central ray passes through the voxel centre; the nearest sample is at most step / 2 away
    assert 7.0 * (1 - 0.125) - 1e-9 <= float(img[16, 16]) <= 7.0
    assert float(img.max()) == float(img[16, 16])
    assert float(img[0, 0]) == 0.0


def test_average_of_a_ramp(device):
    vol = torch.arange(8, dtype=F64, device=device).view(8, 1, 1).expand(8, 3, 3).contiguous()
    img = render(vol, mode="average", view="d")
    assert torch.allclose(img, torch.full_like(img, 3.5))


def test_render_through_offsets_equals_render_of_warped_volume(device):
    torch.manual_seed(0)
    vol = (torch.randn(10, 11, 12, dtype=F64) * 100).to(device)
    offsets = (torch.randn(3, 3, 4, 3, dtype=F64) * 1.3).to(device)
    tf = TransferFunction([-300, 0, 300], [[0, 0, 1], [0, 1, 0], [1, 0, 0]], [0.01, 0.05, 0.2])
    tf = tf.to(F64)
    for mode in ("dvr", "mip", "average"):
        for view in ("d", "-h", "w"):
            a = render(vol, tf=tf, mode=mode, view=view, offsets=offsets, stop=0)
            b = render(warp(vol, offsets, check=False), tf=tf, mode=mode, view=view, stop=0)
            assert torch.allclose(a, b, atol=1e-9), (mode, view)
    a = render(vol, tf=tf, mode="dvr", view="d", offsets=offsets, order="bspline", stop=0)
    b = render(warp(vol, offsets, order="bspline", check=False), tf=tf, mode="dvr", view="d", stop=0)
    assert torch.allclose(a, b, atol=1e-9)
    a = render(vol, tf=tf, mode="mip", view="h", offsets=offsets, warp_mode="knoche")
    b = render(warp(vol, offsets, mode="knoche", check=False), tf=tf, mode="mip", view="h")
    assert torch.allclose(a, b, atol=1e-9)


def test_early_termination_changes_little_and_stops(device):
    vol = torch.full((40, 5, 5), 1.0, dtype=F64, device=device)
    full = render(vol, tf=flat_tf(1.0), mode="dvr", view="d", stop=0)
    early = render(vol, tf=flat_tf(1.0), mode="dvr", view="d", stop=1e-3, chunk_points=25)
    assert early.device == device and torch.allclose(full, early, atol=1e-3)


def test_pieces_that_cover_the_body_with_zero_offsets_are_the_plain_render(device):
    """Two pieces (halves of the node grid along W), unmoved: every sample finds its piece, so the
    image is the plain render (axis view and orbit camera)."""
    torch.manual_seed(3)
    vol = (torch.randn(9, 10, 11, dtype=F64) * 100).to(device)
    zero = torch.zeros(3, 3, 3, 5, dtype=F64, device=device)
    left = torch.zeros(3, 3, 5, dtype=F64, device=device)
    left[..., :3] = 1.0
    pieces = [(zero, left), (zero, 1.0 - left)]
    cam = OrbitCamera(azimuth=25.0, elevation=10.0, size=(8, 8))
    for mode, view in (("mip", "d"), ("average", "-w"), ("mip", cam)):
        a = render(vol, mode=mode, view=view, pieces=pieces)
        b = render(vol, mode=mode, view=view)
        assert a.device == device and torch.allclose(a, b, atol=1e-9), (mode, view)


def test_gradcheck_wrt_offsets_and_transfer_function():
    torch.manual_seed(1)
    vol = torch.rand(5, 4, 6, dtype=F64) * 100
    offsets = (torch.rand(1, 3, 2, 3, 3, dtype=F64) * 0.6 + 0.17).requires_grad_()  # fractional positions
    colors = torch.rand(3, 3, dtype=F64, requires_grad=True)
    sigma = (torch.rand(3, dtype=F64) * 0.3 + 0.05).requires_grad_()

    def f(u, c, s):
        tf = TransferFunction([-10.0, 45.0, 110.0], c, s, resolution=64)
        return render(vol, tf=tf, mode="dvr", view="h", offsets=u, stop=0)

    assert torch.autograd.gradcheck(f, (offsets, colors, sigma))
    cam = OrbitCamera(azimuth=20.0, elevation=15.0, size=(4, 4))
    assert torch.autograd.gradcheck(lambda u: render(vol, mode="average", view=cam, offsets=u, step=0.7), (offsets,))


def test_transfer_function_file_round_trip_and_errors(tmp_path):
    tf = preset("ct-bone")
    tf.save(tmp_path / "bone.tf")
    back = load_tf(tmp_path / "bone.tf")
    assert torch.allclose(back.values, tf.values) and torch.allclose(back.sigma, tf.sigma, atol=1e-6)
    (tmp_path / "bad.tf").write_text("# value r g b opacity\n0 0 0 0 0\n10 1 1 1\n")
    with pytest.raises(ConfigError, match=r"bad\.tf:3: .*five numbers"):
        load_tf(tmp_path / "bad.tf")
    (tmp_path / "order.tf").write_text("10 0 0 0 0\n0 1 1 1 1\n")
    with pytest.raises(ConfigError, match="increasing"):
        load_tf(tmp_path / "order.tf")
    with pytest.raises(ConfigError, match="preset"):
        render(torch.zeros(3, 3, 3), tf="no-such-preset")
    rel = TransferFunction([0.0, 1.0], [[0, 0, 0], [1, 1, 1]], [0.0, 1.0], relative=True)
    _rgb, s = rel(torch.tensor([150.0]), volume=torch.tensor([100.0, 200.0]))
    assert float(s[0]) == pytest.approx(0.5, abs=1e-3)


def test_bad_render_input():
    with pytest.raises(ConfigError, match="view"):
        render(torch.zeros(3, 3, 3), view="x")
    with pytest.raises(ConfigError, match="offsets"):
        render(torch.zeros(3, 3, 3), offsets=torch.zeros(2, 2, 2, 2))
    with pytest.raises(ConfigError, match="finite"):
        render(torch.full((3, 3, 3), float("nan")))


def test_images_and_cli_render(tmp_path, capsys):
    from PIL import Image

    from torchdeform import cli
    from torchdeform.volume import phantom

    vol = phantom(shape=(24, 24, 24))
    np.save(tmp_path / "v.npy", vol.numpy())
    offsets = np.zeros((3, 3, 3, 3), np.float32)
    offsets[0, 2] = 3.0
    np.save(tmp_path / "o.npy", offsets)
    assert cli.main(argv=["render", str(tmp_path / "v.npy"), "--out", str(tmp_path / "a.png"), "--mode", "mip"]) == 0
    assert (
        cli.main(
            argv=[
                "render",
                str(tmp_path / "v.npy"),
                "--out",
                str(tmp_path / "b.png"),
                "--offsets",
                str(tmp_path / "o.npy"),
                "--tf",
                "ct-bone",
            ]
        )
        == 0
    )
    assert (
        cli.main(
            argv=["render", str(tmp_path / "v.npy"), "--out", str(tmp_path / "c.gif"), "--frames", "3", "--size", "16"]
        )
        == 0
    )
    assert Image.open(tmp_path / "a.png").size == (24, 24)
    assert Image.open(tmp_path / "c.gif").n_frames == 3
    img = to_image(render(vol, tf="ct-bone", mode="dvr", view="d"))
    assert img.dtype == np.uint8 and img.shape == (24, 24, 3) and img.max() > 100
    capsys.readouterr()
    assert cli.main(argv=["render", str(tmp_path / "v.npy"), "--out", str(tmp_path / "x.jpg")]) == 2
    assert cli.main(argv=["render", str(tmp_path / "nope.npy"), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 2


# ----------------------------------------------------------------- fast path (engine="eager"; never compiled here)
@pytest.mark.parametrize("mode", ["dvr", "mip", "average"])
def test_fast_engine_equals_grid_sample_path(mode, device):
    torch.manual_seed(2)
    vol = (torch.randn(9, 10, 11, dtype=F64) * 100).to(device)
    offsets = (torch.randn(3, 3, 4, 3, dtype=F64) * 1.3).to(device)
    tf = TransferFunction([-300, 0, 300], [[0, 0, 1], [0, 1, 0], [1, 0, 0]], [0.01, 0.05, 0.2]).to(F64)
    cases = [
        ("d", {}),
        ("-h", dict(padding="zeros", fill=-50.0)),
        ("w", dict(warp_mode="knoche")),
        ("-d", dict(step=0.7, size=(7, 9))),
        ("h", dict(chunk_points=30, stop=0.5)),
    ]
    for view, kw in cases:
        kw = dict(dict(stop=0), **kw)
        a = render(vol, tf=tf, mode=mode, view=view, offsets=offsets, engine="eager", **kw)
        b = render(vol, tf=tf, mode=mode, view=view, offsets=offsets, **kw)
        assert torch.allclose(a, b, atol=1e-10, rtol=0), (mode, view, kw)


def test_fast_engine_mip_equals_scipy_warp(device):
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(5)
    shape = (8, 9, 10)
    vol = rng.normal(size=shape) * 50
    nodes = rng.normal(scale=1.2, size=(3, 3, 3, 4))
    # the offsets at every voxel (corner-aligned trilinear) and the warp, with scipy only
    u = np.stack(
        [
            map_coordinates(
                nodes[c],
                np.meshgrid(*[np.arange(N) * (k - 1) / (N - 1) for k, N in zip(nodes.shape[1:], shape)], indexing="ij"),
                order=1,
            )
            for c in range(3)
        ]
    )
    grid = np.stack(np.meshgrid(*[np.arange(N) for N in shape], indexing="ij"))
    warped = map_coordinates(vol, grid - u, order=1, mode="nearest")
    vol_t, nodes_t = torch.tensor(vol, device=device), torch.tensor(nodes, device=device)
    for view, axis in (("d", 0), ("w", 2)):
        img = render(vol_t, mode="mip", view=view, offsets=nodes_t, engine="eager").cpu()
        assert np.abs(img[0, 0].numpy() - warped.max(axis)).max() < 1e-9
    img = render(vol_t, mode="average", view="-h", offsets=nodes_t, engine="eager").cpu()
    assert np.abs(img[0, 0].numpy() - warped.mean(1)).max() < 1e-9


@pytest.mark.parametrize("padding,mode", [("border", "nearest"), ("zeros", "grid-constant")])
def test_trilinear_flat_equals_map_coordinates(padding, mode):
    from scipy.ndimage import map_coordinates

    from torchdeform.volume.fastpath import trilinear_flat

    rng = np.random.default_rng(6)
    vol = rng.normal(size=(5, 6, 7))
    pts = rng.uniform(-2.5, 8.5, size=(3, 400))
    out = trilinear_flat(torch.tensor(vol).reshape(-1), list(torch.tensor(pts)), vol.shape, padding=padding, fill=0.3)
    ref = map_coordinates(vol, pts, order=1, mode=mode, cval=0.3)
    assert np.abs(out.numpy() - ref).max() < 1e-12


def test_fast_engine_skips_transparent_slabs_and_float32(device):
    from torchdeform.volume import DisplacementField
    from torchdeform.volume.fastpath import _render_axis_fast
    from torchdeform.volume.plan import RenderPlan

    vol = torch.full((40, 12, 12), -1000.0, device=device)
    vol[25:30, 3:9, 3:9] = 800.0  # bone in a slab of air
    offsets = torch.zeros(3, 5, 3, 3, device=device)
    offsets[0, 2] = 1.5
    tf = preset("ct-bone")
    a = render(vol, tf=tf, mode="dvr", view="d", offsets=offsets, engine="eager", chunk_points=144 * 4, stop=0)
    b = render(vol, tf=tf, mode="dvr", view="d", offsets=offsets, chunk_points=144 * 4, stop=0)
    assert float(a[0, 3].max()) > 0.5 and torch.allclose(a, b, atol=1e-5)
    lo, hi = tf.range(volume=vol)
    plan = RenderPlan(
        volume=vol[None, None],
        mode="dvr",
        view="d",
        field=DisplacementField(offsets, vol.shape),
        tf=tf,
        lo=lo,
        hi=hi,
        table=tf.table(dtype=torch.float32, device=device),
        stop=0,
        chunk_points=144 * 4,
        engine="eager",
    )
    _, info = _render_axis_fast(plan)
    assert info["skipped"] >= 6 and info["chunks"] <= 4  # 10 chunks of 4 slabs, 2-3 hold bone
    with pytest.raises(ConfigError, match="engine"):
        render(vol, tf=tf, engine="numba")
