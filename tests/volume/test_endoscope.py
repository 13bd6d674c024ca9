"""The endoscope camera and the interior renderer, each against an independent oracle.

Oracles: closed-form emission-absorption integrals along straight rays (constant extinction
over the box; a slab whose trilinear interpolant is piecewise linear along D, with a transfer
function linear in the value); a dense numeric integral along each ray of the trilinear field by
``scipy.ndimage.map_coordinates`` (order 1) at a 10x finer step in numpy; a hand-written pinhole
formula with the focal length from ``fov`` and ``min(h, w)``; the circle formula of the mask and
Brown's radial law on the rays' angles; the rest-space identity of a pure translation
(``V(p - t)`` seen from ``c`` is ``V`` seen from ``c - t``); the analytic normal of a sphere at the
analytic ray hit; ``torch.autograd.gradcheck`` (finite differences); analytic ray-sphere hits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import map_coordinates

from tests.helpers import F64
from torchdeform.errors import ConfigError
from torchdeform.volume import OrbitCamera, TransferFunction
from torchdeform.volume.endoscope import EndoscopeCamera
from torchdeform.volume.interior import Capsule, Headlight, Sphere, render_endoscope


# ------------------------------------------------------------------ independent helpers (numpy)
def render(*args, **kw):
    """The torch engine (this module's subject); ``engine="auto"`` is compared with it separately."""
    kw.setdefault("engine", "torch")
    return render_endoscope(*args, **kw)


def np_basis(direction, up=(1.0, 0.0, 0.0)):
    """forward, up, right by Gram-Schmidt; right = forward x up in (D, H, W) components."""
    f = np.asarray(direction, float)
    f = f / np.linalg.norm(f)
    u = np.asarray(up, float)
    u = u - (u @ f) * f
    u = u / np.linalg.norm(u)
    return f, u, np.cross(f, u)


def np_pinhole_rays(direction, fov, size, up=(1.0, 0.0, 0.0)):
    """Unit directions (h, w, 3) of the pixel centres of an undistorted pinhole."""
    f, u, r = np_basis(direction, up)
    h, w = size
    m = min(h, w) / 2
    tan = math.tan(math.radians(fov) / 2)
    rows, cols = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    x = (cols - w / 2) / m * tan
    y = (h / 2 - rows) / m * tan
    d = f + x[..., None] * r + y[..., None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def np_box(eye, d, shape):
    """Entry and exit t of the rays (..., 3) through the box [-0.5, N - 0.5]."""
    lo = np.full(3, -0.5)
    hi = np.asarray(shape, float) - 0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - eye) / d
        tb = (hi - eye) / d
    t_in = np.nanmax(np.minimum(ta, tb), axis=-1)
    t_out = np.nanmin(np.maximum(ta, tb), axis=-1)
    return np.maximum(t_in, 0.0), t_out


def flat_tf(sigma, colour=(1.0, 1.0, 1.0)):
    return TransferFunction([-1e4, 1e4], torch.tensor([colour, colour], dtype=F64), torch.full((2,), sigma, dtype=F64))


def linear_tf(s):
    """sigma(v) = s v and white on [0, 1] (exactly linear: the table is linear in v)."""
    return TransferFunction([0.0, 1.0], torch.ones(2, 3, dtype=F64), torch.tensor([0.0, s], dtype=F64))


# ------------------------------------------------------------------ 1. emission-absorption integrals
@pytest.mark.parametrize("direction", [(0, 0, 1), (1, 1, 0), (-0.3, 0.5, -0.8), (1, -2, 0.5)])
@pytest.mark.parametrize("near, far", [(0.0, math.inf), (0.0, 4.0), (1.5, 6.0)])
def test_constant_volume_is_one_minus_exp_of_the_chord(direction, near, far):
    shape, sigma = (10, 12, 14), 0.07
    eye = np.array([4.2, 5.1, 6.3])
    vol = torch.full(shape, 5.0, dtype=F64)
    size, fov = (6, 7), 90.0
    cam = EndoscopeCamera(position=eye, direction=direction, fov=fov, size=size, near=near, far=far, mask=False)
    img = render(vol, cam, tf=flat_tf(sigma), light=None, step=0.37, stop=0)
    d = np_pinhole_rays(direction, fov, size)
    _, t_out = np_box(eye, d, shape)
    L = np.clip(np.minimum(t_out, far) - near, 0, None)
    expected = 1 - np.exp(-sigma * L)
    assert np.abs(img[0, 3].numpy() - expected).max() < 1e-3 * 1.0
    assert torch.allclose(img[0, :3], img[0, 3:4].expand(3, -1, -1), atol=1e-12)  # white emission


def _slab_antiderivative(z, a, b):
    """G(z) = int_{-inf}^z v, v the trilinear interpolant along D of the indicator of voxels a..b."""
    z = np.asarray(z, float)
    out = np.zeros_like(z)
    r1 = (z > a - 1) & (z <= a)
    out[r1] = (z[r1] - (a - 1)) ** 2 / 2
    r2 = (z > a) & (z <= b)
    out[r2] = 0.5 + (z[r2] - a)
    r3 = (z > b) & (z <= b + 1)
    x = z[r3] - b
    out[r3] = 0.5 + (b - a) + x - x * x / 2
    out[z > b + 1] = 1.0 + (b - a)
    return out


@pytest.mark.parametrize("direction", [(1, 0.2, 0.1), (-0.7, 0.4, 0.3), (0.25, -0.6, 0.75), (-1, -1, 2)])
@pytest.mark.parametrize("far", [math.inf, 5.0])
def test_slab_seen_from_inside_equals_its_closed_integral(direction, far):
    shape, a, b, s = (20, 10, 10), 6, 12, 0.5
    vol = torch.zeros(shape, dtype=F64)
    vol[a : b + 1] = 1.0
    eye = np.array([9.3, 4.6, 5.2])  # inside the slab
    size, fov = (5, 6), 80.0
    cam = EndoscopeCamera(position=eye, direction=direction, fov=fov, size=size, far=far, mask=False)
    img = render(vol, cam, tf=linear_tf(s), light=None, step=0.1, stop=0)
    d = np_pinhole_rays(direction, fov, size)
    _, t_out = np_box(eye, d, shape)
    t1 = np.minimum(t_out, far)
    D0, D1 = eye[0] + 0 * t1, eye[0] + d[..., 0] * t1
    integral = (_slab_antiderivative(D1, a, b) - _slab_antiderivative(D0, a, b)) / d[..., 0]
    expected = 1 - np.exp(-s * integral)
    assert np.abs(img[0, 3].numpy() - expected).max() < 1e-3


@pytest.mark.parametrize("eye", [(11.0, 9.0, 10.5), (3.0, 4.0, 2.0)])  # inside the ball; outside it
def test_voxel_ball_matches_a_dense_numeric_integral(eye):
    shape, R, s = (22, 20, 21), 6.0, 0.4
    g = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    vnp = (np.linalg.norm(g - np.array([10.5, 9.7, 10.0]), axis=-1) <= R).astype(float)
    # colour varies with the value: (v, 1 - v, 0.5); sigma = s v
    tf = TransferFunction([0.0, 1.0], torch.tensor([[0, 1, 0.5], [1, 0, 0.5]], dtype=F64), torch.tensor([0.0, s]))
    direction, size, fov = (0.6, 0.5, 0.62), (5, 6), 100.0
    cam = EndoscopeCamera(position=eye, direction=direction, fov=fov, size=size, mask=False)
    img = render(torch.tensor(vnp), cam, tf=tf, light=None, step=0.05, stop=0)
    # oracle: sum over a fine step of T sigma c dt, the trilinear field by map_coordinates
    e = np.asarray(eye, float)
    d = np_pinhole_rays(direction, fov, size).reshape(-1, 3)
    t0, t1 = np_box(e, d, shape)
    out = np.zeros((len(d), 4))
    for k in range(len(d)):
        n = max(1, math.ceil((t1[k] - t0[k]) / 0.005))
        dt = (t1[k] - t0[k]) / n
        t = t0[k] + (np.arange(n) + 0.5) * dt
        p = e[:, None] + d[k][:, None] * t
        v = map_coordinates(vnp, p, order=1, mode="nearest")
        tau = np.concatenate([[0.0], np.cumsum(s * v * dt)])
        w = np.exp(-tau[:-1]) * (-np.expm1(-s * v * dt))
        col = np.stack([v, 1 - v, np.full_like(v, 0.5)])
        out[k, :3] = (col * w).sum(1)
        out[k, 3] = 1 - np.exp(-tau[-1])
    got = img[0].permute(1, 2, 0).reshape(-1, 4).numpy()
    assert np.abs(got - out).max() < 1e-3
    assert out[:, 3].max() > 0.3  # the ball is seen


# ------------------------------------------------------------------ 2. projection
@pytest.mark.parametrize("fov", [100.0, 120.0, 45.0])
def test_project_is_the_hand_pinhole(fov):
    gen = torch.Generator().manual_seed(1)
    eye, direction, up, size = np.array([5.0, 6.0, 7.0]), (0.3, -0.5, 0.8), (1.0, 0.2, 0.0), (30, 40)
    cam = EndoscopeCamera(position=eye, direction=direction, up=up, fov=fov, size=size, mask=False, inside="allow")
    f, u, r = np_basis(direction, up)
    rel = torch.randn(200, 3, generator=gen, dtype=F64).numpy() * 5
    rel = rel[rel @ f > 0.5]
    pix, depth = cam.project(torch.tensor(eye + rel))
    fpx = (min(size) / 2) / math.tan(math.radians(fov) / 2)  # focal length in pixels
    z = rel @ f
    col = size[1] / 2 + fpx * (rel @ r) / z
    row = size[0] / 2 - fpx * (rel @ u) / z
    assert np.allclose(pix.numpy(), np.stack([row, col], -1), atol=1e-9)
    assert np.allclose(depth.numpy(), z, atol=1e-12)
    behind, _ = cam.project(torch.tensor(eye - 2 * f))
    assert bool(torch.isnan(behind).all())


@pytest.mark.parametrize("k1", [0.0, -0.05, 0.2])  # unmasked 9 x 13: k1 > -0.058
@pytest.mark.parametrize("fov", [120.0, 70.0])
def test_rays_through_pixel_centres_project_back_onto_them(k1, fov):
    h, w = 9, 13
    cam = EndoscopeCamera(
        position=(4.0, 5.0, 6.0), direction=(0.2, 1.0, -0.4), fov=fov, size=(h, w), distortion=k1, mask=False
    )
    eye, d, valid = cam.rays((10, 12, 14), dtype=F64)
    assert bool(valid.all()) and torch.allclose(d.norm(dim=0), torch.ones(h, w, dtype=F64))
    pts = eye.view(3, 1, 1) + 3.7 * d
    pix, depth = cam.project(pts.permute(1, 2, 0))
    rows, cols = torch.meshgrid(torch.arange(h, dtype=F64) + 0.5, torch.arange(w, dtype=F64) + 0.5, indexing="ij")
    assert (pix - torch.stack([rows, cols], -1)).abs().max() < 1e-6
    assert bool((depth > 0).all())


def test_undistorted_rays_match_the_orbit_camera():
    """Same pose, h <= w, no mask: the endoscope's rays are the orbit camera's (same frame convention)."""
    shape, size = (16, 18, 20), (6, 9)
    orbit = OrbitCamera(azimuth=35.0, elevation=-20.0, distance=0.3, fov=75.0, size=size)
    eye_o, d_o = orbit.rays(shape, dtype=F64)
    centre = torch.tensor([(n - 1) / 2 for n in shape], dtype=F64)
    cam = EndoscopeCamera(position=eye_o, direction=centre - eye_o, fov=75.0, size=size, mask=False)
    eye, d, _ = cam.rays(shape, dtype=F64)
    assert torch.allclose(eye, eye_o) and torch.allclose(d, d_o, atol=1e-12)


# ------------------------------------------------------------------ 3. mask and distortion
@pytest.mark.parametrize("size", [(7, 10), (8, 8), (11, 6)])
def test_round_mask_is_the_circle(size):
    h, w = size
    cam = EndoscopeCamera(position=(1.0, 1.0, 1.0), direction=(0, 0, 1), size=size)
    _, _, valid = cam.rays((3, 3, 3))
    i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    circle = (i + 0.5 - h / 2) ** 2 + (j + 0.5 - w / 2) ** 2 <= (min(h, w) / 2) ** 2
    assert np.array_equal(valid.numpy(), circle)
    assert bool(EndoscopeCamera(position=(1.0, 1.0, 1.0), direction=(0, 0, 1), size=size, mask=False)
                .rays((3, 3, 3))[2].all())  # fmt: skip


@pytest.mark.parametrize("k1", [-0.12, 0.15])  # masked: monotonic for k1 > -4/27
@pytest.mark.parametrize("fov", [100.0, 140.0])
def test_barrel_distortion_follows_the_radial_law(k1, fov):
    h, w = 15, 17
    direction = (0.3, 0.4, 1.0)
    cam = EndoscopeCamera(position=(2.0, 2.0, 2.0), direction=direction, fov=fov, size=(h, w), distortion=k1)
    _, d, valid = cam.rays((5, 5, 5), dtype=F64)
    f, u, r = np_basis(direction)
    d = d.permute(1, 2, 0).numpy()
    along = d @ f
    across = np.linalg.norm(d - along[..., None] * f, axis=-1)
    ru = across / along / math.tan(math.radians(fov) / 2)  # tan(theta), well conditioned near the axis
    m = min(h, w) / 2
    rows, cols = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    x, y = (cols - w / 2) / m, (h / 2 - rows) / m
    rd = np.hypot(x, y)
    v = valid.numpy()
    assert np.allclose(rd[v], (ru * (1 + k1 * ru**2))[v], atol=1e-9)
    # and the azimuth is kept: the ray's (right, up) components point along (x, y)
    a, b = d @ r, d @ u
    assert np.allclose(a * y, b * x, atol=1e-12)
    assert v.sum() > 100 and np.isfinite(d).all()  # masked pixels still get finite directions


def test_non_monotonic_distortion_is_refused():
    with pytest.raises(ConfigError, match="distortion"):
        EndoscopeCamera(position=(1.0, 1.0, 1.0), direction=(0, 0, 1), distortion=-0.5)
    EndoscopeCamera(position=(1.0, 1.0, 1.0), direction=(0, 0, 1), distortion=-0.14)  # still monotonic: fine


# ------------------------------------------------------------------ 4. a translated body
def _blob(shape=(24, 24, 24), centre=(12.0, 11.5, 12.5), radius=6.0, dtype=F64):
    g = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=dtype) for n in shape], indexing="ij"))
    r = (g - torch.tensor(centre, dtype=dtype).view(3, 1, 1, 1)).norm(dim=0)
    return 1000.0 * (1 - r / radius).clamp(min=0)  # exactly 0 beyond 6 voxels: a transparent margin


def _ramp_tf(dtype=F64):
    return TransferFunction(
        [0.0, 1000.0],
        torch.tensor([[0.2, 0.4, 1.0], [1.0, 0.6, 0.2]], dtype=dtype),
        torch.tensor([0.0, 0.6], dtype=dtype),
    )


@pytest.mark.parametrize("t", [(1.0, -2.0, 1.0), (0.4, -1.3, 0.7)])
@pytest.mark.parametrize("dtype, tol", [(F64, 1e-9), (torch.float32, 2e-5)])
def test_translated_body_equals_the_camera_moved_back(t, dtype, tol):
    vol = _blob(dtype=dtype)
    c = torch.tensor([12.0, 12.0, 3.0], dtype=F64)
    tt = torch.tensor(t, dtype=F64)
    offsets = tt.view(3, 1, 1, 1).expand(3, 3, 3, 3).to(dtype)
    kw = dict(tf=_ramp_tf(dtype), step=0.3, stop=0)
    size, direction = (7, 8), (0.1, -0.05, 1.0)
    moved = render(vol, EndoscopeCamera(position=c, direction=direction, size=size), offsets=offsets, **kw)
    back = render(vol, EndoscopeCamera(position=c - tt, direction=direction, size=size), **kw)
    assert float(back[0, 3].max()) > 0.5  # the blob is in view
    # the sample points coincide in rest space (X = p - t): equal to rounding, integer or fractional t
    assert (moved - back).abs().max() < tol


# ------------------------------------------------------------------ 5. the headlight
def test_headlight_shades_a_sphere_by_its_analytic_normal():
    shape, R, wdt = (40, 40, 40), 10.0, 3.0
    centre = np.array([19.5, 19.5, 19.5])
    g = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    r = np.linalg.norm(g - centre, axis=-1)
    vol = torch.tensor(1000.0 * np.clip((R - r) / wdt + 0.5, 0, 1))
    tv, ts = [0.0, 480.0, 520.0, 1000.0], [0.0, 0.0, 30.0, 30.0]
    tf = TransferFunction(tv, torch.tensor([[0.9, 0.7, 0.5]] * 4, dtype=F64), torch.tensor(ts))
    eye = np.array([19.5, 19.5, 3.0])  # inside the box, outside the sphere
    direction, size, fov = (0.05, 0.02, 1.0), (12, 12), 70.0
    cam = EndoscopeCamera(position=eye, direction=direction, fov=fov, size=size)
    kw = dict(tf=tf, step=0.05)
    lit = render(vol, cam, light="headlight", **kw)[0].numpy()
    unlit = render(vol, cam, light=None, **kw)[0].numpy()
    # oracle: the analytic hit of each ray with the sphere r = R and its normal; the opacity builds up
    # over a thin shell just outside r = R, so the expected factor is the mean of the analytic
    # 0.2 + 0.8 |n . l| weighted by T sigma along the ray through the continuous radial profile
    d = np_pinhole_rays(direction, fov, size)
    oc = eye - centre
    b = d @ oc
    disc = b * b - (oc @ oc - R * R)
    hit = disc > 0
    t_hit = -b - np.sqrt(np.where(hit, disc, 0))
    n_hit = (oc + t_hit[..., None] * d) / R
    ndl = np.abs((n_hit * d).sum(-1))
    use = hit & (ndl > 0.3) & (unlit[3] > 0.99)
    assert use.sum() >= 30
    expected = []
    for i, j in zip(*np.nonzero(use)):
        t = t_hit[i, j] + np.arange(-3.0, 1.0, 0.002)
        p = oc + t[:, None] * d[i, j]
        rr = np.linalg.norm(p, axis=-1)
        sig = np.interp(1000.0 * np.clip((R - rr) / wdt + 0.5, 0, 1), tv, ts)
        tau = np.concatenate([[0.0], np.cumsum(sig * 0.002)])[:-1]
        wgt = np.exp(-tau) * sig
        cos = np.abs((p / rr[:, None]) @ d[i, j])
        expected.append((wgt * (0.2 + 0.8 * cos)).sum() / wgt.sum())
    ratio = lit[0][use] / unlit[0][use]
    assert np.abs(ratio / np.array(expected) - 1).max() < 0.02
    assert np.abs(ratio / (0.2 + 0.8 * ndl[use]) - 1).max() < 0.02  # the normal at the analytic hit itself
    assert np.allclose(lit[:3][:, use] / unlit[:3][:, use], ratio[None], rtol=1e-9)  # one factor for r, g, b


# ------------------------------------------------------------------ 6. gradients
def _smooth_volume(shape=(8, 8, 8)):
    g = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=F64) for n in shape], indexing="ij"))
    return 500 + 300 * torch.sin(0.7 * g[0] + 0.3) * torch.cos(0.5 * g[1] - 0.2) + 150 * torch.sin(0.6 * g[2] + 1.1)


def test_gradcheck_pose_and_transfer_function():
    vol = _smooth_volume()
    pos = torch.tensor([3.3, 3.6, 1.2], dtype=F64, requires_grad=True)
    dirn = torch.tensor([0.2, 0.1, 1.0], dtype=F64, requires_grad=True)
    colours = torch.tensor([[0.1, 0.3, 0.9], [0.8, 0.5, 0.2], [1.0, 0.9, 0.7]], dtype=F64, requires_grad=True)
    sigma = torch.tensor([0.05, 0.3, 0.6], dtype=F64, requires_grad=True)

    def f(p, dr, c, s):
        tf = TransferFunction([0.0, 500.0, 1000.0], c, s)
        cam = EndoscopeCamera(position=p, direction=dr, fov=60.0, size=(4, 5), mask=False)
        return render(vol, cam, tf=tf, step=0.7, stop=0, engine="torch")

    assert torch.autograd.gradcheck(f, (pos, dirn, colours, sigma), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_offsets_and_volume_reach_the_image():
    vol = _smooth_volume((6, 6, 6)).requires_grad_(True)
    offsets = (0.3 * torch.randn(3, 2, 2, 2, dtype=F64)).requires_grad_(True)
    tf = TransferFunction([0.0, 1000.0], torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.8, 0.6]], dtype=F64), [0.05, 0.4])
    cam = EndoscopeCamera(position=(2.6, 2.4, 0.7), direction=(0.15, 0.1, 1.0), fov=50.0, size=(3, 4), mask=False)

    def f(u):
        return render(vol.detach(), cam, tf=tf, offsets=u, step=0.8, stop=0)

    assert torch.autograd.gradcheck(f, (offsets,), eps=1e-6, atol=1e-6, rtol=1e-4)
    img = render(vol, cam, tf=tf, offsets=offsets.detach(), step=0.8)
    img.sum().backward()
    assert vol.grad is not None and float(vol.grad.abs().sum()) > 0


# ------------------------------------------------------------------ 7. bad input
def _one_line(exc_info, key):
    msg = str(exc_info.value)
    assert "\n" not in msg and key in msg, msg


def test_bad_input_raises_one_line_config_errors():
    vol = torch.zeros(6, 6, 6)
    outside = EndoscopeCamera(position=(2.0, 2.0, 9.0), direction=(0, 0, 1), size=(4, 4))
    with pytest.raises(ConfigError) as e:
        render(vol, outside)
    _one_line(e, "position")
    allowed = EndoscopeCamera(position=(2.0, 2.0, -3.0), direction=(0, 0, 1), size=(4, 4), inside="allow")
    assert render(vol, allowed).shape == (1, 4, 4, 4)
    for fov in (0.0, 180.0, 200.0, -5.0, math.nan):
        with pytest.raises(ConfigError) as e:
            EndoscopeCamera(position=(1, 1, 1), direction=(0, 0, 1), fov=fov)
        _one_line(e, "fov")
    with pytest.raises(ConfigError) as e:
        EndoscopeCamera(position=(1, 1, 1), direction=(0, 0, 0))
    _one_line(e, "direction")
    with pytest.raises(ConfigError) as e:
        EndoscopeCamera(position=(1, 1, 1), direction=(0, 0, 1), near=3.0, far=2.0)
    _one_line(e, "far")
    with pytest.raises(ConfigError) as e:
        EndoscopeCamera(position=(1, 1, 1), direction=(0, 0, 1), size=(0, 4))
    _one_line(e, "size")
    cam = EndoscopeCamera(position=(2.0, 2.0, 2.0), direction=(0, 0, 1), size=(4, 4))
    for kw, key in (
        ({"step": 0.0}, "step"),
        ({"step": -1.0}, "step"),
        ({"light": "sun"}, "light"),
        ({"engine": "cuda"}, "engine"),
        ({"surfaces": ["ball"]}, "surfaces"),
    ):
        with pytest.raises(ConfigError) as e:
            render(vol, cam, **kw)
        _one_line(e, key)


def test_up_parallel_to_direction_picks_another_axis():
    cam = EndoscopeCamera(position=(1.0, 1.0, 1.0), direction=(2.0, 0.0, 0.0))  # default up = +D
    f, u, r = cam.basis()
    assert abs(float(f @ u)) < 1e-12 and abs(float(u.norm()) - 1) < 1e-12 and abs(float(r.norm()) - 1) < 1e-12


# ------------------------------------------------------------------ 8. surfaces and depth
def test_sphere_surface_in_an_empty_volume_is_headlit_analytically():
    vol = torch.zeros(20, 20, 20, dtype=F64)
    eye, centre, R, colour = np.array([9.5, 9.0, 1.0]), np.array([10.0, 9.5, 11.0]), 4.0, (0.9, 0.6, 0.3)
    direction, size, fov = (0.0, 0.0, 1.0), (11, 11), 60.0
    cam = EndoscopeCamera(position=eye, direction=direction, fov=fov, size=size)
    light = Headlight(ambient=0.3, diffuse=0.6)
    img, depth = render(vol, cam, surfaces=[Sphere(centre, R, colour)], light=light, return_depth=True, tf=flat_tf(0.0))
    d = np_pinhole_rays(direction, fov, size)
    oc = eye - centre
    b = d @ oc
    disc = b * b - (oc @ oc - R * R)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    n = (oc + t[..., None] * d) / R
    shade = 0.3 + 0.6 * np.abs((n * d).sum(-1))
    _, _, valid = cam.rays(vol.shape)
    on = hit & valid.numpy()
    assert on.sum() > 10 and (valid.numpy() & ~hit).sum() > 0
    for c in range(3):
        assert np.allclose(img[0, c].numpy()[on], colour[c] * shade[on], atol=1e-9)
    assert np.allclose(img[0, 3].numpy()[on], 1.0) and float(img[0].numpy()[:, ~on].max()) == 0
    assert np.allclose(depth[0].numpy()[on], t[on], atol=1e-9) and np.isinf(depth[0].numpy()[~on]).all()


def test_sphere_in_front_of_a_bright_slab_hides_it():
    vol = torch.zeros(16, 16, 24, dtype=F64)
    vol[:, :, 16:] = 1.0  # a bright, dense slab at the back (W >= 16)
    tf = TransferFunction([0.0, 1.0], torch.ones(2, 3, dtype=F64), torch.tensor([0.0, 5.0]))
    cam = EndoscopeCamera(position=(7.5, 7.5, 1.0), direction=(0, 0, 1), fov=50.0, size=(9, 9))
    ball = Sphere((7.5, 7.5, 9.0), 3.0, (1.0, 0.0, 0.0))
    kw = dict(tf=tf, light=None, return_depth=True, stop=0, step=0.1)
    img, depth = render(vol, cam, surfaces=[ball], **kw)
    plain, plain_depth = render(vol, cam, **kw)
    centre = img[0, :, 4, 4]
    assert torch.allclose(centre, torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=F64), atol=1e-12)  # red: the slab hidden
    assert abs(float(depth[0, 4, 4]) - 5.0) < 1e-9  # 8 voxels ahead minus the radius
    assert float(plain[0, 0, 4, 4]) > 0.99  # without the ball the slab shows white
    # the slab's depth: sigma = 5 (W - 15) on the ramp, so alpha = 1/2 at W = 15 + sqrt(2 ln 2 / 5)
    assert abs(float(plain_depth[0, 4, 4]) - (14.0 + math.sqrt(2 * math.log(2) / 5))) < 0.01
    corner = img[0, :, 0, 4]  # a ray that misses the ball sees the slab
    assert torch.allclose(corner, plain[0, :, 0, 4])


def test_capsule_hit_matches_the_analytic_distance():
    cap = Capsule((5.0, 2.0, 8.0), (5.0, 12.0, 8.0), 1.5, (1, 1, 1))
    eye = torch.tensor([5.0, 7.0, 0.0], dtype=F64)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, -0.7, 0.7141428], [1.0, 0.0, 0.0]], dtype=F64).T
    dirs = dirs / dirs.norm(dim=0)
    t, n = cap.hit(eye, dirs)
    p = eye[:, None] + dirs * torch.where(torch.isfinite(t), t, torch.zeros_like(t))
    # oracle: distance to the segment equals the radius at the hit, and no earlier point is inside
    for k in range(dirs.shape[1]):
        if not math.isfinite(float(t[k])):
            continue
        q = p[:, k].numpy()
        s = np.clip((q[1] - 2.0) / 10.0, 0, 1)
        closest = np.array([5.0, 2.0 + 10 * s, 8.0])
        assert abs(np.linalg.norm(q - closest) - 1.5) < 1e-9
        assert np.allclose(n[:, k].numpy(), (q - closest) / 1.5, atol=1e-9)
        ts = np.linspace(0, float(t[k]) - 1e-6, 200)
        pts = eye.numpy()[:, None] + dirs[:, k].numpy()[:, None] * ts
        ss = np.clip((pts[1] - 2.0) / 10.0, 0, 1)
        dist = np.hypot(pts[0] - 5.0, np.hypot(pts[1] - (2.0 + 10 * ss), pts[2] - 8.0))
        assert (dist > 1.5 - 1e-9).all()
    assert abs(float(t[0]) - 6.5) < 1e-12 and math.isinf(float(t[3]))
    # a ray along the axis meets the end ball first: at y = 2 - 1.5
    t_ax, n_ax = cap.hit(torch.tensor([5.0, -5.0, 8.0], dtype=F64), torch.tensor([[0.0], [1.0], [0.0]], dtype=F64))
    assert abs(float(t_ax[0]) - 5.5) < 1e-12 and torch.allclose(n_ax[:, 0], torch.tensor([0.0, -1.0, 0.0], dtype=F64))


# ------------------------------------------------------------------ speed paths: same image
def test_empty_space_skipping_chunks_and_engines_do_not_change_the_image():
    vol = _blob((24, 24, 32), centre=(12.0, 11.0, 22.0))
    offsets = 0.8 * torch.randn(3, 3, 3, 3, dtype=F64)
    cam = EndoscopeCamera(position=(11.5, 12.5, 1.0), direction=(0.02, -0.03, 1.0), fov=80.0, size=(9, 10))
    kw = dict(tf=_ramp_tf(), offsets=offsets, step=0.4, return_depth=True)
    ref, ref_d = render(vol, cam, skip_empty=False, engine="torch", **kw)
    for extra in ({"skip_empty": True}, {"chunk_rays": 7, "chunk_points": 50}, {"engine": "auto"}):
        img, dep = render_endoscope(vol, cam, **{**kw, **extra})
        assert (img - ref).abs().max() < 1e-12, extra
        assert torch.equal(torch.isinf(dep), torch.isinf(ref_d))
        fin = torch.isfinite(dep)
        assert (dep[fin] - ref_d[fin]).abs().max() < 1e-9
    assert float(ref[0, 3].max()) > 0.5


def test_depth_of_a_constant_medium_is_ln2_over_sigma():
    vol = torch.full((12, 12, 12), 3.0, dtype=F64)
    sigma = 0.2
    cam = EndoscopeCamera(position=(5.5, 5.5, 5.5), direction=(1, 0.3, -0.2), fov=90.0, size=(5, 5), near=0.5)
    _, depth = render(vol, cam, tf=flat_tf(sigma), light=None, step=0.3, return_depth=True)
    _, _, valid = cam.rays(vol.shape)
    assert torch.allclose(depth[0][valid], torch.tensor(0.5 + math.log(2) / sigma, dtype=F64), atol=1e-9)
    assert bool(torch.isinf(depth[0][~valid]).all())


def test_batched_volume_and_float32():
    vol = torch.stack([_blob(dtype=torch.float32), 0.5 * _blob(dtype=torch.float32)])[:, None]
    cam = EndoscopeCamera(position=(12.0, 12.0, 2.0), direction=(0, 0, 1), size=(6, 6))
    img = render(vol, cam, tf=_ramp_tf(torch.float32))
    assert img.shape == (2, 4, 6, 6) and img.dtype == torch.float32
    one = render(vol[1, 0], cam, tf=_ramp_tf(torch.float32))
    assert torch.allclose(img[1:], one, atol=1e-6)


def test_skipping_starts_rays_late_where_the_volume_is_empty(monkeypatch):
    import torchdeform.volume.interior as interior

    starts = []
    first = interior._first_segments

    def spy(*args):
        k = first(*args)
        starts.append(k)
        return k

    monkeypatch.setattr(interior, "_first_segments", spy)
    vol = _blob((24, 24, 40), centre=(12.0, 12.0, 30.0))
    cam = EndoscopeCamera(position=(12.0, 12.0, 1.0), direction=(0, 0, 1), fov=40.0, size=(6, 6))
    img = render(vol, cam, tf=_ramp_tf(), step=0.5)
    assert len(starts) == 1 and int(starts[0].min()) >= 2 * 7  # blocks of 8: at least 7 of the 21 empty voxels skipped
    ref = render(vol, cam, tf=_ramp_tf(), step=0.5, skip_empty=False)
    assert torch.equal(img, ref)


def test_auto_engine_in_float32_matches_the_torch_engine():
    """``engine="auto"`` goes to the native kernel when :mod:`.native_march` offers one (float32, no grad)."""
    vol = _blob((24, 24, 32), centre=(12.0, 11.0, 20.0), dtype=torch.float32)
    offsets = 0.7 * torch.randn(3, 3, 3, 3)
    cam = EndoscopeCamera(position=(11.5, 12.5, 1.0), direction=(0.02, -0.03, 1.0), fov=80.0, size=(9, 10))
    kw = dict(tf=_ramp_tf(torch.float32), offsets=offsets, step=0.4, return_depth=True)
    surfaces = [Sphere((11.0, 13.0, 9.0), 2.0, (1.0, 0.2, 0.2))]
    for extra in ({}, {"light": None}, {"surfaces": surfaces}):
        ref, ref_d = render_endoscope(vol, cam, engine="torch", **kw, **extra)
        img, dep = render_endoscope(vol, cam, engine="auto", **kw, **extra)
        assert (img - ref).abs().max() < 1e-4, extra
        assert torch.equal(torch.isinf(dep), torch.isinf(ref_d))
        fin = torch.isfinite(dep)
        assert (dep[fin] - ref_d[fin]).abs().max() < 1e-3
