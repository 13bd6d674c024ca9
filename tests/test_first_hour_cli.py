"""A new user's first hour with the command line: small gaps and bad inputs that must end in one line.

Oracle: the command-line contract of :mod:`torchdeform.options` (exit status 0 with whole outputs,
or 2 with one line per problem naming file, line and key, nothing written) and the version string
of the package; every case runs ``torchdeform.cli.main`` in-process, or a clean subprocess where
the process itself matters.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.test_fuzz import CHAINMAIL as FUZZ_CHAINMAIL
from torchdeform import cli

ROOT = Path(__file__).resolve().parents[1]

CUBE = textwrap.dedent("""\
    [grid]
    shape = [3, 3, 3]
    spacing = 0.01

    [material]
    stiffness = 50.0

    [mass]
    density = 1000.0

    [boundary]
    fixed = "bottom"

    [integrator]
    name = "symplectic"
    dt = 1e-4
    steps = 10
    """)

CHAINMAIL = FUZZ_CHAINMAIL.replace("relax_steps = 1\n", 'relax_steps = 1\nrelax_moved_only = "no"\n')

FIS = textwrap.dedent("""\
    [System]
    Name='tiny'
    Type='mamdani'
    NumInputs=1
    NumOutputs=1
    NumRules=2

    [Input1]
    Name='a'
    Range=[0 1]
    NumMFs=2
    MF1='lo':'trimf',[0 0 1]
    MF2='hi':'trimf',[0 1 1]

    [Output1]
    Name='y'
    Range=[0 1]
    NumMFs=2
    MF1='lo':'trimf',[0 0 1]
    MF2='hi':'trimf',[0 1 1]

    [Rules]
    1, 1 (1) : 1
    2, 2 (1) : 1
    """)


def call(argv, capsys) -> tuple[int, str, str]:
    """``torchdeform ARGV`` in-process: (exit status, stdout, stderr)."""
    try:
        status = cli.main(argv=[str(a) for a in argv])
    except SystemExit as e:  # argparse: --version, --help, usage errors
        status = e.code
    out, err = capsys.readouterr()
    return status, out, err


def one_line(status, err: str) -> str:
    assert status == 2, err
    assert "Traceback" not in err, err
    lines = [x for x in err.splitlines() if x.strip() and ": warning: " not in x]
    assert len(lines) == 1, err
    return lines[0]


def scene(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------ A1 --version
def test_version_prints_the_package_version_in_a_clean_process():
    done = subprocess.run(
        [sys.executable, "-m", "torchdeform", "--version"], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"torchdeform {td.__version__}"


class _Exited(Exception):
    pass


@pytest.mark.parametrize(("argv", "status"), [(["--version"], 0), (["--help"], 0), (["run"], 2)])
def test_argparse_exits_take_the_quick_exit_with_their_status(argv, status, monkeypatch, capsys):
    """--version, --help and usage errors leave through os._exit (no teardown of torch) with argparse's status."""
    import torchdeform.cli as cli

    def fake_exit(code):
        raise _Exited(code)

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    monkeypatch.setattr(cli.atexit, "_run_exitfuncs", lambda: None)  # this process's own exit functions stay
    monkeypatch.setattr(sys, "argv", ["torchdeform", *argv])
    with pytest.raises(_Exited) as exited:
        cli.entry()
    assert exited.value.args == (status,)
    out, err = capsys.readouterr()
    assert (out if status == 0 else err).strip()


# ------------------------------------------------------------------ A2 run --set
def test_run_set_overrides_dotted_keys(tmp_path, capsys):
    path, out = scene(tmp_path, CUBE), tmp_path / "out"
    status, _, err = call(
        [
            "run",
            path,
            "--out",
            out,
            "--quiet",
            "--set",
            "integrator.steps=20",
            "--set",
            "integrator.dt=5e-5",
            "--set",
            "output.name=renamed",
        ],
        capsys,
    )
    assert status == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 20 and summary["dt_s"] == pytest.approx(5e-5) and summary["name"] == "renamed"
    assert "integrator.steps" not in path.read_text().replace("steps = 10", "")  # the file is left as it was


@pytest.mark.parametrize(
    "setting, key",
    [
        ("integrator.stepz=2", "--set"),  # no such key
        ("nosection.dt=1", "--set"),  # no such section
        ("integrator.dt=-1", "--set integrator.dt"),  # a bad value
        ("integrator.steps=many", "--set integrator.steps"),
        ("integrator.dt", "--set"),  # no value
    ],
)
def test_run_set_refuses_a_bad_key_or_value_in_one_line(tmp_path, capsys, setting, key):
    out = tmp_path / "out"
    status, _, err = call(["run", scene(tmp_path, CUBE), "--out", out, "--set", setting], capsys)
    line = one_line(status, err)
    assert line.startswith(f"torchdeform: {key}:"), line
    assert setting.split("=")[0] in line
    assert not out.exists()


def test_run_set_shares_the_sweep_parser():
    from torchdeform.distributed import sweep
    from torchdeform.scene import commands, reader

    assert sweep.parse_set is reader.parse_set and sweep.check_key is commands.check_key


def test_run_set_to_knoche_needs_its_material(tmp_path, capsys):
    text = CUBE.replace(
        "[grid]\nshape = [3, 3, 3]\nspacing = 0.01", "[grid]\nshape = [3, 3, 3]\nspacing = 0.01\ntopology = 6"
    )
    status, _, err = call(
        ["run", scene(tmp_path, text), "--out", tmp_path / "o", "--set", "integrator.name=knoche"], capsys
    )
    assert "integrator.material" in one_line(status, err)


# ------------------------------------------------------------------ A3 tissue names
def test_tissue_names_are_case_insensitive():
    from torchdeform.fuzzy.presets import tissue_parameters, tissue_properties

    lower, upper, soft = tissue_properties(["liver", "Liver", "SOFT"])
    assert upper == lower and soft["density"] is None
    assert tissue_parameters("LIVER") == tissue_parameters("liver")


def test_an_unknown_tissue_lists_every_name(tmp_path, capsys):
    from torchdeform.fuzzy.presets import tissues

    text = CUBE.replace("stiffness = 50.0", 'tissue = "Livr"').replace("[mass]\ndensity = 1000.0\n", "")
    status, _, err = call(["run", scene(tmp_path, text), "--out", tmp_path / "o"], capsys)
    line = one_line(status, err)
    assert "material.tissue" in line and ":6:" in line
    assert all(name in line for name in tissues()), line
    assert all(term in line for term in ("very_soft", "soft", "medium", "firm", "hard"))


def test_a_capitalised_tissue_runs(tmp_path, capsys):
    text = CUBE.replace("stiffness = 50.0", 'tissue = "Liver"').replace("[mass]\ndensity = 1000.0\n", "")
    status, _, err = call(["run", scene(tmp_path, text), "--out", tmp_path / "o", "--quiet"], capsys)
    assert status == 0, err


# ------------------------------------------------------------------ A4 all the problems of one file
def test_scene_problems_are_reported_together(tmp_path, capsys):
    text = (
        CUBE.replace("shape = [3, 3, 3]", "shap = [3, 3, 3]")
        .replace("[material]", "[materal]")
        .replace("fixed = ", "fixd = ")
    )
    path = scene(tmp_path, text)
    status, _, err = call(["run", path, "--out", tmp_path / "o"], capsys)
    assert status == 2 and "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 4, err
    assert all(x.startswith(f"torchdeform: {path}:") for x in lines)
    keys = [x.split(": ")[2] for x in lines]
    assert keys == ["grid.shap", "materal", "boundary.fixd", "material"], lines
    assert lines[0].startswith(f"torchdeform: {path}:2:") and lines[1].startswith(f"torchdeform: {path}:5:")


def test_one_scene_problem_is_still_one_line(tmp_path, capsys):
    status, _, err = call(["run", scene(tmp_path, CUBE + "colour = 1\n"), "--out", tmp_path / "o"], capsys)
    assert "integrator.colour" in one_line(status, err)


# ------------------------------------------------------------------ A5 fuzzy eval
def test_fuzzy_eval_warns_for_an_input_out_of_range(tmp_path, capsys):
    path = tmp_path / "t.fis"
    path.write_text(FIS)
    status, out, err = call(["fuzzy", "eval", path, "a=5"], capsys)
    assert status == 0
    assert out.splitlines()[0] == "a,y"
    (line,) = err.splitlines()
    assert ": warning: input a: 5 outside its range [0, 1]" in line
    status, _, err = call(["fuzzy", "eval", path, "a=0.5"], capsys)
    assert status == 0 and err == ""


@pytest.mark.parametrize(
    "edit, where",
    [
        (("Name='y'", "Name='a'"), ":16: [Output1] Name"),  # a variable's name twice
        (("MF2='hi':'trimf',[0 1 1]\n\n[Output1]", "MF2='lo':'trimf',[0 1 1]\n\n[Output1]"), ":13: [Input1] MF2"),
    ],
)
def test_fuzzy_refuses_duplicate_names(tmp_path, capsys, edit, where):
    path = tmp_path / "t.fis"
    path.write_text(FIS.replace(*edit, 1))
    status, _, err = call(["fuzzy", "eval", path, "a=0.5"], capsys)
    assert where in one_line(status, err)


# ------------------------------------------------------------------ A6 help
@pytest.mark.parametrize("command", ["run", "demo", "view", "sweep"])
def test_help_has_an_example_and_points_to_the_scene_reference(capsys, command):
    status, out, _ = call([command, "--help"], capsys)
    assert status == 0
    assert "example:\n  torchdeform " + command in out and "docs/scenes.md" in out


# ------------------------------------------------------------------ B1 huge counts in a .fis
@pytest.mark.parametrize("command", ["eval", "show"])
@pytest.mark.parametrize("count", ["NumInputs=1000000000", "NumOutputs=1000000000", "NumMFs=1000000000000"])
def test_fis_with_a_huge_count_is_refused_in_one_line(tmp_path, capsys, command, count):
    key = count.split("=")[0]
    path = tmp_path / "t.fis"
    path.write_text(FIS.replace(f"{key}=1" if key != "NumMFs" else "NumMFs=2", count, 1))
    status, _, err = call(["fuzzy", command, path] + (["a=0.5"] if command == "eval" else []), capsys)
    assert key in one_line(status, err)


# ------------------------------------------------------------------ B2 data cube sizes
def test_data_cube_with_a_huge_n_is_refused_before_allocating(tmp_path, capsys):
    out = tmp_path / "c.npz"
    status, _, err = call(["data", "cube", "--n", 10**5, "--out", out], capsys)
    assert "--n" in one_line(status, err) and "fits in memory" in err
    assert not out.exists()


def test_data_cube_300_cubed_under_a_memory_limit(tmp_path, capsys, monkeypatch):
    import torchdeform.checks

    monkeypatch.setattr(torchdeform.checks, "available_memory", lambda device=None: 2 * 2**30)  # 2 GiB
    out = tmp_path / "c.npz"
    status, _, err = call(["data", "cube", "--n", 300, "--steps", 10, "--out", out], capsys)
    line = one_line(status, err)
    assert "--n" in line and "300 x 300 x 300" in line and "2 GiB" in line
    assert not out.exists()


# ------------------------------------------------------------------ B3 knoche without its material
def test_knoche_scene_without_material_is_one_line(tmp_path, capsys):
    text = CUBE.replace("spacing = 0.01", "spacing = 0.01\ntopology = 6").replace('"symplectic"', '"knoche"')
    path = scene(tmp_path, text)
    status, _, err = call(["run", path, "--out", tmp_path / "o"], capsys)
    line = one_line(status, err)
    assert line.startswith(f"torchdeform: {path}:") and "integrator.material" in line
    status, _, err = call(
        ["run", scene(tmp_path, text + "material = 0.5\n"), "--out", tmp_path / "o", "--quiet"], capsys
    )
    assert status == 0, err


# ------------------------------------------------------------------ B4 fit_cube on a series without truth
def test_fit_cube_on_a_series_without_truth_is_one_line(tmp_path, capsys):
    data = tmp_path / "c.npz"
    assert call(["data", "cube", "--n", 3, "--steps", 20, "--out", data], capsys)[0] == 0
    arrays = dict(np.load(data, allow_pickle=False))
    meta = json.loads(str(arrays["meta"]))
    del meta["truth"]
    arrays["meta"] = np.array(json.dumps(meta))
    for k in ("true_stiffness", "true_damping", "true_mass"):
        arrays.pop(k)
    bare = tmp_path / "bare.npz"
    np.savez(bare, **arrays)
    done = subprocess.run(
        [sys.executable, str(ROOT / "training" / "fit_cube.py"), "--data", str(bare), "--out", str(tmp_path / "fit")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    line = one_line(done.returncode, done.stderr)
    assert line.startswith("fit_cube.py: --data:") and "true_stiffness" in line and "truth" in line
    assert not (tmp_path / "fit" / "result.json").exists()


# ------------------------------------------------------------------ B5 a diverged series is no data
def test_data_cube_with_a_large_dt_stops_with_the_divergence_line(tmp_path, capsys):
    out = tmp_path / "c.npz"
    status, _, err = call(["data", "cube", "--n", 4, "--dt", 0.2, "--steps", 10, "--out", out], capsys)
    line = one_line(status, err)
    assert "diverged at step" in line and "safe time step" in line
    assert not out.exists() and not list(tmp_path.iterdir())


# ------------------------------------------------------------------ B6 simulate from a non-finite state
@pytest.mark.parametrize("steps", [0, 3])
def test_simulate_refuses_a_non_finite_start_state(steps):
    model = td.Model(td.Grid((3, 3, 3), spacing=0.01), stiffness=10.0, mass=1e-3)
    rest = model.rest_state()
    x = rest.x.clone()
    x[0, 0, 1, 1, 1] = float("nan")
    with pytest.raises(td.ConfigError, match=r"state\.x: expected a finite start state"):
        td.simulate(model, td.State(x, rest.v), 1e-4, steps=steps)
    v = rest.v.clone()
    v[0, 1, 2, 2, 2] = float("inf")
    with pytest.raises(td.ConfigError, match=r"state\.v"):
        td.simulate(model, td.State(rest.x, v), 1e-4, steps=steps)
    state, _ = td.simulate(model, rest, 1e-4, steps=0)
    assert bool(torch.isfinite(state.x).all())


# ------------------------------------------------------------------ B7 strings where booleans are expected
@pytest.mark.parametrize("value", ['"no"', '"false"', "0", "1"])
def test_chainmail_boolean_refuses_a_string_or_number(tmp_path, capsys, value):
    path = scene(tmp_path, CHAINMAIL.replace('"no"', value))
    status, _, err = call(["run", path, "--out", tmp_path / "o"], capsys)
    line = one_line(status, err)
    assert line.startswith(f"torchdeform: {path}:10: chainmail.relax_moved_only: expected true or false"), line


@pytest.mark.parametrize("value", ["true", "false"])
def test_chainmail_boolean_takes_a_boolean(tmp_path, capsys, value):
    path = scene(tmp_path, CHAINMAIL.replace('"no"', value))
    status, _, err = call(["run", path, "--out", tmp_path / "o", "--quiet"], capsys)
    assert status == 0, err


@pytest.mark.parametrize(
    "section, key, extra",
    [
        ("strain_limit", "update_velocity", ""),
        ("tear", "one_per_step", "max_strain = 0.5\n"),
        ("output", "animation", ""),
    ],
)
def test_every_boolean_scene_key_refuses_a_string(tmp_path, capsys, section, key, extra):
    text = CUBE + f'\n[{section}]\n{extra}{key} = "no"\n'
    status, _, err = call(["run", scene(tmp_path, text), "--out", tmp_path / "o"], capsys)
    assert f"{section}.{key}: expected true or false" in one_line(status, err)


def test_a_garbled_rule_line_is_refused_at_once(tmp_path, capsys):
    import time

    path = tmp_path / "t.fis"
    path.write_text(FIS.replace("2, 2 (1) : 1", "1" * 40 + " " + "2" * 40 + " x (1) : 1"))
    start = time.perf_counter()
    status, _, err = call(["fuzzy", "show", path], capsys)
    assert "[Rules]" in one_line(status, err)
    assert time.perf_counter() - start < 2.0  # a backtracking pattern took minutes on such lines
