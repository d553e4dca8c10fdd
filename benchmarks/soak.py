"""Soak: the daemon flying the circuit for a long accelerated run, its memory, file descriptors and
threads sampled over time.

``python -m benchmarks.soak --minutes 10 [--speedup 20] [--every 10] [--json out.json]``

Three processes, as a user would run them (the same set-up as :mod:`benchmarks.daemon_bench`):

1. ``companion sim`` (ArduPilot flavour, default scenario) at ``--speedup``;
2. the pilot (a thread here, plain pymavlink): GUIDED, arm, take off, then GCS heartbeats;
3. ``companion run`` with ``config/sitl.yaml`` at the same speed-up: it commands the circuit lap
   after lap, maps with the synthetic camera, publishes on Zenoh (a status subscriber listens, so
   the publications really go out), and snapshots the map every ``snapshot_interval_s``.

Every ``--every`` wall seconds the daemon's resident memory (``VmRSS``) and thread count
(``/proc/PID/status``) and its open file descriptors (``/proc/PID/fd``) are read, together with
the daemon's own status (uptime on the companion clock, laps, frames mapped, map size, snapshots
written). The table ends with the least-squares slope of each figure per wall minute and per
simulated hour over the samples after ``--warmup`` wall seconds (the first lap maps new ground,
so the map, and with it the memory, legitimately grows until the circuit is covered).

Speed-up: the simulator and the daemon run on one simulated clock at ``--speedup`` times the wall
clock; rates are simulated (15 Hz camera, 20 Hz control), so the CPU cannot follow every frame at
a high speed-up: the frame queue drops the oldest frames (counted in the status), which is what the
daemon does on a slow computer. The run reports how many simulated hours it covered.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
FIGURES = ("rss_mb", "fds", "threads")


@dataclass(frozen=True, slots=True)
class Sample:
    """One look at the daemon: /proc figures and what its status said at that time."""

    wall_s: float  # since the pilot reported the vehicle airborne
    sim_s: float  # the daemon's uptime, companion clock
    rss_mb: float
    fds: int
    threads: int
    lap: int
    frames_mapped: int
    frames_dropped: int
    tiles: int
    cells: int
    map_mb: float
    snapshots: int
    command: str


def proc_figures(pid: int) -> tuple[float, int, int]:
    """(resident set in MB, open file descriptors, threads) of process ``pid`` (Linux /proc)."""
    rss_kb = threads = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss_kb = int(line.split()[1])
            elif line.startswith("Threads:"):
                threads = int(line.split()[1])
    return rss_kb / 1024.0, len(os.listdir(f"/proc/{pid}/fd")), threads


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope dy/dx (0 with fewer than two distinct x)."""
    n = len(xs)
    if n < 2:
        return 0.0
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    if sxx == 0:
        return 0.0
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx


def trends(samples: list[Sample], warmup_s: float) -> dict:
    """Per figure: slope per wall minute and per simulated hour after the warm-up, and the range."""
    steady = [s for s in samples if s.wall_s >= warmup_s]
    out = {"warmup_s": warmup_s, "samples": len(steady)}
    for name in FIGURES + ("tiles", "map_mb"):
        ys = [float(getattr(s, name)) for s in steady]
        if not ys:
            continue
        out[name] = {
            "per_wall_min": round(slope([s.wall_s / 60.0 for s in steady], ys), 4),
            "per_sim_hour": round(slope([s.sim_s / 3600.0 for s in steady], ys), 4),
            "first": ys[0], "last": ys[-1], "min": min(ys), "max": max(ys),
        }
    return out


def soak_config(sim_port: int, zenoh_port: int, directory: str, speedup: float) -> dict:
    with open(REPO / "config" / "sitl.yaml") as f:
        cfg = yaml.safe_load(f)
    cfg.setdefault("link", {})["connection"] = f"tcp:127.0.0.1:{sim_port}"
    cfg.setdefault("zenoh", {}).update(listen=[f"tcp/127.0.0.1:{zenoh_port}"], status_rate_hz=1.0,
                                      multicast_scouting=False, mode="peer")
    cfg.setdefault("persistence", {}).update(directory=directory, snapshot_interval_s=10.0)
    cfg.setdefault("sim", {})["speedup"] = float(speedup)
    return cfg


def run_soak(minutes: float, speedup: float = 20.0, every_s: float = 10.0, warmup_s: float = 30.0,
             log=print, start_lap: int = 0, start_timeout_s: float = 180.0) -> dict:
    """Fly for ``minutes`` wall minutes after take-off; returns the samples, the trends and what
    went wrong (``error``), if anything. With ``start_lap`` the minutes count from the first sample
    on that lap (the laps before map new ground, so memory grows with the map), and the trends
    from there (``steady_from_s``); ``start_timeout_s`` bounds the wait for it."""
    from benchmarks.daemon_bench import Pilot, _wait, _wait_listener, free_port, stop_process
    from drivers.sim.harness import MavClient, SimVehicleProcess

    result: dict = {"minutes": minutes, "speedup": speedup, "every_s": every_s, "error": "", "samples": []}
    tmp = tempfile.TemporaryDirectory(prefix="companion-soak-")
    pilot_client = MavClient.udp_listener()
    sim = SimVehicleProcess(["--flavour", "ardupilot", "--scenario", "default", "--tcp-listen", "127.0.0.1:0",
                             "--udp-out", f"127.0.0.1:{pilot_client.port}", "--speedup", str(speedup),
                             "--origin-delay", "0.5", "--log-level", "WARNING"],
                            stderr_path=os.path.join(tmp.name, "sim.log"))
    daemon = listener = pilot = None
    daemon_log = os.path.join(tmp.name, "daemon.log")
    samples: list[Sample] = []
    try:
        sim.start()
        zenoh_port = free_port()
        cfg = soak_config(sim.endpoints["tcp"], zenoh_port, os.path.join(tmp.name, "map"), speedup)
        cfg_path = os.path.join(tmp.name, "soak.yaml")
        with open(cfg_path, "w") as f:
            yaml.safe_dump(cfg, f)
        pilot = Pilot(pilot_client, float(cfg.get("avoidance", {}).get("nominal_alt_m", 15.0)))
        pilot.start()
        with open(daemon_log, "w") as err:
            daemon = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "--config", cfg_path,
                                       "--log-level", "WARNING"], stdout=subprocess.DEVNULL, stderr=err, cwd=str(REPO))
        listener = _wait_listener(f"tcp/127.0.0.1:{zenoh_port}", 30.0)
        if listener is None:
            raise RuntimeError("no Zenoh session with the daemon")
        if not pilot.airborne.wait(60.0):
            raise RuntimeError(pilot.error or f"vehicle not airborne (altitude {pilot.altitude_m:.1f} m)")
        if not _wait(lambda: listener.get() is not None, 20.0):
            raise RuntimeError("no status from the daemon")
        t0 = time.monotonic()
        end = t0 + minutes * 60.0 if start_lap <= 0 else t0 + start_timeout_s
        started = start_lap <= 0
        next_t = t0
        log(f"soak: {minutes:g} min at speed-up {speedup:g}, a sample every {every_s:g} s")
        log(f"{'wall s':>7} {'sim h':>6} {'RSS MB':>7} {'fds':>4} {'thr':>4} {'lap':>4} {'frames':>7} "
            f"{'dropped':>8} {'tiles':>6} {'map MB':>7} {'snaps':>6}  command")
        while True:
            now = time.monotonic()
            if daemon.poll() is not None:
                raise RuntimeError(f"the daemon exited with status {daemon.returncode}")
            if now >= next_t:
                status = listener.get() or {}
                rss, fds, threads = proc_figures(daemon.pid)
                m = status.get("map", {})
                s = Sample(
                    wall_s=round(now - t0, 1), sim_s=float(status.get("uptime_s", 0.0)), rss_mb=round(rss, 1),
                    fds=fds, threads=threads, lap=int(status.get("control", {}).get("lap", 0)),
                    frames_mapped=int(status.get("mapper", {}).get("frames_mapped", 0)),
                    frames_dropped=int(status.get("camera", {}).get("queue_dropped", 0)),
                    tiles=int(m.get("tiles", 0)), cells=int(m.get("cells", 0)),
                    map_mb=round(m.get("memory_bytes", 0) / 1e6, 2),
                    snapshots=int(status.get("snapshots", {}).get("written", 0)),
                    command=str(status.get("command", ""))[:40],
                )
                samples.append(s)
                log(f"{s.wall_s:7.0f} {s.sim_s / 3600:6.2f} {s.rss_mb:7.1f} {s.fds:4d} {s.threads:4d} {s.lap:4d} "
                    f"{s.frames_mapped:7d} {s.frames_dropped:8d} {s.tiles:6d} {s.map_mb:7.2f} {s.snapshots:6d}  {s.command}")
                next_t += every_s
                if not started and s.lap >= start_lap:
                    started, end = True, now + minutes * 60.0
                    result["steady_from_s"] = s.wall_s
            if now >= end:
                if not started:
                    raise RuntimeError(f"the daemon did not reach lap {start_lap} in {start_timeout_s:g} s")
                break
            time.sleep(max(0.0, min(next_t, end) - time.monotonic()))
    except Exception as exc:  # noqa: BLE001 - reported with the samples taken so far
        result["error"] = str(exc)
    finally:
        if pilot is not None:
            pilot.stop.set()
        if daemon is not None:
            result["daemon_exit"] = stop_process(daemon)
        if listener is not None:
            listener.close()
        sim.stop()
        pilot_client.close()
        if pilot is not None:
            pilot.join(2.0)
        if result["error"] or result.get("daemon_exit") not in (0, None):
            try:
                with open(daemon_log) as f:
                    result["daemon_log_tail"] = f.read()[-3000:]
            except OSError:
                pass
        tmp.cleanup()
    result["samples"] = [asdict(s) for s in samples]
    result["trends"] = trends(samples, max(warmup_s, result.get("steady_from_s", 0.0)))
    if samples:
        result["simulated_hours"] = round(samples[-1].sim_s / 3600.0, 2)
    return result


def print_trends(result: dict, log=print) -> None:
    t = result["trends"]
    log(f"\nafter {t['warmup_s']:g} s of warm-up ({t['samples']} samples; "
        f"{result.get('simulated_hours', 0):g} simulated hours in all):")
    log(f"{'figure':>8} {'first':>8} {'last':>8} {'min':>8} {'max':>8} {'/wall min':>10} {'/sim hour':>10}")
    for name in FIGURES + ("tiles", "map_mb"):
        if name in t:
            f = t[name]
            log(f"{name:>8} {f['first']:8.1f} {f['last']:8.1f} {f['min']:8.1f} {f['max']:8.1f} "
                f"{f['per_wall_min']:10.3f} {f['per_sim_hour']:10.3f}")
    if result["error"]:
        log(f"error: {result['error']}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0, help="wall minutes of flight after take-off")
    p.add_argument("--speedup", type=float, default=20.0, help="simulated seconds per wall second")
    p.add_argument("--every", type=float, default=10.0, help="wall seconds between samples")
    p.add_argument("--warmup", type=float, default=60.0, help="wall seconds left out of the slopes")
    p.add_argument("--json", help="write the samples and trends here")
    args = p.parse_args(argv)
    if args.minutes <= 0 or args.every <= 0 or args.speedup <= 0:
        p.error("--minutes, --every and --speedup must be positive")
    result = run_soak(args.minutes, args.speedup, args.every, args.warmup)
    print_trends(result)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 1 if result["error"] else 0


if __name__ == "__main__":
    sys.exit(main())
