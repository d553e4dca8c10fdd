"""Time sync glue: TIMESYNC round trips to the autopilot (and answers to its own), fed to
:class:`companion.method.navigation.timesync.TimeSync`, and what the link does when the autopilot's
time base changes: a reboot resets navigation and asks for the streams again; a confirmed jump of
its clock clears the navigation history.

:class:`TimeSyncing` is one part of :class:`drivers.autopilot.link.AutopilotLink`; it works on the
link's ``timesync``, ``assembler``, ``nav_buffer`` and ``_timesync_sent``.
"""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger("drivers.autopilot")  # one logger for the whole link, whichever part speaks


class TimeSyncing:
    """The time-sync part of the link (see the module docstring)."""

    async def _timesync_loop(self) -> None:
        period = 1.0 / self.cfg.link.timesync_rate_hz
        while True:
            await self.clock.sleep(period)
            if self._target is None:
                continue
            now = self.clock.now()
            ts1 = int(now * 1e9) + 1  # never 0; tc1 = 0 marks a request
            if self._send(self._mav.timesync_encode(0, ts1)):
                self._timesync_sent[ts1] = now
                while len(self._timesync_sent) > 16:
                    self._timesync_sent.pop(next(iter(self._timesync_sent)))

    def _on_timesync(self, m: Any, now: float) -> None:
        if m.tc1 == 0:  # the autopilot asks for our time (PX4 does, ArduPilot may): answer
            self._send(self._mav.timesync_encode(int(now * 1e9) + 1, m.ts1))
            return
        t_sent = self._timesync_sent.pop(m.ts1, None)
        if t_sent is None:
            return  # an answer to somebody else's request (replies are broadcast)
        if not self.timesync.add_roundtrip(t_sent, m.tc1 * 1e-9, now):
            self.time_rejections["round trip"] = self.time_rejections.get("round trip", 0) + 1
            self._limiter(logging.WARNING, "time-round-trip", "autopilot link: a TIMESYNC answer was unusable (too slow, or off the autopilot's clock)")
        self._check_reboot(now)

    def _check_reboot(self, now: float) -> None:
        """React to a change of the autopilot's time base: a reboot, or a confirmed jump of its clock."""
        if self.timesync.resets != self._seen_time_resets and self.timesync.reboots == self.reboots:
            self._seen_time_resets = self.timesync.resets
            log.warning("autopilot link: the autopilot's time mapping changed (its clock jumped); navigation history cleared")
            self.assembler.forget_state()
            self.nav_buffer.clear()  # stamps before and after the jump are not comparable
            return
        self._seen_time_resets = self.timesync.resets
        if self.timesync.reboots != self.reboots:
            self.reboots = self.timesync.reboots
            log.warning("autopilot link: the autopilot rebooted (its clock went backwards); resetting navigation and streams")
            self.assembler.reset()
            self.nav_buffer.clear()
            self._need_stream_request = True
            self._want_oneshots_again(now)
            self.send_statustext("WARNING", "companion: autopilot reboot detected")
