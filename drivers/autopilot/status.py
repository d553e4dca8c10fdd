"""The link's status: everything an operator needs to judge it, as plain JSON-serialisable data
(docs/mavlink.md, "Status"); the daemon publishes it with its own.

:class:`LinkStatus` is one part of :class:`drivers.autopilot.link.AutopilotLink`.
"""

from __future__ import annotations

from typing import Any

from companion.method.navigation.assembler import TruthPose
from drivers.autopilot.protocol import mav_type_name


class LinkStatus:
    """The status part of the link (see the module docstring)."""

    def status(self) -> dict[str, Any]:
        """Everything an operator needs to judge the link, as plain JSON-serialisable data."""
        now = self.clock.now()
        hb = self._heartbeat
        ts = self.timesync.status()
        latest = self.nav_buffer.latest()
        ok, reason = self.can_command()
        rejected = {f"nav: {k}": v for k, v in self.assembler.rejections.counts.items()}
        rejected.update({f"wire: {k}": v for k, v in self.wire_errors.items()})
        rejected.update({f"nav buffer: {k}": v for k, v in self.nav_buffer.rejected.items()})
        rejected.update({f"handler: {k}": v for k, v in self.handler_errors.items()})
        rejected.update({f"time: {k}": v for k, v in self.time_rejections.items()})
        sp = self.last_setpoint
        return {
            "link": {
                "state": self._state,
                "endpoint": str(self.endpoint),
                "local_address": None if self.local_address is None else list(self.local_address[:2]),
                "autopilot": None
                if hb is None
                else {
                    "system": self._target[0] if self._target else None,
                    "component": self._target[1] if self._target else None,
                    "flavour": self.flavour,
                    "type": mav_type_name(hb.type),
                    "mode": self.mode,
                    "armed": self.armed,
                    "system_status": hb.system_status,
                },
                "heartbeat_age_s": None if self._last_heartbeat is None else round(now - self._last_heartbeat, 3),
                "connects": self.connects,
                "reconnects": self.reconnects,
                "link_losses": self.link_losses,
                "autopilot_reboots": self.reboots,
                "bytes_rx": self.bytes_rx,
                "messages_rx": self.messages_rx,
                "messages_tx": self.messages_tx,
                "ignored_messages": self.ignored_messages,
                "ignored_sources": dict(self.ignored_sources),
                "dropped_writes": 0 if self._transport is None else self._transport.dropped_writes,
                "last_error": self.last_error,
                "telemetry_log": None if self._tlog is None else {"path": str(self._tlog_path), "records": self.tlog_records},
            },
            "streams": {
                s.name: {
                    "requested_hz": s.rate_hz,
                    "result": s.result,
                    "requests": s.requests,
                    "rate_hz": round(self.rates.rate(s.name, now), 2),
                    "arriving": self.rates.last(s.name) is not None and now - self.rates.last(s.name) < self.cfg.link.stream_check_s,
                }
                for s in self._streams.values()
            },
            "rates_hz": self.rates.rates(now),
            "nav": {
                "covariance_source": None if latest is None else latest.covariance_source,
                "age_s": None if latest is None else round(now - latest.t_s, 3),
                "samples": len(self.nav_buffer),
                **self.assembler.status(now),
            },
            "time": {
                "source": ts.source,
                "offset_s": ts.offset_s,
                "jitter_s": ts.jitter_s,
                "rtt_s": ts.rtt_s,
                "samples": ts.samples,
                "resets": ts.resets,
            },
            "rejected": rejected,
            "commanding": {
                "enabled": self.cfg.control.commanding_enabled,
                "active": ok,
                "reason": reason,
                "setpoints_sent": self.setpoints_sent,
                "setpoints_not_sent": self.setpoints_refused,
                "setpoint_rate_hz": round(self.setpoint_rate_hz(now), 2),
                "last_setpoint": None
                if sp is None
                else {
                    "age_s": round(now - sp.t_s, 3),
                    "velocity_ned_mps": list(sp.velocity_ned_mps),
                    "yaw_rad": sp.yaw_rad,
                    "commanded": sp.commanded,
                    "reason": sp.reason,
                    "type_mask": sp.type_mask,
                },
            },
            "truth": None if not self.cfg.link.request_sim_state else _truth_status(self.truth_pose(), now, self.assembler),
            "signing": None if self.signing is None else {
                "required": self.signing.required,
                "accepted_signed": self.signing.accepted_signed,
                "accepted_unsigned": self.signing.accepted_unsigned,
                "streams": len(self.signing.streams),
            },
        }


def _truth_status(truth: TruthPose | None, now: float, assembler) -> dict[str, Any] | None:
    """The latest truth, and how SIM_STATE was timed: ``paired`` with the attitude it followed, or
    stamped on ``arrival`` (``TruthPose``)."""
    if truth is None:
        return None
    return {
        "paired": assembler.truth_paired,
        "arrival": assembler.truth_unpaired,
        "age_s": round(now - truth.t_s, 3),
        "position_ned_m": [round(x, 3) for x in truth.position_ned_m.tolist()],
        "origin_source": truth.origin_source,
        "time_source": truth.time_source,
    }
