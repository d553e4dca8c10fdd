"""The recording interface and what every layout's reader shares.

A recording is a camera model, the mount its navigation states refer to, and a time-ordered stream
of samples, each a camera frame with the navigation state at its capture time (:class:`Recording`,
:class:`Sample`). Pose-given layouts are converted to the project's frames here (:class:`WorldFrame`,
:func:`camera_pose_from_opencv`, :func:`body_pose_from_camera`; the package docstring says how). Damage never stops a replay: a malformed line in any text file is skipped and
counted (:class:`RecordingStats`), a missing or undecodable image yields a sample without a frame, a
frame time the navigation cannot cover yields a sample without navigation (with the reason). Files
that make the whole recording meaningless raise :class:`RecordingError` naming the file and what is
wrong.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from companion.method.geometry import PAPER_TO_OPENCV, CameraMount, PinholeCamera
from companion.method.messages import Frame, NavState
from companion.method.navigation.buffer import NavLookup

IDENTITY_MOUNT = CameraMount(R_bc=np.eye(3), t_bc=np.zeros(3))
VELOCITY_SIGMA_MPS = 0.1  # pose-given layouts have no velocity uncertainty; the mapper never reads it
MAX_EXAMPLES = 20  # problems kept verbatim for the report (all are counted)


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


AxisSpec = str | tuple[float, float, float]  # a world axis by name ("z", "-y") or a direction (3 numbers)


def _axis(name: Any, key: str) -> np.ndarray:
    """A unit world direction from an axis name (``x``, ``-y``, ...) or three numbers (any length)."""
    if isinstance(name, (list, tuple, np.ndarray)):
        try:
            v = np.asarray([float(c) for c in name], dtype=float)
        except (TypeError, ValueError):
            v = np.zeros(0)
        norm = float(np.linalg.norm(v)) if v.size == 3 and np.all(np.isfinite(v)) else 0.0
        if not norm > 0.0:
            raise RecordingError(f"{key}: {list(name)!r} is not a direction (three finite numbers, not all zero)")
        return v / norm
    text = str(name).strip().lower().replace("+", "")
    if text not in _AXES:
        raise RecordingError(f"{key}: {name!r} is not an axis (one of {', '.join(_AXES)}) or a direction [x, y, z]")
    return np.array(_AXES[text])


def _axis_spec(value: Any) -> AxisSpec:
    """An axis as given in meta.yaml, kept as written: a name, or a tuple of three numbers."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return tuple(float(c) if isinstance(c, (int, float)) else c for c in value)
    return str(value)


@dataclass(frozen=True, slots=True)
class WorldFrame:
    """A dataset's world frame declared by its up direction, the direction taken as north and the
    metric scale.

    ``up`` and ``north`` are world axes by name (``z``, ``-y``) or directions in world coordinates
    (three numbers: an SfM model's up is wherever its reconstruction put it). North is projected
    onto the plane perpendicular to up: ``n = (n0 - (n0 . u) u) / |...|``; it must lie more than
    60 deg from up. ``A`` (3, 3) maps world directions to NED: its rows are north, east and down
    written in world coordinates, with down = -up and east = down x north (so that north x east =
    down: a proper rotation, det A = +1, for a right-handed world frame). Positions: ``p_ned =
    scale * A (p_w - o)`` with ``origin`` ``o`` (3,) in world units, the world point taken as the
    local frame's origin (a geo-referenced world, UTM or ECEF, is millions of units from its own).
    The default (up -z, north x, scale 1, origin 0) is NED itself.
    """

    up: AxisSpec = "-z"
    north: AxisSpec = "x"
    scale_m_per_unit: float = 1.0
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        up, north = _axis(self.up, "world_up"), _axis(self.north, "world_north")
        if abs(float(up @ north)) > 0.5:
            raise RecordingError(f"world_north {self.north!r} must be perpendicular to world_up {self.up!r} "
                                 "(more than 60 deg from it; it is projected onto the level plane)")
        if not (math.isfinite(self.scale_m_per_unit) and self.scale_m_per_unit > 0):
            raise RecordingError(f"scale_m_per_unit must be positive and finite, got {self.scale_m_per_unit}")
        if len(self.origin) != 3 or not all(math.isfinite(float(v)) for v in self.origin):
            raise RecordingError(f"origin must be three finite numbers (world units), got {self.origin!r}")

    @classmethod
    def from_up(cls, up: Any, north: Any = None, scale_m_per_unit: float = 1.0,
                origin=(0.0, 0.0, 0.0)) -> "WorldFrame":
        """North defaults to world x, or world y when up is +-x; for an up direction given as numbers,
        to the world axis farthest from it."""
        up = _axis_spec(up)
        if north is None:
            u = _axis(up, "world_up")
            north = ("x", "y", "z")[int(np.argmin(np.abs(u)))] if isinstance(up, tuple) else ("y" if abs(u[0]) > 0.5 else "x")
        return cls(up, _axis_spec(north), float(scale_m_per_unit), tuple(float(v) for v in origin))

    @property
    def A(self) -> np.ndarray:
        down = -_axis(self.up, "world_up")
        north = _axis(self.north, "world_north")
        north = north - (north @ down) * down
        north /= np.linalg.norm(north)
        east = np.cross(down, north)
        return np.vstack([north, east, down])

    def position_to_ned(self, p_w: np.ndarray) -> np.ndarray:
        """World positions (..., 3) in world units -> NED metres (..., 3)."""
        return self.scale_m_per_unit * ((np.asarray(p_w, float) - np.asarray(self.origin)) @ self.A.T)

    def position_from_ned(self, p_ned: np.ndarray) -> np.ndarray:
        return (np.asarray(p_ned, float) @ self.A) / self.scale_m_per_unit + np.asarray(self.origin)

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


def table_rows(path: Path, stats: RecordingStats, sep: str | None = None) -> Iterator[tuple[int, list[str]]]:
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


def finite_float(text: str, what: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{what} {text!r} is not finite")
    return value


def first_existing(folder: Path, names: tuple[str, ...]) -> Path | None:
    return next((folder / n for n in names if (folder / n).is_file()), None)


def read_yaml(path: Path) -> dict[str, Any]:
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


def check_keys(data: dict, known: tuple[str, ...], where: Path) -> None:
    """An unknown key is an error naming the file and the nearest known key (a misspelt optional key
    would otherwise be ignored and its default used without a word)."""
    for key in data:
        if key not in known:
            near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise RecordingError(f"{where}: unknown key '{key}'{hint}; known keys: {', '.join(known)}")


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
            "world": {"up": _json_axis(self.world.up), "north": _json_axis(self.world.north),
                      "scale_m_per_unit": self.world.scale_m_per_unit,
                      "origin": list(self.world.origin)},
            "ground_alt_m": self.ground_alt_m,
            **self.stats.as_dict(),
        }


def _json_axis(axis: AxisSpec) -> str | list[float]:
    return list(axis) if isinstance(axis, tuple) else axis


def sorted_frames(entries: list[tuple[int, Path, float, int]], source: Path, stats: RecordingStats) -> list[FrameEntry]:
    """(line, path, t, sequence) -> frames in time order; repeated times are counted and dropped."""
    entries.sort(key=lambda e: (e[2], e[0]))
    out: list[FrameEntry] = []
    for line_no, path, t, seq in entries:
        if out and t <= out[-1].t_s:
            stats.bad_line(source, line_no, f"time {t!r} repeats an earlier frame's")
            continue
        out.append(FrameEntry(t, seq, path))
    return out


@dataclass(frozen=True, slots=True)
class Overrides:
    """Command-line values that replace a layout's metadata (None = keep the recording's)."""

    pose_sigma_m: float | None = None
    pose_sigma_deg: float | None = None
    ground_alt_m: float | None = None


_NUMBER = re.compile(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?")


def reason_key(reason: str) -> str:
    """A reason with its numbers replaced by ``#``, so that like refusals count together."""
    return _NUMBER.sub("#", reason) if reason else ""
