"""`torchdeform bench frame`: the quick JSON run, and the per-frame surface against the slow reference."""

import json

import numpy as np
import pytest
import torch

import torchdeform as td
from torchdeform import cli
from torchdeform.bench.frame import PUNAK, FrameSurface, parse_sizes
from torchdeform.errors import ConfigError
from torchdeform.sim.packed import PackedModel
from torchdeform.topology import cut_surfaces

pytestmark = pytest.mark.slow  # a bench smoke run


def test_bench_frame_quick_json(capsys, tmp_path):
    rc = cli.main(argv=["bench", "frame", "--quick", "--json", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["bench"] == "frame"
    assert doc["target_ratio"] == 2 and isinstance(doc["met"], bool)
    rows = doc["rows"]
    assert [r["grid"] for r in rows] == ["16^3", "32^3"]
    punak = {"16^3": 90.0, "32^3": 28.0}
    for r in rows:
        assert {
            "grid",
            "fps",
            "punak_fps",
            "ratio",
            "step_ms",
            "surface_ms",
            "threads",
            "engine",
            "vertices",
            "faces",
            "compile_s",
        } <= set(r)
        assert r["engine"] == "eager" and r["compile_s"] is None  # --quick: no torch.compile
        assert r["step_ms"] > 0 and r["surface_ms"] > 0 and r["threads"] >= 1
        assert r["fps"] == pytest.approx(1000.0 / (r["step_ms"] + r["surface_ms"]), rel=1e-9)
        assert r["punak_fps"] == punak[r["grid"]]
        assert r["ratio"] == pytest.approx(r["fps"] / r["punak_fps"], rel=1e-9)
        assert r["faces"] == 2 * r["vertices"] - 4  # one closed genus-0 surface
        assert "volume_ms" not in r
    assert doc["met"] == all(r["ratio"] >= 2 for r in rows)
    assert (tmp_path / "frame.csv").is_file() and (tmp_path / "frame.png").is_file()


def test_punak_table_and_sizes():
    assert PUNAK == {
        (16, 16, 16): 90.0,
        (32, 32, 32): 28.0,
        (40, 60, 20): 21.0,
        (64, 64, 64): 6.1,
        (100, 100, 100): 2.0,
    }
    assert parse_sizes("16, 40x60x20") == [(16, 16, 16), (40, 60, 20)]
    with pytest.raises(ConfigError):
        parse_sizes("16,4x4")


def _brute_normals(v, faces):
    n = np.zeros_like(v)
    for a, b, c in faces:
        fn = np.cross(v[b] - v[a], v[c] - v[a])  # twice the area times the unit normal
        for i in (a, b, c):
            n[i] += fn
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _deformed(grid, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = grid.rest_positions(dtype=torch.float64)
    A = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    x = torch.einsum("ij,bjdhw->bidhw", A, X) + 0.002 * torch.randn(X.shape, generator=g, dtype=torch.float64)
    return X, x


@pytest.mark.parametrize("two_pieces", [False, True])
def test_frame_surface_matches_cut_surfaces(two_pieces):
    grid = td.Grid((5, 6, 7), spacing=(0.01, 0.012, 0.009), topology=26)
    _X, x = _deformed(grid)
    labels = np.zeros(grid.shape, np.int64)
    if two_pieces:
        labels[3:] = 1  # two sides of a cut between layers 2 and 3
    ref = cut_surfaces(grid, x, torch.as_tensor(labels))
    ref_v = np.concatenate([s.vertices for s in ref])
    ref_f = np.concatenate([s.faces + sum(len(p.vertices) for p in ref[:i]) for i, s in enumerate(ref)])
    # grid layout
    surf = FrameSurface(grid, labels=labels, dtype=torch.float64)
    v = surf.vertices(x)
    assert np.abs(v.numpy() - ref_v).max() < 1e-10
    assert np.array_equal(surf.faces.numpy(), ref_f)
    # packed layout (the bench's): read straight from the packed state
    model = td.Model(grid, stiffness=10.0, mass=1e-3, dtype=torch.float64)
    pm = PackedModel(model)
    psurf = FrameSurface(grid, labels=labels, packed=pm, dtype=torch.float64)
    vp = psurf.vertices(pm.pack(x))
    assert np.abs(vp.numpy() - ref_v).max() < 1e-10
    # normals: both formulations against the brute force
    want = _brute_normals(ref_v, ref_f)
    for got in (surf.normals(v), surf._scatter_normals(v), surf._gather_normals(v)):
        assert np.abs(got.numpy() - want).max() < 1e-10


def test_frame_surface_rest_and_float32():
    grid = td.Grid((4, 4, 4), spacing=0.01, topology=26)
    surf = FrameSurface(grid)
    X = grid.rest_positions(dtype=torch.float32)
    v, n = surf(X)
    assert torch.allclose(v, surf.rest)
    assert torch.allclose(n.norm(dim=1), torch.ones(len(n)), atol=1e-6)
    # outward: normals point away from the body's centre
    centre = X.reshape(3, -1).mean(1)
    assert bool(((v - centre) * n).sum(1).gt(0).all())


def test_bench_frame_volume_row(capsys):
    rc = cli.main(
        argv=[
            "bench",
            "frame",
            "--quick",
            "--json",
            "--sizes",
            "16",
            "--volume",
            "--volume-size",
            "16",
            "--repeats",
            "1",
            "--frames",
            "1",
        ]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    (r,) = doc["rows"]
    assert r["volume_ms"] > 0 and r["image"] == "16^2"
    assert r["fps"] == pytest.approx(1000.0 / (r["step_ms"] + r["surface_ms"] + r["volume_ms"]), rel=1e-9)
    assert r["surface_fps"] == pytest.approx(1000.0 / (r["step_ms"] + r["surface_ms"]), rel=1e-9)
    assert doc["met"] == (r["surface_ratio"] >= 2)  # the volume is not part of the target
