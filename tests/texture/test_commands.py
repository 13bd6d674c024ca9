"""`torchdeform texture`: a closed mesh coloured and written; bad input is one line and exit 2."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from torchdeform import cli


@pytest.fixture
def sphere(tmp_path):
    path = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=10.0).export(path)  # millimetres
    return path


def test_texture_command_writes_vertex_colours(tmp_path, sphere, capsys):
    out = tmp_path / "sphere.ply"
    rc = cli.main(
        argv=[
            "texture",
            "liver:32",
            "--mesh",
            str(sphere),
            "--scale",
            "0.001",
            "--out",
            str(out),
            "--voxel",
            "0.0005",  # 40^3 texture voxels (default: the largest extent / 128, 128^3)
            "--block",
            "16",
            "--image",
            str(tmp_path / "view.png"),
            "--seams",
            "3d",
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    assert "textured" in printed and "seams (3d Poisson" in printed
    mesh = trimesh.load(out)
    assert len(mesh.vertices) == 162 and mesh.is_watertight
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    assert colours.std(0).min() > 2 and colours[:, 0].mean() > colours[:, 1].mean()  # textured, reddish
    assert (tmp_path / "view.png").stat().st_size > 1000


BAD = {
    "not rgb": ("gray.npy", "exemplar", "an RGB volume"),
    "slices of different sizes": ("slices", "exemplar", "like the first"),
    "block larger than the exemplar": ("liver:16", "texture.block", "block size"),
    "open mesh": ("liver:16", "--mesh", "closed"),
    "unknown output": ("liver:16", "--out", ".ply, .glb or .obj"),
    "unknown seam method": ("liver:16", "--seams", "none or 3d or slices"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_line_and_exit_2(case, tmp_path, sphere, capsys):
    import matplotlib.image as mpimg

    ex, key, text = BAD[case]
    np.save(tmp_path / "gray.npy", np.zeros((8, 8, 8), dtype=np.uint8))
    (tmp_path / "slices").mkdir()
    mpimg.imsave(tmp_path / "slices" / "a.png", np.zeros((8, 8, 3), dtype=np.uint8))
    mpimg.imsave(tmp_path / "slices" / "b.png", np.zeros((8, 9, 3), dtype=np.uint8))
    mesh = sphere
    if case == "open mesh":
        m = trimesh.creation.icosphere(subdivisions=1)
        m.update_faces(np.arange(len(m.faces)) > 0)
        mesh = tmp_path / "open.stl"
        m.export(mesh)
    ex = str(tmp_path / ex) if not ex.startswith("liver") else ex
    out = tmp_path / ("x.txt" if case == "unknown output" else "x.ply")
    args = (
        ["texture", ex, "--mesh", str(mesh), "--out", str(out)]
        + (["--block", "64"] if "block" in case else [])
        + (["--seams", "poisson"] if "seam" in case else [])
    )
    assert cli.main(argv=args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and key in err[0] and text in err[0], err
