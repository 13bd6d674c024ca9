"""Fuzzing the contract with hypothesis: mutated scene files, ``.fis`` files (huge header counts
among them), CSVs, series and volumes from valid seeds, random values of the ``data cube`` command
(run; huge sizes and large time steps among them), small scenes of every integrator kind with a
section or option missing or a boolean key that holds no boolean, ``run --set`` values, non-finite
start states of ``simulate``, and random values of every option of every command (parsed).

Every generated case must end in exit status 0 with whole, finite outputs, or exit status 2 with
one line on stderr (warnings, one line each, may come before it), never a traceback, and never a
staging file left behind. The commands run in-process (``torchdeform.cli.main``), so a case costs
milliseconds to a few tenths of a second; ``CASES`` per family (1,370 in all) run in about
a minute on 2 cores. Several problems of one scene file are one line each (a few lines).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
import tempfile
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from tests.helpers import cli_call
from torchdeform import cli
from torchdeform.errors import TorchdeformError
from torchdeform.learn import load_series
from torchdeform.outputs import STAGING

pytestmark = pytest.mark.slow  # fuzz campaigns (hypothesis, 1,370 cases)

ROOT = Path(__file__).resolve().parents[1]
#: generated cases per family (60 scene files reach every kind of mutation and every lost section)
CASES = {
    "scene": 60,
    "fis": 250,
    "csv": 150,
    "series": 150,
    "volume": 120,
    "cli": 200,
    "options": 150,
    "kinds": 60,
    "set": 40,
    "state": 60,
}


def fuzz(family: str):
    return settings(
        max_examples=CASES[family],
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


call = cli_call  # ``torchdeform ARGV`` in-process: (exit status, stdout, stderr)


def holds(status, err: str, folder: Path | None = None) -> None:
    """The contract: 0, or 2 with one error line (warning lines may precede it); no traceback."""
    assert status in (0, 2), (status, err)
    assert "Traceback" not in err, err
    event(f"exit {status}")
    lines = [x for x in err.splitlines() if x.strip()]
    errors = [x for x in lines if ": warning: " not in x]
    if status == 2:  # one line; a scene file's several problems: one line each, all naming the file
        assert len(errors) == 1 or (1 < len(errors) <= 12 and all(".toml" in x for x in errors)), err
        event(f"{len(errors)} error lines" if len(errors) > 1 else "one error line")
    else:
        assert not errors, err
    if folder is not None and folder.exists():
        assert not list(folder.rglob(STAGING + "*")), list(folder.rglob("*"))


def finite_npz(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        for k in z.files:
            a = z[k]
            if a.dtype.kind == "f":
                assert np.isfinite(a).all(), (path, k)


# ------------------------------------------------------------------ values a mutation puts in
WILD = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1, 2, 3, 1e-300, 1e300, -1e-9, 0.5, 1e9, 10**12, 26, 6, 7]),
    st.integers(-(10**6), 10**6),
    st.text(max_size=12),
    st.booleans(),
    st.lists(st.sampled_from([0, 1, -1, 2.5, 1e300, "a", None, 3]), max_size=4),
)


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) if x is not None else '"none"' for x in v) + "]"
    return json.dumps(str(v))


# ------------------------------------------------------------------ scene files
SCENE = textwrap.dedent("""\
    [grid]
    shape = [3, 3, 4]
    spacing = 0.01
    topology = 18

    [material]
    stiffness = 40.0
    damping = 0.05

    [mass]
    density = 1000.0

    [boundary]
    fixed = ["bottom"]
    gravity = [-9.81, 0.0, 0.0]

    [[loads]]
    node = [2, 1, 3]
    force = [-0.01, 0.0, 0.0]
    ramp = 0.001

    [[drags]]
    face = "top"
    path = [[0.0, [0.0, 0.0, 0.0]], [0.002, [0.0, 0.0, 0.001]]]

    [integrator]
    name = "symplectic"
    dt = 1e-4
    steps = 30

    [output]
    record_every = 10
    """)
KEYS = [i for i, line in enumerate(SCENE.splitlines()) if "=" in line]
INTEGRATORS = ["explicit", "symplectic", "verlet", "rk4", "implicit", "knoche", "projective", "adaptive", "nope"]


@st.composite
def scenes(draw):
    lines = SCENE.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.sampled_from(KEYS))
        if "=" not in lines[i]:  # dropped by an earlier mutation
            continue
        key = lines[i].split("=")[0].strip()
        kind = draw(st.sampled_from(["value", "value", "fair", "fair", "drop", "unknown", "integrator"]))
        if kind == "value":
            lines[i] = f"{key} = {toml_value(draw(WILD))}"
        elif kind == "fair":  # a plausible value of the right kind: runs mostly
            old = lines[i].split("=", 1)[1].strip()
            try:
                float(old)
            except ValueError:  # a list, string, bool, nan ...: left as it is
                continue
            factor = draw(st.sampled_from([0.5, 2.0, 10.0, 0.1, 3.0]))
            lines[i] = f"{key} = {max(1, int(float(old) * factor)) if old.isdigit() else float(old) * factor!r}"
        elif kind == "drop":
            lines[i] = ""
        elif kind == "unknown":
            lines[i] += f"\n{draw(st.sampled_from(['colour', 'spacingg', 'dt2']))} = 1"
        else:
            lines = [f'name = "{draw(st.sampled_from(INTEGRATORS))}"' if x.startswith("name =") else x for x in lines]
    if draw(st.booleans()) and draw(st.booleans()):
        header = draw(st.sampled_from(["[mass]", "[integrator]", "[material]", "[grid]"]))
        lines = [x for x in lines if x != header]  # a section lost: its keys join another
    return "\n".join(lines) + "\n"


def _small(text: str) -> bool:
    """Cheap enough to run here: at most ~100 nodes x 2,000 steps (others are only loaded)."""
    from torchdeform.scene import load_scene

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.toml"
        path.write_text(text)
        try:
            s = load_scene(path)
        except TorchdeformError:
            return True  # refused while loading: running is cheap too
        steps = getattr(s, "steps", None) or getattr(s, "frames", 1)
        return s.grid.num_nodes <= 200 and steps <= 2000


@fuzz("scene")
@given(scenes())
def test_fuzzed_scene_files(text):
    d = Path(tempfile.mkdtemp())
    try:
        path = d / "s.toml"
        path.write_text(text)
        if not _small(text):
            from torchdeform.scene import load_scene

            load_scene(path)  # loads without a traceback; too long to run here
            event("loaded only (too long to run here)")
            return
        out = d / "out"
        status, _, err = call(["run", path, "--out", out, "--quiet"])
        holds(status, err, out)
        if status == 0:
            assert json.loads((out / "summary.json").read_text())["outputs"] == sorted(
                p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()
            )
            finite_npz(out / "trajectory.npz")
        else:
            assert not out.exists() or not any(out.iterdir())
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ------------------------------------------------------------------ .fis files
FIS = (ROOT / "fuzzy" / "susilap_g.fis").read_text().splitlines()
FIS_LINES = [i for i, line in enumerate(FIS) if line and not line.startswith("%")]


@st.composite
def fis_files(draw):
    lines = list(FIS)
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.sampled_from(FIS_LINES))
        kind = draw(st.sampled_from(["number", "number", "drop", "dup", "garble", "value", "count"]))
        if kind == "count":  # a header count far beyond the file (and beyond memory)
            counts = [
                j for j, x in enumerate(lines) if x.startswith(("NumInputs=", "NumOutputs=", "NumMFs=", "NumRules="))
            ]
            j = draw(st.sampled_from(counts))
            huge = draw(st.sampled_from([10**9, 10**12, 2**63, 10**30, 3]))
            lines[j] = lines[j].split("=")[0] + f"={huge}"
        elif kind == "number":
            import re

            nums = list(re.finditer(r"-?\d+(\.\d+)?(e-?\d+)?", lines[i]))
            if nums:
                m = draw(st.sampled_from(nums))
                new = toml_value(
                    draw(
                        st.one_of(
                            st.floats(allow_nan=True, allow_infinity=True),
                            st.sampled_from([0, -1, 1e40, 1e-40, 5, 1000000]),
                        )
                    )
                )
                lines[i] = lines[i][: m.start()] + new + lines[i][m.end() :]
        elif kind == "drop":
            lines[i] = ""
        elif kind == "dup":
            lines.insert(i, lines[i])
        elif kind == "garble":
            lines[i] = draw(st.text(max_size=20))
        else:
            key = lines[i].split("=")[0] if "=" in lines[i] else lines[i]
            lines[i] = f"{key}={draw(st.text(max_size=10))}"
    return "\n".join(lines) + "\n"


@fuzz("fis")
@given(fis_files(), st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, 5.5, 12.0])))
def test_fuzzed_fis_files(text, value):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "r.fis"
        path.write_bytes(text.encode("utf-8", "replace"))
        holds(*call(["fuzzy", "show", path])[::2])
        status, out, err = call(["fuzzy", "eval", path, f"consistency={value}", "--json"])
        holds(status, err)
        if status == 0:
            doc = json.loads(out)
            assert all(
                math.isfinite(v)
                for row in (doc if isinstance(doc, list) else [doc])
                for v in (row.values() if isinstance(row, dict) else [row])
                if isinstance(v, float)
            )


# ------------------------------------------------------------------ CSV inputs
CELL = st.one_of(
    st.floats(-20, 20).map(lambda v: f"{v:.3f}"),
    st.sampled_from(["5.5", "0", "12", "-1", "1e400", "nan", "inf", "", "x", '"']),
)
ROWS = st.lists(st.lists(CELL, min_size=1, max_size=3).map(",".join), min_size=1, max_size=10)


@fuzz("csv")
@given(
    st.one_of(
        st.binary(max_size=200),
        st.tuples(
            st.sampled_from(["consistency", "consistency,extra", "extra,consistency", " consistency ", "x"]), ROWS
        ).map(lambda hr: ("\n".join([hr[0], *hr[1]]) + "\n").encode()),
        st.tuples(st.just("consistency"), ROWS).map(lambda hr: ("\n".join([hr[0], *hr[1]]) + "\n").encode()),
        st.lists(
            st.lists(
                st.one_of(
                    st.sampled_from(["consistency", "x", "", "nan", "inf", "-1", "5.5", "1e400", '"', ";"]),
                    st.text(max_size=6),
                ),
                max_size=4,
            ),
            max_size=8,
        ).map(lambda rows: "\n".join(",".join(r) for r in rows).encode("utf-8", "replace")),
    )
)
def test_fuzzed_csv_inputs(data):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "in.csv"
        path.write_bytes(data)
        status, out, err = call(["fuzzy", "eval", ROOT / "fuzzy" / "susilap_g.fis", "--inputs", path])
        holds(status, err)
        if status == 0:
            for line in out.splitlines()[1:]:
                assert all(math.isfinite(float(v)) for v in line.split(",")), line


# ------------------------------------------------------------------ series files
_SERIES = {}


def _seed_series() -> dict:
    if not _SERIES:
        with np.load(ROOT / "data" / "radetzky_cube_54.npz", allow_pickle=False) as z:
            _SERIES.update({k: z[k] for k in z.files})
    return _SERIES


@st.composite
def series_files(draw):
    arrays = {k: v.copy() for k, v in _seed_series().items()}
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(arrays)))
        kind = draw(st.sampled_from(["drop", "nan", "shape", "dtype", "meta", "scale"]))
        a = arrays[key]
        if kind == "drop":
            arrays.pop(key)
        elif kind == "nan" and a.dtype.kind == "f" and a.size:
            a = a.copy()
            a.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from([np.nan, np.inf, 1e300]))
            arrays[key] = a
        elif kind == "shape" and a.ndim:
            arrays[key] = a.reshape(-1)[: max(0, a.size - draw(st.integers(1, 3)))]
        elif kind == "dtype" and a.dtype.kind in "biuf":
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                arrays[key] = a.astype(draw(st.sampled_from([np.int8, np.float16, np.bool_, np.complex64])))
        elif kind == "meta":
            meta = json.loads(str(arrays.get("meta", np.array("{}"))))
            if meta:
                k = draw(st.sampled_from(sorted(meta)))
                meta[k] = draw(st.one_of(st.none(), st.integers(-5, 5), st.text(max_size=5), st.floats()))
            arrays["meta"] = np.array(json.dumps(meta))
        elif kind == "scale" and a.dtype.kind == "f":
            arrays[key] = a * draw(st.sampled_from([-1.0, 0.0, 1e30]))
        if not arrays:
            break
    return arrays


@fuzz("series")
@given(series_files())
def test_fuzzed_series_files(arrays):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.npz"
        np.savez(path, **arrays)
        try:
            s = load_series(path)
        except TorchdeformError as e:
            assert "\n" not in str(e)
            event("refused")
            return
        event("loaded")
        assert np.isfinite(np.asarray(s.positions)).all()


# ------------------------------------------------------------------ volumes
@st.composite
def volumes(draw):
    odd = draw(st.integers(0, 3)) == 0  # a quarter: any shape; else a volume (D, H, W)
    shape = draw(
        st.lists(st.integers(0, 9), min_size=1, max_size=4)
        if odd
        else st.lists(st.integers(1, 12), min_size=3, max_size=3)
    )
    dtype = draw(st.sampled_from([np.float32, np.float32, np.float64, np.uint8, np.int16, np.bool_, np.complex64]))
    a = np.asarray(draw(st.floats(-1e3, 1e3)) * np.random.default_rng(len(shape)).random(shape)).astype(dtype)
    if a.size and a.dtype.kind == "f" and draw(st.integers(0, 3)) == 0:
        a.flat[0] = draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e38]))
    return a


@fuzz("volume")
@given(volumes(), st.sampled_from(["mip", "dvr", "average"]), st.sampled_from(["h", "d", "-w", "orbit", "x"]))
def test_fuzzed_volumes(arr, mode, view):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "v.npy"
        np.save(path, arr)
        out = Path(d) / "img.png"
        status, _, err = call(["render", path, "--out", out, "--mode", mode, "--view", view, "--size", "16"])
        holds(status, err, Path(d))
        if status == 0:
            from PIL import Image

            with Image.open(out) as im:
                im.load()
        else:
            assert not out.exists()


# ------------------------------------------------------------------ command-line values
NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "-1", "1e-12", "1e308", "abc", "", "3", "nan", "inf", "0x10"]),
)
COUNT = st.one_of(st.integers(-3, 6).map(str), st.integers(1, 8).map(str), st.sampled_from(["0", "-1", "2.5", "x"]))


@st.composite
def data_cube_argv(draw):
    n = draw(st.sampled_from(["2", "3", "3", "3", "0", "1", "x", "5000", "100000", "1000000000"]))
    argv = ["data", "cube", "--n", n, "--steps", draw(COUNT)]
    if draw(st.integers(0, 3)) == 0:  # a large time step: the true run diverges, finite or not
        argv += ["--dt", draw(st.sampled_from(["0.05", "0.2", "1", "10", "1e6"]))]
    for option in draw(
        st.lists(
            st.sampled_from(
                [
                    "--amplitude",
                    "--noise",
                    "--mass",
                    "--stiffness",
                    "--damping",
                    "--every",
                    "--load",
                    "--topology",
                ]
            ),
            max_size=3,
            unique=True,
        )
    ):
        value = draw(COUNT if option in ("--every", "--topology") else NUMBER)
        if option == "--load":
            value = draw(st.sampled_from(["constant", "ramp", "sine", "indent", "boom"]))
        argv += [option, value]
    return argv


@fuzz("cli")
@given(data_cube_argv())
def test_fuzzed_command_line_values(argv):
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "c.npz"
        status, _, err = call([*argv, "--out", out])
        holds(status, err, Path(d))
        if status == 0:
            finite_npz(out)
            s = load_series(out)  # and no runaway: a series within a few body sizes of rest
            size = max(n * h for n, h in zip(s.grid.shape, s.grid.spacing))
            X = s.grid.rest_positions().double()[0].numpy()
            assert np.abs(np.asarray(s.positions) - X[None]).max() <= 10 * size
        else:
            assert not out.exists()


# ------------------------------------------------------------------ scene kinds: sections, options, booleans
SMALL = textwrap.dedent("""\
    [grid]
    shape = [3, 3, 3]
    spacing = 0.01
    topology = TOPOLOGY

    [material]
    stiffness = 40.0

    [mass]
    density = 1000.0

    [boundary]
    fixed = "bottom"

    [integrator]
    name = "NAME"
    dt = 1e-4
    steps = 5
    """)
CHAINMAIL = textwrap.dedent("""\
    model = "chainmail"

    [grid]
    shape = [3, 3, 3]
    spacing = 0.01

    [chainmail]
    frames = 2
    relax_steps = 1

    [[drags]]
    nodes = [[2, 1, 1]]
    path = [[0.0, [0.0, 0.0, 0.0]], [1.0, [0.001, 0.0, 0.0]]]
    """)
#: the boolean keys of the scene readers, and what a table needs beside them
BOOLEANS = {
    ("chainmail", "relax_moved_only"): "",
    ("strain_limit", "update_velocity"): "",
    ("tear", "one_per_step"): "max_strain = 0.5\n",
    ("output", "animation"): "",
}
NOT_BOOLEAN = st.sampled_from(['"no"', '"yes"', '"false"', '"true"', "0", "1", "0.0", "[]", '""', "{}"])


@st.composite
def scene_kinds(draw):
    """A small scene of each integrator kind with a section or option missing, or a boolean that is not one."""
    kind = draw(st.sampled_from(["missing", "missing", "boolean", "boolean", "both"]))
    key = draw(st.sampled_from(sorted(BOOLEANS)))
    if key[0] == "chainmail":
        text = CHAINMAIL
    else:
        name = draw(
            st.sampled_from(["symplectic", "explicit", "verlet", "rk4", "implicit", "knoche", "adaptive", "static"])
        )
        text = SMALL.replace("NAME", name).replace("TOPOLOGY", "6" if name == "knoche" else "26")
        if name == "knoche" and draw(st.booleans()):
            text += "material = 0.5\n"
        if name == "static":
            text = text.replace("dt = 1e-4\nsteps = 5\n", "")
    if kind in ("missing", "both"):
        headers = [x for x in text.splitlines() if x.startswith("[")]
        drop = draw(st.sampled_from(headers))
        text = text.replace(drop + "\n", "")  # its keys join the section before
    if kind in ("boolean", "both"):
        value = draw(st.one_of(NOT_BOOLEAN, st.sampled_from(["true", "false"])))
        if key[0] == "chainmail":
            text = text.replace("relax_steps = 1\n", f"relax_steps = 1\n{key[1]} = {value}\n")
        else:
            text += f"\n[{key[0]}]\n{BOOLEANS[key]}{key[1]} = {value}\n"
    return text


@fuzz("kinds")
@given(scene_kinds())
def test_fuzzed_scene_kinds_sections_and_booleans(text):
    d = Path(tempfile.mkdtemp())
    try:
        path = d / "s.toml"
        path.write_text(text)
        out = d / "out"
        status, _, err = call(["run", path, "--out", out, "--quiet"])
        holds(status, err, out)
        if status == 0:
            finite_npz(out / "trajectory.npz")
            for line in text.splitlines():  # a boolean key that ran held a boolean
                if any(line.startswith(k + " =") for _, k in BOOLEANS):
                    assert line.split("=", 1)[1].strip() in ("true", "false"), line
        else:
            event(err.split(": expected")[0].rsplit(": ", 1)[-1][:40])
            assert not out.exists() or not any(out.iterdir())
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ------------------------------------------------------------------ run --set
SET_KEYS = [
    "integrator.steps",
    "integrator.dt",
    "integrator.name",
    "output.name",
    "material.stiffness",
    "grid.shape",
    "boundary.fixed",
    "chainmail.relax_moved_only",
    "integrator.stepz",
    "nosection.key",
    "loads.force",
]


@fuzz("set")
@given(
    st.lists(
        st.tuples(st.sampled_from(SET_KEYS), st.one_of(WILD.map(toml_value), st.text(max_size=8))),
        min_size=1,
        max_size=3,
    )
)
def test_fuzzed_run_set_values(sets):
    d = Path(tempfile.mkdtemp())
    try:
        path = d / "s.toml"
        path.write_text(SMALL.replace("NAME", "symplectic").replace("TOPOLOGY", "26"))
        out = d / "out"
        argv = ["run", path, "--out", out, "--quiet"]
        for key, value in sets:
            if key == "integrator.steps" and value.lstrip("-").isdigit() and int(value) > 2000:
                value = "2000"  # cheap enough to run here
            if key == "grid.shape":
                value = "[3, 3, 3]" if value.startswith("[") else value
            argv += ["--set", f"{key}={value}"]
        status, _, err = call(argv)
        holds(status, err, out)
        if status == 0:
            finite_npz(out / "trajectory.npz")
        else:
            assert not out.exists() or not any(out.iterdir())
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ------------------------------------------------------------------ non-finite states
@fuzz("state")
@given(
    st.sampled_from(["x", "v"]),
    st.lists(st.integers(0, 3 * 27 - 1), max_size=3),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e30]),
    st.integers(0, 3),
)
def test_fuzzed_start_states_never_return_a_silent_nan(which, where, value, steps):
    import torch

    import torchdeform as td

    model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3, damping=0.01)
    rest = model.rest_state()
    x, v = rest.x.clone(), rest.v.clone()
    target = x if which == "x" else v
    for i in where:
        target.view(-1)[i] = value
    try:
        state, _ = td.simulate(model, td.State(x, v), 1e-4, steps=steps, check_every=1)
    except TorchdeformError as e:
        assert "\n" not in str(e)
        event(type(e).__name__)
        return
    event("ran")
    assert bool(torch.isfinite(state.x).all() and torch.isfinite(state.v).all())


def _options():
    """Every sub-command (``bench speed`` included) with the options that take a value."""
    parser = cli.build_parser()
    found = []

    def walk(p, words):
        subs = [a for a in p._actions if a.__class__.__name__ == "_SubParsersAction"]
        options = [
            a.option_strings[-1]
            for a in p._actions
            if a.option_strings and a.nargs is None and a.__class__.__name__ == "_StoreAction"
        ]
        positionals = [a for a in p._actions if not a.option_strings and a.__class__.__name__ == "_StoreAction"]
        if options:
            found.append((tuple(words), len(positionals), tuple(options)))
        for sub in subs:
            for name, child in sub.choices.items():
                walk(child, [*words, name])

    walk(parser, [])
    return found


OPTIONS = _options()


@st.composite
def option_argv(draw):
    words, positionals, options = draw(st.sampled_from(OPTIONS))
    argv = [*words, *["x"] * positionals]
    for option in draw(st.lists(st.sampled_from(options), min_size=1, max_size=3, unique=True)):
        argv += [option, draw(st.one_of(NUMBER, COUNT, st.text(max_size=8).filter(lambda t: not t.startswith("-"))))]
    return argv


@fuzz("options")
@given(option_argv())
def test_fuzzed_option_values_parse_or_refuse_in_one_line(argv):
    """Every option of every command: a value is taken, or refused while parsing with one line and exit 2."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            cli.build_parser().parse_args(argv)
            status = 0
        except SystemExit as e:
            status = e.code
    holds(status, err.getvalue())


def test_the_families_add_up_to_at_least_1000_cases():
    assert len(OPTIONS) >= 15  # every command with options is reached
    assert sum(CASES.values()) >= 1000 and set(CASES) == {
        "scene",
        "fis",
        "csv",
        "series",
        "volume",
        "cli",
        "options",
        "kinds",
        "set",
        "state",
    }


@pytest.fixture(autouse=True)
def _no_stray_files():
    before = set(Path(tempfile.gettempdir()).glob(STAGING + "*"))
    yield
    assert set(Path(tempfile.gettempdir()).glob(STAGING + "*")) <= before
