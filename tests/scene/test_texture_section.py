"""The [texture] section: textured.png of the final surfaces; its block table; bad input is exit 2."""

from __future__ import annotations

import math

import pytest

from tests.scene.test_topology_sections import BLADE, body, run, run_part, write
from torchdeform import cli

TEXTURE = """
[texture]
exemplar = "liver:16"
block = 8
voxel = 0.0025
seams = "3d"
"""


def test_texture_section_writes_a_textured_image(tmp_path):
    summary, out = run(tmp_path, body() + BLADE + TEXTURE + run_part())
    tex = summary["texture"]
    # the box: rest extent 3, 2, 3 cm plus two spacings on each side, in 2.5 mm voxels, blocks of 8
    extent = [int((e + 4 * 0.01) / 0.0025) + 2 for e in (0.03, 0.02, 0.03)]
    assert tex["blocks"] == [math.ceil(e / 8) for e in extent] and tex["pieces"] == 2
    assert tex["seams"]["method"] == "3d" and tex["seams"]["seam_after"] < tex["seams"]["seam_before"]
    from matplotlib.image import imread

    img = imread(out / "textured.png")[..., :3]
    body_px = (img < 0.98).any(2)
    assert 0.05 < body_px.mean() < 0.9  # the body is drawn
    assert img[body_px][:, 0].mean() > img[body_px][:, 1].mean()  # liver red


@pytest.mark.parametrize(
    "text, key",
    [
        ('exemplar = "liver:16"\nblock = 32', "texture.block"),
        ('exemplar = "missing.npy"', "exemplar"),
        ('exemplar = "liver:16"\nvoxel = -1.0', "texture.voxel"),
        ('exemplar = "liver:16"\nseams = "poisson"', "texture.seams"),
    ],
)
def test_bad_texture_sections(tmp_path, capsys, text, key):
    path = write(tmp_path, body() + f"\n[texture]\n{text}\n" + run_part(steps=2))
    assert cli.main(argv=["run", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0] and "scene.toml" in err[0], err
