"""The daemon while mapping: frame-to-setpoint latency and control-loop jitter.

Three processes on this machine, as a user would run them:

1. ``companion sim`` (ArduPilot flavour, default scenario, speed-up 1) listening on an ephemeral
   TCP port for the daemon and sending to a UDP port for the pilot;
2. the *pilot* (a thread here, plain pymavlink): GUIDED, arm, take off to the circuit altitude,
   then a GCS heartbeat every second (ArduPilot's GCS failsafe would land the vehicle otherwise);
3. ``companion run --config <generated yaml>``: ``config/sitl.yaml`` with ``camera.rate_hz``
   30, ``sim.speedup`` 1, Zenoh on a free loopback port, persistence in a temporary directory.
   Once the vehicle is above ``control.min_alt_m`` the daemon commands the circuit in GUIDED.

The figures are the daemon's own (``companion.status/1`` on Zenoh, ``control.jitter_ms`` and
``control.frame_to_setpoint_ms``), read by a Zenoh client that knows only the documented key and
JSON fields. The status windows hold the last 30 s (the 40 s run's status covers flight only);
the probe's samples give the steady state and the parts of the latency besides.
"""

from __future__ import annotations

import bisect
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
GUIDED = 4
# Runs a module's ``main(argv)`` on given cores and, optionally, with another GIL switch interval:
# ``python -c LAUNCHER CORES INTERVAL_S|- MODULE <arguments>`` (CORES "-" = inherit).
LAUNCHER = (
    "import importlib, os, sys\n"
    "cores, interval, module = sys.argv[1], sys.argv[2], sys.argv[3]\n"
    "if cores != '-':\n"
    "    os.sched_setaffinity(0, {int(c) for c in cores.split(',')})\n"
    "if interval != '-':\n"
    "    sys.setswitchinterval(float(interval))\n"
    "sys.exit(importlib.import_module(module).main(sys.argv[4:]))\n"
)
SETTLE_S = 5.0  # steady state: samples from this long after take-off


def launcher(module: str, cores: str = "-", switch_interval_s: float | None = None) -> list[str]:
    return [sys.executable, "-c", LAUNCHER, cores, "-" if switch_interval_s is None else repr(switch_interval_s), module]


def daemon_env() -> dict:
    """The environment ``companion run`` gives itself (companion/cli.py): one BLAS / OpenMP thread
    unless set otherwise; the probe imports NumPy before any of the daemon's code runs."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        env.setdefault(name, "1")
    return env


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def daemon_config(sim_port: int, zenoh_port: int, directory: str, rate_hz: float = 30.0) -> dict:
    """config/sitl.yaml with the benchmark's changes (a plain dict, written as YAML)."""
    with open(REPO / "config" / "sitl.yaml") as f:
        cfg = yaml.safe_load(f)
    cfg.setdefault("link", {})["connection"] = f"tcp:127.0.0.1:{sim_port}"
    cfg.setdefault("camera", {})["rate_hz"] = float(rate_hz)
    cfg.setdefault("zenoh", {}).update(listen=[f"tcp/127.0.0.1:{zenoh_port}"], status_rate_hz=2.0,
                                      multicast_scouting=False, mode="peer")
    cfg.setdefault("persistence", {})["directory"] = directory
    cfg.setdefault("sim", {})["speedup"] = 1.0
    return cfg


class Pilot(threading.Thread):
    """GUIDED, arm, take off; then heartbeats until stopped. ``error`` says what failed."""

    def __init__(self, client, takeoff_alt_m: float):
        super().__init__(name="pilot", daemon=True)
        self.client = client
        self.alt = takeoff_alt_m
        self.stop = threading.Event()
        self.airborne = threading.Event()
        self.error = ""
        self.altitude_m = float("nan")

    def run(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav

        c = self.client
        try:
            c.wait_heartbeat(10.0)
            c.heartbeat()
            c.set_interval(mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 5)
            if c.wait_statustext(lambda t: "origin set" in t.lower(), 20.0) is None:
                self.error = "no 'origin set' from the simulator"
                return
            for cmd, args in ((mav.MAV_CMD_DO_SET_MODE, (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)),
                              (mav.MAV_CMD_COMPONENT_ARM_DISARM, (1,)),
                              (mav.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, self.alt))):
                ack = c.command(cmd, *args)
                if ack is None or ack.result != mav.MAV_RESULT_ACCEPTED:
                    self.error = f"command {cmd} not accepted ({ack})"
                    return
            last_hb = 0.0
            while not self.stop.is_set():
                now = time.monotonic()
                if now - last_hb > 0.5:
                    c.heartbeat()
                    last_hb = now
                m = c.latest("LOCAL_POSITION_NED")
                if m is not None:
                    self.altitude_m = -m.z
                    if -m.z > 0.8 * self.alt:
                        self.airborne.set()
                time.sleep(0.05)
        except Exception as exc:  # noqa: BLE001 - reported in the results, never hangs the run
            self.error = f"pilot: {exc!r}"


class StatusListener:
    """Zenoh client subscribed to ``companion/<vehicle>/status``; keeps the newest decoded JSON."""

    def __init__(self, endpoint: str, vehicle: str = "vehicle1"):
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", json.dumps("client"))
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(cfg)
        self.latest: dict | None = None
        self.received = 0
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(f"companion/{vehicle}/status", self._on_sample)

    def _on_sample(self, sample) -> None:
        try:
            body = json.loads(bytes(sample.payload.to_bytes()).decode("utf-8"))
        except (ValueError, UnicodeDecodeError):
            return
        with self._lock:
            self.latest = body
            self.received += 1

    def get(self) -> dict | None:
        with self._lock:
            return self.latest

    def close(self) -> None:
        try:
            self._sub.undeclare()
        finally:
            self.session.close()


def stop_process(proc: subprocess.Popen, grace_s: float = 10.0) -> int | None:
    """SIGTERM, then SIGKILL after ``grace_s``; the exit code (the daemon saves its map on SIGTERM)."""
    proc.terminate()
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
    return proc.returncode


def _wait(pred, timeout_s: float, poll_s: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(poll_s)
    return False


# control.realtime_priority on the vehicle: the service unit's LimitRTPRIO (systemd/companion.service)
VEHICLE_REALTIME_PRIORITY = 10


def run_daemon_benchmark(duration_s: float = 40.0, rate_hz: float = 30.0, log=print, daemon_cores: str = "1",
                         sim_cores: str = "0", switch_interval_s: float | None = None,
                         keep_samples: str | None = None, worker_policy: str = "default",
                         mapper_process: bool = False, camera: str = "stream",
                         realtime_priority: int = VEHICLE_REALTIME_PRIORITY, flow: bool | None = None) -> dict:
    """Fly the circuit with the daemon mapping at ``rate_hz`` for ``duration_s`` after take-off;
    returns the daemon's control figures (and what went wrong, if anything).

    ``daemon_cores`` / ``sim_cores``: CPU sets ("1", "0,1", "-" = inherit) of the two processes;
    by default the daemon has one core and the simulator (which stands in for the autopilot and
    the camera's world) the other. ``switch_interval_s``: the daemon's GIL switch interval
    (``control.gil_switch_interval_ms``; None = the configuration's, 1 ms; 0 = Python's default, 5 ms). ``keep_samples``: copy the probe's
    samples (JSON, :mod:`benchmarks.daemon_probe`) to this path. ``worker_policy``: "idle" or
    "nice" lowers the mapper and render threads' priority (an experiment; see the probe).
    ``mapper_process``: run the daemon's mapper in a child process (companion/service/mapper_process.py)
    instead of its worker thread. ``camera``: "stream" (default) = the simulator renders the camera
    at the true pose of each exposure and sends the frames over TCP stamped in the autopilot's time
    (``companion sim --camera-listen``; the camera has its own hardware, as on a vehicle);
    "synthetic" = the daemon renders them itself from SIM_STATE, in its own process.
    ``realtime_priority``: the daemon's ``control.realtime_priority`` (the vehicle's setting, as the
    service unit allows it; 0 = normal scheduling); what the daemon got is in ``realtime``.
    ``flow``: the daemon's ``mapper.flow_rises`` (None = the configuration's; its own thread beside
    the mapper's, on the daemon's one core here)."""
    if camera not in ("stream", "synthetic"):
        raise ValueError(f"camera must be 'stream' or 'synthetic', got {camera!r}")
    from drivers.sim.harness import MavClient, SimVehicleProcess

    result: dict = {"duration_s": duration_s, "camera_rate_hz": rate_hz, "error": "", "daemon_cores": daemon_cores,
                    "sim_cores": sim_cores, "switch_interval_s": switch_interval_s, "worker_policy": worker_policy,
                    "mapper_process": mapper_process, "camera": camera, "realtime_priority": realtime_priority,
                    "flow": flow}
    tmp = tempfile.TemporaryDirectory(prefix="companion-bench-")
    pilot_client = MavClient.udp_listener()
    sim = SimVehicleProcess(["--flavour", "ardupilot", "--scenario", "default", "--tcp-listen", "127.0.0.1:0",
                             "--udp-out", f"127.0.0.1:{pilot_client.port}", "--speedup", "1",
                             "--origin-delay", "0.5", "--log-level", "WARNING"]
                            + (["--camera-listen", "127.0.0.1:0", "--camera-rate", str(rate_hz)] if camera == "stream" else []),
                            command=launcher("companion.cli", sim_cores) + ["sim"], stderr_path=os.path.join(tmp.name, "sim.log"))
    daemon = listener = pilot = None
    daemon_log = os.path.join(tmp.name, "daemon.log")
    samples_path = os.path.join(tmp.name, "samples.json")
    t_air = None
    try:
        sim.start()
        zenoh_port = free_port()
        cfg = daemon_config(sim.endpoints["tcp"], zenoh_port, os.path.join(tmp.name, "map"), rate_hz)
        cfg.setdefault("control", {})["realtime_priority"] = int(realtime_priority)
        if flow is not None:
            cfg.setdefault("mapper", {}).update(flow_rises=bool(flow), flow_surface=bool(flow))
        if switch_interval_s is not None:  # 0: Python's default (5 ms)
            cfg.setdefault("control", {})["gil_switch_interval_ms"] = 1e3 * switch_interval_s
        if camera == "stream":
            cfg["camera"].update(source="stream", stream_address=f"127.0.0.1:{sim.endpoints['camera']}")
        cfg_path = os.path.join(tmp.name, "bench.yaml")
        with open(cfg_path, "w") as f:
            yaml.safe_dump(cfg, f)
        takeoff = float(cfg.get("avoidance", {}).get("nominal_alt_m", 15.0))
        pilot = Pilot(pilot_client, takeoff)
        pilot.start()
        with open(daemon_log, "w") as err:
            daemon = subprocess.Popen(launcher("benchmarks.daemon_probe", daemon_cores)
                                      + ["--config", cfg_path, "--samples", samples_path, "--log-level", "WARNING",
                                         "--worker-policy", worker_policy]
                                      + (["--mapper-process"] if mapper_process else []),
                                      stdout=subprocess.DEVNULL, stderr=err,
                                      env=daemon_env(), cwd=str(REPO))
        listener = _wait_listener(f"tcp/127.0.0.1:{zenoh_port}", 20.0)
        if listener is None:
            raise RuntimeError("no Zenoh session with the daemon")
        if not pilot.airborne.wait(45.0):
            raise RuntimeError(pilot.error or f"vehicle not airborne (altitude {pilot.altitude_m:.1f} m)")
        t_air = time.monotonic()
        log(f"  daemon: airborne; mapping for {duration_s:.0f} s ...")
        if not _wait(lambda: (listener.get() or {}).get("mapper", {}).get("frames_mapped", 0) > 0, 15.0):
            raise RuntimeError("the daemon mapped no frame")
        time.sleep(max(0.0, duration_s - (time.monotonic() - t_air)))
        seen = listener.received
        _wait(lambda: listener.received > seen, 3.0)  # a status published after the run
        status = listener.get()
        if status is None:
            raise RuntimeError("no status from the daemon")
        control, mapper = status.get("control", {}), status.get("mapper", {})
        result.update(
            jitter_ms=control.get("jitter_ms"),
            frame_to_setpoint_ms=control.get("frame_to_setpoint_ms"),
            control_rate_hz=control.get("rate_hz"),
            control_ticks=control.get("ticks"),
            realtime=control.get("realtime"),
            mapper_step_ms=mapper.get("step_ms"),
            mapper_step_cpu_ms=mapper.get("step_cpu_ms"),
            flow_status=mapper.get("flow"),
            frames_mapped=mapper.get("frames_mapped"),
            frames_in=status.get("camera", {}).get("frames"),
            queue_dropped=status.get("camera", {}).get("queue_dropped"),
            camera_stats=status.get("camera", {}).get("stats"),
            points_converged=mapper.get("points_converged"),
            command=status.get("command"),
            uptime_s=status.get("uptime_s"),
            map=status.get("map"),
        )
    except Exception as exc:  # noqa: BLE001 - the other benchmarks still report
        result["error"] = str(exc)
    finally:
        if pilot is not None:
            pilot.stop.set()
        if daemon is not None:
            result["daemon_exit"] = stop_process(daemon)
            if t_air is not None:
                result["steady_state"] = steady_state(samples_path, t_air + SETTLE_S)
                result["t_airborne_monotonic"] = t_air
            if keep_samples and os.path.exists(samples_path):
                shutil.copyfile(samples_path, keep_samples)
        if listener is not None:
            listener.close()
        sim.stop()
        pilot_client.close()
        if pilot is not None:
            pilot.join(2.0)
        if result["error"]:
            try:
                with open(daemon_log) as f:
                    result["daemon_log_tail"] = f.read()[-2000:]
            except OSError:
                pass
        tmp.cleanup()
    return result


def steady_state(samples_path: str, t_from: float) -> dict:
    """Figures from the probe's samples taken after ``t_from`` (monotonic s), and the parts of the
    frame-to-setpoint latency (ms): frame stamp -> queue, queue wait, mapper step + insert."""
    import numpy as np

    from benchmarks.common import summary

    try:
        with open(samples_path) as f:
            data = json.load(f)
    except (OSError, ValueError) as exc:
        return {"error": f"no probe samples: {exc}"}
    logs = data["logs"]
    out: dict = {"from_s_after_takeoff": SETTLE_S, "missing": data.get("missing", [])}
    for key in ("frame_to_setpoint_ms", "jitter_ms", "step_ms"):
        out[key] = summary([e[1] for e in logs.get(key, []) if e[0] >= t_from])
    put = {round(ts, 9): now for t, ts, now in logs.get("put", []) if t >= t_from}
    cap, wait, mapping = [], [], []
    for t, ts, t0, t1 in logs.get("map", []):
        q = put.get(round(ts, 9))
        if t < t_from or q is None:
            continue
        cap.append((q - ts) * 1e3)
        wait.append((t0 - q) * 1e3)
        mapping.append((t1 - t0) * 1e3)
    # The daemon's own share of each latency sample: the sample minus the frame stamp -> queue part
    # of its frame. The frame is found from the sample itself: its stamp is the probe's clock
    # reading at the sample minus the latency (speed-up 1, the benchmark's), less the moment
    # between the daemon's clock reading and the probe's (>= 0; frames are 33 ms apart).
    stamps = np.array(sorted(put))
    own = []
    for t, v, now in logs.get("frame_to_setpoint_ms", []):
        if t < t_from or not len(stamps):
            continue
        ts = now - v / 1e3
        j = int(np.searchsorted(stamps, ts + 1e-6, side="right")) - 1
        if j >= 0 and ts - stamps[j] < 0.01:
            own.append(v - (put[stamps[j]] - stamps[j]) * 1e3)
    out["queue_to_setpoint_ms"] = summary(own)
    out["late_ticks"] = late_ticks(logs, t_from)
    out["parts_ms"] = {"capture_to_queue": summary(cap), "queue_wait": summary(wait), "map_step_and_insert": summary(mapping),
                       "render_in_daemon": summary([v for t, v in logs.get("render", []) if t >= t_from])}
    if cap and out["frame_to_setpoint_ms"]["n"]:
        out["parts_ms"]["rest_to_setpoint_p50"] = out["frame_to_setpoint_ms"]["median"] - float(
            np.median(cap) + np.median(wait) + np.median(mapping))
    return out


def late_ticks(logs: dict, t_from: float, threshold_ms: float = 3.0) -> dict:
    """Control ticks later than ``threshold_ms`` and how many of them overlap a mapper step (the
    tick was due at ``t - lateness``; the step ran over ``[end - duration, end]``), against the
    chance of that: the share of the time a mapper step (widened by the mean lateness) is running."""
    steps = sorted((t - (t1 - t0), t) for t, _, t0, t1 in logs.get("map", []) if t >= t_from)
    late = [(t, v) for t, v, *_ in logs.get("jitter_ms", []) if t >= t_from and v > threshold_ms]
    if not steps or not late:
        return {"threshold_ms": threshold_ms, "n": len(late)}
    starts = [a for a, _ in steps]
    during = 0
    for t, v in late:
        due = t - v / 1e3
        i = bisect.bisect_right(starts, t) - 1
        if i >= 0 and steps[i][1] >= due:
            during += 1
    span = steps[-1][1] - steps[0][0]
    mean_late = sum(v for _, v in late) / len(late) / 1e3
    busy = sum(b - a + mean_late for a, b in steps) / span
    return {"threshold_ms": threshold_ms, "n": len(late), "during_mapper_step": during,
            "chance_fraction": round(min(1.0, busy), 3)}


def _wait_listener(endpoint: str, timeout_s: float) -> StatusListener | None:
    """A client session once the daemon's Zenoh peer listens (it takes a moment to start)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            return StatusListener(endpoint)
        except Exception:  # noqa: BLE001 - not listening yet
            time.sleep(0.5)
    return None


if __name__ == "__main__":
    print(json.dumps(run_daemon_benchmark(float(sys.argv[1]) if len(sys.argv) > 1 else 20.0), indent=1))
