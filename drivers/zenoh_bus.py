"""The vehicle's Zenoh bus: changed terrain tiles, status, avoidance state, and the whole map on query.

Key expressions (``<v>`` = ``zenoh.vehicle_name``; the wire format is specified in docs/zenoh.md):

==========================================  ======================================================
``companion/<v>/terrain/tile/<tx>/<ty>``    put: one changed tile, binary (docs/terrain.md)
``companion/<v>/status``                    put at ``status_rate_hz``: JSON ``companion.status/1``
``companion/<v>/avoidance``                 put: JSON ``companion.avoidance/1``
``companion/<v>/alive``                     liveliness token while the bus is open
``companion/<v>/terrain/**`` (queryable)    ``terrain/tile/**`` (or any subset): one reply per
                                            tile on its tile key; ``terrain/map?_anyke``: the same
                                            (zenoh refuses tile-keyed replies to a plain
                                            ``terrain/map`` query, so that gets an error reply)
==========================================  ======================================================

The bus does not know the terrain classes: tiles are opaque bytes here (encoded by
``companion.method.terrain``). It keeps the last payload published for each tile, stamped with a Zenoh
timestamp, and answers map queries from that cache. The cache is what subscribers saw, so a late
joiner ends up with the same map as an early one, and the query never touches the live grid from
Zenoh's callback thread.

Blocking: ``publish_*`` never block (congestion control DROP: a full transmit queue drops the
sample and the late-joiner query repairs it). :meth:`ZenohBus.open` may block up to about half a
second (peer scouting delay) and :meth:`ZenohBus.close` until Zenoh has torn the session down, so
async code uses ``async with bus`` (both run in a worker thread). Query callbacks run on Zenoh's
threads; the cache and counters are guarded by a lock.

Unreachable endpoints: in peer mode Zenoh opens the session anyway and keeps retrying the
``connect`` endpoints (``connect/retry`` from ``reconnect_min_s``/``reconnect_max_s``). In client
mode Zenoh refuses to open without its router, so the bus retries the open itself on a background
thread it owns, with the same back-off; tiles published meanwhile are cached and re-published
when the session comes up. Once open, both modes reconnect by themselves after a link loss.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from companion.config import ZenohConfig

log = logging.getLogger(__name__)

KEY_ROOT = "companion"
STATUS_SCHEMA = "companion.status/1"
AVOIDANCE_SCHEMA = "companion.avoidance/1"
TILE_ENCODING = "application/octet-stream;companion.tile"
STATUS_ENCODING = "application/json;" + STATUS_SCHEMA
AVOIDANCE_ENCODING = "application/json;" + AVOIDANCE_SCHEMA
#: Fields every avoidance message carries (docs/zenoh.md); more are allowed.
AVOIDANCE_REQUIRED = ("engaged", "mode", "climb_rate_mps", "restriction_alt_m", "limiting_cell")
#: Envelope fields the bus writes into every JSON message; a body may not set them.
ENVELOPE_FIELDS = ("schema", "vehicle", "seq", "time_unix_s")

# A vehicle name is one key-expression chunk: no separators, wildcards or selector syntax.
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")
_INT = re.compile(r"^-?[0-9]+$")


class BusError(RuntimeError):
    """The bus cannot be configured or opened; the message names the setting at fault."""


# --------------------------------------------------------------------------------------------
# Keys
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BusKeys:
    """The key expressions of one vehicle (docs/zenoh.md, "Keys")."""

    vehicle: str

    def __post_init__(self) -> None:
        if not isinstance(self.vehicle, str) or not _CHUNK.match(self.vehicle):
            raise BusError(
                f"zenoh.vehicle_name must be one key chunk of letters, digits, '_', '-', '.', got {self.vehicle!r}"
            )

    @property
    def root(self) -> str:
        return f"{KEY_ROOT}/{self.vehicle}"

    @property
    def status(self) -> str:
        return f"{self.root}/status"

    @property
    def avoidance(self) -> str:
        return f"{self.root}/avoidance"

    @property
    def alive(self) -> str:
        return f"{self.root}/alive"

    @property
    def terrain(self) -> str:
        """What the queryable serves: everything under ``terrain/``."""
        return f"{self.root}/terrain/**"

    @property
    def map(self) -> str:
        return f"{self.root}/terrain/map"

    @property
    def tiles(self) -> str:
        """All tiles (subscribe or query this)."""
        return f"{self.root}/terrain/tile/*/*"

    def tile(self, tx: int, ty: int) -> str:
        return f"{self.root}/terrain/tile/{int(tx)}/{int(ty)}"

    def parse_tile(self, key: str) -> tuple[int, int] | None:
        """``(tx, ty)`` of a concrete tile key of this vehicle, else None."""
        prefix = f"{self.root}/terrain/tile/"
        if not key.startswith(prefix):
            return None
        parts = key[len(prefix):].split("/")
        if len(parts) != 2 or not all(_INT.match(p) for p in parts):
            return None
        return int(parts[0]), int(parts[1])


# --------------------------------------------------------------------------------------------
# Session configuration
# --------------------------------------------------------------------------------------------


def _insert(zcfg: zenoh.Config, key: str, value: Any, setting: str) -> None:
    try:
        zcfg.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise BusError(f"{setting}: zenoh rejects {value!r}: {exc}") from None


def zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """The Zenoh session configuration for ``cfg``.

    ``cfg.config_file`` (JSON5, JSON or YAML in Zenoh's own format: TLS, access control, ...) is
    loaded first; the companion settings are then written over it: ``mode``,
    ``scouting/multicast/enabled``, ``connect/retry``, and ``listen``/``connect`` endpoints when
    the companion lists any (an empty list leaves the file's, or Zenoh's default, in place).
    """
    if cfg.config_file:
        path = Path(cfg.config_file).expanduser()
        if not path.is_file():
            raise BusError(f"zenoh.config_file: no such file {str(path)!r}")
        try:
            zcfg = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise BusError(f"zenoh.config_file {str(path)!r}: {exc}") from None
    else:
        zcfg = zenoh.Config()
    _insert(zcfg, "mode", cfg.mode, "zenoh.mode")
    _insert(zcfg, "scouting/multicast/enabled", bool(cfg.multicast_scouting), "zenoh.multicast_scouting")
    if cfg.listen:
        _insert(zcfg, "listen/endpoints", list(cfg.listen), "zenoh.listen")
    if cfg.connect:
        _insert(zcfg, "connect/endpoints", list(cfg.connect), "zenoh.connect")
    lo_ms = int(round(cfg.reconnect_min_s * 1000))
    hi_ms = max(lo_ms, int(round(cfg.reconnect_max_s * 1000)))
    _insert(zcfg, "connect/retry", {"period_init_ms": lo_ms, "period_max_ms": hi_ms, "period_increase_factor": 2},
            "zenoh.reconnect_min_s/reconnect_max_s")
    # A peer whose connect endpoint is down must still open (and keep retrying in the background).
    _insert(zcfg, "connect/exit_on_failure", {"peer": False, "router": False, "client": True}, "zenoh.connect")
    return zcfg


# --------------------------------------------------------------------------------------------
# JSON payloads
# --------------------------------------------------------------------------------------------


def _jsonable(value: Any, where: str) -> Any:
    """``value`` as plain JSON types; non-finite floats become null (JSON has no NaN)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: keys must be strings, got {k!r}")
            out[k] = _jsonable(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(value)]
    # NumPy scalars and arrays without importing NumPy here.
    if hasattr(value, "tolist"):
        return _jsonable(value.tolist(), where)
    if hasattr(value, "__float__"):
        return _jsonable(float(value), where)
    raise TypeError(f"{where}: {type(value).__name__} is not JSON-serialisable")


def map_frame_shift(status: Mapping[str, Any]) -> float:
    """How far (m, up) a vehicle's map has moved to follow its navigation's vertical frame, from its
    ``companion.status/1`` document (``map.frame_shift_m``): its tiles are in its map's own frame,
    and their heights plus this are in its navigation's frame now. 0 when absent or not finite."""
    m = status.get("map")
    shift = m.get("frame_shift_m", 0.0) if isinstance(m, Mapping) else 0.0
    return float(shift) if isinstance(shift, (int, float)) and math.isfinite(shift) else 0.0


def json_payload(schema: str, vehicle: str, seq: int, body: Mapping[str, Any]) -> bytes:
    """UTF-8 JSON of ``body`` inside the envelope ``schema``, ``vehicle``, ``seq``, ``time_unix_s``."""
    if not isinstance(body, Mapping):
        raise TypeError(f"{schema}: body must be a mapping, got {type(body).__name__}")
    clash = [k for k in ENVELOPE_FIELDS if k in body]
    if clash:
        raise ValueError(f"{schema}: the bus sets {', '.join(clash)}; remove them from the body")
    doc = {"schema": schema, "vehicle": vehicle, "seq": int(seq), "time_unix_s": round(time.time(), 6)}
    doc.update(_jsonable(body, schema))
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")


# --------------------------------------------------------------------------------------------
# The bus
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BusStats:
    """Counters since the bus was created (a snapshot)."""

    connected: bool
    tiles_cached: int
    published_tiles: int
    published_status: int
    published_avoidance: int
    bytes_published: int
    publish_errors: int
    unpublished_offline: int
    status_provider_errors: int
    queries_answered: int
    replies_sent: int
    bad_queries: int
    query_errors: int
    open_attempts: int
    open_failures: int
    links: int = 0
    link_ups: int = 0
    link_downs: int = 0
    bytes_tiles: int = 0        # of bytes_published: tiles, status, avoidance (what the radio carries)
    bytes_status: int = 0
    bytes_avoidance: int = 0
    published_deltas: int = 0   # of published_tiles: sent as the changed cells only

    def as_dict(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in self.__slots__}


_COUNTERS = [f for f in BusStats.__slots__ if f not in ("connected", "tiles_cached", "links")]

TileProvider = Callable[[], Iterable[tuple[int, int, bytes]]]


class ZenohBus:
    """Publishes the vehicle's map and state on Zenoh and answers map queries.

    ``map_provider`` (optional) replaces the tile cache as the source of query replies; it is
    called on a Zenoh thread, so it must be thread-safe and return encoded tiles.
    """

    def __init__(self, cfg: ZenohConfig, *, map_provider: TileProvider | None = None) -> None:
        if cfg.reconnect_max_s < cfg.reconnect_min_s:
            raise BusError("zenoh.reconnect_max_s must be >= zenoh.reconnect_min_s")
        self.cfg = cfg
        self.keys = BusKeys(cfg.vehicle_name)
        self._map_provider = map_provider
        self._lock = threading.Lock()
        self._tiles: dict[tuple[int, int], tuple[bytes, zenoh.Timestamp | None]] = {}
        self._n = dict.fromkeys(_COUNTERS, 0)
        self._seq = {"status": 0, "avoidance": 0}
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._status_pub: zenoh.Publisher | None = None
        self._avoid_pub: zenoh.Publisher | None = None
        self._stop = threading.Event()
        self._reopener: threading.Thread | None = None
        self._opened = False
        self._link_up_seen: bool | None = None  # None until the first look at the links
        self._listeners: list[Callable[[zenoh.Session], list]] = []

    # ---- lifecycle -------------------------------------------------------------------------

    def open(self) -> None:
        """Open the session and declare the queryable and liveliness token.

        Raises :class:`BusError` for a bad configuration or (peer mode) a listen endpoint that
        cannot be bound. A client whose router is unreachable does not raise: the bus keeps
        retrying in the background (see :attr:`connected`).
        """
        if self._opened:
            raise BusError("zenoh bus already opened")
        zcfg = zenoh_config(self.cfg)  # configuration errors surface here, before any retry
        self._opened = True
        self._stop.clear()
        try:
            session = self._open_session(zcfg)
        except zenoh.ZError as exc:
            if self.cfg.mode == "client":
                log.warning("zenoh: router unreachable (%s); retrying in the background", exc)
                self._reopener = threading.Thread(target=self._reopen_loop, name="zenoh-reopen", daemon=True)
                self._reopener.start()
                return
            self._opened = False
            raise BusError(
                f"zenoh: cannot open a {self.cfg.mode} session (listen={list(self.cfg.listen)}, "
                f"connect={list(self.cfg.connect)}): {exc}"
            ) from None
        try:
            self._attach(session)
        except zenoh.ZError as exc:
            session.close()
            self._opened = False
            raise BusError(f"zenoh: cannot declare the vehicle's keys under {self.keys.root}: {exc}") from None

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        self._stop.set()
        if self._reopener is not None:
            self._reopener.join(timeout=10.0)
            self._reopener = None
        with self._lock:
            session, self._session = self._session, None
            declared, self._declared = self._declared, []
            self._status_pub = self._avoid_pub = None
        for entity in reversed(declared):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - best effort on teardown
                pass
        if session is not None:
            session.close()
        self._opened = False

    def __enter__(self) -> "ZenohBus":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def __aenter__(self) -> "ZenohBus":
        await asyncio.to_thread(self.open)
        return self

    async def __aexit__(self, *exc: object) -> None:
        await asyncio.to_thread(self.close)

    @property
    def connected(self) -> bool:
        """A session exists (peer: always after open; client: once the router answered)."""
        return self._session is not None

    def _open_session(self, zcfg: zenoh.Config) -> zenoh.Session:
        with self._lock:
            self._n["open_attempts"] += 1
        try:
            return zenoh.open(zcfg)
        except zenoh.ZError:
            with self._lock:
                self._n["open_failures"] += 1
            raise

    def _reopen_loop(self) -> None:
        """Client mode: retry ``zenoh.open`` with exponential back-off until it works or close()."""
        delay = self.cfg.reconnect_min_s
        while not self._stop.wait(delay):
            try:
                session = self._open_session(zenoh_config(self.cfg))
            except zenoh.ZError as exc:
                log.debug("zenoh: reopen failed: %s", exc)
                delay = min(2.0 * delay, self.cfg.reconnect_max_s)
                continue
            if self._stop.is_set():
                session.close()
                return
            try:
                self._attach(session)
            except zenoh.ZError as exc:  # e.g. refused by the router's access control
                log.error("zenoh: connected but cannot declare under %s: %s", self.keys.root, exc)
                session.close()
                delay = self.cfg.reconnect_max_s
                continue
            log.info("zenoh: connected to the router")
            self._republish_cache()
            return

    def _attach(self, session: zenoh.Session) -> None:
        k = self.keys
        declared = [
            session.declare_queryable(k.terrain, self._on_query),
            session.liveliness().declare_token(k.alive),
        ]
        status_pub = session.declare_publisher(
            k.status, encoding=STATUS_ENCODING, congestion_control=zenoh.CongestionControl.DROP
        )
        # Avoidance is small and matters more than map data; let it overtake queued tiles.
        avoid_pub = session.declare_publisher(
            k.avoidance, encoding=AVOIDANCE_ENCODING, congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        for declare in self._listeners:
            declared += declare(session)
        with self._lock:
            self._session = session
            self._declared = declared + [status_pub, avoid_pub]
            self._status_pub, self._avoid_pub = status_pub, avoid_pub

    def add_listener(self, declare: Callable[[zenoh.Session], list]) -> None:
        """Subscriptions that live as long as the bus (other vehicles' maps, drivers/fleet_listener.py):
        ``declare(session)`` returns what it declared, and is run on the open session now and on
        every session the bus opens again; the bus undeclares it all on close."""
        self._listeners.append(declare)
        with self._lock:
            session = self._session
        if session is not None:
            entities = declare(session)
            with self._lock:
                self._declared += entities

    def get(self, selector: str, timeout_s: float) -> list:
        """The replies to a query on the bus's session (none while it has no session)."""
        with self._lock:
            session = self._session
        return [] if session is None else list(session.get(selector, timeout=timeout_s))

    def _republish_cache(self) -> None:
        with self._lock:
            items = [(tx, ty, payload) for (tx, ty), (payload, _) in self._tiles.items()]
        self.publish_tiles(items)

    # ---- publishing ------------------------------------------------------------------------

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._n[name] += n

    def publish_tile(self, tx: int, ty: int, payload: bytes, live: bytes | None = None) -> None:
        """Publish one changed tile (encoded by the terrain codec) and remember it for queries.
        ``live``: what goes on the wire instead (a delta on the revision before), while queries
        are still answered with ``payload``, the whole tile."""
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"tile ({tx}, {ty}): payload must be bytes, got {type(payload).__name__}")
        if live is not None and not isinstance(live, (bytes, bytearray, memoryview)):
            raise TypeError(f"tile ({tx}, {ty}): live payload must be bytes, got {type(live).__name__}")
        if isinstance(tx, bool) or isinstance(ty, bool) or int(tx) != tx or int(ty) != ty:
            raise ValueError(f"tile index must be integers, got ({tx!r}, {ty!r})")
        payload = bytes(payload)
        tx, ty = int(tx), int(ty)
        session = self._session
        if session is None:
            with self._lock:
                self._tiles[(tx, ty)] = (payload, None)
                self._n["unpublished_offline"] += 1
            return
        # The same stamp goes on the live sample and on later query replies, so a subscriber can
        # tell which of the two is newer.
        try:
            ts = session.new_timestamp()
        except zenoh.ZError:  # the session is closing underneath us
            ts = None
        with self._lock:
            self._tiles[(tx, ty)] = (payload, ts)
        sent = payload if live is None else bytes(live)
        try:
            session.put(self.keys.tile(tx, ty), sent, encoding=TILE_ENCODING, timestamp=ts,
                        priority=zenoh.Priority.DATA_LOW, congestion_control=zenoh.CongestionControl.DROP)
        except zenoh.ZError as exc:
            log.warning("zenoh: tile (%d, %d) not published: %s", tx, ty, exc)
            self._count("publish_errors")
            return
        with self._lock:
            self._n["published_tiles"] += 1
            self._n["published_deltas"] += live is not None
            self._n["bytes_published"] += len(sent)
            self._n["bytes_tiles"] += len(sent)

    def publish_tiles(self, items: Iterable[tuple[int, int, bytes]]) -> int:
        """Publish several tiles; returns how many."""
        n = 0
        for tx, ty, payload in items:
            self.publish_tile(tx, ty, payload)
            n += 1
        return n

    def publish_grid_changes(self, grid: Any) -> int:
        """Publish the tiles a terrain grid changed since the last call (``grid.pop_dirty()``).

        ``grid`` is a ``companion.method.terrain.grid.TerrainGrid`` (duck-typed: ``pop_dirty()`` and
        ``tile(key, in_map_frame=True)``: heights in the map's own frame, which the status's
        ``map.frame_shift_m`` takes to the vehicle's navigation frame); call it from the thread that
        owns the grid. Returns the tiles published.
        """
        from companion.method.terrain.codec import encode_tile  # the bus itself stays codec-agnostic

        n = 0
        for key in grid.pop_dirty():
            self.publish_tile(key[0], key[1], encode_tile(grid.tile(key, in_map_frame=True)))
            n += 1
        return n

    def _publish_json(self, which: str, schema: str, body: Mapping[str, Any], add_stats: bool = False) -> bytes:
        if add_stats and "zenoh" not in body:  # a body that observed the bus itself keeps its look
            body = {**body, "zenoh": self.stats().as_dict()}
        with self._lock:
            # The sequence number only advances for a message that encodes (a rejected body
            # leaves no gap a subscriber would read as loss).
            payload = json_payload(schema, self.keys.vehicle, self._seq[which] + 1, body)
            self._seq[which] += 1
        pub = self._status_pub if which == "status" else self._avoid_pub
        if pub is None:
            self._count("unpublished_offline")
            return payload
        try:
            pub.put(payload)
        except zenoh.ZError as exc:
            log.warning("zenoh: %s not published: %s", which, exc)
            self._count("publish_errors")
            return payload
        with self._lock:
            self._n[f"published_{which}"] += 1
            self._n["bytes_published"] += len(payload)
            self._n[f"bytes_{which}"] += len(payload)
        return payload

    def publish_status(self, body: Mapping[str, Any]) -> bytes:
        """Publish ``companion.status/1`` (the bus adds the envelope and, unless ``body`` carries
        them already, its own counters as ``zenoh``)."""
        return self._publish_json("status", STATUS_SCHEMA, body, add_stats=True)

    def publish_avoidance(self, body: Mapping[str, Any]) -> bytes:
        """Publish ``companion.avoidance/1``; ``body`` must carry :data:`AVOIDANCE_REQUIRED`."""
        if not isinstance(body, Mapping):
            raise TypeError(f"{AVOIDANCE_SCHEMA}: body must be a mapping, got {type(body).__name__}")
        missing = [k for k in AVOIDANCE_REQUIRED if k not in body]
        if missing:
            raise ValueError(f"{AVOIDANCE_SCHEMA}: missing field(s) {', '.join(missing)}")
        return self._publish_json("avoidance", AVOIDANCE_SCHEMA, body)

    async def run_status(self, provider: Callable[[], Mapping[str, Any]]) -> None:
        """Publish ``provider()`` at ``status_rate_hz`` until cancelled.

        A provider that raises is counted and logged; the loop goes on (a broken status field must
        not silence the vehicle). Missed periods are skipped, not bunched.
        """
        period = 1.0 / self.cfg.status_rate_hz
        loop = asyncio.get_running_loop()
        due = loop.time()
        while True:
            try:
                self.publish_status(provider())
            except Exception:  # noqa: BLE001 - see docstring
                self._count("status_provider_errors")
                failures = self._n["status_provider_errors"]
                if failures == 1 or failures % 60 == 0:  # the first, then once a minute at 1 Hz
                    log.exception("zenoh: status provider failed (%d times)", failures)
            due += period
            now = loop.time()
            if due < now:
                due = now
            await asyncio.sleep(due - now)

    # ---- the queryable ---------------------------------------------------------------------

    def _tile_snapshot(self) -> list[tuple[int, int, bytes, zenoh.Timestamp | None]]:
        if self._map_provider is not None:
            return [(int(tx), int(ty), bytes(p), None) for tx, ty, p in self._map_provider()]
        with self._lock:
            return [(tx, ty, p, ts) for (tx, ty), (p, ts) in self._tiles.items()]

    def _bad_query(self, query: zenoh.Query, why: str) -> None:
        self._count("bad_queries")
        log.debug("zenoh: bad query on %s: %s", query.key_expr, why)  # counted; a flood must not flood the log
        query.reply_err(f"companion: {why}".encode(), encoding="text/plain")

    def _on_query(self, query: zenoh.Query) -> None:
        """Answer a query under ``terrain/**`` (runs on a Zenoh thread; never raises)."""
        try:
            self._answer(query)
        except Exception as exc:  # noqa: BLE001 - a query must never take the bus down
            self._count("query_errors")
            log.warning("zenoh: query on %s failed: %s", query.key_expr, exc)
        finally:
            query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        k = self.keys
        qkey = query.key_expr
        payload = query.payload
        if payload is not None and len(payload) > 0:
            return self._bad_query(query, f"map queries take no payload (got {len(payload)} bytes)")
        wants_map = qkey.intersects(k.map)
        wants_tiles = qkey.intersects(k.tiles)
        text = str(qkey)
        if not (wants_map or wants_tiles):
            return self._bad_query(query, f"unknown key {text!r}; ask {k.map}?_anyke or {k.root}/terrain/tile/**")
        if "*" not in text and not wants_map and k.parse_tile(text) is None:
            return self._bad_query(query, f"malformed tile key {text!r}; tiles are {k.root}/terrain/tile/<tx>/<ty>")
        any_key = query.accepts_replies() == zenoh.ReplyKeyExpr.ANY
        if wants_map and not any_key and not wants_tiles:
            return self._bad_query(
                query,
                f"{k.map} replies on the tiles' own keys: query {k.map}?_anyke "
                f"(or accept_replies=ANY), or query {k.root}/terrain/tile/**",
            )
        sent = 0
        for tx, ty, tile_payload, ts in self._tile_snapshot():
            key = k.tile(tx, ty)
            if (wants_map and any_key) or qkey.intersects(key):
                query.reply(key, tile_payload, encoding=TILE_ENCODING, timestamp=ts)
                sent += 1
        with self._lock:
            self._n["queries_answered"] += 1
            self._n["replies_sent"] += sent

    # ---- introspection ---------------------------------------------------------------------

    def links(self) -> list[str]:
        """Remote locators of the open Zenoh links (peers or routers); empty while nobody is there."""
        session = self._session
        if session is None:
            return []
        try:
            return [str(link.dst) for link in session.info.links()]
        except zenoh.ZError:  # the session is closing underneath us
            return []

    def _observe_links(self) -> int:
        """Count open links; an up/down change is counted and logged once (polled by :meth:`stats`)."""
        n = len(self.links())
        with self._lock:
            was_up = self._link_up_seen
            self._link_up_seen = n > 0
            if was_up is None or was_up == (n > 0):
                return n
            self._n["link_ups" if n > 0 else "link_downs"] += 1
        if n > 0:
            log.info("zenoh: link up (%s)", ", ".join(self.links()) or "?")
        else:
            log.warning("zenoh: link down (no peer or router connected; retrying %s)", list(self.cfg.connect) or "-")
        return n

    def stats(self) -> BusStats:
        links = self._observe_links()
        with self._lock:
            return BusStats(connected=self._session is not None, tiles_cached=len(self._tiles), links=links,
                            **self._n)
