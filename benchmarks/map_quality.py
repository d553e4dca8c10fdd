"""Map quality in the simulated flight: mapper + terrain grid + avoidance law, in process.

What the closed loop of the daemon does, without MAVLink sockets or processes, deterministic
and fast (one lap of the default circuit in a few seconds):

* vehicle: the simulator's own ArduPilot Copter model (:class:`drivers.sim.ardupilot.ArduPilotCopter`:
  point-mass multirotor flown by its position controller, Gauss-Markov navigation error, GPS
  receiver), taken off in GUIDED and flown by the velocity setpoints the daemon would send
  (waypoint guidance along ``World.waypoints_ne_m`` at 6 m/s, vertical speed from
  :class:`companion.method.avoidance.PullUpLaw` on the map being built, or a constant altitude);
* camera: :class:`drivers.sim.renderer.Renderer` at the TRUE camera pose (the vehicle's truth and
  the configured :class:`CameraMount`), 640x480 at 15 Hz, with the sim's sensor noise;
* navigation: the mapper gets the :class:`NavState` that :class:`companion.method.navigation.assembler.NavAssembler`
  builds from the very messages the ArduPilot-flavour simulator sends (LOCAL_POSITION_NED,
  ATTITUDE_QUATERNION, GPS_RAW_INT, EKF_STATUS_REPORT): the estimate (truth + injected error)
  and the covariance the service would have (GPS accuracies + test ratios + floors);
* map: converged points go into a :class:`TerrainGrid`, whose ray cast is the mapper's depth prior
  (as in the daemon); at the end the grid is compared with ``World.true_height_grid``.

Every emitted point is also checked against the world: each measurement a feature took is ray
cast from the true camera pose, so we know which world point(s) the feature really tracked, and
each bad point (height error > 1 m) is classified (see :func:`classify_points`).

Run: ``python benchmarks/map_quality.py`` (default: 3 laps, both parameterisations, navigation
error on and off); ``--laps 1``, ``--quick``, ``--param inverse_depth``, ``--nav on`` narrow it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from companion.config import CompanionConfig, replace  # noqa: E402
from companion.desk import report  # noqa: E402
from companion.desk.quality import engine  # noqa: E402
from companion.method.avoidance import PullUpLaw, nominal_climb_rate  # noqa: E402
from companion.method.geometry import camera_from_config  # noqa: E402
from companion.method.guidance import WaypointGuidance  # noqa: E402
from companion.method.mapper import Mapper  # noqa: E402
from companion.method.mapper.features import HarrisDetector  # noqa: E402
from companion.method.messages import TerrainPoints  # noqa: E402
from companion.method.navigation.assembler import NavAssembler  # noqa: E402
from companion.method.terrain.grid import TerrainGrid  # noqa: E402
from drivers.sim.ardupilot import GUIDED, ArduPilotCopter  # noqa: E402
from drivers.sim.renderer import Renderer, RenderOptions  # noqa: E402
from drivers.sim.world import World  # noqa: E402

CONTROL_RATE_HZ = 20.0  # the daemon's control loop
GPS_MSG_RATE_HZ = 5.0  # GPS_RAW_INT as streamed to the service
EKF_MSG_RATE_HZ = 2.0  # EKF_STATUS_REPORT
BAD_HEIGHT_M = 1.0  # an emitted point whose height error exceeds this is classified
SPURIOUS_M = 2.0  # a cell whose error exceeds this is "spurious"


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunSpec:
    """One flight.

    parameterisation: mapper state ("inverse_depth" or "cartesian"). nav_error: inject the sim's
    navigation error (``cfg.sim`` sigmas) or fly with a perfect estimate. laps: circuits to fly
    (fractions allowed); ``stop_north_m`` ends the flight on the first leg once past this north
    coordinate instead (short tests). avoid: vertical speed from the pull-up law on the map being
    built (else hold ``altitude_m``). nav_covariance: "service" = what NavAssembler builds from the
    ArduPilot messages (GPS accuracies, test ratios, floors), "injected" = the sim's own error
    covariance (the truth about the error, for diagnosis). overrides: dotted config keys
    (``(("mapper.sigma_rho", 0.1),)``).
    """

    parameterisation: str = "inverse_depth"
    nav_error: bool = True
    laps: float = 1.0
    stop_north_m: float | None = None
    avoid: bool = True
    altitude_m: float = 15.0
    seed: int = 1
    frame_rate_hz: float = 15.0
    image_noise: bool = True
    nav_covariance: str = "service"
    overrides: tuple[tuple[str, Any], ...] = ()

    @property
    def label(self) -> str:
        p = "inv-depth" if self.parameterisation == "inverse_depth" else "cartesian"
        return f"{p} nav {'on' if self.nav_error else 'off'} s{self.seed}"


@dataclass
class PointLog:
    """Every emitted point (K rows) with what the world says about it.

    t (K,), ids (K,), est (K, 3) NED, cov (K, 3, 3), truth (K, 3): the world point the feature's
    first measurement saw (ray cast from the true camera), spread (K,): largest distance between
    the world points of its measurements (m), boundary (K,): some measurement sat on a depth
    discontinuity (occlusion boundary / T-junction), nav_frame (K, 3): where the true point lands
    when seen with the estimated camera pose at emission (the map error navigation alone makes),
    range (K,): camera-to-truth distance at emission, updates (K,): measurements taken,
    init_range_err (K,): prior range minus true range at initialisation (m).
    """

    t: list = field(default_factory=list)
    ids: list = field(default_factory=list)
    est: list = field(default_factory=list)
    cov: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    spread: list = field(default_factory=list)
    boundary: list = field(default_factory=list)
    nav_frame: list = field(default_factory=list)
    range: list = field(default_factory=list)
    updates: list = field(default_factory=list)
    init_range_err: list = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {}
        for k in self.__dataclass_fields__:
            v = getattr(self, k)
            out[k] = np.asarray(v) if v else np.zeros((0, 3) if k in ("est", "truth", "nav_frame") else 0)
        if not self.cov:
            out["cov"] = np.zeros((0, 3, 3))
        return out


@dataclass
class RunResult:
    spec: RunSpec
    grid: TerrainGrid
    world: World
    points: PointLog
    trajectory: np.ndarray  # (T, 4): t, north, east, altitude (truth)
    frames: int
    wall_s: float
    laps: int
    inserted: int = 0
    rejected_outlier: int = 0
    max_alt_m: float = 0.0
    oracle: TerrainGrid | None = None  # the same points moved to where navigation error alone puts them


_Link = engine._Link
_command = engine.command
_velocity_setpoint = engine.velocity_setpoint


def _boundary_flags(world: World, p_c: np.ndarray, R_nc: np.ndarray, camera, uv_ideal: np.ndarray,
                    ranges: np.ndarray, offset_px: float = 2.0, jump: float = 0.1) -> np.ndarray:
    """(N,) measurements within ``offset_px`` of a depth discontinuity: the range of a neighbouring
    pixel differs by more than ``jump`` (relative). Corners there are T-junctions of an occluding
    edge over the background, not points of the world."""
    if len(uv_ideal) == 0:
        return np.zeros(0, bool)
    offs = np.array([[offset_px, 0], [-offset_px, 0], [0, offset_px], [0, -offset_px]])
    uv = (uv_ideal[:, None, :] + offs[None]).reshape(-1, 2)
    rays = camera.ray(uv) @ R_nc.T
    r = world.raycast(p_c, rays).reshape(len(uv_ideal), 4)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(r - ranges[:, None]) / ranges[:, None]
    return np.any(~(rel <= jump), axis=1)


def build_config(spec: RunSpec) -> CompanionConfig:
    cfg = replace(CompanionConfig(), **{
        "camera.rate_hz": spec.frame_rate_hz,
        "mapper.parameterisation": spec.parameterisation,
        "sim.origin_delay_s": 0.2,
        "sim.seed": spec.seed,
    })
    if not spec.nav_error:
        cfg = replace(cfg, **{"sim.nav_pos_sigma_h_m": 0.0, "sim.nav_pos_sigma_v_m": 0.0, "sim.nav_vel_sigma_mps": 0.0,
                              "sim.nav_tilt_sigma_deg": 0.0, "sim.nav_yaw_sigma_deg": 0.0})
    if not spec.image_noise:
        cfg = replace(cfg, **{"sim.image_noise_sigma": 0.0})
    if spec.overrides:
        cfg = replace(cfg, **dict(spec.overrides))
    return cfg


_WORLD_CACHE: dict[str, tuple[World, Renderer]] = {}


def world_and_renderer(cfg: CompanionConfig) -> tuple[World, Renderer]:
    """The scenario and its renderer, built once per process (texture synthesis takes ~1 s)."""
    key = f"{cfg.sim.scenario}/{cfg.sim.image_noise_sigma}/{cfg.sim.image_blur_sigma_px}/{cfg.sim.seed}"
    if key not in _WORLD_CACHE:
        world = World.load(cfg.sim.scenario)
        camera, _ = camera_from_config(cfg.camera)
        options = RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, blur_sigma_px=cfg.sim.image_blur_sigma_px,
                                seed=cfg.sim.seed)
        _WORLD_CACHE[key] = (world, Renderer(world, camera, options))
    return _WORLD_CACHE[key]


def fly(spec: RunSpec) -> RunResult:
    """Take off at the first waypoint, fly the circuit with the mapper in the loop, return the map."""
    t_wall = time.perf_counter()
    cfg = build_config(spec)
    world, renderer = world_and_renderer(cfg)
    camera, mount = camera_from_config(cfg.camera)
    grid = TerrainGrid.from_config(cfg.terrain)
    oracle = TerrainGrid.from_config(cfg.terrain)
    detector = HarrisDetector(cfg.mapper, camera.width, camera.height, cfg.camera.border_px)

    def depth_prior(origin, rays):
        return grid.ray_range(origin, rays, cfg.mapper.prior_max_range_m)

    mapper = Mapper(cfg.mapper, camera, mount, depth_prior=depth_prior,
                    default_ground_alt_m=cfg.terrain.default_ground_alt_m, detector=detector)
    law = PullUpLaw(replace(cfg.avoidance, nominal_alt_m=spec.altitude_m))
    waypoints = world.waypoints_ne_m
    guidance = WaypointGuidance(waypoints, world.circuit.speed_mps)
    assembler = NavAssembler(cfg.nav)

    ap = ArduPilotCopter(cfg.sim, seed=spec.seed)
    link = _Link()
    ap.run_for(0.5)  # EKF origin
    assert _command(ap, link, mav.MAV_CMD_DO_SET_MODE, 1, GUIDED) == mav.MAV_RESULT_ACCEPTED
    assert _command(ap, link, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert _command(ap, link, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, spec.altitude_m) == mav.MAV_RESULT_ACCEPTED

    feed = engine.nav_feed(ap, assembler)

    # Track each feature's world points: id -> [first truth (3,), max spread, boundary, n, init range error]
    tracks: dict[int, list] = {}
    log = PointLog()
    traj = []
    frame_dt, control_dt = 1.0 / spec.frame_rate_hz, 1.0 / CONTROL_RATE_HZ
    next_frame = next_control = next_gps = next_ekf = ap.t_s
    frames = 0
    inserted = rejected = 0
    max_alt = 0.0
    climbing = True
    nav = None
    lap_target = spec.laps
    t_end = ap.t_s + 3600.0
    while ap.t_s < t_end:
        ap.step()
        t = ap.t_s
        if t >= next_gps:
            feed((mav.MAVLINK_MSG_ID_GPS_RAW_INT,))
            next_gps += 1.0 / GPS_MSG_RATE_HZ
        if t >= next_ekf:
            feed((mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT,))
            next_ekf += 1.0 / EKF_MSG_RATE_HZ
        alt = -ap.vehicle.p[2]
        if t >= next_control or t >= next_frame:
            truth = ap.truth()
        max_alt = max(max_alt, alt)
        if climbing and alt >= spec.altitude_m - 0.3:
            climbing = False
        if t >= next_control:
            next_control += control_dt
            nav = feed((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)) or nav
            if nav is not None and not climbing:
                g = guidance.update(nav.position_ned_m[:2])
                if spec.avoid:
                    w = law.command(nav.position_ned_m, nav.velocity_ned_mps, grid).climb_rate_mps
                else:
                    w = nominal_climb_rate(spec.altitude_m - nav.altitude_m, cfg.avoidance.accel_mps2,
                                           cfg.avoidance.nominal_time_constant_s)
                ap.handle(_velocity_setpoint(np.array([g.velocity_ne_mps[0], g.velocity_ne_mps[1], -w]), g.yaw_rad), link)
                traj.append((t, truth["p"][0], truth["p"][1], alt))
                if spec.stop_north_m is not None and guidance.target == 1 and truth["p"][0] > spec.stop_north_m:
                    break
                if guidance.lap + _leg_fraction(guidance, nav.position_ned_m[:2]) >= lap_target:
                    break
        if t >= next_frame:
            next_frame += frame_dt
            if alt < 2.0:
                continue
            nav_f = feed((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION))
            if nav_f is None:
                continue
            if spec.nav_covariance == "injected":
                nav_f = dataclasses.replace(nav_f, covariance=ap.nav.spec.covariance, covariance_source="injected")
            p_c, R_nc = mount.camera_pose(truth["p"], truth["R"])
            image = renderer.render(p_c, R_nc)
            step = mapper.step(nav_f, image)
            frames += 1
            _track(world, camera, mount, p_c, R_nc, mapper.last_measurements_raw, step, mapper, nav_f, tracks, log, t)
            stats = grid.add_evidence(step.points, step.free_space, step.floors)
            if len(step.points):
                inserted += stats.inserted
                rejected += stats.rejected_outlier
                k = len(step.points)
                if k and len(log.nav_frame) >= k and log.ids[-k:] == step.points.feature_ids.tolist():
                    oracle.insert(TerrainPoints(step.points.t_s, np.asarray(log.nav_frame[-k:]), step.points.covariances,
                                                step.points.feature_ids))
    return RunResult(spec, grid, world, log, np.asarray(traj), frames, time.perf_counter() - t_wall, guidance.lap,
                     inserted, rejected, max_alt, oracle)


def _leg_fraction(guidance: WaypointGuidance, p_ne: np.ndarray) -> float:
    """Fraction of the current lap flown (by circuit length), for fractional lap counts."""
    wp = guidance.waypoints
    seg = np.linalg.norm(np.diff(np.vstack([wp, wp[:1]]), axis=0), axis=1)
    total = seg.sum()
    k = (guidance.target - 1) % len(wp)
    start = wp[k]
    done = seg[:k].sum() + min(float(np.linalg.norm(np.asarray(p_ne) - start)), seg[k])
    return done / total


def _track(world, camera, mount, p_c, R_nc, uv_raw, step, mapper, nav, tracks, log, t) -> None:
    """Ray cast this frame's measurements and attach their world points to the features."""
    uv = camera.undistort(uv_raw) if len(uv_raw) else np.zeros((0, 2))
    if len(uv) == 0:
        truth = np.zeros((0, 3))
        rng = np.zeros(0)
        bnd = np.zeros(0, bool)
    else:
        rays = camera.ray(uv) @ R_nc.T
        rng = world.raycast(p_c, rays)
        truth = p_c + rng[:, None] * rays
        bnd = _boundary_flags(world, p_c, R_nc, camera, uv, rng)
    # New features: their first world point; the prior range error from the database state.
    snap = None
    if len(step.initialised_ids):
        snap = mapper.features()
        index = {int(i): k for k, i in enumerate(snap.ids)}
        for fid, m in zip(step.initialised_ids.tolist(), step.initialised_measurements.tolist()):
            k = index.get(fid)
            prior_range = np.nan
            if k is not None and mapper.cfg.parameterisation == "inverse_depth":
                rho = snap.states[k, 5]
                prior_range = 1.0 / rho if rho > 0 else np.inf
            elif k is not None:
                prior_range = float(np.linalg.norm(snap.positions_ned_m[k] - p_c))
            tracks[fid] = [truth[m].copy(), 0.0, bool(bnd[m]), 1, prior_range - rng[m]]
    edge_ids = set(mapper.db.ids[mapper.db.active & mapper.db.edge].tolist())
    for fid, m in zip(step.matched_ids.tolist(), step.matched_measurements.tolist()):
        tr = tracks.get(fid)
        if tr is None:
            continue
        # an edge feature's edgels lie anywhere along its edge: their spread says nothing of a mismatch
        d = float(np.linalg.norm(truth[m] - tr[0])) if np.isfinite(truth[m]).all() else np.inf
        tr[1] = max(tr[1], 0.0 if fid in edge_ids else d)
        tr[2] = tr[2] or bool(bnd[m])
        tr[3] += 1
    pts: TerrainPoints = step.points
    if len(pts):
        p_c_est, R_nc_est = mount.camera_pose(nav.position_ned_m, nav.R_nb)
        for k, fid in enumerate(pts.feature_ids.tolist()):
            tr = tracks.get(fid)
            if tr is None:
                continue
            X_true = tr[0]
            # The true point as the (erroneous) navigation frame sees it: same camera-frame vector.
            nav_frame = p_c_est + R_nc_est @ (R_nc.T @ (X_true - p_c))
            log.t.append(t)
            log.ids.append(fid)
            log.est.append(pts.positions_ned_m[k])
            log.cov.append(pts.covariances[k])
            log.truth.append(X_true)
            log.spread.append(tr[1])
            log.boundary.append(tr[2])
            log.nav_frame.append(nav_frame)
            log.range.append(float(np.linalg.norm(X_true - p_c)))
            log.updates.append(tr[3])
            log.init_range_err.append(tr[4])


# ----------------------------------------------------------------------------------------------
# Figures
# ----------------------------------------------------------------------------------------------


def grid_cells(grid: TerrainGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every known cell: global indices ci, cj (K,), height (K,), count (K,)."""
    ci, cj, h, n = [], [], [], []
    for tile in grid.tiles():
        T = tile.tile_cells
        ii, jj = np.nonzero(tile.count > 0)
        ci.append(tile.tx * T + ii)
        cj.append(tile.ty * T + jj)
        h.append(tile.height[ii, jj].astype(float))
        n.append(tile.count[ii, jj].astype(int))
    if not ci:
        z = np.zeros(0, int)
        return z, z, np.zeros(0), z
    return np.concatenate(ci), np.concatenate(cj), np.concatenate(h), np.concatenate(n)


def _neighbourhood(world: World, cn: np.ndarray, ce: np.ndarray, cell: float, textured: bool, op) -> np.ndarray:
    """min or max of the true height over the cell and its 8 neighbours, sampled at 0.25 cell."""
    offs = (np.arange(-6, 7) / 4.0) * cell
    best = None
    for dn in offs:
        for de in offs:
            h = world.terrain_height(cn + dn, ce + de, textured_only=textured)
            best = h if best is None else op(best, h)
    return best


def map_figures(grid: TerrainGrid, world: World, building: str = "building") -> dict[str, float]:
    """Map against the world (docs/mapper.md, "Map quality in the simulated flight").

    Per observed cell: ``e = h_map - h_true`` at the cell centre (strict), and the edge-tolerant
    error ``e_band``: 0 when the mapped height lies between the lowest textured height and the
    highest true height within one cell (a wall's points belong to either side of the wall's
    cell border; the paper's map also stops at the texture), else the distance to that band.
    """
    c = grid.cell_size_m
    ci, cj, h, n = grid_cells(grid)
    cn, ce = (ci + 0.5) * c, (cj + 0.5) * c
    true_full = world.terrain_height(cn, ce)
    lo = _neighbourhood(world, cn, ce, c, True, np.minimum)
    hi = _neighbourhood(world, cn, ce, c, False, np.maximum)
    e = h - true_full
    e_band = np.where(h > hi, h - hi, np.where(h < lo, h - lo, 0.0))
    flat = hi <= 1e-6  # flat ground (no structure within a cell)
    ob = world.obstacle(building)
    fp = np.asarray(ob.footprint_ne_m, float)
    # The footprint grown by one cell, as the demo's metric (companion.desk.report.footprint_cells): a
    # wall's points fall half a cell either side of it.
    centres = np.column_stack([cn, ce])
    inside = _inside_polygon(cn, ce, fp) | (report.distance_to_polygon_edges(centres, fp) <= c)
    hb = h[inside]
    out = {
        "cells": float(len(h)),
        "area_m2": float(len(h) * c * c),
        "rmse_flat": float(np.sqrt(np.mean(e[flat] ** 2))) if flat.any() else math.nan,
        "bias_flat": float(np.mean(e[flat])) if flat.any() else math.nan,
        "rmse_band": float(np.sqrt(np.mean(e_band**2))) if len(h) else math.nan,
        "spurious": float(np.mean(np.abs(e_band) > SPURIOUS_M)) if len(h) else math.nan,
        "spurious_high": float(np.mean(e_band > SPURIOUS_M)) if len(h) else math.nan,
        "spurious_flat": float(np.mean(np.abs(e[flat]) > SPURIOUS_M)) if flat.any() else math.nan,
        "max_err": float(np.max(np.abs(e_band))) if len(h) else math.nan,
        "max_high_flat": float(np.max(e[flat])) if flat.any() else math.nan,
        "building_cells": float(inside.sum()),
        "building_max": float(hb.max()) if len(hb) else math.nan,
        "building_p95": float(np.percentile(hb, 95)) if len(hb) else math.nan,
        "textured_m": float(ob.textured_height_m),
    }
    worst = np.argsort(-np.abs(e_band))[:5]
    out["worst"] = [(float(cn[k]), float(ce[k]), float(h[k]), float(e_band[k]), int(n[k])) for k in worst]
    return out


def versus_oracle(grid: TerrainGrid, oracle: TerrainGrid, world: World) -> dict[str, float]:
    """The map against the oracle map (the same points placed where navigation error alone puts them):
    what the mapper adds to the navigation error. Over the flat-ground cells both hold (near a wall
    a point and its oracle fall on either side of a cell border): rmse, fraction > 2 m."""
    a = grid_cells(grid)
    b = grid_cells(oracle)
    ka = a[0].astype(np.int64) * (1 << 32) + a[1]
    kb = b[0].astype(np.int64) * (1 << 32) + b[1]
    _, ia, ib = np.intersect1d(ka, kb, return_indices=True)
    c = grid.cell_size_m
    flat = _neighbourhood(world, (a[0][ia] + 0.5) * c, (a[1][ia] + 0.5) * c, c, False, np.maximum) <= 1e-6
    d = (a[2][ia] - b[2][ib])[flat]
    if len(d) == 0:
        return {"rmse": math.nan, "spurious": math.nan}
    return {"rmse": float(np.sqrt(np.mean(d * d))), "spurious": float(np.mean(np.abs(d) > SPURIOUS_M))}


def _inside_polygon(x: np.ndarray, y: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(K,) points strictly inside a convex or simple polygon (even-odd rule)."""
    inside = np.zeros(len(x), bool)
    m = len(poly)
    for k in range(m):
        x0, y0 = poly[k]
        x1, y1 = poly[(k + 1) % m]
        cross = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= cross & (x < xi)
    return inside


def classify_points(log: PointLog) -> dict[str, float]:
    """Emitted points whose height error exceeds BAD_HEIGHT_M, by first matching cause.

    occlusion: a measurement sat on a depth discontinuity (T-junction of an edge over the
    background: not a point of the world). mismatch: its measurements saw world points more than
    1 m apart (associated with the wrong corner). nav: the error is within 1 m of what the
    navigation error alone makes (the true point seen from the estimated pose). far: range > 60 m.
    prior: the rest (wrong prior depth not corrected, low parallax, overconfidence).
    """
    a = log.arrays()
    n = len(a["t"])
    if n == 0:
        return {"points": 0}
    dz = -(a["est"][:, 2] - a["truth"][:, 2])
    dz_nav = -(a["est"][:, 2] - a["nav_frame"][:, 2])
    bad = np.abs(dz) > BAD_HEIGHT_M
    occl = bad & a["boundary"]
    mism = bad & ~occl & (a["spread"] > 1.0)
    navc = bad & ~occl & ~mism & (np.abs(dz_nav) <= BAD_HEIGHT_M)
    far = bad & ~occl & ~mism & ~navc & (a["range"] > 60.0)
    other = bad & ~occl & ~mism & ~navc & ~far
    high = dz > 2.0
    return {
        "points": n,
        "bad": float(bad.mean()),
        "high2": float(high.mean()),
        "occlusion": float(occl.mean()),
        "mismatch": float(mism.mean()),
        "nav": float(navc.mean()),
        "far": float(far.mean()),
        "other": float(other.mean()),
        "median_abs_dz": float(np.median(np.abs(dz))),
    }


def table(results: list[RunResult]) -> str:
    rows = [("run", "laps", "frames", "s", "cells", "rmse_flat", "bias_flat", "spur%", "spur_hi%", "max_err",
             "oracle rmse/spur%", "vs-oracle rmse/spur%", "bldg max/p95", "max_alt", "pts", "bad%", "occl/mism/nav/far/oth %")]
    for r in results:
        f = map_figures(r.grid, r.world)
        o = map_figures(r.oracle, r.world) if r.oracle is not None and len(r.oracle) else None
        c = classify_points(r.points)
        rows.append((
            r.spec.label, f"{r.laps}", f"{r.frames}", f"{r.wall_s:.1f}", f"{f['cells']:.0f}",
            f"{f['rmse_flat']:.2f}", f"{f['bias_flat']:+.2f}", f"{100 * f['spurious']:.2f}",
            f"{100 * f['spurious_high']:.2f}", f"{f['max_err']:.1f}",
            "-" if o is None else f"{o['rmse_flat']:.2f}/{100 * o['spurious']:.2f}",
            "-" if o is None else "{rmse:.2f}/{spurious:.2f}".format(**{
                k: v * (100 if k == "spurious" else 1) for k, v in versus_oracle(r.grid, r.oracle, r.world).items()}),
            f"{f['building_max']:.1f}/{f['building_p95']:.1f}", f"{r.max_alt_m:.1f}", f"{c['points']}",
            f"{100 * c.get('bad', 0):.1f}",
            "/".join(f"{100 * c.get(k, 0):.1f}" for k in ("occlusion", "mismatch", "nav", "far", "other")),
        ))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(s.rjust(w) for s, w in zip(row, widths)) for row in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--laps", type=float, default=3.0)
    ap.add_argument("--param", choices=["inverse_depth", "cartesian", "both"], default="both")
    ap.add_argument("--nav", choices=["on", "off", "both"], default="both")
    ap.add_argument("--no-avoid", action="store_true", help="hold the altitude instead of the pull-up law")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1], help="one run per seed (navigation error, sensor noise)")
    ap.add_argument("--worst", action="store_true", help="print the worst cells of each run")
    args = ap.parse_args(argv)
    params = ["inverse_depth", "cartesian"] if args.param == "both" else [args.param]
    navs = [True, False] if args.nav == "both" else [args.nav == "on"]
    results = []
    for p in params:
        for nv in navs:
            for seed in args.seeds:
                r = fly(RunSpec(parameterisation=p, nav_error=nv, laps=args.laps, avoid=not args.no_avoid, seed=seed))
                results.append(r)
                if args.worst:
                    f = map_figures(r.grid, r.world)
                    print(r.spec.label, seed, "worst cells (n, e, h, err, count):",
                          [tuple(round(x, 1) for x in w) for w in f["worst"]])
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
