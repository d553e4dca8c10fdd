"""Recordings the mapper can replay, read into one form: a time-ordered stream of samples, each a
camera frame with the navigation state at its capture time (docs/replay.md).

Three layouts are read:

* ``companion``: the service's own ``--record`` folder (``meta.yaml``, ``frames.csv``,
  ``frames/``, ``telemetry.tlog``; docs/cameras.md). Navigation is rebuilt from the telemetry log
  exactly as the autopilot link builds it live (:class:`TelemetryNav`).
* ``tum``: a folder of images with camera poses in TUM trajectory format
  (``timestamp tx ty tz qx qy qz qw``, camera-to-world, OpenCV camera axes) plus ``camera.yaml``
  (intrinsics, OpenCV distortion, size) and ``meta.yaml`` (the world's up axis, metric scale,
  pose uncertainty). ``pose_sigmas.txt`` gives per-frame uncertainty when present.
* ``euroc``: the EuRoC MAV layout (``mav0/cam0/data.csv``, ``mav0/cam0/sensor.yaml``,
  ``mav0/state_groundtruth_estimate0/data.csv``).

Pose-given layouts (tum, euroc) are converted to the project's frames (docs/conventions.md):
world -> local NED by :class:`WorldFrame` (north = a declared world axis, down = -up, east =
down x north, positions times the metric scale); the OpenCV camera frame (x right, y down, z
optical) -> the paper camera frame (x optical, y right, z down) by ``PAPER_TO_OPENCV``. The
camera pose is then written as a body pose for a mount (identity by default, so the body *is*
the camera and the declared uncertainty applies to the camera pose exactly):
``R_nb = R_nc R_bc^T``, ``p = p_c - R_nb t_bc`` (:func:`body_pose_from_camera`), which
``CameraMount.camera_pose`` maps back exactly.

Damage never stops a replay: a malformed line in any text file is skipped and counted
(:class:`RecordingStats`), a missing or undecodable image yields a sample without a frame, a frame
time the navigation cannot cover yields a sample without navigation (with the reason), corrupt
telemetry bytes are skipped by pymavlink's tlog reader and counted. Files that make the whole
recording meaningless (no camera model, no image list, no poses) raise :class:`RecordingError`
naming the file and what is wrong.
"""

from __future__ import annotations

import bisect
import difflib
import math
import re
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from companion.config import CompanionConfig, ConfigError, NavConfig, config_from_dict
from companion.method.geometry import (
    PAPER_TO_OPENCV,
    CameraMount,
    PinholeCamera,
    camera_from_config,
    matrix_to_quat,
    quat_to_matrix,
)
from companion.method.messages import Frame, NavState
from companion.method.navigation.buffer import NavBuffer, NavLookup, quat_slerp

__all__ = [
    "IDENTITY_MOUNT",
    "Recording",
    "RecordingError",
    "RecordingStats",
    "Sample",
    "WorldFrame",
    "body_pose_from_camera",
    "camera_pose_from_opencv",
    "detect_kind",
    "export_tum",
    "open_recording",
    "pose_covariance",
    "read_gray",
    "recording_config",
]

IDENTITY_MOUNT = CameraMount(R_bc=np.eye(3), t_bc=np.zeros(3))
VELOCITY_SIGMA_MPS = 0.1  # pose-given layouts have no velocity uncertainty; the mapper never reads it
MAX_EXAMPLES = 20  # problems kept verbatim for the report (all are counted)

# TUM folder file names (the first that exists is used).
TUM_IMAGES = ("images.txt", "rgb.txt")
TUM_POSES = ("poses.txt", "groundtruth.txt")
TUM_CAMERA = "camera.yaml"
TUM_META = "meta.yaml"
TUM_SIGMAS = "pose_sigmas.txt"

# EuRoC MAV layout.
EUROC_CAM_CSV = "mav0/cam0/data.csv"
EUROC_CAM_DIR = "mav0/cam0/data"
EUROC_CAM_YAML = "mav0/cam0/sensor.yaml"
EUROC_GROUNDTRUTH = "mav0/state_groundtruth_estimate0/data.csv"

# MAVLink values the telemetry replay needs (common.xml).
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18


class RecordingError(ValueError):
    """A recording cannot be read at all; the message names the file and the problem."""


# --------------------------------------------------------------------------------------------
# Frames: world axes -> NED, OpenCV camera -> paper camera, camera pose -> body pose
# --------------------------------------------------------------------------------------------

_AXES = {
    "x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0),
    "y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
    "z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0),
}  # fmt: skip


def _axis(name: Any, key: str) -> np.ndarray:
    text = str(name).strip().lower().replace("+", "")
    if text not in _AXES:
        raise RecordingError(f"{key}: {name!r} is not an axis (one of {', '.join(_AXES)})")
    return np.array(_AXES[text])


@dataclass(frozen=True, slots=True)
class WorldFrame:
    """A dataset's world frame declared by its up axis, the axis taken as north and the metric scale.

    ``A`` (3, 3) maps world directions to NED: its rows are north, east and down written in world
    coordinates, with down = -up and east = down x north (so that north x east = down: a proper
    rotation, det A = +1, for a right-handed world frame). Positions: ``p_ned = scale * A p_w``.
    The default (up -z, north x, scale 1) is NED itself.
    """

    up: str = "-z"
    north: str = "x"
    scale_m_per_unit: float = 1.0

    def __post_init__(self) -> None:
        up, north = _axis(self.up, "world_up"), _axis(self.north, "world_north")
        if abs(float(up @ north)) > 0.5:
            raise RecordingError(f"world_north {self.north!r} must be perpendicular to world_up {self.up!r}")
        if not (math.isfinite(self.scale_m_per_unit) and self.scale_m_per_unit > 0):
            raise RecordingError(f"scale_m_per_unit must be positive and finite, got {self.scale_m_per_unit}")

    @classmethod
    def from_up(cls, up: str, north: str | None = None, scale_m_per_unit: float = 1.0) -> "WorldFrame":
        """North defaults to world x, or world y when up is +-x."""
        if north is None:
            north = "y" if str(up).strip().lower().lstrip("+-") == "x" else "x"
        return cls(str(up), str(north), float(scale_m_per_unit))

    @property
    def A(self) -> np.ndarray:
        north = _axis(self.north, "world_north")
        down = -_axis(self.up, "world_up")
        east = np.cross(down, north)
        return np.vstack([north, east, down])

    def position_to_ned(self, p_w: np.ndarray) -> np.ndarray:
        """World positions (..., 3) in world units -> NED metres (..., 3)."""
        return self.scale_m_per_unit * (np.asarray(p_w, float) @ self.A.T)

    def position_from_ned(self, p_ned: np.ndarray) -> np.ndarray:
        return (np.asarray(p_ned, float) @ self.A) / self.scale_m_per_unit

    def rotation_to_ned(self, R_w: np.ndarray) -> np.ndarray:
        """Rotations (..., 3, 3) mapping some frame to the world -> the same frame to NED."""
        return self.A @ np.asarray(R_w, float)


def camera_pose_from_opencv(p_c_world: np.ndarray, R_w_cv: np.ndarray, world: WorldFrame) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world pose with OpenCV camera axes (x right, y down, z optical) in a dataset world
    -> camera centre in NED (..., 3) and ``R_nc`` (..., 3, 3) for the paper camera frame (x optical,
    y right, z down). A paper-frame vector ``h`` is ``PAPER_TO_OPENCV h`` in OpenCV axes, so
    ``R_nc = A R_w_cv PAPER_TO_OPENCV``."""
    return world.position_to_ned(p_c_world), world.rotation_to_ned(R_w_cv) @ PAPER_TO_OPENCV


def camera_pose_to_opencv(p_c_ned: np.ndarray, R_nc: np.ndarray, world: WorldFrame) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`camera_pose_from_opencv`."""
    A = world.A
    return world.position_from_ned(p_c_ned), A.T @ np.asarray(R_nc, float) @ PAPER_TO_OPENCV.T


def body_pose_from_camera(p_c: np.ndarray, R_nc: np.ndarray, mount: CameraMount) -> tuple[np.ndarray, np.ndarray]:
    """Body position (3,) and ``R_nb`` (3, 3) for which ``mount.camera_pose(p, R_nb)`` is the given
    camera pose: ``R_nb = R_nc R_bc^T``, ``p = p_c - R_nb t_bc``."""
    R_nb = np.asarray(R_nc, float) @ mount.R_bc.T
    return np.asarray(p_c, float) - R_nb @ mount.t_bc, R_nb


def pose_covariance(sigma_pos_m: np.ndarray, sigma_att_rad: np.ndarray, A: np.ndarray | None = None) -> np.ndarray:
    """9x9 NavState covariance from per-axis sigmas (3,) of position (m) and attitude error (rad)
    given about the axes of a world frame whose directions map to NED by ``A`` (identity = NED):
    ``P_ned = A diag(sigma^2) A^T`` per block; the velocity block is nominal (the mapper uses
    P_x = [position, attitude] only)."""
    A = np.eye(3) if A is None else np.asarray(A, float)
    P = np.zeros((9, 9))
    P[0:3, 0:3] = A @ np.diag(np.asarray(sigma_pos_m, float) ** 2) @ A.T
    P[3:6, 3:6] = np.eye(3) * VELOCITY_SIGMA_MPS**2
    P[6:9, 6:9] = A @ np.diag(np.asarray(sigma_att_rad, float) ** 2) @ A.T
    return P


# --------------------------------------------------------------------------------------------
# Bookkeeping, text tables, images
# --------------------------------------------------------------------------------------------


@dataclass(slots=True)
class RecordingStats:
    """What reading the recording skipped: malformed lines per file, and the first examples."""

    bad_lines: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    telemetry_messages: int = 0
    telemetry_bad: int = 0
    telemetry_ignored: int = 0
    nav_states: int = 0
    nav_rejected: dict[str, int] = field(default_factory=dict)

    def bad_line(self, path: Path, line_no: int, reason: str) -> None:
        self.bad_lines[path.name] = self.bad_lines.get(path.name, 0) + 1
        self.note(f"{path}: line {line_no}: {reason}; skipped")

    def note(self, problem: str) -> None:
        if len(self.problems) < MAX_EXAMPLES:
            self.problems.append(problem)

    def as_dict(self) -> dict[str, Any]:
        return {
            "bad_lines": dict(self.bad_lines),
            "bad_lines_total": sum(self.bad_lines.values()),
            "telemetry_messages": self.telemetry_messages,
            "telemetry_bad": self.telemetry_bad,
            "telemetry_ignored": self.telemetry_ignored,
            "nav_states": self.nav_states,
            "nav_rejected": dict(self.nav_rejected),
            "problems": list(self.problems),
        }


def _rows(path: Path, stats: RecordingStats, sep: str | None = None) -> Iterator[tuple[int, list[str]]]:
    """Non-blank, non-comment lines of a text table as (line number, fields). ``sep`` None =
    whitespace. A line that is not valid UTF-8 is counted and skipped."""
    with open(path, "rb") as f:
        for line_no, raw in enumerate(f, start=1):
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError:
                stats.bad_line(path, line_no, "not UTF-8 text")
                continue
            text = line.split("#", 1)[0].strip()
            if text:
                yield line_no, [t.strip() for t in (text.split(sep) if sep else text.split())]


def _finite(text: str, what: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{what} {text!r} is not finite")
    return value


def _first_existing(folder: Path, names: tuple[str, ...]) -> Path | None:
    return next((folder / n for n in names if (folder / n).is_file()), None)


def _read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping; OpenCV's ``%YAML:1.0`` first line (not valid YAML) is tolerated."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read: {exc}") from exc
    if text.startswith("%YAML:"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise RecordingError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise RecordingError(f"{path}: expected a mapping of keys")
    return data


def read_gray(path: Path, width: int, height: int) -> tuple[np.ndarray | None, str]:
    """An image file as grey ``uint8 (height, width)``, or None and why. 16-bit images are scaled to
    8 bits, colour is converted to grey; a size other than the camera's is refused (the intrinsics
    belong to one size)."""
    if not path.is_file():
        return None, f"{path}: missing"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None, f"{path}: cannot be decoded"
    if image.dtype == np.uint16:
        image = (image.astype(np.uint32) * 255 // 65535).astype(np.uint8)
    elif image.dtype != np.uint8:
        return None, f"{path}: pixel type {image.dtype} (8 or 16 bit expected)"
    if image.ndim == 3:
        conversions = {1: None, 3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}
        if image.shape[2] not in conversions:
            return None, f"{path}: {image.shape[2]} channels"
        image = image[:, :, 0] if image.shape[2] == 1 else cv2.cvtColor(image, conversions[image.shape[2]])
    if image.shape != (height, width):
        return None, f"{path}: {image.shape[1]}x{image.shape[0]} pixels, the camera is {width}x{height}"
    return np.ascontiguousarray(image), ""


# --------------------------------------------------------------------------------------------
# Samples and the recording interface
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sample:
    """One listed frame: ``frame`` (None if the image is unusable, or not loaded) and ``nav`` at its
    capture time (None when the navigation cannot cover it), each with the reason when missing.
    ``t_s`` is on the recording's clock; ``image_path`` is the file the frame came from."""

    index: int
    t_s: float
    sequence: int
    image_path: Path
    frame: Frame | None
    nav: NavState | None
    image_problem: str = ""
    nav_problem: str = ""


@dataclass(frozen=True, slots=True)
class FrameEntry:
    t_s: float
    sequence: int
    path: Path


class Recording:
    """A readable recording: the camera model, the mount the navigation states refer to, and the
    samples in time order. ``world`` converts the dataset's own frame to NED (identity for the
    companion layout); ``ground_alt_m`` is the altitude (m, up, NED origin) of flat ground assumed
    for new features before the map knows better."""

    kind = "?"

    def __init__(self, path: Path, camera: PinholeCamera, mount: CameraMount, frames: list[FrameEntry],
                 stats: RecordingStats, world: WorldFrame | None = None, ground_alt_m: float = 0.0):
        self.path = path
        self.camera = camera
        self.mount = mount
        self.frames = frames
        self.stats = stats
        self.world = world or WorldFrame()
        self.ground_alt_m = float(ground_alt_m)

    def __len__(self) -> int:
        return len(self.frames)

    def _nav_at(self, t_s: float) -> NavLookup:  # pragma: no cover - every layout overrides it
        raise NotImplementedError

    def _start(self) -> None:
        """Called before a pass over the samples (a layout with streaming state rewinds here)."""

    def samples(self, load_images: bool = True, limit: int | None = None) -> Iterator[Sample]:
        """The samples in time order; images are read only for samples that have navigation."""
        self._start()
        cam = self.camera
        for i, entry in enumerate(self.frames[:limit] if limit is not None else self.frames):
            lookup = self._nav_at(entry.t_s)
            frame, problem = None, ""
            if lookup.nav is not None and load_images:
                image, problem = read_gray(entry.path, cam.width, cam.height)
                if image is not None:
                    frame = Frame(entry.t_s, image, entry.sequence, self.kind)
            yield Sample(i, entry.t_s, entry.sequence, entry.path, frame, lookup.nav, problem, lookup.reason)

    def describe(self) -> dict[str, Any]:
        c = self.camera
        return {
            "kind": self.kind,
            "path": str(self.path),
            "frames_listed": len(self.frames),
            "camera": {"width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                       "distortion": [float(d) for d in np.asarray(c.distortion).ravel()]},
            "world": {"up": self.world.up, "north": self.world.north, "scale_m_per_unit": self.world.scale_m_per_unit},
            "ground_alt_m": self.ground_alt_m,
            **self.stats.as_dict(),
        }


def _sorted_frames(entries: list[tuple[int, Path, float, int]], source: Path, stats: RecordingStats) -> list[FrameEntry]:
    """(line, path, t, sequence) -> frames in time order; repeated times are counted and dropped."""
    entries.sort(key=lambda e: (e[2], e[0]))
    out: list[FrameEntry] = []
    for line_no, path, t, seq in entries:
        if out and t <= out[-1].t_s:
            stats.bad_line(source, line_no, f"time {t!r} repeats an earlier frame's")
            continue
        out.append(FrameEntry(t, seq, path))
    return out


# --------------------------------------------------------------------------------------------
# Pose tables (pose-given layouts): camera poses interpolated at frame times
# --------------------------------------------------------------------------------------------


class PoseTable:
    """Camera poses in NED (paper camera frame) at sorted times, interpolated at frame times like
    :class:`NavBuffer` does (position linear, attitude slerp), refused across gaps longer than
    ``max_gap_s`` and more than ``extrapolate_s`` outside the span. The NavState returned is the
    body pose for ``mount`` (:func:`body_pose_from_camera`) with velocity from the bracketing poses.

    t (N,) s increasing; p_c (N, 3); q_nc (N, 4) wxyz of R_nc; covariance (9, 9) for every pose.
    """

    def __init__(self, t: np.ndarray, p_c: np.ndarray, q_nc: np.ndarray, covariance: np.ndarray, mount: CameraMount,
                 max_gap_s: float, extrapolate_s: float, source: str):
        self.t = np.asarray(t, float)
        self.p_c = np.asarray(p_c, float)
        self.q_nc = np.asarray(q_nc, float)
        self.covariance = np.asarray(covariance, float)
        self.mount = mount
        self.max_gap_s = float(max_gap_s)
        self.extrapolate_s = float(extrapolate_s)
        self.source = source
        self._t = self.t.tolist()

    def __len__(self) -> int:
        return len(self._t)

    def lookup(self, t: float, covariance: np.ndarray | None = None) -> NavLookup:
        n = len(self._t)
        if n == 0:
            return NavLookup(None, "no poses")
        if t < self._t[0] - self.extrapolate_s:
            return NavLookup(None, f"{self._t[0] - t:.3f} s before the first pose (nav.buffer_extrapolate_s {self.extrapolate_s:.3f} s)")
        if t > self._t[-1] + self.extrapolate_s:
            return NavLookup(None, f"{t - self._t[-1]:.3f} s after the last pose (nav.buffer_extrapolate_s {self.extrapolate_s:.3f} s)")
        i = bisect.bisect_left(self._t, t)
        if i < n and self._t[i] == t:
            a = b = i
        elif i == 0:
            a = b = 0
        elif i == n:
            a = b = n - 1
        else:
            a, b = i - 1, i
            if self._t[b] - self._t[a] > self.max_gap_s:
                return NavLookup(None, f"gap of {self._t[b] - self._t[a]:.3f} s in the poses "
                                       f"(limit nav.buffer_max_gap_s {self.max_gap_s:.3f} s)")
        if a == b:
            p_c, q = self.p_c[a], self.q_nc[a]
        else:
            alpha = (t - self._t[a]) / (self._t[b] - self._t[a])
            p_c = self.p_c[a] + alpha * (self.p_c[b] - self.p_c[a])
            q = quat_slerp(self.q_nc[a], self.q_nc[b], alpha)
        lo, hi = (max(0, a - 1), min(n - 1, a + 1)) if a == b else (a, b)
        v = (self.p_c[hi] - self.p_c[lo]) / (self._t[hi] - self._t[lo]) if hi > lo else np.zeros(3)
        p, R_nb = body_pose_from_camera(p_c, quat_to_matrix(q), self.mount)
        cov = self.covariance if covariance is None else covariance
        return NavLookup(NavState(float(t), p, v, matrix_to_quat(R_nb), cov.copy(), self.source))


class PoseRecording(Recording):
    """A layout whose navigation is a table of camera poses, with optional per-frame sigmas."""

    def __init__(self, *args, poses: PoseTable, frame_covariances: dict[float, np.ndarray] | None = None,
                 association_s: float = 0.02, **kwargs):
        super().__init__(*args, **kwargs)
        self.poses = poses
        self._cov_t = sorted(frame_covariances or {})
        self._cov = frame_covariances or {}
        self.association_s = association_s

    def _nav_at(self, t_s: float) -> NavLookup:
        return self.poses.lookup(t_s, self._frame_covariance(t_s))

    def _frame_covariance(self, t_s: float) -> np.ndarray | None:
        """The per-frame covariance whose timestamp is nearest ``t_s`` within the association window."""
        if not self._cov_t:
            return None
        i = bisect.bisect_left(self._cov_t, t_s)
        best = min((self._cov_t[j] for j in (i - 1, i) if 0 <= j < len(self._cov_t)), key=lambda c: abs(c - t_s))
        return self._cov[best] if abs(best - t_s) <= self.association_s else None


def _pose_arrays(t: list[float], p_c: list[np.ndarray], R_nc: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not t:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))
    order = np.argsort(np.asarray(t), kind="stable")
    return np.asarray(t)[order], np.asarray(p_c)[order], matrix_to_quat(np.asarray(R_nc)[order])


def _dedupe_times(t: np.ndarray, *arrays: np.ndarray, source: Path, stats: RecordingStats):
    """Drop poses whose time repeats the previous one (counted)."""
    if len(t) < 2:
        return (t, *arrays)
    keep = np.r_[True, np.diff(t) > 0]
    for _ in range(int((~keep).sum())):
        stats.bad_lines[source.name] = stats.bad_lines.get(source.name, 0) + 1
    if not keep.all():
        stats.note(f"{source}: {int((~keep).sum())} poses repeat an earlier time; skipped")
    return (t[keep], *(a[keep] for a in arrays))


# --------------------------------------------------------------------------------------------
# TUM folder
# --------------------------------------------------------------------------------------------


def _camera_from_mapping(data: dict[str, Any], where: Path) -> PinholeCamera:
    _check_keys(data, CAMERA_KEYS, where)
    try:
        width, height = int(data["width"]), int(data["height"])
        fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
        dist = np.asarray(data.get("distortion", [0.0] * 5) or [0.0] * 5, dtype=float).ravel()
    except KeyError as exc:
        raise RecordingError(f"{where}: missing key {exc.args[0]!r} (need width, height, fx, fy, cx, cy[, distortion])") from exc
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: camera values must be numbers: {exc}") from exc
    if width < 16 or height < 16 or not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise RecordingError(f"{where}: implausible camera (size {width}x{height}, fx {fx}, fy {fy})")
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise RecordingError(f"{where}: distortion must be 4, 5, 8, 12 or 14 finite OpenCV coefficients, got {dist.size}")
    return PinholeCamera(fx, fy, cx, cy, width, height, dist)


def _sigmas(text: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """``sp sa`` (isotropic) or ``spx spy spz sax say saz`` -> (3,) m, (3,) rad; attitude in degrees."""
    values = [_finite(v, "sigma") for v in text]
    if any(v < 0 for v in values):
        raise ValueError("sigmas must be >= 0")
    if len(values) == 2:
        return np.full(3, values[0]), np.full(3, math.radians(values[1]))
    if len(values) == 6:
        return np.asarray(values[:3]), np.radians(values[3:])
    raise ValueError(f"{len(values)} sigma values (2 or 6 expected)")


TUM_META_KEYS = ("world_up", "world_north", "scale_m_per_unit", "pose_sigma_m", "pose_sigma_deg", "ground_alt_m",
                 "association_s", "source")
CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")


def _check_keys(data: dict, known: tuple[str, ...], where: Path) -> None:
    """An unknown key is an error naming the file and the nearest known key (a misspelt optional key
    would otherwise be ignored and its default used without a word)."""
    for key in data:
        if key not in known:
            near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise RecordingError(f"{where}: unknown key '{key}'{hint}; known keys: {', '.join(known)}")


def _meta_float(meta: dict, key: str, default: float, lo: float, where: Path) -> float:
    value = meta.get(key, default)
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: '{key}' must be a number, got {value!r}") from exc
    if not math.isfinite(value) or value < lo:
        raise RecordingError(f"{where}: '{key}' = {value} must be finite and >= {lo}")
    return value


@dataclass(frozen=True, slots=True)
class Overrides:
    """Command-line values that replace a layout's metadata (None = keep the recording's)."""

    pose_sigma_m: float | None = None
    pose_sigma_deg: float | None = None
    ground_alt_m: float | None = None


def open_tum(folder: Path, nav: NavConfig, overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> PoseRecording:
    """A TUM-style folder: ``meta.yaml``, ``camera.yaml``, ``images.txt`` (or ``rgb.txt``),
    ``poses.txt`` (or ``groundtruth.txt``) and optionally ``pose_sigmas.txt`` (docs/replay.md)."""
    stats = RecordingStats()
    meta_path = folder / TUM_META
    if not meta_path.is_file():
        raise RecordingError(f"{meta_path}: missing (it declares world_up and scale_m_per_unit; see docs/replay.md)")
    meta = _read_yaml(meta_path)
    _check_keys(meta, TUM_META_KEYS, meta_path)
    if "world_up" not in meta or "scale_m_per_unit" not in meta:
        raise RecordingError(f"{meta_path}: must declare 'world_up' (x, -x, y, -y, z or -z) and 'scale_m_per_unit'")
    world = WorldFrame.from_up(meta["world_up"], meta.get("world_north"), _meta_float(meta, "scale_m_per_unit", 1.0, 1e-12, meta_path))
    sigma_m = overrides.pose_sigma_m if overrides.pose_sigma_m is not None else _meta_float(meta, "pose_sigma_m", 0.02, 0.0, meta_path)
    sigma_deg = overrides.pose_sigma_deg if overrides.pose_sigma_deg is not None else _meta_float(meta, "pose_sigma_deg", 0.2, 0.0, meta_path)
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else _meta_float(meta, "ground_alt_m", 0.0, -1e6, meta_path)
    association_s = _meta_float(meta, "association_s", 0.02, 0.0, meta_path)
    camera_path = folder / TUM_CAMERA
    if not camera_path.is_file():
        raise RecordingError(f"{camera_path}: missing (width, height, fx, fy, cx, cy, distortion)")
    camera = _camera_from_mapping(_read_yaml(camera_path), camera_path)

    images = _first_existing(folder, TUM_IMAGES)
    entries: list[tuple[int, Path, float, int]] = []
    if images is not None:
        for line_no, fields in _rows(images, stats):
            try:
                if len(fields) < 2:
                    raise ValueError(f"{len(fields)} fields, expected 'timestamp filename'")
                entries.append((line_no, folder / fields[1], _finite(fields[0], "timestamp"), len(entries)))
            except ValueError as exc:
                stats.bad_line(images, line_no, str(exc))
        source = images
    else:  # TUM RGB-D style: images/<timestamp>.png
        source = folder / "images"
        if not source.is_dir():
            raise RecordingError(f"{folder}: neither {' nor '.join(TUM_IMAGES)} nor an images/ folder of <timestamp>.<ext> files")
        for k, path in enumerate(sorted(p for p in source.iterdir() if p.is_file())):
            try:
                entries.append((k + 1, path, _finite(path.stem, "timestamp"), k))
            except ValueError:
                stats.bad_line(source, k + 1, f"{path.name}: file name is not a timestamp")
    frames = _sorted_frames(entries, source, stats)

    poses_path = _first_existing(folder, TUM_POSES)
    if poses_path is None:
        raise RecordingError(f"{folder}: no pose file ({' or '.join(TUM_POSES)})")
    t, p, R = [], [], []
    for line_no, fields in _rows(poses_path, stats):
        try:
            if len(fields) != 8:
                raise ValueError(f"{len(fields)} fields, expected 'timestamp tx ty tz qx qy qz qw'")
            values = [_finite(v, "value") for v in fields]
            q_xyzw = np.asarray(values[4:8])
            norm = float(np.linalg.norm(q_xyzw))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"quaternion norm {norm:.6f} (unit quaternion expected)")
            p_c, R_nc = camera_pose_from_opencv(np.asarray(values[1:4]), quat_to_matrix(np.r_[q_xyzw[3], q_xyzw[:3]]), world)
        except ValueError as exc:
            stats.bad_line(poses_path, line_no, str(exc))
            continue
        t.append(values[0])
        p.append(p_c)
        R.append(R_nc)
    if not t:
        raise RecordingError(f"{poses_path}: no usable pose")
    tt, pp, qq = _pose_arrays(t, p, R)
    tt, pp, qq = _dedupe_times(tt, pp, qq, source=poses_path, stats=stats)
    covariance = pose_covariance(np.full(3, sigma_m), np.full(3, math.radians(sigma_deg)))
    table = PoseTable(tt, pp, qq, covariance, mount, nav.buffer_max_gap_s, nav.buffer_extrapolate_s, "tum")

    frame_cov: dict[float, np.ndarray] = {}
    sigmas_path = folder / TUM_SIGMAS
    if sigmas_path.is_file() and overrides.pose_sigma_m is None and overrides.pose_sigma_deg is None:
        for line_no, fields in _rows(sigmas_path, stats):
            try:
                ts = _finite(fields[0], "timestamp")
                sp, sa = _sigmas(fields[1:])
            except (ValueError, IndexError) as exc:
                stats.bad_line(sigmas_path, line_no, str(exc))
                continue
            frame_cov[ts] = pose_covariance(sp, sa, world.A)
    return PoseRecording(folder, camera, mount, frames, stats, world=world, ground_alt_m=ground, poses=table,
                         frame_covariances=frame_cov, association_s=association_s)


# --------------------------------------------------------------------------------------------
# EuRoC MAV
# --------------------------------------------------------------------------------------------

EUROC_WORLD = WorldFrame("z", "x", 1.0)  # EuRoC's Vicon / Leica frame: z up (gravity aligned)


def _euroc_root(path: Path) -> Path:
    """The folder holding ``mav0`` (the argument may be that folder or ``mav0`` itself)."""
    return path.parent if path.name == "mav0" else path


def _matrix_4x4(value: Any, where: Path) -> np.ndarray:
    data = value.get("data") if isinstance(value, dict) else value
    try:
        T = np.asarray(data, dtype=float).reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: T_BS must hold 16 numbers (row-major 4x4): {exc}") from exc
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or np.max(np.abs(R @ R.T - np.eye(3))) > 1e-3 or np.linalg.det(R) < 0:
        raise RecordingError(f"{where}: T_BS rotation is not a rotation matrix")
    return T


def open_euroc(path: Path, nav: NavConfig, overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> PoseRecording:
    """EuRoC MAV: ``cam0`` images and ``state_groundtruth_estimate0`` poses of the body (IMU) frame,
    composed with the camera's ``T_BS`` (camera -> body) into camera poses. Times are nanoseconds;
    they are counted from the first camera timestamp so seconds keep full precision."""
    root = _euroc_root(path)
    stats = RecordingStats()
    where = root / EUROC_CAM_YAML
    if not where.is_file():
        raise RecordingError(f"{where}: missing (camera intrinsics, distortion, resolution and T_BS)")
    sensor = _read_yaml(where)
    model = str(sensor.get("camera_model", "pinhole"))
    dist_model = str(sensor.get("distortion_model", "radial-tangential"))
    if model != "pinhole" or dist_model not in ("radial-tangential", "radtan", "none"):
        raise RecordingError(f"{where}: camera_model {model!r} / distortion_model {dist_model!r} (pinhole radial-tangential supported)")
    try:
        fu, fv, cu, cv_ = (float(v) for v in sensor["intrinsics"])
        width, height = (int(v) for v in sensor["resolution"])
        dist = [float(v) for v in sensor.get("distortion_coefficients", [0, 0, 0, 0])]
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: need intrinsics [fu, fv, cu, cv], resolution [w, h], distortion_coefficients: {exc}") from exc
    camera = _camera_from_mapping({"width": width, "height": height, "fx": fu, "fy": fv, "cx": cu, "cy": cv_,
                                   "distortion": dist if dist_model != "none" else [0.0] * 4}, where)
    T_bc = _matrix_4x4(sensor.get("T_BS"), where) if "T_BS" in sensor else np.eye(4)

    cam_csv = root / EUROC_CAM_CSV
    if not cam_csv.is_file():
        raise RecordingError(f"{cam_csv}: missing (timestamp [ns], filename per image)")
    raw: list[tuple[int, int, str]] = []
    for line_no, fields in _rows(cam_csv, stats, sep=","):
        try:
            if len(fields) < 2 or not fields[1]:
                raise ValueError("expected 'timestamp [ns], filename'")
            raw.append((line_no, int(fields[0]), fields[1]))
        except ValueError as exc:
            stats.bad_line(cam_csv, line_no, str(exc))
    if not raw:
        raise RecordingError(f"{cam_csv}: no usable image line")
    ns0 = min(r[1] for r in raw)
    frames = _sorted_frames([(ln, root / EUROC_CAM_DIR / name, (ns - ns0) * 1e-9, k) for k, (ln, ns, name) in enumerate(raw)],
                            cam_csv, stats)

    gt_path = root / EUROC_GROUNDTRUTH
    if not gt_path.is_file():
        raise RecordingError(f"{gt_path}: missing (replay needs the ground-truth poses)")
    t, p, R = [], [], []
    R_sc, t_sc = T_bc[:3, :3], T_bc[:3, 3]
    for line_no, fields in _rows(gt_path, stats, sep=","):
        try:
            if len(fields) < 8:
                raise ValueError(f"{len(fields)} fields, expected timestamp, p_RS_R xyz, q_RS_R wxyz, ...")
            ns = int(fields[0])
            values = [_finite(v, "value") for v in fields[1:8]]
            q = np.asarray(values[3:7])
            norm = float(np.linalg.norm(q))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"quaternion norm {norm:.6f} (unit quaternion expected)")
            R_rs = quat_to_matrix(q)
            # Camera pose in the world R: T_RC = T_RS T_SC (the body B of cam0's T_BS is the IMU S).
            p_c, R_nc = camera_pose_from_opencv(np.asarray(values[:3]) + R_rs @ t_sc, R_rs @ R_sc, EUROC_WORLD)
        except ValueError as exc:
            stats.bad_line(gt_path, line_no, str(exc))
            continue
        t.append((ns - ns0) * 1e-9)
        p.append(p_c)
        R.append(R_nc)
    if not t:
        raise RecordingError(f"{gt_path}: no usable pose")
    tt, pp, qq = _pose_arrays(t, p, R)
    tt, pp, qq = _dedupe_times(tt, pp, qq, source=gt_path, stats=stats)
    sigma_m = overrides.pose_sigma_m if overrides.pose_sigma_m is not None else 0.02
    sigma_deg = overrides.pose_sigma_deg if overrides.pose_sigma_deg is not None else 0.2
    covariance = pose_covariance(np.full(3, sigma_m), np.full(3, math.radians(sigma_deg)))
    table = PoseTable(tt, pp, qq, covariance, mount, nav.buffer_max_gap_s, nav.buffer_extrapolate_s, "euroc")
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else 0.0
    return PoseRecording(root, camera, mount, frames, stats, world=EUROC_WORLD, ground_alt_m=ground, poses=table)


# --------------------------------------------------------------------------------------------
# The service's own recording: frames.csv + telemetry.tlog
# --------------------------------------------------------------------------------------------


class TelemetryNav:
    """Navigation states from a telemetry log, built as the autopilot link builds them live
    (drivers/autopilot/receive.py): the first autopilot HEARTBEAT picks the target; TIMESYNC answers
    (``ts1`` = our send time in ns + 1, companion clock) and SYSTEM_TIME feed :class:`TimeSync`;
    an autopilot reboot (boot clock going backwards) or an estimator reset clears the state; the
    navigation messages go to :class:`NavAssembler` and its states into a :class:`NavBuffer`.

    ``to_companion(unix_s)`` maps a log timestamp (reception, Unix seconds) to the companion clock.
    :meth:`lookup` must be called with non-decreasing times: the log is read just far enough ahead
    (``lead_s``) that the states bracketing the time have arrived.
    """

    def __init__(self, path: Path, to_companion: Callable[[float], float], cfg: CompanionConfig, stats: RecordingStats,
                 lead_s: float = 1.0):
        self.path = path
        self.to_companion = to_companion
        self.cfg = cfg
        self.stats = stats
        self.lead_s = float(lead_s)
        self.own = (cfg.link.source_system, cfg.link.source_component)
        self._log = None
        self._pending: tuple[Any, float] | None = None
        self._eof = False

    def rewind(self) -> None:
        from companion.method.navigation.assembler import NavAssembler
        from companion.method.navigation.timesync import TimeSync

        if self._log is not None:
            self._log.close()
        self._log = None
        self._eof = not self.path.is_file()
        if not self._eof:
            from pymavlink import mavutil  # tlog reader: 8-byte big-endian microsecond time + packet

            self._log = mavutil.mavlogfile(str(self.path), robust_parsing=True)
        nav = self.cfg.nav
        self.timesync = TimeSync(reboot_threshold_s=1.0)
        self.assembler = NavAssembler(nav, time_map=self.timesync.to_companion)
        self.buffer = NavBuffer(max(nav.buffer_s, 2.0 * self.lead_s + 1.0), nav.buffer_max_gap_s,
                                nav.buffer_extrapolate_s, max_samples=100_000)
        self._target: tuple[int, int] | None = None
        self._reboots = 0
        self._estimator_resets = 0
        self._pending = None
        for key in ("telemetry_messages", "telemetry_bad", "telemetry_ignored", "nav_states"):
            setattr(self.stats, key, 0)
        self.stats.nav_rejected = {}

    def _next(self) -> tuple[Any, float] | None:
        if self._pending is not None:
            item, self._pending = self._pending, None
            return item
        while not self._eof:
            try:
                m = self._log.recv_msg()
            except Exception as exc:  # noqa: BLE001 - a damaged log ends the telemetry, not the replay
                self.stats.note(f"{self.path}: unreadable from here on: {exc}")
                self._eof = True
                return None
            if m is None:
                self._eof = True
                return None
            if m.get_type() == "BAD_DATA":
                self.stats.telemetry_bad += 1
                continue
            t = self.to_companion(float(m._timestamp))
            if not math.isfinite(t):
                self.stats.telemetry_bad += 1
                continue
            self.stats.telemetry_messages += 1
            return m, t
        return None

    def advance(self, t: float) -> None:
        """Dispatch every message received up to ``t + lead_s``."""
        horizon = t + self.lead_s
        while True:
            item = self._next()
            if item is None:
                return
            if item[1] > horizon:
                self._pending = item
                return
            self._dispatch(*item)

    def lookup(self, t: float) -> NavLookup:
        self.advance(t)
        if self._log is None and self.stats.telemetry_messages == 0:
            return NavLookup(None, f"no telemetry log ({self.path.name} missing)")
        return self.buffer.lookup(t)

    def _dispatch(self, m: Any, now: float) -> None:
        from companion.method.navigation.assembler import HANDLED_MESSAGES

        kind = m.get_type()
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == self.own:
            self.stats.telemetry_ignored += 1
            return
        if kind == "HEARTBEAT":
            autopilot = m.autopilot != MAV_AUTOPILOT_INVALID and m.type not in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER)
            wanted = self.cfg.link.target_system
            if autopilot and self._target is None and (not wanted or src[0] == wanted):
                self._target = src
                self.timesync.reset()
                self.assembler.reset()
                self.buffer.clear()
            return
        if self._target is None or src != self._target:
            self.stats.telemetry_ignored += 1
            return
        if kind == "TIMESYNC":
            if m.tc1 != 0:  # an answer: ts1 is the requester's send time (ns + 1 on our clock)
                self.timesync.add_roundtrip((m.ts1 - 1) * 1e-9, m.tc1 * 1e-9, now)
                self._check_reboot()
            return
        boot_ms = getattr(m, "time_boot_ms", None)
        if boot_ms:
            self.timesync.observe_remote_time(boot_ms * 1e-3)
            self._check_reboot()
        if kind == "SYSTEM_TIME" and m.time_boot_ms:
            self.timesync.add_one_way(m.time_boot_ms * 1e-3, now)
            self._check_reboot()
        if kind in HANDLED_MESSAGES:
            nav = self.assembler.update(m, now)
            if self.assembler.estimator_resets != self._estimator_resets:
                self._estimator_resets = self.assembler.estimator_resets
                self.buffer.clear()
            if nav is not None and self.buffer.push(nav):
                self.stats.nav_states += 1
            self.stats.nav_rejected = self.assembler.rejections.snapshot()

    def _check_reboot(self) -> None:
        if self.timesync.reboots != self._reboots:
            self._reboots = self.timesync.reboots
            self.stats.note(f"{self.path}: the autopilot rebooted (boot clock went backwards); navigation reset")
            self.assembler.reset()
            self.buffer.clear()


class CompanionRecording(Recording):
    kind = "companion"

    def __init__(self, *args, telemetry: TelemetryNav, **kwargs):
        super().__init__(*args, **kwargs)
        self.telemetry = telemetry

    def _start(self) -> None:
        self.telemetry.rewind()

    def _nav_at(self, t_s: float) -> NavLookup:
        return self.telemetry.lookup(t_s)


def recording_config(path: Path) -> CompanionConfig | None:
    """The configuration stored in a companion recording's ``meta.yaml`` (None for other layouts,
    or when it does not validate with this version: the caller falls back and says so)."""
    try:
        if detect_kind(path) != "companion":
            return None
    except RecordingError:
        return None
    from drivers.cameras.recorder import read_recording_meta

    try:
        return config_from_dict(read_recording_meta(path).get("config") or {}, str(path / "meta.yaml"))
    except (ConfigError, ValueError):
        return None


def open_companion(folder: Path, cfg: CompanionConfig, overrides: Overrides = Overrides()) -> CompanionRecording:
    """The service's own recording. The camera model and mount come from ``meta.yaml``'s ``camera``
    section (they belong to the images); ``cfg`` gives the nav and link settings used to rebuild
    navigation from ``telemetry.tlog``."""
    from drivers.cameras.recorder import read_recording_meta

    try:
        meta = read_recording_meta(folder)
    except ValueError as exc:
        raise RecordingError(str(exc)) from exc
    where = folder / "meta.yaml"
    try:
        cam_cfg = config_from_dict({"camera": meta.get("camera") or {}}, f"{where} (camera)").camera
    except ConfigError as exc:
        raise RecordingError(str(exc)) from exc
    camera, mount = camera_from_config(cam_cfg)
    clock = meta.get("clock") or {}
    try:
        t0, unix0, speedup = float(clock["t_s"]), float(clock["unix_time_s"]), float(clock.get("speedup", 1.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: 'clock' must give t_s, unix_time_s and speedup to align the telemetry with the frames") from exc
    if not (math.isfinite(t0) and math.isfinite(unix0) and speedup > 0):
        raise RecordingError(f"{where}: clock values must be finite with a positive speedup")

    stats = RecordingStats()
    files = meta.get("files") or {}
    csv_path = folder / str(files.get("frames_csv", "frames.csv"))
    if not csv_path.is_file():
        raise RecordingError(f"{csv_path}: missing (sequence,t_s,filename per frame)")
    rows = _rows(csv_path, stats, sep=",")
    header = next(rows, None)
    if header is None or "t_s" not in header[1] or "filename" not in header[1]:
        raise RecordingError(f"{csv_path}: first line must be the header 'sequence,t_s,filename'")
    names = header[1]
    i_t, i_f = names.index("t_s"), names.index("filename")
    i_s = names.index("sequence") if "sequence" in names else None
    entries: list[tuple[int, Path, float, int]] = []
    for line_no, fields in rows:
        try:
            if len(fields) != len(names):
                raise ValueError(f"{len(fields)} fields, header has {len(names)}")
            if not fields[i_f]:
                raise ValueError("empty filename")
            seq = int(fields[i_s]) if i_s is not None else len(entries)
            entries.append((line_no, folder / fields[i_f], _finite(fields[i_t], "t_s"), seq))
        except ValueError as exc:
            stats.bad_line(csv_path, line_no, str(exc))
    frames = _sorted_frames(entries, csv_path, stats)
    tlog = folder / str(files.get("telemetry", "telemetry.tlog"))
    if not tlog.is_file():
        stats.note(f"{tlog}: missing; no frame has navigation")
    telemetry = TelemetryNav(tlog, lambda unix: t0 + (unix - unix0) * speedup, cfg, stats)
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else cfg.terrain.default_ground_alt_m
    return CompanionRecording(folder, camera, mount, frames, stats, ground_alt_m=ground, telemetry=telemetry)


# --------------------------------------------------------------------------------------------
# Opening any layout
# --------------------------------------------------------------------------------------------


def detect_kind(path: Path) -> str:
    """``companion``, ``euroc`` or ``tum`` from the files present; RecordingError if none fits."""
    path = Path(path)
    if not path.is_dir():
        raise RecordingError(f"{path}: not a folder")
    if (path / "frames.csv").is_file() and (path / "meta.yaml").is_file():
        return "companion"
    if (_euroc_root(path) / EUROC_CAM_CSV).is_file():
        return "euroc"
    if _first_existing(path, TUM_POSES) is not None or (path / TUM_CAMERA).is_file():
        return "tum"
    raise RecordingError(
        f"{path}: not a recording: expected meta.yaml + frames.csv (companion --record), "
        f"mav0/cam0/data.csv (EuRoC) or poses.txt + camera.yaml + meta.yaml (TUM folder)"
    )


def open_recording(path: str | Path, cfg: CompanionConfig | None = None, *, kind: str = "auto",
                   overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> Recording:
    """Open a recording of any supported layout. ``cfg`` supplies the nav settings (interpolation
    limits, telemetry assembly); ``mount`` is the body frame pose-given layouts report (identity:
    the body is the camera)."""
    path = Path(path).expanduser()
    cfg = cfg or CompanionConfig()
    kind = detect_kind(path) if kind == "auto" else kind
    if kind == "companion":
        return open_companion(path, cfg, overrides)
    if kind == "tum":
        rec = open_tum(path, cfg.nav, overrides, mount)
    elif kind == "euroc":
        rec = open_euroc(path, cfg.nav, overrides, mount)
    else:
        raise RecordingError(f"unknown recording kind {kind!r} (auto, companion, tum, euroc)")
    rec.kind = kind
    return rec


# --------------------------------------------------------------------------------------------
# Export to the TUM folder form
# --------------------------------------------------------------------------------------------


def export_tum(recording: Recording, out: str | Path, limit: int | None = None) -> dict[str, int]:
    """Write ``recording`` as a TUM folder (docs/replay.md): the images copied byte for byte, the
    camera poses (camera-to-world, OpenCV axes) in the NED world (``world_up: -z``, north x, scale
    1), per-frame sigmas from the diagonal of each frame's pose covariance, ``camera.yaml`` and
    ``meta.yaml``. Frames without navigation are left out (counted). Refuses a folder that already
    holds poses. Returns counts."""
    out = Path(out)
    if (out / TUM_POSES[0]).exists() or (out / TUM_META).exists():
        raise FileExistsError(f"{out} already holds a TUM export; choose a new folder")
    (out / "images").mkdir(parents=True, exist_ok=True)
    world = WorldFrame()
    counts = {"written": 0, "without_nav": 0, "missing_image": 0}
    with open(out / TUM_IMAGES[0], "w") as f_img, open(out / TUM_POSES[0], "w") as f_pose, open(out / TUM_SIGMAS, "w") as f_sig:
        f_img.write("# timestamp filename\n")
        f_pose.write("# timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes, NED world)\n")
        f_sig.write("# timestamp sigma_north_m sigma_east_m sigma_down_m sigma_rot_north_deg sigma_rot_east_deg sigma_rot_down_deg\n")
        for s in recording.samples(load_images=False, limit=limit):
            if s.nav is None:
                counts["without_nav"] += 1
                continue
            if not s.image_path.is_file():
                counts["missing_image"] += 1
                continue
            name = f"images/{counts['written']:06d}{s.image_path.suffix.lower()}"
            shutil.copyfile(s.image_path, out / name)
            p_c, R_nc = recording.mount.camera_pose(s.nav.position_ned_m, s.nav.R_nb)
            t_w, R_w_cv = camera_pose_to_opencv(p_c, R_nc, world)
            q = matrix_to_quat(R_w_cv)
            t = repr(float(s.t_s))
            f_img.write(f"{t} {name}\n")
            f_pose.write(" ".join([t, *(repr(float(v)) for v in t_w), *(repr(float(v)) for v in (q[1], q[2], q[3], q[0]))]) + "\n")
            sig = np.sqrt(np.clip(np.diag(s.nav.pose_covariance), 0.0, None))
            f_sig.write(" ".join([t, *(repr(float(v)) for v in sig[:3]), *(repr(float(math.degrees(v))) for v in sig[3:])]) + "\n")
            counts["written"] += 1
    c = recording.camera
    camera = {"width": c.width, "height": c.height, "fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy),
              "distortion": [float(d) for d in np.asarray(c.distortion).ravel()]}
    (out / TUM_CAMERA).write_text(yaml.safe_dump(camera, sort_keys=False))
    meta = {
        "world_up": "-z", "world_north": "x", "scale_m_per_unit": 1.0,
        "ground_alt_m": recording.ground_alt_m,
        "pose_sigma_m": 0.02, "pose_sigma_deg": 0.2,
        "source": {"kind": recording.kind, "path": str(recording.path)},
    }  # fmt: skip
    (out / TUM_META).write_text(yaml.safe_dump(meta, sort_keys=False))
    return counts


_NUMBER = re.compile(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?")


def reason_key(reason: str) -> str:
    """A reason with its numbers replaced by ``#``, so that like refusals count together."""
    return _NUMBER.sub("#", reason) if reason else ""
