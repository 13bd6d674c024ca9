r"""Medical images with their affine, in one physical frame: NIfTI, NRRD, ``.npy``/``.npz``, DICOM series.

**The frame.** Every position is in metres in the patient frame **LPS**: x to the patient's
Left, y Posterior, z Superior, the frame DICOM uses. The lattice axes (D, H, W) of torchdeform's
grids are LPS (x, y, z). Other frames and units are converted once, here, where a file is read or
written, and nowhere else:

* NIfTI (nibabel): the affine maps voxel indices to RAS+ millimetres. LPS = RAS with the first two
  axes negated, and mm -> m: ``A_lps = diag(-s, -s, s, 1) @ A_ras`` with ``s = 1e-3`` (or the
  header's ``xyzt_units``: ``meter`` 1, ``micron`` 1e-6; ``unknown`` is read as millimetres).
* NRRD (pynrrd): ``space directions`` (one row per axis), ``space origin`` (the centre of the
  first sample) and ``space`` (``left-posterior-superior`` / ``LPS`` or
  ``right-anterior-superior`` / ``RAS``; other spaces are refused); ``space units`` (default mm).
* DICOM (pydicom, one file per slice, one folder per series), PS3.3 C.7.6.2.1.1: with the row
  direction cosine ``r`` (the first three ``ImageOrientationPatient`` values: where the column
  index grows), the column direction cosine ``c`` (the last three: where the row index grows) and
  the slice normal ``n = r x c``, slices are ordered by ``s = ImagePositionPatient . n`` (never by
  file name or ``InstanceNumber``), and

  .. code-block:: text

      A[:3, 0] = r * PixelSpacing[1]        (i: the column index, along a row)
      A[:3, 1] = c * PixelSpacing[0]        (j: the row index)
      A[:3, 2] = (P[N-1] - P[0]) / (N - 1)  (k: the slice; n * ds for an untilted stack)
      A[:3, 3] = P[0]                       (the first slice's ImagePositionPatient)

  all in mm, then times 1e-3. The slice spacing ``ds`` comes from the positions (their gaps along
  ``n`` must agree to 1 %: a missing slice is refused), never from ``SliceThickness``. Values are
  ``HU = stored * RescaleSlope + RescaleIntercept``; the array keeps the stored integer dtype when
  every slice has slope 1 and intercept 0, and is float32 otherwise.
* ``.npy`` / ``.npz``: the caller (or arrays ``spacing``, ``origin``, ``direction`` inside the
  ``.npz``) gives the geometry, already in LPS metres: ``A[:3, :3] = direction * spacing``
  (columns), ``A[:3, 3] = origin``.

**The array.** :attr:`Image.array` keeps the axes ``(i, j, k)`` as the file indexes them (no
reorientation; NIfTI's order; for DICOM ``(column, row, slice)``), and :attr:`Image.affine` maps the
voxel index ``(i, j, k, 1)`` to the LPS position in metres of the voxel's centre:

.. code-block:: text

    p = A[:3, :3] @ (i, j, k) + A[:3, 3]          (Image.positions)
    (i, j, k) = A[:3, :3]^-1 @ (p - A[:3, 3])      (Image.index_of)

**Errors.** Every problem is one :class:`~torchdeform.errors.ConfigError` line that names the key
the caller gave (``key=``) and the file or folder; big arrays are refused before they are
allocated (:func:`~torchdeform.checks.check_memory`). Writers are whole or nothing: a file goes
through :func:`~torchdeform.outputs.atomic_path`, a DICOM series is written into a hidden
sibling folder renamed into place at the end.

nibabel, pynrrd and pydicom are imported only by the code paths that read or write their formats
(``pip install torchdeform[volume]`` for NIfTI/NRRD, ``torchdeform[anatomy]`` for DICOM).

Example:
    >>> import numpy as np
    >>> from torchdeform.anatomy.images import Image, read_image, write_nifti
    >>> affine = np.diag([0.001, 0.001, 0.002, 1.0])       # 1 x 1 x 2 mm voxels, LPS metres
    >>> affine[:3, 3] = [0.10, -0.05, 0.30]                # centre of voxel (0, 0, 0)
    >>> path = getfixture("tmp_path") / "labels.nii.gz"
    >>> write_nifti(path, np.ones((3, 4, 5), np.uint8), affine)
    >>> image = read_image(path)
    >>> image.array.dtype, image.shape, np.allclose(image.affine, affine)
    (dtype('uint8'), (3, 4, 5), True)
    >>> image.positions([[2, 0, 1]]).round(6).tolist()    # metres, LPS
    [[0.102, -0.05, 0.302]]
    >>> image.index_of([[0.102, -0.05, 0.302]]).round(6).tolist()
    [[2.0, 0.0, 1.0]]
"""

from __future__ import annotations

import math
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..checks import check_memory
from ..errors import ConfigError, ConfigWarning
from ..outputs import STAGING, OutputError, atomic_path

__all__ = ["Image", "read_image", "write_nifti", "write_dicom_series", "SUFFIXES"]

#: file suffixes :func:`read_image` knows (a folder is read as a DICOM series)
SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy", ".npz")

_NIFTI = (".nii", ".nii.gz")
_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse
_NIFTI_UNITS = {"mm": 1e-3, "meter": 1.0, "micron": 1e-6, "unknown": 1e-3}
_NRRD_SPACES = {
    "left-posterior-superior": "LPS",
    "lps": "LPS",
    "right-anterior-superior": "RAS",
    "ras": "RAS",
}
_NRRD_UNITS = {
    "mm": 1e-3,
    "millimeter": 1e-3,
    "millimeters": 1e-3,
    "millimetre": 1e-3,
    "millimetres": 1e-3,
    "m": 1.0,
    "meter": 1.0,
    "meters": 1.0,
    "metre": 1.0,
    "metres": 1.0,
    "cm": 1e-2,
    "um": 1e-6,
    "\N{MICRO SIGN}m": 1e-6,
    "micron": 1e-6,
    "microns": 1e-6,
}
# bytes per voxel of NRRD types (a lower bound for the memory check: unknown names count 1)
_NRRD_BYTES = {
    "signed char": 1, "int8": 1, "int8_t": 1, "uchar": 1, "unsigned char": 1, "uint8": 1, "uint8_t": 1,
    "short": 2, "short int": 2, "signed short": 2, "signed short int": 2, "int16": 2, "int16_t": 2,
    "ushort": 2, "unsigned short": 2, "unsigned short int": 2, "uint16": 2, "uint16_t": 2,
    "int": 4, "signed int": 4, "int32": 4, "int32_t": 4, "uint": 4, "unsigned int": 4, "uint32": 4,
    "uint32_t": 4, "float": 4, "longlong": 8, "long long": 8, "int64": 8, "int64_t": 8, "ulonglong": 8,
    "unsigned long long": 8, "uint64": 8, "uint64_t": 8, "double": 8,
}  # fmt: skip
_EXTRA = {
    "nibabel": "NIfTI files need nibabel: pip install nibabel (or torchdeform[volume])",
    "nrrd": "NRRD files need pynrrd: pip install pynrrd (or torchdeform[volume])",
    "pydicom": "DICOM series need pydicom: pip install pydicom (or torchdeform[anatomy])",
}
_GEOMETRY_ONLY_NUMPY = "spacing, origin and direction only for .npy/.npz files (NIfTI, NRRD and DICOM carry theirs)"
_DICOM_SOP = {"CT": "1.2.840.10008.5.1.4.1.1.2", "MR": "1.2.840.10008.5.1.4.1.1.4"}  # CT / MR Image Storage
# type 2 attributes of the CT/MR image IODs that this writer has no value for: present and empty
_TYPE2 = (
    "PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
    "ReferringPhysicianName", "StudyID", "AccessionNumber", "PositionReferenceIndicator",
)  # fmt: skip
_SINGULAR = 1e-6  # |det A| / prod |A[:, c]|: 1 for orthogonal axes, 0 for coplanar ones
_EVEN = 0.01  # slice gaps may differ from their median by this fraction
_SAME = 1e-4  # direction cosines (unitless) and pixel spacings (relative) equal across slices


# ------------------------------------------------------------------ the image
@dataclass(frozen=True, eq=False)
class Image:
    """Voxels and the affine that puts their centres in LPS metres.

    Attributes:
        array: the voxel values, shape ``(I, J, K)``, axes ``(i, j, k)`` as the file indexes them
            (no reorientation); numeric (integer labels, HU, intensities), finite.
        affine: float64, shape ``(4, 4)``: maps the voxel index ``(i, j, k, 1)`` to the LPS
            position ``(x, y, z, 1)`` of the voxel's centre, in metres; last row ``(0, 0, 0, 1)``,
            a non-singular 3 x 3 part. Stored as a read-only copy.
        source: the file or folder it came from (or a name), for messages; may be empty.

    Raises:
        ConfigError: a 2-D or non-numeric array, NaN/inf voxels, an affine that is not 4 x 4,
            not finite, whose last row is not ``(0, 0, 0, 1)`` or whose 3 x 3 part is singular
            (``|det| <= 1e-6 * prod of its column norms``); the message names ``source``.

    Examples:
        >>> import numpy as np
        >>> image = Image(np.zeros((2, 3, 4), np.int16), np.diag([0.5e-3, 0.5e-3, 1e-3, 1.0]), "ct")
        >>> image.spacing.tolist(), image.origin.tolist(), image.shape
        ([0.0005, 0.0005, 0.001], [0.0, 0.0, 0.0], (2, 3, 4))
        >>> image.positions([1, 2, 3]).tolist()                # metres, LPS
        [0.0005, 0.001, 0.003]
        >>> Image(np.zeros((2, 3, 4)), np.diag([1e-3, 0.0, 1e-3, 1.0]), "ct")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: image.affine: expected a non-singular 3 x 3 part ...
    """

    array: np.ndarray
    affine: np.ndarray
    source: str

    def __post_init__(self):
        object.__setattr__(self, "source", str(self.source))
        object.__setattr__(self, "array", _check_voxels(self.array, self.source, "image.array"))
        object.__setattr__(self, "affine", _check_affine(self.affine, self.source, "image.affine"))

    @property
    def shape(self) -> tuple:
        """``(I, J, K)``: the voxel counts along ``i``, ``j``, ``k``."""
        return tuple(int(n) for n in self.array.shape)

    @property
    def spacing(self) -> np.ndarray:
        """The voxel sizes along ``i``, ``j``, ``k`` [m], shape ``(3,)``: the column norms of ``affine[:3, :3]``."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def origin(self) -> np.ndarray:
        """The LPS position of the centre of voxel ``(0, 0, 0)`` [m], shape ``(3,)``."""
        return self.affine[:3, 3].copy()

    @property
    def direction(self) -> np.ndarray:
        """Unit LPS directions of the axes ``i``, ``j``, ``k`` as columns, shape ``(3, 3)``."""
        return self.affine[:3, :3] / self.spacing

    def positions(self, indices) -> np.ndarray:
        """LPS positions [m] of (fractional) voxel indices: ``A[:3, :3] @ idx + A[:3, 3]``.

        Args:
            indices: ``(..., 3)`` voxel indices ``(i, j, k)``; integers are voxel centres.

        Returns:
            float64 ``(..., 3)``, metres, LPS.

        Examples:
            >>> import numpy as np
            >>> image = Image(np.zeros((4, 4, 4)), np.diag([-1e-3, 1e-3, 2e-3, 1.0]), "demo")
            >>> image.positions([[0, 0, 0], [1, 1, 1]]).tolist()
            [[0.0, 0.0, 0.0], [-0.001, 0.001, 0.002]]
        """
        idx = _triples(indices, "indices")
        return idx @ self.affine[:3, :3].T + self.affine[:3, 3]

    def index_of(self, points) -> np.ndarray:
        """Fractional voxel indices ``(i, j, k)`` of LPS positions [m]: the inverse of :meth:`positions`.

        Args:
            points: ``(..., 3)`` LPS positions in metres.

        Returns:
            float64 ``(..., 3)`` voxel indices (integers at voxel centres; outside ``[0, n - 1]``
            for points outside the image).

        Examples:
            >>> import numpy as np
            >>> image = Image(np.zeros((4, 4, 4)), np.diag([-1e-3, 1e-3, 2e-3, 1.0]), "demo")
            >>> image.index_of([-0.0015, 0.0, 0.004]).tolist()
            [1.5, 0.0, 2.0]
        """
        p = _triples(points, "points")
        flat = (p - self.affine[:3, 3]).reshape(-1, 3).T
        return np.linalg.solve(self.affine[:3, :3], flat).T.reshape(p.shape)

    def __repr__(self) -> str:
        spacing = ", ".join(f"{s:.4g}" for s in self.spacing)
        origin = ", ".join(f"{o:.4g}" for o in self.origin)
        return (
            f"Image(shape={self.shape}, dtype={self.array.dtype}, spacing=({spacing}) m, "
            f"origin=({origin}) m LPS, source={self.source!r})"
        )


def _triples(values, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ConfigError(name, "an array of shape (..., 3)", got=f"shape {arr.shape}")
    return arr


def _got(source, detail: str) -> str:
    return f"{source} ({detail})" if source else detail


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _check_voxels(array, source: str, key: str) -> np.ndarray:
    if hasattr(array, "detach"):  # a torch tensor
        array = array.detach().cpu().numpy()
    arr = np.asarray(array)
    if arr.dtype.kind not in "biuf":
        raise ConfigError(key, "numeric voxels (booleans, integers or floats)", got=_got(source, f"dtype {arr.dtype}"))
    if arr.ndim != 3 or min(arr.shape, default=0) < 1:
        raise ConfigError(key, "a non-empty 3-D array (i, j, k)", got=_got(source, f"shape {arr.shape}"))
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = int(arr.size - np.isfinite(arr).sum())
        raise ConfigError(key, "finite voxels (no NaN or inf)", got=_got(source, f"{bad} non-finite voxels"))
    return arr


def _check_affine(affine, source: str, key: str) -> np.ndarray:
    try:
        a = np.array(affine, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(key, "a 4 x 4 matrix of numbers", got=_got(source, f"{type(affine).__name__}")) from None
    if a.shape != (4, 4):
        raise ConfigError(key, "a 4 x 4 matrix", got=_got(source, f"shape {a.shape}"))
    if not np.isfinite(a).all():
        raise ConfigError(key, "a finite affine (no NaN or inf)", got=_got(source, f"{a.tolist()}"))
    if np.abs(a[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-12:
        raise ConfigError(
            key, "an affine whose last row is (0, 0, 0, 1)", got=_got(source, f"last row {a[3].tolist()}")
        )
    a[3] = (0.0, 0.0, 0.0, 1.0)
    norms = np.linalg.norm(a[:3, :3], axis=0)
    det = float(np.linalg.det(a[:3, :3]))
    if not (norms.min() > 0 and abs(det) > _SINGULAR * float(np.prod(norms))):
        raise ConfigError(
            key,
            "a non-singular 3 x 3 part (three independent voxel axes, each of non-zero length)",
            got=_got(source, f"column lengths {[float(f'{n:.4g}') for n in norms]} m, determinant {det:.3g}"),
        )
    a.setflags(write=False)
    return a


def _image(array, affine, source, key: str) -> Image:
    """An :class:`Image`, its validation errors named by ``key`` (the caller's) instead of ``image.*``."""
    try:
        return Image(array, affine, str(source))
    except ConfigError as e:
        raise ConfigError(key, e.expected, got=e.got) from None


# ------------------------------------------------------------------ reading
def read_image(path, *, key: str = "labels", spacing=None, origin=None, direction=None, dtype=None) -> Image:
    """Read a 3-D image and its affine to LPS metres: NIfTI, NRRD, ``.npy``/``.npz`` or a DICOM series folder.

    Args:
        path: a ``.nii``/``.nii.gz`` (nibabel), ``.nrrd``/``.nhdr`` (pynrrd), ``.npy`` or ``.npz``
            file, or a folder holding the files of one DICOM series (pydicom).
        key: the option or scene key that named ``path``; every error names it.
        spacing: ``.npy``/``.npz`` only: the voxel size [m], one number or three (i, j, k);
            required for ``.npy``; overrides an array ``spacing`` in the ``.npz``.
        origin: ``.npy``/``.npz`` only: the LPS position [m] of the centre of voxel (0, 0, 0),
            3 numbers (default 0, or the ``.npz``'s ``origin``).
        direction: ``.npy``/``.npz`` only: 3 x 3, columns are the LPS directions of the axes
            ``i, j, k`` (default identity, or the ``.npz``'s ``direction``).
        dtype: convert the voxels to this numpy dtype (e.g. ``np.float32`` for intensities);
            None keeps what the file gives: integer labels stay integers, scaled NIfTI and
            rescaled DICOM values are float32.

    Returns:
        The :class:`Image`; its ``source`` is ``str(path)``.

    Raises:
        ConfigError: one line naming ``key`` and the file or folder: an unknown suffix, a
            missing file, a missing optional library, a corrupt file, an NRRD space other than
            LPS/RAS, ``.npy`` without ``spacing``, a singular affine, a folder with no DICOM
            slice or with two series, a missing or duplicate slice, slices that disagree on
            orientation, size or pixel spacing, or an image that does not fit in memory.

    Examples:
        >>> import numpy as np
        >>> path = getfixture("tmp_path") / "ct.npz"
        >>> np.savez(path, array=np.zeros((4, 4, 2), np.int16), spacing=[0.5e-3, 0.5e-3, 2e-3])
        >>> read_image(path, origin=[0.0, 0.0, 0.1])
        Image(shape=(4, 4, 2), dtype=int16, spacing=(0.0005, 0.0005, 0.002) m, origin=(0, 0, 0.1) m LPS, ...)
        >>> read_image(path.with_suffix(".npy"), key="anatomy.labels")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: anatomy.labels: expected an existing file or folder, got '.../ct.npy (not found)'
    """
    path = Path(path)
    geometry = spacing is not None or origin is not None or direction is not None
    if path.is_dir():
        if geometry:
            raise ConfigError(key, _GEOMETRY_ONLY_NUMPY, got=f"{path} (a DICOM series folder)")
        array, affine = _read_dicom(path, key)
    else:
        suffix = _suffix(path)
        if suffix not in SUFFIXES:
            raise ConfigError(
                key,
                "a .nii, .nii.gz, .nrrd, .nhdr, .npy or .npz file, or a folder holding one DICOM series",
                got=str(path),
            )
        if not path.is_file():
            raise ConfigError(key, "an existing file or folder", got=f"{path} (not found)")
        if suffix in (".npy", ".npz"):
            array, affine = _read_numpy(path, suffix, key, spacing, origin, direction)
        elif geometry:
            raise ConfigError(key, _GEOMETRY_ONLY_NUMPY, got=str(path))
        elif suffix in _NIFTI:
            array, affine = _guarded(_read_nifti, path, key, "NIfTI")
        else:
            array, affine = _guarded(_read_nrrd, path, key, "NRRD")
    if dtype is not None:
        array = _convert(array, dtype, key, path)
    return _image(array, affine, path, key)


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return next((s for s in SUFFIXES if name.endswith(s)), path.suffix.lower())


def _optional(module: str, key: str, path):
    try:
        return __import__(module)
    except ImportError:
        raise ConfigError(key, _EXTRA[module], got=str(path)) from None


def _guarded(reader, path: Path, key: str, kind: str):
    """``reader(path, key)``; any exception but a ConfigError becomes one ConfigError line."""
    try:
        return reader(path, key)
    except ConfigError:
        raise
    except Exception as e:  # corrupt files raise many kinds
        raise ConfigError(key, f"a readable {kind} file", got=f"{path} ({type(e).__name__}: {_one_line(e)})") from None


def _convert(array: np.ndarray, dtype, key: str, path) -> np.ndarray:
    try:
        target = np.dtype(dtype)
    except TypeError:
        raise ConfigError(key, "a numpy dtype (e.g. numpy.float32)", got=f"{path} (dtype={dtype!r})") from None
    if target != array.dtype:
        check_memory(key, float(array.size) * target.itemsize, f"{path} as {target}", got=str(path))
    return array.astype(target, copy=False)


def _read_nifti(path: Path, key: str):
    nib = _optional("nibabel", key, path)
    img = nib.load(str(path))
    shape = tuple(int(n) for n in img.shape)
    while len(shape) > 3 and shape[-1] == 1:  # (x, y, z, 1): one volume
        shape = shape[:-1]
    if len(shape) != 3:
        raise ConfigError(key, "a 3-D NIfTI image (4-D only with one volume)", got=f"{path} (shape {img.shape})")
    proxy = img.dataobj
    slope, inter = float(getattr(proxy, "slope", 1.0)), float(getattr(proxy, "inter", 0.0))
    scaled = hasattr(proxy, "get_unscaled") and (slope != 1.0 or inter != 0.0)
    raw = np.dtype(img.get_data_dtype())
    out = np.dtype(np.float64 if raw == np.float64 else np.float32) if scaled else raw
    nbytes = math.prod(shape) * (raw.itemsize + (out.itemsize if scaled else 0))
    check_memory(key, nbytes, f"the NIfTI image of {shape[0]} x {shape[1]} x {shape[2]} voxels", got=str(path))
    if scaled:  # value = stored * scl_slope + scl_inter, in float32 (float64 for float64 storage)
        array = np.asarray(proxy.get_unscaled()).astype(out)
        array *= out.type(slope)
        array += out.type(inter)
    else:
        array = np.asanyarray(proxy)
    array = np.asarray(array).reshape(shape)
    unit = img.header.get_xyzt_units()[0] or "unknown"
    affine = _RAS_TO_LPS @ np.asarray(img.affine, dtype=np.float64)
    affine[:3] *= _NIFTI_UNITS.get(unit, 1e-3)
    return array, affine


def _read_nrrd(path: Path, key: str):
    nrrd = _optional("nrrd", key, path)
    header = nrrd.read_header(str(path))
    sizes = [int(n) for n in np.atleast_1d(header.get("sizes", []))]
    if int(header.get("dimension", len(sizes))) != 3 or len(sizes) != 3:
        raise ConfigError(key, "a 3-D scalar NRRD (dimension: 3)", got=f"{path} (sizes {sizes})")
    space = str(header.get("space", "")).strip()
    frame = _NRRD_SPACES.get(space.lower())
    if frame is None:
        raise ConfigError(
            key,
            "an NRRD space of left-posterior-superior (LPS) or right-anterior-superior (RAS)",
            got=f"{path} (space: {space or 'missing'})",
        )
    if "space directions" not in header:
        raise ConfigError(key, "an NRRD with 'space directions'", got=f"{path} (no space directions)")
    dirs = np.asarray(header["space directions"], dtype=np.float64)
    if dirs.shape != (3, 3) or not np.isfinite(dirs).all():
        raise ConfigError(key, "three spatial axes in 'space directions' (no 'none')", got=f"{path} ({dirs.tolist()})")
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ConfigError(key, "a 'space origin' of three finite numbers", got=f"{path} ({origin.tolist()})")
    units = [str(u).strip().lower() for u in header.get("space units", ["mm"] * 3)]
    if len(set(units)) != 1 or units[0] not in _NRRD_UNITS:
        raise ConfigError(key, "'space units' of one length unit (mm, m, cm, um)", got=f"{path} ({units})")
    itemsize = _NRRD_BYTES.get(str(header.get("type", "")).strip().lower(), 1)
    check_memory(key, math.prod(sizes) * itemsize, f"the NRRD image of {sizes} voxels", got=str(path))
    array, _ = nrrd.read(str(path), index_order="F")  # axis r of the array is row r of 'space directions'
    affine = np.eye(4)
    affine[:3, :3] = dirs.T
    affine[:3, 3] = origin
    if frame == "RAS":
        affine = _RAS_TO_LPS @ affine
    affine[:3] *= _NRRD_UNITS[units[0]]
    return np.asarray(array), affine


def _read_numpy(path: Path, suffix: str, key: str, spacing, origin, direction):
    if suffix == ".npy":
        array, stored = _guarded(_load_npy, path, key, ".npy"), {}
    else:
        array, stored = _guarded(_load_npz, path, key, ".npz")
    spacing = spacing if spacing is not None else stored.get("spacing")
    if spacing is None:
        where = "read_image(..., spacing=...)" + ("" if suffix == ".npy" else " or an array 'spacing' in the .npz")
        raise ConfigError(key, f"the voxel spacing in metres (one number or three): {where}", got=str(path))
    spacing = _numbers(spacing, (3,), "spacing", key, path, scalar=True)
    if not (spacing > 0).all():
        raise ConfigError(key, "a positive spacing in metres", got=f"{path} (spacing {spacing.tolist()})")
    if (spacing > 0.05).any():
        warnings.warn(
            f"{path}: {key}: spacing {spacing.tolist()} is in metres: voxels above 5 cm look like millimetres",
            ConfigWarning,
            stacklevel=3,
        )
    origin = origin if origin is not None else stored.get("origin", np.zeros(3))
    direction = direction if direction is not None else stored.get("direction", np.eye(3))
    affine = np.eye(4)
    affine[:3, :3] = _numbers(direction, (3, 3), "direction", key, path) * spacing
    affine[:3, 3] = _numbers(origin, (3,), "origin", key, path)
    return array, affine


def _numbers(value, shape: tuple, name: str, key: str, path, *, scalar: bool = False) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is not None and scalar and arr.ndim == 0:
        arr = np.full(shape, float(arr))
    if arr is None or arr.shape != shape or not np.isfinite(arr).all():
        what = {"spacing": "one number or three (metres)", "origin": "3 numbers (metres)"}.get(name, "a 3 x 3 matrix")
        raise ConfigError(key, f"{name}: {what}, finite", got=f"{path} ({name} {value!r})")
    return arr


def _load_npy(path: Path, key: str) -> np.ndarray:
    try:
        mapped = np.load(path, mmap_mode="r", allow_pickle=False)  # the header only, until copied
    except ValueError:  # an empty array cannot be mapped
        return np.load(path, allow_pickle=False)
    check_memory(key, float(mapped.nbytes), f"the array of shape {mapped.shape}", got=str(path))
    return np.array(mapped)


_NPZ_GEOMETRY = ("spacing", "origin", "direction")


def _load_npz(path: Path, key: str):
    with np.load(path, allow_pickle=False) as z:
        names = list(z.files)
        data = [n for n in names if n not in _NPZ_GEOMETRY]
        name = "array" if "array" in names else (data[0] if len(data) == 1 else None)
        if name is None:
            raise ConfigError(
                key,
                "an .npz with an array named 'array' (or one array besides spacing, origin, direction)",
                got=f"{path} (arrays {names})",
            )
        nbytes = _npz_nbytes(z, name)
        if nbytes is not None:
            check_memory(key, nbytes, f"the array '{name}'", got=str(path))
        return z[name], {n: z[n] for n in _NPZ_GEOMETRY if n in names}


def _npz_nbytes(z, name: str) -> float | None:
    """Bytes of an ``.npz`` member, from its header (None when it cannot be read)."""
    try:
        with z.zip.open(f"{name}.npy") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(f)
        return float(math.prod(shape)) * np.dtype(dtype).itemsize
    except Exception:
        return None


# ------------------------------------------------------------------ DICOM series
def _read_dicom(folder: Path, key: str):
    pydicom = _optional("pydicom", key, folder)
    slices = _dicom_headers(pydicom, folder, key)
    _one_series(slices, folder, key)
    geom = _dicom_geometry(slices, folder, key)
    order = geom["order"]
    rows, cols, n = geom["rows"], geom["cols"], len(order)
    slopes = [_scalar(slices[i][1], "RescaleSlope", 1.0, folder, key, slices[i][0]) for i in order]
    inters = [_scalar(slices[i][1], "RescaleIntercept", 0.0, folder, key, slices[i][0]) for i in order]
    rescaled = any(s != 1.0 for s in slopes) or any(b != 0.0 for b in inters)
    itemsize = 4 if rescaled else max(1, int(slices[order[0]][1].get("BitsAllocated", 16)) // 8)
    check_memory(
        key, float(rows * cols * n * itemsize), f"a DICOM series of {cols} x {rows} x {n} voxels", got=str(folder)
    )
    pixels = _dicom_pixels(pydicom, slices[order[0]][0], rows, cols, folder, key)
    array = np.empty((cols, rows, n), dtype=np.float32 if rescaled else pixels.dtype)
    for k, i in enumerate(order):
        if k > 0:
            pixels = _dicom_pixels(pydicom, slices[i][0], rows, cols, folder, key)
        if rescaled:  # HU = stored * RescaleSlope + RescaleIntercept
            array[:, :, k] = pixels.T.astype(np.float32) * np.float32(slopes[k]) + np.float32(inters[k])
        else:
            array[:, :, k] = pixels.T  # (row, column) -> (i, j) = (column, row)
    return array, geom["affine"]


def _dicom_headers(pydicom, folder: Path, key: str) -> list:
    """``(file, dataset without pixels)`` of every DICOM image in ``folder`` (other files skipped)."""
    from pydicom.errors import InvalidDicomError

    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    found = []
    for p in files:
        try:
            ds = pydicom.dcmread(str(p), stop_before_pixels=True)
        except InvalidDicomError:  # no DICM preamble: not a DICOM file (a README, a thumbnail)
            continue
        except Exception as e:
            raise ConfigError(
                key, "readable DICOM files", got=f"{folder} ({p.name}: {type(e).__name__}: {_one_line(e)})"
            ) from None
        if "Rows" in ds:  # an image; DICOMDIR, reports and other objects are skipped
            found.append((p, ds))
    if not found:
        raise ConfigError(
            key,
            "a folder holding one DICOM series (image files with the DICM preamble)",
            got=f"{folder} (no DICOM image among {len(files)} files)",
        )
    return found


def _one_series(slices: list, folder: Path, key: str) -> None:
    series: dict = {}
    for p, ds in slices:
        series.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append(p.name)
    if len(series) > 1:
        counts = ", ".join(f"{uid or 'no UID'}: {len(names)} files" for uid, names in sorted(series.items()))
        raise ConfigError(
            key,
            "one DICOM series per folder (one SeriesInstanceUID)",
            got=f"{folder} ({len(series)} SeriesInstanceUIDs: {counts})",
        )


def _values(ds, name: str, n: int, folder: Path, key: str, p: Path) -> np.ndarray:
    value = ds.get(name)
    try:
        arr = np.array([float(v) for v in (value if n > 1 else [value])], dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (n,) or not np.isfinite(arr).all():
        raise ConfigError(key, f"DICOM slices with {name} ({n} numbers)", got=f"{folder} ({p.name}: {name} {value!r})")
    return arr


def _scalar(ds, name: str, default: float, folder: Path, key: str, p: Path) -> float:
    if ds.get(name) in (None, ""):
        return default
    return float(_values(ds, name, 1, folder, key, p)[0])


def _dicom_geometry(slices: list, folder: Path, key: str) -> dict:
    """Slice order, size and affine (LPS metres) of one series, after checking that its slices agree."""
    p0, ds0 = slices[0]
    rows, cols = int(ds0.Rows), int(ds0.Columns)
    iop = _values(ds0, "ImageOrientationPatient", 6, folder, key, p0)
    spacing = _values(ds0, "PixelSpacing", 2, folder, key, p0)  # (between rows, between columns) mm
    positions = []
    for p, ds in slices:
        if int(ds.get("NumberOfFrames", 1) or 1) != 1:
            raise ConfigError(key, "one frame per DICOM file", got=f"{folder} ({p.name}: {ds.NumberOfFrames} frames)")
        for name, value, ref in (
            ("ImageOrientationPatient", _values(ds, "ImageOrientationPatient", 6, folder, key, p), iop),
            ("PixelSpacing", _values(ds, "PixelSpacing", 2, folder, key, p), spacing),
            ("Rows, Columns", np.array([int(ds.Rows), int(ds.Columns)]), np.array([rows, cols])),
        ):
            if np.abs(value - ref).max() > _SAME * max(1.0, float(np.abs(ref).max())):
                raise ConfigError(
                    key,
                    f"slices that agree on {name}",
                    got=f"{folder} ({p0.name}: {ref.tolist()}, {p.name}: {value.tolist()})",
                )
        positions.append(_values(ds, "ImagePositionPatient", 3, folder, key, p))
    r, c = iop[:3], iop[3:]
    if abs(np.linalg.norm(r) - 1) > 1e-3 or abs(np.linalg.norm(c) - 1) > 1e-3 or abs(r @ c) > 1e-3:
        raise ConfigError(
            key, "an ImageOrientationPatient of two orthogonal unit vectors", got=f"{folder} ({iop.tolist()})"
        )
    if not (spacing > 0).all():
        raise ConfigError(key, "a positive PixelSpacing", got=f"{folder} ({p0.name}: {spacing.tolist()})")
    normal = np.cross(r, c)
    normal /= np.linalg.norm(normal)
    pos = np.array(positions)
    order = np.argsort(pos @ normal, kind="stable")
    names = [slices[i][0].name for i in order]
    step = _slice_step(pos[order], normal, names, slices[0][1], folder, key)
    affine = np.eye(4)
    affine[:3, 0] = r * spacing[1]
    affine[:3, 1] = c * spacing[0]
    affine[:3, 2] = step
    affine[:3, 3] = pos[order[0]]
    affine[:3] *= 1e-3  # mm -> m
    return {"order": [int(i) for i in order], "rows": rows, "cols": cols, "affine": affine}


def _slice_step(pos: np.ndarray, normal: np.ndarray, names: list, ds0, folder: Path, key: str) -> np.ndarray:
    """The LPS step [mm] from one slice to the next, after checking even gaps; ``pos`` sorted along ``normal``."""
    n = len(pos)
    if n == 1:  # one slice: the thickness is all there is
        for name in ("SpacingBetweenSlices", "SliceThickness"):
            value = ds0.get(name)
            if value not in (None, "") and float(value) > 0:
                return normal * float(value)
        raise ConfigError(
            key, "a slice spacing: two or more slices, or SliceThickness", got=f"{folder} (one slice, no thickness)"
        )
    s = pos @ normal
    gaps = np.diff(s)
    for k in np.flatnonzero(gaps <= 1e-4):
        raise ConfigError(
            key,
            "one slice per position (no duplicates)",
            got=f"{folder} ({names[k]} and {names[k + 1]} both at {_mm(pos[k])})",
        )
    median = float(np.median(gaps))
    for k in np.flatnonzero(np.abs(gaps - median) > _EVEN * median):
        if gaps[k] > median:
            missing = max(1, round(gaps[k] / median) - 1)
            detail = (
                f"{missing} slice{'s are' if missing > 1 else ' is'} missing at {_mm(pos[k] + normal * median)}, "
                f"between {names[k]} and {names[k + 1]}: gap {gaps[k]:.4g} mm, median {median:.4g} mm"
            )
        else:
            detail = f"gap {gaps[k]:.4g} mm between {names[k]} and {names[k + 1]}, median {median:.4g} mm"
        raise ConfigError(key, "evenly spaced slices (none missing, gaps within 1 %)", got=f"{folder} ({detail})")
    step = (pos[-1] - pos[0]) / (n - 1)  # along the normal, plus any gantry tilt
    off = np.linalg.norm(pos - (pos[0] + np.arange(n)[:, None] * step), axis=1)
    if off.max() > _EVEN * np.linalg.norm(step):
        k = int(off.argmax())
        raise ConfigError(
            key,
            "slice positions on one straight line",
            got=f"{folder} ({names[k]} at {_mm(pos[k])} is {off[k]:.3g} mm off the line of the others)",
        )
    return step


def _mm(p) -> str:
    return "LPS (" + ", ".join(f"{v:.6g}" for v in p) + ") mm"


def _dicom_pixels(pydicom, p: Path, rows: int, cols: int, folder: Path, key: str) -> np.ndarray:
    try:
        pixels = pydicom.dcmread(str(p)).pixel_array
    except Exception as e:  # compressed data without a decoder, truncated files
        raise ConfigError(
            key,
            "DICOM slices whose pixel data pydicom can decode",
            got=f"{folder} ({p.name}: {type(e).__name__}: {_one_line(e)})",
        ) from None
    if pixels.shape != (rows, cols):
        raise ConfigError(
            key, f"one frame of {rows} x {cols} pixels per slice", got=f"{folder} ({p.name}: shape {pixels.shape})"
        )
    return pixels


# ------------------------------------------------------------------ writing
def write_nifti(path, array, affine, *, key: str = "--out") -> None:
    """Write a NIfTI-1 file (``.nii`` or ``.nii.gz``) from voxels and their LPS-metre affine, whole or not at all.

    The header gets the RAS millimetre affine ``diag(-1e3, -1e3, 1e3, 1) @ affine`` as the sform
    (code 1, scanner) and, when the voxel axes are orthogonal, as the qform too (code 1; otherwise
    qform code 0: a quaternion cannot hold a shear); units mm. Booleans are stored as uint8,
    int64 as int32 (when the values fit), float16 as float32.

    Args:
        path: the output file, ``.nii`` or ``.nii.gz``, in an existing folder.
        array: ``(I, J, K)`` voxels (numpy or torch), numeric and finite.
        affine: ``(4, 4)`` voxel index -> LPS metres (see :class:`Image`).
        key: the option that named ``path``, for messages.

    Raises:
        ConfigError: a wrong suffix, an invalid array or affine, int64 values beyond int32.
        OutputError: the write failed (an earlier file at ``path`` is kept).

    Examples:
        >>> import numpy as np
        >>> import nibabel as nib
        >>> path = getfixture("tmp_path") / "ct.nii"
        >>> write_nifti(path, np.zeros((2, 2, 2), np.int16), np.diag([1e-3, 1e-3, 3e-3, 1.0]))
        >>> nib.load(path).affine.diagonal().tolist()          # RAS millimetres
        [-1.0, -1.0, 3.0, 1.0]
    """
    path = Path(path)
    if _suffix(path) not in _NIFTI:
        raise ConfigError(key, "an output file ending in .nii or .nii.gz", got=str(path))
    image = _image(array, affine, path, key)
    nib = _optional("nibabel", key, path)
    data = _nifti_data(image.array, key, path)
    ras = np.diag([-1e3, -1e3, 1e3, 1.0]) @ image.affine
    img = nib.Nifti1Image(data, ras)
    img.set_sform(ras, code=1)
    if _orthogonal_columns(image.affine[:3, :3]):
        img.set_qform(ras, code=1)
    else:
        img.set_qform(None, code=0)
    img.header.set_xyzt_units("mm")
    with atomic_path(path, key=key) as tmp:
        nib.save(img, str(tmp))


def _orthogonal_columns(m: np.ndarray, tol: float = 1e-6) -> bool:
    u = m / np.linalg.norm(m, axis=0)
    return bool(np.abs(u.T @ u - np.eye(3)).max() <= tol)


def _nifti_data(arr: np.ndarray, key: str, path: Path) -> np.ndarray:
    if arr.dtype == np.bool_:
        return arr.astype(np.uint8)
    if arr.dtype == np.float16:
        return arr.astype(np.float32)
    if arr.dtype.kind in "iu" and arr.dtype.itemsize == 8:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < np.iinfo(np.int32).min or hi > np.iinfo(np.int32).max:
            raise ConfigError(key, "integer voxels within int32 for NIfTI", got=f"{path} (range {lo} .. {hi})")
        return arr.astype(np.int32)
    return arr


def write_dicom_series(
    folder,
    array,
    affine,
    *,
    slope: float = 1.0,
    intercept: float = 0.0,
    modality: str = "CT",
    series_uid: str | None = None,
    file_names=None,
    rng=None,
    key: str = "--out",
) -> None:
    """Write a DICOM series, one file per slice ``k``, whole or not at all.

    Each file is a minimal CT (or MR) Image Storage dataset, explicit VR little endian, 16-bit
    stored values ``round((value - intercept) / slope)`` (signed, PixelRepresentation 1; unsigned
    when the values need 32768 .. 65535), with ``ImagePositionPatient = origin + k * A[:3, 2]``,
    ``ImageOrientationPatient`` the unit first and second columns of the affine, ``PixelSpacing``
    (row spacing, column spacing) their lengths, ``SliceThickness`` the slice spacing, all in mm.
    Pixel (row j, column i) of file ``k`` is ``array[i, j, k]``: :func:`read_image` of the folder
    gives back the array (to the quantisation ``slope / 2``) and the affine.

    The folder is filled under a hidden temporary name beside it and renamed at the end; an
    existing folder is replaced only when it holds nothing but ``.dcm`` files (an earlier series).

    Args:
        folder: the series folder (its parent must exist).
        array: ``(I, J, K)`` values (HU for CT), numpy or torch, finite; ``I`` columns, ``J`` rows.
        affine: ``(4, 4)`` voxel index -> LPS metres; its first two columns must be orthogonal and
            its third column the slice normal ``unit(A[:, 0]) x unit(A[:, 1])`` times the slice
            spacing (DICOM slices are planes stacked along their normal; flip the array's ``k``
            axis for the opposite direction).
        slope: ``RescaleSlope`` (non-zero); the value of one stored step.
        intercept: ``RescaleIntercept``.
        modality: ``"CT"`` (CT Image Storage) or ``"MR"`` (MR Image Storage).
        series_uid: the ``SeriesInstanceUID`` (default: a new UID).
        file_names: ``K`` plain file names, one per slice ``k`` (default ``slice_0000.dcm`` ...).
        rng: a seed or ``numpy.random.Generator`` for reproducible UIDs (default: random UIDs).
        key: the option that named ``folder``, for messages.

    Raises:
        ConfigError: pydicom missing, an invalid array or affine, axes DICOM cannot store, stored
            values beyond 16 bits, a bad slope, modality or file names, a folder holding other files.
        OutputError: the write failed (an earlier series is kept).

    Examples:
        >>> import numpy as np
        >>> folder = getfixture("tmp_path") / "ct"
        >>> hu = np.full((4, 3, 2), -1000.0)                      # (columns, rows, slices)
        >>> affine = np.diag([0.5e-3, 0.5e-3, 2e-3, 1.0])
        >>> write_dicom_series(folder, hu, affine, slope=0.5, intercept=-1024.0, rng=0)
        >>> sorted(p.name for p in folder.iterdir())
        ['slice_0000.dcm', 'slice_0001.dcm']
        >>> image = read_image(folder)
        >>> image.array.dtype, image.shape, float(image.array.max()), np.allclose(image.affine, affine)
        (dtype('float32'), (4, 3, 2), -1000.0, True)
    """
    folder = Path(folder)
    pydicom = _optional("pydicom", key, folder)
    image = _image(array, affine, folder, key)
    if modality not in _DICOM_SOP:
        raise ConfigError(key, "modality 'CT' or 'MR'", got=f"{folder} (modality {modality!r})")
    if not (math.isfinite(slope) and slope != 0 and math.isfinite(intercept)):
        raise ConfigError(
            key,
            "a finite non-zero slope and a finite intercept",
            got=f"{folder} (slope {slope}, intercept {intercept})",
        )
    frame = _dicom_frame(image.affine, folder, key)
    stored, signed = _stored_values(image.array, slope, intercept, folder, key)
    names = _slice_names(file_names, image.shape[2], folder, key)
    _check_series_folder(folder, key)
    uid = _uid_maker(pydicom, rng)
    common = {
        "study": uid(),
        "series": series_uid or uid(),
        "frame": uid(),
        "modality": modality,
        "slope": slope,
        "intercept": intercept,
        "signed": signed,
    }
    stage = folder.parent / f"{STAGING}{os.getpid()}-{folder.name}"
    try:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir()
        for k, name in enumerate(names):
            ds = _slice_dataset(pydicom, stored[:, :, k], k, frame, common, uid())
            _save_dataset(pydicom, ds, stage / name)
        _swap_in(stage, folder)
    except OSError as e:
        kept = "the earlier series is kept" if folder.exists() else "nothing was written"
        raise OutputError(f"{folder}: writing the DICOM series failed ({e.strerror or e}); {kept}") from e
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _dicom_frame(affine: np.ndarray, folder: Path, key: str) -> dict:
    """Orientation, spacings and slice positions (mm) of an affine DICOM can store, else a ConfigError."""
    m = affine[:3, :3] * 1e3  # mm
    col_step, row_step = np.linalg.norm(m[:, 0]), np.linalg.norm(m[:, 1])
    r, c = m[:, 0] / col_step, m[:, 1] / row_step
    if abs(r @ c) > 1e-6:
        raise ConfigError(
            key,
            "an affine whose first two columns are orthogonal (DICOM stores one in-plane orientation)",
            got=f"{folder} (cosine {r @ c:.3g} between them)",
        )
    normal = np.cross(r, c)
    normal /= np.linalg.norm(normal)
    gap = float(m[:, 2] @ normal)
    if gap <= 0 or np.linalg.norm(m[:, 2] - gap * normal) > 1e-6 * np.linalg.norm(m[:, 2]):
        raise ConfigError(
            key,
            "an affine whose third column is the slice normal (first x second column) times the slice "
            "spacing (flip the array's k axis for the opposite direction)",
            got=f"{folder} (third column {m[:, 2].round(6).tolist()} mm, normal {normal.round(6).tolist()})",
        )
    return {
        "orientation": [*r.tolist(), *c.tolist()],
        "pixel_spacing": [float(row_step), float(col_step)],
        "thickness": gap,
        "origin": affine[:3, 3] * 1e3,
        "step": m[:, 2],
        "normal": normal,
    }


def _stored_values(values: np.ndarray, slope: float, intercept: float, folder: Path, key: str):
    """``round((value - intercept) / slope)`` as int16 (signed) or uint16, and whether it is signed."""
    q = np.rint((values.astype(np.float64) - intercept) / slope)
    lo, hi = float(q.min()), float(q.max())
    if lo >= -32768 and hi <= 32767:
        return q.astype(np.int16), True
    if lo >= 0 and hi <= 65535:
        return q.astype(np.uint16), False
    raise ConfigError(
        key,
        "stored values within 16 bits: choose slope and intercept so that (value - intercept) / slope "
        "lies in -32768 .. 32767 (or 0 .. 65535)",
        got=f"{folder} (stored range {lo:.0f} .. {hi:.0f} with slope {slope}, intercept {intercept})",
    )


def _slice_names(file_names, n: int, folder: Path, key: str) -> list:
    if file_names is None:
        return [f"slice_{k:04d}.dcm" for k in range(n)]
    names = [str(s) for s in file_names]
    plain = all(s and s == Path(s).name and not s.startswith(".") for s in names)
    if len(names) != n or len(set(names)) != n or not plain:
        raise ConfigError(
            key,
            f"{n} distinct plain file names, one per slice (no folders, not hidden)",
            got=f"{folder} ({len(names)} names, {len(set(names))} distinct)",
        )
    return names


def _check_series_folder(folder: Path, key: str) -> None:
    if not folder.parent.is_dir():
        raise ConfigError(
            key, "a series folder in an existing folder", got=f"{folder} ({folder.parent} does not exist)"
        )
    if folder.exists() and not folder.is_dir():
        raise ConfigError(key, "a folder for the series, not a file", got=str(folder))
    if folder.is_dir():
        others = sorted(p.name for p in folder.iterdir() if not (p.is_file() and p.suffix.lower() == ".dcm"))
        if others:
            raise ConfigError(
                key,
                "a new folder, or one holding only .dcm files (an earlier series, replaced)",
                got=f"{folder} (holds {', '.join(others[:3])}{' ...' if len(others) > 3 else ''})",
            )


def _uid_maker(pydicom, rng):
    from pydicom.uid import generate_uid

    if rng is None:
        return generate_uid
    gen = np.random.default_rng(rng)
    return lambda: generate_uid(entropy_srcs=[str(int(gen.integers(0, 2**63 - 1)))])


def _ds(value: float) -> str:
    """A Decimal String of at most 16 characters (DICOM's limit) with the most digits that fit."""
    from pydicom.valuerep import format_number_as_ds

    return format_number_as_ds(float(value) + 0.0)  # + 0.0: no "-0.0"


def _slice_dataset(pydicom, pixels: np.ndarray, k: int, frame: dict, common: dict, sop_uid: str):
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian

    sop_class = _DICOM_SOP[common["modality"]]
    meta = FileMetaDataset()
    meta.FileMetaInformationVersion = b"\x00\x01"
    meta.MediaStorageSOPClassUID = UID(sop_class)
    meta.MediaStorageSOPInstanceUID = UID(sop_uid)
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = common["study"]
    ds.SeriesInstanceUID = common["series"]
    ds.FrameOfReferenceUID = common["frame"]
    ds.Modality = common["modality"]
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL"]
    for name in _TYPE2:
        setattr(ds, name, "")
    ds.SeriesNumber = 1
    ds.InstanceNumber = k + 1
    position = frame["origin"] + k * frame["step"]
    ds.ImagePositionPatient = [_ds(v) for v in position]
    ds.ImageOrientationPatient = [_ds(v) for v in frame["orientation"]]
    ds.PixelSpacing = [_ds(v) for v in frame["pixel_spacing"]]
    ds.SliceThickness = _ds(frame["thickness"])
    ds.SliceLocation = _ds(position @ frame["normal"])
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = int(pixels.shape[1]), int(pixels.shape[0])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 1 if common["signed"] else 0
    ds.RescaleSlope = _ds(common["slope"])
    ds.RescaleIntercept = _ds(common["intercept"])
    if common["modality"] == "CT":
        ds.RescaleType = "HU"
    image = np.ascontiguousarray(pixels.T)  # (i, j) -> (row j, column i)
    ds.add_new(0x7FE00010, "OW", image.astype("<i2" if common["signed"] else "<u2").tobytes())
    return ds


def _save_dataset(pydicom, ds, path: Path) -> None:
    if int(pydicom.__version__.split(".")[0]) >= 3:
        ds.save_as(str(path), enforce_file_format=True)
    else:  # pydicom 2: the encoding is set on the dataset
        ds.is_little_endian, ds.is_implicit_VR = True, False
        ds.save_as(str(path), write_like_original=False)


def _swap_in(stage: Path, folder: Path) -> None:
    """Rename the filled ``stage`` onto ``folder``; an earlier ``folder`` is removed only after."""
    if not folder.exists():
        os.rename(stage, folder)
        return
    old = folder.parent / f"{STAGING}{os.getpid()}-old-{folder.name}"
    shutil.rmtree(old, ignore_errors=True)
    os.rename(folder, old)
    try:
        os.rename(stage, folder)
    except OSError:
        os.rename(old, folder)
        raise
    shutil.rmtree(old, ignore_errors=True)
