"""The animated demo: frames, panels, motion against the projected nodes, the force caption, the scene hooks."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

import torchdeform as td
from torchdeform import cli
from torchdeform.scene.animation import animate, drag_forces, frame_indices

SHAPE, SPACING, K = (5, 5, 5), 0.002, 2.0


def gif_frames(path):
    """The GIF's frames as RGB uint8 arrays ``(h, w, 3)``."""
    with Image.open(path) as im:
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(np.asarray(im.convert("RGB")))
    return out


def dragged_run(steps=60, every=20):
    """A small float64 body, base fixed, its top centre node dragged 1.5 mm along +W; recorded frames."""
    grid = td.Grid(SHAPE, spacing=SPACING, topology=26)
    top = grid.index_mask([(4, 2, 2)])
    model = td.Model(
        grid,
        stiffness=K,
        density=1000.0,
        fixed=grid.face("bottom"),
        gravity=(-9.81, 0.0, 0.0),
        drags=[td.Drag(top, path=[(0.0, (0.0, 0.0, 0.0)), (0.01, (0.0, 0.0, 0.0015))])],
        decay=50.0,
        dtype=torch.float64,
    )
    _, rec = td.simulate(model, model.rest_state(), 1e-4, steps, record_every=every, warn=False)
    return model, rec["t"].numpy(), rec["x"][:, 0], rec["v"][:, 0]


def project(points, eye, target, fov_deg, size):
    """Pinhole projection, written out here: axis D up, row 0 at the top (the rasteriser's stated formula)."""
    eye, target = np.asarray(eye), np.asarray(target)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    c = (np.asarray(points) - eye) @ np.stack([right, up, fwd]).T
    f = (size / 2) / math.tan(math.radians(fov_deg) / 2)
    return np.stack([size / 2 + f * c[:, 0] / c[:, 2], size / 2 - f * c[:, 1] / c[:, 2]], 1)


def test_frames_panels_and_motion_follow_the_projected_nodes(tmp_path):
    model, t, x, _ = dragged_run(steps=120, every=20)
    # the whole body moved 2 mm along +W on top of the run, so the silhouette shift is large and known
    shift = torch.zeros_like(x)
    shift[:, 2] = torch.linspace(0, 0.002, len(x), dtype=x.dtype).view(-1, 1, 1, 1)
    x = x + shift
    info = animate(
        model.grid,
        t,
        x,
        tmp_path / "a.gif",
        volume="phantom:16",
        frames=4,
        size=320,
        texture={"exemplar": "liver:16", "block": 8},
    )
    frames = gif_frames(tmp_path / "a.gif")
    assert len(frames) == info["frames"] == 4 and info["indices"] == [0, 2, 4, 6]
    h, w, _ = frames[0].shape
    assert w == 2 * 320 and h >= 320 and info["size"] == [h, w]  # two panels of 320 x 320 at least
    first, last = frames[0].astype(int), frames[-1].astype(int)
    assert np.abs(first[:320, :320] - last[:320, :320]).max() > 50  # the surface moved
    assert np.abs(first[:320, 320:] - last[:320, 320:]).max() > 30  # the volume deformed
    assert np.abs(first[320:] - last[320:]).max() > 100  # the caption changed

    def body(frame):  # non-white pixels of the surface
        panel = frame[24:320, :320].astype(int)  # below the title
        rows, cols = np.nonzero((panel < 235).any(2))
        return np.array([cols.mean() + 0.5, rows.mean() + 24.5]), len(rows)

    cam = info["camera"]
    (c0, n0), (c1, n1) = body(frames[0]), body(frames[-1])
    assert n0 > 0.05 * 320 * 296 and n1 > 0.05 * 320 * 296
    nodes = [x[i].reshape(3, -1).T.numpy() for i in (0, info["indices"][-1])]
    p0, p1 = (project(n, cam.eye, cam.target, cam.fov_deg, 320).mean(0) for n in nodes)
    moved, expected = c1 - c0, p1 - p0
    assert np.linalg.norm(expected) > 10  # pixels
    cos = moved @ expected / (np.linalg.norm(moved) * np.linalg.norm(expected))
    assert cos > 0.95 and 0.7 < np.linalg.norm(moved) / np.linalg.norm(expected) < 1.3, (moved, expected)


def oracle_drag_force(x, node, mass, gravity):
    """Force on a node to hold it: minus its springs' pull (a loop over the 26 neighbours) minus its weight."""
    i, j, k = node
    F = np.zeros(3)
    for off in itertools.product((-1, 0, 1), repeat=3):
        n = (i + off[0], j + off[1], k + off[2])
        if off == (0, 0, 0) or not all(0 <= a < s for a, s in zip(n, SHAPE)):
            continue
        d = x[:, n[0], n[1], n[2]] - x[:, i, j, k]
        length = np.linalg.norm(d)
        F += K * (length - SPACING * np.linalg.norm(off)) * d / length
    return -(F + mass * np.asarray(gravity))


def test_drag_force_and_caption_match_a_neighbour_loop(tmp_path):
    model, t, x, v = dragged_run()
    forces = drag_forces(model, x, torch.zeros_like(v), t)  # no damping: v does not matter
    mass = float(model.mass.expand(1, 1, *SHAPE)[0, 0, 4, 2, 2])
    oracle = np.stack([oracle_drag_force(xi.numpy(), (4, 2, 2), mass, (-9.81, 0, 0)) for xi in x])
    np.testing.assert_allclose(forces, oracle, rtol=1e-9, atol=1e-12)
    assert oracle[-1, 2] > 1e-3  # the drag pulls along its path (+W), against the springs
    info = animate(
        model.grid,
        t,
        x,
        tmp_path / "a.gif",
        volume=torch.rand(8, 8, 8) * 1000,
        size=64,
        texture={"exemplar": "liver:16", "block": 8},
        forces={"drag": forces},
    )
    assert info["captions"] == [
        f"t = {ti:.3f} s   drag {np.linalg.norm(f) * 1e3:.2f} mN"
        if np.linalg.norm(f) >= 1e-3
        else f"t = {ti:.3f} s   drag {np.linalg.norm(f) * 1e6:.1f} uN"
        for ti, f in zip(t, oracle)
    ]


def test_frame_indices_spread_evenly():
    assert frame_indices(101, 48)[:3] == [0, 2, 4] and frame_indices(101, 48)[-1] == 100
    assert len(frame_indices(101, 48)) == 48 and frame_indices(4, 48) == [0, 1, 2, 3]


SCENE = """
[grid]
shape = [4, 3, 4]
spacing = 0.01
topology = 26

[material]
stiffness = 20.0

[mass]
density = 1000.0

[boundary]
fixed = "bottom"
gravity = [-9.81, 0.0, 0.0]

[[drags]]
nodes = [[3, 1, 2]]
path = [[0.0, [0.0, 0.0, 0.0]], [0.004, [0.002, 0.0, 0.0]]]

[integrator]
name = "symplectic"
dt = 2e-4
steps = 20
threads = 1

[output]
record_every = 10
"""


def write(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


def test_output_animation_true_writes_animation_gif(tmp_path):
    path = write(tmp_path, SCENE + "animation = true\n")
    summary = td.run_scene(td.load_scene(path), tmp_path / "out", progress=False)
    frames = gif_frames(tmp_path / "out" / "animation.gif")
    assert len(frames) == 3 == summary["animation"]["frames"]  # 20 steps, a frame every 10
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["animation"]["file"] == "animation.gif"


def test_cli_animation_flag(tmp_path, capsys):
    path = write(tmp_path, SCENE)
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "plain"), "--quiet"]) == 0
    assert not (tmp_path / "plain" / "animation.gif").exists()
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "anim"), "--quiet", "--animation"]) == 0
    assert "animation.gif" in capsys.readouterr().out
    assert len(gif_frames(tmp_path / "anim" / "animation.gif")) == 3


@pytest.mark.parametrize("value", ['"yes"', "1"])
def test_bad_animation_value_is_one_line_exit_2(tmp_path, capsys, value):
    path = write(tmp_path, SCENE + f"animation = {value}\n")
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "output.animation" in err[0] and "scene.toml:" in err[0], err


def test_demo_writes_demo_gif(tmp_path, monkeypatch):
    import torchdeform.scene.commands as scene_mod

    def short_demo():
        scene = td.demo_scene()
        scene.steps, scene.record_every = 20, 10
        scene.image_size = 160  # the wiring, not the pictures
        # 8 x fewer texture voxels to synthesise and blend (the 3-D seam blend was most of the test)
        scene.texture = dict(scene.texture, voxel=2 * scene.texture["voxel"])
        return scene

    monkeypatch.setattr(scene_mod, "demo_scene", short_demo)
    assert cli.main(argv=["demo", "--out", str(tmp_path), "--quiet"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["name"] == "demo" and summary["steps"] == 20 and summary["animation"]["file"] == "demo.gif"
    assert summary["embedded_surfaces"]["surfaces"]["label1"]["triangles"] > 1000  # the liver's smooth surface
    with Image.open(tmp_path / "demo.gif") as im:
        assert im.n_frames == 3 and im.size[0] == 2 * 160 and im.size[1] >= 160  # two panels: it has a volume


def test_without_a_volume_one_panel_shows_the_body_and_the_tool_where_it_is(tmp_path):
    """Oracle: the tool's projected centre (the camera's own projection of its position at that
    frame) lies inside the grey pixels drawn for it; a scene without a volume has one panel."""
    from torchdeform.interact import Sphere, Tool

    model, t, x, _ = dragged_run(steps=40, every=20)
    centre = x[-1].reshape(3, -1).mean(1).double()
    top = float(x[-1][0].max())
    tool = Tool(Sphere(0.002), position=(top + 0.002, float(centre[1]), float(centre[2])), name="probe")
    info = animate(model.grid, t, x, tmp_path / "a.gif", frames=2, size=200, tools=[tool])
    frame = gif_frames(tmp_path / "a.gif")[-1]
    assert frame.shape[1] == 200  # one panel
    cam = info["camera"]
    u, v = project(
        np.array([[top + 0.002, float(centre[1]), float(centre[2])]]), cam.eye, cam.target, cam.fov_deg, 200
    )[0]
    r, g, b = (int(c) for c in frame[int(v), int(u)])
    assert abs(r - g) < 25 and abs(g - b) < 30 and b >= r - 5 and 60 < r < 250  # steel grey, not tissue red
