"""`torchdeform bench learn`: the quick JSON run (eager engine, and the rounding-sensitivity trainer)."""

import json

import pytest

from torchdeform import cli
from torchdeform.bench.learn import PERTURBATION

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_learn_quick_json(capsys, tmp_path):
    rc = cli.main(argv=["bench", "learn", "--quick", "--json", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "learn" and doc["met"] is None  # --quick: no compiled engine to judge
    (row,) = doc["rows"]
    assert row["engine"] == "eager" and row["compile_s"] is None and row["threads"] == 1
    assert row["iterations"] == 2 and row["s_per_iteration"] > 0 and row["speedup"] == 1.0
    assert [a["iteration"] for a in doc["agreement"]] == [1, 2]
    for a in doc["agreement"]:
        assert a["compiled_vs_eager"] is None
        # a start moved by 1e-15 (relative) ends two L-BFGS iterations nearby, but not on the same bits
        assert 0 < a["perturbed_vs_eager"] < 1e-8
    assert doc["perturbation"] == PERTURBATION
    assert (tmp_path / "learn.csv").is_file() and (tmp_path / "learn.png").is_file()


def test_bench_learn_refuses_one_iteration(capsys):
    assert cli.main(argv=["bench", "learn", "--iterations", "1", "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "torchdeform: --iterations: expected at least 2 (the first compiled iteration includes the compile), got 1"
    ]
