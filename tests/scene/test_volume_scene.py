"""Scenes with a ``[volume]`` section: the volume is warped and rendered before and after."""

import pytest

from torchdeform.errors import ConfigError


def test_scene_with_volume_writes_renders(tmp_path):
    from torchdeform.scene import load_scene, run_scene

    text = """
[grid]
shape = [3, 3, 3]
spacing = 0.01
topology = 6
[material]
stiffness = 10.0
[mass]
mass = 0.001
[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]
[integrator]
name = "symplectic"
dt = "auto"
steps = 20
[volume]
file = "phantom:16"
mode = "mip"
"""
    (tmp_path / "s.toml").write_text(text)
    summary = run_scene(load_scene(tmp_path / "s.toml"), tmp_path / "out", progress=False)
    assert summary["volume"]["shape"] == [16, 16, 16]
    for name in ("volume_before.png", "volume_after.png", "volume_deformed.npy"):
        assert (tmp_path / "out" / name).is_file()
    (tmp_path / "bad.toml").write_text(text.replace('mode = "mip"', 'mode = "xray"'))
    with pytest.raises(ConfigError, match=r"bad\.toml:\d+: volume\.mode"):
        load_scene(tmp_path / "bad.toml")
