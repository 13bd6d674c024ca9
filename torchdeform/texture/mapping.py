"""Colours on surfaces at material coordinates: the texture moves with the tissue and shows inside cuts.

Every surface vertex of :func:`~torchdeform.topology.surfaces.cut_surfaces` carries its rest
(material) coordinates; the solid texture is looked up there (Chen & He's node colouring), and
inside each triangle at the interpolated rest coordinates of every pixel (the rasteriser's
``texcoords``), so a triangle shows the texture at about one sample per pixel instead of a blend
of its three corner colours. A face that a cut opens has rest coordinates inside the body: it
shows the interior, where it is (the "cutting and interior display" Chen & He left open).

Examples:
    >>> import torch
    >>> import torchdeform as td
    >>> from torchdeform.texture import SolidTexture, liver_exemplar
    >>> from torchdeform.topology import cut_surfaces
    >>> grid = td.Grid((4, 4, 4), spacing=0.002)
    >>> (piece,) = cut_surfaces(grid, grid.rest_positions(dtype=torch.float64), torch.zeros(4, 4, 4, dtype=torch.long))
    >>> tex = SolidTexture(liver_exemplar(size=16), block=8, extent=(16, 16, 16), voxel=0.0005, origin=(-0.001,) * 3)
    >>> vertex_colours(tex, piece).shape == piece.vertices.shape
    True
"""

from __future__ import annotations

import torch

__all__ = ["vertex_colours", "render_textured", "framing_camera", "body_texture", "MAX_SIDE"]


def vertex_colours(texture, surface) -> torch.Tensor:
    """Colours ``(V, 3)`` of a surface's vertices at their rest coordinates (Chen & He's node colouring).

    Args:
        texture: a :class:`~torchdeform.texture.synthesis.SolidTexture`.
        surface: anything with ``rest`` ``(V, 3)`` material coordinates (m), such as a
            :class:`~torchdeform.topology.surfaces.CutSurface`.
    """
    return texture.at_material(torch.as_tensor(surface.rest, dtype=torch.float64)).float()


def framing_camera(vertices, *, direction=(1.2, -1.0, 1.4), fov_deg: float = 40.0, size=(384, 512), up=(1.0, 0.0, 0.0)):
    """A perspective camera looking at the centre of ``vertices`` ``(N, 3)`` from ``direction`` times their size.

    ``direction`` is in units of the largest side of the vertices' bounding box (m), from its centre;
    ``up`` appears upwards in the image (default axis D).
    """
    from ..mesh.raster import Camera

    v = torch.as_tensor(vertices, dtype=torch.float64)
    lo, hi = v.min(0).values, v.max(0).values
    centre, extent = (hi + lo) / 2, float((hi - lo).max())
    eye = centre + torch.tensor(direction, dtype=torch.float64) * extent
    return Camera(eye=tuple(eye.tolist()), target=tuple(centre.tolist()), fov_deg=fov_deg, size=size, up=up)


def render_textured(
    surfaces,
    texture,
    camera,
    *,
    light=None,
    ambient: float = 0.35,
    per_pixel: bool = True,
    background=(1.0, 1.0, 1.0),
    specular: float = 0.0,
    device=None,
) -> dict:
    """Rasterise surfaces (deformed vertices) coloured by the solid texture at material coordinates.

    Args:
        surfaces: a list of surfaces with ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)`` and
            ``rest`` ``(V, 3)`` (for instance one per side of a cut), and optionally ``normals``
            ``(V, 3)`` (smooth shading; surfaces without them are shaded flat).
        texture: the :class:`~torchdeform.texture.synthesis.SolidTexture`.
        camera: a :class:`~torchdeform.mesh.raster.Camera`.
        light: direction towards the light (default: from the camera).
        ambient: ambient share of the Lambert shading.
        per_pixel: look the texture up at every pixel's interpolated rest coordinates (True) or
            interpolate the vertex colours (False, Chen & He's node colouring alone).
        background: RGB where nothing is hit.
        specular: the weight of a white highlight (:func:`~torchdeform.mesh.raster.rasterize`; about
            0.3 gives wet tissue its sheen).
        device: where to rasterise and look the texture up (default: where the surfaces' tensors
            are, the CPU for numpy arrays).

    Returns:
        the rasteriser's dict: ``image`` ``(H, W, 3)``, ``depth``, ``face``, ``bary``, on that device.
    """
    from ..mesh.raster import rasterize

    verts, faces, rest, normals, base = [], [], [], [], 0
    smooth = all(getattr(s, "normals", None) is not None for s in surfaces)
    for s in surfaces:
        v = torch.as_tensor(s.vertices, dtype=torch.float64, device=device)
        verts.append(v)
        faces.append(torch.as_tensor(s.faces, dtype=torch.int64, device=v.device) + base)
        rest.append(torch.as_tensor(s.rest, dtype=torch.float64, device=v.device))
        if smooth:
            normals.append(torch.as_tensor(s.normals, dtype=torch.float64, device=v.device))
        base += len(v)
    v, f, r = torch.cat(verts), torch.cat(faces), torch.cat(rest)
    shading = {"normals": torch.cat(normals) if smooth else None, "specular": specular}
    if per_pixel:
        colours = lambda X: texture.at_material(X).to(X.dtype)
        return rasterize(
            v,
            f,
            camera,
            colors=colours,
            texcoords=r,
            light=light,
            ambient=ambient,
            background=background,
            two_sided=True,
            **shading,
        )
    return rasterize(
        v,
        f,
        camera,
        colors=texture.at_material(r).to(v.dtype),
        light=light,
        ambient=ambient,
        background=background,
        two_sided=True,
        **shading,
    )


#: The longest side of a default body texture (voxels): its seams blend in a few seconds.
MAX_SIDE = 160


def body_texture(grid, *, exemplar="liver:64", block=None, seed: int = 0, voxel=None):
    """A :class:`~torchdeform.texture.SolidTexture` covering the grid's rest box (and two spacings around it).

    The box of ``textured.png`` of a scene's ``[texture]`` section and of the animation's surface panel.

    Args:
        grid: the :class:`~torchdeform.sim.grid.Grid`.
        exemplar: ``(3, E, E, E)`` colours, or ``"liver"`` / ``"liver:N"`` (procedural) or a file.
        block: block size in voxels (default: half the exemplar's smallest side).
        seed: of the block choice (and of a procedural exemplar).
        voxel: texture voxel size (m; default a quarter of the smallest spacing, coarser where the
            texture would otherwise be longer than :data:`MAX_SIDE` voxels).

    Returns:
        the texture.
    """
    if isinstance(exemplar, str):
        from .exemplar import exemplar_from

        exemplar = exemplar_from(exemplar, seed=seed)
    block = block or min(exemplar.shape[1:]) // 2
    X = grid.rest_positions(dtype=torch.float64)[0].reshape(3, -1)
    lo, hi = X.min(1).values, X.max(1).values
    pad = 2 * max(grid.spacing)  # the surfaces reach half a cell out
    voxel = voxel or max(min(grid.spacing) / 4, float((hi - lo).max() + 2 * pad) / MAX_SIDE)
    extent = [int((h - l + 2 * pad) / voxel) + 2 for l, h in zip(lo.tolist(), hi.tolist())]
    from .synthesis import SolidTexture

    return SolidTexture(exemplar, block=block, extent=extent, seed=seed, voxel=voxel, origin=tuple((lo - pad).tolist()))
