"""``torchdeform render --camera endoscope``: one view, a fly-through, a planned path, bad input.

Oracles: the PNG equals :func:`render_endoscope` called by hand with the same camera; the
fly-through's frames are the planner's :func:`fly_through`; the path's runs are the label slabs
crossed at their analytic depths.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from tests.helpers import cli_call
from torchdeform.volume import EndoscopeCamera, load_volume, render_endoscope, to_image


def _cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "torchdeform", "render", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=cwd,
    )


def test_one_view_is_the_renderer_by_hand(tmp_path):
    out = tmp_path / "scope.png"
    r = _cli("phantom-lumen:48", "--camera", "endoscope", "--eye", "15,20,13", "--look", "16,18,17", "--size", 48,
             "--tf", "ct-lumen", "--out", out)  # fmt: skip
    assert r.returncode == 0, r.stderr
    got = np.asarray(Image.open(out).convert("RGB"), dtype=np.float64)
    cam = EndoscopeCamera.look_at((15.0, 20.0, 13.0), (16.0, 18.0, 17.0), size=(48, 48))
    with torch.no_grad():
        ref = to_image(render_endoscope(torch.from_numpy(load_volume("phantom-lumen:48")), cam, tf="ct-lumen"))
    assert np.abs(got - ref).max() <= 1
    assert got[0, 0].max() == 0 and got[24, 24].max() > 0  # the round mask; the lumen's wall in view


def test_a_fly_through_writes_its_frames_and_the_gif(tmp_path):
    out = tmp_path / "fly.gif"
    r = _cli("phantom-lumen:48", "--camera", "endoscope", "--path", "15,20,13;16,19.5,15;16,18.5,17", "--frames", 4,
             "--size", 32, "--tf", "ct-lumen", "--out", out)  # fmt: skip
    assert r.returncode == 0, r.stderr
    frames = sorted((tmp_path / "fly-frames").glob("frame_*.png"))
    assert len(frames) == 4 and Image.open(out).n_frames == 4
    a, b = (np.asarray(Image.open(f).convert("RGB"), dtype=np.float64) for f in (frames[0], frames[-1]))
    assert np.abs(a - b).mean() > 1  # the camera moved


def test_a_planned_path_prints_the_labels_it_crosses(tmp_path):
    labels = np.zeros((20, 20, 40), dtype=np.int16)
    labels[:, :, 10:20] = 1
    labels[:, :, 20:30] = 2
    np.save(tmp_path / "labels.npy", labels)
    vol = tmp_path / "vol.npy"
    np.save(vol, np.where(labels > 0, 40.0, -1000.0).astype(np.float32))
    r = _cli(vol, "--camera", "endoscope", "--eye", "10,10,2", "--look", "10,10,35", "--labels",
             tmp_path / "labels.npy", "--avoid", "2", "--size", 16, "--out", tmp_path / "p.png")  # fmt: skip
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].endswith("NOT ok")  # it crosses the label it must avoid
    runs = [ln.split() for ln in lines if ln.startswith("label ") and ln.split()[1].isdigit()]
    # the slabs W in [9.5, 19.5) and [19.5, 29.5) voxels, entered 7.5 and 17.5 mm after W = 2
    assert [(r[1], float(r[2]), float(r[3])) for r in runs] == [
        ("0", 0.0, 7.5),
        ("1", 7.5, 17.5),
        ("2", 17.5, 27.5),
        ("0", 27.5, 33.0),
    ]
    assert any("CROSSED at 17.500 mm" in ln for ln in lines)


@pytest.mark.parametrize(
    ("args", "key"),
    [
        (("--eye", "400,20,13", "--look", "16,18,17"), "position"),
        (("--eye", "15,20,13", "--look", "16,18,17", "--fov", "180"), "--fov"),
        (("--eye", "15,20,13", "--look", "16,18,17", "--fov", "0"), "--fov"),
        (("--path", "15,20,13"), "--path"),
        (("--eye", "15,20,13"), "--eye"),
        (("--eye", "15,20,13", "--look", "15,20,13"), "trajectory.target"),
    ],
)
def test_bad_input_is_one_line_and_exit_status_2(tmp_path, args, key):
    status, _, err = cli_call(["render", "phantom:16", "--camera", "endoscope", *args, "--out", tmp_path / "x.png"])
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and key in lines[0], err
