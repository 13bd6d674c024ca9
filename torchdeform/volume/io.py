"""Reading and writing volumes: ``.npy``, ``.npz``, NIfTI (``.nii``, ``.nii.gz``) and NRRD (``.nrrd``).

NIfTI needs ``nibabel`` and NRRD ``pynrrd`` (``pip install torchdeform[volume]``); both are
imported only when such a file is read or written. Axis 0 of the stored array is D, axis 1
H, axis 2 W, whatever the format (no reorientation), so a file written and read back is the
same array. ``phantom`` (optionally ``phantom:N``) names the procedural phantom of
:mod:`torchdeform.volume.phantoms` instead of a file.

Example:
    >>> import numpy as np
    >>> from torchdeform.volume.io import load_volume, save_volume
    >>> path = getfixture("tmp_path") / "v.npy"
    >>> save_volume(path, np.zeros((4, 5, 6), np.float32))
    >>> load_volume(path).shape
    (4, 5, 6)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..checks import check_memory
from ..errors import ConfigError
from ..outputs import atomic_path, require_finite

SUFFIXES = (".npy", ".npz", ".nii", ".nii.gz", ".nrrd", ".nhdr")
_EXTRA = {
    "nibabel": "NIfTI files need nibabel: pip install nibabel (or torchdeform[volume])",
    "nrrd": "NRRD files need pynrrd: pip install pynrrd (or torchdeform[volume])",
}


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in SUFFIXES:
        if name.endswith(s):
            return s
    return path.suffix.lower()


def _optional(module: str, key: str, path):
    try:
        return __import__(module)
    except ImportError:
        raise ConfigError(key, _EXTRA[module], got=str(path)) from None


def check_array(arr, key: str, *, path=None, ndim: int = 3) -> np.ndarray:
    """A real numeric array with ``ndim`` axes and finite values, else a one-line ConfigError."""
    arr = np.asarray(arr)
    where = f"{path}: " if path else ""
    if arr.dtype.kind not in "biuf":
        raise ConfigError(key, "a numeric array (integers or floats)", got=f"{where}dtype {arr.dtype}")
    if arr.ndim != ndim or min(arr.shape, default=0) < 1:
        raise ConfigError(
            key, f"a non-empty {ndim}-D array" + (" (D, H, W)" if ndim == 3 else ""), got=f"{where}shape {arr.shape}"
        )
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise ConfigError(
            key, "finite values (no NaN or inf)", got=f"{where}{int((~np.isfinite(arr)).sum())} non-finite values"
        )
    return arr


def read_array(path, *, key: str = "volume") -> np.ndarray:
    """The raw array stored in a file (any number of axes), by file type."""
    path = Path(path)
    suffix = _suffix(path)
    if suffix not in SUFFIXES:
        raise ConfigError(key, "a .npy, .npz, .nii, .nii.gz or .nrrd file", got=str(path))
    if not path.is_file():
        raise ConfigError(key, "an existing file", got=f"{path} (not found)")
    try:
        if suffix == ".npy":
            return np.load(path, allow_pickle=False)
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                names = list(z.files)
                name = "volume" if "volume" in names else (names[0] if len(names) == 1 else None)
                if name is None:
                    raise ConfigError(
                        key, "an .npz with one array or an array named 'volume'", got=f"{path} (arrays {names})"
                    )
                return z[name]
        if suffix in (".nii", ".nii.gz"):
            nib = _optional("nibabel", key, path)
            return np.asarray(nib.load(str(path)).dataobj)
        nrrd = _optional("nrrd", key, path)
        data, _ = nrrd.read(str(path), index_order="C")
        return data
    except ConfigError:
        raise
    except Exception as e:  # corrupt files raise many kinds
        raise ConfigError(key, f"a readable {suffix} file", got=f"{path} ({type(e).__name__}: {e})") from None


def load_volume(path, *, key: str = "volume") -> np.ndarray:
    """A volume ``(D, H, W)`` as float32 numpy (integers converted, NaN/inf rejected).

    ``path`` may also be ``"phantom"`` or ``"phantom:N"`` (the procedural phantom, ``N^3`` voxels,
    default 128), ``"phantom-lumen[:N]"`` (the same with an air-filled bowel loop, for endoscopy),
    or an array (checked and returned as float32).
    """
    if isinstance(path, np.ndarray):  # already in memory
        return np.ascontiguousarray(check_array(path, key), dtype=np.float32)
    text = str(path)
    if is_phantom(text):
        from .phantoms import phantom

        return phantom(shape=(_phantom_side(text, key),) * 3, lumen=text.startswith("phantom-lumen")).numpy()
    arr = check_array(read_array(path, key=key), key, path=path)
    return np.ascontiguousarray(arr, dtype=np.float32)


def is_phantom(text: str) -> bool:
    """Whether a volume source names the procedural phantom (``phantom[:N]``, ``phantom-lumen[:N]``)."""
    return text.split(":", 1)[0] in ("phantom", "phantom-lumen")


def _phantom_side(text: str, key: str) -> int:
    """N of ``phantom:N`` (128 for ``phantom``), checked: >= 8, and its renders fit in memory."""
    try:
        n = int(text.split(":", 1)[1]) if ":" in text else 128
    except ValueError:
        n = 0
    if n < 8:
        raise ConfigError(key, "phantom[:N] or phantom-lumen[:N] with N >= 8 voxels", got=text)
    # the volume, its warped copy and the render's sample buffers: about 6 float32 copies
    check_memory(key, 24.0 * n**3, f"a phantom of {n}^3 voxels", got=text)
    return n


def check_volume_source(path, key: str = "volume") -> None:
    """Refuse, before any work, a volume that :func:`load_volume` would refuse (reads a file once).

    Examples:
        >>> check_volume_source("phantom:64")
        >>> check_volume_source("phantom:4", "volume.file")
        Traceback (most recent call last):
        ...
        torchdeform.errors.ConfigError: volume.file: expected phantom[:N] or phantom-lumen[:N] with N >= 8 voxels, got 'phantom:4'
    """
    if isinstance(path, np.ndarray):  # already in memory
        return np.ascontiguousarray(check_array(path, key), dtype=np.float32)
    text = str(path)
    if is_phantom(text):
        _phantom_side(text, key)
    else:
        load_volume(path, key=key)


def save_volume(path, volume, *, spacing=(1.0, 1.0, 1.0), key: str = "--out") -> None:
    """Write a ``(D, H, W)`` volume (numpy or torch) by file type; ``spacing`` goes into NIfTI/NRRD headers."""
    path = Path(path)
    arr = volume.detach().cpu().numpy() if hasattr(volume, "detach") else np.asarray(volume)
    suffix = _suffix(path)
    if suffix not in SUFFIXES or suffix == ".nhdr":
        raise ConfigError(key, "an output file ending in .npy, .npz, .nii, .nii.gz or .nrrd", got=str(path))
    if path.parent and not path.parent.exists():
        raise ConfigError(key, "a file in an existing folder", got=str(path))
    require_finite(f"{path.name}: volume", arr, what="d, h, w")
    module = None
    if suffix in (".nii", ".nii.gz"):
        module = _optional("nibabel", key, path)
    elif suffix == ".nrrd":
        module = _optional("nrrd", key, path)
    with atomic_path(path, key=key) as tmp:  # a failed write leaves an earlier file whole
        if suffix == ".npy":
            np.save(tmp, arr)
        elif suffix == ".npz":
            np.savez_compressed(tmp, volume=arr)
        elif suffix in (".nii", ".nii.gz"):
            module.save(module.Nifti1Image(arr, np.diag([*map(float, spacing), 1.0])), str(tmp))
        else:
            module.write(str(tmp), arr, {"spacings": [float(s) for s in spacing]}, index_order="C")


__all__ = ["load_volume", "save_volume", "read_array", "check_array", "SUFFIXES"]
