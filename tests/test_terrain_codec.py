"""Tile wire/snapshot codec: bit-exact round trip, the documented byte layout, clear rejections."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.method.messages import TerrainPoints
from companion.method.terrain import TerrainGrid, Tile, decode_tile, encode_tile


def random_tile(rng, t=8, tx=-3, ty=7, cell=0.5, disagreement=False):
    h = rng.normal(0, 50, (t, t)).astype(np.float32)
    v = rng.uniform(0, 4, (t, t)).astype(np.float32)
    n = rng.integers(0, 2**32, (t, t), dtype=np.uint64).astype(np.uint32)
    unknown = rng.random((t, t)) < 0.3
    h[unknown], v[unknown], n[unknown] = np.nan, np.inf, 0
    d = rng.uniform(0, 3, (t, t)).astype(np.float32) if disagreement else None
    pending = None
    if disagreement:  # the fusion state: disagreement and pending heights (NaN: none)
        pending = np.where(rng.random((t, t)) < 0.8, np.nan, rng.normal(10, 5, (t, t))).astype(np.float32)
    return Tile(tx, ty, h, v, n, cell, d, pending)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), t=st.sampled_from([1, 4, 32, 33]),
       tx=st.integers(-2**31, 2**31 - 1), ty=st.integers(-2**31, 2**31 - 1),
       cell=st.floats(0.01, 100.0), dis=st.booleans())
def test_round_trip_is_bit_exact(seed, t, tx, ty, cell, dis):
    tile = random_tile(np.random.default_rng(seed), t, tx, ty, cell, dis)
    data = encode_tile(tile, with_disagreement=dis)
    back = decode_tile(data)
    assert back.same_as(tile)
    assert encode_tile(back, with_disagreement=dis) == data


def test_wire_tile_leaves_out_the_fusion_state():
    tile = random_tile(np.random.default_rng(0), disagreement=True)
    back = decode_tile(encode_tile(tile))
    assert back.disagreement is None and back.pending is None
    assert back.height.tobytes() == tile.height.tobytes()


def test_layout_matches_the_documentation():
    """A decoder written from docs/terrain.md alone (struct + zlib, no project classes)."""
    tile = random_tile(np.random.default_rng(1), t=4, tx=-2, ty=5, cell=1.0)
    data = encode_tile(tile)
    assert data[:4] == b"CTTL"
    version, mask, tx, ty, cell, t, reserved, crc = struct.unpack_from("<HHiidHHI", data, 4)
    assert (version, mask, tx, ty, cell, t, reserved) == (1, 0b111, -2, 5, 1.0, 4, 0)
    assert len(data) == 32 + 3 * 4 * t * t
    assert crc == zlib.crc32(data[32:])
    h = struct.unpack_from(f"<{t * t}f", data, 32)
    n = struct.unpack_from(f"<{t * t}I", data, 32 + 8 * t * t)
    # Row-major [north][east]: the value at i=1, j=2 is element 1*T+2.
    assert h[1 * t + 2] == tile.height[1, 2] and n[3 * t + 0] == tile.count[3, 0]


def test_grid_tiles_survive_the_wire():
    grid = TerrainGrid(tile_cells=16)
    rng = np.random.default_rng(2)
    pos = np.c_[rng.uniform(-40, 40, 500), rng.uniform(-40, 40, 500), rng.normal(-3, 1, 500)]
    grid.insert(TerrainPoints(0.0, pos, np.tile(np.eye(3) * 0.04, (500, 1, 1))))
    remote = TerrainGrid(tile_cells=16)
    for key in grid.pop_dirty():
        remote.put_tile(decode_tile(encode_tile(grid.tile(key))))
    n, e = np.meshgrid(np.linspace(-40, 40, 50), np.linspace(-40, 40, 50))
    for a, b in zip(grid.height_at(n, e), remote.height_at(n, e)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="T=16"):
        TerrainGrid(tile_cells=32).put_tile(grid.tile(grid.keys()[0]))


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: d[:4] + struct.pack("<H", 3) + d[6:], "version"),
        (lambda d: d[:26] + struct.pack("<H", 1) + d[28:], "version 1 with unknown flags"),
        (lambda d: d[:6] + struct.pack("<H", 0b100000111) + d[8:], "layers"),
        (lambda d: d[:6] + struct.pack("<H", 0b011) + d[8:], "layers"),
        (lambda d: d[:-1], "length"),
        (lambda d: d + b"\0", "length"),
        (lambda d: d[:20], "too short"),
        (lambda d: d[:40] + bytes([d[40] ^ 1]) + d[41:], "CRC"),
        (lambda d: d[:16] + struct.pack("<d", -1.0) + d[24:], "cell size"),
        (lambda d: d[:24] + struct.pack("<H", 0) + d[26:], "zero cells"),
    ],
)
def test_bad_payloads_are_rejected(mutate, message):
    data = encode_tile(random_tile(np.random.default_rng(3)))
    with pytest.raises(ValueError, match=message):
        decode_tile(mutate(data))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), t=st.sampled_from([1, 4, 32]), dis=st.booleans())
def test_a_deflated_tile_decodes_to_the_same_tile(seed, t, dis):
    """Format version 2 with the deflate flag: the same tile back, bit for bit, from fewer bytes
    whenever cells are unknown (NaN, +inf, 0 compress to nearly nothing)."""
    tile = random_tile(np.random.default_rng(seed), t, disagreement=dis)
    data = encode_tile(tile, with_disagreement=dis, deflate=True)
    version, flags = struct.unpack_from("<H", data, 4)[0], struct.unpack_from("<H", data, 26)[0]
    assert (version, flags) == (2, 1) and struct.unpack_from("<I", data, 28)[0] == zlib.crc32(data[32:])
    assert decode_tile(data).same_as(tile)
    assert zlib.decompress(data[32:]) == encode_tile(tile, with_disagreement=dis)[32:]  # the documented layout, deflated


def test_a_sparse_tile_deflates_to_a_fraction_and_bad_deflated_payloads_are_refused():
    z = np.full((32, 32), np.nan, np.float32)
    tile = Tile(0, 0, z, np.full((32, 32), np.inf, np.float32), np.zeros((32, 32), np.uint32))
    tile.height[:4], tile.variance[:4], tile.count[:4] = 2.5, 0.3, 2
    plain, small = encode_tile(tile), encode_tile(tile, deflate=True)
    assert len(plain) == 12_320 and len(small) < 200 and decode_tile(small).same_as(tile)

    def framed(body, flags=1, t=32):
        return struct.pack("<4sHHiidHHI", b"CTTL", 2, 0b111, 0, 0, 1.0, t, flags, zlib.crc32(body)) + body

    with pytest.raises(ValueError, match="does not inflate"):
        decode_tile(framed(b"not deflate data"))
    with pytest.raises(ValueError, match=r"inflates to 12289\+ bytes, expected 12288"):  # a deflate bomb stops there
        decode_tile(framed(zlib.compress(bytes(10_000_000))))
    with pytest.raises(ValueError, match="inflates to 100 bytes"):
        decode_tile(framed(zlib.compress(bytes(100))))
    with pytest.raises(ValueError, match="unknown flags"):
        decode_tile(framed(zlib.compress(bytes(12_288)), flags=3))
    with pytest.raises(ValueError, match="CRC"):
        decode_tile(small[:40] + bytes([small[40] ^ 1]) + small[41:])


def test_malformed_tiles_are_refused():
    z = np.zeros((4, 4), np.float32)
    with pytest.raises(ValueError):
        Tile(0, 0, z, np.zeros((3, 3), np.float32), np.zeros((4, 4), np.uint32))
    with pytest.raises(ValueError):
        Tile(0, 0, z, z, np.zeros((4, 4), np.uint32), cell_size_m=0.0)
    with pytest.raises(ValueError, match="disagreement"):
        encode_tile(Tile(0, 0, z, z, np.zeros((4, 4), np.uint32)), with_disagreement=True)


def test_a_snapshot_tile_without_the_pending_layer_still_decodes():
    """Snapshots written before the pending layer (bit 4) existed carry bit 3 only."""
    tile = random_tile(np.random.default_rng(6), disagreement=True)
    old = Tile(tile.tx, tile.ty, tile.height, tile.variance, tile.count, tile.cell_size_m, tile.disagreement)
    data = encode_tile(old, with_disagreement=True)
    assert struct.unpack_from("<H", data, 6)[0] == 0b1111
    back = decode_tile(data)
    assert back.pending is None and back.same_as(old)
    grid = TerrainGrid(tile_cells=tile.tile_cells, cell_size_m=tile.cell_size_m)
    grid.put_tile(back)
    assert np.isnan(grid.tile(tile.key, with_disagreement=True).pending).all()


# ---- deltas --------------------------------------------------------------------------------


def changed_copy(tile: Tile, rng, n: int) -> Tile:
    """``tile`` with ``n`` random cells given new heights, variances and counts."""
    h, v, c = tile.height.copy(), tile.variance.copy(), tile.count.copy()
    idx = rng.choice(h.size, size=n, replace=False)
    h.reshape(-1)[idx] = rng.normal(5.0, 2.0, n).astype(np.float32)
    v.reshape(-1)[idx] = rng.uniform(0.1, 1.0, n).astype(np.float32)
    c.reshape(-1)[idx] += 1
    return Tile(tile.tx, tile.ty, h, v, c, tile.cell_size_m)


def test_a_delta_rebuilds_the_tile_bit_for_bit_and_needs_its_base():
    from companion.method.terrain.codec import MissingBase, TileDelta, apply_update, decode_update, encode_delta

    rng = np.random.default_rng(5)
    base = Tile(3, -2, np.full((32, 32), np.nan, np.float32), np.full((32, 32), np.inf, np.float32),
                np.zeros((32, 32), np.uint32), 1.0)
    held = apply_update(None, encode_tile(base, deflate=True, revision=7))
    assert held.revision == 7 and held.same_as(base)
    tile = base
    for revision in range(8, 20):
        new = changed_copy(tile, rng, int(rng.integers(0, 60)))
        data = encode_delta(new, tile, revision, revision - 1)
        update = decode_update(data)
        assert isinstance(update, TileDelta) and (update.base_revision, update.revision) == (revision - 1, revision)
        held = apply_update(held, data)
        assert held.same_as(new) and held.revision == revision
        assert apply_update(held, data) is held  # already at that revision: nothing to do
        tile = new
    # Twelve deltas of up to 60 cells are each far smaller than the tile.
    assert len(encode_delta(changed_copy(tile, rng, 30), tile, 20, 19)) < len(encode_tile(tile, deflate=True)) / 3
    # A delta on a revision the receiver does not hold (it missed one), or with nothing held.
    skipped = encode_delta(changed_copy(tile, rng, 5), tile, 21, 20)
    with pytest.raises(MissingBase, match="revision 20, this receiver holds revision 19"):
        apply_update(held, skipped)
    with pytest.raises(MissingBase, match="holds no tile"):
        apply_update(None, skipped)
    with pytest.raises(ValueError, match="is a delta"):
        decode_tile(skipped)


def test_malformed_deltas_are_refused_with_the_reason():
    from companion.method.terrain.codec import DELTA, FLAG_DELTA, FLAG_REVISION, HEADER, MAGIC, REQUIRED, decode_update

    def framed(body: bytes, mask: int = REQUIRED, flags: int = FLAG_DELTA | FLAG_REVISION) -> bytes:
        return HEADER.pack(MAGIC, 2, mask, 0, 0, 1.0, 4, flags, zlib.crc32(body)) + body

    cells = np.array([3, 1], "<u4").tobytes() + bytes(24)
    with pytest.raises(ValueError, match="not ascending"):
        decode_update(framed(DELTA.pack(2, 1, 2) + cells))
    with pytest.raises(ValueError, match="of 3 cells in"):
        decode_update(framed(DELTA.pack(2, 1, 3) + cells))
    with pytest.raises(ValueError, match="out of range"):
        decode_update(framed(DELTA.pack(2, 1, 1) + np.array([16], "<u4").tobytes() + bytes(12)))
    with pytest.raises(ValueError, match="published layers only"):
        decode_update(framed(DELTA.pack(2, 1, 0), mask=REQUIRED | 8))
    with pytest.raises(ValueError, match="unknown flags"):
        decode_update(framed(DELTA.pack(2, 1, 0), flags=FLAG_DELTA))


def test_publications_send_deltas_between_whole_tiles():
    """TilePublications: a tile's first publication is whole, the next ones deltas while smaller,
    every keyframe_every-th whole again; revisions count up from first_revision, and every whole
    tile (what queries are answered with) carries its revision."""
    from companion.method.terrain.codec import TilePublications, apply_update, decode_update

    rng = np.random.default_rng(9)
    pubs = TilePublications(deltas=True, keyframe_every=4, first_revision=100)
    tile = Tile(0, 0, np.zeros((32, 32), np.float32), np.ones((32, 32), np.float32), np.ones((32, 32), np.uint32), 1.0)
    held, kinds = None, []
    for k in range(9):
        whole, live = pubs.encode(tile, deflate=True)
        assert decode_update(whole).revision == 100 + k
        kinds.append("whole" if live is None else "delta")
        held = apply_update(held, whole if live is None else live)
        assert held.same_as(tile)
        tile = changed_copy(tile, rng, 10)
    assert kinds == ["whole", "delta", "delta", "delta", "whole", "delta", "delta", "delta", "whole"]  # 100, 104, 108 % 4 == 0
    # Every cell changed: the delta would not be smaller, the tile goes whole.
    big = Tile(0, 0, tile.height + 1, tile.variance + 1, tile.count + 1, 1.0)
    assert pubs.encode(big)[1] is None
    off = TilePublications(deltas=False)
    whole, live = off.encode(tile, deflate=False)
    assert live is None and whole == encode_tile(tile)  # version 1, as before deltas
