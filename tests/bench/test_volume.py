"""`torchdeform bench volume` (quick smoke run) and the inverse-warp rows of the accuracy bench."""

from itertools import pairwise

import pytest
import torch

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_volume_quick_smoke(capsys):
    import json

    from torchdeform import cli

    assert (
        cli.main(argv=["bench", "volume", "--quick", "--json", "--repeats", "1", "--size", "24", "--nodes", "4"]) == 0
    )
    doc = json.loads(capsys.readouterr().out)
    paths = {(r["mode"], r["path"]) for r in doc["rows"]}
    quick = {(m, p) for m in ("mip", "dvr") for p in ("naive", "grid_sample", "eager")}  # quick: no compile
    assert paths == quick | {("dvr", "native")}  # the C marcher composites dvr only
    assert all(r["fps"] > 0 and r["cpu_ms"] >= 0 for r in doc["rows"])
    assert all(r["max_abs_diff"] < 1e-2 for r in doc["rows"] if r["mode"] == "dvr")
    assert all(r["max_abs_diff"] < 0.05 for r in doc["rows"] if r["mode"] == "mip")  # HU, float32 rounding


def test_inverse_warp_accuracy_rows():
    from torchdeform.bench.accuracy.runner import COLUMNS, inverse_warp_rows

    rows, ref = inverse_warp_rows(quick=True, dtype=torch.float64, repeats=1)
    assert all(set(r) == set(COLUMNS) and r["scene"] == "inverse-warp" and r["wall_s"] > 0 for r in rows)
    errors = [r["error"] for r in sorted(rows, key=lambda r: r["steps"])]
    assert rows[0]["steps"] == 0 and errors[0] > 0.1  # first order: visibly wrong
    assert all(b < a for a, b in pairwise(errors))  # each iteration helps
    assert errors[-1] < 1e-3 and "below 1e-3 voxel" in ref["text"]
