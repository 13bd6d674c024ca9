"""Work outside the step on a busy machine: the run's outputs on one thread beside a busy process.

Oracle: the thread count torch reports inside the post-processing (a spy on the energy series),
with the machine's load given by a stand-in for :func:`torchdeform.sim.threads.others_busy`; and
the scene's own thread setting restored afterwards.
"""

from __future__ import annotations

import pytest
import torch

import torchdeform.scene.run as run_mod
import torchdeform.sim.threads as threads_mod
from tests.scene.test_scene import TINY, write
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
