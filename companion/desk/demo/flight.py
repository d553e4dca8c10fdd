"""One closed-loop run of the demo: the simulated vehicle and the service as processes, the pilot and
the ground station in this process; the loop that follows the truth and the map, cuts laps and keeps
each lap's map, and the orderly stop (the service must save its map and exit within a few seconds)."""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from companion.desk import report
from companion.desk.demo.pilot import DemoError, Pilot, TruthLog
from companion.desk.demo.progress import Progress, progress_line

LAP_RADIUS_M = 10.0            # a waypoint is visited when the truth passes this close
STARTUP_WALL_S = 60.0          # processes up, link connected, camera running
STALL_WALL_S = 30.0            # simulated time not moving this long ends the run (a stopped simulator or a held clock)
STOP_WALL_S = 10.0             # SIGTERM to exit


@dataclass
class RunRecord:
    """Everything one run produced that the report needs."""

    parameterisation: str
    truth: TruthLog
    lap_ends: list[int] = field(default_factory=list)          # truth index of each lap's end
    lap_maps: list[report.MapRaster] = field(default_factory=list)
    service_laps: list[float] = field(default_factory=list)    # sim times the service's lap count rose
    detection: list[tuple[float, float]] = field(default_factory=list)  # (sim t, mapped obstacle height)
    final_map: report.MapRaster = field(default_factory=report.MapRaster.empty)
    status: dict[str, Any] | None = None
    engaged_time_s: float = 0.0
    wall_s: float = 0.0
    complete: bool = False
    problem: str = ""
    daemon_exit: dict[str, Any] = field(default_factory=dict)
    sim_exit: dict[str, Any] = field(default_factory=dict)
    ground: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] | None = None                      # the demo's options (a record read back)


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def daemon_config(world, opts, parameterisation: str, tcp_port: int, zenoh_port: int, map_dir: Path) -> dict:
    """The service's configuration for one run (written to ``<run>/daemon.yaml``): what the scenario's
    circuit implies (companion/desk/quality/scenarios.py, shared with the scenario suite), the demo's
    own links and folders, then the scenario's ``service:`` settings, ``--config`` and ``--set``."""
    from companion.desk.quality.scenarios import circuit_settings, merge_layers

    data = circuit_settings(world, opts.scenario, parameterisation, int(opts.seed), float(opts.camera_rate))
    data["link"] = {"connection": f"tcp:127.0.0.1:{tcp_port}"}
    data["zenoh"] = {"mode": "peer", "listen": [f"tcp/127.0.0.1:{zenoh_port}"], "vehicle_name": "demo"}
    data["persistence"] = {"directory": str(map_dir)}
    data["sim"]["speedup"] = float(opts.speedup)
    if not getattr(opts, "no_lockstep", False):
        data["sim"]["clock_file"] = str(map_dir.parent / "clock")  # created by the run's simulator
    if opts.no_avoid:
        data["avoidance"]["enabled"] = False
    service = ((f"scenario {world.name!r} service", world.service),) if world.service else ()
    return merge_layers(data, (*service, *getattr(opts, "overrides", ())))


def _stop(proc: subprocess.Popen | None, timeout_s: float) -> dict[str, Any]:
    """SIGTERM, wait; kill if it does not end. Returns exit status and the time it took."""
    if proc is None:
        return {"returncode": None, "stop_wall_s": None, "killed": False}
    t0 = time.monotonic()
    killed = False
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
            killed = True
    return {"returncode": proc.returncode, "stop_wall_s": round(time.monotonic() - t0, 2), "killed": killed}


def _sim_slips(log_path: Path) -> int:
    """How often the simulator fell behind its clock (its log says so)."""
    try:
        text = log_path.read_text(errors="replace")
    except OSError:
        return -1
    slips = 0
    for line in text.splitlines():
        if "slips" in line and "stopped at" in line:
            words = line.replace(",", " ").split()
            for i, w in enumerate(words):
                if w == "slips" and i > 0 and words[i - 1].isdigit():
                    slips = int(words[i - 1])
    return slips


def run_closed_loop(parameterisation: str, opts, world, obstacle, run_dir: Path, progress: Progress) -> RunRecord:
    """Fly ``opts.laps`` laps with one parameterisation; returns the record (complete or not)."""
    from companion.config import ZenohConfig
    from drivers.ground_station import GroundStation
    from drivers.sim.harness import SimVehicleProcess
    from drivers.sim.vehicle import home_from_scenario

    run_dir.mkdir(parents=True, exist_ok=True)
    map_dir = run_dir / "map"
    if map_dir.exists():
        shutil.rmtree(map_dir)  # a fresh map for every run: the demo owns this folder
    wall0 = time.monotonic()
    pilot = Pilot(home_from_scenario(opts.scenario))
    record = RunRecord(parameterisation, pilot.truth)
    sim = daemon = station = web = feed = None
    daemon_log = None
    try:
        sim = SimVehicleProcess([
            "--scenario", opts.scenario, "--tcp-listen", "127.0.0.1:0", "--udp-out", f"127.0.0.1:{pilot.port}",
            "--speedup", f"{opts.speedup:g}", "--origin-delay", "2", "--seed", str(opts.seed),
            *(() if getattr(opts, "no_lockstep", False) else ("--clock-file", str(run_dir / "clock"))),
        ], stderr_path=str(run_dir / "sim.log")).start()
        zenoh_port = free_tcp_port()
        cfg = daemon_config(world, opts, parameterisation, sim.endpoints["tcp"], zenoh_port, map_dir)
        (run_dir / "daemon.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        daemon_log = open(run_dir / "daemon.log", "w")  # noqa: SIM115 - closed in finally
        daemon = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "--config", str(run_dir / "daemon.yaml")],
                                  stdout=daemon_log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        station = GroundStation(ZenohConfig(mode="peer", connect=(f"tcp/127.0.0.1:{zenoh_port}",), vehicle_name="demo",
                                            reconnect_min_s=0.2, reconnect_max_s=1.0))
        station.open()
        if getattr(opts, "http", None):
            from drivers.ground_web import LiveFeed, MapWebServer, parse_address

            feed = LiveFeed("demo")
            try:
                web = MapWebServer(feed, *parse_address(opts.http)).start()
            except OSError as exc:
                raise DemoError(f"--http {opts.http}: cannot listen: {exc.strerror or exc}") from None
            progress.say(f"companion demo: {parameterisation}: live map at {web.url}")
        pilot.start_streams()
        # Wait for the service to be connected and mapping before taking off, so its start-up
        # (imports, Zenoh) does not eat into the flight.
        deadline = time.monotonic() + STARTUP_WALL_S
        while True:
            station.poll()
            pilot.drain()
            pilot.heartbeat()
            st = station.map.status or {}
            if _link_state(st) == "connected" and (st.get("camera") or {}).get("state") == "ok":
                break
            if daemon.poll() is not None:
                raise DemoError(f"the service exited with status {daemon.returncode} at start-up (see {run_dir / 'daemon.log'})")
            if time.monotonic() > deadline:
                raise DemoError(f"the service did not report a connected link and a running camera within "
                                f"{STARTUP_WALL_S:g} s (see {run_dir / 'daemon.log'})")
            time.sleep(0.05)
        pilot.take_off(float(world.circuit.altitude_agl_m))
        record.complete, record.problem = fly(record, opts, world, obstacle, pilot, station, daemon, progress, wall0, feed)
    except DemoError as exc:
        record.problem = str(exc)
    finally:
        record.wall_s = time.monotonic() - wall0
        if station is not None:
            # The map the metrics use: at the last lap's end, or as far as an unfinished run got.
            record.final_map = record.lap_maps[-1] if record.lap_maps else report.raster_from_tiles(dict(station.map.tiles))
            record.status = station.map.status
        stop_requested = time.time()
        record.daemon_exit = _stop(daemon, STOP_WALL_S)
        snapshot = map_dir / "terrain.snapshot"
        # Saved at shutdown: written after SIGTERM (1 s of slack for file-system time stamps).
        record.daemon_exit["snapshot_saved"] = snapshot.exists() and snapshot.stat().st_mtime >= stop_requested - 1.0
        if station is not None:
            station.poll()
            record.ground = {"counts": dict(station.map.counts), "dropped": station.dropped, "syncs": station.syncs}
            station.close()
        if web is not None:
            web.close()
        if sim is not None:
            t0 = time.monotonic()
            rc = sim.stop(STOP_WALL_S)
            record.sim_exit = {"returncode": rc, "stop_wall_s": round(time.monotonic() - t0, 2),
                               "slips": _sim_slips(run_dir / "sim.log")}
        pilot.close()
        if daemon_log is not None:
            daemon_log.close()
    return record


def fly(record: RunRecord, opts, world, obstacle, pilot: Pilot, station, daemon, progress: Progress,
        wall0: float, feed=None) -> tuple[bool, str]:
    """The main loop of a run: record truth, follow the map, cut laps; (complete, problem). ``feed``
    (:class:`drivers.ground_web.LiveFeed`) gets the ground station's changes for the browsers."""
    counter = report.LapCounter(world.waypoints_ne_m, LAP_RADIUS_M)
    # A generous bound: the laps at the configured speed, times three, plus a minute; in lockstep
    # simulated time may run slower than the speed-up (down to real time within the bound).
    circuit_m = float(report.path_length(np.vstack([world.waypoints_ne_m, world.waypoints_ne_m[:1]]))[-1])
    pace = opts.speedup if getattr(opts, "no_lockstep", False) else min(opts.speedup, 1.0)
    budget_wall_s = 3.0 * (opts.laps * circuit_m / world.circuit.speed_mps + 60.0) / pace + 60.0
    deadline = time.monotonic() + budget_wall_s
    sim_t_seen, sim_t_wall = -1.0, time.monotonic()  # simulated time last seen moving, and when
    seen, tiles_rx = 0, -1
    last_engaged_t, engaged = None, False
    footprint_lo = obstacle.footprint_ne_m.min(axis=0) - 2.0
    footprint_hi = obstacle.footprint_ne_m.max(axis=0) + 2.0
    while True:
        pilot.drain()
        pilot.heartbeat()
        station.poll()
        if feed is not None:
            feed.update_from(station.map)
        n = len(pilot.truth)
        if n > seen:
            ne = np.stack([pilot.truth.north_m[seen:n], pilot.truth.east_m[seen:n]], axis=1)
            for end in counter.update(ne):
                record.lap_ends.append(end)
                record.lap_maps.append(report.raster_from_tiles(dict(station.map.tiles)))
            seen = n
        gm = station.map
        service_lap = int(((gm.status or {}).get("control") or {}).get("lap") or 0)
        while len(record.service_laps) < service_lap:
            record.service_laps.append(pilot.sim_time_s)  # the status is 1 Hz: within a second of the truth
        if gm.counts["tiles_rx"] != tiles_rx:
            tiles_rx = gm.counts["tiles_rx"]
            near = [t for t in gm.tiles.values() if _tile_overlaps(t, footprint_lo, footprint_hi)]
            mapped = report.mapped_height_over_footprint(report.raster_from_tiles(near), obstacle.footprint_ne_m)
            record.detection.append((pilot.sim_time_s, mapped.height_m))
        avoid = gm.avoidance or {}
        now_engaged = bool(avoid.get("engaged")) if avoid else None
        if now_engaged and not engaged:
            last_engaged_t = pilot.sim_time_s
        if engaged and not now_engaged and last_engaged_t is not None:
            record.engaged_time_s += pilot.sim_time_s - last_engaged_t
        engaged = bool(now_engaged)
        st = gm.status or {}
        cam = st.get("camera") or {}
        alt = pilot.truth.alt_m[-1] if pilot.truth.alt_m else math.nan
        progress.update(progress_line(record.parameterisation, counter.laps, opts.laps, pilot.sim_time_s, alt,
                                      len(gm.tiles), int((st.get("mapper") or {}).get("frames_mapped", 0)),
                                      int(cam.get("queue_dropped", 0)), now_engaged, time.monotonic() - wall0,
                                      ((counter.next_wp - 1) % len(world.waypoints_ne_m)) / len(world.waypoints_ne_m)))
        if counter.laps >= opts.laps:
            break
        if daemon.poll() is not None:
            return False, f"the service exited with status {daemon.returncode} during the flight"
        if time.monotonic() > deadline:
            return False, (f"{counter.laps} of {opts.laps} laps after {budget_wall_s:.0f} s (wall): "
                           "the vehicle did not come round the circuit")
        if pilot.sim_time_s != sim_t_seen:
            sim_t_seen, sim_t_wall = pilot.sim_time_s, time.monotonic()
        elif time.monotonic() - sim_t_wall > STALL_WALL_S:
            return False, (f"simulated time stood still at {sim_t_seen:.1f} s for {STALL_WALL_S:g} s (wall): "
                           "the simulator stopped, or the service held its clock (see daemon.log and sim.log)")
        time.sleep(0.02)
    if engaged and last_engaged_t is not None:
        record.engaged_time_s += pilot.sim_time_s - last_engaged_t
    last = station.map.status or record.status or {}  # the service's last status (record.status comes later)
    progress.done(progress_line(record.parameterisation, counter.laps, opts.laps, pilot.sim_time_s,
                                pilot.truth.alt_m[-1], len(station.map.tiles),
                                int((last.get("mapper") or {}).get("frames_mapped", 0)),
                                int((last.get("camera") or {}).get("queue_dropped", 0)),
                                engaged, time.monotonic() - wall0, 0.0))
    return True, ""


def _link_state(status: dict) -> str | None:
    """The autopilot link state in a ``companion.status/1`` document (``link.link.state``)."""
    link = status.get("link") or {}
    inner = link.get("link") if isinstance(link.get("link"), dict) else link
    return inner.get("state")


def _tile_overlaps(tile, lo: np.ndarray, hi: np.ndarray) -> bool:
    size = tile.height.shape[0] * tile.cell_size_m
    n0, e0 = tile.tx * size, tile.ty * size
    return n0 <= hi[0] and n0 + size >= lo[0] and e0 <= hi[1] and e0 + size >= lo[1]
