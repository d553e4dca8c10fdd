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

The service keeps one generation back (``keep_previous``; docs/reliability.md, "Map snapshots")::

    terrain.snapshot                 the newest snapshot
    terrain.snapshot.prev            the one before it (a hard link to the old file, made before
                                     the new one is renamed in, so the newest name never vanishes)
    terrain.snapshot.bad-<unix s>    a file the loader refused, moved aside (the 3 newest are kept)
    .terrain.snapshot.<random>.tmp   a write in progress; one left by a crash is removed at load

:func:`load_latest` tries the newest, then the previous one, and says which it took and why it
refused the others.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import struct
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from companion.config import TerrainConfig
from companion.method.terrain.codec import decode_tile, encode_tile

MAGIC = b"CTSN"
VERSION = 1
HEADER = struct.Struct("<4sHHdII")  # 24 bytes
RECORD = struct.Struct("<I")
DIGEST = 32
PREVIOUS_SUFFIX = ".prev"
BAD_SUFFIX = ".bad-"
KEEP_BAD = 3

log = logging.getLogger(__name__)


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


def previous_path(path: str | Path) -> Path:
    """Where the generation before ``path`` is kept (``<name>.prev``)."""
    path = Path(path)
    return path.with_name(path.name + PREVIOUS_SUFFIX)


def _temporaries(path: Path) -> list[Path]:
    """Temporaries of writes to ``path`` (its own and its ``.prev`` link's) left in its directory."""
    try:
        return sorted(path.parent.glob(f".{path.name}.*.tmp"))
    except OSError:
        return []


def write_snapshot(grid, path: str | Path, *, keep_previous: bool = False) -> None:
    """Atomically replace ``path`` with a snapshot of ``grid`` (see :func:`write_snapshot_bytes`)."""
    write_snapshot_bytes(snapshot_bytes(grid), path, keep_previous=keep_previous)


def write_snapshot_bytes(data: bytes, path: str | Path, *, keep_previous: bool = False) -> None:
    """Atomically replace ``path`` with ``data`` (from :func:`snapshot_bytes`).

    With ``keep_previous`` the file ``path`` held until now stays available as
    :func:`previous_path` (a hard link made once the new data is safely on disk and before the
    rename, so ``path`` itself is never missing; a file system without hard links gets a rename,
    which leaves ``path`` missing for an instant, and the loader then takes ``.prev``).
    Raises OSError (full or read-only disk, missing directory, ...); ``path`` is then unchanged.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if keep_previous and path.exists():
            _keep_previous(path)
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


def _keep_previous(path: Path) -> None:
    prev = previous_path(path)
    link_tmp = path.with_name(f".{path.name}.prev.tmp")
    try:
        link_tmp.unlink(missing_ok=True)
        os.link(path, link_tmp)
        os.replace(link_tmp, prev)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EIO):
            raise
        os.replace(path, prev)  # no hard links here (EPERM, EXDEV...): rename instead


def read_snapshot(path: str | Path, cfg: TerrainConfig | None = None):
    """Build a new TerrainGrid from the snapshot at ``path``.

    Geometry (cell size, T) comes from the file; fusion parameters from ``cfg`` (defaults if
    None). Raises SnapshotError on a missing, truncated, corrupted, foreign, newer-version or
    geometry-mismatched file.
    """
    from companion.method.terrain.grid import TerrainGrid

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


# --------------------------------------------------------------------------------------------
# Loading the newest good generation
# --------------------------------------------------------------------------------------------


def count_known_cells(grid) -> int:
    """Cells holding evidence (the map's size as the status reports it)."""
    return int(round(grid.observed_area_m2() / grid.cell_size_m**2))


@dataclass(frozen=True, slots=True)
class LoadedSnapshot:
    """What :func:`load_latest` found: the grid (empty when nothing loaded) and how it got it.

    ``path`` is the file loaded (None: none), ``age_s`` its age from its modification time
    (wall clock), ``refused`` one line per file that was refused (moved aside as ``.bad-<t>``),
    ``removed_temporaries`` the leftovers of interrupted writes that were deleted.
    """

    grid: object
    path: Path | None
    tiles: int
    cells: int
    age_s: float | None
    refused: tuple[str, ...]
    removed_temporaries: int

    def as_dict(self) -> dict:
        return {"path": None if self.path is None else str(self.path), "tiles": self.tiles, "cells": self.cells,
                "age_s": None if self.age_s is None else round(self.age_s, 1), "refused": list(self.refused),
                "removed_temporaries": self.removed_temporaries}


def _move_aside(path: Path) -> Path:
    """Rename a refused file to ``<name>.bad-<unix s>`` (keeping the newest KEEP_BAD of them)."""
    base = path.name.removesuffix(PREVIOUS_SUFFIX)
    bad = path.with_name(f"{base}{BAD_SUFFIX}{int(time.time())}")
    n = 0
    while bad.exists():
        n += 1
        bad = path.with_name(f"{base}{BAD_SUFFIX}{int(time.time())}.{n}")
    os.replace(path, bad)
    olds = sorted(path.parent.glob(f"{base}{BAD_SUFFIX}*"), key=lambda p: p.stat().st_mtime_ns)
    for old in olds[:-KEEP_BAD]:
        old.unlink(missing_ok=True)
    return bad


def load_latest(path: str | Path, cfg: TerrainConfig | None = None, *, clean: bool = True) -> LoadedSnapshot:
    """The newest good snapshot among ``path`` and its ``.prev`` (an empty grid when neither loads).

    A file that exists but is refused (truncated, corrupted, foreign, geometry differs from
    ``cfg``) is moved aside, so the next write does not push a bad file into ``.prev`` over a
    good one, and the refusal is logged and returned. With ``clean`` the temporaries of writes a
    crash interrupted are removed first (call it only when no writer runs: at start-up).
    """
    from companion.method.terrain.grid import TerrainGrid

    path = Path(path)
    removed = 0
    if clean:
        for tmp in _temporaries(path):
            try:
                tmp.unlink()
                removed += 1
            except OSError:
                pass
        if removed:
            log.warning("map: removed %d temporary file(s) of an interrupted snapshot write next to %s", removed, path)
    refused: list[str] = []
    for candidate in (path, previous_path(path)):
        try:
            if not candidate.is_file():
                continue
        except OSError:
            continue
        try:
            grid = read_snapshot(candidate, cfg)
            age = max(0.0, time.time() - candidate.stat().st_mtime)
        except (SnapshotError, OSError) as exc:
            if isinstance(exc, OSError) or isinstance(exc.__cause__, OSError):
                where = "left in place: the file may be good, reading it failed"
            else:
                try:
                    where = f"moved aside as {_move_aside(candidate).name}"
                except OSError as move_exc:
                    where = f"left in place ({move_exc.strerror or move_exc})"
            refused.append(f"{exc} ({where})")
            log.error("map: refused snapshot %s", refused[-1])
            continue
        return LoadedSnapshot(grid, candidate, len(grid), count_known_cells(grid), age, tuple(refused), removed)
    grid = TerrainGrid.from_config(cfg) if cfg is not None else TerrainGrid()
    return LoadedSnapshot(grid, None, 0, 0, None, tuple(refused), removed)
