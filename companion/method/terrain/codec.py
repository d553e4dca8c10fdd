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
    26     2    uint16   flags (version 2; 0 in version 1): bit0 the payload is deflated (zlib)
    28     4    uint32   CRC-32 (zlib/IEEE) of the payload as stored (deflated or not)
    32     ...  payload: the layers in mask-bit order, each T*T little-endian values,
                row-major [i north][j east]; with flag bit0, those bytes deflated (zlib)

Deflating is for the radio: a tile's unknown cells (NaN, +inf, 0) and its repeated values
compress about six times (docs/zenoh.md, "Bandwidth"). A tile written without it is version 1,
byte for byte what readers of version 1 know.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from companion.method.terrain.tile import Tile

MAGIC = b"CTTL"
VERSION = 1
VERSION_FLAGS = 2      # the flags field is in use
FLAG_DEFLATE = 1
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


def encode_tile(tile: Tile, *, with_disagreement: bool = False, deflate: bool = False) -> bytes:
    """Encode ``tile``; the internal layers (disagreement, and pending, ceiling, weight and floor when the
    tile has them) are written only when asked for (snapshots); ``deflate`` compresses the layers
    (format version 2, flag bit0)."""
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
    version, flags = VERSION, 0
    if deflate:
        payload, version, flags = zlib.compress(payload, 6), VERSION_FLAGS, FLAG_DEFLATE
    header = HEADER.pack(MAGIC, version, mask, tile.tx, tile.ty, float(tile.cell_size_m), t, flags, zlib.crc32(payload))
    return header + payload


def decode_tile(data: bytes | bytearray | memoryview) -> Tile:
    """Decode bytes made by :func:`encode_tile`; ValueError names what is wrong."""
    data = bytes(data)
    if len(data) < HEADER.size:
        raise ValueError(f"tile payload too short: {len(data)} bytes, header alone is {HEADER.size}")
    magic, version, mask, tx, ty, cell, t, flags, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"not a terrain tile: magic {magic!r}, expected {MAGIC!r}")
    if version not in (VERSION, VERSION_FLAGS):
        raise ValueError(f"unsupported terrain tile version {version} (this build reads {VERSION} and {VERSION_FLAGS})")
    if (version == VERSION and flags) or flags & ~FLAG_DEFLATE:
        raise ValueError(f"terrain tile version {version} with unknown flags 0x{flags:04x}")
    if mask & ~KNOWN or (mask & REQUIRED) != REQUIRED:
        raise ValueError(f"terrain tile has unknown or missing layers: mask 0x{mask:04x}")
    if t < 1:
        raise ValueError("terrain tile has zero cells")
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"terrain tile has invalid cell size {cell}")
    expected = encoded_size(t, mask)
    payload = memoryview(data)[HEADER.size :]
    if not flags & FLAG_DEFLATE and len(data) != expected:
        raise ValueError(f"terrain tile length {len(data)} bytes, expected {expected} for T={t}, mask 0x{mask:x}")
    if zlib.crc32(payload) != crc:
        raise ValueError("terrain tile CRC mismatch: payload corrupted")
    if flags & FLAG_DEFLATE:
        inflater = zlib.decompressobj()
        try:  # never more than the layers need: a deflate bomb stops there
            raw = inflater.decompress(payload, expected - HEADER.size + 1)
        except zlib.error as exc:
            raise ValueError(f"terrain tile payload does not inflate: {exc}") from None
        if len(raw) != expected - HEADER.size or not inflater.eof:
            raise ValueError(f"terrain tile inflates to {len(raw)}{'+' if not inflater.eof else ''} bytes, "
                             f"expected {expected - HEADER.size} for T={t}, mask 0x{mask:x}")
        payload = memoryview(raw)
    layers = {}
    offset = 0
    n = t * t
    for bit, name, le, native in LAYERS:
        if mask & bit:
            layers[name] = np.frombuffer(payload, dtype=le, count=n, offset=offset).astype(native).reshape(t, t)
            offset += 4 * n
    return Tile(tx, ty, cell_size_m=cell, **layers)
