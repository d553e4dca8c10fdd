"""Opt-in: the service against a real ArduPilot Copter SITL (an unmodified ``arducopter`` binary).

Skipped unless ``COMPANION_ARDUCOPTER`` names the SITL binary (``build/sitl/bin/arducopter`` of an
ArduPilot tree the user built for SITL as ArduPilot documents it) and ``COMPANION_ARDUPILOT_ROOT``
the ArduPilot tree (for ``Tools/autotest/default_params/copter.parm``). The project does not ship
or build ArduPilot. ``COMPANION_SITL_SPEEDUP`` (default 2) sets SITL's and the service's speedup.

The flight, all real processes on loopback: ``arducopter`` on free ports (SERIAL0 for the operator,
SERIAL1 for the service), this test as the operator (GUIDED, arm, take off to 15 m as a ground
station would), ``companion run`` with the synthetic camera riding the SITL's SIM_STATE truth, and
a Zenoh subscriber. The vehicle flies the default circuit's first leg over the 12 m building.
What it proves (docs/sitl.md has the figures of a run): the link builds navigation with the
ArduPilot covariance model (EKF_STATUS_REPORT + GPS_RAW_INT + floors, covariance streams DENIED),
frames are mapped, ArduPilot accepts the streamed GUIDED velocity setpoints (the vehicle, which
holds position after takeoff, flies north), the climb over the building, and the status and
terrain tiles on Zenoh.
"""

from __future__ import annotations

import math
import os
import socket
import subprocess
import time
from pathlib import Path

import pytest

from drivers.sim.world import World
from tests.processes import ZenohListener, companion, free_port, stop, write_config

ARDUCOPTER = os.environ.get("COMPANION_ARDUCOPTER", "")
ARDUPILOT_ROOT = os.environ.get("COMPANION_ARDUPILOT_ROOT", "")
DEFAULTS = Path(ARDUPILOT_ROOT) / "Tools" / "autotest" / "default_params" / "copter.parm"
HOME = "47.397742,8.545594,488,0"   # the default scenario's home (lat, lon, alt AMSL, heading)
SPEEDUP = float(os.environ.get("COMPANION_SITL_SPEEDUP", "2"))
COPTER_GUIDED = 4
EARTH_RADIUS_M = 6378100.0          # ArduPilot's flat-earth radius (Location::get_distance_NE)


def _skip_reason() -> str | None:
    if not ARDUCOPTER:
        return "opt-in: set COMPANION_ARDUCOPTER to an ArduPilot SITL arducopter binary (and COMPANION_ARDUPILOT_ROOT)"
    if not os.access(ARDUCOPTER, os.X_OK):
        return f"COMPANION_ARDUCOPTER={ARDUCOPTER!r} is not an executable file"
    if not DEFAULTS.is_file():
        return f"COMPANION_ARDUPILOT_ROOT={ARDUPILOT_ROOT!r} has no Tools/autotest/default_params/copter.parm"
    return None


pytestmark = [pytest.mark.slow, pytest.mark.skipif(_skip_reason() is not None, reason=_skip_reason() or "")]


def free_base_port(span: int = 9, attempts: int = 200) -> int:
    """A base port B with TCP B .. B+span-1 free: SITL listens on B + serial index (SERIAL0 = B,
    SERIAL1 = B+2, SERIAL2 = B+3, and B+5 .. B+8 for the higher serials)."""
    for _ in range(attempts):
        base = free_port()
        if base + span >= 65535:
            continue
        socks = []
        try:
            for p in range(base, base + span):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no free block of TCP ports for SITL")


def start_sitl(run_dir: Path, base_port: int, rcin_port: int) -> subprocess.Popen:
    """arducopter as sim_vehicle.py starts it (without MAVProxy), in its own directory (eeprom.bin, logs)."""
    cmd = [ARDUCOPTER, "-S", "--model", "+", "--speedup", f"{SPEEDUP:g}", "--defaults", str(DEFAULTS),
           "--home", HOME, "--base-port", str(base_port), "--rc-in-port", str(rcin_port),
           "--sim-address", "127.0.0.1", "-I0"]
    log = open(run_dir / "sitl.log", "w")  # noqa: SIM115 - closed with the process
    return subprocess.Popen(cmd, cwd=run_dir, stdout=log, stderr=subprocess.STDOUT)


class Operator:
    """The ground station on SERIAL0: GUIDED, arm, take off; records SIM_STATE truth and STATUSTEXT."""

    def __init__(self, port: int, connect_timeout_s: float = 20.0):
        from drivers.sim.harness import MavClient

        deadline = time.monotonic() + connect_timeout_s
        while True:
            try:
                self.client = MavClient(f"tcp:127.0.0.1:{port}")
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        self.boot_s = 0.0
        self.home: tuple[float, float, float] | None = None
        self.truth: list[tuple[float, float, float, float]] = []   # (boot s, north, east, up) from home
        self.events: dict[str, float] = {}                          # first STATUSTEXT substring -> boot s
        self.texts: list[tuple[float, str]] = []
        self._last_hb = -math.inf

    def close(self) -> None:
        self.client.close()

    def pump(self, timeout_s: float = 0.1) -> None:
        """Heartbeat at 1 Hz; read what arrived (up to ``timeout_s`` for the first message)."""
        if time.monotonic() - self._last_hb >= 1.0:
            self.client.heartbeat()
            self._last_hb = time.monotonic()
        m = self.client.conn.recv_match(blocking=True, timeout=timeout_s)
        while m is not None:
            self._record(m)
            m = self.client.conn.recv_match(blocking=False)

    def _record(self, m) -> None:
        kind = m.get_type()
        if kind == "ATTITUDE":
            self.boot_s = m.time_boot_ms / 1000.0
        elif kind == "STATUSTEXT":
            self.texts.append((self.boot_s, m.text))
            for key in ("origin set", "is using GPS", "Takeoff", "Arming motors"):
                if key in m.text:
                    self.events.setdefault(key, self.boot_s)
        elif kind == "SIM_STATE":
            lat, lon = m.lat_int * 1e-7, m.lon_int * 1e-7
            if self.home is None:
                self.home = (lat, lon, m.alt)
            k = EARTH_RADIUS_M * math.pi / 180.0
            north = (lat - self.home[0]) * k
            east = (lon - self.home[1]) * k * math.cos(math.radians(lat))
            self.truth.append((self.boot_s, north, east, m.alt - self.home[2]))

    def command(self, command: int, *params: float, timeout_s: float = 3.0) -> int | None:
        """COMMAND_LONG to the autopilot; its COMMAND_ACK result (None: no answer)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.client.mav.command_long_send(1, 1, command, 0, *p)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.client.conn.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            self._record(m)
            if m.get_type() == "COMMAND_ACK" and m.command == command:
                return m.result
        return None

    def stream(self, msg_id: int, name: str, hz: float, attempts: int = 5) -> None:
        """SET_MESSAGE_INTERVAL until the message arrives: a request made in the first second after
        SERIAL0's client connected (SITL still booting) was seen ACCEPTED and never served."""
        from pymavlink.dialects.v20 import ardupilotmega as mav

        for _ in range(attempts):
            assert self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz) == mav.MAV_RESULT_ACCEPTED
            if self.client.recv(name, 2.0) is not None:
                return
        raise TimeoutError(f"operator: {name} requested {attempts} times, never streamed")

    def until(self, what: str, predicate, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise TimeoutError(f"operator: {what} within {timeout_s:g} s; last texts {self.texts[-8:]}")
            self.pump()

    def take_off(self, altitude_m: float, timeout_s: float) -> None:
        """GUIDED, arm (retried while the pre-arm checks refuse: no position estimate yet), take off."""
        from pymavlink.dialects.v20 import ardupilotmega as mav

        deadline = time.monotonic() + timeout_s
        while True:
            if time.monotonic() > deadline:
                raise TimeoutError(f"operator: could not arm within {timeout_s:g} s; last texts {self.texts[-8:]}")
            if (self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_GUIDED) == mav.MAV_RESULT_ACCEPTED
                    and self.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED):
                break
            self.until("wait", lambda t=time.monotonic() + 2.0: time.monotonic() > t, 5.0)
        self.events.setdefault("armed", self.boot_s)
        result = self.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)
        assert result == mav.MAV_RESULT_ACCEPTED, f"takeoff refused ({result}); last texts {self.texts[-8:]}"


def service_config(tmp: Path, serial1_port: int, zenoh_port: int) -> dict:
    """config/ardupilot-sitl.yaml with this run's ports, directories and speedup."""
    import yaml

    doc = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "ardupilot-sitl.yaml").read_text())
    doc["link"]["connection"] = f"tcp:127.0.0.1:{serial1_port}"
    doc["zenoh"].update({"listen": [f"tcp/127.0.0.1:{zenoh_port}"], "status_rate_hz": 2.0})
    doc["persistence"] = {"directory": str(tmp / "map")}
    doc["sim"]["speedup"] = SPEEDUP
    return doc


def test_flies_against_arducopter_sitl(tmp_path):
    world = World.load("default")
    building = next(o for o in world.obstacles if o.name == "building")
    north_lo, north_hi = building.footprint_ne_m[:, 0].min(), building.footprint_ne_m[:, 0].max()
    base, rcin, zport = free_base_port(), free_port(socket.SOCK_DGRAM), free_port()
    sitl = start_sitl(tmp_path, base, rcin)
    daemon = operator = listener = None
    statuses = []
    t_start = time.monotonic()
    try:
        # SITL waits for a client on SERIAL0 before it boots: the operator first, then the service.
        operator = Operator(base)
        from pymavlink.dialects.v20 import ardupilotmega as mav

        operator.stream(mav.MAVLINK_MSG_ID_ATTITUDE, "ATTITUDE", 10.0)
        operator.stream(mav.MAVLINK_MSG_ID_SIM_STATE, "SIM_STATE", 10.0)
        cfg = write_config(tmp_path / "service.yaml", service_config(tmp_path, base + 2, zport))
        daemon = companion("run", "--config", str(cfg), log=tmp_path / "daemon.log")
        listener = ZenohListener(f"tcp/127.0.0.1:{zport}")
        operator.take_off(15.0, timeout_s=150.0 / SPEEDUP + 30.0)
        t_takeoff = time.monotonic()
        # Above control.min_alt_m the service streams velocity setpoints along the circuit: north first.
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline:
            operator.pump()
            while not listener.status.empty():
                statuses.append(listener.status.get_nowait())
            if operator.truth and operator.truth[-1][1] > north_hi + 10.0:
                break
        statuses.append(listener.latest_status())
    finally:
        if listener:
            listener.close()
        rc = stop(daemon, 10.0) if daemon else None
        if operator:
            operator.close()
        stop(sitl, 5.0)
    wall = time.monotonic() - t_start

    truth = operator.truth
    over = [up for _, n, _, up in truth if north_lo <= n <= north_hi]
    final = statuses[-1]
    nav, streams, commanding = final["nav"], final["streams"], final["commanding"]
    mapped = final["mapper"]["frames_mapped"]
    print(f"\nwall {wall:.0f} s (speedup {SPEEDUP:g}); SITL boot times: {operator.events}; takeoff at wall "
          f"{t_takeoff - t_start:.0f} s")
    print(f"covariance_source {nav['covariance_source']}; blocks {nav.get('covariance_blocks')}")
    print("streams: " + ", ".join(f"{k} {v['result']} {v['rate_hz']} Hz" for k, v in streams.items()))
    print(f"frames mapped {mapped}, map {final['map']}, setpoints sent {commanding['setpoints_sent']} "
          f"({commanding['setpoint_rate_hz']} Hz), not sent {commanding['setpoints_not_sent']}, reason {commanding['reason']}")
    print(f"truth: furthest north {max(n for _, n, _, _ in truth):.1f} m, highest {max(u for *_, u in truth):.1f} m, "
          f"over the building {min(over, default=float('nan')):.1f} .. {max(over, default=float('nan')):.1f} m; "
          f"tiles on Zenoh {len(listener.tiles)}; service exit {rc}")
    assert rc == 0
    assert nav["covariance_source"] == "EKF_STATUS_REPORT+GPS_RAW_INT+floors"
    for name in ("ODOMETRY", "LOCAL_POSITION_NED_COV", "ATTITUDE_QUATERNION_COV", "ESTIMATOR_STATUS"):
        assert streams[name]["result"] == "DENIED", (name, streams[name])
    for name in ("LOCAL_POSITION_NED", "ATTITUDE_QUATERNION", "EKF_STATUS_REPORT", "GPS_RAW_INT", "SIM_STATE"):
        assert streams[name]["result"] == "ACCEPTED" and streams[name]["arriving"], (name, streams[name])
    assert final["truth"]["origin_source"] == "GPS_GLOBAL_ORIGIN"
    assert mapped > 100
    assert commanding["setpoints_sent"] > 50 and commanding["setpoints_not_sent"] == 0
    # GUIDED holds position after takeoff: getting past the building means the setpoints were followed.
    assert max(n for _, n, _, _ in truth) > north_hi + 10.0, "the vehicle did not follow the velocity setpoints"
    # ... and it climbed for the building (12 m roof, 15 m clearance, nominal 15 m): above the roof by
    # half the clearance at the highest, never within 3 m of it.
    assert over, "no truth sample over the building"
    assert max(over) > building.height_m + 0.5 * 15.0 and min(over) > building.height_m + 3.0, (min(over), max(over))
    # the real SITL's order: EKF origin first, GPS use (and LOCAL_POSITION_NED, arming) about 20 s later
    assert operator.events["origin set"] < operator.events["is using GPS"] <= operator.events["armed"]
    assert len(listener.tiles) > 0 and final["map"]["tiles"] > 0
