"""Reading and writing volumes: ``.npy``, ``.npz``, NIfTI (``.nii``, ``.nii.gz``) and NRRD (``.nrrd``).

NIfTI needs ``nibabel`` and NRRD ``pynrrd`` (``pip install torchdeform[volume]``); both are
imported only when such a file is read or written. Axis 0 of the stored array is D, axis 1
H, axis 2 W, whatever the format (no reorientation), so a file written and read back is the
same array. ``phantom`` (optionally ``phantom:N``) names the procedural phantom of
:mod:`torchdeform.phantom` instead of a file.

Example:
    >>> import numpy as np, tempfile, os
    >>> from torchdeform.volume_io import load_volume, save_volume
    >>> path = os.path.join(tempfile.mkdtemp(), "v.npy")
    >>> save_volume(path, np.zeros((4, 5, 6), np.float32))
    >>> load_volume(path).shape
    (4, 5, 6)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import ConfigError

SUFFIXES = (".npy", ".npz", ".nii", ".nii.gz", ".nrrd", ".nhdr")
_EXTRA = {"nibabel": "NIfTI files need nibabel: pip install nibabel (or torchdeform[volume])",
          "nrrd": "NRRD files need pynrrd: pip install pynrrd (or torchdeform[volume])"}


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
        raise ConfigError(key, _EXTRA[module], str(path)) from None


def check_array(arr, key: str, path=None, ndim: int = 3) -> np.ndarray:
    """A real numeric array with ``ndim`` axes and finite values, else a one-line ConfigError."""
    arr = np.asarray(arr)
    where = f"{path}: " if path else ""
    if arr.dtype.kind not in "biuf":
        raise ConfigError(key, "a numeric array (integers or floats)", f"{where}dtype {arr.dtype}")
    if arr.ndim != ndim or min(arr.shape, default=0) < 1:
        raise ConfigError(key, f"a non-empty {ndim}-D array" + (" (D, H, W)" if ndim == 3 else ""),
                          f"{where}shape {arr.shape}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise ConfigError(key, "finite values (no NaN or inf)",
                          f"{where}{int((~np.isfinite(arr)).sum())} non-finite values")
    return arr


def read_array(path, key: str = "volume") -> np.ndarray:
    """The raw array stored in a file (any number of axes), by file type."""
    path = Path(path)
    suffix = _suffix(path)
    if suffix not in SUFFIXES:
        raise ConfigError(key, "a .npy, .npz, .nii, .nii.gz or .nrrd file", str(path))
    if not path.is_file():
        raise ConfigError(key, "an existing file", f"{path} (not found)")
    try:
        if suffix == ".npy":
            return np.load(path, allow_pickle=False)
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                names = list(z.files)
                name = "volume" if "volume" in names else (names[0] if len(names) == 1 else None)
                if name is None:
                    raise ConfigError(key, "an .npz with one array or an array named 'volume'",
                                      f"{path} (arrays {names})")
                return z[name]
        if suffix in (".nii", ".nii.gz"):
            nib = _optional("nibabel", key, path)
            return np.asarray(nib.load(str(path)).dataobj)
        nrrd = _optional("nrrd", key, path)
        data, _ = nrrd.read(str(path), index_order="C")
        return data
    except ConfigError:
        raise
    except Exception as e:                              # corrupt files raise many kinds
        raise ConfigError(key, f"a readable {suffix} file", f"{path} ({type(e).__name__}: {e})") from None


def load_volume(path, key: str = "volume") -> np.ndarray:
    """A volume ``(D, H, W)`` as float32 numpy (integers converted, NaN/inf rejected).

    ``path`` may also be ``"phantom"`` or ``"phantom:N"`` (the procedural phantom, ``N^3`` voxels,
    default 128).
    """
    text = str(path)
    if text == "phantom" or text.startswith("phantom:"):
        from .phantom import phantom
        try:
            n = int(text.split(":", 1)[1]) if ":" in text else 128
        except ValueError:
            n = 0
        if n < 8:
            raise ConfigError(key, "phantom or phantom:N with N >= 8 voxels", text)
        return phantom((n, n, n)).numpy()
    arr = check_array(read_array(path, key), key, path)
    return np.ascontiguousarray(arr, dtype=np.float32)


def save_volume(path, volume, spacing=(1.0, 1.0, 1.0), key: str = "--out") -> None:
    """Write a ``(D, H, W)`` volume (numpy or torch) by file type; ``spacing`` goes into NIfTI/NRRD headers."""
    path = Path(path)
    arr = volume.detach().cpu().numpy() if hasattr(volume, "detach") else np.asarray(volume)
    suffix = _suffix(path)
    if suffix not in SUFFIXES or suffix == ".nhdr":
        raise ConfigError(key, "an output file ending in .npy, .npz, .nii, .nii.gz or .nrrd", str(path))
    if path.parent and not path.parent.exists():
        raise ConfigError(key, "a file in an existing folder", str(path))
    if suffix == ".npy":
        np.save(path, arr)
    elif suffix == ".npz":
        np.savez_compressed(path, volume=arr)
    elif suffix in (".nii", ".nii.gz"):
        nib = _optional("nibabel", key, path)
        nib.save(nib.Nifti1Image(arr, np.diag([*map(float, spacing), 1.0])), str(path))
    else:
        nrrd = _optional("nrrd", key, path)
        nrrd.write(str(path), arr, {"spacings": [float(s) for s in spacing]}, index_order="C")


__all__ = ["load_volume", "save_volume", "read_array", "check_array", "SUFFIXES"]


# ------------------------------------------------------------------ the warp and render commands
def add_warp_arguments(p) -> None:
    p.add_argument("volume", help="volume file (.npy, .npz, .nii, .nii.gz, .nrrd) or phantom[:N]")
    p.add_argument("offsets", help="node offsets .npy/.npz, shape (3, n_d, n_h, n_w), voxels, channels (D, H, W)")
    p.add_argument("--out", required=True, help="output volume (.npy, .npz, .nii, .nii.gz, .nrrd)")
    p.add_argument("--mode", choices=("deform", "carve", "knoche"), default="deform")
    p.add_argument("--inverse-iters", type=int, default=0, help="fixed-point inverse iterations (default 0)")
    p.add_argument("--order", choices=("linear", "bspline"), default="linear", help="offset texture")
    p.add_argument("--padding", choices=("border", "zeros"), default="border")
    p.add_argument("--fill", type=float, default=0.0, help="value outside the volume / of removed material")


def load_offsets(path, volume_shape=None):
    """Node offsets from ``.npy``/``.npz``: a ``(3, n_d, n_h, n_w)`` float tensor checked against the volume."""
    import torch
    from .volume import as_offsets
    arr = read_array(path, "offsets")
    if arr.dtype.kind not in "iuf":
        raise ConfigError("offsets", "a numeric array of node offsets", f"{path}: dtype {arr.dtype}")
    if arr.ndim != 4 or arr.shape[0] != 3:
        raise ConfigError("offsets", "an array of shape (3, n_d, n_h, n_w) (voxels, channels D, H, W)",
                          f"{path}: shape {arr.shape}")
    return as_offsets(torch.as_tensor(np.asarray(arr, dtype=np.float32)), volume_shape, key=f"offsets ({path})")


def warp_command(args) -> int:
    import torch
    from .volume import warp
    vol = load_volume(args.volume)
    offsets = load_offsets(args.offsets, vol.shape)
    if args.inverse_iters < 0:
        raise ConfigError("--inverse-iters", "an integer >= 0", args.inverse_iters)
    with torch.no_grad():
        out, info = warp(torch.from_numpy(vol), offsets, args.mode, inverse_iters=args.inverse_iters,
                         order=args.order, padding=args.padding, fill=args.fill, return_info=True)
    save_volume(args.out, out.numpy())
    folded = info["folded"]
    print(f"warped {args.volume} {vol.shape} by {tuple(offsets.shape[2:])} nodes ({args.mode}"
          f"{', %d inverse iterations' % info['iterations'] if args.inverse_iters else ''}"
          f"{', folded %.2f%%' % (100 * folded) if folded else ''}) -> {args.out}")
    return 0


def add_render_arguments(p) -> None:
    p.add_argument("volume", help="volume file (.npy, .npz, .nii, .nii.gz, .nrrd) or phantom[:N]")
    p.add_argument("--out", required=True, help="image file (.png; .gif writes an orbit)")
    p.add_argument("--offsets", default=None, help="node offsets (3, n_d, n_h, n_w) in voxels: render deformed")
    p.add_argument("--mode", choices=("mip", "dvr", "average"), default="dvr")
    p.add_argument("--tf", default="ct-soft", help="transfer-function preset (ct-bone, ct-soft, grey) or file")
    p.add_argument("--view", default="h", help="axis view d, h, w, -d, -h, -w, or orbit (default h)")
    p.add_argument("--azimuth", type=float, default=30.0, help="orbit view: degrees (default 30)")
    p.add_argument("--elevation", type=float, default=20.0, help="orbit view: degrees (default 20)")
    p.add_argument("--size", type=int, default=256, help="orbit image size in pixels (default 256)")
    p.add_argument("--frames", type=int, default=24, help="GIF orbit frames (default 24)")
    p.add_argument("--step", type=float, default=1.0, help="sample spacing along rays in voxels")
    p.add_argument("--inverse-iters", type=int, default=0)
    p.add_argument("--engine", choices=("grid_sample", "eager", "compiled"), default="grid_sample",
                   help="axis views through --offsets: grid_sample (default), or the fused fast path, "
                        "compiled (~10x faster per frame, 30-60 s to compile once) or eager")


def render_command(args) -> int:
    import torch
    from .render import AXIS_VIEWS, OrbitCamera, get_tf, orbit_frames, render, save_gif, save_png, to_image
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".gif"):
        raise ConfigError("--out", "an image file ending in .png or .gif", str(out))
    if args.view not in AXIS_VIEWS + ("orbit",):
        raise ConfigError("--view", "one of " + ", ".join(AXIS_VIEWS + ("orbit",)), args.view)
    if args.size < 8 or args.frames < 1:
        raise ConfigError("--size", "an image size >= 8 and --frames >= 1", (args.size, args.frames))
    vol = torch.from_numpy(load_volume(args.volume))
    offsets = load_offsets(args.offsets, tuple(vol.shape)) if args.offsets else None
    tf = get_tf(args.tf) if args.mode == "dvr" else None
    kw = dict(tf=tf, mode=args.mode, offsets=offsets, step=args.step, inverse_iters=args.inverse_iters)
    with torch.no_grad():
        if out.suffix.lower() == ".gif":
            save_gif(out, orbit_frames(vol, args.frames, args.elevation, (args.size, args.size), **kw))
        else:
            view = OrbitCamera(args.azimuth, args.elevation, size=(args.size, args.size)) \
                if args.view == "orbit" else args.view
            img = render(vol, view=view, engine=args.engine, **kw)
            save_png(out, to_image(img, flip_up=args.view in ("h", "-h", "w", "-w")))
    print(f"rendered {args.volume} ({args.mode}, view {args.view}) -> {out}")
    return 0


def scene_volume_outputs(volume, x, X, spacing, out_dir, tf: str = "ct-soft", mode: str = "dvr",
                         view: str = "h", base=None) -> dict:
    """Deform a scene's volume by its final node positions and write ``volume_before.png``,
    ``volume_after.png`` and ``volume_deformed.npy`` to ``out_dir``.

    The volume fills the node grid's bounding box (:func:`~torchdeform.volume.node_offsets`).

    Args:
        volume: a file name (relative to ``base``), ``"phantom"`` or ``"phantom:N"``.
        x, X: final and rest node positions ``(1, 3, n_d, n_h, n_w)`` (m); spacing: node spacing (m).
    Returns:
        a summary dict for ``summary.json``.
    """
    import torch
    from .render import render, save_png, to_image
    from .volume import node_offsets, warp
    name = str(volume)
    path = name if name.startswith("phantom") or base is None else str(Path(base) / name)
    vol = torch.from_numpy(load_volume(path, "volume.file"))
    out = Path(out_dir)
    with torch.no_grad():
        offsets = node_offsets(x.double().cpu(), X.double().cpu(), spacing, tuple(vol.shape)).float()
        deformed, info = warp(vol, offsets, return_info=True)
        flip = view in ("h", "-h", "w", "-w")
        save_png(out / "volume_before.png", to_image(render(vol, tf, mode, view), flip_up=flip))
        save_png(out / "volume_after.png", to_image(render(vol, tf, mode, view, offsets=offsets), flip_up=flip))
    save_volume(out / "volume_deformed.npy", deformed.numpy())
    return {"volume": name, "shape": list(vol.shape), "max_offset_voxels": float(offsets.abs().max()),
            "folded_fraction": info["folded"], "outputs": ["volume_before.png", "volume_after.png",
                                                            "volume_deformed.npy"]}
