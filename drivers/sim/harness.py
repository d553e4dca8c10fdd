"""Start the simulated vehicle as a subprocess and talk to it with plain pymavlink.

For tests, benchmarks and the demo: :class:`SimVehicleProcess` runs ``python -m companion.cli sim``
with the given options, reads the endpoint lines it prints (``LISTENING tcp 127.0.0.1:PORT``) and
stops it with SIGTERM. :class:`MavClient` is a deliberately thin pymavlink client (it is not the
companion's autopilot link) with bounded waits everywhere.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

STARTUP_TIMEOUT_S = 20.0


@dataclass
class SimVehicleProcess:
    """``companion sim`` in a subprocess. Use as a context manager; ``endpoints`` maps kind -> port."""

    args: list[str]
    endpoints: dict[str, int] = field(default_factory=dict)
    command: list[str] = field(default_factory=lambda: [sys.executable, "-m", "companion.cli", "sim"])
    proc: subprocess.Popen | None = None
    stderr_path: str | None = None

    def start(self) -> "SimVehicleProcess":
        links = sum(a in ("--tcp-listen", "--udp-in", "--udp-out", "--camera-listen") for a in self.args)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self._stderr = open(self.stderr_path, "w") if self.stderr_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.command + list(self.args), stdout=subprocess.PIPE,
                                     stderr=self._stderr, text=True, env=env)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        lines = []
        while len(lines) < links:
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"companion sim printed no endpoint line within {STARTUP_TIMEOUT_S} s")
            line = self.proc.stdout.readline()
            if not line:
                rc = self.proc.wait(5)
                raise RuntimeError(f"companion sim exited with status {rc} before listening (args {self.args})")
            lines.append(line.strip())
        for line in lines:
            words = line.split()
            if words[0] == "LISTENING":
                self.endpoints[words[1]] = int(words[2].rsplit(":", 1)[1])
            elif words[0] == "SENDING":
                self.endpoints["udp-out"] = int(words[-1])
        return self

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, return the exit status (killed and -9 if it does not stop in time)."""
        if self.proc is None:
            return 0
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        rc = self.proc.returncode
        if self.proc.stdout:
            self.proc.stdout.close()
        if self._stderr not in (None, subprocess.DEVNULL):
            self._stderr.close()
        return rc

    def __enter__(self) -> "SimVehicleProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class MavClient:
    """A plain pymavlink GCS-like client (system 255, component 190 by default)."""

    def __init__(self, url: str, source_system: int = 255, source_component: int = 190):
        self.conn = mavutil.mavlink_connection(url, source_system=source_system, source_component=source_component,
                                               dialect="ardupilotmega", autoreconnect=False)
        self.mav = self.conn.mav
        self.target = (1, 1)
        self.statustexts: list[str] = []  # every STATUSTEXT seen, whatever recv was waiting for

    @classmethod
    def udp_listener(cls) -> "MavClient":
        """Listen on an ephemeral loopback port (give ``port`` to ``companion sim --udp-out``)."""
        return cls("udpin:127.0.0.1:0")

    @property
    def port(self) -> int:
        return self.conn.port.getsockname()[1]

    def close(self) -> None:
        self.conn.close()

    def recv(self, types=None, timeout_s: float = 2.0, condition=None):
        """Next message of ``types`` (name or list) satisfying ``condition``, or None after the timeout."""
        deadline = time.monotonic() + timeout_s
        if isinstance(types, str):
            types = [types]
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            m = self.conn.recv_match(blocking=True, timeout=min(remaining, 0.2))
            if m is None or m.get_type() == "BAD_DATA":
                continue
            if m.get_type() == "STATUSTEXT" and len(self.statustexts) < 10000:
                self.statustexts.append(m.text)
            if types is not None and m.get_type() not in types:
                continue
            if condition is None or condition(m):
                return m

    def latest(self, types, max_messages: int = 100000):
        """Read everything already received (no waiting); the newest message of ``types`` or None.

        For control loops: a client that reads one message per iteration falls behind a sped-up
        simulation and acts on stale state.
        """
        if isinstance(types, str):
            types = [types]
        newest = None
        for _ in range(max_messages):
            m = self.conn.recv_match(blocking=False)
            if m is None:
                break
            if m.get_type() == "STATUSTEXT" and len(self.statustexts) < 10000:
                self.statustexts.append(m.text)
            if m.get_type() in types:
                newest = m
        return newest

    def wait_statustext(self, predicate, timeout_s: float = 2.0) -> str | None:
        """The first STATUSTEXT (already seen or arriving within the timeout) whose text satisfies ``predicate``."""
        for text in self.statustexts:
            if predicate(text):
                return text
        m = self.recv("STATUSTEXT", timeout_s, lambda m: predicate(m.text))
        return None if m is None else m.text

    def wait_heartbeat(self, timeout_s: float = 5.0):
        hb = self.recv("HEARTBEAT", timeout_s, lambda m: m.get_srcComponent() == 1)
        if hb is None:
            raise TimeoutError("no HEARTBEAT from the vehicle")
        self.target = (hb.get_srcSystem(), hb.get_srcComponent())
        return hb

    def heartbeat(self) -> None:
        self.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)

    def command(self, command: int, *params: float, timeout_s: float = 3.0):
        """COMMAND_LONG; returns the matching COMMAND_ACK (or None)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.target[0], self.target[1], command, 0, *p)
        return self.recv("COMMAND_ACK", timeout_s, lambda m: m.command == command)

    def set_interval(self, msg_id: int, hz: float, timeout_s: float = 3.0):
        """MAV_CMD_SET_MESSAGE_INTERVAL; ``hz`` <= 0 stops the stream. Returns the ACK result."""
        interval = 1e6 / hz if hz > 0 else -1
        ack = self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval, timeout_s=timeout_s)
        return None if ack is None else ack.result

    def velocity_setpoint(self, vn: float, ve: float, vd: float, yaw: float | None = None) -> None:
        """SET_POSITION_TARGET_LOCAL_NED, velocity only (type_mask 3527, or 2503 with yaw)."""
        mask = 3527 if yaw is None else 2503
        self.mav.set_position_target_local_ned_send(0, self.target[0], self.target[1], mav.MAV_FRAME_LOCAL_NED, mask,
                                                    0, 0, 0, vn, ve, vd, 0, 0, 0, 0.0 if yaw is None else yaw, 0)
