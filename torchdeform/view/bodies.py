r"""The simulation a live viewer of several bodies drives: play, pause, reset; the scene's tools move.

:class:`BodiesSession` is the :class:`~torchdeform.view.session.ViewerSession` of a scene of several
bodies (``[[bodies]]``, :class:`~torchdeform.scene.bodies.BodiesScene`): the server
(:class:`~torchdeform.view.server.Viewer`) drives it through the same methods (``command``,
``advance``, ``mesh``, ``positions``, ``stats``, ``mesh_version``) and sends the same messages.

Stepping
    The scene's :class:`~torchdeform.interact.bodies.Bodies` (:meth:`BodiesScene.bodies`: every
    body's model, its tools with fresh contacts, the contacts between the bodies), stepped by
    :meth:`~torchdeform.interact.bodies.Bodies.step` with the scene's integrator and the time step
    of ``torchdeform run`` (:meth:`BodiesScene.time_step` of the smallest of the bodies' stability
    bounds; ``dt = "auto"``: ``safety`` times it). A step that leaves a non-finite value is undone
    and the time step halved.

Surfaces
    One per body: the closed surface of its lattice (:class:`~torchdeform.topology.surfaces.FrameSurface`,
    the vertices a fixed sparse linear map of the node positions, equal to
    :func:`~torchdeform.topology.cut_surfaces` to float32 rounding), in the order of ``[[bodies]]``,
    each in its colour of :data:`~torchdeform.scene.animation.BODY_COLOURS` (the animation's).
    :meth:`BodiesSession.mesh` lists them as ``parts`` (``{"name", "vertices", "triangles",
    "color"}``): their vertices and triangles are consecutive in the message's ``vertices`` and
    ``faces`` in that order, and the page draws one mesh per part.

Tools
    The tools of every body (``[[bodies.tools]]``), drawn as the single-body viewer draws a scene's
    tools: their triangles once, their poses at the simulated time in every frame.

Messages
    ``{"cmd": "play"}``, ``{"cmd": "pause"}``, ``{"cmd": "reset"}`` (every body at rest, fresh
    tools). The single-body interactions (drag, release, the viewer's sphere tool, cut, tissue term)
    raise ``ValueError`` with one line saying so, and nothing changes; ``mesh()["commands"]`` lists
    the accepted ones (the page hides the other controls).

Shapes: node positions ``(1, 3, D, H, W)`` (m) per body; vertex positions ``(V, 3)`` in the axis
order ``(D, H, W)``.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import torch

from ..scene.animation import BODY_COLOURS
from ..scene.bodies import BodiesScene
from ..sim.stability import time_step_bound
from ..topology.masks import alive
from ..topology.surfaces import FrameSurface
from .session import _fail, run_for, tool_parts, tool_poses

__all__ = ["BodiesSession", "COMMANDS"]

#: the messages a viewer of several bodies accepts
COMMANDS = ("play", "pause", "reset")
#: what the refusal of another message says
_REFUSED = (
    "not with several bodies: this viewer plays, pauses and resets them (their tools follow the scene's "
    "paths); drag, the viewer's tool, cuts and tissue terms are single-body interactions"
)


class BodiesSession:
    """A scene of several bodies stepped live: every body's surface, the tools, play, pause, reset.

    See the module docstring for the stepping, the surfaces and the messages.

    Args:
        scene: a :class:`~torchdeform.scene.bodies.BodiesScene` (:func:`~torchdeform.scene.load_scene`
            of a ``[[bodies]]`` file).
        device: where to simulate (default: the scene's, else the CPU).
        max_nodes: refuse (``ValueError``) bodies with more nodes than this in all (None: any size).

    Attributes:
        bodies: the live :class:`~torchdeform.interact.bodies.Bodies`.
        states: the live states, one :class:`~torchdeform.sim.model.State` per body.
        dt: the time step (s).
        playing: whether :meth:`advance` steps (True at the start).
        mesh_version: the surfaces' version (0: they never change).
        names: the bodies' names.
        colours: per body its RGB colour in [0, 1].

    Examples:
        >>> import torch
        >>> from torchdeform.scene import load_scene
        >>> s = BodiesSession(load_scene("scenes/organs.toml"))
        >>> m = s.mesh()
        >>> m["surface"], [p["name"] for p in m["parts"]], m["commands"], [t["name"] for t in m["tools"]]
        ('bodies', ['kidney', 'liver'], ['play', 'pause', 'reset'], ['probe'])
        >>> sum(p["vertices"] for p in m["parts"]) == m["vertices"], len(s.positions()) == 4 * (3 * m["vertices"] + 12)
        (True, True)
        >>> s.advance(0.0) >= 1, s.stats()["t"] > 0
        (True, True)
        >>> try:
        ...     s.command({"cmd": "cut", "origin": [0, 0, 0], "u": [0, 1, 0], "v": [0, 0, 1]})
        ... except ValueError as e:
        ...     print(str(e)[:41])
        cut: not with several bodies: this viewer
    """

    def __init__(self, scene, *, device=None, max_nodes=None):
        if not isinstance(scene, BodiesScene):
            _fail(f"scene: expected a scene of several bodies (BodiesScene), got {type(scene).__name__}")
        self.scene = scene
        self.names = list(scene.names)
        self._device = device
        self._lock = threading.Lock()
        nodes = sum(s.grid.num_nodes for s in scene.scenes)
        if max_nodes is not None and nodes > int(max_nodes):
            _fail(f"scene: the bodies have {nodes} nodes, more than max_nodes = {int(max_nodes)}")
        self.mesh_version = 0
        self._reset()
        models = [b.model for b in self.bodies.bodies]
        with torch.no_grad():
            bound = min(time_step_bound(m, integrator=self.bodies.integrator) for m in models)
        self.dt = float(scene.time_step(bound))
        if not (0 < self.dt < math.inf):
            _fail("scene: no finite, positive stable time step for these bodies")
        self._dt0 = self.dt
        self.colours = [BODY_COLOURS[n % len(BODY_COLOURS)] for n in range(len(models))]
        self._surfaces = [
            FrameSurface(m.grid, labels=torch.where(m.grid.nodes(), 0, -1).numpy(), dtype=m.dtype, device=m.device)
            for m in models
        ]
        self._tools = tool_parts([t for s in scene.scenes if s.tools is not None for t in s.tools.tools])
        self._springs = sum(int(alive(m)[0].sum()) for m in models)

    def _reset(self) -> None:
        """Every body at rest, with fresh tool contacts; playing."""
        self.bodies = self.scene.bodies(device=self._device)
        self.states = self.bodies.rest_states()
        self.playing = True
        self._rate = 0.0
        if hasattr(self, "_dt0"):
            self.dt = self._dt0

    # ---------------------------------------------------------- messages
    def command(self, msg: dict) -> None:
        """Apply one message from the page (module docstring); ``ValueError`` for anything else, nothing changed.

        Args:
            msg: the message, e.g. ``{"cmd": "pause"}``.
        """
        if not isinstance(msg, dict):
            _fail(f"message: expected an object with a cmd, got {type(msg).__name__}")
        cmd = msg.get("cmd")
        if not isinstance(cmd, str):
            raise ValueError(f"cmd: expected one of {', '.join(COMMANDS)}, got {cmd!r}"[:200])
        if cmd not in COMMANDS:
            raise ValueError(f"{cmd[:40]}: {_REFUSED}")
        extra = set(msg) - {"cmd"}
        if extra:
            _fail(f"{cmd}: expected the key cmd, unknown {', '.join(sorted(map(str, extra)))}"[:200])
        with self._lock, torch.no_grad():
            if cmd == "reset":
                self._reset()
            else:
                self.playing = cmd == "play"

    # ---------------------------------------------------------- stepping
    def advance(self, seconds: float) -> int:
        """If playing, step for about ``seconds`` of wall time (at least one step); the number of steps.

        Args:
            seconds: wall time to spend (s), >= 0.
        """
        return run_for(self, seconds, self._try_step)

    def _try_step(self) -> None:
        new = self.bodies.step(self.states, self.dt)
        if all(bool(torch.isfinite(s.x).all()) and bool(torch.isfinite(s.v).all()) for s in new):
            self.states = new
        else:  # undo the step, halve dt
            self.dt *= 0.5

    # ---------------------------------------------------------- outputs
    def mesh(self) -> dict:
        """The surfaces to draw: every body's, one part each, their colours, the tools' triangles.

        Returns:
            ``{"type": "mesh", "version", "surface": "bodies", "vertices" (V, all bodies), "faces"
            (flat, 3 per triangle, indices into all the vertices, outward), "colors" (flat, 3 per
            vertex: its body's colour, integers 0-255), "parts" (``[{"name", "vertices",
            "triangles", "color" ([r, g, b] in [0, 1], sRGB)}]``: one per body, consecutive in this
            order), "bounds" ([[min d, h, w], [max d, h, w]] of the rest surfaces, m), "terms" ({}),
            "tool_radius" (0: no viewer tool), "tools" (as :meth:`ViewerSession.mesh`'s), "commands"
            (the accepted messages)}``.
        """
        with self._lock:
            faces, colours, parts, rests, base = [], [], [], [], 0
            for name, colour, surface in zip(self.names, self.colours, self._surfaces):
                src = surface.source
                rest, f = np.asarray(src["rest"]), np.asarray(src["faces"]).reshape(-1, 3)
                faces.append(f + base)
                rgb = np.round(np.asarray(colour) * 255).astype(np.int64)
                colours.append(np.broadcast_to(rgb, (len(rest), 3)))
                parts.append({"name": name, "vertices": len(rest), "triangles": len(f), "color": list(colour)})
                rests.append(rest)
                base += len(rest)
            rest = np.concatenate(rests)
            return {
                "type": "mesh",
                "version": self.mesh_version,
                "surface": "bodies",
                "vertices": base,
                "faces": np.concatenate(faces).reshape(-1).tolist(),
                "colors": np.concatenate(colours).reshape(-1).tolist(),
                "parts": parts,
                "bounds": [rest.min(0).tolist(), rest.max(0).tolist()],
                "terms": {},
                "tool_radius": 0.0,
                "tools": [part for _, part in self._tools],
                "commands": list(COMMANDS),
            }

    def body_vertices(self) -> list:
        """Per body its surface's vertex positions now, ``[(V_n, 3)]`` float32 (m)."""
        with self._lock, torch.no_grad():
            return [s.vertices(st.x[0]).to(torch.float32).cpu() for s, st in zip(self._surfaces, self.states)]

    def vertices(self) -> torch.Tensor:
        """All the surfaces' vertex positions now, ``(V, 3)`` float32 (m): the first part of :meth:`positions`."""
        return torch.cat(self.body_vertices())

    def positions(self) -> bytes:
        """A frame: every body's vertex positions (in the order of the parts), then the tools' poses.

        float32 little-endian, as :meth:`~torchdeform.view.session.ViewerSession.positions`:
        :func:`~torchdeform.view.session.frame_size` bytes of :meth:`mesh`.
        """
        v = self.vertices().numpy().reshape(-1)
        if self._tools:
            with self._lock:
                t = float(self.states[0].t)
            v = np.concatenate([v, tool_poses([tool for tool, _ in self._tools], t).reshape(-1).astype(np.float32)])
        return v.astype("<f4", copy=False).tobytes()

    def stats(self) -> dict:
        """Time, speed and forces for the page.

        Returns:
            ``{"type": "stats", "t" (s), "sim_hz" (steps per wall second, recent; 0 while paused),
            "force" (N, the largest of the scene tools' reactions), "contact" (``{"<a>/<b>": N}``, the
            contact force per pair at the last step), "springs", "playing", "mesh_version"}``.
        """
        with self._lock:
            force, contact = 0.0, {}
            for state in self.states:
                for key, value in (state.readings or {}).items():
                    if not key.endswith(".force") or value is None:
                        continue
                    f = float(value[0].double().norm())
                    name = key[: -len(".force")]
                    if "/" in name:
                        contact[name] = f
                    else:
                        force = max(force, f)
            return {
                "type": "stats",
                "t": float(self.states[0].t),
                "sim_hz": self._rate if self.playing else 0.0,
                "force": force,
                "contact": contact,
                "springs": self._springs,
                "playing": self.playing,
                "mesh_version": self.mesh_version,
            }
