"""The service's own recording (``companion run --record``: ``meta.yaml``, ``frames.csv``, ``frames/``,
``telemetry.tlog``; docs/cameras.md). Navigation is rebuilt from the telemetry log exactly as the
autopilot link builds it live (:class:`TelemetryNav`); corrupt telemetry bytes are skipped by
pymavlink's tlog reader and counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig, ConfigError, config_from_dict
from companion.desk.recordings.recording import (
    Overrides,
    Recording,
    RecordingError,
    RecordingStats,
    finite_float,
    sorted_frames,
    table_rows,
)
from companion.method.geometry import camera_from_config
from companion.method.navigation.buffer import NavBuffer, NavLookup

# MAVLink values the telemetry replay needs (common.xml).
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18


class TelemetryNav:
    """Navigation states from a telemetry log, built as the autopilot link builds them live
    (drivers/autopilot/receive.py): the first autopilot HEARTBEAT picks the target; TIMESYNC answers
    (``ts1`` = our send time in ns + 1, companion clock) and SYSTEM_TIME feed :class:`TimeSync`;
    an autopilot reboot (boot clock going backwards) or an estimator reset clears the state; the
    navigation messages go to :class:`NavAssembler` and its states into a :class:`NavBuffer`.

    ``to_companion(unix_s)`` maps a log timestamp (reception, Unix seconds) to the companion clock.
    :meth:`lookup` must be called with non-decreasing times: the log is read just far enough ahead
    (``lead_s``) that the states bracketing the time have arrived.
    """

    def __init__(self, path: Path, to_companion: Callable[[float], float], cfg: CompanionConfig, stats: RecordingStats,
                 lead_s: float = 1.0):
        self.path = path
        self.to_companion = to_companion
        self.cfg = cfg
        self.stats = stats
        self.lead_s = float(lead_s)
        self.own = (cfg.link.source_system, cfg.link.source_component)
        self._log = None
        self._pending: tuple[Any, float] | None = None
        self._eof = False

    def rewind(self) -> None:
        from companion.method.navigation.assembler import NavAssembler
        from companion.method.navigation.timesync import TimeSync

        if self._log is not None:
            self._log.close()
        self._log = None
        self._eof = not self.path.is_file()
        if not self._eof:
            from pymavlink import mavutil  # tlog reader: 8-byte big-endian microsecond time + packet

            self._log = mavutil.mavlogfile(str(self.path), robust_parsing=True)
        nav = self.cfg.nav
        self.timesync = TimeSync(reboot_threshold_s=1.0)
        self.assembler = NavAssembler(nav, time_map=self.timesync.to_companion)
        self.buffer = NavBuffer(max(nav.buffer_s, 2.0 * self.lead_s + 1.0), nav.buffer_max_gap_s,
                                nav.buffer_extrapolate_s, max_samples=100_000)
        self._target: tuple[int, int] | None = None
        self._reboots = 0
        self._estimator_resets = 0
        self._pending = None
        for key in ("telemetry_messages", "telemetry_bad", "telemetry_ignored", "nav_states"):
            setattr(self.stats, key, 0)
        self.stats.nav_rejected = {}

    def _next(self) -> tuple[Any, float] | None:
        if self._pending is not None:
            item, self._pending = self._pending, None
            return item
        while not self._eof:
            try:
                m = self._log.recv_msg()
            except Exception as exc:  # noqa: BLE001 - a damaged log ends the telemetry, not the replay
                self.stats.note(f"{self.path}: unreadable from here on: {exc}")
                self._eof = True
                return None
            if m is None:
                self._eof = True
                return None
            if m.get_type() == "BAD_DATA":
                self.stats.telemetry_bad += 1
                continue
            t = self.to_companion(float(m._timestamp))
            if not math.isfinite(t):
                self.stats.telemetry_bad += 1
                continue
            self.stats.telemetry_messages += 1
            return m, t
        return None

    def advance(self, t: float) -> None:
        """Dispatch every message received up to ``t + lead_s``."""
        horizon = t + self.lead_s
        while True:
            item = self._next()
            if item is None:
                return
            if item[1] > horizon:
                self._pending = item
                return
            self._dispatch(*item)

    def lookup(self, t: float) -> NavLookup:
        self.advance(t)
        if self._log is None and self.stats.telemetry_messages == 0:
            return NavLookup(None, f"no telemetry log ({self.path.name} missing)")
        return self.buffer.lookup(t)

    def _dispatch(self, m: Any, now: float) -> None:
        from companion.method.navigation.assembler import HANDLED_MESSAGES

        kind = m.get_type()
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == self.own:
            self.stats.telemetry_ignored += 1
            return
        if kind == "HEARTBEAT":
            autopilot = m.autopilot != MAV_AUTOPILOT_INVALID and m.type not in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER)
            wanted = self.cfg.link.target_system
            if autopilot and self._target is None and (not wanted or src[0] == wanted):
                self._target = src
                self.timesync.reset()
                self.assembler.reset()
                self.buffer.clear()
            return
        if self._target is None or src != self._target:
            self.stats.telemetry_ignored += 1
            return
        if kind == "TIMESYNC":
            if m.tc1 != 0:  # an answer: ts1 is the requester's send time (ns + 1 on our clock)
                self.timesync.add_roundtrip((m.ts1 - 1) * 1e-9, m.tc1 * 1e-9, now)
                self._check_reboot()
            return
        boot_ms = getattr(m, "time_boot_ms", None)
        if boot_ms:
            self.timesync.observe_remote_time(boot_ms * 1e-3)
            self._check_reboot()
        if kind == "SYSTEM_TIME" and m.time_boot_ms:
            self.timesync.add_one_way(m.time_boot_ms * 1e-3, now)
            self._check_reboot()
        if kind in HANDLED_MESSAGES:
            nav = self.assembler.update(m, now)
            if self.assembler.estimator_resets != self._estimator_resets:
                self._estimator_resets = self.assembler.estimator_resets
                self.buffer.clear()
            if nav is not None and self.buffer.push(nav):
                self.stats.nav_states += 1
            self.stats.nav_rejected = self.assembler.rejections.snapshot()

    def _check_reboot(self) -> None:
        if self.timesync.reboots != self._reboots:
            self._reboots = self.timesync.reboots
            self.stats.note(f"{self.path}: the autopilot rebooted (boot clock went backwards); navigation reset")
            self.assembler.reset()
            self.buffer.clear()


class CompanionRecording(Recording):
    kind = "companion"

    def __init__(self, *args, telemetry: TelemetryNav, **kwargs):
        super().__init__(*args, **kwargs)
        self.telemetry = telemetry

    def _start(self) -> None:
        self.telemetry.rewind()

    def _nav_at(self, t_s: float) -> NavLookup:
        return self.telemetry.lookup(t_s)


def open_companion(folder: Path, cfg: CompanionConfig, overrides: Overrides = Overrides()) -> CompanionRecording:
    """The service's own recording. The camera model and mount come from ``meta.yaml``'s ``camera``
    section (they belong to the images); ``cfg`` gives the nav and link settings used to rebuild
    navigation from ``telemetry.tlog``."""
    from drivers.cameras.recorder import read_recording_meta

    try:
        meta = read_recording_meta(folder)
    except ValueError as exc:
        raise RecordingError(str(exc)) from exc
    where = folder / "meta.yaml"
    try:
        cam_cfg = config_from_dict({"camera": meta.get("camera") or {}}, f"{where} (camera)").camera
    except ConfigError as exc:
        raise RecordingError(str(exc)) from exc
    camera, mount = camera_from_config(cam_cfg)
    clock = meta.get("clock") or {}
    try:
        t0, unix0, speedup = float(clock["t_s"]), float(clock["unix_time_s"]), float(clock.get("speedup", 1.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: 'clock' must give t_s, unix_time_s and speedup to align the telemetry with the frames") from exc
    if not (math.isfinite(t0) and math.isfinite(unix0) and speedup > 0):
        raise RecordingError(f"{where}: clock values must be finite with a positive speedup")

    stats = RecordingStats()
    files = meta.get("files") or {}
    csv_path = folder / str(files.get("frames_csv", "frames.csv"))
    if not csv_path.is_file():
        raise RecordingError(f"{csv_path}: missing (sequence,t_s,filename per frame)")
    rows = table_rows(csv_path, stats, sep=",")
    header = next(rows, None)
    if header is None or "t_s" not in header[1] or "filename" not in header[1]:
        raise RecordingError(f"{csv_path}: first line must be the header 'sequence,t_s,filename'")
    names = header[1]
    i_t, i_f = names.index("t_s"), names.index("filename")
    i_s = names.index("sequence") if "sequence" in names else None
    entries: list[tuple[int, Path, float, int]] = []
    for line_no, fields in rows:
        try:
            if len(fields) != len(names):
                raise ValueError(f"{len(fields)} fields, header has {len(names)}")
            if not fields[i_f]:
                raise ValueError("empty filename")
            seq = int(fields[i_s]) if i_s is not None else len(entries)
            entries.append((line_no, folder / fields[i_f], finite_float(fields[i_t], "t_s"), seq))
        except ValueError as exc:
            stats.bad_line(csv_path, line_no, str(exc))
    frames = sorted_frames(entries, csv_path, stats)
    tlog = folder / str(files.get("telemetry", "telemetry.tlog"))
    if not tlog.is_file():
        stats.note(f"{tlog}: missing; no frame has navigation")
    telemetry = TelemetryNav(tlog, lambda unix: t0 + (unix - unix0) * speedup, cfg, stats)
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else cfg.terrain.default_ground_alt_m
    return CompanionRecording(folder, camera, mount, frames, stats, ground_alt_m=ground, telemetry=telemetry)
