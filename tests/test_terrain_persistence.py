"""Map snapshots: atomic, checksummed, versioned; a bad file raises and never half-loads."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest

from companion.config import TerrainConfig
from companion.method.messages import TerrainPoints
from companion.method.terrain import SnapshotError, TerrainGrid
from companion.method.terrain.grid import grids_equal


def batch(rng, n=400, spread=60.0, height=0.0):
    pos = np.c_[rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n), -rng.normal(height, 0.5, n)]
    return TerrainPoints(0.0, pos, np.tile(np.diag([0.2, 0.2, 0.25]), (n, 1, 1)))


@pytest.fixture
def grid():
    rng = np.random.default_rng(4)
    g = TerrainGrid()
    for _ in range(3):
        g.insert(batch(rng))
    g.insert(batch(rng, 50, 10.0, 12.0))  # disagreement builds up in some cells
    return g


def test_snapshot_round_trip_resumes_fusion_exactly(grid, tmp_path):
    path = tmp_path / "map.ctsn"
    grid.save_snapshot(path)
    loaded = TerrainGrid.load_snapshot(path)
    assert grids_equal(grid, loaded)
    assert loaded.observed_area_m2() == grid.observed_area_m2()
    assert sorted(loaded.pop_dirty()) == grid.keys()  # restored tiles are announced once
    more = batch(np.random.default_rng(5), 200, 10.0, 12.0)
    assert grid.insert(more) == loaded.insert(more)
    assert grids_equal(grid, loaded)
    assert not [p for p in tmp_path.iterdir() if p.name != "map.ctsn"]  # no temporary left


def test_empty_map_round_trip(tmp_path):
    TerrainGrid(cell_size_m=0.5, tile_cells=16).save_snapshot(tmp_path / "e")
    g = TerrainGrid.load_snapshot(tmp_path / "e")
    assert (g.cell_size_m, g.tile_cells, len(g)) == (0.5, 16, 0)


def test_truncated_or_corrupted_files_raise(grid, tmp_path):
    path = tmp_path / "map.ctsn"
    grid.save_snapshot(path)
    data = path.read_bytes()
    bad = tmp_path / "bad"
    for cut in (0, 10, 24, 100, len(data) // 2, len(data) - 1):
        bad.write_bytes(data[:cut])
        with pytest.raises(SnapshotError, match="truncated|checksum"):
            TerrainGrid.load_snapshot(bad)
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0x10
    bad.write_bytes(bytes(flipped))
    with pytest.raises(SnapshotError, match="checksum"):
        TerrainGrid.load_snapshot(bad)
    bad.write_bytes(b"JUNK" + data[4:])
    with pytest.raises(SnapshotError, match="not a terrain snapshot"):
        TerrainGrid.load_snapshot(bad)
    bad.write_bytes(data[:4] + struct.pack("<H", 9) + data[6:])
    with pytest.raises(SnapshotError, match="version 9"):
        TerrainGrid.load_snapshot(bad)
    with pytest.raises(SnapshotError, match="cannot read"):
        TerrainGrid.load_snapshot(tmp_path / "missing")


def test_geometry_must_match_the_configuration(grid, tmp_path):
    path = tmp_path / "map.ctsn"
    grid.save_snapshot(path)
    with pytest.raises(SnapshotError, match="terrain.cell_size_m"):
        TerrainGrid.load_snapshot(path, TerrainConfig(cell_size_m=0.5))
    g = TerrainGrid.load_snapshot(path, TerrainConfig(gate_sigma=5.0))
    assert g.gate_sigma == 5.0 and grids_equal(g, grid)


def test_failed_write_keeps_the_previous_snapshot(grid, tmp_path, monkeypatch):
    path = tmp_path / "map.ctsn"
    old = TerrainGrid()
    old.save_snapshot(path)
    before = path.read_bytes()

    def broken_fsync(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(OSError):
        grid.save_snapshot(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.ctsn"]
    assert len(TerrainGrid.load_snapshot(path)) == 0
