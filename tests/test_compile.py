"""Inductor's on-disk graph cache for graphs with a ``while_loop`` (the compiled implicit step).

:func:`torchdeform._compile.loop_cache_options` marks the loop cacheable. Each check runs in fresh
processes on a fresh cache folder: a second process must load what the first one built (a cache
hit, the same numbers), and a graph that differs only inside the loop body must not be served
another graph's code (a miss, its own numbers).
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

import torchdeform as td


def _run(script: str, cache, *args) -> dict:
    """``script`` in a fresh interpreter with inductor's cache in ``cache``; its last stdout line as JSON."""
    env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=str(cache), TORCHDEFORM_CACHE_DIR=str(cache / "kernels"))
    # the CPU's vector instructions as it reports them: on a fresh cache folder inductor would otherwise
    # compile and load a probe library per instruction set in each process (about 10 s of the test,
    # not what it checks; both processes use the same setting, so the cache keys agree)
    env["TORCHINDUCTOR_VEC_ISA_OK"] = "1"
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), *map(str, args)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


SCRIPT = """
    import json, sys
    import torch
    torch.set_num_threads(1)
    from torch._higher_order_ops.while_loop import while_loop
    import torchdeform as td
    from torchdeform._compile import graph_cache_counts, loop_cache_options
    from torchdeform.sim.compiled import CompiledStep

    def counted(fn):
        before = graph_cache_counts()
        out = fn()
        return out, dict(zip(("hits", "misses"), (a - b for a, b in zip(graph_cache_counts(), before))))

    def make(factor):                          # graphs that differ only inside the loop body
        def f(x):
            return while_loop(lambda i, y: i < 5, lambda i, y: (i + 1, y * factor),
                              (torch.zeros((), dtype=torch.int64), x))[1]
        return f

    loops = []
    for factor in map(float, sys.argv[1:]):
        torch._dynamo.reset()
        y, c = counted(lambda: torch.compile(make(factor), fullgraph=True, options=loop_cache_options())(torch.ones(4)))
        loops.append(dict(c, factor=factor, y=y.tolist()))

    grid = td.Grid((3, 4, 5), spacing=0.01, topology=6)
    model = td.Model(grid, stiffness=50.0, damping=0.1, mass=1e-3, gravity=(-9.81, 0, 0),
                     fixed=grid.face("bottom") & grid.nodes(), dtype=torch.float64)
    step = CompiledStep(td.ImplicitEuler(cg_iters=8, cg_tol=0), model, 1e-3)
    out, c = counted(lambda: step.packed.unpack_state(step.step_packed(step.packed.pack_state(model.rest_state()))))
    print(json.dumps({"loops": loops, "step": dict(c, x=out.x.flatten().tolist(), v=out.v.flatten().tolist(),
                                                   compiled=step.compiled)}))
"""


@pytest.mark.slow
def test_a_second_process_loads_the_compiled_implicit_step_and_a_changed_loop_misses(tmp_path):
    """Two processes on one fresh cache: the implicit step's graph (CG iterations in a
    ``while_loop``) built by the first is loaded by the second and steps the same, equal to the
    eager step; two small loops differing only in their body constant each get their own entry."""
    first = _run(SCRIPT, tmp_path, 2.0, 3.0)
    second = _run(SCRIPT, tmp_path, 3.0, 2.0)  # the same graphs, in another order
    for loop in first["loops"]:
        assert (loop["hits"], loop["misses"]) == (0, 1)  # 3.0 is not served 2.0's code
    for loop in first["loops"] + second["loops"]:
        assert loop["y"] == [loop["factor"] ** 5] * 4
    for loop in second["loops"]:
        assert (loop["hits"], loop["misses"]) == (1, 0)
    a, b = first["step"], second["step"]
    assert a["compiled"] and b["compiled"]
    assert (a["hits"], a["misses"]) == (0, 1) and (b["hits"], b["misses"]) == (1, 0)
    assert a["x"] == b["x"] and a["v"] == b["v"]
    grid = td.Grid((3, 4, 5), spacing=0.01, topology=6)
    model = td.Model(
        grid,
        stiffness=50.0,
        damping=0.1,
        mass=1e-3,
        gravity=(-9.81, 0, 0),
        fixed=grid.face("bottom") & grid.nodes(),
        dtype=torch.float64,
    )
    ref = td.ImplicitEuler(cg_iters=8, cg_tol=0).step(model, model.rest_state(), 1e-3)
    x, v = (torch.tensor(a[k], dtype=torch.float64).view_as(ref.x) for k in ("x", "v"))
    assert torch.allclose(x, ref.x, rtol=0, atol=1e-12)
    assert torch.allclose(v, ref.v, rtol=0, atol=1e-9)
    assert float(ref.v.abs().max()) > 1e-3  # gravity moved the body: not a trivial step
