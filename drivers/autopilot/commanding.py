"""Commanding the autopilot: COMMAND_LONG one at a time, velocity setpoints when (and only when)
they may be sent, STATUSTEXT to the ground station, and the guarded vehicle commands (mode, arm,
take-off) that the configuration must allow.

A setpoint is sent only when commanding is enabled, navigation is fresh and healthy and the vehicle
is in GUIDED (ArduPilot) / OFFBOARD (PX4); otherwise it is recorded as advisory and nothing is sent.

:class:`Commanding` is one part of :class:`drivers.autopilot.link.AutopilotLink`; it works on the
link's target, heartbeat, navigation buffer and assembler, and sends through the link's ``_send``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from drivers.autopilot.protocol import (
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_RESULT_IN_PROGRESS,
    PX4_MAIN_OFFBOARD,
    PX4_SET_MODE,
    SEVERITIES,
    TYPEMASK_ACCEL,
    TYPEMASK_POSITION,
    TYPEMASK_YAW,
    TYPEMASK_YAW_RATE,
    ardupilot_mode_table,
    result_name,
    statustext_chunks,
)


@dataclass(slots=True)
class SetpointRecord:
    """The latest setpoint handed to the link, commanded or advisory."""

    t_s: float
    velocity_ned_mps: tuple[float, float, float]
    yaw_rad: float | None
    yaw_rate_radps: float | None
    position_ned_m: tuple[float, float, float] | None
    commanded: bool
    reason: str
    type_mask: int


class LinkError(RuntimeError):
    """A command could not be sent (no autopilot on the link)."""


@dataclass(slots=True)
class PendingCommand:
    command: int
    future: asyncio.Future = field(repr=False)


class Commanding:
    """The commanding part of the link (see the module docstring)."""

    async def _command(self, command: int, params: tuple, retries: int | None = None) -> str:
        """COMMAND_LONG to the autopilot, one at a time; the MAV_RESULT name, or NO_ANSWER / NO_LINK."""
        if self._target is None or self._command_lock is None:
            return "NO_LINK"
        lc = self.cfg.link
        attempts = lc.command_retries if retries is None else retries
        async with self._command_lock:
            for confirmation in range(attempts):
                if self._target is None or self._transport is None:
                    return "NO_LINK"
                future: asyncio.Future = asyncio.get_running_loop().create_future()
                self._pending = PendingCommand(command, future)
                try:
                    p = [float(x) for x in params]
                    self._send(self._mav.command_long_encode(self._target[0], self._target[1], command, confirmation, *p))
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(self.clock.wall_seconds(lc.command_timeout_s)):
                            return await future
                finally:
                    self._pending = None
        return "NO_ANSWER"

    def _on_command_ack(self, m: Any) -> None:
        p = self._pending
        if p is None or m.command != p.command or p.future.done():
            return
        target_system = getattr(m, "target_system", 0)
        if target_system not in (0, self.cfg.link.source_system):
            return  # an ACK meant for another component
        if m.result == MAV_RESULT_IN_PROGRESS:
            return
        p.future.set_result(result_name(m.result))

    def can_command(self) -> tuple[bool, str]:
        """Whether a setpoint would be sent now, and why not."""
        c = self.cfg.control
        if not c.commanding_enabled:
            return False, "advisory: control.commanding_enabled is false"
        if self._state != "connected":
            return False, f"autopilot link {self._state}"
        now = self.clock.now()
        latest = self.nav_buffer.latest()
        if latest is None:
            return False, "no navigation received"
        age = now - latest.t_s
        if age > self.cfg.nav.stale_after_s:
            return False, f"navigation stale ({age:.2f} s old, limit {self.cfg.nav.stale_after_s:.2f} s)"
        ok, why = self.assembler.health(now)
        if not ok:
            return False, f"estimator unhealthy: {why}"
        if self._mode_accepts_setpoints():
            return True, f"commanding in {self.mode}"
        if self.flavour == "px4" and c.allow_mode_change:
            return True, "streaming setpoints before the switch to OFFBOARD (PX4 requires the stream first)"
        wanted = "GUIDED" if self.flavour == "ardupilot" else "OFFBOARD" if self.flavour == "px4" else "GUIDED/OFFBOARD"
        return False, f"mode {self.mode} does not accept setpoints (needs {wanted})"

    def _mode_accepts_setpoints(self) -> bool:
        hb = self._heartbeat
        if hb is None:
            return False
        if self.flavour == "ardupilot":
            return self.mode == "GUIDED"
        if self.flavour == "px4":
            return (hb.custom_mode >> 16) & 0xFF == PX4_MAIN_OFFBOARD
        return False

    def send_setpoint(
        self,
        velocity_ned_mps: Any,
        yaw_rad: float | None = None,
        yaw_rate_radps: float | None = None,
        position_ned_m: Any = None,
    ) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) when allowed; else record it as advisory.

        Velocity only: type_mask 3527 = ignore x, y, z (1+2+4), ax, ay, az (64+128+256), yaw (1024) and
        yaw rate (2048). ``yaw_rad`` / ``yaw_rate_radps`` clear their ignore bit. ``position_ned_m``
        (3,) sends position + velocity (feed-forward). A partial position (altitude only) is not
        offered: ArduPilot treats the three position bits as one ("any set -> position ignored").
        The caller streams at a steady rate (ArduPilot GUIDED stops after 3 s without a velocity
        setpoint; PX4 leaves OFFBOARD below 2 Hz); the link never repeats a setpoint on its own.
        Returns True when the message was sent.
        """
        v = np.asarray(velocity_ned_mps, dtype=float).reshape(-1)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"setpoint velocity must be 3 finite numbers (m/s, NED), got {velocity_ned_mps!r}")
        p = None
        if position_ned_m is not None:
            p = np.asarray(position_ned_m, dtype=float).reshape(-1)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError(f"setpoint position must be 3 finite numbers (m, NED), got {position_ned_m!r}")
        for name, value in (("yaw_rad", yaw_rad), ("yaw_rate_radps", yaw_rate_radps)):
            if value is not None and not math.isfinite(value):
                raise ValueError(f"setpoint {name} must be finite, got {value!r}")
        mask = TYPEMASK_ACCEL | (TYPEMASK_POSITION if p is None else 0)
        mask |= TYPEMASK_YAW if yaw_rad is None else 0
        mask |= TYPEMASK_YAW_RATE if yaw_rate_radps is None else 0
        ok, reason = self.can_command()
        now = self.clock.now()
        sent = False
        if ok and self._target is not None:
            pos = p if p is not None else np.zeros(3)
            msg = self._mav.set_position_target_local_ned_encode(
                int(now * 1000) & 0xFFFFFFFF,
                self._target[0],
                self._target[1],
                mavlink2.MAV_FRAME_LOCAL_NED,
                mask,
                *pos,
                *v,
                0.0,
                0.0,
                0.0,
                float(yaw_rad or 0.0),
                float(yaw_rate_radps or 0.0),
            )
            sent = self._send(msg)
            if not sent:
                reason = "transport dropped the setpoint"
        if sent:
            self.setpoints_sent += 1
            self._setpoint_times.append(now)
        else:
            self.setpoints_refused += 1
        self.last_setpoint = SetpointRecord(
            now, tuple(v.tolist()), yaw_rad, yaw_rate_radps, None if p is None else tuple(p.tolist()), sent, reason, mask
        )
        return sent

    def send_statustext(self, severity: int | str, text: str) -> int:
        """STATUSTEXT to the ground station; returns the number of chunks sent or queued.

        Text longer than 50 bytes goes out in chunks (MAVLink 2 ``id`` / ``chunk_seq``), split on UTF-8
        character boundaries, at most 5 chunks (longer text is truncated with '...'); a final full
        chunk is followed by an empty one so receivers see the end. While no autopilot is connected
        the text is queued (the last 16) and sent on reconnection.
        """
        if isinstance(severity, str):
            key = severity.upper().removeprefix("MAV_SEVERITY_")
            if key not in SEVERITIES:
                raise ValueError(f"unknown STATUSTEXT severity {severity!r}; one of {', '.join(SEVERITIES)}")
            level = SEVERITIES[key]
        else:
            level = int(severity)
            if not 0 <= level <= 7:
                raise ValueError(f"STATUSTEXT severity must be 0..7, got {severity}")
        chunks = statustext_chunks(str(text))
        if self._state != "connected":
            self._statustext_queue.append((level, str(text)))
            return len(chunks)
        return self._send_statustext_now(level, chunks)

    def _send_statustext_now(self, level: int, chunks: list[bytes]) -> int:
        if len(chunks) == 1:
            self._send(self._mav.statustext_encode(level, chunks[0], 0, 0))
            return 1
        self._statustext_id = self._statustext_id % 65535 + 1
        for seq, chunk in enumerate(chunks):
            self._send(self._mav.statustext_encode(level, chunk, self._statustext_id, seq))
        return len(chunks)

    # --- guarded vehicle commands ------------------------------------------------------------------

    def _require(self, allowed: bool, key: str, what: str) -> None:
        if not allowed:
            raise PermissionError(f"control.{key} is false: the service does not {what} unless configured to")
        if self._target is None or self._state != "connected":
            raise LinkError(f"cannot {what}: no autopilot connected (link {self._state})")

    async def set_mode(self, name: str) -> str:
        """Switch flight mode by name (GUIDED, OFFBOARD, LOITER, ...); only with ``control.allow_mode_change``."""
        self._require(self.cfg.control.allow_mode_change, "allow_mode_change", "change the flight mode")
        name = name.upper()
        if self.flavour == "px4":
            if name not in PX4_SET_MODE:
                raise ValueError(f"unknown PX4 mode {name!r}; one of {', '.join(PX4_SET_MODE)}")
            main, sub = PX4_SET_MODE[name]
            params = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub, 0, 0, 0, 0)
        else:
            table = ardupilot_mode_table(self._heartbeat.type if self._heartbeat else 2)
            numbers = {v: k for k, v in table.items()}
            if name not in numbers:
                raise ValueError(f"unknown mode {name!r} for this vehicle; one of {', '.join(sorted(numbers))}")
            params = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, numbers[name], 0, 0, 0, 0, 0)
        return await self._command(mavlink2.MAV_CMD_DO_SET_MODE, params)

    async def arm(self, force: bool = False) -> str:
        """Arm (MAV_CMD_COMPONENT_ARM_DISARM); only with ``control.allow_arm``."""
        self._require(self.cfg.control.allow_arm, "allow_arm", "arm the vehicle")
        return await self._command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (1, 21196 if force else 0, 0, 0, 0, 0, 0))

    async def disarm(self) -> str:
        self._require(self.cfg.control.allow_arm, "allow_arm", "disarm the vehicle")
        return await self._command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (0, 0, 0, 0, 0, 0, 0))

    async def takeoff(self, altitude_m: float) -> str:
        """MAV_CMD_NAV_TAKEOFF: ArduPilot climbs to ``altitude_m`` above home (GUIDED, armed); PX4 reads
        param7 as AMSL, so NaN is sent and PX4 uses MIS_TAKEOFF_ALT. Only with ``control.allow_arm``."""
        self._require(self.cfg.control.allow_arm, "allow_arm", "take off")
        alt = float(altitude_m) if self.flavour != "px4" else math.nan
        return await self._command(mavlink2.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, math.nan, math.nan, alt))

    def setpoint_rate_hz(self, now: float | None = None) -> float:
        now = self.clock.now() if now is None else now
        recent = [t for t in self._setpoint_times if now - t <= 2.0]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)
