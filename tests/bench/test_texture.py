"""`torchdeform bench texture`: a smoke run (rows, JSON fields, files) and its meshes against trimesh."""
import json

import trimesh

from torchdeform import cli
from torchdeform.bench.texture import MODELS, hull_mesh


def test_hull_meshes_are_closed_with_chen_and_he_counts():
    for name, _, faces, _, _ in MODELS[:3]:
        v, f = hull_mesh((faces + 4) // 2, seed=ord(name))
        mesh = trimesh.Trimesh(v, f, process=False)
        assert len(f) == faces and mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_bench_texture_json(capsys, tmp_path):
    assert cli.main(["bench", "texture", "--quick", "--json", "--repeats", "1", "--out", str(tmp_path)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "texture" and {"machine", "met", "target_speedup"} <= set(doc)
    rows = {r["model"]: r for r in doc["rows"]}
    assert set(rows) == {"A", "B", "C", "D", "cut face"}
    for name, vertices, faces, gpu_nodes, gpu_triangles in MODELS:
        r = rows[name]
        assert r["faces"] == faces and r["vertices"] == (faces + 4) // 2
        assert r["samples"] > r["faces"] and r["node_ms"] > 0 and r["triangle_ms"] > 0
        assert abs(r["speedup_nodes"] - gpu_nodes * 1e3 / r["node_ms"]) < 1e-9
    assert rows["cut face"]["samples"] > 0 and rows["cut face"]["triangle_ms"] > 0
    assert (tmp_path / "texture.csv").is_file() and (tmp_path / "texture.png").is_file()
