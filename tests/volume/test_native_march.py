"""The native ray marcher (:mod:`torchdeform.volume.native_march`) against an independent float64 oracle.

Oracle: a brute-force march written here in numpy float64, one sample per segment for every ray
at once, with ``scipy.ndimage.map_coordinates(order=1, mode="nearest")`` for the trilinear
volume and node-offset lookups (clamp to the edge), ``numpy.interp`` for the transfer-function
table, central differences of those samples for the headlight, and per-ray early termination.
Then: empty-space leaping and thread counts change nothing; ``clip_rays`` against the box by
hand; and, once :func:`~torchdeform.volume.render_endoscope` exists, its torch engine.
"""

import math

import numpy as np
import pytest
import torch

from torchdeform.volume import TransferFunction, native_march

pytestmark = pytest.mark.skipif(native_march.unavailable() is not None, reason="no C compiler for the native kernel")

SHAPE = (12, 14, 16)
IMG = (20, 24)


def _smooth_volume(shape, seed=0):
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    v = gaussian_filter(rng.standard_normal(shape), 2.0, mode="nearest")
    v = (v - v.min()) / (v.max() - v.min()) * 100.0
    D = shape[0]
    v = v * np.linspace(0.3, 1.1, D)[:, None, None]  # low D mostly transparent: empty blocks to leap
    return torch.tensor(v, dtype=torch.float32)


def _tf():
    # transparent below 40, a faint then an opaque range, colours varying
    return TransferFunction(
        [0.0, 40.0, 50.0, 70.0, 100.0],
        [[0, 0, 0], [0.9, 0.2, 0.1], [0.3, 0.8, 0.2], [0.2, 0.4, 1.0], [1, 1, 1]],
        [0.0, 0.0, 0.15, 1.5, 4.0],
        resolution=256,
    )


def _rays(eye, forward, shape_img, fov_deg, *, mask=True):
    """A private pinhole ray generator: unit directions (3, h, w) and a round mask (the test's own)."""
    f = np.asarray(forward, dtype=np.float64)
    f = f / np.linalg.norm(f)
    up0 = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    right = np.cross(f, up0)
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    h, w = shape_img
    m = min(h, w) / 2
    ys = (h / 2 - (np.arange(h) + 0.5)) / m
    xs = ((np.arange(w) + 0.5) - w / 2) / m
    Y, X = np.meshgrid(ys, xs, indexing="ij")
    tan = math.tan(math.radians(fov_deg) / 2)
    d = f[:, None, None] + tan * (X[None] * right[:, None, None] + Y[None] * up[:, None, None])
    d /= np.linalg.norm(d, axis=0, keepdims=True)
    valid = (X**2 + Y**2 <= 1.0) if mask else np.ones_like(X, dtype=bool)
    return torch.tensor(eye, dtype=torch.float32), torch.tensor(d, dtype=torch.float32), torch.tensor(valid)


def _oracle(
    vol, tf, eye, dirs, valid, t0, t1, *, step, stop, offsets=None, light=True, ambient=0.2, diffuse=0.8, origins=None
):
    """Brute-force float64 march: image (4, h, w) and depth (h, w); rays from ``eye`` or their ``origins``."""
    from scipy.ndimage import map_coordinates

    V = vol.double().numpy()
    shape = V.shape
    lo, hi = tf.range()
    table = tf.table(dtype=torch.float64).numpy()
    R = table.shape[0]
    h, w = valid.shape
    e = eye.double().numpy()[:, None] if origins is None else origins.double().numpy().reshape(3, -1)
    d = dirs.double().numpy().reshape(3, -1)
    a = t0.double().numpy().reshape(-1)
    b = t1.double().numpy().reshape(-1)
    ok = valid.numpy().reshape(-1) & (b > a)
    length = np.where(ok, b - a, 0.0)
    K = math.ceil(length.max() / step) if length.max() > 0 else 0
    P = d.shape[1]
    C = np.zeros((3, P))
    T = np.ones(P)
    depth = np.full(P, np.inf)
    active = ok.copy()
    U = None if offsets is None else offsets.double().numpy()

    def vsample(X):
        return map_coordinates(V, X, order=1, mode="nearest")

    for k in range(K):
        s0 = k * step
        sl = np.clip(length - s0, 0.0, step)
        t = a + s0 + sl / 2
        p = e + d * t[None]
        X = p
        if U is not None:
            q = np.stack([p[c] * (U.shape[1 + c] - 1) / max(shape[c] - 1, 1) for c in range(3)])
            u = np.stack([map_coordinates(U[c], q, order=1, mode="nearest") for c in range(3)])
            X = p - u
        v = vsample(X)
        x = (v - lo) * (R - 1) / (hi - lo)
        ent = np.stack([np.interp(x, np.arange(R), table[:, c]) for c in range(4)])
        sigma = ent[3]
        shade = np.ones(P)
        if light:
            g = np.stack(
                [
                    (vsample(X + 1.0 * (np.arange(3) == c)[:, None]) - vsample(X - 1.0 * (np.arange(3) == c)[:, None]))
                    / 2
                    for c in range(3)
                ]
            )
            gn = np.linalg.norm(g, axis=0)
            cosang = np.abs((g * d).sum(0)) / np.maximum(gn, 1e-300)
            shade = np.where(gn < 1e-6 * (hi - lo), ambient + diffuse, ambient + diffuse * cosang)
        alpha = 1 - np.exp(-sigma * sl)
        alpha = np.where(active & (sl > 0), alpha, 0.0)
        C += T * alpha * ent[:3] * shade
        Tb, T = T, T * (1 - alpha)
        with np.errstate(divide="ignore", invalid="ignore"):
            cross = a + s0 + np.log(2 * Tb) / sigma  # exact inside the segment (constant extinction)
        depth = np.where(np.isinf(depth) & (Tb >= 0.5) & (T < 0.5), cross, depth)
        if stop > 0:
            active &= ~np.less(T, stop)
    img = np.concatenate([C, (1 - T)[None]], 0)
    img[:, ~valid.numpy().reshape(-1)] = 0.0
    return img.reshape(4, h, w), depth.reshape(h, w)


def _native(vol, tf, eye, dirs, valid, t0, t1, **kw):
    lo, hi = tf.range()
    img, depth = native_march.render(vol, tf.table(), lo, hi, eye, dirs, t0=t0, t1=t1, valid=valid, **kw)
    return img[0].double().numpy(), depth[0].double().numpy()


def _compare(got, want, *, tol=1e-4):
    img, depth = got
    rimg, rdepth = want
    assert np.abs(img - rimg).max() < tol
    assert np.array_equal(np.isinf(depth), np.isinf(rdepth))
    fin = np.isfinite(depth)
    assert np.abs(depth[fin] - rdepth[fin]).max(initial=0.0) < tol


VIEWS = {
    # inside the volume looking along +W (an endoscope), outside looking in (an overview)
    "inside": ((6.0, 7.0, 2.0), (0.15, -0.1, 1.0), 100.0),
    "outside": ((-9.0, -6.0, 7.5), (1.0, 0.8, 0.05), 50.0),
}


@pytest.mark.parametrize("view", sorted(VIEWS))
@pytest.mark.parametrize("light", [True, False])
@pytest.mark.parametrize("with_offsets", [False, True])
def test_native_march_matches_float64_oracle(view, light, with_offsets):
    vol, tf = _smooth_volume(SHAPE), _tf()
    pos, fwd, fov = VIEWS[view]
    eye, dirs, valid = _rays(pos, fwd, IMG, fov, mask=view == "inside")
    t0, t1 = native_march.clip_rays(eye, dirs, SHAPE, far=30.0)
    offsets = None
    if with_offsets:
        g = torch.Generator().manual_seed(1)
        offsets = (torch.rand(3, 4, 5, 5, generator=g) * 2 - 1) * 1.5
    kw = dict(step=0.5, stop=1e-3, offsets=offsets, light="headlight" if light else None)
    want = _oracle(vol, tf, eye, dirs, valid, t0, t1, step=0.5, stop=1e-3, offsets=offsets, light=light)
    got = _native(vol, tf, eye, dirs, valid, t0, t1, **kw)
    assert want[0][3].max() > 0.9 and (want[0][3][valid.numpy()] < 0.1).any()  # opaque and clear pixels both
    assert np.isfinite(want[1]).any() and np.isinf(want[1][valid.numpy()]).any()
    _compare(got, want)
    # leaping off (small and default blocks): the same image
    for block, skip in ((8, False), (4, True), (2, True)):
        other = _native(vol, tf, eye, dirs, valid, t0, t1, skip_empty=skip, block=block, **kw)
        assert np.abs(other[0] - got[0]).max() < 1e-5
        assert np.array_equal(other[1], got[1])


def test_native_march_without_early_termination_and_uneven_step():
    vol, tf = _smooth_volume(SHAPE, seed=3), _tf()
    eye, dirs, valid = _rays(*VIEWS["inside"][:2], IMG, 100.0)
    t0, t1 = native_march.clip_rays(eye, dirs, SHAPE)
    for stop in (0.0, 0.05):
        want = _oracle(vol, tf, eye, dirs, valid, t0, t1, step=0.37, stop=stop, light=True)
        got = _native(vol, tf, eye, dirs, valid, t0, t1, step=0.37, stop=stop)
        _compare(got, want)
    # early termination at 1e-3 changes the image by at most the remaining transmittance
    full = _native(vol, tf, eye, dirs, valid, t0, t1, step=0.37, stop=0.0)[0]
    early = _native(vol, tf, eye, dirs, valid, t0, t1, step=0.37, stop=1e-3)[0]
    assert np.abs(full - early).max() <= 1e-3


def test_native_march_leaping_on_a_sparse_volume_and_threads():
    """Blobs in a larger empty volume: many leaps; the image is the same with and without them, on 1 and 2 threads."""
    shape = (40, 36, 44)
    z, y, x = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    v = np.zeros(shape)
    for c, r in (((10, 12, 30), 5.0), ((28, 20, 10), 7.0), ((20, 30, 25), 3.0)):
        v += 100 * np.exp(-(((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2) / (2 * r * r)))
    vol, tf = torch.tensor(v, dtype=torch.float32), _tf()
    eye, dirs, valid = _rays((-20.0, 45.0, -15.0), (1.0, -0.6, 1.0), (32, 36), 60.0, mask=False)
    t0, t1 = native_march.clip_rays(eye, dirs, shape)
    g = torch.Generator().manual_seed(2)
    offsets = (torch.rand(3, 5, 5, 5, generator=g) * 2 - 1) * 4.0
    for u in (None, offsets):
        base = _native(vol, tf, eye, dirs, valid, t0, t1, skip_empty=False, offsets=u, threads=1)
        assert base[0][3].max() > 0.5
        for block, threads in ((8, 2), (4, 1), (16, 2)):
            got = _native(vol, tf, eye, dirs, valid, t0, t1, block=block, offsets=u, threads=threads)
            assert np.abs(got[0] - base[0]).max() < 1e-5
            assert np.array_equal(got[1], base[1])
    want = _oracle(vol, tf, eye, dirs, valid, t0, t1, step=0.5, stop=1e-3, offsets=offsets)
    _compare(_native(vol, tf, eye, dirs, valid, t0, t1, offsets=offsets), want)


def test_native_march_clips_rays_itself():
    """``t0 = t1 = None``: the kernel's own clipping (box, near, far) gives the image of :func:`clip_rays`."""
    vol, tf = _smooth_volume(SHAPE), _tf()
    for view, near, far in (("inside", 0.0, math.inf), ("inside", 1.5, 9.0), ("outside", 0.0, 20.0)):
        eye, dirs, valid = _rays(*VIEWS[view][:2], IMG, VIEWS[view][2], mask=view == "inside")
        t0, t1 = native_march.clip_rays(eye, dirs, SHAPE, near=near, far=far)
        a = _native(vol, tf, eye, dirs, valid, t0, t1)
        b = _native(vol, tf, eye, dirs, valid, None, None, near=near, far=far)
        assert np.abs(a[0] - b[0]).max() < 1e-6 and np.allclose(a[1], b[1], atol=1e-5, equal_nan=False)


def test_native_march_cache_follows_in_place_changes():
    vol, tf = _smooth_volume(SHAPE), _tf()
    eye, dirs, valid = _rays(*VIEWS["outside"][:2], IMG, 50.0, mask=False)
    t0, t1 = native_march.clip_rays(eye, dirs, SHAPE)
    first = _native(vol, tf, eye, dirs, valid, t0, t1)[0]
    vol.mul_(0.0)  # all transparent now: the cached copy must not be used
    assert np.abs(_native(vol, tf, eye, dirs, valid, t0, t1)[0]).max() == 0.0
    assert first[3].max() > 0.5


def test_clip_rays_against_the_box():
    eye = torch.tensor([-3.0, 2.0, 2.0])
    dirs = torch.tensor([[1.0, 0.0], [0.0, 0.6], [0.0, 0.8]]).reshape(3, 1, 2)
    t0, t1 = native_march.clip_rays(eye, dirs, (4, 5, 6))
    assert t0[0, 0].item() == pytest.approx(2.5) and t1[0, 0].item() == pytest.approx(6.5)
    assert t1[0, 1].item() <= t0[0, 1].item()  # along (0, .6, .8) from D = -3: misses the box
    t0, t1 = native_march.clip_rays(torch.tensor([1.0, 2.0, 2.0]), dirs[:, :, :1], (4, 5, 6), near=0.5, far=2.0)
    assert (t0.item(), t1.item()) == (pytest.approx(0.5), pytest.approx(2.0))


def test_native_march_refuses_bad_arguments():
    vol, tf = _smooth_volume(SHAPE), _tf()
    eye, dirs, _ = _rays(*VIEWS["outside"][:2], IMG, 50.0)
    t0, t1 = native_march.clip_rays(eye, dirs, SHAPE)
    with pytest.raises(ValueError, match="table"):
        native_march.render(vol, torch.zeros(5, 3), 0.0, 1.0, eye, dirs, t0=t0, t1=t1)
    with pytest.raises(ValueError, match="directions"):
        native_march.render(vol, tf.table(), 0.0, 100.0, eye, dirs[:, :5], t0=t0, t1=t1)
    with pytest.raises(ValueError, match="light"):
        native_march.render(vol, tf.table(), 0.0, 100.0, eye, dirs, t0=t0, t1=t1, light="spot")


def _interior():
    try:
        from torchdeform.volume.endoscope import EndoscopeCamera
        from torchdeform.volume.interior import Sphere, render_endoscope
    except ImportError:
        return None
    if not callable(render_endoscope) or not isinstance(EndoscopeCamera, type):
        return None
    return render_endoscope, EndoscopeCamera, Sphere


@pytest.mark.skipif(_interior() is None, reason="torchdeform.volume.interior (render_endoscope) not there yet")
@pytest.mark.parametrize("with_offsets", [False, True])
@pytest.mark.parametrize("light", ["headlight", None])
def test_native_march_matches_render_endoscope_torch(with_offsets, light, monkeypatch):
    """``render_endoscope(engine="auto")`` runs the kernel (its hook) and agrees with ``engine="torch"``."""
    render_endoscope, EndoscopeCamera, Sphere = _interior()
    calls = []
    hook = native_march.render_endoscope_native
    monkeypatch.setattr(native_march, "render_endoscope_native", lambda plan: calls.append(1) or hook(plan))
    vol, tf = _smooth_volume(SHAPE), _tf()
    offsets = None
    if with_offsets:
        g = torch.Generator().manual_seed(1)
        offsets = (torch.rand(3, 4, 5, 5, generator=g) * 2 - 1) * 1.5
    for stop in (0.0, 1e-3):
        for surfaces in (None, [Sphere((6.0, 5.0, 9.0), 1.5, (0.2, 0.9, 0.3))]):
            cam = EndoscopeCamera(position=(6.0, 7.0, 2.0), direction=(0.15, -0.1, 1.0), fov=100.0, size=IMG)
            kw = dict(tf=tf, offsets=offsets, light=light, step=0.5, stop=stop, surfaces=surfaces, return_depth=True)
            ref, rdepth = render_endoscope(vol, cam, engine="torch", **kw)
            got, depth = render_endoscope(vol, cam, engine="auto", **kw)
            assert calls and tuple(got.shape) == tuple(ref.shape) == (1, 4, *IMG)
            calls.clear()
            assert float(ref[:, 3].max()) > 0.5
            # torch stops a whole chunk once every ray is below stop, the kernel each ray
            assert float((got - ref).abs().max()) < (1e-4 if stop == 0 else 1.5e-3)
            known = ~torch.isnan(rdepth)  # (the torch engine's depth had NaNs where 0 * inf met, 2026-11-28)
            assert torch.equal(torch.isinf(depth[known]), torch.isinf(rdepth[known]))
            fin = torch.isfinite(depth) & known
            assert not bool(fin.any()) or float((depth[fin] - rdepth[fin]).abs().max()) < 1e-3


# ------------------------------------------------------------------ axis views of render(engine="native")
def _axis_rays(view, shape, size):
    """The test's own parallel rays of an axis view: origins on the entry face, directions, step."""
    axis = "dhw".index(view[-1])
    others = [a for a in range(3) if a != axis]
    h, w = size or tuple(shape[a] for a in others)
    pix = [(np.arange(m) + 0.5) * shape[a] / m - 0.5 for m, a in zip((h, w), others)]
    A, B = np.meshgrid(*pix, indexing="ij")
    o = np.zeros((3, h, w))
    o[others[0]], o[others[1]] = A, B
    o[axis] = shape[axis] - 0.5 if view.startswith("-") else -0.5
    d = np.zeros((3, h, w))
    d[axis] = -1.0 if view.startswith("-") else 1.0
    n = shape[axis]  # step 1: one slab per voxel layer
    return torch.tensor(o), torch.tensor(d), torch.zeros(h, w), torch.full((h, w), float(n))


@pytest.mark.parametrize("view", ["d", "-d", "h", "-h", "w", "-w"])
@pytest.mark.parametrize("with_offsets", [False, True])
def test_axis_views_match_the_float64_oracle_and_grid_sample(view, with_offsets):
    """``render(engine="native")``: parallel rays from the entry face, one sample per slab; the float64
    oracle marching the same rays, and the ``grid_sample`` engine, agree to 1e-4 (no early stop)."""
    from torchdeform.volume import render

    vol, tf = _smooth_volume(SHAPE), _tf()
    offsets = None
    if with_offsets:
        g = torch.Generator().manual_seed(2)
        offsets = (torch.rand(3, 4, 5, 5, generator=g) * 2 - 1) * 1.5
    for size in (None, (9, 13)):
        got = render(vol, tf=tf, view=view, offsets=offsets, size=size, stop=0, engine="native")
        ref = render(vol, tf=tf, view=view, offsets=offsets, size=size, stop=0, engine="grid_sample")
        o, d, t0, t1 = _axis_rays(view, SHAPE, size)
        want, _ = _oracle(
            vol, tf, torch.zeros(3), d, torch.ones(t0.shape, dtype=torch.bool), t0, t1, step=1.0, stop=0.0,
            offsets=offsets, light=False, origins=o,
        )  # fmt: skip
        assert got.dtype == torch.float32 and tuple(got.shape) == (1, 4, *t0.shape)
        assert want[3].max() > 0.9 and want[3].min() < 0.5  # opaque and see-through pixels
        assert np.abs(got[0].double().numpy() - want).max() < 1e-4
        assert float((got - ref).abs().max()) < 1e-4


def test_axis_views_stop_each_ray_and_batch_offsets():
    """With early termination each ray stops at ``stop`` (alpha within ``stop`` of the torch engine's);
    a batch of offsets gives the batch of single renders."""
    from torchdeform.volume import render

    vol, tf = _smooth_volume(SHAPE), _tf()
    g = torch.Generator().manual_seed(3)
    offsets = (torch.rand(2, 3, 4, 5, 5, generator=g) * 2 - 1) * 1.5
    got = render(vol, tf=tf, view="-h", offsets=offsets, stop=0.05, engine="native")
    ref = render(vol, tf=tf, view="-h", offsets=offsets, stop=0.05, engine="grid_sample")
    assert tuple(got.shape) == (2, 4, 12, 16) and float((got - ref).abs().max()) <= 0.05 + 1e-5
    for b in range(2):
        one = render(vol, tf=tf, view="-h", offsets=offsets[b], stop=0.05, engine="native")
        assert torch.equal(one[0], got[b])


def test_axis_engine_auto_falls_back_and_native_says_why():
    """``auto`` takes grid_sample (the same tensor) where the kernel does not apply; ``native`` there
    is one ConfigError naming the reason."""
    from torchdeform.errors import ConfigError
    from torchdeform.volume import render

    vol, tf = _smooth_volume(SHAPE), _tf()
    u = torch.zeros(3, 4, 5, 5)
    cases = [
        (dict(mode="mip"), "mode 'mip'"),
        (dict(volume=vol.double()), "float32"),
        (dict(offsets=u, warp_mode="knoche"), "warp_mode"),
        (dict(offsets=u, inverse_iters=2), "inverse_iters"),
        (dict(padding="zeros"), "padding"),
        (dict(offsets=u.clone().requires_grad_()), "gradient"),
    ]
    for kw, why in cases:
        kw = dict(kw)
        v = kw.pop("volume", vol)
        base = dict(tf=tf if kw.get("mode", "dvr") == "dvr" else None, view="d")
        auto = render(v, engine="auto", **base, **kw)
        assert torch.equal(auto, render(v, engine="grid_sample", **base, **kw)), why
        with pytest.raises(ConfigError, match=why):
            render(v, engine="native", **base, **kw)
    grad = u.clone().requires_grad_()
    render(vol, tf=tf, view="d", offsets=grad, engine="auto")[:, 3].sum().backward()
    assert grad.grad is not None and float(grad.grad.abs().sum()) > 0  # auto kept the gradient
