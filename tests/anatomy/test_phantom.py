"""The abdominal phantom and ``torchdeform data phantom`` (torchdeform.anatomy.phantom, .commands).

Oracles, none of them the phantom's own code: the label array itself, read with plain numpy
slicing (6-neighbours by shifted slices, depths by walking a voxel column, volumes by counting
voxels times the voxel volume); ``scipy.ndimage`` erosion and dilation for interiors and
contacts; the analytic volume of a 22 mm ball; the nominal HU values written out here (not read
from the module); nibabel and pydicom (through ``read_image``) for the files the command writes;
the command line's contract (exit status, one stderr line, the folder before and after).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from scipy import ndimage

from torchdeform import cli
from torchdeform.anatomy import (
    PHANTOM_BACKGROUND,
    PHANTOM_FIXED,
    PHANTOM_TISSUES,
    Image,
    Tissue,
    abdominal_phantom,
    body_from_labels,
    read_image,
)
from torchdeform.errors import ConfigError
from torchdeform.outputs import STAGING

AIR, LIVER, TUMOUR, BONE, VESSEL, SOFT = range(6)
VOXEL_MM3 = 1.0 * 1.0 * 2.0  # at the default voxel
FACES = ndimage.generate_binary_structure(3, 1)


@pytest.fixture(scope="module")
def phantom() -> tuple[Image, Image]:
    return abdominal_phantom()


def neighbours(a: np.ndarray, fill) -> list[np.ndarray]:
    """The 6 face neighbours of every voxel, by shifted slices of a padded copy."""
    p = np.pad(a, 1, constant_values=fill)
    c = slice(1, -1)
    return [
        p[2:, c, c],
        p[:-2, c, c],
        p[c, 2:, c],
        p[c, :-2, c],
        p[c, c, 2:],
        p[c, c, :-2],
    ]


def mm(image: Image, index) -> np.ndarray:
    return image.positions(np.asarray(index, dtype=float)) * 1e3


# ------------------------------------------------------------------ the grid
def test_grid_is_anisotropic_ct_like_and_centred_and_shared(phantom):
    labels, ct = phantom
    assert labels.shape == ct.shape == (200, 160, 80)
    assert labels.array.dtype == np.uint8 and ct.array.dtype == np.float32
    np.testing.assert_array_equal(labels.affine, ct.affine)
    np.testing.assert_allclose(labels.spacing, [0.001, 0.001, 0.002], rtol=0, atol=1e-15)
    np.testing.assert_allclose(labels.direction, np.eye(3), atol=1e-15)
    centre = labels.positions((np.array(labels.shape) - 1) / 2)
    np.testing.assert_allclose(centre, 0.0, atol=1e-12)  # the patient's centre at the LPS origin
    assert sorted(np.unique(labels.array).tolist()) == [AIR, LIVER, TUMOUR, BONE, VESSEL, SOFT]


# ------------------------------------------------------------------ the anatomy
def test_tumour_lies_inside_the_liver(phantom):
    a = phantom[0].array
    tumour = a == TUMOUR
    for nb in neighbours(a, AIR):
        assert np.isin(nb[tumour], [LIVER, TUMOUR, VESSEL]).all()
    idx = np.argwhere(tumour)
    extent = (idx.max(0) - idx.min(0) + 1) * np.array([1.0, 1.0, 2.0])  # mm
    assert (extent >= 19).all() and (extent <= 25).all(), extent


def test_tumour_is_3_to_5_mm_below_the_anterior_liver_surface(phantom):
    labels, _ = phantom
    a = labels.array
    c = np.round(np.argwhere(a == TUMOUR).mean(0)).astype(int)
    column = a[c[0], : c[1] + 1, c[2]][::-1]  # from the tumour's centre towards -y (anterior)
    n_tumour = int(np.argmax(column != TUMOUR))
    rest = column[n_tumour:]
    n_liver = int(np.argmax(rest != LIVER))
    assert 3 <= n_liver <= 5, column[:40]  # 1 mm voxels along y: the tumour's top depth in mm
    assert 13 <= n_tumour + n_liver <= 17  # the centre's depth (mm)
    assert rest[n_liver] == SOFT and (rest[n_liver:] != LIVER).all()  # then the abdominal wall, no more liver
    assert (rest[n_liver:] == AIR).any()  # and the air in front of the patient
    assert mm(labels, c)[0] < -20  # on the patient's right


def test_vessel_crosses_the_liver_along_z(phantom):
    labels, _ = phantom
    a = labels.array
    vessel = a == VESSEL
    k = np.flatnonzero(vessel.any(axis=(0, 1)))
    assert (k[-1] - k[0] + 1) * 2.0 >= 80  # mm along z
    assert np.array_equal(k, np.arange(k[0], k[-1] + 1))  # one unbroken tube
    liver_k = np.flatnonzero((a == LIVER).any(axis=(0, 1)))
    assert liver_k[0] <= k[0] and k[-1] <= liver_k[-1]
    outside = np.zeros_like(vessel)  # vessel voxels with a neighbour outside the liver
    for nb in neighbours(a, AIR):
        outside |= vessel & ~np.isin(nb, [LIVER, TUMOUR, VESSEL])
    ko = np.flatnonzero(outside.any(axis=(0, 1)))
    assert ko.min() <= k[0] + 2 and ko.max() >= k[-1] - 2  # it enters and leaves through the surface
    assert not outside[:, :, k[0] + 5 : k[-1] - 4].any()  # and runs inside the liver in between (10 mm ends)
    middle = vessel[:, :, (k[0] + k[-1]) // 2]
    diameter = 2 * math.sqrt(middle.sum() / math.pi)  # mm, 1 mm pixels
    assert 8 <= diameter <= 10, diameter
    assert not (ndimage.binary_dilation(vessel, FACES, iterations=3) & (a == TUMOUR)).any()


def test_spine_and_ribs_hold_the_liver_from_behind(phantom):
    labels, _ = phantom
    a = labels.array
    x = mm(labels, np.stack([np.arange(a.shape[0]), np.zeros(a.shape[0]), np.zeros(a.shape[0])], 1))[:, 0]
    liver, bone = a == LIVER, a == BONE
    column = bone & (np.abs(x) <= 36)[:, None, None]  # vertebrae (their processes reach |x| = 34 mm)
    ribs = bone & (x < -36)[:, None, None]
    assert not (bone & (x > 36)[:, None, None]).any()  # ribs on the liver's side only
    liver_y = mm(labels, np.argwhere(liver))[:, 1]
    near = liver & ndimage.binary_dilation(column, FACES, iterations=2)
    touching = liver & ndimage.binary_dilation(column, FACES)
    assert touching.sum() >= 1000 and near.sum() >= touching.sum()  # >= 2000 mm^2 of contact
    assert mm(labels, np.argwhere(near))[:, 1].min() > np.median(liver_y)  # on the liver's posterior side
    on_ribs = mm(labels, np.argwhere(liver & ndimage.binary_dilation(ribs, FACES)))
    assert len(on_ribs) >= 300 and on_ribs[:, 1].mean() > np.median(liver_y)  # the back and side
    column_mm = mm(labels, np.argwhere(column))
    assert abs(column_mm[:, 0].mean()) < 2 and column_mm[:, 1].min() > 10  # midline, posterior


def test_liver_shape_and_place(phantom):
    labels, _ = phantom
    a = labels.array
    organ = np.isin(a, [LIVER, TUMOUR, VESSEL])
    p = mm(labels, np.argwhere(organ))
    size = p.max(0) - p.min(0) + np.array([1.0, 1.0, 2.0])
    np.testing.assert_allclose(size, [145, 115, 100], atol=10)
    assert p[:, 0].mean() < -15  # on the patient's right
    assert not (ndimage.binary_dilation(a == AIR, FACES, iterations=10) & organ).any()  # under a wall


@pytest.mark.parametrize(
    "label, lo, hi",  # cm^3: a 22 mm ball is 5.58 cm^3
    [
        (LIVER, 550, 750),
        (TUMOUR, 5.0, 6.2),
        (BONE, 110, 200),
        (VESSEL, 4.0, 7.5),
        (SOFT, 2700, 3700),
        (AIR, 800, 1500),
    ],
)
def test_label_volumes(phantom, label, lo, hi):
    cm3 = int((phantom[0].array == label).sum()) * VOXEL_MM3 / 1e3
    assert lo <= cm3 <= hi, cm3


def test_tumour_volume_is_a_22_mm_ball(phantom):
    cm3 = int((phantom[0].array == TUMOUR).sum()) * VOXEL_MM3 / 1e3
    assert cm3 == pytest.approx(4 / 3 * math.pi * 1.1**3, rel=0.05)


# ------------------------------------------------------------------ the CT
@pytest.mark.parametrize("label, hu", [(AIR, -1000), (LIVER, 60), (TUMOUR, 30), (BONE, 700), (VESSEL, 160)])
def test_mean_hu_inside_each_label(phantom, label, hu):
    labels, ct = phantom
    inner = ndimage.binary_erosion(labels.array == label, FACES)  # partial volume only at boundaries
    assert inner.sum() > 500
    assert abs(float(ct.array[inner].mean()) - hu) <= 15


def test_torso_is_fat_and_soft_tissue_and_the_noise_is_10_hu(phantom):
    labels, ct = phantom
    values = ct.array[ndimage.binary_erosion(labels.array == SOFT, FACES)]
    assert 0.1 < np.mean(np.abs(values + 100) < 40) < 0.4  # subcutaneous fat, -100 HU
    assert np.mean(np.abs(values - 40) < 40) > 0.5  # muscle and soft tissue, 40 HU
    liver = ct.array[ndimage.binary_erosion(labels.array == LIVER, FACES)]
    assert 8 < float(liver.std()) < 12


def test_partial_volume_at_the_tumour_boundary(phantom):
    labels, ct = phantom
    a = labels.array
    rim = (a == TUMOUR) & ndimage.binary_dilation(a == LIVER, FACES)
    core = ndimage.binary_erosion(a == TUMOUR, FACES, iterations=3)
    assert ct.array[core].mean() < ct.array[rim].mean() < 60  # between tumour (30) and liver (60)


def test_same_seed_same_arrays_and_the_seed_changes_only_the_noise():
    a_labels, a_ct = abdominal_phantom(voxel=0.004, seed=3)
    _, b_ct = abdominal_phantom(voxel=0.004, seed=3)
    c_labels, c_ct = abdominal_phantom(voxel=0.004, seed=4)
    np.testing.assert_array_equal(a_ct.array, b_ct.array)
    np.testing.assert_array_equal(a_labels.array, c_labels.array)
    assert not np.array_equal(a_ct.array, c_ct.array)
    assert abs(float((a_ct.array - c_ct.array).std()) - 10 * math.sqrt(2)) < 1


@pytest.mark.parametrize("kw", [{"voxel": 0.0001}, {"voxel": 0.1}, {"voxel": float("nan")}, {"seed": -1}])
def test_bad_arguments_are_refused(kw):
    with pytest.raises(ConfigError, match=next(iter(kw))):
        abdominal_phantom(**kw)


def test_phantom_is_fast():
    t0 = time.perf_counter()
    abdominal_phantom()
    assert time.perf_counter() - t0 < 5.0


# ------------------------------------------------------------------ a body


def test_the_suggested_tissues_build_a_body(phantom, one_thread):
    liver_E = Tissue.of("liver", key="t").youngs_modulus
    assert 10 <= Tissue.of(PHANTOM_TISSUES[2], key="t").youngs_modulus / liver_E <= 12
    assert Tissue.of(PHANTOM_TISSUES[4], key="t").youngs_modulus < liver_E
    assert list(PHANTOM_FIXED) == [BONE] and sorted(PHANTOM_BACKGROUND) == [AIR, SOFT]
    body = body_from_labels(phantom[0], 0.004, tissues=PHANTOM_TISSUES, fixed=[3], background=[0, 5])
    nodes = body.grid.nodes()
    assert int(nodes.sum()) > 0 and int(body.fixed.sum()) > 0
    present = set(np.unique(body.labels[nodes].numpy()).tolist())
    assert {LIVER, TUMOUR, VESSEL, BONE} <= present
    pieces, count = ndimage.label(nodes.numpy(), structure=np.ones((3, 3, 3)))  # 26-neighbour springs
    held = np.unique(pieces[body.fixed.numpy()])
    assert set(held.tolist()) == set(range(1, count + 1))  # fixing the spine holds every piece


# ------------------------------------------------------------------ the command
def listing(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_command_writes_nifti_and_a_dicom_series_that_read_back(tmp_path, capsys, phantom):
    out = tmp_path / "phantom"
    assert cli.main(argv=["data", "phantom", "--labels", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("\n") == 1 and "200 x 160 x 80" in printed and "ct_dicom" in printed
    assert sorted(p.name for p in out.iterdir()) == ["ct.nii.gz", "ct_dicom", "labels.nii.gz"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(STAGING)]
    labels, ct = phantom
    got_labels = read_image(out / "labels.nii.gz")
    got_ct = read_image(out / "ct.nii.gz")
    got_dicom = read_image(out / "ct_dicom")
    assert got_labels.array.dtype == np.uint8
    np.testing.assert_array_equal(got_labels.array, labels.array)
    np.testing.assert_array_equal(got_ct.array, ct.array)
    assert got_dicom.shape == ct.shape and np.abs(got_dicom.array - ct.array).max() <= 1.0
    for image in (got_labels, got_ct, got_dicom):
        np.testing.assert_allclose(image.affine, labels.affine, rtol=0, atol=1e-9)


def test_command_without_dicom_and_at_another_voxel(tmp_path, capsys):
    out = tmp_path / "new" / "phantom"  # missing folders are made
    assert (
        cli.main(argv=["data", "phantom", "--labels", str(out), "--voxel", "0.004", "--seed", "2", "--no-dicom"]) == 0
    )
    assert sorted(p.name for p in out.iterdir()) == ["ct.nii.gz", "labels.nii.gz"]
    assert "50 x 40 x 20" in capsys.readouterr().out
    np.testing.assert_array_equal(read_image(out / "ct.nii.gz").array, abdominal_phantom(voxel=0.004, seed=2)[1].array)


def test_command_refuses_a_folder_that_holds_files_and_changes_nothing(tmp_path, capsys):
    out = tmp_path / "phantom"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    before = listing(tmp_path)
    assert cli.main(argv=["data", "phantom", "--labels", str(out), "--voxel", "0.004"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("torchdeform: --labels:") and "Traceback" not in err
    assert listing(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["phantom"]


def test_command_refuses_a_file_and_bad_values_in_one_line(tmp_path, capsys):
    path = tmp_path / "a_file"
    path.write_text("x")
    assert cli.main(argv=["data", "phantom", "--labels", str(path)]) == 2
    assert "this path is a file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(argv=["data", "phantom", "--labels", str(tmp_path / "b"), "--voxel", "0.1"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--voxel" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_an_empty_folder_is_filled(tmp_path, capsys):
    out = tmp_path / "empty"
    out.mkdir()
    assert cli.main(argv=["data", "phantom", "--labels", str(out), "--voxel", "0.004", "--no-dicom"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["ct.nii.gz", "labels.nii.gz"]


def test_the_other_data_commands_still_dispatch(tmp_path, capsys):
    out = tmp_path / "c.npz"
    assert cli.main(argv=["data", "cube", "--n", "2", "--steps", "3", "--out", str(out)]) == 0
    assert out.is_file()
