"""The ground station's live map in a real browser: a vehicle's bus on loopback publishes tiles,
status and avoidance; ``companion ground``'s station and web server follow it; Debian's Chromium,
driven by Playwright, opens the page and we check what a person would see (pixels and text), then
publish a new tile and wait for its pixels without reloading the page.

The browser is the system's ``chromium`` (``.ci/run`` installs Debian's package where it is
missing); Playwright comes with the test extra. Without either the test says which is missing
and how to get it.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
import base64
import contextlib
import urllib.error
import urllib.request

import numpy as np
import pytest

from companion.config import ZenohConfig
from companion.method.terrain.codec import encode_tile
from companion.method.terrain.tile import Tile
from drivers.ground_station import GroundStation
from drivers.ground_web import LiveFeed, MapWebServer
from drivers.zenoh_bus import ZenohBus
from tests.processes import free_port

T, CELL = 8, 2.0
SIDE = T * CELL  # a tile covers 16 m x 16 m
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def cfg(**kw) -> ZenohConfig:
    base = dict(mode="peer", multicast_scouting=False, vehicle_name="v1", reconnect_min_s=0.2, reconnect_max_s=0.5)
    return ZenohConfig(**{**base, **kw})


def tile(tx: int, ty: int, height: float, known_rows: int = T) -> Tile:
    """Every cell at ``height``; only the southern ``known_rows`` rows hold evidence."""
    known = np.zeros((T, T), bool)
    known[:known_rows] = True
    return Tile(tx, ty, np.where(known, height, np.nan).astype(np.float32), np.where(known, 0.25, np.inf).astype(np.float32),
                np.where(known, 3, 0).astype(np.uint32), cell_size_m=CELL)


STATUS = {"health": "ok", "problems": [], "link": {"link": {"state": "connected"}},
          "nav": {"covariance_source": "EKF_STATUS_REPORT", "age_s": 0.02}, "camera": {"state": "ok"},
          "mapper": {"frames_mapped": 120, "points_converged": 64}}
AVOIDANCE = {"engaged": True, "mode": "advisory", "climb_rate_mps": 1.5, "restriction_alt_m": 25.0,
             "limiting_cell": [3.0, 26.0], "speed_limit_mps": 4.2, "position_ned_m": [2.0, 2.0, -15.0],
             "velocity_ned_mps": [5.0, 0.0, 0.0]}


@pytest.fixture
def browser():
    if CHROMIUM is None:
        pytest.skip("no Chromium on this machine: the page is checked in a real browser "
                    "(Debian: apt-get install chromium; .ci/run installs it where it is missing)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright is not installed: pip install -e '.[test]' (it drives the system's Chromium)")
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        try:
            yield b
        finally:
            b.close()


@contextlib.contextmanager
def served_page(browser, station_cfg: ZenohConfig, tiles: int, vehicles: tuple[str, ...] | None = None):
    """A ground station (on its own thread, as ``companion ground --http`` runs it) serving the page,
    and the page open in the browser once it shows ``tiles`` tiles: yields (page, server)."""
    feed = LiveFeed("test")
    web = MapWebServer(feed, "127.0.0.1", 0).start()
    stop = threading.Event()
    with GroundStation(station_cfg, vehicles=vehicles) as station:
        runner = threading.Thread(target=station.run, kwargs=dict(summary_every_s=0, stop=stop, feed=feed, tick_s=0.02))
        runner.start()
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            page.goto(web.url)
            page.wait_for_function(f"window.companionMap && companionMap.tiles() === {tiles}", timeout=15_000)
            yield page, web
        finally:
            stop.set()
            runner.join(10)
            web.close()


def test_the_page_draws_the_map_lists_the_vehicle_and_follows_new_tiles(browser):
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus(cfg(listen=(ep,))) as bus:
        for t in (tile(0, 0, 0.0), tile(0, 1, 10.0), tile(1, 0, 5.0, known_rows=T // 2)):
            bus.publish_tile(t.tx, t.ty, encode_tile(t))
        with served_page(browser, cfg(connect=(ep,)), tiles=3) as (page, web):
            # Status and avoidance are published after the page is up: they reach it live, each
            # on its own (the station may hand them over in separate batches), so wait for both.
            def live() -> bool:
                return page.text_content("#engaged") == "ENGAGED" and page.text_content("#health") == "ok"

            deadline = time.monotonic() + 15
            while not live() and time.monotonic() < deadline:
                bus.publish_status(STATUS)
                bus.publish_avoidance(AVOIDANCE)
                time.sleep(0.1)
            page.evaluate("window.__sameDocument = true")

            def colour(north, east):
                return np.array(page.evaluate(f"companionMap.colourAt({north}, {east})"), float)

            def expected(h):
                return np.array(page.evaluate(f"companionMap.heightColour({h})"), float)

            # Heights in colour: the lowest tile at the ramp's low end, the highest at its top,
            # the half-known tile's known half at 5 m, its unknown half a grey checker.
            assert page.evaluate("companionMap.range()") == [0, 10]
            assert np.abs(colour(0.5 * SIDE, 0.5 * SIDE) - expected(0.0)).max() <= 2
            assert np.abs(colour(0.75 * SIDE, 1.5 * SIDE) - expected(10.0)).max() <= 2
            assert np.abs(colour(1.2 * SIDE, 0.5 * SIDE) - expected(5.0)).max() <= 2
            grey = colour(1.8 * SIDE, 0.5 * SIDE)
            assert grey[0] == grey[1] == grey[2] and grey[0] in (140.0, 166.0)
            assert colour(0.5 * SIDE, 0.5 * SIDE)[2] > colour(0.5 * SIDE, 0.5 * SIDE)[0]  # low: blue
            assert colour(0.75 * SIDE, 1.5 * SIDE)[0] > colour(0.75 * SIDE, 1.5 * SIDE)[2]  # high: red
            # The vehicle: named, healthy, linked, avoiding; drawn (white) where it is.
            assert page.text_content("#vehicle") == "v1"
            assert page.text_content("#health") == "ok" and page.text_content("#link") == "connected"
            assert "EKF_STATUS_REPORT" in page.text_content("#nav") and "4.2 m/s" in page.text_content("#speed")
            assert (colour(2.0, 2.0) >= 240).all()
            assert "v1: 3 tiles" in page.text_content("#sources")

            # A new tile: its pixels appear without a reload.
            new = tile(1, 1, 7.5)
            t0 = time.monotonic()
            bus.publish_tile(1, 1, encode_tile(new))
            page.wait_for_function(
                f"""() => {{
                    if (companionMap.tiles() !== 4) return false;
                    const c = companionMap.colourAt({1.5 * SIDE}, {1.5 * SIDE}), e = companionMap.heightColour(7.5);
                    return c.every((v, k) => Math.abs(v - e[k]) <= 2);
                }}""", polling="raf", timeout=10_000)
            latency_ms = 1000 * (time.monotonic() - t0)
            assert page.evaluate("window.__sameDocument === true")
            print(f"\ntile published -> its pixels in the browser: {latency_ms:.0f} ms")
            assert latency_ms < 10_000

            # The same snapshot for scripts.
            state = json.loads(urllib.request.urlopen(web.url + "state.json", timeout=5).read())
            assert list(state["vehicles"]) == ["v1"] and len(state["tiles"]) == 4 and state["browsers"] == 1
            v1 = state["vehicles"]["v1"]
            assert v1["avoidance"]["engaged"] is True and v1["track"] == [[2.0, 2.0]] and v1["offset_m"] == [0.0, 0.0, 0.0]


def test_the_server_answers_unknown_paths_with_404_and_streams_a_snapshot_to_late_browsers():
    """Without a browser: a late subscriber to /events gets every tile already seen, then changes."""
    from drivers.ground_station import GroundMap

    gmap = GroundMap("v1")
    feed = LiveFeed("v1")
    web = MapWebServer(feed, "127.0.0.1", 0).start()
    try:
        assert gmap.apply(gmap.keys.tile(0, 0), encode_tile(tile(0, 0, 3.0)))
        assert feed.update_from(gmap) == 2  # the vehicle's frame (first seen: at the origin), the tile
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(web.url + "nothing-here", timeout=5)
        assert err.value.code == 404
        stream = urllib.request.urlopen(web.url + "events", timeout=5)
        assert stream.headers["Content-Type"] == "text/event-stream"
        lines = []
        while len([ln for ln in lines if ln.startswith(b"event: ")]) < 3:  # hello, the vehicle's frame, the tile
            lines.append(stream.readline().strip())
        lines.append(stream.readline().strip())  # the tile's data line
        events = [ln.split(b": ", 1)[1] for ln in lines if ln.startswith(b"event: ")]
        assert events == [b"hello", b"frame", b"tile"]
        data = json.loads(lines[lines.index(b"event: tile") + 1].split(b": ", 1)[1])
        h = np.frombuffer(base64.b64decode(data["height"]), "<f4").reshape(T, T)
        assert (data["tx"], data["ty"], data["cells"], data["cell_m"]) == (0, 0, T, CELL) and np.all(h == 3.0)
        # A change reaches the open stream.
        assert gmap.apply(gmap.keys.tile(2, 0), encode_tile(tile(2, 0, 4.0, known_rows=1)))
        feed.update_from(gmap)
        while not (line := stream.readline().strip()).startswith(b"event: "):
            pass
        assert line == b"event: tile"
        data = json.loads(stream.readline().strip().split(b": ", 1)[1])
        h = np.frombuffer(base64.b64decode(data["height"]), "<f4").reshape(T, T)
        assert data["tx"] == 2 and np.all(h[0] == 4.0) and np.isnan(h[1:]).all()
        stream.close()
    finally:
        web.close()


ORIGIN = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_m": 488.0, "source": "GPS_GLOBAL_ORIGIN"}
NORTH_300_M = 300.0 / 111_194.9  # degrees of latitude in 300 m (sphere of radius 6,371 km)


def test_the_page_shows_a_fleet_through_a_router_each_vehicle_in_its_place(browser):
    """Two vehicles whose EKF origins are 300 m apart publish through ``companion router``; a ground
    station following every vehicle (``--all-vehicles``) serves the page. Each vehicle's tiles are
    in its own frame: the page places the second vehicle's, from the two origins in their statuses,
    300 m north of the first's, and lists both; the second is drawn only once its origin is known.
    Each map has moved to follow its vehicle's navigation (``map.frame_shift_m`` in the status,
    -0.5 m and +1.5 m): the tiles, published in each map's own frame, are drawn raised by it."""
    from benchmarks.fleet_bench import Router

    router = Router()
    client = dict(mode="client", connect=(router.endpoint,))
    try:
        with ZenohBus(cfg(vehicle_name="v1", **client)) as v1, ZenohBus(cfg(vehicle_name="v2", **client)) as v2:
            v1.publish_tile(0, 0, encode_tile(tile(0, 0, 0.0), deflate=True))
            v2.publish_tile(0, 0, encode_tile(tile(0, 0, 10.0), deflate=True))
            with served_page(browser, cfg(**client), tiles=2, vehicles=("*",)) as (page, _):
                assert page.evaluate("companionMap.offset('v2')") is None  # no origin yet: not drawn
                assert "not placed yet" in page.text_content("#fleet")
                deadline = time.monotonic() + 15
                while page.evaluate("companionMap.offset('v2')") is None and time.monotonic() < deadline:
                    v1.publish_status({**STATUS, "frame": {"axes": "NED", "origin": ORIGIN, "projection": "ardupilot"},
                                       "map": {"frame_shift_m": -0.5}})
                    v2.publish_status({**STATUS, "frame": {"axes": "NED", "projection": "ardupilot",
                                                           "origin": {**ORIGIN, "lat_deg": ORIGIN["lat_deg"] + NORTH_300_M}},
                                       "map": {"frame_shift_m": 1.5}})
                    time.sleep(0.1)
                offset = page.evaluate("companionMap.offset('v2')")
                assert offset[0] == pytest.approx(300.0, abs=1.0) and abs(offset[1]) < 0.01 and abs(offset[2] - 1.5) < 0.05
                page.wait_for_function("companionMap.offset('v1')[2] === -0.5 && companionMap.range()[1] >= 11", timeout=5_000)

                def colour(north, east):
                    return np.array(page.evaluate(f"companionMap.colourAt({north}, {east})"), float)

                def expected(h):
                    return np.array(page.evaluate(f"companionMap.heightColour({h})"), float)

                assert np.abs(colour(0.5 * SIDE, 0.5 * SIDE) - expected(-0.5)).max() <= 2          # v1's tile at home
                assert np.abs(colour(offset[0] + 0.5 * SIDE, 0.5 * SIDE) - expected(10.0 + offset[2])).max() <= 2  # v2's, 300 m north
                assert (colour(150.0, 0.5 * SIDE) < 60).all()                                         # nothing between
                assert page.evaluate("companionMap.vehicles()") == ["v1", "v2"]
                assert "v1: 1 tiles" in page.text_content("#sources") and "v2: 1 tiles" in page.text_content("#sources")
                page.click("#fleet .pick[data-vehicle='v2']")
                assert page.text_content("#vehicle") == "v2" and page.text_content("#health") == "ok"
    finally:
        router.close()
