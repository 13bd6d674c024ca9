"""The physics set-up a new user gets wrong, caught with one clear line.

Units and axes (a body in millimetres, a tool path in millimetres, a tool that starts inside the
body, a mesh whose up axis is z), divergence messages that name the term that diverged, a run that
starts settled under gravity, and the peak and final displacement of a run.

Oracles: the geometry of the scenes (extents, which nodes lie below a height), the static solver
for the settled start (:func:`torchdeform.solve_static`, float64, its own Newton iteration), and
the drag path's own peak offset for the peak displacement.
"""

from __future__ import annotations

import json
import textwrap
import warnings

import numpy as np
import pytest
import torch
import trimesh

import torchdeform as td
from torchdeform import cli
from torchdeform.errors import ConfigWarning
from torchdeform.scene import load_scene

BODY = """
[grid]
shape = [5, 5, 5]
spacing = 0.01
[material]
stiffness = 20.0
[mass]
density = 1000.0
[boundary]
fixed = "bottom"
"""
RUN = """
[integrator]
dt = 0.0005
steps = 20
"""


def write(tmp_path, text: str, name: str = "scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def run(path, out) -> int:
    return cli.main(argv=["run", str(path), "--out", str(out), "--quiet"])


# ------------------------------------------------------------------ units and axes
def test_a_body_in_millimetres_warns_naming_the_key_and_metres(tmp_path):
    path = write(tmp_path, BODY.replace("spacing = 0.01", "spacing = 2") + RUN)
    with pytest.warns(ConfigWarning) as caught:
        load_scene(path)
    (line,) = [str(w.message) for w in caught if "metres across" in str(w.message)]
    assert f"{path}:4: grid.spacing = 2" in line and "8 metres across" in line and "\n" not in line


def test_a_body_of_tissue_size_does_not_warn(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        load_scene(write(tmp_path, BODY + RUN))


PROBE = """
[[tools]]
name = "probe"
shape = "sphere"
radius = 0.01
path = [[0.0, [0.065, 0.02, 0.02]], [0.01, [0.045, 0.02, 0.02]]]
"""


def test_a_tool_path_in_millimetres_warns_that_it_never_reaches_the_body(tmp_path):
    mm = PROBE.replace("0.065, 0.02, 0.02", "65, 20, 20").replace("0.045, 0.02, 0.02", "45, 20, 20")
    path = write(tmp_path, BODY + mm + RUN)
    with pytest.warns(ConfigWarning) as caught:
        load_scene(path)
    (line,) = [str(w.message) for w in caught if "never comes within" in str(w.message)]
    assert "tools[0].path" in line and "'probe'" in line and "metres" in line and "\n" not in line
    with warnings.catch_warnings():  # the same path in metres reaches the body
        warnings.simplefilter("error", ConfigWarning)
        load_scene(write(tmp_path, BODY + PROBE + RUN, "metres.toml"))


def test_a_tool_that_starts_inside_the_body_is_an_error_unless_asked_for(tmp_path, capsys):
    inside = PROBE.replace("0.065, 0.02, 0.02", "0.03, 0.02, 0.02")
    path = write(tmp_path, BODY + inside + RUN)
    assert run(path, tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}:" in err[0] and "tools[0].path" in err[0] and "start_inside" in err[0]
    assert not (tmp_path / "out").exists()
    ok = write(
        tmp_path, BODY + inside.replace('name = "probe"', 'name = "probe"\nstart_inside = true') + RUN, "ok.toml"
    )
    assert load_scene(ok).tools.start_inside == [True]


def _tall_mesh(folder) -> str:
    trimesh.creation.box((0.008, 0.012, 0.03)).export(folder / "tall.stl")  # tall along mesh z
    return "tall.stl"


def test_a_mesh_up_axis_maps_onto_axis_d_and_a_base_patch_fixes_only_the_base(tmp_path):
    name = _tall_mesh(tmp_path)
    mesh_body = BODY.replace("shape = [5, 5, 5]\nspacing = 0.01", f'mesh = "{name}"\nspacing = 0.002')
    plain = load_scene(write(tmp_path, mesh_body + RUN, "plain.toml"))
    up = load_scene(write(tmp_path, mesh_body.replace("spacing = 0.002", 'spacing = 0.002\nup = "z"') + RUN, "up.toml"))
    assert np.argmax(plain.grid.shape) == 2 and np.argmax(up.grid.shape) == 0  # z: along W, then along D (up)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.01)
    ball.export(tmp_path / "ball.stl")
    sphere_body = BODY.replace("shape = [5, 5, 5]\nspacing = 0.01", 'mesh = "ball.stl"\nspacing = 0.002')
    bottom = load_scene(write(tmp_path, sphere_body + RUN, "bottom.toml")).model_args["fixed"]
    patch_scene = load_scene(
        write(tmp_path, sphere_body.replace('fixed = "bottom"', "fixed = {below = 0.002}") + RUN, "patch.toml")
    )
    patch = patch_scene.model_args["fixed"]
    X = patch_scene.grid.rest_positions(dtype=torch.float64)[0, 0]
    nodes = patch_scene.grid.nodes()
    lowest = float(X[nodes].min())
    assert torch.equal(patch, nodes & (lowest + 0.002 + 1e-12 >= X))  # oracle: the nodes below the height
    box = f"fixed = {{box = {{lo = [-1.0, -1.0, -1.0], hi = [{lowest + 0.002!r}, 1.0, 1.0]}}}}"
    boxed = load_scene(write(tmp_path, sphere_body.replace('fixed = "bottom"', box) + RUN, "box.toml"))
    assert torch.equal(boxed.model_args["fixed"], patch)  # the same base patch as a box
    assert int(bottom.sum()) > 2 * int(patch.sum()) > 0
    assert float(X[bottom].max()) > lowest + 0.007  # "bottom" of a ball: its lower half-shell, up near the equator


def test_a_surface_up_axis_turns_the_embedded_mesh(tmp_path):
    name = _tall_mesh(tmp_path)
    box = BODY.replace(
        "shape = [5, 5, 5]\nspacing = 0.01", "shape = [9, 9, 9]\nspacing = 0.005\norigin = [-0.02, -0.02, -0.02]"
    )
    text = box + f'[[surfaces]]\nfile = "{name}"\nup = "z"\n' + RUN
    v = np.asarray(load_scene(write(tmp_path, text)).embedded["tall"][0])
    extent = v.max(0) - v.min(0)
    np.testing.assert_allclose(extent, [0.03, 0.008, 0.012], atol=1e-9)  # mesh z, x, y along D, H, W


# ------------------------------------------------------------------ divergence messages
def _diagnosis(scene) -> str:
    model = scene.build()
    monitor = td.DivergenceMonitor(model, scene.dt, scene.integrator)
    with pytest.raises(td.DivergenceError) as e:
        monitor.fail(12, "velocity", float("inf"), state=model.rest_state())
    return str(e.value)


def test_an_undamped_body_pressed_by_a_tool_names_the_tool_and_the_missing_damping(tmp_path):
    text = _diagnosis(load_scene(write(tmp_path, BODY + PROBE + RUN)))
    assert 'tool "probe"' in text and "no damping" in text and "\n" not in text
    damped = load_scene(
        write(tmp_path, BODY.replace("stiffness = 20.0", "stiffness = 20.0\ndamping = 0.05") + PROBE + RUN, "d.toml")
    )
    assert "no damping" not in _diagnosis(damped)


def test_a_run_that_diverges_under_a_stiff_tool_names_it_and_the_missing_damping(tmp_path, capsys):
    stiff = PROBE.replace("radius = 0.01\n", 'radius = 0.01\ncontact = "penalty"\nstiffness = 1e9\n')
    path = write(tmp_path, BODY + stiff + RUN.replace("steps = 20", 'steps = 40\nengine = "eager"'))
    assert run(path, tmp_path / "out") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "diverged" in line and 'tool "probe"\'s penalty stiffness 1e+09 N/m' in line and "no damping" in line


def test_a_tool_that_swallows_the_body_is_named_as_such(tmp_path):
    blob = PROBE.replace("radius = 0.01", "radius = 0.2\nstart_inside = true")
    text = _diagnosis(load_scene(write(tmp_path, BODY + blob + RUN)))
    assert 'tool "probe" swallows the body' in text


# ------------------------------------------------------------------ settle under gravity
SAG = (
    BODY.replace('fixed = "bottom"', 'fixed = "bottom"\ngravity = [-9.81, 0, 0]') + RUN + "[output]\nrecord_every = 2\n"
)


def test_settle_starts_the_run_at_rest_under_gravity(tmp_path):
    path = write(tmp_path, SAG.replace("steps = 20", "steps = 20\nsettle = true"))
    assert run(path, tmp_path / "settled") == 0
    assert run(write(tmp_path, SAG, "plain.toml"), tmp_path / "plain") == 0
    settled, plain = (np.load(tmp_path / d / "trajectory.npz") for d in ("settled", "plain"))
    summary = json.loads((tmp_path / "settled" / "summary.json").read_text())
    assert summary["settle"]["method"] == "static"
    scene = load_scene(path)
    model = td.Model(scene.grid, **scene.model_args, dtype=torch.float64)
    eq, info = td.solve_static(model, tol=1e-10)  # oracle: the static equilibrium
    assert info["converged"]
    np.testing.assert_allclose(settled["x"][0], eq.x[0].numpy(), atol=1e-6 * 0.04 + 1e-7)
    assert float(np.max(np.abs(settled["x"][0] - settled["X"]))) > 1e-4  # it did sag
    assert settled["kinetic"][:5].max() < 1e-6 * plain["kinetic"][:5].max()


# ------------------------------------------------------------------ peak and final displacement
def test_max_displacement_is_the_peak_and_the_final_one_has_its_own_name(tmp_path, capsys):
    drag = """
[[drags]]
face = "top"
path = [[0.0, [0.0, 0.0, 0.0]], [0.004, [0.003, 0.0, 0.0]], [0.008, [0.0, 0.0, 0.0]]]
"""
    lift = BODY + drag + RUN.replace("steps = 20", "steps = 24") + "[output]\nrecord_every = 2\n"
    path = write(tmp_path, lift.replace("stiffness = 20.0", "stiffness = 20.0\ndamping = 0.05"))
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out")]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["max_displacement_m"] == pytest.approx(0.003, rel=1e-3)  # oracle: the drag's peak offset
    assert summary["final_displacement_m"] < 0.5 * summary["max_displacement_m"]
    assert f"max displacement {summary['max_displacement_m'] * 1e3:.3g} mm (peak)" in line
    assert f"final displacement {summary['final_displacement_m'] * 1e3:.3g} mm" in line


def test_settle_takes_damped_steps_where_the_static_solve_cannot(tmp_path):
    free = SAG.replace('fixed = "bottom"\n', "").replace("steps = 20", "steps = 4\nsettle = 0.01")
    scene = load_scene(write(tmp_path, free))
    model = scene.build()
    state, info = td.scene.run.settle_state(scene, model, 0.0005)
    assert info["method"] == "steps" and info["time_s"] == 0.01  # a body held by nothing has no equilibrium
    assert float(state.v.abs().max()) == 0.0 and state.t == 0.0
