"""Embedded surfaces in scenes: the user's meshes (``[[surfaces]]``) and the cuts that cut them (``[[cuts]]``).

Oracles, each independent of the code under test:

- the input mesh itself: at rest, frame 0 holds its vertices times ``scale`` (float32 files, so
  the mesh lies within 16 mm of the origin: 1e-9 m);
- ``scipy.interpolate.RegularGridInterpolator`` (trilinear) of the recorded node positions at the
  rest vertices, for every written frame;
- the blade's plane and parallelogram: no written triangle has corners on both sides of it with a
  point of its trace strictly inside the blade (sampled along the trace);
- ``scipy.sparse.csgraph.connected_components`` for the pieces of each written frame;
- the errors' contract: one line naming the scene file, the line, the key and the mesh file; exit
  status 2 from the command line, nothing written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from torchdeform import cli
from torchdeform.errors import ConfigError
from torchdeform.scene import load_scene, run_scene

RADIUS_MM = 9.0


@pytest.fixture
def ball_dir(tmp_path) -> Path:
    """A folder with ``ball.stl``: an icosphere of radius 9 mm about the origin, in millimetres."""
    trimesh.creation.icosphere(3, radius=RADIUS_MM).export(tmp_path / "ball.stl")
    return tmp_path


def stl(folder: Path) -> trimesh.Trimesh:
    """``ball.stl`` as trimesh reads it (an STL stores three corners per triangle: trimesh merges them)."""
    return trimesh.load(folder / "ball.stl", force="mesh")


def box_body(*, gravity="0.0", extra="") -> str:
    """A 35 x 25 x 25 mm box of springs about the origin (8 x 6 x 6 nodes, 5 mm apart), fixed at the bottom."""
    return f"""
[grid]
shape = [8, 6, 6]
spacing = 0.005
origin = [-0.0175, -0.0125, -0.0125]

[material]
stiffness = 50.0

[mass]
density = 1000.0

[boundary]
fixed = "bottom"
gravity = [{gravity}, 0.0, 0.0]
{extra}
[[surfaces]]
file = "ball.stl"
scale = 0.001
"""


def run_part(*, steps=30, dt=1e-3, record_every=10, extra="") -> str:
    return f"""
[integrator]
name = "implicit"
dt = {dt}
steps = {steps}
dtype = "float64"

[output]
record_every = {record_every}
surfaces = "embedded"
surface_format = "ply"
{extra}"""


def write(folder: Path, text: str, name: str = "scene.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def frame(out: Path, i: int) -> trimesh.Trimesh:
    """Written frame ``i`` as stored (no merging of the vertices a cut split)."""
    return trimesh.load(out / "surfaces" / f"frame_{i:04d}.ply", process=False)


def components(faces: np.ndarray, n: int) -> np.ndarray:
    """Piece label ``(n,)`` of every vertex (vertices joined by the triangles' edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)[1]


def straddling(v: np.ndarray, faces: np.ndarray, origin, u, w, *, tol=1e-8, margin=1e-3) -> int:
    """Triangles with corners more than ``tol`` on both sides of the plane of the parallelogram
    ``origin + a u + b w`` whose trace on it has a sampled point inside (``a, b`` in ``(margin, 1 - margin)``)."""
    o, u, w = (np.asarray(a, dtype=np.float64) for a in (origin, u, w))
    n = np.cross(u, w)
    n /= np.linalg.norm(n)
    h = (v - o) @ n
    G = np.linalg.inv(np.array([[u @ u, u @ w], [u @ w, w @ w]]))
    count = 0
    for f in faces:
        hf = h[f]
        if not (hf.max() > tol and hf.min() < -tol):
            continue
        ends = [
            v[f[i]] + hf[i] / (hf[i] - hf[j]) * (v[f[j]] - v[f[i]])
            for i, j in ((0, 1), (1, 2), (2, 0))
            if (hf[i] > tol and hf[j] < -tol) or (hf[i] < -tol and hf[j] > tol)
        ] + [v[f[i]] for i in range(3) if abs(hf[i]) <= tol]
        pts = ends[0] + np.linspace(0, 1, 32)[:, None] * (ends[1] - ends[0])
        ab = (pts - o) @ np.stack([u, w], 1) @ G
        count += bool(((ab > margin) & (ab < 1 - margin)).all(1).any())
    return count


# ------------------------------------------------------------------ a user's mesh, embedded
def test_a_user_stl_is_written_at_rest_and_follows_the_trilinear_map_of_the_lattice(ball_dir):
    from scipy.interpolate import RegularGridInterpolator

    path = write(ball_dir, box_body(gravity="-9.81") + run_part(steps=20))
    scene = load_scene(path)
    assert list(scene.embedded) == ["ball"]
    summary = run_scene(scene, ball_dir / "out", progress=False)
    info = summary["embedded_surfaces"]
    assert info["surfaces"] == {"ball": {"vertices": 642, "triangles": 1280}} and "cut_at_s" not in info
    rest = stl(ball_dir).vertices * 1e-3
    traj = np.load(ball_dir / "out" / "trajectory.npz")
    assert info["frames"] == len(traj["t"]) == 3
    first = frame(ball_dir / "out", 0)
    assert np.abs(first.vertices - rest).max() < 1e-9  # at rest: the input, times scale
    g = scene.grid
    axes = [g.origin[a] + g.spacing[a] * np.arange(g.shape[a]) for a in range(3)]
    for i in range(3):
        lattice = [RegularGridInterpolator(axes, traj["x"][i][c].astype(np.float64)) for c in range(3)]
        want = np.stack([f(rest) for f in lattice], 1)
        assert np.abs(frame(ball_dir / "out", i).vertices - want).max() < 1e-8
    sag = frame(ball_dir / "out", 2).vertices[:, 0] - rest[:, 0]
    assert sag.min() < -1e-4  # the run moved it (gravity along -D)


def test_a_mesh_body_grows_to_cover_its_own_surface(ball_dir):
    """The voxelised ball leaves out the cells its surface crosses; with [[surfaces]] it takes them."""
    from torchdeform.mesh import grid_from_mesh

    text = (
        box_body()
        .replace(
            "shape = [8, 6, 6]\nspacing = 0.005\norigin = [-0.0175, -0.0125, -0.0125]",
            'mesh = "ball.stl"\nscale = 0.001\nspacing = 0.003\npadding = 1',
        )
        .replace('fixed = "bottom"\n', "")
    )
    scene = load_scene(write(ball_dir, text + run_part(steps=2)))
    plain = grid_from_mesh(ball_dir / "ball.stl", 0.003, padding=1, scale=0.001)
    assert scene.grid.shape == plain.shape and scene.grid.num_nodes > plain.num_nodes
    assert bool((scene.grid.nodes() | ~plain.nodes()).all())  # it only grows
    assert list(scene.embedded) == ["ball"]


BAD = {
    "missing file": (
        lambda t: t.replace('file = "ball.stl"', 'file = "nothere.stl"'),
        "surfaces[0].file",
        r"expected an existing mesh file, got '.*nothere\.stl \(not found\)'",
        'file = "nothere.stl"',
    ),
    "outside the lattice": (
        lambda t: t.replace("scale = 0.001\n", ""),
        "surfaces[0].file",
        r"expected a mesh within one spacing of the body's lattice .*scale = 0\.001\), got 'ball\.stl: 642 of 642 vertices",
        'file = "ball.stl"',
    ),
    "open mesh": (
        lambda t: t.replace('file = "ball.stl"', 'file = "open.stl"'),
        "surfaces[0].file",
        r"closed \(watertight\).*open\.stl",
        'file = "open.stl"',
    ),
    "bad scale": (
        lambda t: t.replace("scale = 0.001", "scale = -1.0"),
        "surfaces[0].scale",
        "a positive number",
        "scale = -1.0",
    ),
    "unknown key": (
        lambda t: t.replace("scale = 0.001", "scale = 0.001\ncolour = 3"),
        "surfaces[0].colour",
        "one of the keys file, scale, name",
        "colour = 3",
    ),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_surfaces_are_one_line_naming_the_file_and_key_exit_2(case, ball_dir, capsys):
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    trimesh.Trimesh(box.vertices, box.faces[:-2]).export(ball_dir / "open.stl")
    edit, key, expected, needle = BAD[case]
    text = edit(box_body() + run_part(steps=2))
    path = write(ball_dir, text, "bad.toml")
    line = text[: text.index(needle)].count("\n") + 1
    with pytest.raises(ConfigError, match=expected) as e:
        load_scene(path)
    assert str(e.value).startswith(f"{path}:{line}: {key}: ") and "\n" not in str(e.value)
    rc = cli.main(argv=["run", str(path), "--out", str(ball_dir / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith(f"torchdeform: {path}:{line}: {key}: "), err
    assert not (ball_dir / "out").exists()


def test_embedded_output_needs_labels_or_surfaces(ball_dir):
    text = box_body().split("[[surfaces]]")[0] + run_part(steps=2)
    with pytest.raises(ConfigError, match=r"output.surfaces: .*\[grid\] labels\) or \[\[surfaces\]\]"):
        load_scene(write(ball_dir, text))


# ------------------------------------------------------------------ cuts through the surfaces
# a blade between node layers (d = 0.7 mm; nodes at -2.5 and +2.5 mm) wider than the body, at t = 0;
# the top is then pulled 4 mm up: the upper half of the body, cut off, follows it
PLANE_D = 0.0007
CUT = """
[[drags]]
face = "top"
path = [[0.0, [0.0, 0.0, 0.0]], [0.02, [0.004, 0.0, 0.0]]]

[[cuts]]
origin = [0.0007, -0.02, -0.02]
u = [0.0, 0.04, 0.0]
v = [0.0, 0.0, 0.04]
"""


def test_a_planar_cut_through_a_scene_cuts_the_embedded_surface_and_the_sides_separate(ball_dir):
    path = write(ball_dir, box_body(extra=CUT) + run_part())
    out = ball_dir / "out"
    summary = run_scene(load_scene(path), out, progress=False)
    info = summary["embedded_surfaces"]
    assert info["cut_at_s"] == [0.0] and info["frames"] == 4
    gaps = []
    for i in range(4):
        mesh = frame(out, i)
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        label = components(f, len(v))
        assert len(np.unique(label[np.unique(f)])) == 2  # two pieces in every frame, the cut one included
        top = label == label[np.argmax(v[:, 0])]
        if i == 0:  # at rest: each piece is one side of the blade, and no triangle straddles it
            assert v[top, 0].min() >= PLANE_D - 1e-9 and v[~top, 0].max() <= PLANE_D + 1e-9
            assert straddling(v, f, (PLANE_D, -0.02, -0.02), (0.0, 0.04, 0.0), (0.0, 0.0, 0.04), tol=1e-9) == 0
        gaps.append(v[top, 0].min() - v[~top, 0].max())
    assert abs(gaps[0]) < 1e-9 and gaps[1] > 0.001 and gaps[-1] > 0.003  # the sides move apart


# a scalpel: its edge through the whole depth (D) at w = 1.3 mm (between node layers), drawn along H
# from outside the body to 3 mm past the ball's centre: it cuts part of the ball
SCALPEL = """
[[tools]]
name = "scalpel"
shape = "sphere"
radius = 0.001
contact = "none"
path = [[0.0, [0.0, -0.02, 0.0013]], [0.02, [0.0, 0.003, 0.0013]]]

[[cuts]]
tool = "scalpel"
edge = [[-0.02, 0.0, 0.0], [0.02, 0.0, 0.0]]
stop = 0.02
"""


def test_a_scalpel_cuts_part_of_the_embedded_surface_frame_by_frame(ball_dir):
    path = write(ball_dir, box_body(extra=SCALPEL) + run_part(steps=40, dt=5e-4, extra=""))
    out = ball_dir / "out"
    summary = run_scene(load_scene(path), out, progress=False)
    info = summary["embedded_surfaces"]
    assert len(info["cut_at_s"]) >= 2 and info["frames"] == 5  # the sweep reaches the surfaces frame by frame
    faces = [len(frame(out, i).faces) for i in range(5)]
    assert faces[0] == 1280 and faces == sorted(faces) and faces[-1] > 1280
    last = frame(out, 4)
    v, f = np.asarray(last.vertices), np.asarray(last.faces)
    assert len(np.unique(components(f, len(v))[np.unique(f)])) == 1  # a partial cut: one piece
    # nothing moves the body: the swept parallelogram at rest splits every triangle it crosses
    assert straddling(v, f, (-0.02, -0.02, 0.0013), (0.04, 0.0, 0.0), (0.0, 0.023, 0.0)) == 0
    ball = stl(ball_dir)
    beyond = ball.vertices[ball.faces][:, :, 1].min(1) > 3.5
    assert {tuple(t) for t in ball.faces[beyond].tolist()} <= {tuple(t) for t in f.tolist()}  # past its end: unchanged
    assert (
        json.loads((out / "summary.json").read_text())["embedded_surfaces"]["after_cuts"]["ball"]["triangles"]
        == faces[-1]
    )


def test_the_animation_shows_each_frame_its_own_cut_surfaces(tmp_path):
    """``animate`` takes the surfaces as a function of the frame: the cut run's frames show the cut ones."""
    import torch

    import torchdeform as td
    from torchdeform.mesh import EmbeddedSurface
    from torchdeform.scene.animation import animate

    grid = td.Grid((8, 6, 6), spacing=0.005, origin=(-0.0175, -0.0125, -0.0125))
    ball = trimesh.creation.icosphere(2, radius=0.009)
    whole = EmbeddedSurface(ball.vertices, ball.faces, grid)
    cut = whole.cut_patches([((PLANE_D, -0.02, -0.02), (0.0, 0.04, 0.0), (0.0, 0.0, 0.04), False)])
    X = grid.rest_positions()[0]
    apart = X.clone()
    apart[0] = torch.where(X[0] > PLANE_D, X[0] + 0.003, X[0])
    asked = []

    def surfaces(i):
        asked.append(i)
        return [whole] if i == 0 else [cut]

    info = animate(
        grid,
        np.array([0.0, 0.01]),
        torch.stack([X, apart]),
        tmp_path / "a.gif",
        surfaces=surfaces,
        texture={"exemplar": "liver:16", "block": 8, "seams": "none"},
        size=64,
        frames=2,
    )
    assert info["frames"] == 2 and asked == [0, 1]


def test_a_body_of_labels_covers_the_users_surfaces_and_names_one_outside(tmp_path):
    """A block of label 1 (16 x 14 x 12 voxels of 1 mm about the origin) and a ball inside it: the body
    covers the ball's cells; a ball 0.5 m away is refused, naming its file and key."""
    from torchdeform.anatomy import write_nifti

    labels = np.zeros((20, 18, 16), np.uint8)
    labels[2:18, 2:16, 2:14] = 1
    affine = np.diag([0.001, 0.001, 0.001, 1.0])
    affine[:3, 3] = -0.0095, -0.0085, -0.0075
    write_nifti(tmp_path / "labels.nii.gz", labels, affine)
    trimesh.creation.icosphere(2, radius=5.0).export(tmp_path / "ball.stl")
    trimesh.creation.icosphere(2, radius=5.0).apply_translation([500.0, 0, 0]).export(tmp_path / "far.stl")
    text = """
[grid]
labels = "labels.nii.gz"
spacing = 0.003

[[tissues]]
label = 1
tissue = "liver"

[integrator]
dt = 1e-5
steps = 2

[[surfaces]]
file = "ball.stl"
scale = 0.001
"""
    scene = load_scene(write(tmp_path, text))
    assert list(scene.embedded) == ["ball"]
    path = write(tmp_path, text.replace("ball.stl", "far.stl"), "far.toml")
    with pytest.raises(ConfigError, match=r"surfaces\[0\]\.file: expected meshes inside the box .*got 'far\.stl: "):
        load_scene(path)
