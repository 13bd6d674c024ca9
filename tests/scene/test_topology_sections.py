"""Scene sections for topology changes: ``[[cuts]]``, ``[[cautery]]``, ``[tear]``, ``[[coagulate]]``,
``[output] surfaces``, and what ``run_scene`` reports about them.

Expectations come from formulas and from the recorded positions, not from the code under test: a
flat cut across an ``n_h x n_w`` cross-section removes ``n_h n_w`` springs (6 neighbours) or
``(3 n_h - 2)(3 n_w - 2)`` (26: the nine half-directions with a step along the cut's normal, each
``(n_h - |dh|)(n_w - |dw|)`` times); a burnt node's mass is its share of the cells around it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from torchdeform import cli
from torchdeform.scene import energy_series, load_scene, run_scene

SCENES = Path(__file__).resolve().parents[2] / "scenes"


def body(shape=(4, 3, 4), topology=26, spacing=0.01, gravity=-9.81):
    return f"""
[grid]
shape = {list(shape)}
spacing = {spacing}
topology = {topology}

[material]
stiffness = 20.0
damping = 1e-3

[mass]
density = 1000.0

[boundary]
fixed = "bottom"
gravity = [{gravity}, 0.0, 0.0]
"""


def run_part(steps=40, dt=2e-4, extra=""):
    return f"""
[integrator]
name = "symplectic"
dt = {dt}
steps = {steps}
threads = 1

[output]
record_every = 10
{extra}"""


# a flat blade between node layers 1 and 2 (d = 15 mm), wider than the body, at t = 2 ms
BLADE = """
[[cuts]]
origin = [0.015, -0.01, -0.01]
u = [0.0, 0.05, 0.0]
v = [0.0, 0.0, 0.06]
at = 0.002
"""


def write(folder, text, name="scene.toml"):
    path = Path(folder) / name
    path.write_text(text)
    return path


def run(tmp_path, text):
    out = tmp_path / "out"
    summary = run_scene(load_scene(write(tmp_path, text)), out, progress=False)
    assert json.loads((out / "summary.json").read_text())["topology"] == json.loads(json.dumps(summary["topology"]))
    return summary, out


def lumped_masses(shape, spacing, density):
    """Mass per node (kg): density times the node's share of the cells around it (half a spacing at faces)."""
    m = np.full(shape, density, dtype=np.float64)
    for axis, n in enumerate(shape):
        w = np.full(n, spacing)
        w[[0, -1]] = spacing / 2
        m = m * w.reshape([-1 if a == axis else 1 for a in range(3)])
    return m


# ------------------------------------------------------------------ cuts
@pytest.mark.parametrize("topology", [6, 26])
def test_full_blade_cut_counts_pieces_and_closed_surfaces(tmp_path, topology):
    n_h, n_w = 3, 4
    text = body((4, n_h, n_w), topology) + BLADE + run_part(extra="surfaces = [0.0, 0.006]")
    summary, out = run(tmp_path, text)
    topo = summary["topology"]
    expected = n_h * n_w if topology == 6 else (3 * n_h - 2) * (3 * n_w - 2)
    assert topo["springs_removed_by_cuts"] == expected
    assert topo["sections"]["cuts[0]"]["springs"] == expected
    assert topo["sections"]["cuts[0]"]["first_t_s"] == pytest.approx(0.002)
    assert topo["springs_left"] == summary["springs"] - expected
    assert topo["components"] == 2
    assert topo["springs_removed_by_tear"] == topo["cautery_nodes_removed"] == topo["coagulated_springs"] == 0
    before, after = topo["surfaces"]
    assert before["components"] == 1 and len(before["files"]) == 1  # at t = 0: not cut yet
    assert after["components"] == 2 and len(after["files"]) == 2
    for name in before["files"] + after["files"]:
        mesh = trimesh.load(out / name)
        assert mesh.is_watertight and mesh.volume > 0, name
    assert (out / "topology.png").stat().st_size > 0


def test_scalpel_cuts_what_its_edge_sweeps(tmp_path):
    # a vertical edge drawn along H through the whole body at w = 15 mm (between W nodes 1 and 2),
    # reaching from above the top down to d = 15 mm: it cuts layers 2 and 3 (of 4) all along H.
    n_d, n_h = 4, 3
    tool = """
[[tools]]
name = "knife"
shape = "sphere"
radius = 0.001
contact = "none"
path = [[0.0, [0.05, -0.01, 0.015]], [0.004, [0.05, 0.03, 0.015]]]

[[cuts]]
tool = "knife"
edge = [[0.0, 0.0, 0.0], [-0.035, 0.0, 0.0]]
stop = 0.004
pieces = 2
"""
    summary, _ = run(tmp_path, body((n_d, n_h, 4), 6, gravity=0.0) + tool + run_part(steps=30))
    topo = summary["topology"]
    assert topo["springs_removed_by_cuts"] == 2 * n_h  # springs along W in layers 2, 3
    assert topo["components"] == 1
    assert summary["tools"]["knife"]["contact"] == "none"


# ------------------------------------------------------------------ cautery
def test_cautery_removes_the_nodes_inside_the_tool_and_their_mass(tmp_path):
    shape, spacing, density = (4, 4, 4), 0.01, 1000.0
    centre, radius = np.array([0.03, 0.015, 0.015]), 0.012
    tools = f"""
[[tools]]
name = "cautery"
shape = "sphere"
radius = {radius}
contact = "none"
position = {centre.tolist()}

[[cautery]]
tool = "cautery"
at = 0.002
"""
    summary, out = run(tmp_path, body(shape, 26, spacing) + tools + run_part())
    topo = summary["topology"]
    traj = np.load(out / "trajectory.npz")
    k = int(np.flatnonzero(np.isclose(traj["t"], 0.002))[0])  # burnt after this frame's step
    x = traj["x"][k].astype(np.float64)
    inside = np.linalg.norm(x - centre.reshape(3, 1, 1, 1), axis=0) < radius
    assert inside.sum() > 0
    assert topo["cautery_nodes_removed"] == int(inside.sum())
    mass = lumped_masses(shape, spacing, density)
    assert topo["cautery_mass_removed_kg"] == pytest.approx(float(mass[inside].sum()), rel=1e-5)
    v = traj["v"][k].astype(np.float64)
    momentum = (mass[None] * v)[:, inside].sum(1)
    assert topo["cautery_momentum_removed_kg_m_per_s"] == pytest.approx(momentum.tolist(), rel=1e-3, abs=1e-12)
    assert np.all(traj["v"][-1][:, inside] == 0)  # burnt nodes stay at rest


def test_cautery_every_other_step_along_a_path(tmp_path):
    shape, spacing, density = (4, 4, 4), 0.01, 1000.0
    tools = """
[[tools]]
name = "cautery"
shape = "sphere"
radius = 0.006
contact = "none"
path = [[0.0, [0.03, -0.01, 0.015]], [0.006, [0.03, 0.04, 0.015]]]

[[cautery]]
tool = "cautery"
start = 0.001
stop = 0.006
every = 2
"""
    summary, out = run(tmp_path, body(shape, 26, spacing) + tools + run_part())
    topo = summary["topology"]
    v = np.load(out / "trajectory.npz")["v"][-1]
    bottom = np.zeros(shape, dtype=bool)
    bottom[0] = True
    burnt = (np.abs(v).max(0) == 0) & ~bottom  # burnt nodes are held at rest
    assert 0 < burnt.sum() < 16 and not burnt[:-1].any()  # nodes of the top layer only
    assert topo["cautery_nodes_removed"] == int(burnt.sum())
    assert topo["cautery_mass_removed_kg"] == pytest.approx(
        float(lumped_masses(shape, spacing, density)[burnt].sum()), rel=1e-5
    )
    calls = topo["sections"]["cautery[0]"]["calls"]
    assert calls == 13  # even steps 6 (t >= 1 ms) to 30 (6 ms)


# ------------------------------------------------------------------ tear and coagulation
@pytest.mark.parametrize("limit", ["max_strain = 0.21", "max_force = 0.042"])  # 0.21 k l0 = 0.21 x 20 x 0.01 N
def test_a_stretched_spring_tears(tmp_path, limit):
    text = (
        body((2, 1, 1), 6, gravity=0.0)
        + """
[[drags]]
face = "top"
path = [[0.0, [0.0, 0.0, 0.0]], [0.004, [0.005, 0.0, 0.0]]]

[tear]
"""
        + limit
        + "\n"
        + run_part(steps=30)
    )
    topo = run(tmp_path, text)[0]["topology"]
    assert topo["springs_removed_by_tear"] == 1
    assert topo["components"] == 2
    # the strain (5 mm / 4 ms) t / 10 mm = 125 t passes 0.21 after t = 1.68 ms: the first state after it, step 9
    assert topo["sections"]["tear"]["first_t_s"] == pytest.approx(0.0018)


def test_coagulation_counts_the_springs_inside_the_region(tmp_path):
    n_d, n_h, n_w = 2, 3, 3  # the two lowest layers of 4
    region = """
[[coagulate]]
at = 0.004
box = {lo = [0.0, 0.0, 0.0], hi = [0.01, 0.02, 0.02]}
viscosity_factor = 3.0
"""
    topo = run(tmp_path, body((4, 3, 3), 6) + region + run_part())[0]["topology"]
    expected = (n_d - 1) * n_h * n_w + n_d * (n_h - 1) * n_w + n_d * n_h * (n_w - 1)
    assert topo["coagulated_springs"] == expected
    assert topo["components"] == 1 and topo["springs_removed_by_cuts"] == 0


def test_shipped_cut_scene_loads():
    scene = load_scene(SCENES / "cut.toml")
    assert scene.topology is not None and len(scene.topology.cuts) == 1
    assert scene.topology.surfaces == [pytest.approx(scene.steps * scene.dt)]
    assert scene.grid.shape == (8, 16, 16) and scene.grid.topology == 26


@pytest.mark.slow
def test_shipped_cut_scene_opens_the_block(tmp_path):
    scene = load_scene(SCENES / "cut.toml")
    scene.texture = None  # checked here: the opening; the scene's texture is run by test_scene.py
    summary = run_scene(scene, tmp_path, progress=False)
    topo = summary["topology"]
    assert topo["springs_removed_by_cuts"] > 0 and topo["components"] == 1
    names = topo["surfaces"][0]["files"]  # one closed surface per side of the cut (Punak)
    assert len(names) == 2 and all(trimesh.load(tmp_path / name).is_watertight for name in names)
    x = np.load(tmp_path / "trajectory.npz")["x"][-1]
    assert x[2, -1, 8, 8] - x[2, -1, 8, 7] > 0.0025  # the top lips, 2 mm apart at rest, move apart
    # the carved render, looking along the cut (view h, 96 x 96 pixels, D up): the cut plane w = 15 mm
    # is the middle of the 30 mm block (columns 47, 48); it reaches from the top down to d = 6.5 mm
    # of 14 (the upper 54 %: rows 0 .. 51). Below the sagging top, the gap is empty after the cut
    # and tissue before it.
    from PIL import Image

    before = np.asarray(Image.open(tmp_path / "volume_before.png")).astype(float).sum(2)
    after = np.asarray(Image.open(tmp_path / "volume_after.png")).astype(float).sum(2)
    gap = (slice(20, 41), slice(47, 49))
    assert before[gap].min() > 100 and after[gap].max() == 0
    assert after[60:90].mean() > 100  # below the cut the tissue is still there


# ------------------------------------------------------------------ bad input
TOOL = """
[[tools]]
name = "knife"
shape = "sphere"
radius = 0.001
path = [[0.0, [0.035, -0.01, 0.015]], [0.004, [0.035, 0.03, 0.015]]]
"""
GOOD = body() + BLADE + TOOL + run_part()


def _edit(old, new, text=GOOD):
    assert old in text, old
    return text.replace(old, new, 1)


BAD = {
    # id: (scene text, key, expected text, text of the line the message points to)
    "blade misses the body": (
        _edit("origin = [0.015,", "origin = [0.5,"),
        "cuts[0].origin",
        "a blade that reaches the body",
        "origin =",
    ),
    "degenerate triangle": (
        _edit(
            "origin = [0.015, -0.01, -0.01]\nu = [0.0, 0.05, 0.0]\nv = [0.0, 0.0, 0.06]",
            "triangle = [[0.01, 0.0, 0.0], [0.02, 0.01, 0.0], [0.03, 0.02, 0.0]]",
        ),
        "cuts[0].triangle",
        "a non-degenerate triangle",
        "triangle =",
    ),
    "parallel blade edges": (
        _edit("v = [0.0, 0.0, 0.06]", "v = [0.0, 0.1, 0.0]"),
        "cuts[0].origin",
        "a non-degenerate blade",
        "origin =",
    ),
    "swept edges of one pose": (
        _edit(
            "origin = [0.015, -0.01, -0.01]\nu = [0.0, 0.05, 0.0]\nv = [0.0, 0.0, 0.06]",
            "edges = [[[0.015, 0.0, 0.0], [0.015, 0.0, 0.03]]]",
        ),
        "cuts[0].edges",
        "two or more poses",
        "edges =",
    ),
    "negative strain limit": (
        GOOD + "\n[tear]\nmax_strain = -0.1\n",
        "tear.max_strain",
        "a positive strain",
        "max_strain =",
    ),
    "zero force limit": (GOOD + "\n[tear]\nmax_force = 0\n", "tear.max_force", "a positive force", "max_force ="),
    "strain and force": (
        GOOD + "\n[tear]\nmax_strain = 0.1\nmax_force = 1.0\n",
        "tear.max_force",
        "exactly one of max_strain or max_force",
        "max_force =",
    ),
    "time before zero": (_edit("at = 0.002", "at = -0.001"), "cuts[0].at", "a time >= 0", "at = -0.001"),
    "time after the end": (_edit("at = 0.002", "at = 0.5"), "cuts[0].at", "a time in [0, 0.008] s", "at = 0.5"),
    "surfaces after the end": (
        _edit("record_every = 10", "record_every = 10\nsurfaces = [0.001, 1.0]"),
        "output.surfaces",
        "a time in [0, 0.008] s",
        "surfaces =",
    ),
    "unknown tool": (
        GOOD + '\n[[cautery]]\ntool = "laser"\nat = 0.001\n',
        "cautery[0].tool",
        "the name of a [[tools]] tool (knife)",
        'tool = "laser"',
    ),
    "unknown cut tool": (
        GOOD + '\n[[cuts]]\ntool = "scalpel"\nedge = [[0, 0, 0], [0.01, 0, 0]]\n',
        "cuts[1].tool",
        "the name of a [[tools]] tool (knife)",
        'tool = "scalpel"',
    ),
    "unknown key": (_edit("at = 0.002", "at = 0.002\nspeed = 1.0"), "cuts[0].speed", "one of the keys", "speed ="),
    "unknown tear key": (GOOD + "\n[tear]\nmax_strain = 0.5\nlimit = 2\n", "tear.limit", "one of the keys", "limit ="),
    "key of another form": (
        _edit("at = 0.002", "at = 0.002\nstop = 0.004"),
        "cuts[0].stop",
        "no stop with origin",
        "stop =",
    ),
    "scalpel edge misses the body": (
        GOOD + '\n[[cuts]]\ntool = "knife"\nedge = [[0, 0, 0], [0.001, 0, 0]]\n',
        "cuts[1].edge",
        "an edge that reaches the body",
        "edge = [[0, 0, 0], [0.001",
    ),
    "scalpel edge of one point": (
        GOOD + '\n[[cuts]]\ntool = "knife"\nedge = [[0, 0, 0], [0, 0, 0]]\n',
        "cuts[1].edge",
        "two different ends",
        "edge = [[0, 0, 0], [0, 0",
    ),
    "gape of one": (_edit("at = 0.002", "at = 0.002\ngape = 1.0"), "cuts[0].gape", "a fraction in [0, 1)", "gape ="),
    "cautery at and start": (
        GOOD + '\n[[cautery]]\ntool = "knife"\nat = 0.001\nstart = 0.0\n',
        "cautery[0].start",
        "no start together with cautery[0].at",
        "start =",
    ),
    "coagulate outside the body": (
        GOOD + "\n[[coagulate]]\nbox = {lo = [1, 1, 1], hi = [2, 2, 2]}\n",
        "coagulate[0].box",
        "at least one node",
        "box =",
    ),
    "viscosity factor below one": (
        GOOD + "\n[[coagulate]]\nsphere = {center = [0, 0, 0], radius = 0.02}\nviscosity_factor = 0.5\n",
        "coagulate[0].viscosity_factor",
        "a factor >= 1",
        "viscosity_factor =",
    ),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_topology_input_is_one_line_exit_2(case, bad_dir, capsys):
    text, key, expected, needle = BAD[case]
    path = write(bad_dir, text, "bad.toml")
    rc = cli.main(argv=["run", str(path), "--out", str(bad_dir / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.endswith("\n") and err.count("\n") == 1, err
    line = text[: text.index(needle)].count("\n") + 1
    assert err.startswith(f"torchdeform: {path}:{line}: {key}: expected "), err
    assert expected in err, err
    assert not (bad_dir / "out" / "summary.json").exists()


def test_time_after_the_end_with_auto_dt_is_found_when_the_run_starts(bad_dir, capsys):
    text = _edit("at = 0.002", "at = 5.0", _edit("dt = 0.0002", 'dt = "auto"'))
    path = write(bad_dir, text, "bad.toml")
    load_scene(path)  # the run's length is not known yet
    rc = cli.main(argv=["run", str(path), "--out", str(bad_dir / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert err.startswith(
        f"torchdeform: {path}:{text[: text.index('at = 5.0')].count(chr(10)) + 1}: cuts[0].at: expected a time in [0, "
    ), err
    assert not (bad_dir / "out" / "summary.json").exists()


def test_energies_of_each_frame_use_the_springs_of_that_frame(tmp_path):
    """Frames before the cut: the uncut model's energies; after it, the cut springs store less energy."""
    text = body((4, 3, 4), 26, gravity=-30.0) + BLADE.replace("at = 0.002", "at = 0.004") + run_part(steps=40)
    summary, out = run(tmp_path, text)
    rec = np.load(out / "trajectory.npz")
    scene = load_scene(write(tmp_path, text, "again.toml"))
    uncut = scene.build()  # a fresh model: no spring cut
    x, v = torch.from_numpy(rec["x"]), torch.from_numpy(rec["v"])
    oracle = energy_series(uncut, x, v)
    before = rec["t"] < 0.004 - 1e-9
    after = rec["t"] > 0.004 + 1e-9
    assert before.sum() >= 2 and after.sum() >= 2
    for key in ("kinetic", "elastic", "gravity", "total"):
        np.testing.assert_allclose(rec[key][before], oracle[key][before], rtol=1e-5, atol=1e-12)
    # after the cut the removed springs hold no energy: less elastic energy than the uncut model gives
    assert (rec["elastic"][after] < oracle["elastic"][after] - 1e-9).all()
    assert summary["final_energy_J"]["elastic"] == pytest.approx(float(rec["elastic"][-1]))


# ------------------------------------------------------------------ every engine
EVERY_CHANGE = (
    body((5, 4, 4), 26)
    + BLADE.replace("at = 0.002", "at = 0.002\ngape = 0.25")
    + """
[[tools]]
name = "cautery"
shape = "sphere"
radius = 0.012
contact = "none"
position = [0.04, 0.015, 0.015]

[[cautery]]
tool = "cautery"
at = 0.003

[[coagulate]]
at = 0.004
box = {lo = [0.0, 0.0, 0.0], hi = [0.01, 0.03, 0.03]}
viscosity_factor = 3.0

[[drags]]
face = "w+"
path = [[0.0, [0.0, 0.0, 0.0]], [0.008, [0.0, 0.0, 0.006]]]

[tear]
max_strain = 0.6
"""
    + run_part(steps=40)
)


# a gaping cut alone through an Elastic body (cells die, springs are re-assembled, damping zeroed)
ELASTIC_CUT = (
    body((5, 4, 4), 26).replace(
        "stiffness = 20.0\ndamping = 1e-3", 'tissue = "liver"\npoisson_ratio = 0.45\ndamping = 2e-4'
    )
    + BLADE.replace("at = 0.002", "at = 0.002\ngape = 0.25")
    + """
[[drags]]
face = "w+"
path = [[0.0, [0.0, 0.0, 0.0]], [0.008, [0.0, 0.0, 0.004]]]
"""
    + run_part(steps=40)
)
SCENE_TEXTS = {"every change": EVERY_CHANGE, "elastic cut": ELASTIC_CUT}


@pytest.mark.parametrize(
    "engine, scene",
    [
        ("native", "every change"),
        ("native", "elastic cut"),
        pytest.param("compiled", "elastic cut", marks=pytest.mark.slow),
    ],
)
def test_topology_changes_on_a_packed_engine_follow_the_eager_run(tmp_path, engine, scene):
    """A gaping cut, cautery, coagulation and tears, or a gaping cut of an Elastic body, on the
    native (or compiled) engine: the packed step shares the model's fields, so the run equals the
    eager one (float32 rounding) with the same changes counted."""
    from torchdeform.sim import native

    if native.unavailable():
        pytest.skip(native.unavailable())
    if engine == "compiled":
        pytest.importorskip("torch._inductor")
    runs = {}
    for name in ("eager", engine):
        text = SCENE_TEXTS[scene].replace("threads = 1", f'threads = 1\nengine = "{name}"')
        (tmp_path / name).mkdir()
        summary, out = run(tmp_path / name, text)
        assert summary["engine"]["ran"] == name
        runs[name] = summary, np.load(out / "trajectory.npz")
    (ref, ref_traj), (got, traj) = runs["eager"], runs[engine]
    counts = ("springs_removed_by_cuts", "springs_removed_by_tear", "cautery_nodes_removed", "coagulated_springs")
    if scene == "every change":
        assert all(ref["topology"][k] > 0 for k in counts), ref["topology"]  # every change happened
    else:
        assert ref["topology"]["springs_removed_by_cuts"] > 0
    assert {k: got["topology"][k] for k in counts} == {k: ref["topology"][k] for k in counts}
    assert np.abs(traj["x"] - ref_traj["x"]).max() < 1e-6  # m, float32 rounding over 40 steps
