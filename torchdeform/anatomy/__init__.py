"""From images to bodies: label volumes, DICOM series, resampling with the affine, tissues per label.

Every position is in metres in the patient frame LPS (x to the patient's Left, y Posterior, z
Superior), the DICOM frame; the lattice axes (D, H, W) of torchdeform's grids are LPS (x, y, z).
File formats that use other frames or units (NIfTI's RAS millimetres, NRRD's ``space``) are
converted once, where the file is read or written.

=====================  ===========================================================================
:mod:`.images`         :class:`Image` (voxels and their 4 x 4 affine to LPS metres),
                       :func:`read_image` (NIfTI, NRRD, ``.npy``/``.npz``, DICOM series),
                       :func:`write_nifti`, :func:`write_dicom_series`
:mod:`.labels`         :func:`body_from_labels`: a lattice body of a label volume, a tissue per
                       label, series moduli across labels, partial-volume fill, fixed labels
                       (:class:`LabelBody`, :class:`Tissue`)
:mod:`.frame`          look-ups of voxels at lattice points, :func:`resample_image` (a CT onto the
                       lattice's axes)
:mod:`.phantom`        :func:`abdominal_phantom`: a procedural abdomen (liver, tumour, vessel, bone,
                       torso) as labels and a CT in HU, and its tissues (:data:`PHANTOM_TISSUES`)
:mod:`.commands`       ``torchdeform data phantom --labels DIR``: the phantom as NIfTI and DICOM
=====================  ===========================================================================

Example:
    >>> import numpy as np
    >>> from torchdeform.anatomy import read_image
    >>> path = getfixture("tmp_path") / "labels.npy"
    >>> np.save(path, np.zeros((4, 5, 6), np.uint8))
    >>> image = read_image(path, spacing=0.002)       # 2 mm voxels, given in metres
    >>> image.shape, image.spacing.tolist()
    ((4, 5, 6), [0.002, 0.002, 0.002])
"""

from .frame import resample_image
from .images import Image, read_image, write_dicom_series, write_nifti
from .labels import LabelBody, Tissue, body_from_labels
from .phantom import PHANTOM_BACKGROUND, PHANTOM_FIXED, PHANTOM_TISSUES, abdominal_phantom

__all__ = [
    "Image",
    "read_image",
    "write_nifti",
    "write_dicom_series",
    "body_from_labels",
    "LabelBody",
    "Tissue",
    "resample_image",
    "abdominal_phantom",
    "PHANTOM_TISSUES",
    "PHANTOM_FIXED",
    "PHANTOM_BACKGROUND",
]
