"""The autopilot link: MAVLink 2 over UDP, TCP or a serial port, asyncio-native.

:class:`AutopilotLink` is one long-running task of the daemon (``await link.run()`` inside its
TaskGroup). It

* opens the connection string as MAVProxy / mavlink-router users write it
  (:func:`drivers.autopilot.connection.parse_connection`, :mod:`drivers.autopilot.transport`);
* sends HEARTBEAT at ``link.heartbeat_rate_hz`` as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID
  from ``source_system`` / ``source_component`` (191 = MAV_COMP_ID_ONBOARD_COMPUTER);
* waits for an autopilot's HEARTBEAT (autopilot field not MAV_AUTOPILOT_INVALID, not a GCS or an
  onboard controller, ``target_system`` if configured), and tells ArduPilot (MAV_AUTOPILOT_ARDUPILOTMEGA)
  from PX4 (MAV_AUTOPILOT_PX4);
* requests every stream it can use with MAV_CMD_SET_MESSAGE_INTERVAL, one command at a time so each
  COMMAND_ACK (which names only the command) is known to belong to one message; records ACCEPTED /
  DENIED, and requests again, with backoff, a stream that was accepted but does not arrive
  (ArduPilot streams nothing until asked, and sends LOCAL_POSITION_NED only once its EKF origin
  exists) (:mod:`drivers.autopilot.streams`);
* runs TIMESYNC round trips (and answers the autopilot's own), maps autopilot time to companion
  time (:class:`companion.method.navigation.timesync.TimeSync`) and detects autopilot reboots
  (:mod:`drivers.autopilot.timing`);
* feeds navigation messages to :class:`companion.method.navigation.assembler.NavAssembler` and the resulting
  NavState to :attr:`nav_buffer` (thread-safe: the mapper reads it from its worker thread)
  (:mod:`drivers.autopilot.receive`);
* sends velocity setpoints only when commanding is enabled, navigation is fresh and healthy and
  the vehicle is in GUIDED (ArduPilot) / OFFBOARD (PX4); otherwise the numbers are recorded as
  advisory and nothing is sent (:mod:`drivers.autopilot.commanding`);
* declares the link lost after ``heartbeat_timeout_s`` of autopilot silence and reconnects with
  exponential backoff capped at ``reconnect_backoff_max_s``;
* reports all of it in :meth:`status` (:mod:`drivers.autopilot.status`).

The class is assembled from those parts, one file per responsibility; they share the link's state,
which this file creates in ``__init__``, and the connection's life (run, session, heartbeat,
reconnection, signing, sending) stays here.

Why not ``mavutil.mavlink_connection``: its TCP connect blocks (with sleeps between retries),
its serial class needs pyserial (not a dependency), it selects MAVLink 1 or 2 through a
process-wide environment variable and dialect global, and it has no asyncio integration. Here
the sockets are asyncio transports (UDP datagram endpoint, TCP stream, a non-blocking tty fd on
``loop.add_reader``), so reading never blocks the event loop and no thread is needed; pymavlink's
generated MAVLink 2 ``ardupilotmega`` dialect does the encoding, CRC and decoding. Framing is
:class:`drivers.autopilot.framing.MavlinkFramer`, which resynchronises after every bad frame (pymavlink's
robust parser drops up to 280 bytes after a stray start byte, valid frames included) and checks
MAVLink 2 signatures itself: bad input becomes a counted rejection (by category, logged once per
kind and then at most every 30 s), never an exception, and the valid frames around it get through.

Everything runs on the event loop thread; only :attr:`nav_buffer` may be read from other threads.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import stat
import time
from collections import deque
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.config import CompanionConfig, ConfigError
from companion.method.navigation.assembler import NavAssembler, TruthPose
from companion.method.navigation.buffer import NavBuffer
from companion.method.navigation.timesync import TimeSync
from drivers.autopilot.commanding import Commanding, PendingCommand, SetpointRecord
from drivers.autopilot.connection import parse_connection
from drivers.autopilot.framing import MavlinkFramer, SignatureCheck
from drivers.autopilot.meters import LogLimiter, RateMeter
from drivers.autopilot.protocol import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_INVALID,
    MAV_AUTOPILOT_PX4,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_STATE_ACTIVE,
    MAV_TYPE_GCS,
    MAV_TYPE_ONBOARD_CONTROLLER,
    ardupilot_mode_name,
    mav_type_name,
    px4_mode_name,
    statustext_chunks,
)
from drivers.autopilot.receive import Receiving
from drivers.autopilot.status import LinkStatus
from drivers.autopilot.streams import StreamRequest, StreamRequests
from drivers.autopilot.timing import TimeSyncing
from drivers.autopilot.transport import Transport, make_transport
from drivers.clock import Clock

log = logging.getLogger("drivers.autopilot")  # one logger for the whole link, whichever part speaks

SIGNING_KEY_BYTES = 32
# A signing key readable or writable by anyone but its owner is refused (as ssh refuses a private key).
SIGNING_KEY_FORBIDDEN_MODE = 0o077


class AutopilotLink(Receiving, StreamRequests, TimeSyncing, Commanding, LinkStatus):
    """MAVLink link to one autopilot. See the module docstring for the behaviour.

    Public API (event loop thread unless noted):
      ``await run()``; ``nav_buffer`` (any thread); ``status() -> dict``;
      ``send_setpoint(velocity_ned_mps, yaw_rad=None, yaw_rate_radps=None, position_ned_m=None) -> bool``;
      ``can_command() -> (bool, reason)``; ``send_statustext(severity, text) -> int``;
      ``await set_mode(name)``, ``await arm()``, ``await disarm()``, ``await takeoff(alt_m)`` (only when allowed
      by ``control.allow_mode_change`` / ``control.allow_arm``); ``truth_pose()``; ``await wait_connected(timeout)``;
      ``record_telemetry(path | None)`` (a .tlog of every packet in and out).
    """

    def __init__(self, cfg: CompanionConfig, clock: Clock | None = None) -> None:
        self.cfg = cfg
        self.clock = clock or Clock()
        lc = cfg.link
        try:
            self.endpoint = parse_connection(lc.connection, lc.baud)
        except ValueError as exc:
            raise ConfigError(f"link.connection: {exc}") from exc
        self.timesync = TimeSync(reboot_threshold_s=1.0)
        self.assembler = NavAssembler(cfg.nav, time_map=self.timesync.to_companion)
        self.nav_buffer = NavBuffer(cfg.nav.buffer_s, cfg.nav.buffer_max_gap_s, cfg.nav.buffer_extrapolate_s)
        self.rates = RateMeter()
        # _mav encodes (and signs) what we send; _framer decodes what we receive.
        self._mav = mavlink2.MAVLink(None, srcSystem=lc.source_system, srcComponent=lc.source_component)
        self.signing = self._setup_signing()
        self._framer = MavlinkFramer(self.signing)
        self._limiter = LogLimiter()
        self.assembler.rejections.listener = lambda reason, detail: self._limiter(
            logging.WARNING, f"nav-{reason}", f"autopilot link: navigation input rejected ({reason}: {detail[:80]})"
        )

        self._transport: Transport | None = None
        self._lost_event: asyncio.Event | None = None
        self._state = "stopped"
        self._target: tuple[int, int] | None = None
        self._heartbeat: Any = None
        self._last_heartbeat: float | None = None
        self._lost_since: float | None = None
        self._connected_event = asyncio.Event()
        self._command_lock: asyncio.Lock | None = None
        self._pending: PendingCommand | None = None
        self._timesync_sent: dict[int, float] = {}
        self._statustext_queue: deque[tuple[int, str]] = deque(maxlen=16)
        self._statustext_id = 0
        self._need_stream_request = False
        self._fallback_requested = False
        self._streams = self._wanted_streams()
        self._oneshots: dict[str, StreamRequest] = {
            "GPS_GLOBAL_ORIGIN": StreamRequest("GPS_GLOBAL_ORIGIN", mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0.0),
            "HOME_POSITION": StreamRequest("HOME_POSITION", mavlink2.MAVLINK_MSG_ID_HOME_POSITION, 0.0),
        }
        self._seen_estimator_resets = 0
        self._seen_time_resets = 0
        self._seen_basis_changes = 0
        self._tlog: Any = None  # open binary file while recording telemetry
        self._tlog_anchor = (0.0, 0.0)  # (unix time, companion time) sampled together
        self._tlog_path: Path | None = None
        self.tlog_records = 0

        # Counters for the status.
        self.wire_errors: dict[str, int] = {}
        self.time_rejections: dict[str, int] = {}
        self.handler_errors: dict[str, int] = {}
        self.last_error = ""
        self.bytes_rx = 0
        self.messages_rx = 0
        self.messages_tx = 0
        self.ignored_messages = 0
        self.ignored_sources: dict[str, int] = {}
        self.connects = 0
        self.reconnects = 0
        self.link_losses = 0
        self.reboots = 0
        self.setpoints_sent = 0
        self.setpoints_refused = 0
        self.last_setpoint: SetpointRecord | None = None
        self._setpoint_times: deque[float] = deque(maxlen=64)

    # ------------------------------------------------------------------------------------------
    # Configuration helpers
    # ------------------------------------------------------------------------------------------

    def _setup_signing(self) -> SignatureCheck | None:
        """MAVLink 2 signing from ``link.signing_key_file``; ConfigError naming the key for a bad file.

        The file holds the 32-byte secret, raw or as 64 hex characters. Like ssh with a private key,
        a key file that its group or others may read or write is refused: whoever reads it can
        command the vehicle.
        """
        path = self.cfg.link.signing_key_file
        if not path:
            if self.cfg.link.signing_required:
                raise ConfigError("link.signing_required is true but link.signing_key_file is empty: give the key file")
            return None
        where = f"link.signing_key_file {path!r}"
        try:
            st = os.stat(path)
            if not stat.S_ISREG(st.st_mode):
                raise ConfigError(f"{where}: not a regular file")
            if st.st_mode & SIGNING_KEY_FORBIDDEN_MODE:
                raise ConfigError(
                    f"{where}: permissions {stat.S_IMODE(st.st_mode):04o} are too open (readable or writable by group "
                    f"or others); the key lets anyone command the vehicle: chmod 600 {path}"
                )
            raw = Path(path).read_bytes()
        except OSError as exc:
            raise ConfigError(f"{where}: cannot read: {exc.strerror or exc}") from exc
        text = raw.strip()
        if len(raw) == SIGNING_KEY_BYTES:
            key = raw
        elif len(text) == 2 * SIGNING_KEY_BYTES and re.fullmatch(rb"[0-9A-Fa-f]{64}", text):
            key = bytes.fromhex(text.decode())
        else:
            raise ConfigError(f"{where}: expected 32 raw bytes or 64 hex characters, got {len(raw)} bytes")
        check = SignatureCheck(key, self.cfg.link.signing_required)
        s = self._mav.signing
        s.secret_key = key
        s.sign_outgoing = True
        s.link_id = 0
        s.timestamp = check.timestamp()
        return check

    # ------------------------------------------------------------------------------------------
    # Properties
    # ------------------------------------------------------------------------------------------

    @property
    def state(self) -> str:
        return self._state

    @property
    def connected(self) -> bool:
        return self._state == "connected"

    @property
    def target(self) -> tuple[int, int] | None:
        return self._target

    @property
    def flavour(self) -> str:
        configured = self.cfg.link.autopilot
        if configured != "auto":
            return configured
        if self._heartbeat is None:
            return "unknown"
        return {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}.get(self._heartbeat.autopilot, "generic")

    @property
    def armed(self) -> bool:
        return bool(self._heartbeat is not None and self._heartbeat.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode(self) -> str:
        hb = self._heartbeat
        if hb is None:
            return "UNKNOWN"
        if self.flavour == "ardupilot":
            return ardupilot_mode_name(hb.type, hb.custom_mode)
        if self.flavour == "px4":
            return px4_mode_name(hb.custom_mode)
        return f"custom {hb.custom_mode}"

    @property
    def local_address(self) -> tuple | None:
        return None if self._transport is None else self._transport.local_address

    def truth_pose(self) -> TruthPose | None:
        """Latest simulator truth (SIM_STATE) in the local NED frame, when ``link.request_sim_state``."""
        return self.assembler.truth_pose() if self.cfg.link.request_sim_state else None

    def record_telemetry(self, path: str | os.PathLike | None) -> None:
        """Write every MAVLink packet received (and sent) to ``path`` as a .tlog; None stops.

        The format MAVProxy and pymavlink write and ``mavutil.mavlink_connection(path)`` reads: per
        packet an 8-byte big-endian Unix time in microseconds (low 2 bits clear) and the packet
        exactly as on the wire. The Unix time is the companion clock at reception mapped through
        (time.time(), clock.now()) sampled together now, so ``unix = u0 + (t_s - t0) / speedup``
        holds as in the recorder's meta.yaml. Corrupt input (BAD_DATA) is not logged. An open error
        raises OSError; a write error later stops the recording and is logged (the link goes on).
        """
        if self._tlog is not None:
            with contextlib.suppress(OSError):
                self._tlog.close()
            self._tlog = None
            self._tlog_path = None
        if path is None:
            return
        self._tlog = open(path, "ab")  # noqa: SIM115 - owned by the link until stopped or replaced
        self._tlog_path = Path(path)
        self._tlog_anchor = (time.time(), self.clock.now())

    def _log_packet(self, t_companion: float, packet: bytes) -> None:
        unix0, t0 = self._tlog_anchor
        usec = int((unix0 + (t_companion - t0) / self.clock.speedup) * 1e6) & ~3
        try:
            self._tlog.write(usec.to_bytes(8, "big") + bytes(packet))
            self.tlog_records += 1
        except (OSError, ValueError) as exc:
            self._error(f"telemetry log {self._tlog_path}: {exc}; recording stopped", key="tlog")
            with contextlib.suppress(OSError, ValueError):
                self._tlog.close()
            self._tlog = None

    async def wait_connected(self, timeout_s: float) -> bool:
        """Wait (clock seconds) until an autopilot heartbeat is being received."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.clock.wall_seconds(timeout_s)):
                await self._connected_event.wait()
        return self.connected

    # ------------------------------------------------------------------------------------------
    # Run: connect, session, reconnect with backoff
    # ------------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Own the link until cancelled: connect, keep the session, reconnect with backoff."""
        lc = self.cfg.link
        backoff_min = min(0.25, lc.reconnect_backoff_max_s)
        backoff = backoff_min
        self._command_lock = asyncio.Lock()
        try:
            while True:
                self._set_state("connecting")
                self._lost_event = asyncio.Event()
                transport = make_transport(self.endpoint, self._on_bytes, self._on_transport_lost, lc.connect_timeout_s)
                try:
                    await transport.open()
                except (OSError, TimeoutError) as exc:
                    transport.close()
                    self._error(f"cannot open {self.endpoint}: {exc or type(exc).__name__}", key="open")
                    self._set_state("reconnecting")
                    await self.clock.sleep(backoff)
                    backoff = min(2 * backoff, lc.reconnect_backoff_max_s)
                    continue
                self._transport = transport
                self._framer.reset()  # a partial frame from the previous connection is not continued
                log.info("autopilot link: opened %s (local %s)", self.endpoint, transport.local_address)
                reached = False
                try:
                    reached = await self._session()
                finally:
                    transport.close()
                    self._transport = None
                    self._mark_lost("transport closed")
                if reached:
                    backoff = backoff_min
                self._set_state("reconnecting")
                await self.clock.sleep(backoff)
                backoff = min(2 * backoff, lc.reconnect_backoff_max_s)
        finally:
            if self._transport is not None:
                self._transport.close()
                self._transport = None
            self._set_state("stopped")
            self._fail_pending("link stopped")
            self.record_telemetry(None)

    async def _session(self) -> bool:
        """Run the periodic tasks until the transport is lost. True if an autopilot was heard."""
        assert self._lost_event is not None
        self._set_state("waiting_heartbeat")
        self._session_start = self.clock.now()
        self._heard_autopilot = False
        tasks = [
            asyncio.create_task(self._heartbeat_loop(), name="link-heartbeat"),
            asyncio.create_task(self._timesync_loop(), name="link-timesync"),
            asyncio.create_task(self._stream_loop(), name="link-streams"),
            asyncio.create_task(self._supervise_loop(), name="link-supervise"),
        ]
        lost = asyncio.create_task(self._lost_event.wait(), name="link-lost")
        try:
            done, _ = await asyncio.wait([lost, *tasks], return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not lost and not t.cancelled() and t.exception() is not None:
                    exc = t.exception()
                    log.error("autopilot link: %s failed: %r; reconnecting", t.get_name(), exc, exc_info=exc)
                    self.last_error = f"{t.get_name()} failed: {exc!r}"
        finally:
            for t in (lost, *tasks):
                t.cancel()
            await asyncio.gather(lost, *tasks, return_exceptions=True)
        return self._heard_autopilot

    def _on_transport_lost(self, reason: str) -> None:
        self._error(f"autopilot link lost: {reason}", key="transport")
        if self._lost_event is not None:
            self._lost_event.set()

    def _set_state(self, state: str) -> None:
        if state != self._state:
            log.debug("autopilot link: %s -> %s", self._state, state)
        self._state = state
        if state == "connected":
            self._connected_event.set()
        else:
            self._connected_event.clear()

    def _mark_lost(self, why: str) -> None:
        if self._state == "connected":
            self.link_losses += 1
            self._lost_since = self.clock.now()
            log.warning("autopilot link: lost (%s)", why)
        self._set_state("lost")
        for s in self._streams.values():  # ask again when the autopilot comes back
            s.result = "not requested"
        self._fail_pending(why)

    def _error(self, message: str, key: str) -> None:
        self.last_error = message
        self._limiter(logging.WARNING, key, message)

    def _fail_pending(self, why: str) -> None:
        p = self._pending
        if p is not None and not p.future.done():
            p.future.set_result("NO_LINK")

    # ------------------------------------------------------------------------------------------
    # Periodic tasks
    # ------------------------------------------------------------------------------------------

    async def _heartbeat_loop(self) -> None:
        period = 1.0 / self.cfg.link.heartbeat_rate_hz
        while True:
            self._send(self._mav.heartbeat_encode(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE))
            if self._tlog is not None:
                try:
                    self._tlog.flush()  # at most a heartbeat period of telemetry is lost in a crash
                except OSError as exc:
                    self._error(f"telemetry log {self._tlog_path}: {exc}; recording stopped", key="tlog")
                    self._tlog = None
            await self.clock.sleep(period)

    async def _supervise_loop(self) -> None:
        """Heartbeat timeout -> lost; TCP to a silent peer -> reconnect."""
        lc = self.cfg.link
        while True:
            await self.clock.sleep(min(0.1, lc.heartbeat_timeout_s / 5))
            now = self.clock.now()
            if self._state == "connected" and self._last_heartbeat is not None and now - self._last_heartbeat > lc.heartbeat_timeout_s:
                self._mark_lost(f"no HEARTBEAT for {now - self._last_heartbeat:.1f} s")
                self.last_error = f"autopilot heartbeat timeout ({lc.heartbeat_timeout_s:.1f} s)"
                if self._transport is not None and self._transport.stream and self.endpoint.kind == "tcp":
                    return  # a silent TCP peer: reconnect rather than wait on a dead connection
            elif self._state == "waiting_heartbeat" and self.endpoint.kind == "tcp" and now - self._session_start > 2 * lc.heartbeat_timeout_s:
                self._error(f"no autopilot HEARTBEAT on {self.endpoint} within {2 * lc.heartbeat_timeout_s:.1f} s", key="no-heartbeat")
                return

    # ------------------------------------------------------------------------------------------
    # Sending
    # ------------------------------------------------------------------------------------------

    def _send(self, msg: Any) -> bool:
        t = self._transport
        if t is None:
            return False
        if self.signing is not None:
            # The wall clock, never going back (pymavlink would only add 1 per message, and a stamp
            # that falls behind real time is refused as stale by a receiver that restarts).
            self._mav.signing.timestamp = self.signing.timestamp()
        try:
            buf = msg.pack(self._mav)
        except Exception as exc:  # a value out of its field's range: a bug in the caller, say which
            self._error(f"cannot encode {msg.get_type()}: {exc}", key=f"encode-{msg.get_type()}")
            return False
        self._mav.seq = (self._mav.seq + 1) % 256
        ok = t.write(buf)
        if ok:
            self.messages_tx += 1
            if self._tlog is not None:
                self._log_packet(self.clock.now(), buf)
        return ok

    # ------------------------------------------------------------------------------------------
    # The autopilot's heartbeat: who we follow, and when the link is up
    # ------------------------------------------------------------------------------------------

    def _on_heartbeat(self, m: Any, src: tuple[int, int], now: float) -> None:
        if m.autopilot == MAV_AUTOPILOT_INVALID or m.type in (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER):
            self._ignore(src)
            return  # a GCS, another companion, a gimbal or camera: not an autopilot
        wanted = self.cfg.link.target_system
        if wanted and src[0] != wanted:
            self._ignore(src)
            return
        if self._target is not None and src != self._target:
            if self._state == "connected":
                self._ignore(src)
                return  # a second autopilot while ours is alive
            log.warning("autopilot link: switching from autopilot %s to %s", self._target, src)
            self._target = None
        if self._target is None:
            self._target = src
            self.timesync.reset()
            self._seen_time_resets = self.timesync.resets
            self.assembler.reset()
            self.nav_buffer.clear()
            self._want_oneshots_again(now)
        self._heartbeat = m
        self._last_heartbeat = now
        self._heard_autopilot = True
        self.rates.tick("HEARTBEAT", now)
        if self._state != "connected":
            self._on_connected(now)

    def _on_connected(self, now: float) -> None:
        first = self.connects == 0
        self.connects += 1
        if not first:
            self.reconnects += 1
        self._set_state("connected")
        self._need_stream_request = True
        self._fallback_requested = False
        configured = self.cfg.link.autopilot
        detected = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", MAV_AUTOPILOT_PX4: "px4"}.get(self._heartbeat.autopilot, "generic")
        if configured != "auto" and configured != detected:
            self.last_error = f"link.autopilot is {configured!r} but the HEARTBEAT says {detected!r}; using {configured!r}"
            log.warning("autopilot link: %s", self.last_error)
        log.info(
            "autopilot link: connected to system %d component %d (%s, %s, mode %s) over %s",
            self._target[0], self._target[1], detected, mav_type_name(self._heartbeat.type), self.mode, self.endpoint,
        )  # fmt: skip
        if self._lost_since is not None:
            gap = now - self._lost_since
            self._lost_since = None
            self.send_statustext("NOTICE", f"companion: autopilot link back after {gap:.1f} s")
        while self._statustext_queue:
            level, text = self._statustext_queue.popleft()
            self._send_statustext_now(level, statustext_chunks(text))
