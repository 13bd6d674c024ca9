r"""Tools in mass-spring scene files, and what a run reports about them.

Reading (:func:`tools_section`, :func:`strain_limit_section`, :func:`palpation_option`): the
``[[tools]]`` tables become :class:`~torchdeform.interact.tools.Tool` s with their contact
responses and grasps, ``[strain_limit]`` a :class:`~torchdeform.interact.strain.StrainLimit`; a
:class:`ToolSet` keeps them and builds fresh interaction objects for every run
(:meth:`ToolSet.interactions`), in the order strain limiting, contacts (one per tool, in file
order), grasps: contact comes after strain limiting so no node ends a step inside a tool, and a
grasp comes last so held nodes end every step exactly on the forceps.

Running (:class:`ToolRecorder`, :func:`tool_outputs`): every step's readings
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
* with ``[output] palpation``: the presses of one tool (:func:`palpation`), ``palpation.png`` and
  a ``"palpation"`` part of ``summary.json``.

Force along the motion: the tool works against the tissue along ``u`` (:func:`work_direction`: its
directions of motion weighted by the power it puts into the tissue; down for a probe pressing
into a surface, up for forceps lifting tissue). With ``p0`` its first position, the displacement is
``s = (p - p0) . u`` (m) and the force along the motion ``-F . u`` (N): the tissue's resistance,
positive when it pushes back against the probe or pulls back on the forceps. Tools that do not move
(a table) appear only in the force-over-time panel.

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
    >>> tools = tools_section(Source("s.toml", text), [probe], base=".")
    >>> [type(c).__name__ for c in tools.interactions()], tools.names
    (['ProjectionContact'], ['probe'])
    >>> tools_section(Source("s.toml", text), [{**probe, "radius": -0.003}], base=".")
    Traceback (most recent call last):
    ...
    torchdeform.errors.ConfigError: s.toml:5: tools[0].radius: expected a positive number of metres, got -0.003
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..interact.contact import DIRECTIONS, PenaltyContact, ProjectionContact
from ..interact.grasp import Grasp
from ..interact.reactions import support_reaction
from ..interact.strain import StrainLimit
from ..interact.tools import Box, Capsule, HalfSpace, Sphere, Tool
from ..outputs import save_figure
from ..sim.model import State
from .reader import SECTIONS, Source, Table, is_number

__all__ = [
    "SHAPE_KEYS",
    "CONTACTS",
    "ToolSet",
    "tools_section",
    "strain_limit_section",
    "palpation_option",
    "ToolRecorder",
    "tool_outputs",
    "support_series",
    "work_direction",
    "palpation",
    "plot_forces",
    "plot_palpation",
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
@dataclass(eq=False)
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
        >>> tools = ToolSet([probe], [("projection", {"friction": 0.5})], [None], {"min_ratio": 0.8})
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

    @property
    def names(self) -> list:
        """The tools' names, in file order."""
        return [tool.name for tool in self.tools]

    def interactions(self) -> list:
        """New interaction objects (contacts and grasps keep state between steps): strain limit, contacts, grasps."""
        out = [] if self.strain_limit is None else [StrainLimit(**self.strain_limit)]
        for tool, (kind, kwargs) in zip(self.tools, self.contacts):
            if kind == "projection":
                out.append(ProjectionContact(tool, **kwargs))
            elif kind == "penalty":
                out.append(PenaltyContact(tool, **kwargs))
        out += [Grasp(tool, **g) for tool, g in zip(self.tools, self.grasps) if g is not None]
        return out


def _flag(t: Table, k: str, default: bool) -> bool:
    v = t.data.get(k, default)
    if not isinstance(v, bool):
        raise t.fail(k, "true or false", v)
    return v


def _shape(t: Table, kind: str, base: Path):
    for k in (k for keys in SHAPE_KEYS.values() for k in keys):
        if t.has(k) and k not in SHAPE_KEYS[kind]:
            raise t.fail(k, f'no {k} for shape = "{kind}" (its keys: {", ".join(SHAPE_KEYS[kind])})', t.data[k])
    metres = "a positive number of metres"
    if kind == "sphere":
        return Sphere(t.num("radius", metres, lo=0, lo_open=True))
    if kind == "capsule":
        axis = t.raw("axis", '"d", "h" or "w" (or 0, 1, 2): the grid axis of the shaft')
        if axis in _AXES:
            axis = _AXES[axis]
        if axis not in (0, 1, 2) or isinstance(axis, bool):
            raise t.fail("axis", '"d", "h" or "w" (or 0, 1, 2): the grid axis of the shaft', t.data["axis"])
        return Capsule(
            t.num("radius", metres, lo=0, lo_open=True), t.num("half_length", "a number of metres >= 0", lo=0), axis
        )
    if kind == "box":
        h = t.vec("half_extents", "three positive numbers [hd, hh, hw] in metres")
        if min(h) <= 0:
            raise t.fail("half_extents", "three positive numbers [hd, hh, hw] in metres", list(h))
        return Box(h)
    if kind == "half_space":
        normal = t.vec("normal", "three numbers [nd, nh, nw], the outward direction", (1.0, 0.0, 0.0))
        if not any(normal):
            raise t.fail("normal", "a non-zero direction [nd, nh, nw]", list(normal))
        return HalfSpace(normal)
    try:  # mesh: the optional module, imported when used
        from ..interact.meshes import MeshShape
    except ImportError:  # pragma: no cover
        raise t.fail(
            "shape",
            "one of "
            + ", ".join(f'"{s}"' for s in SHAPE_KEYS if s != "mesh")
            + " (mesh tools need torchdeform.interact.meshes)",
            "mesh",
        ) from None
    file = t.text("file", "a closed triangle mesh file (relative to the scene file; x, y, z = D, H, W in m)")
    resolution = t.integer("resolution", "an integer >= 4 (distance-field points along the longest axis)", 32, lo=4)
    with t.src.located(t.key("file"), {"mesh_shape.resolution": t.key("resolution")}):
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
        raise t.fail("path", _WAYPOINTS + ", all of one kind", v)
    return [tuple([float(w[0])] + [tuple(float(c) for c in p) for p in w[1:]]) for w in v]


def _grasp(t: Table, tool: Tool) -> dict:
    g = Table(t.src, t.key("grasp"), t.data["grasp"], ("close", "open", "margin"))
    close = g.num("close", "a time in seconds >= 0 when the jaws close", lo=0)
    opened = g.data.get("open")
    if (opened is not None and not (is_number(opened) or opened == math.inf)) or isinstance(opened, bool):
        raise g.fail("open", "a time in seconds after close (inf: never)", opened)
    kwargs = {"close": close, "open": opened, "margin": g.num("margin", "metres >= 0", 0.0, lo=0)}
    keys = {"grasp": g.name, **{f"grasp.{k}": g.key(k) for k in ("close", "open", "margin")}}
    with t.src.located(g.name, keys):
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
        raise src.error("tools", "[[tools]] tables", items)
    out = ToolSet()
    for n, item in enumerate(items):
        t = Table(src, f"tools[{n}]", item, SECTIONS["tools"])
        name = t.text("name", "a tool name (letters, digits, _ and -)", f"tool{n + 1}")
        if not _NAME.match(name):
            raise t.fail("name", "a tool name (letters, digits, _ and -, not starting with a digit)", name)
        if name in out.names:
            raise t.fail("name", "a name no other tool has", name)
        kind = t.text("shape", "one of " + ", ".join(f'"{s}"' for s in SHAPE_KEYS), choices=SHAPE_KEYS)
        shape = _shape(t, kind, Path(base))
        if t.one_of("position", "path") == "position":
            pose = {
                "position": t.vec("position", "three numbers [d, h, w] in metres"),
                "orientation": t.vec("orientation", "a rotation vector [rd, rh, rw] in radians", None),
            }
        else:
            if t.has("orientation"):
                raise t.fail(
                    "orientation",
                    "no orientation with a path (rotations go into its waypoints [t, [d, h, w], [rd, rh, rw]])",
                    t.data["orientation"],
                )
            pose = {"path": _path(t)}
        with src.located(t.key("path" if "path" in pose else "position")):
            tool = Tool(shape, **pose, name=name)

        contact = t.text("contact", "one of " + ", ".join(f'"{c}"' for c in CONTACTS), "projection", CONTACTS)
        for k in (k for keys in CONTACTS.values() for k in keys):
            if t.has(k) and k not in CONTACTS[contact]:
                owner = next(c for c, keys in CONTACTS.items() if k in keys)
                raise t.fail(
                    k, f'no {k} with contact = "{contact}" (it is an option of contact = "{owner}")', t.data[k]
                )
        if contact == "projection":
            kwargs = {
                "friction": t.num("friction", "a Coulomb coefficient >= 0", 0.0, lo=0),
                "direction": t.text("direction", " or ".join(f'"{d}"' for d in DIRECTIONS), "normal", DIRECTIONS),
                "hold": _flag(t, "hold", False),
                "haptic_gain": t.num("haptic_gain", "a gain >= 0 (N/m)", None, lo=0),
            }
        elif contact == "penalty":
            kwargs = {
                "stiffness": t.num("stiffness", "a positive number (N/m per metre of penetration)", lo=0, lo_open=True),
                "damping": t.num("damping", "a number >= 0 (N s/m)", 0.0, lo=0),
            }
        else:
            kwargs = {}
        grasp = _grasp(t, tool) if t.has("grasp") else None
        if contact == "none" and grasp is None:
            raise t.fail(
                "contact",
                '"projection" or "penalty" (a tool with contact = "none" does nothing without a grasp)',
                "none",
            )
        out.tools.append(tool)
        out.contacts.append((contact, kwargs))
        out.grasps.append(grasp)
    return out


def strain_limit_section(t: Table) -> dict:
    """Keyword arguments of :class:`~torchdeform.interact.StrainLimit` from ``[strain_limit]``.

    Keys: ``min`` (0.9), ``max`` (1.1): the bounds of a spring's length over its rest length;
    ``passes`` (4) Jacobi passes per step; ``update_velocity`` (true).
    """
    kwargs = {
        "min_ratio": t.num("min", "a ratio in (0, 1] (shortest length / rest length)", 0.9, lo=0, hi=1, lo_open=True),
        "max_ratio": t.num("max", "a ratio >= 1 (longest length / rest length)", 1.1, lo=1),
        "passes": t.integer("passes", "an integer >= 1 (Jacobi passes per step)", 4, lo=1),
        "update_velocity": _flag(t, "update_velocity", True),
    }
    keys = {
        "strain_limit.min_ratio": t.key("min"),
        "strain_limit.max_ratio": t.key("max"),
        "strain_limit.passes": t.key("passes"),
    }
    with t.src.located(t.name, keys):
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
    raise out.fail("palpation", expected + known, v)


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
        >>> rec(1, State(x, x, 0.1, {"probe.force": torch.tensor([[1.0, 2.0, 3.0]]),
        ...                         "probe.contacts": torch.tensor([4.0])}))
        >>> rec(2, State(x, x, 0.2, {}))
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


def _blocks(a: np.ndarray, size: int) -> np.ndarray:
    """Means over consecutive blocks of ``size`` rows (the last block may be shorter)."""
    if size <= 1:
        return a
    n = len(a)
    starts = np.arange(0, n, size)
    sums = np.add.reduceat(a, starts, axis=0)
    counts = np.diff(np.append(starts, n)).reshape((-1,) + (1,) * (a.ndim - 1))
    return sums / counts


def _round(a, digits: int = 6):
    """Nested lists of floats with ``digits`` significant digits (keeps summary.json small)."""
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return a.tolist()
    return np.vectorize(lambda x: float(f"{x:.{digits}g}"), otypes=[np.float64])(a).tolist()


def work_direction(t: np.ndarray, position: np.ndarray, force: np.ndarray) -> np.ndarray:
    """The unit vector ``(3,)`` along which a tool works against the tissue (zero if it never does).

    ``u`` is proportional to ``sum_t max(0, -F . v) v / |v|``: the tool's directions of motion,
    weighted by the power it puts into the tissue (``-F`` is its push on the tissue, ``v`` its
    velocity from ``position``). Down for a probe pressing into a surface, up for forceps lifting
    tissue; ``-sum F`` for a tool that does no work, e.g. one that stands still.

    Args:
        t: times ``(T,)`` s.
        position: the tool's positions ``(T, 3)`` m.
        force: the force it feels ``(T, 3)`` N.
    """
    v = np.gradient(position, t, axis=0) if len(t) > 1 else np.zeros_like(position)
    speed = np.linalg.norm(v, axis=1, keepdims=True)
    power = np.clip(-(force * v).sum(1, keepdims=True), 0, None)
    u = (power * v / np.where(speed > 0, speed, 1)).sum(0)
    if not np.linalg.norm(u) > 0:
        u = -force.sum(0)
    length = np.linalg.norm(u)
    return u / length if length > 0 else np.zeros(3)


def tool_outputs(
    tools: ToolSet, series: dict, frames: tuple, out_dir, title: str = "", max_points: int = MAX_POINTS
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
    t_mean = _blocks(t, block)
    npz, summary, curves = {"t": t}, {}, {}
    for tool in tools.tools:
        name = tool.name
        force = series[f"{name}.force"]
        position = np.asarray(tool.position(t), dtype=np.float64).reshape(-1, 3) * np.ones((len(t), 1))
        npz[f"{name}.force"], npz[f"{name}.position"] = force, position
        f_mean = _blocks(force, block)
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
            "t_s": _round(t_mean),
            "force_N": _round(f_mean),
            "position_m": _round(p_mean),
            "max_force_N": float(magnitude[peak]) if len(magnitude) else 0.0,
            "max_force_t_s": float(t_mean[peak]) if len(magnitude) else 0.0,
            "work_direction": _round(u),
            "moving": moving,
        }
        for key in ("contacts", "grasped"):
            if f"{name}.{key}" in series:
                npz[f"{name}.{key}"] = series[f"{name}.{key}"]
                entry[key] = _round(_blocks(series[f"{name}.{key}"], block), 4)
        summary[name] = entry
        curves[name] = (t_mean, p_mean, f_mean, u if moving else None)
    np.savez(out / "tools.npz", **npz)
    ft, fr = frames
    every = max(1, math.ceil(len(ft) / max_points))
    result = {
        "tools": summary,
        "support_reaction_N": {
            "t_s": _round(ft[::every]),
            "force_N": _round(fr[::every]),
            "max_N": float(np.linalg.norm(fr, axis=1).max()) if len(fr) else 0.0,
        },
    }
    plot_forces(out / "forces.png", curves, frames, title)
    if tools.palpation is not None:
        name = tools.palpation
        tool = tools.tools[tools.names.index(name)]
        position = npz[f"{name}.position"]
        contacts = series.get(f"{name}.contacts")
        if contacts is None:  # a penalty contact reports contacts too
            contacts = (np.linalg.norm(series[f"{name}.force"], axis=1) > 0).astype(float)
        velocity = np.array([tool.velocity(float(s)) for s in t], dtype=np.float64).reshape(-1, 3)
        result["palpation"] = {"tool": tool.name, **palpation(t, series[f"{name}.force"], position, contacts, velocity)}
        plot_palpation(out / "palpation.png", result["palpation"], title)
    return result


# ------------------------------------------------------------------ palpation
def _episodes(touching: np.ndarray, min_steps: int) -> list:
    """``[(start, stop), ...]`` of the runs of ``touching``; gaps shorter than a tenth of both runs are bridged."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], touching.astype(np.int8), [0]])))
    runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]
    merged = []
    for a, b in runs:
        if merged and a - merged[-1][1] < 0.1 * min(b - a, merged[-1][1] - merged[-1][0]):
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    return [(a, b) for a, b in merged if b - a >= min_steps]


def _smooth(a: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average of odd ``width`` (shorter at the ends)."""
    if width <= 1 or len(a) < 3:
        return a
    kernel = np.ones(width)
    return np.convolve(a, kernel, "same") / np.convolve(np.ones_like(a), kernel, "same")


def palpation(
    t: np.ndarray,
    force: np.ndarray,
    position: np.ndarray,
    contacts: np.ndarray,
    velocity: np.ndarray | None = None,
    curve_points: int = 100,
) -> dict:
    """The presses of a tool: force against indentation at each point, and where the tissue is stiffest.

    A press is a run of steps in which the tool touches the tissue (``contacts > 0``; gaps shorter
    than a tenth of the runs beside them are bridged, runs under 10 steps dropped). In each press,
    from the tool's position ``p_on`` at first contact, the press direction ``n`` points to the
    deepest position ``p_max`` (the farthest from ``p_on``), the indentation is
    ``delta = (p - p_on) . n`` and the force ``F_n = -F . n`` (N, the tissue pushing back). On the
    loading branch (first contact to ``p_max`` while the tool moves inwards, ``velocity . n > 0``: the
    step at which it turns round is left out; ``F_n`` smoothed over about 2 % of the branch): the peak
    force, the indentation there, the slope of ``F_n`` against ``delta`` (N/m, a least-squares line
    through ``delta_max / 2 .. delta_max``), ``p_max``, and the branch as the force-indentation
    curve. Positions along the line of presses are
    ``(p_max - p_max[0]) . e`` with ``e`` the unit vector from the first press to the last.

    Args:
        t: times ``(T,)`` s.
        force: the force the tool feels ``(T, 3)`` N.
        position: the tool's position ``(T, 3)`` m.
        contacts: nodes touched per step ``(T,)``.
        velocity: the tool's velocity ``(T, 3)`` m/s (that of the path segment entered at each time),
            or None: forward differences of ``position``.
        curve_points: points per force-indentation curve in the result.

    Returns:
        ``{"points": [{"position_m", "along_m", "t_s" (start, end), "indentation_m", "peak_force_N",
        "stiffness_N_per_m", "curve": {"indentation_m", "force_N"}}, ...], "stiffest": {...}}``;
        ``stiffest`` is the press with the largest peak force (``index``, ``along_m``,
        ``position_m``, ``peak_force_N``, ``ratio_to_median``) or None when there is no press.

    Examples:
        >>> import numpy as np
        >>> t = np.linspace(0, 2, 2001)
        >>> depth = np.clip(1 - abs((t % 1) - 0.5) * 4, 0, None) * 1e-3          # two presses, 1 mm deep
        >>> position = np.stack([-depth, np.zeros_like(t), np.floor(t) * 0.01], 1)
        >>> stiffness = np.where(t < 1, 100.0, 300.0)                           # N/m: the second is stiffer
        >>> force = np.stack([stiffness * depth, 0 * t, 0 * t], 1)              # the tissue pushes up
        >>> r = palpation(t, force, position, depth > 0)
        >>> [round(p["stiffness_N_per_m"]) for p in r["points"]], r["stiffest"]["index"], r["stiffest"]["along_m"]
        ([100, 300], 1, 0.01)
    """
    t, force, position = np.asarray(t, float), np.asarray(force, float), np.asarray(position, float)
    points = []
    for a, b in _episodes(np.asarray(contacts) > 0, min_steps=10):
        p = position[a:b]
        offset = p - p[0]
        k = int(np.argmax(np.linalg.norm(offset, axis=1)))
        depth = float(np.linalg.norm(offset[k]))
        if depth == 0:
            continue
        n = offset[k] / depth
        inward = (velocity[a:b] @ n) > 0 if velocity is not None else np.diff(offset @ n, append=-np.inf) > 0
        while k > 0 and not inward[k]:  # the loading branch ends where the tool
            k -= 1  # last moved inwards (not at its turn)
        delta = (offset @ n)[: k + 1]
        f = _smooth(-(force[a : a + k + 1] @ n), 2 * max(1, (k + 1) // 100) + 1)
        peak = int(np.argmax(f))
        upper = np.flatnonzero(delta >= 0.5 * depth)
        slope = (
            float(np.polyfit(delta[upper], f[upper], 1)[0])
            if len(upper) >= 2 and np.ptp(delta[upper]) > 0
            else float("nan")
        )
        keep = np.unique(np.linspace(0, k, min(curve_points, k + 1)).round().astype(int))  # the loading branch
        points.append(
            {
                "position_m": _round(p[k]),
                "t_s": _round([t[a], t[b - 1]]),
                "indentation_m": depth,
                "peak_force_N": float(f[peak]),
                "peak_indentation_m": float(delta[peak]),
                "stiffness_N_per_m": slope if math.isfinite(slope) else None,
                "curve": {"indentation_m": _round(delta[keep]), "force_N": _round(f[keep])},
            }
        )
    if points:
        first, last = np.array(points[0]["position_m"]), np.array(points[-1]["position_m"])
        line = last - first
        e = line / np.linalg.norm(line) if np.linalg.norm(line) > 0 else np.zeros(3)
        for q in points:
            q["along_m"] = float(f"{float((np.array(q['position_m']) - first) @ e):.6g}")
        peaks = np.array([q["peak_force_N"] for q in points])
        i = int(np.argmax(peaks))
        stiffest = {
            "index": i,
            "along_m": points[i]["along_m"],
            "position_m": points[i]["position_m"],
            "peak_force_N": float(peaks[i]),
            "ratio_to_median": float(peaks[i] / np.median(peaks)) if np.median(peaks) > 0 else None,
        }
    else:
        stiffest = None
    return {"points": points, "stiffest": stiffest}


# ------------------------------------------------------------------ plots
def _figure(size):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def plot_forces(path, curves: dict, frames: tuple, title: str = "") -> None:
    """Write ``forces.png``: per tool the force along its motion (N) against its displacement (mm), and |F| over time.

    Args:
        path: the PNG file.
        curves: ``{name: (t (T,), position (T, 3), force (T, 3), u (3,) or None)}``: ``u`` the
            direction the tool works in (:func:`work_direction`), None for a tool that stands still
            (not drawn against its displacement).
        frames: ``(t (F,), support reaction (F, 3))`` (drawn over time, dashed).
        title: the figure's title.
    """
    fig = _figure((11, 4.5))
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


def plot_palpation(path, result: dict, title: str = "") -> None:
    """Write ``palpation.png``: left force-indentation per press, right peak force and slope along the line.

    Args:
        path: the PNG file.
        result: the ``"palpation"`` part of the summary (:func:`palpation` plus ``"tool"``).
        title: the figure's title.
    """
    from matplotlib import colormaps

    fig = _figure((11, 4.5))
    left, right = fig.subplots(1, 2)
    points = result["points"]
    cmap = colormaps["viridis"]
    for i, q in enumerate(points):
        colour = cmap(i / max(1, len(points) - 1))
        left.plot(
            np.array(q["curve"]["indentation_m"]) * 1e3,
            q["curve"]["force_N"],
            color=colour,
            lw=1.2,
            label=f"{q['along_m'] * 1e3:.1f} mm",
        )
    left.set_xlabel("indentation (mm)")
    left.set_ylabel("force (N)")
    left.set_title(f"force-indentation, {result['tool']}")
    left.grid(alpha=0.3)
    if points:
        left.legend(loc="upper left", fontsize="x-small", title="position", title_fontsize="x-small")
        along = np.array([q["along_m"] for q in points]) * 1e3
        peaks = np.array([q["peak_force_N"] for q in points])
        right.plot(along, peaks, "o-", color="tab:red", label="peak force")
        best = result["stiffest"]
        right.annotate(
            f"stiffest: {best['along_m'] * 1e3:.1f} mm",
            (best["along_m"] * 1e3, best["peak_force_N"]),
            textcoords="offset points",
            xytext=(8, -4),
            ha="left",
            fontsize="small",
        )
        right.margins(y=0.12)
        twin = right.twinx()
        slopes = [np.nan if q["stiffness_N_per_m"] is None else q["stiffness_N_per_m"] for q in points]
        twin.plot(along, slopes, "s--", color="tab:blue", label="slope")
        twin.set_ylabel("slope of the loading half (N/m)", color="tab:blue")
        right.legend(loc="upper left", fontsize="small")
        twin.legend(loc="upper right", fontsize="small")
    right.set_xlabel("position along the line of presses (mm)")
    right.set_ylabel("peak force (N)", color="tab:red")
    right.set_title("peak force along the line")
    right.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    save_figure(fig, path, dpi=100)


def support_series(model, t: np.ndarray, x: torch.Tensor, v: torch.Tensor) -> np.ndarray:
    """The supports' reaction ``(F, 3)`` N at recorded frames ``x``, ``v`` ``(F, 3, D, H, W)`` (batch entry 0)."""
    out = []
    with torch.no_grad():
        for i in range(len(t)):
            state = State(
                x[i : i + 1].to(model.device, model.dtype), v[i : i + 1].to(model.device, model.dtype), float(t[i])
            )
            out.append(support_reaction(model, state)[0].double().cpu())
    return torch.stack(out).numpy() if out else np.zeros((0, 3))
