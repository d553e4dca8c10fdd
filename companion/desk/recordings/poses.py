"""Pose tables: the navigation of the pose-given layouts (TUM, EuRoC), camera poses interpolated at
frame times, and the camera model such a layout declares.
"""

from __future__ import annotations

import bisect
import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.desk.recordings.recording import body_pose_from_camera
from companion.desk.recordings.recording import Recording, RecordingError, RecordingStats, check_keys
from companion.method.geometry import CameraMount, PinholeCamera, matrix_to_quat, quat_to_matrix
from companion.method.messages import NavState
from companion.method.navigation.buffer import NavLookup, quat_slerp

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion")


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


def sorted_poses(t: list[float], p_c: list[np.ndarray], R_nc: list[np.ndarray], source: Path,
                 stats: RecordingStats) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The poses read from ``source`` as arrays in time order: t (N,), p_c (N, 3), q_nc (N, 4) wxyz; a
    pose that repeats the previous one's time is dropped and counted. RecordingError when none was usable."""
    if not t:
        raise RecordingError(f"{source}: no usable pose")
    tt, pp, qq = _pose_arrays(t, p_c, R_nc)
    return _dedupe_times(tt, pp, qq, source=source, stats=stats)


def camera_from_mapping(data: dict[str, Any], where: Path) -> PinholeCamera:
    check_keys(data, CAMERA_KEYS, where)
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
