"""ChainMail scenes (``model = "chainmail"``): a run that follows its drag and keeps the limits, and a bad
option reported with file and line."""

import numpy as np
import pytest

import torchdeform as td
from torchdeform.errors import ConfigError

SCENE = """\
model = "chainmail"

[grid]
shape = [10, 8, 8]
spacing = 0.001

[chainmail]
method = "enhanced"
compression = 0.8
stretch = 1.2
shear = 0.2
frames = 6
relax_steps = 2

[boundary]
fixed = "bottom"

[[drags]]
nodes = [[9, 4, 4]]
path = [[0.0, [0.0, 0.0, 0.0]], [1.0, [0.0015, 0.001, 0.0]]]
"""


def test_chainmail_scene_runs(tmp_path):
    path = tmp_path / "pull.toml"
    path.write_text(SCENE)
    scene = td.load_scene(path)
    summary = td.run_scene(scene, tmp_path / "out", progress=False)
    data = np.load(tmp_path / "out" / "trajectory.npz")
    assert data["x"].shape == (7, 3, 10, 8, 8)
    np.testing.assert_allclose(data["x"][-1][:, 9, 4, 4] - data["X"][:, 9, 4, 4], [0.0015, 0.001, 0.0], atol=1e-9)
    assert summary["max_violation_m"] <= 1e-12 and summary["frames"] == 7 and summary["blocked_frames"] == 0
    assert np.all(data["x"][:, :, 0] == data["X"][None, :, 0])  # the fixed bottom stays
    assert (tmp_path / "out" / "summary.json").is_file() and (tmp_path / "out" / "energy.png").is_file()
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace("shear = 0.2", "shear = -0.2"))
    with pytest.raises(ConfigError, match=r"bad.toml:\d+: chainmail.shear"):
        td.load_scene(bad)
