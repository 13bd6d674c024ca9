"""``scenes/endoscopy.toml`` and the ``[camera]`` section: what an endoscope riding a tool sees.

Oracles: the same scene without the pressing probe (the control: the view differs only where the
probe deforms the lumen's wall), the endoscope camera rendered by hand at the scope's first pose
through the undeformed volume (the first frame), and the scene's keys refused one line each.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.helpers import cli_call
from torchdeform.scene import load_scene, run_scene
from torchdeform.scene.camera import world_to_voxel

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "endoscopy.toml"


def _frames(path: Path) -> list:
    im = Image.open(path)
    out = []
    for k in range(im.n_frames):
        im.seek(k)
        out.append(np.asarray(im.convert("RGB"), dtype=np.float64))
    return out


def _run(tmp_path: Path, text: str, name: str) -> tuple:
    f = tmp_path / f"{name}.toml"
    f.write_text(text)
    scene = load_scene(f)
    scene.steps = 360  # 0.3 s of the scene's 0.4 s: the probe is 9 mm in
    scene.record_every = 90  # five frames
    summary = run_scene(scene, tmp_path / name, progress=False)
    return summary, tmp_path / name


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("endoscopy")
    text = SCENE.read_text()
    control = re.sub(r"\[\[tools\]\]\s+# a probe.*?\n\n", "", text, flags=re.S)
    assert control != text and 'name = "probe"' not in control
    return _run(tmp, text, "pressed"), _run(tmp, control, "control")


def test_the_endoscope_writes_its_frames_and_sees_the_wall_move(runs, one_thread):
    (summary, out), (_, control_out) = runs
    cam = summary["camera"]
    assert cam["tool"] == "scope" and cam["frames"] == 5 and cam["ms_per_frame"] > 0
    assert {"endoscope.gif", "endoscope.png"} <= {p.name for p in out.iterdir()}
    pressed, control = _frames(out / "endoscope.gif"), _frames(control_out / "endoscope.gif")
    assert len(pressed) == len(control) >= 4
    h, w = pressed[0].shape[:2]
    yy, xx = np.mgrid[:h, :w]
    outside = (yy + 0.5 - h / 2) ** 2 + (xx + 0.5 - w / 2) ** 2 > (min(h, w) / 2 + 1) ** 2
    assert pressed[0][outside].max() == 0  # the round mask
    # before the probe reaches the body the two runs see the same (to the GIF palettes' rounding);
    # at the end the wall has moved in view
    same = np.abs(pressed[0] - control[0]).max(axis=2)
    changed = np.abs(pressed[-1] - control[-1]).max(axis=2)
    assert same.mean() <= 2.0 and (same > 40).mean() <= 0.002
    assert (changed > 40).mean() >= 0.01 and changed.mean() >= 4 * max(same.mean(), 1.0)
    # the last frame as endoscope.png
    last = np.asarray(Image.open(out / "endoscope.png").convert("RGB"), dtype=np.float64)
    assert np.abs(last - pressed[-1]).mean() <= 2  # the GIF's palette rounds


def test_the_first_frame_is_the_camera_at_the_scopes_first_pose(runs, one_thread):
    """The first frame (nothing moved yet) equals render_endoscope by hand at the path's first point,
    looking at its second, through the undeformed phantom (to the GIF's colour rounding)."""
    from torchdeform.volume import EndoscopeCamera, load_volume, render_endoscope, to_image

    (_, out), _ = runs
    scene = load_scene(SCENE)
    vol = torch.from_numpy(load_volume("phantom-lumen:64"))
    grid = scene.grid

    def vox(p):
        return world_to_voxel(p, origin=grid.origin, spacing=grid.spacing, nodes=grid.shape, volume_shape=(64,) * 3)

    a, b = np.array([0.0190, 0.0255, 0.0165]), np.array([0.0199, 0.0248, 0.0189])
    cam = EndoscopeCamera(position=vox(a).tolist(), direction=(vox(b) - vox(a)).tolist(), fov=110.0, size=(160, 160))
    cam.far = 0.025 * float(np.mean(vox(np.ones(3)) - vox(np.zeros(3))))
    with torch.no_grad():
        ref = to_image(render_endoscope(vol, cam, tf="ct-lumen"))
    first = _frames(out / "endoscope.gif")[0]
    assert np.abs(first - np.asarray(ref, dtype=np.float64)).mean() <= 2.0


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("fov = 110.0", "fov = 200.0"), "camera.fov"),
        (('kind = "endoscope"', 'kind = "orbit"'), "camera.kind"),
        (("size = [160, 160]", "size = [160]"), "camera.size"),
        (("far = 0.025", "far = 0.0"), "camera.far"),
        (("[volume]                      # the CT", "[notvolume]                   # the CT"), "notvolume"),
    ],
)
def test_bad_camera_keys_are_one_line_and_exit_status_2(tmp_path, edit, message):
    text = SCENE.read_text()
    assert edit[0] in text
    f = tmp_path / "bad.toml"
    f.write_text(text.replace(*edit))
    status, _, err = cli_call(["run", f, "--out", tmp_path / "o"])
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], err


def test_a_camera_without_a_volume_is_refused(tmp_path):
    from torchdeform.errors import ConfigError

    text = SCENE.read_text()
    text = re.sub(r"\[volume\].*?\n\n", "", text, flags=re.S)
    f = tmp_path / "novolume.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=r"camera\.kind: expected a \[volume\] section"):
        load_scene(f)


def test_summary_json_names_the_outputs(runs):
    (_, out), _ = runs
    doc = json.loads((out / "summary.json").read_text())
    assert doc["camera"]["outputs"] == ["endoscope.gif", "endoscope.png"]


def test_a_camera_on_an_unknown_tool_is_refused():
    from torchdeform.errors import ConfigError
    from torchdeform.interact import Sphere, Tool
    from torchdeform.scene.camera import camera_section
    from torchdeform.scene.reader import Source
    from torchdeform.scene.tools import ToolSet

    tools = ToolSet(tools=[Tool(Sphere(0.001), position=(0.0, 0.0, 0.0), name="scope")])
    data = {"camera": {"tool": "scalpel"}}
    with pytest.raises(ConfigError, match=r"camera\.tool: expected the name of one of the scene's tools \(scope\)"):
        camera_section(Source(path="s.toml", text='[camera]\ntool = "scalpel"\n'), data, tools, has_volume=True)
    assert (
        camera_section(Source(path="s.toml", text=""), {"camera": {"tool": "scope"}}, tools, has_volume=True)["fov"]
        == 100.0
    )


def test_embedded_organ_surfaces_are_drawn_where_the_body_moved_them():
    """An embedded sphere in a translated body: the endoscope sees it where the analytic sphere,
    moved with the body, is (pixels agree but for the silhouette of the triangulation)."""
    import trimesh

    from torchdeform.interact import Sphere as SphereShape
    from torchdeform.interact import Tool
    from torchdeform.mesh.embed import EmbeddedSurface
    from torchdeform.scene.camera import SceneEndoscope, camera_section
    from torchdeform.scene.reader import Source
    from torchdeform.scene.tools import ToolSet
    from torchdeform.sim.grid import Grid
    from torchdeform.volume import Sphere

    grid = Grid((5, 5, 5), spacing=0.01)
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.008)
    centre = np.array([0.02, 0.02, 0.025])
    ball = EmbeddedSurface(ico.vertices + centre, ico.faces, grid, dtype=torch.float64)
    tools = ToolSet(tools=[Tool(SphereShape(0.001), position=(0.02, 0.02, 0.004), name="scope")])
    data = {"camera": {"tool": "scope", "look": [0.0, 0.0, 1.0], "fov": 70.0, "size": [48, 48]}}
    spec = camera_section(Source(path="s.toml", text=""), data, tools, has_volume=True)
    air = np.full((41, 41, 41), -1000.0, dtype=np.float32)
    rig = SceneEndoscope(spec, tools, air, grid=grid, tf="ct-lumen", meshes={"ball": ball})
    X = grid.rest_positions(dtype=torch.float64)
    shift = torch.tensor([0.0, 0.004, 0.0], dtype=torch.float64).view(1, 3, 1, 1, 1)
    img = rig.render(0.0, X + shift, X)
    seen = img.max(axis=2) > 0
    cam = rig.camera(0.0, rig.look(0.0))
    eye, d, valid = cam.rays(air.shape, dtype=torch.float64)
    moved = rig.to_voxel(centre + shift.flatten().numpy())
    t, _ = Sphere(moved.tolist(), 0.008 * rig.voxel_per_m, (1, 1, 1)).hit(eye, d.reshape(3, -1))
    expected = (torch.isfinite(t).view(48, 48) & valid).numpy()
    assert expected.sum() > 200 and (seen == expected).mean() > 0.97, (seen == expected).mean()
    still = rig.render(0.0, X, X).max(axis=2) > 0
    assert (still != seen).sum() > 20  # the body's move moved the organ in view
