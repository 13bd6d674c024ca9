"""Compiled training rollouts (``WindowLoss(engine="compiled")``) against the eager reference.

The graphs are captured and differentiated with the ``aot_eager`` backend (dynamo + AOTAutograd,
the same graphs inductor would turn into code, in seconds instead of ~40 s); ``bench learn``
runs the inductor build and times it.
"""

from __future__ import annotations

import warnings

import pytest
import torch

import torchdeform as td
from torchdeform import learn
from torchdeform._compile import CompileFallbackWarning
from torchdeform.sim.springs import spring_forces


def _loss_and_grad(loss, params):
    for p in params.parameters():
        p.grad = None
    value = loss(params)
    value.backward()
    return value.detach(), torch.cat([p.grad.reshape(-1) for p in params.parameters()])


def _compare(series, window, **kw):
    params, _ = learn.per_spring_start(series, seed=3)
    eager = learn.WindowLoss(series, window=window, **kw)
    compiled = learn.WindowLoss(series, window=window, engine="compiled", backend="aot_eager", **kw)
    (le, ge), (lc, gc) = _loss_and_grad(eager, params), _loss_and_grad(compiled, params)
    assert le > 0 and ge.norm() > 0
    assert abs(float(lc - le)) <= 1e-12 * float(le)
    assert float((gc - ge).norm()) <= 1e-12 * float(ge.norm())
    return compiled, params


@pytest.mark.slow
def test_compiled_loss_and_gradient_equal_eager_on_radetzkys_cube():
    _compare(learn.radetzky_cube(springs=70, steps=40), window=10)


@pytest.mark.slow
def test_compiled_loss_follows_drags_and_checkpoints():
    """A dragged top face (the drag table inside the compiled step) and checkpointed segments."""
    series = learn.cube_series(n=3, topology=26, load="sine", steps=30, dt=0.005, period=0.1)
    _compare(series, window=None, checkpoint=10)


@pytest.mark.slow
def test_new_parameter_values_do_not_recompile():
    """The model's tensors are graph inputs: a new start (new values) reuses the graphs."""
    torch._dynamo.reset()
    series = learn.radetzky_cube(springs=70, steps=20)
    compiled, params = _compare(series, window=10)
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    other, _ = learn.per_spring_start(series, seed=11)
    _loss_and_grad(compiled, other)
    _loss_and_grad(compiled, params)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs


@pytest.mark.slow
def test_failed_compilation_warns_once_and_runs_eagerly():
    def broken(gm, example_inputs):
        raise RuntimeError("no compiler here")

    series = learn.radetzky_cube(springs=70, steps=20)
    params, _ = learn.per_spring_start(series)
    eager = learn.WindowLoss(series, window=10)
    compiled = learn.WindowLoss(series, window=10, engine="compiled", backend=broken)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = compiled(params)
    assert compiled._compiled is None
    assert any(issubclass(w.category, CompileFallbackWarning) for w in caught)
    assert float(value.detach()) == float(eager(params).detach())


def test_unknown_engine_is_refused():
    with pytest.raises(td.ConfigError, match="engine"):
        learn.WindowLoss(learn.radetzky_cube(steps=20), engine="fast")


@pytest.mark.slow
def test_traced_spring_sum_is_the_in_place_sum_to_the_bit():
    """Under torch.compile the springs are summed as zero-padded terms, not in-place slice updates:
    the same additions in the same order (forces and their gradient, float64)."""
    grid = td.Grid((3, 4, 5), spacing=0.01, topology=26)
    g = torch.Generator().manual_seed(0)
    x = grid.rest_positions(dtype=torch.float64) + 1e-3 * torch.randn(1, 3, 3, 4, 5, generator=g, dtype=torch.float64)
    v = torch.randn(1, 3, 3, 4, 5, generator=g, dtype=torch.float64)
    k = (1 + torch.rand(1, grid.S, 3, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    c = torch.rand(1, grid.S, 3, 4, 5, generator=g, dtype=torch.float64)
    l0 = grid.rest_lengths(dtype=torch.float64).view(1, grid.S, 1, 1, 1)

    def forces(k):
        return spring_forces(x, v, grid, k, l0, c=c, projected=True)

    traced = torch.compile(forces, backend="eager", fullgraph=True)
    fe, ft = forces(k), traced(k)
    assert torch.equal(fe, ft)
    w = torch.randn(fe.shape, generator=g, dtype=torch.float64)
    (ge,) = torch.autograd.grad((fe * w).sum(), k)
    (gt,) = torch.autograd.grad((ft * w).sum(), k)
    assert torch.equal(ge, gt)
