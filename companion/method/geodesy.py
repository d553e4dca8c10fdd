"""Placing one vehicle's local frame on the Earth, and another's in it (docs/conventions.md,
"The local frame on the Earth").

Every vehicle maps in its autopilot's local NED frame: metres north, east and down from the EKF
origin (GPS_GLOBAL_ORIGIN). Two vehicles have two origins, and the autopilots do not agree on how
a local offset maps to latitude and longitude, so placing a tile of one in the frame of another
needs both origins and both mappings. The mappings are the autopilots' own (facts from their
sources, formulas written here):

* ``ardupilot``: equirectangular on a sphere of radius 6 378 100 m (``Location``
  offsets): north = dlat * R, east = dlon * R * cos(mean latitude of the two points), R being
  ArduPilot's RADIUS_OF_EARTH (one 1e-7 degree of latitude is 0.011131884502145034 m);
* ``px4``: azimuthal equidistant projection about the origin on a sphere of R = 6 371 000 m
  (``MapProjection``): distances and bearings from the origin are exact on that sphere;
* ``wgs84``: the WGS-84 ellipsoid's tangent plane at the origin, for recordings made in a true
  local tangent frame (e.g. from RTK or photogrammetry).

Down is the altitude difference from the origin in all three (the autopilots' local z): a height
``h`` (up) in one frame is ``h + alt0_from - alt0_to`` in the other. Pure functions, NumPy arrays,
no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from typing import Any

import numpy as np

PROJECTIONS = ("ardupilot", "px4", "wgs84")
ARDUPILOT_RADIUS_M = 6378100.0  # RADIUS_OF_EARTH: LOCATION_SCALING_FACTOR = 1e-7 * pi / 180 * this
PX4_RADIUS_M = 6371000.0  # CONSTANTS_RADIUS_OF_EARTH
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass(frozen=True, slots=True)
class LocalFrame:
    """A vehicle's local NED frame: its origin (deg, deg, m) and its autopilot's projection."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    projection: str = "ardupilot"

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            raise ValueError(f"frame projection must be one of {PROJECTIONS}, got {self.projection!r}")
        if not (abs(self.lat_deg) < 90.0 and abs(self.lon_deg) <= 180.0 and math.isfinite(self.alt_m)):
            raise ValueError(f"frame origin out of range: {self.lat_deg}, {self.lon_deg}, {self.alt_m}")

    @classmethod
    def from_dict(cls, d: dict) -> "LocalFrame":
        """From the ``frame`` object of the status (docs/zenoh.md)."""
        o = d["origin"]
        return cls(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_m"]), str(d.get("projection", "ardupilot")))

    @classmethod
    def from_status(cls, status: Any) -> "LocalFrame | None":
        """The sender's frame from a ``companion.status/1`` document, None while it has no origin
        (or the document is not one)."""
        frame = status.get("frame") if isinstance(status, dict) else None
        if not isinstance(frame, dict) or not isinstance(frame.get("origin"), dict):
            return None
        try:
            return cls.from_dict({**frame, "projection": frame.get("projection") or "ardupilot"})
        except (KeyError, TypeError, ValueError):
            return None

    def to_geodetic(self, ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) local NED (m) -> latitude, longitude (deg) and altitude (m), each (N,)."""
        p = np.asarray(ned, dtype=np.float64).reshape(-1, 3)
        alt = self.alt_m - p[:, 2]
        if self.projection == "ardupilot":
            lat = self.lat_deg + np.degrees(p[:, 0] / ARDUPILOT_RADIUS_M)
            scale = np.cos(np.radians(0.5 * (lat + self.lat_deg)))
            lon = self.lon_deg + np.degrees(p[:, 1] / (ARDUPILOT_RADIUS_M * scale))
            return lat, _wrap(lon), alt
        if self.projection == "px4":
            lat, lon = _aeqd_inverse(p[:, 0], p[:, 1], self.lat_deg, self.lon_deg, PX4_RADIUS_M)
            return lat, lon, alt
        # The horizontal position on the tangent plane at the origin's height; down is the altitude
        # difference, as in the autopilots' frames (the plane's departure from the ellipsoid, d^2/2R,
        # moves the horizontal position by d^3/2R^2: micrometres at a kilometre).
        flat = np.stack([p[:, 0], p[:, 1], np.zeros(len(p))], axis=1)
        lat, lon, _ = _geodetic(_ecef(self.lat_deg, self.lon_deg, 0.0) + flat @ _ned_rotation(self.lat_deg, self.lon_deg))
        return lat, lon, alt

    def from_geodetic(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        """Latitude, longitude (deg), altitude (m), broadcast to (N,) -> (N, 3) local NED (m)."""
        lat, lon, alt = (np.asarray(x, dtype=np.float64).reshape(-1) for x in np.broadcast_arrays(lat_deg, lon_deg, alt_m))
        down = self.alt_m - alt
        if self.projection == "ardupilot":
            north = np.radians(lat - self.lat_deg) * ARDUPILOT_RADIUS_M
            scale = np.cos(np.radians(0.5 * (lat + self.lat_deg)))
            east = np.radians(_wrap(lon - self.lon_deg)) * ARDUPILOT_RADIUS_M * scale
            return np.stack([north, east, down], axis=1)
        if self.projection == "px4":
            north, east = _aeqd_forward(lat, lon, self.lat_deg, self.lon_deg, PX4_RADIUS_M)
            return np.stack([north, east, down], axis=1)
        d = _ecef(lat, lon, np.zeros_like(lat)) - _ecef(self.lat_deg, self.lon_deg, 0.0)
        ne = d @ _ned_rotation(self.lat_deg, self.lon_deg).T
        return np.stack([ne[:, 0], ne[:, 1], down], axis=1)


def transform(ned: np.ndarray, source: LocalFrame, target: LocalFrame) -> np.ndarray:
    """(N, 3) points in ``source``'s local NED -> the same points in ``target``'s (m)."""
    lat, lon, alt = source.to_geodetic(ned)
    return target.from_geodetic(lat, lon, alt)


def place_cells(north_m: np.ndarray, east_m: np.ndarray, height_m: np.ndarray,
                source: LocalFrame, target: LocalFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell centres and heights (up) of a map in ``source`` -> north, east, height in ``target``,
    each (N,): e.g. another vehicle's tile (docs/zenoh.md, "Placing another vehicle's tiles")."""
    p = np.stack([np.ravel(north_m), np.ravel(east_m), -np.ravel(height_m)], axis=1).astype(np.float64)
    q = transform(p, source, target)
    return q[:, 0], q[:, 1], -q[:, 2]


def _wrap(lon_deg: np.ndarray) -> np.ndarray:
    return (np.asarray(lon_deg) + 180.0) % 360.0 - 180.0


def _aeqd_forward(lat_deg, lon_deg, lat0_deg, lon0_deg, radius):
    """Azimuthal equidistant projection about (lat0, lon0) on a sphere: (north, east) (m)."""
    lat, dlon = np.radians(lat_deg), np.radians(_wrap(np.asarray(lon_deg) - lon0_deg))
    lat0 = math.radians(lat0_deg)
    s0, c0 = math.sin(lat0), math.cos(lat0)
    cos_c = np.clip(s0 * np.sin(lat) + c0 * np.cos(lat) * np.cos(dlon), -1.0, 1.0)
    c = np.arccos(cos_c)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(c > 0.0, c / np.sin(c), 1.0)
    north = k * (c0 * np.sin(lat) - s0 * np.cos(lat) * np.cos(dlon)) * radius
    east = k * np.cos(lat) * np.sin(dlon) * radius
    return north, east


def _aeqd_inverse(north, east, lat0_deg, lon0_deg, radius):
    """Inverse of :func:`_aeqd_forward`: (lat, lon) (deg)."""
    x, y = np.asarray(north) / radius, np.asarray(east) / radius
    c = np.hypot(x, y)
    lat0 = math.radians(lat0_deg)
    s0, c0 = math.sin(lat0), math.cos(lat0)
    sin_c, cos_c = np.sin(c), np.cos(c)
    with np.errstate(invalid="ignore", divide="ignore"):
        lat = np.where(c > 0.0, np.arcsin(np.clip(cos_c * s0 + x * sin_c * c0 / c, -1.0, 1.0)), lat0)
    lon = math.radians(lon0_deg) + np.arctan2(y * sin_c, c * c0 * cos_c - x * s0 * sin_c)
    return np.degrees(lat), _wrap(np.degrees(lon))


def _ecef(lat_deg, lon_deg, h_m) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack([(n + h_m) * np.cos(lat) * np.cos(lon), (n + h_m) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - WGS84_E2) + h_m) * np.sin(lat)], axis=-1)


def _ned_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3): rows are north, east, down in ECEF at (lat, lon); ``ned = R (ecef - ecef0)``."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [-cl * co, -cl * so, -sl]])


def _geodetic(ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (N, 3) -> latitude, longitude (deg), ellipsoidal height (m); fixed-point iteration
    on the latitude, converged to below a micrometre in five steps at these heights."""
    x, y, z = ecef[:, 0], ecef[:, 1], ecef[:, 2]
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(6):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return np.degrees(lat), np.degrees(np.arctan2(y, x)), h
