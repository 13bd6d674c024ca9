r"""Tools in mass-spring scene files, and what a run reports about them.

Reading (:func:`tools_section`, :func:`strain_limit_section`, :func:`palpation_option`): the
``[[tools]]`` tables become :class:`~torchdeform.interact.tools.Tool` s with their contact
responses and grasps, ``[strain_limit]`` a :class:`~torchdeform.interact.strain.StrainLimit`; a
:class:`ToolSet` keeps them and builds fresh interaction objects for every run
(:meth:`ToolSet.interactions`), in the order strain limiting, contacts (one per tool, in file
order), grasps: contact comes after strain limiting so no node ends a step inside a tool, and a
grasp comes last so held nodes end every step exactly on the forceps.

Running (:class:`ToolRecorder`, :func:`tool_outputs`; the analysis of the series is
:mod:`torchdeform.interact.palpation`'s): every step's readings
(``State.readings["<name>.force"]``, ``(B, 3)`` N, the force the tissue exerts on the tool as
the hand feels it; ``.contacts``; ``.grasped``) of batch entry 0 are copied into one buffer on
the model's device, ``(steps, tools, 5)``, moved to the CPU once at the end. ``tool_outputs``
writes

* ``tools.npz``: the full per-step series, ``t`` ``(T,)`` s and per tool ``<name>.force``
  ``(T, 3)`` N, ``<name>.position`` ``(T, 3)`` m (the tool's path at those times),
  ``<name>.contacts`` and ``<name>.grasped`` ``(T,)``;
* the ``"tools"`` part of ``summary.json``: the same series averaged over blocks of
  ``ceil(T / 1000)`` steps (block means of the force: the impulse per time, so no spike of a single
  step is lost or exaggerated; times and positions at the block means), at most 1000 points;
  ``max_force_N`` the largest magnitude of that series; and the supports' reaction at the
  recorded frames (:func:`~torchdeform.interact.support_reaction`);
* ``forces.png``: per tool the force along its motion against its displacement, and the force
  magnitude over time;
* with ``[output] palpation``: the presses of one tool
  (:func:`~torchdeform.interact.palpation.palpation`), ``palpation.png`` and
  a ``"palpation"`` part of ``summary.json``.

Force along the motion: the tool works against the tissue along ``u``
(:func:`~torchdeform.interact.palpation.work_direction`: its directions of motion weighted by the
power it puts into the tissue; down for a probe pressing into a surface, up for forceps lifting
tissue). With ``p0`` its first position, the displacement is ``s = (p - p0) . u`` (m) and the
force along the motion ``-F . u`` (N): the tissue's resistance, positive when it pushes back
against the probe or pulls back on the forceps. Tools that do not move (a table) appear only in the
force-over-time panel.

Example:
    >>> from torchdeform.scene.reader import Source
    >>> text = '''
    ... [[tools]]
    ... name = "probe"
    ... shape = "sphere"
    ... radius = -0.003
    ... path = [[0.0, [0.02, 0.01, 0.01]], [0.1, [0.018, 0.01, 0.01]]]
    ... '''
    >>> probe = {"name": "probe", "shape": "sphere", "radius": 0.003, "friction": 0.3,
    ...          "path": [[0.0, [0.02, 0.01, 0.01]], [0.1, [0.018, 0.01, 0.01]]]}
    >>> tools = tools_section(Source(path="s.toml", text=text), [probe], base=".")
    >>> [type(c).__name__ for c in tools.interactions()], tools.names
    (['ProjectionContact'], ['probe'])
    >>> tools_section(Source(path="s.toml", text=text), [{**probe, "radius": -0.003}], base=".")
    Traceback (most recent call last):
    ...
    torchdeform.errors.ConfigError: s.toml:5: tools[0].radius: expected a positive number of metres, got -0.003
"""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigWarning
from ..interact.contact import DIRECTIONS, PenaltyContact, ProjectionContact
from ..interact.grasp import Grasp
from ..interact.palpation import block_means, palpation, plot_palpation, significant, work_direction
from ..interact.reactions import support_reaction
from ..interact.strain import StrainLimit
from ..interact.tools import Box, Capsule, HalfSpace, Sphere, Tool
from ..outputs import figure, save_figure
from ..sim.model import State
from .reader import SECTIONS, Source, Table, is_number

__all__ = [
    "SHAPE_KEYS",
    "CONTACTS",
    "ToolSet",
    "tools_section",
    "check_tool_reach",
    "strain_limit_section",
    "palpation_option",
    "ToolRecorder",
    "tool_outputs",
    "support_series",
    "tool_forces_at",
    "plot_forces",
    "MAX_POINTS",
]

#: size keys of each tool shape
SHAPE_KEYS = {
    "sphere": ("radius",),
    "capsule": ("radius", "half_length", "axis"),
    "box": ("half_extents",),
    "half_space": ("normal",),
    "mesh": ("file", "resolution"),
}
#: contact responses of a tool and their own keys
CONTACTS = {
    "projection": ("friction", "direction", "hold", "haptic_gain"),
    "penalty": ("stiffness", "damping"),
    "none": (),
}
#: most points of a series in summary.json
MAX_POINTS = 1000
_AXES = {"d": 0, "h": 1, "w": 2}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_WAYPOINTS = "waypoints [[t, [d, h, w]], ...] or [[t, [d, h, w], [rd, rh, rw]], ...] (s, m, rad)"


# ------------------------------------------------------------------ the tools of a scene
@dataclass(eq=False, kw_only=True)
class ToolSet:
    """The tools of a scene, their contact responses and grasps, and strain limiting.

    Args:
        tools: the :class:`~torchdeform.interact.tools.Tool` s (unique names).
        contacts: per tool ``(kind, keyword arguments)``: ``"projection"``
            (:class:`~torchdeform.interact.ProjectionContact`), ``"penalty"``
            (:class:`~torchdeform.interact.PenaltyContact`) or ``"none"``.
        grasps: per tool the keyword arguments of :class:`~torchdeform.interact.Grasp`, or None.
        strain_limit: keyword arguments of :class:`~torchdeform.interact.StrainLimit`, or None.
        palpation: the name of the tool whose presses ``run_scene`` analyses, or None.

    Examples:
        >>> from torchdeform.interact import Sphere, Tool
        >>> probe = Tool(Sphere(0.003), position=(0.02, 0.01, 0.01), name="probe")
        >>> tools = ToolSet(tools=[probe], contacts=[("projection", {"friction": 0.5})], grasps=[None],
        ...                 strain_limit={"min_ratio": 0.8})
        >>> [type(c).__name__ for c in tools.interactions()]
        ['StrainLimit', 'ProjectionContact']
        >>> tools.interactions()[1] is tools.interactions()[1]      # fresh objects every call
        False
    """

    tools: list = field(default_factory=list)
    contacts: list = field(default_factory=list)
    grasps: list = field(default_factory=list)
    strain_limit: dict | None = None
    palpation: str | None = None
    #: per tool: ``start_inside = true`` (the tool may start inside the body)
    start_inside: list = field(default_factory=list)
    #: per tool: True when its table gives a ``path`` (else a ``position``)
    paths: list = field(default_factory=list)

    @property
    def names(self) -> list:
        """The tools' names, in file order."""
        return [tool.name for tool in self.tools]

    def interactions(self) -> list:
        """New interaction objects (contacts and grasps keep state between steps): strain limit, contacts, grasps."""
        out: list = [] if self.strain_limit is None else [StrainLimit(**self.strain_limit)]
        for tool, (kind, kwargs) in zip(self.tools, self.contacts):
            if kind == "projection":
                out.append(ProjectionContact(tool, **kwargs))
            elif kind == "penalty":
                out.append(PenaltyContact(tool, **kwargs))
        out += [Grasp(tool, **g) for tool, g in zip(self.tools, self.grasps) if g is not None]
        return out


def _shape(t: Table, kind: str, base: Path):
    for k in (k for keys in SHAPE_KEYS.values() for k in keys):
        if t.has(k) and k not in SHAPE_KEYS[kind]:
            raise t.fail(k, f'no {k} for shape = "{kind}" (its keys: {", ".join(SHAPE_KEYS[kind])})', got=t.data[k])
    metres = "a positive number of metres"
    if kind == "sphere":
        return Sphere(t.num("radius", metres, lo=0, lo_open=True))
    if kind == "capsule":
        axis = t.raw("axis", '"d", "h" or "w" (or 0, 1, 2): the grid axis of the shaft')
        if axis in _AXES:
            axis = _AXES[axis]
        if axis not in (0, 1, 2) or isinstance(axis, bool):
            raise t.fail("axis", '"d", "h" or "w" (or 0, 1, 2): the grid axis of the shaft', got=t.data["axis"])
        return Capsule(
            t.num("radius", metres, lo=0, lo_open=True),
            t.num("half_length", "a number of metres >= 0", lo=0),
            axis=axis,
        )
    if kind == "box":
        h = t.vec("half_extents", "three positive numbers [hd, hh, hw] in metres")
        if min(h) <= 0:
            raise t.fail("half_extents", "three positive numbers [hd, hh, hw] in metres", got=list(h))
        return Box(h)
    if kind == "half_space":
        normal = t.vec("normal", "three numbers [nd, nh, nw], the outward direction", default=(1.0, 0.0, 0.0))
        if not any(normal):
            raise t.fail("normal", "a non-zero direction [nd, nh, nw]", got=list(normal))
        return HalfSpace(normal=normal)
    try:  # mesh: the optional module, imported when used
        from ..interact.meshes import MeshShape
    except ImportError:  # pragma: no cover
        raise t.fail(
            "shape",
            "one of "
            + ", ".join(f'"{s}"' for s in SHAPE_KEYS if s != "mesh")
            + " (mesh tools need torchdeform.interact.meshes)",
            got="mesh",
        ) from None
    file = t.text("file", "a closed triangle mesh file (relative to the scene file; x, y, z = D, H, W in m)")
    resolution = t.integer(
        "resolution", "an integer >= 4 (distance-field points along the longest axis)", default=32, lo=4
    )
    with t.src.located(t.key("file"), keys={"mesh_shape.resolution": t.key("resolution")}):
        return MeshShape(Path(base) / file, resolution=resolution)


def _path(t: Table) -> list:
    v = t.data["path"]
    ok = (
        isinstance(v, list)
        and v
        and all(
            isinstance(w, list)
            and len(w) in (2, 3)
            and is_number(w[0])
            and all(isinstance(p, list) and len(p) == 3 and all(is_number(c) for c in p) for p in w[1:])
            for w in v
        )
    )
    if not ok or len({len(w) for w in v}) != 1:
        raise t.fail("path", _WAYPOINTS + ", all of one kind", got=v)
    return [tuple([float(w[0])] + [tuple(float(c) for c in p) for p in w[1:]]) for w in v]


def _grasp(t: Table, tool: Tool) -> dict:
    g = Table(t.src, t.key("grasp"), t.data["grasp"], ("close", "open", "margin"))
    close = g.num("close", "a time in seconds >= 0 when the jaws close", lo=0)
    opened = g.data.get("open")
    if (opened is not None and not (is_number(opened) or opened == math.inf)) or isinstance(opened, bool):
        raise g.fail("open", "a time in seconds after close (inf: never)", got=opened)
    kwargs = {"close": close, "open": opened, "margin": g.num("margin", "metres >= 0", default=0.0, lo=0)}
    keys = {"grasp": g.name, **{f"grasp.{k}": g.key(k) for k in ("close", "open", "margin")}}
    with t.src.located(g.name, keys=keys):
        Grasp(tool, **kwargs)  # its own checks: both times, open after close
    return kwargs


def tools_section(src: Source, items, base) -> ToolSet:
    """The :class:`ToolSet` of the ``[[tools]]`` tables ``items`` (``base``: the folder mesh files are in).

    Keys of a ``[[tools]]`` table: ``name`` (default ``tool1``, ``tool2``, ...; unique), ``shape``
    (``"sphere"``, ``"capsule"``, ``"box"``, ``"half_space"``, ``"mesh"``) and its size keys
    (``radius``; ``radius``, ``half_length``, ``axis``; ``half_extents``; ``normal``; ``file``,
    ``resolution``), the pose (``position`` with an optional ``orientation``, or ``path``), the
    contact (``contact``, ``friction``, ``direction``, ``hold``, ``haptic_gain``; ``stiffness``,
    ``damping`` for ``contact = "penalty"``) and ``grasp = {close, open, margin}``.

    Raises:
        ConfigError: naming the file, the line and the key (``tools[1].radius``).
    """
    if not isinstance(items, list):
        raise src.error("tools", "[[tools]] tables", got=items)
    out = ToolSet()
    for n, item in enumerate(items):
        t = Table(src, f"tools[{n}]", item, SECTIONS["tools"])
        name = t.text("name", "a tool name (letters, digits, _ and -)", default=f"tool{n + 1}")
        if not _NAME.match(name):
            raise t.fail("name", "a tool name (letters, digits, _ and -, not starting with a digit)", got=name)
        if name in out.names:
            raise t.fail("name", "a name no other tool has", got=name)
        kind = t.text("shape", "one of " + ", ".join(f'"{s}"' for s in SHAPE_KEYS), choices=SHAPE_KEYS)
        shape = _shape(t, kind, Path(base))
        if t.one_of("position", "path") == "position":
            pose = {
                "position": t.vec("position", "three numbers [d, h, w] in metres"),
                "orientation": t.vec("orientation", "a rotation vector [rd, rh, rw] in radians", default=None),
            }
        else:
            if t.has("orientation"):
                raise t.fail(
                    "orientation",
                    "no orientation with a path (rotations go into its waypoints [t, [d, h, w], [rd, rh, rw]])",
                    got=t.data["orientation"],
                )
            pose = {"path": _path(t)}
        with src.located(t.key("path" if "path" in pose else "position")):
            tool = Tool(shape, **pose, name=name)

        contact = t.text(
            "contact", "one of " + ", ".join(f'"{c}"' for c in CONTACTS), default="projection", choices=CONTACTS
        )
        for k in (k for keys in CONTACTS.values() for k in keys):
            if t.has(k) and k not in CONTACTS[contact]:
                owner = next(c for c, keys in CONTACTS.items() if k in keys)
                raise t.fail(
                    k, f'no {k} with contact = "{contact}" (it is an option of contact = "{owner}")', got=t.data[k]
                )
        if contact == "projection":
            kwargs = {
                "friction": t.num("friction", "a Coulomb coefficient >= 0", default=0.0, lo=0),
                "direction": t.text(
                    "direction", " or ".join(f'"{d}"' for d in DIRECTIONS), default="normal", choices=DIRECTIONS
                ),
                "hold": t.flag("hold", default=False),
                "haptic_gain": t.num("haptic_gain", "a gain >= 0 (N/m)", default=None, lo=0),
            }
        elif contact == "penalty":
            kwargs = {
                "stiffness": t.num("stiffness", "a positive number (N/m per metre of penetration)", lo=0, lo_open=True),
                "damping": t.num("damping", "a number >= 0 (N s/m)", default=0.0, lo=0),
            }
        else:
            kwargs = {}
        grasp = _grasp(t, tool) if t.has("grasp") else None
        if contact == "none" and grasp is None:
            raise t.fail(
                "contact",
                '"projection" or "penalty" (a tool with contact = "none" does nothing without a grasp)',
                got="none",
            )
        out.tools.append(tool)
        out.contacts.append((contact, kwargs))
        out.grasps.append(grasp)
        out.start_inside.append(t.flag("start_inside", default=False))
        out.paths.append("path" in pose)
    return out


def _warn(src: Source, key: str, message: str) -> None:
    """A one-line :class:`~torchdeform.errors.ConfigWarning` naming the file, the line and ``key``."""
    import warnings

    line = src.line_of(key) if src.path is not None else None
    where = f"{src.path}:{line}: " if src.path is not None and line else ""
    named = getattr(src, "scene_key", lambda k: k)(key)  # a body of several: bodies[n].tools[k]...
    warnings.warn(f"{where}{named}: {message}", ConfigWarning, stacklevel=3)


def _pose_times(tool: Tool) -> list:
    """Times (s) at which to look at a tool: its waypoints and 16 points within each segment (a pose: 0)."""
    times = list(getattr(tool._path, "times", None) or [0.0]) if tool._fn is None else [0.0]
    out = [times[0]]
    for a, b in itertools.pairwise(times):
        out += [a + (b - a) * i / 16 for i in range(1, 17)]
    return out


@torch.no_grad()
def check_tool_reach(src: Source, tools: ToolSet, grid) -> None:
    """Refuse a tool that starts inside the body, warn about one that never comes near it.

    At ``t = 0`` a contact tool must not hold a rest node deeper than half the spacing unless its table
    says ``start_inside = true`` (a grasp, ``contact = "none"``, may start around the tissue): the
    contact would fling those nodes out in the first step. Over its whole path (waypoints and 16
    points between each two) a tool should come within the spacing (plus a grasp's margin) of a
    rest node; one that never does touches nothing (a path in millimetres, a body in metres). A tool
    that only cuts or burns (``contact = "none"``, no grasp) is left to the cuts' own checks.

    Raises:
        ConfigError: ``tools[n].position`` (or ``.path``) of a tool that starts inside the body.
    """
    X = grid.rest_positions(dtype=torch.float64)
    nodes = grid.nodes()
    h = min(grid.spacing)
    far = torch.full_like(X[:, 0], math.inf)
    for n, tool in enumerate(tools.tools):
        kind = tools.contacts[n][0]
        grasp = tools.grasps[n]
        key = f"tools[{n}].{'path' if tools.paths and tools.paths[n] else 'position'}"
        d0 = torch.where(nodes, tool.sdf(X, 0.0)[0][:, 0], far)
        depth = -float(d0.min())
        if kind != "none" and depth > 0.5 * h and not (tools.start_inside and tools.start_inside[n]):
            raise src.error(
                key,
                f"a start pose outside the body: tool {tool.name!r} holds rest nodes {depth * 1e3:.3g} mm deep at "
                f"t = 0 (spacing {h * 1e3:.3g} mm), and its contact would fling them out in the first step; "
                f"move it out, or set tools[{n}].start_inside = true if that is meant",
            )
        if kind == "none" and grasp is None:
            continue  # a tool that only cuts or burns: its blade's reach is checked with the cuts
        reach = h + (grasp.get("margin", 0.0) if grasp else 0.0)
        nearest = min(float(torch.where(nodes, tool.sdf(X, s)[0][:, 0], far).min()) for s in _pose_times(tool))
        if nearest > reach:
            lo = [float(c) for c in X[0].flatten(1)[:, nodes.flatten()].amin(1)]
            hi = [float(c) for c in X[0].flatten(1)[:, nodes.flatten()].amax(1)]
            _warn(
                src,
                key,
                f"tool {tool.name!r} never comes within {reach * 1e3:.3g} mm of the body (it stays {nearest:.3g} m "
                f"away; the body spans [{', '.join(f'{c:.3g}' for c in lo)}] .. [{', '.join(f'{c:.3g}' for c in hi)}]"
                " m): positions are in metres, a path in millimetres needs the factor 0.001",
            )


def strain_limit_section(t: Table) -> dict:
    """Keyword arguments of :class:`~torchdeform.interact.StrainLimit` from ``[strain_limit]``.

    Keys: ``min`` (0.9), ``max`` (1.1): the bounds of a spring's length over its rest length;
    ``passes`` (4) Jacobi passes per step; ``update_velocity`` (true).
    """
    kwargs = {
        "min_ratio": t.num(
            "min", "a ratio in (0, 1] (shortest length / rest length)", default=0.9, lo=0, hi=1, lo_open=True
        ),
        "max_ratio": t.num("max", "a ratio >= 1 (longest length / rest length)", default=1.1, lo=1),
        "passes": t.integer("passes", "an integer >= 1 (Jacobi passes per step)", default=4, lo=1),
        "update_velocity": t.flag("update_velocity", default=True),
    }
    keys = {
        "strain_limit.min_ratio": t.key("min"),
        "strain_limit.max_ratio": t.key("max"),
        "strain_limit.passes": t.key("passes"),
    }
    with t.src.located(t.name, keys=keys):
        StrainLimit(**kwargs)
    return kwargs


def palpation_option(out: Table, tools: ToolSet | None) -> str | None:
    """The tool named by ``[output] palpation`` (``true``: the first tool with a contact), or None."""
    if not out.has("palpation"):
        return None
    v = out.data["palpation"]
    touching = [
        tool.name
        for tool, (kind, _) in zip(tools.tools if tools else [], tools.contacts if tools else [])
        if kind != "none"
    ]
    expected = "true, false or the name of a [[tools]] tool with a contact"
    if v is False:
        return None
    if v is True and touching:
        return touching[0]
    if isinstance(v, str) and v in touching:
        return v
    known = f" ({', '.join(touching)})" if touching else " (there is none)"
    raise out.fail("palpation", expected + known, got=v)


# ------------------------------------------------------------------ recording a run
class ToolRecorder:
    """Per-step tool readings of batch entry 0, kept on the model's device until the end.

    Call it as ``simulate``'s ``callback(step, state)``.

    Args:
        names: the tools' names.
        steps: the number of steps.
        device: the model's device.
        dtype: the model's dtype.

    Examples:
        >>> import torch
        >>> from torchdeform.sim.model import State
        >>> rec = ToolRecorder(["probe"], steps=2, device="cpu", dtype=torch.float64)
        >>> x = torch.zeros(1, 3, 1, 1, 1)
        >>> rec(1, State(x, x, t=0.1, readings={"probe.force": torch.tensor([[1.0, 2.0, 3.0]]),
        ...                                       "probe.contacts": torch.tensor([4.0])}))
        >>> rec(2, State(x, x, t=0.2, readings={}))
        >>> s = rec.series()
        >>> s["t"].tolist(), s["probe.force"].tolist(), s["probe.contacts"].tolist()
        ([0.1, 0.2], [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]], [4.0, 0.0])
    """

    #: channels of the buffer: force (3), contacts, grasped
    CHANNELS = ("force", "contacts", "grasped")
    #: it reads a state's ``t`` and ``readings`` only: a compiled run need not unpack positions for it
    reads_positions = False

    def __init__(self, names, steps: int, device, dtype):
        self.names = list(names)
        self.buffer = torch.zeros(int(steps), len(self.names), 5, device=device, dtype=dtype)
        self.t = np.zeros(int(steps))
        self.seen = set()
        self._keys = [tuple(f"{n}.{c}" for c in self.CHANNELS) for n in self.names]

    def __call__(self, step: int, state: State) -> None:
        """Store the readings of ``state`` as step ``step`` (1-based)."""
        self.t[step - 1] = float(state.t)
        readings = state.readings
        if not readings:
            return
        row = self.buffer[step - 1]
        for k, (force, contacts, grasped) in enumerate(self._keys):
            if force in readings:
                row[k, :3] = readings[force][0]
                self.seen.add(force)
            if contacts in readings:
                row[k, 3] = readings[contacts][0]
                self.seen.add(contacts)
            if grasped in readings:
                row[k, 4] = readings[grasped][0]
                self.seen.add(grasped)

    def series(self) -> dict:
        """``{"t": (T,), "<name>.force": (T, 3), "<name>.contacts": (T,), "<name>.grasped": (T,)}`` (numpy, float64).

        ``contacts`` and ``grasped`` only for tools whose responses reported them.
        """
        data = self.buffer.detach().to("cpu", torch.float64).numpy()
        out = {"t": self.t.copy()}
        for k, name in enumerate(self.names):
            out[f"{name}.force"] = data[:, k, :3]
            for c, key in ((3, "contacts"), (4, "grasped")):
                if f"{name}.{key}" in self.seen:
                    out[f"{name}.{key}"] = data[:, k, c]
        return out


def tool_outputs(
    tools: ToolSet, series: dict, frames: tuple, out_dir, *, title: str = "", max_points: int = MAX_POINTS
) -> dict:
    """Write ``tools.npz``, ``forces.png`` (and ``palpation.png``); return the summary's tool parts.

    Args:
        tools: the scene's :class:`ToolSet`.
        series: :meth:`ToolRecorder.series` of the run.
        frames: ``(t (F,), support reaction (F, 3))`` at the recorded frames.
        out_dir: the output folder.
        title: the plots' title.
        max_points: most points per series in the summary.

    Returns:
        ``{"tools": {name: {...}}, "support_reaction_N": {...}}`` and ``"palpation"`` when asked.
    """
    out = Path(out_dir)
    t = series["t"]
    block = max(1, math.ceil(len(t) / max_points))
    t_mean = block_means(t, block)
    npz, summary, curves = {"t": t}, {}, {}
    for tool in tools.tools:
        name = tool.name
        force = series[f"{name}.force"]
        position = np.asarray(tool.position(t), dtype=np.float64).reshape(-1, 3) * np.ones((len(t), 1))
        npz[f"{name}.force"], npz[f"{name}.position"] = force, position
        f_mean = block_means(force, block)
        p_mean = np.asarray(tool.position(t_mean), dtype=np.float64).reshape(-1, 3) * np.ones((len(t_mean), 1))
        magnitude = np.linalg.norm(f_mean, axis=1)
        peak = int(np.argmax(magnitude)) if len(magnitude) else 0
        u = work_direction(t, position, force)
        moving = bool(np.ptp(position, axis=0).max() > 0) if len(t) else False
        entry = {
            "contact": tools.contacts[tools.names.index(name)][0],
            "grasp": tools.grasps[tools.names.index(name)] is not None,
            "points": len(t_mean),
            "steps_per_point": block,
            "t_s": significant(t_mean),
            "force_N": significant(f_mean),
            "position_m": significant(p_mean),
            "max_force_N": float(magnitude[peak]) if len(magnitude) else 0.0,
            "max_force_t_s": float(t_mean[peak]) if len(magnitude) else 0.0,
            "work_direction": significant(u),
            "moving": moving,
        }
        for key in ("contacts", "grasped"):
            if f"{name}.{key}" in series:
                npz[f"{name}.{key}"] = series[f"{name}.{key}"]
                entry[key] = significant(block_means(series[f"{name}.{key}"], block), digits=4)
        summary[name] = entry
        curves[name] = (t_mean, p_mean, f_mean, u if moving else None)
    np.savez(out / "tools.npz", **npz)
    ft, fr = frames
    every = max(1, math.ceil(len(ft) / max_points))
    result = {
        "tools": summary,
        "support_reaction_N": {
            "t_s": significant(ft[::every]),
            "force_N": significant(fr[::every]),
            "max_N": float(np.linalg.norm(fr, axis=1).max()) if len(fr) else 0.0,
        },
    }
    plot_forces(out / "forces.png", curves, frames, title=title)
    if tools.palpation is not None:
        name = tools.palpation
        tool = tools.tools[tools.names.index(name)]
        position = npz[f"{name}.position"]
        contacts = series.get(f"{name}.contacts")
        if contacts is None:  # a penalty contact reports contacts too
            contacts = (np.linalg.norm(series[f"{name}.force"], axis=1) > 0).astype(float)
        velocity = np.array([tool.velocity(float(s)) for s in t], dtype=np.float64).reshape(-1, 3)
        result["palpation"] = {
            "tool": tool.name,
            **palpation(t, series[f"{name}.force"], position, contacts, velocity=velocity),
        }
        plot_palpation(out / "palpation.png", result["palpation"], title=title)
    return result


# ------------------------------------------------------------------ plots
def plot_forces(path, curves: dict, frames: tuple, *, title: str = "") -> None:
    """Write ``forces.png``: per tool the force along its motion (N) against its displacement (mm), and |F| over time.

    Args:
        path: the PNG file.
        curves: ``{name: (t (T,), position (T, 3), force (T, 3), u (3,) or None)}``: ``u`` the
            direction the tool works in (:func:`~torchdeform.interact.palpation.work_direction`), None
            for a tool that stands still (not drawn against its displacement).
        frames: ``(t (F,), support reaction (F, 3))`` (drawn over time, dashed).
        title: the figure's title.
    """
    fig = figure(figsize=(11, 4.5))
    left, right = fig.subplots(1, 2)
    for name, (t, position, force, u) in curves.items():
        (line,) = right.plot(t, np.linalg.norm(force, axis=1), lw=1.2, label=f"{name} |F|")
        if u is not None:
            left.plot(
                (position - position[0]) @ u * 1e3,
                -(force @ u),
                lw=1.2,
                color=line.get_color(),
                label=f"{name} along [{', '.join(f'{c:.2f}' for c in np.round(u, 2) + 0.0)}]",
            )
    ft, fr = frames
    if len(ft):
        right.plot(ft, np.linalg.norm(fr, axis=1), "k--", lw=1, label="supports |R|")
    left.set_xlabel("tool displacement from its start along the direction it works in (mm)")
    left.set_ylabel("force against the motion (N)")
    left.set_title("force-displacement")
    right.set_xlabel("time (s)")
    right.set_ylabel("force magnitude (N)")
    right.set_title("forces over time")
    for ax in (left, right):
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(loc="best", fontsize="small")
    if title:
        fig.suptitle(title)
    save_figure(fig, path, dpi=100)


def support_series(model, t: np.ndarray, x: torch.Tensor, v: torch.Tensor) -> np.ndarray:
    """The supports' reaction ``(F, 3)`` N at recorded frames ``x``, ``v`` ``(F, 3, D, H, W)`` (batch entry 0)."""
    out = []
    with torch.no_grad():
        for i in range(len(t)):
            state = State(
                x[i : i + 1].to(model.device, model.dtype), v[i : i + 1].to(model.device, model.dtype), t=float(t[i])
            )
            out.append(support_reaction(model, state)[0].double().cpu())
    return torch.stack(out).numpy() if out else np.zeros((0, 3))


def tool_forces_at(series: dict, names, t: np.ndarray) -> dict:
    """The tools' forces at recorded frame times, from the per-step series of :class:`ToolRecorder`.

    Args:
        series: :meth:`ToolRecorder.series` (``"t"`` ``(steps,)``, ``"<name>.force"`` ``(steps, 3)``).
        names: the tools' names.
        t: frame times ``(T,)`` (s).

    Returns:
        ``{name: (T, 3)}`` (N): the reading of the step nearest each frame (zero before the first step).

    Examples:
        >>> import numpy as np
        >>> series = {"t": np.array([0.1, 0.2, 0.3]), "probe.force": np.array([[1.0, 0, 0], [2, 0, 0], [3, 0, 0]])}
        >>> tool_forces_at(series, ["probe"], np.array([0.0, 0.2, 0.3]))["probe"][:, 0].tolist()
        [0.0, 2.0, 3.0]
    """
    st = np.asarray(series["t"], dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if not len(st):
        return {name: np.zeros((len(t), 3)) for name in names}
    k = np.clip(np.searchsorted(st, t), 0, len(st) - 1)
    prev = np.clip(k - 1, 0, len(st) - 1)
    k = np.where(np.abs(st[prev] - t) < np.abs(st[k] - t), prev, k)
    before = t < st[0] / 2  # the start frame: no step yet
    return {name: np.where(before[:, None], 0.0, np.asarray(series[f"{name}.force"])[k]) for name in names}
