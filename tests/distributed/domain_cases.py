"""The domain-decomposition cases of ``test_domain.py``: models built the same way by the test (one
process) and by each rank of a ``torchrun`` launch of this file.

    python -m torch.distributed.run --standalone --nproc-per-node 2 tests/distributed/domain_cases.py OUT_DIR CASE...

writes ``OUT_DIR/<case>.npz`` (float64 records, final state, communication figures) from rank 0.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

import torchdeform as td
from torchdeform.topology import Blade

SHAPE = (7, 4, 5)  # 3 ranks: slabs of 3, 2 and 2 rows
H = 0.01
DT = 2e-4
STEPS = 50
RECORD_EVERY = 5  # 11 frames
CUT_AT = 25 * DT


#: case -> neighbours
CASES = {
    "symplectic6": 6,
    "rk4_26": 26,
    "verlet26_law_mask": 26,
    "implicit6": 6,
    "implicit26": 26,
    "implicit26_elastic": 26,  # an Elastic body: the volume term's cells span the slab boundaries
}


def build(name: str):
    """``(model, integrator, cuts)`` of case ``name`` (float64)."""
    topology = CASES[name]
    mask = None
    law, home = None, None
    if name == "verlet26_law_mask":
        mask = torch.ones(SHAPE, dtype=torch.bool)
        mask[3:5, 0, 0] = False  # a notch across a slab boundary
        law, home = "exponential", 5.0
    grid = td.Grid(SHAPE, spacing=H, topology=topology, node_mask=mask)
    side = torch.zeros(SHAPE, dtype=torch.bool)
    side[1:, :, -1] = True  # the far w face, over every slab, dragged sideways
    drag = td.Drag(side, path=[(0.0, (0.0, 0.0, 0.0)), (STEPS * DT, (0.0, 0.0, 0.004))])
    stiffness = {6: 400.0, 26: 200.0}[topology]
    if name == "implicit26_elastic":  # axis springs of about 100 N/m inside, a stiff volume term
        stiffness = td.Elastic(2e4, 0.45)
    model = td.Model(
        grid,
        stiffness=stiffness,
        damping=0.2,
        density=1000.0,
        gravity=(-9.81, 0.0, 0.0),
        fixed=grid.face("bottom"),
        drags=[drag],
        law=law,
        home=home,
        dtype=torch.float64,
    )
    # half way through, a blade between layers h = 1 and 2 cuts the lower half of w through every slab
    blade = Blade((-0.005, 0.015, -0.005), (0.08, 0.0, 0.0), (0.0, 0.0, 0.025))
    integrator = {
        "symplectic6": td.SymplecticEuler(),
        "rk4_26": td.RK4(),
        "verlet26_law_mask": td.DampedVerlet(),
        # a fixed count of CG iterations: no residual norm to reduce over ranks each iteration
        "implicit6": td.ImplicitEuler(cg_iters=16, cg_tol=0.0),
        "implicit26": td.ImplicitEuler(cg_iters=16, cg_tol=0.0),
        "implicit26_elastic": td.ImplicitEuler(cg_iters=16, cg_tol=0.0),
    }[name]
    return model, integrator, [(CUT_AT, blade)]


def start(model):
    """A start state with some motion, so every term is exercised from the first step."""
    s = model.rest_state()
    g = torch.Generator().manual_seed(0)
    x = s.x + 1e-4 * torch.randn(s.x.shape, generator=g, dtype=s.x.dtype) * (
        model.free if model.free is not None else 1
    )
    return td.State(x, s.v, t=0.0)


def main(out: Path, names: list) -> None:
    import torch.distributed as dist

    from torchdeform.distributed.domain import decomposed_simulate

    dist.init_process_group("gloo")
    torch.set_num_threads(1)
    try:
        for name in names:
            model, integrator, cuts = build(name)
            run = decomposed_simulate(
                model, start(model), DT, STEPS, integrator=integrator, record_every=RECORD_EVERY, cuts=cuts
            )
            if dist.get_rank() == 0:
                cells = {}
                if run.whole.volume is not None:  # an Elastic body: its cells and springs, gathered
                    cells = {
                        "kappa": run.whole.volume[0].numpy(),
                        "mu_cells": run.whole.mu_cells.numpy(),
                        "stiffness": run.whole.stiffness.numpy(),
                    }
                np.savez(
                    out / f"{name}.npz",
                    **cells,
                    x=run.record["x"].numpy(),
                    v=run.record["v"].numpy(),
                    t=run.record["t"].numpy(),
                    exchanges=run.model.halo.exchanges,
                    bytes=run.model.halo.bytes,
                    wall_s=run.wall_s,
                    comm_s=run.comm_s,
                )
    finally:
        dist.barrier()
        dist.destroy_process_group()


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2:])
