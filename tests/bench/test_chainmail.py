"""`torchdeform bench chainmail`: the quick JSON run (rows, variants, files)."""

import json

import pytest

from torchdeform import cli

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_chainmail_quick_json(capsys, tmp_path):
    rc = cli.main(argv=["bench", "chainmail", "--quick", "--json", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "chainmail"
    rows = doc["rows"]
    assert {r["variant"] for r in rows} == {"gibson", "enhanced", "tensor"}
    for r in rows:
        assert {"grid", "moved", "variant", "ms"} <= set(r) and r["ms"] > 0 and r["moved"] > 0
    tensor = [r for r in rows if r["variant"] == "tensor"]
    assert all(r["sweeps"] >= r["depth"] for r in tensor)
    # checked: the elements the sweeps visited (active boxes), at most the whole grid per sweep
    assert all(0 < r["checked"] <= (r["sweeps"] + 1) * r["n"] ** 3 for r in tensor)
    assert "pull_100" in doc and "tensor_pull_100" in doc  # None here: no 100^3 grid in --quick
    assert (tmp_path / "chainmail.csv").is_file() and (tmp_path / "chainmail.png").is_file()
