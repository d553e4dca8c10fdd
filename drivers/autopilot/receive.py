"""Receiving: bytes -> MAVLink frames -> the handlers, and navigation messages -> NavState -> the buffer.

Framing is :class:`drivers.autopilot.framing.MavlinkFramer`: bad input becomes a counted rejection
(by category, logged once per kind and then at most every 30 s), never an exception, and the valid
frames around it get through. Messages from anything but the autopilot the link follows are counted
and dropped; a message stamped off the autopilot's clock is dropped (one stray stamp is not a
reboot); navigation messages go to :class:`companion.method.navigation.assembler.NavAssembler` and
the states it produces to the link's :attr:`nav_buffer`, which is cleared whenever the estimate or
the time base jumps, so that it never interpolates across one.

:class:`Receiving` is one part of :class:`drivers.autopilot.link.AutopilotLink`.
"""

from __future__ import annotations

import logging
from typing import Any

from companion.method.navigation.assembler import HANDLED_MESSAGES
from drivers.autopilot.framing import Rejected

log = logging.getLogger("drivers.autopilot")  # one logger for the whole link, whichever part speaks
IGNORED_SOURCES_KEPT = 16  # the status lists at most this many other systems/components heard


class Receiving:
    """The receiving part of the link (see the module docstring)."""

    def _on_bytes(self, data: bytes, packet_end: bool = False) -> bool:
        """Frame, check and dispatch received bytes; True if at least one frame was acceptable."""
        self.bytes_rx += len(data)
        try:
            items = self._framer.feed(data, packet_end)
        except Exception as exc:  # the framer does not raise; if it ever does, drop the buffer and go on
            self._count_wire(f"framing error: {type(exc).__name__}", str(exc))
            self._framer.reset()
            return False
        now = self.clock.now()
        accepted = False
        for m in items:
            if isinstance(m, Rejected):
                self._count_wire(m.category, m.detail)
                continue
            accepted = True
            if self._tlog is not None:
                self._log_packet(now, m.get_msgbuf())
            try:
                self._dispatch(m, now)
            except Exception as exc:  # one bad message must not stop the others
                kind = m.get_type()
                self.handler_errors[kind] = self.handler_errors.get(kind, 0) + 1
                self._error(f"autopilot link: error handling {kind}: {exc!r}", key=f"handler-{kind}")
                log.debug("handler error", exc_info=True)
        return accepted

    def _count_wire(self, category: str, detail: str) -> None:
        self.wire_errors[category] = self.wire_errors.get(category, 0) + 1
        self._limiter(
            logging.WARNING,
            f"wire-{category}",
            f"autopilot link {self.endpoint}: corrupt MAVLink input ({category}: {detail[:80]}); "
            "check the baud rate, that only MAVLink is written to this port, and the signing key",
        )

    def _dispatch(self, m: Any, now: float) -> None:
        kind = m.get_type()
        self.messages_rx += 1
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == (self.cfg.link.source_system, self.cfg.link.source_component):
            return  # our own traffic echoed by a router
        if kind == "HEARTBEAT":
            self._on_heartbeat(m, src, now)
            return
        if self._target is None or src != self._target:
            self._ignore(src)
            return
        self.rates.tick(kind, now)
        if kind == "TIMESYNC":
            self._on_timesync(m, now)
            return
        if kind == "COMMAND_ACK":
            self._on_command_ack(m)
            return
        if kind == "STATUSTEXT":
            self._limiter(logging.INFO, f"ap-text-{m.text}", f"autopilot says: {m.text}")
            return
        boot_ms = getattr(m, "time_boot_ms", None)
        if boot_ms:
            verdict = self.timesync.check_remote_time(boot_ms * 1e-3, now)
            self._check_reboot(now)
            if verdict in ("behind", "ahead"):
                # One stamp off the autopilot's clock is a stray or corrupt message, not a reboot (that
                # takes several consistent ones): it must not move the time base or reach the state.
                self.time_rejections[verdict] = self.time_rejections.get(verdict, 0) + 1
                self._limiter(logging.WARNING, f"time-{verdict}",
                              f"autopilot link: {kind} stamped {boot_ms} ms dropped: {verdict} the autopilot's clock (one stray stamp is not a reboot)")
                return
        if kind == "SYSTEM_TIME" and m.time_boot_ms:
            self.timesync.add_one_way(m.time_boot_ms * 1e-3, now)
            self._check_reboot(now)
        if kind in HANDLED_MESSAGES:
            nav = self.assembler.update(m, now)
            if self.assembler.estimator_resets != self._seen_estimator_resets:
                self._seen_estimator_resets = self.assembler.estimator_resets
                self.nav_buffer.clear()  # the estimate jumped: never interpolate across a reset
            if self.assembler.time_basis_changes != self._seen_basis_changes:
                self._seen_basis_changes = self.assembler.time_basis_changes
                self.nav_buffer.clear()  # arrival-stamped and synchronised states are not mixed
            if nav is not None and not self.nav_buffer.push(nav):
                self._limiter(logging.WARNING, "nav-buffer", f"autopilot link: navigation state not buffered ({self.nav_buffer.rejected})")

    def _ignore(self, src: tuple[int, int]) -> None:
        """A message from a system/component that is not our autopilot (GCS, gimbal, another vehicle)."""
        self.ignored_messages += 1
        key = f"{src[0]}/{src[1]}"
        if key in self.ignored_sources or len(self.ignored_sources) < IGNORED_SOURCES_KEPT:
            self.ignored_sources[key] = self.ignored_sources.get(key, 0) + 1
        else:
            self.ignored_sources["others"] = self.ignored_sources.get("others", 0) + 1
