"""Versioned little-endian binary encoding of one terrain tile (docs/terrain.md, "Tile format").

The same bytes are the Zenoh payload of a tile and the record of a tile in a snapshot, so a
C or JavaScript subscriber needs nothing but the layout below::

    offset size type     field
    0      4    bytes    magic b"CTTL"
    4      2    uint16   format version: 1, or 2 when a flag is set
    6      2    uint16   layer mask: bit0 height f32, bit1 variance f32, bit2 count u32,
                         bit3 disagreement f32, bit4 pending height f32, bit5 ceiling f32,
                         bit6 evidence weight f32, bit7 floor f32 (bits 3-7: snapshots only);
                         bits 0-2 always set
    8      4    int32    tx
    12     4    int32    ty
    16     8    float64  cell size (m)
    24     2    uint16   T, tile edge in cells
    26     2    uint16   flags (version 2; 0 in version 1): bit0 the payload is deflated (zlib),
                         bit1 the payload is a delta, bit2 the payload starts with revisions
    28     4    uint32   CRC-32 (zlib/IEEE) of the payload as stored (deflated or not)
    32     ...  payload: the layers in mask-bit order, each T*T little-endian values,
                row-major [i north][j east]; with flag bit0, those bytes deflated (zlib)

With flag bit2 the (inflated) payload starts with ``uint32 revision``: the publisher's count of
this tile's publications. With bits 1 and 2 it is a delta on the tile of an earlier revision::

    uint32 revision, uint32 base revision, uint32 n,
    n x uint32 cell index (i * T + j, ascending),
    then per layer in mask-bit order n little-endian values: the changed cells' new values

Deflating is for the radio: a tile's unknown cells (NaN, +inf, 0) and its repeated values
compress about six times (docs/zenoh.md, "Bandwidth"); a delta sends only the cells that
changed since the revision before (docs/terrain.md, "Tile deltas"). A tile written without
either is version 1, byte for byte what readers of version 1 know.
"""

from __future__ import annotations

import random
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from companion.method.terrain.tile import Tile

MAGIC = b"CTTL"
VERSION = 1
VERSION_FLAGS = 2      # the flags field is in use
FLAG_DEFLATE = 1
FLAG_DELTA = 2         # the payload holds the changed cells only (needs FLAG_REVISION)
FLAG_REVISION = 4      # the payload starts with the tile's revision
FLAGS = FLAG_DEFLATE | FLAG_DELTA | FLAG_REVISION
REVISION = struct.Struct("<I")
DELTA = struct.Struct("<III")  # revision, base revision, changed cells
HEADER = struct.Struct("<4sHHiidHHI")  # 32 bytes
LAYER_HEIGHT, LAYER_VARIANCE, LAYER_COUNT, LAYER_DISAGREEMENT, LAYER_PENDING = 1, 2, 4, 8, 16
LAYER_CEILING, LAYER_WEIGHT, LAYER_FLOOR = 32, 64, 128
# Layer bit -> (Tile attribute, little-endian dtype, native dtype), in payload order.
LAYERS = (
    (LAYER_HEIGHT, "height", "<f4", np.float32),
    (LAYER_VARIANCE, "variance", "<f4", np.float32),
    (LAYER_COUNT, "count", "<u4", np.uint32),
    (LAYER_DISAGREEMENT, "disagreement", "<f4", np.float32),
    (LAYER_PENDING, "pending", "<f4", np.float32),
    (LAYER_CEILING, "ceiling", "<f4", np.float32),
    (LAYER_WEIGHT, "weight", "<f4", np.float32),
    (LAYER_FLOOR, "floor", "<f4", np.float32),
)
REQUIRED = LAYER_HEIGHT | LAYER_VARIANCE | LAYER_COUNT
KNOWN = REQUIRED | LAYER_DISAGREEMENT | LAYER_PENDING | LAYER_CEILING | LAYER_WEIGHT | LAYER_FLOOR


def encoded_size(tile_cells: int, mask: int = REQUIRED) -> int:
    """Bytes of an encoded tile with ``tile_cells`` cells a side and the given layer mask."""
    return HEADER.size + 4 * tile_cells * tile_cells * bin(mask).count("1")


class MissingBase(ValueError):
    """A delta whose base revision the receiver does not hold (it missed a publication, or joined
    late): the receiver asks for the whole tile, or waits for the publisher's next whole one."""


@dataclass(frozen=True, slots=True, eq=False)
class TileDelta:
    """The cells of tile (tx, ty) that changed from ``base_revision`` to ``revision``: flat indices
    ``index`` (n,) into the (T, T) layers, and their new ``height``, ``variance``, ``count`` (n,)."""

    tx: int
    ty: int
    cell_size_m: float
    tile_cells: int
    revision: int
    base_revision: int
    index: np.ndarray
    height: np.ndarray
    variance: np.ndarray
    count: np.ndarray


def encode_tile(tile: Tile, *, with_disagreement: bool = False, deflate: bool = False,
                revision: int | None = None) -> bytes:
    """Encode ``tile``; the internal layers (disagreement, and pending, ceiling, weight and floor when the
    tile has them) are written only when asked for (snapshots); ``deflate`` compresses the layers
    (format version 2, flag bit0); ``revision`` prefixes the payload with the tile's revision
    (format version 2, flag bit2), for receivers of deltas."""
    t = tile.tile_cells
    if t > 0xFFFF:
        raise ValueError(f"tile of {t} cells a side cannot be encoded (max 65535)")
    if with_disagreement and tile.disagreement is None:
        raise ValueError("tile has no disagreement layer to encode")
    mask = REQUIRED
    if with_disagreement:
        mask |= LAYER_DISAGREEMENT | (LAYER_PENDING if tile.pending is not None else 0)
        mask |= LAYER_CEILING if tile.ceiling is not None else 0
        mask |= LAYER_WEIGHT if tile.weight is not None else 0
        mask |= LAYER_FLOOR if tile.floor is not None else 0
    payload = b"".join(
        np.ascontiguousarray(getattr(tile, name), dtype=le).tobytes()
        for bit, name, le, _ in LAYERS
        if mask & bit
    )
    flags = 0
    if revision is not None:
        payload, flags = REVISION.pack(_revision(revision)) + payload, FLAG_REVISION
    return _frame(tile.tx, tile.ty, tile.cell_size_m, t, mask, payload, flags, deflate)


def encode_delta(tile: Tile, base: Tile, revision: int, base_revision: int, *, deflate: bool = True) -> bytes:
    """The published layers (height, variance, count) of ``tile`` as a delta on ``base``, the same
    tile at ``base_revision``: only the cells whose bits differ (flags bit1 and bit2)."""
    if (tile.tx, tile.ty, tile.tile_cells, tile.cell_size_m) != (base.tx, base.ty, base.tile_cells, base.cell_size_m):
        raise ValueError(f"delta of tile ({tile.tx}, {tile.ty}) on a base of another tile or size")
    changed = np.zeros(tile.height.shape, dtype=bool)
    for bit, name, le, _ in LAYERS:
        if REQUIRED & bit:
            new = np.ascontiguousarray(getattr(tile, name), dtype=le)
            old = np.ascontiguousarray(getattr(base, name), dtype=le)
            changed |= new.view(np.uint32) != old.view(np.uint32)
    index = np.flatnonzero(changed)
    payload = DELTA.pack(_revision(revision), _revision(base_revision), len(index)) + index.astype("<u4").tobytes()
    payload += b"".join(
        np.ascontiguousarray(getattr(tile, name).reshape(-1)[index], dtype=le).tobytes()
        for bit, name, le, _ in LAYERS
        if REQUIRED & bit
    )
    return _frame(tile.tx, tile.ty, tile.cell_size_m, tile.tile_cells, REQUIRED, payload,
                  FLAG_DELTA | FLAG_REVISION, deflate)


def _revision(value: int) -> int:
    if not 0 <= int(value) <= 0xFFFFFFFF:
        raise ValueError(f"tile revision {value} outside 0..2^32-1")
    return int(value)


def _frame(tx: int, ty: int, cell_m: float, t: int, mask: int, payload: bytes, flags: int, deflate: bool) -> bytes:
    """Header + payload; version 1 when no flag is set."""
    if deflate:
        payload, flags = zlib.compress(payload, 6), flags | FLAG_DEFLATE
    version = VERSION_FLAGS if flags else VERSION
    header = HEADER.pack(MAGIC, version, mask, tx, ty, float(cell_m), t, flags, zlib.crc32(payload))
    return header + payload


def decode_tile(data: bytes | bytearray | memoryview) -> Tile:
    """Decode a whole tile made by :func:`encode_tile`; ValueError names what is wrong (a delta is
    refused: :func:`decode_update` and :func:`apply_update` read those)."""
    update = decode_update(data)
    if isinstance(update, TileDelta):
        raise ValueError(f"terrain tile ({update.tx}, {update.ty}) is a delta (revision {update.base_revision} -> "
                         f"{update.revision}): it needs the tile it changes")
    return update


def decode_update(data: bytes | bytearray | memoryview) -> Tile | TileDelta:
    """Decode a whole tile or a delta; ValueError names what is wrong."""
    data = bytes(data)
    if len(data) < HEADER.size:
        raise ValueError(f"tile payload too short: {len(data)} bytes, header alone is {HEADER.size}")
    magic, version, mask, tx, ty, cell, t, flags, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"not a terrain tile: magic {magic!r}, expected {MAGIC!r}")
    if version not in (VERSION, VERSION_FLAGS):
        raise ValueError(f"unsupported terrain tile version {version} (this build reads {VERSION} and {VERSION_FLAGS})")
    if (version == VERSION and flags) or flags & ~FLAGS or (flags & FLAG_DELTA and not flags & FLAG_REVISION):
        raise ValueError(f"terrain tile version {version} with unknown flags 0x{flags:04x}")
    if mask & ~KNOWN or (mask & REQUIRED) != REQUIRED:
        raise ValueError(f"terrain tile has unknown or missing layers: mask 0x{mask:04x}")
    if t < 1:
        raise ValueError("terrain tile has zero cells")
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"terrain tile has invalid cell size {cell}")
    n = t * t
    delta = bool(flags & FLAG_DELTA)
    if delta and mask != REQUIRED:
        raise ValueError(f"terrain tile delta with layers 0x{mask:04x}: deltas carry the published layers only")
    prefix = DELTA.size if delta else REVISION.size if flags & FLAG_REVISION else 0
    # The largest payload this header allows: a delta changes at most every cell (index + layers).
    body = (4 * n * (1 + bin(mask).count("1")) if delta else encoded_size(t, mask) - HEADER.size) + prefix
    payload = memoryview(data)[HEADER.size :]
    if not flags & FLAG_DEFLATE and (len(payload) > body if delta else len(payload) != body):
        raise ValueError(f"terrain tile length {len(data)} bytes, expected {HEADER.size + body} for T={t}, mask 0x{mask:x}")
    if zlib.crc32(payload) != crc:
        raise ValueError("terrain tile CRC mismatch: payload corrupted")
    if flags & FLAG_DEFLATE:
        inflater = zlib.decompressobj()
        try:  # never more than the layers need: a deflate bomb stops there
            raw = inflater.decompress(payload, body + 1)
        except zlib.error as exc:
            raise ValueError(f"terrain tile payload does not inflate: {exc}") from None
        if (len(raw) > body if delta else len(raw) != body) or not inflater.eof:
            raise ValueError(f"terrain tile inflates to {len(raw)}{'+' if not inflater.eof else ''} bytes, "
                             f"expected {body} for T={t}, mask 0x{mask:x}")
        payload = memoryview(raw)
    if delta:
        return _delta(payload, tx, ty, cell, t)
    revision = REVISION.unpack_from(payload)[0] if flags & FLAG_REVISION else None
    layers = {}
    offset = prefix
    for bit, name, le, native in LAYERS:
        if mask & bit:
            layers[name] = np.frombuffer(payload, dtype=le, count=n, offset=offset).astype(native).reshape(t, t)
            offset += 4 * n
    return Tile(tx, ty, cell_size_m=cell, revision=revision, **layers)


def _delta(payload: memoryview, tx: int, ty: int, cell: float, t: int) -> TileDelta:
    if len(payload) < DELTA.size:
        raise ValueError(f"terrain tile delta too short: {len(payload)} bytes")
    revision, base, k = DELTA.unpack_from(payload)
    if k > t * t or len(payload) != DELTA.size + 16 * k:
        raise ValueError(f"terrain tile delta of {k} cells in {len(payload)} bytes (T={t})")
    index = np.frombuffer(payload, dtype="<u4", count=k, offset=DELTA.size).astype(np.int64)
    if k and (index[-1] >= t * t or np.any(np.diff(index) <= 0)):
        raise ValueError("terrain tile delta: cell indices out of range or not ascending")
    values = {}
    offset = DELTA.size + 4 * k
    for bit, name, le, native in LAYERS:
        if REQUIRED & bit:
            values[name] = np.frombuffer(payload, dtype=le, count=k, offset=offset).astype(native)
            offset += 4 * k
    return TileDelta(tx, ty, cell, t, revision, base, index, **values)


def apply_delta(base: Tile | None, delta: TileDelta) -> Tile:
    """The tile ``delta`` makes of ``base``; ``base`` itself when it is already at the delta's
    revision (a query for the whole tile answered first); :class:`MissingBase` when ``base`` is not
    the tile at the delta's base revision (None, another revision, another tile or size)."""
    if base is not None and base.revision == delta.revision and base.key == (delta.tx, delta.ty):
        return base
    if base is None or base.revision != delta.base_revision:
        have = "no tile" if base is None else f"revision {base.revision}"
        raise MissingBase(f"terrain tile ({delta.tx}, {delta.ty}): delta on revision {delta.base_revision}, "
                          f"this receiver holds {have}")
    if (base.tx, base.ty, base.tile_cells, base.cell_size_m) != (delta.tx, delta.ty, delta.tile_cells, delta.cell_size_m):
        raise MissingBase(f"terrain tile ({delta.tx}, {delta.ty}): delta on a tile of another index or size")
    layers = {}
    for name in ("height", "variance", "count"):
        layer = getattr(base, name).copy()
        layer.reshape(-1)[delta.index] = getattr(delta, name)
        layers[name] = layer
    return Tile(base.tx, base.ty, cell_size_m=base.cell_size_m, revision=delta.revision, **layers)


def apply_update(current: Tile | None, data: bytes | bytearray | memoryview) -> Tile:
    """The tile after ``data``: a whole tile as it is, a delta applied to ``current``
    (:class:`MissingBase` when ``current`` is not its base); ValueError for malformed bytes."""
    update = decode_update(data)
    return apply_delta(current, update) if isinstance(update, TileDelta) else update


class TilePublications:
    """What a publisher sends for each changed tile (docs/terrain.md, "Tile deltas"): per tile the
    revision last published and its published layers, so the next publication can be the cells that
    changed since. ``encode(tile)`` -> (whole tile, what goes on the wire: the delta when deltas are
    on, it is smaller than the whole tile and this is not a ``keyframe_every``-th publication; else
    None, meaning the whole tile). The whole tile is what the publisher answers queries with.

    A tile's first revision is ``first_revision`` (random by default): after a restart a receiver
    still holding a tile of the run before cannot take the new run's delta for its base."""

    def __init__(self, deltas: bool = True, keyframe_every: int = 10, first_revision: int | None = None) -> None:
        if keyframe_every < 1:
            raise ValueError(f"keyframe_every must be at least 1, got {keyframe_every}")
        self.deltas = deltas
        self.keyframe_every = int(keyframe_every)
        self.first_revision = _revision(random.getrandbits(32) if first_revision is None else first_revision)
        self._last: dict[tuple[int, int], tuple[int, Tile]] = {}
        self.wholes = 0
        self.delta_count = 0

    def encode(self, tile: Tile, deflate: bool = True) -> tuple[bytes, bytes | None]:
        if not self.deltas:
            self.wholes += 1
            return encode_tile(tile, deflate=deflate), None
        previous = self._last.get(tile.key)
        revision = self.first_revision if previous is None else (previous[0] + 1) & 0xFFFFFFFF
        whole = encode_tile(tile, deflate=deflate, revision=revision)
        live = None
        if previous is not None and revision % self.keyframe_every != 0:
            delta = encode_delta(tile, previous[1], revision, previous[0], deflate=deflate)
            if len(delta) < len(whole):
                live = delta
        self._last[tile.key] = (revision, Tile(tile.tx, tile.ty, tile.height, tile.variance, tile.count, tile.cell_size_m))
        self.delta_count += live is not None
        self.wholes += live is None
        return whole, live
