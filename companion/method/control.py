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
  when a route is configured, slowed to the law's speed limits (mapped terrain it cannot climb over
  in time; terrain the camera cannot see yet), else the vehicle's own horizontal velocity
  (advisory use);
* below ``control.min_alt_m`` nothing is to be sent: take-off and landing belong to the autopilot,
  and a velocity setpoint would cancel them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.method.avoidance import AvoidanceCommand, PullUpLaw, view_distance, view_speed_limit
from companion.method.geometry import camera_from_config, view_depression
from companion.config import CompanionConfig
from companion.method.guidance import WaypointGuidance
from companion.method.messages import NavState
from companion.method.terrain.grid import TerrainGrid


def level_flight_view_limit(cfg: CompanionConfig) -> tuple[float, float]:
    """(view distance m, view speed limit m/s) of the configured camera mount with the body level
    (docs/avoidance.md, "What the camera can see"): the most the view limit allows, since flying
    forward pitches the nose, and the camera, further down. An operator whose route's speed is above
    it will see the vehicle fly slower; a camera looking straight down sees no terrain ahead at all
    and allows no speed (set ``avoidance.view_speed_limit: false`` for a nadir survey camera)."""
    camera, mount = camera_from_config(cfg.camera)
    depression = view_depression(camera, mount, np.eye(3), cfg.camera.border_px)
    distance = view_distance(depression, cfg.avoidance)
    return distance, view_speed_limit(distance, cfg.avoidance)


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
        self._camera, self._mount = camera_from_config(cfg.camera)
        self._depression: float | None = None  # the camera's highest line of sight, averaged (rad)
        self._depression_t = 0.0
        self._climb_sent: float | None = None  # the last climb-rate setpoint sent, and its time
        self._climb_t = 0.0

    def _slew(self, climb: float, t_s: float, sending: bool) -> float:
        """The climb-rate setpoint moved from the last one by at most ``command_climb_accel_mps2`` dt
        up and ``accel_mps2`` dt down (docs/avoidance.md, "A smooth command"). The law's bound is a
        profile with acceleration a_c, so a limit above a_c leaves the climb it plans intact; what
        the limit removes are the steps between control ticks when the limiting cell changes, which
        pitch a multirotor and shake the features out of the camera's tracking. Starts afresh below
        ``control.min_alt_m`` (nothing is sent there) and after a gap of more than a second."""
        a = self.cfg.avoidance
        last, dt = self._climb_sent, t_s - self._climb_t
        if sending and last is not None and a.command_climb_accel_mps2 > 0 and 0.0 <= dt <= 1.0:
            climb = min(max(climb, last - a.accel_mps2 * dt), last + a.command_climb_accel_mps2 * dt)
        self._climb_sent, self._climb_t = (climb if sending else None), t_s
        return climb

    def _view_depression(self, nav: NavState) -> float:
        """How far below the horizontal the camera's highest line of sight looks, averaged over
        ``avoidance.view_smoothing_s`` (first order, in the navigation's time; docs/avoidance.md,
        "What the camera can see"). The attitude of the moment would close a loop: the limit slows
        the vehicle, it pitches its nose up to brake, the camera sees farther, the limit rises, it
        pitches down to speed up, and so on. Starts afresh after a gap of more than a second."""
        now = view_depression(self._camera, self._mount, nav.R_nb, self.cfg.camera.border_px)
        tau, last, dt = self.cfg.avoidance.view_smoothing_s, self._depression, nav.t_s - self._depression_t
        if last is not None and tau > 0.0 and 0.0 <= dt <= 1.0:
            now = last + (now - last) * dt / (tau + dt)
        self._depression, self._depression_t = now, nav.t_s
        return now

    @property
    def lap(self) -> int:
        return self.guidance.lap if self.guidance is not None else 0

    def decide(self, nav: NavState, grid: TerrainGrid) -> ControlDecision:
        """One control step on ``nav`` (finite, fresh: the caller checks age) and the map ``grid``
        (the caller holds its lock). ValueError from the law on a non-finite state."""
        a = self.cfg.avoidance
        yaw = None
        lap = 0
        intent = None
        if self.guidance is not None:
            out = self.guidance.update(nav.position_ned_m[:2])
            horizontal, yaw, lap = out.velocity_ne_mps, out.yaw_rad, out.lap
            intent = horizontal  # the law looks along the leg the vehicle is turning onto
        else:
            horizontal = np.asarray(nav.velocity_ned_mps, dtype=float)[:2]
        cmd = self.law.command(nav.position_ned_m, nav.velocity_ned_mps, grid, direction_ne=intent,
                               view_depression_rad=self._view_depression(nav))
        if self.guidance is not None and a.enabled:
            # Never faster than the law can clear the mapped terrain ahead at, nor than lets the
            # vehicle stop for terrain the camera has not seen yet (docs/avoidance.md).
            speed = float(np.hypot(horizontal[0], horizontal[1]))
            if speed > cmd.speed_limit_mps:
                horizontal = horizontal * (cmd.speed_limit_mps / speed)
        climb = cmd.climb_rate_mps
        if not a.enabled:  # nominal altitude only (demo --no-avoid); the law is still published
            climb = min(max(cmd.nominal_climb_mps, -a.max_descent_mps), a.max_climb_mps)
        send = nav.altitude_m >= self.cfg.control.min_alt_m
        climb = self._slew(climb, nav.t_s, send)
        velocity = np.array([horizontal[0], horizontal[1], -climb], dtype=float)
        return ControlDecision(cmd, velocity, yaw, lap, send)
