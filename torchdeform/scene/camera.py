"""A scene's ``[camera]``: what an endoscope riding one of the scene's tools sees, frame by frame.

The camera rides a tool of ``[[tools]]`` (``tool = "<name>"``; the endoscope is a tool, so it also
touches the tissue) and looks through the scene's ``[volume]``, deformed by the body at every
recorded frame (:func:`~torchdeform.volume.render_endoscope`, the volume filling the node grid's
box as for the other volume outputs). The scene's other sphere and capsule tools are drawn where
they are in view. Keys (world axes ``(D, H, W)``, metres)::

    [camera]
    kind = "endoscope"        # the only kind
    tool = "scope"            # the tool it rides (required)
    look = [-1.0, 0.0, 0.0]   # the view direction; default: along the tool's motion at each frame
    up = [0.0, 0.0, 1.0]      # the image's up (default +D, or +W when looking along D)
    ahead = 0.002             # m: the lens in front of the tool's centre along the view (default 0)
    fov = 100.0               # degrees across the round image (0, 180)
    size = [192, 192]         # image height, width in pixels
    far = 0.03                # m: how deep the view reaches (the volume of interest; default: all)
    distortion = 0.0          # barrel coefficient k1 (negative: barrel)
    every = 1                 # every k-th recorded frame
    step = 0.5                # samples along the rays, voxels
    inside = "require"        # the lens inside the volume at every frame ("allow": anywhere)

It writes ``endoscope.gif`` (one image per used frame) and ``endoscope.png`` (the last).

Example:
    >>> import numpy as np
    >>> world_to_voxel(np.array([0.01, 0.0, 0.02]), origin=(0, 0, 0), spacing=(0.01, 0.01, 0.01),
    ...                nodes=(3, 3, 3), volume_shape=(21, 21, 21)).tolist()
    [10.0, 0.0, 20.0]
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from .reader import Source, Table

__all__ = ["camera_section", "scene_endoscope", "world_to_voxel", "CAMERA_KINDS"]

CAMERA_KINDS = ("endoscope",)


def world_to_voxel(p, *, origin, spacing, nodes, volume_shape) -> np.ndarray:
    """World points ``p`` ``(..., 3)`` (m) as voxel coordinates of a volume filling the node grid's box.

    Node ``(0, 0, 0)`` is at voxel centre ``(0, 0, 0)``, the last node at the last voxel centre
    (:func:`~torchdeform.volume.node_offsets`).
    """
    scale = np.array([(N - 1) / (s * max(k - 1, 1)) for N, s, k in zip(volume_shape, spacing, nodes)])
    return (np.asarray(p, dtype=np.float64) - np.asarray(origin, dtype=np.float64)) * scale


def camera_section(src: Source, data: dict, tools, *, has_volume: bool) -> dict | None:
    """Read ``[camera]`` (module docstring) against the scene's tools; None without the section.

    Raises:
        ConfigError: a key out of range, an unknown tool, no ``[volume]`` to look through.
    """
    if "camera" not in data:
        return None
    from .reader import SECTIONS

    t = Table(src, "camera", data["camera"], SECTIONS["camera"])
    spec = {
        "kind": t.text("kind", "endoscope", default="endoscope", choices=CAMERA_KINDS),
        "tool": t.text("tool", "the name of the tool the endoscope rides"),
        "look": t.vec("look", "[d, h, w]: a view direction, not zero", default=None),
        "up": t.vec("up", "[d, h, w]: the image's up direction, not zero", default=None),
        "ahead": t.num("ahead", "a distance >= 0 in metres", default=0.0, lo=0.0),
        "fov": t.num(
            "fov",
            "an angle in degrees strictly between 0 and 180",
            default=100.0,
            lo=0.0,
            hi=180.0,
            lo_open=True,
            hi_open=True,
        ),
        "far": t.num("far", "a depth > 0 in metres", default=math.inf, lo=0.0, lo_open=True),
        "distortion": t.num("distortion", "a finite radial coefficient k1", default=0.0),
        "every": t.integer("every", "an integer >= 1 (every k-th recorded frame)", default=1, lo=1),
        "step": t.num("step", "a sample spacing in voxels in [0.05, 4]", default=0.5, lo=0.05, hi=4.0),
        "inside": t.text("inside", '"require" or "allow"', default="require", choices=("require", "allow")),
    }
    size = t.raw("size", "[height, width]: pixels, each in [16, 2048]", default=[192, 192])
    if not (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= 2048 for v in size)
    ):
        raise t.fail("size", "[height, width]: pixels, each in [16, 2048]", got=size)
    spec["size"] = tuple(size)
    for k in ("look", "up"):
        if spec[k] is not None and not any(spec[k]):
            raise t.fail(k, "a direction [d, h, w], not zero", got=list(spec[k]))
    if not has_volume:
        raise t.fail("kind", "a [volume] section to look through (the endoscope renders the scene's volume)", got=None)
    names = [] if tools is None else tools.names
    if spec["tool"] not in names:
        known = ", ".join(names) if names else "none: add [[tools]]"
        raise t.fail("tool", f"the name of one of the scene's tools ({known})", got=spec["tool"])
    return spec


def _poses(spec: dict, tool, times: np.ndarray, to_voxel) -> tuple:
    """Lens positions ``(F, 3)`` and view directions ``(F, 3)`` in voxels at ``times`` (s)."""
    world = np.array([[float(c) for c in tool.position(float(t))] for t in times])  # (F, 3) m
    if spec["look"] is not None:
        look = np.tile(np.asarray(spec["look"], dtype=np.float64), (len(times), 1))
    else:  # along the motion: the path's direction around each frame (held: the last one)
        eps = 1e-3
        ahead = np.array([[float(c) for c in tool.position(float(t) + eps)] for t in times])
        look = ahead - world
        moving = np.linalg.norm(look, axis=1) > 1e-12
        if not moving.any():
            raise ConfigError("camera.look", "a view direction (the tool does not move)", got=None)
        last = look[np.flatnonzero(moving)[0]]
        for k in range(len(look)):
            if moving[k]:
                last = look[k]
            look[k] = last
    look = look / np.linalg.norm(look, axis=1, keepdims=True)
    lens = world + spec["ahead"] * look
    lens_v = to_voxel(lens)
    dir_v = to_voxel(world + look * 1e-3) - to_voxel(world)  # a direction through the anisotropic scale
    return lens_v, dir_v / np.linalg.norm(dir_v, axis=1, keepdims=True)


def _surfaces(tools, skip: str, t: float, to_voxel, voxel_per_m: float) -> list:
    """The scene's other sphere and capsule tools at time ``t`` as opaque surfaces of the renderer."""
    from ..interact.tools import Capsule as CapsuleShape
    from ..interact.tools import Sphere as SphereShape
    from ..volume import Capsule, Sphere

    out = []
    for tool in tools.tools:
        if tool.name == skip:
            continue
        c = np.array([float(v) for v in tool.position(t)])
        if isinstance(tool.shape, SphereShape):
            out.append(Sphere(to_voxel(c).tolist(), tool.shape.radius * voxel_per_m, (0.75, 0.75, 0.8)))
        elif isinstance(tool.shape, CapsuleShape):
            axis = np.zeros(3)
            axis[tool.shape.axis] = tool.shape.half_length
            a, b = to_voxel(c - axis), to_voxel(c + axis)
            out.append(Capsule(a.tolist(), b.tolist(), tool.shape.radius * voxel_per_m, (0.75, 0.75, 0.8)))
    return out


def scene_endoscope(spec: dict, tools, volume, grid, t: np.ndarray, x: torch.Tensor, X, out_dir, *, tf, progress=True):
    """Render the endoscope's view at the recorded frames and write ``endoscope.gif`` and ``endoscope.png``.

    Args:
        spec: the ``[camera]`` of :func:`camera_section`.
        tools: the scene's :class:`~torchdeform.scene.tools.ToolSet`.
        volume: the ``(D, H, W)`` volume (a numpy array or tensor).
        grid: the body's :class:`~torchdeform.sim.grid.Grid` (its box holds the volume).
        t: frame times ``(F,)`` s.
        x: node positions of the frames ``(F, 3, n_d, n_h, n_w)`` m.
        X: rest positions ``(1, 3, n_d, n_h, n_w)`` m.
        out_dir: the run's output folder.
        tf: the transfer function (the ``[volume]`` section's).
        progress: a progress bar over the frames.

    Returns:
        the summary part: frames, milliseconds per frame, the files.
    """
    from tqdm import tqdm

    from ..volume import EndoscopeCamera, node_offsets, render_endoscope, save_gif, save_png, to_image

    vol = torch.as_tensor(np.asarray(volume, dtype=np.float32))
    shape = tuple(vol.shape)
    tool = next(tl for tl in tools.tools if tl.name == spec["tool"])

    def to_voxel(p):
        return world_to_voxel(p, origin=grid.origin, spacing=grid.spacing, nodes=grid.shape, volume_shape=shape)

    voxel_per_m = float(np.mean(to_voxel(np.ones(3)) - to_voxel(np.zeros(3))))
    use = list(range(0, len(t), spec["every"]))
    if use[-1] != len(t) - 1:
        use.append(len(t) - 1)
    lens, look = _poses(spec, tool, t[use], to_voxel)
    far = spec["far"] * voxel_per_m if math.isfinite(spec["far"]) else math.inf
    up = spec["up"]
    if up is None:  # +D, or +W where the view runs along D
        up = (0.0, 0.0, 1.0) if abs(look[0][0]) > 0.99 else (1.0, 0.0, 0.0)
    up_v = to_voxel(np.asarray(up, dtype=np.float64) * 1e-3) - to_voxel(np.zeros(3))
    frames, seconds = [], []
    for k, i in enumerate(tqdm(use, disable=not progress, desc="endoscope", unit="frame")):
        camera = EndoscopeCamera(
            position=lens[k].tolist(),
            direction=look[k].tolist(),
            up=up_v.tolist(),
            fov=spec["fov"],
            size=spec["size"],
            far=far,
            distortion=spec["distortion"],
            inside=spec["inside"],
        )
        try:
            camera.check_inside(shape)
        except ConfigError:
            raise ConfigError(
                "camera.tool",
                f'a tool whose lens stays inside the volume (at t = {t[i]:.4g} s it is outside; or inside = "allow")',
                got=spec["tool"],
            ) from None
        with torch.no_grad():
            offsets = node_offsets(x[i : i + 1].double(), X.double().cpu(), grid.spacing, shape).float()
            t0 = time.perf_counter()
            img = render_endoscope(
                vol,
                camera,
                tf=tf,
                offsets=offsets[0],
                step=spec["step"],
                surfaces=_surfaces(tools, spec["tool"], float(t[i]), to_voxel, voxel_per_m) or None,
            )
            seconds.append(time.perf_counter() - t0)
        assert isinstance(img, torch.Tensor)  # no depth asked for: the image alone
        frames.append(to_image(img))
    out = Path(out_dir)
    save_gif(out / "endoscope.gif", frames)
    save_png(out / "endoscope.png", frames[-1])
    return {
        "tool": spec["tool"],
        "frames": len(frames),
        "fov_deg": spec["fov"],
        "size": list(spec["size"]),
        "far_m": spec["far"] if math.isfinite(spec["far"]) else None,
        "ms_per_frame": 1e3 * float(np.median(seconds)),
        "outputs": ["endoscope.gif", "endoscope.png"],
    }
