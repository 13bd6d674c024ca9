"""Medical images in one frame (LPS metres): NIfTI, NRRD, .npy/.npz and DICOM series, read and written.

Oracles, none of them torchdeform's own output:

* the DICOM standard's geometry (PS3.3 C.7.6.2.1.1) evaluated here on the datasets pydicom reads
  back: pixel (row j, column i) of a slice lies at ``IPP + r * PixelSpacing[1] * i + c *
  PixelSpacing[0] * j``, with ``r, c`` the two ``ImageOrientationPatient`` cosines;
* nibabel's RAS millimetre affine of a file built in the test, turned into LPS metres by hand:
  ``diag(-1, -1, 1) @ RAS / 1000``; pynrrd's ``space directions`` likewise;
* the same physical data written as a NIfTI file (nibabel) and as a DICOM series (pydicom) must
  read back to the same array (to the quantisation ``slope / 2``) and the same affine;
* every refusal is one ``ConfigError`` line that names the key and the file or folder.
"""

from __future__ import annotations

import math
import re
import shutil

import nibabel as nib
import nrrd
import numpy as np
import pytest

import torchdeform.anatomy.images as images
from torchdeform.anatomy import Image, read_image, write_dicom_series, write_nifti
from torchdeform.errors import ConfigError
from torchdeform.outputs import STAGING

pydicom = pytest.importorskip("pydicom", reason="DICOM needs the optional package pydicom (torchdeform[anatomy])")

KEY = "anatomy.image"


def rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues' rotation matrix about ``axis``."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * kx + (1 - math.cos(t)) * kx @ kx


def oblique_affine(spacing_mm=(0.7, 0.8, 1.25), origin_mm=(-120.5, 35.25, 80.0)) -> np.ndarray:
    """A rotated LPS-metre affine; the origin is exact in float32 mm (NIfTI stores float32)."""
    a = np.eye(4)
    a[:3, :3] = rotation((1.0, 2.0, 3.0), 25.0) @ np.diag(spacing_mm) * 1e-3
    a[:3, 3] = np.asarray(origin_mm) * 1e-3
    return a


def refused(excinfo, *names: str, key: str = KEY) -> str:
    """The error's message, after checking it is one line naming ``key`` and each of ``names``."""
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    assert msg.startswith(f"{key}: expected "), msg
    for name in names:
        assert str(name) in msg, (name, msg)
    return msg


def datasets(folder):
    return [(p, pydicom.dcmread(p)) for p in sorted(folder.iterdir())]


def scramble_instance_numbers(folder, rng):
    """Give the slices InstanceNumbers unrelated to their positions (the reader must not use them)."""
    files = sorted(folder.iterdir())
    for p, number in zip(files, rng.permutation(len(files)) + 1):
        ds = pydicom.dcmread(p)
        ds.InstanceNumber = int(number)
        ds.save_as(p, enforce_file_format=True)


# ------------------------------------------------------------------ DICOM against NIfTI
@pytest.mark.parametrize("names", ["shuffled", "opposite"])
def test_dicom_series_reads_back_as_the_nifti_of_the_same_data(tmp_path, names):
    rng = np.random.default_rng(7)
    hu = rng.uniform(-1000.0, 2000.0, (12, 10, 7)).astype(np.float32)
    affine = oblique_affine()
    K = hu.shape[2]
    if names == "shuffled":
        file_names = list(rng.permutation([f"im{k}.dcm" for k in range(K)]))
    else:  # names sort opposite to the slice positions
        file_names = [f"{K - k:02d}.dcm" for k in range(K)]
    write_dicom_series(tmp_path / "ct", hu, affine, slope=0.5, intercept=-1024.0, file_names=file_names, rng=1)
    scramble_instance_numbers(tmp_path / "ct", rng)
    write_nifti(tmp_path / "ct.nii.gz", hu, affine)

    dicom = read_image(tmp_path / "ct", key=KEY)
    nifti = read_image(tmp_path / "ct.nii.gz", key=KEY)
    assert dicom.array.dtype == np.float32 and dicom.shape == hu.shape
    np.testing.assert_array_equal(nifti.array, hu)
    assert np.abs(dicom.array - nifti.array).max() <= 0.25 + 1e-4  # half a stored step
    np.testing.assert_allclose(dicom.affine, nifti.affine, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dicom.affine, affine, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dicom.spacing, [0.7e-3, 0.8e-3, 1.25e-3], rtol=1e-12)


def test_integer_series_with_identity_rescale_keeps_its_dtype(tmp_path):
    labels = np.random.default_rng(0).integers(0, 5, (6, 5, 4)).astype(np.int16)
    write_dicom_series(tmp_path / "lab", labels, np.diag([1e-3, 1e-3, 2e-3, 1.0]), rng=0)
    image = read_image(tmp_path / "lab")
    assert image.array.dtype == np.int16
    np.testing.assert_array_equal(image.array, labels)
    as_float = read_image(tmp_path / "lab", dtype=np.float32)
    assert as_float.array.dtype == np.float32 and np.array_equal(as_float.array, labels)


# ------------------------------------------------------------------ DICOM geometry from the datasets
def dicom_position(ds, i, j) -> np.ndarray:
    """PS3.3 C.7.6.2.1.1: the LPS position (mm) of column i, row j of one slice."""
    ipp = np.array([float(v) for v in ds.ImagePositionPatient])
    iop = np.array([float(v) for v in ds.ImageOrientationPatient])
    row_spacing, col_spacing = (float(v) for v in ds.PixelSpacing)
    return ipp + iop[:3] * col_spacing * i + iop[3:] * row_spacing * j


@pytest.mark.parametrize("tilt_mm", [0.0, 0.3])
def test_positions_follow_the_written_datasets(tmp_path, tilt_mm):
    rng = np.random.default_rng(3)
    hu = np.rint(rng.uniform(-1000.0, 1000.0, (9, 8, 5)))
    write_dicom_series(tmp_path / "ct", hu, oblique_affine(), slope=1.0, intercept=-1024.0, rng=2)
    if tilt_mm:  # a gantry tilt: each slice shifted along the row cosine (a sheared stack)
        for p, ds in datasets(tmp_path / "ct"):
            k = int(p.stem.split("_")[1])
            r = np.array([float(v) for v in ds.ImageOrientationPatient[:3]])
            ipp = np.array([float(v) for v in ds.ImagePositionPatient]) + k * tilt_mm * r
            ds.ImagePositionPatient = [f"{v:.10f}" for v in ipp]
            ds.save_as(p, enforce_file_format=True)
    image = read_image(tmp_path / "ct")
    found = set()
    for _, ds in datasets(tmp_path / "ct"):
        values = ds.pixel_array.astype(np.float64) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
        matches = [k for k in range(image.shape[2]) if np.array_equal(image.array[:, :, k].T, values)]
        assert len(matches) == 1
        k = matches[0]
        found.add(k)
        for i, j in [(0, 0), (8, 0), (0, 7), (5, 3)]:
            np.testing.assert_allclose(image.positions([i, j, k]) * 1e3, dicom_position(ds, i, j), atol=1e-6)
    assert found == set(range(image.shape[2]))
    points = image.positions(np.array([[0.5, 1.0, 2.0], [8.0, 7.0, 4.0]]))
    np.testing.assert_allclose(image.index_of(points), [[0.5, 1.0, 2.0], [8.0, 7.0, 4.0]], atol=1e-9)


# ------------------------------------------------------------------ NIfTI and NRRD frames
@pytest.mark.parametrize("unit, metres", [("mm", 1e-3), ("meter", 1.0)])
def test_nifti_ras_becomes_lps_metres(tmp_path, unit, metres):
    ras = np.eye(4)
    ras[:3, :3] = rotation((0.0, 1.0, 1.0), 40.0) @ np.diag([0.9, 1.1, 2.5])
    ras[:3, 3] = [12.5, -30.25, 7.0]
    labels = np.arange(4 * 5 * 6, dtype=np.uint8).reshape(4, 5, 6) % 7
    img = nib.Nifti1Image(labels, ras)
    img.header.set_xyzt_units(unit)
    nib.save(img, tmp_path / "labels.nii.gz")
    stored = nib.load(tmp_path / "labels.nii.gz").affine  # the RAS affine as the file holds it

    image = read_image(tmp_path / "labels.nii.gz")
    assert image.array.dtype == np.uint8
    np.testing.assert_array_equal(image.array, labels)
    idx = np.array([[0, 0, 0], [3, 4, 5], [1, 2, 3], [2.5, 0.5, 1.0]])
    expected = (idx @ stored[:3, :3].T + stored[:3, 3]) * np.array([-1.0, -1.0, 1.0]) * metres
    np.testing.assert_allclose(image.positions(idx), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(image.index_of(expected), idx, atol=1e-9)


def test_nifti_scaling_gives_float32_values(tmp_path):
    raw = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    img = nib.Nifti1Image(raw, np.eye(4))
    img.header.set_slope_inter(0.5, -1024.0)
    nib.save(img, tmp_path / "ct.nii")
    image = read_image(tmp_path / "ct.nii")
    assert image.array.dtype == np.float32
    np.testing.assert_array_equal(image.array, raw * 0.5 - 1024.0)


@pytest.mark.parametrize("space", ["right-anterior-superior", "RAS", "left-posterior-superior", "LPS", "LPS-cm"])
def test_nrrd_spaces_give_the_same_lps_positions(tmp_path, space):
    data = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5)
    axes_lps = np.array([[0.8, 0.1, 0.0], [-0.1, 0.9, 0.2], [0.0, -0.3, 2.0]])  # one row per axis, mm
    origin_lps = np.array([10.0, -20.0, 30.0])
    header = {"space directions": axes_lps, "space origin": origin_lps}
    if space in ("right-anterior-superior", "RAS"):
        flip = np.array([-1.0, -1.0, 1.0])
        header = {"space directions": axes_lps * flip, "space origin": origin_lps * flip}
    elif space == "LPS-cm":
        header = {"space directions": axes_lps / 10, "space origin": origin_lps / 10, "space units": ["cm"] * 3}
    header["space"] = space.removesuffix("-cm")
    nrrd.write(str(tmp_path / "v.nrrd"), data, header, index_order="F")

    image = read_image(tmp_path / "v.nrrd")
    np.testing.assert_array_equal(image.array, data)
    idx = np.array([[0, 0, 0], [2, 3, 4], [1, 0, 2]])
    expected = (idx @ axes_lps + origin_lps) * 1e-3
    np.testing.assert_allclose(image.positions(idx), expected, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ .npy and .npz
def test_npz_geometry_and_caller_override(tmp_path):
    direction = rotation((0.0, 0.0, 1.0), 90.0)
    np.savez(
        tmp_path / "v.npz",
        array=np.ones((2, 3, 4), np.float32),
        spacing=np.array([1e-3, 2e-3, 3e-3]),
        origin=np.array([0.1, 0.2, 0.3]),
        direction=direction,
    )
    image = read_image(tmp_path / "v.npz")
    np.testing.assert_allclose(image.positions([1, 1, 1]), [0.1, 0.2, 0.3] + direction @ [1e-3, 2e-3, 3e-3])
    image = read_image(tmp_path / "v.npz", spacing=5e-4, origin=[0, 0, 0])
    np.testing.assert_allclose(image.affine[:3, :3], direction * 5e-4)
    np.testing.assert_allclose(image.origin, 0.0)
    np.save(tmp_path / "v.npy", np.zeros((2, 2, 2)))
    np.testing.assert_allclose(read_image(tmp_path / "v.npy", spacing=[1e-3, 1e-3, 2e-3]).spacing, [1e-3, 1e-3, 2e-3])


# ------------------------------------------------------------------ refusals: one line, key and file
def test_folder_with_two_series(tmp_path):
    a = np.zeros((4, 4, 3))
    write_dicom_series(tmp_path / "one", a, np.diag([1e-3, 1e-3, 1e-3, 1.0]), rng=0)
    write_dicom_series(tmp_path / "two", a, np.diag([1e-3, 1e-3, 1e-3, 1.0]), rng=1)
    for p in (tmp_path / "two").iterdir():
        shutil.copy(p, tmp_path / "one" / f"other_{p.name}")
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "one", key=KEY)
    assert "2 SeriesInstanceUIDs" in refused(e, tmp_path / "one")


def test_folder_with_a_missing_slice(tmp_path):
    affine = oblique_affine()
    write_dicom_series(tmp_path / "ct", np.zeros((4, 4, 6)), affine, rng=0)
    lost = pydicom.dcmread(tmp_path / "ct" / "slice_0003.dcm").ImagePositionPatient
    (tmp_path / "ct" / "slice_0003.dcm").unlink()
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "ct", key=KEY)
    msg = refused(e, tmp_path / "ct", "slice_0002.dcm", "slice_0004.dcm")
    where = re.search(r"1 slice is missing at LPS \(([^)]*)\) mm", msg)
    assert where, msg
    np.testing.assert_allclose([float(v) for v in where.group(1).split(",")], [float(v) for v in lost], atol=1e-3)


def test_folder_with_a_duplicate_or_mismatched_slice(tmp_path):
    write_dicom_series(tmp_path / "ct", np.zeros((4, 4, 3)), np.diag([1e-3, 1e-3, 1e-3, 1.0]), rng=0)
    shutil.copy(tmp_path / "ct" / "slice_0001.dcm", tmp_path / "ct" / "copy.dcm")
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "ct", key=KEY)
    assert "no duplicates" in refused(e, tmp_path / "ct", "copy.dcm")
    (tmp_path / "ct" / "copy.dcm").unlink()
    ds = pydicom.dcmread(tmp_path / "ct" / "slice_0002.dcm")
    ds.PixelSpacing = ["0.5", "1"]
    ds.save_as(tmp_path / "ct" / "slice_0002.dcm", enforce_file_format=True)
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "ct", key=KEY)
    assert "agree on PixelSpacing" in refused(e, tmp_path / "ct", "slice_0002.dcm")


def test_folder_without_dicom_files(tmp_path):
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "README.txt").write_text("not an image\n")
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "notes", key=KEY)
    assert "no DICOM image among 1 files" in refused(e, tmp_path / "notes")


def test_singular_affine_from_npz(tmp_path):
    direction = np.eye(3)
    direction[:, 1] = 0.0
    np.savez(tmp_path / "flat.npz", array=np.zeros((2, 2, 2)), spacing=1e-3, direction=direction)
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "flat.npz", key=KEY)
    assert "non-singular" in refused(e, tmp_path / "flat.npz")


def test_npy_without_spacing(tmp_path):
    np.save(tmp_path / "labels.npy", np.zeros((2, 2, 2), np.uint8))
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "labels.npy", key=KEY)
    assert "spacing" in refused(e, tmp_path / "labels.npy")


def test_unknown_nrrd_space(tmp_path):
    nrrd.write(str(tmp_path / "v.nrrd"), np.zeros((2, 2, 2)), {"space": "scanner-xyz", "space directions": np.eye(3)})
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "v.nrrd", key=KEY)
    assert "scanner-xyz" in refused(e, tmp_path / "v.nrrd")


def test_other_bad_inputs(tmp_path):
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "v.mha", key=KEY)
    refused(e, "v.mha")
    np.save(tmp_path / "v.npy", np.zeros((2, 2)))
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "v.npy", key=KEY, spacing=1e-3)
    assert "3-D" in refused(e, "v.npy")
    nib.save(nib.Nifti1Image(np.zeros((2, 2, 2), np.int16), np.eye(4)), tmp_path / "v.nii")
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "v.nii", key=KEY, spacing=1e-3)
    refused(e, "v.nii")
    (tmp_path / "broken.nii").write_bytes(b"not a nifti")
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "broken.nii", key=KEY)
    assert "readable NIfTI" in refused(e, "broken.nii")


def test_memory_is_checked_before_reading(tmp_path, monkeypatch):
    np.save(tmp_path / "big.npy", np.zeros((16, 16, 16)))
    monkeypatch.setattr("torchdeform.checks.available_memory", lambda device=None: 1000)
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "big.npy", key=KEY, spacing=1e-3)
    assert "fits in memory" in refused(e, "big.npy")


def test_missing_pydicom_is_one_line(tmp_path, monkeypatch):
    (tmp_path / "ct").mkdir()
    monkeypatch.setitem(__import__("sys").modules, "pydicom", None)
    with pytest.raises(ConfigError) as e:
        read_image(tmp_path / "ct", key=KEY)
    assert "pip install pydicom" in refused(e, tmp_path / "ct")


@pytest.mark.parametrize(
    "affine, words",
    [
        (np.array([[1e-3, 0, 0, 0], [0, 1e-3, 0, 0], [0, 0, 1e-3, 0], [0, 0, 1e-3, 1]]), "last row"),
        (np.diag([1e-3, np.nan, 1e-3, 1.0]), "finite affine"),
        (np.eye(3), "4 x 4"),
    ],
)
def test_image_refuses_bad_affines(affine, words):
    with pytest.raises(ConfigError) as e:
        Image(np.zeros((2, 2, 2)), affine, "scan.nii")
    assert words in refused(e, "scan.nii", key="image.affine")


def test_image_refuses_bad_voxels():
    with pytest.raises(ConfigError) as e:
        Image(np.array([[[np.nan]]]), np.eye(4), "scan.nii")
    assert "1 non-finite" in refused(e, "scan.nii", key="image.array")


# ------------------------------------------------------------------ writers
def test_dicom_writer_refuses_what_dicom_cannot_store(tmp_path):
    sheared = np.diag([1e-3, 1e-3, 1e-3, 1.0])
    sheared[0, 1] = 5e-4
    with pytest.raises(ConfigError) as e:
        write_dicom_series(tmp_path / "a", np.zeros((2, 2, 2)), sheared, key=KEY)
    assert "orthogonal" in refused(e, tmp_path / "a")
    with pytest.raises(ConfigError) as e:
        write_dicom_series(tmp_path / "a", np.zeros((2, 2, 2)), np.diag([1e-3, 1e-3, -1e-3, 1.0]), key=KEY)
    assert "slice normal" in refused(e, tmp_path / "a")
    with pytest.raises(ConfigError) as e:
        write_dicom_series(tmp_path / "a", np.full((2, 2, 2), 1e6), np.diag([1e-3, 1e-3, 1e-3, 1.0]), key=KEY)
    assert "16 bits" in refused(e, tmp_path / "a")
    assert not (tmp_path / "a").exists()


def test_dicom_writer_is_whole_or_nothing(tmp_path, monkeypatch):
    affine = np.diag([1e-3, 1e-3, 1e-3, 1.0])
    write_dicom_series(tmp_path / "ct", np.zeros((3, 3, 4)), affine, rng=0)
    before = {p.name: p.read_bytes() for p in (tmp_path / "ct").iterdir()}
    save = images._save_dataset
    calls = []

    def failing(pydicom, ds, path):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(28, "No space left on device", str(path))
        save(pydicom, ds, path)

    monkeypatch.setattr(images, "_save_dataset", failing)
    with pytest.raises(OSError, match="earlier series is kept"):
        write_dicom_series(tmp_path / "ct", np.ones((3, 3, 4)), affine, rng=1)
    assert {p.name: p.read_bytes() for p in (tmp_path / "ct").iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(STAGING)]
    monkeypatch.undo()
    write_dicom_series(tmp_path / "ct", np.ones((3, 3, 2)), affine, rng=1)  # an earlier series is replaced
    assert sorted(p.name for p in (tmp_path / "ct").iterdir()) == ["slice_0000.dcm", "slice_0001.dcm"]
    (tmp_path / "ct" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError) as e:
        write_dicom_series(tmp_path / "ct", np.ones((3, 3, 2)), affine, key=KEY)
    assert "notes.txt" in refused(e, tmp_path / "ct")


def test_nifti_writer_sets_both_forms(tmp_path):
    affine = oblique_affine()
    write_nifti(tmp_path / "v.nii", np.zeros((2, 3, 4), np.int64), affine)
    img = nib.load(tmp_path / "v.nii")
    assert img.get_data_dtype() == np.int32
    ras = np.diag([-1e3, -1e3, 1e3, 1.0]) @ affine
    for form, code in (img.header.get_sform(coded=True), img.header.get_qform(coded=True)):
        assert code == 1
        np.testing.assert_allclose(form, ras, atol=1e-4)
    with pytest.raises(ConfigError) as e:
        write_nifti(tmp_path / "v.nrrd", np.zeros((2, 2, 2)), affine, key=KEY)
    refused(e, "v.nrrd")
