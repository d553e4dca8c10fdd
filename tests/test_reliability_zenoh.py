"""Reliability of the Zenoh side: garbage on the wire is rejected and counted, and a
daemon whose Zenoh peer or router is unreachable keeps mapping, says the link is down, and
reconnects and publishes when something appears on the endpoint.

Real Zenoh sessions on 127.0.0.1 with ephemeral ports; the daemon test runs the real processes.
"""

from __future__ import annotations

import json
import queue
import socket
import time

import numpy as np
import pytest
import zenoh

from companion.config import ZenohConfig
from companion.method.terrain.codec import decode_tile, decode_update, encode_tile
from companion.method.terrain.tile import Tile
from drivers.ground_station import GroundStation
from drivers.sim.harness import MavClient, SimVehicleProcess
from drivers.zenoh_bus import BusKeys, ZenohBus, json_payload
from tests.processes import companion, free_port, poll_until, stop, write_config


def cfg(**kw) -> ZenohConfig:
    return ZenohConfig(**{"mode": "peer", "multicast_scouting": False, "vehicle_name": "v1",
                          "reconnect_min_s": 0.2, "reconnect_max_s": 0.5, **kw})


def raw_session(listen=(), connect=()) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def a_tile(tx: int, ty: int, fill: float) -> Tile:
    return Tile(tx, ty, np.full((8, 8), fill, np.float32), np.full((8, 8), 0.1, np.float32), np.ones((8, 8), np.uint32))


def test_garbage_published_to_a_ground_station_is_counted_and_the_map_survives():
    """A stranger on the network puts garbage on the vehicle's keys (tiles, status, avoidance): the
    ground station's subscribers count every sample as a rejection and keep the real map."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = BusKeys("v1")
    good = a_tile(0, 0, 5.0)
    with ZenohBus(cfg(listen=(ep,))) as bus, GroundStation(cfg(connect=(ep,))) as station:
        bus.publish_tile(0, 0, encode_tile(good))
        assert poll_until(station, lambda: (0, 0) in station.map.tiles)
        stranger = raw_session(connect=[ep])
        try:
            wrong_place = encode_tile(a_tile(7, 7, 1.0))
            garbage = [
                (keys.tile(0, 0), b""),
                (keys.tile(0, 0), b"\x00" * 5000),
                (keys.tile(0, 0), encode_tile(good)[:-3]),  # truncated
                (keys.tile(0, 0), wrong_place),  # a valid tile under another tile's key
                (keys.tile(1, 1), bytes(reversed(encode_tile(good)))),
                (keys.status, b"\xff\xfe\xfd"),
                (keys.status, b'{"schema": "companion.status/9"}'),
                (keys.status, b"[]"),
                (keys.avoidance, b"{\"schema\": "),
                (keys.avoidance, json_payload("companion.status/1", "v1", 1, {})),  # the wrong schema on this key
            ]
            deadline = time.monotonic() + 5
            rejected = 0
            # Re-send until every kind has been seen once (the stranger's link may need a moment).
            while time.monotonic() < deadline and rejected < len(garbage):
                for key, payload in garbage:
                    stranger.put(key, payload)
                time.sleep(0.2)
                station.poll()
                rejected = station.map.counts["bad_tiles"] + station.map.counts["bad_json"]
        finally:
            stranger.close()
        counts = dict(station.map.counts)
        assert counts["bad_tiles"] >= 5 and counts["bad_json"] >= 5, counts
        assert list(station.map.tiles) == [(0, 0)] and station.map.tiles[(0, 0)].same_as(good)
        assert station.map.status is None  # nothing valid came on the status key
        # The vehicle's own map is untouched (it never subscribes to its own keys) and still served.
        station.sync()
        assert list(station.map.tiles) == [(0, 0)] and station.map.tiles[(0, 0)].same_as(good)
        assert bus.stats().query_errors == 0
    print(f"\ngarbage samples counted by the ground station: {counts}")


def test_garbage_queries_do_not_disturb_publication():
    """Many malformed queries at once (payloads, bad keys): each answered with an error and counted;
    the bus publishes and serves the map in between."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(cfg(listen=(ep,))) as bus:
        bus.publish_tile(2, 2, encode_tile(a_tile(2, 2, 1.0)))
        ground = raw_session(connect=[ep])
        try:
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline and not list(ground.get("companion/v1/terrain/tile/**", timeout=1.0)):
                time.sleep(0.05)
            selectors = ["companion/v1/terrain/tile/x/y", "companion/v1/terrain/tile/1/2/3", "companion/v1/terrain/zz",
                         "companion/v1/terrain/map"]
            errors = 0
            for i in range(40):
                kw = {"payload": bytes([i]) * (i * 100)} if i % 2 else {}
                for r in ground.get(selectors[i % 4], timeout=2.0, **kw):
                    errors += r.err is not None
            good = [r for r in ground.get("companion/v1/terrain/tile/**", timeout=2.0) if r.ok is not None]
        finally:
            ground.close()
        stats = bus.stats()
    assert errors == 40 and stats.bad_queries == 40 and stats.query_errors == 0
    assert len(good) == 1 and decode_tile(good[0].ok.payload.to_bytes()).key == (2, 2)


# ------------------------------------------------------------------------------------------
# The daemon with its Zenoh peer unreachable
# ------------------------------------------------------------------------------------------


def read_statuses(sock: socket.socket, seconds: float) -> list[str]:
    """The STATUS= lines the daemon sent to the systemd notify socket in the next ``seconds``."""
    out = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            msg = sock.recv(4096).decode()
        except TimeoutError:
            continue
        out += [line[len("STATUS="):] for line in msg.split("\n") if line.startswith("STATUS=")]
    return out


def field(summary: str, suffix: str) -> int:
    """The integer before ``suffix`` in a STATUS summary ("...; 12 tiles; ...")."""
    part = next(p for p in summary.split("; ") if p.endswith(suffix))
    return int(part.split()[-2])


@pytest.mark.slow
def test_daemon_keeps_mapping_without_its_zenoh_peer_then_reconnects_and_publishes(tmp_path):
    """The daemon flies and maps with ``zenoh.connect`` pointing at an endpoint nobody listens on.
    Meanwhile (seen through the systemd STATUS lines) the map grows and the status says "zenoh
    down". A peer then starts listening on that endpoint: the daemon connects, publishes status
    (link up, counted) and new tiles, and a query from that late joiner returns the whole map."""
    from tests.test_daemon_process import CIRCUIT, take_off

    speedup = 3.0
    ep = f"tcp/127.0.0.1:{free_port()}"
    pilot = MavClient.udp_listener()
    sim = SimVehicleProcess(["--scenario", "default", "--tcp-listen", "127.0.0.1:0", "--udp-out",
                             f"127.0.0.1:{pilot.port}", "--speedup", str(speedup), "--origin-delay", "1"],
                            stderr_path=str(tmp_path / "sim.log")).start()
    config = write_config(tmp_path / "c.yaml", {
        "link": {"connection": f"tcp:127.0.0.1:{sim.endpoints['tcp']}", "heartbeat_timeout_s": 1.5},
        "camera": {"source": "synthetic", "rate_hz": 15.0},
        "control": {"commanding_enabled": True, "waypoints_ne_m": CIRCUIT, "cruise_speed_mps": 6.0},
        "zenoh": {"enabled": True, "connect": [ep], "listen": ["tcp/127.0.0.1:0"], "status_rate_hz": 4.0,
                  "reconnect_min_s": 0.2, "reconnect_max_s": 0.5},
        "persistence": {"directory": str(tmp_path / "map"), "snapshot_interval_s": 5.0},
        "sim": {"scenario": "default", "speedup": speedup},
    })
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.settimeout(0.2)
    daemon = companion("run", "--config", str(config), env={"NOTIFY_SOCKET": str(tmp_path / "notify.sock")},
                       log=tmp_path / "daemon.log")
    ground = None
    try:
        take_off(pilot)
        # Zenoh down: the mapper goes on and the map grows all the same.
        def grown(a: str, b: str) -> bool:
            return (field(b, " frames") >= field(a, " frames") + 30
                    and (field(b, " tiles") > field(a, " tiles") or field(b, " cells") > field(a, " cells")))

        down = []
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline:
            down += [s for s in read_statuses(sock, 0.5) if "zenoh " in s]
            if len(down) >= 2 and field(down[-1], " tiles") >= 2 and grown(down[0], down[-1]):
                break
        assert down and all("zenoh down" in s and s.startswith("degraded") for s in down), down[-3:]
        assert grown(down[0], down[-1]), (down[0], down[-1])

        # A peer appears on the endpoint (zenoh 1.x: a listening peer serves as the router).
        ground = raw_session(listen=[ep])
        statuses: queue.Queue = queue.Queue()
        live: queue.Queue = queue.Queue()
        ground.declare_subscriber("companion/vehicle1/status", lambda s: statuses.put(json.loads(s.payload.to_bytes())))
        ground.declare_subscriber("companion/vehicle1/terrain/tile/*/*",
                                  lambda s: live.put((str(s.key_expr), s.payload.to_bytes())))
        t_up = time.monotonic()
        # A status built a moment before the link came up may still arrive over it: each message
        # is one look at the bus, so wait for the first that saw the link (bounded).
        first = statuses.get(timeout=10)
        while first["zenoh"]["links"] == 0:
            assert first["zenoh_link"] == "down" and any("zenoh link down" in p for p in first["problems"]), first
            first = statuses.get(timeout=5)
        t_first = time.monotonic() - t_up
        assert first["zenoh"]["link_ups"] >= 1 and first["zenoh_link"] == "up"
        assert not any("zenoh" in p for p in first["problems"])
        assert first["map"]["tiles"] >= field(down[-1], " tiles") > 0
        # New tiles are published live again as the map changes.
        key, payload = live.get(timeout=15)
        update = decode_update(payload)  # a whole tile or a delta
        assert BusKeys("vehicle1").parse_tile(key) == (update.tx, update.ty)
        # The late joiner asks for the whole map: every tile the daemon holds, including those
        # published while nobody was there.
        latest = statuses.get(timeout=5)
        while not statuses.empty():
            latest = statuses.get_nowait()
        replies = [r.ok for r in ground.get("companion/vehicle1/terrain/tile/**", timeout=5.0) if r.ok is not None]
        tiles = {decode_tile(r.payload.to_bytes()).key for r in replies}
        assert len(tiles) == len(replies) >= latest["map"]["tiles"] - 1  # a tile may be created in between
        up_lines = [s for s in read_statuses(sock, 1.0) if "zenoh " in s]
        assert up_lines and "zenoh up" in up_lines[-1]
    finally:
        if ground:
            ground.close()
        rc = stop(daemon)
        sim.stop()
        pilot.close()
        sock.close()
    assert rc == 0
    print(f"\nzenoh down: {len(down)} status lines, map {field(down[0], ' tiles')} -> {field(down[-1], ' tiles')} tiles, "
          f"{field(down[0], ' frames')} -> {field(down[-1], ' frames')} frames mapped; "
          f"peer up: first status after {t_first:.2f} s, late-joiner query {len(replies)} tiles "
          f"(status: {latest['map']['tiles']})")
    log = (tmp_path / "daemon.log").read_text()
    assert "zenoh: link up" in log
