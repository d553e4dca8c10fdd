"""``companion run`` with a probe: the same :class:`companion.service.daemon.Daemon`, started the way
``companion run --config FILE`` starts it, that also keeps every latency and jitter sample with the
time it was taken and writes them to a JSON file when it stops.

Why: the daemon's status gives p50/p99 over the last 30 s only. With the time of each sample the
benchmark can also report the steady state (all samples from 5 s after take-off), and split the
frame-to-setpoint latency into its parts:

- ``capture_to_queue``: frame stamp -> frame in the mapper's queue (for the synthetic camera: age
  of the simulator pose it renders from, plus the render);
- ``queue_wait``: in the queue until the mapper thread takes it;
- ``map``: mapper step + grid insert (``Daemon._map_frame``);
- the rest, to the setpoint: waking the event loop and the control step.

It also times the synthetic camera's render (``Renderer.render``), which runs inside the daemon's
process in simulation only, and the map snapshots. ``--mapper-process`` runs the daemon's mapper in
a child process (companion/service/mapper_process.py). ``--worker-policy idle|nice`` is an experiment:
the mapper thread and the render threads at ``SCHED_IDLE`` or nice +10 (measured worse: a
low-priority thread preempted while it holds the GIL keeps the event loop waiting).

Nothing in the daemon's code is changed: the probe replaces the daemon's sample windows with
subclasses that also log, and wraps, on the instance, the frame queue's ``put``, ``_map_frame``,
``control_step``, ``save_snapshot`` (and ``_mapper_worker`` for the experiment). It starts the
daemon through ``companion.service.daemon._run``, as ``companion run`` does; a renamed attribute is
listed under ``missing`` in the samples instead of failing the run.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import threading
import time


def main(argv=None) -> int:
    from companion.config import ConfigError, load_config
    from companion.service.daemon import Daemon, Percentiles, _run, setup_logging

    p = argparse.ArgumentParser(prog="python -m benchmarks.daemon_probe")
    p.add_argument("--config", required=True)
    p.add_argument("--samples", required=True, help="JSON file written at exit")
    p.add_argument("--log-level", default="WARNING")
    p.add_argument("--mapper-process", action="store_true",
                   help="run the mapper in a child process (companion/service/mapper_process.py) instead of the daemon's thread")
    p.add_argument("--worker-policy", choices=("default", "idle", "nice"), default="default",
                   help="experiment: run the mapper thread (and the synthetic camera's render threads) at "
                        "SCHED_IDLE or nice +10, so the event loop's wake-ups preempt them at once")
    args = p.parse_args(argv)
    setup_logging(args.log_level)
    try:
        daemon = Daemon(load_config(args.config), mapper_process=args.mapper_process)
    except ConfigError as exc:
        print(f"configuration: {exc}", file=sys.stderr)
        return 2

    clock = daemon.clock

    class Logged(Percentiles):
        """The daemon's window (unchanged for its status) that also logs (monotonic time, value,
        companion clock time)."""

        def __init__(self, log: list):
            super().__init__()
            self.log = log

        def add(self, v: float) -> None:
            super().add(v)
            self.log.append((time.monotonic(), v, clock.now()))

    logs: dict[str, list] = {k: [] for k in ("frame_to_setpoint_ms", "jitter_ms", "step_ms", "put", "map", "render",
                                             "snapshot", "control_step")}
    missing = []
    for attr, key in (("frame_to_setpoint_ms", "frame_to_setpoint_ms"), ("control_jitter_ms", "jitter_ms"),
                      ("step_ms", "step_ms")):
        if isinstance(getattr(daemon, attr, None), Percentiles):
            setattr(daemon, attr, Logged(logs[key]))
        else:
            missing.append(attr)
    frames = getattr(daemon, "frames", None)
    if frames is not None and hasattr(frames, "put"):
        put = frames.put

        def logged_put(frame):
            logs["put"].append((time.monotonic(), frame.t_s, clock.now()))
            put(frame)

        frames.put = logged_put
    if hasattr(daemon, "_map_frame"):
        map_frame = daemon._map_frame

        def logged_map(frame):
            t0 = clock.now()
            map_frame(frame)
            logs["map"].append((time.monotonic(), frame.t_s, t0, clock.now()))

        daemon._map_frame = logged_map
    def lower_priority() -> None:
        """Lower the calling thread's scheduling priority (Linux: policies and nice are per thread)."""
        if args.worker_policy == "idle":
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        elif args.worker_policy == "nice":
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)

    if args.worker_policy != "default" and hasattr(daemon, "_mapper_worker"):
        worker = daemon._mapper_worker

        def low_priority_worker():
            lower_priority()
            worker()

        daemon._mapper_worker = low_priority_worker
    lowered: set[int] = set()
    if hasattr(daemon, "control_step"):
        control_step = daemon.control_step

        def logged_control(now):
            t0 = time.perf_counter()
            try:
                return control_step(now)
            finally:
                logs["control_step"].append((time.monotonic(), (time.perf_counter() - t0) * 1e3))

        daemon.control_step = logged_control

    if hasattr(daemon, "save_snapshot"):
        save = daemon.save_snapshot

        def logged_save():
            t0 = time.perf_counter()
            try:
                return save()
            finally:
                logs["snapshot"].append((time.monotonic(), (time.perf_counter() - t0) * 1e3))

        daemon.save_snapshot = logged_save
    try:  # the synthetic camera's render runs in this process (a real camera's work would not)
        from drivers.sim.renderer import Renderer

        render = Renderer.render

        def logged_render(self, *a, **k):
            if args.worker_policy != "default" and threading.get_native_id() not in lowered:
                lower_priority()
                lowered.add(threading.get_native_id())
            t0 = time.perf_counter()
            try:
                return render(self, *a, **k)
            finally:
                logs["render"].append((time.monotonic(), (time.perf_counter() - t0) * 1e3))

        Renderer.render = logged_render
    except ImportError:
        pass
    try:
        asyncio.run(_run(daemon))
    finally:
        with open(args.samples, "w") as f:
            json.dump({"logs": logs, "missing": missing, "speedup": clock.speedup if hasattr(clock, "speedup") else None},
                      f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
