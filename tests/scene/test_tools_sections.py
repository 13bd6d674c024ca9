"""Scene sections for tools: ``[[tools]]``, ``[strain_limit]``, tissue words and ``[[regions]]``, and the
tool outputs of ``run_scene`` (force series, forces.png, palpation)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from torchdeform import cli
from torchdeform.fuzzy import load_preset, tissue_parameters
from torchdeform.fuzzy.coupling import Ellipsoid, node_inputs, spring_parameters
from torchdeform.interact import (
    Box,
    Capsule,
    Grasp,
    HalfSpace,
    PenaltyContact,
    ProjectionContact,
    Sphere,
    StrainLimit,
    Tool,
    support_reaction,
)
from torchdeform.scene import load_scene, run_scene
from torchdeform.scene.mass_spring import lattice_modulus, tissue_moduli
from torchdeform.scene.tools import ToolSet, tool_outputs

BODY = """
[grid]
shape = [4, 4, 5]
spacing = 0.005
topology = 26

[material]
stiffness = 5.0
damping = 1e-3

[mass]
density = 1000.0

[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
"""

RUN = """
[integrator]
name = "symplectic"
dt = 2e-4
steps = 100

[output]
record_every = 20
"""

# a probe pressing 2 mm into the top face above node (3, 1, 1), forceps lifting node (3, 1, 4) by 5 mm
TOOLS = """
[[tools]]
name = "probe"
shape = "sphere"
radius = 0.004
friction = 0.3
haptic_gain = 10.0
path = [[0.0, [0.0195, 0.005, 0.005]], [0.02, [0.0170, 0.005, 0.005]]]

[[tools]]
name = "forceps"
shape = "box"
half_extents = [0.003, 0.003, 0.003]
contact = "none"
grasp = {close = 0.005, open = 0.015}
path = [[0.0, [0.015, 0.005, 0.02]], [0.005, [0.015, 0.005, 0.02]], [0.015, [0.02, 0.005, 0.02]]]

[strain_limit]
min = 0.8
max = 1.2
passes = 1
"""

GOOD = BODY + TOOLS + RUN


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def line_containing(text, needle):
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


# ------------------------------------------------------------------ comparing objects
def assert_same_tool(a: Tool, b: Tool):
    assert a.name == b.name and type(a.shape) is type(b.shape)
    if hasattr(a.shape, "field"):  # a MeshShape: its sampled field
        assert torch.equal(a.shape.field, b.shape.field) and a.shape.origin == b.shape.origin
    else:
        assert vars(a.shape) == vars(b.shape)
    for t in (0.0, 0.004, 0.01, 0.05, 0.1, 0.3):
        assert a.position(t) == pytest.approx(b.position(t)) and a.velocity(t) == pytest.approx(b.velocity(t))
        ra, rb = a.rotation(t), b.rotation(t)
        assert (ra is None) == (rb is None) and (ra is None or ra == pytest.approx(rb))


def assert_same_interactions(a: list, b: list):
    assert [type(c) for c in a] == [type(c) for c in b]
    for ca, cb in zip(a, b):
        tools_a = getattr(ca, "tools", None) or [ca.tool] if not isinstance(ca, StrainLimit) else []
        tools_b = getattr(cb, "tools", None) or [cb.tool] if not isinstance(cb, StrainLimit) else []
        assert len(tools_a) == len(tools_b)
        for ta, tb in zip(tools_a, tools_b):
            assert_same_tool(ta, tb)
        skip = {"tools", "tool", "_held", "held"}
        assert {k: v for k, v in vars(ca).items() if k not in skip} == {
            k: v for k, v in vars(cb).items() if k not in skip
        }


# ------------------------------------------------------------------ parsing
def test_every_tool_key_builds_the_same_objects(tmp_path):
    from torchdeform.interact.meshes import MeshShape

    trimesh.creation.icosphere(subdivisions=2, radius=0.003).export(tmp_path / "ball.stl")
    text = (
        BODY
        + """
    [[tools]]
    name = "probe"
    shape = "sphere"
    radius = 0.004
    position = [0.03, 0.01, 0.01]
    orientation = [0.0, 0.0, 0.5]
    friction = 0.4
    direction = "motion"
    hold = true
    haptic_gain = 20.0

    [[tools]]
    shape = "capsule"
    radius = 0.002
    half_length = 0.01
    axis = "h"
    contact = "penalty"
    stiffness = 50.0
    damping = 0.1
    path = [[0.0, [0.03, 0.0, 0.0], [0.0, 0.0, 0.0]], [0.1, [0.02, 0.0, 0.01], [0.0, 0.0, 1.0]]]

    [[tools]]
    shape = "box"
    half_extents = [0.003, 0.004, 0.005]
    contact = "none"
    grasp = {close = 0.01, open = 0.2, margin = 0.001}
    path = [[0.0, [0.015, 0.005, 0.02]], [0.05, [0.025, 0.005, 0.02]]]

    [[tools]]
    shape = "half_space"
    normal = [0.0, 0.0, 2.0]
    position = [0.0, 0.0, -0.001]
    contact = "projection"

    [[tools]]
    shape = "mesh"
    file = "ball.stl"
    resolution = 16
    position = [0.02, 0.0075, 0.01]

    [strain_limit]
    min = 0.75
    max = 1.5
    passes = 3
    update_velocity = false
    """
        + RUN
    )
    scene = load_scene(write(tmp_path, text))
    probe = Tool(Sphere(0.004), position=(0.03, 0.01, 0.01), orientation=(0.0, 0.0, 0.5), name="probe")
    shaft = Tool(
        Capsule(0.002, 0.01, axis=1),
        path=[(0.0, (0.03, 0.0, 0.0), (0.0, 0.0, 0.0)), (0.1, (0.02, 0.0, 0.01), (0.0, 0.0, 1.0))],
        name="tool2",
    )
    jaws = Tool(
        Box((0.003, 0.004, 0.005)), path=[(0.0, (0.015, 0.005, 0.02)), (0.05, (0.025, 0.005, 0.02))], name="tool3"
    )
    wall = Tool(HalfSpace(normal=(0.0, 0.0, 1.0)), position=(0.0, 0.0, -0.001), name="tool4")
    ball = Tool(MeshShape(tmp_path / "ball.stl", resolution=16), position=(0.02, 0.0075, 0.01), name="tool5")
    expected = [
        StrainLimit(min_ratio=0.75, max_ratio=1.5, passes=3, update_velocity=False),
        ProjectionContact(probe, friction=0.4, direction="motion", hold=True, haptic_gain=20.0),
        PenaltyContact(shaft, stiffness=50.0, damping=0.1),
        ProjectionContact(wall),
        ProjectionContact(ball),
        Grasp(jaws, close=0.01, open=0.2, margin=0.001),
    ]
    assert scene.tools.names == ["probe", "tool2", "tool3", "tool4", "tool5"]
    assert_same_interactions(scene.model_args["interactions"], expected)
    assert_same_interactions(scene.build().interactions, expected)
    assert_same_interactions(scene.tools.interactions(), expected)
    assert scene.tools.interactions()[1] is not scene.tools.interactions()[1]  # fresh for every run


def test_grasp_open_never_and_strain_limit_defaults(tmp_path):
    text = GOOD.replace("open = 0.015", "open = inf").replace("min = 0.8\nmax = 1.2\npasses = 1\n", "")
    scene = load_scene(write(tmp_path, text))
    strain, _, grasp = scene.model_args["interactions"]
    assert grasp.open == math.inf and grasp.closed_at(1e6)
    assert (strain.min_ratio, strain.max_ratio, strain.passes, strain.update_velocity) == (0.9, 1.1, 4, True)


def test_tissue_words_and_regions_are_the_fuzzy_librarys(tmp_path):
    """Tissue words in the regions of a body of springs: k = E / lattice_modulus (an elastic body: test_elastic_scene)."""
    region = """
    [[regions]]
    sphere = {center = [0.01, 0.005, 0.01], radius = 0.006}
    tissue = "firm"
    """
    grid = load_scene(write(tmp_path, BODY + RUN, "grid.toml")).grid
    per_k = lattice_modulus(grid)
    assert per_k == pytest.approx(2.7 / 0.005)
    base = f"stiffness = {tissue_parameters('liver')['youngs_modulus'] / per_k!r}"  # liver's springs
    text = BODY.replace("stiffness = 5.0", base) + region + RUN
    scene = load_scene(write(tmp_path, text))
    # independently: the fuzzy library's coupling (per-node consistency -> per-spring E, harmonic means)
    fis = load_preset("tissue_si")
    inputs = node_inputs(
        grid,
        fis,
        {"consistency": tissue_parameters("liver")["consistency"]},
        regions=[(Ellipsoid((0.01, 0.005, 0.01), (0.006,) * 3), {"consistency": fis.inputs[0].terms["firm"].peak()})],
    )
    E = spring_parameters(fis, grid, inputs, dtype=torch.float64)["youngs_modulus"]
    assert torch.allclose(scene.model_args["stiffness"], E / per_k, rtol=1e-6, atol=0)
    liver = tissue_parameters("liver")["youngs_modulus"]
    assert float(scene.model_args["stiffness"][0, 0, 0, 0]) == pytest.approx(liver / per_k, rel=1e-6)
    assert tissue_moduli([2.5])[0] == pytest.approx(liver, rel=1e-6)  # liver's consistency
    assert float(E.max()) > 5 * liver  # "firm" is stiffer

    # a later region with its own stiffness wins on its nodes: springs inside it get exactly that
    box = "\n[[regions]]\nbox = {lo = [0.0, 0.0, 0.015], hi = [0.015, 0.015, 0.02]}\nstiffness = 30.0\n"
    boxed = BODY.replace("stiffness = 5.0", base) + region + box + RUN
    k = load_scene(write(tmp_path, boxed, "box.toml")).model_args["stiffness"]
    inside = grid.box_mask((0.0, 0.0, 0.015), (0.015, 0.015, 0.02))
    along_w = grid.directions.index((0, 0, 1))  # springs from w = 15 mm to w = 20 mm
    assert torch.allclose(k[along_w][inside & (torch.arange(5) == 3)], torch.tensor(30.0, dtype=torch.float64))
    untouched = k == scene.model_args["stiffness"]
    assert bool(untouched[:, :, :, :2].all())  # far from the box: unchanged


@pytest.mark.parametrize("topology, factor", [(6, 1.0), (18, 2.5), (26, 2.7)])
def test_lattice_modulus_known_values(topology, factor):
    assert lattice_modulus(td.Grid((2, 2, 2), spacing=0.002, topology=topology)) == pytest.approx(factor / 0.002)


# ------------------------------------------------------------------ bad files
def _edit(old, new, text=GOOD):
    assert old in text
    return text.replace(old, new, 1)


SPHERE = """
[[tools]]
shape = "sphere"
radius = 0.004
position = [0.03, 0.01, 0.01]
"""
MESH = """
[[tools]]
shape = "mesh"
file = "open.stl"
position = [0.03, 0.01, 0.01]
"""

BAD = {
    # id: (scene text, key in the message, expected text, text of the line it points to)
    "negative radius": (
        _edit("radius = 0.004", "radius = -0.004"),
        "tools[0].radius",
        "a positive number of metres",
        "radius =",
    ),
    "unknown shape": (
        _edit('shape = "sphere"', 'shape = "cone"'),
        "tools[0].shape",
        '"sphere", "capsule", "box", "half_space", "mesh"',
        "cone",
    ),
    "path times not increasing": (
        _edit("[0.02, [0.0170", "[0.0, [0.0170"),
        "tools[0].path",
        "strictly increasing",
        "path = [[0.0, [0.0195",
    ),
    "bad path": (
        _edit("[0.02, [0.0170, 0.005, 0.005]]", "[0.02, [0.0170, 0.005]]"),
        "tools[0].path",
        "waypoints [[t, [d, h, w]], ...]",
        "path = [[0.0, [0.0195",
    ),
    "grasp close without open": (
        _edit("grasp = {close = 0.005, open = 0.015}", "grasp = {close = 0.005}"),
        "tools[1].grasp",
        "both a close and an open time",
        "grasp =",
    ),
    "grasp opens before it closes": (
        _edit("open = 0.015", "open = 0.001"),
        "tools[1].grasp.open",
        "a time after close",
        "grasp =",
    ),
    "grasp unknown key": (
        _edit("open = 0.015", "open = 0.015, force = 1.0"),
        "tools[1].grasp.force",
        "one of the keys close, open, margin",
        "grasp =",
    ),
    "duplicate name": (
        _edit('name = "forceps"', 'name = "probe"'),
        "tools[1].name",
        "a name no other tool has",
        'name = "probe"\nshape = "box"',
    ),
    "key of another shape": (
        _edit("radius = 0.004", "radius = 0.004\nhalf_extents = [0.001, 0.001, 0.001]"),
        "tools[0].half_extents",
        'no half_extents for shape = "sphere"',
        "half_extents = [0.001",
    ),
    "penalty without stiffness": (
        _edit("friction = 0.3\nhaptic_gain = 10.0", 'contact = "penalty"'),
        "tools[0].stiffness",
        "(required)",
        "[[tools]]",
    ),
    "option of another contact": (
        _edit("friction = 0.3", 'contact = "penalty"\nstiffness = 10.0\nfriction = 0.3'),
        "tools[0].friction",
        'an option of contact = "projection"',
        "friction =",
    ),
    "contact none without grasp": (
        _edit("friction = 0.3\nhaptic_gain = 10.0", 'contact = "none"'),
        "tools[0].contact",
        "does nothing without a grasp",
        'contact = "none"',
    ),
    "position and path": (
        _edit("radius = 0.004", "radius = 0.004\nposition = [0.0, 0.0, 0.0]"),
        "tools[0].path",
        "exactly one of position or path",
        "path = [[0.0, [0.0195",
    ),
    "orientation with a path": (
        _edit("radius = 0.004", "radius = 0.004\norientation = [0.0, 0.0, 1.0]"),
        "tools[0].orientation",
        "rotations go into its waypoints",
        "orientation =",
    ),
    "capsule axis": (
        BODY + SPHERE.replace('"sphere"', '"capsule"') + "half_length = 0.01\naxis = 3\n" + RUN,
        "tools[0].axis",
        '"d", "h" or "w"',
        "axis =",
    ),
    "bad name": (_edit('name = "probe"', 'name = "my probe"'), "tools[0].name", "a tool name", "my probe"),
    "strain limit min": (_edit("min = 0.8", "min = 1.5"), "strain_limit.min", "a ratio in (0, 1]", "min ="),
    "strain limit passes": (_edit("passes = 1", "passes = 0"), "strain_limit.passes", "an integer >= 1", "passes ="),
    "strain limit unknown key": (
        _edit("passes = 1", "passes = 1\nratio = 2"),
        "strain_limit.ratio",
        "one of the keys min, max, passes, update_velocity",
        "ratio =",
    ),
    "palpation without such tool": (
        _edit("record_every = 20", 'record_every = 20\npalpation = "forceps"'),
        "output.palpation",
        "a [[tools]] tool with a contact (probe)",
        "palpation =",
    ),
    "unknown tissue": (
        _edit("stiffness = 5.0", 'tissue = "bone"'),
        "material.tissue",
        "a tissue of the fuzzy library",
        "tissue =",
    ),
    "region outside the body": (
        GOOD + "\n[[regions]]\nsphere = {center = [1.0, 1.0, 1.0], radius = 0.001}\nstiffness = 3.0\n",
        "regions[0].sphere",
        "at least one node",
        "sphere =",
    ),
    "region tissue number out of range": (
        GOOD + "\n[[regions]]\nbox = {lo = [0, 0, 0], hi = [0.01, 0.01, 0.01]}\ntissue = 11.0\n",
        "regions[0].tissue",
        "a consistency value in [0, 10]",
        "tissue = 11.0",
    ),
    "regions with a class table": (
        _edit("stiffness = 5.0", "stiffness = {axis = 5.0, face = 5.0, body = 5.0}")
        + "\n[[regions]]\nbox = {lo = [0, 0, 0], hi = [0.01, 0.01, 0.01]}\n"
        "stiffness = 3.0\n",
        "material",
        "stiffness = a number or tissue",
        "[material]",
    ),
    "mesh not closed": (BODY + MESH + RUN, "tools[0].file", "closed (watertight)", "file ="),
    "mesh not found": (
        BODY + MESH.replace("open.stl", "none.stl") + RUN,
        "tools[0].file",
        "an existing mesh file",
        "file =",
    ),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_tools_are_one_line_exit_2(case, bad_dir, capsys):
    text, key, expected, needle = BAD[case]
    path = bad_dir / "bad.toml"
    path.write_text(text)
    rc = cli.main(argv=["run", str(path), "--out", str(bad_dir / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.endswith("\n") and err.count("\n") == 1, err
    line = text[: text.index(needle)].count("\n") + 1  # where the needle (maybe two lines) starts
    assert err.startswith(f"torchdeform: {path}:{line}: {key}: expected "), err
    assert expected in err, err
    assert not (bad_dir / "out" / "summary.json").exists()


def test_bad_mesh_tool_through_the_entry_point(bad_dir):
    path = write(bad_dir, BODY + MESH + RUN, "bad.toml")
    proc = subprocess.run(
        [sys.executable, "-m", "torchdeform", "run", str(path), "--out", str(bad_dir / "o")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    line = line_containing(BODY + MESH + RUN, "file =")
    assert proc.stderr.startswith(f"torchdeform: {path}:{line}: tools[0].file: expected a closed (watertight)")


# ------------------------------------------------------------------ running
def direct_model():
    """The model of GOOD, built with the Python API alone."""
    grid = td.Grid((4, 4, 5), spacing=0.005, topology=26)
    probe = Tool(Sphere(0.004), path=[(0.0, (0.0195, 0.005, 0.005)), (0.02, (0.017, 0.005, 0.005))], name="probe")
    forceps = Tool(
        Box((0.003, 0.003, 0.003)),
        name="forceps",
        path=[(0.0, (0.015, 0.005, 0.02)), (0.005, (0.015, 0.005, 0.02)), (0.015, (0.02, 0.005, 0.02))],
    )
    interactions = [
        StrainLimit(min_ratio=0.8, max_ratio=1.2, passes=1),
        ProjectionContact(probe, friction=0.3, haptic_gain=10.0),
        Grasp(forceps, close=0.005, open=0.015),
    ]
    return td.Model(
        grid,
        stiffness=5.0,
        damping=1e-3,
        density=1000.0,
        fixed=grid.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        interactions=interactions,
    ), (probe, forceps)


def test_run_writes_the_readings_of_the_same_model_in_python(tmp_path):
    scene = load_scene(write(tmp_path, GOOD))
    out = tmp_path / "out"
    summary = run_scene(scene, out, progress=False)
    summary_again = run_scene(scene, tmp_path / "again", progress=False)  # fresh grasp: the same run

    model, tools = direct_model()
    readings, frames = [], []

    def keep(i, state):
        readings.append({k: v[0].clone() for k, v in state.readings.items()})
        if i % 20 == 0:
            frames.append((state.t, support_reaction(model, state)[0]))

    td.simulate(model, model.rest_state(), 2e-4, 100, integrator=td.SymplecticEuler(), callback=keep)
    zero = torch.zeros(3)
    data = np.load(out / "tools.npz")
    t = np.array([2e-4 * (i + 1) for i in range(100)])
    assert np.allclose(data["t"], t, rtol=1e-12, atol=0)
    for tool in tools:
        force = torch.stack([r.get(f"{tool.name}.force", zero) for r in readings]).double().numpy()
        assert np.array_equal(data[f"{tool.name}.force"], force)  # bit for bit
        entry = summary["tools"][tool.name]
        assert entry["points"] == 100 and entry["steps_per_point"] == 1
        assert np.allclose(entry["force_N"], force, rtol=1e-5, atol=1e-12)  # 6 digits in the JSON
        assert np.allclose(entry["position_m"], [tool.position(float(s)) for s in t], rtol=1e-5)
        assert entry["max_force_N"] == pytest.approx(np.linalg.norm(force, axis=1).max(), rel=1e-6)
        assert summary_again["tools"][tool.name]["force_N"] == entry["force_N"]
    contacts = np.array([float(r["probe.contacts"]) for r in readings])
    grasped = np.array([float(r["forceps.grasped"]) for r in readings])
    assert np.array_equal(data["probe.contacts"], contacts) and contacts.max() >= 1
    assert np.array_equal(data["forceps.grasped"], grasped) and grasped.max() == 1 and grasped[-1] == 0
    assert summary["tools"]["probe"]["max_force_N"] > 0 and summary["tools"]["forceps"]["max_force_N"] > 0
    # supports' reaction at the recorded frames (0, 20, ..., 100)
    reaction = summary["support_reaction_N"]
    assert reaction["t_s"][1:] == pytest.approx([f[0] for f in frames])
    assert np.allclose(reaction["force_N"][1:], torch.stack([f[1] for f in frames]).numpy(), rtol=1e-5, atol=1e-9)
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary)) and "palpation" not in summary
    png = (out / "forces.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_long_series_are_block_means(tmp_path):
    probe = Tool(Sphere(0.004), path=[(0.0, (0.0, 0.0, 0.0)), (1.0, (-0.002, 0.0, 0.0))], name="probe")
    tools = ToolSet(tools=[probe], contacts=[("projection", {})], grasps=[None])
    T = 2500
    t = np.arange(1, T + 1) * 4e-4
    force = np.random.default_rng(0).normal(size=(T, 3))
    series = {"t": t, "probe.force": force, "probe.contacts": np.ones(T)}
    result = tool_outputs(tools, series, (t[::500], force[::500]), tmp_path)
    entry = result["tools"]["probe"]
    assert entry["steps_per_point"] == 3 and entry["points"] == 834 <= 1000
    padded = np.concatenate([force, np.full((2, 3), np.nan)]).reshape(-1, 3, 3)  # 833 full blocks + 1 step
    means = np.concatenate([padded[:-1].mean(1), force[-1:]])
    assert np.allclose(entry["force_N"], means, rtol=1e-5, atol=1e-12)
    assert entry["t_s"][0] == pytest.approx(t[:3].mean()) and entry["t_s"][-1] == pytest.approx(t[-1])
    assert np.allclose(entry["position_m"], [probe.position(float(s)) for s in entry["t_s"]], rtol=1e-5, atol=1e-12)
    assert entry["max_force_N"] == pytest.approx(np.linalg.norm(means, axis=1).max(), rel=1e-9)
    assert entry["work_direction"] == pytest.approx([-1.0, 0.0, 0.0]) and entry["moving"]  # it moves down
    data = np.load(tmp_path / "tools.npz")
    assert np.array_equal(data["probe.force"], force) and data["probe.position"].shape == (T, 3)
    assert len(result["support_reaction_N"]["t_s"]) == 5 and (tmp_path / "forces.png").exists()


def test_scene_without_tools_writes_no_tool_outputs(tmp_path):
    scene = load_scene(write(tmp_path, BODY + RUN))
    summary = run_scene(scene, tmp_path / "out", progress=False)
    assert scene.tools is None and "tools" not in summary and "support_reaction_N" not in summary
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["energy.png", "summary.json", "trajectory.npz"]


def test_threads_are_set_for_the_run_and_restored(tmp_path):
    before = torch.get_num_threads()
    scene = load_scene(write(tmp_path, _edit("steps = 100", "steps = 5\nthreads = 1")))
    assert scene.threads == 1
    summary = run_scene(scene, tmp_path / "out", progress=False)
    assert summary["threads"] == 1 and torch.get_num_threads() == before


# ------------------------------------------------------------------ palpation
def _presses(points, top=0.0075, radius=0.004, depth=0.0015, h=0.005, press=0.02):
    """Waypoints of presses at the W positions ``points``: 0.5 mm above the surface, ``depth`` in, up, over."""
    above, below = top + radius + 0.0005, top + radius - depth
    rows, t = [], 0.0
    for w in points:
        rows += [
            [round(t, 6), [above, h, w]],
            [round(t + press, 6), [below, h, w]],
            [round(t + 1.5 * press, 6), [above, h, w]],
        ]
        t += 2 * press
    return rows


def test_tiny_palpation_finds_the_lump(tmp_path):
    path = _presses([0.005, 0.0125, 0.02])
    text = f"""
    [grid]
    shape = [4, 5, 11]
    spacing = 0.0025

    [material]
    tissue = "fat"

    [[regions]]
    sphere = {{center = [0.005, 0.005, 0.0125], radius = 0.003}}
    tissue = "firm"

    [mass]
    density = 1000.0

    [boundary]
    fixed = "bottom"
    decay = 100.0

    [[tools]]
    name = "finger"
    shape = "sphere"
    radius = 0.004
    path = {json.dumps(path)}

    [integrator]
    dt = "auto"
    steps = 650
    threads = 1

    [output]
    palpation = true
    """
    scene = load_scene(write(tmp_path, text))
    assert scene.tools.palpation == "finger"
    summary = run_scene(scene, tmp_path / "out", progress=False)
    assert summary["simulated_time_s"] > path[-1][0]
    result = summary["palpation"]
    assert result["tool"] == "finger" and len(result["points"]) == 3
    peaks = [p["peak_force_N"] for p in result["points"]]
    assert result["stiffest"]["index"] == 1 and peaks[1] > 1.2 * max(peaks[0], peaks[2])
    assert result["stiffest"]["along_m"] == pytest.approx(0.0075, abs=1e-6)
    assert [p["along_m"] for p in result["points"]] == pytest.approx([0.0, 0.0075, 0.015], abs=1e-6)
    for p in result["points"]:
        assert p["indentation_m"] == pytest.approx(0.0015, rel=0.05)  # over a node: from contact
        assert p["stiffness_N_per_m"] > 0 and len(p["curve"]["force_N"]) <= 100
    png = (tmp_path / "out" / "palpation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
