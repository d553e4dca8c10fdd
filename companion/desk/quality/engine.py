"""The service's closed loop in one process, in simulated time: deterministic and fast.

What ``companion demo`` runs as three processes over MAVLink and Zenoh, stepped here in lockstep:

* vehicle: the simulator's ArduPilot Copter model (:class:`drivers.sim.ardupilot.ArduPilotCopter`:
  point-mass multirotor, its position controller, the injected navigation error, the GPS receiver),
  armed and taken off in GUIDED as the demo's pilot does;
* navigation: :class:`companion.navigation.NavAssembler` fed the very MAVLink messages the vehicle
  builds (LOCAL_POSITION_NED, ATTITUDE_QUATERNION at the control and frame times; GPS_RAW_INT at
  5 Hz; EKF_STATUS_REPORT at 2 Hz), so the mapper gets the estimate and covariance the service has;
* camera: the renderer at the TRUE camera pose (what the synthetic camera does from SIM_STATE),
  at ``camera.rate_hz`` with the simulator's sensor noise;
* mapper and map: :class:`Mapper` with the grid's ray cast as its depth prior, converged points
  into the :class:`TerrainGrid` (as the daemon's mapper worker);
* control: :class:`companion.control.Controller`, the daemon's own decision, at ``control.rate_hz``;
  its velocity setpoint goes to the vehicle as SET_POSITION_TARGET_LOCAL_NED.

What differs from the processes: no transport latency (a map update reaches the next control
step, ~50 ms, as in the daemon when it keeps up) and no dropped frames. Same inputs, same flight,
bit for bit.

The record (:class:`FlightRecord`) holds what the pilot's figures need (companion/quality/metrics.py).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.desk import report
from companion.method.avoidance import margin_height
from companion.config import CompanionConfig
from companion.method.control import Controller
from companion.method.geometry import camera_from_config
from companion.method.mapper import Mapper, mean_innovation_squared
from companion.method.mapper.features import HarrisDetector
from companion.method.mapper.flow_depth import FlowRanger
from companion.method.messages import NavState
from companion.method.navigation.assembler import NavAssembler
from companion.method.terrain.grid import TerrainGrid

GPS_MSG_RATE_HZ = 5.0      # GPS_RAW_INT as streamed to the service
EKF_MSG_RATE_HZ = 2.0      # EKF_STATUS_REPORT
HELD_SAMPLE_S = 0.5        # how often the map's hold on each obstacle is sampled (simulated s)
SWATH_GRID = (12, 9)       # pixel rays per frame cast to find the ground the camera saw
TAKEOFF_TIMEOUT_S = 120.0  # simulated seconds to reach the control altitude
CRUISE_REACHED_M = 0.5     # the record starts when the vehicle first comes this close to the nominal altitude
POINT_OFF_M = 2.0          # an emitted point this far along its line of sight from the true surface
POINT_OFF_SIGMA = 5.0      # and this many of its own sigmas is counted as off (points_in_front / points_behind)
POINT_CONE_RAD = (0.002, 0.005, 0.01)  # lines this far off a point's line of sight: the nearest surface may be there (an outline)


@dataclass
class FlightRecord:
    """What one flight produced (simulated seconds; local NED; altitudes up), from the first time the
    vehicle reached its nominal altitude after take-off.

    t_s (T,), truth_ne_m (T, 2), truth_alt_m (T,), truth_speed_mps (T,): the true state at every
    control step after take-off; nav_alt_m (T,): the estimate the law used; per step the law's
    output: climb_mps (T,) commanded, nominal_climb_mps (T,), engaged (T,) bool, limiting_ne_m (T, 2)
    (NaN when none), limiting_law_height_m (T,) (the cell as the law took it: estimate + margin),
    limiting_map_height_m (T,) (the cell's mapped estimate), limiting_source_ne_m (T, 2) and
    limiting_source_map_height_m (T,) (when the limiting cell is unmapped, the mapped cell it stands
    in for and its estimate; NaN otherwise), lap (T,) the guidance's completed laps.
    lap_ends: index into t_s of each lap's end; lap_maps: the map at each lap's end.
    held: obstacle name -> (K, 2) [t, highest footprint cell as the law takes it], sampled every
    ``HELD_SAMPLE_S``. swath_cells: (M, 2) int cell indices (floor(n / c), floor(e / c)) where a
    camera ray met the ground or a structure. final_map: the map at the end.
    innovation_nis_sum / corner_updates: the mapper's innovation squared summed over its corner
    updates, and their count (the filter's consistency; docs/replay.md, "Filter consistency").
    points_scored: emitted points whose line of sight meets the world; of them points_in_front /
    points_behind: more than ``POINT_OFF_M`` and ``POINT_OFF_SIGMA`` sigma nearer the camera than
    the nearest surface about their line of sight (a phantom: above the ground or before a face),
    or farther (:func:`point_depth_errors`).
    """

    scenario: str
    seed: int
    parameterisation: str
    laps_requested: int
    cfg: CompanionConfig
    t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    truth_alt_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_speed_mps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nav_alt_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    climb_mps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nominal_climb_mps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    engaged: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    limiting_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    limiting_law_height_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    limiting_map_height_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    limiting_source_ne_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    limiting_source_map_height_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lap: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    lap_ends: list[int] = field(default_factory=list)
    lap_maps: list[report.MapRaster] = field(default_factory=list)
    held: dict[str, np.ndarray] = field(default_factory=dict)
    swath_cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    final_map: report.MapRaster = field(default_factory=report.MapRaster.empty)
    frames: int = 0
    points_converged: int = 0
    innovation_nis_sum: float = 0.0
    corner_updates: int = 0
    points_scored: int = 0
    points_in_front: int = 0
    points_behind: int = 0
    sim_time_s: float = 0.0
    wall_s: float = 0.0
    complete: bool = False
    problem: str = ""

    @property
    def realtime_factor(self) -> float:
        return self.sim_time_s / self.wall_s if self.wall_s > 0 else math.nan


class _Link:
    """What ArduPilotCopter.handle needs to know about the link a message came on."""

    def __init__(self) -> None:
        from drivers.sim.mavlink_endpoint import StreamSchedule

        self.name = "quality"
        self.schedule = StreamSchedule()


def _from_gcs(msg):
    """A constructed message with a sender, as the vehicle parses it from the wire."""
    enc = mav.MAVLink(None, srcSystem=255, srcComponent=191)
    return mav.MAVLink(None).parse_buffer(msg.pack(enc))[0]


def command(ap, link: _Link, cmd: int, *params: float) -> int:
    """COMMAND_LONG to the simulated vehicle; the COMMAND_ACK result (-1 if none)."""
    p = list(params) + [0.0] * (7 - len(params))
    ap.outbox.clear()
    ap.handle(_from_gcs(mav.MAVLink_command_long_message(1, 1, cmd, 0, *p)), link)
    acks = [m for _, m in ap.outbox if m.get_type() == "COMMAND_ACK"]
    return acks[-1].result if acks else -1


def velocity_setpoint(v_ned: np.ndarray, yaw: float | None):
    """SET_POSITION_TARGET_LOCAL_NED, velocity only (type_mask 3527), with the yaw when given."""
    mask = 3527 if yaw is None else 3527 & ~1024
    return _from_gcs(mav.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mav.MAV_FRAME_LOCAL_NED, mask, 0, 0, 0, float(v_ned[0]), float(v_ned[1]), float(v_ned[2]),
        0, 0, 0, 0.0 if yaw is None else float(yaw), 0))


def nav_feed(ap, assembler: NavAssembler) -> Callable[[tuple[int, ...]], NavState | None]:
    """``feed(message ids)``: the simulated vehicle builds each message now and the service's
    NavAssembler takes it, as the autopilot link would; the last state assembled (None if none)."""
    def feed(ids: tuple[int, ...]) -> NavState | None:
        nav = None
        for msg_id in ids:
            msg = ap.build(msg_id)
            if msg is not None:
                got = assembler.update(msg, ap.t_s)
                nav = got if got is not None else nav
        return nav

    return feed


def footprint_cell_centres(polygon: np.ndarray, cell_m: float, margin_m: float) -> np.ndarray:
    """(K, 2) centres of the grid cells within ``margin_m`` of the polygon (inside or near an edge)."""
    lo = np.floor((polygon.min(axis=0) - margin_m) / cell_m)
    hi = np.ceil((polygon.max(axis=0) + margin_m) / cell_m)
    n = (np.arange(lo[0], hi[0]) + 0.5) * cell_m
    e = (np.arange(lo[1], hi[1]) + 0.5) * cell_m
    pts = np.stack(np.meshgrid(n, e, indexing="ij"), axis=-1).reshape(-1, 2)
    near = report.points_in_polygon(pts, polygon) | (report.distance_to_polygon_edges(pts, polygon) <= margin_m)
    return pts[near]


class _Recorder:
    """Lists grown during the flight, turned into the record's arrays at the end."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []
        self.swath: list[np.ndarray] = []
        self.held: dict[str, list[tuple[float, float]]] = {}


def _law_height_over(grid: TerrainGrid, centres: np.ndarray, k_sigma: float) -> float:
    """Highest cell over ``centres`` (K, 2) as the law takes it (estimate + k sigma); NaN if none known."""
    h, v, n = grid.height_at(centres[:, 0], centres[:, 1])
    known = n > 0
    if not known.any():
        return math.nan
    return float(np.max(margin_height(h[known], v[known], k_sigma)))


def fly(scenario: str, cfg: CompanionConfig, laps: int, *, seed: int | None = None,
        world=None, renderer=None, on_frame: Callable[..., None] | None = None,
        law_view: Callable[[TerrainGrid], Any] | None = None) -> FlightRecord:
    """Take off at the circuit's first waypoint and fly ``laps`` laps with the service's mapper, map
    and control in the loop. ``cfg`` is the flight's configuration (companion/quality/scenarios.py,
    ``flight_config``); ``world`` and ``renderer`` may be given to reuse them across flights.
    ``on_frame(t, truth, p_c, R_nc, image, step, mapper, nav, grid)`` is called after each mapped
    frame (diagnostics); ``law_view(grid)`` is what the law reads instead of the grid (another
    vehicle's evidence fused in: companion/method/terrain/sharing.py). Never raises for a flight that goes wrong: ``complete`` is False and
    ``problem`` says why."""
    from drivers.sim.ardupilot import GUIDED, ArduPilotCopter
    from drivers.sim.renderer import Renderer, RenderOptions
    from drivers.sim.world import World

    wall0 = time.perf_counter()
    seed = cfg.sim.seed if seed is None else seed
    rec = FlightRecord(scenario, seed, cfg.mapper.parameterisation, laps, cfg)
    if world is None:
        world = World.load(scenario)
    camera, mount = camera_from_config(cfg.camera)
    if renderer is None:
        renderer = Renderer(world, camera, RenderOptions(noise_sigma=cfg.sim.image_noise_sigma,
                                                         blur_sigma_px=cfg.sim.image_blur_sigma_px, seed=seed))
    grid = TerrainGrid.from_config(cfg.terrain)
    mapper = Mapper(cfg.mapper, camera, mount,
                    depth_prior=lambda origin, rays: grid.ray_range(origin, rays, cfg.mapper.prior_max_range_m),
                    default_ground_alt_m=cfg.terrain.default_ground_alt_m,
                    detector=HarrisDetector(cfg.mapper, camera.width, camera.height, cfg.camera.border_px))
    # rises and surfaces seen by dense flow: the stage beside the mapper (the service runs it in its own thread)
    flow = FlowRanger(cfg.mapper, camera, mount) if cfg.mapper.flow_on else None
    controller = Controller(cfg)
    assembler = NavAssembler(cfg.nav)
    obstacles = {o.name: footprint_cell_centres(o.footprint_ne_m, grid.cell_size_m, grid.cell_size_m)
                 for o in world.obstacles}
    k_sigma = cfg.avoidance.height_margin_sigma
    out = _Recorder()
    out.held = {name: [] for name in obstacles}
    # Pixel rays for the swath: a coarse lattice over the image.
    gu, gv = SWATH_GRID
    uu, vv = np.meshgrid(np.linspace(0, camera.width - 1, gu), np.linspace(0, camera.height - 1, gv))
    swath_rays_cam = camera.ray(np.stack([uu.ravel(), vv.ravel()], axis=1))

    ap = ArduPilotCopter(cfg.sim, seed=seed)
    link = _Link()

    feed = nav_feed(ap, assembler)

    try:
        ap.run_for(max(0.5, cfg.sim.origin_delay_s + cfg.sim.gps_delay_s + 0.2))  # EKF origin, GPS use
        takeoff_alt = float(cfg.avoidance.nominal_alt_m)
        for what, cmd_id, params in (("GUIDED", mav.MAV_CMD_DO_SET_MODE, (1, GUIDED)),
                                     ("arming", mav.MAV_CMD_COMPONENT_ARM_DISARM, (1,)),
                                     ("takeoff", mav.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, takeoff_alt))):
            result = command(ap, link, cmd_id, *params)
            if result != mav.MAV_RESULT_ACCEPTED:
                raise RuntimeError(f"the simulated vehicle refused {what} (COMMAND_ACK result {result})")
        circuit_m = float(report.path_length(np.vstack([world.waypoints_ne_m, world.waypoints_ne_m[:1]]))[-1])
        speed = max(cfg.control.cruise_speed_mps, 0.5)
        t_end = ap.t_s + TAKEOFF_TIMEOUT_S + 3.0 * laps * circuit_m / speed + 60.0
        frame_dt, control_dt = 1.0 / cfg.camera.rate_hz, 1.0 / cfg.control.rate_hz
        next_frame = next_control = next_gps = next_ekf = next_held = ap.t_s
        flying = False  # the service commands (above control.min_alt_m)
        cruising = False  # recorded from the first time the nominal altitude is reached
        t_takeoff = ap.t_s
        while True:
            ap.step()
            t = ap.t_s
            if t > t_end:
                raise RuntimeError(f"{int(controller.lap)} of {laps} laps after {t - t_takeoff:.0f} s of flight: "
                                   "the vehicle did not come round the circuit")
            if t >= next_gps:
                feed((mav.MAVLINK_MSG_ID_GPS_RAW_INT,))
                next_gps += 1.0 / GPS_MSG_RATE_HZ
            if t >= next_ekf:
                feed((mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT,))
                next_ekf += 1.0 / EKF_MSG_RATE_HZ
            if t >= next_control:
                next_control += control_dt
                nav = feed((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION))
                if nav is not None:
                    decision = controller.decide(nav, grid if law_view is None else law_view(grid))
                    if decision.send:
                        flying = True
                        ap.handle(velocity_setpoint(decision.velocity_ned_mps, decision.yaw_rad), link)
                    elif not flying and t - t_takeoff > TAKEOFF_TIMEOUT_S:
                        raise RuntimeError(f"the vehicle did not climb to control.min_alt_m = {cfg.control.min_alt_m:g} m "
                                           f"within {TAKEOFF_TIMEOUT_S:g} s of take-off")
                    truth = ap.truth()
                    if not cruising and -truth["p"][2] >= cfg.avoidance.nominal_alt_m - CRUISE_REACHED_M:
                        cruising = True  # the climb-out is the autopilot's take-off, not the service's flight
                    if cruising:
                        c = decision.command
                        lim = c.limiting_cell_ne if c.engaged and c.limiting_cell_ne is not None else (math.nan, math.nan)
                        map_h = (float(grid.height_at(lim[0], lim[1])[0]) if math.isfinite(lim[0]) else math.nan)
                        src = c.limiting_source_ne if c.engaged and c.limiting_source_ne is not None else (math.nan, math.nan)
                        src_h = (float(grid.height_at(src[0], src[1])[0]) if math.isfinite(src[0]) else math.nan)
                        out.rows.append((t, truth["p"][0], truth["p"][1], -truth["p"][2], math.hypot(truth["v"][0], truth["v"][1]),
                                         nav.altitude_m, decision.climb_rate_mps, c.nominal_climb_mps, c.engaged,
                                         lim[0], lim[1], c.limiting_height_m if c.engaged else math.nan, map_h, decision.lap,
                                         src[0], src[1], src_h))
                        if decision.lap > len(rec.lap_ends):
                            rec.lap_ends.append(len(out.rows) - 1)
                            rec.lap_maps.append(report.raster_from_tiles(grid.tiles()))
                            if len(rec.lap_ends) >= laps:
                                break
            if cruising and t >= next_held:
                next_held += HELD_SAMPLE_S
                for name, centres in obstacles.items():
                    out.held[name].append((t, _law_height_over(grid, centres, k_sigma)))
            if t >= next_frame:
                next_frame += frame_dt
                if -ap.vehicle.p[2] < 2.0:
                    continue
                nav_f = feed((mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION))
                if nav_f is None:
                    continue
                truth = ap.truth()
                p_c, R_nc = mount.camera_pose(truth["p"], truth["R"])
                image = renderer.render(p_c, R_nc)
                step = mapper.step(nav_f, image)
                rec.frames += 1
                rays = swath_rays_cam @ R_nc.T
                r = world.raycast(p_c, rays)
                hit = np.isfinite(r)
                if hit.any():
                    pts = p_c[None, :] + r[hit, None] * (rays[hit] / np.linalg.norm(rays[hit], axis=1, keepdims=True))
                    out.swath.append(np.floor(pts[:, :2] / grid.cell_size_m).astype(np.int64))
                grid.add_evidence(step.points, step.free_space, step.floors)
                if flow is not None:
                    flowed = flow.step(nav_f, image)
                    grid.add_flow(flowed.surface, flowed.floors)
                rec.points_converged += len(step.points)
                rec.innovation_nis_sum += step.innovation_nis_sum
                rec.corner_updates += step.n_corner_updates
                if len(step.points):
                    p_c_est, R_nc_est = mount.camera_pose(nav_f.position_ned_m, nav_f.R_nb)
                    _score_points(rec, step.points, p_c, R_nc, p_c_est, R_nc_est, world)
                if on_frame is not None:
                    on_frame(t, truth, p_c, R_nc, image, step, mapper, nav_f, grid)
        rec.complete = True
    except Exception as exc:  # noqa: BLE001 - a failed flight is a result (reported, never dropped)
        rec.problem = f"{type(exc).__name__}: {exc}"
    rec.sim_time_s = float(ap.t_s)
    rec.final_map = report.raster_from_tiles(grid.tiles())
    if out.rows:
        a = np.array(out.rows, dtype=float)
        rec.t_s, rec.truth_ne_m, rec.truth_alt_m, rec.truth_speed_mps = a[:, 0], a[:, 1:3], a[:, 3], a[:, 4]
        rec.nav_alt_m, rec.climb_mps, rec.nominal_climb_mps = a[:, 5], a[:, 6], a[:, 7]
        rec.engaged = a[:, 8].astype(bool)
        rec.limiting_ne_m, rec.limiting_law_height_m, rec.limiting_map_height_m = a[:, 9:11], a[:, 11], a[:, 12]
        rec.lap = a[:, 13].astype(np.int64)
        rec.limiting_source_ne_m, rec.limiting_source_map_height_m = a[:, 14:16], a[:, 16]
    if out.swath:
        rec.swath_cells = np.unique(np.concatenate(out.swath), axis=0)
    rec.held = {name: np.array(v, dtype=float).reshape(-1, 2) for name, v in out.held.items()}
    rec.wall_s = time.perf_counter() - wall0
    return rec


def point_depth_errors(positions_ned_m: np.ndarray, covariances: np.ndarray, p_c: np.ndarray, R_nc: np.ndarray,
                       p_c_est: np.ndarray, R_nc_est: np.ndarray, raycast) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far each emitted point (N, 3) lies along its line of sight from the true surface:
    (error (N,) m, nearest (N,) m, sigma (N,) m). ``error`` = the point's range minus the surface's
    along the line of sight, < 0 = nearer the camera (a phantom above the ground or before a face);
    ``nearest`` = of the line of sight and four lines at each angle of ``POINT_CONE_RAD`` off it,
    the error of the one whose surface is nearest the point's range: a point on an obstacle's
    outline, whose line of sight just misses the roof and meets the ground behind it, is near the
    roof (``error`` metres, ``nearest`` well under ``POINT_OFF_M``); NaN where no line meets
    anything. ``sigma``: the point's covariance along the line of sight, ``sqrt(u_est^T C u_est)``.

    The points live in the navigation estimate's frame, in which the camera was at ``p_c_est``,
    ``R_nc_est``; the true camera was at ``p_c``, ``R_nc``. The estimate's frame maps into the true
    one rigidly about the camera, ``X = p_c + R_nc R_nc_est^T (X_est - p_c_est)``, so the point is
    compared with the surface it was seen on, not with the navigation's error. ``raycast(origin
    (3,), unit rays (N, 3))`` -> ranges (N,) (inf where nothing is hit)."""
    X_est = np.asarray(positions_ned_m, dtype=float).reshape(-1, 3)
    A = R_nc @ R_nc_est.T
    d = (X_est - p_c_est) @ A.T
    r = np.sqrt((d * d).sum(axis=1))
    ok = np.isfinite(r) & (r > 0)
    u = np.zeros_like(d)
    u[ok] = d[ok] / r[ok, None]
    ranges = np.full((len(r), 1 + 4 * len(POINT_CONE_RAD)), np.inf)
    if ok.any():
        uo = u[ok]
        side = np.cross(uo, [0.0, 0.0, 1.0])
        flat = np.linalg.norm(side, axis=1) < 1e-6  # looking straight down or up
        side[flat] = np.cross(uo[flat], [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side, axis=1, keepdims=True)
        up = np.cross(uo, side)
        rays = [uo] + [uo + a * v for a in POINT_CONE_RAD for v in (side, -side, up, -up)]
        rays = np.stack(rays, axis=1)
        rays /= np.linalg.norm(rays, axis=2, keepdims=True)
        ranges[ok] = np.asarray(raycast(p_c, rays.reshape(-1, 3)), dtype=float).reshape(len(uo), -1)
    errors = np.where(np.isfinite(ranges), r[:, None] - ranges, np.nan)  # NaN where a line meets nothing
    closest = np.argmin(np.where(np.isfinite(errors), np.abs(errors), np.inf), axis=1)  # 0 (NaN) if none meets
    nearest = errors[np.arange(len(r)), closest]
    u_est = u @ A
    sigma = np.sqrt(np.einsum("ni,nij,nj->n", u_est, np.asarray(covariances, dtype=float), u_est))
    return errors[:, 0], nearest, sigma


def _score_points(rec: FlightRecord, points, p_c, R_nc, p_c_est, R_nc_est, world) -> None:
    """Add one step's emitted points to the record's point figures (:class:`FlightRecord`); the
    camera's true pose and its pose in the navigation estimate as in :func:`point_depth_errors`."""
    _, nearest, sigma = point_depth_errors(points.positions_ned_m, points.covariances, p_c, R_nc, p_c_est, R_nc_est,
                                           world.raycast)
    seen = np.isfinite(nearest) & (sigma > 0)
    e, sigma = nearest[seen], sigma[seen]
    off = (np.abs(e) > POINT_OFF_M) & (np.abs(e) > POINT_OFF_SIGMA * sigma)
    rec.points_scored += int(len(e))
    rec.points_in_front += int(np.count_nonzero(off & (e < 0)))
    rec.points_behind += int(np.count_nonzero(off & (e > 0)))


def record_summary(rec: FlightRecord) -> dict[str, Any]:
    """A few numbers about the flight itself (not the pilot's figures)."""
    nis = mean_innovation_squared(rec.innovation_nis_sum, rec.corner_updates)
    return {"frames": rec.frames, "points_converged": rec.points_converged,
            "innovation_nis_mean": round(nis, 3) if nis is not None else None,
            "points_scored": rec.points_scored, "points_in_front": rec.points_in_front, "points_behind": rec.points_behind,
            "sim_time_s": round(rec.sim_time_s, 1),
            "wall_s": round(rec.wall_s, 1), "realtime_factor": round(rec.realtime_factor, 1) if rec.wall_s else None}
