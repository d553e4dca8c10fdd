"""The demo's operator: a plain pymavlink client on the simulator's ``--udp-out`` endpoint that
switches to GUIDED, arms and takes off like an operator at a ground station, and records the true
trajectory (SIM_STATE)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

TRUTH_RATE_HZ = 25.0           # SIM_STATE (and ATTITUDE for its time stamp) to the pilot


class DemoError(RuntimeError):
    """A run could not start or went wrong in a way that makes its figures meaningless."""


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
