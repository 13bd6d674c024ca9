"""Label volumes to bodies (torchdeform.anatomy.labels).

Oracles: a brute-force per-node look-up (each node's rest position mapped through the inverse
affine, in numpy, one node at a time); the analytic volume of a ball; the series combination of
two moduli, 2 E1 E2 / (E1 + E2); the geometry of cells and their corners.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform.anatomy import Image, body_from_labels
from torchdeform.anatomy.frame import resample_image


def _rotation(axis, angle) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _oblique_affine() -> np.ndarray:
    """Anisotropic voxels (0.8 x 1.1 x 2.5 mm), a rotated direction matrix with one axis flipped."""
    R = _rotation((1.0, 2.0, 0.5), 0.7) @ np.diag([1.0, -1.0, 1.0])
    A = np.eye(4)
    A[:3, :3] = R * np.array([0.0008, 0.0011, 0.0025])
    A[:3, 3] = (0.031, -0.12, 0.4)
    return A


def _blob_labels(shape=(40, 34, 18), seed=0) -> np.ndarray:
    """Two overlapping ellipsoids (labels 1 and 2) and a slab of label 3 in a background of 0."""
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape], indexing="ij")
    lab = np.zeros(shape, np.int16)
    lab[((i - 20) / 14) ** 2 + ((j - 17) / 12) ** 2 + ((k - 9) / 6) ** 2 < 1] = 1
    lab[((i - 24) / 5) ** 2 + ((j - 15) / 6) ** 2 + ((k - 9) / 3) ** 2 < 1] = 2
    lab[(j < 6) & (i > 10) & (i < 30)] = 3
    return lab


def test_each_node_takes_the_label_of_the_voxel_holding_it_under_an_oblique_flipped_affine():
    lab = _blob_labels()
    A = _oblique_affine()
    img = Image(lab, A, "oblique.nii.gz")
    body = body_from_labels(img, 0.003, tissues={1: "liver", 2: 5.0}, fixed=[3])
    X = body.grid.rest_positions()[0].permute(1, 2, 3, 0).reshape(-1, 3).double().numpy()
    inv = np.linalg.inv(A)
    expected = np.empty(len(X), np.int64)
    for n, p in enumerate(X):  # brute force, one node at a time
        q = inv[:3, :3] @ p + inv[:3, 3]
        r = np.round(q).astype(int)
        inside = all(0 <= r[a] < lab.shape[a] for a in range(3))
        expected[n] = lab[tuple(r)] if inside else 0
    got = body.labels.reshape(-1).numpy()
    assert np.array_equal(got, expected)
    # every body node is a corner of a cell with tissue; fixed nodes are the label-3 nodes of the body
    assert bool((body.fixed == ((body.labels == 3) & body.grid.nodes())).all())
    assert set(np.unique(got[body.grid.nodes().reshape(-1).numpy()])) <= {0, 1, 2, 3}


def test_fill_and_node_fractions_measure_the_volume_of_a_ball():
    n, r = 48, 17.0  # voxels of 0.5 mm; a ball of 8.5 mm
    i, j, k = np.meshgrid(*[np.arange(n, dtype=np.float64)] * 3, indexing="ij")
    lab = ((i - 23.5) ** 2 + (j - 23.5) ** 2 + (k - 23.5) ** 2 < r**2).astype(np.uint8)
    A = np.diag([0.0005, 0.0005, 0.0005, 1.0])
    h = 0.002
    body = body_from_labels(Image(lab, A, "ball.npy"), h, tissues={1: {"youngs_modulus": 3e3, "density": 1000.0}})
    ball = 4 / 3 * math.pi * (r * 0.0005) ** 3
    voxels = lab.sum() * 0.0005**3  # the voxelised ball: what the samples see
    assert float(body.cell_fill.sum()) * h**3 == pytest.approx(voxels, rel=0.02)
    assert float(body.fraction.sum()) * h**3 == pytest.approx(voxels, rel=0.02)
    assert voxels == pytest.approx(ball, rel=0.02)
    # min_fraction 0: the mass is the tissue's, density x volume
    body0 = body_from_labels(Image(lab, A, "ball.npy"), h, tissues={1: {"youngs_modulus": 3e3}}, min_fraction=0.0)
    assert float(body0.mass.sum()) == pytest.approx(1000.0 * voxels, rel=0.02)
    assert float(body.fraction.min()) >= 0 and float(body.fraction.max()) <= 1


def test_a_cell_across_two_labels_takes_their_moduli_in_series():
    # voxels of 1 mm (centres at 0, 1, ... mm), lattice of 4 mm; label 1 below x = 11.5 mm (a node plane)
    # in the first body, below x = 12.5 mm (a quarter into a cell) in the second
    E1, E2 = 2e3, 8e3
    tissues = {1: {"youngs_modulus": E1}, 2: {"youngs_modulus": E2}}
    A = np.diag([0.001, 0.001, 0.001, 1.0])
    for first, share in ((12, None), (13, 0.25)):
        lab = np.ones((24, 12, 12), np.uint8)
        lab[first:] = 2
        body = body_from_labels(Image(lab, A, "layers.npy"), 0.004, tissues=tissues, samples=8)
        E = body.youngs_modulus[body.cell_fill == 1.0]
        mixed = E[(E > E1 * 1.001) & (E < E2 * 0.999)]
        assert float(E.min()) == pytest.approx(E1) and float(E.max()) == pytest.approx(E2)
        if share is None:
            assert len(mixed) == 0  # the interface on a node plane: every cell is one tissue
        else:  # a quarter E1, three quarters E2, in series
            assert len(mixed) > 0
            assert torch.allclose(mixed, torch.tensor(1 / (share / E1 + (1 - share) / E2), dtype=torch.float64))
    half = body_from_labels(
        Image(np.where(np.arange(24)[:, None, None] < 14, 1, 2) * np.ones((24, 12, 12), np.uint8), A, "h"),
        0.004,
        tissues=tissues,
        samples=8,
    )
    E = half.youngs_modulus[half.cell_fill == 1.0]
    assert bool(torch.isclose(E, torch.tensor(2 * E1 * E2 / (E1 + E2), dtype=torch.float64)).any())  # halves in series


def test_points_to_cover_get_all_eight_corners_in_the_body():
    lab = _blob_labels()
    A = _oblique_affine()
    img = Image(lab, A, "oblique.nii.gz")
    rng = np.random.default_rng(3)
    centres = np.argwhere(lab == 1)[rng.choice(int((lab == 1).sum()), 200)] + rng.uniform(-0.5, 0.5, (200, 3))
    pts = centres @ A[:3, :3].T + A[:3, 3]
    body = body_from_labels(img, 0.004, tissues={1: "liver", 2: "liver"}, fixed=[3], cover=pts)
    q = (pts - np.asarray(body.grid.origin)) / 0.004
    c = np.floor(q).astype(int)
    nodes = body.grid.nodes().numpy()
    for a, b, e in np.ndindex(2, 2, 2):
        assert nodes[c[:, 0] + a, c[:, 1] + b, c[:, 2] + e].all()


def test_the_model_of_a_label_body_is_at_rest_unloaded_and_its_fixed_nodes_stay_under_gravity():
    lab = _blob_labels()
    body = body_from_labels(Image(lab, _oblique_affine(), "blob"), 0.004, tissues={1: "liver", 2: "liver"}, fixed=[3])
    model = body.model(dtype=torch.float64, gravity=(0.0, 9.81, 0.0))
    state = model.rest_state()
    f = body.model(dtype=torch.float64).forces(state.x, state.v)
    assert float(f.abs().max()) < 1e-12  # no load, no stress at rest
    integ = td.SymplecticEuler()
    for _ in range(20):
        state = integ.step(model, state, 2e-5)
    moved = (state.x - model.rest_state().x).norm(dim=1)[0]
    assert float(moved[body.fixed].max()) == 0.0 and float(moved[body.grid.nodes() & ~body.fixed].max()) > 0
    assert float(model.mass.sum()) == pytest.approx(float(body.mass.sum()), rel=1e-12)


def test_a_label_without_a_tissue_names_the_file_and_the_label():
    lab = _blob_labels()
    with pytest.raises(td.ConfigError, match=r"oblique.nii.gz: label 2 has none"):
        body_from_labels(Image(lab, _oblique_affine(), "oblique.nii.gz"), 0.004, tissues={1: "liver"}, fixed=[3])


def test_a_body_that_would_not_fit_in_memory_is_refused_before_it_is_built():
    lab = _blob_labels()
    with pytest.raises(td.ConfigError, match=r"fits in memory"):
        body_from_labels(
            Image(lab, _oblique_affine(), "oblique.nii.gz"), 1e-6, tissues={1: "liver", 2: "liver", 3: "fat"}
        )


def test_a_ct_resampled_onto_the_lattice_axes_matches_the_voxel_it_falls_in():
    rng = np.random.default_rng(0)
    ct = rng.normal(0, 100, (30, 26, 14)).astype(np.float32)
    A = _oblique_affine()
    img = Image(ct, A, "ct.nii.gz")
    # points exactly at voxel centres: the resampled value is the voxel's own
    idx = np.array([[3, 4, 5], [20, 10, 7], [15, 20, 2]])
    for ijk in idx:
        p = A[:3, :3] @ ijk + A[:3, 3]
        v = resample_image(img, origin=tuple(p), spacing=(0.001,) * 3, shape=(1, 1, 1))
        assert float(v) == pytest.approx(float(ct[tuple(ijk)]), abs=1e-3)
