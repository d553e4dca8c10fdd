"""``companion demo``: the closed loop on this machine, with a report.

For each parameterisation asked for (inverse depth, then the Cartesian baseline), one run:

```
companion sim  (subprocess) --TCP MAVLink--> companion run (subprocess, generated YAML)
      |  --UDP MAVLink--> this process: the "pilot" (GUIDED, arm, take off; logs SIM_STATE truth)
companion run --Zenoh--> this process: the ground station (tiles, status, avoidance)
```

The demo plays the operator: it arms the simulated vehicle and takes off to the circuit
altitude; above ``control.min_alt_m`` the service flies the circuit, maps the terrain with the
synthetic camera and keeps its clearance. The truth trajectory (SIM_STATE) splits into laps;
at each lap's end the ground station's map is kept. After the laps asked for, the service and
the simulator get SIGTERM (the service must save its map and exit within a few seconds).

Then :mod:`companion.desk.report` turns trajectories and maps into ``metrics.json`` and the PNGs
(docs/demo.md describes both). Nothing is tuned per run: the figures are what the loop did.
"""

from __future__ import annotations

import argparse
import json
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

from companion.config import ConfigError
from companion.desk import plots, report

PARAMETERISATIONS = ("inverse_depth", "cartesian")
DEFAULT_SPEEDUP = 3.0          # both runs of 3 laps in about 3.5 min on the 2-core machine, frames kept up (docs/demo.md)
CAMERA_RATE_HZ = 15.0          # simulated seconds; the paper's camera ran at 16 Hz
TRUTH_RATE_HZ = 25.0           # SIM_STATE (and ATTITUDE for its time stamp) to the pilot
DETECTION_FRACTION = 0.5       # the obstacle counts as mapped once half its textured height is
LAP_RADIUS_M = 10.0            # a waypoint is visited when the truth passes this close
STARTUP_WALL_S = 60.0          # processes up, link connected, camera running
STOP_WALL_S = 10.0             # SIGTERM to exit
CLEARANCE_ISSUE, CLEARANCE_GOAL = 0.8, 0.9
MAP_MARGIN_M = 40.0            # the map figure shows the circuit and this much around it
MAP_RANGE_M = (-5.0, 2.0)      # colour range: from -5 m to twice the obstacle's roof height


class DemoError(RuntimeError):
    """A run could not start or went wrong in a way that makes its figures meaningless."""


# --------------------------------------------------------------------------------------------
# Progress on stderr
# --------------------------------------------------------------------------------------------


class Progress:
    """One line per run, redrawn in place on a terminal; plain lines every few seconds otherwise."""

    def __init__(self, stream=None, every_s: float = 5.0):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s
        self._last = -math.inf
        self._width = 0

    def update(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            if now - self._last < 0.1 and not force:
                return
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            if now - self._last < self.every_s and not force:
                return
            self.stream.write(text + "\n")
        self._last = now
        self.stream.flush()

    def done(self, text: str) -> None:
        self.update(text, force=True)
        if self.tty:
            self.stream.write("\n")
            self._width = 0
        self.stream.flush()

    def say(self, text: str) -> None:
        if self.tty and self._width:
            self.stream.write("\n")
            self._width = 0
        self.stream.write(text + "\n")
        self.stream.flush()


def progress_line(param: str, laps: int, n_laps: int, t_s: float, alt_m: float, tiles: int, frames: int,
                  dropped: int, engaged: bool | None, wall_s: float, lap_fraction: float = 0.0) -> str:
    """``inverse_depth [#####-----] lap 1/3  t 85 s  alt 15.2 m  tiles 34  frames 1200 (0 dropped)  clear  42 s``."""
    total = max(1, n_laps)
    filled = int(round(20 * min(1.0, (laps + min(lap_fraction, 0.99)) / total)))
    state = "-" if engaged is None else ("ENGAGED" if engaged else "clear")
    return (f"{param:>13} [{'#' * filled}{'-' * (20 - filled)}] lap {min(laps + 1, n_laps) if laps < n_laps else n_laps}/{n_laps}"
            f"  t {t_s:5.0f} s  alt {alt_m:5.1f} m  tiles {tiles:3d}  frames {frames:5d} ({dropped} dropped)"
            f"  {state:7s}  wall {wall_s:4.0f} s")


# --------------------------------------------------------------------------------------------
# The pilot: a plain pymavlink client on the simulator's --udp-out endpoint
# --------------------------------------------------------------------------------------------


@dataclass
class TruthLog:
    """The true trajectory as SIM_STATE reports it (simulated seconds since boot; local NED)."""

    t_s: list[float] = field(default_factory=list)
    north_m: list[float] = field(default_factory=list)
    east_m: list[float] = field(default_factory=list)
    alt_m: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t_s)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.asarray(self.t_s, float), np.stack([np.asarray(self.north_m, float), np.asarray(self.east_m, float)],
                                                      axis=1).reshape(-1, 2), np.asarray(self.alt_m, float))


class Pilot:
    """GUIDED, arm and take off like an operator at a ground station; record the truth."""

    GUIDED = 4  # ArduPilot Copter custom mode

    def __init__(self, home):
        from drivers.sim.harness import MavClient

        self.client = MavClient.udp_listener()
        self.home = home
        self.truth = TruthLog()
        self.sim_time_s = 0.0
        self.statustexts: list[str] = []
        self._last_hb = -math.inf

    @property
    def port(self) -> int:
        return self.client.port

    def close(self) -> None:
        self.client.close()

    def heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_hb >= 1.0:
            self.client.heartbeat()
            self._last_hb = now

    def _record(self, m) -> None:
        kind = m.get_type()
        if kind == "ATTITUDE":
            self.sim_time_s = m.time_boot_ms / 1000.0
        elif kind == "SIM_STATE":
            # lat_int/lon_int (1e-7 deg, ~1 cm): the float lat/lon fields are float32 degrees (~0.5 m).
            lat = m.lat_int * 1e-7 if getattr(m, "lat_int", 0) else m.lat
            lon = m.lon_int * 1e-7 if getattr(m, "lon_int", 0) else m.lon
            n, e, d = self.home.global_to_ned(lat, lon, m.alt)
            self.truth.t_s.append(self.sim_time_s)
            self.truth.north_m.append(n)
            self.truth.east_m.append(e)
            self.truth.alt_m.append(-d)
        elif kind == "STATUSTEXT":
            self.statustexts.append(m.text)

    def drain(self, max_messages: int = 20000) -> int:
        """Read everything already received; returns the messages read."""
        n = 0
        for n in range(1, max_messages + 1):
            m = self.client.conn.recv_match(blocking=False)
            if m is None:
                return n - 1
            if m.get_type() != "BAD_DATA":
                self._record(m)
        return n

    def wait(self, what: str, predicate, timeout_wall_s: float) -> None:
        deadline = time.monotonic() + timeout_wall_s
        while time.monotonic() < deadline:
            self.heartbeat()
            m = self.client.conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_type() != "BAD_DATA":
                self._record(m)
                if predicate(m):
                    return
        raise DemoError(f"pilot: {what} within {timeout_wall_s:g} s (wall)")

    def command(self, what: str, command: int, *params: float, attempts: int = 5) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        result = None
        for _ in range(attempts):
            self.heartbeat()
            p = list(params) + [0.0] * (7 - len(params))
            self.client.mav.command_long_send(1, 1, command, 0, *p)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                m = self.client.conn.recv_match(blocking=True, timeout=0.1)
                if m is None or m.get_type() == "BAD_DATA":
                    continue
                self._record(m)
                if m.get_type() == "COMMAND_ACK" and m.command == command:
                    result = m.result
                    break
            if result == mav.MAV_RESULT_ACCEPTED:
                return
            time.sleep(0.3)
        raise DemoError(f"pilot: {what} refused (COMMAND_ACK result {result})")

    def start_streams(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        self.wait("no HEARTBEAT from the simulated vehicle", lambda m: m.get_type() == "HEARTBEAT", 20.0)
        interval_us = 1e6 / TRUTH_RATE_HZ
        for msg_id in (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_SIM_STATE):
            self.command(f"stream {msg_id}", mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)

    def take_off(self, altitude_m: float) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        if not any("origin set" in t for t in self.statustexts):
            self.wait("no EKF origin", lambda m: m.get_type() == "STATUSTEXT" and "origin set" in m.text, 30.0)
        # ArduPilot refuses to arm ("PreArm: Need Position Estimate") until its EKF uses GPS, which
        # comes after the origin (real SITL: about 21 s later): wait for it rather than retry arming.
        if not any("using GPS" in t for t in self.statustexts):
            self.wait("no GPS use by the EKF", lambda m: m.get_type() == "STATUSTEXT" and "using GPS" in m.text, 60.0)
        self.command("GUIDED", mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self.GUIDED)
        self.command("arming", mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        self.command("takeoff", mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)


# --------------------------------------------------------------------------------------------
# One closed-loop run
# --------------------------------------------------------------------------------------------


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
    sim = daemon = station = None
    daemon_log = None
    try:
        sim = SimVehicleProcess([
            "--scenario", opts.scenario, "--tcp-listen", "127.0.0.1:0", "--udp-out", f"127.0.0.1:{pilot.port}",
            "--speedup", f"{opts.speedup:g}", "--origin-delay", "2", "--seed", str(opts.seed),
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
        record.complete, record.problem = fly(record, opts, world, obstacle, pilot, station, daemon, progress, wall0)
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
        wall0: float) -> tuple[bool, str]:
    """The main loop of a run: record truth, follow the map, cut laps; (complete, problem)."""
    counter = report.LapCounter(world.waypoints_ne_m, LAP_RADIUS_M)
    # A generous bound: the laps at the configured speed, times three, plus a minute.
    circuit_m = float(report.path_length(np.vstack([world.waypoints_ne_m, world.waypoints_ne_m[:1]]))[-1])
    budget_wall_s = 3.0 * (opts.laps * circuit_m / world.circuit.speed_mps + 60.0) / opts.speedup + 60.0
    deadline = time.monotonic() + budget_wall_s
    seen, tiles_rx = 0, -1
    last_engaged_t, engaged = None, False
    footprint_lo = obstacle.footprint_ne_m.min(axis=0) - 2.0
    footprint_hi = obstacle.footprint_ne_m.max(axis=0) + 2.0
    while True:
        pilot.drain()
        pilot.heartbeat()
        station.poll()
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


# --------------------------------------------------------------------------------------------
# Metrics and figures
# --------------------------------------------------------------------------------------------


def _num(x: Any, digits: int = 3):
    """JSON-safe number: None for NaN/inf."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def warning_needed_s(world, obstacle) -> float:
    """The law's time (s) to climb from the nominal altitude to the textured height plus clearance
    (the demo flies the law's default acceleration and climb-rate limits)."""
    from companion.method.avoidance import stopping_time
    from companion.config import AvoidanceConfig

    a = AvoidanceConfig()
    gain = obstacle.textured_height_m + float(world.clearance_m) - float(world.circuit.altitude_agl_m)
    return stopping_time(gain, a.accel_mps2, a.max_climb_mps)


def run_metrics(rec: RunRecord, world, obstacle, clearance_m: float) -> dict[str, Any]:
    """The figures of one run (the ``runs.<parameterisation>`` entry of metrics.json)."""
    t, ne, alt = rec.truth.arrays()
    det_t = np.array([d[0] for d in rec.detection], float)
    det_h = np.array([d[1] for d in rec.detection], float)
    detected_t = report.first_detection_time(det_t, det_h, DETECTION_FRACTION * obstacle.textured_height_m)
    needed_s = warning_needed_s(world, obstacle)
    ground = report.ground_around(obstacle.footprint_ne_m, world.terrain_height)
    laps = []
    starts = [0] + rec.lap_ends[:-1]
    for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
        sl = slice(s, e + 1)
        crossing = report.min_clearance_over_footprint(t[sl], ne[sl], alt[sl], obstacle.footprint_ne_m, world.terrain_height)
        mapped = report.mapped_height_over_footprint(rec.lap_maps[k], obstacle.footprint_ne_m, ground_m=ground)
        err = report.map_error(rec.lap_maps[k], world.terrain_height)
        agl = alt[sl] - world.terrain_height(ne[sl, 0], ne[sl, 1])
        laps.append({
            "lap": k + 1,
            "min_clearance_m": _num(crossing.min_clearance_m),
            "mapped_obstacle_height_m": _num(mapped.height_m),
            "mapped_obstacle_max_m": _num(mapped.max_m),
            "mapped_obstacle_cells": mapped.cells,
            "start_t_s": _num(t[s], 2), "end_t_s": _num(t[e], 2),
            "crossing_t_s": _num(crossing.entered_t_s, 2),
            "min_clearance_at_ne_m": None if crossing.at_ne_m is None else [_num(v, 2) for v in crossing.at_ne_m],
            "mapped_before_lap": bool(np.isfinite(detected_t) and detected_t <= t[s]),
            "mapped_before_crossing": bool(np.isfinite(detected_t) and np.isfinite(crossing.entered_t_s)
                                           and detected_t <= crossing.entered_t_s),
            "warning_s": _num(crossing.entered_t_s - detected_t, 2),
            "mapped_in_time": report.mapped_in_time(detected_t, crossing.entered_t_s, needed_s),
            "max_alt_m": _num(np.max(alt[sl])),
            "max_height_above_terrain_m": _num(np.max(agl)),
            "cruise_height_over_flat_m": _num(report.height_over_flat_ground(ne[sl], alt[sl], world.terrain_height)[0]),
            "map_rmse_m": _num(err.rmse_m),
            "service_lap_end_t_s": _num(rec.service_laps[k], 2) if k < len(rec.service_laps) else None,
        })
    final_err = report.map_error(rec.final_map, world.terrain_height)
    textured_err = report.map_error(rec.final_map, lambda n, e: world.terrain_height(n, e, textured_only=True))
    st = rec.status or {}
    mapper, cam, control = st.get("mapper") or {}, st.get("camera") or {}, st.get("control") or {}
    return {
        "laps": laps,
        "map_rmse_m": _num(final_err.rmse_m),
        "map_error": {
            "cells": final_err.cells, "bias_m": _num(final_err.bias_m), "within_1m": _num(final_err.within_1m),
            "p95_abs_m": _num(final_err.p95_abs_m), "max_abs_m": _num(final_err.max_abs_m),
            "cells_over_3m_high": final_err.over_3m, "rmse_vs_textured_m": _num(textured_err.rmse_m),
        },
        "first_detection_t_s": _num(detected_t, 2),
        "complete": rec.complete,
        "problem": rec.problem,
        "wall_time_s": _num(rec.wall_s, 1),
        "sim_time_s": _num(t[-1] if len(t) else math.nan, 1),
        "avoidance_engaged_s": _num(rec.engaged_time_s, 1),
        "frames": cam.get("frames"),
        "frames_mapped": mapper.get("frames_mapped"),
        "frames_dropped": cam.get("queue_dropped"),
        "points_converged": mapper.get("points_converged"),
        "map_tiles": (st.get("map") or {}).get("tiles"),
        "service": {
            "mapper_step_ms": mapper.get("step_ms"),
            "frame_to_setpoint_ms": control.get("frame_to_setpoint_ms"),
            "control_jitter_ms": control.get("jitter_ms"),
            "control_rate_hz": control.get("rate_hz"),
            "lap_count": control.get("lap"),
            "health": st.get("health"), "problems": st.get("problems"),
            "exit": rec.daemon_exit,
        },
        "simulator_exit": rec.sim_exit,
        "ground_station": rec.ground,
    }


def write_figures(records: dict[str, RunRecord], world, obstacle, out: Path) -> list[Path]:
    """map_<p>.png, profile_<p>_lap<k>.png for each run, and comparison.png."""
    written = []
    from companion.config import AvoidanceConfig

    outlines = [o.footprint_ne_m for o in world.obstacles]
    clearance = float(world.clearance_m)
    miss = AvoidanceConfig().miss_distance_m  # the law's corridor half-width (the demo keeps the default)
    for param, rec in records.items():
        t, ne, alt = rec.truth.arrays()
        starts = [0] + rec.lap_ends[:-1]
        paths = [(ne[s:e + 1], f"lap {k + 1}", plots.PALETTE[k % len(plots.PALETTE)])
                 for k, (s, e) in enumerate(zip(starts, rec.lap_ends))]
        m = rec.final_map
        if m.shape[0] and m.shape[1]:
            wp = np.asarray(world.waypoints_ne_m, float)
            lo, hi = wp.min(axis=0) - MAP_MARGIN_M, wp.max(axis=0) + MAP_MARGIN_M
            view = m.crop(lo[0], hi[0], lo[1], hi[1])
            outside = m.observed_cells() - view.observed_cells()
            vmin, vmax = MAP_RANGE_M[0], MAP_RANGE_M[1] * obstacle.height_m
            written.append(plots.height_map(
                out / f"map_{param}.png", view.height, view.north0_m, view.east0_m, view.cell_m,
                f"{param.replace('_', ' ')}: terrain map (altitude, m) after {len(rec.lap_ends)} lap(s)",
                paths=paths, outlines=outlines, vmin=vmin, vmax=vmax, scale_px=max(1, min(4, 840 // view.shape[0])),
                notes=[f"outlines: true footprints ({obstacle.name}: roof {obstacle.height_m:g} m, "
                       f"textured to {obstacle.textured_height_m:g} m)",
                       f"colours clipped to {vmin:g}..{vmax:g} m; view: circuit + {MAP_MARGIN_M:g} m "
                       f"({outside} mapped cells lie outside it)"]))
        for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
            prof = report.lap_profile(ne[s:e + 1], alt[s:e + 1], world.terrain_height, rec.lap_maps[k],
                                      lambda n, e_: world.terrain_height(n, e_, textured_only=True), corridor_m=miss)
            d = prof.distance_m
            series = [
                plots.Series(d, prof.true_terrain_m, "true terrain", plots.PALETTE[5], 1, fill_to_bottom=True),
                plots.Series(d, prof.mapped_corridor_max_m, f"mapped, highest within {miss:g} m across",
                             plots.PALETTE[3], 1),
                plots.Series(d, prof.mapped_terrain_m, "mapped terrain under the path", plots.PALETTE[2], 2),
                plots.Series(d, prof.true_terrain_m + clearance, f"terrain + clearance {clearance:g} m",
                             plots.PALETTE[1], 1, dashed=True),
                plots.Series(d, prof.alt_m, "altitude (truth)", plots.PALETTE[0], 2),
            ]
            written.append(plots.line_chart(
                out / f"profile_{param}_lap{k + 1}.png", series,
                f"{param.replace('_', ' ')}, lap {k + 1}: side profile along the circuit",
                "distance along the lap (m); mapped = the ground station's map at the lap's end", "altitude (m)"))
    written.append(comparison_figure(records, world, obstacle, out / "comparison.png"))
    return written


def comparison_figure(records: dict[str, RunRecord], world, obstacle, path: Path) -> Path:
    """Two bar charts stacked: mapped obstacle height per lap (textured height as reference), and
    the least clearance over the obstacle per lap (configured clearance as reference)."""
    import cv2

    n_laps = max((len(r.lap_ends) for r in records.values()), default=0)
    ground = report.ground_around(obstacle.footprint_ne_m, world.terrain_height)
    groups = [f"lap {k + 1}" for k in range(max(1, n_laps))]
    heights, clearances = {}, {}
    for param, rec in records.items():
        t, ne, alt = rec.truth.arrays()
        starts = [0] + rec.lap_ends[:-1]
        h, c = [], []
        for k, (s, e) in enumerate(zip(starts, rec.lap_ends)):
            h.append(report.mapped_height_over_footprint(rec.lap_maps[k], obstacle.footprint_ne_m, ground_m=ground).height_m)
            c.append(report.min_clearance_over_footprint(t[s:e + 1], ne[s:e + 1], alt[s:e + 1], obstacle.footprint_ne_m,
                                                         world.terrain_height).min_clearance_m)
        heights[param.replace("_", " ")] = h
        clearances[param.replace("_", " ")] = c
    tmp = path.with_name(path.stem + ".parts")
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        a = plots.bar_chart(tmp / "h.png", groups, heights,
                            f"{obstacle.name}: mapped height at the end of each lap (m)", "height (m)",
                            reference=[(obstacle.textured_height_m, f"textured height {obstacle.textured_height_m:g} m"),
                                       (obstacle.height_m, f"roof {obstacle.height_m:g} m", plots.GREY),
                                       (report.PAPER_MAPPED_FRACTION * obstacle.height_m,
                                        f"paper: {100 * report.PAPER_MAPPED_FRACTION:.0f}% of the roof", plots.PALETTE[3])],
                            size=(760, 400))
        b = plots.bar_chart(tmp / "c.png", groups, clearances,
                            f"{obstacle.name}: least clearance over it in each lap (m)", "clearance (m)",
                            reference=[(float(world.clearance_m), f"configured {world.clearance_m:g} m"),
                                       (CLEARANCE_ISSUE * world.clearance_m, f"issue: {CLEARANCE_ISSUE:g} x configured", plots.GREY),
                                       (CLEARANCE_GOAL * world.clearance_m, f"goal: {CLEARANCE_GOAL:g} x configured",
                                        plots.PALETTE[3])],
                            size=(760, 400))
        parts = [cv2.imread(str(a)), cv2.imread(str(b))]
        width = max(part.shape[1] for part in parts)  # tight bounding boxes differ by their legends
        img = np.vstack([cv2.copyMakeBorder(part, 0, 0, 0, width - part.shape[1], cv2.BORDER_CONSTANT,
                                            value=plots.WHITE) for part in parts])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return plots.write_png(path, img)


def write_trajectory(rec: RunRecord, path: Path) -> Path:
    t, ne, alt = rec.truth.arrays()
    lap = np.zeros(len(t), int)
    for end in rec.lap_ends:
        lap[end + 1:] += 1
    with open(path, "w") as f:
        f.write("t_s,north_m,east_m,alt_m,lap\n")
        for row in zip(t, ne[:, 0], ne[:, 1], alt, lap + 1):
            f.write(f"{row[0]:.3f},{row[1]:.3f},{row[2]:.3f},{row[3]:.3f},{row[4]}\n")
    return path


OPTION_KEYS = ("scenario", "laps", "speedup", "seed", "no_avoid", "camera_rate", "config", "set")


def save_record(rec: RunRecord, path: Path, opts=None) -> Path:
    """Everything the report needs from one run, in one ``.npz`` (``--replot`` reads it back)."""
    t, ne, alt = rec.truth.arrays()
    arrays: dict[str, Any] = {"t_s": t, "ne_m": ne, "alt_m": alt, "lap_ends": np.asarray(rec.lap_ends, np.int64),
                              "detection": np.asarray(rec.detection, float).reshape(-1, 2)}
    for k, m in enumerate(rec.lap_maps):
        arrays[f"lap{k}_height"], arrays[f"lap{k}_count"] = m.height.astype(np.float32), m.count.astype(np.uint32)
        arrays[f"lap{k}_origin"] = np.array([m.north0_m, m.east0_m, m.cell_m])
    meta = {k: getattr(rec, k) for k in ("parameterisation", "status", "engaged_time_s", "wall_s", "complete", "problem",
                                         "daemon_exit", "sim_exit", "ground", "service_laps")}
    if opts is not None:
        meta["options"] = {k: getattr(opts, k, None) for k in OPTION_KEYS}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load_record(path: Path) -> RunRecord:
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        truth = TruthLog(list(z["t_s"]), list(z["ne_m"][:, 0]), list(z["ne_m"][:, 1]), list(z["alt_m"]))
        maps = []
        k = 0
        while f"lap{k}_height" in z:
            n0, e0, c = (float(v) for v in z[f"lap{k}_origin"])
            maps.append(report.MapRaster(z[f"lap{k}_height"].astype(float), z[f"lap{k}_count"].astype(np.int64), n0, e0, c))
            k += 1
        rec = RunRecord(meta.pop("parameterisation"), truth, [int(i) for i in z["lap_ends"]], maps,
                        detection=[(float(a), float(b)) for a, b in z["detection"]])
    rec.options = meta.pop("options", None)
    for key, value in meta.items():
        setattr(rec, key, value)
    if maps:
        rec.final_map = maps[-1]
    return rec


def build_metrics(records: dict[str, RunRecord], world, obstacle, opts, wall_s: float) -> dict[str, Any]:
    clearance = float(world.clearance_m)
    runs = {p: run_metrics(r, world, obstacle, clearance) for p, r in records.items()}
    verdicts = {}
    for p, m in runs.items():
        other = [q for q in runs if q != p]
        other_laps = runs[other[0]]["laps"] if (p == "inverse_depth" and other) else None
        laps = [{k: (math.nan if v is None else v) for k, v in lap.items()} for lap in m["laps"]]
        olaps = None if other_laps is None else [{k: (math.nan if v is None else v) for k, v in lap.items()}
                                                 for lap in other_laps]
        verdicts[p] = {k: (_num(v) if isinstance(v, float) else v)
                       for k, v in report.criteria(laps, clearance, obstacle.textured_height_m, olaps,
                                                                 float(obstacle.height_m)).items()}
    return {
        "schema": "companion.demo/1",
        "clearance_m": clearance,
        "obstacle_textured_height_m": float(obstacle.textured_height_m),
        "obstacle": {"name": obstacle.name, "height_m": float(obstacle.height_m),
                     "footprint_ne_m": obstacle.footprint_ne_m.tolist()},
        "runs": runs,
        "criteria": verdicts,
        "warning_needed_s": _num(warning_needed_s(world, obstacle), 2),
        "paper": {"mapped_fraction_of_height": report.PAPER_MAPPED_FRACTION,
                  "note": "Magree, Mooney, Johnson, section IV: the 40 ft structure (texture to ~30 ft) was mapped at about 30 ft"},
        "definitions": {
            "cruise_height_over_flat_m": "median (altitude - true terrain) over the lap where the terrain is flat within 15 m (nominal altitude + the 2-sigma map margin)",
            "min_clearance_m": "least (altitude - true terrain) while the true position is over the obstacle's footprint, per lap",
            "mapped_obstacle_height_m": "95th percentile of the mapped heights of the footprint cells (grown by one cell) "
                                        "holding >= 2 points, in the ground station's map at the lap's end",
            "first_detection_t_s": f"first time the mapped obstacle height reached {DETECTION_FRACTION:g} x the textured height",
            "mapped_in_time": "first detection at least warning_needed_s before the lap's crossing (the law's time to climb "
                              "from the nominal altitude to textured height + clearance); the clearance criteria judge these laps",
            "map_rmse_m": "RMSE of every observed cell of the final map against the scenario's true heights at cell centres",
            "laps": f"cut where the true trajectory comes back within {LAP_RADIUS_M:g} m of the first waypoint after the others",
        },
        "scenario": opts.scenario,
        "laps_requested": opts.laps,
        "speedup": opts.speedup,
        "camera_rate_hz": opts.camera_rate,
        "seed": opts.seed,
        "avoidance_enabled": not opts.no_avoid,
        "wall_time_s": round(wall_s, 1),
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
    }


DROPPED_WARN = 0.05  # a larger share of camera frames dropped by the service is worth a word


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A few lines for the terminal: per lap, mapped height and least clearance; a warning when the
    service could not keep up with the camera."""
    out = [f"obstacle textured to {metrics['obstacle_textured_height_m']:g} m (roof {metrics['obstacle']['height_m']:g} m); "
           f"clearance {metrics['clearance_m']:g} m; the paper mapped ~{100 * report.PAPER_MAPPED_FRACTION:.0f}% of the roof height"]
    for p, run in metrics["runs"].items():
        laps = "  ".join(
            f"lap {lap['lap']}: height {_fmt(lap['mapped_obstacle_height_m'])} m, clearance {_fmt(lap['min_clearance_m'])} m"
            for lap in run["laps"])
        out.append(f"{p:>13}: {laps or 'no complete lap'}; map RMSE {_fmt(run['map_rmse_m'])} m"
                   + (f"  [{run['problem']}]" if run["problem"] else ""))
        frames, dropped = run.get("frames") or 0, run.get("frames_dropped") or 0
        if frames and dropped > DROPPED_WARN * frames:
            out.append(f"{'':>13}  warning: the service dropped {100 * dropped / frames:.0f}% of the camera frames "
                       f"(busy machine or --speedup {metrics['speedup']:g} too high for it): try a lower --speedup")
    return out


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.1f}"


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="default", help="scenario name in config/scenarios/ or a YAML path (default: default)")
    p.add_argument("--laps", type=int, default=3, help="laps of the circuit per run (default 3, as in the paper)")
    p.add_argument("--speedup", type=float, default=DEFAULT_SPEEDUP,
                   help=f"simulated seconds per wall second for the vehicle and the service (default {DEFAULT_SPEEDUP:g})")
    p.add_argument("--output", default="demo-report", help="report folder (default ./demo-report)")
    p.add_argument("--seed", type=int, default=1, help="random seed of the simulated navigation error, wind and camera noise")
    p.add_argument("--no-avoid", action="store_true",
                   help="hold the nominal altitude only (the law is still evaluated and published, not obeyed)")
    p.add_argument("--parameterisation", choices=("inverse_depth", "cartesian", "both"), default="both",
                   help="mapper feature parameterisation; both = inverse depth, then the Cartesian baseline (default)")
    p.add_argument("--replot", action="store_true",
                   help="do not fly: rebuild metrics.json and the figures from the runs saved in --output")
    p.add_argument("--config", metavar="FILE",
                   help="service configuration for the run (YAML, partial; over the scenario's own settings)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="one service setting for the run, e.g. camera.mount_pitch_deg=-30 (repeatable; after --config)")
    p.add_argument("--camera-rate", type=float, default=CAMERA_RATE_HZ, metavar="HZ",
                   help=f"synthetic camera rate in simulated Hz (default {CAMERA_RATE_HZ:g})")


def _check_options(args: argparse.Namespace) -> None:
    if not 1 <= args.laps <= 100:
        raise ConfigError(f"--laps must be within 1..100, got {args.laps}")
    if not (math.isfinite(args.speedup) and 0.1 <= args.speedup <= 100.0):
        raise ConfigError(f"--speedup must be within 0.1..100, got {args.speedup}")
    if not (math.isfinite(args.camera_rate) and 0.5 <= args.camera_rate <= 60.0):
        raise ConfigError(f"--camera-rate must be within 0.5..60 Hz, got {args.camera_rate}")
    if not 0 <= args.seed < 2**31:
        raise ConfigError(f"--seed must be within 0..2^31-1, got {args.seed}")


def main(args: argparse.Namespace) -> int:
    from drivers.sim.world import World

    from companion.desk.quality.scenarios import flight_config, override_layers, world_for

    try:
        _check_options(args)
        world = World.load(args.scenario)
        # --config / --set are validated like `companion run`'s configuration before anything starts;
        # the figures are then judged against the circuit the service was told to fly
        args.overrides = override_layers(getattr(args, "config", None), getattr(args, "set", None))
        world = world_for(world, flight_config(world, args.scenario, "inverse_depth", args.seed, args.camera_rate,
                                               args.overrides))
        plots.require()  # before the flight, not at its figures
    except (ConfigError, plots.DeskExtraMissing) as exc:
        print(f"companion demo: {exc}", file=sys.stderr)
        return 2
    obstacle = pick_obstacle(world)
    if obstacle is None:
        print(f"companion demo: scenario {args.scenario!r} has no obstacle to fly over", file=sys.stderr)
        return 2
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    params = PARAMETERISATIONS if args.parameterisation == "both" else (args.parameterisation,)
    progress = Progress()
    progress.say(f"companion demo: scenario {args.scenario}, {args.laps} lap(s), x{args.speedup:g} real time, "
                 f"{' then '.join(params)}{', avoidance OFF' if args.no_avoid else ''}; report in {out}/")
    wall0 = time.monotonic()
    records: dict[str, RunRecord] = {}
    interrupted = False
    if args.replot:
        for p in params:
            path = out / "runs" / p / "record.npz"
            if not path.exists():
                print(f"companion demo: --replot: no saved run {path}", file=sys.stderr)
                return 2
            records[p] = load_record(path)
            for k, v in (records[p].options or {}).items():
                setattr(args, k, v)  # the figures describe the run as it was flown
        args.overrides = override_layers(args.config, args.set)
        world = world_for(World.load(args.scenario), flight_config(World.load(args.scenario), args.scenario, "inverse_depth",
                                                                   args.seed, args.camera_rate, args.overrides))
    else:
        try:
            for p in params:
                records[p] = run_closed_loop(p, args, world, obstacle, out / "runs" / p, progress)
                if records[p].problem:
                    progress.say(f"companion demo: {p}: {records[p].problem}")
                save_record(records[p], out / "runs" / p / "record.npz", args)
                write_trajectory(records[p], out / "runs" / p / "trajectory.csv")
        except KeyboardInterrupt:
            interrupted = True
            progress.say("companion demo: interrupted; writing what was flown")
    wall = time.monotonic() - wall0 if not args.replot else sum(r.wall_s for r in records.values())
    metrics = build_metrics(records, world, obstacle, args, wall)
    figures = write_figures({p: r for p, r in records.items() if r.lap_ends}, world, obstacle, out)
    metrics["figures"] = [f.name for f in figures]
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=2, allow_nan=False))
    os.replace(tmp, out / "metrics.json")
    for line in summary_lines(metrics):
        progress.say(line)
    progress.say(f"companion demo: {wall:.0f} s wall; wrote {out / 'metrics.json'} and {len(figures)} PNG(s)")
    ok = not interrupted and all(r.complete for r in records.values())
    return 0 if ok else 1


def pick_obstacle(world):
    """The structure the report is about: the tallest building, else the tallest obstacle."""
    if not world.obstacles:
        return None
    buildings = [o for o in world.obstacles if o.kind == "building"] or list(world.obstacles)
    return max(buildings, key=lambda o: o.height_m)
