"""Smoke test of ``torchdeform bench speed --quick --json`` (one compiled shape, ~10-20 s).

Speed targets live in the benchmark, not here: this checks the command runs, prints exactly
one JSON document, its arithmetic, and that the compiled step equals the eager one.
"""

import json

import pytest

import torchdeform as td
from torchdeform import cli

pytestmark = pytest.mark.slow  # a bench smoke run


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
    for topology in (6, 26):
        assert any(r["mode"] == "eager" and r["topology"] == topology for r in rows)
    compiled = [r for r in rows if r["mode"] == "compiled"]
    assert len(compiled) == 1  # --quick compiles one tiny shape only
    c = compiled[0]
    assert not c["fallback"], "torch.compile fell back to eager"
    assert c["compile_s"] > 0 and c["compile_cache"] in ("built", "loaded")  # inductor's disk cache took it
    assert c["max_abs_diff"] is not None and c["max_abs_diff"] <= 1e-5
    assert (tmp_path / "speed.csv").is_file() and (tmp_path / "speed.png").is_file()


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


def test_bench_bad_option_is_one_line(capsys):
    assert cli.main(argv=["bench", "speed", "--topologies", "7"]) == 2
    err = capsys.readouterr().err
    assert "--topologies" in err and "Traceback" not in err
