"""Typed configuration, loaded once from YAML and validated.

Every section is a frozen dataclass. A field's ``metadata`` may carry ``unit`` (documentation),
``min``/``max`` (inclusive bounds) and ``choices``. :func:`load_config` reads a YAML file,
merges it over the defaults, and raises :class:`ConfigError` naming the file and the dotted
key for any unknown key, wrong type or out-of-range value, so the daemon refuses to start
rather than guess.

Sections own their keys: ``link`` (autopilot MAVLink), ``nav`` (covariance floors),
``camera`` (source, intrinsics, mount), ``mapper``, ``terrain``, ``avoidance``,
``control``, ``zenoh``, ``persistence``, ``sim``.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml


class ConfigError(ValueError):
    """A configuration problem; the message names the file and the dotted key."""


def _f(default: Any, unit: str = "", lo: float | None = None, hi: float | None = None, doc: str = ""):
    """A dataclass field with documentation metadata and inclusive bounds."""
    meta = {"unit": unit, "min": lo, "max": hi, "doc": doc}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults")
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------------------------
# Sections
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LinkConfig:
    """Autopilot link (pymavlink connection string as MAVProxy/mavlink-router users write it)."""

    connection: str = _f("udpin:127.0.0.1:14550", doc="udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial device")
    baud: int = _f(921600, "bit/s", 1200, 10_000_000, "serial baud rate (ignored for network links)")
    source_system: int = _f(1, "", 1, 255, "our MAVLink system id (normally the vehicle's)")
    source_component: int = _f(191, "", 1, 255, "our component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)")
    target_system: int = _f(0, "", 0, 255, "autopilot system id; 0 = the first autopilot heard")
    autopilot: Literal["auto", "ardupilot", "px4"] = _f("auto", doc="autopilot flavour; auto = from HEARTBEAT")
    heartbeat_rate_hz: float = _f(1.0, "Hz", 0.1, 10.0)
    nav_stream_rate_hz: float = _f(50.0, "Hz", 1.0, 400.0, "requested rate of navigation messages")
    heartbeat_timeout_s: float = _f(3.0, "s", 0.5, 60.0, "autopilot heartbeat silence that counts as link lost")
    reconnect_backoff_max_s: float = _f(5.0, "s", 0.1, 300.0)
    signing_key_file: str = _f("", doc="MAVLink 2 signing key file (32 bytes or 64 hex chars, mode 600: refused if group/others may read it); empty = no signing")
    signing_required: bool = _f(False, doc="reject unsigned messages (badly signed and replayed ones are always rejected)")
    connect_timeout_s: float = _f(3.0, "s", 0.1, 60.0, "TCP connect attempt limit")
    aux_stream_rate_hz: float = _f(5.0, "Hz", 0.1, 50.0, "requested rate of EKF_STATUS_REPORT, ESTIMATOR_STATUS, GPS_RAW_INT")
    timesync_rate_hz: float = _f(1.0, "Hz", 0.1, 10.0, "TIMESYNC round trips per second (SYSTEM_TIME is requested at the same rate)")
    stream_check_s: float = _f(3.0, "s", 0.5, 60.0, "a requested stream silent this long is requested again (with backoff)")
    command_timeout_s: float = _f(1.0, "s", 0.05, 30.0, "wait for COMMAND_ACK before resending")
    command_retries: int = _f(3, "", 1, 20, "COMMAND_LONG attempts before giving up")
    request_sim_state: bool = _f(False, doc="also request SIM_STATE (simulator truth) for a synthetic camera")


@dataclass(frozen=True, slots=True)
class NavConfig:
    """Navigation covariance floors (used when the autopilot reports less, or nothing)."""

    position_sigma_floor_m: float = _f(0.3, "m", 0.0, 100.0)
    velocity_sigma_floor_mps: float = _f(0.1, "m/s", 0.0, 100.0)
    attitude_sigma_floor_deg: float = _f(0.5, "deg", 0.0, 45.0)
    yaw_sigma_floor_deg: float = _f(0.0, "deg", 0.0, 90.0, "heading floor on top of attitude_sigma_floor_deg (0 = that floor alone); "
                                    "ArduPilot sends no attitude covariance, so with it this is the heading sigma the mapper assumes "
                                    "(config/sitl.yaml: the simulator's sim.nav_yaw_sigma_deg)")
    stale_after_s: float = _f(0.5, "s", 0.01, 10.0, "navigation older than this stops commanding")
    buffer_s: float = _f(5.0, "s", 0.1, 120.0, "history kept for interpolation at frame times")
    buffer_max_gap_s: float = _f(0.5, "s", 0.01, 60.0, "no interpolation across a gap in the navigation longer than this")
    buffer_extrapolate_s: float = _f(0.05, "s", 0.0, 5.0, "how far past the newest navigation a frame time may be extrapolated")
    max_skew_s: float = _f(0.1, "s", 0.001, 5.0, "position and attitude further apart than this are not combined into a state")
    covariance_max_age_s: float = _f(2.0, "s", 0.05, 60.0, "covariance evidence (*_COV, EKF/GPS status) older than this is not used")
    innovation_ratio_good: float = _f(0.5, "", 0.01, 10.0, "test ratio below which the EKF_STATUS_REPORT/ESTIMATOR_STATUS heuristic leaves sigmas unscaled")


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """Camera source, pinhole intrinsics (pixels), OpenCV distortion and the mount on the body."""

    source: Literal["v4l2", "file", "synthetic", "stream"] = _f("synthetic", doc="synthetic = rendered in this process from the simulator's truth; stream = frames over TCP stamped in the autopilot's time (companion sim --camera-listen; docs/cameras.md)")
    device: str = _f("/dev/video0", doc="V4L2 device path or index")
    stream_address: str = _f("127.0.0.1:5600", doc="stream source: HOST:PORT of the frame stream server")
    path: str = _f("", doc="recorded source: video file or image folder")
    realtime: bool = _f(True, doc="recorded source: replay at the recorded rate (false = as fast as possible)")
    width: int = _f(640, "px", 16, 8192)
    height: int = _f(480, "px", 16, 8192)
    rate_hz: float = _f(20.0, "Hz", 0.5, 500.0)
    pixel_format: str = _f("GREY", doc="V4L2 FOURCC (GREY, YUYV, MJPG)")
    exposure_us: float = _f(0.0, "us", 0.0, 1e6, "0 = automatic")
    fx: float = _f(625.3, "px", 1.0, 1e5, "focal length along u (paper f_u); default = 42 deg vertical FOV at 480 px")
    fy: float = _f(625.3, "px", 1.0, 1e5)
    cx: float = _f(319.5, "px", -1e4, 1e4)
    cy: float = _f(239.5, "px", -1e4, 1e4)
    distortion: tuple[float, ...] = _f((0.0, 0.0, 0.0, 0.0, 0.0), doc="OpenCV k1 k2 p1 p2 [k3 ...]")
    mount_roll_deg: float = _f(0.0, "deg", -180.0, 180.0, "camera axes relative to the body (FRD), ZYX Euler")
    mount_pitch_deg: float = _f(-45.0, "deg", -90.0, 90.0, "-45 = optical axis 45 deg below the nose")
    mount_yaw_deg: float = _f(0.0, "deg", -180.0, 180.0)
    mount_offset_m: tuple[float, ...] = _f((0.0, 0.0, 0.0), "m", doc="camera centre in body FRD")
    border_px: int = _f(8, "px", 0, 1000, "features closer than this to the image edge (or a black mask) are ignored")
    timestamps_file: str = _f("", doc="recorded source: timestamp file; empty = frames.csv / timestamps.txt in the folder, <video>.csv beside a video, else the video's frame rate")
    reconnect_backoff_max_s: float = _f(5.0, "s", 0.05, 300.0, "V4L2: longest wait between reopen attempts after the device is lost")
    blank_std_max: float = _f(1.0, "grey levels", 0.0, 255.0, "frames whose pixel standard deviation is at most this (all black, white or flat) are rejected; 0 = off")
    gap_factor: float = _f(3.0, "frame periods", 1.5, 1e6, "an interval longer than this many frame periods is counted as a gap")
    record_format: Literal["png", "jpg"] = _f("png", doc="--record image format: png is lossless")
    record_png_compression: int = _f(-1, "", -1, 9, "--record PNG zlib level; -1 = OpenCV's default (fast)")
    record_jpeg_quality: int = _f(95, "", 1, 100, "--record JPEG quality")
    record_queue_frames: int = _f(64, "frames", 1, 10000, "--record queue; frames beyond it are dropped and counted, never waited for")


@dataclass(frozen=True, slots=True)
class MapperConfig:
    """Monocular terrain mapper (seed 000, section II)."""

    parameterisation: Literal["inverse_depth", "cartesian"] = _f("inverse_depth")
    max_features: int = _f(50, "", 1, 5000, "feature database capacity (paper: 50)")
    max_detections: int = _f(100, "", 1, 10000, "Harris corners passed on per frame, in score order")
    bins_x: int = _f(8, "", 1, 64)
    bins_y: int = _f(6, "", 1, 64)
    per_bin: int = _f(4, "", 1, 1000, "maximum corners per bin")
    min_distance_px: float = _f(10.0, "px", 0.0, 1000.0)
    harris_k: float = _f(0.04, "", 0.0, 0.25)
    harris_block_size: int = _f(3, "px", 2, 31)
    harris_quality: float = _f(0.01, "", 0.0, 1.0, "minimum response relative to the frame's best")
    harris_min_response: float = _f(1e-8, "", 0.0, 1.0, "absolute response floor (OpenCV's 8-bit scaling; 1e-8 ~ a 7-grey-level step corner)")
    subpix_window_px: int = _f(3, "px", 0, 15, "half-size of the sub-pixel corner refinement window; 0 = integer pixels")
    pixel_sigma_px: float = _f(1.0, "px", 0.01, 100.0, "R_img = sigma^2 I")
    max_edgels: int = _f(40, "", 0, 10000, "edgels (points on image edges) passed on per frame from the bins where no corner was found: a plain roof's or wall's outline measures its height where it has no corner (docs/mapper.md, \"Edgels\"); 0 = corners only (the paper)")
    edgel_min_step_grey: float = _f(8.0, "grey levels", 1.0, 255.0, "an edgel's edge is a grey-level step at least this high")
    edgel_min_crossing_deg: float = _f(45.0, "deg", 0.0, 90.0, "an edgel is used only where its edge crosses the image motion of the camera's translation at least at this angle: an edge along that motion says nothing of depth, and a slightly curved one slides along itself into a false depth")
    edgel_max_turn_deg: float = _f(30.0, "deg", 0.0, 90.0, "an edgel is matched to an edge feature only if its edge turned at most this much since the feature's last match")
    gate_chi2: float = _f(9.21, "", 0.1, 1000.0, "Z_lim: chi-square 2 dof (9.21 = 99%)")
    sigma_rho: float = _f(0.05, "1/m", 1e-6, 10.0, "inverse-depth prior sigma at initialisation")
    sigma_depth_rel: float = _f(0.5, "", 1e-3, 10.0, "Cartesian baseline: depth prior sigma relative to depth")
    converged_rel_depth_sigma: float = _f(0.1, "", 1e-4, 1.0, "converged when sigma_depth / depth falls below this")
    confidence_max: int = _f(100, "", 1, 10000)
    init_index_max: float = _f(20.0, "", 0.0, 10000.0, "initialisation index when nothing matched")
    init_exclusion_chi2: float = _f(23.0, "", 0.1, 1000.0, "an unmatched measurement this close (Mahalanobis) to a stored feature is not initialised (23 = 1e-5 tail)")
    converge_min_updates: int = _f(3, "", 1, 10000, "EKF updates a feature needs before it may count as converged")
    converged_max_depth_sigma_m: float = _f(0.6, "m", 1e-3, 1e4, "converged also needs the depth sigma (m) below this (a far feature at 10 % is metres off), or below converged_depth_sigma_per_height times the camera's height above the feature where that is more")
    converged_depth_sigma_per_height: float = _f(0.04, "", 0.0, 10.0, "the emission limit grows with the camera's height above the feature: what its sigma eats into is the clearance over it, and from the height of a climb the ground beyond is far (docs/mapper.md, \"Convergence and emission\"); 0 = converged_max_depth_sigma_m alone")
    calibrate_point_covariance: bool = _f(True, "", None, None, "scale each emitted point's covariance by the filter's measured consistency: the running mean of the corner updates' innovation squared over its expectation, 2 (docs/mapper.md, \"Calibrated point covariance\"); false = the filter's own covariance")
    point_tilt_covariance: bool = _f(True, "", None, None, "add to each emitted point's covariance what the navigation's roll and pitch sigma make of it at its lever arm from the camera: a tilt of the estimate raises the map ahead of the vehicle by the range times the angle, and the vehicle does not share that error (docs/mapper.md, \"The navigation's tilt\"); only with the correlated navigation model (nav_attitude_correlation_s > 0: with the paper's independent P_x every frame the updates hold it already); false = the feature's covariance alone")
    calibration_memory_updates: float = _f(5000.0, "updates", 1.0, 1e9, "that running mean forgets with this many corner updates (about 100 frames)")
    calibration_min_updates: float = _f(500.0, "updates", 0.0, 1e9, "the filter's own covariance until the running mean holds this many corner updates")
    calibration_max_factor: float = _f(10.0, "", 1.0, 1000.0, "the scale stays within 1/this .. this: a filter whose innovations are far off its covariance has a defect to fix, not a scale to find")
    floor_max_depth_sigma_m: float = _f(2.0, "m", 0.0, 1e4, "a feature not yet converged whose depth sigma is below this bounds the terrain in its cell from below, every frame, until it converges: the warning a far surface gives before its point is precise (docs/mapper.md); 0 = none")
    floor_sigma: float = _f(1.0, "sigma", 0.0, 10.0, "that lower bound is the lower of the estimate and its point this many sigma farther along the line of sight")
    track_window_px: int = _f(0, "px", 0, 63, "window of the pyramidal Lucas-Kanade tracker that follows each corner that measured a feature not yet converged last frame into this frame, as a measurement beside the detector's corners (one the detector did not find again still updates its feature; a tracked point never starts a feature) (docs/mapper.md, \"Tracking between detections\"); 0 = detections only (the paper)")
    track_levels: int = _f(2, "", 0, 6, "pyramid levels above the image for that tracker (each halves the image: 2 follows motions up to about 4 windows)")
    track_max_fb_px: float = _f(0.5, "px", 0.0, 100.0, "a tracked point is kept only if tracking it back into the last frame lands within this of where it started (forward-backward check)")
    appearance_patch_px: int = _f(9, "px", 0, 31, "edge of the grey-level patch compared between a feature and a measurement; 0 = Mahalanobis matching only (the paper)")
    appearance_min_ncc: float = _f(0.7, "", -1.0, 1.0, "a pair is only matched if the patches' normalised cross-correlation reaches this")
    map_depth_prior: bool = _f(True, "", None, None, "a new feature's depth prior is the range to the mapped terrain along its line of sight where the map has one; false = the flat ground at terrain.default_ground_alt_m for every feature (the paper's eq. 16)")
    prior_min_range_m: float = _f(1.0, "m", 0.01, 1e4, "depth prior ranges are clipped to at least this")
    prior_max_range_m: float = _f(200.0, "m", 1.0, 1e6, "range given to rays that miss the ground (rho = 1/this)")
    retire_converged: bool = _f(True, "", None, None, "a converged feature (its point is in the map) is the first to give its slot to a new measurement, so the database keeps room for the terrain ahead; false = the paper's rule alone")
    free_space_sigma: float = _f(3.0, "sigma", 0.0, 10.0, "free space for the map's carving: each updated feature's line of sight up to the nearest it can be at this many sigma (inverse depth: rho + k sigma_rho); 0 = none")
    nav_attitude_correlation_s: float = _f(10.0, "s", 0.0, 1e6, "features live in the autopilot's estimated frame, which drifts between frames: "
                                           "attitude as a Gauss-Markov error with this correlation time, (1 - exp(-2 dt / this)) P_att; 0 = the paper's independent P_x every frame")
    flow_rises: bool = _f(True, doc="range a lattice of pixels by dense optical flow against earlier frames and give a floor to each cell whose top stands flow_min_rise_m above the ground around it in most of the last frames: a face whose corners lose to the ground's (a mast in shade) warns the law at the range the flow sees it (docs/mapper.md, \"Rises seen by dense flow\"); the service runs it in a thread of its own beside the mapper's; false = corners and edgels only")
    flow_frames_apart: tuple[int, ...] = _f((3, 10), "frames", doc="the earlier frames each frame's flow is measured against (a near one ranges what moves fast in the image, a far one gives the parallax for far surfaces)")
    flow_lattice_px: int = _f(8, "px", 2, 64, "spacing of the pixels ranged by the flow")
    flow_every_frames: int = _f(2, "frames", 1, 100, "measure the flow on every this many frames (each pair costs two flows, one each way, about 3.5 ms each at 640 x 480 on one core); the others are kept for later pairs; the votes below count the frames measured")
    flow_pixel_sigma_px: float = _f(0.7, "px", 0.01, 100.0, "error of a flow vector's end, per line of sight, in the range's sigma")
    flow_max_fb_px: float = _f(0.7, "px", 0.0, 100.0, "a pixel is ranged only if its flow into the earlier frame and back lands within this of where it started (occlusions and slid matches fail)")
    flow_min_range_m: float = _f(10.0, "m", 0.0, 1e4, "ranges nearer than this are not used (a wrong flow's lines of sight cross near the camera, with a small sigma)")
    flow_max_range_sigma_m: float = _f(0.8, "m", 0.01, 1e4, "ranges less precise than this are not used")
    flow_cell_m: float = _f(1.0, "m", 0.05, 100.0, "the cell a rise is judged in (the terrain grid's, terrain.cell_size_m)")
    flow_ground_radius_m: float = _f(5.0, "m", 0.0, 1000.0, "a cell's ground is the lowest median height of the cells within this radius, in the same frame")
    flow_min_rise_m: float = _f(2.0, "m", 0.0, 1e4, "a cell rises when its top (second highest point) stands more than this above its ground")
    flow_persist_frames: int = _f(3, "frames", 1, 1000, "a rising cell gets a floor once it rose in this many of the last flow_persist_window frames (one pair's wrong flow or pose does not)")
    flow_persist_window: int = _f(5, "frames", 1, 1000, "the frames that vote on a rise")
    flow_surface: bool = _f(True, doc="the flat surfaces the flow's nearest pair ranges go to the map as evidence: per frame, each cell whose points lie on one flat surface with its neighbours gives the median of its points' heights, with the variance of the median and of the pair's pose error (docs/mapper.md, \"Surfaces seen by dense flow\"); the ground the corners leave unmapped gets a height, and the law no longer stands in the highest cell near it; false = the flow's rises only")
    flow_surface_min_points: int = _f(5, "points", 3, 10000, "a cell's flat surface needs at least this many of the frame's points in the cell, and in each neighbour it is compared with")
    flow_surface_flat_m: float = _f(1.0, "m", 0.01, 100.0, "a cell is flat when its points (second highest minus second lowest) and the medians of its neighbours lie within this of each other: a wall's face or the ground beside it is not")
    flow_surface_looks: int = _f(3, "frames", 1, 100, "a cell's flat surface goes to the map as the mean of this many measured frames' looks at it (one frame's pose error moves all its cells at once; each look is given once)")
    flow_pair_position_sigma_m: float = _f(0.03, "m", 0.0, 100.0, "the navigation's position error between two frames a flow pair apart (per axis): it scales every range of the pair by its share of the baseline")
    flow_pair_attitude_sigma_deg: float = _f(0.03, "deg", 0.0, 90.0, "the navigation's attitude error between two frames a flow pair apart: it turns every line of sight of one frame against the other's")
    flow_thread_nice: int = _f(10, "", 0, 19, "the service runs the dense flow in a thread of its own at this nice value (Linux): where it shares a core with the mapper's thread, the mapper's frames go first and the flow takes what is left; 0 = the same priority")

    @property
    def flow_on(self) -> bool:
        """Whether the dense-flow stage runs (its rises, its surfaces, or both)."""
        return self.flow_rises or self.flow_surface


@dataclass(frozen=True, slots=True)
class TerrainConfig:
    """Evidence grid of terrain altitudes (seed 000, section II.E)."""

    cell_size_m: float = _f(1.0, "m", 0.05, 100.0)
    tile_cells: int = _f(32, "cells", 4, 1024, "tile edge length in cells")
    default_ground_alt_m: float = _f(0.0, "m", -1e4, 1e4, "altitude (up, local NED origin) assumed before the map knows")
    spread_sigma: float = _f(2.0, "sigma", 0.5, 5.0, "a point's horizontal covariance spreads it over the cells within this many sigma")
    max_spread_cells: int = _f(3, "cells", 0, 16, "largest spread radius around a point's own cell")
    min_height_sigma_m: float = _f(0.05, "m", 1e-4, 100.0, "floor on a point's height sigma (no point is exact)")
    max_horizontal_sigma_m: float = _f(2.0, "m", 0.01, 1e4, "a point whose horizontal sigma (largest axis) exceeds this cannot say which cell it is in: rejected")
    gate_sigma: float = _f(3.0, "sigma", 0.5, 100.0, "a point this far above a cell's estimate (innovation sigma) is a higher surface: it waits for a second one to confirm it, then replaces the cell")
    below_gate_sigma: float = _f(3.0, "sigma", 0.5, 100.0, "a point this far below a cell's estimate (innovation sigma) is a lower surface of the cell (a wall's face): ignored for the height, counted as disagreement (reset_evidence)")
    gate_min_count: int = _f(2, "points", 1, 1_000_000, "the gates apply once a cell holds this much evidence")
    reset_evidence: float = _f(20.0, "points", 0.1, 1e6, "points below a cell, with none agreeing in between, that bring it down to them (a wall's face sends many: keep it well above a few)")
    process_noise_m2: float = _f(1e-4, "m^2", 0.0, 100.0, "added to a cell's variance before each update, so the map can forget")
    max_abs_coordinate_m: float = _f(1e6, "m", 1.0, 1e8, "points further from the local origin are rejected as invalid")
    carve_start_m: float = _f(2.0, "m", 0.0, 1000.0, "free-space carving starts this far (horizontally) from the camera: a line of sight near the camera's own height bounds nothing a vehicle could fly over")
    carve_end_margin_m: float = _f(1.5, "m", 0.0, 100.0, "free-space carving stops this far (horizontally) short of the end of each line of sight, so a feature's own cell and a wall's face are never carved")
    carve_margin_m: float = _f(0.5, "m", 0.0, 100.0, "a line of sight passing this far (plus gate_sigma sigma) below a cell's height contradicts it")
    carve_rays: float = _f(3.0, "rays", 0.5, 1000.0, "frames whose lines of sight pass under a cell's height, with no point agreeing in between, that clear the cell (a phantom does not survive the next look)")
    carve_lateral_sigma_m: float = _f(0.5, "m", 0.0, 100.0, "a line of sight takes away a mapped height, a pending height or a floor only where it is known laterally to this: its horizontal distance from the camera times the navigation's attitude sigma (0.5 m: within 14 m of the camera at 2 deg). Farther it may have passed beside the cell: a heading error turns every line of sight about the camera, and a thin mast mapped on an earlier pass is cleared by lines of sight that truly passed beside it (docs/terrain.md, \"Free space\"); it still lowers the ceilings")
    lone_rise_m: float = _f(1.5, "m", 0.01, 1e6, "a point coming into an empty cell more than this above every height near it (mapped cells, pending heights and floors in the 3x3 blocks of lone_block_cells around it, and the other points of its batch there) waits for a second point, as a point above a mapped cell does: one mismatched track never builds an obstacle out of nothing (docs/terrain.md, \"A lone point\"); 1e6 = off")
    lone_block_cells: int = _f(4, "cells", 1, 1024, "the neighbourhood of lone_rise_m: the 3x3 blocks of this many cells around a point's own (the largest divisor of tile_cells not above it)")
    frame_tracking: bool = _f(True, doc="keep the map in the navigation's vertical frame: the weighted median of the residuals of new points against cells made frame_min_age_s ago or more moves the whole map (docs/terrain.md, \"The navigation's frame\"); false = a cell stays in the frame it was made in")
    frame_min_age_s: float = _f(20.0, "s", 0.0, 1e6, "cells updated this long ago or more are the navigation's older frame; newer ones are the frame of the moment and say nothing of its drift")
    frame_window_s: float = _f(3.0, "s", 0.01, 3600.0, "the residuals of this long are pooled into one median")
    frame_min_points: float = _f(10.0, "points", 1.0, 1e6, "the map moves only on at least this many points' residuals")
    frame_max_offset_m: float = _f(3.0, "m", 0.01, 1e4, "a residual larger than this is another surface, not the frame's drift")
    frame_deadband_m: float = _f(0.05, "m", 0.0, 100.0, "the map moves only by more than this")


@dataclass(frozen=True, slots=True)
class AvoidanceConfig:
    """Pull-up / push-over law (seed 000, section III)."""

    clearance_m: float = _f(15.0, "m", 0.0, 1000.0, "h_c")
    accel_mps2: float = _f(1.0, "m/s^2", 0.01, 50.0, "a_c, vertical acceleration the law may ask for")
    command_climb_accel_mps2: float = _f(2.5, "m/s^2", 0.0, 100.0, "the climb-rate setpoint rises by at most this per second (it falls by at most accel_mps2): a step in the setpoint pitches a multirotor, and a pitching camera loses its features (docs/avoidance.md, \"A smooth command\"); 0 = unlimited")
    miss_distance_m: float = _f(5.0, "m", 0.0, 1000.0, "horizontal miss distance (corridor half-width)")
    lookahead_m: float = _f(100.0, "m", 1.0, 10000.0)
    max_climb_mps: float = _f(3.0, "m/s", 0.0, 50.0)
    max_descent_mps: float = _f(2.0, "m/s", 0.0, 50.0)
    nominal_alt_m: float = _f(15.0, "m", -1e4, 1e4, "altitude to return to after an obstacle (up, local frame)")
    nominal_time_constant_s: float = _f(1.5, "s", 0.05, 60.0, "near the nominal altitude the return is exponential with this time constant")
    ground_reference_radius_m: float = _f(10.0, "m", 0.0, 1000.0, "the nominal altitude is kept above the ground the map holds around the vehicle, not above the local frame's zero: the median height of the mapped cells within this radius of the vehicle (at least 10 of them) is added to it. The navigation's vertical error moves the map with the altitude, so the map's ground is where the vehicle's altitude says the ground is (docs/avoidance.md, \"The ground the nominal altitude stands on\"); 0 = the local frame's zero")
    ground_reference_max_m: float = _f(3.0, "m", 0.0, 1000.0, "the ground reference moves the nominal altitude by at most this, up or down: about four sigmas of the simulated navigation's vertical error (0.8 m); obstacles are the law's, not the reference's")
    ground_band_m: float = _f(1.5, "m", 0.0, 100.0, "terrain within this of the ground reference is flown at the nominal altitude and terrain two bands above it with the full clearance, a linear ramp between: the law takes a cell at h - b up to one band above the ground, at g + 2 (h - g - b) up to two, at h above. The clearance over terrain near the ground falls short by at most one band; the noise of a flat map no longer engages the law (a ground cell of one point is taken k sigma, about 0.7 m, above its estimate: 1.5 m leaves about two of its sigmas of noise above that, where 1 m left one), and with nominal_alt_m at least clearance_m terrain within one band of the ground is the nominal command's to follow, not the law's (docs/avoidance.md, \"The ground the nominal altitude stands on\"); never more than speed_limit_shortfall x clearance_m; 0 = every cell at its own height")
    hover_speed_mps: float = _f(0.3, "m/s", 0.0, 10.0, "below this horizontal speed the look-ahead is a disc around the vehicle")
    descend_known_fraction: float = _f(0.03, "", 0.0, 1.0, "descend only when at least this fraction of the cells below the vehicle is mapped: those it flew over within the miss distance behind and either side (within the miss distance around at hover); never push over into unseen terrain, e.g. a plain roof, but one mapped cell in thirty is enough over sparsely mapped ground")
    descend_ground_radius_m: float = _f(20.0, "m", 0.0, 1000.0, "where fewer than descend_known_fraction of the cells below are mapped, the vehicle still descends to the clearance above the highest mapped cell of the ground it flew over within this distance behind it (at least 10 mapped cells there): sparsely mapped open ground after an obstacle is ground, while the outline of a plain roof it is still over holds it (docs/avoidance.md, \"Unmapped cells\"); 0 = off")
    unknown_fill_m: float = _f(5.0, "m", 0.0, 1000.0, "an unmapped cell is taken as high as the highest mapped cell within this along-track distance in the corridor")
    local_radius_m: float = _f(2.0, "m", 0.0, 50.0, "a mapped cell's height is estimated with the mapped cells within this radius, as one surface with its own relief (the relief estimated from the cells' scatter): one noisy point no longer sets the law's height over flat ground, and tree crowns keep their tops; a cell more than local_outlier_sigma from its neighbours, or more than speed_limit_shortfall x clearance_m, keeps its own height (docs/avoidance.md, \"The surface a cell belongs to\"); 0 = each cell alone")
    local_outlier_sigma: float = _f(2.0, "sigma", 0.5, 10.0, "a cell this far from its neighbours' mean (innovation sigma) keeps its own height: an obstacle's first point, a mast, a wall's top, the ground beside them")
    height_margin_sigma: float = _f(2.0, "sigma", 0.0, 10.0, "a mapped cell counts as h + k sqrt(variance): the clearance is kept above the map's uncertainty too (0 = the estimate alone)")
    speed_limit: bool = _f(True, doc="slow down for mapped terrain the law cannot climb over in time at the commanded speed: never faster than lets the vehicle make the climb, or stop, before it (docs/avoidance.md, \"Slowing for a late obstacle\"); false = the route's speed whatever the map holds")
    speed_limit_shortfall: float = _f(0.1, "", 0.0, 1.0, "the speed limit leaves shortfalls below this fraction of the clearance to the law (it makes them up as it flies); a larger one it must be able to climb, or brake, for")
    view_speed_limit: bool = _f(True, doc="slow down to what the camera can see: terrain high enough to need a climb is in view only clearance x (1 - speed_limit_shortfall) / tan(depression of the image's top row) ahead, so never faster than lets the vehicle stop within that distance after the map's latency (docs/avoidance.md, \"What the camera can see\"); false = fly the route's speed into terrain the camera has not seen")
    view_smoothing_s: float = _f(5.0, "s", 0.0, 600.0, "time constant of the average of the camera's line of sight the view limit uses: long against a multirotor's pitch while it speeds up or slows down, which would otherwise feed back into the limit (nose down to speed up: a lower view, a lower limit; nose up to slow down: the reverse); 0 = the attitude of the moment")
    map_latency_s: float = _f(1.5, "s", 0.0, 60.0, "time from terrain entering the camera's view to the map holding it (features converge with parallax); the view speed limit counts it before braking")
    known_horizon: bool = _f(True, doc="the view speed limit looks past the view distance over ground lines of sight have proven low: a corridor cell a line of sight crossed below the heights that would need a climb cannot hold such terrain, so the vehicle need only be able to stop before the first cell beyond the view that no line of sight has proven so (docs/avoidance.md, \"The known horizon\"); false = the view distance alone")
    known_horizon_mapped: bool = _f(True, doc="the known horizon also passes over cells the map holds low: a mapped cell whose height as the law takes it (its risk quantile, at least its floor) is below the heights that would need a climb counts as proven, as a line of sight below them does, so a route flown again over ground the map knows is flown at its speed; unmapped cells still end the horizon (docs/avoidance.md, \"The known horizon\"); false = lines of sight alone")
    brake_accel_mps2: float = _f(2.0, "m/s^2", 0.05, 50.0, "horizontal deceleration the speed limit counts on (below what the vehicle can do)")
    reaction_time_s: float = _f(0.5, "s", 0.0, 10.0, "time before braking starts: the control period, the map's latency and the autopilot's response")
    enabled: bool = _f(True, doc="false = command the nominal altitude only; the law is still evaluated and published (demo --no-avoid)")


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """Fixed-rate control loop and commanding policy."""

    rate_hz: float = _f(20.0, "Hz", 1.0, 200.0)
    commanding_enabled: bool = _f(False, doc="false = advisory: publish the setpoint, command nothing")
    allow_arm: bool = _f(False, doc="the service may arm the vehicle (sim/demo only)")
    allow_mode_change: bool = _f(False, doc="the service may switch to GUIDED / OFFBOARD (sim/demo only)")
    min_alt_m: float = _f(5.0, "m", -1e4, 1e4, "no setpoints below this altitude (local frame): takeoff and landing stay the autopilot's")
    cruise_speed_mps: float = _f(6.0, "m/s", 0.0, 50.0)
    waypoints_ne_m: tuple[tuple[float, float], ...] = _f((), "m", doc="horizontal route (north, east) flown when commanding")
    gil_switch_interval_ms: float = _f(1.0, "ms", 0.0, 100.0, "how long the mapper thread may keep the control loop waiting for Python's lock (sys.setswitchinterval); 0 = Python's default, 5 ms")
    realtime_priority: int = _f(0, "", 0, 99, "SCHED_FIFO priority of the control loop's thread, so a busy mapper never delays a tick (Linux; needs root, CAP_SYS_NICE or LimitRTPRIO); 0 = normal scheduling")


@dataclass(frozen=True, slots=True)
class ZenohConfig:
    """Zenoh session and keys."""

    enabled: bool = _f(True)
    mode: Literal["peer", "client"] = _f("peer")
    listen: tuple[str, ...] = _f((), doc="endpoints, e.g. tcp/127.0.0.1:7447")
    connect: tuple[str, ...] = _f((), doc="endpoints, e.g. tcp/192.168.1.10:7447")
    multicast_scouting: bool = _f(False)
    vehicle_name: str = _f("vehicle1", doc="key prefix: companion/<vehicle_name>/...")
    status_rate_hz: float = _f(1.0, "Hz", 0.1, 50.0)
    avoidance_rate_hz: float = _f(5.0, "Hz", 0.1, 200.0, "the avoidance state is published at most this often, and at once when it engages or releases (the law runs at control.rate_hz)")
    tile_interval_s: float = _f(1.0, "s", 0.05, 60.0, "a changed tile is published at most this often: the changes in between go out together (docs/zenoh.md, \"Bandwidth\")")
    tile_deflate: bool = _f(True, doc="publish tiles deflated (format version 2, about 6 times smaller); false = version 1, for readers that only know it")
    tile_deltas: bool = _f(True, doc="publish a changed tile as the cells that changed since its last publication when that is smaller (flags bit1-2 of tile format version 2; docs/terrain.md, \"Tile deltas\"); a receiver that missed one asks for the whole tile; false = whole tiles only")
    tile_keyframe_every: int = _f(10, "", 1, 100000, "with tile_deltas, every this many publications of a tile it goes out whole, so a receiver that missed a delta and cannot ask has it again")
    share_from: tuple[str, ...] = _f((), doc="other vehicles whose maps the avoidance law also reads (their <vehicle> names, or \"*\" for every vehicle heard); empty = none (docs/terrain.md, \"Evidence from other vehicles\")")
    share_ignore: tuple[str, ...] = _f((), doc="vehicles never read, even under \"*\"")
    share_weight: float = _f(1.0, "-", 0.01, 1.0, "trust in other vehicles' maps: their variances are divided by it (1 = as their own)")
    config_file: str = _f("", doc="extra Zenoh JSON5 config (TLS, access control) merged under ours")
    reconnect_min_s: float = _f(1.0, "s", 0.05, 60.0, "first retry after a connect endpoint is unreachable (doubles each try)")
    reconnect_max_s: float = _f(4.0, "s", 0.05, 600.0, "longest wait between connection retries")


@dataclass(frozen=True, slots=True)
class PersistenceConfig:
    """Map snapshots."""

    directory: str = _f("/var/lib/companion", doc="where map snapshots live")
    snapshot_interval_s: float = _f(10.0, "s", 0.5, 3600.0, "at most this much of the map is lost to a crash (companion clock)")
    keep_previous: bool = _f(True, doc="keep the snapshot before the newest as terrain.snapshot.prev (loaded if the newest is bad)")
    warn_every_s: float = _f(60.0, "s", 1.0, 3600.0, "while snapshots fail: repeat the log line and STATUSTEXT at most this often")


@dataclass(frozen=True, slots=True)
class SimConfig:
    """Simulated world (used by the synthetic camera and the simulated vehicle)."""

    scenario: str = _f("default", doc="name in config/scenarios/ or a path to a YAML scenario")
    seed: int = _f(1, "", 0, 2**31 - 1)
    speedup: float = _f(1.0, "", 0.1, 1000.0, "simulated seconds per wall-clock second")
    clock_file: str = _f("", doc="lockstep: the clock file of `companion sim --clock-file`; the service reads time from it and holds it while its mapper is behind (docs/sim.md); empty: its own clock at sim.speedup")
    # --- world renderer and synthetic camera (drivers/sim/renderer.py, docs/sim.md) ---
    image_noise_sigma: float = _f(2.0, "gray", 0.0, 50.0, "synthetic camera: additive Gaussian sensor noise")
    image_blur_sigma_px: float = _f(0.0, "px", 0.0, 10.0, "synthetic camera: Gaussian optical blur (0 = none)")
    max_pose_age_s: float = _f(1.0, "s", 0.01, 60.0, "synthetic camera: refuse to render from a vehicle pose older than this")
    # --- simulated vehicle (drivers/sim/vehicle.py, docs/sim.md) ---
    flavour: Literal["ardupilot", "px4"] = _f("ardupilot", doc="which autopilot the simulated vehicle imitates")
    physics_rate_hz: float = _f(400.0, "Hz", 50.0, 2000.0, "fixed physics step of the simulated vehicle (simulated time)")
    nav_rate_hz: float = _f(50.0, "Hz", 1.0, 400.0, "update rate of the navigation error, wind gusts and failsafe checks")
    origin_delay_s: float = _f(15.0, "s", 0.0, 600.0, "EKF origin (and GPS fix) this long after boot; no LOCAL_POSITION_NED before")
    gps_delay_s: float = _f(0.0, "s", 0.0, 600.0, "ArduPilot: the EKF uses GPS (position estimate, LOCAL_POSITION_NED, arming in GUIDED) this long after its origin is set; real Copter 4.6 SITL: about 21 s (docs/sitl.md)")
    accel_h_mps2: float = _f(3.0, "m/s^2", 0.1, 20.0, "horizontal acceleration limit of the velocity reference")
    accel_v_mps2: float = _f(2.5, "m/s^2", 0.1, 20.0, "vertical acceleration limit of the velocity reference")
    speed_h_mps: float = _f(15.0, "m/s", 0.1, 50.0, "horizontal speed limit")
    climb_mps: float = _f(5.0, "m/s", 0.1, 20.0, "climb rate limit")
    descent_mps: float = _f(3.0, "m/s", 0.1, 20.0, "descent rate limit")
    tilt_max_deg: float = _f(35.0, "deg", 5.0, 70.0, "lean angle limit")
    pos_gain_per_s: float = _f(1.0, "1/s", 0.05, 10.0, "position loop P gain")
    vel_gain_per_s: float = _f(2.5, "1/s", 0.1, 20.0, "velocity loop P gain")
    drag_per_s: float = _f(0.3, "1/s", 0.0, 5.0, "linear air drag (acceleration per m/s of airspeed)")
    wind_ned_mps: tuple[float, float, float] = _f((0.0, 0.0, 0.0), "m/s", -50.0, 50.0, "steady wind (north, east, down)")
    gust_sigma_mps: float = _f(0.0, "m/s", 0.0, 20.0, "gust standard deviation per horizontal axis (Gauss-Markov, from the seed)")
    gust_tau_s: float = _f(3.0, "s", 0.1, 600.0, "gust correlation time")
    nav_pos_sigma_h_m: float = _f(0.5, "m", 0.0, 100.0, "injected navigation error: horizontal position sigma per axis "
                                  "(position and velocity error per axis: one critically damped process, time constant pos/vel sigma)")
    nav_pos_sigma_v_m: float = _f(0.8, "m", 0.0, 100.0, "injected navigation error: vertical position sigma")
    nav_vel_sigma_mps: float = _f(0.1, "m/s", 0.0, 10.0, "injected navigation error: velocity sigma per axis")
    nav_tilt_sigma_deg: float = _f(0.5, "deg", 0.0, 30.0, "injected navigation error: roll/pitch sigma")
    nav_yaw_sigma_deg: float = _f(2.0, "deg", 0.0, 90.0, "injected navigation error: yaw sigma")
    nav_att_tau_s: float = _f(10.0, "s", 0.01, 3600.0, "harsh model: correlation time of the attitude error")
    nav_error_model: Literal["ekf", "harsh"] = _f("ekf", doc="ekf = a slow error (position and attitude wandering over tens "
                                                "of seconds) plus a small white part, as an autopilot's EKF; harsh = one "
                                                "faster process per component, no white part (docs/sim.md)")
    nav_pos_tau_h_s: float = _f(60.0, "s", 0.1, 36000.0, "ekf model: integral correlation time of the horizontal position error")
    nav_pos_tau_v_s: float = _f(60.0, "s", 0.1, 36000.0, "ekf model: integral correlation time of the vertical position error")
    nav_att_tau_ekf_s: float = _f(30.0, "s", 0.1, 36000.0, "ekf model: integral correlation time of the attitude error")
    nav_pos_white_m: float = _f(0.02, "m", 0.0, 10.0, "ekf model: white part of the position error per axis")
    nav_vel_white_mps: float = _f(0.02, "m/s", 0.0, 10.0, "ekf model: white part of the velocity error per axis (the slow "
                                  "part is the rate of the slow position error)")
    nav_tilt_white_deg: float = _f(0.02, "deg", 0.0, 10.0, "ekf model: white part of the roll/pitch error")
    nav_yaw_white_deg: float = _f(0.05, "deg", 0.0, 10.0, "ekf model: white part of the yaw error")
    gps_noise_m: float = _f(0.2, "m", 0.0, 100.0, "white noise of the simulated GPS fix about the navigation estimate")
    gps_vel_noise_mps: float = _f(0.05, "m/s", 0.0, 10.0, "white noise of the simulated GPS velocity")


@dataclass(frozen=True, slots=True)
class CompanionConfig:
    link: LinkConfig = field(default_factory=LinkConfig)
    nav: NavConfig = field(default_factory=NavConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    avoidance: AvoidanceConfig = field(default_factory=AvoidanceConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    persistence: PersistenceConfig = field(default_factory=PersistenceConfig)
    sim: SimConfig = field(default_factory=SimConfig)


# --------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str, where: str) -> Any:
    """Check ``value`` against type ``tp``; return it converted (lists -> tuples, int -> float)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: '{key}' must be a mapping of {tp.__name__} keys, got {type(value).__name__}")
        return _build(tp, value, key, where)
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{where}: '{key}' must be one of {', '.join(map(repr, args))}, got {value!r}")
        return value
    if origin in (types.UnionType, typing.Union):
        errors = []
        for alternative in args:
            if alternative is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, alternative, key, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: '{key}' has an invalid value {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: '{key}' must be a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]", where) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: '{key}' must have {len(args)} elements, got {len(value)}")
        return tuple(_coerce(v, a, f"{key}[{i}]", where) for i, (v, a) in enumerate(zip(value, args)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: '{key}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: '{key}' must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where}: '{key}' must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: '{key}' must be a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: '{key}' has unsupported type {_type_name(tp)}")  # pragma: no cover


def _check_range(value: Any, f: dataclasses.Field, key: str, where: str) -> None:
    lo, hi = f.metadata.get("min"), f.metadata.get("max")
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if isinstance(v, tuple) or isinstance(v, (str, bool)) or v is None:
            continue
        unit = f.metadata.get("unit") or ""
        if lo is not None and v < lo:
            raise ConfigError(f"{where}: '{key}' = {v} is below the minimum {lo} {unit}".rstrip())
        if hi is not None and v > hi:
            raise ConfigError(f"{where}: '{key}' = {v} is above the maximum {hi} {unit}".rstrip())


def _build(cls: type, data: dict, prefix: str, where: str):
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        full = [f"{prefix}.{k}" if prefix else str(k) for k in unknown]
        raise ConfigError(f"{where}: unknown key {', '.join(repr(k) for k in full)} (known: {', '.join(sorted(fields))})")
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _coerce(value, hints[name], key, where)
        _check_range(kwargs[name], fields[name], key, where)
    return cls(**kwargs)


def config_from_dict(data: dict | None, where: str = "<dict>") -> CompanionConfig:
    """Validate a plain mapping (as parsed from YAML) into a :class:`CompanionConfig`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: the top level must be a mapping of sections")
    return _build(CompanionConfig, data, "", where)


def load_config(path: str | Path) -> CompanionConfig:
    """Load and validate a YAML configuration file. Missing keys take their defaults."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration: {exc.strerror or exc}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    return config_from_dict(data, str(path))


def replace(cfg: Any, **changes: Any) -> Any:
    """``dataclasses.replace`` for nested sections: ``replace(cfg, **{"mapper.max_features": 300})``."""
    nested: dict[str, dict[str, Any]] = {}
    direct = {}
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[key] = value
    for head, sub in nested.items():
        direct[head] = replace(getattr(cfg, head), **sub)
    return dataclasses.replace(cfg, **direct)


def describe(cls: type = CompanionConfig, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """(dotted key, default, unit, doc) for every leaf key, for documentation and tests."""
    rows = []
    instance = cls()
    for f in dataclasses.fields(cls):
        key = f"{prefix}.{f.name}" if prefix else f.name
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            rows.extend(describe(type(value), key))
        else:
            rows.append((key, value, f.metadata.get("unit", ""), f.metadata.get("doc", "")))
    return rows
