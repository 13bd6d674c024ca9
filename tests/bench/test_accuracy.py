"""``torchdeform bench accuracy``: a smoke run of ``--quick --json --out`` (about 10-15 s on 2
cores) checked for real behaviour, and the Pareto front against a brute-force check.
"""

import contextlib
import csv
import io
import json
import math
import random
from itertools import pairwise

import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.bench.accuracy.report import TARGETS, pareto_front
from torchdeform.bench.accuracy.runner import COLUMNS
from torchdeform.bench.accuracy.scenes import SCENES, SIDE, cell_share, cube

pytestmark = pytest.mark.slow  # a bench smoke run

EXPLICIT = ("explicit", "symplectic", "verlet", "rk4")
SMOOTH = ("load", "supports")  # the drag path has kinks, which cap the observed order


def _main(argv):
    """``cli.main(["bench", "accuracy", *argv])``; returns ``(rc, stdout)``."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli.main(argv=["bench", "accuracy", *argv])
    return rc, out.getvalue()


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    path = tmp_path_factory.mktemp("accuracy")
    threads = torch.get_num_threads()
    rc, out = _main(["--quick", "--json", "--out", str(path)])
    assert torch.get_num_threads() == threads  # the bench restores the thread count
    assert rc == 0
    return json.loads(out), path  # exactly one JSON document on stdout


def _ok(rows, scene, method):
    return sorted(
        (r for r in rows if r["scene"] == scene and r["method"] == method and r["status"] == "ok"),
        key=lambda r: (r["dt"] or 0, r["n"]),
    )


def test_quick_json_rows_and_references(quick):
    doc, _ = quick
    assert doc["bench"] == "accuracy" and doc["dtype"] == "float64" and doc["quick"] is True
    rows = doc["rows"]
    assert rows
    for r in rows:
        assert set(r) == set(COLUMNS)
        assert r["status"] in ("ok", "diverged")
        assert r["wall_s"] is not None and r["wall_s"] > 0
        if r["status"] == "ok":
            assert r["error"] is not None and math.isfinite(r["error"]) and r["error"] >= 0
    # every integrator has rows or a stated reason to be left out
    methods = {r["method"] for r in rows}
    for name in td.INTEGRATORS:
        assert name in methods or name in doc["skipped"], name
    assert set(EXPLICIT) | {"implicit", "static"} <= methods
    assert "knoche" in doc["skipped"] and doc["skipped"]["knoche"]
    assert {r["scene"] for r in rows} == set(SCENES)
    for name, ref in doc["references"].items():
        assert ref["text"] and ref["max_displacement_m"] > 0
        if name == "load-static":
            assert ref["method"] == "static" and ref["n"] == 5
        else:
            assert ref["method"] == "rk4" and ref["dt_bound"] <= 0.25
            assert ref["halving_diff"] < 1e-2  # halving the reference step changes little


def test_quick_orders_and_stability(quick):
    doc, _ = quick
    rows = doc["rows"]
    refs = doc["references"]
    for scene in SMOOTH:
        for method, low, high in (("rk4", 2.0, 6.0), ("symplectic", 0.6, 1.6)):
            ok = [r for r in _ok(rows, scene, method) if r["dt_bound"] < 1]
            assert len(ok) >= 2, (scene, method)
            for a, b in pairwise(ok):
                assert a["error"] < b["error"], (scene, method)  # error grows with dt
                assert a["error"] > 10 * refs[scene]["error_estimate"]  # above the reference's own error
            if scene == "load" or method == "symplectic":
                a, b = ok[0], ok[-1]
                order = math.log(b["error"] / a["error"]) / math.log(b["dt"] / a["dt"])
                assert low <= order <= high, (scene, method, order)
    # implicit Euler: stable above the explicit (symplectic) bound
    implicit = [r for r in rows if r["method"] == "implicit"]
    assert implicit and all(r["status"] == "ok" and r["error"] < 1 for r in implicit)
    assert any(r["dt_bound"] > 1.5 for r in implicit)
    # explicit methods: diverged well above their bound, stable below it
    for method in EXPLICIT:
        above = [r for r in rows if r["method"] == method and r["dt_bound"] >= 2]
        assert above, method
        assert all(r["status"] == "diverged" for r in above if method != "explicit"), method
        # explicit Euler's instability grows slowly (|1 + h lambda| a little above 1): in a short
        # quick run it may not have blown up yet, but it must be far worse than below the bound
        for r in above:
            below = [q for q in _ok(rows, r["scene"], method) if q["dt_bound"] < 1]
            assert r["status"] == "diverged" or r["error"] > 10 * max(q["error"] for q in below)
        assert any(r["status"] == "diverged" for r in above)
        assert all(r["status"] == "ok" for r in rows if r["method"] == method and r["dt_bound"] < 1)
    static = _ok(rows, "load-static", "static")
    assert [r["n"] for r in static] == [2, 3] and static[1]["error"] < static[0]["error"]


def test_quick_pareto_and_recommendation(quick):
    doc, _ = quick
    rows = doc["rows"]
    for scene in {r["scene"] for r in rows}:
        ok = [r for r in rows if r["scene"] == scene and r["status"] == "ok"]
        for p in ok:
            dominated = any(
                q["error"] <= p["error"]
                and q["wall_s"] <= p["wall_s"]
                and (q["error"] < p["error"] or q["wall_s"] < p["wall_s"])
                for q in ok
            )
            assert p["pareto"] == (not dominated), (scene, p["method"], p["param"])
        assert any(p["pareto"] for p in ok)
    assert not any(r["pareto"] for r in rows if r["status"] != "ok")
    assert doc["targets"] == list(TARGETS)
    for rec in doc["recommendations"]:
        reach = [r for r in rows if r["scene"] == rec["scene"] and r["status"] == "ok" and r["error"] <= rec["target"]]
        if not reach:
            assert rec["method"] is None
        else:
            best = min(r["wall_s"] for r in reach)
            assert rec["wall_s"] == best and rec["error"] <= rec["target"]
            assert any(
                r["method"] == rec["method"] and r["param"] == rec["param"] and r["wall_s"] == best for r in reach
            )


def test_quick_files(quick):
    doc, path = quick
    with open(path / "accuracy.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == len(doc["rows"]) and set(table[0]) == set(COLUMNS)
    png = path / "accuracy.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 400_000


def test_pareto_front_brute_force():
    rng = random.Random(0)
    for trial in range(200):
        n = rng.randint(0, 30)
        # few distinct values, so that ties in one or both coordinates are common
        pts = [
            (
                rng.choice([0.1, 0.2, 0.3, 0.5, 1.0, 2.0]) if rng.random() > 0.05 else None,
                rng.choice([1, 2, 3, 4, 5, math.inf]) if trial % 2 else rng.random(),
            )
            for _ in range(n)
        ]
        got = pareto_front(pts)
        valid = [p[0] is not None and math.isfinite(p[0]) and math.isfinite(p[1]) for p in pts]
        want = []
        for i, p in enumerate(pts):
            if not valid[i]:
                want.append(False)
                continue
            want.append(
                not any(
                    valid[j] and q[0] <= p[0] and q[1] <= p[1] and (q[0] < p[0] or q[1] < p[1])
                    for j, q in enumerate(pts)
                )
            )
        assert got == want, pts


def test_cell_share_and_scaling():
    grid = td.Grid((3, 3, 3), topology=26)
    s = cell_share(grid)
    axis_d = grid.directions.index((1, 0, 0))
    assert s[axis_d, 0, 1, 1] == 1.0  # interior edge: 4 cells
    assert s[axis_d, 0, 0, 1] == 0.5  # in a face of the box: 2 cells
    assert s[axis_d, 0, 0, 0] == 0.25  # along an edge of the box: 1 cell
    body = grid.directions.index((1, 1, 1))
    assert bool((s[body] == 1).all())  # a body diagonal lies in one cell
    # k = E h s: the same cube at two resolutions has the same total spring "modulus" per volume
    g3, kw3 = cube(3, 5e3, 4e-4, None)
    g5, kw5 = cube(5, 5e3, 4e-4, None)
    m3 = td.Model(g3, **kw3, dtype=torch.float64)
    m5 = td.Model(g5, **kw5, dtype=torch.float64)
    assert float(m3.mass.sum()) == pytest.approx(float(m5.mass.sum()))  # rho * volume
    # sum over springs of k l0^2 (~ E * volume for a lattice) does not depend on the spacing
    ksum = [float((m.stiffness * m.rest_length**2 * g.spring_mask()).sum()) for m, g in ((m3, g3), (m5, g5))]
    assert ksum[0] == pytest.approx(ksum[1], rel=1e-12)
    assert ksum[0] == pytest.approx(27 * 5e3 * SIDE**3, rel=1e-12)  # 3 + 6*2 + 4*3 per cell volume


def test_bad_options_are_one_line(capsys):
    cases = (
        (["--scenes", "load,nope"], "--scenes"),
        (["--resolutions", "4", "--ref-n", "17"], "--resolutions"),
        (["--targets", "0.1,x"], "--targets"),
        (["--methods", "static", "--scenes", "drag"], "--methods"),
    )
    for argv, key in cases:
        rc, out = _main(argv)
        err = capsys.readouterr().err
        assert rc == 2 and key in err and "Traceback" not in err and out == ""
