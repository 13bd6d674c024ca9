"""``torchdeform bench batch``: a batched step is the bodies' separate steps, and the command's output.

The oracle steps each body alone with the plain eager integrator (``SymplecticEuler.step`` on a
one-body grid-layout state) and stacks the results.
"""

import json

import pytest
import torch

from torchdeform import cli
from torchdeform.bench import batch
from torchdeform.bench.common import speed_cube
from torchdeform.sim import native
from torchdeform.sim.compiled import CompiledStep
from torchdeform.sim.integrators import SymplecticEuler
from torchdeform.sim.model import State


def _separate(model, state, dt):
    """Each body stepped alone by the eager integrator, stacked: ``(B, 3, D, H, W)`` x and v."""
    outs = [
        SymplecticEuler().step(model, State(state.x[b : b + 1], state.v[b : b + 1], t=state.t), dt)
        for b in range(state.x.shape[0])
    ]
    return torch.cat([o.x for o in outs]), torch.cat([o.v for o in outs])


def _scene(device, *, n=4, topology=26, bodies=3):
    model, one, dt = speed_cube(n, topology, device=device)
    return model, one, batch.batch_state(model, one, bodies), dt


def test_batch_state_body_zero_is_the_speed_scene(device):
    model, one, state, _ = _scene(device, bodies=5)
    assert state.x.shape == (5, 3, 4, 4, 4) and state.x.device == model.X.device
    assert torch.equal(state.x[:1], one.x) and torch.equal(state.v[:1], one.v)
    assert (state.x[1:] - model.X).abs().max() < 1e-3  # near rest, each body its own draw
    assert not torch.equal(state.v[1], state.v[2])
    assert batch.batch_state(model, one, 1) is one


def test_eager_batch_equals_separate_steps(device):
    model, _, state, dt = _scene(device)
    row = batch.batch_row(model, state, dt, "eager", device=str(device), steps=1, repeats=1)
    x, v = _separate(model, state, dt)
    first = row["_first"]
    assert first.x.shape == x.shape
    assert torch.allclose(first.x, x, rtol=0, atol=1e-7) and torch.allclose(first.v, v, rtol=0, atol=1e-6)
    assert row["bodies"] == 3 and row["ms_per_step"] > 0
    assert row["body_steps_per_s"] == pytest.approx(3 / (row["ms_per_step"] / 1e3))


@pytest.mark.parametrize("topology", [6, 26])
def test_packed_batch_equals_separate_steps(device, topology):
    """The packed layout the compiled engine steps (here uncompiled) keeps the bodies apart."""
    model, _, state, dt = _scene(device, topology=topology, bodies=4)
    cs = CompiledStep(SymplecticEuler(), model, dt, enable=False)
    with torch.no_grad():
        out = cs.packed.unpack_state(cs.step_packed(cs.packed.pack_state(state)))
    x, v = _separate(model, state, dt)
    assert torch.allclose(out.x, x, rtol=0, atol=1e-7) and torch.allclose(out.v, v, rtol=0, atol=1e-5)


@pytest.mark.slow  # compiles one graph
def test_compiled_batch_equals_separate_steps(device):
    model, _, state, dt = _scene(device)
    row = batch.batch_row(model, state, dt, "compiled", device=str(device), steps=1, repeats=1)
    assert not row["fallback"], "torch.compile fell back to eager"
    x, v = _separate(model, state, dt)
    assert torch.allclose(row["_first"].x, x, rtol=0, atol=1e-7)
    assert torch.allclose(row["_first"].v, v, rtol=0, atol=1e-5)


def test_memory_needed_and_target():
    assert batch.memory_needed(16, 1024) == 6 * 1024 * 3 * 18**3 * 4
    rows = [
        {"engine": "compiled", "bodies": 1, "per_body_speedup": 1.0},
        {"engine": "compiled", "bodies": 1024, "per_body_speedup": 120.0},
        {"engine": "eager", "bodies": 1024, "per_body_speedup": 30.0},
    ]
    assert batch._target(rows, "compiled")["met"] is True
    assert batch._target(rows, "eager") == {
        "bodies": 1024,
        "per_body_speedup": 100.0,
        "engine": "eager",
        "value": 30.0,
        "met": False,
    }
    assert batch._target(rows[:1], "compiled")["met"] is None  # no 1,024-body row


def test_bench_batch_eager_json(capsys, tmp_path):
    argv = ["bench", "batch", "--quick", "--no-compile", "--size", "4", "--bodies", "3", "--steps", "2"]
    rc = cli.main(argv=[*argv, "--repeats", "1", "--json", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)  # stdout holds exactly one JSON document
    assert doc["bench"] == "batch" and doc["machine"]["device"] == "cpu"
    rows = doc["rows"]
    assert [(r["bodies"], r["engine"]) for r in rows] == [(1, "eager"), (3, "eager")]  # 1 added: the reference
    one, three = rows
    for r in rows:
        assert r["grid"] == "4^3" and r["topology"] == 26 and r["dtype"] == "float32" and r["steps"] == 2
        assert r["body_steps_per_s"] == pytest.approx(r["bodies"] / (r["ms_per_step"] / 1e3), rel=1e-9)
    assert one["per_body_speedup"] == 1.0 and one["max_abs_diff"] is None
    assert three["per_body_speedup"] == pytest.approx(three["body_steps_per_s"] / one["body_steps_per_s"])
    assert three["max_abs_diff"] == 0.0  # body 0 of the batch steps exactly as alone
    assert doc["compiled_vs_eager"] is None and doc["met"] is None and doc["target"]["value"] is None
    assert (tmp_path / "batch.csv").is_file() and (tmp_path / "batch.png").is_file()


def test_bench_batch_table(capsys):
    argv = ["bench", "batch", "--no-compile", "--size", "3", "--bodies", "1,2", "--steps", "1", "--repeats", "1"]
    assert cli.main(argv=argv) == 0
    out = capsys.readouterr().out
    assert "body-steps/s" in out and "per body x" in out and "not measured" in out


def test_bench_batch_refuses_a_batch_that_cannot_fit(capsys):
    assert cli.main(argv=["bench", "batch", "--bodies", "1,1000000000", "--size", "64"]) == 2
    err = capsys.readouterr().err
    assert "--bodies" in err and "fits in memory" in err and "Traceback" not in err


def test_bench_batch_bad_topology(capsys):
    assert cli.main(argv=["bench", "batch", "--topology", "7"]) == 2
    assert "--topology" in capsys.readouterr().err


@pytest.mark.slow  # compiles two batch sizes
def test_bench_batch_quick_json(capsys):
    assert cli.main(argv=["bench", "batch", "--quick", "--json", "--threads", "2"]) == 0
    captured = capsys.readouterr()
    assert "recompile_limit" not in captured.err
    doc = json.loads(captured.out)
    rows = doc["rows"]
    engines = ["eager"] + ([] if native.unavailable() else ["native"]) + ["compiled"]
    assert [(r["engine"], r["bodies"]) for r in rows] == [(e, b) for e in engines for b in (1, 8)]
    for r in rows:
        assert r["grid"] == "16^3" and r["ms_per_step"] > 0 and r["nodes_per_body"] == 16**3
    for r in rows[2:]:
        assert not r["fallback"] and r["compile_s"] is not None
    # batching changes no body (the native kernel's and the compiled step's batch entries included)
    assert all(r["max_abs_diff"] <= 1e-6 for r in rows if r["bodies"] == 8)
    assert doc["compiled_vs_eager"] <= 1e-5
    assert doc["target"]["engine"] == "compiled" and doc["met"] is None  # no 1,024-body row in --quick
