"""What the viewer shows of a scene: embedded surfaces, texture colours and the scene's tools.

Oracles:

* vertex positions: trilinear interpolation of the frame's node positions at each rest vertex of
  ``scene.embedded`` by ``scipy.interpolate.RegularGridInterpolator`` (linear, extrapolating one
  cell past the border), independent of the lattice cells and sparse weights of
  :class:`~torchdeform.mesh.embed.EmbeddedSurface`;
* colours: the solid texture looked up at the rest vertices of ``scene.embedded`` (a constant
  exemplar gives its own colour, whatever the position);
* tools: the sphere's radius, and the probe's path interpolated with ``numpy.interp`` at the frame's
  simulated time;
* the server: the bytes of its first mesh message and of its frames against the session's own.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

import torchdeform as td
from torchdeform.view.session import ViewerSession, frame_size

RADIUS = 0.003  # the probe's radius (m)
PATH = [[0.0, [0.021, 0.009, 0.008]], [0.004, [0.016, 0.009, 0.008]], [0.008, [0.017, 0.010, 0.009]]]

LABEL_SCENE = f"""
[grid]
labels = "labels.npy"
label_spacing = 0.001
spacing = 0.003

[[tissues]]
label = 1
tissue = "liver"

[[tissues]]
label = 2
fixed = true

[boundary]
gravity = [-9.81, 0.0, 0.0]

[[tools]]
name = "probe"
shape = "sphere"
radius = {RADIUS}
path = {json.dumps(PATH)}
start_inside = true           # it starts at the surface: the test is what is drawn, not the contact

[integrator]
name = "symplectic"
dt = "auto"
steps = 20

[output]
surfaces = "embedded"

[texture]
exemplar = "liver:16"
block = 8
seams = "none"
"""

CUBE_SCENE = f"""
[grid]
shape = [5, 5, 5]
spacing = 0.003

[material]
stiffness = 5.0
damping = 1e-4

[mass]
density = 1000.0

[boundary]
fixed = "bottom"

[[tools]]
name = "probe"
shape = "sphere"
radius = {RADIUS}
path = {json.dumps(PATH)}

[integrator]
name = "symplectic"
dt = "auto"
steps = 20
"""


def _labels() -> np.ndarray:
    """A 20 x 18 x 16 voxel label volume (1 mm): an ellipsoid (1) resting on a fixed slab (2)."""
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in (20, 18, 16)], indexing="ij")
    lab = np.zeros((20, 18, 16), np.uint8)
    lab[((i - 11) / 8) ** 2 + ((j - 9) / 7) ** 2 + ((k - 8) / 6) ** 2 < 1] = 1
    slab = lab[1:5, 2:16, 2:14]
    lab[1:5, 2:16, 2:14] = np.where(slab == 0, 2, slab)
    return lab


@pytest.fixture(scope="module")
def label_scene(tmp_path_factory):
    pytest.importorskip("fast_simplification", reason="label surfaces need the optional package (torchdeform[anatomy])")
    folder = tmp_path_factory.mktemp("label-scene")
    np.save(folder / "labels.npy", _labels())
    (folder / "scene.toml").write_text(LABEL_SCENE)
    return td.scene.load_scene(folder / "scene.toml")


@pytest.fixture(scope="module")
def cube_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("cube-scene") / "scene.toml"
    path.write_text(CUBE_SCENE)
    return td.scene.load_scene(path)


def _trilinear(grid, x: torch.Tensor, points: np.ndarray) -> np.ndarray:
    """Node positions ``x`` ``(3, D, H, W)`` interpolated (and extrapolated) at ``points`` ``(P, 3)`` (m)."""
    axes = [o + s * np.arange(n) for o, s, n in zip(grid.origin, grid.spacing, grid.shape)]
    xs = x.detach().double().cpu().numpy()
    return np.stack(
        [RegularGridInterpolator(axes, xs[c], bounds_error=False, fill_value=None)(points) for c in range(3)], 1
    )


def _rest(scene) -> tuple[np.ndarray, np.ndarray]:
    """The embedded surfaces' rest vertices and faces, concatenated in the scene's order."""
    verts, faces, base = [], [], 0
    for v, f in scene.embedded.values():
        verts.append(np.asarray(v, dtype=np.float64))
        faces.append(np.asarray(f, dtype=np.int64) + base)
        base += len(verts[-1])
    return np.concatenate(verts), np.concatenate(faces)


def _frame(s: ViewerSession, mesh: dict) -> tuple[np.ndarray, np.ndarray]:
    """A frame split into vertex positions ``(V, 3)`` and tool poses ``(T, 12)``."""
    data = s.positions()
    assert len(data) == frame_size(mesh)
    f = np.frombuffer(data, dtype="<f4").astype(np.float64)
    V = mesh["vertices"]
    return f[: 3 * V].reshape(V, 3), f[3 * V :].reshape(-1, 12)


def _path_at(t: float) -> np.ndarray:
    times = [w[0] for w in PATH]
    return np.array([np.interp(t, times, [w[1][c] for w in PATH]) for c in range(3)])


def _steps(s: ViewerSession, n: int) -> None:
    for _ in range(n):
        assert s.advance(0.0) == 1


# ------------------------------------------------------------------ embedded surfaces
def test_the_mesh_of_a_label_scene_is_its_embedded_surfaces_textured(label_scene, device, one_thread):
    s = ViewerSession(label_scene, device=device)
    m = s.mesh()
    rest, faces = _rest(label_scene)
    assert m["surface"] == "embedded" == s.surface
    assert [p["name"] for p in m["parts"]] == list(label_scene.embedded) == ["label1", "label2"]
    assert [p["vertices"] for p in m["parts"]] == [len(v) for v, _ in label_scene.embedded.values()]
    assert m["vertices"] == len(rest)
    assert np.array_equal(np.asarray(m["faces"]).reshape(-1, 3), faces)
    np.testing.assert_allclose(np.asarray(m["bounds"]), [rest.min(0), rest.max(0)], atol=1e-6)
    # the scene's [texture] (16-voxel liver, blocks of 8), looked up at the rest vertices
    assert s.texture.block == 8 and tuple(s.texture.exemplar.shape) == (3, 16, 16, 16)
    want = (s.texture.at_material(torch.as_tensor(rest)).clamp(0, 1) * 255).double().numpy()
    got = np.asarray(m["colors"]).reshape(-1, 3)
    assert got.dtype.kind == "i" and got.min() >= 0 and got.max() <= 255
    assert np.abs(got - want).max() <= 0.5 + 1e-3 and got.std() > 1  # rounded; not one flat colour
    # at rest the frame is the rest surface
    v, _ = _frame(s, m)
    np.testing.assert_allclose(v, rest, atol=1e-6)


def test_frames_follow_the_lattice_by_trilinear_interpolation(label_scene, device, one_thread):
    s = ViewerSession(label_scene, device=device)
    m = s.mesh()
    rest, _ = _rest(label_scene)
    _steps(s, 150)  # the probe presses into the top, gravity sags the free body
    x = s.state.x[0]
    assert float((x - s.model.X[0]).abs().max()) > 1e-4
    v, _ = _frame(s, m)
    np.testing.assert_allclose(v, _trilinear(label_scene.grid, x, rest), atol=1e-6)
    # the same as the library's own per-frame call
    from torchdeform.mesh import EmbeddedSurface

    own = [
        EmbeddedSurface(p, f, label_scene.grid, dtype=torch.float64).update(x.double().cpu())[0]
        for p, f in label_scene.embedded.values()
    ]
    np.testing.assert_allclose(v, torch.cat(own).numpy(), atol=1e-6)


def test_a_cut_splits_the_embedded_surfaces_and_a_reset_restores_them(label_scene, one_thread):
    s = ViewerSession(label_scene)
    V0 = s.mesh()["vertices"]
    s.command({"cmd": "cut", "origin": [0.0105, -0.01, -0.01], "u": [0.0, 0.04, 0.0], "v": [0.0, 0.0, 0.04]})
    m = s.mesh()
    assert s.mesh_version == 1 and m["surface"] == "embedded" and m["vertices"] > V0  # the crossing edges split
    assert len(m["colors"]) == 3 * m["vertices"]
    rest, _ = _frame(s, m)  # no step yet: the rest surface
    s.command({"cmd": "pause"})
    s.command({"cmd": "drag", "vertex": int(np.argmax(rest[:, 0])), "target": [0.03, 0.009, 0.008]})
    s.command({"cmd": "play"})
    _steps(s, 100)
    v, _ = _frame(s, m)
    assert np.isfinite(v).all()
    # the top vertex's piece is dragged: the top half lifts, the bottom half stays on the slab
    top = rest[:, 0] > 0.0105
    assert v[top, 0].max() > rest[top, 0].max() + 1e-3
    s.command({"cmd": "reset"})
    assert s.mesh()["vertices"] == V0 and s.mesh()["surface"] == "embedded"


# ------------------------------------------------------------------ tools
def test_the_probe_is_sent_once_and_posed_on_its_path(label_scene, one_thread):
    s = ViewerSession(label_scene)
    m = s.mesh()
    (probe,) = m["tools"]
    assert probe["name"] == "probe" and probe["smooth"] is True and len(probe["color"]) == 3
    pv = np.asarray(probe["vertices"]).reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(pv, axis=1), RADIUS, atol=1e-6)  # in its own frame
    assert len(probe["faces"]) % 3 == 0 and max(probe["faces"]) < len(pv)
    for n in (0, 40, 40, 80):  # before, during and after the press
        _steps(s, n)
        _, poses = _frame(s, m)
        assert poses.shape == (1, 12)
        t = float(s.state.t)
        np.testing.assert_allclose(poses[0, :3], _path_at(t), atol=1e-7)
        np.testing.assert_allclose(poses[0, 3:], np.eye(3).reshape(-1), atol=0)
    assert float(s.state.t) > PATH[1][0]  # the pose has moved down and back up


def test_a_scene_without_labels_keeps_the_lattice_surface_and_draws_its_tool(cube_scene, one_thread):
    from torchdeform.topology import cut_surfaces

    s = ViewerSession(cube_scene)
    m = s.mesh()
    assert m["surface"] == "lattice" and m["parts"] == [{"name": "lattice", "vertices": m["vertices"]}]
    assert tuple(s.texture.exemplar.shape) == (3, 64, 64, 64)  # no [texture]: the procedural liver
    assert len(m["colors"]) == 3 * m["vertices"] and len(m["tools"]) == 1
    assert frame_size(m) == 4 * (3 * m["vertices"] + 12)
    _steps(s, 60)
    v, poses = _frame(s, m)
    (piece,) = cut_surfaces(s.grid, s.state.x.double(), s.labels)
    np.testing.assert_allclose(v, piece.vertices, atol=1e-6)
    np.testing.assert_allclose(poses[0, :3], _path_at(float(s.state.t)), atol=1e-7)


def test_colours_come_from_the_texture_given(label_scene, one_thread):
    from torchdeform.texture.mapping import body_texture

    constant = torch.tensor([0.2, 0.4, 0.6]).view(3, 1, 1, 1).expand(3, 8, 8, 8).contiguous()
    s = ViewerSession(label_scene, texture=body_texture(label_scene.grid, exemplar=constant, block=4))
    got = np.asarray(s.mesh()["colors"]).reshape(-1, 3)
    assert (got == [51, 102, 153]).all()


# ------------------------------------------------------------------ through the server
def test_the_server_sends_faces_colours_once_then_frames_of_positions_and_poses(label_scene, one_thread):
    websockets = pytest.importorskip("websockets")  # noqa: F841
    from websockets.sync.client import connect

    from torchdeform.view.server import Viewer

    s = ViewerSession(label_scene)
    _steps(s, 60)  # the probe in the tissue
    s.command({"cmd": "pause"})  # frames of this state only
    rest, faces = _rest(label_scene)
    x, t = s.state.x[0].clone(), float(s.state.t)
    v = Viewer(s).start()
    try:
        with connect(f"ws://127.0.0.1:{v.port}/ws?token={v.token}", origin=f"http://127.0.0.1:{v.port}") as ws:
            first = ws.recv(timeout=20)
            frames, end = [], time.monotonic() + 20
            while not frames and time.monotonic() < end:  # paused: one frame, then none until a change
                msg = ws.recv(timeout=20)
                if isinstance(msg, bytes):
                    frames.append(msg)
                else:
                    assert json.loads(msg)["type"] == "stats"  # no second mesh
    finally:
        v.stop()
    assert isinstance(first, str)
    mesh = json.loads(first)
    assert mesh["type"] == "mesh" and mesh["surface"] == "embedded"
    assert np.array_equal(np.asarray(mesh["faces"]).reshape(-1, 3), faces)
    assert mesh["colors"] == s.mesh()["colors"] and len(mesh["colors"]) == 3 * len(rest)
    assert [tool["name"] for tool in mesh["tools"]] == ["probe"]
    assert frames and all(len(f) == frame_size(mesh) for f in frames)
    data = np.frombuffer(frames[-1], dtype="<f4").astype(np.float64)
    np.testing.assert_allclose(data[: 3 * len(rest)].reshape(-1, 3), _trilinear(label_scene.grid, x, rest), atol=1e-6)
    np.testing.assert_allclose(data[3 * len(rest) : 3 * len(rest) + 3], _path_at(t), atol=1e-7)
