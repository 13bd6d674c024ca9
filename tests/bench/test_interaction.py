"""`torchdeform bench interaction`: an eager smoke run (rows, JSON fields, files) and its force figure
against a plain simulation of the same scene (grid layout, an independent path to the packed step)."""

import json

import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.bench.interaction import pressing_scene

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_interaction_eager_json(capsys, tmp_path):
    rc = cli.main(
        argv=[
            "bench",
            "interaction",
            "--quick",
            "--no-compile",
            "--json",
            "--sizes",
            "5",
            "--haptic-size",
            "5",
            "--seconds",
            "0.2",
            "--steps",
            "20",
            "--dtype",
            "float64",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "interaction" and {"machine", "haptic", "step_24"} <= set(doc)
    step, haptic = doc["rows"]
    for r in (step, haptic):
        assert {"n", "topology", "mode", "hz", "force_N"} <= set(r) and r["n"] == 5 and r["topology"] == 26
        assert r["hz"] > 0 and r["force_N"] > 0
    assert step["mode"] == "step" and haptic["mode"] == "haptic" and haptic["body_hz"] > 0
    # the step row's force: the same scene stepped on the grid layout (press to t >= 0.1 s, then 3 x 20 steps)
    model, _, dt = pressing_scene(5, dtype=torch.float64)
    t, steps = dt, 1  # the first (compiling) step, then on to t >= 0.1 s
    while t < 0.1:
        t, steps = t + dt, steps + 1
    steps += 60
    state, _ = td.simulate(model, model.rest_state(), dt=dt, steps=steps, warn=False)
    assert abs(state.readings["probe.force"][0, 0].item() - step["force_N"]) < 1e-9
    assert (tmp_path / "interaction.csv").is_file() and (tmp_path / "interaction.png").is_file()
