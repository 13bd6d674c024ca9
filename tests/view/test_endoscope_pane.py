"""The viewer's endoscope pane: the session's image of the current state and the server's messages.

Oracles:

* the image: :func:`~torchdeform.volume.render_endoscope` with an
  :class:`~torchdeform.volume.EndoscopeCamera` built by hand: the scope's position on its path
  (``numpy.interp`` of the scene file's waypoints at the session's simulated time), looking along the
  path's segment, the world-to-voxel scale ``(N - 1) / (spacing (n - 1))`` written out, the probe as a
  sphere at its own waypoint, the volume deformed through
  :func:`~torchdeform.volume.node_offsets` of the session's current positions: the same uint8 within 1;
* the server: the messages a real websocket client receives, parsed by the layout the module
  docstring gives (magic, height, width, time, sequence, then RGB), against the session's own image.
"""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchdeform.scene import load_scene
from torchdeform.view.session import ViewerSession, frame_size

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "endoscopy.toml"
MAGIC = b"\x45\x4e\xc4\x7f"  # uint32 0x7FC44E45, little endian
STEPS = 60  # viewer steps before the image is compared

NO_CAMERA = """
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

[integrator]
name = "symplectic"
dt = "auto"
steps = 20
"""


def _texture(grid):
    """A constant solid texture (fast: no procedural exemplar)."""
    from torchdeform.texture.mapping import body_texture

    constant = torch.tensor([0.2, 0.4, 0.6]).view(3, 1, 1, 1).expand(3, 8, 8, 8).contiguous()
    return body_texture(grid, exemplar=constant, block=4)


def _session(path) -> ViewerSession:
    scene = load_scene(path)
    return ViewerSession(scene, texture=_texture(scene.grid))


@pytest.fixture(scope="module")
def doc() -> dict:
    return tomllib.loads(SCENE.read_text())


def _tool(doc: dict, name: str) -> dict:
    return next(t for t in doc["tools"] if t["name"] == name)


def _at(path: list, t: float) -> np.ndarray:
    """The waypoints' linear interpolation at ``t`` (held outside), m."""
    times = [w[0] for w in path]
    return np.array([np.interp(t, times, [w[1][c] for w in path]) for c in range(3)])


def _hand_render(doc: dict, session: ViewerSession, t: float, *, deformed: bool = True) -> np.ndarray:
    """The endoscope image at ``t`` of the session's current positions, every step written out here."""
    from torchdeform.volume import EndoscopeCamera, Sphere, load_volume, node_offsets, render_endoscope, to_image

    vol = torch.from_numpy(load_volume(doc["volume"]["file"]))
    shape = tuple(vol.shape)
    n, h = doc["grid"]["shape"], doc["grid"]["spacing"]
    scale = np.array([(N - 1) / (h * (k - 1)) for N, k in zip(shape, n)])  # voxels per metre, origin 0

    scope = _tool(doc, "scope")["path"]
    times = [w[0] for w in scope]
    seg = int(np.searchsorted(times, t, side="right")) - 1  # the path segment the scope is on
    assert 0 <= seg < len(scope) - 1
    look = (np.array(scope[seg + 1][1]) - np.array(scope[seg][1])) * scale
    probe = _tool(doc, "probe")
    cam_doc = doc["camera"]
    cam = EndoscopeCamera(
        position=(_at(scope, t) * scale).tolist(),
        direction=(look / np.linalg.norm(look)).tolist(),
        up=(scale * [1.0, 0.0, 0.0]).tolist(),  # +D: the view is not along D
        fov=cam_doc["fov"],
        size=tuple(cam_doc["size"]),
        far=cam_doc["far"] * float(scale.mean()),
    )
    ball = Sphere((_at(probe["path"], t) * scale).tolist(), probe["radius"] * float(scale.mean()), (0.75, 0.75, 0.8))
    with torch.no_grad():
        x, X = session.state.x.double().cpu(), session.model.X.double().cpu()
        offsets = node_offsets(x, X, (h, h, h), shape).float()[0]
        img = render_endoscope(vol, cam, tf=doc["volume"]["tf"], offsets=offsets if deformed else None, surfaces=[ball])
    return to_image(img)


def test_the_sessions_image_is_the_endoscope_at_the_tool_now(doc, one_thread):
    s = _session(SCENE)
    assert s.camera == {"kind": "endoscope", "tool": "scope", "size": [160, 160], "fov": 110.0}
    assert s.mesh()["camera"] == s.camera
    # pull the front of the abdomen in, near the lumen, so that the volume in view deforms
    v = np.frombuffer(s.positions(), dtype="<f4")[: 3 * s.mesh()["vertices"]].reshape(-1, 3)
    i = int(np.argmin(((v - [0.02, 0.0, 0.03]) ** 2).sum(1)))
    s.command({"cmd": "drag", "vertex": i, "target": [0.02, 0.012, 0.03]})
    for _ in range(STEPS):
        assert s.advance(0.0) == 1
    scoped = s.endoscope()
    assert scoped is not None
    t, img = scoped
    assert t == float(s.state.t) > 0.02
    assert float((s.state.x - s.model.X).abs().max()) > 1e-3  # the body has moved: offsets matter
    assert img.dtype == np.uint8 and img.shape == (160, 160, 3)
    ref = _hand_render(doc, s, t)
    diff = np.abs(img.astype(int) - ref.astype(int))
    assert diff.max() <= 1, (diff.max(), (diff > 1).mean())
    assert (img.max(axis=2) > 30).mean() > 0.2  # the lumen's wall in view, not a black image
    rest = _hand_render(doc, s, t, deformed=False)
    moved = (np.abs(img.astype(int) - rest).max(axis=2) > 10).mean()
    print(f"\nendoscope: {moved:.2%} of the pixels differ from the undeformed volume's")
    assert moved > 0.01  # the drag deformed what the endoscope sees
    # a reset shows the start again: the image of the rest state at t = 0
    s.command({"cmd": "reset"})
    scoped = s.endoscope()
    assert scoped is not None
    t0, start = scoped
    assert t0 == 0.0
    assert np.abs(start.astype(int) - _hand_render(doc, s, 0.0).astype(int)).max() <= 1


def test_a_scene_without_camera_has_no_pane(tmp_path):
    (tmp_path / "cube.toml").write_text(NO_CAMERA)
    s = _session(tmp_path / "cube.toml")
    assert s.camera is None and s.endoscope() is None
    assert "camera" not in s.mesh()


# ------------------------------------------------------------------ through the server
def _collect(viewer, seconds: float, *, until=None, timeout: float = 10.0) -> tuple:
    """The mesh message, the frames and the endoscope messages a page receives in ``seconds``
    (with ``until``: for ``seconds`` after the first endoscope message ``m`` with ``until(m)``, at most ``timeout``)."""
    from websockets.sync.client import connect

    mesh, frames, scopes = None, [], []
    url = f"ws://127.0.0.1:{viewer.port}/ws?token={viewer.token}"
    with connect(url, origin=f"http://127.0.0.1:{viewer.port}", open_timeout=10) as ws:
        end = time.monotonic() + (timeout if until is not None else seconds)
        while time.monotonic() < end:
            try:
                msg = ws.recv(timeout=max(0.01, end - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["type"] == "mesh":
                    mesh = m
            elif msg[:4] == MAGIC:
                scopes.append((time.monotonic(), msg))
                if until is not None and until(msg):
                    end, until = min(end, time.monotonic() + seconds), None
            else:
                frames.append(msg)
    return mesh, frames, scopes


def test_the_server_sends_endoscope_images_at_a_modest_rate(one_thread):
    pytest.importorskip("websockets")
    from torchdeform.view.server import ENDOSCOPE_HEADER, Viewer

    s = _session(SCENE)
    v = Viewer(s).start()
    try:
        assert v.scoped
        mesh, frames, scopes = _collect(v, 1.5)
        s.command({"cmd": "pause"})
        scoped = s.endoscope()  # the paused state's image, as a new page gets it
        assert scoped is not None
        t, img = scoped
        _, _, later = _collect(v, 0.5, until=lambda m: struct.unpack("<f", m[8:12])[0] == np.float32(t))
    finally:
        v.stop()
    assert mesh is not None and mesh["camera"]["size"] == [160, 160] and mesh["camera"]["tool"] == "scope"
    assert frames and all(len(f) == frame_size(mesh) for f in frames)
    assert 2 <= len(scopes) <= 1.5 * 10 + 3, len(scopes)  # at most ~10 a second (fewer on a busy machine)
    seqs, times = [], []
    for _, m in scopes:
        magic, h, w, tt, seq = struct.unpack("<IHHfI", m[:ENDOSCOPE_HEADER])
        assert magic == 0x7FC44E45 and (h, w) == (160, 160) and len(m) == ENDOSCOPE_HEADER + 3 * h * w
        seqs.append(seq)
        times.append(tt)
    assert seqs == sorted(seqs) and times == sorted(times) and times[-1] > times[0]  # a live, moving view
    # paused: a page that connects gets the image of the state now (after the last one rendered while a
    # page was connected, if the state moved since), then nothing new
    assert 1 <= len(later) <= 2, [struct.unpack("<f", m[8:12]) for _, m in later]
    _, h, w, tt, _ = struct.unpack("<IHHfI", later[-1][1][:ENDOSCOPE_HEADER])
    assert tt == np.float32(t)
    np.testing.assert_array_equal(np.frombuffer(later[-1][1], np.uint8, offset=ENDOSCOPE_HEADER).reshape(h, w, 3), img)


def test_the_server_sends_no_endoscope_without_a_camera(tmp_path, one_thread):
    pytest.importorskip("websockets")
    from torchdeform.view.server import Viewer

    (tmp_path / "cube.toml").write_text(NO_CAMERA)
    v = Viewer(_session(tmp_path / "cube.toml")).start()
    try:
        assert not v.scoped and v._scope_thread is None
        mesh, frames, scopes = _collect(v, 0.8)
    finally:
        v.stop()
    assert mesh is not None and "camera" not in mesh
    assert frames and all(len(f) == frame_size(mesh) for f in frames)
    assert scopes == [] and v.endoscope_images == 0
