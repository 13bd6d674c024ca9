r"""A procedural abdominal phantom: a label volume and a CT of a supine patient, in LPS metres.

:func:`abdominal_phantom` draws a crop of an adult abdomen at the level of the liver, the kind of
image a scene of palpation or needle insertion starts from, without shipping a patient's data:

=====  ==============  =========================================================================
label  structure       shape (LPS millimetres; x to the patient's Left, y Posterior, z Superior)
=====  ==============  =========================================================================
0      air             around the patient
1      liver           a soft union of four ellipsoids on the patient's right (x < 0): a right
                       lobe, a thinner anterior left lobe crossing the midline, the right lobe's
                       posterior part and a caudate-like part; moulded to the inside of the
                       abdominal wall (16 mm inside the skin, where the ribs are) and to the
                       vertebral bodies it lies against; about 145 x 115 x 100 mm, with gentle
                       bumps of 1.2 mm
2      tumour          a sphere of 22 mm diameter in the right lobe, centred at x = -45 mm,
                       z = +5 mm, its top 4 mm below the anterior liver surface (the -y side,
                       a subcapsular lesion): pressing on the front of the liver feels it
3      bone            the vertebral column: vertebrae every 32 mm along z (bodies 25 mm tall,
                       38 x 28 mm across, centred at y = +32 mm) with a posterior arch around the
                       spinal canal, a spinous process and transverse processes; and three ribs
                       on the right (9 x 11 mm across, 34 mm apart, descending towards the
                       front) from beside the spine round to the side, their inner surface
                       touching the liver's back and side. Fixed in scenes: the liver lies on them
4      vessel          a portal-vein-like tube of 9 mm diameter running along z through the liver
                       (centred near x = -22 mm, y = +2 mm), cut at the liver's surface
5      soft tissue     the torso: a super-ellipse 192 x 152 mm across (the whole z range), a 7 mm
                       layer of subcutaneous fat around muscle and viscera, the intervertebral
                       discs and the spinal canal; usually background in scenes
=====  ==============  =========================================================================

**The grid.** ``voxel`` metres along x and y and ``2 * voxel`` along z (thicker slices, as in a
CT), direction identity (the DICOM axial orientation: columns to the patient's left, rows
posterior, slices superior), the centre of the volume at the LPS origin; 200 x 160 x 80 voxels
(200 x 160 x 160 mm) at the default ``voxel = 0.001``. The labels and the CT share the affine.

**Labels and partial volume.** Every structure is an implicit function ``d`` (approximately the
signed distance in mm, negative inside: ellipsoids by the gradient-normalised estimate
``k0 (k0 - 1) / k1``, a polynomial smooth minimum of width ``k`` for the liver's lobes,
``min(a, b) - k h^2 / 4`` with ``h = max(k - |a - b|, 0) / k``). A voxel's label is the last
structure, in the order fat, soft tissue, liver, vessel, tumour, discs, bone, whose ``d`` is
negative at the voxel's centre. The CT composites the same structures in the same order with the
fraction of the voxel each covers, ``f = clip(1/2 - d / w, 0, 1)`` for the mean voxel edge ``w``:
``HU <- HU + f (HU_structure - HU)``, so a boundary voxel has a value between its neighbours'
(partial volume) while a voxel one edge inside a structure has the structure's value. Gaussian
noise of 10 HU (seeded) is added last.

**Values** (:data:`PHANTOM_HU`, HU): air -1000, fat -100, 40 for muscle and soft tissue, liver 60,
tumour 30 (hypodense), vessel 160 (contrast-enhanced), bone 700.

**Tissues** (:data:`PHANTOM_TISSUES`, with :data:`PHANTOM_FIXED` and :data:`PHANTOM_BACKGROUND`):
liver from the tissue library (about 3.7 kPa), the tumour a material about 11 times stiffer
(40 kPa: malignant liver lesions are several times stiffer than the parenchyma in
elastography), the vessel a softer blood-filled tube (2 kPa); the bone fixed; air and the torso
left out. As ``[[tissues]]`` of a scene file:

.. code-block:: toml

    [[tissues]]
    label = 1
    tissue = "liver"

    [[tissues]]
    label = 2
    youngs_modulus = 4.0e4
    poisson_ratio = 0.45
    density = 1060.0

    [[tissues]]
    label = 4
    youngs_modulus = 2.0e3
    poisson_ratio = 0.45
    density = 1060.0

    [[tissues]]
    label = 3
    fixed = true

    [[tissues]]
    label = 5
    background = true

The geometry does not depend on ``seed`` (only the noise does); the same seed gives the same
arrays, bit for bit. ``torchdeform data phantom --labels DIR`` writes both images as NIfTI and the
CT as a DICOM series (:mod:`torchdeform.anatomy.commands`).

Example:
    >>> import numpy as np
    >>> from torchdeform.anatomy import abdominal_phantom
    >>> labels, ct = abdominal_phantom(voxel=0.004)               # 4 x 4 x 8 mm voxels
    >>> labels.shape, labels.array.dtype, ct.array.dtype
    ((50, 40, 20), dtype('uint8'), dtype('float32'))
    >>> labels.spacing.tolist(), np.array_equal(labels.affine, ct.affine)
    ([0.004, 0.004, 0.008], True)
    >>> sorted(np.unique(labels.array).tolist())
    [0, 1, 2, 3, 4, 5]
"""

from __future__ import annotations

import math

import numpy as np

from ..checks import check_memory
from ..errors import ConfigError
from .images import Image

__all__ = [
    "abdominal_phantom",
    "PHANTOM_LABELS",
    "PHANTOM_HU",
    "PHANTOM_TISSUES",
    "PHANTOM_FIXED",
    "PHANTOM_BACKGROUND",
    "VOXEL_RANGE",
]

#: the structure of each label
PHANTOM_LABELS = {0: "air", 1: "liver", 2: "tumour", 3: "spine and ribs", 4: "vessel", 5: "soft tissue"}

#: nominal CT values (HU) of the phantom's materials
PHANTOM_HU = {
    "air": -1000.0,
    "fat": -100.0,
    "soft": 40.0,
    "liver": 60.0,
    "tumour": 30.0,
    "vessel": 160.0,
    "bone": 700.0,
}

#: suggested ``tissues=`` of :func:`~torchdeform.anatomy.labels.body_from_labels` for the phantom
#: (liver from the library, about 3.7 kPa; a tumour about 11 times stiffer; a softer vessel)
PHANTOM_TISSUES = {
    1: "liver",
    2: {"youngs_modulus": 4.0e4, "poisson_ratio": 0.45, "density": 1060.0},
    4: {"youngs_modulus": 2.0e3, "poisson_ratio": 0.45, "density": 1060.0},
}
#: the labels whose nodes are fixed (bone: the spine and the ribs)
PHANTOM_FIXED = (3,)
#: the labels left out of a body (air, the torso's fat and muscle)
PHANTOM_BACKGROUND = (0, 5)

#: the voxel sizes (x and y; z is twice as thick) :func:`abdominal_phantom` accepts, metres
VOXEL_RANGE = (0.0005, 0.005)

_EXTENT_MM = (200.0, 160.0, 160.0)  # the field of view along x, y, z
_TORSO = (96.0, 76.0, 2.6)  # super-ellipse semi-axes (mm) and exponent
_FAT_MM = 7.0  # subcutaneous fat
# liver lobes: centre, semi-axes (mm)
_RIGHT_LOBE = ((-40.0, -8.0, 0.0), (48.0, 54.0, 50.0))
_LEFT_LOBE = ((20.0, -36.0, 12.0), (44.0, 22.0, 30.0))
_CAUDATE = ((-14.0, 16.0, 4.0), (24.0, 22.0, 36.0))
_POSTERIOR = ((-48.0, 26.0, 0.0), (46.0, 40.0, 46.0))  # the right lobe's back, against the ribs
_BLEND_MM = (12.0, 10.0, 10.0)  # smooth-union widths: right + left lobe, + caudate, + posterior part
_WALL_MM = 16.0  # the liver stays this far inside the skin (fat, muscle; the ribs' inner surface)
# ribs (right side): half thickness (radial) and half height (z), mm, reaching _RIB_OVERLAP_MM inside
# the liver's limit; from _RIB_ARC[0] to _RIB_ARC[1] rad around the torso from the posterior midline,
# every _RIB_PERIOD_MM along z, descending _RIB_DROP_MM per radian towards the front
_RIB_HALF_MM, _RIB_OVERLAP_MM, _RIB_ARC, _RIB_PERIOD_MM, _RIB_DROP_MM = (4.5, 5.5), 0.5, (0.35, 2.0), 34.0, 12.0
_BUMP_MM = 1.2
# tumour: radius, x and z of its centre, depth of its top below the anterior liver surface (mm)
_TUMOUR_RADIUS_MM, _TUMOUR_XZ_MM, _TUMOUR_TOP_DEPTH_MM = 11.0, (-45.0, 5.0), 4.0
_VESSEL_RADIUS_MM = 4.5
# the vertebral column: body centre (x, y) and semi-axes, vertebra period and heights along z (mm)
_BODY = ((0.0, 32.0), (19.0, 14.0))
_PERIOD_MM, _BODY_HALF_MM, _ARCH_HALF_MM, _PROCESS_HALF_MM = 32.0, 12.5, 10.0, 6.0
_CANAL = ((0.0, 52.0), 7.0, 12.0)  # centre (x, y), inner and outer radius of the arch


# ------------------------------------------------------------------ implicit functions (mm, < 0 inside)
def _ellipsoid(x, y, z, centre, radii):
    """The gradient-normalised distance estimate to an ellipsoid, ``k0 (k0 - 1) / k1``."""
    qx, qy, qz = (x - centre[0]) / radii[0], (y - centre[1]) / radii[1], (z - centre[2]) / radii[2]
    k0 = np.sqrt(qx * qx + qy * qy + qz * qz)
    k1 = np.sqrt((qx / radii[0]) ** 2 + (qy / radii[1]) ** 2 + (qz / radii[2]) ** 2)
    return np.where(k1 > 0, k0 * (k0 - 1) / np.maximum(k1, 1e-12), -min(radii))


def _ellipse(x, y, centre, radii):
    """The same estimate for an elliptic cylinder along z."""
    qx, qy = (x - centre[0]) / radii[0], (y - centre[1]) / radii[1]
    k0 = np.sqrt(qx * qx + qy * qy)
    k1 = np.sqrt((qx / radii[0]) ** 2 + (qy / radii[1]) ** 2)
    return np.where(k1 > 0, k0 * (k0 - 1) / np.maximum(k1, 1e-12), -min(radii))


def _smooth_min(a, b, k: float):
    """Polynomial smooth minimum of width ``k`` (mm): a soft union of two implicit functions."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * (k / 4)


def _torso(x, y, shrink: float):
    """A super-ellipse ``|x / a|^p + |y / b|^p = 1`` shrunk by ``shrink`` mm; radial distance."""
    a, b, p = _TORSO
    g = (np.abs(x / (a - shrink)) ** p + np.abs(y / (b - shrink)) ** p) ** (1 / p)
    r = np.sqrt(x * x + y * y)
    return np.where(g > 0, r * (g - 1) / np.maximum(g, 1e-12), -(b - shrink))


def _liver(x, y, z):
    r = _ellipsoid(x, y, z, *_RIGHT_LOBE)
    left = _ellipsoid(x, y, z, *_LEFT_LOBE)
    caudate = _ellipsoid(x, y, z, *_CAUDATE)
    back = _ellipsoid(x, y, z, *_POSTERIOR)
    d = _smooth_min(_smooth_min(r, left, _BLEND_MM[0]), caudate, _BLEND_MM[1])
    d = _smooth_min(d, back, _BLEND_MM[2])
    bump = np.sin(2 * math.pi * x / 70) * np.sin(2 * math.pi * y / 55 + 1.0) * np.sin(2 * math.pi * z / 60 + 0.5)
    d = d + _BUMP_MM * bump
    column = _ellipse(x, y, *_BODY)
    return np.maximum(np.maximum(d, _torso(x, y, _WALL_MM)), -column)  # inside the wall, beside the column


def _ribs(x, y, z):
    """Ribs on the right: elliptic tubes whose inner surface is the liver's outer limit (they touch it)."""
    phi = np.arctan2(np.abs(x), y)  # 0 at the posterior midline, pi / 2 at the sides, pi in front
    hr, hz = _RIB_HALF_MM
    dr = _torso(x, y, _WALL_MM) - (hr - _RIB_OVERLAP_MM)  # radial, from the rib's centre line
    level = z + _RIB_DROP_MM * phi  # the height of the rib's posterior end
    dz = np.mod(level + _RIB_PERIOD_MM / 2, _RIB_PERIOD_MM) - _RIB_PERIOD_MM / 2
    tube = (np.sqrt((dr / hr) ** 2 + (dz / hz) ** 2) - 1) * min(hr, hz)
    ends = np.maximum(_RIB_ARC[0] - phi, phi - _RIB_ARC[1]) * np.sqrt(x * x + y * y)  # arc length beyond
    three = np.abs(level) - 1.5 * _RIB_PERIOD_MM  # the ribs at the liver's heights: posterior ends at 0, +-P
    return np.maximum(np.maximum(tube, ends), np.maximum(three, x))


def _vessel_axis(z):
    """The tube's centre line ``(x(z), y(z))`` in mm: a gentle S along z."""
    return -22.0 + 4.0 * np.sin(math.pi * z / 100), 2.0 - 0.05 * z


def _box2(x, y, centre, half):
    """A rectangle's signed distance in the x-y plane (a prism along z)."""
    qx, qy = np.abs(x - centre[0]) - half[0], np.abs(y - centre[1]) - half[1]
    outside = np.sqrt(np.maximum(qx, 0.0) ** 2 + np.maximum(qy, 0.0) ** 2)
    return outside + np.minimum(np.maximum(qx, qy), 0.0)


def _bone(x, y, z, column):
    """The vertebrae and the ribs (``column``: the vertebral bodies' elliptic cylinder, all z)."""
    zz = np.abs(np.mod(z + _PERIOD_MM / 2, _PERIOD_MM) - _PERIOD_MM / 2)  # distance from a vertebra's mid-plane
    body = np.maximum(column, zz - _BODY_HALF_MM)
    (cx, cy), r_in, r_out = _CANAL
    r = np.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    arch = np.maximum(np.maximum(r - r_out, r_in - r), (_BODY[0][1] + 12.0) - y)  # behind the body
    arch = np.maximum(arch, zz - _ARCH_HALF_MM)
    spinous = np.maximum(_box2(x, y, (0.0, cy + r_out), (3.5, 4.0)), zz - _ARCH_HALF_MM + 1.0)
    transverse = np.maximum(_box2(x, y, (0.0, cy - 2.0), (34.0, 4.0)), zz - _PROCESS_HALF_MM)
    return np.minimum(np.minimum(np.minimum(body, arch), np.minimum(spinous, transverse)), _ribs(x, y, z))


def _tumour_centre_y() -> float:
    """The y (mm) of the tumour's centre: its top ``_TUMOUR_TOP_DEPTH_MM`` below the anterior liver surface."""
    x0, z0 = _TUMOUR_XZ_MM
    y = np.arange(-80.0, 0.0, 0.001)
    inside = _liver(np.full_like(y, x0), y, np.full_like(y, z0)) < 0
    surface = float(y[np.argmax(inside)])  # the first point inside, going posterior
    return surface + _TUMOUR_TOP_DEPTH_MM + _TUMOUR_RADIUS_MM


def _structures(x, y, z, tumour_y: float):
    """``(label, HU, d)`` in compositing order; ``d`` broadcast over ``x, y, z`` (mm)."""
    hu = PHANTOM_HU
    torso = _torso(x, y, 0.0)
    inner = _torso(x, y, _FAT_MM)
    column = _ellipse(x, y, *_BODY)
    liver = _liver(x, y, z)
    vx, vy = _vessel_axis(z)
    tube = np.sqrt((x - vx) ** 2 + (y - vy) ** 2) - _VESSEL_RADIUS_MM
    x0, z0 = _TUMOUR_XZ_MM
    tumour = np.sqrt((x - x0) ** 2 + (y - tumour_y) ** 2 + (z - z0) ** 2) - _TUMOUR_RADIUS_MM
    return [
        (5, hu["fat"], torso),
        (5, hu["soft"], inner),
        (1, hu["liver"], liver),
        (4, hu["vessel"], np.maximum(tube, liver)),
        (2, hu["tumour"], tumour),
        (5, hu["soft"], column),  # intervertebral discs
        (3, hu["bone"], _bone(x, y, z, column)),
    ]


def _grid(voxel: float) -> tuple[tuple[int, int, int], np.ndarray]:
    spacing = np.array([voxel, voxel, 2 * voxel])
    shape = tuple(max(1, round(e * 1e-3 / s)) for e, s in zip(_EXTENT_MM, spacing, strict=True))
    affine = np.eye(4)
    affine[:3, :3] = np.diag(spacing)
    affine[:3, 3] = -(np.array(shape) - 1) / 2 * spacing  # the centre of the volume at the origin
    return (int(shape[0]), int(shape[1]), int(shape[2])), affine


def abdominal_phantom(*, voxel: float = 0.001, seed: int = 0) -> tuple[Image, Image]:
    """A procedural abdominal phantom of a supine patient: ``(labels, ct)`` with one affine (LPS metres).

    The structures, their labels and values are in the module's description
    (:mod:`torchdeform.anatomy.phantom`); the body to build from it takes :data:`PHANTOM_TISSUES`,
    ``fixed=PHANTOM_FIXED`` and ``background=PHANTOM_BACKGROUND``.

    Args:
        voxel: the voxel size along x and y in metres, within :data:`VOXEL_RANGE`; slices along z
            are ``2 * voxel`` thick. The field of view stays 200 x 160 x 160 mm, so the shape is
            ``(round(0.2 / voxel), round(0.16 / voxel), round(0.08 / voxel))``: 200 x 160 x 80 at
            the default 1 mm.
        seed: the seed of the CT's Gaussian noise (10 HU); an integer >= 0. The labels do not
            depend on it.

    Returns:
        ``(labels, ct)``: two :class:`~torchdeform.anatomy.images.Image` of shape ``(I, J, K)``
        along LPS ``(x, y, z)``: uint8 labels 0..5 and a float32 CT in HU, with the same affine
        (``diag(voxel, voxel, 2 voxel)``, the volume's centre at the origin).

    Raises:
        ConfigError: a voxel outside :data:`VOXEL_RANGE`, a negative or non-integer seed, a volume
            that does not fit in memory.

    Example:
        >>> import numpy as np
        >>> labels, ct = abdominal_phantom(voxel=0.004, seed=1)
        >>> labels.positions([0, 0, 0]).round(4).tolist()       # metres, LPS: right, anterior, inferior
        [-0.098, -0.078, -0.076]
        >>> voxels = labels.array
        >>> tumour_mm3 = int((voxels == 2).sum()) * 4 * 4 * 8
        >>> 4000 < tumour_mm3 < 8000                              # a 22 mm sphere: 5575 mm^3
        True
        >>> liver, tumour = (float(np.median(ct.array[voxels == label])) for label in (1, 2))   # HU
        >>> round(liver, -1), tumour < liver - 15                     # a hypodense tumour
        (60.0, True)
    """
    lo, hi = VOXEL_RANGE
    if isinstance(voxel, bool) or not isinstance(voxel, int | float) or not lo <= float(voxel) <= hi:
        raise ConfigError("voxel", f"a voxel size in [{lo:g}, {hi:g}] m (x and y; z is twice as thick)", got=voxel)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or int(seed) < 0:
        raise ConfigError("seed", "an integer >= 0", got=seed)
    shape, affine = _grid(float(voxel))
    n = shape[0] * shape[1] * shape[2]
    slab = max(1, min(shape[2], 500_000 // (shape[0] * shape[1])))  # slices computed at once
    check_memory(
        "voxel", n * 9 + shape[0] * shape[1] * slab * 4 * 40, f"a phantom of {shape} voxels", got=voxel
    )  # uint8 labels, float32 CT and noise; about 40 float32 temporaries per slab

    spacing_mm = np.diag(affine)[:3] * 1e3
    x = ((affine[0, 3] * 1e3 + np.arange(shape[0]) * spacing_mm[0]).astype(np.float32))[:, None, None]
    y = ((affine[1, 3] * 1e3 + np.arange(shape[1]) * spacing_mm[1]).astype(np.float32))[None, :, None]
    zs = (affine[2, 3] * 1e3 + np.arange(shape[2]) * spacing_mm[2]).astype(np.float32)
    width = float(spacing_mm.mean())  # the mean voxel edge: the width of a partial-volume ramp (mm)
    tumour_y = _tumour_centre_y()

    labels = np.zeros(shape, np.uint8)
    hu = np.empty(shape, np.float32)
    for k0 in range(0, shape[2], slab):
        z = zs[k0 : k0 + slab][None, None, :]
        lab = np.zeros((shape[0], shape[1], z.shape[2]), np.uint8)
        val = np.full(lab.shape, PHANTOM_HU["air"], np.float32)
        for label, value, d in _structures(x, y, z, tumour_y):
            d = np.broadcast_to(d, lab.shape)
            frac = np.clip(0.5 - d / width, 0.0, 1.0).astype(np.float32)
            val += frac * (np.float32(value) - val)
            lab[d < 0] = label
        labels[:, :, k0 : k0 + slab] = lab
        hu[:, :, k0 : k0 + slab] = val
    hu += np.random.default_rng(int(seed)).standard_normal(shape, dtype=np.float32) * np.float32(10.0)
    name = f"abdominal phantom (voxel {float(voxel):g} m, seed {int(seed)})"
    return Image(labels, affine, f"{name} labels"), Image(hu, affine, f"{name} CT")
