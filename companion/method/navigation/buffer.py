"""Time-indexed navigation history: the state at a frame's capture time.

Frames are stamped at capture; the autopilot's navigation arrives at its own rate (tens of Hz)
and a little late. :class:`NavBuffer` keeps the last ``horizon_s`` seconds of :class:`NavState`
in time order and answers ``at(t)`` by interpolating between the two samples around ``t``:
position and velocity linearly, the attitude by spherical linear interpolation (slerp) of the
body->NED quaternion, the covariance as the same convex combination of the two covariances
(a convex combination of PSD matrices is PSD). It refuses, with a reason, to answer outside the
history (before the oldest sample, across a gap longer than ``max_gap_s``, or more than
``extrapolate_s`` after the newest sample: beyond that the state is a guess, not a measurement).

Lookup is O(log n) (bisect over a sorted list of times); memory is bounded by the horizon and by
``max_samples``. The link pushes from the event loop while the mapper reads from its worker
thread, so every method takes a lock (held for microseconds).
"""

from __future__ import annotations

import math
import bisect
import threading
from dataclasses import dataclass

import numpy as np

from companion.method.geometry import matrix_to_quat, quat_to_matrix, so3_exp
from companion.method.messages import NavState


@dataclass(frozen=True, slots=True)
class NavLookup:
    """Result of :meth:`NavBuffer.lookup`: the state, or None and the reason it was refused."""

    nav: NavState | None
    reason: str = ""

    def __bool__(self) -> bool:
        return self.nav is not None


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (w, x, y, z) along the shorter arc.

    ``alpha`` in [0, 1] (values slightly outside extrapolate along the same great circle).
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # q and -q are the same rotation: take the short way round
        q1 = -q1
        dot = -dot
    if dot > 0.9995:  # nearly parallel: linear interpolation is exact to ~1e-7 and avoids 0/0
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    s = np.sin(theta)
    q = (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / s
    return q / np.linalg.norm(q)


# The attitude rate used to extrapolate is taken over at least this long (closer samples would
# amplify their noise: extrapolating 20 ms from a 1 ms baseline multiplies it by 20).
MIN_RATE_BASELINE_S = 0.01


class NavBuffer:
    """Bounded, time-ordered history of NavState with interpolation at arbitrary times.

    horizon_s: samples older than (newest - horizon_s) are dropped.
    max_gap_s: no interpolation across a gap between samples longer than this.
    extrapolate_s: how far after the newest sample ``at`` may still answer (position
        extrapolated with the velocity, attitude at the rate of the last 10 ms or more: extrapolate).
    max_samples: hard cap on memory whatever the rate.
    """

    def __init__(
        self,
        horizon_s: float = 5.0,
        max_gap_s: float = 0.5,
        extrapolate_s: float = 0.05,
        max_samples: int = 4096,
    ) -> None:
        if not horizon_s > 0:
            raise ValueError(f"nav buffer horizon must be positive, got {horizon_s}")
        if max_samples < 2:
            raise ValueError(f"nav buffer needs room for at least 2 samples, got {max_samples}")
        self.horizon_s = float(horizon_s)
        self.max_gap_s = float(max_gap_s)
        self.extrapolate_s = float(extrapolate_s)
        self.max_samples = int(max_samples)
        self._t: list[float] = []
        self._nav: list[NavState] = []
        self._start = 0  # logical start: entries before it are evicted (compacted lazily)
        self._lock = threading.Lock()
        self.rejected: dict[str, int] = {}

    # ------------------------------------------------------------------------------------------

    def __len__(self) -> int:
        with self._lock:
            return len(self._t) - self._start

    def clear(self) -> None:
        with self._lock:
            self._t.clear()
            self._nav.clear()
            self._start = 0

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return False

    def push(self, nav: NavState) -> bool:
        """Append a state. Returns False (counted in :attr:`rejected`) for out-of-order or non-finite states.

        A state with exactly the newest time replaces it (position and attitude messages of one
        autopilot cycle often share a timestamp; the later one is assembled from more recent parts).
        """
        if not (np.isfinite(nav.t_s) and nav.is_finite()):
            return self._reject("non-finite state")
        with self._lock:
            if len(self._t) > self._start:
                newest = self._t[-1]
                if nav.t_s < newest:
                    return self._reject("older than the newest sample")
                if nav.t_s == newest:
                    self._nav[-1] = nav
                    return True
            self._t.append(nav.t_s)
            self._nav.append(nav)
            self._evict(nav.t_s)
        return True

    def _evict(self, newest: float) -> None:
        cutoff = newest - self.horizon_s
        # Keep one sample at or before the cutoff so times just inside the horizon still interpolate.
        first_inside = bisect.bisect_left(self._t, cutoff, lo=self._start)
        self._start = max(self._start, first_inside - 1)
        overflow = len(self._t) - self._start - self.max_samples
        if overflow > 0:
            self._start += overflow
        if self._start > 1024 and self._start * 2 > len(self._t):  # amortised O(1) compaction
            del self._t[: self._start]
            del self._nav[: self._start]
            self._start = 0

    # ------------------------------------------------------------------------------------------

    def latest(self) -> NavState | None:
        with self._lock:
            return self._nav[-1] if len(self._t) > self._start else None

    def oldest(self) -> NavState | None:
        with self._lock:
            return self._nav[self._start] if len(self._t) > self._start else None

    def age(self, now: float) -> float:
        """Seconds since the newest sample's time of validity (inf when empty)."""
        latest = self.latest()
        return float("inf") if latest is None else now - latest.t_s

    def at(self, t: float) -> NavState | None:
        """The state at companion time ``t``, or None (see :meth:`lookup` for the reason)."""
        return self.lookup(t).nav

    def _rate_partner(self) -> NavState | None:
        """The newest state at least ``MIN_RATE_BASELINE_S`` older than the newest one and within
        ``max_gap_s`` of it (the pair the attitude rate is taken from), or None. Call under the lock."""
        last = self._t[-1]
        for i in range(len(self._t) - 2, max(self._start, len(self._t) - 9) - 1, -1):
            age = last - self._t[i]
            if age > self.max_gap_s:
                return None
            if age >= MIN_RATE_BASELINE_S:
                return self._nav[i]
        return None

    def lookup(self, t: float) -> NavLookup:
        """The state at time ``t`` interpolated from its neighbours, or a refusal with its reason."""
        if not np.isfinite(t):
            return NavLookup(None, f"time {t} is not finite")
        with self._lock:
            n = len(self._t) - self._start
            if n == 0:
                return NavLookup(None, "no navigation received yet")
            t_old, t_new = self._t[self._start], self._t[-1]
            if t > t_new:
                ahead = t - t_new
                if ahead > self.extrapolate_s:
                    return NavLookup(
                        None,
                        f"{ahead:.3f} s after the newest navigation (extrapolation limited to {self.extrapolate_s:.3f} s)",
                    )
                return NavLookup(extrapolate(self._nav[-1], self._rate_partner(), t))
            if t < t_old:
                return NavLookup(None, f"{t_old - t:.3f} s before the oldest navigation kept ({self.horizon_s:.1f} s history)")
            i = bisect.bisect_left(self._t, t, lo=self._start)
            if self._t[i] == t:
                return NavLookup(self._nav[i])
            a, b = self._nav[i - 1], self._nav[i]
        gap = b.t_s - a.t_s
        if gap > self.max_gap_s:
            return NavLookup(None, f"gap of {gap:.3f} s in the navigation around t (limit {self.max_gap_s:.3f} s)")
        return NavLookup(interpolate(a, b, t))


def interpolate(a: NavState, b: NavState, t: float) -> NavState:
    """State at ``t`` between ``a`` (earlier) and ``b`` (later): lerp, slerp, convex covariance."""
    alpha = (t - a.t_s) / (b.t_s - a.t_s)
    return NavState(
        t_s=float(t),
        position_ned_m=a.position_ned_m + alpha * (b.position_ned_m - a.position_ned_m),
        velocity_ned_mps=a.velocity_ned_mps + alpha * (b.velocity_ned_mps - a.velocity_ned_mps),
        quaternion_wxyz=quat_slerp(a.quaternion_wxyz, b.quaternion_wxyz, alpha),
        covariance=(1.0 - alpha) * a.covariance + alpha * b.covariance,
        covariance_source=a.covariance_source if alpha < 0.5 else b.covariance_source,
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix whose angle is below pi (the inverse of so3_exp)."""
    c = min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) / 2.0))
    angle = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-6:
        return 0.5 * w  # sin(angle) ~ angle
    return w * (angle / (2.0 * math.sin(angle)))


def extrapolate(a: NavState, prev: NavState | None, t: float) -> NavState:
    """State at ``t`` after the newest state ``a``: position carried at its velocity, attitude at
    the rotation rate between ``prev`` (an older state, or None: attitude held) and ``a``, i.e. the
    slerp from ``prev`` to ``a`` continued past ``a`` (constant body rate). A camera frame is often
    stamped a few milliseconds after the newest navigation sample (navigation comes at 50 Hz):
    held, the attitude would be off by the turn rate times that gap (0.4 deg at 20 deg/s and
    20 ms), more than the attitude sigma the mapper is told."""
    dt = t - a.t_s
    q = a.quaternion_wxyz
    if prev is not None and a.t_s > prev.t_s:
        # R(t) = R_a Exp(s Log(R_prev^T R_a)), s = dt / (t_a - t_prev): the same body rotation per second
        R_a = quat_to_matrix(a.quaternion_wxyz)
        step = quat_to_matrix(prev.quaternion_wxyz).T @ R_a
        q = matrix_to_quat(R_a @ so3_exp(so3_log(step) * (dt / (a.t_s - prev.t_s))))
    return NavState(
        t_s=float(t),
        position_ned_m=a.position_ned_m + dt * a.velocity_ned_mps,
        velocity_ned_mps=a.velocity_ned_mps,
        quaternion_wxyz=q,
        covariance=a.covariance,
        covariance_source=a.covariance_source,
    )
