"""Fixtures shared by the scene tests."""

import pytest
import trimesh


@pytest.fixture
def bad_dir(tmp_path):
    """A folder with ``open.stl``: a box mesh with two faces missing (not closed)."""
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    trimesh.Trimesh(box.vertices, box.faces[:-2]).export(tmp_path / "open.stl")
    return tmp_path
