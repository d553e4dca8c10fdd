"""Autopilot time -> companion time.

The autopilot stamps its messages with its own boot clock (``time_boot_ms``, ``time_usec``);
frames are stamped on the companion :class:`drivers.clock.Clock`. This module estimates

    offset = t_companion - t_autopilot      (seconds, constant up to crystal drift)

from two kinds of evidence, both pure numbers handed in by the link:

* **Round trips** (MAVLink ``TIMESYNC``): we send ``tc1 = 0, ts1 = t_sent`` (our time, ns); the
  autopilot answers ``tc1 = its time, ts1 = t_sent`` (ArduPilot: ``micros64() * 1000``, PX4:
  ``hrt_absolute_time() * 1000``, both the clock behind ``time_boot_ms``). With symmetric path
  delays ``offset_i = (t_sent + t_recv) / 2 - t_remote`` and the error of that sample is at most
  ``rtt_i / 2``. The estimate is the median of the offsets of the lowest-RTT quarter of the window
  (the samples that queued least), so a burst of delayed replies does not move it.
* **One-way arrivals** (``SYSTEM_TIME.time_boot_ms``): ``t_recv - t_remote = offset + delay >= offset``,
  so the minimum over the window is the best bound; it is biased late by the smallest one-way
  delay and is used only while no round trip has been answered.

``jitter_s`` is the robust spread (1.4826 x median absolute deviation) of the per-sample offsets
in the window: how much a single sample would have been off. ``rtt_s`` is the median RTT.

An autopilot reboot restarts its boot clock. Every remote stamp is checked against the clock seen
so far (:meth:`check_remote_time`): the autopilot clock runs at our rate, so a stamp should lie
near ``latest_remote + (t_local - latest_local)``. A stamp more than ``reboot_threshold_s`` behind
the latest, or more than ``ahead_tolerance_s`` ahead of that expectation, is a discontinuity. One
such stamp is an outlier (a corrupt or stray message, a packet delayed from before a reboot): it
is rejected and counted, and the time base stays. ``jump_confirmations`` consecutive stamps that
agree with each other (same ``t_local - t_remote`` within ``jump_threshold_s``) confirm it: behind
= a reboot (:attr:`reboots`), ahead = the clock jumped (another autopilot behind a router); either
way the window is cleared (:attr:`resets`). A persistent jump of the offset seen by round trips
(``jump_confirmations`` consecutive samples further than ``jump_threshold_s`` from the estimate)
also resets. Both clocks run at the same rate (the simulated autopilot uses the same speed-up), so the
offset is modelled as a constant; drift of a few ppm over the window is below the jitter.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class TimeSyncStatus:
    """Snapshot for the status: which evidence, the estimate and its quality (seconds)."""

    source: str  # "TIMESYNC", "SYSTEM_TIME" or "none"
    offset_s: float | None
    jitter_s: float | None
    rtt_s: float | None
    samples: int
    reboots: int
    resets: int
    rejected: int


class TimeSync:
    """Estimator of ``offset = companion - autopilot`` from TIMESYNC round trips and one-way stamps.

    window: number of samples kept per kind (round trip / one-way).
    max_rtt_s: round trips slower than this are discarded (their error bound rtt/2 is useless).
    reboot_threshold_s: remote time going backwards by more than this means the autopilot rebooted.
    ahead_tolerance_s: how far a stamp may run ahead of the remote clock's expected reading (message
        latency varies: a stamp after a delayed one runs ahead by the delay).
    jump_threshold_s / jump_confirmations: a persistent offset change resets the estimate; a
        discontinuity of the remote clock needs this many consistent stamps in a row.
    """

    def __init__(
        self,
        window: int = 32,
        max_rtt_s: float = 1.0,
        reboot_threshold_s: float = 1.0,
        jump_threshold_s: float = 0.5,
        jump_confirmations: int = 3,
        ahead_tolerance_s: float = 1.0,
    ) -> None:
        if window < 1:
            raise ValueError(f"timesync window must be >= 1, got {window}")
        self.window = int(window)
        self.max_rtt_s = float(max_rtt_s)
        self.reboot_threshold_s = float(reboot_threshold_s)
        self.jump_threshold_s = float(jump_threshold_s)
        self.jump_confirmations = int(jump_confirmations)
        self.ahead_tolerance_s = float(ahead_tolerance_s)
        self.reboots = 0
        self.clock_jumps = 0
        self.resets = 0
        self.rejected = 0
        self.outliers = {"behind": 0, "ahead": 0}  # remote stamps rejected as discontinuities
        self._rt: deque[tuple[float, float]] = deque(maxlen=self.window)  # (offset_i, rtt_i)
        self._ow: deque[float] = deque(maxlen=self.window)  # t_recv - t_remote
        self._latest_remote: float | None = None
        self._latest_local: float | None = None  # companion time at which _latest_remote was seen
        self._discontinuity: list[float] = []  # t_local - t_remote of consecutive discontinuous stamps
        self._jumps = 0
        self._offset: float | None = None
        self._jitter: float | None = None
        self._rtt: float | None = None
        self._source = "none"

    # ------------------------------------------------------------------------------------------
    # Evidence
    # ------------------------------------------------------------------------------------------

    def observe_remote_time(self, t_remote: float, t_local: float | None = None) -> bool:
        """Note a remote (autopilot boot) time seen in any message; True if it reveals a reboot.

        With ``t_local`` (the companion time of arrival) this is :meth:`check_remote_time`: a reboot
        needs consistent confirmation. Without it (a caller that has no arrival time), any stamp
        more than ``reboot_threshold_s`` behind the latest is taken as a reboot at once.
        """
        if t_local is not None:
            return self.check_remote_time(t_remote, t_local) == "reboot"
        latest = self._latest_remote
        if latest is not None and t_remote < latest - self.reboot_threshold_s:
            self.reboots += 1
            self.reset()
            self._latest_remote = t_remote
            return True
        if latest is None or t_remote > latest:
            self._latest_remote = t_remote
        return False

    def check_remote_time(self, t_remote: float, t_local: float) -> str:
        """Classify an autopilot stamp seen at companion time ``t_local`` (cheap: call it for every one).

        Returns "ok", "reboot" (confirmed: the estimate was cleared and this stamp starts the new
        clock), "jump" (the clock jumped ahead, confirmed: cleared likewise), or "behind" / "ahead"
        (an outlier, or a discontinuity not yet confirmed: the caller should not use the message).
        """
        if not (np.isfinite(t_remote) and np.isfinite(t_local)):
            self.rejected += 1
            return "behind"
        latest, latest_local = self._latest_remote, self._latest_local
        if latest is None or latest_local is None:
            self._latest_remote, self._latest_local = t_remote, t_local
            return "ok"
        if t_remote < latest - self.reboot_threshold_s:
            kind = "behind"
        elif t_remote > latest + (t_local - latest_local) + self.ahead_tolerance_s:
            kind = "ahead"
        else:
            self._discontinuity.clear()
            if t_remote > latest:
                self._latest_remote, self._latest_local = t_remote, t_local
            return "ok"
        offset = t_local - t_remote
        if self._discontinuity and abs(offset - self._discontinuity[0]) > self.jump_threshold_s:
            self._discontinuity.clear()  # not the same new clock as the previous outliers
        self._discontinuity.append(offset)
        if len(self._discontinuity) < self.jump_confirmations:
            self.outliers[kind] += 1
            return kind
        if kind == "behind":
            self.reboots += 1
        else:
            self.clock_jumps += 1
        self.reset()
        self._latest_remote, self._latest_local = t_remote, t_local
        return "reboot" if kind == "behind" else "jump"

    def add_roundtrip(self, t_sent: float, t_remote: float, t_received: float) -> bool:
        """One TIMESYNC answer: our send time, the autopilot's time, our receive time (s).

        Returns False (and counts it) when the sample is unusable: negative or too long a round trip.
        """
        rtt = t_received - t_sent
        if not (np.isfinite(rtt) and np.isfinite(t_remote)) or rtt < 0 or rtt > self.max_rtt_s:
            self.rejected += 1
            return False
        if self.check_remote_time(t_remote, t_received) in ("behind", "ahead"):
            self.rejected += 1
            return False
        offset_i = 0.5 * (t_sent + t_received) - t_remote
        if self._is_jump(offset_i, tolerance=0.5 * rtt):
            return True
        self._rt.append((offset_i, rtt))
        self._estimate()
        return True

    def add_one_way(self, t_remote: float, t_received: float) -> None:
        """A message stamped ``t_remote`` by the autopilot arrived at ``t_received`` (e.g. SYSTEM_TIME)."""
        if not (np.isfinite(t_remote) and np.isfinite(t_received)):
            self.rejected += 1
            return
        if self.check_remote_time(t_remote, t_received) in ("behind", "ahead"):
            self.rejected += 1
            return
        offset_i = t_received - t_remote
        if not self._rt and self._is_jump(offset_i, tolerance=0.0):
            return
        self._ow.append(offset_i)
        if not self._rt:
            self._estimate()

    def reset(self) -> None:
        """Forget every sample (after a reboot, a reconnection to a different autopilot, ...)."""
        self.resets += 1
        self._rt.clear()
        self._ow.clear()
        self._jumps = 0
        self._latest_remote = None
        self._latest_local = None
        self._discontinuity = []
        self._offset = self._jitter = self._rtt = None
        self._source = "none"

    # ------------------------------------------------------------------------------------------
    # Estimate
    # ------------------------------------------------------------------------------------------

    def _is_jump(self, offset_i: float, tolerance: float) -> bool:
        """True while a sample disagrees with the estimate; resets after enough in a row."""
        if self._offset is None or abs(offset_i - self._offset) <= self.jump_threshold_s + tolerance:
            self._jumps = 0
            return False
        self._jumps += 1
        if self._jumps >= self.jump_confirmations:
            latest = (self._latest_remote, self._latest_local)
            self.reset()
            self._latest_remote, self._latest_local = latest
            return False  # the caller adds this sample to the fresh window
        return True

    def _estimate(self) -> None:
        if self._rt:
            samples = np.array(self._rt)
            offsets, rtts = samples[:, 0], samples[:, 1]
            k = max(1, len(rtts) // 4)
            best = np.argsort(rtts, kind="stable")[:k]
            self._offset = float(np.median(offsets[best]))
            self._rtt = float(np.median(rtts))
            self._jitter = _robust_spread(offsets)
            self._source = "TIMESYNC"
        elif self._ow:
            offsets = np.array(self._ow)
            self._offset = float(offsets.min())
            self._rtt = None
            self._jitter = _robust_spread(offsets)
            self._source = "SYSTEM_TIME"

    @property
    def synced(self) -> bool:
        return self._offset is not None

    @property
    def offset_s(self) -> float | None:
        """companion - autopilot (s), or None before any evidence."""
        return self._offset

    @property
    def jitter_s(self) -> float | None:
        return self._jitter

    @property
    def rtt_s(self) -> float | None:
        return self._rtt

    @property
    def source(self) -> str:
        return self._source

    def to_companion(self, t_remote: float) -> float | None:
        """Companion time of an autopilot time (s), or None when not synchronised yet."""
        if self._offset is None:
            return None
        return t_remote + self._offset

    def status(self) -> TimeSyncStatus:
        return TimeSyncStatus(
            source=self._source,
            offset_s=self._offset,
            jitter_s=self._jitter,
            rtt_s=self._rtt,
            samples=len(self._rt) if self._rt else len(self._ow),
            reboots=self.reboots,
            resets=self.resets,
            rejected=self.rejected,
        )


def _robust_spread(x: np.ndarray) -> float:
    """1.4826 x median absolute deviation: the standard deviation for Gaussian samples, robust to outliers."""
    if len(x) < 2:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))
