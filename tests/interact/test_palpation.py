"""Reading a tool's force series (torchdeform.interact.palpation): work direction, block means, presses.

Oracles: series built by hand with a known answer: a press against a linear spring ``F = k delta``
has slope ``k`` and peak ``k delta_max``; block means against ``reshape(...).mean``; the work
direction of a tool moving along one axis against the force is that axis. A press simulated on
the device of the run reads as the same run on the CPU.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.interact import ProjectionContact, Sphere, Tool
from torchdeform.interact.palpation import block_means, palpation, plot_palpation, significant, work_direction


def _presses(stiffness, depth=1e-3, steps=1000, spacing=0.01):
    """A tool pressing ``depth`` into linear springs of ``stiffness`` (N/m) at ``spacing`` along W, one per second."""
    k = np.repeat(np.asarray(stiffness, dtype=float), steps)
    t = np.arange(len(k)) / steps
    phase = t % 1.0
    delta = np.clip(1 - np.abs(phase - 0.5) * 4, 0, None) * depth  # 0 -> depth -> 0 in the middle half
    position = np.stack([-delta, np.zeros_like(t), np.floor(t) * spacing], 1)
    force = np.stack([k * delta, 0 * t, 0 * t], 1)  # the tissue pushes the tool back up
    return t, force, position, delta > 0


def test_presses_of_linear_springs():
    t, force, position, contacts = _presses([100.0, 400.0, 200.0])
    r = palpation(t, force, position, contacts)
    assert len(r["points"]) == 3
    for p, k in zip(r["points"], (100.0, 400.0, 200.0)):
        assert p["stiffness_N_per_m"] == pytest.approx(k, rel=1e-3)
        assert p["indentation_m"] == pytest.approx(1e-3, rel=1e-2)
        assert p["peak_force_N"] == pytest.approx(k * 1e-3, rel=2e-2)
        assert len(p["curve"]["force_N"]) <= 100 and p["curve"]["indentation_m"][0] >= 0
    assert [p["along_m"] for p in r["points"]] == pytest.approx([0.0, 0.01, 0.02])
    s = r["stiffest"]
    assert s["index"] == 1 and s["along_m"] == pytest.approx(0.01)
    assert s["ratio_to_median"] == pytest.approx(2.0, rel=2e-2)


def _simulated_press(device):
    """A sphere pressed 2 mm into a block and lifted again: ``(t, force, position, contacts)`` as numpy.

    The readings stay on ``device`` while the body steps and come back once, at the end.
    """
    grid = td.Grid((3, 3, 3), spacing=0.01, topology=26)
    up, down = (0.031, 0.01, 0.01), (0.028, 0.01, 0.01)  # the sphere's bottom 1 mm above the top, then 2 mm in
    probe = Tool(Sphere(0.01), path=[(0.0, up), (0.05, down), (0.1, up)], name="probe")
    model = td.Model(
        grid,
        stiffness=30.0,
        damping=0.05,
        mass=1e-3,
        fixed=grid.face("bottom"),
        interactions=[ProjectionContact(probe)],
        dtype=F64,
        device=device,
    )
    rows = []

    def keep(i, s):
        rows.append((float(s.t), s.readings["probe.force"][0], s.readings["probe.contacts"][0]))

    td.simulate(model, model.rest_state(), dt=5e-4, steps=200, callback=keep)
    t = np.array([r[0] for r in rows])
    force = torch.stack([r[1] for r in rows]).cpu().numpy()
    contacts = torch.stack([r[2] for r in rows]).cpu().numpy()
    return t, force, np.array([probe.position(ti) for ti in t]), contacts


def test_a_press_simulated_on_the_device_reads_as_on_the_cpu(device):
    got = palpation(*_simulated_press(device))
    ref = palpation(*_simulated_press("cpu"))  # the oracle: the same run on the CPU
    assert len(got["points"]) == len(ref["points"]) == 1
    p, q = got["points"][0], ref["points"][0]
    assert q["peak_force_N"] > 0.01 and q["stiffness_N_per_m"] > 1.0 and q["indentation_m"] > 1e-3
    assert p["peak_force_N"] == pytest.approx(q["peak_force_N"], rel=1e-9)
    assert p["stiffness_N_per_m"] == pytest.approx(q["stiffness_N_per_m"], rel=1e-6)
    assert p["indentation_m"] == pytest.approx(q["indentation_m"], rel=1e-12)


def test_given_velocity_and_curve_points():
    t, force, position, contacts = _presses([100.0, 300.0])
    velocity = np.gradient(position, t, axis=0)
    r = palpation(t, force, position, contacts, velocity=velocity, curve_points=20)
    assert [round(p["stiffness_N_per_m"]) for p in r["points"]] == [100, 300]
    assert all(len(p["curve"]["force_N"]) <= 20 for p in r["points"])


def test_short_gaps_are_bridged_and_short_touches_dropped():
    t, force, position, contacts = _presses([100.0, 300.0])
    contacts = contacts.copy()
    on = np.flatnonzero(contacts[:1000])
    contacts[on[200] : on[200] + 3] = False  # a 3-step gap in a ~500-step press: bridged
    contacts[1900:1905] = True  # 5 steps of touch between presses, the tool at rest: no press
    r = palpation(t, force, position, contacts)
    assert len(r["points"]) == 2


def test_no_presses():
    t = np.linspace(0, 1, 50)
    assert palpation(t, np.zeros((50, 3)), np.zeros((50, 3)), np.zeros(50)) == {"points": [], "stiffest": None}


def test_work_direction():
    t = np.linspace(0.0, 1.0, 101)
    down = np.stack([-1e-3 * t, 0 * t, 0 * t], 1)
    push_back = np.stack([0.05 * t, 0 * t, 0 * t], 1)
    assert work_direction(t, down, push_back) == pytest.approx([-1.0, 0.0, 0.0])
    lift = -down
    pull_back = -push_back  # forceps lifting tissue: the tissue pulls them down
    assert work_direction(t, lift, pull_back) == pytest.approx([1.0, 0.0, 0.0])
    still = np.zeros_like(down)  # no work: minus the summed force
    assert work_direction(t, still, np.tile([0.0, 2.0, 0.0], (101, 1))) == pytest.approx([0.0, -1.0, 0.0])
    assert work_direction(t, still, np.zeros_like(down)).tolist() == [0.0, 0.0, 0.0]


def test_block_means_and_significant():
    a = np.arange(20.0).reshape(10, 2)
    assert np.array_equal(block_means(a, 5), a.reshape(2, 5, 2).mean(1))
    last = block_means(a, 4)
    assert np.array_equal(last[:2], a[:8].reshape(2, 4, 2).mean(1)) and np.array_equal(last[2], a[8:].mean(0))
    assert block_means(a, 1) is a
    assert significant([[1.23456789, 1e-9 / 3]]) == [[1.23457, 3.33333e-10]]
    assert significant(np.pi, digits=3) == 3.14 and significant([]) == []


def test_plot_palpation_writes_a_png(tmp_path):
    t, force, position, contacts = _presses([100.0, 300.0])
    result = {"tool": "finger", **palpation(t, force, position, contacts)}
    plot_palpation(tmp_path / "palpation.png", result, title="two presses")
    png = (tmp_path / "palpation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
