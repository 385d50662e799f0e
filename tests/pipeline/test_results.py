"""Results store: meshes and reports beside the take, atomic writes, PLY/GLB export."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from pipeline.results import ResultsStore, atomic_write_bytes


def test_meshes_round_trip_exactly_and_list_frames(tmp_path):
    store = ResultsStore(tmp_path / "walk.results")
    assert store.frames() == []
    a = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    b = trimesh.creation.box(extents=(10, 20, 30))
    store.write_mesh(123, a)
    store.write_mesh(7, (b.vertices, b.faces))
    assert store.frames() == [7, 123]
    assert store.mesh_path(123).name == "frame_000123.ply"
    got = store.read_mesh(123)
    assert np.array_equal(got.vertices, a.vertices) and np.array_equal(got.faces, a.faces)
    assert got.is_watertight
    store.write_mesh(123, b)  # replaces
    assert len(store.read_mesh(123).faces) == len(b.faces)
    with pytest.raises(KeyError):
        store.read_mesh(5)


def test_export_ply_and_glb_load_back(tmp_path):
    store = ResultsStore(tmp_path / "r")
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=3.0)
    store.write_mesh(0, mesh)
    for fmt in ("ply", "glb"):
        p = store.export(0, fmt)
        assert p.suffix == f".{fmt}" and p.is_file()
        back = trimesh.load(str(p), force="mesh")
        assert len(back.faces) == len(mesh.faces)
        np.testing.assert_allclose(np.sort(back.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-5)
    p = store.export(0, "ply", path=tmp_path / "elsewhere" / "x.ply")
    assert p == tmp_path / "elsewhere" / "x.ply" and p.is_file()


def test_atomic_write_leaves_no_half_file(tmp_path, monkeypatch):
    target = tmp_path / "d" / "f.bin"
    atomic_write_bytes(target, b"old contents")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # the process dies between writing and renaming

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b"new")
    monkeypatch.undo()
    assert target.read_bytes() == b"old contents"
    assert sorted(p.name for p in target.parent.iterdir()) == ["f.bin"]  # no temporary left


def test_invalid_input(tmp_path):
    with pytest.raises(ValueError, match="path"):
        ResultsStore("")
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        ResultsStore(f)
    store = ResultsStore(tmp_path / "r")
    mesh = trimesh.creation.box()
    with pytest.raises(ValueError, match="frame"):
        store.write_mesh(-1, mesh)
    with pytest.raises(ValueError, match="frame"):
        store.write_mesh(1.5, mesh)
    with pytest.raises(ValueError, match="mesh"):
        store.write_mesh(0, "mesh")
    with pytest.raises(ValueError, match="faces"):
        store.write_mesh(0, (mesh.vertices, mesh.faces + 100))
    with pytest.raises(ValueError, match="vertices"):
        store.write_mesh(0, (np.full((3, 3), np.nan), [[0, 1, 2]]))
    store.write_mesh(0, mesh)
    with pytest.raises(ValueError, match="fmt"):
        store.export(0, "obj")
