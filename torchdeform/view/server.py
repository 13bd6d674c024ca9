"""The local viewer's server: the page, its static files and a WebSocket on one loopback port.

The simulation (a :class:`~torchdeform.view.session.ViewerSession`) runs in a worker thread at its
own rate; an asyncio loop serves the page and, to every connected page, sends

* a ``"mesh"`` JSON text message on connect and whenever the session's ``mesh_version`` changes
  (a cut): what is drawn and does not move (:meth:`~torchdeform.view.session.ViewerSession.mesh`):
  ``surface`` (``"embedded"``: the scene's smooth embedded surfaces, or ``"lattice"``), the
  vertex count ``V``, the triangles, per-vertex colours of the solid texture at the rest positions
  (0-255), the rest bounds, the tissue terms, and ``tools``: each scene tool's triangles in its own
  frame;
* a binary message per frame (up to ``frame_rate`` Hz), float32 little endian
  (:meth:`~torchdeform.view.session.ViewerSession.positions`): the ``V * 3`` vertex positions in
  metres, axis order (D, H, W), then 12 values per tool, its pose at the simulated time (position
  ``c``, m, and rotation ``R`` row-major: a tool vertex ``p`` is drawn at ``c + R p``); in all
  :func:`~torchdeform.view.session.frame_size` bytes. Only the latest frame is ever
  sent: a slow page skips frames, it never receives stale ones from a queue. A page that sends
  ``{"cmd": "next"}`` is sent frames only when it asks (at most two ahead): the bundled page asks
  once per frame it draws, so no frame is encoded, sent and dropped for nothing;
* a ``"stats"`` JSON text message about ``stats_rate`` times a second (simulated time, sim rate,
  tool force, springs, the page's frame rate as ``page_fps``);
* for a scene with ``[camera]`` only (the mesh message then has ``camera``: ``{"kind", "tool",
  "size": [h, w], "fov"}``), an endoscope image as a binary message, at most ``endoscope_rate`` Hz
  (10) and only when the state changed (or to a page that has none yet): what the endoscope riding
  the tool sees of the current state
  (:meth:`~torchdeform.view.session.ViewerSession.endoscope`). It is rendered in its own thread,
  pushed rather than pulled, and like the frames never queued: only the latest unsent image is
  sent. Its layout (:func:`endoscope_message`), little endian: a 16-byte header, ``uint32`` magic
  ``0x7FC44E45`` (the bytes ``45 4E C4 7F``: as float32 a NaN, which no frame starts with, a
  frame's values being finite; a frame is told from an image by this alone), ``uint16`` height
  ``h``, ``uint16`` width ``w``, ``float32`` simulated time ``t`` (s), ``uint32`` sequence number;
  then ``h * w * 3`` bytes of RGB, rows from the top, 0 outside the round mask. A scene without
  ``[camera]`` sends none and renders nothing.

Safe by default:

* it listens on ``127.0.0.1`` only, unless told another host;
* the page (``GET /?token=T``) and the socket (``GET /ws?token=T``) need the random token of the
  URL printed at start (compared with :func:`hmac.compare_digest`), else HTTP 403;
* the socket also needs the ``Origin`` header of the page's own address ``http://HOST:PORT``
  (for a loopback host the ``localhost`` and ``127.0.0.1`` spellings are both accepted), else 403:
  another web site open in the same browser can neither read nor drive the simulation;
* the static files (``GET /static/NAME``) are served without the token: only the files shipped in
  the package's ``static`` folder (a fixed list, each with its content type), which hold no data
  and allow no control;
* every message from the page is validated: bad JSON, non-objects, unknown commands, wrong types,
  non-finite or out-of-range values and oversized messages are ignored with one logged line
  (logger ``torchdeform.view``), never a crash; closing the page leaves the server running.

The ``websockets`` library (``pip install torchdeform[viewer]``) is imported only when serving.

Examples:
    >>> check_token("abc", "abc"), check_token(None, "abc"), check_token("abd", "abc")
    (True, False, False)
    >>> allowed_origins("127.0.0.1", 8000) == {"http://127.0.0.1:8000", "http://localhost:8000"}
    True
    >>> validate({"cmd": "drag", "vertex": 3, "target": [0.0, 0.01, 0.0]}, vertices=10)
    {'cmd': 'drag', 'vertex': 3, 'target': [0.0, 0.01, 0.0]}
    >>> validate({"cmd": "drag", "vertex": 30, "target": [0.0, 0.01, 0.0]}, vertices=10)
    Traceback (most recent call last):
    ...
    ValueError: drag.vertex: expected a vertex index in [0, 10), got 30
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import math
import secrets
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from .session import _number, _point, frame_size

__all__ = [
    "Viewer",
    "serve",
    "validate",
    "check_token",
    "allowed_origins",
    "endoscope_message",
    "STATIC_FILES",
    "MAX_MESSAGE",
    "ENDOSCOPE_MAGIC",
    "ENDOSCOPE_HEADER",
]

logger = logging.getLogger("torchdeform.view")

STATIC_DIR = Path(__file__).with_name("static")
#: The files ``GET /static/NAME`` may serve, with their content types: nothing else is ever read.
STATIC_FILES = {
    "viewer.js": "text/javascript; charset=utf-8",
    "socket-worker.js": "text/javascript; charset=utf-8",
    "three.module.min.js": "text/javascript; charset=utf-8",
    "LICENSE-three.txt": "text/plain; charset=utf-8",
}
#: The largest message accepted from a page (bytes); a larger one closes that page's connection.
MAX_MESSAGE = 16 * 1024
#: The largest coordinate (m) accepted in a command: the viewer's bodies are centimetres to a metre.
MAX_COORDINATE = 1e3
LOOPBACK = {"127.0.0.1", "localhost", "::1"}
COMMANDS = ("play", "pause", "reset", "drag", "release", "tool", "cut", "term", "fps", "next")
#: The first four bytes of an endoscope message (``uint32`` little endian; as float32 a NaN, which no
#: frame of finite positions starts with).
ENDOSCOPE_MAGIC = 0x7FC44E45
#: The bytes of an endoscope message's header: magic, height, width, simulated time, sequence number.
ENDOSCOPE_HEADER = 16
_ENDOSCOPE = struct.Struct("<IHHfI")
_PAGE_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; connect-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
    "Cache-Control": "no-store",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
}


def check_token(given: str | None, token: str) -> bool:
    """Whether a request's token is the server's (constant-time comparison).

    Args:
        given: the token of the request (``None`` when it has none).
        token: the server's token.

    Returns:
        ``True`` when they are equal.
    """
    if given is None:
        return False
    return hmac.compare_digest(given.encode("utf-8", "surrogatepass"), token.encode("utf-8"))


def allowed_origins(host: str, port: int, *, request_host: str | None = None) -> set[str]:
    """The ``Origin`` values the socket accepts: the page's own address.

    Args:
        host: the host the server listens on.
        port: its port.
        request_host: the request's ``Host`` header; used only when the server listens on all
            interfaces (``0.0.0.0`` or ``::``), where the page's address is not known in advance.

    Returns:
        The accepted origins, e.g. ``{"http://127.0.0.1:8000", "http://localhost:8000"}``.
    """
    if host in LOOPBACK:
        names = {"127.0.0.1", "localhost"} | ({"[::1]"} if host == "::1" else set())
    elif host in ("0.0.0.0", "::", ""):
        names = {"127.0.0.1", "localhost"}
        if request_host:
            return {f"http://{n}:{port}" for n in names} | {f"http://{request_host}"}
    else:
        names = {f"[{host}]" if ":" in host else host}
    return {f"http://{n}:{port}" for n in names}


def endoscope_message(image, t: float, *, seq: int = 0) -> bytes:
    """An endoscope image as the binary message to the page (module docstring).

    Args:
        image: uint8 RGB ``(h, w, 3)`` (a numpy array).
        t: the simulated time of the image (s).
        seq: its sequence number (wraps at ``2**32``).

    Returns:
        ``ENDOSCOPE_HEADER + 3 h w`` bytes.

    Example:
        >>> import numpy as np
        >>> m = endoscope_message(np.zeros((16, 20, 3), np.uint8), 0.5, seq=3)
        >>> len(m), m[:4].hex(), struct.unpack("<IHHfI", m[:16])[1:]
        (976, '454ec47f', (16, 20, 0.5, 3))
    """
    h, w, c = image.shape
    if c != 3 or image.dtype.name != "uint8":
        raise ValueError(f"image: expected uint8 (h, w, 3), got {image.dtype.name} {tuple(image.shape)}")
    header = _ENDOSCOPE.pack(ENDOSCOPE_MAGIC, h, w, float(t), int(seq) & 0xFFFFFFFF)
    return header + image.tobytes(order="C")


# ------------------------------------------------------------------ messages from the page
def _vector(value: Any, key: str) -> list[float]:
    """Three finite coordinates within ``MAX_COORDINATE`` m (the session's own point check)."""
    return list(_point(value, key, (-MAX_COORDINATE,) * 3, (MAX_COORDINATE,) * 3))


def validate(msg: Any, *, vertices: int | None = None) -> dict:
    """Check one decoded message from the page; returns a clean copy (known keys only).

    Args:
        msg: the decoded JSON message.
        vertices: the surface's vertex count (a drag's vertex must be below it), if known.

    Returns:
        The message with its ``cmd`` and that command's keys, numbers as ``float`` (``int`` for
        a vertex).

    Raises:
        ValueError: naming what was wrong (not an object, unknown command, wrong types,
            non-finite or out-of-range values).
    """
    if not isinstance(msg, dict):
        raise ValueError(f"expected a JSON object, got {type(msg).__name__}")
    cmd = msg.get("cmd")
    if not isinstance(cmd, str) or cmd not in COMMANDS:
        raise ValueError(f"cmd: expected one of {', '.join(COMMANDS)}, got {str(cmd)[:40]!r}")
    if cmd in ("play", "pause", "reset", "release", "next"):
        return {"cmd": cmd}
    if cmd == "drag":
        vertex = msg.get("vertex")
        if (
            isinstance(vertex, bool)
            or not isinstance(vertex, int)
            or vertex < 0
            or (vertices is not None and vertex >= vertices)
        ):
            bound = f"[0, {vertices})" if vertices is not None else ">= 0"
            raise ValueError(f"drag.vertex: expected a vertex index in {bound}, got {str(vertex)[:40]}")
        return {"cmd": cmd, "vertex": vertex, "target": _vector(msg.get("target"), "drag.target")}
    if cmd == "tool":
        position = msg.get("position")
        return {"cmd": cmd, "position": None if position is None else _vector(position, "tool.position")}
    if cmd == "cut":
        return {"cmd": cmd, **{k: _vector(msg.get(k), f"cut.{k}") for k in ("origin", "u", "v")}}
    if cmd == "term":
        name = msg.get("name")
        if not isinstance(name, str) or not 0 < len(name) <= 64:
            raise ValueError("term.name: expected a term name")
        return {"cmd": cmd, "name": name, "value": _number(msg.get("value"), "term.value")}
    return {"cmd": cmd, "value": _number(msg.get("value"), "fps.value", 0.0, 1000.0)}  # fps


def _short(raw: Any, n: int = 60) -> str:
    text = raw if isinstance(raw, str) else f"<{len(raw)} bytes>"
    return repr(text[:n] + ("..." if len(text) > n else ""))


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float as ``None`` and tensors/numpy scalars as numbers (JSON)."""
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    try:
        value = float(value)
    except (TypeError, ValueError):
        return str(value)
    return value if math.isfinite(value) else None


# ------------------------------------------------------------------ one connected page
class _Page:
    """One connected page: the latest unsent mesh, stats and frame (never a queue), and its sender."""

    def __init__(self, ws):
        self.ws = ws
        self.mesh: str | None = None
        self.stats: str | None = None
        self.frame: bytes | None = None
        self.endoscope: bytes | None = None
        self.scoped = False  # has been posted an endoscope image
        self.wake = asyncio.Event()
        self.sent_frames = 0
        self.primed = False  # has been posted a frame of the current body
        self.pull = False  # the page asks for each frame ("next"): none sent unasked
        self.credit = 0  # frames it asked for and has not been sent

    def ask(self) -> None:
        """The page asked for a frame ("next"): from now on frames go only when asked, at most 2 ahead."""
        self.pull = True
        self.credit = min(self.credit + 1, 2)
        self.wake.set()

    def post(
        self,
        mesh: str | None = None,
        stats: str | None = None,
        frame: bytes | None = None,
        endoscope: bytes | None = None,
    ) -> None:
        if mesh is not None:
            self.mesh, self.frame = mesh, None  # a frame of the old mesh is stale
            self.primed = False
        if stats is not None:
            self.stats = stats
        if frame is not None:
            self.frame = frame  # replaces an unsent one: the page skips it
        if endoscope is not None:
            self.endoscope = endoscope  # likewise
        self.wake.set()

    async def send_loop(self) -> None:
        while True:
            await self.wake.wait()
            self.wake.clear()
            for name in ("mesh", "stats", "frame", "endoscope"):
                data = getattr(self, name)
                if data is None or (name == "frame" and self.pull and self.credit <= 0):
                    continue  # a pulling page gets the newest frame when it asks
                setattr(self, name, None)
                await self.ws.send(data)  # waits while the page is slow; newer data replaces
                if name == "frame":
                    self.sent_frames += 1
                    self.credit -= self.pull


# ------------------------------------------------------------------ the server
class Viewer:
    """The viewer's server: a session, its worker thread and the page's WebSocket.

    Args:
        session: the simulation (:class:`~torchdeform.view.session.ViewerSession` or anything with
            its ``command``, ``advance``, ``mesh``, ``positions``, ``stats`` and ``mesh_version``).
        host: the interface to listen on (default loopback only).
        port: the port (0: a free one, see :attr:`port` once started).
        token: the URL's secret (default: a fresh ``secrets.token_urlsafe(24)``).
        frame_rate: the most frames per second sent to a page.
        stats_rate: stats messages per second.
        endoscope_rate: the most endoscope images per second (a session with a ``camera`` only).

    Use :meth:`run` (blocking, Ctrl-C stops it) or :meth:`start` / :meth:`stop` (a background
    thread, as the tests do).
    """

    def __init__(
        self,
        session,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        token: str | None = None,
        frame_rate: float = 60.0,
        stats_rate: float = 5.0,
        endoscope_rate: float = 10.0,
    ):
        self.session = session
        self.host = host
        self.port = int(port)
        self.token = token or secrets.token_urlsafe(24)
        self.frame_rate = float(frame_rate)
        self.stats_rate = float(stats_rate)
        self.endoscope_rate = float(endoscope_rate)
        # the endoscope pane: a session with a camera (ViewerSession of a [camera] scene) and a rate
        self.scoped = (
            getattr(session, "camera", None) is not None
            and callable(getattr(session, "endoscope", None))
            and self.endoscope_rate > 0
        )
        self.page_fps: float | None = None
        self.frames = 0  # frames taken from the session and posted to the pages
        self.ignored = 0  # messages ignored (logged)
        self.pages: set[_Page] = set()
        self._stop_sim = threading.Event()
        self._sim_thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._mesh_json: str | None = None
        self._mesh_version: int | None = None
        self._vertices: int | None = None
        self._frame_size = 0  # bytes of a frame of the mesh last sent
        self._frame: tuple[int, bytes] | None = None  # (sequence number, positions) of the last snapshot
        self._changed = False  # a command may have moved the body
        self._endoscope: tuple[int, bytes] | None = None  # (sequence number, message) of the last image
        self._scope_dirty = True  # the state changed since the last endoscope image
        self._scope_thread: threading.Thread | None = None
        self.endoscope_images = 0  # endoscope images rendered

    # -------------------------------------------------------------- addresses
    @property
    def url(self) -> str:
        """The page's address with the token (what to open in a browser)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        host = "127.0.0.1" if self.host in ("0.0.0.0", "", "::") else host
        return f"http://{host}:{self.port}/?token={self.token}"

    # -------------------------------------------------------------- HTTP before the upgrade
    def _response(self, status: int, body: bytes, content_type: str, extra: dict | None = None):
        from websockets.datastructures import Headers
        from websockets.http11 import Response

        reasons = {200: "OK", 403: "Forbidden", 404: "Not Found", 405: "Method Not Allowed"}
        headers = Headers(
            {
                "Content-Type": content_type,
                "Content-Length": str(len(body)),
                "X-Content-Type-Options": "nosniff",
                "Connection": "close",
            }
        )
        for k, v in (extra or {}).items():
            headers[k] = v
        return Response(status, reasons.get(status, ""), headers, body)

    def _forbidden(self, why: str, path: str):
        logger.info("refused %s: %s", path, why)
        return self._response(403, b"403 Forbidden\n", "text/plain; charset=utf-8")

    def process_request(self, connection, request):
        """The ``websockets`` hook: serve the page and static files, check token and Origin.

        Args:
            connection: the server connection (unused).
            request: the HTTP request.

        Returns:
            An HTTP response, or ``None`` to go on with the WebSocket handshake (``/ws`` only,
            token and Origin good).
        """
        parts = urlsplit(request.path)
        path = parts.path
        given = parse_qs(parts.query).get("token", [None])[0]
        if path.startswith("/static/"):
            name = path[len("/static/") :]
            if name not in STATIC_FILES:
                return self._response(404, b"404 Not Found\n", "text/plain; charset=utf-8")
            body = (STATIC_DIR / name).read_bytes()
            return self._response(200, body, STATIC_FILES[name], {"Cache-Control": "no-cache"})
        if path in ("/", "/index.html"):
            if not check_token(given, self.token):
                return self._forbidden("no or wrong token", path)
            body = (STATIC_DIR / "index.html").read_bytes()
            return self._response(200, body, "text/html; charset=utf-8", _PAGE_HEADERS)
        if path == "/ws":
            if not check_token(given, self.token):
                return self._forbidden("no or wrong token", path)
            origin = request.headers.get("Origin")
            if origin not in allowed_origins(self.host, self.port, request_host=request.headers.get("Host")):
                return self._forbidden(f"Origin {str(origin)[:80]!r} is not the page's", path)
            return None
        if path == "/favicon.ico":
            return self._response(404, b"", "text/plain; charset=utf-8")
        return self._response(404, b"404 Not Found\n", "text/plain; charset=utf-8")

    # -------------------------------------------------------------- the WebSocket
    async def _handler(self, ws) -> None:
        page = _Page(ws)
        if self._mesh_json is None:
            await self._refresh_mesh()
        page.post(mesh=self._mesh_json)
        self.pages.add(page)
        self._changed = True  # the worker takes a fresh snapshot for it
        sender = asyncio.create_task(page.send_loop())
        try:
            async for raw in ws:
                await self._on_message(raw, page)
        except Exception as e:  # a broken or oversized message closes this page only
            logger.info("page connection closed: %s", e)
        finally:
            self.pages.discard(page)
            sender.cancel()
            await asyncio.gather(sender, return_exceptions=True)

    def _ignore(self, raw, why: str) -> None:
        self.ignored += 1
        logger.warning("ignored message %s: %s", _short(raw), why)

    async def _on_message(self, raw, page: _Page | None = None) -> None:
        if not isinstance(raw, str):
            return self._ignore(raw, "expected a JSON text message, got binary")
        try:
            msg = json.loads(raw, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"{c} is not JSON")))
        except (ValueError, RecursionError) as e:
            return self._ignore(raw, f"bad JSON ({str(e)[:60]})")
        try:
            msg = validate(msg, vertices=self._vertices)
        except ValueError as e:
            return self._ignore(raw, str(e))
        if msg["cmd"] == "fps":
            self.page_fps = msg["value"]
            return
        if msg["cmd"] == "next":
            if page is not None:
                page.ask()
            return
        try:
            await asyncio.to_thread(self.session.command, msg)
        except ValueError as e:
            return self._ignore(raw, str(e))
        except Exception as e:  # a session bug must not stop the server
            return self._ignore(raw, f"{type(e).__name__}: {e}")
        self._changed = True
        self._scope_dirty = True  # e.g. the viewer's tool placed while paused
        await self._refresh_mesh()

    # -------------------------------------------------------------- broadcasting
    async def _refresh_mesh(self) -> None:
        if self._mesh_json is not None and self.session.mesh_version == self._mesh_version:
            return
        mesh = await asyncio.to_thread(self.session.mesh)
        self._mesh_version = mesh.get("version", self.session.mesh_version)
        self._vertices = int(mesh["vertices"])
        self._frame_size = frame_size(mesh)
        self._mesh_json = json.dumps(mesh, separators=(",", ":"))
        for page in self.pages:
            page.post(mesh=self._mesh_json)

    async def _stats_json(self) -> str:
        stats = dict(await asyncio.to_thread(self.session.stats))
        stats["page_fps"] = self.page_fps
        stats["pages"] = len(self.pages)
        return json.dumps(_finite(stats), separators=(",", ":"))

    async def _broadcast(self) -> None:
        period, stats_period = 1.0 / self.frame_rate, 1.0 / self.stats_rate
        last, last_stats, next_stats, last_scope = None, None, 0.0, None
        loop = asyncio.get_running_loop()
        while True:
            start = loop.time()
            if self.pages:
                await self._refresh_mesh()
                if start >= next_stats:
                    next_stats = start + stats_period
                    last_stats = await self._stats_json()
                    for page in self.pages:
                        page.post(stats=last_stats)
                seq, frame = self._frame or (None, b"")
                # a frame of another size belongs to a mesh not yet sent: wait for the next
                if seq is not None and len(frame) == self._frame_size:
                    fresh = seq != last
                    last = seq
                    for page in list(self.pages):
                        if fresh or not page.primed:  # a new page gets the body even when still
                            page.primed = True
                            page.post(frame=frame)
                    self.frames += fresh
                if self._endoscope is not None:
                    seq, image = self._endoscope
                    fresh, last_scope = seq != last_scope, seq
                    for page in list(self.pages):
                        if fresh or not page.scoped:
                            page.scoped = True
                            page.post(endoscope=image)
            else:
                last = last_scope = None
            await asyncio.sleep(max(0.0, start + period - loop.time()))

    # -------------------------------------------------------------- the simulation thread
    def _simulate(self) -> None:
        """The worker thread: step while playing and take a snapshot of the surface after each chunk.

        Snapshots are taken here, between chunks of steps, rather than by the event loop: the loop
        never waits for the session's lock while a step holds it.
        """
        chunk = 1.0 / self.frame_rate
        seq = 0
        while not self._stop_sim.is_set():
            try:
                steps = self.session.advance(chunk)
            except Exception as e:  # e.g. a divergence: pause, say so once, keep serving
                logger.error("simulation stopped: %s: %s", type(e).__name__, e)
                with contextlib.suppress(Exception):
                    self.session.command({"cmd": "pause"})
                steps = 0
            changed, self._changed = self._changed, False
            if steps:
                self._scope_dirty = True  # the endoscope's view moved too
            if self.pages and (steps or changed or self._frame is None):
                try:
                    frame = self.session.positions()
                except Exception as e:
                    logger.error("no frame: %s: %s", type(e).__name__, e)
                else:
                    seq += 1
                    self._frame = (seq, frame)
            if not steps:
                self._stop_sim.wait(chunk)

    def _watch_endoscope(self) -> None:
        """The endoscope thread (a session with a camera): the current state's image, at a modest rate.

        It renders at most ``endoscope_rate`` times a second, while pages are connected and the
        state changed. A failed render (e.g. the lens left the volume) is logged once until one succeeds again.
        """
        period, seq, failing = 1.0 / self.endoscope_rate, 0, False
        while not self._stop_sim.is_set():
            start = time.perf_counter()
            if self.pages and (self._scope_dirty or self._endoscope is None):
                self._scope_dirty = False
                try:
                    t, image = self.session.endoscope()
                except Exception as e:
                    if not failing:
                        logger.error("no endoscope image: %s: %s", type(e).__name__, e)
                    failing = True
                else:
                    failing = False
                    seq += 1
                    self.endoscope_images += 1
                    self._endoscope = (seq, endoscope_message(image, t, seq=seq))
            self._stop_sim.wait(max(0.0, start + period - time.perf_counter()))

    # -------------------------------------------------------------- life cycle
    async def serve_async(self, *, ready: Callable[[Viewer], None] | None = None) -> None:
        """Serve until :meth:`stop` (or cancellation); the simulation thread runs meanwhile.

        Args:
            ready: called with this viewer once it listens (its :attr:`port` known).
        """
        from websockets.asyncio.server import serve as ws_serve

        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        self._stop_sim.clear()
        self._sim_thread = threading.Thread(target=self._simulate, name="torchdeform-view-sim", daemon=True)
        if self.scoped:
            self._scope_thread = threading.Thread(
                target=self._watch_endoscope, name="torchdeform-view-endoscope", daemon=True
            )
        async with ws_serve(
            self._handler,
            self.host,
            self.port,
            process_request=self.process_request,
            max_size=MAX_MESSAGE,
            compression=None,
            write_limit=2**20,
            logger=logging.getLogger("torchdeform.view.websockets"),
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._sim_thread.start()
            if self._scope_thread is not None:
                self._scope_thread.start()
            broadcaster = asyncio.create_task(self._broadcast())
            try:
                if ready is not None:
                    ready(self)
                await self._stopped.wait()
            finally:
                broadcaster.cancel()
                await asyncio.gather(broadcaster, return_exceptions=True)
                server.close()
                self._stop_sim.set()
                await asyncio.to_thread(self._sim_thread.join)
                if self._scope_thread is not None:
                    await asyncio.to_thread(self._scope_thread.join)

    def run(self, *, ready: Callable[[Viewer], None] | None = None) -> None:
        """Serve in this thread until :meth:`stop` or Ctrl-C (which stops cleanly).

        Args:
            ready: called with this viewer once it listens.
        """
        try:
            asyncio.run(self.serve_async(ready=ready))
        except KeyboardInterrupt:
            logger.info("interrupted: viewer stopped")
        finally:
            self._stop_sim.set()
            for thread in (self._sim_thread, self._scope_thread):
                if thread is not None and thread.is_alive():
                    thread.join()

    def start(self, *, timeout: float = 30.0) -> Viewer:
        """Serve in a background thread; returns once it listens.

        Args:
            timeout: seconds to wait for the server to listen.

        Returns:
            This viewer (its :attr:`port` and :attr:`url` set).
        """

        def target():
            try:
                asyncio.run(self.serve_async(ready=lambda _: self._ready.set()))
            except BaseException as e:
                self._error = e
                self._ready.set()

        self._thread = threading.Thread(target=target, name="torchdeform-view", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout) or self._error is not None:
            raise RuntimeError(f"the viewer did not start: {self._error!r}")
        return self

    def stop(self, *, timeout: float = 30.0) -> None:
        """Stop serving (from any thread) and wait for the server and the simulation to end.

        Args:
            timeout: seconds to wait for the background thread of :meth:`start`.
        """
        if self._loop is not None and self._stopped is not None and not self._loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop has just closed
                self._loop.call_soon_threadsafe(self._stopped.set)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)


def serve(
    session,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    token: str | None = None,
    log: Callable[[str], Any] | None = print,
    open_browser: bool = False,
) -> int:
    """Serve the viewer of ``session`` until Ctrl-C; returns the exit status (0).

    Args:
        session: the simulation (see :class:`Viewer`).
        host: the interface to listen on (default loopback only).
        port: the port (0: a free one).
        token: the URL's secret (default: a random one).
        log: called once with the page's URL (token included) when the server listens.
        open_browser: also open the URL in a browser (:mod:`webbrowser`).

    Returns:
        0 once stopped (Ctrl-C).
    """

    def ready(viewer: Viewer) -> None:
        if log is not None:
            log(viewer.url)
        if open_browser:
            import webbrowser

            webbrowser.open(viewer.url)

    Viewer(session, host=host, port=port, token=token).run(ready=ready)
    return 0
