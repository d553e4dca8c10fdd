"""The daemon as a real process: systemd notifications, clean shutdown with the map saved and
reloaded, a camera that ends, a vehicle that dies and comes back, and the end-to-end flight
(simulated vehicle + daemon + Zenoh subscriber over loopback)."""

from __future__ import annotations

import signal
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.method.messages import TerrainPoints
from companion.method.terrain.grid import TerrainGrid
from drivers.sim.harness import MavClient, SimVehicleProcess
from drivers.sim.world import World
from tests.processes import ZenohListener, companion, free_port, stop, write_config

pytestmark = pytest.mark.slow

CIRCUIT = [[0.0, 0.0], [200.0, 0.0], [200.0, 60.0], [0.0, 60.0]]


def daemon_config(tmp: Path, link: str, **sections) -> dict:
    doc = {
        "link": {"connection": link, "heartbeat_timeout_s": 1.5, "reconnect_backoff_max_s": 0.5},
        "camera": {"source": "synthetic", "rate_hz": 15.0},
        "zenoh": {"enabled": False},
        "persistence": {"directory": str(tmp / "map"), "snapshot_interval_s": 2.0},
        "sim": {"scenario": "default", "speedup": 1.0},
    }
    for name, values in sections.items():
        doc.setdefault(name, {}).update(values)
    return doc


def notify_socket(tmp: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(tmp / "notify.sock"))
    s.settimeout(0.5)
    return s


def receive_until(sock: socket.socket, wanted: str, timeout_s: float) -> list[str]:
    seen = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            msg = sock.recv(4096).decode()
        except TimeoutError:
            continue
        seen.append(msg)
        if wanted in msg.split("\n"):
            return seen
    raise TimeoutError(f"no {wanted} within {timeout_s} s; got {seen}")


def seeded_grid() -> TerrainGrid:
    grid = TerrainGrid(1.0, 32)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-20, 60, 400), rng.uniform(-20, 60, 400), -rng.uniform(0, 5, 400)])
    grid.insert(TerrainPoints(0.0, pts, np.tile(np.diag([0.01, 0.01, 0.04]), (400, 1, 1))))
    return grid


def test_ready_watchdog_and_sigterm_saves_and_reloads_the_map(tmp_path):
    """Type=notify: READY then WATCHDOG from the control loop; SIGTERM: STOPPING, exit 0 within the unit's
    TimeoutStopSec, and the
    map (loaded from the previous snapshot) saved again, bit for bit."""
    grid = seeded_grid()
    (tmp_path / "map").mkdir()
    snapshot = tmp_path / "map" / "terrain.snapshot"
    grid.save_snapshot(snapshot)
    cfg = write_config(tmp_path / "c.yaml", daemon_config(tmp_path, f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"))
    sock = notify_socket(tmp_path)
    proc = companion("run", "--config", str(cfg), env={"NOTIFY_SOCKET": str(tmp_path / "notify.sock"),
                                                       "WATCHDOG_USEC": "1000000"}, log=tmp_path / "daemon.log")
    try:
        receive_until(sock, "READY=1", 30)
        receive_until(sock, "WATCHDOG=1", 5)
        snapshot.unlink()  # it must be written again at shutdown
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(10)
        elapsed = time.monotonic() - t0
        receive_until(sock, "STOPPING=1", 1)
    finally:
        stop(proc)
        sock.close()
    print(f"shutdown took {elapsed:.2f} s")
    # What matters is that systemd never has to kill it: the unit's TimeoutStopSec (about 2 s on an
    # idle machine, more when the cores are busy)
    unit = (Path(__file__).resolve().parents[1] / "systemd" / "companion.service").read_text()
    stop_timeout_s = float(next(line.split("=", 1)[1] for line in unit.splitlines() if line.startswith("TimeoutStopSec=")))
    assert rc == 0 and elapsed < stop_timeout_s
    log = (tmp_path / "daemon.log").read_text()
    assert f"loaded {len(grid)} tiles" in log
    reloaded = TerrainGrid.load_snapshot(snapshot)
    assert sorted(reloaded.keys()) == sorted(grid.keys())
    for key in grid.keys():
        a, b = grid.tile(key), reloaded.tile(key)
        np.testing.assert_array_equal(a.height, b.height)
        np.testing.assert_array_equal(a.variance, b.variance)
        np.testing.assert_array_equal(a.count, b.count)


def test_refuses_to_start_on_a_bad_config(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("control:\n  comanding_enabled: true\n")
    proc = companion("run", "--config", str(cfg), log=tmp_path / "daemon.log")
    assert proc.wait(30) == 2
    assert "control.comanding_enabled" in (tmp_path / "daemon.log").read_text()


def write_video(path: Path, frames: int = 12) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (640, 480), isColor=False)
    rng = np.random.default_rng(0)
    for _ in range(frames):
        writer.write(rng.integers(0, 255, (480, 640), dtype=np.uint8))
    writer.release()


def take_off(pilot: MavClient, altitude_m: float = 15.0, timeout_s: float = 40.0) -> None:
    """The operator's part (the service never arms): GUIDED, arm, take off, wait until airborne."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    pilot.wait_heartbeat(10)
    pilot.set_interval(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 10)
    assert pilot.recv("LOCAL_POSITION_NED", 20) is not None, "EKF origin never set"
    pilot.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)  # GUIDED
    ack = pilot.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack is not None and ack.result == 0
    ack = pilot.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)
    assert ack is not None and ack.result == 0
    assert pilot.recv("LOCAL_POSITION_NED", timeout_s, lambda m: -m.z > 6.0) is not None, "never got airborne"


def test_camera_end_and_vehicle_restart_keep_the_service_alive(tmp_path):
    """The recording ends: link and control loop go on and the status says so. The vehicle process is
    killed: the link is reported lost, and when a vehicle is back on the same port the daemon reconnects."""
    video = tmp_path / "short.avi"
    write_video(video)
    tcp = free_port()
    zport = free_port()
    sim_args = ["--scenario", "default", "--tcp-listen", f"127.0.0.1:{tcp}", "--origin-delay", "1"]
    cfg = write_config(tmp_path / "c.yaml", daemon_config(
        tmp_path, f"tcp:127.0.0.1:{tcp}",
        camera={"source": "file", "path": str(video), "realtime": True, "rate_hz": 15.0},
        zenoh={"enabled": True, "listen": [f"tcp/127.0.0.1:{zport}"], "status_rate_hz": 4.0},
    ))
    sim = SimVehicleProcess(sim_args, stderr_path=str(tmp_path / "sim1.log")).start()
    daemon = companion("run", "--config", str(cfg), log=tmp_path / "daemon.log")
    listener = None
    try:
        listener = ZenohListener(f"tcp/127.0.0.1:{zport}")
        ended = listener.wait_status(lambda s: s["camera"]["state"] == "ended" and s["link"]["state"] == "connected", 40)
        later = listener.wait_status(lambda s: s["control"]["ticks"] > ended["control"]["ticks"] + 10, 10)
        assert later["health"] == "degraded" and any("camera ended" in p for p in later["problems"])
        assert later["link"]["state"] == "connected"

        sim.stop()  # the vehicle dies
        lost = listener.wait_status(lambda s: s["link"]["state"] != "connected", 15)
        assert any("autopilot link" in p for p in lost["problems"])
        sim = SimVehicleProcess(sim_args, stderr_path=str(tmp_path / "sim2.log")).start()
        back = listener.wait_status(lambda s: s["link"]["state"] == "connected", 30)
        assert back["link"]["reconnects"] >= 1 or back["link"]["connects"] >= 2
        assert daemon.poll() is None
    finally:
        if listener:
            listener.close()
        assert stop(daemon) == 0
        sim.stop()


# The simulated time's speed-up of the flights below. They fly in lockstep (docs/sim.md, "Lockstep"):
# the simulator's clock waits for the frames the service has not mapped yet, so a machine busy with
# the rest of the suite slows the flight instead of blinding it, and what the tests measure (the
# climb before the building, the map's errors against its sigmas) does not depend on the load.
FLIGHT_SPEEDUP = 3.0


def start_flight(tmp: Path, *daemon_args: str, camera: str = "synthetic", **sections):
    """A simulated vehicle with an operator's pymavlink link, and the daemon commanding the circuit,
    at ``FLIGHT_SPEEDUP`` at most, in lockstep through ``tmp/clock``.

    camera: "synthetic" (rendered in the daemon from SIM_STATE) or "stream" (rendered by the simulator
    process and sent over TCP, stamped in the autopilot's time: ``companion sim --camera-listen``)."""
    pilot = MavClient.udp_listener()
    clock = tmp / "clock"
    extra = ["--camera-listen", "127.0.0.1:0", "--camera-rate", "15"] if camera == "stream" else []
    sim = SimVehicleProcess(["--scenario", "default", "--tcp-listen", "127.0.0.1:0",
                             "--udp-out", f"127.0.0.1:{pilot.port}", "--speedup", str(FLIGHT_SPEEDUP), "--origin-delay", "1",
                             "--clock-file", str(clock), *extra], stderr_path=str(tmp / "sim.log")).start()
    if camera == "stream":
        sections["camera"] = {"source": "stream", "stream_address": f"127.0.0.1:{sim.endpoints['camera']}",
                              **sections.get("camera", {})}
    cfg = write_config(tmp / "c.yaml", daemon_config(
        tmp, f"tcp:127.0.0.1:{sim.endpoints['tcp']}",
        control={"commanding_enabled": True, "waypoints_ne_m": CIRCUIT, "cruise_speed_mps": 6.0},
        sim={"scenario": "default", "speedup": FLIGHT_SPEEDUP, "clock_file": str(clock)}, **sections,
    ))
    daemon = companion("run", "--config", str(cfg), *daemon_args, log=tmp / "daemon.log")
    return pilot, sim, daemon


def end_flight(listener, daemon, sim, pilot) -> int:
    """Close the subscriber, stop the daemon (its exit status), the simulator and the operator's link."""
    if listener:
        listener.close()
    rc = stop(daemon)
    sim.stop()
    pilot.close()
    return rc


def known_cells(tiles: dict) -> int:
    return sum(int(np.count_nonzero(tile.count > 0)) for tile in list(tiles.values()))


@pytest.mark.parametrize("camera", ["synthetic", "stream"])
def test_end_to_end_flight_maps_the_building_and_climbs_before_it(tmp_path, camera):
    """Simulated vehicle + daemon + Zenoh subscriber, all real processes on loopback. The vehicle flies the
    default circuit's first leg toward the 12 m building; the daemon maps it and commands a climb before
    reaching it; the subscriber's tiles agree with the world. With the camera rendered in the daemon
    (synthetic) and in the simulator, its frames sent over TCP stamped in the autopilot's time (stream)."""
    world = World.load("default")
    building = next(o for o in world.obstacles if o.name == "building")
    zport = free_port()
    pilot, sim, daemon = start_flight(tmp_path, camera=camera,
                                      zenoh={"enabled": True, "listen": [f"tcp/127.0.0.1:{zport}"], "status_rate_hz": 2.0})
    listener = None
    try:
        listener = ZenohListener(f"tcp/127.0.0.1:{zport}")
        take_off(pilot)
        early_climb = None
        south_wall = building.footprint_ne_m[:, 0].min()
        track = []
        limited = []  # avoidance messages carrying the camera's view distance
        deadline = time.monotonic() + 180  # wall time; in lockstep a busy machine slows the flight
        north = alt = 0.0
        while time.monotonic() < deadline:
            msg = pilot.recv("LOCAL_POSITION_NED", 1.0)
            if msg is not None:
                north, alt = msg.x, -msg.z
            while not listener.avoidance.empty():
                a = listener.avoidance.get()
                cell = a.get("limiting_cell")
                track.append((round(north, 1), round(alt, 1), a["engaged"], cell, a["climb_rate_mps"], a["reason"]))
                if a.get("view_distance_m") is not None:
                    limited.append(a)
                # A climb for the building: the limiting cell is tall and lies on the building (grown by the
                # grid's spreading of a point's horizontal uncertainty), the vehicle still short of it.
                if (early_climb is None and a["engaged"] and cell is not None and a["climb_rate_mps"] > 0.5
                        and (a["limiting_height_m"] or 0.0) > 5.0 and north < south_wall
                        and south_wall - 6 <= cell[0] <= building.footprint_ne_m[:, 0].max() + 6):
                    early_climb = (north, alt, a)
            if north > building.footprint_ne_m[:, 0].max() + 5:
                break
        # Enough mapped cells for the comparison below: the vehicle flies on along the leg until the
        # subscriber holds them.
        enough = time.monotonic() + 60
        while known_cells(listener.tiles) < 280 and time.monotonic() < enough:
            pilot.recv("LOCAL_POSITION_NED", 0.5)
        # A tile whose first samples were deltas (published before this subscriber connected) is asked
        # for whole, as a ground station does.
        listener.complete()
        status = listener.latest_status()
    finally:
        rc = end_flight(listener, daemon, sim, pilot)
    assert rc == 0
    print("\n".join(map(str, track[::20])))
    assert early_climb is not None, "no climb commanded for the building before reaching it"
    # The camera's view limit is published with the speed limit it takes part in (docs/zenoh.md).
    assert limited, "no avoidance message carried the camera's view distance"
    for a in limited:  # the view limit (avoidance.view_speed_limit, on by default) bounds the speed limit
        assert a["view_distance_m"] > 0 and a["view_speed_limit_mps"] > 0
        assert a["speed_limit_mps"] <= a["view_speed_limit_mps"] + 1e-3
        # the known horizon (on by default) is published beside it: a distance along track, or null
        assert "known_horizon_m" in a and (a["known_horizon_m"] is None or a["known_horizon_m"] >= 0.0)
    assert any(a["known_horizon_m"] is not None for a in limited)
    # The ground the nominal altitude stands on (docs/avoidance.md): the mapped ground's median
    # height around the vehicle, within avoidance.ground_reference_max_m (3 m) of the local zero,
    # and found once the ground below is mapped.
    grounds = [a["ground_reference_m"] for a in limited if a["ground_reference_m"] is not None]
    assert grounds and all(abs(g) <= 3.0 + 1e-6 for g in grounds)
    assert any(g != 0.0 for g in grounds), "the ground reference never found ten mapped cells around the vehicle"
    assert set(status["avoidance"]) >= {"speed_limit_mps", "view_distance_m", "view_speed_limit_mps", "known_horizon_m",
                                        "ground_reference_m"}
    if camera == "synthetic":
        # Frames rendered at SIM_STATE's truth are timed by the attitude it followed in the same
        # simulator step, not by its arrival (docs/mavlink.md, "Simulator truth").
        truth = status["truth"]
        print(f"truth: {truth['paired']} SIM_STATE paired with their attitude, {truth['arrival']} timed on arrival")
        assert truth["time_source"] == "ATTITUDE_QUATERNION" and truth["paired"] > 50 * max(truth["arrival"], 1)
    # Where the map lies on the Earth: the EKF origin the simulated ArduPilot reported, and its projection.
    frame = status["frame"]
    assert frame["projection"] == "ardupilot" and frame["axes"] == "NED"
    assert frame["origin"]["source"] == "GPS_GLOBAL_ORIGIN"
    assert (frame["origin"]["lat_deg"], frame["origin"]["lon_deg"], frame["origin"]["alt_m"]) == pytest.approx(
        (world.home.lat_deg, world.home.lon_deg, world.home.alt_m), abs=1e-6)
    print(f"climb commanded at north {early_climb[0]:.1f} m (building starts at "
          f"{building.footprint_ne_m[:, 0].min():.0f} m), altitude {early_climb[1]:.1f} m: {early_climb[2]}")
    # The subscriber's tiles against the world's true heights.
    errors, sigmas = [], []
    assert not listener.missing  # a delta that found no base here was asked for whole (listener.complete)
    for tile in listener.tiles.values():
        n = tile.height.shape[0]
        ii, jj = np.nonzero(tile.count > 0)
        north_m = (tile.tx * n + ii + 0.5) * tile.cell_size_m
        east_m = (tile.ty * n + jj + 0.5) * tile.cell_size_m
        # A 1 m cell cannot hold a vertical wall: cells within 2 m of a structure's edge may carry
        # either height, so they are left out of the comparison (the wall is judged by the climb above).
        near_edge = (world.terrain_height(north_m, east_m) != world.terrain_height(north_m + 2, east_m)) | \
                    (world.terrain_height(north_m, east_m) != world.terrain_height(north_m - 2, east_m)) | \
                    (world.terrain_height(north_m, east_m) != world.terrain_height(north_m, east_m + 2)) | \
                    (world.terrain_height(north_m, east_m) != world.terrain_height(north_m, east_m - 2))
        keep = ~near_edge
        errors.append(tile.height[ii, jj][keep] - world.terrain_height(north_m[keep], east_m[keep]))
        sigmas.append(np.sqrt(tile.variance[ii, jj][keep]))
    err, sigma = np.concatenate(errors), np.concatenate(sigmas)
    print(f"{len(listener.tiles)} tiles, {err.size} cells: median |error| {np.median(np.abs(err)):.2f} m, "
          f"90th percentile {np.percentile(np.abs(err), 90):.2f} m; control {status['control']}; "
          f"frames mapped {status['mapper']['frames_mapped']}, dropped {status['camera']['queue_dropped']}")
    assert err.size > 200
    # The dense flow (on by default) ran in its own thread on the same frames: it measured frames,
    # ranged lattice points on them, and failed on none. In lockstep neither the mapper's queue nor the
    # flow's dropped a frame, however busy the machine.
    flow = status["mapper"]["flow"]
    print(f"dense flow: {flow['frames_measured']} frames measured, {flow['ranged']} points ranged, {flow['floors']} floors, "
          f"{flow['surface_inserted']} flat-surface heights in the map, "
          f"step {flow['step_ms']}, capture -> map {flow['frame_to_map_ms']}, dropped {flow['queue_dropped']}")
    assert status["camera"]["queue_dropped"] == 0 and flow["queue_dropped"] == 0
    assert flow["on"] and flow["errors"] == 0 and flow["frames_measured"] > 0 and flow["ranged"] > 0
    # The flat ground it ranged went to the map (a cell goes there after three looks in six measured frames).
    assert flow["surface_inserted"] > 0
    assert flow["thread_nice"] >= 10  # below the mapper's thread (mapper.flow_thread_nice)
    # the filter's consistency, as the operator reads it in the status (docs/replay.md, "Filter consistency")
    nis = status["mapper"]["innovation_nis_mean"]
    print(f"mean innovation squared of the corner updates {nis} (2 = consistent)")
    assert nis is not None and 0.0 < nis < 9.21
    # Against the truth the map carries the navigation error of the pass: the simulator injects a
    # slowly varying error (0.8 m vertical sigma, smooth attitude error; drivers/sim/navigation_error.py),
    # common to the points of a few seconds. Its shape (spread about the common offset) is the mapper's,
    # and each cell says how far to trust it: its published sigma, so the spread is judged in each
    # cell's own sigmas: for errors as wide as the sigmas claim the median |z| is 0.67. In lockstep, with
    # two other flights running beside it, this flight gave 0.75 and 0.76 (synthetic, stream camera);
    # wall-paced, a machine too busy to map every frame gave 1.26. The bound: cells no more than 1.5
    # times as sure as their errors.
    bias = np.median(err)
    z = (err - bias) / sigma
    print(f"offset {bias:+.2f} m, spread about it: median {np.median(np.abs(err - bias)):.2f} m, "
          f"median |z| {np.median(np.abs(z)):.2f}, 99th percentile {np.percentile(np.abs(z), 99):.1f}")
    assert abs(bias) < 2 * 0.8
    assert np.median(np.abs(z)) < 1.0
    assert np.median(np.abs(err - bias)) < 1.0
    assert np.percentile(np.abs(err), 90) < 2.0


def grid_cells(grid: TerrainGrid) -> dict[tuple[int, int], float]:
    """{(north index, east index): height} of every cell with evidence."""
    cells = {}
    for tile in grid.tiles():
        n = tile.height.shape[0]
        for i, j in zip(*np.nonzero(tile.count > 0)):
            cells[(tile.tx * n + int(i), tile.ty * n + int(j))] = float(tile.height[i, j])
    return cells


def recorded_frames(rec: Path) -> int:
    index = rec / "frames.csv"
    return max(len(index.read_text().splitlines()) - 1, 0) if index.exists() else 0


def test_recorded_flight_replays_to_the_same_map_also_after_tum_export(tmp_path):
    """`companion run --record DIR` during a real (simulated) flight, then the documented commands:
    `companion replay DIR`, `companion replay DIR --export-tum TUM`, `companion replay TUM`. The TUM
    replay gives the recording's map exactly; the replay agrees with the live map on the cells both have."""
    rec = tmp_path / "rec"
    pilot, sim, daemon = start_flight(tmp_path, "--record", str(rec))
    try:
        take_off(pilot)
        pilot.recv("LOCAL_POSITION_NED", 60, lambda m: m.x > 60.0)
        # Fly on until the recording holds enough of the camera's frames.
        enough = time.monotonic() + 60
        while recorded_frames(rec) <= 100 and time.monotonic() < enough:
            pilot.recv("LOCAL_POSITION_NED", 0.5)
    finally:
        rc = stop(daemon)
        sim.stop()
        pilot.close()
    assert rc == 0
    frames = recorded_frames(rec)
    assert frames > 100 and (rec / "telemetry.tlog").stat().st_size > 10_000

    for args in (["replay", str(rec), "--output", str(tmp_path / "replay"), "--no-progress"],
                 ["replay", str(rec), "--export-tum", str(tmp_path / "tum")],
                 ["replay", str(tmp_path / "tum"), "--output", str(tmp_path / "replay_tum"), "--no-progress"]):
        proc = companion(*args, log=tmp_path / "replay.log")
        assert proc.wait(180) == 0, (tmp_path / "replay.log").read_text()[-2000:]

    live = grid_cells(TerrainGrid.load_snapshot(tmp_path / "map" / "terrain.snapshot"))
    replayed = grid_cells(TerrainGrid.load_snapshot(tmp_path / "replay" / "terrain.snapshot"))
    from_tum = grid_cells(TerrainGrid.load_snapshot(tmp_path / "replay_tum" / "terrain.snapshot"))
    assert replayed.keys() == from_tum.keys()
    assert max(abs(replayed[k] - from_tum[k]) for k in replayed) < 0.01
    common = live.keys() & replayed.keys()
    diff = np.array([replayed[k] - live[k] for k in common])
    print(f"{frames} frames recorded; live map {len(live)} cells, replay {len(replayed)} cells, {len(common)} in common; "
          f"median |replay - live| {np.median(np.abs(diff)):.3f} m, 90th percentile {np.percentile(np.abs(diff), 90):.3f} m")
    assert len(common) > 0.6 * min(len(live), len(replayed))
    assert np.median(np.abs(diff)) < 0.3


def test_a_wall_another_vehicle_mapped_makes_the_law_climb_before_the_camera_sees_it(tmp_path):
    """The daemon reads other vehicles' maps (``zenoh.share_from: ["*"]``). A second vehicle on the
    same Zenoh network ("scout", same EKF origin) publishes a 30 m wall 40 m up the circuit's first
    leg, where the world has flat ground: the daemon's law climbs for it before the vehicle gets
    there, the wall it publishes itself is not in its own map, and its status names the source."""
    from companion.config import ZenohConfig
    from companion.method.terrain.codec import encode_tile
    from companion.method.terrain.tile import Tile
    from drivers.zenoh_bus import ZenohBus

    zport = free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    pilot, sim, daemon = start_flight(tmp_path, zenoh={"enabled": True, "listen": [endpoint], "status_rate_hz": 2.0,
                                                            "share_from": ["*"]})
    listener = scout = None
    found = None
    try:
        listener = ZenohListener(endpoint)
        scout = ZenohBus(ZenohConfig(mode="peer", connect=(endpoint,), vehicle_name="scout", multicast_scouting=False,
                                     reconnect_min_s=0.2, reconnect_max_s=0.5))
        scout.open()
        origin = listener.wait_status(lambda s: (s.get("frame") or {}).get("origin") is not None, 30.0)["frame"]
        h = np.full((32, 32), np.nan, np.float32)
        v = np.full((32, 32), np.inf, np.float32)
        n = np.zeros((32, 32), np.uint32)
        h[8:10], v[8:10], n[8:10] = 30.0, 0.1, 6  # north 40-41
        for ty in (-1, 0):  # east -32..31
            scout.publish_tile(1, ty, encode_tile(Tile(1, ty, h, v, n, cell_size_m=1.0), deflate=True))
        take_off(pilot)
        deadline = time.monotonic() + 60
        north = 0.0
        while time.monotonic() < deadline and north < 40.0:
            scout.publish_status({"frame": origin})  # its origin is the daemon's: offset zero
            msg = pilot.recv("LOCAL_POSITION_NED", 0.5)
            if msg is not None:
                north = msg.x
            while not listener.avoidance.empty():
                a = listener.avoidance.get()
                cell = a.get("limiting_cell")
                if (found is None and a["engaged"] and cell is not None and 39.0 <= cell[0] <= 42.0
                        and (a.get("limiting_height_m") or 0.0) > 25.0 and a["climb_rate_mps"] > 0.5 and north < 39.0):
                    found = (round(north, 1), a)
        listener.complete()  # tiles first heard as deltas, asked for whole
        status = listener.latest_status()
    finally:
        if scout is not None:
            scout.close()
        rc = end_flight(listener, daemon, sim, pilot)
    assert rc == 0
    assert found is not None, "no climb for the shared wall before reaching it"
    print(f"\nclimbing for the scout's 30 m wall at north {found[0]} m: {found[1]['limiting_height_m']} m, "
          f"{found[1]['climb_rate_mps']} m/s")
    assert status["sharing"]["sources"] == ["scout"] and status["sharing"]["tiles_applied"] >= 2
    # Its own published map never takes the scout's wall in: no cell of it holds the wall's 30 m.
    assert status["map"]["cells"] > 0
    copied = [k for k, tile in listener.tiles.items() if np.any(np.abs(tile.height - 30.0) < 0.01)]
    tall = {k: round(float(np.nanmax(tile.height)), 1) for k, tile in listener.tiles.items()
            if np.nanmax(tile.height, initial=-1.0) > 5.0}
    print(f"own tiles with cells above 5 m over the flat ground (the climb's pitch): {tall}")
    assert not copied
