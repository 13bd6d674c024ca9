"""Adaptive steps (torchdeform.sim.adaptive) against analytic solutions and a tight reference run."""

from __future__ import annotations

import math

import pytest
import torch

import torchdeform as td
from torchdeform.errors import ConfigError
from torchdeform.sim.adaptive import PAIRS, stability_limits
from torchdeform.sim.integrators import rates
from torchdeform.sim.model import State


def oscillator():
    """One spring, one free node of 1 kg: omega = 1 rad/s; x(t) = 1 + 0.1 cos t along W."""
    grid = td.Grid((1, 1, 2), spacing=1.0, topology=6)
    model = td.Model(grid, stiffness=1.0, mass=1.0, fixed=grid.index_mask([(0, 0, 0)]), dtype=torch.float64)
    s = model.rest_state()
    s.x[0, 2, 0, 0, 1] += 0.1
    return model, s


@pytest.mark.parametrize("name", list(PAIRS))
def test_each_pair_has_its_order_and_its_error_estimate_the_embedded_order(name):
    """One try from t = 0.3 on the oscillator: the propagated solution's local error falls like
    h^(p+1), the error estimate like h^(q+1) (p, q the pair's orders), against the exact solution."""
    model, _ = oscillator()
    pair, adaptive = PAIRS[name], td.Adaptive(pair=name)
    t0 = 0.3
    x = model.X.clone()
    x[0, 2, 0, 0, 1] += 0.1 * math.cos(t0)
    v = torch.zeros_like(x)
    v[0, 2, 0, 0, 1] = -0.1 * math.sin(t0)
    errors, estimates = [], []
    for h in (0.1, 0.05):
        x1, _, ex, _ = adaptive._try(rates(model), t0, x, v, h)
        errors.append(abs(float(x1[0, 2, 0, 0, 1]) - 1 - 0.1 * math.cos(t0 + h)))
        estimates.append(abs(float(ex[0, 2, 0, 0, 1])))
    assert math.log2(errors[0] / errors[1]) == pytest.approx(pair.order + 1, abs=0.35)
    assert math.log2(estimates[0] / estimates[1]) == pytest.approx(pair.error_order + 1, abs=0.35)


def test_stability_limits_of_the_tableaux():
    """|R(iy)| = |1 + iy - y^2/2 - i y^3/6| for Bogacki-Shampine: <= 1 exactly up to sqrt(3);
    Heun (2nd order) has no stretch of the imaginary axis; both reach -2 or beyond on the real axis."""
    imag, real = stability_limits(PAIRS["bogacki_shampine"])
    assert imag == pytest.approx(math.sqrt(3), abs=2e-4) and real > 2.5
    assert stability_limits(PAIRS["heun_euler"]) == (0.0, pytest.approx(2.0, abs=2e-4))


def test_rtol_gives_the_analytic_oscillation_to_the_tolerance():
    model, s = oscillator()
    for rtol in (1e-3, 1e-6):
        adaptive = td.Adaptive(rtol=rtol)
        out, rec = td.simulate(model, s, dt=0.5, steps=20, integrator=adaptive, record_every=1, warn=False)
        exact = 1 + 0.1 * torch.cos(rec["t"])
        err = float((rec["x"][:, 0, 2, 0, 0, 1] - exact).abs().max()) / 0.1
        assert rtol / 10 <= err <= 10 * rtol, (rtol, err)
        assert out.t == pytest.approx(10.0, abs=1e-12)
    assert adaptive.stats["max_h"] <= 0.9 * math.sqrt(3) / 1.0 + 1e-12  # the stability cap


def body(drag: bool):
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    extra = (
        {"drags": [td.Drag(grid.index_mask([(3, 2, 2)]), offset=(0.004, 0.002, 0.0), period=0.1)]}
        if drag
        else {"loads": [td.PointForce((3, 1, 1), (-0.05, 0.02, 0.0), ramp=0.02)]}
    )
    return td.Model(
        grid, stiffness=50.0, damping=0.02, mass=1e-3, fixed=grid.face("bottom"), dtype=torch.float64, **extra
    )


@pytest.mark.parametrize("drag", [False, True], ids=["load", "drag"])
@pytest.mark.slow
def test_global_error_follows_the_tolerance_on_the_load_and_drag_scenes(drag):
    """Positions every 10 ms over 0.05 s against Dormand-Prince at rtol 1e-10, relative to the largest
    displacement: Bogacki-Shampine's error stays within 10x of rtol, and steps get rejected on the way."""
    model = body(drag)
    _, ref = td.simulate(
        model,
        model.rest_state(),
        0.01,
        5,
        integrator=td.Adaptive(rtol=1e-10, pair="dormand_prince"),
        record_every=1,
        warn=False,
    )
    amp = float((ref["x"] - model.X).abs().max())
    for rtol in (1e-2, 1e-4, 1e-6):
        adaptive = td.Adaptive(rtol=rtol)
        _, rec = td.simulate(
            model, model.rest_state(), 0.01, 5, rtol=None, integrator=adaptive, record_every=1, warn=False
        )
        err = float((rec["x"] - ref["x"]).abs().max()) / amp
        assert rtol / 10 <= err <= 10 * rtol, (rtol, err)
    assert adaptive.stats["accepted"] > 10


def test_a_step_below_min_step_stops_with_one_line():
    """A 1,000x stiffer body asked for 1e-9 with min_step a tenth of the output interval."""
    model = body(drag=False)
    model.stiffness = model.stiffness * 1000
    with pytest.raises(td.StepSizeError) as e:
        td.simulate(model, model.rest_state(), 0.01, 5, integrator=td.Adaptive(rtol=1e-9, min_step=1e-3), warn=False)
    msg = str(e.value)
    assert "\n" not in msg and "below min_step 0.001 s" in msg and "rtol 1e-09" in msg
    assert isinstance(e.value, td.DivergenceError)


def test_rtol_argument_checks_and_the_engine():
    model, s = oscillator()
    with pytest.raises(ConfigError, match="rtol"):
        td.simulate(model, s, 0.1, 3, integrator=td.SymplecticEuler(), rtol=1e-3)
    for bad in (0, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="rtol"):
            td.Adaptive(rtol=bad)
    with pytest.raises(ConfigError, match="pair"):
        td.Adaptive(pair="rk45")
    engine = td.Engine(mode="auto")
    td.simulate(model, s, 0.1, 20, rtol=1e-4, engine=engine, warn=False)
    assert engine.ran == "eager" and "adaptive" in engine.reason


def test_adaptive_state_time_lands_on_the_output_grid():
    model, s = oscillator()
    st = td.Adaptive(rtol=1e-5).step(model, State(s.x, s.v, t=0.25), 0.7)
    assert st.t == 0.25 + 0.7
