"""Rendered images out: display mapping, PNG and GIF files, a turntable of orbit views.

A rendered image (:func:`~torchdeform.volume.render`) is a tensor ``(B, C, h, w)``: ``C = 4``
premultiplied RGB and alpha in ``[0, 1]`` (``dvr``) or ``C = 1`` values in volume units
(``mip``, ``average``). :func:`to_image` maps the first of the batch to uint8 RGB ``(h, w, 3)``
(numpy): ``dvr`` composited over a background colour, ``mip``/``average`` by a linear window
``(lo, hi)`` to black..white, each channel rounded as ``floor(255 x + 0.5)`` after clamping to
``[0, 1]``. :func:`save_png` and :func:`save_gif` write such arrays with PIL (imported on use),
through an atomic rename, so a failed write leaves an earlier file whole. :func:`orbit_frames`
renders a turntable with :class:`~torchdeform.volume.OrbitCamera`.

Example:
    >>> import torch
    >>> from torchdeform.volume import to_image
    >>> img = torch.tensor([[[[0.0, 50.0], [100.0, 25.0]]]])      # (1, 1, 2, 2), a mip image
    >>> to_image(img)[..., 0].tolist(), to_image(img, window=(0, 50))[..., 0].tolist()
    ([[0, 128], [255, 64]], [[0, 255], [255, 128]])
"""

from __future__ import annotations

import torch

from ..outputs import atomic_path
from .cameras import OrbitCamera
from .rendering import render

__all__ = ["to_image", "save_png", "save_gif", "orbit_frames"]


def to_image(image: torch.Tensor, *, window=None, background=(0.0, 0.0, 0.0), flip_up: bool = False):
    """A rendered image ``(B, C, h, w)`` (first of the batch) -> uint8 numpy ``(h, w, 3)``.

    ``dvr`` images are composited over ``background``; ``mip``/``average`` images are mapped
    linearly from ``window = (lo, hi)`` (default: the image's own range) to black..white.
    ``flip_up``: flip the rows (for side views, so that high D is at the top).
    """
    import numpy as np

    img = image.detach()[0].double().cpu()
    if img.shape[0] == 4:
        bg = torch.tensor(background, dtype=torch.float64).view(3, 1, 1)
        rgb = img[:3] + (1 - img[3:4]) * bg
    else:
        lo, hi = window if window is not None else (float(img.min()), float(img.max()))
        rgb = ((img - lo) / ((hi - lo) or 1.0)).expand(3, *img.shape[1:])
    out = (rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).numpy()
    if flip_up:
        out = out[::-1]
    return np.ascontiguousarray(out)


def save_png(path, rgb) -> None:
    """Write a uint8 ``(h, w, 3)`` array as PNG."""
    from PIL import Image

    with atomic_path(path) as tmp:  # a failed write leaves an earlier image whole
        Image.fromarray(rgb).save(str(tmp))


def save_gif(path, frames, *, fps: float = 12.0) -> None:
    """Write uint8 ``(h, w, 3)`` frames as a looping GIF."""
    from PIL import Image

    ims = [Image.fromarray(f) for f in frames]
    with atomic_path(path) as tmp:
        ims[0].save(str(tmp), save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0)


def orbit_frames(volume, *, frames: int = 24, elevation: float = 20.0, size=(256, 256), **kw) -> list:
    """Renders from ``frames`` azimuths around the volume (a turntable), as uint8 images."""
    out = []
    for i in range(int(frames)):
        cam = OrbitCamera(azimuth=360.0 * i / frames, elevation=elevation, size=size)
        with torch.no_grad():
            out.append(to_image(render(volume, view=cam, **kw)))
    return out
