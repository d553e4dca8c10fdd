"""The companion clock: monotonic seconds, optionally running faster than the wall clock.

Simulation runs faster than real time by a speed-up factor. The simulated vehicle and the
daemon each hold a :class:`Clock` with the same factor, so rates configured in simulated
seconds (a 20 Hz control loop, a 20 Hz camera) keep their meaning and the autopilot's
timestamps (TIMESYNC, time_boot_ms) map onto companion time with unit rate.

A :class:`SharedClock` is one clock for several processes, read from a small file: the simulator
creates it (``companion sim --clock-file``) and the service opens it (``sim.clock_file``). The
service may hold it (lockstep, as ArduPilot SITL's with its physics back end): simulated time then
waits at the hold for every process until the service lets it go on, so a host too slow for the
speed-up runs the simulation slower instead of dropping camera frames.
"""

from __future__ import annotations

import asyncio
import math
import mmap
import os
import struct
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

    @property
    def held(self) -> bool:
        """True while time waits for a holder (only a :class:`SharedClock` is ever held)."""
        return False

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


# The shared clock's file: a sequence number (odd while the writer is writing), the anchor
# (clock seconds at a time.monotonic() wall instant), the hold (clock seconds; +inf: none) and
# the speed-up. time.monotonic() is CLOCK_MONOTONIC, the same in every process of the host.
_LAYOUT = struct.Struct("<Qdddd")
_MAGIC = b"companion-clock/1\n"
_HEADER = len(_MAGIC)
HELD_POLL_WALL_S = 0.002  # a sleeper's poll while the clock is held (wall seconds)


class SharedClock(Clock):
    """A :class:`Clock` whose time several processes read from one file, and one of them may hold.

    ``now() = min(anchor + (monotonic - anchor_wall) * speedup, hold)``. Only :meth:`hold_at`
    writes, from one process (the service): it re-anchors at the current time, so time never
    jumps or goes back when a hold moves. Sleepers poll while the clock is held.
    """

    __slots__ = ("_fd", "_map", "path")

    def __init__(self, path: str, fd: int, speedup: float):
        super().__init__(speedup)
        self.path = path
        self._fd = fd
        self._map = mmap.mmap(fd, _HEADER + _LAYOUT.size)

    @classmethod
    def create(cls, path: str, speedup: float) -> SharedClock:
        """A new clock at 0 s now, running ``speedup`` times the wall clock, unheld (replaces ``path``)."""
        if not speedup > 0:
            raise ValueError(f"clock speedup must be positive, got {speedup}")
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            f.write(_MAGIC + _LAYOUT.pack(0, 0.0, time.monotonic(), math.inf, float(speedup)))
        os.replace(tmp, path)  # a reader never sees half a header
        return cls.open(path)

    @classmethod
    def open(cls, path: str) -> SharedClock:
        """The clock another process created at ``path``; ValueError if it is not one."""
        fd = os.open(path, os.O_RDWR)
        try:
            head = os.pread(fd, _HEADER + _LAYOUT.size, 0)
            if len(head) != _HEADER + _LAYOUT.size or head[:_HEADER] != _MAGIC:
                raise ValueError(f"{path}: not a companion clock file (written by companion sim --clock-file)")
            speedup = _LAYOUT.unpack_from(head, _HEADER)[4]
            return cls(path, fd, speedup)
        except BaseException:
            os.close(fd)
            raise

    def _read(self) -> tuple[float, float, float]:
        """(anchor clock s, anchor wall s, hold), consistent (seqlock: retried while being written)."""
        while True:
            seq, t0, wall0, hold, _ = _LAYOUT.unpack_from(self._map, _HEADER)
            if seq % 2 == 0 and _LAYOUT.unpack_from(self._map, _HEADER)[0] == seq:
                return t0, wall0, hold

    def _projection(self) -> tuple[float, float]:
        """(time without the hold, the hold)."""
        t0, wall0, hold = self._read()
        return t0 + (time.monotonic() - wall0) * self.speedup, hold

    def now(self) -> float:
        t, hold = self._projection()
        return min(t, hold)

    @property
    def held(self) -> bool:
        """True while time waits at the hold."""
        t, hold = self._projection()
        return t >= hold

    def hold_at(self, t_hold: float) -> None:
        """Let time run up to ``t_hold`` clock seconds and wait there (``math.inf``: release; a hold
        before now holds at now). One writer: the process that holds (the service)."""
        wall = time.monotonic()
        t0, wall0, hold = self._read()
        now = min(t0 + (wall - wall0) * self.speedup, hold)  # the new anchor: time at the same wall instant
        seq = _LAYOUT.unpack_from(self._map, _HEADER)[0]
        fields = (now, wall, max(t_hold, now), self.speedup)
        _LAYOUT.pack_into(self._map, _HEADER, seq + 1, *fields)  # odd: readers retry
        _LAYOUT.pack_into(self._map, _HEADER, seq + 2, *fields)

    def release(self) -> None:
        """Time runs free again (the holder stops)."""
        self.hold_at(math.inf)

    def _wall_delay(self, t: float) -> float | None:
        """Wall seconds to sleep towards ``t``; None once it is reached."""
        now, hold = self._projection()
        if min(now, hold) >= t:
            return None
        if now >= hold:
            return HELD_POLL_WALL_S  # held: until the holder lets time go on
        return (min(t, hold) - now) / self.speedup

    async def sleep(self, clock_seconds: float) -> None:
        await self.sleep_until(self.now() + max(0.0, clock_seconds))

    async def sleep_until(self, t: float) -> None:
        while (delay := self._wall_delay(t)) is not None:
            await asyncio.sleep(delay)

    def blocking_sleep_until(self, t: float) -> None:
        while (delay := self._wall_delay(t)) is not None:
            time.sleep(delay)

    def close(self) -> None:
        self._map.close()
        os.close(self._fd)
