"""Cautery (torchdeform.topology.cauterize).

* mass and momentum: the body's mass and momentum after, plus what was removed, equal those
  before (float64, 1e-15 relative);
* the cauterized body moves exactly like a body built without those nodes (a grid node mask:
  an independent construction path through Grid and Model), to 1e-12 over 300 steps;
* removed nodes stay put, and the pieces a burn separates are counted.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform as td
from tests.helpers import F64, make_grid, make_model
from torchdeform.errors import ConfigError
from torchdeform.interact import Capsule, Sphere, Tool
from torchdeform.topology import cauterize, components

H = 0.01


def _body(node_mask=None, device=None):
    grid = make_grid((5, 4, 4), spacing=H, node_mask=node_mask)
    return make_model(
        grid, stiffness=20.0, damping=0.02, gravity=(-9.81, 0, 0), fixed=grid.face("bottom"), device=device
    )


def test_removed_mass_and_momentum_are_accounted_for(device):
    model = _body(device=device)
    state, _ = td.simulate(model, model.rest_state(), dt=2e-4, steps=50)
    m0 = float(model.mass.expand(1, 1, *model.grid.shape).sum())
    p0 = (model.mass * state.v).flatten(2).sum(2)[0]
    v_before = state.v.clone()
    out = cauterize(model, state, Tool(Sphere(0.013), position=(0.04, 0.015, 0.015)))
    assert out["nodes"] == 8  # the 4 top-centre nodes and 4 below them
    assert float(model.mass.sum()) + out["mass_kg"] == pytest.approx(m0, rel=1e-15)
    p1 = (model.mass * v_before).flatten(2).sum(2)[0]
    assert torch.allclose(p1 + torch.tensor(out["momentum"], dtype=F64, device=device), p0, rtol=0, atol=1e-18)
    assert bool((state.v[0, :, model.removed] == 0).all())
    assert cauterize(model, state, Tool(Sphere(0.013), position=(0.04, 0.015, 0.015)))["nodes"] == 0


def test_cauterized_body_moves_like_one_built_without_those_nodes(device):
    model = _body(device=device)
    burn_tool = Tool(Capsule(0.006, 0.01, axis=1), position=(0.04, 0.015, 0.015))
    cauterize(model, model.rest_state(), burn_tool)
    reference = _body(node_mask=~model.removed.cpu(), device=device)
    a, _ = td.simulate(model, model.rest_state(), dt=2e-4, steps=300)
    b, _ = td.simulate(reference, reference.rest_state(), dt=2e-4, steps=300)
    body = ~model.removed
    assert (a.x[0][:, body] - b.x[0][:, body]).abs().max() < 1e-12
    assert (a.x[0][:, model.removed] - model.X[0][:, model.removed]).abs().max() == 0  # removed: still


def test_a_burn_through_the_body_leaves_two_pieces(device):
    model = _body(device=device)
    wall = Tool(td.interact.Box((0.004, 0.05, 0.05)), position=(0.02, 0.015, 0.015))  # the middle layer
    out = cauterize(model, model.rest_state(), wall)
    assert out["nodes"] == 16
    assert components(model)[1] == 2


def test_cautery_needs_one_body():
    model = _body()
    with pytest.raises(ConfigError, match=r"cauterize\.state"):
        cauterize(model, model.rest_state(batch=2), Tool(Sphere(0.01), position=(0.04, 0.0, 0.0)))
