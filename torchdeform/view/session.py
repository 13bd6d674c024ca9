r"""The simulation a live viewer drives: play, pause, reset, drag, a sphere tool, cuts, tissue terms.

:class:`ViewerSession` knows nothing of sockets or pages: a server calls :meth:`~ViewerSession.command`
with each message from the page (a dict from JSON), :meth:`~ViewerSession.advance` from its loop,
and sends :meth:`~ViewerSession.mesh` (after a topology change), :meth:`~ViewerSession.positions`
(every frame) and :meth:`~ViewerSession.stats`. Every method takes one lock, so the server may
step in one thread and answer messages in another.

Model and time step
    The scene's model (:meth:`~torchdeform.scene.Scene.build`) is copied and made editable
    (:meth:`~torchdeform.scene.topology.TopologySet.prepare`), so cuts and stiffness changes write
    into its tensors in place. The integrator is the scene's when it is symplectic Euler, damped
    Verlet or RK4, and symplectic Euler otherwise (explicit Euler has no stable step without
    damping; the implicit ones are too slow per step for a live view). The time step is
    ``min(scene dt, safety * bound / sqrt(2))`` with ``bound`` from
    :func:`~torchdeform.sim.stability.time_step_bound`: the factor ``1 / sqrt(2)`` leaves room for
    the tool's penalty stiffness ``k_t = m_min G / 4`` (``G``: the Gershgorin bound on
    ``omega_max^2``, at most about three times the true ``Lk``; ``m_min`` the lightest free node's
    mass), whose own rate ``k_t / m`` stays below ``Lk``, so ``omega_max^2`` with the tool is at
    most ``2 Lk``. A tissue-term change
    recomputes both; a cut only removes stiffness and keeps them. A step that leaves a non-finite
    value is undone and the time step halved (the body never blows up on screen).

Surface
    A scene with embedded surfaces (``scene.embedded``: the smooth label surfaces of a
    ``[grid] labels`` body, :mod:`torchdeform.scene.anatomy`) is drawn as those surfaces: each an
    :class:`~torchdeform.mesh.embed.EmbeddedSurface`, whose vertices are the trilinear interpolation
    of the node positions at their rest cell (:meth:`~torchdeform.mesh.embed.EmbeddedSurface.positions`,
    one sparse ``(V, N)`` product per frame). A cut splits them along the blade's plane (at rest,
    :meth:`~torchdeform.mesh.embed.EmbeddedSurface.cut`), each side then following its own nodes;
    where that is not possible (a plane along the skin) the lattice surface below is drawn instead,
    until a reset.

    Otherwise the page draws the closed surface of every piece of the lattice
    (:func:`~torchdeform.topology.cut_surfaces`: connected components, each split by the plane of
    every blade that cut something, so a cut's faces show). Its vertices are a fixed linear function
    of the node positions: marching tetrahedra puts each vertex at fractional node indices ``q``; the
    vertex is the trilinear interpolation ``T`` at ``q`` of the piece's own positions
    ``x_L = X + E (x - X)``, where ``E`` extends the piece's displacement one layer beyond it (the
    linear extrapolation of :func:`~torchdeform.topology.extend_displacement`; every cell a vertex
    reads lies within that layer). So ``vertices = rest + (T E) (x - X)``
    (:func:`~torchdeform.topology.surfaces.surface_map`), one sparse ``(V, N)`` product per frame,
    exactly the vertices :func:`~torchdeform.topology.cut_surfaces` computes (to float32 rounding).

    Either surface shares its vertices between its triangles: the page shades it smoothly with
    per-vertex normals it computes from the positions (area-weighted, as
    :meth:`~torchdeform.mesh.embed.EmbeddedSurface.normals` does).

Texture
    Every vertex is coloured once (after a topology change) by the solid texture at its rest position,
    its material coordinates (:func:`~torchdeform.texture.mapping.vertex_colours`, the node colouring
    of the animation and ``textured.png``): the scene's ``[texture]``
    (:func:`~torchdeform.scene.run.scene_texture`, seams blended as the section says), else the
    procedural liver of the animation (``liver:64``) with its seams not blended (blending a large
    body's texture takes tens of seconds).

Tools
    The scene's ``[[tools]]`` are drawn where they are: each tool's triangles in its own frame
    (:func:`~torchdeform.interact.meshes.tool_surface` of its shape, sent once) and, every frame,
    its pose at the simulated time ``t``: position ``c`` and rotation ``R``
    (:meth:`~torchdeform.interact.tools.Tool.frame`), a vertex ``p`` of its own frame drawn at
    ``c + R p``. A half-space has no finite surface and is not drawn.

Endoscope
    A scene with ``[camera]`` (and so ``[volume]``) loads its volume once
    (:func:`~torchdeform.scene.camera.load_scene_endoscope`); :meth:`~ViewerSession.endoscope`
    renders what the endoscope riding its tool sees of the current state, by the same per-frame
    function as the run's ``endoscope.gif`` (:meth:`~torchdeform.scene.camera.SceneEndoscope.render`:
    the camera's pose from the tool at the simulated time, the node offsets of the current positions,
    the other tools), plus the viewer's sphere tool when placed. Looking along the motion, the view
    before the tool first moves is the first direction it moves in over the scene's run (its
    ``steps``); a reset restores it. A scene without ``[camera]`` loads and renders nothing.

Messages (JSON objects; any other key, type or value raises ``ValueError`` with one line, and
nothing changes)
    ``{"cmd": "play"}``, ``{"cmd": "pause"}``, ``{"cmd": "reset"}`` (rest state, the scene's
    model, no tool, no drag, the initial terms); ``{"cmd": "drag", "vertex": i, "target": [d, h,
    w]}``: the free node of vertex ``i``'s piece (for an embedded surface: the piece of the node
    that weighs most in the vertex) nearest to the vertex (rest positions) is held at the target
    (m) from the next step on, ``{"cmd": "release"}`` lets it go; ``{"cmd": "tool",
    "position": [d, h, w] | null}``: the sphere tool (radius :attr:`~ViewerSession.tool_radius`,
    penalty contact) placed or removed; ``{"cmd": "cut", "origin": [..], "u": [..], "v": [..]}``:
    a parallelogram blade (:class:`~torchdeform.topology.Blade`) cuts the springs it crosses at
    the current positions; ``{"cmd": "term", "name": "consistency", "value": c}``, ``c`` in
    ``[0, 10]``: the body's consistency, Young's modulus ``E(c)`` from the fuzzy tissue library
    (:func:`~torchdeform.scene.mass_spring.tissue_moduli`), every spring's stiffness scaled by
    ``E(c) / E_0`` (``E_0``: the scene's modulus, ``lattice_modulus * median k``; for a uniform
    body ``k = E(c) / lattice_modulus``). Points must lie within twice the body's size of it.

Outputs
    :meth:`~ViewerSession.mesh` (a dict for JSON: faces, colours, the tools' triangles) and
    :meth:`~ViewerSession.positions` (bytes: vertex positions, then the tools' poses); their layouts
    are in their docstrings and :func:`frame_size` gives the size of the second.

Shapes: node positions ``(1, 3, D, H, W)`` (m); vertex positions ``(V, 3)`` in the axis order
``(D, H, W)``.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import torch

from ..errors import ConfigError
from ..interact import Capsule, PenaltyContact, Sphere, Tool
from ..interact.reactions import report_momentum
from ..scene.mass_spring import Scene, lattice_modulus, tissue_moduli
from ..scene.topology import TopologySet
from ..sim.integrators import SymplecticEuler
from ..sim.stability import gershgorin_omega2, time_step_bound
from ..topology import Blade, components, cut, sides
from ..topology.masks import alive, full
from ..topology.surfaces import FrameSurface

__all__ = ["ViewerSession", "TERM_RANGE", "DEFAULT_TEXTURE", "frame_size", "tool_parts", "tool_poses"]

#: the range of the ``consistency`` term (the input of the fuzzy tissue system)
TERM_RANGE = (0.0, 10.0)
#: the texture of a scene without ``[texture]`` (a ``[texture]`` spec): the animation's procedural
#: liver, its seams not blended (a large body's blend takes tens of seconds)
DEFAULT_TEXTURE = {"exemplar": "liver:64", "block": None, "seed": 0, "voxel": None, "seams": "none"}
#: the integrators the session keeps from a scene (others run with symplectic Euler)
_KEPT = ("symplectic", "verlet", "rk4")
_TOOL, _DRAG = "viewer_tool", "viewer_drag"
_KEYS = {
    "play": (),
    "pause": (),
    "reset": (),
    "release": (),
    "drag": ("vertex", "target"),
    "tool": ("position",),
    "cut": ("origin", "u", "v"),
    "term": ("name", "value"),
}


def tool_parts(tools) -> list:
    """``[(tool, message part)]``: each drawable tool and its triangles in its own frame (metres).

    A part is ``{"name", "vertices" (flat, 3 per vertex, m), "faces" (flat, 3 per triangle),
    "smooth", "color"}`` (:meth:`ViewerSession.mesh`'s ``tools``); a half-space is left out.

    Example:
        >>> from torchdeform.interact import Sphere, Tool
        >>> [(t.name, p["smooth"], len(p["faces"]) % 3) for t, p in tool_parts([Tool(Sphere(0.01), position=(0, 0, 0), name="s")])]
        [('s', True, 0)]
    """
    from ..interact.meshes import tool_surface
    from ..scene.animation import TOOL_COLOUR

    out = []
    for tool in tools:
        mesh = tool_surface(Tool(tool.shape, position=(0.0, 0.0, 0.0)), 0.0)
        if mesh is None:  # a half-space: no finite surface
            continue
        v, f = mesh
        part = {
            "name": tool.name,
            "vertices": np.round(v, 7).reshape(-1).tolist(),
            "faces": f.reshape(-1).tolist(),
            "smooth": isinstance(tool.shape, (Sphere, Capsule)),
            "color": list(TOOL_COLOUR),
        }
        out.append((tool, part))
    return out


def tool_poses(tools, t: float) -> np.ndarray:
    """float64 ``(T, 12)``: each tool's position ``c`` (m) and rotation ``R`` (row-major) at time ``t`` (s).

    Example:
        >>> from torchdeform.interact import Sphere, Tool
        >>> tool_poses([Tool(Sphere(0.01), position=(0.01, 0.02, 0.03))], 0.0)[0, :6].tolist()
        [0.01, 0.02, 0.03, 1.0, 0.0, 0.0]
    """
    like = torch.zeros(1, 3, dtype=torch.float64)
    out = np.zeros((len(tools), 12))
    for k, tool in enumerate(tools):
        c, R = tool.frame(float(t), like)
        out[k, :3] = c.reshape(-1, 3)[0].detach().double().cpu().numpy()
        out[k, 3:] = np.eye(3).reshape(-1) if R is None else R[0].detach().double().cpu().numpy().reshape(-1)
    return out


def frame_size(mesh: dict) -> int:
    """The bytes of a frame (:meth:`ViewerSession.positions`) of the surface a :meth:`ViewerSession.mesh` describes.

    ``4 * (3 V + 12 T)``: float32 positions of its ``V`` vertices, then a pose (12 values) per drawn tool.

    Example:
        >>> frame_size({"vertices": 10, "tools": [{}, {}]}), frame_size({"vertices": 10})
        (216, 120)
    """
    return 4 * (3 * int(mesh["vertices"]) + 12 * len(mesh.get("tools", ())))


@functools.lru_cache(maxsize=4)
def _exemplar(spec: str, seed: int) -> torch.Tensor:
    """A procedural exemplar ``(3, E, E, E)``, made once per process (a second or more each)."""
    from ..texture.exemplar import exemplar_from

    return exemplar_from(spec, seed=seed)


# ------------------------------------------------------------------ a node held at a target
class _Hold:
    """An interaction that puts one node at a target after every step (the viewer's drag).

    Reports ``viewer_drag.force`` ``(B, 3)``: the force the tissue pulls the held node with (N).
    """

    eager_only = True

    def __init__(self, node_mask: torch.Tensor, target: torch.Tensor):
        self.mask, self.target = node_mask, target  # (1, 1, D, H, W) bool, (1, 3, 1, 1, 1)

    def force(self, model, x, v, t):
        """Holding adds no force."""
        return None

    def project(self, model, x, v, t, dt, *, readings=None):
        """The held node at the target, at rest; its velocity change reported as a force."""
        x = torch.where(self.mask, self.target, x)
        v1 = torch.where(self.mask, torch.zeros_like(v), v)
        report_momentum(readings, _DRAG, model.mass, v1 - v, x, self.target, dt)
        return x, v1


# ------------------------------------------------------------------ checks of the messages
def _fail(text: str):
    raise ValueError(text)


def _number(value, key: str, lo=-math.inf, hi=math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(f"{key}: expected a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        _fail(f"{key}: expected a finite number, got {value!r}")
    if not lo <= v <= hi:
        _fail(f"{key}: expected a number in [{lo:g}, {hi:g}], got {v:g}")
    return v


def _point(value, key: str, lo, hi) -> tuple:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        _fail(
            f"{key}: expected three numbers [d, h, w] in metres, got {type(value).__name__}"
            + (f" of length {len(value)}" if isinstance(value, (list, tuple)) else "")
        )
    return tuple(_number(c, f"{key}[{i}]", lo[i], hi[i]) for i, c in enumerate(value))


# ------------------------------------------------------------------ the session
def run_for(session, seconds: float, try_step) -> int:
    """While ``session.playing``, call ``try_step()`` for about ``seconds`` of wall time (at least once).

    Each call holds the session's lock and runs without autograd; the session's step rate
    (``session._rate``, steps per second) follows the measured one. Returns the number of steps.
    """
    seconds = _number(seconds, "seconds", 0.0)
    start, steps = time.perf_counter(), 0
    while True:
        with session._lock, torch.no_grad():
            if not session.playing:
                break
            try_step()
        steps += 1
        if time.perf_counter() - start >= seconds:
            break
    elapsed = time.perf_counter() - start
    if steps:
        rate = steps / max(elapsed, 1e-9)
        session._rate = rate if not session._rate else 0.7 * session._rate + 0.3 * rate
    return steps


class ViewerSession:
    """A mass-spring scene stepped live, with the viewer's drag, sphere tool, cuts and tissue slider.

    See the module docstring for the messages, the time step and the surface.

    Args:
        scene: a mass-spring :class:`~torchdeform.scene.Scene` (:func:`~torchdeform.scene.load_scene`,
            :func:`~torchdeform.cube_scene`).
        device: where to simulate (default: the scene's, else the CPU).
        max_nodes: refuse (``ValueError``) a grid with more nodes than this (None: any size).
        texture: the :class:`~torchdeform.texture.SolidTexture` the surfaces are coloured with
            (default: the scene's ``[texture]``, else :data:`DEFAULT_TEXTURE`; module docstring).

    Attributes:
        model: the live :class:`~torchdeform.sim.model.Model` (editable: cuts and terms change it in place).
        state: the live :class:`~torchdeform.sim.model.State` ``(1, 3, D, H, W)``.
        mesh_version: incremented whenever the surface's topology changes (a cut, a reset after one).
        playing: whether :meth:`advance` steps (True at the start).
        dt: the time step (s).
        tool_radius: the sphere tool's radius (m): three node spacings (the largest).
        labels: int ``(D, H, W)``: the piece of every node whose surface is drawn (negative: none).
        texture: the solid texture the vertices are coloured with.
        surface: ``"embedded"`` (the scene's embedded surfaces are drawn) or ``"lattice"``.
        camera: the endoscope pane of a scene with ``[camera]`` (:meth:`mesh`'s ``camera``), else None.

    Examples:
        >>> import torchdeform as td
        >>> from torchdeform.view.session import ViewerSession
        >>> s = ViewerSession(td.cube_scene())                       # an 11^3 cube, base fixed
        >>> m = s.mesh()
        >>> m["type"], m["surface"], len(m["faces"]) % 3, len(m["colors"]) == 3 * m["vertices"], m["tools"]
        ('mesh', 'lattice', 0, True, [])
        >>> len(s.positions()) == 4 * 3 * m["vertices"] == frame_size(m)
        True
        >>> s.command({"cmd": "tool", "position": [0.011, 0.005, 0.005]})     # pressed into the top
        >>> s.command({"cmd": "cut", "origin": [0.0055, -0.001, -0.001], "u": [0, 0.012, 0], "v": [0, 0, 0.006]})
        >>> s.mesh_version, s.advance(0.0) >= 1, s.stats()["force"] > 0
        (1, True, True)
        >>> try:
        ...     s.command({"cmd": "term", "name": "consistency", "value": 11})
        ... except ValueError as e:
        ...     print(e)
        value: expected a number in [0, 10], got 11
    """

    def __init__(self, scene, *, device=None, max_nodes=None, texture=None):
        if not isinstance(scene, Scene):
            _fail(f"scene: expected a mass-spring Scene, got {type(scene).__name__}")
        grid = scene.grid
        if max_nodes is not None and grid.num_nodes > int(max_nodes):
            _fail(f"scene: the grid has {grid.num_nodes} nodes, more than max_nodes = {int(max_nodes)}")
        self.scene, self.grid = scene, grid
        self._lock = threading.Lock()
        self._base = scene.build(device=device)
        self.integrator = scene.integrator if scene.integrator.name in _KEPT else SymplecticEuler()
        with torch.no_grad():
            X = self._base.X[0]
            nodes = grid.nodes().to(X.device)
            pts = X[:, nodes]
            self._lo, self._hi = pts.amin(1).tolist(), pts.amax(1).tolist()
            size = max(max(h - lo for lo, h in zip(self._lo, self._hi)), max(grid.spacing))
            self._reach = (tuple(lo - 2 * size for lo in self._lo), tuple(h + 2 * size for h in self._hi))
            self._span = 4 * size
            self.tool_radius = 3.0 * max(grid.spacing)
            self._k0 = full(self._base, self._base.stiffness).clone()  # the scene's springs
            k = self._k0[(self._k0 > 0) & grid.spring_mask(device=self._k0.device)]
            self._lattice = lattice_modulus(grid)
            self._E0 = float(k.double().median()) * self._lattice if k.numel() else 0.0
        self._c0 = self._scene_consistency() if self._E0 > 0 else None
        self.texture = texture if texture is not None else self._scene_texture()
        self._embedded = self._embedded_surfaces()
        self._tools = self._tool_meshes()
        self._scope, self.camera = self._scene_endoscope()
        self._scope_lock = threading.Lock()  # one endoscope render at a time (it keeps the held view)
        self._timing = None  # (dt, tool stiffness) of the scene's model
        self._reset()
        self._retime()
        self._timing = (self.dt, self._tool_k)
        if self._scope is not None:  # the direction before the tool first moves, over the scene's run
            self._scope.prime(np.linspace(0.0, max(int(self.scene.steps), 1) * self.dt, 1001))
            self._held = self._scope.held

    # ---------------------------------------------------------- set-up
    def _scene_consistency(self) -> float:
        """The scene's consistency: its ``[material] tissue`` if it has one, else from its modulus."""
        from ..fuzzy.presets import load_preset, tissues

        try:
            import tomllib
        except ImportError:  # Python 3.10
            import tomli as tomllib
        try:
            tissue = tomllib.loads(self.scene.source.text or "").get("material", {}).get("tissue")
        except (tomllib.TOMLDecodeError, AttributeError):
            tissue = None
        if isinstance(tissue, (int, float)) and not isinstance(tissue, bool) and 0 <= tissue <= 10:
            return float(tissue)
        if isinstance(tissue, str):
            library, var = tissues(), load_preset("tissue_si").inputs[0]
            if tissue in library:
                return float(library[tissue]["consistency"])
            if tissue in var.term_names:
                return float(var.terms[tissue].peak())
        grid = np.linspace(*TERM_RANGE, 1001)  # E(c) is non-decreasing: invert it
        E = np.asarray(tissue_moduli(grid.tolist()))
        i = int(np.searchsorted(E, self._E0))
        if i == 0 or i == len(E):
            return float(grid[min(i, len(E) - 1)])
        a, b = E[i - 1], E[i]
        return float(grid[i - 1] + (grid[i] - grid[i - 1]) * (self._E0 - a) / (b - a))

    def _scene_texture(self):
        """The scene's ``[texture]`` (:func:`~torchdeform.scene.run.scene_texture`), else :data:`DEFAULT_TEXTURE`."""
        from ..scene.run import scene_texture

        spec = self.scene.texture
        if spec is None:
            spec = {**DEFAULT_TEXTURE, "exemplar": _exemplar(DEFAULT_TEXTURE["exemplar"], DEFAULT_TEXTURE["seed"])}
        return scene_texture(spec, self.grid)[0]

    def _embedded_surfaces(self) -> list | None:
        """``[(name, EmbeddedSurface)]`` of ``scene.embedded`` on the model's dtype and device, or None."""
        if not self.scene.embedded:
            return None
        from ..scene.run import embedded_surfaces

        base = self._base
        return list(embedded_surfaces(self.scene, self.grid, dtype=base.dtype, device=base.device).items())

    def _tool_meshes(self) -> list:
        """``[(tool, message part)]``: each drawable scene tool and its triangles in its own frame (metres)."""
        return tool_parts(self.scene.tools.tools if self.scene.tools is not None else ())

    def _scene_endoscope(self) -> tuple:
        """``(endoscope, pane)``: the scene's endoscope, its volume loaded, and the pane for :meth:`mesh`.

        :class:`~torchdeform.scene.camera.SceneEndoscope` and :meth:`mesh`'s ``camera``, or
        ``(None, None)`` without ``[camera]``.
        """
        if self.scene.camera_view is None:
            return None, None
        from ..scene.camera import load_scene_endoscope

        scope = load_scene_endoscope(self.scene)
        assert scope is not None
        spec = self.scene.camera_view
        return scope, {"kind": spec["kind"], "tool": spec["tool"], "size": list(scope.size), "fov": spec["fov"]}

    def _reset(self) -> None:
        """The scene's model (a fresh editable copy, fresh scene tools), at rest; no tool, no drag."""
        model = TopologySet(self.grid).prepare(self._base)
        scene_tools = self.scene.tools.interactions() if self.scene.tools is not None else self._base.interactions
        self._scene_interactions = list(scene_tools)
        model.interactions = list(self._scene_interactions)
        self.model = model
        self.state = model.rest_state()
        self.playing = True
        self._tool = self._contact = self._hold = None
        self._tool_pos = torch.zeros(3, dtype=model.dtype, device=model.device)
        self._drag_node = None
        self._blades = []
        self._consistency = self._c0
        self._rate = 0.0
        self._springs = int(alive(model)[0].sum())
        if self._timing is not None:
            self.dt, self._tool_k = self._timing
        if self._scope is not None and self._timing is not None:  # the view as at the start
            self._scope.reset(held=self._held)
        self._build_surface()

    def _retime(self) -> None:
        """Time step and tool stiffness for the current springs (module docstring)."""
        model = self.model
        saved, model.interactions = model.interactions, list(self._scene_interactions)
        try:
            with torch.no_grad():
                bound = time_step_bound(model, integrator=self.integrator)
                lk = gershgorin_omega2(model) / 4
        finally:
            model.interactions = saved
        shape = (1, 1, *self.grid.shape)
        free = model.free.expand(shape) > 0 if model.free is not None else torch.ones(shape, dtype=torch.bool)
        mass = model.mass.expand(shape)[free.to(model.mass.device)]
        m_min = float(mass.min()) if mass.numel() else 1.0
        self._tool_k = max(lk, 1e-30) * m_min
        stable = self.scene.safety * bound / math.sqrt(2) if math.isfinite(bound) else math.inf
        given = self.scene.dt if self.scene.dt != "auto" else math.inf
        self.dt = float(min(given, stable))
        if not (0 < self.dt < math.inf):
            _fail("scene: no finite, positive stable time step for this body")
        if self._contact is not None:
            self._contact.stiffness = self._tool_k

    def _pieces(self) -> torch.Tensor:
        """Labels ``(D, H, W)``: the components, each split by the plane of every blade that cut (rest side)."""
        labels, _ = components(self.model)
        for blade in self._blades:
            side = (sides(self.model.X, blade)[0, 0] > 0).to(labels.device)
            split = torch.where(labels >= 0, labels * 2 + side, labels)
            ids = torch.unique(split[split >= 0])
            labels = torch.where(split >= 0, torch.searchsorted(ids, split), split)
        return labels

    def _build_surface(self, blade: Blade | None = None) -> None:
        """The surface drawn for the current pieces and its vertex colours; ``blade``: the cut that changed them."""
        from ..texture.mapping import vertex_colours

        self.labels = self._pieces().cpu()
        parts = self._embedded if blade is None else self._cut_parts(blade)
        self._parts = parts
        if parts is not None:
            self.surface, self._surface = "embedded", None
            sizes = [s.num_vertices for _, s in parts]
            starts = np.cumsum([0] + sizes[:-1])
            rest = torch.cat([s.rest_vertices for _, s in parts]).double().cpu().numpy()
            faces = np.concatenate([s.faces.cpu().numpy() + k for (_, s), k in zip(parts, starts)])
            # the piece of a vertex: that of the node weighing most in it (its rest cell is of one piece)
            heaviest = torch.cat([s.corners.gather(1, s.weights.argmax(1, keepdim=True)) for _, s in parts])
            vlabel = self.labels.reshape(-1)[heaviest.view(-1).cpu()].numpy()
            self._part_info = [{"name": name, "vertices": n} for (name, _), n in zip(parts, sizes)]
        else:
            self.surface = "lattice"
            self._surface = FrameSurface(
                self.grid, labels=self.labels.numpy(), dtype=self.model.dtype, device=self.model.device
            )
            surf = self._surface.source
            rest, faces, vlabel = surf["rest"], surf["faces"], surf["label"]
            self._part_info = [{"name": "lattice", "vertices": len(rest)}]
        self._rest_np, self._faces, self._vlabel = rest, faces, vlabel
        colours = vertex_colours(self.texture, SimpleNamespace(rest=rest)).clamp(0, 1)
        self._colours = (colours * 255 + 0.5).to(torch.uint8).numpy()
        self.mesh_version = getattr(self, "mesh_version", -1) + 1

    def _cut_parts(self, blade: Blade) -> list | None:
        """The drawn embedded surfaces split where the blade cut the lattice, or None (draw the lattice's)."""
        if self._parts is None:
            return None
        try:
            return [(name, s.cut_patches(blade, x=self.state.x)) for name, s in self._parts]
        except ConfigError:  # a plane along the skin: no cell of a side's own nodes near some vertex
            return None

    def _set_interactions(self) -> None:
        extra = [c for c in (self._contact, self._hold) if c is not None]
        self.model.interactions = self._scene_interactions + extra

    # ---------------------------------------------------------- messages
    def command(self, msg: dict) -> None:
        """Apply one message from the page (module docstring); ``ValueError`` for anything invalid, nothing changed.

        Args:
            msg: the message, e.g. ``{"cmd": "drag", "vertex": 12, "target": [0.01, 0.005, 0.005]}``.
        """
        if not isinstance(msg, dict):
            _fail(f"message: expected an object with a cmd, got {type(msg).__name__}")
        cmd = msg.get("cmd")
        if not isinstance(cmd, str) or cmd not in _KEYS:
            _fail(f"cmd: expected one of {', '.join(_KEYS)}, got {cmd!r}"[:200])
        extra = set(msg) - {"cmd", *_KEYS[cmd]}
        missing = [k for k in _KEYS[cmd] if k not in msg]
        if extra or missing:
            _fail(
                f"{cmd}: expected the keys {', '.join(('cmd',) + _KEYS[cmd])}"
                + (f", unknown {', '.join(sorted(map(str, extra)))}" if extra else "")
                + (f", missing {', '.join(missing)}" if missing else "")
            )
        with self._lock, torch.no_grad():
            getattr(self, f"_cmd_{cmd}")(msg)

    def _cmd_play(self, msg):
        self.playing = True

    def _cmd_pause(self, msg):
        self.playing = False

    def _cmd_reset(self, msg):
        changed, version = bool(self._blades), self.mesh_version
        self._reset()
        self.mesh_version = version + 1 if changed else version

    def _cmd_release(self, msg):
        self._hold, self._drag_node = None, None
        self._set_interactions()

    def _cmd_drag(self, msg):
        i = msg["vertex"]
        V = len(self._rest_np)
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < V:
            _fail(f"vertex: expected a vertex index in [0, {V}), got {i!r}"[:200])
        target = _point(msg["target"], "target", *self._reach)
        free = self.labels == int(self._vlabel[i])
        if self.model.free is not None:
            free = free & (self.model.free[0, 0].cpu() > 0)
        if not bool(free.any()):
            _fail(f"vertex: vertex {i} belongs to a piece with no free node")
        X = self.model.X[0].cpu().double()
        r = torch.as_tensor(self._rest_np[i]).view(3, 1, 1, 1)
        d = ((X - r) ** 2).sum(0)
        d = torch.where(free, d, torch.full_like(d, math.inf))
        node = int(d.argmin())
        mask = torch.zeros(math.prod(self.grid.shape), dtype=torch.bool)  # every grid point, body or not
        mask[node] = True
        dev, dtype = self.model.device, self.model.dtype
        self._hold = _Hold(
            mask.view(1, 1, *self.grid.shape).to(dev), torch.tensor(target, dtype=dtype, device=dev).view(1, 3, 1, 1, 1)
        )
        self._drag_node = tuple(int(c) for c in np.unravel_index(node, self.grid.shape))
        self._set_interactions()

    def _cmd_tool(self, msg):
        p = msg["position"]
        if p is None:
            self._tool = self._contact = None
        else:
            p = _point(p, "position", *self._reach)
            self._tool_pos.copy_(torch.tensor(p, dtype=self._tool_pos.dtype))
            if self._tool is None:
                self._tool = Tool(Sphere(self.tool_radius), position=self._tool_pos, name=_TOOL)
                self._contact = PenaltyContact(self._tool, stiffness=self._tool_k)
        self._set_interactions()

    def _cmd_cut(self, msg):
        o = _point(msg["origin"], "origin", *self._reach)
        span = (tuple(-self._span for _ in range(3)), tuple(self._span for _ in range(3)))
        u, v = _point(msg["u"], "u", *span), _point(msg["v"], "v", *span)
        try:
            blade = Blade(o, u, v)
        except ValueError as e:
            _fail(f"cut: {e}".splitlines()[0])
        n = cut(self.model, self.state.x, blade)
        if n:
            self._blades.append(blade)
            self._springs -= n
            self._build_surface(blade)

    def _cmd_term(self, msg):
        name = msg["name"]
        if name != "consistency" or self._c0 is None:
            _fail(
                f"name: expected one of {', '.join(self._terms()) or 'no term (this body has no springs)'}, "
                f"got {name!r}"[:200]
            )
        value = _number(msg["value"], "value", *TERM_RANGE)
        factor = tissue_moduli([value])[0] / self._E0
        k = self.model.stiffness
        new = torch.where(k != 0, self._k0 * factor, torch.zeros_like(k))
        old, old_c = k.clone(), self._consistency
        k.copy_(new)
        try:
            self._retime()
        except ValueError:
            k.copy_(old)
            self._consistency = old_c
            raise
        self._consistency = value

    def _terms(self) -> dict:
        if self._c0 is None:
            return {}
        return {"consistency": {"value": self._consistency, "min": TERM_RANGE[0], "max": TERM_RANGE[1]}}

    # ---------------------------------------------------------- stepping
    def advance(self, seconds: float) -> int:
        """If playing, step for about ``seconds`` of wall time (at least one step); the number of steps.

        Args:
            seconds: wall time to spend (s), >= 0.
        """
        return run_for(self, seconds, self._try_step)

    def _try_step(self) -> None:
        new = self.integrator.step(self.model, self.state, self.dt)
        if bool(torch.isfinite(new.x).all()) and bool(torch.isfinite(new.v).all()):
            self.state = new
        else:  # undo the step, halve dt
            self.dt *= 0.5

    # ---------------------------------------------------------- outputs
    def mesh(self) -> dict:
        """The surface to draw (after a topology change): faces, colours, rest bounds, terms, the tools' triangles.

        Returns:
            ``{"type": "mesh", "version", "surface" ("embedded" or "lattice"), "vertices" (V),
            "faces" (flat, 3 per triangle, counter-clockwise seen from outside), "colors" (flat, 3
            per vertex: the texture's sRGB at the vertex's rest position, integers 0-255), "parts"
            (``[{"name", "vertices"}]``: the surfaces, their vertices consecutive in this order),
            "bounds" ([[min d, h, w], [max d, h, w]] of the rest surface, m), "terms",
            "tool_radius" (m, the page's sphere tool), "tools"}``. ``tools`` lists the scene's drawn
            tools, in the order of their poses in a frame: ``{"name", "vertices" (flat, 3 per vertex,
            m, the tool's own frame), "faces" (flat, 3 per triangle, outward), "smooth" (shade with
            vertex normals, else flat), "color" ([r, g, b] in [0, 1], sRGB)}``. A scene with ``[camera]``
            adds ``"camera": {"kind", "tool", "size" ([h, w] pixels), "fov" (degrees)}``: the endoscope
            pane's (:meth:`endoscope`).
        """
        with self._lock:
            rest = self._rest_np
            bounds = [rest.min(0).tolist(), rest.max(0).tolist()] if len(rest) else [self._lo, self._hi]
            return {
                "type": "mesh",
                "version": self.mesh_version,
                "surface": self.surface,
                "vertices": len(rest),
                "faces": self._faces.reshape(-1).tolist(),
                "colors": self._colours.reshape(-1).tolist(),
                "parts": [dict(p) for p in self._part_info],
                "bounds": bounds,
                "terms": self._terms(),
                "tool_radius": self.tool_radius,
                "tools": [part for _, part in self._tools],
                **({"camera": dict(self.camera)} if self.camera is not None else {}),
            }

    def _vertices(self) -> torch.Tensor:
        """The drawn surface's vertex positions now ``(V, 3)`` (m); under the lock."""
        x = self.state.x[0]
        if self._parts is not None:
            return torch.cat([s.positions(x) for _, s in self._parts])
        assert self._surface is not None  # the lattice's surface is built whenever no embedded one is drawn
        return self._surface.vertices(x)

    def _poses(self) -> np.ndarray:
        """float64 ``(T, 12)``: each drawn tool's position ``c`` (m) and rotation ``R`` (row-major) now."""
        return tool_poses([tool for tool, _ in self._tools], float(self.state.t))

    def positions(self) -> bytes:
        """A frame: the surface's vertex positions and the tools' poses now, float32 little-endian.

        ``V * 3`` vertex positions (m, axes D, H, W; :meth:`mesh` lists the vertices), then per drawn
        tool (:meth:`mesh`'s ``tools``, in order) 12 values: its position ``c`` (3, m) and rotation
        ``R`` (3 x 3, row-major) at the simulated time, a vertex ``p`` of the tool's own frame being at
        ``c + R p``. :func:`frame_size` bytes in all.
        """
        with self._lock, torch.no_grad():
            v = self._vertices().to(torch.float32).cpu().numpy().reshape(-1)
            if self._tools:
                v = np.concatenate([v, self._poses().reshape(-1).astype(np.float32)])
            return v.astype("<f4", copy=False).tobytes()

    def vertices(self) -> torch.Tensor:
        """The surface's vertex positions now, ``(V, 3)`` float32 (m): the first part of :meth:`positions`."""
        with self._lock, torch.no_grad():
            return self._vertices().to(torch.float32).cpu()

    def endoscope(self) -> tuple[float, np.ndarray] | None:
        """The endoscope's view of the current state: ``(t, image)``, or None for a scene without ``[camera]``.

        The state is copied under the lock and rendered outside it (the simulation goes on meanwhile):
        :meth:`~torchdeform.scene.camera.SceneEndoscope.render` at the simulated time ``t`` (s) of the
        node positions now, float32; the viewer's sphere tool, when placed, is drawn too.

        Returns:
            ``t`` and the image, uint8 RGB ``(h, w, 3)`` (``[camera] size``), 0 outside the round mask.

        Raises:
            ConfigError: the lens outside the volume (``inside = "require"``).
        """
        if self._scope is None:
            return None
        with self._lock, torch.no_grad():
            x, X, t = self.state.x.detach().cpu().clone(), self.model.X.detach().cpu(), float(self.state.t)
            extra = [(self._tool_pos.tolist(), self.tool_radius)] if self._tool is not None else []
        with self._scope_lock:
            return t, self._scope.render(t, x, X, extra=extra)

    def stats(self) -> dict:
        """Time, speed, forces and state for the page.

        Returns:
            ``{"type": "stats", "t" (s), "sim_hz" (steps per wall second, recent; 0 while paused),
            "force" (N, the sphere tool's reaction), "drag_force" (N), "springs" (alive),
            "playing", "mesh_version"}``.
        """
        with self._lock:
            readings = self.state.readings or {}

            def magnitude(name):
                f = readings.get(f"{name}.force")
                return float(f[0].double().norm()) if f is not None else 0.0

            return {
                "type": "stats",
                "t": float(self.state.t),
                "sim_hz": self._rate if self.playing else 0.0,
                "force": magnitude(_TOOL) if self._tool is not None else 0.0,
                "drag_force": magnitude(_DRAG) if self._hold is not None else 0.0,
                "springs": self._springs,
                "playing": self.playing,
                "mesh_version": self.mesh_version,
            }
