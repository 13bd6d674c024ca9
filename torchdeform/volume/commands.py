"""Command-line code of volumes: ``torchdeform warp`` and ``torchdeform render``.

Bad input (wrong shapes or dtypes, NaN voxels, unknown file types, a node grid finer than the
volume) is a :class:`~torchdeform.errors.ConfigError`: one line on stderr and exit status 2.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from ..options import int_list, integer, number, number_list
from .cameras import OrbitCamera
from .deform import as_offsets, warp
from .images import orbit_frames, save_gif, save_png, to_image
from .io import load_volume, read_array, save_volume
from .plan import AXIS_VIEWS
from .rendering import render
from .transfer import get_tf

__all__ = ["add_warp_arguments", "add_render_arguments", "warp_command", "render_command", "load_offsets"]


def add_warp_arguments(p) -> None:
    """The arguments of ``torchdeform warp`` on an :mod:`argparse` parser."""
    p.add_argument("volume", help="volume file (.npy, .npz, .nii, .nii.gz, .nrrd) or phantom[:N]")
    p.add_argument("offsets", help="node offsets .npy/.npz, shape (3, n_d, n_h, n_w), voxels, channels (D, H, W)")
    p.add_argument("--out", required=True, help="output volume (.npy, .npz, .nii, .nii.gz, .nrrd)")
    p.add_argument("--mode", choices=("deform", "carve", "knoche"), default="deform")
    p.add_argument("--inverse-iters", type=integer(lo=0), default=0, help="fixed-point inverse iterations (default 0)")
    p.add_argument("--order", choices=("linear", "bspline"), default="linear", help="offset texture")
    p.add_argument("--padding", choices=("border", "zeros"), default="border")
    p.add_argument("--fill", type=number(), default=0.0, help="value outside the volume / of removed material")


def load_offsets(path, *, volume_shape=None):
    """Node offsets from ``.npy``/``.npz``: a ``(3, n_d, n_h, n_w)`` float tensor checked against the volume."""
    arr = read_array(path, key="offsets")
    if arr.dtype.kind not in "iuf":
        raise ConfigError("offsets", "a numeric array of node offsets", got=f"{path}: dtype {arr.dtype}")
    if arr.ndim != 4 or arr.shape[0] != 3:
        raise ConfigError(
            "offsets",
            "an array of shape (3, n_d, n_h, n_w) (voxels, channels D, H, W)",
            got=f"{path}: shape {arr.shape}",
        )
    return as_offsets(
        torch.as_tensor(np.asarray(arr, dtype=np.float32)), volume_shape=volume_shape, key=f"offsets ({path})"
    )


def warp_command(args) -> int:
    """``torchdeform warp``: deform a volume by node offsets and save it; returns the exit status."""
    vol = load_volume(args.volume)
    offsets = load_offsets(args.offsets, volume_shape=vol.shape)
    if args.inverse_iters < 0:
        raise ConfigError("--inverse-iters", "an integer >= 0", got=args.inverse_iters)
    with torch.no_grad():
        out, info = warp(
            torch.from_numpy(vol),
            offsets,
            mode=args.mode,
            inverse_iters=args.inverse_iters,
            order=args.order,
            padding=args.padding,
            fill=args.fill,
            return_info=True,
        )
    save_volume(args.out, out.numpy())
    folded = info["folded"]
    iterations = f", {int(info['iterations'])} inverse iterations" if args.inverse_iters else ""
    folding = f", folded {100 * folded:.2f}%" if folded else ""
    print(
        f"warped {args.volume} {vol.shape} by {tuple(offsets.shape[2:])} nodes ({args.mode}{iterations}{folding}) -> {args.out}"
    )
    return 0


def add_render_arguments(p) -> None:
    """The arguments of ``torchdeform render`` on an :mod:`argparse` parser."""
    p.add_argument("volume", help="volume file (.npy, .npz, .nii, .nii.gz, .nrrd) or phantom[:N]")
    p.add_argument("--out", required=True, help="image file (.png; .gif writes an orbit)")
    p.add_argument("--offsets", default=None, help="node offsets (3, n_d, n_h, n_w) in voxels: render deformed")
    p.add_argument("--mode", choices=("mip", "dvr", "average"), default="dvr")
    p.add_argument("--tf", default="ct-soft", help="transfer-function preset (ct-bone, ct-soft, grey) or file")
    p.add_argument("--view", default="h", help="axis view d, h, w, -d, -h, -w, or orbit (default h)")
    p.add_argument("--azimuth", type=number(), default=30.0, help="orbit view: degrees (default 30)")
    p.add_argument("--elevation", type=number(), default=20.0, help="orbit view: degrees (default 20)")
    p.add_argument("--size", type=integer(lo=8, hi=16384), default=256, help="orbit image size in pixels (default 256)")
    p.add_argument("--frames", type=integer(lo=1, hi=3600), default=24, help="GIF orbit frames (default 24)")
    p.add_argument("--step", type=number(lo=0.05), default=1.0, help="sample spacing along rays in voxels")
    p.add_argument("--inverse-iters", type=integer(lo=0), default=0)
    p.add_argument(
        "--engine",
        choices=("auto", "native", "grid_sample", "eager", "compiled"),
        default="auto",
        help="axis views: auto (default: the C ray marcher for dvr of a float32 volume, else "
        "grid_sample), native, grid_sample, or through --offsets the fused fast path, compiled "
        "(30-60 s to compile once) or eager",
    )
    e = p.add_argument_group(
        "endoscope",
        "--camera endoscope: a wide-angle camera inside the volume (voxel coordinates D,H,W), headlit. "
        "Example: torchdeform render phantom-lumen:128 --camera endoscope --eye 40,53.4,35 --look 42,49,45 "
        "--tf ct-lumen --out scope.png",
    )
    e.add_argument("--camera", choices=("endoscope",), default=None, help="the endoscope instead of --view")
    e.add_argument("--eye", type=number_list(count=3), default=None, help="camera position D,H,W (voxels)")
    e.add_argument("--look", type=number_list(count=3), default=None, help="a point it looks at, D,H,W (voxels)")
    e.add_argument(
        "--path",
        default=None,
        help="a .gif: the fly-through along points 'D,H,W;D,H,W;...' (voxels; at least two), one frame per --frames",
    )
    e.add_argument("--fov", type=number(lo=0, hi=180, lo_open=True, hi_open=True), default=100.0, help="degrees")
    e.add_argument("--far", type=number(lo=0, lo_open=True), default=None, help="depth of view in voxels (default all)")
    e.add_argument("--distortion", type=number(), default=0.0, help="barrel coefficient k1 (negative: barrel)")
    e.add_argument("--labels", default=None, help="a label volume: print what the path passes through")
    e.add_argument("--avoid", type=int_list(), default=None, help="labels the path must keep --min-distance from")
    e.add_argument("--min-distance", type=number(lo=0), default=0.0, help="mm from the --avoid labels")
    e.add_argument(
        "--spacing", type=number_list(count=3, lo=0, lo_open=True), default=None, help="voxel size D,H,W in mm"
    )


def _path_points(text: str) -> list:
    """``--path``: ``'D,H,W;D,H,W;...'`` as a list of points (at least two)."""
    parse = number_list(count=3)
    try:
        points = [parse(p) for p in str(text).split(";") if p.strip()]
    except Exception:
        points = []
    if len(points) < 2:
        raise ConfigError("--path", "at least two points 'D,H,W;D,H,W' in voxels", got=text)
    return points


def _endoscope_command(args, out: Path) -> int:
    """``torchdeform render --camera endoscope``: one view (PNG) or a fly-through (GIF and its frames)."""
    from .endoscope import EndoscopeCamera
    from .interior import render_endoscope
    from .planning import Trajectory, check_trajectory, fly_through

    vol = torch.from_numpy(load_volume(args.volume))
    offsets = load_offsets(args.offsets, volume_shape=tuple(vol.shape)) if args.offsets else None
    far = math.inf if args.far is None else args.far
    size = (args.size, args.size)
    kw = dict(fov=args.fov, size=size, far=far, distortion=args.distortion)
    if args.path is not None:
        trajectory = Trajectory.from_points(_path_points(args.path))
    elif args.eye is not None and args.look is not None:
        trajectory = Trajectory(args.eye, args.look)
    else:
        raise ConfigError("--eye", "--eye and --look (or --path) with --camera endoscope", got=None)
    if args.labels is not None:
        labels = load_volume(args.labels, key="--labels")
        report = check_trajectory(
            labels, trajectory, spacing=args.spacing, avoid=args.avoid, min_distance=args.min_distance, kind="labels"
        )
        print("\n".join(report.lines()))
    with torch.no_grad():
        if out.suffix.lower() == ".gif":
            folder = out.with_name(out.stem + "-frames")  # frame_000.png, ... and the GIF
            frames = fly_through(vol, trajectory, frames=args.frames, tf=args.tf, offsets=offsets, out=folder, **kw)
            save_gif(out, frames)
            print(
                f"flew through {args.volume} along {len(trajectory.vertices)} points: {len(frames)} frames -> {out}, {folder}"
            )
            return 0
        cam = EndoscopeCamera.look_at(args.eye, args.look, **kw)
        img = render_endoscope(vol, cam, tf=args.tf, offsets=offsets, step=min(args.step, 0.5))
        save_png(out, to_image(img))
    print(f"rendered {args.volume} (endoscope at {args.eye}, fov {args.fov:g} deg) -> {out}")
    return 0


def render_command(args) -> int:
    """``torchdeform render``: a PNG of one view, or a GIF orbit; returns the exit status."""
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".gif"):
        raise ConfigError("--out", "an image file ending in .png or .gif", got=str(out))
    if args.camera == "endoscope":
        return _endoscope_command(args, out)
    if args.view not in AXIS_VIEWS + ("orbit",):
        raise ConfigError("--view", "one of " + ", ".join(AXIS_VIEWS + ("orbit",)), got=args.view)
    if args.size < 8 or args.frames < 1:
        raise ConfigError("--size", "an image size >= 8 and --frames >= 1", got=(args.size, args.frames))
    vol = torch.from_numpy(load_volume(args.volume))
    offsets = load_offsets(args.offsets, volume_shape=tuple(vol.shape)) if args.offsets else None
    tf = get_tf(args.tf) if args.mode == "dvr" else None
    kw = dict(tf=tf, mode=args.mode, offsets=offsets, step=args.step, inverse_iters=args.inverse_iters)
    with torch.no_grad():
        if out.suffix.lower() == ".gif":
            frames = orbit_frames(vol, frames=args.frames, elevation=args.elevation, size=(args.size, args.size), **kw)
            save_gif(out, frames)
        else:
            view = (
                OrbitCamera(azimuth=args.azimuth, elevation=args.elevation, size=(args.size, args.size))
                if args.view == "orbit"
                else args.view
            )
            img = render(vol, view=view, engine=args.engine, **kw)
            save_png(out, to_image(img, flip_up=args.view in ("h", "-h", "w", "-w")))
    print(f"rendered {args.volume} ({args.mode}, view {args.view}) -> {out}")
    return 0
