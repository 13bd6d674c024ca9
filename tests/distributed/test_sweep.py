"""``torchdeform sweep``: the table against runs of edited scene files, over 1, 2 and 3 ranks
(torchrun, gloo on 127.0.0.1), a killed sweep resumed, and bad input."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import torchdeform as td
from torchdeform import cli
from torchdeform.bench.distributed import SWEEP_SCENE
from torchdeform.distributed.sweep import parse_set, product, read_points

SCENE = SWEEP_SCENE.replace("steps = {steps}", 'steps = {steps}\nengine = "eager"')  # the bench's cube; one engine
# for the table and the single runs (the engines round float32 differently, about 5e-6 apart)
SETS = ["material.stiffness=25,50,100", "integrator.dt=1e-4,2e-4"]


def scene_file(tmp_path, steps=60):
    path = tmp_path / "cube.toml"
    path.write_text(SCENE.format(steps=steps))
    return path


def table(out):
    with open(out / "sweep.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def same_rows(a, b):
    """Row for row, everything but the wall time."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert {k: v for k, v in x.items() if k != "wall_s"} == {k: v for k, v in y.items() if k != "wall_s"}


def sweep_cli(*argv):
    return cli.main(argv=["sweep", *map(str, argv), "--quiet"])


def torchrun(n, *argv, timeout=120):
    """``torchrun --standalone --nproc-per-node n -m torchdeform sweep ...`` (a free port on this machine), bounded in time."""
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        str(n),
        "-m",
        "torchdeform",
        "sweep",
        *map(str, argv),
        "--quiet",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)


def test_parse_and_product():
    assert parse_set('integrator.name="rk4",symplectic') == ("integrator.name", ["rk4", "symplectic"])
    assert parse_set("a.b=1, 2.0 ,true") == ("a.b", [1, 2.0, True])
    pts = product([("a.x", [1, 2]), ("b.y", [3, 4, 5])])
    assert len(pts) == 6 and pts[0] == {"a.x": 1, "b.y": 3} and pts[-1] == {"a.x": 2, "b.y": 5}
    for bad in ("stiffness", "=1,2", "a.b="):
        with pytest.raises(td.ConfigError, match="--set"):
            parse_set(bad)


def test_table_equals_runs_of_edited_scene_files(tmp_path):
    """Each row's figures equal ``run_scene`` of the scene file with the point's values written in."""
    path = scene_file(tmp_path)
    assert sweep_cli(path, "--set", SETS[0], "--set", SETS[1], "--out", tmp_path / "out") == 0
    rows = table(tmp_path / "out")
    assert [(float(r["material.stiffness"]), float(r["integrator.dt"])) for r in rows] == [
        (k, dt) for k in (25, 50, 100) for dt in (1e-4, 2e-4)
    ]
    for r in rows:
        text = (
            SCENE.format(steps=60)
            .replace("stiffness = 50.0", f"stiffness = {r['material.stiffness']}")
            .replace("dt = 1e-4", f"dt = {r['integrator.dt']}")
        )
        edited = tmp_path / f"p{r['point']}.toml"
        edited.write_text(text)
        summary = td.run_scene(td.load_scene(edited), tmp_path / f"run{r['point']}", progress=False)
        assert r["status"] == "ok" and int(r["steps"]) == 60
        np.testing.assert_allclose(float(r["max_displacement_m"]), summary["max_displacement_m"], rtol=1e-6)
        np.testing.assert_allclose(float(r["peak_displacement_m"]), summary["peak_displacement_m"], rtol=1e-6)
        np.testing.assert_allclose(float(r["kinetic_J"]), summary["final_energy_J"]["kinetic"], rtol=1e-5)
    assert (tmp_path / "out" / "sweep.png").stat().st_size > 0
    # a list file of points gives the same rows
    (tmp_path / "points.csv").write_text(
        "material.stiffness,integrator.dt\n"
        + "".join(f"{r['material.stiffness']},{r['integrator.dt']}\n" for r in rows)
    )
    assert read_points(tmp_path / "points.csv")[1] == {"material.stiffness": 25, "integrator.dt": 2e-4}
    assert sweep_cli(path, "--points", tmp_path / "points.csv", "--out", tmp_path / "list") == 0
    same_rows(table(tmp_path / "list"), rows)


@pytest.mark.parametrize("ranks", [3])  # an odd count of ranks; 2 ranks run the same code
@pytest.mark.slow
def test_ranks_gather_the_single_process_table(tmp_path, ranks):
    path = scene_file(tmp_path)
    assert sweep_cli(path, "--set", SETS[0], "--set", SETS[1], "--out", tmp_path / "one") == 0
    res = torchrun(ranks, path, "--set", SETS[0], "--set", SETS[1], "--out", tmp_path / "many")
    assert res.returncode == 0, res.stderr[:4000] + " ... " + res.stderr[-1500:]
    same_rows(table(tmp_path / "many"), table(tmp_path / "one"))
    assert 1 < len(list((tmp_path / "many" / "records").glob("rank*.jsonl"))) <= ranks  # a rank per batch at most
    assert f"over {ranks} ranks" in res.stderr


def test_batched_points_equal_one_by_one(tmp_path):
    """Points that differ only in stiffness and damping run as one batched model (per time step):
    the same rows as one point at a time. A point that diverges (k = 1e6 N/m, 10x past its
    bound) sends its batch back to one by one, and only its row says so."""
    path = scene_file(tmp_path)
    (tmp_path / "points.csv").write_text(
        "material.stiffness,material.damping,integrator.dt\n"
        "25,0.02,1e-4\n50,0.05,1e-4\n25,0.05,1e-4\n25,0.02,2e-4\n1e6,0.02,2e-4\n"
    )
    assert sweep_cli(path, "--points", tmp_path / "points.csv", "--out", tmp_path / "batched") == 0
    assert sweep_cli(path, "--points", tmp_path / "points.csv", "--batch", "1", "--out", tmp_path / "single") == 0
    batched, single = table(tmp_path / "batched"), table(tmp_path / "single")
    assert [r["batch"] for r in batched] == ["3", "3", "3", "1", "1"] and {r["batch"] for r in single} == {"1"}
    for b, s in zip(batched, single):
        diverged = float(b["material.stiffness"]) == 1e6
        assert b["status"].startswith("diverged") == s["status"].startswith("diverged") == diverged
        if not diverged:
            assert b["status"] == "ok"
            for k in ("max_displacement_m", "peak_displacement_m", "kinetic_J", "total_J"):
                np.testing.assert_allclose(float(b[k]), float(s[k]), rtol=1e-6, err_msg=k)


@pytest.mark.slow
def test_a_killed_sweep_reruns_only_the_missing_points(tmp_path):
    path = scene_file(tmp_path, steps=300)
    argv = [
        sys.executable,
        "-m",
        "torchdeform",
        "sweep",
        str(path),
        "--set",
        "material.stiffness=20,30,40,50,60,70",
        "--batch",
        "1",
        "--out",
        str(tmp_path / "out"),
        "--quiet",
    ]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
    records = tmp_path / "out" / "records" / "rank0.jsonl"
    end = time.monotonic() + 60
    while time.monotonic() < end and (not records.exists() or len(records.read_text().splitlines()) < 2):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    first = len(records.read_text().splitlines())
    assert 2 <= first < 6 and not (tmp_path / "out" / "sweep.csv").exists()
    res = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[:4000] + " ... " + res.stderr[-1500:]
    assert f"{first} already done" in res.stderr
    assert len(records.read_text().splitlines()) == 6  # each point ran once in all
    assert (
        sweep_cli(path, "--set", "material.stiffness=20,30,40,50,60,70", "--batch", "1", "--out", tmp_path / "fresh")
        == 0
    )
    same_rows(table(tmp_path / "out"), table(tmp_path / "fresh"))


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--set", "material.stiffnes=1,2"], "--set: expected SECTION.KEY"),
        (["--set", "material.stiffness=1,abc"], "--set material.stiffness: expected a number"),
        (["--set", "integrator.dt=1e-4,-1"], "--set integrator.dt: expected"),
        (["--set", "loads.force=1"], "--set: expected SECTION.KEY"),
        ([], "--set KEY=V1,V2,... (repeatable) or --points"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    path = scene_file(tmp_path)
    assert sweep_cli(path, *argv, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchdeform: ") and "\n" not in err and message in err, err
    assert not (tmp_path / "out").exists()  # checked before any work


@pytest.mark.slow
def test_bad_input_on_two_ranks_stops_every_rank(tmp_path):
    """Every rank checks the points before any collective: no rank hangs; rank 0 alone prints the
    line (torchrun then reports the failed ranks itself and exits 1)."""
    path = scene_file(tmp_path)
    res = torchrun(2, path, "--set", "material.stiffnes=1,2", "--out", tmp_path / "out", timeout=60)
    assert res.returncode != 0
    assert res.stderr.count("torchdeform: --set: expected SECTION.KEY") == 1
    assert "exitcode  : 2" in res.stderr
