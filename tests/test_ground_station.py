"""The ground station: map reassembly, the PNG, and the subscriber against a real bus on loopback."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from companion.config import ZenohConfig
from companion.method.terrain.codec import encode_tile
from companion.method.terrain.tile import Tile
from drivers.ground_station import UNKNOWN_BGR, GroundMap, GroundStation
from drivers.zenoh_bus import BusKeys, ZenohBus, json_payload
from tests.processes import free_port, poll_until

T = 8
CELL = 2.0
KEYS = BusKeys("v1")


def make_tile(tx, ty, fill=None, known=None, cell=CELL, t=T) -> Tile:
    """Height = 100*tx + 10*ty + i + j/10 unless ``fill``; ``known`` (T, T) bool mask (default all)."""
    i, j = np.meshgrid(np.arange(t), np.arange(t), indexing="ij")
    h = (100.0 * tx + 10.0 * ty + i + j / 10.0) if fill is None else np.full((t, t), fill)
    known = np.ones((t, t), bool) if known is None else known
    count = np.where(known, 3, 0).astype(np.uint32)
    h = np.where(known, h, np.nan).astype(np.float32)
    var = np.where(known, 0.25, np.inf).astype(np.float32)
    return Tile(tx, ty, h, var, count, cell_size_m=cell)


def feed(gmap: GroundMap, tile: Tile, stamp=None) -> bool:
    return gmap.apply(KEYS.tile(tile.tx, tile.ty), encode_tile(tile), stamp)


# ------------------------------------------------------------------------------------------
# GroundMap
# ------------------------------------------------------------------------------------------


def test_mosaic_places_tiles_in_the_local_frame():
    g = GroundMap("v1")
    assert g.mosaic() is None
    assert feed(g, make_tile(-1, 2)) and feed(g, make_tile(1, 3))
    m = g.mosaic()
    # Tiles -1..1 north (3 tiles, one missing), 2..3 east.
    assert m.height.shape == (3 * T, 2 * T)
    assert (m.north0_m, m.east0_m, m.cell_size_m) == (-1 * T * CELL, 2 * T * CELL, CELL)
    # Cell [i, j] of tile (1, 3) is mosaic [2T + i, T + j].
    assert m.height[2 * T + 5, T + 4] == pytest.approx(100 + 30 + 5 + 0.4)
    assert m.height[5, 4] == pytest.approx(-100 + 20 + 5 + 0.4)
    assert np.isnan(m.height[T:2 * T]).all()  # the tile row nobody saw
    assert g.cells_known() == 2 * T * T


def test_large_maps_are_decimated_on_the_cell_lattice():
    g = GroundMap("v1")
    feed(g, make_tile(0, -1))
    feed(g, make_tile(1, 0))
    full = g.mosaic()
    m = g.mosaic(max_cells=6)  # 16 x 16 cells -> every 3rd cell
    assert m.height.shape == (6, 6) and m.cell_size_m == 3 * CELL
    assert (m.north0_m, m.east0_m) == (full.north0_m, full.east0_m)
    np.testing.assert_array_equal(m.height, full.height[::3, ::3])
    assert g.height_range() == (float(np.nanmin(full.height)), float(np.nanmax(full.height)))


def test_unknown_cells_stay_unknown_and_stale_tiles_lose():
    known = np.zeros((T, T), bool)
    known[:2] = True
    g = GroundMap("v1")
    assert feed(g, make_tile(0, 0, fill=5.0, known=known), stamp=200)
    assert g.cells_known() == 2 * T
    assert not feed(g, make_tile(0, 0, fill=1.0), stamp=100)  # older than what we have
    assert g.counts["stale_tiles"] == 1 and g.mosaic().height[0, 0] == 5.0
    assert feed(g, make_tile(0, 0, fill=7.0), stamp=300)
    assert g.mosaic().height[0, 0] == 7.0 and g.cells_known() == T * T


def test_bad_inputs_are_counted_not_fatal():
    g = GroundMap("v1")
    good = encode_tile(make_tile(0, 0))
    assert not g.apply(KEYS.tile(0, 0), b"\x00garbage")
    assert not g.apply(KEYS.tile(0, 0), good[:-1] + bytes([good[-1] ^ 1]))  # CRC
    assert not g.apply(KEYS.tile(5, 5), good)  # payload says (0, 0)
    assert g.counts["bad_tiles"] == 3 and not g.tiles
    assert g.apply(KEYS.tile(0, 0), good)
    assert not feed(g, make_tile(1, 0, cell=1.0))  # different grid than the map's
    assert not feed(g, make_tile(1, 0, t=4))
    assert g.counts["bad_tiles"] == 5 and list(g.tiles) == [(0, 0)]
    assert not g.apply(KEYS.status, b"\xff\xfe not json")
    assert not g.apply(KEYS.status, json.dumps({"schema": "companion.status/2"}).encode())
    assert not g.apply(KEYS.avoidance, b"[1, 2]")
    assert g.counts["bad_json"] == 3 and g.status is None
    assert not g.apply("companion/v2/status", b"{}")
    assert g.counts["ignored"] == 1
    assert g.apply(KEYS.status, json_payload("companion.status/1", "v1", 4, {"state": "mapping"}))
    assert g.status["state"] == "mapping"
    assert "#4 mapping" in g.summary() and "5 bad" not in g.summary()
    assert "map frame" not in g.summary()
    # The map has moved 1.25 m to follow the vehicle's navigation: the tiles' heights are the
    # map's own frame, and the line says how far the vehicle's frame is from it.
    assert g.apply(KEYS.status, json_payload("companion.status/1", "v1", 5, {"state": "mapping", "map": {"frame_shift_m": 1.25}}))
    assert "(map frame; +1.25 m to the vehicle's)" in g.summary()


def test_png_is_north_up_with_heights_colour_mapped(tmp_path):
    g = GroundMap("v1")
    known = np.ones((T, T), bool)
    known[3, 6] = False
    feed(g, make_tile(0, 0, fill=10.0, known=known))
    feed(g, make_tile(1, 0, fill=30.0))  # the northern tile is the high one
    feed(g, make_tile(0, 1, fill=20.0))
    path = tmp_path / "out" / "map.png"
    layout = g.write_png(path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["map.png"]  # no temp file left
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    assert (layout.height_lo_m, layout.height_hi_m) == (10.0, 30.0)

    def colour(level):
        return tuple(int(c) for c in cv2.applyColorMap(np.uint8([[level]]), cv2.COLORMAP_TURBO)[0, 0])

    def at(north, east):
        x, y = layout.pixel(north, east)
        return tuple(int(c) for c in img[y, x])

    edge = T * CELL
    assert at(1.0, 1.0) == colour(0)  # lowest known height
    assert at(edge + 1.0, 1.0) == colour(255)  # highest
    assert at(1.0, edge + 1.0) == colour(128)  # 20 m: halfway
    assert at(3 * CELL + 1.0, 6 * CELL + 1.0) == UNKNOWN_BGR  # the one unknown cell
    assert at(edge + 1.0, edge + 1.0) == UNKNOWN_BGR  # the tile nobody saw
    # North up: the northern tile is drawn above the southern one.
    assert layout.pixel(edge + 1.0, 1.0)[1] < layout.pixel(1.0, 1.0)[1]
    # East right.
    assert layout.pixel(1.0, edge + 1.0)[0] > layout.pixel(1.0, 1.0)[0]


def test_empty_map_still_renders(tmp_path):
    g = GroundMap("v1")
    assert g.write_png(tmp_path / "m.png") is None
    assert cv2.imread(str(tmp_path / "m.png")) is not None
    assert "0 tiles" in g.summary()


# ------------------------------------------------------------------------------------------
# Over Zenoh
# ------------------------------------------------------------------------------------------


def cfg(**kw) -> ZenohConfig:
    base = dict(mode="peer", multicast_scouting=False, vehicle_name="v1", reconnect_min_s=0.2, reconnect_max_s=0.5)
    base.update(kw)
    return ZenohConfig(**base)


def test_late_ground_station_reassembles_the_map_and_follows_changes():
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(cfg(listen=(ep,))) as bus:
        tiles = [make_tile(tx, ty) for tx in (-1, 0) for ty in (0, 1, 2)]
        for t in tiles:
            bus.publish_tile(t.tx, t.ty, encode_tile(t))
        with GroundStation(cfg(connect=(ep,))) as station:
            # Before any live sample: the start-up query (re-run when the vehicle's liveliness
            # token shows up) brings the whole map.
            assert poll_until(station, lambda: len(station.map.tiles) == len(tiles))
            for t in tiles:
                assert station.map.tiles[(t.tx, t.ty)].same_as(t)
            # Live changes and state follow.
            changed = make_tile(0, 1, fill=42.0)
            bus.publish_tile(0, 1, encode_tile(changed))
            bus.publish_status({"state": "mapping"})
            bus.publish_avoidance({"engaged": True, "mode": "advisory", "climb_rate_mps": 1.5,
                                   "restriction_alt_m": 57.0, "limiting_cell": [3.0, 4.0]})
            assert poll_until(station, lambda: station.map.tiles[(0, 1)].same_as(changed)
                              and station.map.status is not None and station.map.avoidance is not None)
            line = station.map.summary()
            assert "6 tiles" in line and "mapping" in line and "ENGAGED" in line and "+1.50 m/s" in line
            assert station.map.counts["bad_tiles"] == 0


def test_station_asks_again_when_the_vehicle_appears():
    """A vehicle that comes up after the station (or comes back after a link loss) is asked for
    its map when its liveliness token appears. Here the vehicle never publishes a tile live (its
    map is served by a map_provider), so the query is the only way the station can get them."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    tiles = [make_tile(3, ty) for ty in range(4)]
    with GroundStation(cfg(listen=(ep,))) as station:
        station.poll()  # the start-up query: nobody there yet
        assert station.syncs == 1 and not station.map.tiles
        provider = lambda: [(t.tx, t.ty, encode_tile(t)) for t in tiles]  # noqa: E731
        with ZenohBus(cfg(connect=(ep,)), map_provider=provider) as bus:
            assert poll_until(station, lambda: len(station.map.tiles) == len(tiles), timeout_s=8)
            assert station.syncs >= 2
            assert all(station.map.tiles[(t.tx, t.ty)].same_as(t) for t in tiles)
            assert bus.stats().published_tiles == 0


def test_ground_command_writes_the_png_and_prints_summaries(tmp_path, capsys):
    from companion.cli import main

    ep = f"tcp/127.0.0.1:{free_port()}"
    png = tmp_path / "map.png"
    with ZenohBus(cfg(listen=(ep,), vehicle_name="vehicle7")) as bus:
        for tx in range(2):
            t = make_tile(tx, 0)
            bus.publish_tile(tx, 0, encode_tile(t))
        rc = main(["ground", "--connect", ep, "--vehicle", "vehicle7", "--png", str(png),
                   "--duration", "1.0", "--png-every", "0.3", "--summary-every", "0.3"])
    assert rc == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "vehicle7:" in ln]
    assert len(lines) >= 3, out
    assert "final: vehicle7: 2 tiles, 128 cells known" in lines[-1]
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 100


def test_ground_command_rejects_bad_arguments(capsys):
    from companion.cli import main

    assert main(["ground", "--connect", "nonsense", "--duration", "0.1"]) == 1
    assert "zenoh.connect" in capsys.readouterr().err
    assert main(["ground", "--vehicle", "a/b", "--duration", "0.1"]) == 1
    assert "vehicle_name" in capsys.readouterr().err
    assert main(["ground", "--png-every", "0", "--duration", "0.1"]) == 2


def test_station_applies_deltas_and_asks_whole_for_a_tile_whose_delta_found_no_base():
    """Deltas over a real session: the station rebuilds each tile from the cells that changed; when
    a publication is lost, the next delta finds no base, is counted, and the station asks the
    vehicle for that tile whole (the bus answers with the whole tile of the last revision)."""
    from companion.method.terrain.codec import TilePublications

    ep = f"tcp/127.0.0.1:{free_port()}"
    pubs = TilePublications(deltas=True, keyframe_every=1000, first_revision=1)
    rng = np.random.default_rng(2)

    def changed(tile: Tile) -> Tile:
        h = tile.height.copy()
        h.reshape(-1)[rng.choice(h.size, 6, replace=False)] += 1.0
        return Tile(tile.tx, tile.ty, h, tile.variance, tile.count, tile.cell_size_m)

    def publish(tile: Tile) -> bool:
        whole, live = pubs.encode(tile)
        bus.publish_tile(tile.tx, tile.ty, whole, live)
        return live is not None

    with ZenohBus(cfg(listen=(ep,))) as bus:
        tile = make_tile(2, 5, t=32)
        publish(tile)
        with GroundStation(cfg(connect=(ep,))) as station:
            assert poll_until(station, lambda: (2, 5) in station.map.tiles)
            for _ in range(3):
                tile = changed(tile)
                assert publish(tile)
                assert poll_until(station, lambda: station.map.tiles[(2, 5)].same_as(tile))
            # (a re-sync when the vehicle's liveliness token shows up may bring one of them whole)
            assert station.map.counts["deltas_rx"] >= 1 and bus.stats().published_deltas == 3
            lost = changed(tile)
            pubs.encode(lost)  # published nowhere: the station never hears of this revision
            tile = changed(lost)
            assert publish(tile)
            assert poll_until(station, lambda: station.map.tiles[(2, 5)].same_as(tile))
            assert station.map.counts["missing_base"] == 1 and station.tile_queries == 1, (station.map.counts, station.tile_queries, station.map.last_error)
            assert station.map.counts["bad_tiles"] == 0
