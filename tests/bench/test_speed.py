"""Smoke test of ``torchdeform bench speed --quick --json`` (one compiled shape, ~10-20 s).

Speed targets live in the benchmark, not here: this checks the command runs, prints exactly
one JSON document, its arithmetic, and that the compiled step equals the eager one.
"""

import argparse
import json

import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.bench import speed
from torchdeform.bench.common import copy_bandwidth
from torchdeform.sim.packed import PackedModel


@pytest.mark.slow  # a bench smoke run
def test_bench_speed_quick_json(capsys, tmp_path):
    rc = cli.main(argv=["bench", "speed", "--quick", "--json", "--threads", "2", "--out", str(tmp_path)])
    assert rc == 0
    captured = capsys.readouterr()
    assert "recompile_limit" not in captured.err  # one compilation per shape, not per step
    doc = json.loads(captured.out)  # stdout holds exactly one JSON document
    assert doc["bench"] == "speed"
    assert doc["machine"]["torch"] and doc["machine"]["device"] == "cpu"
    rows = [r for r in doc["rows"] if not r["mode"].startswith("warp")]
    warp = [r for r in doc["rows"] if r["mode"].startswith("warp")]
    assert {r["topology"] for r in rows} == {6, 26}
    assert "ratio_vs_warp" in doc and doc["ratio_vs_warp"] is None  # no 64^3 row in --quick
    assert doc["bandwidth_case"] is None  # no 256^3 row either
    copy = doc["copy_gb_per_s"]
    assert 0 < copy < 1e4
    from torchdeform.bench.warp_baseline import warp_available

    if warp_available()[0]:
        assert doc["warp"] == "measured" and len(warp) == 1
        w = warp[0]
        assert w["threads"] == 1 and w["max_abs_diff"] <= 1e-6  # Warp computes the same step
        eager = next(r for r in rows if (r["n"], r["topology"], r["mode"]) == (w["n"], w["topology"], "eager"))
        assert eager["vs_warp"] == pytest.approx(eager["msprings_per_s"] / w["msprings_per_s"])
    else:
        assert doc["warp"].startswith("skipped") and not warp
    beam = doc["beam"]
    assert [b["mode"] for b in beam] == ["eager"] and beam[0]["cg_iters"] == 20
    assert beam[0]["steps_per_s"] == pytest.approx(1e3 / beam[0]["ms_per_step"])
    keys = {
        "grid",
        "topology",
        "mode",
        "dtype",
        "threads",
        "msprings_per_s",
        "node_steps_per_s",
        "ms_per_step",
        "compile_s",
        "max_abs_diff",
    }
    for r in rows:
        assert keys <= set(r)
        assert r["dtype"] == "float32" and r["threads"] == 2
        assert r["msprings_per_s"] > 0 and r["node_steps_per_s"] > 0 and r["ms_per_step"] > 0
        grid = td.Grid((r["n"],) * 3, topology=r["topology"])
        assert r["springs"] == grid.num_springs and r["nodes"] == grid.num_nodes
        sec = r["ms_per_step"] / 1e3
        assert r["msprings_per_s"] == pytest.approx(grid.num_springs / sec / 1e6, rel=1e-9)
        assert r["node_steps_per_s"] == pytest.approx(grid.num_nodes / sec, rel=1e-9)
        assert r["bytes_per_step"] >= 4 * 3 * r["nodes"] * 4  # x and v read and written, float32
        assert r["gb_per_s"] == pytest.approx(r["bytes_per_step"] / sec / 1e9, rel=1e-9)
        assert r["of_copy"] == pytest.approx(r["gb_per_s"] / copy, rel=1e-9)
    for topology in (6, 26):
        assert any(r["mode"] == "eager" and r["topology"] == topology for r in rows)
    compiled = [r for r in rows if r["mode"] == "compiled"]
    assert len(compiled) == 1  # --quick compiles one tiny shape only
    c = compiled[0]
    assert not c["fallback"], "torch.compile fell back to eager"
    assert c["compile_s"] > 0 and c["compile_cache"] in ("built", "loaded")  # inductor's disk cache took it
    assert c["max_abs_diff"] is not None and c["max_abs_diff"] <= 1e-5
    assert (tmp_path / "speed.csv").is_file() and (tmp_path / "speed.png").is_file()


@pytest.mark.slow  # a bench smoke run
def test_bench_speed_table_eager_only(capsys):
    assert (
        cli.main(
            argv=[
                "bench",
                "speed",
                "--quick",
                "--no-compile",
                "--no-warp",
                "--no-beam",
                "--sizes",
                "4",
                "--topologies",
                "6",
                "--steps",
                "2",
                "--repeats",
                "1",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "Msprings/s" in out and "4^3" in out and "compiled" not in out
    assert "GB/s" in out and "of copy" in out and "copy bandwidth (read + write)" in out


def test_copy_bandwidth_sanity():
    gbs = copy_bandwidth("cpu", nbytes=2**22, repeats=3)  # 4 MiB: in cache, fast and plausible
    assert 0.01 < gbs < 1e4


def test_bytes_per_step_hand_count():
    """A 3^3 cube, 6 neighbours, float32, damped, no gravity, by hand."""
    model = td.Model(td.Grid((3, 3, 3), spacing=0.01, topology=6), stiffness=100.0, damping=0.05, mass=1e-3)
    # eager: x and v (3 x 27 values each) read and written; k, l0, c one value per direction, 1/m one value
    assert speed.bytes_per_step(model, "eager") == 4 * 3 * 27 * 4 == 1296
    assert speed.bytes_per_step(model, "eager", batch=2) == 2 * 1296
    pm = PackedModel(model)
    # packed: (3 + 2)^3 = 125 nodes with the halo, padded to G = 25 + 5 + 1 = 31 and 2 G - 125 = -63 = 1 mod 8
    assert pm.P == 126
    state, inside, inv_mass, mass = 4 * 3 * 126 * 4, 126 * 4, 126 * 4, 126 * 4
    assert speed.bytes_per_step(pm, "compiled") == state + inside + inv_mass == 7056
    assert speed.bytes_per_step(pm, "native") == state + inside + inv_mass + mass == 7560  # the fused kernel reads m
    # per-spring stiffness (a spring mask): S = 3 values per node, stored as (1, S, 3, 3, 3)
    mask = torch.ones(3, 3, 3, 3, dtype=torch.bool)
    mask[0, 0, 0, 0] = False
    cut = td.Model(model.grid, stiffness=100.0, damping=0.05, mass=1e-3, spring_mask=mask)
    assert speed.bytes_per_step(cut, "eager") == 1296 + 2 * 3 * 27 * 4  # stiffness and damping per spring
    # gravity: the step reads the mass; a per-node mass (3, 3, 3) counts in the eager layout too
    heavy = td.Model(model.grid, stiffness=100.0, mass=torch.full((3, 3, 3), 1e-3), gravity=(0, 0, -9.81))
    assert speed.bytes_per_step(heavy, "eager") == 1296 + 27 * 4 + 27 * 4  # 1/m and m per node
    with pytest.raises(ValueError):
        speed.bytes_per_step(model, "compiled")  # a packed mode reads a packed model


def test_native_rows_are_planned_where_the_kernel_runs_and_modes_pick_rows():
    """Native rows where the device's kernel runs (C on the CPU, Triton on CUDA); ``--modes`` keeps a subset."""
    from torchdeform.sim import native, native_cuda

    args = argparse.Namespace(no_compile=False, no_warp=True, no_beam=True, quick=False, materials=["springs"])
    for device, why in (("cuda", native_cuda.unavailable()), ("cpu", native.unavailable())):
        tasks, _, _ = speed._plan(args, device, [16], [26], ["float32"], [1])
        assert [t[5] for t in tasks] == (["eager", "compiled"] if why else ["eager", "native", "compiled"])
    args.modes = ["compiled", "eager"]
    tasks, _, _ = speed._plan(args, "cpu", [16, 32], [26], ["float32"], [1])
    assert [(t[1], t[5]) for t in tasks] == [(16, "eager"), (16, "compiled"), (32, "eager"), (32, "compiled")]


def test_an_unknown_mode_is_refused_by_name(capsys):
    assert cli.main(argv=["bench", "speed", "--quick", "--modes", "eager,fast"]) == 2
    out, err = capsys.readouterr()
    assert "--modes" in err and "fast" in err and "Traceback" not in err and out == ""


def test_elastic_rows_are_planned_beside_the_springs_and_compared_with_them():
    args = argparse.Namespace(
        no_compile=True, no_warp=True, no_beam=True, quick=False, materials=["springs", "elastic"]
    )
    tasks, _, _ = speed._plan(args, "cpu", [16], [6, 26], ["float32"], [1])
    assert [(t[2], t[6]) for t in tasks] == [(6, "springs"), (26, "springs"), (26, "elastic")]  # no 6-neighbour solid
    row = dict(n=64, topology=26, dtype="float32", threads=2)
    rows = [
        dict(row, mode="native", material="springs", msprings_per_s=1200.0),
        dict(row, mode="native", material="elastic", msprings_per_s=700.0),
        dict(row, mode="native", material="elastic", msprings_per_s=300.0, contention=True, vs_idle=0.43),
    ]
    t = speed._targets(rows, [])["elastic_vs_springs_64"]
    assert t["value"] == pytest.approx(700 / 1200) and t["busy_vs_idle"] == 0.43 and t["met"]
    rows[1]["msprings_per_s"] = 500.0
    assert not speed._targets(rows, [])["elastic_vs_springs_64"]["met"]


@pytest.mark.slow  # a bench smoke run
def test_bench_bad_option_is_one_line(capsys):
    assert cli.main(argv=["bench", "speed", "--topologies", "7"]) == 2
    err = capsys.readouterr().err
    assert "--topologies" in err and "Traceback" not in err
