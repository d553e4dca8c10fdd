"""Waypoint guidance: flies the legs of a closed circuit and counts laps."""

import numpy as np
import pytest

from companion.method.guidance import WaypointGuidance


def fly(guidance, start, dt=0.1, steps=4000):
    p = np.array(start, dtype=float)
    path = [p.copy()]
    for _ in range(steps):
        out = guidance.update(p)
        p = p + out.velocity_ne_mps * dt
        path.append(p.copy())
    return np.array(path)


def test_circuit_is_flown_at_cruise_speed_and_laps_are_counted():
    square = [(0, 0), (100, 0), (100, 50), (0, 50)]
    g = WaypointGuidance(square, speed_mps=6.0)
    path = fly(g, (0.0, 0.0), dt=0.1, steps=3000)  # 300 s at 6 m/s = 1800 m = 6 laps of 300 m
    assert g.lap in (5, 6)
    speeds = np.linalg.norm(np.diff(path, axis=0), axis=1) / 0.1
    np.testing.assert_allclose(speeds, 6.0, atol=1e-9)
    # The path stays near the square's edges (distance to the nearest edge).
    edges = [(np.array(a, float), np.array(b, float)) for a, b in zip(square, square[1:] + square[:1])]

    def dist_to_edges(q):
        d = []
        for a, b in edges:
            t = np.clip(np.dot(q - a, b - a) / np.dot(b - a, b - a), 0, 1)
            d.append(np.linalg.norm(a + t * (b - a) - q))
        return min(d)

    assert max(dist_to_edges(q) for q in path[::10]) < 6.0


def test_converges_onto_leg_from_offset_start():
    g = WaypointGuidance([(0, 0), (200, 0), (200, 10)], speed_mps=5.0)
    path = fly(g, (0.0, 20.0), dt=0.1, steps=300)
    assert abs(path[-1][1]) < 0.5  # back on the east = 0 line
    assert g.update(path[-1]).yaw_rad == pytest.approx(0.0)


def test_rejects_bad_routes():
    with pytest.raises(ValueError):
        WaypointGuidance([(0, 0)], 5.0)
    with pytest.raises(ValueError):
        WaypointGuidance([(0, 0), (np.nan, 1)], 5.0)
