"""``companion router``: a Zenoh router for a fleet (docs/zenoh.md, "A fleet through a router").

Vehicles and ground stations connect to it (``zenoh.mode: client`` or ``peer`` with
``zenoh.connect`` set to the router's endpoint) instead of to each other: a vehicle publishes
once, the router forwards to every subscriber, and a ground station anywhere the router is
reachable sees the whole fleet. It is a Zenoh session in router mode, the same routing engine as
Eclipse Zenoh's ``zenohd`` (which can take its place where it is installed; the keys and payloads
do not change).

Once a ``--summary-every`` interval it prints one line: the sessions connected and the router's
own CPU time and memory (what a fleet costs the machine it runs on).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time

import zenoh

from drivers.zenoh_bus import BusError


def process_usage(pid: int | None = None) -> tuple[float, int]:
    """CPU time (s, user + system) and resident memory (bytes) of a process (Linux ``/proc``)."""
    pid = os.getpid() if pid is None else pid
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    cpu_s = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14 and 15 of stat)
    rss = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024
                break
    return cpu_s, rss


def router_config(listen: list[str], config_file: str | None = None) -> zenoh.Config:
    try:
        cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps("router"))
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        cfg.insert_json5("scouting/multicast/enabled", "false")
    except zenoh.ZError as exc:
        raise BusError(f"zenoh router configuration: {exc}") from None
    return cfg


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable; default tcp/[::]:7447, every interface, as zenohd)")
    p.add_argument("--zenoh-config", metavar="JSON5", help="Zenoh config file (TLS, access control) under these settings")
    p.add_argument("--summary-every", type=float, default=10.0, metavar="S", help="0 = no summary lines")
    p.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0 = until SIGTERM/Ctrl-C)")


def main(args: argparse.Namespace) -> int:
    for name in ("summary_every", "duration"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0):
            print(f"companion router: --{name.replace('_', '-')} must be a finite number >= 0", file=sys.stderr)
            return 2
    listen = args.listen or ["tcp/[::]:7447"]
    try:
        session = zenoh.open(router_config(listen, args.zenoh_config))
    except (BusError, zenoh.ZError) as exc:
        print(f"companion router: cannot start on {', '.join(listen)}: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(f"companion router: listening on {', '.join(listen)} (zid {session.zid()})", flush=True)
    start = time.monotonic()
    cpu0, _ = process_usage()
    next_summary = start + args.summary_every if args.summary_every > 0 else math.inf
    try:
        while not stop.is_set():
            now = time.monotonic()
            if args.duration and now - start >= args.duration:
                break
            if now >= next_summary:
                cpu, rss = process_usage()
                links = list(session.info.links()) if hasattr(session.info, "links") else []
                print(f"[{now - start:7.1f} s] {len(links)} sessions connected; router CPU {100 * (cpu - cpu0) / (now - start):.1f} % "
                      f"of a core since start, memory {rss / 1e6:.1f} MB", flush=True)
                next_summary = now + args.summary_every
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0
