"""Command-line code of solid textures: ``torchdeform texture EXEMPLAR --mesh MESH --out OUT``.

Colours any closed triangle mesh with a solid texture: the mesh's own coordinates are its
material coordinates. Bad input (an exemplar that is not RGB, slice images of different sizes, a
block larger than the exemplar, a mesh that is not closed, an unknown output type or seam method) is a
:class:`~torchdeform.errors.ConfigError`: one line on stderr and exit status 2.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..errors import ConfigError
from ..options import integer, number

__all__ = ["add_arguments", "command"]


def add_arguments(p) -> None:
    """The arguments of ``torchdeform texture`` on an :mod:`argparse` parser."""
    p.add_argument(
        "exemplar",
        help="liver[:N] (procedural, N^3 voxels, default 128), a .npy/.npz RGB volume or a folder of slice images",
    )
    p.add_argument("--mesh", required=True, help="a closed triangle mesh (.stl, .obj, .ply, .off, ...)")
    p.add_argument("--out", required=True, help="output: .ply (vertex colours), .glb or .obj (texture atlas)")
    p.add_argument("--scale", type=number(lo=0, lo_open=True), default=1.0, help="metres per mesh unit (default 1)")
    p.add_argument(
        "--voxel",
        type=number(lo=0, lo_open=True),
        default=None,
        help="texture voxel size in metres (default: the mesh's largest extent / 128)",
    )
    p.add_argument(
        "--block", type=integer(lo=1), default=None, help="block size in voxels (default: half the exemplar)"
    )
    p.add_argument(
        "--seed", type=integer(lo=0), default=0, help="seed of the block offsets (and of a procedural exemplar)"
    )
    p.add_argument(
        "--seams",
        default="none",
        help="blend the block seams: none (default), 3d (3-D Poisson) or slices (Chen & He's per-slice 2-D Poisson)",
    )
    p.add_argument("--image", default=None, help="also write a PNG view of the textured mesh")


def command(args) -> int:
    """``torchdeform texture``: colour a closed mesh with a solid texture; returns the exit status."""
    from ..mesh import load_mesh
    from .exemplar import exemplar_from
    from .synthesis import SEAM_METHODS, SolidTexture

    out = Path(args.out)
    if out.suffix.lower() not in (".ply", ".glb", ".obj"):
        raise ConfigError("--out", "a .ply, .glb or .obj file", got=str(out))
    if args.seams not in SEAM_METHODS:
        raise ConfigError("--seams", " or ".join(SEAM_METHODS), got=args.seams)
    vertices, faces = load_mesh(args.mesh, scale=args.scale, key="--mesh")
    ex = exemplar_from(args.exemplar, seed=args.seed)
    lo, hi = vertices.min(0), vertices.max(0)
    voxel = args.voxel or float((hi - lo).max()) / 128
    if not voxel > 0:
        raise ConfigError("--voxel", "a positive voxel size (m)", got=args.voxel)
    block = args.block or min(ex.shape[1:]) // 2
    extent = [int((h - l) / voxel) + 2 for l, h in zip(lo, hi)]
    tex = SolidTexture(ex, block=block, extent=extent, seed=args.seed, voxel=voxel, origin=tuple(lo))
    seams = ""
    if args.seams != "none":
        r = tex.blend(method=args.seams)
        seams = (
            f"; seams ({args.seams} Poisson, {r['seconds']:.1f} s): jump {r['seam_before']:.2f} -> "
            f"{r['seam_after']:.2f}, histogram distance {r['histogram_before']:.4f} -> {r['histogram_after']:.4f}"
        )
    t0 = time.perf_counter()
    from .atlas import export_textured

    export_textured(out, vertices, faces, vertices, tex)
    took = time.perf_counter() - t0
    if args.image:
        _image(args.image, vertices, faces, tex)
    print(
        f"textured {args.mesh} ({len(vertices)} vertices, {len(faces)} faces) with {args.exemplar} "
        f"({'x'.join(map(str, ex.shape[1:]))} voxels, {block}^3 blocks, {'x'.join(map(str, tex.blocks))} of them, "
        f"{voxel * 1e3:.3g} mm voxels) in {took:.2f} s -> {out}" + (f", {args.image}" if args.image else "") + seams
    )
    return 0


def _image(path, vertices, faces, tex) -> None:
    """A perspective view of the textured mesh from an oblique corner."""
    from ..mesh import save_png
    from ..topology.surfaces import CutSurface
    from .mapping import framing_camera, render_textured

    cam = framing_camera(vertices, direction=(1.2, -1.0, 1.4), fov_deg=40.0, size=(384, 512))
    out = render_textured([CutSurface(0, vertices, faces, vertices)], tex, cam, light=(1.0, -0.5, 0.7))
    save_png(path, out["image"])
