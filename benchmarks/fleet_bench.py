"""``python -m benchmarks.fleet_bench``: a fleet through one Zenoh router on loopback.

``companion router`` runs as its own process. N vehicles each open a client session to it and
publish as the service does (a ``ZenohBus`` per vehicle: deflated tiles of a partly mapped
terrain at the rate the demo measured, status at 1 Hz, avoidance at 5 Hz); two ground stations
subscribe, through the same router, to every vehicle's tiles (``companion/*/terrain/tile/**``)
and decode each. For each N it reports tile delivery latency (Zenoh timestamp at publication ->
the subscriber's callback, p50 and p99 over both stations), loss (tiles published x stations -
tiles received; reliable delivery, must be 0), and the router's CPU (share of one core) and
memory (resident). Nothing here asserts; tests/test_zenoh_fleet.py asserts no loss for five
vehicles and two stations.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh

from companion.config import ZenohConfig
from companion.method.terrain.codec import decode_tile, encode_tile
from companion.method.terrain.tile import Tile
from drivers.zenoh_bus import ZenohBus, zenoh_config
from drivers.zenoh_router import process_usage

TILE_CELLS = 32
TILES_PER_S = 4.0        # per vehicle: what the demo's vehicle publishes with zenoh.tile_interval_s 1 s
STATUS_HZ, AVOIDANCE_HZ = 1.0, 5.0
KNOWN_FRACTION = 0.4     # cells of a published tile holding evidence (the demo's map: 0.1-0.6)


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def synthetic_tile(rng: np.random.Generator, tx: int, ty: int) -> Tile:
    """A partly mapped tile: ground heights with 0.5 m noise and a few raised cells."""
    t = TILE_CELLS
    known = rng.random((t, t)) < KNOWN_FRACTION
    h = (rng.normal(0.0, 0.5, (t, t)) + np.where(rng.random((t, t)) < 0.02, 8.0, 0.0)).astype(np.float32)
    v = rng.uniform(0.05, 1.0, (t, t)).astype(np.float32)
    n = rng.integers(1, 20, (t, t)).astype(np.uint32)
    return Tile(tx, ty, np.where(known, h, np.nan).astype(np.float32), np.where(known, v, np.inf).astype(np.float32),
                np.where(known, n, 0).astype(np.uint32), cell_size_m=1.0)


@dataclass
class Station:
    """A ground-station session on every vehicle's tiles: (vehicle, tile key, stamp) -> latency."""

    endpoint: str
    received: dict = field(default_factory=dict)
    bad: int = 0

    def open(self) -> "Station":
        cfg = zenoh_config(ZenohConfig(mode="client", connect=(self.endpoint,)))
        self._session = zenoh.open(cfg)
        self._lock = threading.Lock()
        self._sub = self._session.declare_subscriber("companion/*/terrain/tile/**", self._on)
        return self

    def _on(self, sample) -> None:
        now_ns = time.time_ns()
        key = str(sample.key_expr)
        stamp = sample.timestamp.get_time_as_ntp64().as_nanos() if sample.timestamp is not None else None
        try:
            decode_tile(sample.payload.to_bytes())
        except ValueError:
            with self._lock:
                self.bad += 1
            return
        with self._lock:
            self.received[(key, stamp)] = (now_ns - stamp) / 1e6 if stamp is not None else float("nan")

    def close(self) -> None:
        self._sub.undeclare()
        self._session.close()


def vehicle_loop(bus: ZenohBus, index: int, duration_s: float, published: list, stop: threading.Event) -> None:
    """Publish like the service: tiles at TILES_PER_S (round-robin over a few tiles), status, avoidance."""
    rng = np.random.default_rng(index)
    payloads = [encode_tile(synthetic_tile(rng, index, k), deflate=True) for k in range(8)]
    t0 = time.monotonic()
    k = 0
    next_tile = next_status = next_avoid = t0
    while not stop.is_set():
        now = time.monotonic()
        if now - t0 >= duration_s:
            break
        if now >= next_tile:
            bus.publish_tile(index, k % len(payloads), payloads[k % len(payloads)])
            published.append(len(payloads[k % len(payloads)]))
            k += 1
            next_tile += 1.0 / TILES_PER_S
        if now >= next_status:
            bus.publish_status({"health": "ok", "state": "mapping"})
            next_status += 1.0 / STATUS_HZ
        if now >= next_avoid:
            bus.publish_avoidance({"engaged": False, "mode": "advisory", "climb_rate_mps": 0.0, "restriction_alt_m": None,
                                   "limiting_cell": None, "position_ned_m": [float(k), 0.0, -15.0]})
            next_avoid += 1.0 / AVOIDANCE_HZ
        time.sleep(max(0.0, min(next_tile, next_status, next_avoid) - time.monotonic()))


def run_fleet(n_vehicles: int, duration_s: float, router_endpoint: str, router_pid: int | None, stations: int = 2) -> dict:
    """One measurement (module docstring) against a running router."""
    subs = [Station(router_endpoint).open() for _ in range(stations)]
    buses = [ZenohBus(ZenohConfig(mode="client", connect=(router_endpoint,), vehicle_name=f"vehicle{k + 1}")) for k in range(n_vehicles)]
    for b in buses:
        b.open()
    time.sleep(0.5)  # subscriptions propagated through the router
    published: list[list[int]] = [[] for _ in buses]
    stop = threading.Event()
    cpu0, _ = process_usage(router_pid) if router_pid else (0.0, 0)
    wall0 = time.monotonic()
    threads = [threading.Thread(target=vehicle_loop, args=(b, k + 1, duration_s, published[k], stop)) for k, b in enumerate(buses)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    sent = sum(len(p) for p in published)
    deadline = time.monotonic() + 5.0  # delivery of what is in flight: wait for it, bounded
    while time.monotonic() < deadline and any(len(s.received) < sent for s in subs):
        time.sleep(0.05)
    wall = time.monotonic() - wall0
    cpu1, rss = process_usage(router_pid) if router_pid else (0.0, 0)
    for b in buses:
        b.close()
    latencies = np.array([v for s in subs for v in s.received.values()], float)
    vehicles_seen = [len({key.split("/")[1] for key, _ in s.received}) for s in subs]
    for s in subs:
        s.close()
    return {
        "vehicles": n_vehicles, "stations": stations, "seconds": round(duration_s, 1),
        "tiles_published": sent, "tiles_received": int(sum(len(s.received) for s in subs)),
        "loss": int(sent * stations - sum(len(s.received) for s in subs)), "bad": int(sum(s.bad for s in subs)),
        "vehicles_seen": vehicles_seen,
        "latency_p50_ms": float(np.percentile(latencies, 50)) if latencies.size else None,
        "latency_p99_ms": float(np.percentile(latencies, 99)) if latencies.size else None,
        "tile_bytes_mean": float(np.mean([x for p in published for x in p])) if sent else 0.0,
        "router_cpu_percent": round(100.0 * (cpu1 - cpu0) / wall, 1) if router_pid else None,
        "router_rss_mb": round(rss / 1e6, 1) if router_pid else None,
    }


class Router:
    """``companion router`` as its own process on a loopback port."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "router", "--listen", self.endpoint,
                                      "--summary-every", "0"], stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        if "listening" not in line:
            self.proc.kill()
            raise RuntimeError(f"companion router did not start: {line!r}")

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.fleet_bench", description=__doc__.splitlines()[0])
    p.add_argument("--vehicles", type=int, nargs="+", default=[1, 2, 5, 8])
    p.add_argument("--seconds", type=float, default=10.0)
    args = p.parse_args(argv)
    rows = []
    for n in args.vehicles:
        router = Router()  # a fresh router for each fleet size: its memory is that fleet's
        try:
            rows.append(run_fleet(n, args.seconds, router.endpoint, router.proc.pid))
        finally:
            router.close()
        r = rows[-1]
        print(f"{n:3d} vehicles, 2 stations: {r['tiles_published']} tiles published, {r['tiles_received']} received, "
              f"loss {r['loss']}, latency p50 {r['latency_p50_ms']:.2f} ms p99 {r['latency_p99_ms']:.2f} ms, "
              f"router CPU {r['router_cpu_percent']} % of a core, memory {r['router_rss_mb']} MB", flush=True)
    print("\n| vehicles | tiles published | loss | latency p50 (ms) | latency p99 (ms) | router CPU (% of a core) | router memory (MB) |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['vehicles']} | {r['tiles_published']} | {r['loss']} | {r['latency_p50_ms']:.2f} | {r['latency_p99_ms']:.2f} | "
              f"{r['router_cpu_percent']} | {r['router_rss_mb']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
