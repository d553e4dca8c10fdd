"""The service: ``companion run``. One asyncio TaskGroup wires the parts together.

```
autopilot --MAVLink--> AutopilotLink --NavState--> nav buffer
camera ----Frame-----> camera task --drop-oldest queue--> mapper worker thread
mapper worker: nav = buffer.at(frame.t) -> Mapper.step -> converged points -> TerrainGrid
control loop (fixed rate, and at once after each map update): PullUpLaw + guidance -> setpoint
publisher: changed tiles -> Zenoh;  status (1 Hz) -> Zenoh, systemd STATUS, log
snapshots: TerrainGrid -> persistence.directory/terrain.snapshot (atomic, checksummed, the one before kept
           as terrain.snapshot.prev), the newest good one loaded on start (docs/reliability.md)
```

The mapper is CPU work; it runs in one worker thread owned by the daemon (NumPy and OpenCV
release the GIL; or, with ``mapper_process=True``, in a child process driven by that thread)
fed by a bounded queue that drops the oldest frame, so a slow frame never delays the control loop. The grid is shared between that thread and the event loop under one
lock. With ``control.realtime_priority`` the event loop's thread runs ``SCHED_FIFO`` and preempts
the mapper thread the moment a tick is due (companion/service/realtime.py). SIGTERM or SIGINT ends every
task, saves the map and exits within about two seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import concurrent.futures
import copy
import logging
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import CompanionConfig, ConfigError, load_config
from companion.config import replace as replace_config
from companion.method.avoidance import AvoidanceCommand
from companion.method.control import Controller, level_flight_view_limit
from companion.method.geometry import camera_from_config
from companion.method.mapper import Mapper, mean_innovation_squared
from companion.method.mapper.flow_depth import FlowRanger
from companion.method.messages import Frame, NavState
from companion.method.terrain.codec import TilePublications
from companion.method.terrain.grid import TerrainGrid
from companion.method.terrain.persistence import count_known_cells, load_latest, snapshot_bytes, write_snapshot_bytes
from companion.service import realtime
from companion.service.lockstep import MAPPER_LEAD_PERIODS, FrameLockstep
from companion.service.mapper_process import MapperProcess
from companion.service.sdnotify import SystemdNotifier
from drivers.clock import HELD_POLL_WALL_S, Clock, SharedClock

log = logging.getLogger("companion")

SNAPSHOT_NAME = "terrain.snapshot"
# MAV_SEVERITY values used in STATUSTEXT.
SEVERITY_WARNING, SEVERITY_NOTICE, SEVERITY_INFO = 4, 5, 6
# Minimum time (companion seconds) between avoidance engaged/released STATUSTEXTs.
STATUSTEXT_HOLD_S = 5.0


class _Shutdown(Exception):
    """Raised inside the TaskGroup to end every task together."""


# Frames waiting for the dense flow's thread; beyond it the oldest is dropped (counted): a pair then
# spans more time, which the poses account for.
FLOW_QUEUE_FRAMES = 8
FLOW_WAIT_S = 0.1  # the longest a measured frame's flow waits for the mapper to be idle
STATUS_WINDOW_S = 30.0  # the status figures cover this much recent time: how the service runs now


@dataclass(slots=True)
class Percentiles:
    """Recent samples with p50 / p99: those of the last ``window_s`` seconds (monotonic clock), at most
    ``maxlen``, so that the status tells how the service runs now rather than since start-up (whose
    imports and take-off would otherwise stay in the p99 for good). Safe to add to from one thread
    while another summarises."""

    maxlen: int = 2000
    window_s: float = STATUS_WINDOW_S
    values: collections.deque = field(default_factory=collections.deque)  # (monotonic s, value)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, v: float, t: float | None = None) -> None:
        with self.lock:
            if len(self.values) >= self.maxlen:
                self.values.popleft()
            self.values.append((time.monotonic() if t is None else t, v))

    def summary(self, scale: float = 1.0, now: float | None = None) -> dict[str, float | int | None]:
        """n, p50, p99, max of the samples of the window ending at ``now`` (monotonic; default: now)."""
        start = (time.monotonic() if now is None else now) - self.window_s
        with self.lock:
            while self.values and self.values[0][0] < start:
                self.values.popleft()
            recent = [v for _, v in self.values]
        if not recent:
            return {"n": 0, "p50": None, "p99": None, "max": None, "window_s": self.window_s}
        a = np.asarray(recent, float) * scale
        return {"n": int(a.size), "p50": round(float(np.percentile(a, 50)), 3),
                "p99": round(float(np.percentile(a, 99)), 3), "max": round(float(a.max()), 3),
                "window_s": self.window_s}


class FrameQueue:
    """Bounded queue between the camera task and a worker thread that drops the oldest frame.

    ``idle`` is set while the worker has finished every frame put (it calls :meth:`done` after
    each): another thread can wait for it to use the worker's idle time."""

    def __init__(self, maxlen: int = 2):
        self._frames: collections.deque[Frame] = collections.deque(maxlen=maxlen)
        self._cond = threading.Condition()
        self.dropped = 0
        self.closed = False
        self.idle = threading.Event()
        self.idle.set()

    def put(self, frame: Frame) -> Frame | None:
        """Queue ``frame``; returns the oldest frame, dropped to make room (None: nothing dropped)."""
        with self._cond:
            dropped = None
            if len(self._frames) == self._frames.maxlen:
                self.dropped += 1
                dropped = self._frames[0]
            self._frames.append(frame)
            self.idle.clear()
            self._cond.notify()
            return dropped

    def done(self) -> None:
        """The worker finished a frame: idle again if none is waiting."""
        with self._cond:
            if not self._frames:
                self.idle.set()

    def get(self, timeout_s: float) -> Frame | None:
        with self._cond:
            if not self._frames and not self.closed:
                self._cond.wait(timeout_s)
            return self._frames.popleft() if self._frames else None

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


def clock_from_config(cfg: CompanionConfig) -> Clock:
    """The service's clock: its own at ``sim.speedup``, or the simulator's shared one (``sim.clock_file``)."""
    if not cfg.sim.clock_file:
        return Clock(cfg.sim.speedup)
    try:
        return SharedClock.open(cfg.sim.clock_file)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"'sim.clock_file': cannot open the simulator's clock: {exc}") from None


def _finite_or_none(x: float, digits: int = 3) -> float | None:
    """A number for the status JSON: None for inf/NaN (no limit, unknown)."""
    return round(float(x), digits) if math.isfinite(x) else None


def frame_status(origin, flavour: str) -> dict[str, Any]:
    """Where the map's local frame lies on the Earth (docs/zenoh.md, "Status"; companion/method/geodesy.py):
    the EKF origin as the autopilot reported it, and the autopilot's mapping between local offsets
    and latitude/longitude (``projection``, None until the autopilot is known)."""
    return {
        "axes": "NED",
        "origin": None if origin is None else {
            "lat_deg": origin.lat_deg, "lon_deg": origin.lon_deg, "alt_m": origin.alt_m, "source": origin.source},
        "projection": flavour if flavour in ("ardupilot", "px4") else None,
    }


class Daemon:
    """The running service. Build it from a validated config, then ``await run()``."""

    def __init__(self, cfg: CompanionConfig, *, record_dir: str | None = None, clock: Clock | None = None,
                 mapper_process: bool = False):
        from drivers.autopilot.link import AutopilotLink  # loaded with a daemon, not with the command line

        if cfg.control.commanding_enabled and len(cfg.control.waypoints_ne_m) < 2:
            raise ConfigError(
                "'control.waypoints_ne_m' needs at least two waypoints when 'control.commanding_enabled' is true: "
                "the service owns the whole velocity setpoint in GUIDED/OFFBOARD and must know where to fly"
            )
        if cfg.camera.source == "synthetic" and not cfg.link.request_sim_state:
            # The synthetic camera renders at the simulator's true pose, which arrives as SIM_STATE.
            cfg = replace_config(cfg, **{"link.request_sim_state": True})
        self.cfg = cfg
        self.clock = clock or clock_from_config(cfg)
        self.link = AutopilotLink(cfg, self.clock)
        self.camera_model, self.mount = camera_from_config(cfg.camera)
        self.snapshot_path = Path(cfg.persistence.directory) / SNAPSHOT_NAME
        self.grid = self._load_map()
        self.grid_lock = threading.Lock()
        # The revision and layers of each tile as last published, for deltas (docs/terrain.md).
        self.tile_payloads = TilePublications(cfg.zenoh.tile_deltas, cfg.zenoh.tile_keyframe_every)
        # The mapper runs in the worker thread; mapper_process=True runs it in a child process instead
        # (companion/service/mapper_process.py: the control loop never waits for a GIL the mapper holds, at
        # ~1.5 ms of inter-process cost per frame; measured no better here, docs/performance.md).
        self.mapper: Mapper | MapperProcess
        if mapper_process:
            self.mapper = MapperProcess(cfg, self._with_map)
        else:
            self.mapper = Mapper(
                cfg.mapper, self.camera_model, self.mount, depth_prior=self._depth_prior,
                default_ground_alt_m=cfg.terrain.default_ground_alt_m, border_px=cfg.camera.border_px,
            )
        self.controller = Controller(cfg)  # the law and the route (companion/method/control.py)
        self.notifier = SystemdNotifier()
        self.record_dir = record_dir
        self.frames = FrameQueue(maxlen=2)
        # Rises and flat surfaces seen by dense flow (mapper.flow_rises, flow_surface; docs/mapper.md): a
        # stage of its own, in a thread of its own beside the mapper's, so its flows run on the other
        # core and never delay a frame's corners on their way to the setpoint. It keeps earlier frames
        # itself, so it gets every frame (a deeper queue: storing a frame it does not measure costs a copy).
        self.flow: FlowRanger | None = None
        if cfg.mapper.flow_on:
            self.flow = FlowRanger(cfg.mapper, self.camera_model, self.mount)
        self.flow_frames = FrameQueue(maxlen=FLOW_QUEUE_FRAMES)
        self._flow_thread: threading.Thread | None = None
        # Lockstep with the simulator (sim.clock_file): time waits while the workers are behind.
        self.lockstep: FrameLockstep | None = None
        if isinstance(self.clock, SharedClock):
            leads = {"mapper": MAPPER_LEAD_PERIODS}
            if self.flow is not None:
                leads["flow"] = FLOW_QUEUE_FRAMES - MAPPER_LEAD_PERIODS  # it lags as far as its queue holds, never beyond
            self.lockstep = FrameLockstep(self.clock, 1.0 / cfg.camera.rate_hz, leads)
        # control.realtime_priority: what the loop's thread got ({priority, active, reason}; None: not asked)
        self.realtime_state: dict | None = None
        self._snapshot_executor: concurrent.futures.ThreadPoolExecutor | None = None
        self.camera: Any = None
        self.bus: Any = None
        self.fleet: Any = None      # other vehicles' maps for the law (zenoh.share_from)
        self.shared: Any = None
        self.recorder: Any = None
        self._stop = asyncio.Event()
        self._map_updated = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._mapper_thread: threading.Thread | None = None
        self._started = self.clock.now()
        # Counters and figures for the status.
        self.camera_state = "starting"
        self.camera_error = ""
        self.frames_in = 0
        self.frames_mapped = 0
        self.frames_no_nav: collections.Counter[str] = collections.Counter()
        self.mapper_errors = 0
        self.points_converged = 0
        self.edgels_in = 0  # edgels passed to the mapper (docs/mapper.md, "Edgels")
        self.edge_updates = 0  # edge features updated across their edge
        self.flow_measured = 0  # frames the dense flow measured (docs/mapper.md, "Rises seen by dense flow")
        self.flow_ranged = 0  # lattice points it ranged
        self.flow_floors = 0  # floors it gave to rising cells
        self.flow_surface_inserted = 0  # its flat cells' heights the map took (docs/mapper.md, "Surfaces seen by dense flow")
        self.flow_errors = 0
        self.flow_thread_nice: int | None = None  # the flow thread's nice value (None: not started, or unknown)
        self.flow_no_nav: collections.Counter[str] = collections.Counter()
        self.flow_step_ms = Percentiles()  # a measured frame's flow, ranging and votes
        self.flow_to_map_ms = Percentiles()  # capture of a measured frame to its floors in the map
        self.innovation_nis_sum = 0.0  # the filter's consistency (docs/replay.md, "Filter consistency")
        self.corner_updates = 0
        self.point_covariance_scale = 1.0  # the last step's (docs/mapper.md, "Calibrated point covariance")
        self.grid_rejections: collections.Counter[str] = collections.Counter()
        self.step_ms = Percentiles()
        self.step_cpu_ms = Percentiles()  # the mapper thread's CPU time per step: step_ms less what other threads took
        self.frame_to_setpoint_ms = Percentiles()
        self.control_jitter_ms = Percentiles()
        self.control_ticks = 0
        self._setpoint_t = 0.0
        self.last_command: AvoidanceCommand | None = None
        self.last_frame_mapped_t: float | None = None
        # Capture times of the frames whose map update no setpoint has used yet (appended under the
        # grid lock, right after the insert), and how many of them the last control step's law saw.
        self._map_updates: collections.deque[float] = collections.deque(maxlen=256)
        self._updates_in_setpoint = 0
        self.command_state = "starting"
        self.engaged = False
        self._engaged_changed_t = -math.inf
        self._avoidance_published_t = -math.inf  # when the avoidance state last went out, and what it was
        self._avoidance_published_state: tuple[bool, bool] | None = None
        self.snapshot_ok_t: float | None = None
        self.snapshot_error = ""
        self.snapshot_failures = 0
        self.snapshot_failures_in_a_row = 0
        self.snapshots_written = 0
        self.snapshot_last: dict[str, Any] | None = None
        self._snapshot_warned: tuple[float, Any] = (-math.inf, None)  # (when, kind of error) of the last warning
        self.lap = 0

    # ---- map and persistence ---------------------------------------------------------------

    def _load_map(self) -> TerrainGrid:
        """The newest good snapshot (or the one before it), else an empty map; never raises.

        The outcome is kept for the status (``snapshots.loaded``): file, tiles, cells and the
        snapshot's age, so an operator sees how much map survived a restart.
        """
        loaded = load_latest(self.snapshot_path, self.cfg.terrain)
        self.snapshot_loaded = loaded.as_dict()
        for why in loaded.refused:
            self.link.send_statustext(SEVERITY_WARNING, "companion: bad map snapshot refused")
            log.error("map: %s", why)
        if loaded.path is None:
            log.info("map: no usable snapshot at %s; starting with an empty map", self.snapshot_path)
        else:
            log.info("map: loaded %d tiles, %d cells from %s (snapshot %.1f s old)",
                     loaded.tiles, loaded.cells, loaded.path, loaded.age_s or 0.0)
        return loaded.grid

    def _statustext_from_any_thread(self, severity: int, text: str) -> None:
        """STATUSTEXT from a worker thread: the link belongs to the event loop."""
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self.link.send_statustext, severity, text)
        else:
            self.link.send_statustext(severity, text)

    def save_snapshot(self) -> bool:
        """Write the map atomically; never raises.

        Only a copy of the map is taken under the grid lock; it is encoded, written and fsync'ed
        outside it, so neither a large map nor a slow disk holds the control loop. A failure (disk full, read-only, the
        directory gone or not a directory) is counted and reported in the status at once, and in
        the log and a STATUSTEXT on the first failure, when the kind of error changes and at most
        every ``persistence.warn_every_s`` after that; the vehicle keeps flying and mapping and
        the next interval tries again. The first success after failures says so.
        """
        t0 = time.perf_counter()
        try:
            with self.grid_lock:
                # A private copy of the layers (a memory copy: ~30 ms for 1000 tiles, against ~300 ms
                # to encode them) is all the lock covers; the mapper and control loop go on meanwhile.
                grid = copy.deepcopy(self.grid)
            data = snapshot_bytes(grid)
            tiles, cells = len(grid), count_known_cells(grid)
            del grid
            write_snapshot_bytes(data, self.snapshot_path, keep_previous=self.cfg.persistence.keep_previous)
        except Exception as exc:  # noqa: BLE001 - a full or read-only disk must not stop the vehicle
            now = self.clock.now()
            self.snapshot_failures += 1
            self.snapshot_failures_in_a_row += 1
            self.snapshot_error = f"map snapshot to {self.snapshot_path} failed: {exc}"
            kind = (type(exc).__name__, getattr(exc, "errno", None))
            last_t, last_kind = self._snapshot_warned
            if kind != last_kind or now - last_t >= self.cfg.persistence.warn_every_s:
                self._snapshot_warned = (now, kind)
                log.error("%s (%d in a row; the vehicle keeps flying and mapping, the map lives in memory)",
                          self.snapshot_error, self.snapshot_failures_in_a_row)
                reason = getattr(exc, "strerror", None) or type(exc).__name__
                self._statustext_from_any_thread(SEVERITY_WARNING, f"companion: map snapshot failing: {reason}")
            return False
        if self.snapshot_failures_in_a_row:
            log.warning("map snapshots work again after %d failures (%s)", self.snapshot_failures_in_a_row,
                        self.snapshot_path)
            self._statustext_from_any_thread(SEVERITY_INFO, "companion: map snapshots resumed")
        self.snapshot_error = ""
        self.snapshot_failures_in_a_row = 0
        self._snapshot_warned = (-math.inf, None)
        self.snapshots_written += 1
        self.snapshot_ok_t = self.clock.now()
        self.snapshot_last = {"tiles": tiles, "cells": cells, "bytes": len(data),
                              "ms": round((time.perf_counter() - t0) * 1e3, 1)}
        return True

    def _with_map(self, use) -> None:
        """``use(grid)`` under the map lock (the mapper process starts from the map as it is)."""
        with self.grid_lock:
            use(self.grid)

    def _depth_prior(self, origin_ned: np.ndarray, rays_ned: np.ndarray) -> np.ndarray:
        """The mapper's depth prior: the range to the mapped terrain along each ray (NaN if unknown)."""
        with self.grid_lock:
            return self.grid.ray_range(origin_ned, rays_ned, self.cfg.mapper.prior_max_range_m)

    # ---- camera and mapper -----------------------------------------------------------------

    def _build_camera(self):
        if self.cfg.camera.source == "synthetic":
            from drivers.cameras.synthetic import synthetic_camera_from_config

            return synthetic_camera_from_config(self.cfg, self.clock, self._truth_pose)
        if self.cfg.camera.source == "stream":
            from drivers.cameras.stream import StreamCamera

            return StreamCamera(self.cfg.camera, self.link.timesync.to_companion)
        from drivers.cameras.factory import build_camera

        return build_camera(self.cfg.camera, self.clock)

    def _truth_pose(self):
        """The simulator's true body pose (SIM_STATE over MAVLink), for the synthetic camera."""
        truth = self.link.truth_pose()
        if truth is None:
            return None
        return truth.t_s, truth.position_ned_m, truth.quaternion_wxyz

    async def _camera_task(self) -> None:
        from drivers.cameras.base import CameraError, CorruptInput, EndOfStream

        try:
            self.camera = await asyncio.to_thread(self._build_camera)
        except (ConfigError, OSError, ValueError) as exc:
            self.camera_state, self.camera_error = "failed", str(exc)
            log.error("camera: cannot start: %s (mapping is off; link, control and publishing go on)", exc)
            return
        lost_since: float | None = None
        while not self._stop.is_set():
            try:
                frame = await self.camera.read()
            except CameraError as exc:
                if lost_since is None and self.frames_in > 0:
                    lost_since = self.clock.now()
                    log.warning("camera lost: %s", exc)
                    self.link.send_statustext(SEVERITY_WARNING, "companion: camera lost")
                self.camera_state = "lost" if self.frames_in > 0 else "waiting"
                self.camera_error = str(exc)
                await self.clock.sleep(min(1.0, 2.0 / self.cfg.camera.rate_hz))
                continue
            except (EndOfStream, CorruptInput) as exc:
                self.camera_state = "ended" if isinstance(exc, EndOfStream) else "corrupt"
                self.camera_error = str(exc) or "end of recording"
                log.warning("camera: %s (%s); link, control and publishing go on", self.camera_state, self.camera_error)
                self.link.send_statustext(SEVERITY_WARNING, f"companion: camera {self.camera_state}")
                return
            if lost_since is not None:
                log.info("camera back after %.1f s", self.clock.now() - lost_since)
                self.link.send_statustext(SEVERITY_INFO, "companion: camera back")
                lost_since = None
            self.camera_state, self.camera_error = "ok", ""
            self.frames_in += 1
            if self.lockstep is not None:
                self.lockstep.captured(frame)
            self._finished_unmapped(self.frames.put(frame), "mapper")
            if self.flow is not None:
                self._finished_unmapped(self.flow_frames.put(frame), "flow")
            if self.recorder is not None:
                self.recorder.submit(frame)

    def _finished_unmapped(self, dropped: Frame | None, worker: str) -> None:
        """A frame a full queue dropped is done with, for the lockstep (a hold must not wait for it)."""
        if dropped is not None and self.lockstep is not None:
            self.lockstep.finished(dropped, worker)

    def _mapper_worker(self) -> None:
        """Worker thread: frames -> mapper -> terrain grid. One bad frame never stops the others."""
        if isinstance(self.mapper, MapperProcess):
            try:
                self.mapper.start()  # now, rather than with the first frame (a new interpreter takes a moment)
            except Exception:  # noqa: BLE001 - the first step tries again
                self.mapper_errors += 1
                log.exception("mapper: the mapper process did not start; trying again with the next frame")
        while not self.frames.closed:
            frame = self.frames.get(timeout_s=0.2)
            if frame is None:
                continue
            try:
                self._map_frame(frame)
            except Exception:  # noqa: BLE001
                self.mapper_errors += 1
                log.exception("mapper: frame %d failed; continuing with the next frame", frame.sequence)
            finally:
                self.frames.done()
                if self.lockstep is not None:
                    self.lockstep.finished(frame, "mapper")

    def _flow_worker(self) -> None:
        """Worker thread: frames -> dense flow -> floors and flat surfaces in the terrain grid
        (docs/mapper.md, "Rises seen by dense flow", "Surfaces seen by dense flow"). One bad frame
        never stops the others."""
        self.flow_thread_nice, why = realtime.yield_to_others(self.cfg.mapper.flow_thread_nice)
        if why:
            log.warning("flow: thread at the mapper's priority (mapper.flow_thread_nice %d not applied: %s)",
                        self.cfg.mapper.flow_thread_nice, why)
        while not self.flow_frames.closed:
            frame = self.flow_frames.get(timeout_s=0.2)
            if frame is None:
                continue
            if self.flow.will_measure():
                # A measured frame's flows take two to three of the mapper's steps: started while the
                # mapper is idle (just after a step), they fill the time until its next frame instead of
                # competing with it for a shared core and Python's lock. A mapper that stays busy
                # (more frames than it can map) holds the flow back at most FLOW_WAIT_S.
                self.frames.idle.wait(FLOW_WAIT_S)
            try:
                self._flow_frame(frame)
            except Exception:  # noqa: BLE001
                self.flow_errors += 1
                log.exception("flow: frame %d failed; continuing with the next frame", frame.sequence)
            finally:
                if self.lockstep is not None:
                    self.lockstep.finished(frame, "flow")

    def _flow_frame(self, frame: Frame) -> None:
        lookup = self.link.nav_buffer.lookup(frame.t_s)
        if lookup.nav is None:
            self.flow_no_nav[lookup.reason or "no navigation"] += 1
            self.flow.reset()  # a pair across the gap would range with a pose nobody has
            return
        t0 = time.perf_counter()
        step = self.flow.step(lookup.nav, frame.image)
        if step.refused:
            self.flow_no_nav[step.refused] += 1
        if not step.measured:
            return
        self.flow_measured += 1
        self.flow_ranged += step.n_ranged
        self.flow_floors += len(step.floors)
        self.flow_step_ms.add((time.perf_counter() - t0) * 1e3)
        if len(step.floors) or len(step.surface):
            with self.grid_lock:
                self.flow_surface_inserted += self.grid.add_flow(step.surface, step.floors).inserted
            self.flow_to_map_ms.add(max(0.0, self.clock.wall_seconds(self.clock.now() - frame.t_s)) * 1e3)
            if self._loop is not None:
                self._loop.call_soon_threadsafe(self._map_updated.set)  # the law reads the floors at once

    def _map_frame(self, frame: Frame) -> None:
        lookup = self.link.nav_buffer.lookup(frame.t_s)
        nav: NavState | None = lookup.nav
        if nav is None:
            self.frames_no_nav[lookup.reason or "no navigation"] += 1
            return
        t0, c0 = time.perf_counter(), time.thread_time()
        step = self.mapper.step(nav, frame.image)
        self.edgels_in += step.n_edgels
        self.edge_updates += step.n_edge_matched
        self.innovation_nis_sum += step.innovation_nis_sum
        self.corner_updates += step.n_corner_updates
        self.point_covariance_scale = step.point_covariance_scale
        changed = bool(len(step.points) or len(step.free_space) or len(step.floors) or step.floors.n_ended)
        if changed:
            with self.grid_lock:
                stats = self.grid.add_evidence(step.points, step.free_space, step.floors)
                self._map_updates.append(frame.t_s)
            self.points_converged += len(step.points)
            for name in ("rejected_invalid", "rejected_outlier", "rejected_imprecise", "lone_points", "lone_floors"):
                self.grid_rejections[name] += int(getattr(stats, name, 0))
        self.step_ms.add((time.perf_counter() - t0) * 1e3)
        self.step_cpu_ms.add((time.thread_time() - c0) * 1e3)
        self.frames_mapped += 1
        self.last_frame_mapped_t = frame.t_s
        if changed and self._loop is not None:
            self._loop.call_soon_threadsafe(self._map_updated.set)  # the control loop runs at once

    # ---- control ---------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Fixed-rate loop; also runs at once when the map changed (frame-to-setpoint latency).

        Jitter: how late each fixed-rate tick runs. Frame-to-setpoint: for every frame whose map
        update reached the grid, the time from the frame's capture to the setpoint of the first
        control step whose law read the grid with that update in it (sent to the autopilot, or
        decided as advisory; the status text and the Zenoh publication follow it); a frame whose
        update waits for a later step (navigation stale) counts that wait.
        """
        period = 1.0 / self.cfg.control.rate_hz
        next_tick = self.clock.now() + period
        while not self._stop.is_set():
            timeout = self.clock.wall_seconds(next_tick - self.clock.now())
            if self.clock.held:
                timeout = min(timeout, HELD_POLL_WALL_S)  # the tick comes when the holder lets time go on
            map_changed = False
            if timeout > 0:
                try:
                    await asyncio.wait_for(self._map_updated.wait(), timeout)
                    map_changed = True
                except TimeoutError:
                    pass
            self._map_updated.clear()
            now = self.clock.now()
            if not map_changed and now < next_tick:
                continue  # the wait ended before the tick in clock time: a held clock (sim.clock_file)
            if not map_changed or now >= next_tick:
                self.control_jitter_ms.add(self.clock.wall_seconds(now - next_tick) * 1e3)
                next_tick += period
                if now - next_tick > 5 * period:  # fell far behind (suspended?): resynchronise
                    next_tick = now + period
                self.control_ticks += 1
                self.notifier.watchdog()
            self._updates_in_setpoint = 0
            if self.control_step(now) and self._updates_in_setpoint:
                t_setpoint = self._setpoint_t  # when the setpoint left (or the advisory was decided)
                for _ in range(min(self._updates_in_setpoint, len(self._map_updates))):
                    t_frame = self._map_updates.popleft()
                    self.frame_to_setpoint_ms.add(self.clock.wall_seconds(t_setpoint - t_frame) * 1e3)

    def control_step(self, now: float) -> bool:
        """One evaluation of the law and, when allowed, one setpoint (else an advisory one).
        False when there is no setpoint at all (no or stale navigation)."""
        nav = self.link.nav_buffer.latest()
        if nav is None:
            self.command_state = "no navigation yet"
            return False
        age = now - nav.t_s
        if age > self.cfg.nav.stale_after_s:
            self.command_state = f"navigation stale ({age:.2f} s old)"
            return False
        with self.grid_lock:
            decision = self.controller.decide(nav, self._law_map())
            self._updates_in_setpoint = len(self._map_updates)  # the updates this law has seen
        cmd, velocity = decision.command, decision.velocity_ned_mps
        self.last_command = cmd
        self.lap = decision.lap
        if not decision.send:
            # Takeoff and landing belong to the autopilot: a velocity setpoint would cancel them.
            sent = False
            self.command_state = f"advisory (below control.min_alt_m = {self.cfg.control.min_alt_m:g} m)"
        else:
            sent = self.link.send_setpoint(velocity, yaw_rad=decision.yaw_rad)
            record = self.link.last_setpoint
            self.command_state = "commanding" if sent else f"advisory ({record.reason if record else 'not sent'})"
        self._setpoint_t = self.clock.now()  # frame-to-setpoint ends here; the status text and publishing follow
        airborne = nav.altitude_m >= self.cfg.control.min_alt_m
        if airborne and cmd.engaged != self.engaged and now - self._engaged_changed_t >= STATUSTEXT_HOLD_S:
            # Held for a few seconds so a law that flickers at the threshold does not flood the GCS.
            self.engaged = cmd.engaged
            self._engaged_changed_t = now
            if cmd.engaged:
                text = f"companion: avoid {cmd.limiting_height_m:.0f}m terrain, climb {cmd.climb_rate_mps:.1f}"
                log.warning("avoidance engaged: terrain %.1f m at %s, climb %.2f m/s (%s)",
                            cmd.limiting_height_m, cmd.limiting_cell_ne, cmd.climb_rate_mps, self.command_state)
                self.link.send_statustext(SEVERITY_WARNING, text)
            else:
                log.info("avoidance released")
                self.link.send_statustext(SEVERITY_INFO, "companion: avoidance released")
        if self.bus is not None and self._avoidance_due(now, cmd.engaged, sent):
            self.bus.publish_avoidance(self.avoidance_body(cmd, velocity, sent, nav))
        return True

    def _law_map(self):
        """What the law reads: the own grid, with other vehicles' evidence fused in when
        ``zenoh.share_from`` names any (companion/method/terrain/sharing.py). Under grid_lock."""
        if self.fleet is None:
            return self.grid
        from companion.method.geodesy import LocalFrame
        from companion.method.terrain.sharing import SharedView

        origin, flavour = self.link.assembler.origin, self.link.flavour
        own = None if origin is None else LocalFrame(origin.lat_deg, origin.lon_deg, origin.alt_m,
                                                     flavour if flavour in ("ardupilot", "px4") else "ardupilot")
        self.fleet.drain(self.shared, own, self.cfg.zenoh.share_weight)
        return SharedView(self.grid, self.shared, self.cfg.terrain.gate_sigma)

    def _avoidance_due(self, now: float, engaged: bool, sent: bool) -> bool:
        """Publish the avoidance state at ``zenoh.avoidance_rate_hz``, and at once when the law
        engages or releases or the mode changes (a ground station never misses a transition)."""
        state = (bool(engaged), bool(sent))
        if state != self._avoidance_published_state or now - self._avoidance_published_t >= 1.0 / self.cfg.zenoh.avoidance_rate_hz:
            self._avoidance_published_state, self._avoidance_published_t = state, now
            return True
        return False

    def avoidance_body(self, cmd: AvoidanceCommand, velocity: np.ndarray, sent: bool, nav: NavState | None = None) -> dict[str, Any]:
        """The ``companion.avoidance/1`` payload (docs/zenoh.md): required fields first; with the
        navigation state the law used, where the vehicle was (what a map display draws it at)."""
        def num(x):
            return None if x is None or not math.isfinite(x) else round(float(x), 3)

        return {
            "engaged": cmd.engaged,
            "mode": "commanding" if sent else "advisory",
            "climb_rate_mps": num(cmd.climb_rate_mps),
            "restriction_alt_m": num(cmd.required_alt_m),
            "limiting_cell": None if cmd.limiting_cell_ne is None else [round(float(c), 2) for c in cmd.limiting_cell_ne],
            "time_to_cell_s": num(cmd.time_to_go_s),
            "limiting_height_m": num(cmd.limiting_height_m),
            "nominal_alt_m": self.cfg.avoidance.nominal_alt_m,
            "ground_reference_m": num(cmd.ground_reference_m),
            "nominal_climb_mps": num(cmd.nominal_climb_mps),
            "unknown_cells_ahead": int(cmd.unknown_cells_ahead),
            "speed_limit_mps": num(cmd.speed_limit_mps),
            "view_distance_m": num(cmd.view_distance_m),
            "view_speed_limit_mps": num(cmd.view_speed_limit_mps),
            "known_horizon_m": num(cmd.known_horizon_m),
            "setpoint_velocity_ned_mps": [round(float(v), 3) for v in velocity],
            "reason": self.command_state,
            "position_ned_m": None if nav is None else [num(v) for v in nav.position_ned_m],
            "velocity_ned_mps": None if nav is None else [num(v) for v in nav.velocity_ned_mps],
        }

    # ---- publishing, status, snapshots -----------------------------------------------------

    async def _publish_loop(self) -> None:
        """Every ``zenoh.tile_interval_s``, the tiles that changed since the last round (a tile
        that changed several times goes out once, as it is now); deflated unless
        ``zenoh.tile_deflate`` is off (docs/zenoh.md, "Bandwidth")."""
        while not self._stop.is_set():
            await self.clock.sleep(self.cfg.zenoh.tile_interval_s)
            if self.bus is not None:
                self.publish_changed_tiles()

    def publish_changed_tiles(self) -> int:
        """Publish the tiles the map changed since the last call, in the map's own frame: moving
        the map to follow the navigation changes no tile there, and the status's
        ``map.frame_shift_m`` takes their heights to the vehicle's frame (docs/zenoh.md). Returns
        the tiles published."""
        with self.grid_lock:
            changed = [(k, self.grid.tile(k, in_map_frame=True)) for k in self.grid.pop_dirty()]
        for (tx, ty), tile in changed:
            whole, live = self.tile_payloads.encode(tile, self.cfg.zenoh.tile_deflate)
            self.bus.publish_tile(tx, ty, whole, live)
        return len(changed)

    def status(self) -> dict[str, Any]:
        now = self.clock.now()
        link = self.link.status()
        problems = []
        if not self.link.connected:
            problems.append(f"autopilot link {self.link.state}")
        if self.camera_state != "ok":
            problems.append(f"camera {self.camera_state}: {self.camera_error}".rstrip(": "))
        if self.snapshot_error:
            problems.append(self.snapshot_error)
        # One look at the bus a message: its links and the problem they raise come from the same
        # observation (a link that came up between two looks made a status say both up and down).
        zenoh_stats = None if self.bus is None else self.bus.stats().as_dict()
        zenoh_link = "off" if zenoh_stats is None else ("up" if zenoh_stats["links"] > 0 else "down")
        if zenoh_link == "down" and self.cfg.zenoh.connect:
            # Only an expected peer or router missing is a problem; nobody listening in is normal.
            problems.append(f"zenoh link down (connect {', '.join(self.cfg.zenoh.connect)})")
        uptime = max(now - self._started, 1e-9)
        with self.grid_lock:
            grid = {
                "tiles": len(self.grid),
                "cells": count_known_cells(self.grid),
                "observed_area_m2": round(float(self.grid.observed_area_m2()), 1),
                "memory_bytes": int(self.grid.memory_bytes()),
                "cell_size_m": self.grid.cell_size_m,
                "frame_shift_m": round(self.grid.frame_shift_m, 3), "frame_shifts": self.grid.frame_shifts,
            }
        camera_stats = getattr(self.camera, "stats", None)
        nis = mean_innovation_squared(self.innovation_nis_sum, self.corner_updates)
        return {
            "health": "ok" if not problems else "degraded",
            "problems": problems,
            "zenoh_link": zenoh_link,
            "uptime_s": round(uptime, 1),
            "command": self.command_state,
            **link,  # link, streams, rates_hz, nav, time, rejected, commanding, truth (docs/mavlink.md)
            "camera": {
                "state": self.camera_state, "error": self.camera_error, "frames": self.frames_in,
                "queue_dropped": self.frames.dropped,
                "stats": camera_stats.as_dict() if hasattr(camera_stats, "as_dict") else None,
                # sim.clock_file: frames outstanding, frames time waited for (None: no lockstep)
                "lockstep": None if self.lockstep is None else self.lockstep.status(),
            },
            "mapper": {
                "parameterisation": self.cfg.mapper.parameterisation,
                "frames_mapped": self.frames_mapped, "frames_without_nav": dict(self.frames_no_nav),
                "errors": self.mapper_errors, "points_converged": self.points_converged,
                "edgels": self.edgels_in, "edge_updates": self.edge_updates,
                "flow": {"on": self.flow is not None, "thread_nice": self.flow_thread_nice, "frames_measured": self.flow_measured,
                         "ranged": self.flow_ranged, "floors": self.flow_floors,
                         "surface_inserted": self.flow_surface_inserted, "errors": self.flow_errors,
                         "frames_without_nav": dict(self.flow_no_nav), "queue_dropped": self.flow_frames.dropped,
                         "step_ms": self.flow_step_ms.summary(), "frame_to_map_ms": self.flow_to_map_ms.summary()},
                "innovation_nis_mean": None if nis is None else round(nis, 3),
                "point_covariance_scale": round(self.point_covariance_scale, 3),
                "step_ms": self.step_ms.summary(), "step_cpu_ms": self.step_cpu_ms.summary(),
            },
            "map": {**grid, "rejections": dict(self.grid_rejections)},
            "sharing": None if self.fleet is None else self.fleet.status(),
            "frame": frame_status(self.link.assembler.origin, self.link.flavour),
            "avoidance": None if self.last_command is None else {
                "engaged": self.last_command.engaged, "climb_rate_mps": round(self.last_command.climb_rate_mps, 3),
                "speed_limit_mps": _finite_or_none(self.last_command.speed_limit_mps),
                "view_distance_m": _finite_or_none(self.last_command.view_distance_m),
                "view_speed_limit_mps": _finite_or_none(self.last_command.view_speed_limit_mps),
                "known_horizon_m": _finite_or_none(self.last_command.known_horizon_m),
                "ground_reference_m": _finite_or_none(self.last_command.ground_reference_m),
            },
            "control": {
                "rate_hz": self.cfg.control.rate_hz, "ticks": self.control_ticks,
                "jitter_ms": self.control_jitter_ms.summary(),
                "frame_to_setpoint_ms": self.frame_to_setpoint_ms.summary(),
                "realtime": self.realtime_state,
                "lap": self.lap,
            },
            "snapshots": {
                "path": str(self.snapshot_path), "interval_s": self.cfg.persistence.snapshot_interval_s,
                "state": "failing" if self.snapshot_error else ("ok" if self.snapshot_ok_t is not None else "none yet"),
                "error": self.snapshot_error, "written": self.snapshots_written, "failures": self.snapshot_failures,
                "failures_in_a_row": self.snapshot_failures_in_a_row,
                "last_ok_age_s": None if self.snapshot_ok_t is None else round(now - self.snapshot_ok_t, 1),
                "last": self.snapshot_last, "loaded": self.snapshot_loaded,
            },
            **({} if zenoh_stats is None else {"zenoh": zenoh_stats}),
        }

    async def _status_loop(self) -> None:
        rate = self.cfg.zenoh.status_rate_hz
        n = 0
        while not self._stop.is_set():
            await self.clock.sleep(1.0 / rate)
            status = self.status()
            if self.bus is not None:
                self.bus.publish_status(status)
            summary = (f"{status['health']}; link {self.link.state}; camera {self.camera_state}; "
                       f"mapped {self.frames_mapped} frames; {status['map']['tiles']} tiles; {status['map']['cells']} cells; "
                       f"zenoh {status['zenoh_link']}; snapshots {status['snapshots']['state']}; {self.command_state}")
            self.notifier.status(summary)
            n += 1
            if n % max(1, int(10 * rate)) == 0:
                log.info("status: %s", summary)

    async def _snapshot_loop(self) -> None:
        while not self._stop.is_set():
            await self.clock.sleep(self.cfg.persistence.snapshot_interval_s)
            await self._save_snapshot_in_background()

    async def _save_snapshot_in_background(self) -> bool:
        """:meth:`save_snapshot` on its own thread, at normal scheduling (a thread the loop's thread
        starts does not inherit its real-time policy, companion/service/realtime.py): writing the map is
        bulk work that must not hold up the control loop or the I/O threads."""
        if self._snapshot_executor is None:
            self._snapshot_executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="companion-snapshot")
        return await asyncio.get_running_loop().run_in_executor(self._snapshot_executor, self.save_snapshot)

    # ---- lifecycle -------------------------------------------------------------------------

    def request_stop(self) -> None:
        self._stop.set()

    async def _stopper(self) -> None:
        await self._stop.wait()
        raise _Shutdown()

    async def run(self) -> None:
        """Run until :meth:`request_stop` (SIGTERM / SIGINT in :func:`main`)."""
        self._loop = asyncio.get_running_loop()
        if self.cfg.control.realtime_priority > 0:
            # The I/O threads (camera reads: on the frame's way to the setpoint) one priority below
            # the control loop's thread (companion/service/realtime.py); normal scheduling where refused.
            self._loop.set_default_executor(concurrent.futures.ThreadPoolExecutor(
                thread_name_prefix="companion-io", initializer=realtime.below,
                initargs=(self.cfg.control.realtime_priority,)))
        if self.cfg.control.gil_switch_interval_ms > 0:
            # The mapper thread holds Python's lock between its OpenCV calls (~3 ms a frame); a
            # control tick or a frame arriving meanwhile waits until the lock is handed over, after
            # at most this interval (docs/performance.md, "Control loop").
            sys.setswitchinterval(self.cfg.control.gil_switch_interval_ms * 1e-3)
        if self.cfg.zenoh.enabled:
            from drivers.zenoh_bus import ZenohBus

            self.bus = ZenohBus(self.cfg.zenoh)  # answers map queries from the tiles it published
            await asyncio.to_thread(self.bus.open)
            if self.cfg.zenoh.share_from:
                from companion.method.terrain.sharing import SharedEvidence
                from drivers.fleet_listener import FleetListener

                self.shared = SharedEvidence(self.cfg.zenoh.vehicle_name, self.grid.cell_size_m, self.grid.tile_cells)
                self.fleet = FleetListener(self.cfg.zenoh).open(self.bus)  # on the bus's session, closed with it
                log.info("reading other vehicles' maps: %s (trust %g)", ", ".join(self.cfg.zenoh.share_from),
                         self.cfg.zenoh.share_weight)
        if self.record_dir:
            from drivers.cameras.recorder import FrameRecorder

            self.recorder = FrameRecorder.from_config(self.record_dir, self.cfg, self.clock)
            self.recorder.start()
            self.link.record_telemetry(self.recorder.telemetry_path)
        self._mapper_thread = threading.Thread(target=self._mapper_worker, name="mapper", daemon=True)
        self._mapper_thread.start()
        if self.flow is not None:
            self._flow_thread = threading.Thread(target=self._flow_worker, name="flow", daemon=True)
            self._flow_thread.start()
        scheduling_before = self._enter_realtime()  # after the threads that must stay at normal priority
        self.notifier.ready("starting: waiting for the autopilot")
        log.info("companion running: link %s, camera %s, mapper %s, commanding %s",
                 self.cfg.link.connection, self.cfg.camera.source, self.cfg.mapper.parameterisation,
                 "enabled" if self.cfg.control.commanding_enabled else "off (advisory)")
        if self.lockstep is not None:
            log.info("lockstep: simulated time from %s (x%g at most), held while the mapper or the dense flow is "
                     "behind (docs/sim.md)", self.lockstep.clock.path, self.clock.speedup)
        view_m, view_mps = level_flight_view_limit(self.cfg)
        if self.cfg.avoidance.view_speed_limit and view_mps < self.cfg.control.cruise_speed_mps:
            log.warning("view speed limit: with camera.mount_pitch_deg %g the camera sees terrain that would need a "
                        "climb only %.0f m ahead in level flight, so the vehicle flies at most %.1f m/s of "
                        "control.cruise_speed_mps %g (less with its nose down); pitch the camera nearer the horizon, "
                        "or set avoidance.view_speed_limit: false to fly the route's speed into terrain the camera "
                        "has not seen", self.cfg.camera.mount_pitch_deg, view_m, view_mps,
                        self.cfg.control.cruise_speed_mps)
        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(self.link.run(), name="link")
                tg.create_task(self._camera_task(), name="camera")
                tg.create_task(self._control_loop(), name="control")
                tg.create_task(self._publish_loop(), name="publish")
                tg.create_task(self._status_loop(), name="status")
                tg.create_task(self._snapshot_loop(), name="snapshots")
                tg.create_task(self._stopper(), name="stopper")
        except* _Shutdown:
            pass
        finally:
            await self._shutdown()
            realtime.restore(scheduling_before)

    def _enter_realtime(self) -> realtime.Scheduling | None:
        """Put the event loop's thread under ``SCHED_FIFO`` at ``control.realtime_priority``
        (companion/service/realtime.py): it preempts the mapper thread, which stays at normal scheduling,
        as do the snapshot thread and the threads it starts from now on (``SCHED_RESET_ON_FORK``);
        the executor's threads run one priority below it (:meth:`run`). Returns the thread's
        scheduling before (None: unchanged)."""
        priority = self.cfg.control.realtime_priority
        if priority <= 0:
            return None
        before, reason = realtime.enter_fifo(priority)
        self.realtime_state = {"priority": priority, "active": not reason, "reason": reason}
        if reason:
            log.warning("control loop at normal priority: %s; a busy mapper can delay control ticks", reason)
        else:
            log.info("control loop thread at SCHED_FIFO priority %d, I/O threads at %d, mapper at normal priority",
                     priority, max(1, priority - 1))
        return before

    async def _shutdown(self) -> None:
        self.notifier.stopping()
        if self.lockstep is not None:
            self.lockstep.close()  # the simulation goes on without the service
        self.frames.close()
        self.flow_frames.close()
        if self._mapper_thread is not None:
            await asyncio.to_thread(self._mapper_thread.join, 2.0)
        if self._flow_thread is not None:
            await asyncio.to_thread(self._flow_thread.join, 2.0)
        if isinstance(self.mapper, MapperProcess):
            await asyncio.to_thread(self.mapper.close, 1.0)
        saved = await self._save_snapshot_in_background()
        self._snapshot_executor.shutdown(wait=False)
        self._snapshot_executor = None
        log.info("map %s at shutdown (%s)", "saved" if saved else "NOT saved", self.snapshot_path)
        if self.camera is not None:
            try:
                await asyncio.wait_for(self.camera.close(), 1.0)
            except Exception as exc:  # noqa: BLE001
                log.warning("camera close: %s", exc)
        if self.recorder is not None:
            await asyncio.to_thread(self.recorder.close)
        if self.bus is not None:
            await asyncio.to_thread(self.bus.close)
        self.notifier.close()


# ---- command line ----------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="YAML configuration (see config/default.yaml)")
    p.add_argument("--record", metavar="DIR", help="record frames, timestamps and MAVLink telemetry to DIR for replay")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])


def setup_logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


async def _run(daemon: Daemon) -> None:
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, daemon.request_stop)
    await daemon.run()


def main(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    try:
        cfg = load_config(args.config)
        daemon = Daemon(cfg, record_dir=args.record)
    except ConfigError as exc:
        log.error("configuration: %s; refusing to start", exc)
        return 2
    asyncio.run(_run(daemon))
    return 0
