"""Horizontal guidance: the nominal trajectory the avoidance law modifies.

When the service commands the vehicle (ArduPilot GUIDED, PX4 OFFBOARD) it owns the whole
velocity setpoint, so it needs a horizontal route as well as the vertical law. This is the
simplest useful one: fly a closed circuit of (north, east) waypoints at a cruise speed along
straight legs, counting laps. The vertical channel comes from :mod:`companion.avoidance`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class GuidanceOutput:
    """velocity_ne_mps: (2,) horizontal velocity command; yaw_rad: heading of the leg;
    leg: index of the waypoint being flown to; lap: completed laps."""

    velocity_ne_mps: np.ndarray
    yaw_rad: float
    leg: int
    lap: int


class WaypointGuidance:
    """Line-following guidance over a closed circuit.

    The command points at a carrot ``lookahead_m`` ahead of the vehicle's projection on the
    current leg, so the vehicle converges onto the straight leg instead of cutting corners. A
    waypoint is reached when the vehicle passes within ``accept_radius_m`` of it or beyond the
    end of the leg. A lap is counted each time the first waypoint is passed again.
    """

    def __init__(self, waypoints_ne_m, speed_mps: float, lookahead_m: float = 8.0, accept_radius_m: float = 3.0):
        wp = np.asarray(waypoints_ne_m, dtype=float).reshape(-1, 2)
        if len(wp) < 2:
            raise ValueError("guidance needs at least two waypoints")
        if not np.all(np.isfinite(wp)):
            raise ValueError("waypoints must be finite")
        self.waypoints = wp
        self.speed_mps = float(speed_mps)
        self.lookahead_m = float(lookahead_m)
        self.accept_radius_m = float(accept_radius_m)
        self.target = 1
        self.lap = 0

    def _leg(self) -> tuple[np.ndarray, np.ndarray]:
        start = self.waypoints[(self.target - 1) % len(self.waypoints)]
        end = self.waypoints[self.target]
        return start, end

    def update(self, position_ne_m: np.ndarray) -> GuidanceOutput:
        """Advance along the circuit and return the horizontal velocity command."""
        p = np.asarray(position_ne_m, dtype=float)[:2]
        for _ in range(len(self.waypoints)):  # skip every waypoint already reached
            start, end = self._leg()
            leg = end - start
            length = float(np.linalg.norm(leg))
            along = float(np.dot(p - start, leg) / length) if length > 0 else 0.0
            if np.linalg.norm(end - p) > self.accept_radius_m and along < length:
                break
            self.target = (self.target + 1) % len(self.waypoints)
            if self.target == 1:
                self.lap += 1
        start, end = self._leg()
        leg = end - start
        length = float(np.linalg.norm(leg))
        direction = leg / length if length > 0 else np.zeros(2)
        along = float(np.clip(np.dot(p - start, direction), 0.0, length))
        carrot = start + direction * min(length, along + self.lookahead_m)
        to_carrot = carrot - p
        dist = float(np.linalg.norm(to_carrot))
        velocity = to_carrot / dist * self.speed_mps if dist > 1e-6 else np.zeros(2)
        yaw = float(np.arctan2(direction[1], direction[0]))
        return GuidanceOutput(velocity, yaw, self.target, self.lap)
