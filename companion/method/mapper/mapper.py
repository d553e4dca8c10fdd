"""The monocular terrain mapper: one step per camera frame (seed 000, section II, fig. 1).

``step_measurements(nav, uv, descriptors)``: validate the navigation state -> drop bad measurements
-> drift of the estimate's frame as process noise (correlated navigation error; docs/mapper.md)
-> predict every stored feature (eqs. 3-4) and drop those that left the view -> appearance check,
gate and match (eqs. 10-12) -> batched EKF update of the matched features (eqs. 6-9) -> confidence
indices -> convergence (relative and absolute depth sigma) -> initialise unmatched measurements
(eqs. 13-17) into free or replaceable slots. Converged features come out as
:class:`~companion.messages.TerrainPoints`.

Emission rule: a feature is emitted once, when it first converges (the earliest warning for the
avoidance law). It is not emitted again with its later estimate when it leaves the database: the
terrain map fuses points as independent evidence, and the same feature twice is not (it halved the
variance of the cells it built and let one feature confirm its own higher surface; docs/terrain.md).

The core is pure: no I/O, no logging; everything worth knowing is counted in :class:`MapperStep`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from statistics import NormalDist
from dataclasses import dataclass, field, replace
from types import ModuleType

import numpy as np

from companion.config import MapperConfig
from companion.method.geometry import CameraMount, PinholeCamera, skew
from companion.method.mapper import cartesian, inverse_depth
from companion.method.mapper.appearance import FramePatches, GivenPatches, pair_correlation
from companion.method.mapper.database import FeatureDatabase
from companion.method.mapper.depth_prior import DepthPrior, prior_ranges
from companion.method.mapper.matching import (
    candidate_pairs,
    gate_and_match_pairs,
    innovation_covariance,
    inverse_2x2,
    navigation_term_vanishes,
    near_stored_pairs,
)
from companion.method.mapper.projection import CameraPose, camera_ray_from_pixel
from companion.method.mapper.update import ekf_update, ekf_update_across
from companion.method.messages import FreeSpaceRays, NavState, TerrainFloors, TerrainPoints

Detector = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

# Edgels of one edge in a gate lie within this many pixel sigmas of each other across it; a gate
# whose edgels spread wider holds two edges (docs/mapper.md, "Edgels").
EDGE_SPREAD_SIGMA = 3.0

PARAMETERISATIONS: dict[str, ModuleType] = {"inverse_depth": inverse_depth, "cartesian": cartesian}


def _empty_ids() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


def _in_image(uv: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """``camera.in_image(uv)`` (N,) bool (NaN and inf are outside) without its error-state context,
    which costs more than the test on a few hundred points."""
    u, v = uv[:, 0], uv[:, 1]
    return (u >= 0.0) & (u <= camera.width - 1) & (v >= 0.0) & (v <= camera.height - 1)


def chi2_one_dof(chi2_two_dof: float) -> float:
    """The 1-dof gate with the same tail probability as a 2-dof gate: the 2-dof chi-square has
    ``P(Z < g) = 1 - exp(-g / 2)``, and a 1-dof one is the square of a standard normal, so
    ``g_1 = Phi^-1((1 + p) / 2)^2`` (9.21 -> 6.63, both 99 %)."""
    p = -math.expm1(-0.5 * chi2_two_dof)
    return NormalDist().inv_cdf(0.5 * (1.0 + min(p, 1.0 - 1e-15))) ** 2


def emission_depth_sigma_limit(height_above_m: np.ndarray, cfg: MapperConfig) -> np.ndarray:
    """The depth sigma (m) below which a feature goes to the map (docs/mapper.md, "Convergence and
    emission"): ``max(converged_max_depth_sigma_m, converged_depth_sigma_per_height * dh)``, ``dh``
    the camera's height above the feature (m, (K,)). The law keeps its clearance above a point's
    ``h + k sigma``, so a sigma is paid for out of the clearance over that point: a fixed share
    of the height flown above it, never less than the absolute limit (a face near the camera's
    own height). NaN height: NaN (never below it)."""
    dh = np.asarray(height_above_m, dtype=np.float64)
    return np.maximum(cfg.converged_max_depth_sigma_m, cfg.converged_depth_sigma_per_height * dh)


def tilt_covariance(lever_ned: np.ndarray, P_attitude: np.ndarray) -> np.ndarray:
    """The covariance (K, 3, 3) a point at ``lever_ned`` (K, 3) from the camera takes from the
    navigation's roll and pitch error (docs/mapper.md, "The navigation's tilt"). An attitude error
    ``e`` (a rotation vector in NED, ``R_true = Exp(e) R_est``) turns every line of sight of the
    moment about the camera, so a point triangulated then sits at ``X = c + Exp(-e) (X_true - c)``,
    to first order ``X - X_true = [r]x e`` with ``r = X - c``: ``J = [r]x``, covariance
    ``J P_e J^T``. Only the tilt (the N and E components of ``e``; ``P_attitude`` (3, 3) in NED) is
    taken: the vehicle does not share it (a vertical error of the estimate moves the vehicle and
    the map together, a tilt raises the map ahead by the lever arm times the angle: 0.4 m at 25 m
    for 1 deg), while the yaw turns the map about the vertical, which the law's miss distance
    covers and which would spread each point over metres of cells."""
    P_tilt = np.zeros((3, 3))
    P_tilt[:2, :2] = P_attitude[:2, :2]
    J = skew(lever_ned)
    return J @ P_tilt @ J.transpose(0, 2, 1)  # symmetric as P_tilt is


def _concatenate(t_s: float, parts: list[TerrainPoints]) -> TerrainPoints:
    parts = [p for p in parts if len(p)]
    if not parts:
        return TerrainPoints.empty(t_s)
    return TerrainPoints(
        t_s,
        np.concatenate([p.positions_ned_m for p in parts]),
        np.concatenate([p.covariances for p in parts]),
        np.concatenate([p.feature_ids for p in parts]),
    )


@dataclass(frozen=True, slots=True)
class MapperStep:
    """What one mapper step did.

    points: converged features emitted this step. n_measurements: measurements given;
    n_matched: features updated; n_initialised: new features; n_removed: features dropped (out of
    view, replaced or corrupt); n_active: features stored after the step; n_rejected: measurements
    dropped (``n_dropped``) plus refused feature updates (``n_update_rejected``).
    rejected_reason: non-empty when the whole step was refused (the database is untouched).
    n_ambiguous: measurements inside a gate but not matched (neither used nor initialised).
    n_excluded: other unmatched measurements not initialised because a stored feature's prediction
    is within ``init_exclusion_chi2`` (Mahalanobis) or ``min_distance_px`` of them.
    n_prior_fallback: new features whose depth prior fell back to flat ground.
    init_index: the frame's initialisation confidence index.
    matched_ids / matched_measurements (K,): feature ids and the indices (into the input array) of
    the measurements that updated them; initialised_ids / initialised_measurements likewise;
    removed_ids: features that left the database this step.
    free_space: the segments from the camera to the nearest each updated feature can be
    (``mapper.free_space_sigma``; docs/mapper.md, "Bounds of an unconverged feature"), for the
    map's carving.
    floors: lower bounds on the terrain's height from the features not yet converged
    (``mapper.floor_max_depth_sigma_m``; docs/mapper.md, "Bounds of an unconverged feature"), with
    ``removed_ids`` as its ``ended_ids``.
    n_edgels: measurements that were edgels (docs/mapper.md, "Edgels"); n_edge_matched: edge
    features updated across their edge.
    innovation_nis_sum: the sum over the corners that updated a feature of their normalised
    innovation squared ``nu^T S^-1 nu`` (the matching's Mahalanobis distance, eq. 11), and
    n_corner_updates how many: their mean is 2 (two degrees of freedom) for a filter whose
    covariances are the errors it makes, less for a conservative one (docs/mapper.md, "How
    conservative the filter is, measured").
    point_covariance_scale: the factor the step's points' covariances were scaled by
    (:class:`ConsistencyScale`; 1 = the filter's own).
    """

    points: TerrainPoints
    n_measurements: int
    n_matched: int
    n_initialised: int
    n_removed: int
    n_active: int
    n_rejected: int
    rejected_reason: str = ""
    n_dropped: int = 0
    n_update_rejected: int = 0
    n_ambiguous: int = 0
    n_excluded: int = 0
    n_prior_fallback: int = 0
    init_index: float = 0.0
    matched_ids: np.ndarray = field(default_factory=_empty_ids)
    matched_measurements: np.ndarray = field(default_factory=_empty_ids)
    initialised_ids: np.ndarray = field(default_factory=_empty_ids)
    initialised_measurements: np.ndarray = field(default_factory=_empty_ids)
    removed_ids: np.ndarray = field(default_factory=_empty_ids)
    free_space: FreeSpaceRays = field(default_factory=FreeSpaceRays.empty)
    floors: TerrainFloors = field(default_factory=TerrainFloors.empty)
    n_edgels: int = 0
    n_edge_matched: int = 0
    innovation_nis_sum: float = 0.0
    n_corner_updates: int = 0
    point_covariance_scale: float = 1.0


class ConsistencyScale:
    """The filter's measured consistency as a scale for the covariance of the points it emits
    (docs/mapper.md, "Calibrated point covariance").

    A filter whose innovation covariance is ``S = c S_true`` (its feature covariance and pixel
    noise overstated alike) sees ``E[nu^T S^-1 nu] = tr(S^-1 S_true) = 2 / c`` on a corner's two
    degrees of freedom, and its features' covariance is ``c`` times their errors'. So the running
    mean ``m`` of the innovation squared gives ``1 / c = m / 2``, the factor that makes a point's
    covariance the errors it makes: ``m`` is an exponentially weighted mean forgetting with
    ``memory`` corner updates; the scale is 1 until it holds ``min_updates`` of them and stays in
    ``[1 / max_factor, max_factor]``."""

    def __init__(self, memory: float, min_updates: float, max_factor: float) -> None:
        self.memory = float(memory)
        self.min_updates = float(min_updates)
        self.max_factor = float(max_factor)
        self.nis_sum = 0.0
        self.updates = 0.0

    def add(self, nis_sum: float, n_updates: int) -> None:
        """One step's corner updates: their innovation squared summed, and how many."""
        if n_updates <= 0 or not math.isfinite(nis_sum):
            return
        keep = (1.0 - 1.0 / self.memory) ** n_updates
        self.nis_sum = self.nis_sum * keep + nis_sum
        self.updates = self.updates * keep + n_updates

    @property
    def scale(self) -> float:
        """The factor on an emitted point's covariance, ``m / 2`` (1 before ``min_updates``)."""
        if self.updates < self.min_updates or self.updates <= 0:
            return 1.0
        return min(max(self.nis_sum / self.updates / 2.0, 1.0 / self.max_factor), self.max_factor)


def mean_innovation_squared(nis_sum: float, n_corner_updates: int) -> float | None:
    """The filter's consistency over steps: their ``innovation_nis_sum`` added up, divided by their
    ``n_corner_updates`` added up (2 for a consistent filter; :class:`MapperStep`); None before any
    corner update."""
    return nis_sum / n_corner_updates if n_corner_updates else None


@dataclass(frozen=True, slots=True)
class FeatureSnapshot:
    """The stored features (for status, displays and tests).

    ids (N,) int64; positions_ned_m (N, 3) (NaN if the inverse depth is not positive);
    covariances (N, 3, 3); relative_depth_sigma (N,); converged (N,) bool; confidence (N,) int;
    updates (N,) accepted EKF updates; states (N, D) raw feature states.
    """

    ids: np.ndarray
    positions_ned_m: np.ndarray
    covariances: np.ndarray
    relative_depth_sigma: np.ndarray
    converged: np.ndarray
    confidence: np.ndarray
    updates: np.ndarray
    states: np.ndarray


def navigation_drift(
    P_x: np.ndarray, dt_s: float, attitude_correlation_s: float, displacement_m: np.ndarray | None = None
) -> np.ndarray | None:
    """Covariance (6, 6) of the change of the navigation error over ``dt_s`` (docs/mapper.md,
    "Correlated navigation error"), from the pose covariance ``P_x`` (6, 6) ``[position, attitude]``:

    * attitude: a first-order Gauss-Markov error with stationary covariance ``P_att`` and correlation
      time ``tau`` changes by ``(1 - exp(-2 dt / tau)) P_att`` (the part of ``e(t + dt)`` that is new);
    * position: even a constant attitude error moves the estimate's frame while the vehicle travels
      (the world seen from the estimate is rotated about the vehicle, ``X' = Exp(-dtheta)(X - p) + p``),
      so a displacement ``d`` (3,) (between the two steps' estimated positions) shifts every point by
      ``[dtheta]x d``: ``[d]x P_att [d]x^T``. The position error's own change (velocity error times
      dt, millimetres per frame) is neglected: below a pixel at the ranges mapped, and a pose-only
      recording (TUM) has no velocity covariance, so the mapper stays a function of poses and
      their covariance.

    None when ``dt_s`` is not positive (first step, time going back).
    """
    if not (dt_s > 0) or not np.isfinite(dt_s):
        return None
    q = np.zeros((6, 6))
    P_att = P_x[3:6, 3:6]
    q[3:6, 3:6] = -np.expm1(-2.0 * dt_s / attitude_correlation_s) * P_att
    if displacement_m is not None:
        D = skew(np.asarray(displacement_m, dtype=float).reshape(3))
        q[0:3, 0:3] = D @ P_att @ D.T
    return 0.5 * (q + q.T)


def check_nav(nav: NavState) -> str:
    """Why ``nav`` cannot be used by the mapper, or ``""`` if it can."""
    return _checked_pose_covariance(nav)[0]


_POSE_INDEX = np.array([0, 1, 2, 6, 7, 8])  # [position, attitude] in NavState.covariance (eq. 6)


def _checked_pose_covariance(nav: NavState) -> tuple[str, np.ndarray | None]:
    """:func:`check_nav`'s reason and, when ``nav`` is usable, its pose covariance ``P_x`` (6, 6)
    ``[position, attitude]``, symmetrised (what ``NavState.pose_covariance`` gives, in one gather)."""
    try:
        p = np.asarray(nav.position_ned_m, dtype=float)
        q = np.asarray(nav.quaternion_wxyz, dtype=float)
        cov = np.asarray(nav.covariance, dtype=float)
        v = np.asarray(nav.velocity_ned_mps, dtype=float)
        t_finite = math.isfinite(nav.t_s)
    except (TypeError, ValueError):
        return "nav not numeric", None
    if p.shape != (3,) or q.shape != (4,) or cov.shape != (9, 9):
        return f"nav shapes wrong: position {p.shape}, quaternion {q.shape}, covariance {cov.shape}", None
    # a finite sum means every term is finite (inf and NaN propagate); the exact test otherwise
    if not (t_finite and (math.isfinite(p.sum() + q.sum() + cov.sum() + v.sum()) or nav.is_finite())):
        return "nav not finite", None
    if math.sqrt(float(q @ q)) < 1e-6:  # np.linalg.norm(q)
        return "nav quaternion has zero norm", None
    P_x = cov[_POSE_INDEX[:, None], _POSE_INDEX]
    scale = max(1.0, float(np.max(np.abs(P_x))))
    if np.max(np.abs(P_x - P_x.T)) > 1e-6 * scale:
        return "nav pose covariance not symmetric", None
    P_x = 0.5 * (P_x + P_x.T)
    diagonal = np.diagonal(P_x)
    # the eigenvalues of a diagonal matrix are its diagonal (the usual case: configured floors)
    if np.count_nonzero(P_x) == np.count_nonzero(diagonal):
        lowest = float(diagonal.min())
    else:
        lowest = float(np.linalg.eigvalsh(P_x).min())
    if lowest < -1e-9 * scale:
        return "nav pose covariance not positive semi-definite", None
    return "", P_x


@dataclass(frozen=True, slots=True)
class _EdgePairs:
    """Edge features matched to edgels: ``point`` (K,) rows of the step's features, ``meas`` (K,)
    rows of its measurements; ``ambiguous`` and ``near`` (M,) masks of measurements (see
    :meth:`Mapper._match_edges`)."""

    point: np.ndarray
    meas: np.ndarray
    ambiguous: np.ndarray
    near: np.ndarray


class Mapper:
    """Monocular feature mapper with a fixed-capacity database (seed 000, section II).

    cfg: :class:`MapperConfig` (``parameterisation`` picks inverse depth or the Cartesian
    baseline). camera / mount: intrinsics and mounting. depth_prior: ray-cast prior for new
    features (settable; ``None`` = flat ground at ``default_ground_alt_m``). detector: image ->
    (raw pixels (N, 2), scores (N,)) in score order, used by :meth:`step`; defaults to the Harris
    detector in :mod:`companion.mapper.features`. border_px: passed to the default detector.
    """

    def __init__(
        self,
        cfg: MapperConfig,
        camera: PinholeCamera,
        mount: CameraMount,
        depth_prior: DepthPrior | None = None,
        default_ground_alt_m: float = 0.0,
        detector: Detector | None = None,
        border_px: int = 0,
    ):
        if cfg.parameterisation not in PARAMETERISATIONS:
            raise ValueError(f"mapper.parameterisation must be one of {sorted(PARAMETERISATIONS)}, got {cfg.parameterisation!r}")
        if cfg.prior_min_range_m >= cfg.prior_max_range_m:
            raise ValueError("mapper.prior_min_range_m must be below mapper.prior_max_range_m")
        self.cfg = cfg
        self.camera = camera
        self.mount = mount
        self.depth_prior = depth_prior if cfg.map_depth_prior else None
        self.default_ground_alt_m = float(default_ground_alt_m)
        self.detector = detector
        self.border_px = int(border_px)
        self.model = PARAMETERISATIONS[cfg.parameterisation]
        self.prior_sigma = cfg.sigma_rho if cfg.parameterisation == "inverse_depth" else cfg.sigma_depth_rel
        self.R_img = np.diag([cfg.pixel_sigma_px**2, cfg.pixel_sigma_px**2])
        self.edge_gate = chi2_one_dof(cfg.gate_chi2)  # across an edge: 1 dof, the corners' probability
        self.edge_exclusion = chi2_one_dof(cfg.init_exclusion_chi2)
        self.edge_min_cos = math.cos(math.radians(cfg.edgel_max_turn_deg))
        self.db = FeatureDatabase(cfg.max_features, self.model.STATE_DIM, cfg.appearance_patch_px**2)
        self.frame = 0
        self._detector = None
        self._detector_shape: tuple[int, ...] | None = None
        self._last_nav_t = np.inf  # time of the last accepted step (no drift before the first)
        self._last_nav_p = np.zeros(3)  # body position at that step
        self.consistency = ConsistencyScale(cfg.calibration_memory_updates, cfg.calibration_min_updates,
                                            cfg.calibration_max_factor)
        # the last step's measurements as :meth:`step` detected them (raw pixels, corners then
        # edgels; the indices of MapperStep.*_measurements), for diagnostics
        self.last_measurements_raw = np.zeros((0, 2))
        # Tracking between detections: the last frame (grey) and the raw pixels of its corners that
        # measured a feature not yet converged (matched or initialised), where this frame's tracker
        # starts from.
        self._track_gray: np.ndarray | None = None
        self._track_from = np.zeros((0, 2), dtype=np.float32)

    # ------------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every feature (ids keep increasing)."""
        self.db.clear()
        self._last_nav_t = np.inf
        self._track_gray = None


    def step(self, nav: NavState, image: np.ndarray) -> MapperStep:
        """Detect corners in ``image`` ((H, W) grey or (H, W, 3) BGR uint8), undistort them, then
        :meth:`step_measurements`. A bad navigation state is refused before any detection work."""
        image = np.asarray(image)
        if image.ndim not in (2, 3):
            raise ValueError(f"mapper image must be (H, W) or (H, W, 3), got shape {image.shape}")
        reason, P_x = _checked_pose_covariance(nav)
        if reason:
            self._track_gray = None  # no step: the next frame has nothing to track from
            return self._refused(nav, 0, reason)
        if self.detector is not None:
            uv_raw, _scores = self.detector(image)
        else:
            uv_raw, _scores = self._harris(image)
        uv_raw = np.asarray(uv_raw, dtype=float).reshape(-1, 2)
        normals = None
        tracking = self.cfg.track_window_px > 0
        n_tracked = 0
        if self.cfg.max_edgels > 0 or self.cfg.appearance_patch_px > 0 or tracking:
            from companion.method.mapper.features import as_gray, detect_edgels

            gray = as_gray(image)
        n_corners = len(uv_raw)
        if tracking:
            tracked = self._tracked(gray, uv_raw)
            n_tracked = len(tracked)
            uv_raw = np.concatenate([uv_raw, tracked])
        if self.cfg.max_edgels > 0:
            from companion.method.mapper.features import HarrisDetector

            corner_detector = self.detector if self.detector is not None else self._detector
            # a static mask's or a black border's outline is an edge too: the corners' valid region
            valid = corner_detector.valid_region(gray) if isinstance(corner_detector, HarrisDetector) else None
            # the bins with a detected corner give no edgels (a tracked point is a stored feature)
            edge_uv, edge_n, _strength = detect_edgels(gray, uv_raw[:n_corners], self.cfg, self.border_px, valid)
            if len(edge_uv):
                edge_n = self._undistorted_normals(edge_uv, edge_n)
                # the camera's translation since the last step (poses only: a pose-only recording
                # maps as the live flight did); none before the first step
                moved = np.zeros(3)
                if math.isfinite(self._last_nav_t):
                    moved = np.asarray(nav.position_ned_m, dtype=float) - self._last_nav_p
                pose = CameraPose.from_nav(nav.position_ned_m, nav.quaternion_wxyz, self.mount)
                crossing = self._flow_crossing(pose.R_nc, moved, self.camera.undistort(edge_uv), edge_n)
                keep = crossing >= math.sin(math.radians(self.cfg.edgel_min_crossing_deg))
                normals = np.concatenate([np.zeros_like(uv_raw), edge_n[keep]])
                uv_raw = np.concatenate([uv_raw, edge_uv[keep]])
        self.last_measurements_raw = uv_raw
        patches = None
        if self.cfg.appearance_patch_px > 0:
            # cut later, for the few measurements that need one (appearance.FramePatches)
            patches = FramePatches(gray, uv_raw, self.cfg.appearance_patch_px)
        no_start = None
        if n_tracked:
            no_start = np.zeros(len(uv_raw), dtype=bool)
            no_start[n_corners:n_corners + n_tracked] = True  # corners, tracked points, edgels
        step = self._step_checked(nav, P_x, self.camera.undistort(uv_raw), patches, normals, no_start)
        if tracking:
            # The corners that measured a feature this frame are where the next frame's tracker
            # starts (an edgel slides along its edge under the tracker: not followed).
            # A converged feature's point is in the map already: it is not followed (it gives its
            # slot to new terrain, "Database").
            done = self.db.ids[self.db.active & self.db.converged]
            fresh = ~np.isin(step.matched_ids, done)
            used = np.concatenate([step.matched_measurements[fresh], step.initialised_measurements])
            if normals is not None:
                used = used[~normals[used].any(axis=1)]
            self._track_from = uv_raw[used].astype(np.float32)
            self._track_gray = gray.copy()
        return step

    def _tracked(self, gray: np.ndarray, corners_raw: np.ndarray) -> np.ndarray:
        """Tracking between detections (docs/mapper.md): the last frame's corners that measured a
        feature not yet converged, followed into ``gray`` by pyramidal Lucas-Kanade (``track_window_px``,
        ``track_levels``), kept where tracking back lands within ``track_max_fb_px`` of the start
        and no detected corner of ``corners_raw`` (K, 2) lies within ``min_distance_px`` (the
        detector found it again). Raw pixels (T, 2)."""
        import cv2

        start = self._track_from
        if self._track_gray is None or self._track_gray.shape != gray.shape or len(start) == 0:
            return np.zeros((0, 2))
        w = self.cfg.track_window_px
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
        p0 = start.reshape(-1, 1, 2)
        p1, ok1, _ = cv2.calcOpticalFlowPyrLK(self._track_gray, gray, p0, None, winSize=(w, w),
                                              maxLevel=self.cfg.track_levels, criteria=criteria)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(gray, self._track_gray, p1, None, winSize=(w, w),
                                                maxLevel=self.cfg.track_levels, criteria=criteria)
        p1, back = p1.reshape(-1, 2).astype(float), back.reshape(-1, 2).astype(float)
        fb = np.sqrt(((back - start) ** 2).sum(axis=1))
        keep = (ok1.ravel() == 1) & (ok2.ravel() == 1) & (fb <= self.cfg.track_max_fb_px) & _in_image(p1, self.camera)
        p1 = p1[keep]
        if len(p1) and len(corners_raw):
            d2 = ((p1[:, None, :] - corners_raw[None, :, :]) ** 2).sum(axis=2)
            p1 = p1[d2.min(axis=1) > self.cfg.min_distance_px**2]
        return p1

    def _flow_crossing(self, R_nc: np.ndarray, translation_ned: np.ndarray, uv: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """``|sin|`` of the angle (E,) at which each edge (ideal pixels ``uv`` (E, 2), unit normals
        (E, 2)) crosses the image motion that the camera's translation ``translation_ned`` (3,)
        gives its pixel, the camera's attitude ``R_nc`` (camera -> NED) (docs/mapper.md, "Edgels"):
        only that motion depends on depth, and across the edge is all an edgel measures. A camera
        moving by ``v`` (camera frame, ``v_f`` along the optical axis) moves the normalised image
        point ``x`` of a point at depth ``Z`` by ``(x v_f - v_xy) / Z``; its direction is the same for
        every depth. 0 where the camera does not move or the pixel is the epipole."""
        v = R_nc.T @ np.asarray(translation_ned, dtype=float)  # (forward, right, down)
        cam = self.camera
        x = (uv[:, 0] - cam.cx) / cam.fx
        y = (uv[:, 1] - cam.cy) / cam.fy
        flow = np.column_stack([cam.fx * (x * v[0] - v[1]), cam.fy * (y * v[0] - v[2])])  # pixels, up to 1 / Z
        size = np.sqrt((flow * flow).sum(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            crossing = np.abs((flow * normal).sum(axis=1)) / size
        return np.where(size > 1e-9 * max(cam.fx, cam.fy), crossing, 0.0)

    def _bins(self, uv: np.ndarray) -> np.ndarray:
        """The detector's bin (row by row) of each pixel ``uv`` (K, 2), clipped to the image."""
        from companion.method.mapper.features import bin_of

        return bin_of(uv, self.camera.width, self.camera.height, self.cfg.bins_x, self.cfg.bins_y)

    def _undistorted_normals(self, uv_raw: np.ndarray, normal_raw: np.ndarray) -> np.ndarray:
        """Unit normals (E, 2) in ideal pixels of edges through raw pixels ``uv_raw`` (E, 2) with raw
        normals ``normal_raw`` (E, 2): the edge's direction is carried through the undistortion by
        a second point 2 px along it."""
        if not np.any(self.camera.distortion):
            return normal_raw
        along = np.column_stack([-normal_raw[:, 1], normal_raw[:, 0]])
        d = self.camera.undistort(uv_raw + 2.0 * along) - self.camera.undistort(uv_raw)
        d /= np.maximum(np.sqrt((d * d).sum(axis=1, keepdims=True)), 1e-12)
        n = np.column_stack([d[:, 1], -d[:, 0]])
        return np.where(((n * normal_raw).sum(axis=1) < 0)[:, None], -n, n)

    def _harris(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The default detector, built once per image size (its buffers are reused frame to frame)."""
        from companion.method.mapper.features import HarrisDetector, as_gray  # separate module, imported lazily

        gray = as_gray(image)
        if self._detector is None or self._detector_shape != gray.shape:
            self._detector = HarrisDetector(self.cfg, gray.shape[1], gray.shape[0], self.border_px)
            self._detector_shape = gray.shape
        return self._detector(gray)

    def step_measurements(self, nav: NavState, uv_ideal: np.ndarray, descriptors: np.ndarray | None = None,
                          normals: np.ndarray | None = None) -> MapperStep:
        """One mapper step from ideal (undistorted) pixels ``uv_ideal`` (N, 2) in score order.

        descriptors: optional (N, K) normalised patches (:func:`patch_descriptors`, K =
        ``appearance_patch_px^2``); with them a pair must also pass the appearance check.
        normals: optional (N, 2): a unit normal for each measurement that is an edgel (a point on
        an edge, measured across it only), zeros for a corner (docs/mapper.md, "Edgels").
        """
        uv = np.asarray(uv_ideal, dtype=float)
        if uv.size == 0:
            uv = uv.reshape(0, 2)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"measurements must have shape (N, 2), got {uv.shape}")
        if descriptors is not None:
            descriptors = np.asarray(descriptors, dtype=np.float32)
            if descriptors.shape != (len(uv), self.db.template.shape[1]):
                raise ValueError(f"descriptors must have shape ({len(uv)}, {self.db.template.shape[1]}), got {descriptors.shape}")
        if normals is not None:
            normals = np.asarray(normals, dtype=float)
            if normals.shape != uv.shape:
                raise ValueError(f"normals must have shape {uv.shape}, got {normals.shape}")
        reason, P_x = _checked_pose_covariance(nav)
        if reason:
            return self._refused(nav, len(uv), reason)
        return self._step_checked(nav, P_x, uv, None if descriptors is None else GivenPatches(descriptors), normals)

    def _step_checked(
        self, nav: NavState, P_x: np.ndarray, uv: np.ndarray, patches: FramePatches | GivenPatches | None,
        normals: np.ndarray | None = None, no_start: np.ndarray | None = None,
    ) -> MapperStep:
        """:meth:`step_measurements` after its input checks: ``nav`` accepted by :func:`check_nav`
        with its symmetrised pose covariance ``P_x`` (6, 6), ``uv`` (N, 2) float, ``patches`` the
        measurements' normalised patches (N of them, ``rows(index)`` -> (k, K) float32) or None,
        ``normals`` (N, 2) the edgels' unit normals (zero rows: corners) or None (all corners),
        ``no_start`` (N,) bool the measurements that may update a feature but never start one (the
        tracker's points) or None (none)."""
        cfg, db, model = self.cfg, self.db, self.model
        self.frame += 1
        pose = CameraPose.from_nav(nav.position_ned_m, nav.quaternion_wxyz, self.mount)

        valid = _in_image(uv, self.camera)  # finite and inside
        # (count_nonzero == len is .all() at a third of its cost, which matters a dozen times a step)
        if normals is not None:
            unit = np.sqrt((normals * normals).sum(axis=1))
            valid &= np.isfinite(unit) & ((unit == 0.0) | (np.abs(unit - 1.0) < 1e-3))
        if np.count_nonzero(valid) == len(valid):  # all valid: the usual case (the detector's corners)
            meas_index, z, desc, n_z = np.arange(len(uv)), uv, patches, normals
        else:
            meas_index = np.flatnonzero(valid)  # positions in the caller's array
            z = uv[valid]
            desc = patches.subset(meas_index) if patches is not None else None
            n_z = None if normals is None else normals[valid]
        edgel = np.zeros(len(z), bool) if n_z is None else (n_z != 0.0).any(axis=1)
        may_start = None if no_start is None else ~no_start[meas_index]
        any_edges = bool(edgel.any()) or bool(db.edge[db.active_slots()].any())
        n_dropped = int(len(uv) - len(z))
        emitted: list[TerrainPoints] = []

        # Corrupt features (cannot happen through the update, which refuses non-finite results) go.
        # The stored features are gathered once (y, P, R_ref follow `slots` through the step).
        slots = db.active_slots()
        y, P, R_ref = db.y[slots], db.P[slots], db.R_ref[slots]
        removed_ids = [_empty_ids()]
        n_removed = 0
        if not math.isfinite(y.sum() + P.sum()):  # (a finite sum: every feature finite, the usual case)
            corrupt = ~(np.isfinite(y).all(axis=1) & np.isfinite(P).all(axis=(1, 2)))
            removed_ids.append(db.ids[slots[corrupt]])
            db.remove(slots[corrupt])
            n_removed = int(corrupt.sum())
            slots, y, P, R_ref = slots[~corrupt], y[~corrupt], P[~corrupt], R_ref[~corrupt]

        # Correlated navigation error (docs/mapper.md): the features live in the estimate's frame,
        # which drifts between frames (process noise on every feature); the paper's P_x in eqs. 10
        # and 17 is then zero. nav_attitude_correlation_s = 0: the paper's independent P_x every frame.
        # The direction terms of eq. 3, shared by the drift Jacobian, the prediction and eq. 5.
        directions = model.ray_directions(y, R_ref)
        P_meas = P_x
        if cfg.nav_attitude_correlation_s > 0:
            P_meas = np.zeros_like(P_x)
            q = navigation_drift(P_x, nav.t_s - self._last_nav_t, cfg.nav_attitude_correlation_s, pose.p - self._last_nav_p)
            if len(slots) and q is not None:
                J = model.navigation_frame_jacobian(y, R_ref, pose.p, directions)
                Q = J @ q @ J.transpose(0, 2, 1)
                P += 0.5 * (Q + Q.transpose(0, 2, 1))
                db.P[slots] = P
        self._last_nav_t = float(nav.t_s)
        self._last_nav_p = pose.p.copy()

        # Predict (eqs. 3-4); features behind the camera or outside the image leave the database.
        uv_pred, h_c = model.measurement_model(y, R_ref, pose, self.camera, directions)
        visible = (h_c[:, 0] > 0) & _in_image(uv_pred, self.camera)
        if np.count_nonzero(visible) < len(visible):
            leaving = slots[~visible]
            removed_ids.append(db.ids[leaving])
            db.remove(leaving)
            n_removed += len(leaving)
            slots, y, P, R_ref = slots[visible], y[visible], P[visible], R_ref[visible]
            uv_pred, h_c = uv_pred[visible], h_c[visible]
            directions = None if directions is None else directions.take(visible)

        # Match (eqs. 10-12).
        # Only pairs inside a gate or near a prediction matter (matching.candidate_pairs): the
        # distances of eqs. 11-12 are evaluated for those pairs, not for all N x M.
        C_x, C_y = model.measurement_jacobian(y, R_ref, pose, self.camera, h_c, directions)
        S = innovation_covariance(C_x, C_y, P_meas, P, self.R_img)
        S_inverse = inverse_2x2(S)  # (S^-1, positive definite): the gates', and the update's when its S is this one
        pairs = candidate_pairs(z, uv_pred, S, max(cfg.gate_chi2, cfg.init_exclusion_chi2), cfg.min_distance_px, S_inverse)
        gated = (pairs.Z < cfg.gate_chi2).nonzero()[0]
        edge_feature = db.edge[slots]
        if any_edges:  # corners are matched to corners and edge features to edgels (below)
            gated = gated[~edge_feature[pairs.point[gated]] & ~edgel[pairs.meas[gated]]]
        pair_point, pair_meas, pair_Z = pairs.point[gated], pairs.meas[gated], pairs.Z[gated]
        if desc is not None:
            # Appearance: a pair whose patches do not correlate is not a candidate at all.
            # Patches are cut for the gated pairs' measurements only; the matched ones are among them.
            pair_patches = desc.rows(pair_meas)  # (P, K), one per pair
            pair_row = np.empty(len(z), dtype=np.intp)
            pair_row[pair_meas] = np.arange(len(pair_meas))  # a row holding each paired measurement's patch
            looks = db.has_template[slots[pair_point]]
            ncc = pair_correlation(db.template[slots[pair_point]], pair_patches)
            like = ~(looks & (ncc < cfg.appearance_min_ncc))
            pair_point, pair_meas, pair_Z = pair_point[like], pair_meas[like], pair_Z[like]
        point_idx, match_idx, ambiguous = gate_and_match_pairs(pair_point, pair_meas, pair_Z, cfg.gate_chi2, len(z))
        edge_pairs = None
        if any_edges:
            edge_pairs = self._match_edges(z, n_z, edgel, uv_pred, S, edge_feature, slots, desc)
            ambiguous |= edge_pairs.ambiguous

        # Update (eqs. 6-9), all matched features at once.
        upd = slots[point_idx]
        # Without a navigation term (the correlated navigation model) the update's S of a feature is
        # the one its gate used (C_y P C_y^T + R_img): its inverse is not computed again.
        shared = (S_inverse[0][point_idx], S_inverse[1][point_idx]) if navigation_term_vanishes(P_meas, C_x) else None
        y_new, P_new, ok = ekf_update(
            y[point_idx], P[point_idx], z[match_idx] - uv_pred[point_idx], C_x[point_idx], C_y[point_idx], P_meas, self.R_img,
            shared,
        )
        if desc is not None:
            corner_templates = pair_patches[pair_row[match_idx[ok]]]
        # The consistency figure: each accepted corner update's innovation squared under the S
        # its gate used (MapperStep.innovation_nis_sum).
        nu = z[match_idx[ok]] - uv_pred[point_idx[ok]]
        S_inv = S_inverse[0][point_idx[ok]]
        innovation_nis_sum = float(np.einsum("ni,nij,nj->", nu, S_inv, nu))
        n_corner_updates = int(np.count_nonzero(ok))
        self.consistency.add(innovation_nis_sum, n_corner_updates)
        n_edge_matched = 0
        if edge_pairs is not None and len(edge_pairs.point):
            # across the edge only (update.ekf_update_across): n^T (z - g), n^T C, n^T R_eff n
            e_point, e_meas = edge_pairs.point, edge_pairs.meas
            n = n_z[e_meas]
            nu = ((z[e_meas] - uv_pred[e_point]) * n).sum(axis=1)
            H_y = np.einsum("ni,nij->nj", n, C_y[e_point])
            r = np.full(len(e_point), cfg.pixel_sigma_px**2)
            if not navigation_term_vanishes(P_meas, C_x):
                H_x = np.einsum("ni,nij->nj", n, C_x[e_point])
                r += np.einsum("ni,ij,nj->n", H_x, P_meas, H_x)
            y_e, P_e, ok_e = ekf_update_across(y[e_point], P[e_point], nu, H_y, r)
            point_idx = np.concatenate([point_idx, e_point])
            match_idx = np.concatenate([match_idx, e_meas])
            y_new, P_new, ok = np.concatenate([y_new, y_e]), np.concatenate([P_new, P_e]), np.concatenate([ok, ok_e])
            upd = slots[point_idx]
            db.normal[slots[e_point[ok_e]]] = n[ok_e]
            n_edge_matched = int(ok_e.sum())
            if desc is not None:
                corner_templates = np.concatenate([corner_templates, desc.rows(e_meas[ok_e])])
        y_new = model.normalise_state(y_new)
        db.y[upd] = y_new
        db.P[upd] = P_new
        updated = upd[ok]
        db.updates[updated] += 1
        if desc is not None:
            # A tracked point updates its feature but not its patch: the appearance check keeps
            # comparing with what the detector last found, so a track cannot drift with its patch.
            kept = slice(None) if may_start is None else may_start[match_idx[ok]]
            db.template[updated[kept]] = corner_templates[kept]
            db.has_template[updated] = True

        updated_meas = match_idx[ok]  # measurement of each accepted update
        updated_ids = db.ids[updated].copy()  # before a retired feature's slot takes a new one

        # Confidence index: +1 matched, -1 visible but not matched (or refused).
        not_updated = np.ones(len(slots), dtype=bool)
        not_updated[point_idx[ok]] = False
        unmatched = slots[not_updated]  # ascending, as slots
        db.adjust_confidence(updated, unmatched, cfg.confidence_max)

        # Convergence: a feature goes to the map once, when its depth sigma first falls below the
        # emission limit (emission_depth_sigma_limit). Before that, from floor_max_depth_sigma_m on,
        # it bounds its cell from below every frame (docs/mapper.md, "Bounds of an unconverged feature").
        y_upd, P_upd, R_upd, origin_upd = y_new[ok], P_new[ok], R_ref[point_idx[ok]], db.origin[updated]
        X_upd = model.point(y_upd, R_upd)  # each updated feature's point, for both of its bounds
        angle_sigma = float(np.sqrt(max(np.linalg.eigvalsh(P_x[3:6, 3:6])[-1], 0.0)))  # the attitude's largest axis
        free_space = self._free_space(nav.t_s, pose.p_c, y_upd, P_upd, R_upd, origin_upd, X_upd, updated_ids, angle_sigma)
        rel = model.relative_depth_sigma(y_upd, P_upd, R_upd, origin_upd)
        depth_sigma = rel * model.depth_from_origin(y_upd, R_upd, origin_upd)
        # an edgel measures one coordinate, a corner two: an edge feature needs twice the updates
        min_updates = np.where(db.edge[updated], 2 * cfg.converge_min_updates, cfg.converge_min_updates)
        ready = (db.updates[updated] >= min_updates) & (rel < cfg.converged_rel_depth_sigma)
        limit = emission_depth_sigma_limit(X_upd[:, 2] - pose.p_c[2], cfg)
        newly = ~db.converged[updated] & ready & (depth_sigma < limit)
        bounding = ~db.converged[updated] & ~newly & ready & (depth_sigma < cfg.floor_max_depth_sigma_m)
        floors = self._floors(nav.t_s, y_upd[bounding], P_upd[bounding], R_upd[bounding], origin_upd[bounding],
                              X_upd[bounding], db.ids[updated[bounding]])
        if np.count_nonzero(newly):
            db.converged[updated[newly]] = True
            emitted.append(self._emitted_points(nav.t_s, updated[newly], pose.p_c, P_x[3:6, 3:6]))

        # Initialise unmatched, unambiguous measurements (eqs. 13-17) in score order.
        n_matched = len(updated)
        init_index = max(0.0, cfg.init_index_max * (1.0 - n_matched / db.capacity))
        used = np.zeros(len(z), dtype=bool)
        used[match_idx] = True
        blocked = ambiguous | near_stored_pairs(pairs, len(z), cfg.init_exclusion_chi2, cfg.min_distance_px)
        if edge_pairs is not None:
            blocked |= edge_pairs.near
        candidates = np.flatnonzero(~used & ~blocked if may_start is None else ~used & ~blocked & may_start)
        if any_edges and len(candidates):
            # an edgel in a bin with no corner and no stored feature in view comes before the
            # corners: a plain face's outline would otherwise never get a slot among the corners
            # of a textured ground; but edge features hold at most half the database that way,
            # or the edges of far, blurred ground take the slots a faint obstacle's corners need
            n_bins = cfg.bins_x * cfg.bins_y
            bins = self._bins(z[candidates])
            seen = np.bincount(self._bins(uv_pred), minlength=n_bins) + np.bincount(self._bins(z[~edgel]), minlength=n_bins)
            first = edgel[candidates] & (seen[bins] == 0)
            room = max(0, db.capacity // 2 - int(np.count_nonzero(db.edge & db.active)))
            first &= np.cumsum(first) <= room
            candidates = np.concatenate([candidates[first], candidates[~first]])
        free = db.free_slots()
        replaceable = unmatched[db.confidence[unmatched] < init_index]
        replaceable = replaceable[np.lexsort((db.born_frame[replaceable], db.confidence[replaceable]))]
        if cfg.retire_converged:
            # A converged feature's point is already in the map: its slot goes to new terrain first
            # (oldest first), before the lost features the paper's rule replaces.
            done = slots[db.converged[slots]]
            done = done[~np.isin(done, replaceable)]
            done = done[np.argsort(db.born_frame[done], kind="stable")]
            replaceable = np.concatenate([done, replaceable])
        n_new = min(len(candidates), len(free) + len(replaceable))
        targets = np.concatenate([free, replaceable])[:n_new].astype(np.intp)
        replaced = targets[len(free):]
        if len(replaced):
            removed_ids.append(db.ids[replaced])
            db.remove(replaced)
            n_removed += len(replaced)

        new_ids = _empty_ids()
        n_fallback = 0
        chosen = candidates[:n_new]
        if n_new:
            h, _ = camera_ray_from_pixel(z[chosen], self.camera)
            rays = (h / np.sqrt((h * h).sum(axis=1, keepdims=True))) @ pose.R_nc.T  # unit rays, NED
            ranges, n_fallback = prior_ranges(
                self.depth_prior, pose.p_c, rays, self.default_ground_alt_m, cfg.prior_min_range_m, cfg.prior_max_range_m
            )
            y0, P0, R_ref0 = model.initialise_features(
                z[chosen], ranges, pose, self.camera, self.R_img, self.prior_sigma, P_meas
            )
            new_ids = db.insert(targets, y0, P0, R_ref0, pose.p_c, int(round(init_index)), self.frame,
                                None if n_z is None else n_z[chosen])
            if desc is not None:
                db.template[targets] = desc.rows(chosen)
                db.has_template[targets] = True

        n_update_rejected = int((~ok).sum())
        removed = np.concatenate(removed_ids)
        return MapperStep(
            points=_concatenate(nav.t_s, emitted),
            n_measurements=len(uv),
            n_matched=n_matched,
            n_initialised=n_new,
            n_removed=n_removed,
            n_active=db.n_active,
            n_rejected=n_dropped + n_update_rejected,
            n_dropped=n_dropped,
            n_update_rejected=n_update_rejected,
            n_ambiguous=int(ambiguous.sum()),
            n_excluded=int((blocked & ~used & ~ambiguous).sum()),
            n_prior_fallback=n_fallback,
            init_index=init_index,
            matched_ids=updated_ids,
            matched_measurements=meas_index[updated_meas].astype(np.int64),
            initialised_ids=new_ids,
            initialised_measurements=meas_index[chosen].astype(np.int64),
            removed_ids=removed,
            free_space=free_space,
            floors=replace(floors, ended_ids=removed.copy()),
            n_edgels=int(edgel.sum()),
            n_edge_matched=n_edge_matched,
            innovation_nis_sum=innovation_nis_sum,
            n_corner_updates=n_corner_updates,
            point_covariance_scale=self.point_covariance_scale,
        )

    # ------------------------------------------------------------------------------------------
    def _match_edges(self, z: np.ndarray, n_z: np.ndarray | None, edgel: np.ndarray, uv_pred: np.ndarray,
                     S: np.ndarray, edge_feature: np.ndarray, slots: np.ndarray, desc) -> "_EdgePairs":
        """Edge features (rows of ``uv_pred``, ``S`` where ``edge_feature``) matched to edgels (rows
        of ``z``, ``n_z`` where ``edgel``) (docs/mapper.md, "Edgels"). A pair is a candidate when

        * the distance across the measured edge, ``nu = n^T (z - g)``, is inside the 1-dof gate
          with the same probability as the corners' 2-dof one: ``nu^2 / (n^T S n) < g_1``;
        * along the edge the measurement is no farther from the prediction than the detector's
          spacing plus the prediction's own gate: ``|t^T (z - g)| < min_distance_px + sqrt(g_2 t^T S t)``
          (a straight edge says nothing about where along it the point is, but it must be the
          stretch of edge the feature is on);
        * the edge turned by at most ``edgel_max_turn_deg`` since the feature's last match, the same
          way round (``n^T n_feature >= cos``: bright and dark sides not swapped);
        * the patches correlate (the corners' appearance check).

        A feature whose gate holds two edges (edgels more than ``EDGE_SPREAD_SIGMA`` pixel sigmas
        apart across the edge) is not matched: an edge's patch does not tell two edges apart. Then
        mutual nearest by ``nu^2 / (n^T S n)``, as for corners. Also returns the edgels inside some
        edge feature's gate but not matched (``ambiguous``) and those within the initialisation
        exclusion (``near``), neither of which starts a new feature."""
        cfg = self.cfg
        fe = np.flatnonzero(edge_feature)
        me = np.flatnonzero(edgel)
        ambiguous = np.zeros(len(z), bool)
        near = np.zeros(len(z), bool)
        if len(fe) == 0 or len(me) == 0:
            return _EdgePairs(_empty_ids(), _empty_ids(), ambiguous, near)
        e = z[me][None, :, :] - uv_pred[fe][:, None, :]  # (F, E, 2)
        n = n_z[me][None, :, :]
        t = np.stack([-n[..., 1], n[..., 0]], axis=-1)
        Sf = S[fe][:, None, :, :]  # (F, 1, 2, 2)
        def quad(a):  # a^T S a for the (F, E, 2) directions a
            return a[..., 0] ** 2 * Sf[..., 0, 0] + 2 * a[..., 0] * a[..., 1] * Sf[..., 0, 1] + a[..., 1] ** 2 * Sf[..., 1, 1]
        nu = (e * n).sum(axis=-1)
        along = (e * t).sum(axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            Z = nu * nu / quad(n)
        reach = np.abs(along) < cfg.min_distance_px + np.sqrt(cfg.gate_chi2 * quad(t))
        turn = (n * self.db.normal[slots[fe]][:, None, :]).sum(axis=-1) >= self.edge_min_cos
        close = reach & turn
        near[me[((close & (Z < self.edge_exclusion)) | ((e * e).sum(axis=-1) < cfg.min_distance_px**2)).any(axis=0)]] = True
        inside = close & (Z < self.edge_gate)
        # One edge looks like another (a step's patch correlates with any step of the same turn and
        # polarity), so a feature whose gate holds two edges is not updated: it could be either.
        # Edgels of one edge are at the same distance across it (within the pixel noise); two edges
        # are farther apart than that.
        nu_in = np.where(inside, nu, np.nan)
        with np.errstate(invalid="ignore"):
            spread = np.nanmax(nu_in, axis=1, initial=-np.inf) - np.nanmin(nu_in, axis=1, initial=np.inf)
        inside &= (spread <= EDGE_SPREAD_SIGMA * cfg.pixel_sigma_px)[:, None]
        fi, mi = np.nonzero(inside)
        point, meas, Zp = fe[fi], me[mi], Z[fi, mi]
        if desc is not None and len(point):
            looks = self.db.has_template[slots[point]]
            ncc = pair_correlation(self.db.template[slots[point]], desc.rows(meas))
            like = ~(looks & (ncc < cfg.appearance_min_ncc))
            point, meas, Zp = point[like], meas[like], Zp[like]
        p_idx, m_idx, amb = gate_and_match_pairs(point, meas, Zp, self.edge_gate, len(z))
        return _EdgePairs(p_idx, m_idx, amb, near)

    def _free_space(self, t_s: float, camera_ned: np.ndarray, y: np.ndarray, P: np.ndarray, R_ref: np.ndarray,
                    origin: np.ndarray, X: np.ndarray, ids: np.ndarray, angle_sigma: float = 0.0) -> FreeSpaceRays:
        """The segments this frame saw through (docs/mapper.md, "Bounds of an unconverged feature"):
        from the camera centre along the line of sight of each feature (rows of y, P, R_ref, origin;
        X its point; ids its id; angle_sigma the attitude's sigma, rad), as far as the nearest the
        feature can be at ``free_space_sigma`` sigma (the model's ``point_at_sigma``, taken as a
        range from the camera and laid on the line of sight to the estimate, never beyond the
        estimate)."""
        k = self.cfg.free_space_sigma
        if k <= 0 or len(y) == 0:
            return FreeSpaceRays(t_s, np.asarray(camera_ned, dtype=float), np.zeros((0, 3)), np.zeros(0, np.int64), angle_sigma)
        near = self.model.point_at_sigma(y, P, R_ref, origin, k)
        to_x = X - camera_ned
        r = np.sqrt((to_x * to_x).sum(axis=1))
        r_near = np.sqrt(((near - camera_ned) ** 2).sum(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = np.minimum(r_near, r)
            ends = camera_ned + to_x * (reach / r)[:, None]
        good = np.isfinite(ends).all(axis=1) & (reach > 0)
        return FreeSpaceRays(t_s, np.asarray(camera_ned, dtype=float).copy(), ends[good], np.asarray(ids, np.int64)[good], angle_sigma)

    def _floors(self, t_s: float, y: np.ndarray, P: np.ndarray, R_ref: np.ndarray, origin: np.ndarray,
                X: np.ndarray | None = None, ids: np.ndarray | None = None) -> TerrainFloors:
        """Lower bounds on the terrain's height (docs/mapper.md, "Bounds of an unconverged
        feature"): each feature (rows of y, P, R_ref, origin) lies on the terrain, so the terrain
        in its cell reaches at least the lower of its estimate and its point ``floor_sigma`` sigma
        farther along the line of sight (the far bound; for a line of sight looking down, the lower
        end). Placed at the estimate's north and east. ``X``: the features' points, when known."""
        if len(y) == 0:
            return TerrainFloors.empty(t_s)
        if X is None:
            X = self.model.point(y, R_ref)
        far = self.model.point_at_sigma(y, P, R_ref, origin, -self.cfg.floor_sigma)
        down = np.fmax(X[:, 2], far[:, 2])  # NED: the lower of the two (NaN far: at infinity, no bound)
        keep = np.isfinite(X).all(axis=1) & np.isfinite(far[:, 2])
        return TerrainFloors(t_s, np.column_stack([X[keep, 0], X[keep, 1], down[keep]]),
                             None if ids is None else np.asarray(ids)[keep].copy())

    def _points(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (K, 3) and its covariance ``J P_y J^T`` (K, 3, 3) of the features in ``slots``."""
        X, J = self.model.point_from_state(self.db.y[slots], self.db.R_ref[slots])
        cov = J @ self.db.P[slots] @ J.transpose(0, 2, 1)
        return X, 0.5 * (cov + cov.transpose(0, 2, 1))

    def _emitted_points(self, t_s: float, slots: np.ndarray, camera_ned: np.ndarray, P_attitude: np.ndarray) -> TerrainPoints:
        """Converged features as terrain points, with the feature's own covariance ``J P_y J^T``
        scaled by the measured consistency (:class:`ConsistencyScale`).

        With the correlated navigation model that covariance is relative to the estimate's frame,
        and so is the map: the vehicle flies on the same estimate, so the error the navigation
        shares with every point of a pass moves the vehicle and the map together and is not an error
        of the map for the law (docs/mapper.md, "Point covariance"). Adding it (0.8 m of vertical
        navigation error on every point of the simulated flights) tripled the points' height sigma
        against their scatter in the frame, and the law's margin above each cell with it. What the
        vehicle does not share is the estimate's tilt, which turns the point about ``camera_ned``
        (the camera's position this step): :func:`tilt_covariance` of the roll and pitch block of
        ``P_attitude`` (3, 3) is added after the scale (``mapper.point_tilt_covariance``)."""
        if len(slots) == 0:
            return TerrainPoints.empty(t_s)
        X, cov = self._points(slots)
        cov = cov * self.point_covariance_scale
        if self.cfg.point_tilt_covariance and self.cfg.nav_attitude_correlation_s > 0:
            # (the paper's independent P_x every frame is in the updates already, and so in J P_y J^T)
            cov = cov + tilt_covariance(X - camera_ned, P_attitude)
        finite = np.isfinite(X).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
        return TerrainPoints(t_s, X[finite], cov[finite], self.db.ids[slots][finite].copy())

    @property
    def point_covariance_scale(self) -> float:
        """The factor on emitted points' covariances: the measured consistency's
        (``mapper.calibrate_point_covariance``), else 1."""
        return self.consistency.scale if self.cfg.calibrate_point_covariance else 1.0

    def _refused(self, nav: NavState, n_measurements: int, reason: str) -> MapperStep:
        t_s = float(nav.t_s) if np.isfinite(nav.t_s) else 0.0
        return MapperStep(
            points=TerrainPoints.empty(t_s),
            n_measurements=n_measurements,
            n_matched=0,
            n_initialised=0,
            n_removed=0,
            n_active=self.db.n_active,
            n_rejected=n_measurements,
            rejected_reason=reason,
        )

    def features(self) -> FeatureSnapshot:
        """Every stored feature with its position estimate and covariance."""
        slots = self.db.active_slots()
        X, cov = self._points(slots)
        db = self.db
        rel = self.model.relative_depth_sigma(db.y[slots], db.P[slots], db.R_ref[slots], db.origin[slots])
        return FeatureSnapshot(
            ids=db.ids[slots].copy(),
            positions_ned_m=X,
            covariances=cov,
            relative_depth_sigma=rel,
            converged=db.converged[slots].copy(),
            confidence=db.confidence[slots].copy(),
            updates=db.updates[slots].copy(),
            states=db.y[slots].copy(),
        )
