"""`torchdeform bench fuzzy`: the quick JSON run on MATLAB's tipper against scikit-fuzzy."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # a bench smoke run

TIPPER = Path(__file__).resolve().parents[1] / "data" / "fis" / "tipper.fis"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "torchdeform", *map(str, args)], capture_output=True, text=True)


def test_bench_fuzzy_quick_json():
    pytest.importorskip("skfuzzy")
    res = _cli("bench", "fuzzy", "--quick", "--no-compile", "--json", "--system", TIPPER)
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    modes = {r["mode"]: r for r in doc["rows"]}
    assert set(modes) == {"eager", "scikit-fuzzy"}
    assert modes["scikit-fuzzy"]["max_diff_of_range"] < 1e-3
    assert modes["eager"]["inputs_per_s"] > 0 and modes["eager"]["vs_skfuzzy"] > 1
