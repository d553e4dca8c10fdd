"""The companion clock: monotonic seconds, optionally running faster than the wall clock.

Simulation runs faster than real time by a speed-up factor. The simulated vehicle and the
daemon each hold a :class:`Clock` with the same factor, so rates configured in simulated
seconds (a 20 Hz control loop, a 20 Hz camera) keep their meaning and the autopilot's
timestamps (TIMESYNC, time_boot_ms) map onto companion time with unit rate.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field


@dataclass(slots=True)
class Clock:
    """Monotonic time in (possibly accelerated) seconds. ``speedup`` simulated seconds pass per wall second."""

    speedup: float = 1.0
    _wall0: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        if not self.speedup > 0:
            raise ValueError(f"clock speedup must be positive, got {self.speedup}")

    def now(self) -> float:
        """Seconds since this clock started, in clock units."""
        return (time.monotonic() - self._wall0) * self.speedup

    def wall_seconds(self, clock_seconds: float) -> float:
        """Wall-clock duration of ``clock_seconds``."""
        return clock_seconds / self.speedup

    async def sleep(self, clock_seconds: float) -> None:
        await asyncio.sleep(max(0.0, clock_seconds) / self.speedup)

    async def sleep_until(self, t: float) -> None:
        """Sleep until ``now() >= t`` (returns at once when already past)."""
        await self.sleep(t - self.now())

    def blocking_sleep_until(self, t: float) -> None:
        delay = (t - self.now()) / self.speedup
        if delay > 0:
            time.sleep(delay)
