"""The contract of every command: exit 0 with whole, finite outputs, or exit 2 with one line and
nothing lost (``torchdeform.options``, ``torchdeform.outputs``, ``torchdeform.checks``).

One regression test per example of bad or extreme input that once ended in a traceback, a silent
NaN, a lost file or a misleading message. The oracle is the contract itself: the exit status, the
number of lines on stderr, the absence of a traceback, the files on disk before and after.
"""

from __future__ import annotations

import json
import math
import resource
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.fuzzy.fis import read_fis
from torchdeform.outputs import STAGING

ROOT = Path(__file__).resolve().parents[1]

TINY = """
[grid]
shape = [3, 3, 3]
spacing = 0.01

[material]
stiffness = 50.0
damping = 0.1

[mass]
density = 1000.0

[boundary]
fixed = ["bottom"]
gravity = [-9.81, 0.0, 0.0]

[integrator]
name = "symplectic"
dt = 1e-4
steps = 20
"""


def scene(tmp_path, text=TINY, name="scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def one_line(capsys, start="torchdeform: ") -> str:
    """stderr of the last in-process command: exactly one line, no traceback."""
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and err.startswith(start), err
    return err


def run_cli(*argv, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "torchdeform", *map(str, argv)], capture_output=True, text=True, timeout=120, **kw
    )


def listing(folder: Path) -> list:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


# ------------------------------------------------------------------ tracebacks that are now one line
def test_knoche_scene_without_material(tmp_path, capsys):
    path = scene(
        tmp_path,
        TINY.replace("[material]\nstiffness = 50.0\ndamping = 0.1\n", "").replace(
            'name = "symplectic"', 'name = "knoche"'
        ),
    )
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err  # both problems of the file, one line each
    assert err.count("\n") == 2 and "material: expected a [material] section" in err
    assert "integrator.material: expected the knoche integrator's material" in err


@pytest.mark.parametrize(
    "argv, key",
    [
        (["run", "{huge}", "--out", "{out}"], "grid.shape"),
        (["render", "phantom:100000", "--out", "{out}.png"], "volume"),
        (["render", "phantom:16", "--out", "{out}.png", "--view", "orbit", "--size", "16384"], "size"),
    ],
)
def test_sizes_beyond_memory_are_refused_with_the_key_and_the_bytes(tmp_path, capsys, argv, key):
    huge = scene(tmp_path, TINY.replace("shape = [3, 3, 3]", "shape = [100000, 100000, 100000]"))
    argv = [a.format(huge=huge, out=tmp_path / "out") for a in argv]
    if "--size" in argv:  # 16384 is within --size's range: lower the ceiling the check compares with
        from torchdeform import checks

        avail = checks.available_memory
        checks.available_memory = lambda device=None: 2**30
        try:
            assert cli.main(argv=argv) == 2
        finally:
            checks.available_memory = avail
    else:
        assert cli.main(argv=argv) == 2
    err = one_line(capsys)
    assert key in err and "fits in memory" in err and "B" in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.png").exists()


def test_fuzzy_resolution_beyond_memory(tmp_path, capsys):
    text = (ROOT / "fuzzy" / "susilap_g.fis").read_text().replace("[System]\n", "[System]\nResolution=100000000000\n")
    path = tmp_path / "big.fis"
    path.write_text(text)
    assert cli.main(argv=["fuzzy", "eval", str(path), "consistency=5"]) == 2
    err = one_line(capsys)
    assert "Resolution" in err and f"{path}:" in err and "TiB" in err


def test_fis_path_that_is_a_folder(tmp_path, capsys):
    assert cli.main(argv=["fuzzy", "show", str(tmp_path)]) == 2
    assert "not a folder" in one_line(capsys)


@pytest.mark.parametrize("where", ["fuzzy", "sweep"])
def test_non_utf8_csv_names_the_line(tmp_path, capsys, where):
    csv = tmp_path / "bad.csv"
    csv.write_bytes(b"consistency\n5\n\xff\xfe\n" if where == "fuzzy" else b"material.stiffness\n10\n\xff\n")
    if where == "fuzzy":
        argv = ["fuzzy", "eval", str(ROOT / "fuzzy" / "susilap_g.fis"), "--inputs", str(csv)]
    else:
        argv = ["sweep", str(scene(tmp_path)), "--points", str(csv), "--out", str(tmp_path / "sw")]
    assert cli.main(argv=argv) == 2
    assert f"{csv}:3:" in one_line(capsys) and "UTF-8" in capsys.readouterr().err + "UTF-8"


def test_output_paths_that_are_files_missing_folders_or_unwritable(tmp_path, capsys):
    path = scene(tmp_path)
    assert cli.main(argv=["run", str(path), "--out", str(path), "--quiet"]) == 2  # a file
    assert "this path is a file" in one_line(capsys)
    assert (
        cli.main(argv=["data", "cube", "--out", str(tmp_path / "no" / "such" / "x.npz"), "--n", "3", "--steps", "5"])
        == 0
    )  # folders are made
    assert (
        cli.main(argv=["warp", "phantom:16", str(tmp_path / "x.npy"), "--out", str(tmp_path / "missing" / "w.npy")])
        == 2
    )
    one_line(capsys)
    assert cli.main(argv=["run", str(path), "--out", "/proc/torchdeform-test/out", "--quiet"]) == 2  # cannot be made
    assert "--out" in one_line(capsys)


@pytest.mark.parametrize(
    "argv, option",
    [
        (["data", "cube", "--out", "x.npz", "--dt", "nan"], "--dt"),
        (["data", "cube", "--out", "x.npz", "--dt", "0"], "--dt"),
        (["data", "balloon", "--out", "x.npz", "--dt", "-1"], "--dt"),
        (["bench", "speed", "--quick", "--threads", "0"], "--threads"),
        (["render", "phantom:16", "--out", "x.png", "--size", "0"], "--size"),
        (["sweep", "s.toml", "--set", "material.stiffness=1", "--out", "o", "--batch", "0"], "--batch"),
    ],
)
def test_cli_numbers_are_checked_while_parsing(capsys, argv, option):
    with pytest.raises(SystemExit) as e:
        cli.main(argv=argv)
    assert e.value.code == 2
    err = one_line(capsys, "torchdeform ")
    assert f"argument {option}" in err and "--help" in err


def test_fit_cube_on_the_shipped_layered_series_is_one_line(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "training" / "fit_cube.py"),
            "--data",
            str(ROOT / "data" / "cube4_sine_layers.npz"),
            "--runs",
            "3",
            "--out",
            str(tmp_path),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [x for x in proc.stderr.splitlines() if not x.startswith("run ")]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr
    assert lines[0].startswith("fit_cube.py: --runs:") and "per-region" in lines[0]


@pytest.mark.parametrize("argv", [["--runs", "x"], ["--threads", "0"], ["--offset", "3"], ["--noise", "nan"]])
def test_training_scripts_exit_2_on_bad_options(tmp_path, argv):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "training" / "fit_cube.py"), "--out", str(tmp_path), *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_a_closed_stdout_is_quiet(tmp_path):
    """``torchdeform fuzzy show susilap_g | head -5``: the reader goes away before the writer is done."""
    csv = tmp_path / "many.csv"
    csv.write_text("consistency\n" + "\n".join(f"{v:.4f}" for v in np.linspace(0, 12, 20000)) + "\n")
    for argv in (
        ["fuzzy", "show", "susilap_g"],
        ["fuzzy", "eval", str(ROOT / "fuzzy" / "susilap_g.fis"), "--inputs", str(csv)],
    ):
        shell = " ".join([sys.executable, "-m", "torchdeform", *argv]) + " | head -5"
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", shell], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.count("\n") == 5 and proc.stderr == ""


# ------------------------------------------------------------------ silent NaN or wrong results
def test_fuzzy_ranges_beyond_float32_are_refused(tmp_path, capsys):
    text = (ROOT / "fuzzy" / "susilap_g.fis").read_text()
    path = tmp_path / "wide.fis"
    path.write_text(text.replace("Range=[0 12]", "Range=[0 1e40]", 1))
    assert "Range=[0 1e40]" in path.read_text()
    assert cli.main(argv=["fuzzy", "eval", str(path), "consistency=5"]) == 2
    err = one_line(capsys)
    assert "Range" in err and "1e30" in err


def test_output_term_narrower_than_a_cell_warns(tmp_path, capsys):
    path = tmp_path / "narrow.fis"
    path.write_text(
        textwrap.dedent("""\
        [System]
        Name='narrow'
        NumInputs=1
        NumOutputs=1
        NumRules=2
        [Input1]
        Name='x'
        Range=[0 10]
        NumMFs=2
        MF1='lo':'trimf',[0 0 10]
        MF2='hi':'trimf',[0 10 10]
        [Output1]
        Name='y'
        Range=[0 10]
        NumMFs=2
        MF1='lo':'trimf',[0 0 10]
        MF2='hi':'trimf',[5.001 5.002 5.003]
        [Rules]
        1, 1 (1) : 1
        2, 2 (1) : 1
        """)
    )
    assert cli.main(argv=["fuzzy", "eval", str(path), "x=10"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("torchdeform: warning: narrow: output y's term hi is narrower")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(td.fuzzy.ResolutionWarning):
            read_fis(path)
    text = path.read_text().replace("NumRules=2\n", "NumRules=2\nResolution=100000\n")
    path.write_text(text)  # fine enough cells: no warning, and 'hi' now counts
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fis = read_fis(path)
    assert abs(float(fis.evaluate(x=10.0)["y"]) - 5.002) < 1e-3


@pytest.mark.parametrize("amplitude, code", [("nan", 2), ("1e300", 2)])
def test_data_cube_never_writes_non_finite_series(tmp_path, capsys, amplitude, code):
    out = tmp_path / "c.npz"
    argv = ["data", "cube", "--out", str(out), "--n", "3", "--load", "sine", "--amplitude", amplitude]
    if amplitude == "nan":
        with pytest.raises(SystemExit) as e:
            cli.main(argv=argv)
        assert e.value.code == code
    else:
        assert cli.main(argv=argv) == code
        assert "simulation diverged at step" in one_line(capsys)  # stopped before any file
    assert not out.exists() and listing(tmp_path) == []


def test_chainmail_drag_of_1e300_m_is_refused(tmp_path, capsys):
    path = scene(
        tmp_path,
        """
        model = "chainmail"
        [grid]
        shape = [5, 5, 5]
        spacing = 0.01
        [chainmail]
        method = "gibson"
        compression = 0.5
        stretch = 1.5
        shear = 0.2
        frames = 4
        [boundary]
        fixed = ["bottom"]
        [[drags]]
        face = "top"
        path = [[0.0, [0.0, 0.0, 0.0]], [1.0, [1e300, 0.0, 0.0]]]
        """,
    )
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = one_line(capsys)
    assert f"{path}:16: drags[0].path: expected offsets within 1000 body sizes" in err


def test_training_from_a_diverging_start_stops_with_one_line(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "training" / "fit_cube.py"),
            "--runs",
            "3",
            "--offset",
            "1e9,0.4",
            "--out",
            str(tmp_path),
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = [x for x in proc.stderr.splitlines() if not x.startswith("run ")]
    assert proc.returncode == 2 and len(lines) == 1 and "training cannot start: the loss is not finite" in lines[0]
    assert not (tmp_path / "result.json").exists()


@pytest.mark.parametrize("case", ["no stiffness", "every node fixed"])
def test_time_step_bound_without_springs_or_free_nodes_is_inf(case):
    g = td.Grid((3, 3, 3), spacing=0.01)
    kw = (
        dict(stiffness=0.0)
        if case == "no stiffness"
        else dict(stiffness=10.0, fixed=torch.ones(3, 3, 3, dtype=torch.bool))
    )
    model = td.Model(g, mass=1e-3, **kw)
    for name in ("explicit", "symplectic", "verlet", "rk4"):
        assert td.time_step_bound(model, integrator=name) == math.inf
    assert td.time_step_bound(model, method="gershgorin") == math.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        td.check_dt(model, 1.0, "symplectic")  # any dt is stable: no warning


def test_simulate_zero_steps_returns_the_start():
    g = td.Grid((3, 3, 3), spacing=0.01)
    model = td.Model(g, stiffness=10.0, mass=1e-3, fixed=g.face("bottom"), gravity=(-9.81, 0, 0))
    start = model.rest_state()
    for integrator in (td.SymplecticEuler(), td.RK4(), td.ImplicitEuler(), td.ProjectiveDynamics()):
        final, rec = td.simulate(model, start, 1e-3, 0, integrator=integrator, record_every=1)
        assert final.t == 0.0 and torch.equal(final.x, start.x) and torch.equal(final.v, start.v)
        assert rec["x"].shape[0] == 1 and torch.isfinite(rec["x"]).all()


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_drag_path_with_a_non_finite_time_is_refused(bad):
    g = td.Grid((3, 3, 3), spacing=0.01)
    with pytest.raises(td.ConfigError, match="finite waypoint times"):
        td.Drag(g.face("top"), path=[(0.0, (0.0, 0.0, 0.0)), (bad, (0.0, 0.0, 0.01))])


def test_fixed_nodes_never_move_even_with_a_start_velocity():
    g = td.Grid((3, 3, 3), spacing=0.01)
    model = td.Model(g, stiffness=10.0, damping=0.01, mass=1e-3, fixed=g.face("bottom"), dtype=torch.float64)
    rest = model.rest_state()
    start = td.State(rest.x, torch.full_like(rest.v, 0.1))
    finals = {}
    for integrator in (td.SymplecticEuler(), td.RK4(), td.ImplicitEuler(cg_tol=1e-12), td.ProjectiveDynamics()):
        final, _ = td.simulate(model, start, 1e-4, 20, integrator=integrator)
        assert float((final.x - rest.x)[0, :, 0].abs().max()) == 0.0, integrator.name
        finals[integrator.name] = final.x
    # the free nodes moved (the start velocity was kept there) and implicit Euler agrees with PD
    assert float((finals["symplectic"] - rest.x)[0, :, 1:].abs().min()) > 1e-5
    assert float((finals["implicit"] - finals["projective"]).abs().max()) < 1e-6


# ------------------------------------------------------------------ nothing lost
def _limited(limit_bytes: int):
    def set_limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return set_limit


def test_a_write_failure_during_a_rerun_keeps_the_previous_run(tmp_path):
    path = scene(tmp_path, TINY.replace("steps = 20", "steps = 200").replace("shape = [3, 3, 3]", "shape = [6, 6, 6]"))
    out = tmp_path / "out"
    assert run_cli("run", path, "--out", out, "--quiet").returncode == 0
    before = {p: (out / p).read_bytes() for p in listing(out)}
    assert (out / "trajectory.npz").stat().st_size > 40_000
    proc = run_cli("run", path, "--out", out, "--quiet", preexec_fn=_limited(20_000))  # ulimit -f
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "File too large" in proc.stderr
    assert {p: (out / p).read_bytes() for p in listing(out)} == before  # the previous run, untouched
    np.load(out / "trajectory.npz")["x"]


@pytest.mark.parametrize("command", ["data", "warp", "render"])
def test_single_file_commands_leave_an_earlier_file_whole(tmp_path, command):
    offsets = tmp_path / "offsets.npy"
    np.save(offsets, np.zeros((3, 4, 4, 4), np.float32))
    target = tmp_path / {"data": "c.npz", "warp": "w.npy", "render": "r.png"}[command]
    argv = {
        "data": ["data", "cube", "--n", "4", "--steps", "400", "--noise", "0.01"],
        "warp": ["warp", "phantom:64", offsets],
        "render": ["render", "phantom:64", "--size", "512"],
    }[command]
    assert run_cli(*argv, "--out", target).returncode == 0
    good = target.read_bytes()
    proc = run_cli(*argv, "--out", target, preexec_fn=_limited(len(good) // 3))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert target.read_bytes() == good and not [p for p in tmp_path.iterdir() if p.name.startswith(STAGING)]


def test_volume_section_is_checked_before_the_simulation(tmp_path, capsys, monkeypatch):
    path = scene(tmp_path, TINY + '\n[volume]\nfile = "missing.npy"\n')
    import torchdeform.scene.run as run_module

    monkeypatch.setattr(run_module, "simulate", lambda *a, **k: pytest.fail("the simulation ran"))
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert f"{path}:23: volume.file" in one_line(capsys)
    assert not (tmp_path / "out").exists()


def test_a_rerun_leaves_exactly_its_own_outputs(tmp_path, capsys):
    out = tmp_path / "out"
    with_volume = scene(tmp_path, TINY + '\n[volume]\nfile = "phantom:16"\n', "a.toml")
    assert cli.main(argv=["run", str(with_volume), "--out", str(out), "--quiet"]) == 0
    first = listing(out)
    assert "volume_after.png" in first and json.loads((out / "summary.json").read_text())["outputs"] == first
    assert cli.main(argv=["run", str(scene(tmp_path, TINY, "b.toml")), "--out", str(out), "--quiet"]) == 0
    second = listing(out)
    assert second == ["energy.png", "summary.json", "trajectory.npz"]
    assert json.loads((out / "summary.json").read_text())["outputs"] == second


def test_a_folder_with_other_files_needs_force(tmp_path, capsys):
    path = scene(tmp_path)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path), "--quiet"]) == 2  # holds scene.toml
    assert "--force" in one_line(capsys) and listing(tmp_path) == ["scene.toml"]
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path), "--quiet", "--force"]) == 0
    capsys.readouterr()
    assert listing(tmp_path) == ["energy.png", "scene.toml", "summary.json", "trajectory.npz"]


# ------------------------------------------------------------------ misleading messages
def test_divergence_under_a_huge_load_does_not_blame_dt():
    g = td.Grid((3, 3, 3), spacing=0.01)
    model = td.Model(
        g, stiffness=10.0, mass=1e-3, fixed=g.face("bottom"), loads=[td.PointForce((2, 1, 1), (1e300, 0, 0))]
    )
    with pytest.raises(td.DivergenceError) as e:
        td.simulate(model, model.rest_state(), 1e-4, 100)
    assert "the time step is not the cause" in str(e.value) and "safe time step" not in str(e.value)
    assert e.value.safe_dt is None


def test_divergence_above_the_bound_still_names_a_safe_dt():
    g = td.Grid((3, 3, 3), spacing=0.01)
    model = td.Model(g, stiffness=10.0, mass=1e-3, fixed=g.face("bottom"), gravity=(-9.81, 0, 0))
    bound = td.time_step_bound(model)
    with pytest.raises(td.DivergenceError) as e:
        td.simulate(model, model.rest_state(), 3 * bound, 400, warn=False)
    assert e.value.safe_dt == pytest.approx(0.9 * bound) and "safe time step" in str(e.value)


def test_stability_warning_with_a_zero_bound_reads(capsys, tmp_path):
    path = scene(tmp_path, TINY.replace('name = "symplectic"', 'name = "explicit"').replace("damping = 0.1\n", ""))
    cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    warning = [x for x in err.splitlines() if "warning" in x]
    assert len(warning) == 1 and "unstable at every time step" in warning[0] and "dt <= 0 s" not in err


def test_warnings_are_one_line_each(tmp_path, capsys):
    path = scene(tmp_path, TINY.replace("dt = 1e-4", "dt = 3e-4"))  # above the bound: a StabilityWarning
    cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert err and all(x.startswith("torchdeform: ") for x in err.splitlines()), err
    assert sum("warning: dt = 0.0003 s exceeds the stability bound" in x for x in err.splitlines()) == 1


def test_a_rollout_that_cannot_fit_is_refused_before_training(monkeypatch):
    """The autograd graph of a loss evaluation is estimated first; checkpointing is suggested."""
    from torchdeform import checks, learn

    series = learn.radetzky_cube(springs=54, steps=40)
    learn.WindowLoss(series, window=None)  # fits in the real memory
    monkeypatch.setattr(checks, "available_memory", lambda device=None: 10_000)
    with pytest.raises(
        td.ConfigError,
        match=r"^window: expected a size that fits in memory: the autograd graph "
        r"of 40 steps .* \(set checkpoint to keep fewer\)",
    ):
        learn.WindowLoss(series, window=None)
