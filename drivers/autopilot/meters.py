"""The link's bookkeeping: arrival rates per message type (:class:`RateMeter`) and a log that states
a repeated problem once, then at most every 30 s with the count in between (:class:`LogLimiter`)."""

from __future__ import annotations

import logging
import math
import time
from collections import deque

log = logging.getLogger("drivers.autopilot")  # one logger for the whole link, whichever part speaks


class RateMeter:
    """Arrival rate per message type over a sliding window (bounded memory).

    rate = arrivals in the last ``window_s`` / min(window_s, time since the type was first seen), so a
    burst (ten COMMAND_ACKs in 50 ms) reads as its average, and a stream silent for a window reads 0.
    """

    def __init__(self, window_s: float = 2.0, maxlen: int = 1024) -> None:
        self.window_s = window_s
        self.maxlen = maxlen
        self._t: dict[str, deque[float]] = {}
        self._first: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def tick(self, kind: str, now: float) -> None:
        q = self._t.get(kind)
        if q is None:
            q = self._t[kind] = deque(maxlen=self.maxlen)
            self._first[kind] = now
        q.append(now)
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def last(self, kind: str) -> float | None:
        q = self._t.get(kind)
        return q[-1] if q else None

    def rate(self, kind: str, now: float) -> float:
        q = self._t.get(kind)
        if not q:
            return 0.0
        n = sum(1 for t in q if t > now - self.window_s)
        span = min(self.window_s, now - self._first[kind])
        return n / span if span > 0 else 0.0

    def rates(self, now: float) -> dict[str, float]:
        return {k: round(self.rate(k, now), 2) for k in sorted(self._t)}


class LogLimiter:
    """Log a problem the first time, then at most once per ``interval_s`` with the count in between."""

    def __init__(self, interval_s: float = 30.0) -> None:
        self.interval_s = interval_s
        self._last: dict[str, tuple[float, int]] = {}

    def __call__(self, level: int, key: str, message: str) -> None:
        now = time.monotonic()
        last, suppressed = self._last.get(key, (-math.inf, 0))
        if now - last >= self.interval_s:
            suffix = f" ({suppressed} more since last report)" if suppressed else ""
            log.log(level, "%s%s", message, suffix)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, suppressed + 1)
