r"""Scenes of several bodies touching each other: ``[[bodies]]`` entries, one run for all.

A scene file with ``[[bodies]]`` entries holds several mass-spring bodies, each on its own grid
placed in the world by ``[bodies.grid] origin`` (m), stepped together by
:class:`~torchdeform.interact.bodies.Bodies` (one integrator, then the contacts between them).

**Syntax.** Each ``[[bodies]]`` entry has a ``name`` (letters, digits, ``_`` and ``-``; unique) and
the sections of one body as its sub-tables: :data:`PER_BODY` (``[bodies.grid]``,
``[bodies.material]``, ``[bodies.mass]``, ``[bodies.boundary]``, ``[[bodies.regions]]``,
``[[bodies.tissues]]``, ``[[bodies.loads]]``, ``[[bodies.drags]]``, ``[[bodies.tools]]``,
``[bodies.strain_limit]``). ``[integrator]`` (required), ``[output]`` (``record_every``, ``name``) and
``[contact]`` (``friction``, the Coulomb coefficient between bodies, 0) are global; ``[output]`` also
takes the animation's keys (``animation``, ``image_size``, ``camera``, ``camera_up``, as for one body).
A tool touches only the body that lists it. Topology changes, volumes, textures, embedded surfaces,
surface files, palpation, ``settle`` and the static solve are single-body features, refused here with
one line.

**Building.** Each body is a single-body document (its sub-tables plus the global
``[integrator]`` and ``[output]``) built by :func:`~torchdeform.scene.mass_spring.mass_spring_scene`,
through a :class:`BodySource` that names its keys ``bodies[n].<key>`` and finds their lines inside the
``n``-th ``[[bodies]]`` entry: every single-body check holds, with the file and line of the key.
Bodies that start inside each other are an error naming both (``bodies[n].grid.origin``).

**Run** (:func:`run_bodies`): ``dt = "auto"`` is ``safety`` times the smallest of the bodies'
stability bounds. Writes ``trajectory.npz`` (``t`` ``(T,)`` s; per body ``<name>.x`` ``(T, 3, D, H,
W)`` m, ``<name>.X`` rest positions ``(3, D, H, W)``, ``<name>.node_mask`` ``(D, H, W)``; ``names``),
``contact.png`` and ``summary.json``: per body the nodes, peak and final largest displacement (m),
final support reaction (N, bodies with fixed nodes) and tool forces; per pair ``"<a>/<b>"`` the series
at the recorded frames (``t_s``): ``force_N`` ``(T, 3)`` (the force ``a`` exerts on ``b``, averaged over
the steps since the previous frame: momentum over time), ``contacts`` (nodes of either body inside
the other, at the frame's step) and ``penetration_m`` (the deepest before projection over those
steps), with their maxima. With ``[output] animation = true``, ``animation.gif`` (:func:`animate_bodies`):
every body's surface in its own colour, the tools, and the contact force per pair over time. The
browser viewer (``torchdeform view``) shows such a scene too (:mod:`torchdeform.view.bodies`).
"""

from __future__ import annotations

import copy
import math
import re
import time
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..checks import read_text
from ..errors import ConfigError, DivergenceError
from ..interact.bodies import Bodies, Body, rest_member
from ..interact.reactions import support_reaction
from ..outputs import manifest, require_finite, save_figure, summary_json
from ..sim.integrators import Integrator
from ..sim.stability import check_dt, time_step_bound
from .mass_spring import EXPLICIT, mass_spring_scene
from .reader import LISTS, MISSING, SECTIONS, Source, Table, check_sections, read
from .tools import ToolRecorder, tool_forces_at

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # pyright: ignore[reportMissingImports]  # installed on Python 3.10 only

__all__ = [
    "BodiesScene",
    "BodiesFile",
    "BodySource",
    "bodies_scene",
    "run_bodies",
    "bodies_report",
    "animate_bodies",
    "read_scene",
    "check_bodies_sections",
    "PER_BODY",
    "GLOBAL",
]

#: the sections each ``[[bodies]]`` entry holds as sub-tables (those of one mass-spring body)
PER_BODY = ("grid", "material", "regions", "tissues", "mass", "boundary", "loads", "drags", "tools", "strain_limit")
#: the global sections of a scene of several bodies, and their keys (``[integrator]``: as for one body)
GLOBAL = {
    "integrator": None,
    "output": ("record_every", "name", "animation", "image_size", "camera", "camera_up"),
    "contact": ("friction",),
}
#: ``[integrator]`` settings a scene of several bodies refuses, and why
_NO_INTEGRATOR = {
    "settle": "no settle with several bodies (start them apart and let them fall, with [bodies.boundary] decay)",
}
_NAME = re.compile(r"[A-Za-z0-9_-]+")
_BODY_HEADER = re.compile(r"^\s*\[\[\s*bodies\s*\]\]")
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?")
_NOT_YET = "a single-body feature, not with several bodies yet"


# ------------------------------------------------------------------ reading
class BodiesFile(Source):
    """A scene file of several bodies: :meth:`line_of` finds ``bodies[n].<key>`` inside the n-th entry."""

    def line_of(self, key: str) -> int | None:
        """1-based line of a dotted key (``bodies[1].material.stiffness``, ``integrator.dt``), else None."""
        if key.startswith("bodies["):
            return body_line(self.path, self.text, key)
        return super().line_of(key)


class BodySource(BodiesFile):
    r"""The scene file seen from body ``index``: keys of per-body sections become ``bodies[index].<key>``.

    Errors built through it (by the single-body builder) name the file and the line of the key
    inside the ``index``-th ``[[bodies]]`` entry; keys of the global sections keep their own lines.

    Example:
        >>> text = '[[bodies]]\nname = "a"\n[bodies.material]\nstiffness = 1\n\n[[bodies]]\nname = "b"\n' \
        ...        '[bodies.material]\nstiffness = -1\n[integrator]\ndt = 1\n'
        >>> src = BodySource(Source(path="s.toml", text=text), 1)
        >>> print(src.error("material.stiffness", "a number >= 0", got=-1))
        s.toml:9: bodies[1].material.stiffness: expected a number >= 0, got -1
        >>> src.line_of("integrator.dt"), src.line_of("bodies[0].material.stiffness")
        (11, 4)
    """

    def __init__(self, src: Source, index: int):
        super().__init__(path=src.path, text=src.text)
        self.index = index

    def scene_key(self, key: str) -> str:
        """``grid.origin`` -> ``bodies[n].grid.origin``; keys of the global sections as they are."""
        first = re.sub(r"\[\d+\]$", "", key.split(".")[0])
        return f"bodies[{self.index}].{key}" if first in PER_BODY else key

    def error(self, key: str, expected: str, *, got=MISSING) -> ConfigError:
        """A ConfigError for the body's dotted ``key`` (named ``bodies[n].<key>``), located in the file."""
        return super().error(key if key.startswith("bodies[") else self.scene_key(key), expected, got=got)

    def line_of(self, key: str) -> int | None:
        """1-based line of a key of this body (``material.stiffness``) or of the file (``bodies[1].name``)."""
        return super().line_of(key if key.startswith("bodies[") else self.scene_key(key))


def body_line(path, text: str, key: str) -> int | None:
    r"""1-based line of ``bodies[n].<key>`` (``bodies[1].tools[0].radius``): searched inside the n-th entry.

    The entry runs from its ``[[bodies]]`` header to the next header that is not one of its
    sub-tables (``[bodies.<section>]``, ``[[bodies.<section>]]``).

    Example:
        >>> text = '[[bodies]]\nname = "a"\n[[bodies]]\nname = "b"\n[[bodies.tools]]\nname = "t"\n' \
        ...        '[[bodies.tools]]\nradius = 1\n'
        >>> body_line(None, text, "bodies[1].tools[1].radius"), body_line(None, text, "bodies[0].name")
        (8, 2)
    """
    m = re.fullmatch(r"bodies\[(\d+)\](?:\.(.*))?", key)
    if m is None:
        return Source(path=path, text=text).line_of(key)
    lines = text.splitlines()
    starts = [i for i, line in enumerate(lines) if _BODY_HEADER.match(line)]
    n = int(m.group(1))
    if n >= len(starts):
        return None
    start = starts[n]
    end = next(
        (
            i
            for i in range(start + 1, len(lines))
            if (h := _HEADER.match(lines[i])) and not h.group(1).startswith("bodies.")
        ),
        len(lines),
    )
    masked = "\n".join(line if start <= i < end else "" for i, line in enumerate(lines))
    return Source(path=path, text=masked).line_of("bodies" + (f".{m.group(2)}" if m.group(2) else ""))


def read_scene(path) -> tuple[Source, dict]:
    """Read and parse a scene file (``(source, data)``), checked as :func:`~torchdeform.scene.reader.read` does.

    A file with ``[[bodies]]`` is checked by :func:`check_bodies_sections`, any other by
    :func:`~torchdeform.scene.reader.read` (which also reports syntax errors with their line).
    """
    text = read_text(Path(path), "scene", what="scene file (.toml)")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return read(path)  # raises the located syntax error
    if "bodies" not in data:
        return read(path)
    src = BodiesFile(path=Path(path), text=text)
    check_bodies_sections(src, data)
    return src, data


def check_bodies_sections(src: Source, data: dict) -> None:
    """Check a scene of several bodies: its top-level sections, the entries' names and their sections' keys.

    Raises:
        ConfigError: naming the file and line: a top-level body section beside ``[[bodies]]``, an
            unknown or unsupported section or key, a body without a name or with another's name,
            ``[integrator]`` missing (the first problem by line).
    """
    bodies = data["bodies"]
    errors = _top_level_errors(src, data) + _global_errors(src, data)
    if not isinstance(bodies, list) or not bodies:
        errors.append(src.error("bodies", "[[bodies]] tables, one per body", got=bodies))
        bodies = []
    errors += _entry_errors(src, bodies)
    if errors:
        raise sorted(errors, key=lambda e: (e.line is None, e.line or 0))[0]
    for n in range(len(bodies)):  # each body's sections, as one body's, keys named bodies[n].<key>
        check_sections(BodySource(src, n), body_document(data, n))


def _top_level_errors(src: Source, data: dict) -> list:
    """The model and the top-level sections: no body section beside ``[[bodies]]``, no unknown one."""
    errors = []
    model = data.get("model", "mass-spring")
    if model != "mass-spring":
        errors.append(src.error("model", '"mass-spring" (the default) in a scene of several bodies', got=model))
    for name in data:
        if name in ("model", "bodies") or name in GLOBAL:
            continue
        if name in PER_BODY:
            sub = f"[[bodies.{name}]]" if name in LISTS else f"[bodies.{name}]"
            errors.append(
                src.error(name, f"no top-level [{name}] beside [[bodies]] (each body has its own {sub})", got=name)
            )
        elif name in SECTIONS:
            errors.append(src.error(name, f"no [{name}] in a scene of several bodies ({_NOT_YET})", got=name))
        else:
            expected = "one of the sections [[bodies]], " + ", ".join(f"[{s}]" for s in GLOBAL)
            errors.append(src.error(name, expected, got=name))
    if "integrator" not in data:
        errors.append(src.error("integrator", "a [integrator] section (required)"))
    return errors


def _global_errors(src: Source, data: dict) -> list:
    """The keys of ``[output]`` and ``[contact]``, and the ``[integrator]`` settings several bodies refuse."""
    errors = []
    for name in ("output", "contact"):
        table = data.get(name)
        if name in data and not isinstance(table, dict):
            errors.append(src.error(name, "a table", got=table))
        elif isinstance(table, dict):
            for k in table:
                if k in GLOBAL[name]:
                    continue
                if name == "output" and k in SECTIONS["output"]:
                    expected = f"no {k} with several bodies (surface files and palpation are single-body features)"
                else:
                    expected = "one of the keys " + ", ".join(GLOBAL[name])
                errors.append(src.error(f"{name}.{k}", expected, got=k))
    integrator = data.get("integrator")
    if not isinstance(integrator, dict):
        return errors
    if integrator.get("name") == "static":
        expected = "a time integrator (a static solve has no contacts between bodies)"
        errors.append(src.error("integrator.name", expected, got="static"))
    for k, why in _NO_INTEGRATOR.items():
        if k in integrator:
            errors.append(src.error(f"integrator.{k}", why, got=integrator[k]))
    if integrator.get("engine", "auto") not in ("auto", "eager"):
        expected = '"auto" or "eager" (several bodies step eagerly, with their contacts)'
        errors.append(src.error("integrator.engine", expected, got=integrator["engine"]))
    return errors


def _entry_errors(src: Source, bodies: list) -> list:
    """Each ``[[bodies]]`` entry: a table, a unique name, and only the sections of one body."""
    errors, names = [], []
    for n, item in enumerate(bodies):
        where = f"bodies[{n}]"
        if not isinstance(item, dict):
            errors.append(src.error(where, "a table", got=item))
            continue
        name = item.get("name", MISSING)
        if name is MISSING:
            errors.append(src.error(f"{where}.name", "a name for every body (required; letters, digits, _ and -)"))
        elif not (isinstance(name, str) and _NAME.fullmatch(name)):
            errors.append(src.error(f"{where}.name", "a name of letters, digits, _ and -", got=name))
        elif name in names:
            errors.append(src.error(f"{where}.name", "a name no other body has", got=name))
        names.append(name)
        for k in item:
            if k == "name" or k in PER_BODY:
                continue
            if k in GLOBAL:
                expected = f"no [bodies.{k}]: [{k}] is global, one for all bodies"
            elif k in SECTIONS:
                expected = f"no [bodies.{k}] ({_NOT_YET})"
            else:
                expected = "one of the keys name, " + ", ".join(PER_BODY)
            errors.append(src.error(f"{where}.{k}", expected, got=k))
    return errors


def body_document(data: dict, n: int) -> dict:
    """The single-body document of entry ``n``: its sub-tables and the global ``[integrator]``, ``[output]``."""
    doc = {k: v for k, v in data["bodies"][n].items() if k != "name"}
    for k in ("integrator", "output"):
        if k in data:
            doc[k] = data[k]
    return doc


# ------------------------------------------------------------------ the scene
@dataclass(eq=False)
class BodiesScene:
    """A scene of several bodies: one single-body :class:`Scene` per body and the run settings they share.

    Args:
        names: the bodies' names.
        scenes: per body its :class:`~torchdeform.scene.mass_spring.Scene` (its grid, model keywords,
            tools), built from its sub-tables and the global sections.
        friction: Coulomb coefficient between the bodies (``[contact] friction``).
        integrator: the :class:`~torchdeform.sim.integrators.Integrator` of every body.
        dt: seconds, or ``"auto"`` (``safety`` times the smallest of the bodies' bounds).
        steps: number of steps.
        record_every: steps between saved frames (default: about 100 frames).
        name: title of the run.
        dtype, device, threads, safety: as for :class:`Scene`.
        source: the scene file (:class:`Source`) for error messages.
    """

    names: list
    scenes: list
    _: KW_ONLY
    friction: float = 0.0
    integrator: Integrator | None = None
    dt: float | str = "auto"
    steps: int = 1000
    record_every: int | None = None
    name: str = "bodies"
    dtype: torch.dtype = torch.float32
    device: str | None = None
    safety: float = 0.9
    threads: int | None = None
    source: Source = field(default_factory=Source)
    #: per body: True where its ``[bodies.grid]`` gives an ``origin`` (errors of bodies that overlap name it)
    placed: list = field(default_factory=list)
    #: ``"animation.gif"`` for ``[output] animation = true`` (:func:`animate_bodies`), else None
    animation: str | None = None
    #: the side (pixels) of each square panel of the animation (``[output] image_size``)
    image_size: int = 512
    #: the animation's view, ``(3,)`` from the bodies' centre, and the direction upwards in it (``[output]
    #: camera``, ``camera_up``); None: the animation's defaults
    camera: tuple | None = None
    camera_up: tuple | None = None
    #: single-body outputs that a scene of several bodies does not write (yet): always None
    volume: None = None
    texture: None = None

    @property
    def grid(self):
        """The first body's grid (code written for one body reads it); :attr:`grids` has every body's."""
        return self.scenes[0].grid

    @property
    def grids(self) -> dict:
        """``{name: Grid}`` of every body."""
        return {n: s.grid for n, s in zip(self.names, self.scenes)}

    @property
    def frames_every(self) -> int:
        """Steps between saved frames."""
        return self.record_every or max(1, self.steps // 100)

    def time_step(self, bound: float) -> float:
        """The time step (s): ``dt``, or ``safety * bound`` for ``dt = "auto"`` (``bound``: the smallest)."""
        return self.scenes[0].time_step(bound) if self.dt == "auto" else float(self.dt)

    def bodies(self, *, device=None) -> Bodies:
        """A fresh :class:`~torchdeform.interact.bodies.Bodies` on ``device``: each model with fresh tool contacts.

        Raises:
            ConfigError: bodies that start inside each other (naming the file, the line and both bodies).
        """
        bodies = []
        for name, scene in zip(self.names, self.scenes):
            model = scene.build(device=device)
            if scene.tools is not None:  # fresh contacts and grasps: they keep state
                model = copy.copy(model)
                model.interactions = scene.tools.interactions()
            bodies.append(Body(name, model))
        return Bodies(bodies, integrator=self.integrator, friction=self.friction)

    def check_apart(self, bodies: Bodies, states: list) -> None:
        """:meth:`Bodies.check_apart`, its error naming the file, the line of the body's origin and both bodies."""
        try:
            bodies.check_apart(states)
        except ConfigError as e:
            if e.file is not None:
                raise
            raise self.apart_error(e) from None

    def apart_error(self, e: ConfigError) -> ConfigError:
        """The located form of :meth:`Bodies.check_apart`'s error ``e`` (key ``bodies.<name>``)."""
        name = e.key.split(".", 1)[1] if e.key.startswith("bodies.") else None
        n = self.names.index(name) if name in self.names else 0
        key = f"bodies[{n}].grid.origin" if n < len(self.placed) and self.placed[n] else f"bodies[{n}].grid"
        return self.source.error(key, e.expected + "; move one with [bodies.grid] origin (m)")

    def run(self, out_dir, *, progress: bool = True, device=None) -> dict:
        """Run the scene into ``out_dir`` (:func:`run_bodies`); returns the summary."""
        return run_bodies(self, Path(out_dir), progress=progress, device=device)


def bodies_scene(src: Source, data: dict, base: Path, *, name: str = "scene") -> BodiesScene:
    """Build a :class:`BodiesScene` from a parsed scene file with ``[[bodies]]`` (checked by :func:`read_scene`).

    Each body is built by :func:`~torchdeform.scene.mass_spring.mass_spring_scene` from its
    single-body document (:func:`body_document`) through a :class:`BodySource`; then the bodies are
    placed and checked to start apart.
    """
    friction = 0.0
    if "contact" in data:
        t = Table(src, "contact", data["contact"], GLOBAL["contact"])
        friction = t.num("friction", "a Coulomb coefficient >= 0 between the bodies", default=0.0, lo=0)
    names, scenes, placed = [], [], []
    for n, item in enumerate(data["bodies"]):
        bsrc = BodySource(src, n)
        try:
            scene = mass_spring_scene(bsrc, body_document(data, n), base, name=item["name"])
        except ConfigError as e:
            if e.file is not None or src.path is None:
                raise
            raise bsrc.error(e.key, e.expected, got=e.got if e.show_got else MISSING) from None
        if scene.tools is not None and scene.tools.palpation is not None:
            raise bsrc.error("output.palpation", f"no palpation with several bodies ({_NOT_YET})")
        placed.append(isinstance(item.get("grid"), dict) and "origin" in item["grid"])
        names.append(item["name"])
        scenes.append(scene)
    first = scenes[0]
    out = data.get("output") or {}
    scene = BodiesScene(
        names,
        scenes,
        friction=friction,
        integrator=first.integrator,
        dt=first.dt,
        steps=first.steps,
        record_every=first.record_every,
        name=out.get("name", name),
        dtype=first.dtype,
        device=first.device,
        safety=first.safety,
        threads=first.threads,
        source=src,
        placed=placed,
        animation=first.animation,
        image_size=first.image_size,
        camera=first.camera,
        camera_up=first.camera_up,
    )
    bodies = scene.bodies(device="cpu")
    scene.check_apart(bodies, bodies.rest_states())
    return scene


# ------------------------------------------------------------------ the run
class _PairRecorder:
    """Per-step contact readings of every pair (batch entry 0), kept on the device until the end."""

    def __init__(self, names: list, steps: int, device, dtype):
        self.pairs = [(i, j, f"{names[i]}/{names[j]}") for i in range(len(names)) for j in range(i + 1, len(names))]
        self.buffer = torch.zeros(int(steps), len(self.pairs), 5, device=device, dtype=dtype)

    def __call__(self, step: int, states: list) -> None:
        row = self.buffer[step - 1]
        for p, (i, _, key) in enumerate(self.pairs):
            readings = states[i].readings or {}
            if f"{key}.force" in readings:
                row[p, :3] = readings[f"{key}.force"][0]
                row[p, 3] = readings[f"{key}.contacts"][0]
                row[p, 4] = readings[f"{key}.penetration"][0]

    def at_frames(self, steps_at: np.ndarray) -> dict:
        """Per pair, at frames taken after ``steps_at`` ``(T,)`` steps: mean force, contacts, deepest penetration."""
        data = self.buffer.detach().to("cpu", torch.float64).numpy()
        out = {}
        for p, (_, _, key) in enumerate(self.pairs):
            force = np.zeros((len(steps_at), 3))
            contacts = np.zeros(len(steps_at))
            depth = np.zeros(len(steps_at))
            for f in range(1, len(steps_at)):
                a, b = int(steps_at[f - 1]), int(steps_at[f])
                if b > a:
                    force[f] = data[a:b, p, :3].mean(0)
                    contacts[f] = data[b - 1, p, 3]
                    depth[f] = data[a:b, p, 4].max()
            out[key] = {"force": force, "contacts": contacts, "penetration": depth}
        return out


def run_bodies(scene: BodiesScene, out: Path, *, progress: bool = True, device=None) -> dict:
    """Run a :class:`BodiesScene`, writing ``trajectory.npz``, ``contact.png`` and ``summary.json`` into ``out``.

    ``out`` is the staging folder of :func:`~torchdeform.scene.run_scene` (whole or nothing); the
    outputs are described in the module docstring. ``scene.threads`` sets torch's CPU threads.

    Returns:
        the summary (also written to ``summary.json``).

    Raises:
        ConfigError: bodies that start inside each other; ``dt = "auto"`` without a finite bound.
        DivergenceError: a recorded frame that is not finite.
    """
    threads = torch.get_num_threads()
    if scene.threads:
        torch.set_num_threads(scene.threads)
    try:
        return _run(scene, Path(out), progress, device)
    finally:
        torch.set_num_threads(threads)


def _run(scene: BodiesScene, out: Path, progress: bool, device) -> dict:
    bodies = scene.bodies(device=device)
    models = [b.model for b in bodies.bodies]
    integrator = bodies.integrator
    bounds = [time_step_bound(m, integrator=integrator) for m in models]
    bound = min(bounds)
    dt = scene.time_step(bound)
    if integrator.name in EXPLICIT:
        for m, b in zip(models, bounds):
            check_dt(m, dt, integrator, bound=b)
    states = bodies.rest_states()
    scene.check_apart(bodies, states)
    every, steps = scene.frames_every, scene.steps
    model0 = models[0]
    pairs = _PairRecorder(scene.names, steps, model0.device, model0.dtype)
    tools = [
        ToolRecorder(s.tools.names, steps, model0.device, model0.dtype)
        if s.tools is not None and s.tools.tools
        else None
        for s in scene.scenes
    ]
    frames = [[s.x[:1].detach().cpu()] for s in states]
    t_frames, steps_at = [0.0], [0]

    def record(k, sts):
        pairs(k, sts)
        for rec, st in zip(tools, sts):
            if rec is not None:
                rec(k, st)
        if k % every == 0 or k == steps:
            for n, st in enumerate(sts):
                x = st.x[:1].detach().cpu()
                if not bool(torch.isfinite(x).all()):
                    raise DivergenceError(
                        k, f"position of body {scene.names[n]}", float("nan"), dt=dt, safe_dt=0.9 * bound
                    )
                frames[n].append(x)
            t_frames.append(float(sts[0].t))
            steps_at.append(k)

    start = time.perf_counter()
    final = bodies.simulate(states, dt=dt, steps=steps, callback=record, progress=progress)
    wall = time.perf_counter() - start

    t = np.asarray(t_frames)
    xs = [torch.cat(f) for f in frames]  # (T, 3, D, H, W)
    arrays: dict = {"t": t, "names": np.array(scene.names), "dt": dt, "integrator": integrator.name}
    summary_bodies = {}
    energy: dict = {}
    for n, (name, body, x) in enumerate(zip(scene.names, bodies.bodies, xs)):
        model = body.model
        require_finite(f"trajectory.npz: {name}.x", x, what="frame, ...", cause="the run diverged")
        X = model.X[0].detach().cpu()
        member = rest_member(model).reshape(model.grid.shape)
        u = (x - X).norm(dim=1).flatten(1)[:, member.flatten()]  # (T, nodes)
        disp = u.amax(1).double().numpy() if u.numel() else np.zeros(len(t))
        arrays[f"{name}.x"] = x.float().numpy()
        arrays[f"{name}.X"] = X.float().numpy()
        arrays[f"{name}.node_mask"] = member.numpy()
        grid = model.grid
        entry = {
            "nodes": grid.num_nodes,
            "grid": {
                "shape": list(grid.shape),
                "spacing": list(grid.spacing),
                "origin": list(grid.origin),
                "topology": grid.topology,
            },
            "peak_displacement_m": float(disp.max()),
            "final_displacement_m": float(disp[-1]),
        }
        with torch.no_grad():
            for k, v in model.energy(final[n]).items():
                energy[k] = energy.get(k, 0.0) + float(v[0])
            if model.free is not None:
                entry["support_reaction_N"] = support_reaction(model, final[n])[0].double().cpu().tolist()
        recorder = tools[n]
        if recorder is not None:
            series = recorder.series()
            entry["tools"] = {
                tool: {
                    "max_force_N": float(np.linalg.norm(series[f"{tool}.force"], axis=1).max(initial=0.0)),
                    "final_force_N": series[f"{tool}.force"][-1].tolist() if len(series["t"]) else [0.0, 0.0, 0.0],
                }
                for tool in recorder.names
            }
        summary_bodies[name] = entry

    contact = pairs.at_frames(np.asarray(steps_at))
    summary_contact = {}
    for key, s in contact.items():
        require_finite(f"summary.json: contact {key}", s["force"], what="frame", cause="the run diverged")
        magnitude = np.linalg.norm(s["force"], axis=1)
        summary_contact[key] = {
            "force_N": s["force"].tolist(),
            "contacts": s["contacts"].tolist(),
            "penetration_m": s["penetration"].tolist(),
            "max_force_N": float(magnitude.max()),
            "final_force_N": s["force"][-1].tolist(),
            "max_contacts": float(s["contacts"].max()),
            "max_penetration_m": float(s["penetration"].max()),
        }
    np.savez(out / "trajectory.npz", **arrays)
    title = f"{scene.name}: {integrator.name}, dt = {dt:.3g} s"
    if contact:
        plot_contact(out / "contact.png", t, contact, title=title)
    animation = None
    if scene.animation:
        animation = animate_bodies(scene, bodies, t, xs, tools, contact, out, progress=progress)
    options = {k: v for k, v in vars(integrator).items() if isinstance(v, (int, float, str)) and not k.startswith("_")}
    summary = {
        "name": scene.name,
        "scene": scene.source.path,
        "bodies": summary_bodies,
        "contact": summary_contact,
        "friction": scene.friction,
        "t_s": t.tolist(),
        "integrator": {"name": integrator.name, **options},
        "steps": steps,
        "dt_s": dt,
        "dt_auto": scene.dt == "auto",
        "simulated_time_s": float(final[0].t),
        "time_step_bound_s": bound if math.isfinite(bound) else None,
        "wall_time_s": wall,
        "steps_per_s": steps / wall if wall > 0 else None,
        "engine": {"requested": "auto", "ran": "eager", "why": "several bodies step eagerly, with their contacts"},
        "nodes": sum(m.grid.num_nodes for m in models),
        "dtype": str(model0.dtype).replace("torch.", ""),
        "device": str(model0.device),
        **({"threads": scene.threads} if scene.threads else {}),
        "frames": len(t),
        "final_energy_J": energy,
        "max_displacement_m": max(b["peak_displacement_m"] for b in summary_bodies.values()),
        "final_displacement_m": max(b["final_displacement_m"] for b in summary_bodies.values()),
    }
    if animation is not None:
        summary["animation"] = animation
    summary["outputs"] = manifest(out)
    (out / "summary.json").write_text(summary_json(summary) + "\n")
    return summary


def animate_bodies(
    scene: BodiesScene,
    bodies: Bodies,
    t: np.ndarray,
    xs: list,
    tools: list,
    contact: dict,
    out: Path,
    *,
    progress=False,
) -> dict:
    """Write ``scene.animation`` (a GIF of every body, :func:`torchdeform.scene.animation.animate_bodies`).

    Each body is drawn in its colour of :data:`~torchdeform.scene.animation.BODY_COLOURS` (in the
    order of ``[[bodies]]``), the tools of every body where they are, the caption gives each tool's
    force and a panel the contact force per pair over time.

    Args:
        scene: the :class:`BodiesScene`.
        bodies: the :class:`~torchdeform.interact.bodies.Bodies` of the run (their grids).
        t: frame times ``(T,)`` (s).
        xs: per body its positions ``(T, 3, D, H, W)`` (m).
        tools: per body its :class:`~torchdeform.scene.tools.ToolRecorder`, or None.
        contact: per pair ``{"force": (T, 3), ...}`` (:meth:`_PairRecorder.at_frames`).
        out: the output folder.
        progress: show a progress bar.

    Returns:
        a summary dict for ``summary.json``: ``file``, ``frames``, ``size``, ``panel``, ``bytes``,
        ``colours`` (per body name, sRGB bytes), ``wall_time_s``.
    """
    from .animation import animate_bodies as animate

    start = time.perf_counter()
    assert scene.animation is not None  # the file name of the animation asked for
    forces, drawn = {}, []
    for s, recorder in zip(scene.scenes, tools):
        if s.tools is None:
            continue
        drawn += list(s.tools.tools)
        if recorder is not None:
            forces.update(tool_forces_at(recorder.series(), s.tools.names, t))
    info = animate(
        [b.model.grid for b in bodies.bodies],
        t,
        xs,
        out / scene.animation,
        names=scene.names,
        tools=drawn,
        forces=forces,
        contact={k: c["force"] for k, c in contact.items()} or None,
        size=scene.image_size,
        camera=scene.camera,
        camera_up=scene.camera_up,
        progress=progress,
    )
    return {k: info[k] for k in ("file", "frames", "size", "panel", "bytes")} | {
        "colours": dict(zip(scene.names, info["colours"])),
        "wall_time_s": time.perf_counter() - start,
    }


def plot_contact(path, t: np.ndarray, contact: dict, *, title: str = "") -> None:
    """Write a PNG: per pair, the contact force's magnitude (N), the contacts and the penetration (mm) over time (s).

    Args:
        path: the PNG file.
        t: frame times ``(T,)`` (s).
        contact: ``{"<a>/<b>": {"force": (T, 3), "contacts": (T,), "penetration": (T,)}}``.
        title: the figure's title.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    fig.subplots_adjust(left=0.12, right=0.97, top=0.94, bottom=0.08, hspace=0.1)
    for key, s in contact.items():
        (line,) = axes[0].plot(t, np.linalg.norm(s["force"], axis=1), label=f"{key}: |F|")
        axes[0].plot(
            t,
            -s["force"][:, 0],
            ls="--",
            color=line.get_color(),
            lw=1,
            label=f"{key}: force on the second body along -D",
        )
        axes[1].plot(t, s["contacts"], color=line.get_color(), label=key)
        axes[2].plot(t, s["penetration"] * 1e3, color=line.get_color(), label=key)
    axes[0].set_ylabel("contact force (N)")
    axes[1].set_ylabel("contacts (nodes)")
    axes[2].set_ylabel("penetration (mm)")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize="small")
    axes[0].set_title(title)
    save_figure(fig, path, dpi=100)


def bodies_report(summary: dict, out_dir) -> str:
    """One line for the CLI: what ran, how fast, the contacts, and where the outputs are."""
    files = summary.get("outputs") or ["trajectory.npz", "summary.json", "contact.png"]
    contacts = ", ".join(
        f"{key} max force {c['max_force_N']:.3g} N, max penetration {c['max_penetration_m'] * 1e3:.3g} mm"
        for key, c in summary["contact"].items()
    )
    bound = summary["time_step_bound_s"]
    bound = f" (bound {bound:.3g} s)" if bound else ""
    return (
        f"{summary['name']}: {len(summary['bodies'])} bodies, {summary['steps']} {summary['integrator']['name']} "
        f"steps of {summary['dt_s']:.3g} s{bound} in {summary['wall_time_s']:.2f} s, max displacement "
        f"{summary['max_displacement_m'] * 1e3:.3g} mm (peak){'; ' + contacts if contacts else ''}; "
        f"wrote {', '.join(files)} to {out_dir}"
    )
