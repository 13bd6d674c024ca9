"""The z-buffer rasteriser against independent oracles.

* coverage: barycentric coordinates of every pixel centre from a 3x3 linear solve (numpy);
* visibility: the known nearer of two parallel triangles, in either face order, both cameras;
* shading: ``ambient + (1 - ambient) cos(angle)`` on a flat square;
* projection: the OpenGL look-at and perspective matrices (homogeneous coordinates, NDC);
* interpolation: the analytic barycentric combination, perspective-correct from a ray-plane
  intersection computed here;
* a sphere's silhouette: a disc of area ``pi r^2``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from torchdeform.errors import ConfigError
from torchdeform.mesh import Camera, rasterize, save_png


def front_camera(H=40, W=50, **kw):
    """Orthographic, looking down -z from z = 10, one world unit per pixel: x = W/2 + X, y = H/2 - Y."""
    return Camera((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=float(H), size=(H, W), **kw)


def bary_oracle(tri_xy: np.ndarray, H: int, W: int) -> np.ndarray:
    """Barycentric coordinates ``(H, W, 3)`` of every pixel centre, by a 3x3 linear solve."""
    A = np.vstack([tri_xy.T, np.ones(3)])  # rows x, y, 1
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rhs = np.stack([jj, ii, np.ones_like(jj)], -1).reshape(-1, 3).T
    return np.linalg.solve(A, rhs).T.reshape(H, W, 3)


# ------------------------------------------------------------------ (a) coverage
@pytest.mark.parametrize("order", [[0, 1, 2], [0, 2, 1]])  # both windings
def test_coverage_of_one_triangle_equals_point_in_triangle(dtype, order):
    H, W = 40, 50
    world = np.array([[-17.3, -11.1, 0.0], [19.7, -3.3, 0.0], [-2.9, 16.45, 0.0]])
    out = rasterize(torch.tensor(world, dtype=dtype), torch.tensor([order]), front_camera(H, W))
    tri_xy = np.stack([W / 2 + world[:, 0], H / 2 - world[:, 1]], 1)[order]  # the camera, by hand
    expected = (bary_oracle(tri_xy, H, W) >= 0).all(-1)
    assert 200 < expected.sum() < H * W - 200
    np.testing.assert_array_equal((out["face"] == 0).numpy(), expected)
    np.testing.assert_array_equal((out["face"] == -1).numpy(), ~expected)
    assert out["image"].dtype == dtype and out["depth"].dtype == dtype and out["face"].dtype == torch.int64
    assert torch.isinf(out["depth"][~torch.from_numpy(expected)]).all()
    assert (out["image"][~torch.from_numpy(expected)] == 1).all()  # white background


# ------------------------------------------------------------------ (b) visibility
def _two_triangles(z_near, z_far):
    near = [[-8.2, -6.1, z_near], [9.3, -5.7, z_near + 0.3], [0.4, 8.9, z_near - 0.2]]
    far = [[-3.1, -9.4, z_far], [12.2, 1.3, z_far + 0.5], [-6.6, 7.7, z_far - 0.4]]
    return torch.tensor(near + far, dtype=torch.float64)


@pytest.mark.parametrize(
    "camera",
    [front_camera(32, 32), Camera((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=90.0, size=(32, 32))],
)
def test_nearer_triangle_wins_in_either_order(camera):
    v = _two_triangles(1.0, -1.0)
    a = rasterize(v, torch.tensor([[0, 1, 2], [3, 4, 5]]), camera)
    b = rasterize(v, torch.tensor([[3, 4, 5], [0, 1, 2]]), camera)
    near_a, far_a = a["face"] == 0, a["face"] == 1
    near_b = b["face"] == 1
    # coverage of each triangle alone
    only_near = rasterize(v, torch.tensor([[0, 1, 2]]), camera)["face"] == 0
    only_far = rasterize(v, torch.tensor([[3, 4, 5]]), camera)["face"] == 0
    overlap = only_near & only_far
    assert overlap.sum() > 30 and (only_far & ~only_near).sum() > 5
    assert torch.equal(near_a, only_near) and torch.equal(near_b, only_near)  # nearer wins everywhere
    assert torch.equal(far_a, only_far & ~only_near)
    assert torch.equal(a["depth"], b["depth"]) and torch.equal(a["image"], b["image"])
    assert (a["depth"][overlap] < 9.5).all()  # eye at z = 10, near plane z ~ 1


def test_exact_depth_tie_goes_to_lower_face_index():
    v = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0]], dtype=torch.float64)
    out = rasterize(v, torch.tensor([[0, 1, 2], [0, 1, 2]]), front_camera(16, 16), chunk_pairs=1)
    assert set(out["face"].unique().tolist()) == {-1, 0}


# ------------------------------------------------------------------ (c) Lambert
@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 60.0, 89.0, 120.0])
def test_lambert_on_a_flat_square(dtype, angle_deg):
    v = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]], dtype=dtype)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])  # counter-clockwise seen from +z
    t = math.radians(angle_deg)
    light = (math.sin(t) * math.cos(0.7), math.sin(t) * math.sin(0.7), math.cos(t))
    colour = torch.tensor([0.9, 0.5, 0.25], dtype=dtype).expand(4, 3)
    ambient = 0.15
    out = rasterize(v, f, front_camera(16, 16), colors=colour, light=light, ambient=ambient)
    hit = out["face"] >= 0
    assert hit.sum() == 100
    shade = ambient + (1 - ambient) * max(0.0, math.cos(t))
    expected = torch.tensor([0.9, 0.5, 0.25], dtype=torch.float64) * shade
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(out["image"][hit].double(), expected.expand(100, 3), atol=tol, rtol=0)
    # two-sided: the back of the square under the same light gives |cos|
    back = rasterize(v, f.flip(1), front_camera(16, 16), colors=colour, light=light, ambient=ambient, two_sided=True)
    expected2 = torch.tensor([0.9, 0.5, 0.25], dtype=torch.float64) * (ambient + (1 - ambient) * abs(math.cos(t)))
    torch.testing.assert_close(back["image"][hit].double(), expected2.expand(100, 3), atol=tol, rtol=0)


def test_headlight_lights_faces_towards_the_camera_and_not_back_faces():
    v = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0]], dtype=torch.float64)
    front = rasterize(v, torch.tensor([[0, 1, 2]]), front_camera(16, 16), ambient=0.3)
    back = rasterize(v, torch.tensor([[0, 2, 1]]), front_camera(16, 16), ambient=0.3)
    hit = front["face"] >= 0
    assert torch.allclose(front["image"][hit], torch.ones(1, dtype=torch.float64))
    assert torch.allclose(back["image"][hit], torch.full((1,), 0.3, dtype=torch.float64))


# ------------------------------------------------------------------ (d) projection
def _look_at(eye, target, up):
    """gluLookAt as a 4x4 matrix (OpenGL: the camera looks along -z of its own frame)."""
    f = np.subtract(target, eye)
    f = f / np.linalg.norm(f)
    s = np.cross(f, up)
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    M = np.eye(4)
    M[0, :3], M[1, :3], M[2, :3] = s, u, -f
    return M @ np.array([[1, 0, 0, -eye[0]], [0, 1, 0, -eye[1]], [0, 0, 1, -eye[2]], [0, 0, 0, 1.0]])


def _perspective(fovy_deg, aspect, near, far):
    """gluPerspective as a 4x4 matrix."""
    g = 1 / math.tan(math.radians(fovy_deg) / 2)
    return np.array(
        [
            [g / aspect, 0, 0, 0],
            [0, g, 0, 0],
            [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
            [0, 0, -1, 0],
        ]
    )


def test_perspective_projection_equals_the_opengl_pinhole(dtype):
    eye, target, up = (1.0, 2.0, 3.0), (0.2, -0.1, 0.3), (0.0, 0.3, 1.0)
    H, W, fov = 48, 64, 50.0
    cam = Camera(eye, target, up=up, fov_deg=fov, size=(H, W))
    pts = np.random.default_rng(1).uniform(-1, 1, (20, 3))
    pix, depth = cam.project(torch.tensor(pts, dtype=dtype))
    clip = (_perspective(fov, W / H, 0.1, 100.0) @ _look_at(eye, target, up) @ np.c_[pts, np.ones(20)].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    expected = np.stack([(ndc[:, 0] + 1) * W / 2, (1 - ndc[:, 1]) * H / 2], 1)  # NDC y up, rows down
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    np.testing.assert_allclose(pix.numpy(), expected, atol=tol * W, rtol=0)
    np.testing.assert_allclose(depth.numpy(), clip[:, 3], atol=tol, rtol=0)  # w_clip = distance along view
    assert pix.dtype == dtype and depth.dtype == dtype
    # the target projects to the image centre
    c, _ = cam.project(torch.tensor([target], dtype=torch.float64))
    np.testing.assert_allclose(c.numpy(), [[W / 2, H / 2]], atol=1e-9)


def test_orthographic_projection_by_hand():
    cam = front_camera(40, 50)
    p = torch.tensor([[3.0, 4.0, -2.0], [-1.5, 0.25, 7.0]], dtype=torch.float64)
    pix, depth = cam.project(p)
    assert pix.tolist() == [[28.0, 16.0], [23.5, 19.75]] and depth.tolist() == [12.0, 3.0]


# ------------------------------------------------------------------ (e) interpolation
def test_vertex_colours_interpolate_barycentrically_orthographic():
    H, W = 40, 50
    world = np.array([[-17.3, -11.1, 0.0], [19.7, -3.3, 2.0], [-2.9, 16.45, -1.0]])
    rgb = np.eye(3) * 0.8 + 0.1
    out = rasterize(
        torch.tensor(world),
        torch.tensor([[0, 1, 2]]),
        front_camera(H, W),
        colors=torch.tensor(rgb),
        ambient=0.0,
        light=np.cross(world[1] - world[0], world[2] - world[0]),
    )  # shade 1
    b = bary_oracle(np.stack([W / 2 + world[:, 0], H / 2 - world[:, 1]], 1), H, W)
    inside = (b > 0).all(-1)
    assert inside.sum() > 300
    np.testing.assert_allclose(out["bary"].numpy()[inside], b[inside], atol=1e-12)
    np.testing.assert_allclose(out["image"].numpy()[inside], b[inside] @ rgb, atol=1e-12)
    np.testing.assert_allclose(out["depth"].numpy()[inside], 10.0 - b[inside] @ world[:, 2], atol=1e-12)


def test_perspective_correct_interpolation_from_the_ray(dtype):
    H, W, fov = 40, 40, 60.0
    eye = np.array([0.0, 0.0, 10.0])
    cam = Camera(tuple(eye), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=fov, size=(H, W))
    world = np.array([[-6.0, -5.0, -6.0], [6.0, -4.0, 5.0], [0.5, 6.0, -1.0]])  # strongly tilted in depth
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    n = np.cross(world[1] - world[0], world[2] - world[0])
    out = rasterize(
        torch.tensor(world, dtype=dtype), torch.tensor([[0, 1, 2]]), cam, colors=torch.tensor(rgb), ambient=0.0, light=n
    )
    focal = (H / 2) / math.tan(math.radians(fov) / 2)
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    checked = 0
    for i, j in [(i, j) for i in range(1, H, 3) for j in range(1, W, 3)]:
        # the ray through the pixel centre (camera right = +x, up = +y, forward = -z)
        d = np.array([(j + 0.5 - W / 2) / focal, -(i + 0.5 - H / 2) / focal, -1.0])
        t = n @ (world[0] - eye) / (n @ d)
        p = eye + t * d
        lam = np.linalg.lstsq(np.vstack([world.T, np.ones(3)]), np.r_[p, 1.0], rcond=None)[0]
        if not (lam > 1e-6).all():
            continue
        checked += 1
        np.testing.assert_allclose(out["bary"][i, j].double().numpy(), lam, atol=tol)
        np.testing.assert_allclose(out["image"][i, j].double().numpy(), lam @ rgb, atol=tol)
        np.testing.assert_allclose(out["depth"][i, j].item(), t, rtol=tol)  # forward component of t d is t
    assert checked >= 40


def test_colour_callable_is_a_solid_texture_at_texcoords():
    v = torch.tensor([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    rest = v * 0.1 + 0.5  # in [0, 1]^3

    def texture(p):
        return torch.stack([p[:, 0], p[:, 1], torch.zeros_like(p[:, 0])], 1)

    out = rasterize(v, f, front_camera(16, 16), colors=texture, texcoords=rest, ambient=0.0)
    # pixel [i, j] has centre X = j + 0.5 - 8, Y = 8 - (i + 0.5)
    for i, j in [(4, 4), (7, 10), (11, 5)]:
        X, Y = j + 0.5 - 8, 8 - (i + 0.5)
        np.testing.assert_allclose(out["image"][i, j].numpy(), [X * 0.1 + 0.5, Y * 0.1 + 0.5, 0.0], atol=1e-12)


# ------------------------------------------------------------------ (f) sphere
@pytest.mark.parametrize("perspective", [False, True])
def test_sphere_silhouette_is_a_disc(perspective):
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)  # 5120 faces, closed
    H = W = 200
    if perspective:
        dist, fov = 6.0, 30.0
        cam = Camera((0.0, 0.0, dist), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=fov, size=(H, W))
        focal = (H / 2) / math.tan(math.radians(fov) / 2)
        r_px = focal * math.tan(math.asin(1.0 / dist))  # the cone tangent to the sphere
    else:
        cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=2.5, size=(H, W))
        r_px = H / 2.5
    out = rasterize(torch.tensor(s.vertices, dtype=torch.float32), torch.tensor(s.faces), cam, chunk_pairs=20000)
    hit = out["face"] >= 0
    assert abs(hit.sum().item() / (math.pi * r_px**2) - 1) < 0.02
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rr = np.hypot(jj - W / 2, ii - H / 2)
    assert hit.numpy()[rr < 0.97 * r_px].all() and not hit.numpy()[rr > r_px + 0.5].any()
    assert abs(out["depth"][H // 2, W // 2].item() - (4.0 if not perspective else dist - 1)) < 2e-3
    # the visible faces are the front half: outward normals point at the eye (headlight shade > ambient)
    assert (out["image"][hit] > 0.2).all()


# ------------------------------------------------------------------ files and errors
def test_save_png_round_trip(tmp_path):
    from PIL import Image

    s = trimesh.creation.icosphere(subdivisions=2)
    cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=3.0, size=(12, 20))
    out = rasterize(torch.tensor(s.vertices), torch.tensor(s.faces), cam, background=(0.0, 0.0, 1.0))
    save_png(tmp_path / "s.png", out["image"])
    back = np.asarray(Image.open(tmp_path / "s.png"))
    assert back.shape == (12, 20, 3) and back.dtype == np.uint8
    np.testing.assert_array_equal(back, np.round(out["image"].numpy() * 255).astype(np.uint8))
    assert tuple(back[0, 0]) == (0, 0, 255)


@pytest.mark.parametrize(
    "kwargs, key",
    [
        (dict(fov_deg=None), "camera"),
        (dict(fov_deg=40.0, ortho_height=2.0), "camera"),
        (dict(fov_deg=180.0), "fov_deg"),
        (dict(fov_deg=40.0, up=(0.0, 0.0, 2.0)), "up"),
        (dict(ortho_height=-1.0), "ortho_height"),
        (dict(fov_deg=40.0, size=(0, 4)), "size"),
    ],
)
def test_camera_errors(kwargs, key):
    with pytest.raises(ConfigError, match=key):
        Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), **kwargs)


def test_rasterize_errors():
    v, f, cam = torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), front_camera(4, 4)
    with pytest.raises(ConfigError, match="faces"):
        rasterize(v, torch.tensor([[0, 1, 3]]), cam)
    with pytest.raises(ConfigError, match="colors"):
        rasterize(v, f, cam, colors=torch.zeros(2, 3))
    with pytest.raises(ConfigError, match="ambient"):
        rasterize(v, f, cam, ambient=1.5)
    with pytest.raises(ConfigError, match="light"):
        rasterize(v, f, cam, light=(0.0, 0.0, 0.0))


def test_empty_and_behind_the_eye():
    cam = Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=60.0, size=(8, 8))
    behind = torch.tensor([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0]])
    out = rasterize(behind, torch.tensor([[0, 1, 2]]), cam)
    assert (out["face"] == -1).all() and (out["image"] == 1).all()
    out = rasterize(behind, torch.zeros(0, 3, dtype=torch.long), cam)
    assert (out["face"] == -1).all()


def test_gradients_with_respect_to_colours_and_vertices():
    world = torch.tensor([[-2.73, -2.11, 0.3], [2.97, -1.33, -0.2], [-0.29, 2.645, 0.1]], dtype=torch.float64)
    rgb = torch.tensor([[0.9, 0.1, 0.2], [0.1, 0.8, 0.3], [0.2, 0.3, 0.7]], dtype=torch.float64)
    cam = Camera((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_deg=40.0, size=(10, 10))
    hit = rasterize(world, torch.tensor([[0, 1, 2]]), cam)["face"] >= 0
    assert hit.sum() > 10

    def image(v, c):
        return rasterize(v, torch.tensor([[0, 1, 2]]), cam, colors=c, light=(0.3, 0.2, 1.0))["image"][hit]

    assert torch.autograd.gradcheck(image, (world.clone().requires_grad_(), rgb.clone().requires_grad_()))


def test_smooth_normals_shade_a_sphere_as_its_analytic_lambert_and_the_highlight_sits_at_the_half_vector():
    """Oracle: for a unit sphere under an orthographic camera and a headlight, the smooth-shaded value at
    a pixel is ambient + (1 - ambient) n.l with n the sphere's analytic normal there; the Blinn-Phong
    highlight peaks where n is the half vector (the sphere's front point for a headlight)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v, f = torch.as_tensor(s.vertices), torch.as_tensor(s.faces)
    cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), ortho_height=2.5, size=(65, 65))
    out = rasterize(v, f, cam, normals=v, ambient=0.2)
    flat = rasterize(v, f, cam, ambient=0.2)
    hit = out["face"] >= 0
    py, px = torch.nonzero(hit, as_tuple=True)
    x = (px.double() + 0.5 - 32.5) * 2.5 / 65
    y = -(py.double() + 0.5 - 32.5) * 2.5 / 65
    nz = (1 - x**2 - y**2).clamp_min(0).sqrt()
    expected = 0.2 + 0.8 * nz
    inner = nz > 0.3
    err_smooth = (out["image"][py, px, 0] - expected)[inner].abs().max()
    err_flat = (flat["image"][py, px, 0] - expected)[inner].abs().max()
    assert float(err_smooth) < 0.01 and float(err_smooth) < float(err_flat) / 2
    grey = torch.full_like(v, 0.4)  # dark enough that nothing clips at 1
    dry = rasterize(v, f, cam, colors=grey, normals=v, ambient=0.2)
    wet = rasterize(v, f, cam, colors=grey, normals=v, ambient=0.2, specular=0.5, shininess=40.0)
    diff = wet["image"][..., 0] - dry["image"][..., 0]
    assert float(diff[hit].min()) >= 0 and float(diff.max()) == pytest.approx(0.5, rel=0.02)
    peak = torch.nonzero(diff == diff.max())[0]
    assert abs(int(peak[0]) - 32) <= 1 and abs(int(peak[1]) - 32) <= 1  # the front point: h = l = view
