"""Scene files: loading, the demo, the runner's outputs, and bad files at the CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from torchdeform import ConfigError, cli
from torchdeform.scene import Scene, cube_scene, load_scene, run_scene

SCENES = Path(__file__).resolve().parents[2] / "scenes"

TINY = """
[grid]
shape = [3, 3, 4]
spacing = 0.01
topology = 18

[material]
stiffness = {axis = 40.0, face = 20.0}
damping = 0.01

[mass]
density = 1000.0

[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]

[[loads]]
node = [2, 1, 3]
force = [0.0, 0.01, 0.0]
ramp = 0.01

[integrator]
name = "symplectic"
dt = "auto"
steps = 10

[output]
record_every = 3
name = "tiny"
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


# -------------------------------------------------------------- equivalence helpers
def assert_same_model(a: td.Model, b: td.Model):
    for name in ("X", "stiffness", "damping", "mass", "inv_mass", "constrained", "gravity", "k_home"):
        ta, tb = getattr(a, name), getattr(b, name)
        assert (ta is None) == (tb is None), name
        if ta is not None:
            assert torch.equal(ta, tb), name
    assert a.projected == b.projected and a.decay == b.decay and a.dtype == b.dtype
    assert len(a.loads) == len(b.loads)
    for (la, da), (lb, db) in zip(a.loads, b.loads):
        assert torch.equal(da, db) and [la.factor(t) for t in (0, 0.01, 1)] == [lb.factor(t) for t in (0, 0.01, 1)]
    assert len(a.drags) == len(b.drags)
    for da, db in zip(a.drags, b.drags):
        assert torch.equal(torch.as_tensor(da.nodes), torch.as_tensor(db.nodes))
        for t in (0.0, 0.01, 0.05, 0.2):
            assert da.offset(t) == pytest.approx(db.offset(t)) and da.velocity(t) == pytest.approx(db.velocity(t))


def assert_same_scene(a: Scene, b: Scene):
    assert a.grid.shape == b.grid.shape and a.grid.spacing == b.grid.spacing
    assert a.grid.topology == b.grid.topology and a.grid.origin == b.grid.origin
    assert torch.equal(a.grid.nodes(), b.grid.nodes())
    assert_same_model(a.build(), b.build())
    assert type(a.integrator) is type(b.integrator) and vars(a.integrator) == vars(b.integrator)
    assert (a.dt, a.steps, a.frames_every, a.name, a.dtype, a.safety) == (
        b.dt,
        b.steps,
        b.frames_every,
        b.name,
        b.dtype,
        b.safety,
    )
    volume = [{k: v for k, v in (s.volume or {}).items() if k != "base"} for s in (a, b)]
    assert volume[0] == volume[1]
    assert bool(a.animation) == bool(b.animation)


# ------------------------------------------------------------------ loading
def test_cube_file_equals_cube_scene():
    assert_same_scene(load_scene(SCENES / "cube.toml"), cube_scene())


def test_demo_file_is_the_one_the_package_ships():
    from importlib.resources import files

    assert (SCENES / "demo.toml").read_text() == (files("torchdeform.scene") / "demo.toml").read_text()


def test_cube_dt_is_below_its_bound():
    scene = cube_scene()
    assert scene.dt < td.time_step_bound(scene.build(), integrator=scene.integrator)


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.toml")), ids=lambda p: p.name)
def test_shipped_scenes_load_and_start(path, tmp_path):
    scene = load_scene(path)
    scene.steps = 4
    scene.record_every = 2
    scene.image_size = 128  # a start: small animation panels
    if scene.texture:  # a start: 8 x fewer texture voxels to synthesise and blend, as 4 steps are fewer steps
        scene.texture = dict(scene.texture, voxel=2 * scene.texture["voxel"])
    summary = run_scene(scene, tmp_path, progress=False)
    steps = 0 if "static" in summary else 4  # a static scene solves once (liver_static.toml)
    assert summary["steps"] == steps and math.isfinite(summary["final_energy_J"]["total"])


def test_python_api_builds_the_same_scene(tmp_path):
    grid = td.Grid((3, 3, 4), spacing=0.01, topology=18)
    args = dict(
        stiffness={"axis": 40.0, "face": 20.0},
        normalize=False,
        damping=0.01,
        damping_mode="projected",
        density=1000.0,
        fixed=grid.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        loads=[td.PointForce((2, 1, 3), (0.0, 0.01, 0.0), start=0.0, ramp=0.01)],
    )
    api = Scene(grid, args, integrator=td.SymplecticEuler(), dt="auto", steps=10, record_every=3, name="tiny")
    assert_same_scene(load_scene(write(tmp_path, TINY)), api)


def test_every_section_and_option(tmp_path):
    text = """
    [grid]
    shape = [4, 3, 3]
    spacing = [0.01, 0.012, 0.011]
    topology = 26
    origin = [0.1, 0.0, -0.2]

    [material]
    spring_modulus = {axis = 1.0, face = 0.5, body = 0.25}
    damping = 0.001
    damping_mode = "unprojected"

    [mass]
    mass = 0.002

    [boundary]
    fixed = ["d-", "w+"]
    fixed_nodes = [[3, 0, 0]]
    home = 0.5
    anchors = {stiffness = 2.0, every = 3}
    decay = 1.5
    gravity = [0.0, -9.81, 0.0]

    [[loads]]
    face = "top"
    traction = [1.0, 0.0, 0.0]
    start = 0.01

    [[drags]]
    box = {lo = [0.13, 0.0, -0.2], hi = [0.13, 0.024, -0.2]}
    path = [[0.0, [0.0, 0.0, 0.0]], [0.1, [0.001, 0.0, 0.0]]]

    [[drags]]
    face = "h+"
    path = [[0.0, [0.0, 0.0, 0.0]]]

    [integrator]
    name = "implicit"
    dt = 0.001
    steps = 3
    cg_iters = 50
    cg_tol = 1e-8
    newton_iters = 1
    dtype = "float64"
    device = "cpu"
    """
    scene = load_scene(write(tmp_path, text))
    grid = scene.grid
    model = scene.build()
    expected = td.Model(
        grid,
        stiffness={"axis": 1.0, "face": 0.5, "body": 0.25},
        normalize=True,
        damping=0.001,
        damping_mode="unprojected",
        mass=0.002,
        fixed=grid.face("d-") | grid.face("w+") | grid.index_mask([(3, 0, 0)]),
        home=0.5,
        anchors=(2.0, 3),
        decay=1.5,
        gravity=(0, -9.81, 0),
        loads=[td.SurfaceForce("top", (1.0, 0, 0), start=0.01)],
        drags=[
            td.Drag(grid.box_mask((0.13, 0, -0.2), (0.13, 0.024, -0.2)), path=[(0.0, (0, 0, 0)), (0.1, (0.001, 0, 0))]),
            td.Drag(grid.face("h+"), path=[(0.0, (0, 0, 0))]),
        ],
        dtype=torch.float64,
    )
    assert_same_model(model, expected)
    assert int(model.drags[0].nodes.sum()) == 3  # a line of 3 nodes along H
    assert isinstance(scene.integrator, td.ImplicitEuler)
    assert (scene.integrator.cg_iters, scene.integrator.cg_tol, scene.integrator.newton_iters) == (50, 1e-8, 1)
    assert scene.name == "scene" and scene.frames_every == 1


def test_mesh_scene(tmp_path):
    trimesh.creation.icosphere(subdivisions=2, radius=5.0).export(tmp_path / "ball.stl")  # millimetres
    text = """
    [grid]
    mesh = "ball.stl"
    scale = 0.001
    spacing = 0.001
    topology = 6
    [material]
    stiffness = 10.0
    [mass]
    density = 1000.0
    [integrator]
    name = "knoche"
    material = 0.5
    dt = 1.0
    steps = 2
    """
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "ball.stl").write_bytes((tmp_path / "ball.stl").read_bytes())
    scene = load_scene(write(sub, text))  # mesh path relative to the scene
    assert scene.grid.shape == (11, 11, 11) and scene.grid.node_mask is not None
    assert 0 < scene.grid.num_nodes < 11**3
    assert isinstance(scene.integrator, td.KnocheRelaxation) and scene.integrator.material == 0.5


# ------------------------------------------------------------------ running
def test_run_scene_outputs(tmp_path):
    scene = load_scene(write(tmp_path, TINY))
    out = tmp_path / "out"
    summary = run_scene(scene, out, progress=False)
    model = scene.build()

    data = np.load(out / "trajectory.npz")
    T = 5  # steps 0, 3, 6, 9 and the final 10
    assert data["x"].shape == data["v"].shape == (T, 3, 3, 3, 4)
    assert data["x"].dtype == np.float32 and data["t"].shape == (T,)
    bound = td.time_step_bound(model, integrator="symplectic")
    dt = 0.9 * bound
    assert np.allclose(data["t"], np.array([0, 3, 6, 9, 10]) * dt)
    assert np.array_equal(data["X"], model.X[0].numpy())
    assert tuple(data["shape"]) == (3, 3, 4) and int(data["topology"]) == 18
    assert float(data["dt"]) == pytest.approx(dt) and str(data["integrator"]) == "symplectic"
    assert np.array_equal(data["x"][0], data["X"])  # starts at rest

    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    assert summary["steps"] == 10 and summary["dt_auto"] is True and summary["frames"] == T
    assert summary["dt_s"] == pytest.approx(dt) and summary["time_step_bound_s"] == pytest.approx(bound)
    assert summary["integrator"]["name"] == "symplectic" and "power" in summary["stability_bound_method"]
    assert summary["nodes"] == 36 and summary["springs"] == model.grid.num_springs
    final = td.State(torch.from_numpy(data["x"][-1:]), torch.from_numpy(data["v"][-1:]))
    energy = model.energy(final)
    for k in ("kinetic", "elastic", "gravity", "total"):
        assert summary["final_energy_J"][k] == pytest.approx(float(energy[k]), rel=1e-5, abs=1e-15)
        assert data[k][-1] == pytest.approx(float(energy[k]), rel=1e-5, abs=1e-15)
    disp = np.linalg.norm(data["x"] - data["X"], axis=1).reshape(T, -1).max(1)
    assert summary["final_displacement_m"] == pytest.approx(disp[-1], rel=1e-5)
    assert summary["max_displacement_m"] == summary["peak_displacement_m"] == pytest.approx(disp.max(), rel=1e-5)
    free_disp = np.linalg.norm(data["x"] - data["X"], axis=1)[:, 1:].reshape(T, -1).max(1)  # base fixed
    assert summary["final_free_displacement_m"] == pytest.approx(free_disp[-1], rel=1e-5)
    assert summary["max_free_displacement_m"] == pytest.approx(free_disp.max(), rel=1e-5)
    assert np.allclose(data["max_free_displacement"], free_disp, rtol=1e-5)
    assert 0 < summary["max_displacement_m"] < 0.01 and summary["wall_time_s"] > 0

    png = (out / "energy.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_implicit_summary_has_no_bound(tmp_path):
    text = TINY.replace('name = "symplectic"', 'name = "implicit"').replace('dt = "auto"', "dt = 0.01")
    summary = run_scene(load_scene(write(tmp_path, text)), tmp_path / "out", progress=False)
    assert summary["time_step_bound_s"] is None and "unconditionally" in summary["stability_bound_method"]


def test_divergence_propagates(tmp_path):
    text = TINY.replace('dt = "auto"', "dt = 0.05").replace("steps = 10", "steps = 400")
    with pytest.warns(td.StabilityWarning), pytest.raises(td.DivergenceError):
        run_scene(load_scene(write(tmp_path, text)), tmp_path / "out", progress=False)


# ------------------------------------------------------------------ the CLI
def test_cli_run_prints_summary(tmp_path, capsys):
    path = write(tmp_path, TINY)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "tiny: 10 symplectic steps" in captured.out and captured.err == ""
    assert (tmp_path / "out" / "summary.json").exists()


def test_cli_warning_and_divergence_are_single_lines(tmp_path, capsys):
    text = TINY.replace('dt = "auto"', "dt = 0.05").replace("steps = 10", "steps = 400")
    path = write(tmp_path, text)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("torchdeform: warning: dt = 0.05 s exceeds the stability bound")
    assert lines[1].startswith("torchdeform: simulation diverged at step") and "safe time step" in lines[1]


GOOD = TINY


def _edit(old, new):
    assert old in GOOD
    return GOOD.replace(old, new, 1)


BAD = {
    # id: (scene text, key in the message, expected text, text of the line it points to or None)
    "unknown key": (_edit("damping = 0.01", "dampin = 0.01"), "material.dampin", "one of the keys", "dampin"),
    "unknown section": (GOOD + "\n[gird]\nshape = 1\n", "gird", "one of the sections", "[gird]"),
    "wrong type": (_edit("steps = 10", 'steps = "10"'), "integrator.steps", "an integer >= 0", "steps ="),
    "wrong type in table": (
        _edit("face = 20.0}", 'face = "soft"}'),
        "material.stiffness",
        "a number >= 0",
        "stiffness =",
    ),
    "missing section": (_edit("[mass]\ndensity = 1000.0", ""), "mass", "a [mass] section (required)", None),
    "incompressible": (
        _edit("stiffness = {axis = 40.0, face = 20.0}", "youngs_modulus = 5000.0\npoisson_ratio = 0.5"),
        "material.poisson_ratio",
        "a Poisson ratio in [0.25, 0.5)",
        "poisson_ratio",
    ),
    "poisson without modulus": (
        _edit("damping = 0.01", "poisson_ratio = 0.45"),
        "material.poisson_ratio",
        "no poisson_ratio together with material.youngs_modulus",
        "poisson_ratio",
    ),
    "young's modulus not a number": (
        _edit("stiffness = {axis = 40.0, face = 20.0}", 'youngs_modulus = "5 kPa"\npoisson_ratio = 0.45'),
        "material.youngs_modulus",
        "Young's modulus E in Pa",
        "youngs_modulus",
    ),
    "material on a 6-neighbour grid": (
        _edit("stiffness = {axis = 40.0, face = 20.0}", "youngs_modulus = 5000.0\npoisson_ratio = 0.45").replace(
            "topology = 18", "topology = 6"
        ),
        "material",
        "14, 18 or 26",
        "youngs_modulus",
    ),
    "missing key": (_edit("steps = 10", ""), "integrator.steps", "(required)", "[integrator]"),
    "zero dt": (_edit('dt = "auto"', "dt = 0"), "integrator.dt", 'a positive number of seconds or "auto"', "dt ="),
    "negative dt": (_edit('dt = "auto"', "dt = -1e-4"), "integrator.dt", "a positive number", "dt ="),
    "negative steps": (_edit("steps = 10", "steps = -5"), "integrator.steps", "an integer >= 0", "steps ="),
    "zero-size grid": (_edit("shape = [3, 3, 4]", "shape = [0, 3, 4]"), "grid.shape", "each >= 1", "shape ="),
    "shape and mesh": (
        _edit("spacing = 0.01", 'spacing = 0.01\nmesh = "a.stl"'),
        "grid.mesh",
        "exactly one of",
        "mesh =",
    ),
    "mesh not found": (
        _edit("shape = [3, 3, 4]", 'mesh = "organ.stl"'),
        "grid.mesh",
        "an existing mesh file",
        "mesh =",
    ),
    "mesh not closed": (_edit("shape = [3, 3, 4]", 'mesh = "open.stl"'), "grid.mesh", "closed (watertight)", "mesh ="),
    "toml syntax": (_edit("steps = 10", "steps = = 10"), "toml", "valid TOML syntax", "steps ="),
    "bad face": (_edit('fixed = "bottom"', 'fixed = ["bottom", "side"]'), "boundary.fixed", '"w+"', "fixed ="),
    "node outside grid": (_edit("node = [2, 1, 3]", "node = [2, 1, 4]"), "loads[0].node", "inside the grid", "node ="),
    "bad integrator": (_edit('name = "symplectic"', 'name = "leapfrog"'), "integrator.name", '"rk4"', "leapfrog"),
    "option of another integrator": (
        _edit("steps = 10", "steps = 10\ncg_iters = 5"),
        "integrator.cg_iters",
        "options of symplectic: none",
        "cg_iters",
    ),
    "auto dt for implicit": (
        _edit('name = "symplectic"', 'name = "implicit"'),
        "integrator.dt",
        '"auto" needs an explicit integrator',
        "dt =",
    ),
    "bad dtype": (_edit("steps = 10", 'steps = 10\ndtype = "float16"'), "integrator.dtype", '"float64"', "dtype"),
    "negative stiffness": (_edit("axis = 40.0", "axis = -40.0"), "material.stiffness", "a number >= 0", "stiffness ="),
    "both mass and density": (
        _edit("density = 1000.0", "density = 1000.0\nmass = 1.0"),
        "mass.density",
        "exactly one of mass or density",
        "density =",
    ),
    "drag path backwards": (
        GOOD + "\n[[drags]]\nnodes = [[2, 1, 1]]\npath = [[0.1, [0, 0, 0]], [0.0, [0, 0, 0]]]\n",
        "drags[0].path",
        "strictly increasing",
        "path =",
    ),
    "record_every zero": (
        _edit("record_every = 3", "record_every = 0"),
        "output.record_every",
        "an integer >= 1",
        "record_every",
    ),
}


def line_containing(text, needle):
    """1-based number of the first line of ``text`` containing ``needle``."""
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_scene_is_one_line_exit_2(case, bad_dir, capsys):
    text, key, expected, needle = BAD[case]
    line = needle and line_containing(text, needle)
    path = bad_dir / "bad.toml"
    path.write_text(text)
    rc = cli.main(argv=["run", str(path), "--out", str(bad_dir / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.endswith("\n") and err.count("\n") == 1, err
    where = f"{path}:{line}: " if line else f"{path}: "
    assert err.startswith(f"torchdeform: {where}"), err
    assert key in err and "expected" in err and expected in err, err
    assert not (bad_dir / "out" / "summary.json").exists()


def test_youngs_modulus_and_poisson_ratio_make_an_elastic_body(tmp_path):
    text = TINY.replace("stiffness = {axis = 40.0, face = 20.0}", "youngs_modulus = 5000.0\npoisson_ratio = 0.45")
    model = load_scene(write(tmp_path, text)).build()
    assert model.volume is not None
    ref = td.Model(model.grid, td.Elastic(5000.0, 0.45), density=1000.0, dtype=model.dtype)
    assert torch.equal(model.stiffness, ref.stiffness) and torch.equal(model.volume[0], ref.volume[0])


def test_old_modulus_key_and_implausible_springs_warn_in_one_line(tmp_path):
    old = TINY.replace("stiffness = {axis = 40.0, face = 20.0}", "modulus = 0.4")
    with pytest.warns(td.ConfigWarning, match="now called material.spring_modulus"):
        a = load_scene(write(tmp_path, old)).build()
    new = old.replace("modulus = 0.4", "spring_modulus = 0.4")
    b = load_scene(write(tmp_path, new, "new.toml")).build()
    assert torch.equal(a.stiffness, b.stiffness)
    # E = 5 kPa written as a spring modulus: springs ~1e5 N/m, a lattice of ~1e8 Pa
    path = write(tmp_path, TINY.replace("stiffness = {axis = 40.0, face = 20.0}", "spring_modulus = 5000.0"), "e.toml")
    with pytest.warns(td.ConfigWarning, match=r"e\.toml:\d+: material\.spring_modulus = 5000 makes a lattice") as w:
        load_scene(path)
    assert "\n" not in str(w[0].message) and "youngs_modulus" in str(w[0].message)


def test_missing_scene_file(tmp_path, capsys):
    assert cli.main(argv=["run", str(tmp_path / "none.toml"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none.toml" in err and "an existing scene file" in err


def test_load_scene_raises_config_error(tmp_path):
    with pytest.raises(ConfigError) as info:
        load_scene(write(tmp_path, _edit('dt = "auto"', "dt = 0")))
    assert (
        info.value.key == "integrator.dt"
        and info.value.line == line_containing(TINY, "dt =")
        and info.value.file.endswith("scene.toml")
    )


def test_bad_scene_subprocess_has_no_traceback(tmp_path):
    path = write(tmp_path, _edit("steps = 10", "steps = 1.5"), "bad.toml")
    proc = subprocess.run(
        [sys.executable, "-m", "torchdeform", "run", str(path), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    line = line_containing(TINY, "steps =")
    assert proc.stderr.startswith(f"torchdeform: {path}:{line}: integrator.steps: expected an integer >= 0")


@pytest.mark.parametrize("device", ["foo", "cuda:99", "meta", "xpu"])
def test_cli_bad_device_is_one_line(device, tmp_path, capsys):
    """A --device that torch names but cannot use (meta, xpu) is refused as --device, not as a scene line."""
    path = write(tmp_path, TINY)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--device", device, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("torchdeform: --device: expected") and str(path) not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("device", ["foo", "meta", "xpu"])
def test_scene_device_that_cannot_compute_names_its_line(device, tmp_path, capsys):
    path = write(tmp_path, TINY.replace("[integrator]\n", f'[integrator]\ndevice = "{device}"\n'))
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    line = line_containing(path.read_text(), "device =")
    assert err.count("\n") == 1 and err.startswith(f"torchdeform: {path}:{line}: integrator.device: expected")
