"""Work outside the step on a busy machine: the run's outputs on one thread beside a busy process.

Oracle: the thread count torch reports inside the post-processing (a spy on the energy series),
with the machine's load given by a stand-in for :func:`torchdeform.sim.threads.others_busy`; and
the scene's own thread setting restored afterwards; the same for a run's set-up, with the load of
the last seconds given by a stand-in for :func:`torchdeform.sim.threads.recent_load`. The energy
series in batches against each frame's energy computed alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchdeform.scene.commands as commands_mod
import torchdeform.scene.run as run_mod
import torchdeform.sim.threads as threads_mod
from tests.scene.test_scene import TINY, write
from torchdeform import cli
from torchdeform.scene import load_scene, run_scene


@pytest.mark.parametrize(("busy", "expected"), [(1.0, 1), (0.0, 2)], ids=["busy", "idle"])
def test_outputs_run_on_one_thread_beside_a_busy_process(tmp_path, monkeypatch, busy, expected):
    seen = []
    energy = run_mod.energy_series

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return energy(*args, **kwargs)

    monkeypatch.setattr(threads_mod, "others_busy", lambda seconds=0.2: busy)
    monkeypatch.setattr(run_mod, "energy_series", spy)
    scene = load_scene(write(tmp_path, TINY.replace("steps = 10", "steps = 10\nthreads = 2")))
    before = torch.get_num_threads()
    summary = run_scene(scene, tmp_path / "out", progress=False)
    assert summary["steps"] == 10 and seen and set(seen) == {expected}
    assert torch.get_num_threads() == before  # the caller's setting is back


@pytest.mark.parametrize("nodes_per_call", [1, 3 * 36 + 1, 1 << 16], ids=["frame-by-frame", "uneven", "all"])
def test_energy_series_in_batches_equals_each_frame_alone(tmp_path, nodes_per_call, monkeypatch):
    # oracle: Model.energy of each frame by itself, and |x - X| taken in numpy
    model = load_scene(write(tmp_path, TINY)).build()  # 36 nodes: 3 frames a batch when uneven
    g = torch.Generator().manual_seed(0)
    x = model.X + 1e-4 * torch.randn(7, *model.X.shape[1:], generator=g, dtype=model.dtype)
    v = torch.randn(x.shape, generator=g, dtype=model.dtype)
    threads = []
    energy = type(model).energy

    def spy(self, state):
        threads.append(torch.get_num_threads())
        return energy(self, state)

    monkeypatch.setattr(type(model), "energy", spy)
    with threads_mod.omp_threads(2):
        series = run_mod.energy_series(model, x, v, nodes_per_call=nodes_per_call)
        assert torch.get_num_threads() == 2
    monkeypatch.undo()
    # batches of a body smaller than a call on one thread; a larger body's frames on the caller's threads
    assert set(threads) == {1 if model.grid.num_nodes <= nodes_per_call else 2}
    assert len(threads) == -(-7 // max(1, nodes_per_call // model.grid.num_nodes))
    u = np.linalg.norm((x - model.X).numpy(), axis=1).reshape(7, -1)
    free = ~model.constrained.reshape(-1).numpy()
    for i in range(7):
        alone = model.energy(run_mod.State(x[i : i + 1], v[i : i + 1]))
        for k, val in alone.items():
            assert series[k][i] == pytest.approx(float(val), rel=1e-12, abs=1e-18), k
        assert series["max_displacement"][i] == pytest.approx(u[i].max(), rel=1e-12)
        assert series["max_free_displacement"][i] == pytest.approx(u[i][free].max(), rel=1e-12)


@pytest.mark.parametrize(("load", "expected"), [(1.0, 1), (0.0, 2)], ids=["busy", "idle"])
def test_a_runs_set_up_takes_one_thread_beside_a_busy_process(tmp_path, monkeypatch, load, expected):
    """The command's scene loading and the run's stability bound run on one thread when the load of
    the last seconds (a stand-in for ``recent_load``) says another process keeps a core busy."""
    seen = {}
    bound, read = run_mod.time_step_bound, commands_mod.scene_with_values

    def spy_bound(*args, **kwargs):
        seen["bound"] = torch.get_num_threads()
        return bound(*args, **kwargs)

    def spy_read(*args, **kwargs):
        seen["scene"] = torch.get_num_threads()
        return read(*args, **kwargs)

    monkeypatch.setattr(threads_mod, "recent_load", lambda: load)
    monkeypatch.setattr(run_mod, "time_step_bound", spy_bound)
    monkeypatch.setattr(commands_mod, "scene_with_values", spy_read)
    path = write(tmp_path, TINY)
    with threads_mod.omp_threads(2):
        status = cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
        assert torch.get_num_threads() == 2  # the caller's setting is back
    assert status == 0 and seen == {"scene": expected, "bound": expected}
