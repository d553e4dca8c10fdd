"""Map snapshots: the whole grid in one checksummed, versioned file, written atomically.

Layout (little-endian; docs/terrain.md, "Snapshot format")::

    offset size type     field
    0      4    bytes    magic b"CTSN"
    4      2    uint16   snapshot version (1)
    6      2    uint16   reserved, 0
    8      8    float64  cell size (m)
    16     4    uint32   T, tile edge in cells
    20     4    uint32   number of tiles K
    24     ...  K records: uint32 length L, then L bytes of an encoded tile (codec.py, with the
                disagreement layer so fusion resumes exactly)
    end-32 32   bytes    SHA-256 of every byte before it

The write goes to a temporary file in the same directory, is flushed and fsync'ed, then renamed
over the target (atomic on POSIX) and the directory fsync'ed: a crash leaves either the old
snapshot or the new one, never a mixture. The reader checks the digest before parsing anything
and builds a fresh grid, so a bad file raises and leaves nothing half-loaded.
"""

from __future__ import annotations

import hashlib
import os
import struct
import tempfile
from pathlib import Path

from companion.config import TerrainConfig
from companion.terrain.codec import decode_tile, encode_tile

MAGIC = b"CTSN"
VERSION = 1
HEADER = struct.Struct("<4sHHdII")  # 24 bytes
RECORD = struct.Struct("<I")
DIGEST = 32


class SnapshotError(ValueError):
    """A snapshot file that cannot be loaded; the message says why."""


def snapshot_bytes(grid) -> bytes:
    """The snapshot of ``grid`` as bytes (tiles in key order, so equal maps give equal bytes)."""
    parts = [HEADER.pack(MAGIC, VERSION, 0, grid.cell_size_m, grid.tile_cells, len(grid))]
    for tile in grid.tiles(with_disagreement=True):
        blob = encode_tile(tile, with_disagreement=True)
        parts.append(RECORD.pack(len(blob)))
        parts.append(blob)
    body = b"".join(parts)
    return body + hashlib.sha256(body).digest()


def write_snapshot(grid, path: str | Path) -> None:
    """Atomically replace ``path`` with a snapshot of ``grid``."""
    path = Path(path)
    data = snapshot_bytes(grid)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def read_snapshot(path: str | Path, cfg: TerrainConfig | None = None):
    """Build a new TerrainGrid from the snapshot at ``path``.

    Geometry (cell size, T) comes from the file; fusion parameters from ``cfg`` (defaults if
    None). Raises SnapshotError on a missing, truncated, corrupted, foreign, newer-version or
    geometry-mismatched file.
    """
    from companion.terrain.grid import TerrainGrid

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SnapshotError(f"{path}: cannot read terrain snapshot: {exc.strerror or exc}") from exc
    if len(data) < HEADER.size + DIGEST:
        raise SnapshotError(f"{path}: terrain snapshot truncated ({len(data)} bytes)")
    magic, version, _reserved, cell, t, n_tiles = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise SnapshotError(f"{path}: not a terrain snapshot (magic {magic!r})")
    if version != VERSION:
        raise SnapshotError(f"{path}: terrain snapshot version {version}, this build reads {VERSION}")
    body, digest = data[:-DIGEST], data[-DIGEST:]
    if hashlib.sha256(body).digest() != digest:
        raise SnapshotError(f"{path}: terrain snapshot checksum mismatch (truncated or corrupted)")
    if cfg is not None and (cfg.cell_size_m != cell or cfg.tile_cells != t):
        raise SnapshotError(
            f"{path}: snapshot geometry (cell {cell} m, {t} cells a tile) differs from the configuration "
            f"(terrain.cell_size_m = {cfg.cell_size_m}, terrain.tile_cells = {cfg.tile_cells})"
        )
    try:
        grid = TerrainGrid.from_config(cfg) if cfg is not None else TerrainGrid(cell, t)
        offset = HEADER.size
        seen = set()
        for i in range(n_tiles):
            if offset + RECORD.size > len(body):
                raise ValueError(f"record {i} of {n_tiles} missing")
            (length,) = RECORD.unpack_from(body, offset)
            offset += RECORD.size
            if offset + length > len(body):
                raise ValueError(f"record {i} runs past the end")
            tile = decode_tile(body[offset : offset + length])
            offset += length
            if tile.key in seen:
                raise ValueError(f"tile {tile.key} appears twice")
            seen.add(tile.key)
            grid.put_tile(tile)
        if offset != len(body):
            raise ValueError(f"{len(body) - offset} bytes after the last tile")
    except ValueError as exc:
        raise SnapshotError(f"{path}: bad terrain snapshot: {exc}") from exc
    # Every loaded tile stays dirty: the publisher announces the restored map once.
    return grid
