"""The Zenoh bus against real Zenoh sessions on 127.0.0.1 (ephemeral ports, no multicast).

The "ground" side of every test is a plain ``zenoh`` session, not project code, so these tests
also check that the wire is usable by anyone who knows only docs/zenoh.md.
"""

from __future__ import annotations

import asyncio
import json
import queue
import re
import socket
import time
from pathlib import Path

import pytest
import zenoh

from companion.config import ZenohConfig
from drivers.zenoh_bus import (
    AVOIDANCE_SCHEMA,
    STATUS_SCHEMA,
    BusError,
    BusKeys,
    ZenohBus,
    zenoh_config,
)
from tests.processes import free_port

VEHICLE = "v1"


def bus_config(**kw) -> ZenohConfig:
    base = dict(mode="peer", listen=(), connect=(), multicast_scouting=False, vehicle_name=VEHICLE,
                reconnect_min_s=0.2, reconnect_max_s=0.5)
    base.update(kw)
    return ZenohConfig(**base)


def raw_session(mode="peer", listen=(), connect=(), base: zenoh.Config | None = None) -> zenoh.Session:
    """A session built with zenoh alone (what a third-party ground station would do)."""
    c = base or zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def wait_for(predicate, timeout=5.0, step=0.02):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


class Inbox:
    """Samples received by a raw subscriber: (arrival perf_counter, key, payload bytes, timestamp)."""

    def __init__(self, session: zenoh.Session, key: str):
        self.q: queue.Queue = queue.Queue()
        self.sub = session.declare_subscriber(
            key, lambda s: self.q.put((time.perf_counter(), str(s.key_expr), s.payload.to_bytes(), s.timestamp))
        )

    def drain(self) -> list:
        out = []
        while True:
            try:
                out.append(self.q.get_nowait())
            except queue.Empty:
                return out

    def get(self, timeout=5.0):
        return self.q.get(timeout=timeout)


def link_up(bus: ZenohBus, inbox: Inbox, timeout=5.0) -> None:
    """Publish probe statuses until the subscriber hears one, then forget the probes."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        bus.publish_status({"probe": True})
        try:
            inbox.get(timeout=0.05)
            time.sleep(0.05)
            inbox.drain()
            return
        except queue.Empty:
            pass
    raise AssertionError("subscriber never connected to the bus")


@pytest.fixture
def linked():
    """A bus listening on an ephemeral port and a raw peer connected to it."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    bus = ZenohBus(bus_config(listen=(ep,)))
    bus.open()
    ground = raw_session(connect=[ep])
    try:
        yield bus, ground
    finally:
        ground.close()
        bus.close()


def tile_bytes(tx: int, ty: int, rev: int = 0, n: int = 64) -> bytes:
    return bytes([(tx * 7 + ty * 13 + rev + i) % 256 for i in range(n)])


# ------------------------------------------------------------------------------------------
# Keys and configuration
# ------------------------------------------------------------------------------------------


def test_keys_follow_the_documented_layout():
    k = BusKeys("vehicle1")
    assert k.tile(-3, 12) == "companion/vehicle1/terrain/tile/-3/12"
    assert k.status == "companion/vehicle1/status"
    assert k.avoidance == "companion/vehicle1/avoidance"
    assert k.map == "companion/vehicle1/terrain/map"
    assert k.parse_tile("companion/vehicle1/terrain/tile/-3/12") == (-3, 12)
    for bad in ("companion/vehicle1/terrain/tile/a/1", "companion/vehicle1/terrain/tile/1",
                "companion/other/terrain/tile/1/1", "companion/vehicle1/terrain/tile/1/2/3"):
        assert k.parse_tile(bad) is None
    for bad_name in ("a/b", "", "x*", "a?b", "$x"):
        with pytest.raises(BusError, match="vehicle_name"):
            BusKeys(bad_name)


def test_session_config_carries_the_companion_settings():
    cfg = bus_config(mode="client", connect=("tcp/10.0.0.1:7447",), listen=("tcp/127.0.0.1:0",),
                     reconnect_min_s=0.5, reconnect_max_s=8.0)
    z = zenoh_config(cfg)
    assert json.loads(z.get_json("mode")) == "client"
    assert json.loads(z.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    retry = json.loads(z.get_json("connect/retry"))
    assert (retry["period_init_ms"], retry["period_max_ms"]) == (500, 8000)


def test_bad_settings_are_named():
    with pytest.raises(BusError, match="zenoh.connect"):
        zenoh_config(bus_config(connect=("not-an-endpoint",)))
    with pytest.raises(BusError, match="zenoh.config_file"):
        zenoh_config(bus_config(config_file="/nonexistent/zenoh.json5"))


def test_config_file_is_merged_under_the_companion_settings(tmp_path):
    f = tmp_path / "extra.json5"
    f.write_text('{ id: "c0ffee01", mode: "router", listen: { endpoints: ["tcp/127.0.0.1:0"] } }')
    z = zenoh_config(bus_config(config_file=str(f)))
    assert json.loads(z.get_json("id")) == "c0ffee01"  # the file's own setting survives
    assert json.loads(z.get_json("mode")) == "peer"  # ours wins where we have a setting
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]  # ours empty: file's kept
    broken = tmp_path / "broken.json5"
    broken.write_text("{ access_control: ")
    with pytest.raises(BusError, match="broken.json5"):
        zenoh_config(bus_config(config_file=str(broken)))


def _documented_acl() -> str:
    """The access-control example of docs/zenoh.md, bound to the loopback interface."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "zenoh.md").read_text()
    block = next(b for b in re.findall(r"```json5\n(.*?)```", text, flags=re.S) if "access_control" in b)
    return re.sub(r"interfaces: \[[^\]]*\]", 'interfaces: ["lo"]', block)


@pytest.mark.parametrize("with_acl", [True, False])
def test_documented_access_control_file_is_enforced(tmp_path, with_acl):
    """With the docs' ACL as config_file, a ground peer reads and queries but cannot publish in."""
    acl = tmp_path / "acl.json5"
    acl.write_text(_documented_acl())
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(bus_config(listen=(ep,), vehicle_name="vehicle1", config_file=str(acl) if with_acl else "")) as bus:
        # White-box spy: a subscriber in the vehicle's own session shows what reaches the vehicle.
        spy: queue.Queue = queue.Queue()
        spy_sub = bus._session.declare_subscriber("companion/vehicle1/status", lambda s: spy.put(s.payload.to_bytes()))
        ground = raw_session(connect=[ep])
        try:
            inbox = Inbox(ground, "companion/vehicle1/**")
            assert wait_for(lambda: (bus.publish_status({"x": 1}), not inbox.q.empty())[1], timeout=5)
            bus.publish_tile(1, 2, b"tile")
            got = replies(ground, "companion/vehicle1/terrain/tile/**")
            assert got == [("ok", "companion/vehicle1/terrain/tile/1/2", b"tile")]
            for _ in range(10):
                ground.put("companion/vehicle1/status", b"forged")
                time.sleep(0.02)
            time.sleep(0.3)
            seen = []
            while not spy.empty():
                seen.append(spy.get())
            assert (b"forged" in seen) is (not with_acl)
        finally:
            spy_sub.undeclare()
            ground.close()


# ------------------------------------------------------------------------------------------
# Publishing
# ------------------------------------------------------------------------------------------


def test_changed_tiles_reach_a_subscriber(linked):
    bus, ground = linked
    inbox = Inbox(ground, "companion/v1/terrain/tile/*/*")
    status_inbox = Inbox(ground, "companion/v1/status")
    link_up(bus, status_inbox)
    sent = {(tx, ty): tile_bytes(tx, ty) for tx in (-1, 0, 2) for ty in (-2, 5)}
    t_sent = {}
    for (tx, ty), payload in sent.items():
        t_sent[(tx, ty)] = time.perf_counter()
        bus.publish_tile(tx, ty, payload)
    got = {}
    latencies = []
    deadline = time.monotonic() + 5
    while len(got) < len(sent) and time.monotonic() < deadline:
        t, key, payload, ts = inbox.get(timeout=5)
        k = BusKeys(VEHICLE).parse_tile(key)
        got[k] = payload
        latencies.append(t - t_sent[k])
        assert ts is not None  # stamped so a late joiner can order query replies against live tiles
    assert got == sent
    s = bus.stats()
    assert s.published_tiles == len(sent) and s.bytes_published >= sum(map(len, sent.values()))
    print(f"\ntile publish->receive over loopback: median {sorted(latencies)[len(latencies) // 2] * 1e3:.2f} ms, "
          f"max {max(latencies) * 1e3:.2f} ms ({len(latencies)} tiles of {len(next(iter(sent.values())))} B)")


def test_grid_changes_are_published_once(linked):
    from companion.method.terrain.codec import decode_tile
    from companion.method.terrain.grid import TerrainGrid
    from companion.method.terrain.tile import Tile
    import numpy as np

    bus, ground = linked
    inbox = Inbox(ground, "companion/v1/terrain/tile/*/*")
    link_up(bus, Inbox(ground, "companion/v1/status"))
    grid = TerrainGrid(cell_size_m=1.0, tile_cells=4)
    for tx, ty in ((0, 0), (-1, 2)):
        h = np.full((4, 4), 10.0 + tx + ty, np.float32)
        grid.put_tile(Tile(tx, ty, h, np.ones((4, 4), np.float32), np.ones((4, 4), np.uint32)))
    assert bus.publish_grid_changes(grid) == 2
    assert bus.publish_grid_changes(grid) == 0  # nothing changed since
    got = {}
    for _ in range(2):
        _, key, payload, _ = inbox.get(timeout=5)
        got[BusKeys(VEHICLE).parse_tile(key)] = decode_tile(payload)
    assert sorted(got) == [(-1, 2), (0, 0)]
    assert got[(-1, 2)].same_as(grid.tile((-1, 2)))
    # The map moved to follow the navigation's frame: published tiles are in the map's own frame,
    # which did not move, so nothing goes out; the navigation's heights are theirs plus the shift.
    grid.shift_heights(0.7)
    assert bus.publish_grid_changes(grid) == 0
    assert got[(-1, 2)].same_as(grid.tile((-1, 2), in_map_frame=True))
    assert np.allclose(grid.tile((-1, 2)).height, got[(-1, 2)].height + 0.7)


def test_the_daemon_publishes_its_map_in_the_map_s_own_frame_and_the_shift_in_its_status(linked, tmp_path):
    """The service's publisher: tiles in the map's own frame, so the map moving to follow the
    navigation sends nothing; the status carries the shift that takes them to the vehicle's frame."""
    import numpy as np

    from companion.config import CompanionConfig
    from companion.config import replace as replace_config
    from companion.method.messages import TerrainPoints
    from companion.method.terrain.codec import apply_update
    from companion.service.daemon import Daemon

    bus, ground = linked
    inbox = Inbox(ground, "companion/v1/terrain/tile/*/*")
    link_up(bus, Inbox(ground, "companion/v1/status"))
    daemon = Daemon(replace_config(CompanionConfig(), **{"zenoh.enabled": False, "persistence.directory": str(tmp_path)}))
    daemon.bus = bus
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(5, 15, 400), rng.uniform(5, 15, 400), rng.normal(-2.0, 0.1, 400)])
    daemon.grid.insert(TerrainPoints(0.0, pts, np.tile(np.diag([0.01, 0.01, 0.01]), (400, 1, 1))))
    assert daemon.publish_changed_tiles() == 1
    _, key, payload, _ = inbox.get(timeout=5)
    sent = apply_update(None, payload)
    daemon.grid.shift_heights(1.25)
    assert daemon.publish_changed_tiles() == 0
    assert sent.same_as(daemon.grid.tile((0, 0), in_map_frame=True))
    status = daemon.status()["map"]
    assert status["frame_shift_m"] == 1.25 and status["frame_shifts"] == 1
    known = sent.count > 0
    assert np.allclose(sent.height[known] + status["frame_shift_m"], daemon.grid.tile((0, 0)).height[known])
    assert not inbox.drain()


def test_tile_arguments_are_checked(linked):
    bus, _ = linked
    with pytest.raises(TypeError, match="bytes"):
        bus.publish_tile(0, 0, "not bytes")
    with pytest.raises(ValueError, match="integers"):
        bus.publish_tile(0.5, 0, b"x")
    assert bus.stats().tiles_cached == 0


def test_status_is_published_at_the_configured_rate():
    ep = f"tcp/127.0.0.1:{free_port()}"
    rate = 20.0
    with ZenohBus(bus_config(listen=(ep,), status_rate_hz=rate)) as bus:
        ground = raw_session(connect=[ep])
        try:
            inbox = Inbox(ground, "companion/v1/status")
            link_up(bus, inbox)
            calls = {"n": 0}

            def provider():
                calls["n"] += 1
                if calls["n"] == 3:
                    raise RuntimeError("a broken status field")
                return {"mode": "advisory", "map_cells": calls["n"], "nan_field": float("nan")}

            async def run_for(seconds):
                task = asyncio.create_task(bus.run_status(provider))
                await asyncio.sleep(seconds)
                task.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await task

            asyncio.run(run_for(1.0))
            time.sleep(0.1)
            msgs = inbox.drain()
        finally:
            ground.close()
    docs = [json.loads(p.decode("utf-8")) for _, _, p, _ in msgs]
    # 1 s at 20 Hz is 20 or 21 calls; one raised and was skipped.
    assert 15 <= len(docs) <= 21, len(docs)
    assert all(d["schema"] == STATUS_SCHEMA and d["vehicle"] == VEHICLE for d in docs)
    seqs = [d["seq"] for d in docs]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(d["nan_field"] is None for d in docs)  # JSON has no NaN: null
    assert docs[-1]["zenoh"]["status_provider_errors"] == 1
    gaps = [b[0] - a[0] for a, b in zip(msgs, msgs[1:])]
    assert 0.03 < sorted(gaps)[len(gaps) // 2] < 0.07  # median spacing is the 50 ms period


def test_avoidance_is_checked_and_published(linked):
    bus, ground = linked
    inbox = Inbox(ground, "companion/v1/avoidance")
    status_inbox = Inbox(ground, "companion/v1/status")
    link_up(bus, status_inbox)
    with pytest.raises(ValueError, match="limiting_cell"):
        bus.publish_avoidance({"engaged": True, "mode": "commanding", "climb_rate_mps": 1.0,
                               "restriction_alt_m": 20.0})
    with pytest.raises(ValueError, match="seq"):
        bus.publish_avoidance({"engaged": True, "mode": "commanding", "climb_rate_mps": 1.0,
                               "restriction_alt_m": 20.0, "limiting_cell": [1, 2], "seq": 5})
    with pytest.raises(TypeError, match="not JSON"):
        bus.publish_avoidance({"engaged": True, "mode": "commanding", "climb_rate_mps": object(),
                               "restriction_alt_m": 20.0, "limiting_cell": None})
    bus.publish_avoidance({"engaged": True, "mode": "commanding", "climb_rate_mps": 1.25,
                           "restriction_alt_m": 27.5, "limiting_cell": (12.0, -3.0), "time_to_cell_s": float("inf")})
    _, key, payload, _ = inbox.get(timeout=5)
    doc = json.loads(payload)
    assert key == "companion/v1/avoidance"
    assert doc == {**doc, "schema": AVOIDANCE_SCHEMA, "engaged": True, "mode": "commanding", "climb_rate_mps": 1.25,
                   "restriction_alt_m": 27.5, "limiting_cell": [12.0, -3.0], "time_to_cell_s": None, "seq": 1}


# ------------------------------------------------------------------------------------------
# The map queryable
# ------------------------------------------------------------------------------------------


def replies(session, selector, **kw):
    out = []
    for r in session.get(selector, timeout=3.0, **kw):
        if r.ok is not None:
            out.append(("ok", str(r.ok.key_expr), r.ok.payload.to_bytes()))
        else:
            out.append(("err", None, r.err.payload.to_bytes()))
    return out


def test_late_joiner_gets_the_whole_map():
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(bus_config(listen=(ep,))) as bus:
        latest = {}
        for tx in range(-2, 3):
            for ty in range(0, 3):
                latest[(tx, ty)] = tile_bytes(tx, ty, rev=0)
                bus.publish_tile(tx, ty, latest[(tx, ty)])
        latest[(0, 1)] = tile_bytes(0, 1, rev=99)  # a tile that changed again: the newest wins
        bus.publish_tile(0, 1, latest[(0, 1)])
        ground = raw_session(connect=[ep])  # joins after everything was published
        try:
            k = BusKeys(VEHICLE)
            assert wait_for(lambda: len(replies(ground, "companion/v1/terrain/tile/**")) == len(latest))
            for selector, kw in (("companion/v1/terrain/tile/**", {}),
                                 ("companion/v1/terrain/map?_anyke", {}),
                                 ("companion/v1/terrain/map", {"accept_replies": zenoh.ReplyKeyExpr.ANY}),
                                 ("companion/v1/**", {})):
                got = replies(ground, selector, **kw)
                assert all(kind == "ok" for kind, _, _ in got), got
                assert {k.parse_tile(key): p for _, key, p in got} == latest, selector
            column = replies(ground, "companion/v1/terrain/tile/-2/*")
            assert {k.parse_tile(key) for _, key, _ in column} == {(-2, 0), (-2, 1), (-2, 2)}
            single = replies(ground, "companion/v1/terrain/tile/0/1")
            assert single == [("ok", k.tile(0, 1), latest[(0, 1)])]
            # Zenoh forbids tile-keyed replies to a plain map query: the asker is told what to do.
            plain = replies(ground, "companion/v1/terrain/map")
            assert len(plain) == 1 and plain[0][0] == "err" and b"_anyke" in plain[0][2]
            assert bus.stats().queries_answered >= 6
        finally:
            ground.close()


def test_garbage_queries_are_answered_with_errors_and_counted(linked):
    bus, ground = linked
    bus.publish_tile(1, 1, tile_bytes(1, 1))
    assert wait_for(lambda: len(replies(ground, "companion/v1/terrain/tile/**")) == 1)
    before = bus.stats()
    cases = [
        ("companion/v1/terrain/tile/**", {"payload": b"\xff\x00\x13garbage"}),
        ("companion/v1/terrain/tile/abc/def", {}),
        ("companion/v1/terrain/nonsense", {}),
        ("companion/v1/terrain/tile/1/2/3", {}),
        ("companion/v1/terrain/map", {"payload": "drop table tiles"}),
    ]
    for selector, kw in cases:
        got = replies(ground, selector, **kw)
        assert len(got) == 1 and got[0][0] == "err", (selector, got)
        assert got[0][2].startswith(b"companion: ")
    after = bus.stats()
    assert after.bad_queries - before.bad_queries == len(cases)
    assert after.query_errors == 0
    # ... and the bus still serves the map.
    assert replies(ground, "companion/v1/terrain/tile/**") == [("ok", BusKeys(VEHICLE).tile(1, 1), tile_bytes(1, 1))]


# ------------------------------------------------------------------------------------------
# Unreachable endpoints
# ------------------------------------------------------------------------------------------


def test_peer_keeps_running_through_an_absent_then_lost_listener():
    ep = f"tcp/127.0.0.1:{free_port()}"  # nobody listens here yet
    with ZenohBus(bus_config(connect=(ep,))) as bus:
        assert bus.connected
        bus.publish_tile(4, 4, tile_bytes(4, 4))  # must not raise
        bus.publish_status({"alone": True})
        ground = raw_session(listen=[ep])  # the ground station comes up later
        try:
            inbox = Inbox(ground, "companion/v1/**")
            t0 = time.monotonic()
            assert wait_for(lambda: (bus.publish_tile(4, 4, tile_bytes(4, 4)), not inbox.q.empty())[1],
                            timeout=8.0, step=0.05)
            print(f"\npeer reached a late listener after {time.monotonic() - t0:.2f} s "
                  f"(retry {bus.cfg.reconnect_min_s}-{bus.cfg.reconnect_max_s} s)")
            _, key, payload, _ = inbox.get(timeout=1)
            assert key == "companion/v1/terrain/tile/4/4" and payload == tile_bytes(4, 4)
        finally:
            ground.close()
        # The link drops (the ground station goes away) and comes back: the bus reconnects.
        bus.publish_tile(5, 5, tile_bytes(5, 5))  # nobody there: must not raise
        ground = raw_session(listen=[ep])
        try:
            inbox = Inbox(ground, "companion/v1/terrain/tile/*/*")
            assert wait_for(lambda: (bus.publish_tile(5, 5, tile_bytes(5, 5)), not inbox.q.empty())[1],
                            timeout=8.0, step=0.05)
            assert bus.stats().publish_errors == 0
        finally:
            ground.close()


def test_client_without_its_router_keeps_running_and_catches_up():
    ep = f"tcp/127.0.0.1:{free_port()}"
    # The first retry comes after 1 s so the router below has declared its subscriber by then
    # (tiles re-published on connecting reach the subscribers the router already knows).
    bus = ZenohBus(bus_config(mode="client", connect=(ep,), reconnect_min_s=1.0, reconnect_max_s=1.0))
    bus.open()  # the router is down: no exception
    try:
        assert not bus.connected
        bus.publish_tile(2, 3, tile_bytes(2, 3))  # cached, not lost
        bus.publish_status({"alone": True})
        assert bus.stats().unpublished_offline == 2
        router = raw_session(mode="router", listen=[ep])
        try:
            inbox = Inbox(router, "companion/v1/terrain/**")
            assert wait_for(lambda: bus.connected, timeout=5.0)
            # On connecting, the cached tiles are published again.
            _, key, payload, _ = inbox.get(timeout=5)
            assert key == "companion/v1/terrain/tile/2/3" and payload == tile_bytes(2, 3)
            got = replies(router, "companion/v1/terrain/tile/**")
            assert got == [("ok", key, payload)]
            assert bus.stats().open_failures >= 1
        finally:
            router.close()
    finally:
        bus.close()
    assert not bus.connected


def test_a_busy_listen_endpoint_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        bus = ZenohBus(bus_config(listen=(ep,)))
        with pytest.raises(BusError, match="cannot open"):
            bus.open()
        bus.close()


def test_async_context_manager_opens_and_closes_off_the_loop():
    ep = f"tcp/127.0.0.1:{free_port()}"

    async def main():
        async with ZenohBus(bus_config(listen=(ep,))) as bus:
            assert bus.connected
            return bus

    bus = asyncio.run(main())
    assert not bus.connected
