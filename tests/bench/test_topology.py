"""`torchdeform bench topology`: an eager smoke run; its counts against the analytic formulas."""

import json

import pytest

from torchdeform import cli

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_topology_eager_json(capsys, tmp_path):
    rc = cli.main(
        argv=[
            "bench",
            "topology",
            "--quick",
            "--no-compile",
            "--json",
            "--sizes",
            "4,6",
            "--steps",
            "3",
            "--repeats",
            "2",
            "--dtype",
            "float64",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "topology" and {"machine", "targets", "met"} <= set(doc)
    formulas = {6: lambda n: n * n, 18: lambda n: n * n + 4 * n * (n - 1), 26: lambda n: (3 * n - 2) ** 2}
    assert sorted((r["topology"], r["n"]) for r in doc["rows"]) == [(t, n) for t in (6, 18, 26) for n in (4, 6)]
    for r in doc["rows"]:
        assert {
            "topology",
            "n",
            "springs_removed",
            "expected",
            "components",
            "cut_ms",
            "step_ms_before",
            "step_ms_after",
        } <= set(r)
        assert r["springs_removed"] == r["expected"] == formulas[r["topology"]](r["n"])
        assert r["components"] == 2
        assert r["cut_ms"] > 0 and r["step_ms_before"] > 0 and r["step_ms_after"] > 0
    assert doc["met"]["counts"] is True
    assert (tmp_path / "topology.csv").is_file() and (tmp_path / "topology.png").is_file()


def test_bench_topology_refuses_bad_sizes(capsys):
    assert cli.main(argv=["bench", "topology", "--sizes", "2", "--no-compile"]) == 2
    assert "--sizes" in capsys.readouterr().err
