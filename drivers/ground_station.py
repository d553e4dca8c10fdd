"""``companion ground``: a ground-station subscriber that rebuilds the vehicle's terrain map.

It subscribes to the vehicle's tiles, status and avoidance state (docs/zenoh.md), asks for the
whole map when it starts and whenever the vehicle's liveliness token (re)appears, keeps the
tiles in a :class:`GroundMap`, rewrites a PNG of the map every few seconds (atomically), prints a
one-line summary, and with ``--http`` serves the map live to browsers (:mod:`drivers.ground_web`).

Ordering: live tiles and query replies both carry the Zenoh timestamp the vehicle stamped the
tile with, so a reply older than a live tile already applied is dropped (counted as stale)
whatever order they arrive in.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import cv2
import numpy as np
import zenoh

from companion.config import ConfigError, ZenohConfig, load_config
from drivers.zenoh_bus import AVOIDANCE_SCHEMA, KEY_ROOT, STATUS_SCHEMA, BusError, BusKeys, map_frame_shift, zenoh_config

UNKNOWN_BGR = (128, 128, 128)
COLORMAP = cv2.COLORMAP_TURBO
MAX_MOSAIC_CELLS = 4096  # per side; larger maps are decimated for display


def _has_schema(doc: Any, schema: str) -> bool:
    """True when ``doc`` is a JSON object of exactly ``schema`` (a new major version is a new name)."""
    return isinstance(doc, dict) and doc.get("schema") == schema


@dataclass(frozen=True, slots=True)
class Mosaic:
    """The known map on one regular grid.

    height: (H, W) float32 altitude (m, up), NaN unknown; row i is north, column j east, row 0 is
        the southern edge (the tile layer convention, docs/terrain.md).
    north0_m, east0_m: south-west corner of cell [0, 0]; cell_size_m: edge of one (displayed) cell.
    """

    height: np.ndarray
    north0_m: float
    east0_m: float
    cell_size_m: float


@dataclass(frozen=True, slots=True)
class MapLayout:
    """Where the map sits in a rendered image (north up, east right)."""

    x0: int
    y0: int
    cell_px: int
    rows: int
    cols: int
    north0_m: float
    east0_m: float
    cell_size_m: float
    height_lo_m: float
    height_hi_m: float

    def pixel(self, north_m: float, east_m: float) -> tuple[int, int]:
        """(x, y) image pixel at the centre of the displayed cell containing (north, east)."""
        i = int(math.floor((north_m - self.north0_m) / self.cell_size_m))
        j = int(math.floor((east_m - self.east0_m) / self.cell_size_m))
        if not (0 <= i < self.rows and 0 <= j < self.cols):
            raise ValueError(f"({north_m}, {east_m}) m is outside the rendered map")
        row = self.rows - 1 - i  # north up
        return self.x0 + j * self.cell_px + self.cell_px // 2, self.y0 + row * self.cell_px + self.cell_px // 2


class GroundMap:
    """Tiles, status and avoidance state of one vehicle, rebuilt from Zenoh samples.

    Single-threaded: feed it from one thread (the ground station drains a queue into it).
    """

    def __init__(self, vehicle: str) -> None:
        self.keys = BusKeys(vehicle)
        self.tiles: dict[tuple[int, int], Any] = {}  # (tx, ty) -> companion.method.terrain.tile.Tile
        self._stamps: dict[tuple[int, int], int | None] = {}
        self.status: dict[str, Any] | None = None
        self.avoidance: dict[str, Any] | None = None
        self.status_rx_monotonic: float | None = None
        self.counts = dict.fromkeys(
            ("tiles_rx", "deltas_rx", "status_rx", "avoidance_rx", "bad_tiles", "stale_tiles", "missing_base",
             "bad_json", "ignored", "query_errors"), 0
        )
        self.missing: set[tuple[int, int]] = set()  # tiles a delta could not be applied to: ask for them whole
        self.last_error = ""
        self.changed_tiles: set[tuple[int, int]] = set()  # since the last take_changes()
        self.changed_status = self.changed_avoidance = False

    def take_changes(self) -> tuple[set[tuple[int, int]], bool, bool]:
        """The tiles, and whether the status and the avoidance state, changed since the last call."""
        out = (self.changed_tiles, self.changed_status, self.changed_avoidance)
        self.changed_tiles, self.changed_status, self.changed_avoidance = set(), False, False
        return out

    # ---- applying samples --------------------------------------------------------------------

    def apply(self, key: str, payload: bytes, stamp: int | None = None) -> bool:
        """Route one sample by key; False (and counted) when it was rejected or not ours."""
        if key == self.keys.status or key == self.keys.avoidance:
            return self.apply_json(key, payload)
        if self.keys.parse_tile(key) is not None:
            return self.apply_tile(key, payload, stamp)
        self.counts["ignored"] += 1
        return False

    def reject(self, counter: str, why: str) -> bool:
        """Count a rejected input under ``counter`` and remember why (for the summary)."""
        self.counts[counter] += 1
        self.last_error = why
        return False

    def apply_tile(self, key: str, payload: bytes, stamp: int | None = None) -> bool:
        """Decode and store a tile unless it is malformed, misplaced, inconsistent or stale."""
        # Imported on use: the ground station's wiring (and its tests) must not depend on the
        # terrain package being importable at module load.
        from companion.method.terrain.codec import MissingBase, TileDelta, apply_delta, decode_update

        index = self.keys.parse_tile(key)
        if index is None:
            return self.reject("bad_tiles", f"not a tile key: {key!r}")
        try:
            tile = decode_update(payload)
        except ValueError as exc:
            return self.reject("bad_tiles", f"{key}: {exc}")
        if (tile.tx, tile.ty) != index:
            return self.reject("bad_tiles", f"{key}: payload is tile ({tile.tx}, {tile.ty})")
        delta = isinstance(tile, TileDelta)  # the cells that changed since its base revision
        if delta:
            try:
                tile = apply_delta(self.tiles.get(index), tile)
            except MissingBase as exc:
                self.counts["missing_base"] += 1
                self.last_error = str(exc)
                self.missing.add(index)
                return False
        if self.tiles:
            ref = next(iter(self.tiles.values()))
            if tile.tile_cells != ref.tile_cells or tile.cell_size_m != ref.cell_size_m:
                return self.reject(
                    "bad_tiles",
                    f"{key}: {tile.tile_cells} cells of {tile.cell_size_m} m, the map has "
                    f"{ref.tile_cells} of {ref.cell_size_m} m",
                )
        old = self._stamps.get(index)
        if stamp is not None and old is not None and stamp < old:
            self.counts["stale_tiles"] += 1
            return False
        self.tiles[index] = tile
        self._stamps[index] = stamp
        self.changed_tiles.add(index)
        self.missing.discard(index)
        self.counts["tiles_rx"] += 1
        self.counts["deltas_rx"] += delta
        return True

    def apply_json(self, key: str, payload: bytes) -> bool:
        """Status or avoidance JSON (``companion.status/1``, ``companion.avoidance/1``)."""
        try:
            doc = json.loads(bytes(payload).decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            return self.reject("bad_json", f"{key}: not UTF-8 JSON: {exc}")
        if key == self.keys.status:
            if not _has_schema(doc, STATUS_SCHEMA):
                return self.reject("bad_json", f"{key}: schema {doc.get('schema') if isinstance(doc, dict) else None!r}")
            self.status = doc
            self.status_rx_monotonic = time.monotonic()
            self.changed_status = True
            self.counts["status_rx"] += 1
            return True
        if not _has_schema(doc, AVOIDANCE_SCHEMA):
            return self.reject("bad_json", f"{key}: schema {doc.get('schema') if isinstance(doc, dict) else None!r}")
        self.avoidance = doc
        self.changed_avoidance = True
        self.counts["avoidance_rx"] += 1
        return True

    # ---- the map on one grid -----------------------------------------------------------------

    def cells_known(self) -> int:
        return int(sum(int(np.count_nonzero(t.count > 0)) for t in self.tiles.values()))

    def height_range(self) -> tuple[float, float] | None:
        """Lowest and highest known height (m), None when no cell is known."""
        known = [t.height[t.count > 0] for t in self.tiles.values()]
        known = [h for h in known if h.size]
        if not known:
            return None
        return float(min(np.nanmin(h) for h in known)), float(max(np.nanmax(h) for h in known))

    def mosaic(self, max_cells: int = MAX_MOSAIC_CELLS) -> Mosaic | None:
        """All tiles on one grid, keeping every ``step``-th cell so that neither side exceeds
        ``max_cells`` (``step`` = 1 for maps that fit); None when there are no tiles."""
        if not self.tiles:
            return None
        ref = next(iter(self.tiles.values()))
        t, c = ref.tile_cells, ref.cell_size_m
        txs = [k[0] for k in self.tiles]
        tys = [k[1] for k in self.tiles]
        i_min, j_min = min(txs) * t, min(tys) * t  # global cell index of the south-west corner
        rows, cols = (max(txs) + 1) * t - i_min, (max(tys) + 1) * t - j_min
        step = max(1, math.ceil(max(rows, cols) / max(1, int(max_cells))))
        out = np.full((math.ceil(rows / step), math.ceil(cols / step)), np.nan, dtype=np.float32)
        for (tx, ty), tile in self.tiles.items():
            gi, gj = tx * t - i_min, ty * t - j_min  # tile origin in mosaic cells
            si, sj = (-gi) % step, (-gj) % step  # first tile cell on the decimated lattice
            h = np.where(tile.count > 0, tile.height, np.nan)[si::step, sj::step]
            oi, oj = (gi + si) // step, (gj + sj) // step
            out[oi : oi + h.shape[0], oj : oj + h.shape[1]] = h
        return Mosaic(out, i_min * c, j_min * c, c * step)

    # ---- rendering ---------------------------------------------------------------------------

    def render(self, max_px: int = 640) -> tuple[np.ndarray, MapLayout | None]:
        """BGR image: height colour-mapped (TURBO, lowest known -> 0, highest -> 255), unknown
        cells grey, north up, with a colour bar in metres, a scale bar and a north arrow."""
        font = cv2.FONT_HERSHEY_SIMPLEX
        m = self.mosaic(max_cells=max_px)
        if m is None:
            img = np.full((120, 360, 3), 40, np.uint8)
            cv2.putText(img, f"{self.keys.vehicle}: no map yet", (12, 66), font, 0.6, (230, 230, 230), 1, cv2.LINE_AA)
            return img, None
        rows, cols = m.height.shape
        known = np.isfinite(m.height)
        lo = float(np.nanmin(m.height)) if known.any() else 0.0
        hi = float(np.nanmax(m.height)) if known.any() else 1.0
        span = hi - lo if hi - lo > 1e-6 else 1.0
        level = np.zeros(m.height.shape, np.uint8)
        level[known] = np.round((m.height[known] - lo) / span * 255.0).astype(np.uint8)
        cells = cv2.applyColorMap(level, COLORMAP)
        cells[~known] = UNKNOWN_BGR
        cells = cells[::-1]  # row 0 of the mosaic is the south edge; images start at the top
        cell_px = int(np.clip(max_px // max(rows, cols), 1, 16))
        cells = cv2.resize(cells, (cols * cell_px, rows * cell_px), interpolation=cv2.INTER_NEAREST)

        margin, title_h, bottom_h, right_w = 10, 26, 46, 110
        map_h, map_w = cells.shape[:2]
        canvas_h = title_h + max(map_h, 140) + bottom_h
        canvas_w = margin + max(map_w, 200) + right_w
        img = np.full((canvas_h, canvas_w, 3), 255, np.uint8)
        x0, y0 = margin, title_h
        img[y0 : y0 + map_h, x0 : x0 + map_w] = cells
        cv2.rectangle(img, (x0 - 1, y0 - 1), (x0 + map_w, y0 + map_h), (0, 0, 0), 1)
        title = f"{self.keys.vehicle}  {len(self.tiles)} tiles, {self.cells_known()} cells known"
        cv2.putText(img, title, (x0, 18), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)

        # Colour bar with the height range in metres.
        bx, bh = x0 + max(map_w, 200) + 14, max(map_h, 140) - 30
        ramp = np.linspace(255, 0, bh).astype(np.uint8).reshape(-1, 1)
        img[y0 + 24 : y0 + 24 + bh, bx : bx + 14] = cv2.applyColorMap(ramp, COLORMAP).repeat(14, axis=1)
        cv2.putText(img, f"{hi:.1f} m", (bx + 18, y0 + 32), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, f"{lo:.1f} m", (bx + 18, y0 + 24 + bh), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        img[y0 : y0 + 12, bx : bx + 14] = UNKNOWN_BGR
        cv2.putText(img, "unknown", (bx + 18, y0 + 10), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)

        # North arrow, top-right of the map.
        ax, ay = x0 + max(map_w, 200) - 14, y0 + 30
        cv2.arrowedLine(img, (ax, ay), (ax, ay - 22), (0, 0, 0), 2, cv2.LINE_AA, tipLength=0.35)
        cv2.putText(img, "N", (ax - 5, ay + 14), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)

        # Scale bar: the largest 1-2-5 length that fits in a third of the map width.
        px_per_m = cell_px / m.cell_size_m
        want_m = max(map_w / 3.0, 20) / px_per_m
        exp = 10.0 ** math.floor(math.log10(want_m))
        length_m = max(f * exp for f in (1.0, 2.0, 5.0) if f * exp <= want_m)
        length_px = max(1, int(round(length_m * px_per_m)))
        sy = y0 + max(map_h, 140) + 18
        cv2.line(img, (x0, sy), (x0 + length_px, sy), (0, 0, 0), 2)
        for x in (x0, x0 + length_px):
            cv2.line(img, (x, sy - 5), (x, sy + 5), (0, 0, 0), 1)
        cv2.putText(img, f"{length_m:g} m", (x0 + length_px + 8, sy + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)

        layout = MapLayout(x0, y0, cell_px, rows, cols, m.north0_m, m.east0_m, m.cell_size_m, lo, hi)
        return img, layout

    def write_png(self, path: str | Path) -> MapLayout | None:
        """Render and replace ``path`` atomically (a viewer never sees a half-written file)."""
        path = Path(path)
        img, layout = self.render()
        ok, data = cv2.imencode(".png", img)
        if not ok:
            raise RuntimeError("PNG encoding failed")
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data.tobytes())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return layout

    # ---- summary -----------------------------------------------------------------------------

    def summary(self) -> str:
        """One line: map size, height range, vehicle status and avoidance state, error counts."""
        parts = [f"{self.keys.vehicle}: {len(self.tiles)} tiles, {self.cells_known()} cells known"]
        span = self.height_range()
        if span is not None:
            shift = 0.0 if self.status is None else map_frame_shift(self.status)
            frame = f" (map frame; {shift:+.2f} m to the vehicle's)" if shift else ""
            parts.append(f"height {span[0]:.1f}..{span[1]:.1f} m{frame}")
        if self.status is None:
            parts.append("status: none yet")
        else:
            age = time.monotonic() - (self.status_rx_monotonic or time.monotonic())
            state = self.status.get("state", "?")
            parts.append(f"status #{self.status.get('seq')} {state} ({age:.1f} s ago)")
        if self.avoidance is not None:
            a = self.avoidance
            climb = a.get("climb_rate_mps")
            climb_txt = f"{climb:+.2f} m/s" if isinstance(climb, (int, float)) else "-"
            parts.append(f"avoidance {a.get('mode')} {'ENGAGED' if a.get('engaged') else 'clear'} climb {climb_txt}")
        bad = self.counts["bad_tiles"] + self.counts["bad_json"]
        parts.append(f"rx {self.counts['tiles_rx']} tiles, {bad} bad, {self.counts['stale_tiles']} stale")
        return " | ".join(parts)


class GroundStation:
    """The Zenoh side: subscriptions and map queries feeding one :class:`GroundMap` per vehicle.

    ``vehicles``: the vehicles followed (default: ``cfg.vehicle_name``), or ``("*",)`` for every
    vehicle that publishes under ``companion/``. :attr:`map` is the first vehicle's map (the PNG
    and the summary line are of it); :attr:`maps` holds them all, a vehicle's map created when
    its first sample arrives.

    Zenoh delivers samples on its own threads; they are queued and applied by :meth:`poll` on
    the caller's thread, so the maps are only ever touched by one thread.
    """

    def __init__(self, cfg: ZenohConfig, gmap: GroundMap | None = None, *, query_timeout_s: float = 5.0,
                 max_queue: int = 10_000, vehicles: tuple[str, ...] | None = None) -> None:
        self.cfg = cfg
        self.vehicles = tuple(vehicles) if vehicles else (cfg.vehicle_name,)
        self.every_vehicle = self.vehicles == ("*",)
        primary = cfg.vehicle_name if self.every_vehicle else self.vehicles[0]
        self.map = gmap or GroundMap(primary)
        self.maps: dict[str, GroundMap] = {self.map.keys.vehicle: self.map}
        if not self.every_vehicle:
            for v in self.vehicles:
                self.maps.setdefault(v, GroundMap(v))
        self.keys = self.map.keys
        self.query_timeout_s = query_timeout_s
        self._q: queue.Queue = queue.Queue(maxsize=max_queue)
        self._resync = threading.Event()
        self._session = None
        self._declared: list[Any] = []
        self.dropped = 0
        self.syncs = 0
        self.tile_queries = 0  # tiles asked for whole after a missed delta

    def _roots(self) -> list[str]:
        """The key roots subscribed and queried: one per vehicle followed, or the wildcard."""
        return [f"{KEY_ROOT}/*"] if self.every_vehicle else [BusKeys(v).root for v in self.maps]

    def map_for(self, key: str) -> GroundMap | None:
        """The map a sample's key belongs to (created for a newly seen vehicle when following every one)."""
        parts = key.split("/")
        if len(parts) < 3 or parts[0] != KEY_ROOT:
            return None
        vehicle = parts[1]
        if vehicle not in self.maps and self.every_vehicle:
            try:
                self.maps[vehicle] = GroundMap(vehicle)
            except BusError:
                return None
        return self.maps.get(vehicle)

    def open(self) -> None:
        try:
            self._session = zenoh.open(zenoh_config(self.cfg))
        except zenoh.ZError as exc:
            raise BusError(f"zenoh: cannot open the ground station's {self.cfg.mode} session: {exc}") from None
        s = self._session
        self._declared = []
        for root in self._roots():
            self._declared += [
                s.declare_subscriber(f"{root}/terrain/tile/*/*", self._on_sample),
                s.declare_subscriber(f"{root}/status", self._on_sample),
                s.declare_subscriber(f"{root}/avoidance", self._on_sample),
                # A vehicle's token appearing (at start-up or after a link loss) means "ask again".
                s.liveliness().declare_subscriber(f"{root}/alive", self._on_alive, history=True),
            ]
        self._resync.set()

    def close(self) -> None:
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001 - best effort on teardown
                pass
        self._declared = []
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "GroundStation":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def links(self) -> list[str]:
        """Remote locators of the open Zenoh links (empty while not connected)."""
        if self._session is None:
            return []
        return [str(link.dst) for link in self._session.info.links()]

    @staticmethod
    def _stamp(sample) -> int | None:
        ts = sample.timestamp
        return None if ts is None else ts.get_time_as_ntp64().as_nanos()

    def _on_sample(self, sample) -> None:
        try:
            self._q.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), self._stamp(sample)))
        except queue.Full:
            self.dropped += 1

    def _on_alive(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._resync.set()

    def sync(self) -> int:
        """Ask the vehicles for their whole maps (``terrain/tile/**``); returns the tiles applied."""
        self._resync.clear()
        self.syncs += 1
        applied = 0
        for root in self._roots():
            for reply in self._session.get(f"{root}/terrain/tile/**", timeout=self.query_timeout_s):
                sample = reply.ok
                if sample is None:
                    self.map.reject("query_errors", f"map query error: {reply.err.payload.to_bytes()[:200]!r}")
                    continue
                applied += self._apply(str(sample.key_expr), sample.payload.to_bytes(), self._stamp(sample))
        return applied

    def _apply(self, key: str, payload: bytes, stamp: int | None) -> bool:
        gmap = self.map_for(key)
        if gmap is None:
            self.map.counts["ignored"] += 1
            return False
        return gmap.apply(key, payload, stamp)

    def poll(self) -> int:
        """Apply queued samples (and re-sync when asked); returns the samples handled. A tile whose
        delta could not be applied (its base was missed) is then asked for whole."""
        if self._resync.is_set():
            self.sync()
        n = 0
        while True:
            try:
                key, payload, stamp = self._q.get_nowait()
            except queue.Empty:
                break
            self._apply(key, payload, stamp)
            n += 1
        for gmap in list(self.maps.values()):
            if gmap.missing and self._session is not None:
                self.ask_tiles(gmap)
        return n

    def ask_tiles(self, gmap: GroundMap) -> int:
        """Ask the vehicle for each of ``gmap.missing`` whole; returns the tiles applied."""
        wanted, gmap.missing = sorted(gmap.missing), set()
        applied = 0
        for tx, ty in wanted:
            for reply in self._session.get(gmap.keys.tile(tx, ty), timeout=self.query_timeout_s):
                sample = reply.ok
                if sample is None:
                    gmap.reject("query_errors", f"tile query error: {reply.err.payload.to_bytes()[:200]!r}")
                    continue
                applied += gmap.apply(str(sample.key_expr), sample.payload.to_bytes(), self._stamp(sample))
        self.tile_queries += len(wanted)
        return applied

    def run(self, *, duration_s: float = 0.0, png: str | None = None, png_every_s: float = 2.0,
            summary_every_s: float = 1.0, out: TextIO | None = None, tick_s: float = 0.05,
            stop: threading.Event | None = None, feed=None) -> None:
        """Poll until ``duration_s`` passed (0: forever) or ``stop`` is set, writing the PNG and summary;
        ``feed`` (:class:`drivers.ground_web.LiveFeed`) gets every change for the browsers."""
        out = out or sys.stdout
        start = time.monotonic()
        next_png = next_summary = start
        while True:
            now = time.monotonic()
            self.poll()
            if feed is not None:
                for gmap in list(self.maps.values()):
                    feed.update_from(gmap)
            if png and now >= next_png:
                self.map.write_png(png)
                next_png = now + png_every_s
            if summary_every_s > 0 and now >= next_summary:
                print(f"[{now - start:7.1f} s] {self.map.summary()}", file=out, flush=True)
                next_summary = now + summary_every_s
            if (duration_s and now - start >= duration_s) or (stop is not None and stop.is_set()):
                break
            time.sleep(tick_s)
        self.poll()
        if png:
            self.map.write_png(png)
        print(f"[{time.monotonic() - start:7.1f} s] final: {self.map.summary()}", file=out, flush=True)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="YAML", help="take the zenoh section (vehicle, endpoints, TLS file) from this file")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint of the vehicle or a router, e.g. tcp/192.168.1.10:7447 (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    p.add_argument("--mode", choices=("peer", "client"), help="Zenoh mode (default: peer, or the config file's)")
    p.add_argument("--vehicle", action="append", default=[],
                   help="vehicle name: the <vehicle> of companion/<vehicle>/... (default vehicle1); repeat it to follow "
                        "several (the PNG and the summary are of the first, the page shows them all)")
    p.add_argument("--all-vehicles", action="store_true", help="follow every vehicle publishing under companion/ (a fleet)")
    p.add_argument("--zenoh-config", metavar="JSON5", help="extra Zenoh config file (TLS, access control)")
    p.add_argument("--multicast-scouting", action="store_true", help="also discover the vehicle by UDP multicast")
    p.add_argument("--http", metavar="HOST:PORT", help="serve the live map to browsers here, e.g. 127.0.0.1:8080 "
                                                        "(0.0.0.0:8080 for a phone on the same network)")
    p.add_argument("--png", metavar="PATH", help="rewrite this PNG of the map every --png-every seconds")
    p.add_argument("--png-every", type=float, default=2.0, metavar="S")
    p.add_argument("--summary-every", type=float, default=1.0, metavar="S", help="0 = only the final summary")
    p.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0 = run until Ctrl-C)")


def _settings(args: argparse.Namespace) -> ZenohConfig:
    cfg = load_config(args.config).zenoh if args.config else ZenohConfig()
    changes: dict[str, Any] = {}
    if args.connect:
        changes["connect"] = tuple(args.connect)
    if args.listen:
        changes["listen"] = tuple(args.listen)
    if args.mode:
        changes["mode"] = args.mode
    if args.vehicle:
        changes["vehicle_name"] = args.vehicle[0]
    if args.zenoh_config:
        changes["config_file"] = args.zenoh_config
    if args.multicast_scouting:
        changes["multicast_scouting"] = True
    return replace(cfg, **changes)


def main(args: argparse.Namespace) -> int:
    for name in ("png_every", "summary_every", "duration"):
        if getattr(args, name) < 0 or not math.isfinite(getattr(args, name)):
            print(f"companion ground: --{name.replace('_', '-')} must be a finite number >= 0", file=sys.stderr)
            return 2
    if args.png_every <= 0:
        print("companion ground: --png-every must be > 0", file=sys.stderr)
        return 2
    address = None
    if args.http:
        from drivers.ground_web import parse_address

        try:
            address = parse_address(args.http)
        except ValueError as exc:
            print(f"companion ground: --http {exc}", file=sys.stderr)
            return 2
    try:
        cfg = _settings(args)
        station = GroundStation(cfg, vehicles=("*",) if args.all_vehicles else (tuple(args.vehicle) or None))
        station.open()
    except (ConfigError, BusError) as exc:
        print(f"companion ground: {exc}", file=sys.stderr)
        return 1
    web = feed = None
    if address is not None:
        from drivers.ground_web import LiveFeed, MapWebServer

        feed = LiveFeed(f"companion ground ({'every vehicle' if station.every_vehicle else ', '.join(station.vehicles)})")
        try:
            web = MapWebServer(feed, *address).start()
        except OSError as exc:
            station.close()
            print(f"companion ground: --http {args.http}: cannot listen: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"companion ground: live map at {web.url}", flush=True)
    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        station.run(duration_s=args.duration, png=args.png, png_every_s=args.png_every,
                    summary_every_s=args.summary_every, stop=stop, feed=feed)
    except KeyboardInterrupt:
        pass
    finally:
        if web is not None:
            web.close()
        station.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0
