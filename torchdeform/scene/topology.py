r"""Topology changes in mass-spring scene files, and what a run reports about them.

Reading (:func:`topology_section`, :func:`tools_with_cutters`): the ``[[cuts]]``, ``[[cautery]]``,
``[tear]`` and ``[[coagulate]]`` sections and ``[output] surfaces`` become a :class:`TopologySet`;
for every run it builds fresh events (:meth:`TopologySet.events`: the scalpels keep state) on a
fresh, editable copy of the model (:meth:`TopologySet.prepare`), so a scene can be run twice.

Timing: events happen between steps, at the first state whose time ``t`` reaches the event's time
(``t >= at``, to a millionth of a step); at ``t = 0`` that is before the first step. At one such
moment they run in the order cuts (blades, then scalpels), cautery, coagulation, tearing, and then
the surfaces of that moment are written, so they show what just happened.

Embedded surfaces (a body of labels, ``[[surfaces]]``) are cut with the lattice: every blade cuts
them with its own patches at the node positions of the moment it cuts the springs
(:meth:`~torchdeform.mesh.embed.EmbeddedSurface.cut_patches`); a scalpel cuts the springs at every
step and its sweep reaches the surfaces at every recorded frame and when it stops (the patches of
the steps since, at the positions of that moment: the frames show the same opening, without the
slivers of triangles a cut per step would leave). :attr:`TopologyEvents.embedded_versions` keeps
the surfaces after each change for the frames.

Keys
----
``[[cuts]]`` (repeatable), one blade per table, one of
    ``origin = [d, h, w]``, ``u = [..]``, ``v = [..]``: the parallelogram ``origin + a u + b v``,
    ``a, b`` in ``[0, 1]`` (m);
    ``triangle = [[d, h, w], [..], [..]]``: a triangle (m);
    ``edges = [[[d, h, w], [d, h, w]], ...]``: the surface a straight edge sweeps through two or
    more poses (m);
    each cutting once at ``at`` (s, default 0); or
    ``tool = "<a [[tools]] name>"`` with ``edge = [[d, h, w], [d, h, w]]`` (the cutting edge in the
    tool's frame, m): a scalpel cutting what the edge sweeps between ``start`` (s, default 0) and
    ``stop`` (s, default the end of the run), ``pieces`` triangles per step (default 1);
    all take ``gape`` in ``[0, 1)`` (pre-tension: the springs left at the cut's nodes shorten by
    this fraction, and the cut opens; default 0).
``[[cautery]]`` (repeatable): ``tool = "<name>"``; the nodes inside the tool are burnt away, once
    ``at`` a time (s) or at every ``every``-th step (default 1; steps counted from the run's
    start) from ``start`` (default 0) to ``stop`` (default the end; always burns there).
``[tear]``: ``max_strain`` (``l / l0 - 1`` > 0) or ``max_force`` (N > 0: the strain
    ``F / (k l0)`` of each spring); ``one_per_step`` (false: every spring past the limit breaks;
    true: only the most strained one per step); ``start`` (s, default 0).
``[[coagulate]]`` (repeatable): ``at`` (s, default 0); a region as in ``[[regions]]``:
    ``box = {lo = [..], hi = [..]}`` or ``sphere = {center = [..], radius = r}`` (rest positions,
    m); ``viscosity_factor`` (>= 1, default 1). Springs with both ends in the region take their
    current length as rest length and their damping times the factor.
``[output] surfaces = [t1, t2, ...]`` (s): at those times, the closed surface of every connected
    piece (:func:`~torchdeform.topology.components`,
    :func:`~torchdeform.topology.cut_surfaces`) as ``surface_<t in ms>ms_<label>.ply``.

A tool that only cuts or burns may have ``contact = "none"`` (without a grasp).

Every time must lie in ``[0, steps x dt]``; a blade (or the edge of a scalpel along its path)
must reach the body's rest bounding box.

Outputs (:meth:`TopologyEvents.outputs`): the ``"topology"`` part of ``summary.json`` (springs
removed by cuts and by tearing, nodes and mass and momentum removed by cautery, coagulated springs,
the final number of components, each section's events, the surface files) and ``topology.png``
(springs removed and nodes burnt over time; the final nodes coloured by component in a w-d slice
through the middle of H and in the top layer).

Example:
    >>> import torch
    >>> from torchdeform.scene.reader import SECTIONS, Source, Table
    >>> from torchdeform.sim.grid import Grid
    >>> text = '''
    ... [[cuts]]
    ... triangle = [[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]]
    ... '''
    >>> src = Source(path="s.toml", text=text)
    >>> data = {"cuts": [{"triangle": [[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]]}]}
    >>> out = Table(src, "output", {}, SECTIONS["output"])
    >>> topology_section(src, data, Grid((3, 3, 3), spacing=0.01), None, out, end=1.0)
    Traceback (most recent call last):
    ...
    torchdeform.errors.ConfigError: s.toml:3: cuts[0].triangle: expected a non-degenerate triangle: three corners not on one line, got ((0.0, 0.0, 0.0), (0.01, 0.0, 0.0), (0.02, 0.0, 0.0))
"""

from __future__ import annotations

import copy
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..outputs import save_figure
from ..sim.grid import Grid
from ..sim.model import State
from ..topology import (
    Blade,
    Scalpel,
    cauterize,
    coagulate,
    components,
    cut,
    cut_surfaces,
    save_cut_surfaces,
    sides,
    strain_limit_from_force,
    tear,
)
from ..topology.masks import alive, editable
from .reader import SECTIONS, Source, Table, is_number, region_mask

__all__ = ["TOPOLOGY", "TopologySet", "TopologyEvents", "topology_section", "tools_with_cutters", "plot_topology"]

#: the sections read here
TOPOLOGY = ("cuts", "cautery", "tear", "coagulate")
#: the keys of each form of a ``[[cuts]]`` table (besides ``gape``)
CUT_FORMS = {
    "origin": ("origin", "u", "v", "at"),
    "triangle": ("triangle", "at"),
    "edges": ("edges", "at"),
    "tool": ("tool", "edge", "start", "stop", "pieces"),
}
_METRES = "three numbers [d, h, w] in metres"


# ------------------------------------------------------------------ regions (shared with [[regions]])
# ------------------------------------------------------------------ tools that only cut or burn
def tools_with_cutters(src: Source, data: dict, base):
    """The :class:`~torchdeform.scene.tools.ToolSet` of ``data["tools"]``; cutting tools need no contact.

    A tool used by ``[[cuts]]`` or ``[[cautery]]``, or ridden by the ``[camera]``, may have
    ``contact = "none"`` without a grasp (it touches nothing: it cuts, burns or carries the
    camera); any other tool is read by :func:`~torchdeform.scene.tools.tools_section` unchanged.
    """
    from .tools import CONTACTS, tools_section

    items = data["tools"]
    users = {
        e.get("tool")
        for s in ("cuts", "cautery")
        if isinstance(data.get(s), list)
        for e in data[s]
        if isinstance(e, dict)
    }
    if isinstance(data.get("camera"), dict):
        users.add(data["camera"].get("tool"))
    options = {k for keys in CONTACTS.values() for k in keys}
    quiet = []
    if isinstance(items, list):
        for n, item in enumerate(items):
            if (
                isinstance(item, dict)
                and item.get("contact") == "none"
                and "grasp" not in item
                and item.get("name", f"tool{n + 1}") in users
                and not options & set(item)
            ):
                quiet.append(n)
        items = [{**item, "contact": "projection"} if n in quiet else item for n, item in enumerate(items)]
    tools = tools_section(src, items, base)
    for n in quiet:
        tools.contacts[n] = ("none", {})
    return tools


# ------------------------------------------------------------------ reading
@dataclass(eq=False)
class TopologySet:
    """The topology changes of a scene and its surface times; builds fresh events for every run.

    Args:
        grid: the scene's grid.
        source: the scene file (for errors found when the run's length is known).
        cuts: per ``[[cuts]]`` table a dict: ``key``, ``gape`` and either ``blade``
            (:class:`~torchdeform.topology.Blade`) and ``at``, or ``tool``, ``edge``, ``start``,
            ``stop`` (None: the end), ``pieces``.
        cautery: per ``[[cautery]]`` table: ``key``, ``tool``, ``at`` (or None), ``every``, ``start``, ``stop``.
        tear: ``{"key", "max_strain" or "max_force", "one_per_step", "start"}`` or None.
        coagulate: per table: ``key``, ``at``, ``region`` (bool ``(D, H, W)``), ``viscosity_factor``.
        surfaces: times (s) at which the pieces' surfaces are written.
        times: ``[(dotted key, time)]`` checked against the run's length.
        tools: the tools by name.
    """

    grid: Grid
    _: KW_ONLY
    source: Source = field(default_factory=Source)
    cuts: list = field(default_factory=list)
    cautery: list = field(default_factory=list)
    tear: dict | None = None
    coagulate: list = field(default_factory=list)
    surfaces: list = field(default_factory=list)
    times: list = field(default_factory=list)
    tools: dict = field(default_factory=dict)
    #: the run's length the times were checked against when the file was read (``dt`` a number), or None:
    #: ``run_scene`` checks them when it starts (a scene changed from Python afterwards is not checked again)
    checked_end: float | None = None

    def body_box(self) -> tuple:
        """The rest bounding box ``(low (3,), high (3,))`` of the body's nodes (m)."""
        X = self.grid.rest_positions(dtype=torch.float64)[0][:, self.grid.nodes()]
        return tuple(X.amin(1).tolist()), tuple(X.amax(1).tolist())

    def check(self, end: float) -> None:
        """Raise a located ConfigError for a time outside ``[0, end]`` or a scalpel that misses the body."""
        tol = 1e-9 * max(1.0, end)
        for key, value in self.times:
            if not -tol <= value <= end + tol:
                raise self.source.error(
                    key, f"a time in [0, {end:g}] s (the run lasts steps x dt = {end:g} s)", got=value
                )
        lo, hi = self.body_box()
        for c in self.cuts:
            if "tool" not in c:
                continue
            scalpel = Scalpel(self.tools[c["tool"]], c["edge"])
            stop = end if c["stop"] is None else c["stop"]
            edges = torch.stack([scalpel.edge_at(c["start"] + (stop - c["start"]) * i / 256) for i in range(257)])
            box = (edges.flatten(0, 1).amin(0).tolist(), edges.flatten(0, 1).amax(0).tolist())
            if not _meets(box, (lo, hi)):
                raise self.source.error(
                    f"{c['key']}.edge",
                    f"an edge that reaches the body (its path from "
                    f"{c['start']:g} to {stop:g} s stays within {_box_text(box)}, the body's "
                    f"rest box is {_box_text((lo, hi))})",
                    got=[list(p) for p in c["edge"]],
                )

    def prepare(self, model):
        """A copy of ``model`` for one run: its spring and node fields its own, stored per slot (editable)."""
        model = copy.copy(model)
        for name in ("stiffness", "rest_length", "damping", "mass", "inv_mass", "free", "k_home"):
            if getattr(model, name) is not None:
                setattr(model, name, getattr(model, name).clone())
        model = editable(model)
        model.constrained = model.constrained.clone()
        model.removed = model.removed.clone() if model.removed is not None else None
        model.cut_nodes = model.cut_nodes.clone() if model.cut_nodes is not None else None
        return model

    def events(
        self, model, dt: float, end: float, *, out_dir=None, embedded: dict | None = None, every: int = 1
    ) -> TopologyEvents:
        """Fresh :class:`TopologyEvents` for one run of ``model`` (from :meth:`prepare`).

        ``embedded``: the run's embedded surfaces ``{name: EmbeddedSurface}`` (cut with the lattice),
        ``every``: the steps between recorded frames (when a scalpel's sweep reaches them).
        """
        return TopologyEvents(self, model, dt, end, out_dir=out_dir, embedded=embedded, every=every)


def _meets(a, b) -> bool:
    """The boxes ``(lo, hi)`` overlap (touching counts)."""
    tol = 1e-12
    return all(a[0][i] <= b[1][i] + tol and b[0][i] <= a[1][i] + tol for i in range(3))


def _box_text(box) -> str:
    return "[" + ", ".join(f"{lo:g}..{hi:g}" for lo, hi in zip(*box)) + "] m"


def _points(t: Table, k: str, n: int, expected: str) -> list:
    """A list of ``n`` points ``[d, h, w]`` (``n`` None: two or more)."""
    v = t.raw(k, expected)
    ok = (
        isinstance(v, list)
        and (len(v) == n if n else len(v) >= 2)
        and all(isinstance(p, list) and len(p) == 3 and all(is_number(c) for c in p) for p in v)
    )
    if not ok:
        raise t.fail(k, expected, got=v)
    return [tuple(float(c) for c in p) for p in v]


def _time(t: Table, k: str, times: list, default: float | None = 0.0):
    v = t.num(k, "a time >= 0 (s)", default=default, lo=0)
    if k in t.data:
        times.append((t.key(k), v))
    return v


def _tool(t: Table, tools) -> str:
    names = tools.names if tools is not None else []
    expected = "the name of a [[tools]] tool " + (f"({', '.join(names)})" if names else "(there is none)")
    name = t.raw("tool", expected)
    if not isinstance(name, str) or name not in names:
        raise t.fail("tool", expected, got=name)
    return name


def _cut(t: Table, grid, tools, out: TopologySet) -> dict:
    which = t.one_of(*CUT_FORMS)
    for k in t.data:
        if k != "gape" and k not in CUT_FORMS[which]:
            owner = next(f for f, keys in CUT_FORMS.items() if k in keys)
            raise t.fail(k, f"no {k} with {which} = .. (it goes with {owner} = ..)", got=t.data[k])
    entry = {
        "key": t.name,
        "gape": t.num("gape", "a fraction in [0, 1) of the rest length", default=0.0, lo=0, hi=1, hi_open=True),
    }
    if which == "tool":
        entry["tool"] = _tool(t, tools)
        edge = _points(t, "edge", 2, "the cutting edge's two ends [[d, h, w], [d, h, w]] in the tool's frame (m)")
        with t.src.located(t.key("edge"), keys={"scalpel.edge": t.key("edge"), "scalpel.pieces": t.key("pieces")}):
            Scalpel(out.tools[entry["tool"]], edge)
        start, stop = _time(t, "start", out.times), _time(t, "stop", out.times, None)
        if stop is not None and stop <= start:
            raise t.fail("stop", f"a time after start ({start:g} s)", got=stop)
        entry.update(
            edge=tuple(edge),
            start=start,
            stop=stop,
            pieces=t.integer("pieces", "an integer >= 1 (triangles per step)", default=1, lo=1),
        )
        return entry
    key = t.key(which)
    if which == "origin":
        with t.src.located(key):
            blade = Blade(
                t.vec("origin", _METRES),
                t.vec("u", "three numbers [ud, uh, uw] in metres (an edge)"),
                t.vec("v", "three numbers [vd, vh, vw] in metres (an edge)"),
                key=key,
            )
    elif which == "triangle":
        corners = _points(t, "triangle", 3, "three corners [[d, h, w], [d, h, w], [d, h, w]] in metres")
        with t.src.located(key):
            blade = Blade.triangle(*corners, key=key)
    else:
        v = t.data["edges"]
        expected = "the edge's ends at two or more poses [[[d, h, w], [d, h, w]], ...] in metres"
        if not (
            isinstance(v, list)
            and len(v) >= 2
            and all(
                isinstance(e, list)
                and len(e) == 2
                and all(isinstance(p, list) and len(p) == 3 and all(is_number(c) for c in p) for p in e)
                for e in v
            )
        ):
            raise t.fail("edges", expected, got=v)
        with t.src.located(key):
            blade = Blade.swept(v, key=key)
    box = blade.bounds()
    body = out.body_box()
    if not _meets(box, body):
        raise t.fail(
            which,
            f"a blade that reaches the body (the blade lies within {_box_text(box)}, the body's "
            f"rest box is {_box_text(body)})",
            got=t.data[which],
        )
    entry.update(blade=blade, at=_time(t, "at", out.times))
    return entry


def _cautery(t: Table, tools, out: TopologySet) -> dict:
    entry: dict[str, Any] = {"key": t.name, "tool": _tool(t, tools)}
    if t.has("at"):
        for k in ("every", "start", "stop"):
            t.only_with(k, "at")
        entry.update(at=_time(t, "at", out.times), every=1, start=0.0, stop=None)
        return entry
    start, stop = _time(t, "start", out.times), _time(t, "stop", out.times, None)
    if stop is not None and stop < start:
        raise t.fail("stop", f"a time not before start ({start:g} s)", got=stop)
    entry.update(
        at=None,
        every=t.integer("every", "an integer >= 1 (steps between burns)", default=1, lo=1),
        start=start,
        stop=stop,
    )
    return entry


def _tear(t: Table, out: TopologySet) -> dict:
    which = t.one_of("max_strain", "max_force")
    expected = (
        "a positive strain l / l0 - 1 at which a spring breaks"
        if which == "max_strain"
        else "a positive force (N) at which a spring breaks"
    )
    return {
        "key": t.name,
        which: t.num(which, expected, lo=0, lo_open=True),
        "one_per_step": t.flag("one_per_step", default=False),
        "start": _time(t, "start", out.times),
    }


def _coagulate(t: Table, grid, out: TopologySet) -> dict:
    return {
        "key": t.name,
        "at": _time(t, "at", out.times),
        "region": region_mask(t, grid),
        "viscosity_factor": t.num("viscosity_factor", "a factor >= 1 (the rise of the damping)", default=1.0, lo=1),
    }


def topology_section(src: Source, data: dict, grid, tools, out: Table, *, end: float | None = None) -> TopologySet:
    """The :class:`TopologySet` of a scene's topology sections and ``[output] surfaces``.

    The sections: ``[[cuts]]``, ``[[cautery]]``, ``[tear]`` and ``[[coagulate]]`` (module docstring).

    Args:
        src: the file (for located errors).
        data: its parsed TOML.
        grid: the scene's grid.
        tools: its :class:`~torchdeform.scene.tools.ToolSet`, or None.
        out: the ``[output]`` table.
        end: the run's length ``steps x dt`` (s) when known (``dt`` a number): times are checked
            now; otherwise when the run starts (:meth:`TopologySet.check`).

    Raises:
        ConfigError: naming the file, the line and the key (``cuts[1].triangle``).
    """
    result = TopologySet(grid, source=src, tools={tool.name: tool for tool in (tools.tools if tools else [])})
    for name in ("cuts", "cautery", "coagulate"):
        if name in data and not isinstance(data[name], list):
            raise src.error(name, f"[[{name}]] tables", got=data[name])
    for n, item in enumerate(data.get("cuts", [])):
        result.cuts.append(_cut(Table(src, f"cuts[{n}]", item, SECTIONS["cuts"]), grid, tools, result))
    for n, item in enumerate(data.get("cautery", [])):
        result.cautery.append(_cautery(Table(src, f"cautery[{n}]", item, SECTIONS["cautery"]), tools, result))
    if "tear" in data:
        result.tear = _tear(Table(src, "tear", data["tear"], SECTIONS["tear"]), result)
    for n, item in enumerate(data.get("coagulate", [])):
        result.coagulate.append(_coagulate(Table(src, f"coagulate[{n}]", item, SECTIONS["coagulate"]), grid, result))
    if out.has("surfaces") and out.data["surfaces"] != "embedded":
        v = out.data["surfaces"]
        expected = (
            "a list of times [t1, t2, ...] (s) at which to write the pieces' surfaces, "
            'or "embedded" (a body of labels: its smooth surfaces at every recorded frame)'
        )
        if not (isinstance(v, list) and v and all(is_number(s) for s in v)):
            raise out.fail("surfaces", expected, got=v)
        if min(v) < 0:
            raise out.fail("surfaces", "times >= 0 (s)", got=v)
        result.surfaces = sorted(float(s) for s in v)
        result.times += [(out.key("surfaces"), s) for s in result.surfaces]
    if end is not None:
        result.check(end)
        result.checked_end = end
    return result


# ------------------------------------------------------------------ running
class TopologyEvents:
    """The topology changes of one run: call it between steps (``simulate``'s ``callback(step, state)``).

    Call :meth:`begin` with the start state before the first step (events at ``t = 0``), the
    instance after every step, and :meth:`outputs` at the end.

    Args:
        spec: the :class:`TopologySet`.
        model: the run's model (from :meth:`TopologySet.prepare`; changed in place).
        dt: the time step (s).
        end: the run's length (s).
        out_dir: where surface files go (None: not written).
        embedded: the run's embedded surfaces ``{name: EmbeddedSurface}``, or None: every cut cuts
            them too (:meth:`~torchdeform.mesh.embed.EmbeddedSurface.cut_patches`), with the same
            blade and at the same node positions as the lattice. A blade cuts them when it cuts the
            springs; a scalpel's sweep reaches them at every recorded frame (``every`` steps) and when
            it stops: the blade it swept since, patch by patch, at the positions of that moment.
        every: the steps between recorded frames.

    Attributes:
        totals: ``{"cut", "tear", "nodes", "mass_kg", "momentum", "coagulated"}`` so far.
        history: ``[(t, springs removed by cuts, by tearing, nodes burnt)]`` (cumulative), one row per
            moment something changed.
        embedded_versions: ``[(t, {name: EmbeddedSurface})]``: the embedded surfaces from the start
            (``t`` None) and after every cut that changed them (``t`` the time it was applied, s).
    """

    def __init__(self, spec: TopologySet, model, dt: float, end: float, *, out_dir=None, embedded=None, every: int = 1):
        self.spec, self.model, self.dt, self.end = spec, model, float(dt), float(end)
        self.embedded_versions: list = [(None, dict(embedded))] if embedded else []
        self.every = max(int(every), 1)
        self._swept_to: list = [None] * len(spec.cuts)  # a scalpel's time swept into the surfaces' pending blade
        self._pending: list = [[] for _ in spec.cuts]  # its patches swept since they were last cut
        self.out = None if out_dir is None else Path(out_dir)
        self.scalpels = [
            Scalpel(spec.tools[c["tool"]], c["edge"], pieces=c["pieces"], gape=c["gape"]) if "tool" in c else None
            for c in spec.cuts
        ]
        self.started = [False] * len(spec.cuts)
        self.done = {
            "cuts": [False] * len(spec.cuts),
            "cautery": [False] * len(spec.cautery),
            "coagulate": [False] * len(spec.coagulate),
            "surfaces": [False] * len(spec.surfaces),
        }
        self.log = {
            c["key"]: {"calls": 0, "first_t_s": None, "last_t_s": None}
            for c in spec.cuts + spec.cautery + spec.coagulate + ([spec.tear] if spec.tear else [])
        }
        self.totals = {"cut": 0, "tear": 0, "nodes": 0, "mass_kg": 0.0, "momentum": [0.0, 0.0, 0.0], "coagulated": 0}
        self.history = [(0.0, 0, 0, 0)]
        self.surface_files = []
        self.blade = None  # the latest blade: its plane splits the surfaces
        self._tol = 1e-6 * self.dt

    def _due(self, t: float, at: float) -> bool:
        return t >= at - self._tol

    def _note(self, key: str, t: float, **counts) -> None:
        entry = self.log[key]
        entry["calls"] += 1
        entry["first_t_s"] = t if entry["first_t_s"] is None else entry["first_t_s"]
        entry["last_t_s"] = t
        for k, v in counts.items():
            entry[k] = entry.get(k, 0) + v

    def begin(self, state: State) -> None:
        """The events at ``t = 0`` (before the first step)."""
        self(0, state)

    def __call__(self, step: int, state: State) -> None:
        """Apply what is due at ``state.t`` (after step ``step``; 0 before the first)."""
        t = float(state.t)
        before = (self.totals["cut"], self.totals["tear"], self.totals["nodes"])
        with torch.no_grad():
            self._cuts(step, t, state)
            self._cautery(step, t, state)
            self._coagulate(t, state)
            self._tear(t, state)
        now = (self.totals["cut"], self.totals["tear"], self.totals["nodes"])
        if now != before:
            self.history.append((t, *now))
        for i, ts in enumerate(self.spec.surfaces):
            if not self.done["surfaces"][i] and self._due(t, ts):
                self.done["surfaces"][i] = True
                self._surfaces(state, ts, t)

    def _cuts(self, step: int, t: float, state: State) -> None:
        """Blades due at ``t`` cut at once; scalpels sweep from ``start`` to ``stop``."""
        model = self.model
        for i, c in enumerate(self.spec.cuts):
            if "blade" in c:
                if not self.done["cuts"][i] and self._due(t, c["at"]):
                    n = cut(model, state.x, c["blade"], gape=c["gape"])
                    self._cut_embedded(c["blade"].patches, state, t)
                    self.blade = c["blade"]
                    self.done["cuts"][i] = True
                    self.totals["cut"] += n
                    self._note(c["key"], t, springs=n)
                continue
            stop = self.end if c["stop"] is None else c["stop"]
            if self.done["cuts"][i] or not self._due(t, c["start"]):
                continue
            knife = self.scalpels[i]
            assert knife is not None  # a cut without a blade is a scalpel's
            if not self.started[i]:  # the sweep starts at `start`, not at this step
                knife.update(model, State(state.x, state.v, t=c["start"]))
                self.started[i] = True
            n = knife.update(model, State(state.x, state.v, t=min(t, stop)))
            self.blade = knife.swept(c["start"], min(t, stop)) or self.blade
            self.totals["cut"] += n
            self._note(c["key"], t, springs=n)
            if self.embedded_versions:  # the sheet of this step: the blade knife.update just cut with
                since = c["start"] if self._swept_to[i] is None else self._swept_to[i]
                piece = knife.swept(since, min(t, stop)) if min(t, stop) > since else None
                self._pending[i] += piece.patches if piece is not None else []
                self._swept_to[i] = min(t, stop)
                if self._pending[i] and (step % self.every == 0 or self._due(t, stop) or self._due(t, self.end)):
                    self._cut_embedded(self._pending[i], state, t)
                    self._pending[i] = []
            if self._due(t, stop):
                self.done["cuts"][i] = True

    def _cut_embedded(self, patches, state: State, t: float) -> None:
        """Cut the embedded surfaces with a blade's ``patches`` at the positions of ``state``."""
        if not self.embedded_versions:
            return
        current = self.embedded_versions[-1][1]
        cut_now = {name: s.cut_patches(patches, x=state.x[:1]) for name, s in current.items()}
        if any(cut_now[name] is not s for name, s in current.items()):
            self.embedded_versions.append((t, cut_now))

    def _cautery(self, step: int, t: float, state: State) -> None:
        """Burns due at ``t``: once (``at``) or every ``every`` steps from ``start`` to ``stop``."""
        for i, c in enumerate(self.spec.cautery):
            if self.done["cautery"][i]:
                continue
            if c["at"] is not None:
                if not self._due(t, c["at"]):
                    continue
                self.done["cautery"][i] = True
            else:
                stop = self.end if c["stop"] is None else c["stop"]
                if not self._due(t, c["start"]) or (step % c["every"] and not self._due(t, stop)):
                    continue
                if self._due(t, stop):
                    self.done["cautery"][i] = True
            state.v = state.v.clone()  # a recorded frame may share the velocities
            burnt = cauterize(self.model, state, self.spec.tools[c["tool"]])
            self.totals["nodes"] += burnt["nodes"]
            self.totals["mass_kg"] += burnt["mass_kg"]
            self.totals["momentum"] = [a + b for a, b in zip(self.totals["momentum"], burnt["momentum"])]
            self._note(c["key"], t, nodes=burnt["nodes"], mass_kg=burnt["mass_kg"])

    def _coagulate(self, t: float, state: State) -> None:
        """Coagulations due at ``t``."""
        for i, c in enumerate(self.spec.coagulate):
            if not self.done["coagulate"][i] and self._due(t, c["at"]):
                n = coagulate(
                    self.model, state.x[:1], c["region"].to(state.x.device), viscosity_factor=c["viscosity_factor"]
                )
                self.done["coagulate"][i] = True
                self.totals["coagulated"] += n
                self._note(c["key"], t, springs=n)

    def _tear(self, t: float, state: State) -> None:
        """Tearing from ``start`` on: springs past the strain limit break."""
        spec, model = self.spec.tear, self.model
        if spec is not None and self._due(t, spec["start"]):
            limit = spec.get("max_strain")
            if limit is None:
                limit = strain_limit_from_force(model, spec["max_force"])
            n = tear(model, state.x, limit, one_per_step=spec["one_per_step"])
            self.totals["tear"] += n
            if n:
                self._note("tear", t, springs=n)

    def pieces(self) -> torch.Tensor:
        """Labels ``(D, H, W)`` of the pieces whose surfaces are drawn (Punak: one surface per side).

        The components of the body, each split by the plane of the latest blade (rest positions:
        the material side), so a partial cut shows as two closed faces with the opening between.
        """
        labels, _ = components(self.model)
        if self.blade is None:
            return labels
        side = (sides(self.model.X, self.blade)[0, 0] > 0).to(labels.device)
        split = torch.where(labels >= 0, labels * 2 + side, labels)
        ids = torch.unique(split[split >= 0])
        return torch.where(split >= 0, torch.searchsorted(ids, split), split)

    def _surfaces(self, state: State, ts: float, t: float) -> None:
        _, count = components(self.model)
        labels = self.pieces()
        files = []
        if self.out is not None:
            pieces = cut_surfaces(self.model.grid, state.x[:1].detach().double().cpu(), labels.cpu())
            paths = save_cut_surfaces(self.out, pieces, stem=f"surface_{ts * 1e3:g}ms")
            files = [p.name for p in paths]
        self.surface_files.append({"t_s": ts, "step_t_s": t, "components": count, "files": files})

    def summary(self) -> dict:
        """The ``"topology"`` part of ``summary.json``."""
        _, count = components(self.model)
        springs = int(alive(self.model)[0].sum())
        sections = {}
        for key, entry in self.log.items():
            if entry["calls"]:
                sections[key] = {k: (round(v, 12) if isinstance(v, float) else v) for k, v in entry.items()}
        return {
            "springs_removed_by_cuts": self.totals["cut"],
            "springs_removed_by_tear": self.totals["tear"],
            "cautery_nodes_removed": self.totals["nodes"],
            "cautery_mass_removed_kg": self.totals["mass_kg"],
            "cautery_momentum_removed_kg_m_per_s": self.totals["momentum"],
            "coagulated_springs": self.totals["coagulated"],
            "springs_left": springs,
            "components": count,
            "sections": sections,
            "surfaces": self.surface_files,
            "outputs": ["topology.png"] + [f for s in self.surface_files for f in s["files"]],
        }

    def outputs(self, state: State, out_dir, *, title: str = "") -> dict:
        """Write ``topology.png``; return :meth:`summary`."""
        summary = self.summary()
        labels, _ = components(self.model)
        x = state.x[:1].detach().double().cpu()
        plot_topology(
            Path(out_dir) / "topology.png",
            np.array(self.history + [(float(state.t),) + self.history[-1][1:]]),
            x[0].numpy(),
            labels.cpu().numpy(),
            title=title,
            surfaces=cut_surfaces(self.model.grid, x, self.pieces().cpu()),
        )
        return summary


# ------------------------------------------------------------------ the figure
def plot_topology(
    path, history: np.ndarray, x: np.ndarray, labels: np.ndarray, *, title: str = "", surfaces=None
) -> None:
    """Write ``topology.png``: changes over time, the final nodes by component in two slices, the final surfaces.

    Args:
        path: the PNG file.
        history: ``(T, 4)``: time (s), springs removed by cuts, by tearing, nodes burnt (cumulative).
        x: final node positions ``(3, D, H, W)`` (m).
        labels: components ``(D, H, W)`` (negative: not in the body).
        title: the figure's title.
        surfaces: optional :class:`~torchdeform.topology.surfaces.CutSurface` list of the final
            frame, drawn shaded in 3-D (axis D up) in a fourth panel.
    """
    from ..outputs import figure

    fig = figure(figsize=(17.5 if surfaces else 13, 4.2))
    left, mid, right = fig.subplots(1, 4 if surfaces else 3)[:3]
    if surfaces:
        _surface_panel(fig.add_subplot(1, 4, 4, projection="3d"), surfaces)
        fig.axes[3].remove()
    for col, name in ((1, "springs cut"), (2, "springs torn"), (3, "nodes burnt")):
        if history[:, col].any():
            left.step(history[:, 0], history[:, col], where="post", label=name)
    left.set_xlabel("time (s)")
    left.set_ylabel("count (cumulative)")
    left.set_title("topology changes")
    left.grid(alpha=0.3)
    if left.lines:
        left.legend(loc="best", fontsize="small")
    inside = labels >= 0
    ids = np.unique(labels[inside])
    colour = np.searchsorted(ids, np.where(inside, labels, ids[0] if len(ids) else 0))
    D, H, _ = labels.shape
    views = (
        (mid, (slice(None), H // 2, slice(None)), (2, 0), f"w-d slice at h node {H // 2}"),
        (right, (D - 1, slice(None), slice(None)), (2, 1), f"h-w, top layer (d node {D - 1})"),
    )
    for ax, at, (a, b), name in views:
        keep = inside[at]
        p = x[(slice(None),) + at][:, keep] * 1e3
        ax.scatter(p[a], p[b], c=colour[at][keep], cmap="tab10", vmin=0, vmax=9, s=8)
        ax.set_xlabel("dhw"[a] + " (mm)")
        ax.set_ylabel("dhw"[b] + " (mm)")
        ax.set_aspect("equal")
        ax.set_title(f"final nodes by component ({len(ids)}): {name}", fontsize="small")
    if title:
        fig.suptitle(title)
    save_figure(fig, path, dpi=100)


def _surface_panel(ax, surfaces) -> None:
    """The cut surfaces shaded by a light from above (Lambert), axis D up, in millimetres."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    light = np.array([0.8, -0.3, 0.5])
    light /= np.linalg.norm(light)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for k, piece in enumerate(surfaces):
        v = piece.vertices[:, [2, 1, 0]] * 1e3  # (w, h, d): d drawn upwards
        tri = v[piece.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.65 * np.abs(n @ light[[2, 1, 0]])
        base = np.array([0.85, 0.45, 0.4]) if k % 2 == 0 else np.array([0.45, 0.6, 0.85])
        ax.add_collection3d(Poly3DCollection(tri, facecolors=shade[:, None] * base, edgecolors="none"))
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    span = np.maximum(hi - lo, 0.05 * (hi - lo).max() + 1e-9)  # a flat body keeps a visible extent
    mid = (hi + lo) / 2
    for axis, c, w in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid, span):
        axis(c - w / 2, c + w / 2)
    ax.set_box_aspect(tuple(span))
    ax.view_init(elev=55, azim=-60)
    ax.set_xlabel("w (mm)")
    ax.set_ylabel("h (mm)")
    ax.set_zlabel("d (mm)")
    ax.set_title(f"final surface ({len(surfaces)} piece(s))", fontsize="small")
