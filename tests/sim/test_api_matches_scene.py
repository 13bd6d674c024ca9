"""The Python API takes what a scene file takes: face names for ``fixed``, a duration for ``simulate``,
and it says so clearly when a state lacks its batch dimension.

Oracles: :meth:`Grid.face` for the face masks, ``ceil(duration / dt)`` for the number of steps.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td


@pytest.fixture
def grid():
    return td.Grid((4, 4, 4), spacing=0.01)


def test_fixed_takes_a_face_name_or_a_list_of_them(grid):
    model = td.Model(grid, stiffness=50.0, density=1000.0, fixed="bottom")
    assert torch.equal(model.constrained.cpu(), grid.face("d-"))
    both = td.Model(grid, stiffness=50.0, density=1000.0, fixed=["bottom", "w+"])
    assert torch.equal(both.constrained.cpu(), grid.face("bottom") | grid.face("w+"))
    with pytest.raises(td.ConfigError, match="face name"):
        td.Model(grid, stiffness=50.0, density=1000.0, fixed="botom")


def test_an_unbatched_state_is_refused_with_a_clear_message(grid):
    model = td.Model(grid, stiffness=50.0, density=1000.0, fixed="bottom")
    rest = model.rest_state()
    with pytest.raises(td.ConfigError, match=r"batch dimension, State\(x\[None\], v\[None\]\)") as e:
        td.simulate(model, td.State(rest.x[0], rest.v[0]), 1e-4, 2)
    assert "(3, 4, 4, 4)" in str(e.value)


def test_simulate_takes_a_duration_instead_of_steps(grid):
    model = td.Model(grid, stiffness=50.0, damping=0.1, density=1000.0, fixed="bottom", gravity=(-9.81, 0, 0))
    dt = 1e-4
    final, _ = td.simulate(model, model.rest_state(), dt, duration=0.001)
    assert round(final.t / dt) == 10
    final, _ = td.simulate(model, model.rest_state(), dt, duration=0.00105)
    assert round(final.t / dt) == 11  # ceil: the whole duration is covered
    for kwargs in ({}, {"steps": 3, "duration": 0.001}):
        with pytest.raises(td.ConfigError, match="exactly one of steps"):
            td.simulate(model, model.rest_state(), dt, **kwargs)
