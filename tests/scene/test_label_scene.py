"""Scenes of label volumes: ``[grid] labels`` with ``[[tissues]]`` (torchdeform.scene.anatomy).

Oracles: the same body built through the API (:func:`torchdeform.anatomy.body_from_labels`) from
the array and affine the file was written with; the tissue library's own values; the errors'
contract (one line naming the file, the line and the key; exit status 2 from the command line).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform.anatomy import Image, body_from_labels, write_nifti


def _labels() -> np.ndarray:
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in (24, 20, 16)], indexing="ij")
    lab = np.zeros((24, 20, 16), np.uint8)
    lab[((i - 12) / 10) ** 2 + ((j - 10) / 8) ** 2 + ((k - 8) / 6) ** 2 < 1] = 1
    lab[((i - 14) / 3) ** 2 + ((j - 10) / 3) ** 2 + ((k - 8) / 3) ** 2 < 1] = 2
    lab[:, 17:, :] = np.where(lab[:, 17:, :] == 0, 3, lab[:, 17:, :])
    return lab


AFFINE = np.array([[0.0, 0.0, 0.0015, 0.01], [0.0, -0.001, 0.0, 0.02], [0.001, 0.0, 0.0, -0.03], [0, 0, 0, 1.0]])

SCENE = """
[grid]
labels = "labels.nii.gz"
spacing = 0.003

[[tissues]]
label = 1
tissue = "liver"

[[tissues]]
label = 2
youngs_modulus = 2.0e4
poisson_ratio = 0.45
density = 1100.0

[[tissues]]
label = 3
fixed = true

[boundary]
gravity = [0.0, 9.81, 0.0]

[integrator]
name = "symplectic"
dt = 2e-5
steps = 20
"""


@pytest.fixture
def scene_dir(tmp_path):
    write_nifti(tmp_path / "labels.nii.gz", _labels(), AFFINE)
    (tmp_path / "liver.toml").write_text(SCENE)
    return tmp_path


def test_a_label_scene_builds_the_body_the_api_builds_and_runs(scene_dir, tmp_path):
    scene = td.scene.load_scene(scene_dir / "liver.toml")
    tissues = {1: "liver", 2: {"youngs_modulus": 2e4, "poisson_ratio": 0.45, "density": 1100.0}}
    body = body_from_labels(Image(_labels(), AFFINE, "labels.nii.gz"), 0.003, tissues=tissues, fixed=[3])
    assert scene.grid.shape == body.grid.shape and scene.grid.origin == pytest.approx(body.grid.origin, abs=1e-12)
    assert torch.equal(scene.grid.nodes(), body.grid.nodes())
    model = scene.build()
    ref = body.model(dtype=model.dtype)
    assert torch.allclose(model.stiffness, ref.stiffness)
    assert torch.allclose(model.mass, ref.mass)
    liver = td.fuzzy.presets.tissue_properties(["liver"])[0]
    tau = liver["viscosity"] / liver["youngs_modulus"]  # Kelvin-Voigt damping of the library tissue
    only_liver = (body.labels == 1) & scene.grid.nodes()
    c, k = model.damping[0], model.stiffness[0]
    inner = only_liver & (body.fraction == 1)
    ratio = (c / k.clamp_min(1e-30))[:, inner][k[:, inner] > 0]
    assert float(ratio.min()) > 0 and float(ratio.max()) <= tau * (1 + 1e-6)
    td.scene.run_scene(scene, tmp_path / "run", progress=False)
    traj = np.load(tmp_path / "run" / "trajectory.npz")
    x, X = traj["x"][-1], traj["X"]
    moved = np.linalg.norm(x - X, axis=0)
    assert np.isfinite(x).all() and moved[body.fixed.numpy()].max() == 0 and moved.max() > 0
    sag = (x - X)[1][scene.grid.nodes().numpy() & ~body.fixed.numpy()]  # gravity along +y (posterior)
    assert sag.mean() > 0


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: s.replace("label = 3\nfixed = true", "label = 4\nfixed = true"), r"grid.labels.*label 3 has none"),
        (lambda s: s.replace('tissue = "liver"', 'tissue = "granite"'), r"tissues\[0\]\.tissue"),
        (lambda s: s + "\n[mass]\ndensity = 1000.0\n", r"\[mass\] with \[grid\] labels"),
        (lambda s: s.replace("spacing = 0.003", "spacing = 0.003\nshape = [4, 4, 4]"), r"grid.shape"),
        (lambda s: s.replace('labels = "labels.nii.gz"', 'labels = "missing.nii.gz"'), r"missing.nii.gz"),
        (lambda s: s.replace("spacing = 0.003", "spacing = 1e-6"), r"fits in memory"),
        (lambda s: s + '\n[volume]\nfile = "phantom"\n', r"grid.labels: expected \"phantom\" with \[volume\]"),
    ],
    ids=[
        "label-without-tissue",
        "unknown-tissue",
        "mass-section",
        "shape-and-labels",
        "missing-file",
        "too-large",
        "phantom-ct-of-other-labels",
    ],
)
def test_bad_label_scenes_name_file_line_and_key(scene_dir, edit, message):
    path = scene_dir / "liver.toml"
    path.write_text(edit(SCENE))
    with pytest.raises(td.ConfigError, match=message) as e:
        td.scene.load_scene(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_the_command_line_refuses_a_bad_label_scene_with_status_2_and_writes_nothing(scene_dir):
    path = scene_dir / "liver.toml"
    path.write_text(SCENE.replace("label = 3\nfixed = true", "label = 4\nfixed = true"))
    out = scene_dir / "run"
    p = subprocess.run(
        [sys.executable, "-m", "torchdeform", "run", str(path), "--out", str(out), "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2, p.stderr
    assert "label 3 has none" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_embedded_surfaces_are_written_per_frame_and_follow_the_lattice(scene_dir, tmp_path):
    """Oracle: scipy's trilinear interpolation of the recorded node positions at each rest vertex
    (RegularGridInterpolator over the lattice's rest coordinates) gives the written vertices."""
    import trimesh
    from scipy.interpolate import RegularGridInterpolator

    path = scene_dir / "liver.toml"
    path.write_text(SCENE + '\n[output]\nrecord_every = 10\nsurfaces = "embedded"\nsurface_format = "glb"\n')
    scene = td.scene.load_scene(path)
    assert set(scene.embedded) == {"label1", "label2", "label3"}
    summary = td.scene.run_scene(scene, tmp_path / "run", progress=False)
    info = summary["embedded_surfaces"]
    traj = np.load(tmp_path / "run" / "trajectory.npz")
    assert info["frames"] == len(traj["t"]) == 3
    g = scene.grid
    axes = [g.origin[a] + g.spacing[a] * np.arange(g.shape[a]) for a in range(3)]
    for i in (0, 2):
        glb = trimesh.load(tmp_path / "run" / "surfaces" / f"frame_{i:04d}.glb")
        for name, (rest, faces) in scene.embedded.items():
            mesh = glb.geometry[name]
            expected = np.stack(
                [
                    RegularGridInterpolator(axes, traj["x"][i][c], bounds_error=False, fill_value=None)(rest)
                    for c in range(3)
                ],
                1,
            )
            assert len(mesh.faces) == len(faces) <= 10_000
            assert np.abs(mesh.vertices - expected).max() < 1e-6  # float32 files
            if i == 0:
                assert np.abs(mesh.vertices - rest).max() < 1e-6  # at rest: the surface itself


def test_embedded_surfaces_need_a_body_of_labels(tmp_path):
    path = tmp_path / "box.toml"
    path.write_text(
        "[grid]\nshape = [4, 4, 4]\nspacing = 0.01\n[material]\nstiffness = 10.0\n[mass]\ndensity = 1000.0\n"
        '[integrator]\ndt = 1e-4\nsteps = 2\n[output]\nsurfaces = "embedded"\n'
    )
    with pytest.raises(td.ConfigError, match=r"box.toml:\d+: output.surfaces: .*\[grid\] labels"):
        td.scene.load_scene(path)


def test_a_phantom_scene_has_its_ct_on_the_lattice_box(tmp_path):
    """Oracle: the phantom's stated values (liver 60 HU, air -1000 HU): the CT resampled onto the
    lattice's box reads about 60 HU at the rest positions of the nodes inside the liver."""
    path = tmp_path / "phantom.toml"
    path.write_text(
        '[grid]\nlabels = "phantom:0.004"\nspacing = 0.008\n'
        '[[tissues]]\nlabel = 1\ntissue = "liver"\n[[tissues]]\nlabel = 2\ntissue = "liver"\n'
        '[[tissues]]\nlabel = 4\ntissue = "liver"\n[[tissues]]\nlabel = 3\nfixed = true\n'
        "[[tissues]]\nlabel = 5\nbackground = true\n"
        '[integrator]\ndt = 1e-4\nsteps = 2\n[volume]\nfile = "phantom"\n'
    )
    scene = td.scene.load_scene(path)
    vol = scene.volume["file"]
    g = scene.grid
    assert isinstance(vol, np.ndarray) and vol.ndim == 3 and max(vol.shape) <= 160
    # the volume fills the lattice's box: node (i, j, k) sits at voxel i (n_v - 1) / (n - 1) along each axis
    from torchdeform.anatomy.phantom import abdominal_phantom

    labels = abdominal_phantom(voxel=0.004)[0]
    body = body_from_labels(labels, 0.008, tissues={1: "liver", 2: "liver", 4: "liver"}, fixed=[3], background=[0, 5])
    inside = torch.nonzero((body.labels == 1) & (body.fraction == 1) & g.nodes())
    assert len(inside) > 20
    scale = [(vol.shape[a] - 1) / (g.shape[a] - 1) for a in range(3)]
    hu = [vol[tuple(round(int(n[a]) * scale[a]) for a in range(3))] for n in inside]
    assert 40 < float(np.median(hu)) < 80
