"""Colours on surfaces at material coordinates (texture.mapping) against direct texture lookups."""

from __future__ import annotations

import numpy as np
import torch

from torchdeform.mesh import Camera
from torchdeform.texture import SolidTexture, liver_exemplar, render_textured, vertex_colours
from torchdeform.topology.surfaces import CutSurface


def _square(shift=(0.0, 0.0, 0.0)):
    """A square at d = 4.2 mm (off the texture's block faces) facing +d (the camera), rest coordinates = its rest place."""
    v = np.array([[0.0042, 0.0, 0.0], [0.0042, 0.01, 0.0], [0.0042, 0.01, 0.01], [0.0042, 0.0, 0.01]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return CutSurface(0, v + np.array(shift), f, v.copy())


def test_vertex_colours_are_texture_lookups_at_rest_coordinates():
    tex = SolidTexture(liver_exemplar(size=16, seed=1), block=8, extent=(24, 24, 24), voxel=0.0005)
    s = _square()
    assert torch.allclose(vertex_colours(tex, s), tex.at_material(torch.from_numpy(s.rest)).float())


def test_every_pixel_shows_the_texture_at_its_material_point_however_the_surface_moved(device):
    tex = SolidTexture(liver_exemplar(size=16, seed=1).double(), block=8, extent=(24, 24, 24), voxel=0.0005)
    moved = _square(shift=(0.0, 0.003, -0.002))  # a translated surface, same material
    cam = Camera(
        eye=(0.05, 0.008, 0.003), target=(0.0, 0.008, 0.003), up=(0.0, 0.0, 1.0), ortho_height=0.008, size=(32, 32)
    )
    out = render_textured(
        [moved], tex, cam, light=(1.0, 0.0, 0.0), ambient=0.0, background=(0.0, 0.0, 0.0), device=device
    )
    assert out["image"].device == device
    out = {k: v.cpu() for k, v in out.items()}
    hit = out["face"] >= 0
    assert int(hit.sum()) > 500
    # the world point under each pixel (on the plane d = 4.2 mm), moved back to its material point
    rows, cols = torch.nonzero(hit, as_tuple=True)
    H, W = 32, 32
    # orthographic, looking along -d with up = +w: image right is +h; pixel centres
    y = (cols.double() + 0.5 - W / 2) * (0.008 / H)
    z = (H / 2 - rows.double() - 0.5) * (0.008 / H)
    world = torch.stack([torch.full_like(y, 0.0042), 0.008 + y, 0.003 + z], 1)
    material = world - torch.tensor([0.0, 0.003, -0.002], dtype=torch.float64)
    expect = tex.at_material(material)  # light along the normal: shade 1
    assert torch.allclose(out["image"][rows, cols].double(), expect, atol=1e-6)
