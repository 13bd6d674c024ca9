"""Trajectory planning: runs of labels along a path, clearance from structures to avoid, a fly-through.

Oracles (independent of the module's sampling, bisection and k-d tree):

* runs: the analytic crossings of a straight line with the voxel faces between slabs of labels
  (a slab ``w0 <= w < w1`` of voxel centres has its faces at ``w0 - 1/2`` and ``w1 - 1/2``), in mm
  along the path for anisotropic voxels;
* clearance: the analytic distance from a sphere's centre to the segment minus its radius (mm),
  within one voxel diagonal above it for the voxelised sphere (never below), and a brute-force minimum over every
  voxel centre of the sphere of the closed-form point-to-segment distance (written here);
* densities: a linear ramp, which trilinear interpolation reproduces exactly;
* the fly-through: files on disk, frames that differ, the first frame equal to a rendering from
  the entry.
"""

from __future__ import annotations

import json
import math
from itertools import pairwise

import numpy as np
import pytest
import torch

from torchdeform.errors import ConfigError
from torchdeform.volume.planning import Trajectory, check_trajectory, fly_through

SPACING = (0.7, 1.3, 0.9)  # mm per voxel along (D, H, W): anisotropic


def slabs(shape=(24, 20, 40)):
    """Labels 1, 2, 3 in slabs along W: voxel centres w < 12, 12 <= w < 26, w >= 26."""
    lab = np.ones(shape, np.uint8)
    lab[:, :, 12:26] = 2
    lab[:, :, 26:] = 3
    return lab


def sphere(lab, centre, radius_mm, label, spacing=SPACING):
    """Sets ``label`` on the voxels whose centre is within ``radius_mm`` of ``centre`` (voxels) in mm."""
    idx = np.indices(lab.shape).reshape(3, -1).T
    inside = np.linalg.norm((idx - np.asarray(centre)) * np.asarray(spacing), axis=1) <= radius_mm
    lab.reshape(-1)[inside] = label
    return inside.reshape(lab.shape)


def seg_dist_mm(c, a, b, spacing=SPACING):
    """Closed-form distance (mm) from points c (K, 3) to the segment a-b (voxels), all scaled by spacing."""
    sp = np.asarray(spacing)
    c, a, b = np.atleast_2d(c) * sp, np.asarray(a) * sp, np.asarray(b) * sp
    ab = b - a
    t = np.clip((c - a) @ ab / (ab @ ab), 0, 1)
    return np.linalg.norm(c - a - t[:, None] * ab, axis=1)


# ------------------------------------------------------------------ trajectory


def test_trajectory_geometry():
    path = Trajectory((1.0, 2.0, 3.0), (4.0, 6.0, 3.0))
    assert path.length == 5.0
    assert path.direction.tolist() == [0.6, 0.8, 0.0]
    assert torch.allclose(path.at(0.0), path.entry) and torch.allclose(path.at(1.0), path.target)
    assert torch.allclose(
        path.at(torch.tensor([0.2, 0.6])), torch.tensor([[1.6, 2.8, 3.0], [2.8, 4.4, 3.0]], dtype=torch.float64)
    )
    pts = path.points(spacing=0.3)
    gaps = pts.diff(dim=0).norm(dim=1)
    assert len(pts) == math.ceil(5 / 0.3) + 1 and float(gaps.max()) <= 0.3 + 1e-12
    assert path.length_mm(spacing=SPACING) == pytest.approx(math.hypot(3 * 0.7, 4 * 1.3))


def test_polyline_geometry():
    path = Trajectory.from_points([(0, 0, 0), (0, 0, 6), (0, 8, 6)])
    assert path.length == 14.0 and not path.straight
    assert path.at(3 / 14).tolist() == [0.0, 0.0, 3.0]
    assert path.at(10 / 14).tolist() == [0.0, 4.0, 6.0]
    assert path.tangent(0.9).tolist() == [0.0, 1.0, 0.0]
    pts = path.points(spacing=1.0)
    assert [0.0, 0.0, 6.0] in pts.tolist() and len(pts) == 15  # every vertex, once
    assert Trajectory.from_points(np.array([(0, 0, 0), (1, 1, 1)])).straight


@pytest.mark.parametrize(
    "make, key",
    [
        (lambda: Trajectory.from_points([(1.0, 2.0, 3.0)]), "trajectory.points"),
        (lambda: Trajectory.from_points([]), "trajectory.points"),
        (lambda: Trajectory((1.0, 2.0, 3.0), (1.0, 2.0, 3.0)), "trajectory.target"),
        (lambda: Trajectory((1.0, math.nan, 3.0), (1.0, 2.0, 3.0)), "trajectory.entry"),
        (lambda: Trajectory((1.0, 2.0, 3.0), (1.0, 2.0, math.inf)), "trajectory.target"),
        (lambda: Trajectory((1.0, 2.0), (1.0, 2.0, 3.0)), "trajectory.entry"),
        (lambda: Trajectory.from_points([(0, 0, 0), (0, 0, 0), (1, 1, 1)]), "trajectory.points[1]"),
        (lambda: Trajectory.from_points([(0, 0, 0), (np.nan, 0, 0)]), "trajectory.points[1]"),
        (lambda: Trajectory((0, 0, 0), (1, 1, 1)).at(1.5), "s"),
        (lambda: Trajectory((0, 0, 0), (1, 1, 1)).points(spacing=0), "spacing"),
        (lambda: check_trajectory(slabs(), [(1, 1, 1)]), "trajectory.points"),
        (lambda: check_trajectory(slabs(), Trajectory((0, 0, 0), (1, 1, 1)), spacing=(1, -1, 1)), "spacing"),
        (lambda: check_trajectory(slabs(), Trajectory((0, 0, 0), (1, 1, 1)), step=math.nan), "step"),
        (lambda: check_trajectory(slabs(), Trajectory((0, 0, 0), (1, 1, 1)), min_distance=-1), "min_distance"),
        (lambda: check_trajectory(slabs(), Trajectory((0, 0, 0), (1, 1, 1)), avoid="vessel"), "avoid"),
        (lambda: check_trajectory(np.zeros((4, 4)), Trajectory((0, 0, 0), (1, 1, 1))), "volume"),
        (lambda: check_trajectory(np.zeros((4, 4, 4)), Trajectory((0, 0, 0), (1, 1, 1)), avoid=1), "avoid"),
    ],
)
def test_bad_inputs_are_one_line_config_errors(make, key):
    with pytest.raises(ConfigError) as info:
        make()
    assert info.value.key == key
    assert "\n" not in str(info.value) and str(info.value).startswith(f"{key}: expected")


# ------------------------------------------------------------------ runs


@pytest.mark.parametrize("step", [0.25, 1.0, 3.0])
def test_runs_cross_slab_faces_where_the_line_does(step):
    lab = slabs()
    entry, target = np.array([2.3, 3.1, 0.4]), np.array([20.6, 17.2, 38.9])
    names = {1: "fat", 2: "liver", 3: "tumour"}
    rep = check_trajectory(lab, Trajectory(entry, target), spacing=SPACING, names=names, step=step)
    length_mm = float(np.linalg.norm((target - entry) * SPACING))
    faces = [11.5, 25.5]  # between voxel centres 11|12 and 25|26
    cross = [(w - entry[2]) / (target[2] - entry[2]) * length_mm for w in faces]
    assert [r.label for r in rep.runs] == [1, 2, 3]
    assert [r.name for r in rep.runs] == ["fat", "liver", "tumour"]
    expected = [(0.0, cross[0]), (cross[0], cross[1]), (cross[1], length_mm)]
    got = [(r.entry_mm, r.exit_mm) for r in rep.runs]
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose([r.length_mm for r in rep.runs], np.diff([0.0, *cross, length_mm]), atol=1e-5)
    assert rep.length_mm == pytest.approx(length_mm) and rep.ok and rep.clearances == []


def test_runs_outside_the_volume_and_on_a_polyline():
    lab = slabs()
    # from outside (w = -5.5) through the three slabs, then a bend along +D that leaves the volume
    path = Trajectory.from_points([(5.0, 5.0, -5.5), (5.0, 5.0, 30.0), (30.0, 5.0, 30.0)])
    sp = (2.0, 1.0, 0.5)
    rep = check_trajectory(lab, path, spacing=sp)
    assert [r.label for r in rep.runs] == [None, 1, 2, 3, None]
    assert rep.runs[0].name == "outside"
    # faces: w = -0.5, 11.5, 25.5 (0.5 mm per voxel along W), then d = 23.5 (2 mm per voxel) on the bend
    ends = [r.exit_mm for r in rep.runs]
    expected = [5.0 * 0.5, 17.0 * 0.5, 31.0 * 0.5, 35.5 * 0.5 + (23.5 - 5.0) * 2.0, 35.5 * 0.5 + 25.0 * 2.0]
    np.testing.assert_allclose(ends, expected, atol=1e-5)


def test_density_profile_is_trilinear():
    d, h, w = np.indices((10, 12, 14), dtype=np.float64)
    vol = 2.0 * d - 0.5 * h + 0.25 * w + 3.0  # linear: trilinear interpolation is exact
    path = Trajectory((1.2, 2.7, 0.3), (8.4, 9.1, 12.9))
    rep = check_trajectory(vol, path, spacing=SPACING)
    dist, val = rep.profile
    assert rep.kind == "density" and rep.runs == []
    pts = path.at(torch.from_numpy(dist / rep.length_mm)).numpy()
    np.testing.assert_allclose(val, pts @ [2.0, -0.5, 0.25] + 3.0, atol=1e-9)
    json.dumps(rep.to_dict())
    assert rep.lines()[1].startswith("density along the path: min")


# ------------------------------------------------------------------ clearance


@pytest.mark.parametrize("seed", range(4))
def test_clearance_from_a_sphere(seed):
    rng = np.random.default_rng(seed)
    lab = slabs()
    centre, radius = np.array([12.0, 9.5, 20.0]) + rng.uniform(-1, 1, 3), 5.5  # mm
    sphere(lab, centre, radius, 4)
    entry = np.array([2.0, 1.0, 1.0]) + rng.uniform(0, 2, 3)
    target = np.array([22.0, 3.0, 38.0]) + rng.uniform(-2, 0, 3)
    rep = check_trajectory(lab, Trajectory(entry, target), spacing=SPACING, avoid=[4], names={4: "vessel"})
    (c,) = rep.clearances
    analytic = float(seg_dist_mm(centre, entry, target)[0]) - radius
    assert analytic > 1.0  # the path misses the sphere
    # every point of the ball shrunk by half a voxel diagonal rho has a voxel centre within rho, inside
    # the ball: the nearest centre inside is at most 2 rho (one voxel diagonal) farther than the sphere
    diagonal = float(np.linalg.norm(SPACING))
    assert analytic - 1e-9 <= c.distance_mm <= analytic + diagonal
    brute = float(seg_dist_mm(np.argwhere(lab == 4), entry, target).min())
    assert c.distance_mm == pytest.approx(brute, abs=1e-9)
    assert not c.crossed and c.present and c.name == "vessel"
    # the reported closest point and voxel are where that distance is
    assert float(np.linalg.norm((np.array(c.point) - np.array(c.voxel)) * SPACING)) == pytest.approx(c.distance_mm)
    assert float(seg_dist_mm(c.point, entry, target)[0]) < 1e-9
    assert c.at_mm == pytest.approx(float(np.linalg.norm((np.array(c.point) - entry) * SPACING)))
    # ok against the required distance
    assert check_trajectory(lab, Trajectory(entry, target), spacing=SPACING, avoid=4, min_distance=brute - 0.01).ok
    bad = check_trajectory(lab, Trajectory(entry, target), spacing=SPACING, avoid=4, min_distance=brute + 0.01)
    assert not bad.ok and len(bad.problems) == 1 and "less than" in bad.problems[0]


def test_clearance_exact_for_a_single_voxel_near_a_coarse_sampling():
    lab = np.zeros((30, 30, 30), np.uint8)
    lab[15, 16, 15] = 5  # one voxel, 1 voxel off the line's sample points' gaps
    entry, target = (15.0, 15.0, 0.0), (15.0, 15.0, 29.0)
    for step in (0.25, 4.0, 29.0):  # even one segment sampled at its ends only
        rep = check_trajectory(lab, Trajectory(entry, target), spacing=SPACING, avoid=[5], step=step)
        assert rep.clearances[0].distance_mm == pytest.approx(1.3)  # one voxel along H
        assert rep.clearances[0].voxel == (15, 16, 15)


def test_crossing_an_avoided_label_is_not_ok():
    lab = slabs()
    sphere(lab, (12.0, 10.0, 20.0), 4.0, 4)
    path = Trajectory((12.0, 10.0, 0.0), (12.0, 10.0, 39.0))  # through the sphere's centre
    rep = check_trajectory(lab, path, spacing=SPACING, avoid=[4, 9], names={4: "vessel"})
    c, absent = rep.clearances
    assert c.crossed and c.distance_mm == 0.0 and not rep.ok
    vessel = [r for r in rep.runs if r.label == 4]
    assert len(vessel) == 1
    # the sphere's voxel centres along W at d=12, h=10: |w - 20| * 0.9 <= 4 -> w in 16..24, faces 15.5, 24.5
    assert vessel[0].entry_mm == pytest.approx(15.5 * 0.9, abs=1e-5)
    assert vessel[0].exit_mm == pytest.approx(24.5 * 0.9, abs=1e-5)
    assert c.at_mm == pytest.approx(15.5 * 0.9, abs=1e-5)
    assert not absent.present and math.isinf(absent.distance_mm)
    assert rep.problems == ["crosses vessel from 13.950 mm"]
    d = rep.to_dict()
    assert json.loads(json.dumps(d, allow_nan=False))["clearances"][1]["distance_mm"] is None
    text = "\n".join(rep.lines())
    assert "NOT ok" in text and "vessel" in text and "CROSSED" in text and "label 9: not in the volume" in text


def test_image_from_the_anatomy_package_gives_spacing_in_mm():
    from torchdeform.anatomy import Image

    lab = slabs()
    image = Image(lab, np.diag([*(s * 1e-3 for s in SPACING), 1.0]), "slabs")
    path = Trajectory((2.0, 2.0, 0.0), (2.0, 2.0, 39.0))
    rep = check_trajectory(image, path)
    assert rep.spacing == pytest.approx(SPACING)
    assert rep.runs[0].exit_mm == pytest.approx(11.5 * 0.9, abs=1e-5)


# ------------------------------------------------------------------ fly-through


def test_fly_through_writes_frames_that_move(tmp_path):
    from PIL import Image as PILImage

    from torchdeform.volume.endoscope import EndoscopeCamera
    from torchdeform.volume.images import to_image
    from torchdeform.volume.interior import render_endoscope

    # a tube along W with a bright ring pattern on its wall, a cap at the far end
    d, h, w = np.indices((16, 16, 24), dtype=np.float32)
    r = np.hypot(d - 7.5, h - 7.5)
    vol = np.where(r > 5.0, 1.0 + 0.5 * (w // 3 % 2), 0.0).astype(np.float32)
    vol[:, :, 21:] = 1.0
    vol = torch.from_numpy(vol)
    path = Trajectory((7.5, 7.5, 1.0), (7.5, 7.5, 20.0))
    frames = fly_through(vol, path, frames=4, size=(32, 32), standoff=2.0, out=tmp_path, fps=5, progress=False)
    assert len(frames) == 4 and all(f.shape == (32, 32, 3) and f.dtype == np.uint8 for f in frames)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["fly_through.gif", "frame_000.png", "frame_001.png", "frame_002.png", "frame_003.png"]
    np.testing.assert_array_equal(np.asarray(PILImage.open(tmp_path / "frame_002.png").convert("RGB")), frames[2])
    with PILImage.open(tmp_path / "fly_through.gif") as gif:
        assert gif.n_frames == 4
    assert all(not np.array_equal(a, b) for a, b in pairwise(frames))
    first = EndoscopeCamera(
        position=(7.5, 7.5, 1.0), direction=(0.0, 0.0, 1.0), up=(1.0, 0.0, 0.0), fov=100.0, size=(32, 32)
    )
    with torch.no_grad():
        np.testing.assert_array_equal(frames[0], to_image(render_endoscope(vol, first)))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("step", [0.25, 3.0])
def test_clearance_is_exact_for_scattered_voxels(seed, step):
    """Many small structures, coarse samples: still the brute-force minimum over every voxel centre."""
    rng = np.random.default_rng(seed)
    lab = np.zeros((20, 22, 24), np.int32)
    idx = rng.integers(0, lab.shape, size=(60, 3))
    lab[idx[:, 0], idx[:, 1], idx[:, 2]] = 7
    checked = 0
    for _ in range(20):
        pts = rng.uniform(-2, np.array(lab.shape) + 1, size=(3, 3))
        path = Trajectory.from_points(pts)
        c = check_trajectory(lab, path, spacing=SPACING, avoid=7, step=step).clearances[0]
        if c.crossed:
            continue
        brute = min(float(seg_dist_mm(np.argwhere(lab == 7), a, b).min()) for a, b in pairwise(pts))
        assert c.distance_mm == pytest.approx(brute, abs=1e-9)
        checked += 1
    assert checked >= 5
