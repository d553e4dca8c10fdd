"""Other vehicles' maps for this vehicle's avoidance law (``zenoh.share_from``; docs/terrain.md,
"Evidence from other vehicles"; docs/zenoh.md, "Sharing the map between vehicles").

On the service's own Zenoh session (the bus's), it subscribes to the tiles and statuses of
the vehicles it is told to listen to, asks each for its whole map when its liveliness token
appears (a vehicle that joins late, or comes back), and queues what arrives. The service drains the
queue on its own thread (:meth:`FleetListener.drain`) into a
:class:`companion.method.terrain.sharing.SharedEvidence`: a source is placed once both its origin
(its status's ``frame``) and this vehicle's are known; its tiles wait until then. This vehicle's
own keys, the ``zenoh.share_ignore`` list and malformed samples are counted and dropped. A
vehicle's name put on ``companion/<this vehicle>/sharing/withdraw`` withdraws its evidence while the
service runs (and ignores it until restart).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections import Counter
from typing import Any

import numpy as np
import zenoh

from companion.config import ZenohConfig
from drivers.zenoh_bus import KEY_ROOT, STATUS_SCHEMA, map_frame_shift

log = logging.getLogger("companion.fleet")
MAX_QUEUE = 20_000


class FleetListener:
    """Subscriptions to other vehicles' tiles and statuses (module docstring)."""

    def __init__(self, cfg: ZenohConfig) -> None:
        self.cfg = cfg
        self.own = cfg.vehicle_name
        self.sources = tuple(cfg.share_from)
        self.ignore = set(cfg.share_ignore)
        self._q: queue.Queue = queue.Queue(MAX_QUEUE)
        self._bus = None
        self._frames: dict[str, Any] = {}                 # source -> (LocalFrame, map frame shift m) from its status
        self._pending: dict[str, dict[tuple[int, int], Any]] = {}  # tiles of sources not placed yet
        self._placed_with: dict[str, Any] = {}            # source -> the own frame it was placed in
        self._wanted: set[str] = set()                    # sources whose map to ask for
        self._received: dict[tuple[str, int, int], Any] = {}  # (source, tx, ty) -> its tile as last received
        self._missing: set[tuple[str, int, int]] = set()   # tiles a delta could not be applied to: asked whole
        self.counts = Counter()

    # ---- Zenoh side (its threads) ------------------------------------------------------------

    def _roots(self) -> list[str]:
        return [f"{KEY_ROOT}/*"] if self.sources == ("*",) else [f"{KEY_ROOT}/{v}" for v in self.sources]

    def open(self, bus) -> "FleetListener":
        """Listen on ``bus``'s session (a :class:`drivers.zenoh_bus.ZenohBus`): the subscriptions
        follow the bus through reconnections and close with it."""
        self._bus = bus
        bus.add_listener(self._declare)
        return self

    def _declare(self, session) -> list:
        # The operator's word: put a vehicle's name on companion/<this vehicle>/sharing/withdraw and
        # its evidence leaves the law's map, and is not read again until the service restarts.
        declared = [session.declare_subscriber(f"{KEY_ROOT}/{self.own}/sharing/withdraw", self._on_withdraw)]
        for root in self._roots():
            declared += [
                session.declare_subscriber(f"{root}/terrain/tile/*/*", self._on_sample),
                session.declare_subscriber(f"{root}/status", self._on_sample),
                session.liveliness().declare_subscriber(f"{root}/alive", self._on_alive, history=True),
            ]
        return declared

    def _source_of(self, key: str) -> str | None:
        parts = key.split("/")
        if len(parts) < 3 or parts[0] != KEY_ROOT:
            return None
        source = parts[1]
        if source == self.own:
            self.counts["own_ignored"] += 1  # never take one's own evidence back
            return None
        if source in self.ignore or (self.sources != ("*",) and source not in self.sources):
            self.counts["ignored"] += 1
            return None
        return source

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        source = self._source_of(key)
        if source is None:
            return
        try:
            self._q.put_nowait((source, key, sample.payload.to_bytes()))
        except queue.Full:
            self.counts["dropped"] += 1

    def _on_withdraw(self, sample) -> None:
        try:
            source = sample.payload.to_bytes().decode("utf-8").strip()
        except UnicodeDecodeError:
            source = ""
        if source:
            try:
                self._q.put_nowait((source, "withdraw", b""))
            except queue.Full:
                self.counts["dropped"] += 1

    def _on_alive(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            source = self._source_of(str(sample.key_expr))
            if source is not None:
                self._wanted.add(source)

    def _ask(self, sources: set[str], tiles: set[tuple[str, int, int]] = frozenset()) -> None:
        """The whole map of each source that (re)appeared: a late joiner starts with what it has;
        and each tile whose delta found no base here, whole."""
        selectors = [f"{KEY_ROOT}/{source}/terrain/tile/**" for source in sorted(sources)]
        selectors += [f"{KEY_ROOT}/{source}/terrain/tile/{tx}/{ty}" for source, tx, ty in sorted(tiles)]
        for selector in selectors:
            for reply in self._bus.get(selector, 5.0):
                if reply.ok is not None:
                    self._on_sample(reply.ok)
            self.counts["queries_answered"] += 1

    # ---- the service's side (its thread) -----------------------------------------------------

    def drain(self, shared, own_frame, weight: float = 1.0) -> int:
        """Apply what arrived to ``shared`` (a ``SharedEvidence``), placing each source from its
        origin and ``own_frame`` (a ``LocalFrame``, None while this vehicle has no origin: tiles
        wait). Returns the tiles applied."""
        from companion.method.geodesy import place_cells
        from companion.method.terrain.codec import MissingBase, apply_update

        if self._bus is not None and (self._wanted or self._missing):
            wanted, self._wanted = self._wanted, set()  # each appearance asked once
            missing, self._missing = self._missing, set()
            threading.Thread(target=self._ask, args=(wanted, missing), name="companion-fleet-query", daemon=True).start()
        applied = 0
        while True:
            try:
                source, key, payload = self._q.get_nowait()
            except queue.Empty:
                break
            if key == "withdraw":
                self.ignore.add(source)
                shared.withdraw(source)
                self._received = {k: t for k, t in self._received.items() if k[0] != source}
                self._frames.pop(source, None)
                self._pending.pop(source, None)
                self._placed_with.pop(source, None)
                self.counts["withdrawn"] += 1
                log.warning("fleet: %s's map withdrawn on request; not read again until restart", source)
                continue
            if key.endswith("/status"):
                frame = _frame_of(payload)
                if frame is None:
                    self.counts["status_without_origin"] += 1
                else:
                    self._frames[source] = frame
                continue
            index = _tile_index(key)
            if index is None:
                self.counts["bad_tiles"] += 1
                continue
            try:
                tile = apply_update(self._received.get((source, *index)), payload)
            except MissingBase as exc:  # a delta on a tile not held here: ask for it whole
                self.counts["missing_base"] += 1
                self._missing.add((source, *index))
                log.debug("fleet: %s: %s", key, exc)
                continue
            except ValueError as exc:
                self.counts["bad_tiles"] += 1
                log.debug("fleet: %s: %s", key, exc)
                continue
            if index != (tile.tx, tile.ty):
                self.counts["bad_tiles"] += 1
                continue
            self._received[(source, tile.tx, tile.ty)] = tile
            self._pending.setdefault(source, {})[(tile.tx, tile.ty)] = tile
        for source, (frame, map_shift) in self._frames.items():
            if own_frame is None:
                break
            if self._placed_with.get(source) != (own_frame, frame, map_shift):
                north, east, up = place_cells(np.zeros(1), np.zeros(1), np.zeros(1), frame, own_frame)
                shared.set_frame(source, (float(north[0]), float(east[0]), float(up[0]) + map_shift), weight)
                self._placed_with[source] = (own_frame, frame, map_shift)
            for tile in self._pending.pop(source, {}).values():
                if shared.put(source, tile):
                    applied += 1
                else:
                    self.counts["tiles_refused"] += 1
        self.counts["tiles_applied"] += applied
        return applied

    def status(self) -> dict[str, Any]:
        return {"sources": sorted(self._frames), "waiting_for_origin": sorted(set(self._pending) - set(self._frames)),
                **dict(self.counts)}


def _tile_index(key: str) -> tuple[int, int] | None:
    """(tx, ty) of a ``companion/<v>/terrain/tile/<tx>/<ty>`` key, None when it is not one."""
    parts = key.split("/")
    if len(parts) != 6 or parts[2:4] != ["terrain", "tile"]:
        return None
    try:
        return int(parts[4]), int(parts[5])
    except ValueError:
        return None


def _frame_of(payload: bytes):
    """From a ``companion.status/1`` payload, the sender's local frame and how far its map has been
    moved to follow its navigation's vertical frame (``map.frame_shift_m``: its tiles' heights plus
    this are in its local frame now; 0 when absent); None without an origin."""
    from companion.method.geodesy import LocalFrame

    try:
        doc = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    if not (isinstance(doc, dict) and doc.get("schema") == STATUS_SCHEMA):
        return None
    frame = LocalFrame.from_status(doc)
    return None if frame is None else (frame, map_frame_shift(doc))
