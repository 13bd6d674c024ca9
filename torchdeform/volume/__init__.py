"""Volume deformation and rendering.

A CT/MR volume deformed by a model's node offsets through an offset texture (Knoche 2008) and
rendered, differentiable end to end.

=====================  ===========================================================================
:mod:`.deform`         offset texture (trilinear, cubic B-spline), :func:`warp` (deform, carve,
                       Knoche's lookup), fixed-point inverse, folding detection, node offsets
:mod:`.transfer`       transfer functions: control points, lookup table, presets, files
:mod:`.cameras`        axis views and the perspective :class:`OrbitCamera`
:mod:`.endoscope`      the virtual endoscope :class:`EndoscopeCamera` (wide angle, round mask, distortion)
:mod:`.interior`       :func:`render_endoscope`: headlit rendering from inside a (deformed) volume,
                       analytic opaque surfaces (:class:`Sphere`, :class:`Capsule`), depth
:mod:`.plan`           the render plan: :func:`render`'s arguments resolved once, for every path
:mod:`.rendering`      :func:`render` (MIP, average, emission-absorption; axis views and orbit
                       views; through offsets or the pieces of a cut)
:mod:`.fastpath`       the fast path of axis views through offsets (eager or compiled),
                       :func:`trilinear_flat`
:mod:`.images`         display mapping, PNG and GIF files, turntables
:mod:`.io`             ``.npy``/``.npz``/NIfTI/NRRD volumes (nibabel and pynrrd imported on use)
:mod:`.native_march`   the endoscope's march as a C kernel (``engine="auto"`` without gradients)
:mod:`.planning`       :class:`Trajectory`, :func:`check_trajectory` (labels passed, clearance of
                       structures), :func:`fly_through`
:mod:`.phantoms`       the procedural CT phantom (``lumen=True``: with a bowel loop)
:mod:`.commands`       ``torchdeform warp`` and ``torchdeform render``
=====================  ===========================================================================

Example:
    >>> import torch
    >>> from torchdeform.volume import phantom, warp, render, to_image
    >>> vol = phantom(shape=(32, 32, 32))
    >>> offsets = torch.zeros(3, 5, 5, 5)
    >>> offsets[0, 4, 2, 2] = 3.0                   # top centre node moved 3 voxels along +D
    >>> img = render(warp(vol, offsets), mode="mip", view="h")
    >>> to_image(img).shape                         # uint8 RGB (numpy)
    (32, 32, 3)
"""

from .cameras import OrbitCamera
from .deform import (
    MODES,
    DisplacementField,
    FoldingWarning,
    as_offsets,
    as_volume,
    axis_weights,
    axis_weights_at,
    check_folding,
    folding_fraction,
    identity_points,
    inverse_points,
    inverse_residual,
    jacobian_determinant,
    node_offsets,
    offset_texture,
    sample,
    sample_points,
    to_grid_sample,
    warp,
)
from .endoscope import INSIDE_MODES, EndoscopeCamera
from .fastpath import RenderCompileWarning, trilinear_flat
from .images import orbit_frames, save_gif, save_png, to_image
from .interior import Capsule, Headlight, Mesh, Sphere, render_endoscope
from .io import SUFFIXES, check_array, load_volume, read_array, save_volume
from .phantoms import lumen_centre, phantom
from .plan import AXIS_VIEWS, ENGINES, RENDER_MODES
from .planning import Trajectory, TrajectoryReport, check_trajectory, fly_through
from .rendering import render
from .transfer import PRESETS, TransferFunction, get_tf, load_tf, preset

__all__ = [
    "FoldingWarning",
    "DisplacementField",
    "MODES",
    "as_volume",
    "as_offsets",
    "to_grid_sample",
    "identity_points",
    "sample",
    "axis_weights",
    "axis_weights_at",
    "offset_texture",
    "inverse_points",
    "inverse_residual",
    "jacobian_determinant",
    "folding_fraction",
    "check_folding",
    "sample_points",
    "warp",
    "node_offsets",
    "SUFFIXES",
    "check_array",
    "load_volume",
    "read_array",
    "save_volume",
    "phantom",
    "TransferFunction",
    "PRESETS",
    "preset",
    "load_tf",
    "get_tf",
    "OrbitCamera",
    "render",
    "to_image",
    "save_png",
    "save_gif",
    "orbit_frames",
    "RENDER_MODES",
    "AXIS_VIEWS",
    "ENGINES",
    "trilinear_flat",
    "RenderCompileWarning",
    "EndoscopeCamera",
    "INSIDE_MODES",
    "render_endoscope",
    "Headlight",
    "Sphere",
    "Capsule",
    "Mesh",
    "lumen_centre",
    "Trajectory",
    "TrajectoryReport",
    "check_trajectory",
    "fly_through",
]
