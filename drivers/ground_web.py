"""``companion ground --http HOST:PORT``: the ground station's map, live in a browser.

A small HTTP server (the standard library's, one thread per connection) beside the ground station:

* ``GET /`` - the page (``drivers/ground_web_page.html``: one file, no asset from the internet, so
  it works on a field laptop or a phone with no connection but the vehicle's);
* ``GET /events`` - a Server-Sent Events stream: on connect every vehicle's frame, latest status
  and avoidance state, the whole map and the tracks, then every change as the ground station
  applies it (``frame``, ``tile``, ``status``, ``avoidance``, ``track`` events; the browser's
  EventSource reconnects by itself and gets the whole map again);
* ``GET /state.json`` - the same snapshot as one JSON document (for scripts).

Event data (JSON): a tile is ``{"vehicle", "tx", "ty", "cells", "cell_m", "height"}`` with
``height`` the tile's ``cells x cells`` heights as little-endian float32 in base64, row-major
``[i north][j east]``, NaN where the cell holds no evidence (docs/zenoh.md, "Tile payload"); a
status or avoidance event is the vehicle's JSON document as received (with ``vehicle``). The
track is the avoidance messages' ``position_ned_m`` (one point per 0.5 m moved, the last 5,000).
Each vehicle maps in its own local frame; a ``frame`` event says where its origin lies in the
page's frame, the first vehicle's (:meth:`LiveFeed._place`).

Threads: the ground station applies samples on its own thread and hands the changes to
:class:`LiveFeed` (:meth:`LiveFeed.update_from`); each HTTP connection reads its own bounded
queue. A browser too slow to keep up is disconnected (counted) and comes back with a fresh
snapshot, so a stalled page never holds the ground station up.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import queue
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np

from companion.method.geodesy import LocalFrame
from drivers.zenoh_bus import map_frame_shift

log = logging.getLogger("companion.ground.web")

PAGE = Path(__file__).with_name("ground_web_page.html")
CLIENT_QUEUE = 4096        # events a browser may be behind before it is dropped (it reconnects)
KEEPALIVE_S = 10.0         # an SSE comment this often keeps proxies and the browser's timer happy
TRACK_MAX = 5000           # track points kept
TRACK_STEP_M = 0.5         # a new track point once the vehicle moved this far


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8080`` for IPv6) -> (host, port); ValueError saying what is expected."""
    host, _, port = str(text).rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host.strip("[]"), int(port)


def tile_event(vehicle: str, tile) -> dict[str, Any]:
    """A tile as the page reads it (module docstring)."""
    height = np.where(tile.count > 0, tile.height, np.nan).astype("<f4")
    return {"vehicle": vehicle, "tx": int(tile.tx), "ty": int(tile.ty), "cells": int(tile.tile_cells),
            "cell_m": float(tile.cell_size_m), "height": base64.b64encode(height.tobytes()).decode("ascii")}


def _sse(event: str, data: Any) -> bytes:
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'), allow_nan=False)}\n\n".encode()


class LiveFeed:
    """What the page shows, kept for new browsers, and fanned out to the connected ones: every
    vehicle's tiles, status, avoidance state and track, and where its local frame lies in the
    page's frame (:meth:`_place`)."""

    def __init__(self, name: str = "ground") -> None:
        self.name = name
        self._lock = threading.Lock()
        self._order: list[str] = []                               # vehicles in the order first seen
        self._tiles: dict[tuple[str, int, int], bytes] = {}
        self._state: dict[tuple[str, str], bytes] = {}            # (vehicle, "status" | "avoidance" | "frame")
        self._track: dict[str, list[list[float]]] = {}
        self._frames: dict[str, Any] = {}                          # vehicle -> (LocalFrame or None, map shift m)
        self._offsets: dict[str, list[float] | None] = {}
        self._clients: set[queue.Queue] = set()
        self.counts = {"events": 0, "clients": 0, "clients_dropped": 0}

    # ---- from the ground station's thread ----------------------------------------------------

    def update_from(self, gmap) -> int:
        """Hand over what changed in a :class:`drivers.ground_station.GroundMap`; returns events sent."""
        vehicle = gmap.keys.vehicle
        tiles, status, avoidance = gmap.take_changes()
        n = 0
        if vehicle not in self._order:
            self._order.append(vehicle)
            n += self._place()
        for index in sorted(tiles):
            n += self._publish(_sse("tile", tile_event(vehicle, gmap.tiles[index])), tile=(vehicle, *index))
        if status and gmap.status is not None:
            n += self._publish(_sse("status", {"vehicle": vehicle, **_finite(gmap.status)}), state=(vehicle, "status"))
            frame = (LocalFrame.from_status(gmap.status), map_frame_shift(gmap.status))
            if frame != self._frames.get(vehicle):
                self._frames[vehicle] = frame
                n += self._place()
        if avoidance and gmap.avoidance is not None:
            n += self._publish(_sse("avoidance", {"vehicle": vehicle, **_finite(gmap.avoidance)}), state=(vehicle, "avoidance"))
            n += self._track_point(vehicle, gmap.avoidance.get("position_ned_m"))
        return n

    def _place(self) -> int:
        """Where each vehicle's local frame lies in the page's frame (the first vehicle's): the
        offset (north, east, up; m) of its origin, from both origins (``frame`` in the status,
        companion/method/geodesy.py). The page draws a vehicle's tiles, track and position shifted by
        it: a translation, exact at the origins and within centimetres over a few kilometres (the
        two tangent planes turn by distance / Earth radius). None (not drawn) until both origins
        are known; the first vehicle is at zero whatever its origin. ``up`` raises the vehicle's
        tile heights only, and includes its map's shift (``map.frame_shift_m`` in its status: its
        tiles are in its map's own frame), so every vehicle's tiles are drawn in the first
        vehicle's navigation frame of the moment. Publishes what changed."""
        from companion.method.geodesy import place_cells

        ref = self._order[0]
        ref_frame = self._frames.get(ref, (None, 0.0))[0]
        n = 0
        for vehicle in self._order:
            frame, shift = self._frames.get(vehicle, (None, 0.0))
            if vehicle == ref:
                offset = [0.0, 0.0, round(shift, 3)]
            elif frame is None or ref_frame is None:
                offset = None
            else:
                north, east, up = place_cells(np.zeros(1), np.zeros(1), np.zeros(1), frame, ref_frame)
                offset = [round(float(north[0]), 3), round(float(east[0]), 3), round(float(up[0]) + shift, 3)]
            if vehicle not in self._offsets or self._offsets[vehicle] != offset:
                self._offsets[vehicle] = offset
                n += self._publish(_sse("frame", {"vehicle": vehicle, "offset_m": offset, "reference": ref}), state=(vehicle, "frame"))
        return n

    def _track_point(self, vehicle: str, position: Any) -> int:
        try:
            north, east = float(position[0]), float(position[1])
        except (TypeError, ValueError, IndexError):
            return 0
        if not (math.isfinite(north) and math.isfinite(east)):
            return 0
        track = self._track.setdefault(vehicle, [])
        if track and math.hypot(north - track[-1][0], east - track[-1][1]) < TRACK_STEP_M:
            return 0
        point = [round(north, 2), round(east, 2)]
        with self._lock:
            track.append(point)
            del track[:-TRACK_MAX]
        return self._publish(_sse("track", {"vehicle": vehicle, "points": [point]}))

    def _publish(self, event: bytes, tile: tuple[str, int, int] | None = None, state: tuple[str, str] | None = None) -> int:
        with self._lock:
            if tile is not None:
                self._tiles[tile] = event
            if state is not None:
                self._state[state] = event
            self.counts["events"] += 1
            for q in list(self._clients):
                try:
                    q.put_nowait(event)
                except queue.Full:  # a stalled browser: drop it, it reconnects with a snapshot
                    self._clients.discard(q)
                    self.counts["clients_dropped"] += 1
        return 1

    # ---- from the HTTP threads ---------------------------------------------------------------

    def subscribe(self) -> tuple[queue.Queue, list[bytes]]:
        """A new browser: its queue, and the snapshot to send first (hello; each vehicle's frame,
        status and avoidance; the tiles; the tracks)."""
        q: queue.Queue = queue.Queue(CLIENT_QUEUE)
        with self._lock:
            hello = _sse("hello", {"station": self.name, "vehicles": list(self._order), "tiles": len(self._tiles)})
            states = [self._state[(v, k)] for v in self._order for k in ("frame", "status", "avoidance") if (v, k) in self._state]
            tracks = [_sse("track", {"vehicle": v, "points": list(t), "reset": True}) for v, t in self._track.items()]
            snapshot = [hello, *states, *self._tiles.values(), *tracks]
            self._clients.add(q)
            self.counts["clients"] += 1
        return q, snapshot

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            self._clients.discard(q)

    def connected(self, q: queue.Queue) -> bool:
        with self._lock:
            return q in self._clients

    def state(self) -> dict[str, Any]:
        """The snapshot as one JSON-ready document (``/state.json``)."""
        def data(event: bytes | None):
            return None if event is None else json.loads(event.decode().split("data: ", 1)[1])

        with self._lock:
            return {"station": self.name, "vehicles": {
                        v: {"status": data(self._state.get((v, "status"))), "avoidance": data(self._state.get((v, "avoidance"))),
                            "offset_m": self._offsets.get(v), "track": list(self._track.get(v, []))} for v in self._order},
                    "tiles": [data(e) for e in self._tiles.values()],
                    "counts": dict(self.counts), "browsers": len(self._clients)}


def _finite(doc: Any) -> Any:
    """JSON has no NaN: non-finite numbers become null (the vehicle already sends them so)."""
    if isinstance(doc, dict):
        return {k: _finite(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_finite(v) for v in doc]
    if isinstance(doc, float) and not math.isfinite(doc):
        return None
    return doc


class MapWebServer:
    """The HTTP server of the page (module docstring); ``start`` binds and serves on a thread."""

    def __init__(self, feed: LiveFeed, host: str = "127.0.0.1", port: int = 8080) -> None:
        self.feed = feed
        self._stop = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, fmt: str, *args: Any) -> None:  # the station's own log, not stderr
                log.debug("%s %s", self.address_string(), fmt % args)

            def do_GET(self) -> None:  # noqa: N802 - the standard library's name
                path = self.path.split("?", 1)[0]
                if path in ("/", "/index.html"):
                    self._send(HTTPStatus.OK, "text/html; charset=utf-8", PAGE.read_bytes())
                elif path == "/state.json":
                    self._send(HTTPStatus.OK, "application/json", json.dumps(server.feed.state()).encode())
                elif path == "/events":
                    self._events()
                elif path == "/favicon.ico":
                    self._send(HTTPStatus.NO_CONTENT, "image/x-icon", b"")
                else:
                    self._send(HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8", b"not found\n")

            def _send(self, status: HTTPStatus, kind: str, body: bytes) -> None:
                self.send_response(status)
                self.send_header("Content-Type", kind)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _events(self) -> None:
                self.send_response(HTTPStatus.OK)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.send_header("Connection", "close")
                self.end_headers()
                self.close_connection = True
                q, snapshot = server.feed.subscribe()
                try:
                    self.wfile.write(b"retry: 1000\n\n" + b"".join(snapshot))
                    self.wfile.flush()
                    while not server._stop.is_set() and server.feed.connected(q):
                        try:
                            event = q.get(timeout=KEEPALIVE_S)
                        except queue.Empty:
                            event = b": keepalive\n\n"
                        batch = [event]
                        while len(batch) < 256:  # what else is waiting goes in the same write
                            try:
                                batch.append(q.get_nowait())
                            except queue.Empty:
                                break
                        self.wfile.write(b"".join(batch))
                        self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError, OSError):
                    pass
                finally:
                    server.feed.unsubscribe(q)

        self._httpd = ThreadingHTTPServer((host, port), Handler)
        self._httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._httpd.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        host, port = self.address
        return f"http://{host}:{port}/"

    def start(self) -> "MapWebServer":
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="companion-ground-http", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._httpd.shutdown()
        self._httpd.server_close()
        if self._thread is not None:
            self._thread.join(5.0)
