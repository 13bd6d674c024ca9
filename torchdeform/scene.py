"""Scene files (TOML) -> :class:`Model` + integrator + run settings, and the runner.

A scene file only builds the objects of the Python API: :class:`Scene` holds a
:class:`~torchdeform.grid.Grid`, the keyword arguments of :class:`~torchdeform.model.Model`
(``scene.model_args``), an :class:`~torchdeform.integrators.Integrator` and the run settings;
:func:`demo_scene` builds the built-in demo with the API alone. :func:`run_scene` runs a
scene and writes ``trajectory.npz``, ``summary.json`` and ``energy.png``.

Units are SI (m, kg, s, N). Vectors are in channel order ``(D, H, W)``; axis D is "up" in
the built-in scenes (face ``"bottom"`` = ``"d-"``, ``"top"`` = ``"d+"``). Node indices are
``[i, j, k]`` along ``(D, H, W)``, from 0.

Keys
----
``[grid]`` (required)
    ``shape = [D, H, W]``  node counts, each >= 1 (or ``mesh``)
    ``mesh = "organ.stl"``  a closed triangle mesh voxelised into the node mask (instead of
    ``shape``; path relative to the scene file; mesh x, y, z -> D, H, W)
    ``spacing``  metres, one number or ``[sd, sh, sw]`` (required)
    ``topology``  6, 14, 18 or 26 neighbours (default 26)
    ``origin = [od, oh, ow]``  position of node [0, 0, 0] in metres (default 0; ``shape`` only)
    ``padding``  extra node layers around the mesh's bounding box (default 0; ``mesh`` only)
    ``scale``  metres per mesh unit, e.g. 0.001 for a mesh in mm (default 1; ``mesh`` only)
``[material]`` (required)
    ``stiffness``  spring stiffness k in N/m: a number, or one per direction class
    ``{axis = .., face = .., body = ..}`` (only the classes of the topology are needed)
    ``modulus``  instead of ``stiffness``: Y in N, each spring gets ``k = Y / l0``
    (resolution-independent); a number or a table as for ``stiffness``
    ``damping``  dashpot along each spring in N s/m (divided by l0 too with ``modulus``);
    a number or a class table (default: none)
    ``damping_mode``  ``"projected"`` (default) or ``"unprojected"`` (Radetzky)
``[mass]`` (required, exactly one key)
    ``mass``  kg per node, or ``density``  kg/m^3 (lumped from cell volumes)
``[boundary]`` (optional)
    ``fixed``  a face name or a list of them: ``"bottom"``, ``"top"``, ``"d-"``, ``"d+"``,
    ``"h-"``, ``"h+"``, ``"w-"``, ``"w+"``
    ``fixed_nodes = [[i, j, k], ...]``  more fixed nodes
    ``home``  stiffness (N/m) of home springs to every node's rest position (Punak)
    ``anchors = {stiffness = .., every = ..}``  anchor springs (N/m) on every k-th node (Radetzky)
    ``decay``  global drag rate c in 1/s: ``v <- v exp(-c dt)`` each step
    ``gravity = [gd, gh, gw]``  m/s^2
``[[loads]]`` (optional, repeatable), one of
    ``node = [i, j, k]`` with ``force = [fd, fh, fw]`` (N), or
    ``face = "top"`` with ``traction = [td, th, tw]`` (Pa, lumped onto the face's nodes);
    both take ``start`` (s, default 0) and ``ramp`` (s to reach full strength, default 0)
``[[drags]]`` (optional, repeatable): a group of nodes moved rigidly along a path
    ``nodes = [[i, j, k], ...]`` or ``face = "top"`` or ``box = {lo = [..], hi = [..]}``
    (rest positions in metres, bounds included), and
    ``path = [[t, [od, oh, ow]], ...]``  offsets (m) from the rest position at increasing
    times (s), linear in between, held after the last
``[integrator]`` (required)
    ``name``  ``"explicit"``, ``"symplectic"`` (default), ``"verlet"``, ``"rk4"``,
    ``"implicit"`` or ``"knoche"``
    ``dt``  seconds > 0, or ``"auto"`` (explicit integrators: ``safety`` x the stability bound)
    ``safety``  fraction of the bound used by ``dt = "auto"`` (default 0.9)
    ``steps``  number of steps >= 0 (required)
    ``dtype``  ``"float32"`` (default) or ``"float64"``;  ``device``  ``"cpu"`` (default), ``"cuda"``
    options of ``verlet``: ``kd`` (per-step damping in [0, 1), default 0);
    of ``implicit``: ``cg_iters`` (100), ``cg_tol`` (1e-6), ``newton_iters`` (0);
    of ``knoche`` (needs ``topology = 6``): ``material`` (w in [0, 1], a number or a
    ``[D][H][W]`` array), ``eps`` (1e-3), ``gain`` (default 3 / D)
``[output]`` (optional)
    ``record_every``  steps between saved frames (default: about 100 frames)
    ``name``  title of the run (default: the file's name)
``[volume]`` (optional): a volume filling the grid's bounding box, deformed by the final state;
    the run also writes ``volume_before.png``, ``volume_after.png``, ``volume_deformed.npy``
    ``file``  a volume file (.npy, .npz, .nii, .nrrd; relative to the scene file) or ``"phantom:N"``
    ``tf``  transfer-function preset or file (default ``"ct-soft"``); ``mode``  ``"dvr"``
    (default), ``"mip"`` or ``"average"``; ``view``  axis view (default ``"h"``)
``model = "chainmail"`` (optional top-level key, before any section): a ChainMail scene instead
    of a mass-spring one: ``[grid]``, ``[chainmail]`` (required), ``[boundary]`` (``fixed``,
    ``fixed_nodes``), ``[[drags]]`` (the picked elements and their paths), ``[output]``; see
    :func:`torchdeform.chainmail.chainmail_scene` for the ``[chainmail]`` keys

Every problem is a :class:`~torchdeform.errors.ConfigError` naming the file, the line (found
by a text search, best effort), the dotted key (``integrator.dt``, ``loads[0].force``; array
tables count from 0) and what was expected.

Example:
    >>> from torchdeform.scene import demo_scene, run_scene
    >>> summary = run_scene(demo_scene(), "demo-out", progress=False)   # doctest: +SKIP
"""
from __future__ import annotations

import json
import math
import re
import sys
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .errors import ConfigError
from .forces import Drag, PointForce, SurfaceForce
from .grid import CLASSES, FACES, TOPOLOGIES, Grid
from .integrators import INTEGRATORS, Integrator, SymplecticEuler, simulate
from .model import Model, State
from .stability import check_dt, time_step_bound

try:
    import tomllib
except ModuleNotFoundError:                                   # Python 3.10
    import tomli as tomllib

SECTIONS = {
    "grid": ("shape", "mesh", "spacing", "topology", "origin", "padding", "scale"),
    "material": ("stiffness", "modulus", "damping", "damping_mode"),
    "mass": ("mass", "density"),
    "boundary": ("fixed", "fixed_nodes", "home", "anchors", "decay", "gravity"),
    "loads": ("node", "force", "face", "traction", "start", "ramp"),
    "drags": ("nodes", "face", "box", "path"),
    "integrator": ("name", "dt", "safety", "steps", "dtype", "device"),
    "output": ("record_every", "name"),
    "volume": ("file", "tf", "mode", "view"),
    "chainmail": ("method", "compression", "stretch", "shear", "tissue", "reference_stress", "frames",
                  "relax_steps", "relax_mode", "relax_moved_only", "on_blocked"),
}
REQUIRED = ("grid", "material", "mass", "integrator")
#: Options of each integrator (keyword arguments of its class): key -> what is expected.
INTEGRATOR_OPTIONS = {
    "explicit": {}, "symplectic": {}, "rk4": {},
    "verlet": {"kd": "a number in [0, 1)"},
    "implicit": {"cg_iters": "an integer >= 1", "cg_tol": "a positive number", "newton_iters": "an integer >= 0"},
    "knoche": {"material": "a number in [0, 1] or a [D][H][W] array of them", "eps": "a positive number",
               "gain": "a positive number"},
}
EXPLICIT = ("explicit", "symplectic", "verlet", "rk4")
DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: Model keyword -> scene key, to locate errors raised by the core.
MODEL_KEYS = {"stiffness": "material.stiffness", "damping": "material.damping",
              "damping_mode": "material.damping_mode", "mass": "mass", "density": "mass.density",
              "gravity": "boundary.gravity", "home": "boundary.home", "anchors.stiffness": "boundary.anchors.stiffness",
              "anchors.every": "boundary.anchors.every", "decay": "boundary.decay", "fixed": "boundary.fixed"}

_MISSING = object()
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?")


# ------------------------------------------------------------------ locating errors
class Source:
    """A scene file's path and text: builds :class:`ConfigError` s that name file and line."""

    def __init__(self, path=None, text: str = ""):
        self.path, self.text = (None if path is None else str(path)), text

    def error(self, key: str, expected: str, got=_MISSING) -> ConfigError:
        """A ConfigError for the dotted ``key``; ``got`` omitted = not shown."""
        shown = got is not _MISSING
        return ConfigError(key, expected, got if shown else None, file=self.path,
                           line=self.line_of(key) if self.path else None, show_got=shown)

    def line_of(self, key: str) -> int | None:
        """1-based line of a dotted key like ``loads[1].force`` (best effort), else None."""
        lines = self.text.splitlines()
        parts = [re.fullmatch(r"(.*?)(?:\[(\d+)\])?", p).groups() for p in key.split(".")]
        names = [p[0] for p in parts]
        headers = [(i, m.group(1)) for i, line in enumerate(lines) if (m := _HEADER.match(line))]
        start, end, best, rest = -1, headers[0][0] if headers else len(lines), None, names
        for n in range(len(names), 0, -1):                     # longest matching table header
            hits = [i for i, h in headers if h == ".".join(names[:n])]
            index = int(parts[n - 1][1] or 0)
            if len(hits) > index:
                start = best = hits[index]
                end = next((i for i, _ in headers if i > start), len(lines))
                rest = names[n:]
                break
        pos = start + 1
        for name in rest:
            pat = re.compile(r"(^|[\s{,])" + re.escape(name) + r"\s*=")
            found = next((i for i in range(pos, end) if pat.search(lines[i].split("#")[0])), None)
            if found is None:
                break
            best = pos = found
        return None if best is None else best + 1

    @contextmanager
    def located(self, key: str, keys: dict | None = None):
        """Re-raise a core ConfigError as one about scene ``key`` (or ``keys[core key]``)."""
        try:
            yield
        except ConfigError as e:
            if e.file is not None:
                raise
            shown = e.show_got
            if e.key in (keys or {}):
                key = keys[e.key]
            elif e.key.split(".")[0] in SECTIONS and "." in e.key:     # already a scene key
                key = e.key
            raise self.error(key, e.expected, e.got if shown else _MISSING) from None


# ------------------------------------------------------------------ typed values
def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class _Table:
    """One TOML table with its dotted name; typed getters raise located ConfigErrors."""

    def __init__(self, src: Source, name: str, data, allowed):
        if not isinstance(data, dict):
            raise src.error(name, "a table", data)
        unknown = [k for k in data if k not in allowed]
        if unknown:
            raise src.error(f"{name}.{unknown[0]}", "one of the keys " + ", ".join(allowed), unknown[0])
        self.src, self.name, self.data = src, name, data

    def key(self, k: str) -> str:
        return f"{self.name}.{k}"

    def has(self, k: str) -> bool:
        return k in self.data

    def fail(self, k: str, expected: str, got=_MISSING) -> ConfigError:
        return self.src.error(self.key(k), expected, got)

    def raw(self, k, expected, default=_MISSING):
        """The value of ``k``, or ``default``; a missing key without default is an error."""
        if k not in self.data:
            if default is _MISSING:
                raise self.fail(k, expected + " (required)")
            return default
        return self.data[k]

    def num(self, k, expected="a number", default=_MISSING, lo=None, hi=None, lo_open=False, hi_open=False):
        """A finite number, optionally in ``[lo, hi]`` (ends open with ``lo_open``/``hi_open``)."""
        if k not in self.data:
            return self.raw(k, expected, default)
        v = self.data[k]
        ok = _is_num(v) and (lo is None or (v > lo if lo_open else v >= lo)) \
            and (hi is None or (v < hi if hi_open else v <= hi))
        if not ok:
            raise self.fail(k, expected, v)
        return float(v)

    def integer(self, k, expected, default=_MISSING, lo=0):
        """An integer >= ``lo``."""
        if k not in self.data:
            return self.raw(k, expected, default)
        v = self.data[k]
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise self.fail(k, expected, v)
        return v

    def text(self, k, expected, default=_MISSING, choices=None):
        """A string, optionally one of ``choices``."""
        if k not in self.data:
            return self.raw(k, expected, default)
        v = self.data[k]
        if not isinstance(v, str) or (choices is not None and v not in choices):
            raise self.fail(k, expected, v)
        return v

    def vec(self, k, expected="three numbers [d, h, w]", default=_MISSING):
        """Three finite numbers."""
        if k not in self.data:
            return self.raw(k, expected, default)
        v = self.data[k]
        if not (isinstance(v, list) and len(v) == 3 and all(_is_num(c) for c in v)):
            raise self.fail(k, expected, v)
        return tuple(float(c) for c in v)

    def index(self, k, value=_MISSING, where=None):
        """A node index ``[i, j, k]`` (three integers >= 0)."""
        v = self.raw(k, "a node index [i, j, k]") if value is _MISSING else value
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(c, int) and not isinstance(c, bool)
                                                            and c >= 0 for c in v)):
            raise self.src.error(where or self.key(k), "a node index [i, j, k] of three integers >= 0", v)
        return tuple(v)

    def per_class(self, k, unit):
        """A number >= 0 or a table by direction class ``{axis, face, body}``."""
        expected = f"a number >= 0 ({unit}) or a table {{axis = .., face = .., body = ..}}"
        v = self.raw(k, expected)
        if isinstance(v, dict):
            if not v or not all(c in CLASSES and _is_num(x) and x >= 0 for c, x in v.items()):
                raise self.fail(k, expected, v)
            return {c: float(x) for c, x in v.items()}
        if not _is_num(v) or v < 0:
            raise self.fail(k, expected, v)
        return float(v)

    def one_of(self, *keys) -> str:
        """The one key of ``keys`` that is present (exactly one must be)."""
        present = [k for k in keys if k in self.data]
        if len(present) != 1:
            what = " or ".join(keys)
            raise (self.fail(present[1], f"exactly one of {what}", present) if present else
                   self.src.error(self.name, f"exactly one of the keys {what}"))
        return present[0]

    def only_with(self, k, other):
        if k in self.data:
            raise self.fail(k, f"no {k} together with {self.name}.{other}", self.data[k])


# ------------------------------------------------------------------ the scene
@dataclass(eq=False)
class Scene:
    """A scene: a grid, the keyword arguments of :class:`Model`, an integrator and run settings.

    Args:
        grid: the :class:`~torchdeform.grid.Grid`.
        model_args: keyword arguments of :class:`~torchdeform.model.Model` besides ``grid``,
            ``dtype`` and ``device`` (``stiffness``, ``density``, ``fixed``, ``drags``, ...).
        integrator: an :class:`~torchdeform.integrators.Integrator`.
        dt: seconds, or ``"auto"`` (``safety`` times the stability bound of ``integrator``).
        steps: number of steps.
        record_every: steps between saved frames (default: about 100 frames).
        name: title of the run.
        dtype, device: of the model (``device`` None = CPU).
        safety: fraction of the stability bound used by ``dt = "auto"``.
        source: the scene file (:class:`Source`) for error messages, or None.
    """

    grid: Grid
    model_args: dict
    integrator: Integrator = field(default_factory=SymplecticEuler)
    dt: float | str = "auto"
    steps: int = 1000
    record_every: int | None = None
    name: str = "scene"
    dtype: torch.dtype = torch.float32
    device: str | None = None
    safety: float = 0.9
    source: Source = field(default_factory=Source)
    #: optional ``{"file": .., "tf": .., "mode": .., "view": ..}``: a volume (file or ``"phantom:N"``)
    #: deformed by the final state; ``run_scene`` then writes before/after renders and the deformed volume
    volume: dict | None = None
    _models: dict = field(default_factory=dict, init=False, repr=False)

    def build(self, device=None) -> Model:
        """The :class:`Model` on ``device`` (default: the scene's, else CPU); built once per device."""
        try:
            dev = torch.device(device or self.device or "cpu")
        except (RuntimeError, ValueError):
            raise self.source.error("integrator.device", 'a device name such as "cpu" or "cuda"',
                                    device or self.device) from None
        if dev.type == "cuda" and not torch.cuda.is_available():
            raise self.source.error("integrator.device", '"cpu" (CUDA is not available here)', str(dev))
        if dev.type == "cuda" and (dev.index or 0) >= torch.cuda.device_count():
            raise self.source.error("integrator.device", f"one of the {torch.cuda.device_count()} CUDA devices",
                                    str(dev))
        if str(dev) not in self._models:
            with self.source.located("material", MODEL_KEYS):
                self._models[str(dev)] = Model(self.grid, **self.model_args, dtype=self.dtype, device=dev)
        return self._models[str(dev)]

    def time_step(self, bound: float) -> float:
        """The time step (s): ``dt``, or ``safety * bound`` for ``dt = "auto"``."""
        if self.dt != "auto":
            return float(self.dt)
        if not (0 < bound < math.inf):
            raise self.source.error(
                "integrator.dt", f'seconds: "auto" needs a finite, positive stability bound and '
                f'{self.integrator.name} has {bound:g} s here', "auto")
        return self.safety * bound

    @property
    def frames_every(self) -> int:
        """Steps between saved frames."""
        return self.record_every or max(1, self.steps // 100)


# ------------------------------------------------------------------ reading files
def _read(path) -> tuple[Source, dict]:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("scene", "an existing scene file (.toml)", str(path)) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError("scene", "a readable UTF-8 text file", f"{path} ({e})") from None
    src = Source(path, text)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = re.search(r"\(at line (\d+), column (\d+)\)", msg)
        line = int(m.group(1)) if m else None
        msg = re.sub(r"\s*\(at line \d+, column \d+\)", "", msg) + (f" at column {m.group(2)}" if m else "")
        raise ConfigError("toml", f"valid TOML syntax ({msg})", file=str(path), line=line) from None
    model = data.get("model", "mass-spring")                 # top-level key: which deformation model
    if model not in ("mass-spring", "chainmail"):
        raise src.error("model", '"mass-spring" (default) or "chainmail"', model)
    for name in data:
        if name not in SECTIONS and name != "model":
            raise src.error(name, "one of the sections " + ", ".join(f"[{s}]" for s in SECTIONS), name)
    for name in (("grid", "chainmail") if model == "chainmail" else REQUIRED):
        if name not in data:
            raise src.error(name, f"a [{name}] section (required)")
    return src, data


def _grid(t: _Table, base: Path) -> Grid:
    spacing = t.raw("spacing", "one positive number or three [sd, sh, sw] in metres")
    if not (_is_num(spacing) and spacing > 0) and not (isinstance(spacing, list) and len(spacing) == 3
                                                        and all(_is_num(s) and s > 0 for s in spacing)):
        raise t.fail("spacing", "one positive number or three [sd, sh, sw] in metres", spacing)
    topology = t.integer("topology", "6, 14, 18 or 26", 26)
    if topology not in TOPOLOGIES:
        raise t.fail("topology", "6, 14, 18 or 26", topology)
    if t.one_of("shape", "mesh") == "mesh":
        from .mesh import grid_from_mesh
        t.only_with("origin", "mesh")
        mesh = t.text("mesh", "a mesh file name (relative to the scene file)")
        padding = t.integer("padding", "an integer >= 0 (node layers)", 0)
        scale = t.num("scale", "a positive number (metres per mesh unit)", 1.0, lo=0, lo_open=True)
        with t.src.located(t.key("mesh"), {k: t.key(k) for k in ("spacing", "padding", "scale")}):
            return grid_from_mesh(base / mesh, spacing, topology, padding, scale)
    t.only_with("padding", "shape")
    t.only_with("scale", "shape")
    shape = t.raw("shape", "three node counts [D, H, W]")
    if not (isinstance(shape, list) and len(shape) == 3 and all(isinstance(n, int) and not isinstance(n, bool)
                                                                 for n in shape)) or min(shape) < 1:
        raise t.fail("shape", "three node counts [D, H, W], each >= 1", shape)
    origin = t.vec("origin", "three numbers [od, oh, ow] in metres", (0.0, 0.0, 0.0))
    with t.src.located(t.name):
        return Grid(tuple(shape), spacing, topology, origin=origin)


def _material(t: _Table) -> dict:
    which = t.one_of("stiffness", "modulus")
    args = {"stiffness": t.per_class(which, "N/m" if which == "stiffness" else "N"),
            "normalize": which == "modulus"}
    if t.has("damping"):
        args["damping"] = t.per_class("damping", "N s/m")
    args["damping_mode"] = t.text("damping_mode", '"projected" or "unprojected"', "projected",
                                 ("projected", "unprojected"))
    return args


def _mass(t: _Table) -> dict:
    which = t.one_of("mass", "density")
    unit = "kg per node" if which == "mass" else "kg/m^3"
    return {which: t.num(which, f"a positive number ({unit})", lo=0, lo_open=True)}


def _faces(t: _Table, k: str, grid: Grid) -> torch.Tensor:
    v = t.data[k]
    names = [v] if isinstance(v, str) else v
    expected = "a face name or a list of them: " + ", ".join(f'"{f}"' for f in FACES)
    if not isinstance(names, list) or not all(isinstance(n, str) and n in FACES for n in names):
        raise t.fail(k, expected, v)
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    for n in names:
        mask |= grid.face(n)
    return mask


def _node_list(t: _Table, k: str, grid: Grid) -> torch.Tensor:
    v = t.raw(k, "a list of node indices [[i, j, k], ...]")
    if not isinstance(v, list) or not v:
        raise t.fail(k, "a non-empty list of node indices [[i, j, k], ...]", v)
    for n, ijk in enumerate(v):
        t.index(k, ijk, where=f"{t.key(k)}[{n}]")
    with t.src.located(t.key(k)):
        return grid.index_mask(v)


def _boundary(t: _Table, grid: Grid) -> dict:
    args = {}
    fixed = None
    if t.has("fixed"):
        fixed = _faces(t, "fixed", grid)
    if t.has("fixed_nodes"):
        nodes = _node_list(t, "fixed_nodes", grid)
        fixed = nodes if fixed is None else fixed | nodes
    if fixed is not None:
        args["fixed"] = fixed
    if t.has("home"):
        args["home"] = t.num("home", "a number >= 0 (N/m)", lo=0)
    if t.has("anchors"):
        a = _Table(t.src, t.key("anchors"), t.data["anchors"], ("stiffness", "every"))
        args["anchors"] = (a.num("stiffness", "a number >= 0 (N/m)", lo=0),
                           a.integer("every", "an integer >= 1 (every k-th node)", lo=1))
    if t.has("decay"):
        args["decay"] = t.num("decay", "a rate >= 0 (1/s)", lo=0)
    if t.has("gravity"):
        args["gravity"] = t.vec("gravity", "three numbers [gd, gh, gw] in m/s^2")
    return args


def _loads(src: Source, items, grid: Grid) -> list:
    if not isinstance(items, list):
        raise src.error("loads", "[[loads]] tables", items)
    loads = []
    for n, item in enumerate(items):
        t = _Table(src, f"loads[{n}]", item, SECTIONS["loads"])
        timing = dict(start=t.num("start", "a time >= 0 (s)", 0.0, lo=0),
                      ramp=t.num("ramp", "a duration >= 0 (s)", 0.0, lo=0))
        if t.one_of("node", "face") == "node":
            t.only_with("traction", "node")
            node = t.index("node")
            with src.located(t.key("node")):
                grid.index_mask([node])
            loads.append(PointForce(node, t.vec("force", "three numbers [fd, fh, fw] in N"), **timing))
        else:
            t.only_with("force", "face")
            face = t.text("face", "a face name: " + ", ".join(f'"{f}"' for f in FACES), choices=FACES)
            loads.append(SurfaceForce(face, t.vec("traction", "three numbers [td, th, tw] in Pa"), **timing))
    return loads


def _drags(src: Source, items, grid: Grid) -> list:
    if not isinstance(items, list):
        raise src.error("drags", "[[drags]] tables", items)
    drags = []
    for n, item in enumerate(items):
        t = _Table(src, f"drags[{n}]", item, SECTIONS["drags"])
        which = t.one_of("nodes", "face", "box")
        if which == "nodes":
            nodes = _node_list(t, "nodes", grid)
        elif which == "face":
            nodes = _faces(t, "face", grid)
        else:
            b = _Table(src, t.key("box"), t.data["box"], ("lo", "hi"))
            lo, hi = b.vec("lo", "three numbers [d, h, w] in metres"), b.vec("hi", "three numbers [d, h, w] in metres")
            nodes = grid.box_mask(lo, hi)
            if not bool(nodes.any()):
                raise t.fail("box", "a box {lo, hi} (rest positions, m) containing at least one node",
                             {"lo": list(lo), "hi": list(hi)})
        expected = "a list of waypoints [[t, [od, oh, ow]], ...] (s, m)"
        path = t.raw("path", expected)
        if not (isinstance(path, list) and path and all(
                isinstance(p, list) and len(p) == 2 and _is_num(p[0]) and isinstance(p[1], list)
                and len(p[1]) == 3 and all(_is_num(c) for c in p[1]) for p in path)):
            raise t.fail("path", expected, path)
        with src.located(t.key("path")):
            drags.append(Drag(nodes, [(float(p[0]), tuple(float(c) for c in p[1])) for p in path]))
    return drags


def _integrator(t: _Table, grid: Grid) -> dict:
    name = t.text("name", "one of " + ", ".join(f'"{n}"' for n in INTEGRATORS), "symplectic", INTEGRATORS)
    options = INTEGRATOR_OPTIONS[name]
    for k in t.data:
        if k not in SECTIONS["integrator"] and k not in options:
            own = ", ".join(options) if options else "none"
            raise t.fail(k, f"one of the keys {', '.join(SECTIONS['integrator'])} (options of {name}: {own})", k)
    kwargs = {}
    for k, expected in options.items():
        if not t.has(k):
            continue
        if k in ("cg_iters", "newton_iters"):
            kwargs[k] = t.integer(k, expected, lo=1 if k == "cg_iters" else 0)
        elif k == "kd":
            kwargs[k] = t.num(k, expected, lo=0, hi=1, hi_open=True)
        elif k == "material":
            v = t.data[k]
            try:
                w = torch.as_tensor(v, dtype=torch.float64)
            except (TypeError, ValueError, RuntimeError):
                raise t.fail(k, expected, v) from None
            if isinstance(v, bool) or not (w.dim() == 0 or tuple(w.shape) == grid.shape) \
                    or not bool(((w >= 0) & (w <= 1)).all()):
                raise t.fail(k, expected + f" (grid {grid.shape})", v if w.dim() == 0 else tuple(w.shape))
            kwargs[k] = float(w) if w.dim() == 0 else w
        else:
            kwargs[k] = t.num(k, expected, lo=0, lo_open=True)
    if name == "knoche" and grid.topology != 6:
        raise t.src.error("grid.topology", "6 for the knoche integrator", grid.topology)
    with t.src.located(t.name):
        integrator = INTEGRATORS[name](**kwargs)

    dt = t.raw("dt", 'a positive number of seconds or "auto"')
    if dt == "auto":
        if name not in EXPLICIT:
            raise t.fail("dt", f'a positive number of seconds ("auto" needs an explicit integrator, '
                               f'not {name})', dt)
    elif not (_is_num(dt) and dt > 0):
        raise t.fail("dt", 'a positive number of seconds or "auto"', dt)
    if t.has("safety") and dt != "auto":
        raise t.fail("safety", 'no safety unless dt = "auto"', t.data["safety"])
    device = t.text("device", 'a device name such as "cpu" or "cuda"', None)
    if device is not None:
        try:
            torch.device(device)
        except (RuntimeError, ValueError):
            raise t.fail("device", 'a device name such as "cpu" or "cuda"', device) from None
    return dict(integrator=integrator, dt=dt if dt == "auto" else float(dt),
                safety=t.num("safety", "a number in (0, 1]", 0.9, lo=0, hi=1, lo_open=True),
                steps=t.integer("steps", "an integer >= 0 (number of steps)"),
                dtype=DTYPES[t.text("dtype", '"float32" or "float64"', "float32", DTYPES)], device=device)


def load_scene(path) -> Scene:
    """Read a TOML scene file (see the module docstring for its keys) into a :class:`Scene`.

    The model is built once (on the CPU) to check every value.

    Raises:
        ConfigError: naming the file, the line (best effort), the dotted key and what was
            expected: syntax errors, unknown keys, wrong types, missing sections or keys, bad
            values, a missing or open mesh.
    """
    src, data = _read(path)
    base = Path(path).parent
    if data.get("model") == "chainmail":                     # torchdeform.chainmail runs these
        from .chainmail import chainmail_scene
        return chainmail_scene(src, data, base, Path(path).stem)
    if "chainmail" in data:
        raise src.error("chainmail", 'model = "chainmail" (a top-level key) for a [chainmail] section')
    options = tuple(k for opts in INTEGRATOR_OPTIONS.values() for k in opts)
    section = {name: _Table(src, name, data[name], keys + (options if name == "integrator" else ()))
               for name, keys in SECTIONS.items() if name in data and name not in ("loads", "drags")}
    grid = _grid(section["grid"], base)
    model_args = {**_material(section["material"]), **_mass(section["mass"])}
    if "boundary" in section:
        model_args.update(_boundary(section["boundary"], grid))
    if "loads" in data:
        model_args["loads"] = _loads(src, data["loads"], grid)
    if "drags" in data:
        model_args["drags"] = _drags(src, data["drags"], grid)
    run = _integrator(section["integrator"], grid)
    out = section.get("output") or _Table(src, "output", {}, SECTIONS["output"])
    scene = Scene(grid, model_args, **run, source=src,
                  record_every=out.integer("record_every", "an integer >= 1 (steps between frames)", None, lo=1),
                  name=out.text("name", "a string", Path(path).stem))
    if "volume" in data:
        vt = _Table(src, "volume", data["volume"], SECTIONS["volume"])
        scene.volume = {"file": vt.text("file", 'a volume file or "phantom:N"'),
                        "tf": vt.text("tf", "a transfer-function preset or file", "ct-soft"),
                        "mode": vt.text("mode", '"dvr", "mip" or "average"', "dvr", ("dvr", "mip", "average")),
                        "view": vt.text("view", "an axis view d, h, w, -d, -h, -w", "h",
                                        ("d", "h", "w", "-d", "-h", "-w")), "base": str(base)}
    scene.build("cpu")
    return scene


# ------------------------------------------------------------------ the demo
def demo_scene() -> Scene:
    """The built-in demo (same as ``scenes/demo.toml``), built with the Python API.

    A 1 cm cube of liver-like tissue (11 x 11 x 11 nodes, 1 mm apart, 26 neighbours,
    density 1000 kg/m^3, k = 3 N/m, i.e. E of roughly 8 kPa), its base fixed, sagging under
    gravity (along -D), its top centre node dragged 2 mm up and 1 mm sideways within 50 ms
    and then held; symplectic Euler at dt = 0.1 ms (below the bound of about 0.12 ms) for
    0.15 s, with global drag so it settles.
    """
    grid = Grid((11, 11, 11), spacing=0.001, topology=26)
    top_centre = Drag(grid.index_mask([(10, 5, 5)]), [(0.0, (0.0, 0.0, 0.0)), (0.05, (0.002, 0.001, 0.0))])
    model_args = dict(stiffness=3.0, normalize=False, damping=1e-4, damping_mode="projected", density=1000.0,
                      fixed=grid.face("bottom"), decay=100.0, gravity=(-9.81, 0.0, 0.0), drags=[top_centre])
    # the procedural CT phantom fills the cube; run_scene also writes its before/after renders
    volume = {"file": "phantom:64", "tf": "ct-soft", "mode": "dvr", "view": "h"}
    return Scene(grid, model_args, SymplecticEuler(), dt=1e-4, steps=1500, record_every=15, name="demo",
                 volume=volume)


# ------------------------------------------------------------------ running
@contextmanager
def one_line_warnings(prefix: str = "torchdeform: warning: "):
    """Show warnings (e.g. :class:`StabilityWarning`) as one line on stderr, for the CLI."""
    with warnings.catch_warnings():
        warnings.showwarning = lambda message, *args, **kw: print(f"{prefix}{message}", file=sys.stderr)
        yield


def energy_series(model: Model, x: torch.Tensor, v: torch.Tensor, chunk: int = 1) -> dict:
    """Energies and largest displacement of recorded frames.

    Args:
        x, v: frames ``(T, 3, D, H, W)`` (any device).
        chunk: frames per evaluation (1 by default: batched small frames run multi-threaded,
            which is slower than a loop when the CPU cores are shared).
    Returns:
        dict of ``(T,)`` float64 numpy arrays: ``kinetic``, ``elastic``, ``gravity`` (if the
        model has gravity), ``total`` (J), ``max_displacement`` (m, largest ``|x - X|``) and
        ``max_free_displacement`` (m, the same over nodes that are neither fixed nor dragged).
    """
    out = {}
    free = ~model.constrained.view(1, *model.grid.shape)
    with torch.no_grad():
        for a in range(0, len(x), chunk):
            xc = x[a:a + chunk].to(model.device, model.dtype)
            vc = v[a:a + chunk].to(model.device, model.dtype)
            terms = model.energy(State(xc, vc))
            u = (xc - model.X).norm(dim=1)                                  # (T, D, H, W)
            terms["max_displacement"] = u.flatten(1).amax(1)
            terms["max_free_displacement"] = (u * free).flatten(1).amax(1)
            for k, val in terms.items():
                out.setdefault(k, []).append(val.double().cpu())
    return {k: torch.cat(v).numpy() for k, v in out.items()}


def plot_energy(path, t: np.ndarray, series: dict, title: str = "") -> None:
    """Write a PNG: energies (J) and largest displacement (mm) over time (s)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True)
    for k in ("kinetic", "elastic", "gravity", "total"):
        if k in series:
            top.plot(t, series[k], label=k, lw=2 if k == "total" else 1.2)
    top.set_ylabel("energy (J)")
    top.legend(loc="best", fontsize="small")
    top.grid(alpha=0.3)
    top.set_title(title)
    bottom.plot(t, series["max_displacement"] * 1e3, color="k", label="all nodes")
    bottom.plot(t, series["max_free_displacement"] * 1e3, color="tab:blue", ls="--",
                label="free nodes (not fixed or dragged)")
    bottom.legend(loc="best", fontsize="small")
    bottom.set_ylabel("max displacement (mm)")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    fig.savefig(path, dpi=100)


def _out_dir(out_dir) -> Path:
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError("--out", f"a folder that can be created ({e.strerror})", str(out)) from None
    return out


def _bound_method(name: str) -> str:
    if name == "implicit":
        return "none: implicit Euler is unconditionally stable"
    if name == "knoche":
        return "none: relaxation, dt only advances the clock"
    return "power iteration on the spring stencil (linearised at rest)"


def run_scene(scene: Scene, out_dir, progress: bool = True, device=None) -> dict:
    """Run a scene and write ``trajectory.npz``, ``summary.json`` and ``energy.png`` to ``out_dir``.

    ``trajectory.npz``: ``t`` ``(T,)`` s (float64), ``x``, ``v`` ``(T, 3, D, H, W)`` (float32),
    rest positions ``X`` ``(3, D, H, W)``, ``node_mask`` ``(D, H, W)``, ``shape``, ``spacing``,
    ``origin``, ``topology``, ``dt``, ``integrator``, and the series of :func:`energy_series`
    (``kinetic``, ``elastic``, ``gravity``, ``total``, ``max_displacement``,
    ``max_free_displacement``, each ``(T,)``). The last frame is always the final state.

    Args:
        scene: a :class:`Scene` (:func:`load_scene`, :func:`demo_scene` or your own).
        out_dir: output folder (created).
        progress: show a progress bar.
        device: run on this device instead of the scene's.
    Returns:
        the summary (also written to ``summary.json``).
    Raises:
        DivergenceError: the run became unstable (naming step and a safe dt).
    """
    if not isinstance(scene, Scene):                          # a ChainMail scene runs itself
        return scene.run(_out_dir(out_dir), progress=progress, device=device)
    out = _out_dir(out_dir)
    model = scene.build(device)
    integrator = scene.integrator
    bound = time_step_bound(model, integrator)
    dt = scene.time_step(bound)
    if integrator.name in EXPLICIT:
        check_dt(model, dt, integrator, bound)
    state = model.rest_state()

    start = time.perf_counter()
    final, rec = simulate(model, state, dt, scene.steps, integrator, record_every=scene.frames_every,
                          progress=progress, warn=False)
    wall = time.perf_counter() - start

    t, x, v = rec["t"].numpy(), rec["x"][:, 0], rec["v"][:, 0]
    if scene.steps % scene.frames_every:
        t = np.append(t, final.t)
        x = torch.cat([x, final.x[:1].detach().cpu()])
        v = torch.cat([v, final.v[:1].detach().cpu()])
    series = energy_series(model, x, v)
    grid = model.grid
    np.savez(out / "trajectory.npz", t=t, x=x.float().numpy(), v=v.float().numpy(),
             X=model.X[0].float().cpu().numpy(), node_mask=grid.nodes().numpy(),
             shape=np.array(grid.shape), spacing=np.array(grid.spacing), origin=np.array(grid.origin),
             topology=grid.topology, dt=dt, integrator=integrator.name, **series)

    options = {k: v for k, v in vars(integrator).items() if isinstance(v, (int, float, str)) and not k.startswith("_")}
    summary = {
        "name": scene.name,
        "scene": scene.source.path,
        "integrator": {"name": integrator.name, **options},
        "steps": scene.steps,
        "dt_s": dt,
        "dt_auto": scene.dt == "auto",
        "simulated_time_s": float(final.t),
        "time_step_bound_s": bound if math.isfinite(bound) else None,
        "stability_bound_method": _bound_method(integrator.name),
        "wall_time_s": wall,
        "steps_per_s": scene.steps / wall if wall > 0 else None,
        "nodes": grid.num_nodes,
        "springs": grid.num_springs,
        "grid": {"shape": list(grid.shape), "spacing": list(grid.spacing), "origin": list(grid.origin),
                 "topology": grid.topology},
        "dtype": str(model.dtype).replace("torch.", ""),
        "device": str(model.device),
        "frames": len(t),
        "final_energy_J": {k: float(series[k][-1]) for k in ("kinetic", "elastic", "gravity", "total")
                           if k in series},
        "max_displacement_m": float(series["max_displacement"][-1]),
        "peak_displacement_m": float(series["max_displacement"].max()),
        "max_free_displacement_m": float(series["max_free_displacement"][-1]),
    }
    if scene.volume:
        from .volume_io import scene_volume_outputs
        v = dict(scene.volume)
        summary["volume"] = scene_volume_outputs(v.pop("file"), final.x[:1], model.X, grid.spacing, out, **v)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    plot_energy(out / "energy.png", t, series, f"{scene.name}: {integrator.name}, dt = {dt:.3g} s")
    return summary


def report(summary: dict, out_dir) -> str:
    """One line for the CLI: what ran, how fast, and where the outputs are."""
    bound = summary["time_step_bound_s"]
    bound = f" (bound {bound:.3g} s)" if bound else ""
    return (f"{summary['name']}: {summary['steps']} {summary['integrator']['name']} steps of "
            f"{summary['dt_s']:.3g} s{bound} in {summary['wall_time_s']:.2f} s, max displacement "
            f"{summary['max_displacement_m'] * 1e3:.3g} mm; wrote trajectory.npz, summary.json, "
            f"energy.png to {out_dir}")


__all__ = ["Scene", "Source", "load_scene", "demo_scene", "run_scene", "energy_series", "plot_energy",
           "one_line_warnings", "report", "SECTIONS"]
