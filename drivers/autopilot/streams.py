"""Stream requests: the messages the link asks the autopilot for, and what became of each request.

ArduPilot streams nothing until asked and a request made while it boots is acknowledged but lost,
so the link asks for every message it can use with MAV_CMD_SET_MESSAGE_INTERVAL (one command at a
time: a COMMAND_ACK names only the command), asks again with backoff for an accepted stream that
does not arrive, falls back to REQUEST_DATA_STREAM when the autopilot knows no message intervals,
and asks for the one-shot messages (GPS_GLOBAL_ORIGIN, HOME_POSITION) with MAV_CMD_REQUEST_MESSAGE
until they come.

:class:`StreamRequests` is one part of :class:`drivers.autopilot.link.AutopilotLink`; it works on the
link's ``_streams``, ``_oneshots``, ``_need_stream_request`` and ``_fallback_requested`` and sends
through the link's ``_command`` and ``_send``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

log = logging.getLogger("drivers.autopilot")  # one logger for the whole link, whichever part speaks


@dataclass(slots=True)
class StreamRequest:
    """One message the link asks for, and what became of the request."""

    name: str
    msg_id: int
    rate_hz: float
    result: str = "not requested"
    requests: int = 0
    requested_at: float | None = None
    next_check: float = 0.0
    backoff_s: float = 0.0
    wanted_since: float = -math.inf  # one-shot messages: only an arrival after this counts


class StreamRequests:
    """The stream-request part of the link (see the module docstring)."""

    def _wanted_streams(self) -> dict[str, StreamRequest]:
        """Every message the link can use, at its rate; the autopilot's answers show which exist."""
        lc = self.cfg.link
        nav, aux, ts = lc.nav_stream_rate_hz, lc.aux_stream_rate_hz, lc.timesync_rate_hz
        wanted = [
            ("LOCAL_POSITION_NED", nav),
            ("ATTITUDE_QUATERNION", nav),
            ("ODOMETRY", nav),  # PX4: pose + covariance; ArduPilot: DENIED
            ("LOCAL_POSITION_NED_COV", nav),
            ("ATTITUDE_QUATERNION_COV", nav),
            ("EKF_STATUS_REPORT", aux),  # ArduPilot innovation test ratios
            ("ESTIMATOR_STATUS", aux),  # PX4 accuracies and ratios
            ("GPS_RAW_INT", aux),  # h_acc / v_acc (mm)
            ("SYSTEM_TIME", ts),
        ]
        if lc.request_sim_state:
            wanted.append(("SIM_STATE", nav))
        return {name: StreamRequest(name, getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"), rate) for name, rate in wanted}

    async def _stream_loop(self) -> None:
        """Request the streams on (re)connection; re-request accepted streams that do not arrive."""
        while True:
            await self.clock.sleep(0.2)
            if self._state != "connected" or self._target is None:
                continue
            now = self.clock.now()
            if self._need_stream_request:
                self._need_stream_request = False
                for s in self._streams.values():
                    await self._request_stream(s)
                self._maybe_fallback()
                continue
            check = self.cfg.link.stream_check_s
            for s in self._streams.values():
                if s.result in ("DENIED", "UNSUPPORTED") or now < s.next_check:
                    continue
                last = self.rates.last(s.name)
                if last is not None and now - last < check:
                    s.backoff_s = check
                    s.next_check = now + check
                    continue
                if s.requested_at is not None and now - s.requested_at < check:
                    continue
                self._limiter(logging.INFO, f"stream-{s.name}", f"autopilot link: {s.name} ({s.result}) has not arrived for {check:.1f} s; requesting it again")
                await self._request_stream(s)
                s.backoff_s = min(max(2 * s.backoff_s, check), 30.0)
                s.next_check = self.clock.now() + s.backoff_s
            for o in self._oneshots.values():  # sent once by the autopilot (when it exists): ask until it comes
                last = self.rates.last(o.name)
                if last is not None and last >= o.wanted_since:
                    continue
                if now >= o.next_check:
                    o.result = await self._command(mavlink2.MAV_CMD_REQUEST_MESSAGE, (o.msg_id, 0, 0, 0, 0, 0, 0), retries=1)
                    o.requests += 1
                    o.backoff_s = min(max(2 * o.backoff_s, 2.0), 30.0)
                    o.next_check = self.clock.now() + o.backoff_s

    async def _request_stream(self, s: StreamRequest) -> None:
        interval_us = 1e6 / s.rate_hz
        s.result = await self._command(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (s.msg_id, interval_us, 0, 0, 0, 0, 0))
        s.requests += 1
        s.requested_at = self.clock.now()
        s.next_check = s.requested_at + self.cfg.link.stream_check_s
        if s.result != "ACCEPTED":
            self._limiter(logging.INFO, f"stream-result-{s.name}", f"autopilot link: SET_MESSAGE_INTERVAL {s.name} -> {s.result}")

    def _maybe_fallback(self) -> None:
        """Autopilots without SET_MESSAGE_INTERVAL: the older REQUEST_DATA_STREAM groups."""
        if self._fallback_requested or any(s.result in ("ACCEPTED", "DENIED") for s in self._streams.values()):
            return
        self._fallback_requested = True
        lc = self.cfg.link
        log.warning("autopilot link: SET_MESSAGE_INTERVAL not supported; falling back to REQUEST_DATA_STREAM")
        sys_id, comp_id = self._target  # type: ignore[misc]
        for stream_id, rate in (
            (mavlink2.MAV_DATA_STREAM_POSITION, lc.nav_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTRA1, lc.nav_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS, lc.aux_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTRA3, lc.aux_stream_rate_hz),
        ):
            self._send(self._mav.request_data_stream_encode(sys_id, comp_id, stream_id, max(1, int(round(rate))), 1))

    def _want_oneshots_again(self, now: float) -> None:
        """A new or rebooted autopilot: its origin and home must be asked for again."""
        for o in self._oneshots.values():
            o.wanted_since = now
            o.next_check = 0.0
            o.backoff_s = 0.0
