"""Command-line code of anatomy: ``torchdeform data phantom --labels DIR``.

``torchdeform data phantom --labels DIR [--voxel 0.001] [--seed 0] [--dicom | --no-dicom]`` writes
the abdominal phantom (:func:`~torchdeform.anatomy.phantom.abdominal_phantom`) into the folder
``DIR``, which must be new or empty:

* ``labels.nii.gz``: uint8 labels (0 air, 1 liver, 2 tumour, 3 spine, 4 vessel, 5 soft tissue);
* ``ct.nii.gz``: the CT, float32 HU;
* ``ct_dicom/``: the CT as a DICOM series, one file per axial slice (16-bit, slope 1, intercept
  -1024: HU rounded to integers), unless ``--no-dicom``. The labels are not written as DICOM (a
  segmentation is not a CT image; NIfTI is what segmentation tools read and write).

All three share one affine (LPS metres; NIfTI stores it as RAS millimetres), so :func:`read_image`
of any of them gives the same geometry. The files are written into a hidden sibling folder that is
renamed to ``DIR`` at the end: a failed or interrupted run leaves nothing behind. A folder that
holds anything, a ``DIR`` that is a file and a missing nibabel or pydicom are refused before any
work with one line and exit status 2.
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

from ..errors import ConfigError
from ..options import integer, number
from ..outputs import STAGING, OutputError

__all__ = ["add_phantom_arguments", "phantom_command"]

_KEY = "--labels"


def add_phantom_arguments(subparsers) -> None:
    """Add ``phantom`` to the sub-parsers of ``torchdeform data`` (``--labels DIR``, ``--voxel``, ``--seed``, ``--dicom``)."""
    from .phantom import VOXEL_RANGE

    p = subparsers.add_parser(
        "phantom", help="an abdominal phantom: labels and CT (NIfTI) and the CT as DICOM, into a new folder"
    )
    p.add_argument(
        _KEY, required=True, metavar="DIR", help="output folder, new or empty: labels.nii.gz, ct.nii.gz, ct_dicom/"
    )
    p.add_argument(
        "--voxel",
        type=number(lo=VOXEL_RANGE[0], hi=VOXEL_RANGE[1], unit="m"),
        default=0.001,
        help="voxel size along x and y in metres (slices along z twice as thick); default 0.001",
    )
    p.add_argument("--seed", type=integer(lo=0), default=0, help="seed of the CT noise (10 HU); default 0")
    p.add_argument(
        "--dicom",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also write the CT as a DICOM series in ct_dicom/ (default: yes; needs pydicom)",
    )


def _check_out(out: Path) -> None:
    """Refuse a ``--labels`` folder that is a file, not empty, or cannot be created."""
    if out.exists() and not out.is_dir():
        raise ConfigError(_KEY, "a folder (this path is a file)", got=str(out))
    if out.is_dir():
        entries = sorted(p.name for p in out.iterdir())
        if entries:
            shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
            raise ConfigError(
                _KEY,
                f"a new or empty folder (it holds {len(entries)} entries: {shown}); choose another folder",
                got=str(out),
            )
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(_KEY, f"a folder that can be created ({parent} is a file)", got=str(out))
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(_KEY, f"a folder this user can write to ({parent} is not writable)", got=str(out))


def _require(module: str, what: str, out: Path) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise ConfigError(_KEY, what, got=str(out))


def phantom_command(args) -> int:
    """Run ``torchdeform data phantom``: write the phantom's files into ``args.labels``; prints one line.

    Args:
        args: the parsed options: ``labels`` (the output folder), ``voxel`` (m), ``seed``, ``dicom``.

    Returns:
        ``0``. Problems a user can cause raise :class:`~torchdeform.errors.ConfigError` (or
        :class:`~torchdeform.outputs.OutputError` for a failed write), which the command line turns
        into one line and exit status 2, the folder left as it was.

    Example:
        >>> import argparse
        >>> out = getfixture("tmp_path") / "phantom"
        >>> phantom_command(argparse.Namespace(labels=str(out), voxel=0.004, seed=0, dicom=False))
        abdominal phantom 50 x 40 x 20 voxels of 4 x 4 x 8 mm (LPS), seed 0 -> .../phantom: labels.nii.gz (uint8 labels 0-5), ct.nii.gz (HU)
        0
        >>> sorted(p.name for p in out.iterdir())
        ['ct.nii.gz', 'labels.nii.gz']
    """
    from .images import write_dicom_series, write_nifti
    from .phantom import abdominal_phantom

    out = Path(args.labels)
    _check_out(out)
    _require("nibabel", "nibabel for NIfTI files: pip install nibabel (or torchdeform[volume])", out)
    if args.dicom:
        _require("pydicom", "pydicom for the DICOM series: pip install pydicom (or --no-dicom)", out)
    labels, ct = abdominal_phantom(voxel=args.voxel, seed=args.seed)

    parent = out.absolute().parent
    stage = parent / f"{STAGING}{os.getpid()}-{out.name}"
    try:
        parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir()
        write_nifti(stage / "labels.nii.gz", labels.array, labels.affine, key=_KEY)
        write_nifti(stage / "ct.nii.gz", ct.array, ct.affine, key=_KEY)
        if args.dicom:
            write_dicom_series(
                stage / "ct_dicom", ct.array, ct.affine, slope=1.0, intercept=-1024.0, rng=args.seed, key=_KEY
            )
        if out.is_dir():
            out.rmdir()  # empty (checked above); a file put there meanwhile stops the rename
        os.rename(stage, out)
    except OutputError:
        raise
    except OSError as e:
        raise OutputError(f"{out}: writing the phantom failed ({e.strerror or e}); nothing was written") from e
    finally:
        shutil.rmtree(stage, ignore_errors=True)

    mm = " x ".join(f"{s * 1e3:g}" for s in labels.spacing)
    files = "labels.nii.gz (uint8 labels 0-5), ct.nii.gz (HU)"
    if args.dicom:
        files += f", ct_dicom/ ({labels.shape[2]} slices, CT only)"
    shape = " x ".join(str(n) for n in labels.shape)
    print(f"abdominal phantom {shape} voxels of {mm} mm (LPS), seed {args.seed} -> {out}: {files}")
    return 0
