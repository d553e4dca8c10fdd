"""Other vehicles' maps reach this vehicle's law over a real Zenoh session on loopback
(drivers/fleet_listener.py into companion/method/terrain/sharing.py): placed from the two EKF
origins, fetched whole when a vehicle appears, counted once, never one's own, never an ignored one,
and withdrawn on the operator's word."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from companion.config import ZenohConfig
from companion.method.geodesy import LocalFrame
from companion.method.terrain.codec import encode_tile
from companion.method.terrain.sharing import SharedEvidence
from companion.method.terrain.tile import Tile
from drivers.fleet_listener import FleetListener
from drivers.zenoh_bus import ZenohBus, zenoh_config
from tests.processes import free_port

T = 32
ORIGIN = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_m": 488.0, "source": "GPS_GLOBAL_ORIGIN"}
NORTH_50_M = 50.0 / 111_194.9


def cfg(**kw) -> ZenohConfig:
    base = dict(mode="peer", multicast_scouting=False, reconnect_min_s=0.2, reconnect_max_s=0.5)
    return ZenohConfig(**{**base, **kw})


def wall(tx: int, ty: int, height: float) -> Tile:
    h = np.full((T, T), np.nan, np.float32)
    v = np.full((T, T), np.inf, np.float32)
    n = np.zeros((T, T), np.uint32)
    h[10:12], v[10:12], n[10:12] = height, 0.3, 5
    return Tile(tx, ty, h, v, n, cell_size_m=1.0)


def status(bus, lat_offset_deg: float) -> None:
    bus.publish_status({"frame": {"axes": "NED", "projection": "ardupilot",
                                  "origin": {**ORIGIN, "lat_deg": ORIGIN["lat_deg"] + lat_offset_deg}}})


def drain_until(listener, shared, own, done, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        listener.drain(shared, own)
        if done():
            return True
        time.sleep(0.05)
    return False


def test_another_vehicle_s_wall_is_placed_from_the_origins_and_counted_once():
    ep = f"tcp/127.0.0.1:{free_port()}"
    own = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"])
    with ZenohBus(cfg(listen=(ep,), vehicle_name="v2")) as v2:
        # Published before the listener exists: fetched when v2's liveliness token is seen.
        v2.publish_tile(0, 0, encode_tile(wall(0, 0, 9.0), deflate=True))
        host = ZenohBus(cfg(connect=(ep,), vehicle_name="v1"))  # this vehicle's bus: the listener uses its session
        host.open()
        listener = FleetListener(cfg(connect=(ep,), vehicle_name="v1", share_from=("*",), share_ignore=("v3",))).open(host)
        try:
            shared = SharedEvidence("v1", 1.0, T)
            with ZenohBus(cfg(connect=(ep,), vehicle_name="v3")) as v3:
                host.publish_tile(5, 5, encode_tile(wall(5, 5, 30.0)))  # our own, heard back
                v3.publish_tile(6, 6, encode_tile(wall(6, 6, 30.0)))   # a vehicle we ignore
                status(v3, 0.0)
                # v2's tile arrives by the query its liveliness token prompts; with no origin from
                # v2 yet, it waits. Our own tile and v3's are heard and dropped.
                assert drain_until(listener, shared, own, lambda: listener.counts["own_ignored"] > 0
                                   and listener.counts["ignored"] > 0 and listener.status()["waiting_for_origin"] == ["v2"])
                assert shared.sources == []
                deadline = time.monotonic() + 10
                while not shared.sources and time.monotonic() < deadline:
                    status(v2, NORTH_50_M)  # v2's origin is 50 m north of ours
                    listener.drain(shared, own)
                    time.sleep(0.1)
            assert shared.sources == ["v2"] and listener.counts["tiles_applied"] == 1
            h, v, n = shared.lookup("v2", np.array([10 + 50, 11 + 50, 10]), np.array([3, 3, 3]))
            assert h[0] == pytest.approx(9.0, abs=0.01) and n[0] == 5 and h[1] == pytest.approx(9.0, abs=0.01) and np.isnan(h[2])
            # The same tile again (republished): the evidence is the same, not doubled.
            for _ in range(3):
                v2.publish_tile(0, 0, encode_tile(wall(0, 0, 9.0), deflate=True))
            assert drain_until(listener, shared, own, lambda: listener.counts["tiles_applied"] >= 2)
            again = shared.lookup("v2", np.array([60]), np.array([3]))
            assert (float(again[0][0]), float(again[1][0]), int(again[2][0])) == (float(h[0]), float(v[0]), int(n[0]))
            # The operator withdraws v2: its evidence leaves, and what it sends next is not read.
            operator = zenoh.open(zenoh_config(cfg(connect=(ep,))))
            try:
                deadline = time.monotonic() + 10
                while shared.sources and time.monotonic() < deadline:
                    operator.put("companion/v1/sharing/withdraw", b"v2")
                    listener.drain(shared, own)
                    time.sleep(0.1)
            finally:
                operator.close()
            assert shared.sources == [] and listener.counts["withdrawn"] >= 1
            ignored = listener.counts["ignored"]
            v2.publish_tile(0, 0, encode_tile(wall(0, 0, 9.0), deflate=True))
            assert drain_until(listener, shared, own, lambda: listener.counts["ignored"] > ignored) and shared.sources == []
        finally:
            host.close()


def test_another_vehicle_s_deltas_rebuild_its_tiles_and_a_missed_one_is_asked_for_whole():
    """v2 publishes its tile whole, then as deltas (TilePublications); this vehicle's law sees the
    tile each delta makes. A publication v2 made while nobody heard it leaves the next delta without
    its base: counted, and the tile is asked for whole (v2's bus answers with the last revision)."""
    from companion.method.terrain.codec import TilePublications

    ep = f"tcp/127.0.0.1:{free_port()}"
    own = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"])
    pubs = TilePublications(deltas=True, keyframe_every=1000, first_revision=40)
    ground = np.random.default_rng(4).normal(0.0, 0.3, (T, T)).astype(np.float32)  # a whole tile of it is large

    def tile_with(height: float) -> Tile:
        h = ground.copy()
        h[10, 3] = height
        return Tile(0, 0, h, np.full((T, T), 0.3, np.float32), np.full((T, T), 5, np.uint32), cell_size_m=1.0)

    with ZenohBus(cfg(listen=(ep,), vehicle_name="v2")) as v2:
        def publish(height: float) -> None:
            whole, live = pubs.encode(tile_with(height))
            v2.publish_tile(0, 0, whole, live)

        host = ZenohBus(cfg(connect=(ep,), vehicle_name="v1"))
        host.open()
        listener = FleetListener(cfg(connect=(ep,), vehicle_name="v1", share_from=("v2",))).open(host)
        try:
            shared = SharedEvidence("v1", 1.0, T)
            publish(5.0)
            deadline = time.monotonic() + 10
            while not shared.sources and time.monotonic() < deadline:
                status(v2, 0.0)
                listener.drain(shared, own)
                time.sleep(0.1)

            def height() -> float:
                return float(shared.lookup("v2", np.array([10]), np.array([3]))[0][0])

            # v2's appearance prompted a query for its whole map: once answered, only live samples come.
            assert drain_until(listener, shared, own, lambda: height() == pytest.approx(5.0)
                               and listener.counts["queries_answered"] >= 1)
            publish(6.0)
            assert drain_until(listener, shared, own, lambda: height() == pytest.approx(6.0))
            pubs.encode(tile_with(7.0))  # revision 42: heard by nobody
            publish(8.0)                  # a delta on 42
            assert drain_until(listener, shared, own, lambda: height() == pytest.approx(8.0))
            assert listener.counts["missing_base"] == 1 and listener.counts["bad_tiles"] == 0, dict(listener.counts)
            assert v2.stats().published_deltas == 2
        finally:
            host.close()


def test_another_vehicle_s_map_frame_offset_from_its_status_raises_its_tiles_without_new_ones():
    """A vehicle publishes its tiles in its map's own frame and, in its status, how far the map has
    moved to follow its navigation (``map.frame_shift_m``): its heights reach this vehicle's law
    raised by that, and a new offset needs no tile sent again."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    own = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"])

    def status_with_shift(bus, shift_m: float) -> None:
        bus.publish_status({"frame": {"axes": "NED", "projection": "ardupilot", "origin": ORIGIN},
                            "map": {"frame_shift_m": shift_m}})

    with ZenohBus(cfg(listen=(ep,), vehicle_name="v2")) as v2:
        host = ZenohBus(cfg(connect=(ep,), vehicle_name="v1"))
        host.open()
        listener = FleetListener(cfg(connect=(ep,), vehicle_name="v1", share_from=("v2",))).open(host)
        try:
            shared = SharedEvidence("v1", 1.0, T)
            v2.publish_tile(0, 0, encode_tile(wall(0, 0, 9.0)))

            def height() -> float:
                return float(shared.lookup("v2", np.array([10]), np.array([3]))[0][0]) if shared.sources else float("nan")

            deadline = time.monotonic() + 10
            while not height() == pytest.approx(10.5) and time.monotonic() < deadline:
                status_with_shift(v2, 1.5)
                listener.drain(shared, own)
                time.sleep(0.1)
            assert height() == pytest.approx(10.5, abs=1e-4)
            # v2's appearance prompted a query for its whole map, which may bring the tile once more:
            # wait until it is answered (its replies are queued before it counts), so that what
            # follows is the shift alone.
            assert drain_until(listener, shared, own, lambda: listener.counts["queries_answered"] >= 1)
            listener.drain(shared, own)
            applied = listener.counts["tiles_applied"]
            deadline = time.monotonic() + 10
            while not height() == pytest.approx(8.7) and time.monotonic() < deadline:
                status_with_shift(v2, -0.3)
                listener.drain(shared, own)
                time.sleep(0.1)
            assert height() == pytest.approx(8.7, abs=1e-4)
            assert listener.counts["tiles_applied"] == applied  # no tile came again: the offset moved them
        finally:
            host.close()
