"""Animated GIFs of a run: the textured, shaded surface beside the deformed volume render.

Each frame of :func:`animate` has two square panels of ``size`` pixels and a caption band under
them:

* **left**, the body's closed surface (:func:`~torchdeform.topology.cut_surfaces` of the recorded
  node positions) coloured by a solid texture at its material coordinates and Lambert shaded
  (:func:`~torchdeform.texture.render_textured`), seen by one perspective camera that frames every
  shown frame (:func:`surface_camera`), so the motion of the body is seen against a fixed view;
* **right**, the volume (a file or the procedural phantom) filling the node grid's bounding box,
  deformed by the frame's node offsets and rendered along an axis
  (:func:`~torchdeform.volume.render` through :func:`~torchdeform.volume.node_offsets`, the same
  render as ``volume_after.png``), fitted to the panel at its physical aspect ratio;
* the **caption**: the simulated time and the force of every tool or drag at that frame
  (:func:`caption`).

A scene of several bodies (:func:`animate_bodies`) has the same surface panel, every body in its
own flat colour (:data:`BODY_COLOURS`; :func:`render_surfaces` keeps the nearest body at each
pixel, :func:`surface_panel` adds the tools), beside a panel of the contact force per pair over time
(:func:`curve_panel`).

The force a drag shows (:func:`drag_forces`) is the force it exerts to hold its nodes on their
path: minus the sum of the model's forces (springs, gravity, loads, contacts) on the dragged nodes,
the inertia of the dragged nodes left out (their path is piecewise linear: no acceleration between
waypoints).

Only the mesh, texture, topology, volume, interact (the tools' triangles) and sim layers are imported (the scene runner imports this
module inside the function that writes the animation). Pillow writes the GIF and the text.

Example:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.scene.animation import animate
    >>> grid = td.Grid((3, 3, 3), spacing=0.01)
    >>> X = grid.rest_positions(dtype=torch.float32)[0]
    >>> x = torch.stack([X, X + 0.002])                   # two frames: the body moves 2 mm along each axis
    >>> out = getfixture("tmp_path") / "a.gif"
    >>> info = animate(grid, [0.0, 0.1], x, out, volume=torch.rand(8, 8, 8) * 1000, size=64,
    ...                texture={"exemplar": "liver:16", "block": 8},
    ...                forces={"drag": [[0.0, 0.0, 0.0], [0.0, 0.003, 0.004]]})
    >>> info["frames"], info["size"], info["captions"][-1]
    (2, [88, 128], 't = 0.100 s   drag 5.00 mN')
    >>> from PIL import Image
    >>> with Image.open(out) as gif:
    ...     gif.n_frames, gif.size                         # (width, height): two 64-pixel panels, a caption band
    (2, (128, 88))
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
import torch

from ..errors import ConfigError
from ..outputs import atomic_path
from ..texture.mapping import body_texture

__all__ = [
    "animate",
    "animate_bodies",
    "render_surfaces",
    "surface_panel",
    "curve_panel",
    "BODY_COLOURS",
    "frame_indices",
    "drag_forces",
    "body_texture",
    "surface_camera",
    "format_force",
    "caption",
    "compose",
    "write_gif",
    "SURFACE_DIRECTION",
    "SURFACE_FOV",
    "LIGHT",
    "TOOL_COLOUR",
]

#: where the surface camera looks from, in units of the body's largest side from its centre
SURFACE_DIRECTION = (1.3, -1.1, 0.9)
#: the surface camera's vertical field of view (degrees)
SURFACE_FOV = 38.0
#: direction towards the light of the surface panel
LIGHT = (1.0, -0.5, 0.6)
#: image axes (rows, columns) of the volume renders of each axis view
_VIEW_AXES = {"d": (1, 2), "h": (0, 2), "w": (0, 1)}


def frame_indices(n: int, frames: int) -> list:
    """``min(n, frames)`` indices spread evenly over ``n`` recorded frames, first and last included.

    Args:
        n: number of recorded frames (>= 1).
        frames: the most frames to show (>= 1).

    Returns:
        increasing indices into the recorded frames.

    Example:
        >>> frame_indices(101, 5), frame_indices(3, 10), frame_indices(7, 1)
        ([0, 25, 50, 75, 100], [0, 1, 2], [6])
    """
    n, frames = int(n), int(frames)
    if n < 1 or frames < 1:
        raise ConfigError("frames", "at least one recorded and one shown frame", got=(n, frames))
    if frames == 1:
        return [n - 1]
    if frames >= n:
        return list(range(n))
    return sorted({round(i * (n - 1) / (frames - 1)) for i in range(frames)})


def drag_forces(model, x, v, t) -> np.ndarray:
    """The total force the model's drags exert to hold their nodes, at recorded frames.

    Minus the sum of :meth:`~torchdeform.sim.model.Model.forces` (springs, gravity, loads, contacts)
    over every dragged node: what the hand (or tool) holding them feels, pushing on the tissue. The
    dragged nodes' own inertia is left out.

    Args:
        model: the :class:`~torchdeform.sim.model.Model` of the run (with ``drags``).
        x: positions ``(T, 3, D, H, W)`` (m, any device; batch entry 0 of the recording).
        v: velocities ``(T, 3, D, H, W)`` (m/s).
        t: times ``(T,)`` (s).

    Returns:
        float64 numpy ``(T, 3)`` (N), zeros when the model has no drags.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((2, 1, 1), spacing=0.01)
        >>> top = grid.index_mask([(1, 0, 0)])
        >>> model = td.Model(grid, stiffness=10.0, density=1000.0, fixed=grid.face("bottom"),
        ...                  drags=[td.Drag(top, offset=(0.001, 0.0, 0.0))], dtype=torch.float64)
        >>> x = model.X.clone(); x[0, 0, 1] += 0.001             # the spring stretched by 1 mm
        >>> drag_forces(model, x, torch.zeros_like(x), [0.0]).round(6).tolist()   # 10 N/m * 1 mm, upwards
        [[0.01, 0.0, 0.0]]
    """
    T = len(x)
    out = np.zeros((T, 3))
    if not model.drags:
        return out
    mask = torch.zeros(model.grid.shape, dtype=torch.bool, device=model.device)
    for m in model.drag_masks:
        mask = mask | m[0, 0]
    with torch.no_grad():
        for i in range(T):
            xi = x[i : i + 1].to(model.device, model.dtype)
            vi = v[i : i + 1].to(model.device, model.dtype)
            F = model.forces(xi, vi, t=float(t[i]))[0]  # (3, D, H, W)
            out[i] = (-F[:, mask].sum(1)).double().cpu().numpy() + 0.0  # no -0.0
    return out


def surface_camera(
    grid,
    x,
    *,
    size: int = 320,
    direction=SURFACE_DIRECTION,
    fov_deg: float = SURFACE_FOV,
    fill: float = 0.9,
    up=(1.0, 0.0, 0.0),
    points=None,
):
    """The perspective camera of the surface panel: it frames the body in every frame of ``x``.

    The box of all node positions, widened by half a spacing (the surfaces reach that far), is looked
    at from its centre along ``direction`` (:func:`~torchdeform.texture.mapping.framing_camera`,
    axis D up), from the distance at which the box's projected corners fill ``fill`` of the image
    about its centre.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid` (spacing).
        x: node positions ``(T, 3, D, H, W)`` (m).
        size: the square image's side (pixels).
        direction: from the box centre towards the eye (its length is adjusted).
        fov_deg: vertical field of view (degrees).
        fill: the largest distance of a projected box corner from the image centre, in half image sides.
        up: the direction that appears upwards in the image (default axis D).
        points: ``(N, 3)`` positions (m) to frame instead of the nodes (embedded surfaces' vertices).

    Returns:
        a :class:`~torchdeform.mesh.Camera` of ``size x size`` pixels.

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> grid = td.Grid((3, 3, 3), spacing=0.01)
        >>> cam = surface_camera(grid, grid.rest_positions(dtype=torch.float64), size=64)
        >>> cam.size, [round(c, 4) for c in cam.target]
        ((64, 64), [0.01, 0.01, 0.01])
        >>> corners = torch.tensor([[a, b, c] for a in (-0.005, 0.025) for b in (-0.005, 0.025) for c in (-0.005, 0.025)])
        >>> round(float((cam.project(corners)[0] - 32).abs().max() / 32), 2)
        0.9
    """
    from ..texture.mapping import framing_camera

    if points is not None:
        p = torch.as_tensor(points).detach().double().cpu().reshape(-1, 3).t()
    else:
        p = torch.as_tensor(x).detach().double().cpu().transpose(0, 1).reshape(3, -1)
    half = torch.tensor(grid.spacing, dtype=torch.float64) / 2
    lo, hi = p.min(1).values - half, p.max(1).values + half
    corners = torch.stack(
        [torch.where(torch.tensor([(c >> k) & 1 for k in range(3)], dtype=torch.bool), hi, lo) for c in range(8)]
    )
    d = torch.tensor(direction, dtype=torch.float64)
    d = d / d.norm()
    for _ in range(8):  # the projected size is about inverse to the distance
        cam = framing_camera(
            corners, direction=tuple(d.tolist()), fov_deg=fov_deg, size=(int(size), int(size)), up=tuple(up)
        )
        reach = float((cam.project(corners)[0] - size / 2).abs().max()) / (size / 2)
        if abs(reach - fill) < 1e-3:
            break
        d = d * reach / fill
    return cam


def format_force(force) -> str:
    """The magnitude of a force ``(3,)`` (N) with a unit that keeps it readable.

    Example:
        >>> format_force([0.0, 0.003, 0.004]), format_force([2.5, 0, 0]), format_force([0, 0, 2e-6])
        ('5.00 mN', '2.50 N', '2.0 uN')
    """
    f = float(np.linalg.norm(np.asarray(force, dtype=np.float64)))
    if f >= 1.0:
        return f"{f:.2f} N"
    if f >= 1e-3:
        return f"{f * 1e3:.2f} mN"
    return f"{f * 1e6:.1f} uN"  # the default font has no micro sign


def caption(t: float, *, forces: dict | None = None) -> str:
    """The caption of a frame: the simulated time and each named force's magnitude.

    Args:
        t: simulated time (s).
        forces: ``{name: force (3,)}`` (N) of the tools or drags at that time, or None.

    Returns:
        one line, e.g. ``"t = 0.050 s   drag 2.31 mN"``.

    Example:
        >>> caption(0.05, forces={"drag": [0.0, 0.002, 0.0]}), caption(1.0)
        ('t = 0.050 s   drag 2.00 mN', 't = 1.000 s   (no tool or drag)')
    """
    parts = ", ".join(f"{name} {format_force(f)}" for name, f in (forces or {}).items())
    return f"t = {float(t):.3f} s   " + (parts or "(no tool or drag)")


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the bitmap font
        return ImageFont.load_default()


def compose(surface, volume, text: str, *, titles=("surface", "volume")) -> np.ndarray:
    """One frame: one or two square panels side by side, a title on each and a caption band underneath.

    Args:
        surface: uint8 ``(S, S, 3)`` the left panel.
        volume: uint8 ``(S, S, 3)`` the right panel, or None (a scene without a volume: one panel).
        text: the caption (:func:`caption`).
        titles: the panels' titles (top left of each).

    Returns:
        uint8 ``(S + band, 2 S, 3)`` (``(S + band, S, 3)`` without a volume) with ``band = max(24, S // 9)``
        pixels of caption.

    Example:
        >>> import numpy as np
        >>> compose(np.zeros((64, 64, 3), np.uint8), np.zeros((64, 64, 3), np.uint8), "t = 0 s").shape
        (88, 128, 3)
    """
    from PIL import Image, ImageDraw

    S = surface.shape[0]
    band = max(24, S // 9)
    canvas = Image.new("RGB", ((1 if volume is None else 2) * S, S + band), (255, 255, 255))
    canvas.paste(Image.fromarray(np.ascontiguousarray(surface)), (0, 0))
    draw = ImageDraw.Draw(canvas)
    small = _font(max(10, S // 24))
    pad = max(3, S // 64)
    draw.text((pad, pad), titles[0], fill=(40, 40, 40), font=small)
    if volume is not None:
        canvas.paste(Image.fromarray(np.ascontiguousarray(volume)), (S, 0))
        draw.text((S + pad, pad), titles[1], fill=(235, 235, 235), font=small)
        draw.line([(S, 0), (S, S - 1)], fill=(255, 255, 255))
    big = _font(max(10, int(band * 0.6)))
    draw.text((pad, S + band // 2), text, fill=(20, 20, 20), font=big, anchor="lm")
    return np.asarray(canvas)


def write_gif(frames, path, *, fps: float = 12.0, hold: float = 1.0, colours: int = 256) -> int:
    """Write uint8 ``(h, w, 3)`` frames as a looping GIF; the last frame stays ``hold`` seconds.

    All frames share one palette of ``colours`` colours, taken from up to four frames spread over the
    animation, without dithering: colours do not flicker between frames, and pixels that do not change
    are identical, so each frame stores only the box that changed.

    Args:
        frames: a list of uint8 ``(h, w, 3)`` arrays of one size.
        path: the ``.gif`` file.
        fps: frames per second.
        hold: seconds the last frame is shown before the loop starts again.
        colours: size of the palette (2 to 256).

    Returns:
        the file's size in bytes.
    """
    from PIL import Image

    ims = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
    picks = [ims[i] for i in frame_indices(len(ims), 4)]
    w, h = ims[0].size
    montage = Image.new("RGB", (w, h * len(picks)))
    for k, im in enumerate(picks):
        montage.paste(im, (0, h * k))
    palette = montage.quantize(colours, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    ims = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in ims]
    step = round(1000 / fps)
    durations = [step] * (len(ims) - 1) + [max(step, round(1000 * hold))]
    with atomic_path(path) as tmp:
        ims[0].save(str(tmp), save_all=True, append_images=ims[1:], duration=durations, loop=0)
    return Path(path).stat().st_size


def _volume_panel(vol, offsets, tf, mode, view, extent, size, render_scale) -> np.ndarray:
    """The volume render fitted into a black ``size x size`` panel at its physical aspect ratio."""
    from PIL import Image

    from ..volume import render, to_image

    rows, cols = _VIEW_AXES[view.lstrip("-")]
    er, ec = extent[rows], extent[cols]
    ph, pw = (size, max(1, round(size * ec / er))) if er >= ec else (max(1, round(size * er / ec)), size)
    rh, rw = max(1, round(ph * render_scale)), max(1, round(pw * render_scale))
    with torch.no_grad():
        img = render(vol, tf=tf, mode=mode, view=view, offsets=offsets, size=(rh, rw), engine="auto")
    rgb = to_image(img, flip_up=view.lstrip("-") in ("h", "w"))
    im = Image.fromarray(rgb)
    if (rh, rw) != (ph, pw):
        im = im.resize((pw, ph), Image.Resampling.BICUBIC)
    panel = Image.new("RGB", (size, size), (0, 0, 0))
    panel.paste(im, ((size - pw) // 2, (size - ph) // 2))
    return np.asarray(panel)


class _Piece:
    """A surface to draw: deformed ``vertices``, ``normals`` and ``rest`` positions ``(V, 3)``, ``faces``."""

    def __init__(self, vertices, normals, faces, rest):
        self.vertices, self.normals, self.faces, self.rest = vertices, normals, faces, rest


#: the colour of a drawn tool (steel)
TOOL_COLOUR = (0.62, 0.65, 0.7)


class _Flat:
    """A paint of one colour: :func:`~torchdeform.texture.render_textured` looks it up as a texture."""

    def __init__(self, colour):
        self.colour = torch.as_tensor(colour, dtype=torch.float64)

    def at_material(self, X: torch.Tensor) -> torch.Tensor:
        """The colour at every material point ``X`` ``(N, 3)``: ``(N, 3)``."""
        return self.colour.to(X.device, X.dtype).expand(len(X), 3)


def render_surfaces(layers, camera, *, light=LIGHT, specular: float = 0.3) -> dict:
    """Several bodies' surfaces in one image: each rendered with its own paint, the nearest kept (depth test).

    Args:
        layers: ``[(pieces, paint)]``: per body the surfaces to draw (``vertices``, ``faces``, ``rest``,
            optionally ``normals``, as :func:`~torchdeform.texture.render_textured` takes them) and a
            :class:`~torchdeform.texture.SolidTexture` or an RGB colour ``(3,)`` in [0, 1].
        camera: the :class:`~torchdeform.mesh.Camera`.
        light: direction towards the light.
        specular: the weight of the wet highlight.

    Returns:
        ``{"image": (H, W, 3), "depth": (H, W)}`` (``inf`` where nothing is hit; white there).

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> from torchdeform.topology import cut_surfaces
        >>> a, b = td.Grid((2, 2, 2), spacing=0.01), td.Grid((2, 2, 2), spacing=0.01, origin=(0.0, 0.02, 0.0))
        >>> pa = cut_surfaces(a, a.rest_positions(dtype=torch.float64), torch.zeros(2, 2, 2, dtype=torch.long))
        >>> pb = cut_surfaces(b, b.rest_positions(dtype=torch.float64), torch.zeros(2, 2, 2, dtype=torch.long))
        >>> both = torch.cat([a.rest_positions(dtype=torch.float64), b.rest_positions(dtype=torch.float64)], 2)
        >>> cam = surface_camera(a, both[None], size=48)
        >>> out = render_surfaces([(pa, (1.0, 0.0, 0.0)), (pb, (0.0, 0.0, 1.0))], cam, specular=0.0)
        >>> img = out["image"]
        >>> bool(((img[..., 0] > 0.2) & (img[..., 2] < 0.05)).any()), bool(((img[..., 2] > 0.2) & (img[..., 0] < 0.05)).any())
        (True, True)
    """
    from ..texture import render_textured

    image = depth = None
    for pieces, paint in layers:
        if not len(pieces):
            continue
        texture = paint if hasattr(paint, "at_material") else _Flat(paint)
        out = render_textured(pieces, texture, camera, light=light, specular=specular)
        if image is None or depth is None:
            image, depth = out["image"], out["depth"]
            continue
        front = out["depth"] < depth
        image = torch.where(front[..., None], out["image"], image)
        depth = torch.where(front, out["depth"], depth)
    if image is None:  # nothing to draw: a white panel
        h, w = camera.size
        image = torch.ones(h, w, 3, dtype=torch.float64)
        depth = torch.full((h, w), torch.inf, dtype=torch.float64)
    return {"image": image, "depth": depth}


def surface_panel(layers, camera, *, t: float = 0.0, tools=(), light=LIGHT, specular: float = 0.3) -> np.ndarray:
    """The surface panel of a frame: the bodies' surfaces (:func:`render_surfaces`) and the tools at ``t``.

    Args:
        layers: ``[(pieces, paint)]`` as :func:`render_surfaces` takes them.
        camera: the :class:`~torchdeform.mesh.Camera`.
        t: the simulated time (s): where the tools are.
        tools: :class:`~torchdeform.interact.tools.Tool` s drawn in front of or behind the bodies.
        light: direction towards the light.
        specular: the weight of the tissue's wet highlight.

    Returns:
        uint8 ``(H, W, 3)``.
    """
    out = render_surfaces(layers, camera, light=light, specular=specular)
    image = _with_tools(out, tools or (), float(t), camera, light).clamp(0, 1)
    return (image * 255 + 0.5).to(torch.uint8).numpy()


def _with_tools(out: dict, tools, t: float, camera, light=LIGHT) -> torch.Tensor:
    """The rendered body ``out`` with the tools at time ``t`` drawn in front of or behind it (depth test)."""
    from ..interact.meshes import tool_surface
    from ..interact.tools import Sphere
    from ..mesh.raster import rasterize

    image, depth = out["image"], out["depth"]
    for tool in tools:
        mesh = tool_surface(tool, t)
        if mesh is None:
            continue
        v = torch.as_tensor(mesh[0], dtype=image.dtype)
        f = torch.as_tensor(mesh[1])
        normals = v - v.mean(0) if isinstance(tool.shape, Sphere) else None  # a ball: smooth; edges stay sharp
        r = rasterize(
            v,
            f,
            camera,
            colors=torch.tensor(TOOL_COLOUR, dtype=image.dtype).expand(len(v), 3),
            light=light,
            ambient=0.3,
            normals=normals,
            specular=0.5,
        )
        front = r["depth"] < depth
        image = torch.where(front[..., None], r["image"], image)
        depth = torch.where(front, r["depth"], depth)
    return image


def _view(camera, camera_up) -> tuple:
    """``(up, light)`` of the surface panel: axis D up and :data:`LIGHT`, or lit from just above a given eye."""
    up = (1.0, 0.0, 0.0) if camera_up is None else tuple(float(c) for c in camera_up)
    light = LIGHT
    if camera is not None:
        d, u = np.asarray(camera, dtype=np.float64), np.asarray(up, dtype=np.float64)
        light = tuple((d / np.linalg.norm(d) + 0.5 * u / np.linalg.norm(u)).tolist())
    return up, light


def animate(
    grid,
    t,
    x,
    out_path,
    *,
    labels=None,
    texture=None,
    volume=None,
    tf: str = "ct-soft",
    mode: str = "dvr",
    view: str = "h",
    forces: dict | None = None,
    frames: int = 48,
    size: int = 512,
    fps: float = 12.0,
    render_scale: float = 0.4,
    progress: bool = False,
    surfaces=None,
    tools=None,
    specular: float = 0.3,
    camera=None,
    camera_up=None,
) -> dict:
    """Write an animated GIF of recorded frames: textured surface | deformed volume, time and forces.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid` of the run.
        t: times ``(T,)`` (s) of the recorded frames.
        x: node positions ``(T, 3, D, H, W)`` (m; batch entry 0 of the recording).
        out_path: the ``.gif`` file (its folder must exist).
        labels: int ``(D, H, W)`` pieces of the body (negative outside; default: the grid's nodes, one
            piece), as :func:`~torchdeform.topology.cut_surfaces` takes them.
        texture: a :class:`~torchdeform.texture.SolidTexture`, or the keyword arguments of
            :func:`body_texture` (``exemplar``, ``block``, ``seed``, ``voxel``) and ``seams`` (a
            method of :meth:`~torchdeform.texture.SolidTexture.blend`, default ``"3d"``), or None
            (the procedural liver, its seams blended).
        volume: ``(D', H', W')`` values, a volume file, ``"phantom"`` or ``"phantom:N"``; it fills the
            node grid's bounding box. None (the default): no volume panel.
        tf: transfer-function preset or file (``dvr``).
        mode: ``"dvr"``, ``"mip"`` or ``"average"``.
        view: the volume's axis view, ``"d"``, ``"h"``, ``"w"``, ``"-d"``, ``"-h"`` or ``"-w"``.
        forces: ``{name: (T, 3)}`` forces (N) of tools or drags at the recorded frames, or None.
        frames: the most frames shown (spread evenly over the recording, :func:`frame_indices`).
        size: side of each square panel (pixels).
        fps: frames per second of the GIF.
        render_scale: the volume is rendered at this fraction of the panel's resolution and scaled up
            (0.4 by default: a sixth of the rays, for speed).
        progress: show a progress bar.
        surfaces: :class:`~torchdeform.mesh.embed.EmbeddedSurface` s to show instead of the
            lattice's own surface (smooth, per-vertex normals), a function of the recorded frame's
            index giving them (surfaces cut during the run), or None.
        tools: :class:`~torchdeform.interact.tools.Tool` s drawn where they are at each frame
            (grey, shiny), or None.
        specular: the weight of the tissue's wet highlight (0: matt).
        camera: where the surface panel looks from ``(3,)``, from the body's centre (its length is
            fitted), or None (:data:`SURFACE_DIRECTION`, lit by :data:`LIGHT`). A given camera is lit
            from just above it (along ``camera_up``).
        camera_up: the direction ``(3,)`` upwards in the surface panel, or None (axis D).

    Returns:
        dict: ``file`` (the GIF's name), ``frames``, ``size`` ``[height, width]`` of a frame (pixels),
        ``panel`` (pixels), ``indices`` (the recorded frames shown), ``times_s``, ``captions``,
        ``bytes``, and ``camera``, the surface panel's :class:`~torchdeform.mesh.Camera`.
    """
    from tqdm.auto import tqdm

    from ..topology import cut_surfaces
    from ..volume import load_volume, node_offsets

    t = np.asarray(t, dtype=np.float64).reshape(-1)
    x = torch.as_tensor(x).detach().double().cpu()
    if x.dim() != 5 or x.shape[1] != 3 or tuple(x.shape[2:]) != grid.shape or len(x) != len(t):
        raise ConfigError("x", f"node positions (T, 3) + {grid.shape} with T = len(t) = {len(t)}", got=tuple(x.shape))
    if view.lstrip("-") not in _VIEW_AXES or view.count("-") > 1:
        raise ConfigError("view", "an axis view d, h, w, -d, -h, -w", got=view)
    size = int(size)
    idx = frame_indices(len(t), frames)
    if labels is None:
        labels = torch.where(grid.nodes(), 0, -1)
    if texture is None or isinstance(texture, dict):
        spec = dict(texture or {})
        seams = spec.pop("seams", "3d")
        texture = body_texture(grid, **spec)
        if seams != "none":
            texture.blend(method=seams)  # no square tiles on the surface
    if isinstance(volume, (str, Path)):
        volume = load_volume(str(volume), key="volume.file")
    vol = None
    if volume is not None:
        vol = torch.as_tensor(np.asarray(volume) if not torch.is_tensor(volume) else volume).float()
    X = grid.rest_positions(dtype=torch.float64)
    extent = [(n - 1) * s for n, s in zip(grid.shape, grid.spacing)]
    extent = [e if e > 0 else s for e, s in zip(extent, grid.spacing)]
    up, light = _view(camera, camera_up)
    shown = {}  # the embedded surfaces of each shown frame: the camera frames them, not the lattice
    for i in idx if surfaces else ():
        shown[i] = []
        for s in cast("list", surfaces(i) if callable(surfaces) else surfaces):
            p, n = s.update(x[i])
            shown[i].append(_Piece(p, n, s.faces, s.rest_vertices))
    points = torch.cat([q.vertices for i in shown for q in shown[i]]) if shown else None
    camera = surface_camera(
        grid,
        x[idx],
        size=size,
        up=up,
        direction=SURFACE_DIRECTION if camera is None else tuple(camera),
        points=points,
    )
    forces = {k: np.asarray(f, dtype=np.float64).reshape(len(t), 3) for k, f in (forces or {}).items()}
    titles = ("surface: solid texture, shaded", f"volume: {mode}, view {view}")
    if surfaces:
        titles = ("embedded surfaces: solid texture, smooth, wet", titles[1])
    images, captions = [], []
    for i in tqdm(idx, disable=not progress, desc="animate", unit="frame"):
        pieces = shown[i] if surfaces else cut_surfaces(grid, x[i : i + 1], labels)
        surface = surface_panel([(pieces, texture)], camera, t=float(t[i]), tools=tools, light=light, specular=specular)
        right = None
        if vol is not None:
            offsets = node_offsets(x[i : i + 1], X, grid.spacing, tuple(vol.shape)).float()
            right = _volume_panel(vol, offsets, tf, mode, view, extent, size, render_scale)
        text = caption(float(t[i]), forces={k: f[i] for k, f in forces.items()})
        captions.append(text)
        images.append(compose(surface, right, text, titles=titles))
    return _written(images, out_path, fps, size, idx, t, captions, camera)


def _written(images, out_path, fps, size, idx, t, captions, camera) -> dict:
    """Write the animation's frames ``images`` as a GIF; its part of ``summary.json``."""
    nbytes = write_gif(images, out_path, fps=fps)
    return {
        "file": Path(out_path).name,
        "frames": len(images),
        "size": list(images[0].shape[:2]),
        "panel": size,
        "indices": idx,
        "times_s": [float(t[i]) for i in idx],
        "captions": captions,
        "bytes": nbytes,
        "camera": camera,
    }


#: the colours of the bodies of a scene of several bodies, in the order of ``[[bodies]]`` (sRGB in [0, 1]):
#: the animation and the viewer draw body ``n`` in ``BODY_COLOURS[n % len(BODY_COLOURS)]``
BODY_COLOURS = (
    (0.80, 0.42, 0.36),  # liver red
    (0.40, 0.58, 0.82),  # blue
    (0.55, 0.76, 0.42),  # green
    (0.88, 0.72, 0.36),  # ochre
    (0.66, 0.48, 0.78),  # violet
    (0.40, 0.76, 0.74),  # teal
)
#: the colours of the curves of the contact panel (sRGB bytes), one per pair
_CURVES = ((255, 196, 92), (120, 200, 255), (160, 230, 120), (255, 130, 160), (200, 170, 255))


def curve_panel(t, curves: dict, now: float, *, size: int = 320, unit: str = "N") -> np.ndarray:
    """A small dark panel: each named series over time, and a vertical line at the time ``now``.

    Args:
        t: times ``(T,)`` (s).
        curves: ``{name: values (T,)}`` (e.g. the contact force's magnitude per pair, N).
        now: the frame's time (s): the curves are drawn up to it, the line marks it.
        size: the square panel's side (pixels).
        unit: ``"N"`` (values as :func:`format_force` writes them) or any unit written after the number.

    Returns:
        uint8 ``(size, size, 3)``.

    Example:
        >>> panel = curve_panel([0.0, 0.1, 0.2], {"a/b": [0.0, 0.5, 1.0]}, 0.1, size=64)
        >>> panel.shape, bool((panel == (255, 196, 92)).all(-1).any())
        ((64, 64, 3), True)
    """
    from PIL import Image, ImageDraw

    t = np.asarray(t, dtype=np.float64).reshape(-1)
    size = int(size)
    im = Image.new("RGB", (size, size), (30, 34, 39))
    draw = ImageDraw.Draw(im)
    small = _font(max(9, size // 28))
    left, right, top, bottom = size // 12, size - size // 24, size // 6, size - size // 9
    top_value = max((float(np.nanmax(np.asarray(v, dtype=np.float64))) for v in curves.values()), default=0.0)
    top_value = top_value * 1.1 if top_value > 0 else 1.0
    t0, t1 = (float(t[0]), float(t[-1])) if len(t) else (0.0, 1.0)
    span = t1 - t0 if t1 > t0 else 1.0

    def px(ti, vi):
        return left + (right - left) * (ti - t0) / span, bottom - (bottom - top) * vi / top_value

    draw.rectangle([left, top, right, bottom], outline=(110, 116, 124))
    fmt = format_force if unit == "N" else (lambda v: f"{float(np.asarray(v).reshape(-1)[0]):.3g} {unit}")
    draw.text((left, top - 3), fmt([top_value, 0, 0]), fill=(200, 200, 200), font=small, anchor="ld")
    draw.text((left - 2, bottom), "0", fill=(200, 200, 200), font=small, anchor="rm")
    draw.text((right, bottom + 2), f"{t1:.2f} s", fill=(200, 200, 200), font=small, anchor="ra")
    shown = t <= now + 1e-12
    for k, (name, values) in enumerate(curves.items()):
        colour = _CURVES[k % len(_CURVES)]
        v = np.nan_to_num(np.asarray(values, dtype=np.float64).reshape(-1))
        points = [px(ti, vi) for ti, vi in zip(t[shown], v[shown])]
        if len(points) > 1:
            draw.line(points, fill=colour, width=max(1, size // 160))
        elif points:
            draw.point(points, fill=colour)
        draw.text((left + 4, top + 4 + k * (size // 22 + 2)), name, fill=colour, font=small)
    x_now = px(min(max(float(now), t0), t1), 0.0)[0]
    draw.line([(x_now, top), (x_now, bottom)], fill=(235, 235, 235))
    return np.asarray(im)


def animate_bodies(
    grids,
    t,
    xs,
    out_path,
    *,
    names=None,
    colours=None,
    tools=None,
    forces: dict | None = None,
    contact: dict | None = None,
    frames: int = 48,
    size: int = 512,
    fps: float = 12.0,
    progress: bool = False,
    specular: float = 0.3,
    camera=None,
    camera_up=None,
) -> dict:
    """Write an animated GIF of several bodies: their surfaces, each in its own colour, and the contact forces.

    Each frame has the surface panel (every body's closed lattice surface,
    :func:`~torchdeform.topology.cut_surfaces` of its recorded node positions, flat-shaded in its own
    colour, the tools drawn where they are; one camera frames every body in every shown frame) and,
    with ``contact``, a panel of the contact force per pair over time up to the frame
    (:func:`curve_panel`), and the caption (time, tool forces).

    Args:
        grids: per body its :class:`~torchdeform.sim.grid.Grid` (placed in the world by its origin).
        t: times ``(T,)`` (s) of the recorded frames.
        xs: per body its node positions ``(T, 3, D, H, W)`` (m).
        out_path: the ``.gif`` file (its folder must exist).
        names: the bodies' names (the panel's title), or None.
        colours: per body an RGB colour in [0, 1] (default :data:`BODY_COLOURS` in turn).
        tools: :class:`~torchdeform.interact.tools.Tool` s of every body, drawn at each frame.
        forces: ``{name: (T, 3)}`` forces (N) of the tools at the recorded frames (the caption), or None.
        contact: ``{"<a>/<b>": (T, 3)}`` contact force (N) per pair at the recorded frames, or None (no
            curve panel).
        frames: the most frames shown (:func:`frame_indices`).
        size: side of each square panel (pixels).
        fps: frames per second of the GIF.
        progress: show a progress bar.
        specular: the weight of the tissue's wet highlight (0: matt).
        camera: where the surface panel looks from ``(3,)``, from the bodies' centre, or None
            (:data:`SURFACE_DIRECTION`).
        camera_up: the direction ``(3,)`` upwards in the surface panel, or None (axis D).

    Returns:
        dict: ``file``, ``frames``, ``size`` ``[height, width]``, ``panel``, ``indices``, ``times_s``,
        ``captions``, ``bytes``, ``camera``, ``colours`` (per body, sRGB bytes).

    Example:
        >>> import torch
        >>> import torchdeform as td
        >>> lower, upper = td.Grid((3, 3, 3), spacing=0.01), td.Grid((2, 2, 2), spacing=0.01, origin=(0.03, 0.005, 0.005))
        >>> xl = lower.rest_positions(dtype=torch.float32)[0].expand(2, 3, 3, 3, 3)
        >>> xu = torch.stack([upper.rest_positions(dtype=torch.float32)[0]] * 2)
        >>> xu[1, 0] -= 0.005                                   # the upper body falls 5 mm
        >>> info = animate_bodies([lower, upper], [0.0, 0.1], [xl, xu], getfixture("tmp_path") / "b.gif",
        ...                       size=64, contact={"lower/upper": [[0, 0, 0], [0.01, 0, 0]]})
        >>> info["frames"], info["size"], info["colours"]
        (2, [88, 128], [[204, 107, 92], [102, 148, 209]])
    """
    from tqdm.auto import tqdm

    from ..topology import cut_surfaces

    t = np.asarray(t, dtype=np.float64).reshape(-1)
    grids = list(grids)
    xs = [torch.as_tensor(x).detach().double().cpu() for x in xs]
    if not grids or len(xs) != len(grids):
        raise ConfigError("xs", f"node positions of every body ({len(grids)})", got=len(xs))
    for n, (grid, x) in enumerate(zip(grids, xs)):
        if x.dim() != 5 or x.shape[1] != 3 or tuple(x.shape[2:]) != grid.shape or len(x) != len(t):
            raise ConfigError(
                f"xs[{n}]", f"node positions (T, 3) + {grid.shape} with T = len(t) = {len(t)}", got=tuple(x.shape)
            )
    names = list(names) if names is not None else [f"body {n}" for n in range(len(grids))]
    colours = [tuple(c) for c in colours] if colours is not None else []
    colours += [BODY_COLOURS[n % len(BODY_COLOURS)] for n in range(len(colours), len(grids))]
    size = int(size)
    idx = frame_indices(len(t), frames)
    labels = [torch.where(grid.nodes(), 0, -1) for grid in grids]
    up, light = _view(camera, camera_up)
    points = torch.cat([x[idx].transpose(1, 2).reshape(-1, 3) for x in xs])
    widest = max(grids, key=lambda g: max(g.spacing))
    camera = surface_camera(
        widest, None, size=size, up=up, direction=SURFACE_DIRECTION if camera is None else tuple(camera), points=points
    )
    forces = {k: np.asarray(f, dtype=np.float64).reshape(len(t), 3) for k, f in (forces or {}).items()}
    curves = None
    if contact:
        curves = {
            k: np.linalg.norm(np.asarray(f, dtype=np.float64).reshape(len(t), 3), axis=1) for k, f in contact.items()
        }
    titles = (", ".join(names) + ": surfaces, shaded", "contact force per pair")
    images, captions = [], []
    for i in tqdm(idx, disable=not progress, desc="animate", unit="frame"):
        layers = [(cut_surfaces(g, x[i : i + 1], lab), c) for g, x, lab, c in zip(grids, xs, labels, colours)]
        surface = surface_panel(layers, camera, t=float(t[i]), tools=tools, light=light, specular=specular)
        right = curve_panel(t, curves, float(t[i]), size=size) if curves is not None else None
        text = caption(float(t[i]), forces={k: f[i] for k, f in forces.items()})
        captions.append(text)
        images.append(compose(surface, right, text, titles=titles))
    summary = _written(images, out_path, fps, size, idx, t, captions, camera)
    summary["colours"] = [[round(255 * v) for v in c] for c in colours]
    return summary
