"""Lockstep with the simulator: simulated time waits while the service's mapper is behind.

With ``sim.clock_file`` the service and ``companion sim --clock-file`` read one
:class:`drivers.clock.SharedClock` (docs/sim.md, "Lockstep"). Every camera frame handed to the
workers (the mapper, and the dense flow when it is on) is outstanding until each of them has
finished it (or dropped it). Time may run at most :data:`MAPPER_LEAD_PERIODS` camera periods past
the capture of the oldest frame the mapper has not finished, then waits there for the whole
simulation, vehicle included: the frame after it is captured while it is mapped (the two overlap,
as in the service on a fast enough computer), the one after that waits until it is done. The dense
flow, which keeps earlier frames itself and measures only some, may lag further, as far as its
queue holds (``FLOW_QUEUE_FRAMES`` in companion/service/daemon.py), so that its work fills the
mapper's idle time instead of holding every frame.

So a host too slow for the speed-up runs the flight slower instead of dropping frames: the flight
is the one a computer fast enough for the camera rate would fly, on any host. What lockstep does
not slow down is the wall time between a map update and the setpoint it causes (an event-loop
wake-up and a control step), which stays a few milliseconds of wall time, that is the speed-up
times as much simulated time.
"""

from __future__ import annotations

import math
import threading

from companion.method.messages import Frame
from drivers.clock import SharedClock

# How far (camera periods) simulated time may run past the capture of the oldest frame the mapper
# has not finished: beyond one period, so that the next frame's tick (at most one period after,
# less the age of the pose it is rendered at) falls inside; under two, so that the tick after it waits.
MAPPER_LEAD_PERIODS = 1.5


class FrameLockstep:
    """Holds a :class:`SharedClock` while camera frames wait for the service's workers.

    ``leads`` maps each worker's name to how far (camera periods) time may run past the capture of
    the oldest frame it has not finished: :data:`MAPPER_LEAD_PERIODS` for the mapper; more for a
    worker built to lag (the dense flow keeps earlier frames itself, and its queue holds several).
    Call :meth:`captured` before a frame is handed to the workers, :meth:`finished` once per worker
    when it is done with it (or dropped it unmapped), :meth:`close` when the service stops.
    Thread-safe: the camera task and the worker threads call it.
    """

    def __init__(self, clock: SharedClock, camera_period_s: float, leads: dict[str, float]):
        if not camera_period_s > 0 or not leads or min(leads.values()) <= 1.0:
            raise ValueError(f"lockstep: camera period {camera_period_s} s, leads {leads} (periods, each above 1)")
        self.clock = clock
        self.lead_s = {name: periods * camera_period_s for name, periods in leads.items()}
        self._outstanding: dict[str, dict[int, float]] = {name: {} for name in leads}  # sequence -> capture s
        self._lock = threading.Lock()
        self.frames_held = {name: 0 for name in leads}  # frames each worker finished while time waited for it
        self._closed = False

    def captured(self, frame: Frame) -> None:
        with self._lock:
            for frames in self._outstanding.values():
                frames[frame.sequence] = frame.t_s
            self._hold()

    def finished(self, frame: Frame, worker: str) -> None:
        with self._lock:
            if self._outstanding[worker].pop(frame.sequence, None) is None:
                return
            if self.clock.held:
                self.frames_held[worker] += 1
            self._hold()

    def _hold(self) -> None:
        if self._closed:
            return
        hold = min((min(frames.values(), default=math.inf) + self.lead_s[name]
                    for name, frames in self._outstanding.items()), default=math.inf)
        self.clock.hold_at(hold)

    def close(self) -> None:
        """Let time run free (the service is stopping: the simulation must not wait for it)."""
        with self._lock:
            self._closed = True
            for frames in self._outstanding.values():
                frames.clear()
            self.clock.release()

    def status(self) -> dict:
        with self._lock:
            return {"outstanding": {name: len(frames) for name, frames in self._outstanding.items()},
                    "frames_held": dict(self.frames_held), "held": self.clock.held,
                    "lead_s": {name: round(v, 4) for name, v in self.lead_s.items()}}
