"""`torchdeform bench texture`: a smoke run (rows, JSON fields, files) and its meshes against trimesh."""

import json

import pytest
import trimesh

from torchdeform import cli
from torchdeform.bench.texture import MODELS, hull_mesh

pytestmark = pytest.mark.slow  # a bench smoke run


def test_hull_meshes_are_closed_with_chen_and_he_counts():
    for name, _, faces, _, _ in MODELS[:3]:
        v, f = hull_mesh((faces + 4) // 2, seed=ord(name))
        mesh = trimesh.Trimesh(v, f, process=False)
        assert len(f) == faces and mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_bench_texture_json(capsys, tmp_path):
    assert (
        cli.main(
            argv=[
                "bench",
                "texture",
                "--quick",
                "--json",
                "--repeats",
                "1",
                "--out",
                str(tmp_path),
                "--seam-blocks",
                "2,1,1",
            ]
        )
        == 0
    )
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "texture" and {"machine", "met", "target_speedup"} <= set(doc)
    rows = {r["model"]: r for r in doc["rows"]}
    assert set(rows) == {"A", "B", "C", "D", "cut face"}
    for name, _vertices, faces, gpu_nodes, _gpu_triangles in MODELS:
        r = rows[name]
        assert r["faces"] == faces and r["vertices"] == (faces + 4) // 2
        assert r["samples"] > r["faces"] and r["node_ms"] > 0 and r["triangle_ms"] > 0
        assert abs(r["speedup_nodes"] - gpu_nodes * 1e3 / r["node_ms"]) < 1e-9
    assert rows["cut face"]["samples"] > 0 and rows["cut face"]["triangle_ms"] > 0
    assert (tmp_path / "texture.csv").is_file() and (tmp_path / "texture.png").is_file()
    seams = {r["method"]: r for r in doc["seams"]}
    assert set(seams) == {"tiled", "3-D Poisson", "per-slice 2-D (D)", "exemplar (floor)"}
    assert seams["tiled"]["box"] == [128, 64, 64]
    for r in seams.values():
        assert abs(r["reduction"] - seams["tiled"]["seam_jump"] / r["seam_jump"]) < 1e-9
    assert seams["3-D Poisson"]["seam_jump"] < seams["tiled"]["seam_jump"]
    assert (tmp_path / "texture_seams.png").is_file()


def test_bad_seam_blocks_is_one_line_and_exit_2(capsys):
    assert cli.main(argv=["bench", "texture", "--seam-blocks", "2,x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--seam-blocks" in err[0], err
