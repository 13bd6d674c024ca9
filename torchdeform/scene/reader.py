r"""Reading scene files (TOML): located errors and typed values, and the sections every model kind shares.

This is the public sibling API of the scene modules: :mod:`.mass_spring` and
:mod:`.chainmail` (and any new model kind) build their scenes from these helpers.

* :class:`Source`: a file's path and text; builds :class:`~torchdeform.errors.ConfigError` s that
  name the file and the line of a dotted key (``loads[1].force``).
* :class:`Table`: one TOML table with typed getters (``num``, ``integer``, ``text``, ``flag``, ``vec``,
  ``index``, ``per_class``, ``one_of``) that raise located errors.
* :func:`read`: the file, parsed and checked for known sections.
* the shared sections: :func:`grid_section` (``[grid]``), :func:`faces`, :func:`node_list`
  (``fixed``, ``fixed_nodes``), :func:`drags_section` (``[[drags]]``).

Example:
    >>> from torchdeform.scene.reader import SECTIONS, Source, Table
    >>> src = Source(path="scene.toml", text="[grid]\nspacing = -1\n")
    >>> t = Table(src, "grid", {"spacing": -1}, SECTIONS["grid"])
    >>> t.num("spacing", "a positive number", lo=0, lo_open=True)
    Traceback (most recent call last):
    ...
    torchdeform.errors.ConfigError: scene.toml:2: grid.spacing: expected a positive number, got -1
"""

from __future__ import annotations

import math
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeGuard

import torch

from ..checks import check_grid, read_text
from ..errors import ConfigError
from ..sim.forces import Drag
from ..sim.grid import CLASSES, FACES, TOPOLOGIES, Grid

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # pyright: ignore[reportMissingImports]  # installed on Python 3.10 only

__all__ = [
    "Source",
    "Table",
    "read",
    "is_number",
    "grid_section",
    "faces",
    "node_list",
    "drags_section",
    "region_mask",
    "parse_value",
    "parse_set",
    "with_values",
    "LISTS",
    "check_sections",
    "SceneErrors",
    "REQUIRED_OPTIONS",
    "SECTIONS",
    "REQUIRED",
    "MISSING",
]


def volume_path(name, base):
    """A scene's ``[volume] file``: ``phantom[:N]`` or an array as it is, a file name relative to the scene's folder ``base``."""
    if not isinstance(name, str):
        return name  # a volume already in memory (a body of labels: its CT on the lattice's box)
    return name if name.startswith("phantom") or base is None else str(Path(base) / name)


SECTIONS = {
    "grid": (
        "shape",
        "mesh",
        "labels",
        "spacing",
        "topology",
        "origin",
        "padding",
        "scale",
        "label_spacing",
        "surface_labels",
        "up",
    ),
    "material": (
        "stiffness",
        "spring_modulus",
        "modulus",
        "tissue",
        "youngs_modulus",
        "poisson_ratio",
        "damping",
        "damping_mode",
        "law",
        "stiffening",
        "quadratic",
        "cubic",
    ),
    "regions": ("sphere", "box", "stiffness", "tissue", "youngs_modulus", "poisson_ratio"),
    "tissues": ("label", "tissue", "youngs_modulus", "poisson_ratio", "density", "fixed", "background"),
    "mass": ("mass", "density"),
    "boundary": ("fixed", "fixed_nodes", "home", "anchors", "decay", "gravity"),
    "loads": ("node", "force", "face", "traction", "start", "ramp"),
    "drags": ("nodes", "face", "box", "path"),
    "integrator": ("name", "dt", "safety", "steps", "dtype", "device", "threads", "engine", "settle"),
    "tools": (
        "name",
        "shape",
        "radius",
        "half_length",
        "axis",
        "half_extents",
        "normal",
        "file",
        "resolution",
        "position",
        "orientation",
        "path",
        "contact",
        "friction",
        "direction",
        "hold",
        "haptic_gain",
        "stiffness",
        "damping",
        "grasp",
        "start_inside",
    ),
    "strain_limit": ("min", "max", "passes", "update_velocity"),
    "cuts": ("origin", "u", "v", "triangle", "edges", "at", "gape", "tool", "edge", "start", "stop", "pieces"),
    "cautery": ("tool", "at", "every", "start", "stop"),
    "tear": ("max_strain", "max_force", "one_per_step", "start"),
    "coagulate": ("at", "box", "sphere", "viscosity_factor"),
    "surfaces": ("file", "scale", "name", "up"),
    "output": (
        "record_every",
        "name",
        "palpation",
        "surfaces",
        "surface_format",
        "surface_faces",
        "animation",
        "image_size",
        "camera",
        "camera_up",
    ),
    "volume": ("file", "tf", "mode", "view"),
    "camera": (
        "kind",
        "tool",
        "look",
        "up",
        "ahead",
        "fov",
        "size",
        "far",
        "distortion",
        "every",
        "step",
        "inside",
    ),
    "texture": ("exemplar", "block", "seed", "voxel", "seams"),
    "chainmail": (
        "method",
        "compression",
        "stretch",
        "shear",
        "tissue",
        "reference_stress",
        "frames",
        "relax_steps",
        "relax_mode",
        "relax_moved_only",
        "on_blocked",
    ),
}
#: sections every mass-spring scene needs (``[mass]`` too, unless ``[material] tissue`` gives the density)
REQUIRED = ("grid", "material", "integrator")
#: marks an argument that was not given (``got`` not shown, no default)
MISSING = object()
_HEADER = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\-]+)\s*\]\]?")


# ------------------------------------------------------------------ locating errors
class Source:
    """A scene file's path and text: builds :class:`ConfigError` s that name file and line."""

    def __init__(self, *, path=None, text: str = ""):
        self.path, self.text = (None if path is None else str(path)), text

    def error(self, key: str, expected: str, *, got=MISSING) -> ConfigError:
        """A ConfigError for the dotted ``key``; ``got`` omitted = not shown."""
        shown = got is not MISSING
        return ConfigError(
            key,
            expected,
            got=got if shown else None,
            file=self.path,
            line=self.line_of(key) if self.path else None,
            show_got=shown,
        )

    def line_of(self, key: str) -> int | None:
        """1-based line of a dotted key like ``loads[1].force`` (best effort), else None."""
        lines = self.text.splitlines()
        parts = [_name_and_index(p) for p in key.split(".")]
        names = [p[0] for p in parts]
        headers = [(i, m.group(1)) for i, line in enumerate(lines) if (m := _HEADER.match(line))]
        start, end, best, rest = -1, headers[0][0] if headers else len(lines), None, names
        for n in range(len(names), 0, -1):  # longest matching table header
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
    def located(self, key: str, *, keys: dict | None = None):
        """Re-raise a core ConfigError as one about scene ``key`` (or ``keys[core key]``)."""
        try:
            yield
        except ConfigError as e:
            if e.file is not None:
                raise
            shown = e.show_got
            if keys and e.key in keys:
                key = keys[e.key]
            elif e.key.split(".")[0] in SECTIONS and "." in e.key:  # already a scene key
                key = e.key
            raise self.error(key, e.expected, got=e.got if shown else MISSING) from None


def _name_and_index(part: str) -> tuple[str, str | None]:
    """``"loads[1]"`` -> ``("loads", "1")``, ``"grid"`` -> ``("grid", None)``."""
    m = re.fullmatch(r"(.*?)(?:\[(\d+)\])?", part)
    assert m is not None  # the pattern matches every string
    return m.group(1), m.group(2)


# ------------------------------------------------------------------ typed values
def is_number(v) -> TypeGuard[float]:
    """True for a finite int or float (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class Table:
    """One TOML table with its dotted name; typed getters raise located ConfigErrors."""

    def __init__(self, src: Source, name: str, data, allowed):
        if not isinstance(data, dict):
            raise src.error(name, "a table", got=data)
        unknown = [k for k in data if k not in allowed]
        if unknown:
            raise src.error(f"{name}.{unknown[0]}", "one of the keys " + ", ".join(allowed), got=unknown[0])
        self.src, self.name, self.data = src, name, data

    def key(self, k: str) -> str:
        """The dotted scene key of ``k`` in this table, e.g. ``integrator.dt``."""
        return f"{self.name}.{k}"

    def has(self, k: str) -> bool:
        """True when the table has the key ``k``."""
        return k in self.data

    def fail(self, k: str, expected: str, *, got=MISSING) -> ConfigError:
        """A located ConfigError for key ``k`` of this table (to raise); ``got`` omitted = not shown."""
        return self.src.error(self.key(k), expected, got=got)

    def raw(self, k, expected, *, default: Any = MISSING) -> Any:
        """The value of ``k``, or ``default``; a missing key without default is an error."""
        if k not in self.data:
            if default is MISSING:
                raise self.fail(k, expected + " (required)")
            return default
        return self.data[k]

    def num(self, k, expected, *, default=MISSING, lo=None, hi=None, lo_open=False, hi_open=False):
        """A finite number, optionally in ``[lo, hi]`` (ends open with ``lo_open``/``hi_open``)."""
        if k not in self.data:
            return self.raw(k, expected, default=default)
        v = self.data[k]
        ok = (
            is_number(v)
            and (lo is None or (v > lo if lo_open else v >= lo))
            and (hi is None or (v < hi if hi_open else v <= hi))
        )
        if not ok:
            raise self.fail(k, expected, got=v)
        return float(v)

    def integer(self, k, expected, *, default=MISSING, lo=0):
        """An integer >= ``lo``."""
        if k not in self.data:
            return self.raw(k, expected, default=default)
        v = self.data[k]
        if not isinstance(v, int) or isinstance(v, bool) or v < lo:
            raise self.fail(k, expected, got=v)
        return v

    def text(self, k, expected, *, default=MISSING, choices=None):
        """A string, optionally one of ``choices``."""
        if k not in self.data:
            return self.raw(k, expected, default=default)
        v = self.data[k]
        if not isinstance(v, str) or (choices is not None and v not in choices):
            raise self.fail(k, expected, got=v)
        return v

    def flag(self, k, *, expected="true or false", default=MISSING) -> bool:
        """A TOML boolean (``true``/``false``); a string (``"no"``), number or anything else is refused."""
        if k not in self.data:
            return self.raw(k, expected, default=default)
        v = self.data[k]
        if not isinstance(v, bool):
            raise self.fail(k, expected + " (a TOML boolean, without quotes)", got=v)
        return v

    def vec(self, k, expected, *, default=MISSING):
        """Three finite numbers."""
        if k not in self.data:
            return self.raw(k, expected, default=default)
        v = self.data[k]
        if not (isinstance(v, list) and len(v) == 3 and all(is_number(c) for c in v)):
            raise self.fail(k, expected, got=v)
        return tuple(float(c) for c in v)

    def index(self, k, *, value=MISSING, where=None):
        """A node index ``[i, j, k]`` (three integers >= 0)."""
        v = self.raw(k, "a node index [i, j, k]") if value is MISSING else value
        if not (
            isinstance(v, list)
            and len(v) == 3
            and all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in v)
        ):
            raise self.src.error(where or self.key(k), "a node index [i, j, k] of three integers >= 0", got=v)
        return tuple(v)

    def per_class(self, k, unit):
        """A number >= 0 or a table by direction class ``{axis, face, body}``."""
        expected = f"a number >= 0 ({unit}) or a table {{axis = .., face = .., body = ..}}"
        v = self.raw(k, expected)
        if isinstance(v, dict):
            if not v or not all(c in CLASSES and is_number(x) and x >= 0 for c, x in v.items()):
                raise self.fail(k, expected, got=v)
            return {c: float(x) for c, x in v.items()}
        if not is_number(v) or v < 0:
            raise self.fail(k, expected, got=v)
        return float(v)

    def one_of(self, *keys) -> str:
        """The one key of ``keys`` that is present (exactly one must be)."""
        present = [k for k in keys if k in self.data]
        if len(present) != 1:
            what = " or ".join(keys)
            raise (
                self.fail(present[1], f"exactly one of {what}", got=present)
                if present
                else self.src.error(self.name, f"exactly one of the keys {what}")
            )
        return present[0]

    def only_with(self, k, other):
        """Raise a located ConfigError if ``k`` is present: it does not go together with ``other``."""
        if k in self.data:
            raise self.fail(k, f"no {k} together with {self.name}.{other}", got=self.data[k])


# ------------------------------------------------------------------ values from the command line
#: sections of array tables (``[[loads]]``): they hold lists, not keys a ``--set`` could name
LISTS = ("loads", "drags", "regions", "tissues", "tools", "cuts", "cautery", "coagulate", "surfaces")


def parse_value(text: str):
    """A TOML value (``1`` int, ``2.5`` float, ``true``, ``"name"``, ``[4, 4, 8]``), else the text as a string.

    Examples:
        >>> parse_value("2e-4"), parse_value("true"), parse_value("liver"), parse_value("[4, 4, 8]")
        (0.0002, True, 'liver', [4, 4, 8])
    """
    text = text.strip()
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_set(text: str, *, several: bool = True) -> tuple[str, Any]:
    """``KEY=V1,V2,...`` (``torchdeform sweep --set``) -> ``(key, [values])``; values as :func:`parse_value`.

    With ``several=False`` (``torchdeform run --set KEY=VALUE``) the value is one TOML value (commas
    and all: ``grid.shape=[4,4,8]``) and is returned as is.

    Examples:
        >>> parse_set("material.stiffness=1,2.5,4e3")
        ('material.stiffness', [1, 2.5, 4000.0])
        >>> parse_set("grid.shape=[4,4,8]", several=False)
        ('grid.shape', [4, 4, 8])
    """
    key, sep, values = str(text).partition("=")
    key = key.strip()
    if not sep or not key or not values.strip():
        example = (
            "KEY=V1,V2,... (e.g. material.stiffness=1,2,4)" if several else "KEY=VALUE (e.g. integrator.steps=200)"
        )
        raise ConfigError("--set", example, got=text)
    if not several:
        return key, parse_value(values)
    return key, [parse_value(v) for v in values.split(",")]


def with_values(data: dict, values: dict) -> dict:
    """A copy of a parsed scene file ``data`` with the dotted keys of ``values`` set (sections made as needed).

    Examples:
        >>> with_values({"integrator": {"steps": 10}}, {"integrator.steps": 200, "output.name": "x"})
        {'integrator': {'steps': 200}, 'output': {'name': 'x'}}
    """
    import copy

    data = copy.deepcopy(data)
    for key, value in values.items():
        if key.startswith("bodies.") and isinstance(data.get("bodies"), list):  # bodies.NAME.SECTION.KEY
            _, name, section, k = key.split(".", 3)
            entries = [b for b in data["bodies"] if isinstance(b, dict) and b.get("name") == name]
            if not entries:
                names = ", ".join(str(b.get("name")) for b in data["bodies"] if isinstance(b, dict))
                raise ConfigError("--set", f"bodies.NAME.SECTION.KEY with a body's name ({names})", got=key)
            table = entries[0].setdefault(section, {})
            if not isinstance(table, dict):
                raise ConfigError(f"--set {key}", f"a body whose [bodies.{section}] is a table", got=table)
            table[k] = value
            continue
        section, _, k = key.partition(".")
        table = data.setdefault(section, {})
        if not isinstance(table, dict):
            raise ConfigError(f"--set {key}", f"a scene whose [{section}] is a table", got=table)
        table[k] = value
    return data


# ------------------------------------------------------------------ reading files
def read(path) -> tuple[Source, dict]:
    """Read and parse a scene file; check its top-level ``model`` key and its sections.

    Returns:
        ``(source, data)``: the :class:`Source` and the parsed TOML.

    Raises:
        ConfigError: a missing or unreadable file, a TOML syntax error (with its line), an
            unknown model or section, or a required section missing.
    """
    path = Path(path)
    text = read_text(path, "scene", what="scene file (.toml)")
    src = Source(path=path, text=text)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = re.search(r"\(at line (\d+), column (\d+)\)", msg)
        line = int(m.group(1)) if m else None
        msg = re.sub(r"\s*\(at line \d+, column \d+\)", "", msg) + (f" at column {m.group(2)}" if m else "")
        raise ConfigError("toml", f"valid TOML syntax ({msg})", file=str(path), line=line) from None
    check_sections(src, data)
    return src, data


#: the sections and their keys of a ChainMail scene (``model = "chainmail"``)
CHAINMAIL_SECTIONS = {
    "grid": SECTIONS["grid"],
    "chainmail": SECTIONS["chainmail"],
    "boundary": ("fixed", "fixed_nodes"),
    "drags": SECTIONS["drags"],
    "output": ("name",),
}
#: keys an integrator cannot run without: integrator name -> keys of ``[integrator]``
REQUIRED_OPTIONS = {"knoche": ("material",)}


class SceneErrors(ConfigError):
    """Several problems of one scene file, reported together: one line each (``errors``, in file order).

    ``key``, ``file`` and ``line`` are those of the first problem.
    """

    def __init__(self, errors: list):
        first = errors[0]
        super().__init__(
            first.key, first.expected, got=first.got, file=first.file, line=first.line, show_got=first.show_got
        )
        self.errors = list(errors)
        self.args = ("\n".join(str(e) for e in self.errors),)

    def __str__(self) -> str:
        return self.args[0]


def _sorted_by_line(errors: list) -> list:
    return sorted(errors, key=lambda e: (e.line is None, e.line or 0))


def check_sections(src: Source, data: dict) -> None:
    r"""Check a parsed scene file's model, sections and keys all at once (before any value is read).

    Every unknown section, unknown key (of each table and each entry of an array table), missing
    required section and missing key that the chosen integrator needs is collected; one problem
    raises its :class:`ConfigError`, several raise a :class:`SceneErrors` of one line each.

    Examples:
        >>> src = Source(path="s.toml", text="[grid]\nshap = [2, 2, 2]\n[integrater]\n")
        >>> try:
        ...     check_sections(src, {"grid": {"shap": [2, 2, 2]}, "integrater": {}})
        ... except SceneErrors as e:
        ...     print(str(e))
        s.toml:2: grid.shap: expected one of the keys shape, mesh, ..., got 'shap'
        s.toml:3: integrater: expected one of the sections [grid], ..., got 'integrater'
        s.toml: material: expected a [material] section (required)
        s.toml: integrator: expected a [integrator] section (required)
    """
    model = data.get("model", "mass-spring")  # top-level key: which deformation model
    if model not in ("mass-spring", "chainmail"):
        raise src.error("model", '"mass-spring" (default) or "chainmail"', got=model)
    sections = CHAINMAIL_SECTIONS if model == "chainmail" else SECTIONS
    errors = _sorted_by_line(_unknown(src, data, sections, chainmail=model == "chainmail"))
    labels = isinstance(data.get("grid"), dict) and "labels" in data["grid"]  # the tissues give the material
    for name in ("grid", "chainmail") if model == "chainmail" else REQUIRED:
        if name == "material" and labels:
            continue
        if name not in data:
            errors.append(src.error(name, f"a [{name}] section (required)"))
    integrator = data.get("integrator")
    if model != "chainmail" and isinstance(integrator, dict):
        for k in REQUIRED_OPTIONS.get(str(integrator.get("name")), ()):
            if k not in integrator:
                errors.append(src.error(f"integrator.{k}", f"the {integrator['name']} integrator's {k} (required)"))
    if len(errors) == 1:
        raise errors[0]
    if errors:
        raise SceneErrors(errors)


def _unknown(src: Source, data: dict, sections: dict, *, chainmail: bool) -> list:
    """The errors of unknown sections and of unknown keys in known ones (array tables entry by entry)."""
    errors = []
    for name in data:
        if name == "model":
            continue
        if name not in sections:
            expected = "one of the sections " + ", ".join(f"[{s}]" for s in sections)
            if chainmail and name in SECTIONS:
                expected += ' (no such section in a scene with model = "chainmail")'
            errors.append(src.error(name, expected, got=name))
    for name, value in data.items():
        if name not in sections:
            continue
        if name == "integrator":  # its keys depend on the integrator: the model kind checks them
            continue
        allowed = sections[name]
        tables = [(name, value)] if name not in LISTS else None
        if tables is None:
            if not isinstance(value, list):
                errors.append(src.error(name, f"[[{name}]] tables", got=value))
                continue
            tables = [(f"{name}[{n}]", item) for n, item in enumerate(value)]
        for where, table in tables:
            if not isinstance(table, dict):
                errors.append(src.error(where, "a table", got=table))
                continue
            known = ", ".join(k for k in sections[name] if k in allowed)
            for k in table:
                if k not in allowed:
                    errors.append(src.error(f"{where}.{k}", "one of the keys " + known, got=k))
    return errors


def grid_section(t: Table, base: Path) -> Grid:
    """The :class:`~torchdeform.sim.grid.Grid` of a ``[grid]`` table (a box ``shape`` or a ``mesh``).

    ``base`` is the folder a mesh path is relative to.
    """
    spacing = t.raw("spacing", "one positive number or three [sd, sh, sw] in metres")
    if not (is_number(spacing) and spacing > 0) and not (
        isinstance(spacing, list) and len(spacing) == 3 and all(is_number(s) and s > 0 for s in spacing)
    ):
        raise t.fail("spacing", "one positive number or three [sd, sh, sw] in metres", got=spacing)
    topology = t.integer("topology", "6, 14, 18 or 26", default=26)
    if topology not in TOPOLOGIES:
        raise t.fail("topology", "6, 14, 18 or 26", got=topology)
    which = t.one_of("shape", "mesh", "labels")
    if which == "labels":
        raise t.fail("labels", 'shape or mesh: a body of labels is a mass-spring scene\'s (model = "mass-spring")')
    if which == "mesh":
        from ..mesh import grid_from_mesh

        t.only_with("origin", "mesh")
        mesh = t.text("mesh", "a mesh file name (relative to the scene file)")
        padding = t.integer("padding", "an integer >= 0 (node layers)", default=0)
        scale = t.num("scale", "a positive number (metres per mesh unit)", default=1.0, lo=0, lo_open=True)
        with t.src.located(t.key("mesh"), keys={k: t.key(k) for k in ("spacing", "padding", "scale")}):
            return grid_from_mesh(base / mesh, spacing, topology=topology, padding=padding, scale=scale)
    t.only_with("label_spacing", "labels")
    t.only_with("padding", "shape")
    t.only_with("scale", "shape")
    shape = t.raw("shape", "three node counts [D, H, W]")
    if (
        not (
            isinstance(shape, list)
            and len(shape) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) for n in shape)
        )
        or min(shape) < 1
    ):
        raise t.fail("shape", "three node counts [D, H, W], each >= 1", got=shape)
    origin = t.vec("origin", "three numbers [od, oh, ow] in metres", default=(0.0, 0.0, 0.0))
    with t.src.located(t.key("shape"), keys={"grid.shape": t.key("shape")}):
        check_grid("grid.shape", shape, topology=topology)
    with t.src.located(t.name):
        spacing = tuple(spacing) if isinstance(spacing, list) else (spacing,) * 3
        return Grid(tuple(shape), spacing=spacing, topology=topology, origin=origin)


def faces(t: Table, k: str, grid: Grid) -> torch.Tensor:
    """Bool ``(D, H, W)`` of the nodes on the face or faces named by key ``k`` (a name or a list)."""
    v = t.data[k]
    names = [v] if isinstance(v, str) else v
    expected = "a face name or a list of them: " + ", ".join(f'"{f}"' for f in FACES)
    if not isinstance(names, list) or not all(isinstance(n, str) and n in FACES for n in names):
        raise t.fail(k, expected, got=v)
    mask = torch.zeros(grid.shape, dtype=torch.bool)
    for n in names:
        mask |= grid.face(n)
    return mask


def node_list(t: Table, k: str, grid: Grid) -> torch.Tensor:
    """Bool ``(D, H, W)`` of the nodes listed by key ``k`` (``[[i, j, k], ...]``)."""
    v = t.raw(k, "a list of node indices [[i, j, k], ...]")
    if not isinstance(v, list) or not v:
        raise t.fail(k, "a non-empty list of node indices [[i, j, k], ...]", got=v)
    for n, ijk in enumerate(v):
        t.index(k, value=ijk, where=f"{t.key(k)}[{n}]")
    with t.src.located(t.key(k)):
        return grid.index_mask(v)


def drags_section(src: Source, items, grid: Grid) -> list:
    """The :class:`~torchdeform.sim.forces.Drag` s of the ``[[drags]]`` tables ``items``."""
    if not isinstance(items, list):
        raise src.error("drags", "[[drags]] tables", got=items)
    drags = []
    for n, item in enumerate(items):
        t = Table(src, f"drags[{n}]", item, SECTIONS["drags"])
        which = t.one_of("nodes", "face", "box")
        if which == "nodes":
            nodes = node_list(t, "nodes", grid)
        elif which == "face":
            nodes = faces(t, "face", grid)
        else:
            b = Table(src, t.key("box"), t.data["box"], ("lo", "hi"))
            lo, hi = b.vec("lo", "three numbers [d, h, w] in metres"), b.vec("hi", "three numbers [d, h, w] in metres")
            nodes = grid.box_mask(lo, hi)
            if not bool(nodes.any()):
                raise t.fail(
                    "box",
                    "a box {lo, hi} (rest positions, m) containing at least one node",
                    got={"lo": list(lo), "hi": list(hi)},
                )
        expected = "a list of waypoints [[t, [od, oh, ow]], ...] (s, m)"
        path = t.raw("path", expected)
        if not (
            isinstance(path, list)
            and path
            and all(
                isinstance(p, list)
                and len(p) == 2
                and is_number(p[0])
                and isinstance(p[1], list)
                and len(p[1]) == 3
                and all(is_number(c) for c in p[1])
                for p in path
            )
        ):
            raise t.fail("path", expected, got=path)
        size = max(n * h for n, h in zip(grid.shape, grid.spacing))
        far = max(math.sqrt(sum(c * c for c in p[1])) for p in path)
        if far > 1000 * size:
            raise t.fail(
                "path",
                f"offsets within 1000 body sizes ({1000 * size:.3g} m here; farther, float32 positions "
                "no longer resolve the node spacing)",
                got=path,
            )
        with src.located(t.key("path")):
            drags.append(Drag(nodes, path=[(float(p[0]), tuple(float(c) for c in p[1])) for p in path]))
    return drags


def region_mask(t: Table, grid) -> torch.Tensor:
    """Bool ``(D, H, W)`` of the nodes in the region of ``t``: ``sphere = {center, radius}`` or ``box = {lo, hi}``.

    Rest positions in metres; a region without a node is an error naming the key.
    """
    which = t.one_of("sphere", "box")
    if which == "sphere":
        b = Table(t.src, t.key("sphere"), t.data["sphere"], ("center", "radius"))
        c = torch.tensor(b.vec("center", "three numbers [d, h, w] in metres"), dtype=torch.float64)
        r = b.num("radius", "a positive number of metres", lo=0, lo_open=True)
        X = grid.rest_positions(dtype=torch.float64)[0]
        mask = ((X - c.view(3, 1, 1, 1)) ** 2).sum(0) <= r * r * (1 + 1e-12)
    else:
        b = Table(t.src, t.key("box"), t.data["box"], ("lo", "hi"))
        mask = grid.box_mask(
            b.vec("lo", "three numbers [d, h, w] in metres"), b.vec("hi", "three numbers [d, h, w] in metres")
        )
    mask = mask & grid.nodes()
    if not bool(mask.any()):
        raise t.fail(which, "a region containing at least one node (rest positions, m)", got=t.data[which])
    return mask
