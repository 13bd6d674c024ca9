"""The viewer's server: token, Origin, static files, malformed messages (torchdeform.view.server).

The server runs in a background thread on a free loopback port with a small scene; the tests talk
to it with plain HTTP (http.client) and the websockets client.
"""

from __future__ import annotations

import http.client
import json
import time

import pytest
import torch

websockets = pytest.importorskip("websockets")
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from torchdeform.view.server import MAX_MESSAGE, STATIC_FILES, Viewer, validate

SCENE = """
[grid]
shape = [{n}, {n}, {n}]
spacing = 0.002
topology = 26
[material]
stiffness = 5.0
damping = 1e-4
[mass]
density = 1000.0
[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
decay = 20.0
[integrator]
name = "symplectic"
dt = 1e-4
steps = 100
"""  # the viewer bench's cube as a file, for the command line


def make_session(n: int = 6):
    """A viewer session of an n^3 cube of soft tissue (the viewer bench's: fixed base, gravity along -D)."""
    from torchdeform.bench.viewer import viewer_cube
    from torchdeform.view.session import ViewerSession

    return ViewerSession(viewer_cube(n))


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    v = Viewer(make_session(), token="s3cret-token-for-tests").start()
    yield v
    v.stop()
    assert not v._thread.is_alive()


def get(v: Viewer, path: str, headers: dict | None = None):
    c = http.client.HTTPConnection("127.0.0.1", v.port, timeout=10)
    try:
        c.request("GET", path, headers=headers or {})
        r = c.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        c.close()


def ws_url(v: Viewer, token: str | None) -> str:
    return f"ws://127.0.0.1:{v.port}/ws" + ("" if token is None else f"?token={token}")


def origin(v: Viewer) -> str:
    return f"http://127.0.0.1:{v.port}"


def frame_sizes(ws, frames: int = 3, timeout: float = 10.0, check_text: bool = True) -> list:
    """The sizes of the next ``frames`` binary frames (text messages between them: stats or mesh)."""
    sizes = []
    end = time.monotonic() + timeout
    while len(sizes) < frames and time.monotonic() < end:
        msg = ws.recv(timeout=timeout)
        if isinstance(msg, bytes):
            sizes.append(len(msg))
        elif check_text:
            assert json.loads(msg)["type"] in ("stats", "mesh")
    return sizes


def receive_mesh_and_frames(ws, frames: int = 3, timeout: float = 10.0):
    """The first message (must be the mesh) and the sizes of the next binary frames."""
    first = ws.recv(timeout=timeout)
    assert isinstance(first, str)
    mesh = json.loads(first)
    assert mesh["type"] == "mesh"
    return mesh, frame_sizes(ws, frames, timeout)


# ------------------------------------------------------------------ HTTP
def test_page_needs_the_token(viewer):
    assert get(viewer, "/")[0] == 403
    assert get(viewer, "/?token=wrong")[0] == 403
    assert get(viewer, "/?token=")[0] == 403
    status, headers, body = get(viewer, f"/?token={viewer.token}")
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b'<canvas id="view"' in body and b"/static/viewer.js" in body
    assert "frame-ancestors 'none'" in headers["Content-Security-Policy"]
    assert viewer.url == f"http://127.0.0.1:{viewer.port}/?token={viewer.token}"


def test_static_files_are_whitelisted(viewer):
    for name, kind in STATIC_FILES.items():
        status, headers, body = get(viewer, f"/static/{name}")
        assert status == 200 and headers["Content-Type"] == kind and body
    for bad in (
        "/static/index.html/../server.py",
        "/static/../server.py",
        "/static/%2e%2e/server.py",
        "/static/",
        "/static/nope.js",
        "/server.py",
        "/ws/../static/viewer.js",
    ):
        assert get(viewer, bad)[0] in (403, 404), bad


def test_plain_http_on_the_socket_path_is_not_an_upgrade(viewer):
    status = get(viewer, f"/ws?token={viewer.token}", {"Origin": origin(viewer)})[0]
    assert status == 426  # websockets: Upgrade Required


# ------------------------------------------------------------------ the socket
@pytest.mark.parametrize(
    "token, org",
    [
        (None, "ok"),
        ("wrong", "ok"),
        ("", "ok"),
        ("s3cret-token-for-test", "ok"),
        ("ok", "http://evil.example"),
        ("ok", None),
        ("ok", "http://127.0.0.1:1"),
        ("ok", "https://127.0.0.1:{port}"),
    ],
)
def test_socket_refused(viewer, token, org):
    token = viewer.token if token == "ok" else token
    org = origin(viewer) if org == "ok" else (org.format(port=viewer.port) if org else None)
    with pytest.raises(InvalidStatus) as e, connect(ws_url(viewer, token), origin=org, open_timeout=10):
        pass
    assert e.value.response.status_code == 403


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost"])
def test_socket_accepted_sends_mesh_then_frames(viewer, host):
    with connect(ws_url(viewer, viewer.token), origin=f"http://{host}:{viewer.port}", open_timeout=10) as ws:
        mesh, sizes = receive_mesh_and_frames(ws)
    V = mesh["vertices"]
    assert V > 0 and len(mesh["faces"]) % 3 == 0 and max(mesh["faces"]) < V
    assert sizes and all(s == 12 * V for s in sizes)


def test_a_pulling_page_gets_only_the_frames_it_asks_for(viewer):
    """After {"cmd": "next"} a page is sent frames only when it asks: silence between requests."""

    def frames(seconds):
        return [m for m in iter_messages(ws, seconds) if isinstance(m, bytes)]

    def answer(timeout=10.0, settle=0.5):
        """The frames that answer a request: wait (a loaded machine may be slow) for the first, then settle."""
        got = []
        end = time.monotonic() + timeout
        while not got and time.monotonic() < end:
            got = frames(min(0.25, end - time.monotonic()))
        return got + frames(settle)

    def stream(count=5, timeout=10.0):
        """Frames pushed without asking: wait (a loaded machine may be slow) until ``count`` have come."""
        got = []
        end = time.monotonic() + timeout
        while len(got) < count and time.monotonic() < end:
            got += frames(min(0.25, end - time.monotonic()))
        return got

    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
        mesh, _ = receive_mesh_and_frames(ws, frames=1)
        pushed = stream()
        ws.send(json.dumps({"cmd": "next"}))
        first = answer()  # the one asked for (and perhaps one pushed before)
        unasked = frames(1.0)
        for _ in range(3):
            ws.send(json.dumps({"cmd": "next"}))
        asked = answer(settle=1.0)
        after = frames(0.5)
    print(
        f"\npushed: {len(pushed)}; pulled: {len(first)}, then {len(unasked)} unasked in 1 s, "
        f"{len(asked)} for 3 requests"
    )
    assert len(pushed) >= 5  # the simulation runs: a pushing page gets a stream
    assert 1 <= len(first) <= 2
    assert unasked == [] and after == []
    assert 1 <= len(asked) <= 3  # two ahead at most, and only fresh frames
    assert all(len(m) == 12 * mesh["vertices"] for m in first + asked)


def iter_messages(ws, seconds: float):
    """Every message received within ``seconds``."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        try:
            yield ws.recv(timeout=left)
        except TimeoutError:
            return


def malformed_messages(n: int = 1000):
    """n messages the server must ignore: bad JSON, non-objects, unknown commands, bad values."""
    fixed = [
        "",
        "{",
        "nul",
        "[1, 2",
        '{"cmd": }',
        "NaN",
        "[]",
        "[1, 2, 3]",
        '"play"',
        "42",
        "null",
        "true",
        '{"cmd": "rm -rf"}',
        '{"cmd": null}',
        '{"cmd": 1}',
        '{"cmd": ["play"]}',
        '{"command": "play"}',
        '{"cmd": "drag"}',
        '{"cmd": "drag", "vertex": -1, "target": [0, 0, 0]}',
        '{"cmd": "drag", "vertex": 1e9, "target": [0, 0, 0]}',
        '{"cmd": "drag", "vertex": 99999999, "target": [0, 0, 0]}',
        '{"cmd": "drag", "vertex": true, "target": [0, 0, 0]}',
        '{"cmd": "drag", "vertex": "3", "target": [0, 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": [0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": [NaN, 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": [Infinity, 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": ["NaN", 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": [1e308, 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": [1e400, 0, 0]}',
        '{"cmd": "drag", "vertex": 0, "target": {"x": 0}}',
        '{"cmd": "tool", "position": [0, 0, "x"]}',
        '{"cmd": "tool", "position": 3}',
        '{"cmd": "tool", "position": [1e30, 0, 0]}',
        '{"cmd": "cut", "origin": [0, 0, 0], "u": [0, 0, 1]}',
        '{"cmd": "cut", "origin": [0, 0, 0], "u": [0, 0, NaN], "v": [0, 1, 0]}',
        '{"cmd": "term", "name": "consistency", "value": "high"}',
        '{"cmd": "term", "name": "consistency", "value": 1e300}',
        '{"cmd": "term", "name": "consistency", "value": -5}',
        '{"cmd": "term", "name": "no-such-term", "value": 1}',
        '{"cmd": "term", "name": 7, "value": 1}',
        '{"cmd": "fps", "value": -1}',
        '{"cmd": "fps", "value": "60"}',
        '{"cmd": "fps", "value": 1e9}',
        "[" * 5000 + "]" * 5000,
        '{"a": ' * 1500 + "1" + "}" * 1500,
        "\x00\xff",
        "\ud800",
    ]
    binary = [b"\x00\x01\x02", b'{"cmd": "play"}']
    out = []
    for i in range(n):
        if i % 10 == 9:
            out.append(binary[i % 2])
        else:
            msg = fixed[i % len(fixed)]
            out.append(msg.encode("utf-8", "surrogatepass").decode("utf-8", "replace"))
    return out


def test_malformed_messages_are_ignored(viewer, caplog):
    session = viewer.session
    before = viewer.ignored
    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
        receive_mesh_and_frames(ws, frames=1)
        # paused while they arrive: a playing body's thread takes the GIL for up to the 5 ms switch
        # interval per message, which makes 1,000 messages take about 8 s to read, not 0.1 s
        ws.send(json.dumps({"cmd": "pause"}))
        for msg in malformed_messages(1000):
            ws.send(msg)
        ws.send(json.dumps({"cmd": "play"}))
        ws.send(json.dumps({"cmd": "fps", "value": 59.5}))
        # the connection is still open and still streams
        sizes = frame_sizes(ws, check_text=False)
        assert sizes
        # (waited for with the connection open: closing it may drop messages the server has not read yet)
        deadline = time.monotonic() + 10
        while viewer.ignored - before < 1000 and time.monotonic() < deadline:
            time.sleep(0.05)
    assert viewer.ignored - before >= 1000
    assert viewer.page_fps == 59.5
    ignored_lines = [r for r in caplog.records if r.name == "torchdeform.view" and "ignored" in r.getMessage()]
    assert ignored_lines and all("\n" not in r.getMessage() for r in ignored_lines)
    # oversized: that connection is closed (1009), the server goes on
    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
        receive_mesh_and_frames(ws, frames=1)
        ws.send("x" * (MAX_MESSAGE + 1))
        with pytest.raises(ConnectionClosed):
            for _ in range(1000):
                ws.recv(timeout=10)
    # a fresh page still works and the body is finite
    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
        mesh, sizes = receive_mesh_and_frames(ws)
        assert sizes and all(s == 12 * mesh["vertices"] for s in sizes)
        ws.send(json.dumps({"cmd": "pause"}))
    assert torch.isfinite(session.state.x).all()
    assert viewer._thread.is_alive() and viewer._sim_thread.is_alive()


def test_closing_the_page_leaves_the_server_serving(viewer):
    for _ in range(3):
        with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
            receive_mesh_and_frames(ws, frames=1)
    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10, close_timeout=0.1) as ws:
        ws.recv(timeout=10)
        ws.socket.close()  # abruptly, without a closing handshake
    assert get(viewer, f"/?token={viewer.token}")[0] == 200
    with connect(ws_url(viewer, viewer.token), origin=origin(viewer), open_timeout=10) as ws:
        assert receive_mesh_and_frames(ws, frames=1)[1]
    deadline = time.monotonic() + 5
    while len(viewer.pages) > 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(viewer.pages) == 0


def test_validate():
    assert validate({"cmd": "play", "extra": 1}) == {"cmd": "play"}
    assert validate({"cmd": "tool", "position": None}) == {"cmd": "tool", "position": None}
    assert validate({"cmd": "cut", "origin": [0, 0, 0], "u": [0, 0, 0.01], "v": [0.01, 0, 0]})["u"] == [0, 0, 0.01]
    for bad in (
        [],
        "play",
        {"cmd": "exec"},
        {"cmd": "drag", "vertex": 1.5, "target": [0, 0, 0]},
        {"cmd": "term", "name": "", "value": 1},
        {"cmd": "fps", "value": float("nan")},
    ):
        with pytest.raises(ValueError):
            validate(bad, vertices=10)


def test_stop_is_clean():
    v = Viewer(make_session(n=4)).start()
    assert len(v.token) >= 24
    port = v.port
    v.stop()
    assert not v._thread.is_alive() and not v._sim_thread.is_alive()
    with pytest.raises(OSError):
        get(v, "/")
    assert port > 0


def test_command_line(tmp_path):
    import signal
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid]\nshape = 3\n")
    for scene in (bad, tmp_path / "missing.toml"):
        r = subprocess.run(
            [sys.executable, "-m", "torchdeform", "view", str(scene)],
            capture_output=True,
            text=True,
            cwd=root,
            timeout=120,
        )
        lines = r.stderr.strip().splitlines()  # one line per problem of the file, each naming it
        assert r.returncode == 2 and lines and all(ln.startswith("torchdeform: ") for ln in lines), r.stderr
        assert all(scene.name in ln for ln in lines) and "Traceback" not in r.stderr
    good = tmp_path / "cube.toml"
    good.write_text(SCENE.format(n=4))
    p = subprocess.Popen(
        [sys.executable, "-m", "torchdeform", "view", str(good), "--token", "a-test-token-123"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=root,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        url = p.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:") and url.endswith("/?token=a-test-token-123")
        port = int(url.split(":")[2].split("/")[0])
        c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        c.request("GET", "/?token=a-test-token-123")
        assert c.getresponse().status == 200
        c.close()
        p.send_signal(signal.SIGINT)  # Ctrl-C: a clean stop, exit status 0
        _out, err = p.communicate(timeout=30)
        assert p.returncode == 0, err
    finally:
        if p.poll() is None:
            p.kill()
