"""The service's control decision: navigation state + terrain map -> velocity setpoint.

Pure: no link, no clock, no I/O. The daemon (companion/daemon.py) calls :meth:`Controller.decide`
once per control step and sends what it returns; the scenario suite's engine
(companion/quality/engine.py) calls the very same method in simulated time, so the suite flies
the service's own control code.

One decision:

* vertical: the pull-up / push-over law (:class:`companion.avoidance.PullUpLaw`) on the map; with
  ``avoidance.enabled`` false the nominal-altitude command alone (the law is still evaluated, and
  published, so an operator sees what it would have done);
* horizontal: the waypoint guidance along ``control.waypoints_ne_m`` at ``control.cruise_speed_mps``
  when a route is configured, else the vehicle's own horizontal velocity (advisory use);
* below ``control.min_alt_m`` nothing is to be sent: take-off and landing belong to the autopilot,
  and a velocity setpoint would cancel them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.method.avoidance import AvoidanceCommand, PullUpLaw
from companion.config import CompanionConfig
from companion.method.guidance import WaypointGuidance
from companion.method.messages import NavState
from companion.method.terrain.grid import TerrainGrid


@dataclass(frozen=True, slots=True)
class ControlDecision:
    """command: the law's output (published whatever is sent). velocity_ned_mps: (3,) setpoint,
    NED (down positive: ``-climb``). yaw_rad: heading of the guidance's leg (None without a route).
    lap: laps completed by the guidance (0 without a route). send: False below
    ``control.min_alt_m`` (advisory only)."""

    command: AvoidanceCommand
    velocity_ned_mps: np.ndarray
    yaw_rad: float | None
    lap: int
    send: bool

    @property
    def climb_rate_mps(self) -> float:
        return float(-self.velocity_ned_mps[2])


class Controller:
    """The law and the route of one vehicle, from its configuration."""

    def __init__(self, cfg: CompanionConfig) -> None:
        self.cfg = cfg
        self.law = PullUpLaw(cfg.avoidance)
        self.guidance = (
            WaypointGuidance(cfg.control.waypoints_ne_m, cfg.control.cruise_speed_mps)
            if len(cfg.control.waypoints_ne_m) >= 2 else None
        )

    @property
    def lap(self) -> int:
        return self.guidance.lap if self.guidance is not None else 0

    def decide(self, nav: NavState, grid: TerrainGrid) -> ControlDecision:
        """One control step on ``nav`` (finite, fresh: the caller checks age) and the map ``grid``
        (the caller holds its lock). ValueError from the law on a non-finite state."""
        a = self.cfg.avoidance
        cmd = self.law.command(nav.position_ned_m, nav.velocity_ned_mps, grid)
        yaw = None
        lap = 0
        if self.guidance is not None:
            out = self.guidance.update(nav.position_ned_m[:2])
            horizontal, yaw, lap = out.velocity_ne_mps, out.yaw_rad, out.lap
        else:
            horizontal = np.asarray(nav.velocity_ned_mps, dtype=float)[:2]
        climb = cmd.climb_rate_mps
        if not a.enabled:  # nominal altitude only (demo --no-avoid); the law is still published
            climb = min(max(cmd.nominal_climb_mps, -a.max_descent_mps), a.max_climb_mps)
        velocity = np.array([horizontal[0], horizontal[1], -climb], dtype=float)
        send = nav.altitude_m >= self.cfg.control.min_alt_m
        return ControlDecision(cmd, velocity, yaw, lap, send)
