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

One frame is :meth:`SceneEndoscope.render`: the camera's pose from the tool at time ``t``, the node
offsets of the positions, the other tools, the render. :func:`scene_endoscope` (the run's GIF) and the
live viewer's endoscope pane (:meth:`~torchdeform.view.session.ViewerSession.endoscope`) both call it;
:func:`load_scene_endoscope` makes one from a loaded scene, its volume loaded once.

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

__all__ = [
    "camera_section",
    "scene_endoscope",
    "load_scene_endoscope",
    "SceneEndoscope",
    "world_to_voxel",
    "CAMERA_KINDS",
]

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


class SceneEndoscope:
    """A scene's endoscope ready to render any frame: the volume, the tool it rides, the voxel mapping.

    One frame (:meth:`render`) is the camera's pose from the tool at time ``t`` (:meth:`look`,
    :meth:`camera`), the node offsets of the positions ``x`` (:func:`~torchdeform.volume.node_offsets`),
    the scene's other sphere and capsule tools at ``t`` as opaque surfaces, and the render
    (:func:`~torchdeform.volume.render_endoscope`, float32). :func:`scene_endoscope` renders a run's
    recorded frames with it; the live viewer (:class:`~torchdeform.view.session.ViewerSession`) its
    current state.

    Looking along the motion (no ``look``): the direction of the tool's path at ``t`` (a forward
    difference of 1 ms); where the tool is still, the last direction it moved in (:attr:`held`),
    or before it has moved the first one of :meth:`prime`. The image's up (default ``+D``, or ``+W``
    when the first frame looks along D) is chosen at the first frame after construction or
    :meth:`reset` and kept, so the image never flips.

    Args:
        spec: the ``[camera]`` of :func:`camera_section`.
        tools: the scene's :class:`~torchdeform.scene.tools.ToolSet`.
        volume: the ``(D, H, W)`` volume (a numpy array or tensor), filling the node grid's box.
        grid: the body's :class:`~torchdeform.sim.grid.Grid`.
        tf: the transfer function (the ``[volume]`` section's).
        meshes: embedded surfaces ``{name:`` :class:`~torchdeform.mesh.embed.EmbeddedSurface` ``}``
            on the body's lattice, drawn opaque where the body has moved them (one colour each), or None.

    Attributes:
        volume: the float32 volume ``(D, H, W)`` on the CPU.
        tool: the :class:`~torchdeform.interact.tools.Tool` the camera rides.
        size: the image's ``(height, width)`` in pixels.
        held: the view direction (world, unit ``(3,)``) kept while the tool is still, or None.
        seconds: the wall time of the last render (s).
    """

    def __init__(self, spec: dict, tools, volume, *, grid, tf, meshes: dict | None = None):
        self.spec, self.tools, self.grid, self.tf = spec, tools, grid, tf
        self.meshes = dict(meshes or {})
        self.volume = torch.as_tensor(np.asarray(volume, dtype=np.float32))
        self.shape = tuple(self.volume.shape)
        self.tool = next(tl for tl in tools.tools if tl.name == spec["tool"])
        self.size = tuple(spec["size"])
        self.voxel_per_m = float(np.mean(self.to_voxel(np.ones(3)) - self.to_voxel(np.zeros(3))))
        self.far = spec["far"] * self.voxel_per_m if math.isfinite(spec["far"]) else math.inf
        self.seconds = 0.0
        self.reset()

    def to_voxel(self, p) -> np.ndarray:
        """World points ``(..., 3)`` (m) as voxel coordinates of the volume (:func:`world_to_voxel`)."""
        g = self.grid
        return world_to_voxel(p, origin=g.origin, spacing=g.spacing, nodes=g.shape, volume_shape=self.shape)

    def reset(self, *, held=None) -> None:
        """Forget the held view direction (or hold ``held``) and the image's up (chosen again at the next frame)."""
        self.held = None if held is None else np.asarray(held, dtype=np.float64)
        self._up = None

    def motion(self, t: float) -> np.ndarray | None:
        """The unit direction ``(3,)`` the tool moves in at ``t`` (s), or None where it is still."""
        eps = 1e-3
        a = np.array([float(c) for c in self.tool.position(float(t))])
        d = np.array([float(c) for c in self.tool.position(float(t) + eps)]) - a
        n = float(np.linalg.norm(d))
        return d / n if n > 1e-12 else None

    def prime(self, times) -> None:
        """Hold the first direction the tool moves in at ``times`` (s), for the frames before it moves.

        Raises:
            ConfigError: no ``look`` and the tool moves at none of ``times``.
        """
        if self.spec["look"] is not None:
            return
        for t in times:
            d = self.motion(float(t))
            if d is not None:
                self.held = d
                return
        raise ConfigError("camera.look", "a view direction (the tool does not move)", got=None)

    def look(self, t: float) -> np.ndarray:
        """The unit view direction ``(3,)`` (world) at ``t``: ``look``, or along the motion (class docstring)."""
        if self.spec["look"] is not None:
            d = np.asarray(self.spec["look"], dtype=np.float64)
            return d / np.linalg.norm(d)
        d = self.motion(t)
        if d is not None:
            self.held = d
        elif self.held is None:
            raise ConfigError("camera.look", "a view direction (the tool does not move)", got=None)
        assert self.held is not None
        return self.held

    def camera(self, t: float, look: np.ndarray):
        """The :class:`~torchdeform.volume.EndoscopeCamera` (voxels) at ``t`` looking along ``look`` (world).

        Raises:
            ConfigError: the lens outside the volume with ``inside = "require"`` (naming ``t``).
        """
        from ..volume import EndoscopeCamera

        spec = self.spec
        world = np.array([float(c) for c in self.tool.position(float(t))])
        lens_v = self.to_voxel(world + spec["ahead"] * look)
        dir_v = self.to_voxel(world + look * 1e-3) - self.to_voxel(world)  # through the anisotropic scale
        dir_v = dir_v / np.linalg.norm(dir_v)
        if self._up is None:
            up = spec["up"]
            if up is None:  # +D, or +W where the view runs along D
                up = (0.0, 0.0, 1.0) if abs(dir_v[0]) > 0.99 else (1.0, 0.0, 0.0)
            self._up = self.to_voxel(np.asarray(up, dtype=np.float64) * 1e-3) - self.to_voxel(np.zeros(3))
        camera = EndoscopeCamera(
            position=lens_v.tolist(),
            direction=dir_v.tolist(),
            up=self._up.tolist(),
            fov=spec["fov"],
            size=spec["size"],
            far=self.far,
            distortion=spec["distortion"],
            inside=spec["inside"],
        )
        try:
            camera.check_inside(self.shape)
        except ConfigError:
            raise ConfigError(
                "camera.tool",
                f'a tool whose lens stays inside the volume (at t = {t:.4g} s it is outside; or inside = "allow")',
                got=spec["tool"],
            ) from None
        return camera

    def surfaces(self, t: float) -> list:
        """The scene's other sphere and capsule tools at time ``t`` as opaque surfaces of the renderer."""
        return _surfaces(self.tools, self.spec["tool"], float(t), self.to_voxel, self.voxel_per_m)

    def render(self, t: float, x: torch.Tensor, X: torch.Tensor, *, extra=()) -> np.ndarray:
        """The endoscope's image at time ``t`` of the body at positions ``x``: uint8 ``(h, w, 3)``.

        Args:
            t: the simulated time (s): the tool's pose and the other tools'.
            x: node positions ``(1, 3, n_d, n_h, n_w)`` (m).
            X: rest positions ``(1, 3, n_d, n_h, n_w)`` (m).
            extra: more spheres to draw, ``[(centre (3,) m, radius m)]`` (the viewer's own tool).

        Raises:
            ConfigError: the lens outside the volume (``inside = "require"``), or no view direction.
        """
        from ..volume import Mesh, Sphere, node_offsets, render_endoscope, to_image

        look = self.look(t)
        camera = self.camera(t, look)
        surfaces = self.surfaces(t)
        for k, embedded in enumerate(self.meshes.values()):  # the organs' surfaces where the body moved them
            p = embedded.positions(x[0].detach())  # (V, 3) m
            colour = _ORGANS[k % len(_ORGANS)]
            surfaces.append(Mesh(self.to_voxel(p.cpu().numpy()), embedded.faces.cpu(), colour))
        for centre, radius in extra:
            c = self.to_voxel(np.asarray(centre, dtype=np.float64))
            surfaces.append(Sphere(c.tolist(), float(radius) * self.voxel_per_m, _STEEL))
        with torch.no_grad():
            offsets = node_offsets(x.detach().double().cpu(), X.detach().double().cpu(), self.grid.spacing, self.shape)
            t0 = time.perf_counter()
            img = render_endoscope(
                self.volume,
                camera,
                tf=self.tf,
                offsets=offsets.float()[0],
                step=self.spec["step"],
                surfaces=surfaces or None,
            )
            self.seconds = time.perf_counter() - t0
        assert isinstance(img, torch.Tensor)  # no depth asked for: the image alone
        return to_image(img)


_STEEL = (0.75, 0.75, 0.8)  # the tools' colour in the endoscope's view
_ORGANS = ((0.75, 0.35, 0.3), (0.9, 0.75, 0.45), (0.55, 0.25, 0.45), (0.45, 0.6, 0.35))  # embedded surfaces


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
            out.append(Sphere(to_voxel(c).tolist(), tool.shape.radius * voxel_per_m, _STEEL))
        elif isinstance(tool.shape, CapsuleShape):
            axis = np.zeros(3)
            axis[tool.shape.axis] = tool.shape.half_length
            a, b = to_voxel(c - axis), to_voxel(c + axis)
            out.append(Capsule(a.tolist(), b.tolist(), tool.shape.radius * voxel_per_m, _STEEL))
    return out


def load_scene_endoscope(scene, *, meshes: dict | None = None) -> SceneEndoscope | None:
    """The :class:`SceneEndoscope` of a loaded scene's ``[camera]`` and ``[volume]`` (the volume loaded once), or None.

    Args:
        scene: a :class:`~torchdeform.scene.Scene` (``scene.camera_view``, ``scene.volume``, ``scene.tools``).
        meshes: the scene's embedded surfaces on its lattice, ``{name:``
            :class:`~torchdeform.mesh.embed.EmbeddedSurface` ``}``, drawn opaque in the view; or None.
    """
    if scene.camera_view is None:
        return None
    from ..volume import load_volume
    from .reader import volume_path

    assert scene.volume is not None and scene.tools is not None  # camera_section requires both
    spec = scene.volume
    volume = load_volume(volume_path(spec["file"], spec.get("base")), key="volume.file")
    return SceneEndoscope(scene.camera_view, scene.tools, volume, grid=scene.grid, tf=spec["tf"], meshes=meshes)


def scene_endoscope(rig: SceneEndoscope, t: np.ndarray, x: torch.Tensor, X, out_dir, *, progress=True) -> dict:
    """Render the endoscope's view at the recorded frames and write ``endoscope.gif`` and ``endoscope.png``.

    Args:
        rig: the scene's :class:`SceneEndoscope` (:func:`load_scene_endoscope`).
        t: frame times ``(F,)`` s.
        x: node positions of the frames ``(F, 3, n_d, n_h, n_w)`` m.
        X: rest positions ``(1, 3, n_d, n_h, n_w)`` m.
        out_dir: the run's output folder.
        progress: a progress bar over the frames.

    Returns:
        the summary part: frames, milliseconds per frame, the files.
    """
    from tqdm import tqdm

    from ..volume import save_gif, save_png

    spec = rig.spec
    use = list(range(0, len(t), spec["every"]))
    if use[-1] != len(t) - 1:
        use.append(len(t) - 1)
    rig.prime([float(t[i]) for i in use])  # frames before the tool moves look where it first goes
    frames, seconds = [], []
    for i in tqdm(use, disable=not progress, desc="endoscope", unit="frame"):
        frames.append(rig.render(float(t[i]), x[i : i + 1], X))
        seconds.append(rig.seconds)
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
