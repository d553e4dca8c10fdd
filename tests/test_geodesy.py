"""Local frames on the Earth: each autopilot's mapping, and one vehicle's map placed in another's frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.method.geodesy import PROJECTIONS, LocalFrame, _ecef, _geodetic, place_cells, transform

ORIGIN = (47.397742, 8.545594, 488.0)  # the SITL default home


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_local_to_geodetic_and_back(projection):
    frame = LocalFrame(*ORIGIN, projection)
    p = np.random.default_rng(3).uniform(-2000.0, 2000.0, (500, 3))
    back = frame.from_geodetic(*frame.to_geodetic(p))
    # Exact but for rounding, except the tangent plane's own departure from the ellipsoid (d^3 / 2 R^2).
    tolerance = 1e-6 if projection != "wgs84" else 3e-4
    np.testing.assert_allclose(back, p, atol=tolerance, rtol=0)


def test_ardupilot_scaling_is_its_location_scaling_factor():
    """1e-7 degree of latitude is 0.011131884502145034 m; east scales by cos of the mean latitude."""
    frame = LocalFrame(*ORIGIN, "ardupilot")
    north = frame.from_geodetic(ORIGIN[0] + 1e-7 * 10000, ORIGIN[1], ORIGIN[2])[0, 0]
    assert north == pytest.approx(10000 * 0.011131884502145034, rel=1e-9)  # (the latitude difference rounds)
    lat2 = ORIGIN[0] + 0.004
    east = frame.from_geodetic(lat2, ORIGIN[1] + 0.003, ORIGIN[2])[0, 1]
    expected = 0.003 * 1e7 * 0.011131884502145034 * math.cos(math.radians(0.5 * (ORIGIN[0] + lat2)))
    assert east == pytest.approx(expected, rel=1e-9)


def test_px4_keeps_distance_and_bearing_from_the_origin_on_its_sphere():
    frame = LocalFrame(*ORIGIN, "px4")
    bearing, distance = math.radians(37.0), 900.0
    lat, lon, _ = frame.to_geodetic(np.array([[distance * math.cos(bearing), distance * math.sin(bearing), 0.0]]))
    # Great-circle distance and initial bearing on a 6 371 000 m sphere, from the haversine formula.
    p1, p2 = math.radians(ORIGIN[0]), math.radians(lat[0])
    dl = math.radians(lon[0] - ORIGIN[1])
    h = math.sin((p2 - p1) / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    assert 2 * 6371000.0 * math.asin(math.sqrt(h)) == pytest.approx(distance, abs=1e-6)
    b = math.atan2(math.sin(dl) * math.cos(p2), math.cos(p1) * math.sin(p2) - math.sin(p1) * math.cos(p2) * math.cos(dl))
    assert b == pytest.approx(bearing, abs=1e-9)


def test_ecef_round_trip_and_a_known_point():
    lat, lon, h = np.array([47.397742, -33.9, 0.0]), np.array([8.545594, 151.2, 0.0]), np.array([488.0, -20.0, 0.0])
    ecef = _ecef(lat, lon, h)
    np.testing.assert_allclose(ecef[2], [6378137.0, 0.0, 0.0], atol=1e-9)  # (0, 0, 0): on the equator's x axis
    back = _geodetic(ecef)
    np.testing.assert_allclose(back[0], lat, atol=1e-10)
    np.testing.assert_allclose(back[1], lon, atol=1e-10)
    np.testing.assert_allclose(back[2], h, atol=1e-6)


@pytest.mark.parametrize("source_projection,target_projection", [("ardupilot", "ardupilot"), ("px4", "ardupilot"),
                                                                   ("ardupilot", "px4"), ("wgs84", "px4")])
def test_another_vehicles_points_land_where_the_world_has_them(source_projection, target_projection):
    """Two vehicles whose EKF origins are 300 to 800 m apart and 4 to 30 m apart in altitude: terrain
    points known by latitude, longitude and altitude, expressed in vehicle B's frame and transformed
    into A's, are where A's own frame puts them, to a millimetre."""
    rng = np.random.default_rng(11)
    a = LocalFrame(*ORIGIN, target_projection)
    for _ in range(5):
        bearing, distance = rng.uniform(0, 2 * math.pi), rng.uniform(300.0, 800.0)
        dlat = distance * math.cos(bearing) / 111_000.0
        dlon = distance * math.sin(bearing) / (111_000.0 * math.cos(math.radians(ORIGIN[0])))
        b = LocalFrame(ORIGIN[0] + dlat, ORIGIN[1] + dlon, ORIGIN[2] + rng.uniform(4.0, 30.0), source_projection)
        lat = ORIGIN[0] + rng.uniform(-0.01, 0.01, 200)
        lon = ORIGIN[1] + rng.uniform(-0.01, 0.01, 200)
        alt = ORIGIN[2] + rng.uniform(-5.0, 40.0, 200)
        in_b = b.from_geodetic(lat, lon, alt)
        in_a = a.from_geodetic(lat, lon, alt)
        assert np.abs(in_b - in_a).max() > 250.0  # the frames really differ
        np.testing.assert_allclose(transform(in_b, b, a), in_a, atol=1e-3, rtol=0)


def test_a_tile_of_another_vehicle_is_placed_cell_by_cell():
    """A tile of B (cell centres, heights up) placed in A's frame: positions and heights agree with the
    geodetic truth, and a height is shifted by the origins' altitude difference."""
    a = LocalFrame(*ORIGIN, "ardupilot")
    b = LocalFrame(ORIGIN[0] + 0.003, ORIGIN[1] - 0.005, ORIGIN[2] + 12.5, "ardupilot")
    ii, jj = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    north_b, east_b = (64 + ii + 0.5) * 1.0, (-32 + jj + 0.5) * 1.0
    height_b = 3.0 + 0.1 * ii
    n, e, h = place_cells(north_b, east_b, height_b, b, a)
    lat, lon, alt = b.to_geodetic(np.stack([north_b.ravel(), east_b.ravel(), -height_b.ravel()], axis=1))
    truth = a.from_geodetic(lat, lon, alt)
    np.testing.assert_allclose(np.c_[n, e], truth[:, :2], atol=1e-6)
    np.testing.assert_allclose(h, height_b.ravel() + 12.5, atol=1e-9)


def test_a_bad_frame_is_refused():
    with pytest.raises(ValueError, match="projection"):
        LocalFrame(*ORIGIN, "mercator")
    with pytest.raises(ValueError, match="out of range"):
        LocalFrame(95.0, 8.0, 0.0)
    frame = LocalFrame.from_dict({"origin": {"lat_deg": ORIGIN[0], "lon_deg": ORIGIN[1], "alt_m": ORIGIN[2]}, "projection": "px4"})
    assert frame == LocalFrame(*ORIGIN, "px4")
