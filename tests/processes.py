"""Helpers for tests that run the service's processes on loopback (no pytest fixtures here)."""

from __future__ import annotations

import json
import os
import queue
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port that was free a moment ago on 127.0.0.1 (ephemeral, so tests can run side by side)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def companion(*args: str, env: dict | None = None, log: Path | None = None) -> subprocess.Popen:
    """Start ``companion ARGS`` as a real process; stderr goes to ``log`` (or is discarded)."""
    full_env = {**os.environ, **(env or {})}
    stderr = open(log, "w") if log else subprocess.DEVNULL  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", "companion.cli", *args], stdout=subprocess.PIPE,
                            stderr=stderr, env=full_env, text=True)


def read_line_starting(proc: subprocess.Popen, prefix: str, timeout_s: float) -> str:
    """The first stdout line of ``proc`` starting with ``prefix`` (bounded wait)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                break
            if line.startswith(prefix):
                return line.strip()
    raise TimeoutError(f"no line starting with {prefix!r} within {timeout_s} s")


def stop(proc: subprocess.Popen, timeout_s: float = 5.0, sig=signal.SIGTERM) -> int | None:
    """Signal a process and wait for it (bounded); SIGKILL if it does not end."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return proc.returncode


class ZenohListener:
    """A plain Zenoh session that collects the JSON and tile samples a vehicle publishes. ``tiles``
    holds each tile as the samples make it (a whole tile, or a delta applied to the one held);
    ``missing_base`` counts deltas that found no base (the session connected after the tile's
    first publication), ``missing`` holds their keys until :meth:`complete` asks for them whole."""

    def __init__(self, endpoint: str, vehicle: str = "vehicle1"):
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.status: queue.Queue = queue.Queue()
        self.avoidance: queue.Queue = queue.Queue()
        self.tiles: dict[str, object] = {}  # key -> companion.method.terrain.tile.Tile
        self.missing_base = 0
        self.missing: set[str] = set()
        root = f"companion/{vehicle}"
        self._subs = [
            self.session.declare_subscriber(f"{root}/status", lambda s: self.status.put(json.loads(s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{root}/avoidance", lambda s: self.avoidance.put(json.loads(s.payload.to_bytes()))),
            self.session.declare_subscriber(f"{root}/terrain/tile/*/*", self._on_tile),
        ]

    def _on_tile(self, sample) -> None:
        from companion.method.terrain.codec import MissingBase, apply_update

        key = str(sample.key_expr)
        try:
            self.tiles[key] = apply_update(self.tiles.get(key), sample.payload.to_bytes())
        except MissingBase:
            self.missing_base += 1
            self.missing.add(key)
        else:
            self.missing.discard(key)

    def complete(self, timeout_s: float = 5.0) -> int:
        """Ask the vehicle for each tile in ``missing`` whole (as a ground station does); returns
        how many arrived."""
        from companion.method.terrain.codec import apply_update

        got = 0
        for key in sorted(self.missing):
            for reply in self.session.get(key, timeout=timeout_s):
                if reply.ok is not None:
                    self.tiles[key] = apply_update(None, reply.ok.payload.to_bytes())
                    self.missing.discard(key)
                    got += 1
        return got

    def wait_status(self, predicate, timeout_s: float) -> dict:
        """The first status message satisfying ``predicate`` (bounded wait)."""
        deadline = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < deadline:
            try:
                last = self.status.get(timeout=0.5)
            except queue.Empty:
                continue
            if predicate(last):
                return last
        raise TimeoutError(f"no matching status within {timeout_s} s; last: {json.dumps(last)[:2000] if last else None}")

    def latest_status(self, timeout_s: float = 5.0) -> dict:
        """The newest status received (waits for one if none is queued)."""
        last = self.status.get(timeout=timeout_s)
        while not self.status.empty():
            last = self.status.get_nowait()
        return last

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()


def poll_until(station, predicate, timeout_s: float = 5.0) -> bool:
    """Poll a ground station (``station.poll()``) until ``predicate()`` holds; False after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        station.poll()
        if predicate():
            return True
        time.sleep(0.02)
    return False
