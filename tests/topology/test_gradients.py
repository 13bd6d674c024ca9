"""Coagulation and pre-tension are learnable: gradients through rest lengths pass gradcheck.

torch.autograd.gradcheck compares the autograd gradient of a short simulation with central finite
differences (float64), for the gape of a cut (pretension) and the coagulated configuration.
"""

from __future__ import annotations

import torch

import torchdeform as td
from tests.helpers import F64
from torchdeform.topology import Blade, coagulated_rest_length, cut, pretension
from torchdeform.topology.masks import ends

H = 0.01


def _grid():
    return td.Grid((4, 2, 2), spacing=H, topology=18)


def _simulate(model, steps=15):
    state, _ = td.simulate(model, model.rest_state(), dt=2e-4, steps=steps)
    return state.x


def test_gradcheck_through_the_gape_of_a_cut(device):
    grid = _grid()
    blade = Blade((1.5 * H, -H, -H), (0.0, 4 * H, 0.0), (0.0, 0.0, 1.5 * H))

    def final(gape):
        model = td.Model(
            grid, stiffness=20.0, damping=0.02, mass=1e-3, fixed=grid.face("bottom"), dtype=F64, device=device
        )
        cut(model, model.X, blade)  # a partial cut: the body stays one piece
        nodes = torch.zeros(grid.shape, dtype=torch.bool)  # on the CPU: pretension takes any device
        nodes[1:3] = True
        model.rest_length = pretension(model, nodes, gape)
        return _simulate(model)

    gape = torch.tensor(0.1, dtype=F64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(final, (gape,), eps=1e-6, atol=1e-8)
    assert float(torch.autograd.grad(final(gape).sum(), gape)[0].abs()) > 0


def test_gradcheck_through_a_coagulated_shape():
    grid = _grid()
    region = torch.zeros(grid.shape, dtype=torch.bool)
    region[2:] = True
    a, b = ends(grid, region)

    def final(xc):
        model = td.Model(grid, stiffness=20.0, damping=0.02, mass=1e-3, fixed=grid.face("bottom"), dtype=F64)
        x = model.X.clone()
        x[:, :, 2:] = xc
        model.rest_length = coagulated_rest_length(model, x, a & b)
        return _simulate(model)

    gen = torch.Generator().manual_seed(0)
    x0 = td.Model(grid, stiffness=1.0, mass=1.0, dtype=F64).X[:, :, 2:]
    xc = (x0 + 0.1 * H * torch.randn(x0.shape, generator=gen, dtype=F64)).requires_grad_()
    assert torch.autograd.gradcheck(final, (xc,), eps=1e-7, atol=1e-7)
