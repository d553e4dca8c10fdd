"""The autopilot link: MAVLink 2 over UDP, TCP or a serial port, asyncio-native.

:class:`AutopilotLink` is one long-running task of the daemon (``await link.run()`` inside its
TaskGroup). It

* opens the connection string as MAVProxy / mavlink-router users write it (:func:`parse_connection`);
* sends HEARTBEAT at ``link.heartbeat_rate_hz`` as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID
  from ``source_system`` / ``source_component`` (191 = MAV_COMP_ID_ONBOARD_COMPUTER);
* waits for an autopilot's HEARTBEAT (autopilot field not MAV_AUTOPILOT_INVALID, not a GCS or an
  onboard controller, ``target_system`` if configured), and tells ArduPilot (MAV_AUTOPILOT_ARDUPILOTMEGA)
  from PX4 (MAV_AUTOPILOT_PX4);
* requests every stream it can use with MAV_CMD_SET_MESSAGE_INTERVAL, one command at a time so each
  COMMAND_ACK (which names only the command) is known to belong to one message; records ACCEPTED /
  DENIED, and requests again, with backoff, a stream that was accepted but does not arrive
  (ArduPilot streams nothing until asked, and sends LOCAL_POSITION_NED only once its EKF origin
  exists);
* runs TIMESYNC round trips (and answers the autopilot's own), maps autopilot time to companion
  time (:class:`companion.method.navigation.timesync.TimeSync`) and detects autopilot reboots;
* feeds navigation messages to :class:`companion.method.navigation.assembler.NavAssembler` and the resulting
  NavState to :attr:`nav_buffer` (thread-safe: the mapper reads it from its worker thread);
* sends velocity setpoints only when commanding is enabled, navigation is fresh and healthy and
  the vehicle is in GUIDED (ArduPilot) / OFFBOARD (PX4); otherwise the numbers are recorded as
  advisory and nothing is sent;
* declares the link lost after ``heartbeat_timeout_s`` of autopilot silence and reconnects with
  exponential backoff capped at ``reconnect_backoff_max_s``.

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
import math
import os
import re
import stat
import termios
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.config import CompanionConfig, ConfigError
from companion.method.navigation.assembler import HANDLED_MESSAGES, NavAssembler, TruthPose
from companion.method.navigation.buffer import NavBuffer
from companion.method.navigation.timesync import TimeSync
from drivers.autopilot.framing import MavlinkFramer, Rejected, SignatureCheck
from drivers.clock import Clock

log = logging.getLogger("drivers.autopilot")  # the link's logger, whichever of its files speaks

# --------------------------------------------------------------------------------------------
# MAVLink facts used below (common.xml, ardupilotmega.xml)
# --------------------------------------------------------------------------------------------

MAV_TYPE_GCS = mavlink2.MAV_TYPE_GCS  # 6
MAV_TYPE_ONBOARD_CONTROLLER = mavlink2.MAV_TYPE_ONBOARD_CONTROLLER  # 18
MAV_AUTOPILOT_ARDUPILOTMEGA = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA  # 3
MAV_AUTOPILOT_PX4 = mavlink2.MAV_AUTOPILOT_PX4  # 12
MAV_AUTOPILOT_INVALID = mavlink2.MAV_AUTOPILOT_INVALID  # 8
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_STATE_ACTIVE = mavlink2.MAV_STATE_ACTIVE
MAV_RESULT_IN_PROGRESS = 5

# POSITION_TARGET_TYPEMASK (common.xml): a set bit means "ignore this field".
TYPEMASK_X, TYPEMASK_Y, TYPEMASK_Z = 1, 2, 4
TYPEMASK_VX, TYPEMASK_VY, TYPEMASK_VZ = 8, 16, 32
TYPEMASK_AX, TYPEMASK_AY, TYPEMASK_AZ = 64, 128, 256
TYPEMASK_YAW, TYPEMASK_YAW_RATE = 1024, 2048
TYPEMASK_POSITION = TYPEMASK_X | TYPEMASK_Y | TYPEMASK_Z
TYPEMASK_ACCEL = TYPEMASK_AX | TYPEMASK_AY | TYPEMASK_AZ
TYPEMASK_VELOCITY_ONLY = TYPEMASK_POSITION | TYPEMASK_ACCEL | TYPEMASK_YAW | TYPEMASK_YAW_RATE  # 3527

PX4_MAIN_MODES = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED", 8: "RATTITUDE"}
PX4_AUTO_SUB_MODES = {1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF"}
PX4_MAIN_OFFBOARD = 6
PX4_SET_MODE = {  # name -> (main mode, sub mode)
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "TAKEOFF": (4, 2), "LOITER": (4, 3), "HOLD": (4, 3),
    "MISSION": (4, 4), "RTL": (4, 5), "LAND": (4, 6), "ACRO": (5, 0), "OFFBOARD": (6, 0), "STABILIZED": (7, 0),
}  # fmt: skip
ARDUCOPTER_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL", 7: "CIRCLE", 9: "LAND",
    11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 16: "POSHOLD", 17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB",
    20: "GUIDED_NOGPS", 21: "SMART_RTL", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID", 26: "AUTOROTATE",
    27: "AUTO_RTL", 28: "TURTLE",
}  # fmt: skip
MULTIROTOR_TYPES = {2, 3, 4, 13, 14, 15, 29, 35}  # quad, coax, heli, hexa, octo, tri, dodeca, deca

SEVERITIES = {name: value for value, name in ((v, e.name.removeprefix("MAV_SEVERITY_")) for v, e in mavlink2.enums["MAV_SEVERITY"].items()) if name != "ENUM_END"}
STATUSTEXT_CHUNK = 50  # bytes per STATUSTEXT.text
STATUSTEXT_MAX_CHUNKS = 5

SIGNING_KEY_BYTES = 32
# A signing key readable or writable by anyone but its owner is refused (as ssh refuses a private key).
SIGNING_KEY_FORBIDDEN_MODE = 0o077
IGNORED_SOURCES_KEPT = 16  # the status lists at most this many other systems/components heard


def _result_name(value: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(int(value))
    return entry.name.removeprefix("MAV_RESULT_") if entry else f"RESULT_{value}"


# --------------------------------------------------------------------------------------------
# Connection strings
# --------------------------------------------------------------------------------------------

_CONNECTION_HELP = (
    "expected udpin:HOST:PORT, udpout:HOST:PORT, udp:HOST:PORT (= udpin), tcp:HOST:PORT, tcpin:HOST:PORT, "
    "the URL forms udp://, udpin://, udpout://, tcp://, tcpout://, tcpin://, serial:///dev/ttyX:BAUD, "
    "or a serial device such as /dev/ttyAMA0 or /dev/ttyAMA0,921600"
)
_SCHEMES = {"udpin": "udpin", "udp": "udpin", "udpout": "udpout", "tcp": "tcp", "tcpout": "tcp", "tcpin": "tcpin", "serial": "serial"}
_LISTENING = {"udpin", "tcpin"}


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed connection string. kind: udpin | udpout | tcp | tcpin | serial."""

    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"{self.device},{self.baud}"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.kind}:{host}:{self.port}"

    @property
    def listening(self) -> bool:
        return self.kind in _LISTENING


def parse_connection(text: str, baud: int = 115200) -> Endpoint:
    """Parse a connection string as MAVProxy, mavlink-router and MAVSDK users write it.

    ``udpin:0.0.0.0:14550`` listen for UDP (replies go to the last sender), ``udpout:10.0.0.2:14550``
    send to a fixed address, ``tcp:127.0.0.1:5760`` connect (SITL), ``tcpin:0.0.0.0:5760`` accept one
    client, ``/dev/ttyAMA0`` or ``/dev/ttyAMA0,921600`` (MAVProxy) or ``/dev/ttyACM0:57600`` or
    ``serial:///dev/ttyAMA0:921600`` (MAVSDK) a serial port; ``baud`` applies when the string has none.
    Raises ValueError naming the string and the accepted forms.
    """
    s = text.strip() if isinstance(text, str) else ""
    if not s:
        raise ValueError(f"empty connection string; {_CONNECTION_HELP}")
    if s.startswith("/"):
        return _serial(s, baud, text)
    m = re.fullmatch(r"([A-Za-z]+):(//)?(.*)", s)
    if not m or m.group(1).lower() not in _SCHEMES:
        raise ValueError(f"connection string {text!r} not understood; {_CONNECTION_HELP}")
    kind, rest = _SCHEMES[m.group(1).lower()], m.group(3)
    if kind == "serial":
        return _serial(rest, baud, text)
    hm = re.fullmatch(r"(\[[0-9A-Fa-f:.]+\]|[^:\[\]]*):(\d+)", rest)
    if not hm:
        raise ValueError(f"connection string {text!r}: expected HOST:PORT after '{m.group(1)}:'")
    host = hm.group(1).strip("[]") or ("0.0.0.0" if kind in _LISTENING else "")
    if not host:
        raise ValueError(f"connection string {text!r}: a host is needed to send to")
    port = int(hm.group(2))
    if port > 65535 or (port == 0 and kind not in _LISTENING):
        raise ValueError(f"connection string {text!r}: port {port} out of range (1..65535; 0 only when listening)")
    return Endpoint(kind, host=host, port=port)


def _serial(spec: str, baud: int, text: str) -> Endpoint:
    m = re.fullmatch(r"(/[^,:]+)(?:[,:](\d+))?", spec)
    if not m:
        raise ValueError(f"connection string {text!r}: expected a device path with an optional ,BAUD or :BAUD")
    rate = int(m.group(2)) if m.group(2) else int(baud)
    if rate <= 0:
        raise ValueError(f"connection string {text!r}: baud rate must be positive")
    return Endpoint("serial", device=m.group(1), baud=rate)


# --------------------------------------------------------------------------------------------
# Transports (asyncio; the link gives them two callbacks)
# --------------------------------------------------------------------------------------------

OnBytes = Callable[..., bool]  # (data, packet_end=False) -> a frame was accepted; packet_end: a whole datagram
OnLost = Callable[[str], None]
TCP_WRITE_BUFFER_LIMIT = 256 * 1024


class Transport:
    """Byte pipe to the autopilot. ``stream`` transports end the session when the peer goes away."""

    stream = False

    def __init__(self, endpoint: Endpoint, on_bytes: OnBytes, on_lost: OnLost, connect_timeout_s: float = 3.0) -> None:
        self.endpoint = endpoint
        self.on_bytes = on_bytes
        self.on_lost = on_lost
        self.connect_timeout_s = connect_timeout_s
        self.dropped_writes = 0

    async def open(self) -> None:
        raise NotImplementedError

    def write(self, data: bytes) -> bool:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def _write_stream(self, t: asyncio.Transport | None, data: bytes) -> bool:
        """Write to a TCP transport unless it is gone or backed up (a slow peer must not grow memory)."""
        if t is None or t.is_closing() or t.get_write_buffer_size() > TCP_WRITE_BUFFER_LIMIT:
            self.dropped_writes += 1
            return False
        t.write(data)
        return True

    @property
    def local_address(self) -> tuple | None:
        return None


class _DatagramProtocol(asyncio.DatagramProtocol):
    def __init__(self, owner: "UdpTransport") -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: tuple) -> None:
        self.owner._received(data, addr)

    def error_received(self, exc: Exception) -> None:  # ICMP port unreachable and the like: the peer may come back
        self.owner.errors += 1

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.owner._closing:
            self.owner.on_lost(f"UDP socket closed: {exc}")


class UdpTransport(Transport):
    """udpin: bind and answer the last sender (as MAVProxy's udpin); udpout: send to a fixed address."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._transport: asyncio.DatagramTransport | None = None
        self.peer: tuple | None = None
        self.errors = 0
        self._closing = False

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        e = self.endpoint
        if e.kind == "udpin":
            self._transport, _ = await loop.create_datagram_endpoint(lambda: _DatagramProtocol(self), local_addr=(e.host, e.port))
        else:
            self._transport, _ = await loop.create_datagram_endpoint(lambda: _DatagramProtocol(self), remote_addr=(e.host, e.port))
            self.peer = (e.host, e.port)

    def _received(self, data: bytes, addr: tuple) -> None:
        # A datagram carries whole frames (a truncated one ends here). udpin answers the last sender,
        # but only one that sent an acceptable frame: line noise, or an unsigned or forged frame when
        # signing is required, must not redirect our heartbeats and setpoints to its sender.
        accepted = self.on_bytes(data, True)
        if self.endpoint.kind == "udpin" and accepted:
            self.peer = addr

    def write(self, data: bytes) -> bool:
        if self.peer is None:
            return False  # udpin before anyone has sent to us: nobody to talk to yet (not a drop)
        if self._transport is None or self._transport.is_closing():
            self.dropped_writes += 1
            return False
        if self.endpoint.kind == "udpin":
            self._transport.sendto(data, self.peer)
        else:
            self._transport.sendto(data)
        return True

    def close(self) -> None:
        self._closing = True
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    @property
    def local_address(self) -> tuple | None:
        return None if self._transport is None else self._transport.get_extra_info("sockname")


class _StreamProtocol(asyncio.Protocol):
    def __init__(self, on_bytes: OnBytes, on_closed: Callable[[Exception | None], None]) -> None:
        self.on_bytes = on_bytes
        self.on_closed = on_closed
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        self.on_bytes(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.on_closed(exc)


class TcpTransport(Transport):
    """tcp: connect to a server (SITL takes one client per port)."""

    stream = True

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._proto: _StreamProtocol | None = None
        self._closing = False

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        e = self.endpoint
        self._proto = _StreamProtocol(self.on_bytes, self._closed)
        # asyncio.timeout, not wait_for: in 3.11 wait_for can swallow a cancellation that races a
        # completion, and a swallowed cancel would keep the link alive through shutdown.
        async with asyncio.timeout(self.connect_timeout_s):
            await loop.create_connection(lambda: self._proto, e.host, e.port)

    def _closed(self, exc: Exception | None) -> None:
        if not self._closing:
            self.on_lost(f"TCP connection closed by the peer{': ' + str(exc) if exc else ''}")

    def write(self, data: bytes) -> bool:
        return self._write_stream(self._proto.transport if self._proto else None, data)

    def close(self) -> None:
        self._closing = True
        if self._proto and self._proto.transport:
            self._proto.transport.close()

    @property
    def local_address(self) -> tuple | None:
        t = self._proto.transport if self._proto else None
        return None if t is None else t.get_extra_info("sockname")


class TcpServerTransport(Transport):
    """tcpin: listen and talk to one client at a time (a new client replaces the previous one)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._server: asyncio.Server | None = None
        self._client: _StreamProtocol | None = None

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(self._accept, self.endpoint.host, self.endpoint.port)

    def _accept(self) -> _StreamProtocol:
        if self._client is not None and self._client.transport is not None:
            self._client.transport.close()
        proto = _StreamProtocol(self.on_bytes, lambda exc: None)
        self._client = proto
        return proto

    def write(self, data: bytes) -> bool:
        return self._write_stream(self._client.transport if self._client else None, data)

    def close(self) -> None:
        if self._client and self._client.transport:
            self._client.transport.close()
        if self._server is not None:
            self._server.close()
            self._server = None

    @property
    def local_address(self) -> tuple | None:
        return None if not self._server or not self._server.sockets else self._server.sockets[0].getsockname()


class SerialTransport(Transport):
    """A tty in raw 8N1 mode at the configured baud, read through ``loop.add_reader`` (no pyserial, no thread)."""

    stream = True

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    async def open(self) -> None:
        speed = getattr(termios, f"B{self.endpoint.baud}", None)
        if speed is None:
            raise OSError(f"baud rate {self.endpoint.baud} is not supported by this system's termios")
        fd = os.open(self.endpoint.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            attrs = termios.tcgetattr(fd)
            attrs[0] = 0  # iflag: no break/parity/CR-LF/flow-control processing
            attrs[1] = 0  # oflag: raw output
            attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | getattr(termios, "CRTSCTS", 0))) | termios.CS8 | termios.CREAD | termios.CLOCAL
            attrs[3] = 0  # lflag: no echo, not canonical, no signals
            attrs[4] = attrs[5] = speed
            attrs[6][termios.VMIN] = 0
            attrs[6][termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except (termios.error, OSError) as exc:
            os.close(fd)
            raise OSError(f"{self.endpoint.device}: cannot configure the serial port: {exc}") from exc
        self._fd = fd
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(fd, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, 4096)  # type: ignore[arg-type]
        except BlockingIOError:
            return
        except OSError as exc:  # EIO: the device went away (USB unplugged, pty closed)
            self._stop_reading()
            self.on_lost(f"{self.endpoint.device}: {exc.strerror or exc}")
            return
        if data:
            self.on_bytes(data)

    def _stop_reading(self) -> None:
        if self._fd is not None and self._loop is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(self._fd)

    def write(self, data: bytes) -> bool:
        if self._fd is None:
            self.dropped_writes += 1
            return False
        try:
            n = os.write(self._fd, data)
        except (BlockingIOError, OSError):
            self.dropped_writes += 1
            return False
        if n < len(data):  # the UART buffer is full: the receiver resynchronises on the next start byte
            self.dropped_writes += 1
            return False
        return True

    def close(self) -> None:
        self._stop_reading()
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


def make_transport(endpoint: Endpoint, on_bytes: OnBytes, on_lost: OnLost, connect_timeout_s: float = 3.0) -> Transport:
    cls = {"udpin": UdpTransport, "udpout": UdpTransport, "tcp": TcpTransport, "tcpin": TcpServerTransport, "serial": SerialTransport}[endpoint.kind]
    return cls(endpoint, on_bytes, on_lost, connect_timeout_s)


# --------------------------------------------------------------------------------------------
# Bookkeeping helpers
# --------------------------------------------------------------------------------------------


class RateMeter:
    """Arrival rate per message type over a sliding window (bounded memory).

    rate = arrivals in the last ``window_s`` / min(window_s, time since the type was first seen), so a
    burst (ten COMMAND_ACKs in 50 ms) reads as its average, and a stream silent for a window reads 0.
    """

    def __init__(self, window_s: float = 2.0, maxlen: int = 1024) -> None:
        self.window_s = window_s
        self.maxlen = maxlen
        self._t: dict[str, deque[float]] = {}
        self._first: dict[str, float] = {}
        self.counts: dict[str, int] = {}

    def tick(self, kind: str, now: float) -> None:
        q = self._t.get(kind)
        if q is None:
            q = self._t[kind] = deque(maxlen=self.maxlen)
            self._first[kind] = now
        q.append(now)
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def last(self, kind: str) -> float | None:
        q = self._t.get(kind)
        return q[-1] if q else None

    def rate(self, kind: str, now: float) -> float:
        q = self._t.get(kind)
        if not q:
            return 0.0
        n = sum(1 for t in q if t > now - self.window_s)
        span = min(self.window_s, now - self._first[kind])
        return n / span if span > 0 else 0.0

    def rates(self, now: float) -> dict[str, float]:
        return {k: round(self.rate(k, now), 2) for k in sorted(self._t)}


class LogLimiter:
    """Log a problem the first time, then at most once per ``interval_s`` with the count in between."""

    def __init__(self, interval_s: float = 30.0) -> None:
        self.interval_s = interval_s
        self._last: dict[str, tuple[float, int]] = {}

    def __call__(self, level: int, key: str, message: str) -> None:
        now = time.monotonic()
        last, suppressed = self._last.get(key, (-math.inf, 0))
        if now - last >= self.interval_s:
            suffix = f" ({suppressed} more since last report)" if suppressed else ""
            log.log(level, "%s%s", message, suffix)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, suppressed + 1)


@dataclass(slots=True)
class StreamRequest:
    """One message the link asks for, and what became of the request."""

    name: str
    msg_id: int
    rate_hz: float
    result: str = "not requested"
    requests: int = 0
    requested_at: float | None = None
    next_check: float = 0.0
    backoff_s: float = 0.0
    wanted_since: float = -math.inf  # one-shot messages: only an arrival after this counts


@dataclass(slots=True)
class SetpointRecord:
    """The latest setpoint handed to the link, commanded or advisory."""

    t_s: float
    velocity_ned_mps: tuple[float, float, float]
    yaw_rad: float | None
    yaw_rate_radps: float | None
    position_ned_m: tuple[float, float, float] | None
    commanded: bool
    reason: str
    type_mask: int


class LinkError(RuntimeError):
    """A command could not be sent (no autopilot on the link)."""


@dataclass(slots=True)
class _Pending:
    command: int
    future: asyncio.Future = field(repr=False)


# --------------------------------------------------------------------------------------------
# The link
# --------------------------------------------------------------------------------------------


class AutopilotLink:
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
        self._pending: _Pending | None = None
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

    def _wanted_streams(self) -> dict[str, StreamRequest]:
        """Every message the link can use, at its rate; the autopilot's answers show which exist."""
        lc = self.cfg.link
        nav, aux, ts = lc.nav_stream_rate_hz, lc.aux_stream_rate_hz, lc.timesync_rate_hz
        wanted = [
            ("LOCAL_POSITION_NED", nav),
            ("ATTITUDE_QUATERNION", nav),
            ("ODOMETRY", nav),  # PX4: pose + covariance; ArduPilot: DENIED
            ("LOCAL_POSITION_NED_COV", nav),
            ("ATTITUDE_QUATERNION_COV", nav),
            ("EKF_STATUS_REPORT", aux),  # ArduPilot innovation test ratios
            ("ESTIMATOR_STATUS", aux),  # PX4 accuracies and ratios
            ("GPS_RAW_INT", aux),  # h_acc / v_acc (mm)
            ("SYSTEM_TIME", ts),
        ]
        if lc.request_sim_state:
            wanted.append(("SIM_STATE", nav))
        return {name: StreamRequest(name, getattr(mavlink2, f"MAVLINK_MSG_ID_{name}"), rate) for name, rate in wanted}

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
            return _ardupilot_mode_name(hb.type, hb.custom_mode)
        if self.flavour == "px4":
            return _px4_mode_name(hb.custom_mode)
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

    async def _timesync_loop(self) -> None:
        period = 1.0 / self.cfg.link.timesync_rate_hz
        while True:
            await self.clock.sleep(period)
            if self._target is None:
                continue
            now = self.clock.now()
            ts1 = int(now * 1e9) + 1  # never 0; tc1 = 0 marks a request
            if self._send(self._mav.timesync_encode(0, ts1)):
                self._timesync_sent[ts1] = now
                while len(self._timesync_sent) > 16:
                    self._timesync_sent.pop(next(iter(self._timesync_sent)))

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

    async def _stream_loop(self) -> None:
        """Request the streams on (re)connection; re-request accepted streams that do not arrive."""
        while True:
            await self.clock.sleep(0.2)
            if self._state != "connected" or self._target is None:
                continue
            now = self.clock.now()
            if self._need_stream_request:
                self._need_stream_request = False
                for s in self._streams.values():
                    await self._request_stream(s)
                self._maybe_fallback()
                continue
            check = self.cfg.link.stream_check_s
            for s in self._streams.values():
                if s.result in ("DENIED", "UNSUPPORTED") or now < s.next_check:
                    continue
                last = self.rates.last(s.name)
                if last is not None and now - last < check:
                    s.backoff_s = check
                    s.next_check = now + check
                    continue
                if s.requested_at is not None and now - s.requested_at < check:
                    continue
                self._limiter(logging.INFO, f"stream-{s.name}", f"autopilot link: {s.name} ({s.result}) has not arrived for {check:.1f} s; requesting it again")
                await self._request_stream(s)
                s.backoff_s = min(max(2 * s.backoff_s, check), 30.0)
                s.next_check = self.clock.now() + s.backoff_s
            for o in self._oneshots.values():  # sent once by the autopilot (when it exists): ask until it comes
                last = self.rates.last(o.name)
                if last is not None and last >= o.wanted_since:
                    continue
                if now >= o.next_check:
                    o.result = await self._command(mavlink2.MAV_CMD_REQUEST_MESSAGE, (o.msg_id, 0, 0, 0, 0, 0, 0), retries=1)
                    o.requests += 1
                    o.backoff_s = min(max(2 * o.backoff_s, 2.0), 30.0)
                    o.next_check = self.clock.now() + o.backoff_s

    async def _request_stream(self, s: StreamRequest) -> None:
        interval_us = 1e6 / s.rate_hz
        s.result = await self._command(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (s.msg_id, interval_us, 0, 0, 0, 0, 0))
        s.requests += 1
        s.requested_at = self.clock.now()
        s.next_check = s.requested_at + self.cfg.link.stream_check_s
        if s.result != "ACCEPTED":
            self._limiter(logging.INFO, f"stream-result-{s.name}", f"autopilot link: SET_MESSAGE_INTERVAL {s.name} -> {s.result}")

    def _maybe_fallback(self) -> None:
        """Autopilots without SET_MESSAGE_INTERVAL: the older REQUEST_DATA_STREAM groups."""
        if self._fallback_requested or any(s.result in ("ACCEPTED", "DENIED") for s in self._streams.values()):
            return
        self._fallback_requested = True
        lc = self.cfg.link
        log.warning("autopilot link: SET_MESSAGE_INTERVAL not supported; falling back to REQUEST_DATA_STREAM")
        sys_id, comp_id = self._target  # type: ignore[misc]
        for stream_id, rate in (
            (mavlink2.MAV_DATA_STREAM_POSITION, lc.nav_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTRA1, lc.nav_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTENDED_STATUS, lc.aux_stream_rate_hz),
            (mavlink2.MAV_DATA_STREAM_EXTRA3, lc.aux_stream_rate_hz),
        ):
            self._send(self._mav.request_data_stream_encode(sys_id, comp_id, stream_id, max(1, int(round(rate))), 1))

    async def _command(self, command: int, params: tuple, retries: int | None = None) -> str:
        """COMMAND_LONG to the autopilot, one at a time; the MAV_RESULT name, or NO_ANSWER / NO_LINK."""
        if self._target is None or self._command_lock is None:
            return "NO_LINK"
        lc = self.cfg.link
        attempts = lc.command_retries if retries is None else retries
        async with self._command_lock:
            for confirmation in range(attempts):
                if self._target is None or self._transport is None:
                    return "NO_LINK"
                future: asyncio.Future = asyncio.get_running_loop().create_future()
                self._pending = _Pending(command, future)
                try:
                    p = [float(x) for x in params]
                    self._send(self._mav.command_long_encode(self._target[0], self._target[1], command, confirmation, *p))
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(self.clock.wall_seconds(lc.command_timeout_s)):
                            return await future
                finally:
                    self._pending = None
        return "NO_ANSWER"

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

    def can_command(self) -> tuple[bool, str]:
        """Whether a setpoint would be sent now, and why not."""
        c = self.cfg.control
        if not c.commanding_enabled:
            return False, "advisory: control.commanding_enabled is false"
        if self._state != "connected":
            return False, f"autopilot link {self._state}"
        now = self.clock.now()
        latest = self.nav_buffer.latest()
        if latest is None:
            return False, "no navigation received"
        age = now - latest.t_s
        if age > self.cfg.nav.stale_after_s:
            return False, f"navigation stale ({age:.2f} s old, limit {self.cfg.nav.stale_after_s:.2f} s)"
        ok, why = self.assembler.health(now)
        if not ok:
            return False, f"estimator unhealthy: {why}"
        if self._mode_accepts_setpoints():
            return True, f"commanding in {self.mode}"
        if self.flavour == "px4" and c.allow_mode_change:
            return True, "streaming setpoints before the switch to OFFBOARD (PX4 requires the stream first)"
        wanted = "GUIDED" if self.flavour == "ardupilot" else "OFFBOARD" if self.flavour == "px4" else "GUIDED/OFFBOARD"
        return False, f"mode {self.mode} does not accept setpoints (needs {wanted})"

    def _mode_accepts_setpoints(self) -> bool:
        hb = self._heartbeat
        if hb is None:
            return False
        if self.flavour == "ardupilot":
            return self.mode == "GUIDED"
        if self.flavour == "px4":
            return (hb.custom_mode >> 16) & 0xFF == PX4_MAIN_OFFBOARD
        return False

    def send_setpoint(
        self,
        velocity_ned_mps: Any,
        yaw_rad: float | None = None,
        yaw_rate_radps: float | None = None,
        position_ned_m: Any = None,
    ) -> bool:
        """SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) when allowed; else record it as advisory.

        Velocity only: type_mask 3527 = ignore x, y, z (1+2+4), ax, ay, az (64+128+256), yaw (1024) and
        yaw rate (2048). ``yaw_rad`` / ``yaw_rate_radps`` clear their ignore bit. ``position_ned_m``
        (3,) sends position + velocity (feed-forward). A partial position (altitude only) is not
        offered: ArduPilot treats the three position bits as one ("any set -> position ignored").
        The caller streams at a steady rate (ArduPilot GUIDED stops after 3 s without a velocity
        setpoint; PX4 leaves OFFBOARD below 2 Hz); the link never repeats a setpoint on its own.
        Returns True when the message was sent.
        """
        v = np.asarray(velocity_ned_mps, dtype=float).reshape(-1)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"setpoint velocity must be 3 finite numbers (m/s, NED), got {velocity_ned_mps!r}")
        p = None
        if position_ned_m is not None:
            p = np.asarray(position_ned_m, dtype=float).reshape(-1)
            if p.shape != (3,) or not np.all(np.isfinite(p)):
                raise ValueError(f"setpoint position must be 3 finite numbers (m, NED), got {position_ned_m!r}")
        for name, value in (("yaw_rad", yaw_rad), ("yaw_rate_radps", yaw_rate_radps)):
            if value is not None and not math.isfinite(value):
                raise ValueError(f"setpoint {name} must be finite, got {value!r}")
        mask = TYPEMASK_ACCEL | (TYPEMASK_POSITION if p is None else 0)
        mask |= TYPEMASK_YAW if yaw_rad is None else 0
        mask |= TYPEMASK_YAW_RATE if yaw_rate_radps is None else 0
        ok, reason = self.can_command()
        now = self.clock.now()
        sent = False
        if ok and self._target is not None:
            pos = p if p is not None else np.zeros(3)
            msg = self._mav.set_position_target_local_ned_encode(
                int(now * 1000) & 0xFFFFFFFF,
                self._target[0],
                self._target[1],
                mavlink2.MAV_FRAME_LOCAL_NED,
                mask,
                *pos,
                *v,
                0.0,
                0.0,
                0.0,
                float(yaw_rad or 0.0),
                float(yaw_rate_radps or 0.0),
            )
            sent = self._send(msg)
            if not sent:
                reason = "transport dropped the setpoint"
        if sent:
            self.setpoints_sent += 1
            self._setpoint_times.append(now)
        else:
            self.setpoints_refused += 1
        self.last_setpoint = SetpointRecord(
            now, tuple(v.tolist()), yaw_rad, yaw_rate_radps, None if p is None else tuple(p.tolist()), sent, reason, mask
        )
        return sent

    def send_statustext(self, severity: int | str, text: str) -> int:
        """STATUSTEXT to the ground station; returns the number of chunks sent or queued.

        Text longer than 50 bytes goes out in chunks (MAVLink 2 ``id`` / ``chunk_seq``), split on UTF-8
        character boundaries, at most 5 chunks (longer text is truncated with '...'); a final full
        chunk is followed by an empty one so receivers see the end. While no autopilot is connected
        the text is queued (the last 16) and sent on reconnection.
        """
        if isinstance(severity, str):
            key = severity.upper().removeprefix("MAV_SEVERITY_")
            if key not in SEVERITIES:
                raise ValueError(f"unknown STATUSTEXT severity {severity!r}; one of {', '.join(SEVERITIES)}")
            level = SEVERITIES[key]
        else:
            level = int(severity)
            if not 0 <= level <= 7:
                raise ValueError(f"STATUSTEXT severity must be 0..7, got {severity}")
        chunks = statustext_chunks(str(text))
        if self._state != "connected":
            self._statustext_queue.append((level, str(text)))
            return len(chunks)
        return self._send_statustext_now(level, chunks)

    def _send_statustext_now(self, level: int, chunks: list[bytes]) -> int:
        if len(chunks) == 1:
            self._send(self._mav.statustext_encode(level, chunks[0], 0, 0))
            return 1
        self._statustext_id = self._statustext_id % 65535 + 1
        for seq, chunk in enumerate(chunks):
            self._send(self._mav.statustext_encode(level, chunk, self._statustext_id, seq))
        return len(chunks)

    # --- guarded vehicle commands ------------------------------------------------------------------

    def _require(self, allowed: bool, key: str, what: str) -> None:
        if not allowed:
            raise PermissionError(f"control.{key} is false: the service does not {what} unless configured to")
        if self._target is None or self._state != "connected":
            raise LinkError(f"cannot {what}: no autopilot connected (link {self._state})")

    async def set_mode(self, name: str) -> str:
        """Switch flight mode by name (GUIDED, OFFBOARD, LOITER, ...); only with ``control.allow_mode_change``."""
        self._require(self.cfg.control.allow_mode_change, "allow_mode_change", "change the flight mode")
        name = name.upper()
        if self.flavour == "px4":
            if name not in PX4_SET_MODE:
                raise ValueError(f"unknown PX4 mode {name!r}; one of {', '.join(PX4_SET_MODE)}")
            main, sub = PX4_SET_MODE[name]
            params = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub, 0, 0, 0, 0)
        else:
            table = _ardupilot_mode_table(self._heartbeat.type if self._heartbeat else 2)
            numbers = {v: k for k, v in table.items()}
            if name not in numbers:
                raise ValueError(f"unknown mode {name!r} for this vehicle; one of {', '.join(sorted(numbers))}")
            params = (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, numbers[name], 0, 0, 0, 0, 0)
        return await self._command(mavlink2.MAV_CMD_DO_SET_MODE, params)

    async def arm(self, force: bool = False) -> str:
        """Arm (MAV_CMD_COMPONENT_ARM_DISARM); only with ``control.allow_arm``."""
        self._require(self.cfg.control.allow_arm, "allow_arm", "arm the vehicle")
        return await self._command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (1, 21196 if force else 0, 0, 0, 0, 0, 0))

    async def disarm(self) -> str:
        self._require(self.cfg.control.allow_arm, "allow_arm", "disarm the vehicle")
        return await self._command(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, (0, 0, 0, 0, 0, 0, 0))

    async def takeoff(self, altitude_m: float) -> str:
        """MAV_CMD_NAV_TAKEOFF: ArduPilot climbs to ``altitude_m`` above home (GUIDED, armed); PX4 reads
        param7 as AMSL, so NaN is sent and PX4 uses MIS_TAKEOFF_ALT. Only with ``control.allow_arm``."""
        self._require(self.cfg.control.allow_arm, "allow_arm", "take off")
        alt = float(altitude_m) if self.flavour != "px4" else math.nan
        return await self._command(mavlink2.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, math.nan, math.nan, alt))

    # ------------------------------------------------------------------------------------------
    # Receiving
    # ------------------------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, packet_end: bool = False) -> bool:
        """Frame, check and dispatch received bytes; True if at least one frame was acceptable."""
        self.bytes_rx += len(data)
        try:
            items = self._framer.feed(data, packet_end)
        except Exception as exc:  # the framer does not raise; if it ever does, drop the buffer and go on
            self._count_wire(f"framing error: {type(exc).__name__}", str(exc))
            self._framer.reset()
            return False
        now = self.clock.now()
        accepted = False
        for m in items:
            if isinstance(m, Rejected):
                self._count_wire(m.category, m.detail)
                continue
            accepted = True
            if self._tlog is not None:
                self._log_packet(now, m.get_msgbuf())
            try:
                self._dispatch(m, now)
            except Exception as exc:  # one bad message must not stop the others
                kind = m.get_type()
                self.handler_errors[kind] = self.handler_errors.get(kind, 0) + 1
                self._error(f"autopilot link: error handling {kind}: {exc!r}", key=f"handler-{kind}")
                log.debug("handler error", exc_info=True)
        return accepted

    def _count_wire(self, category: str, detail: str) -> None:
        self.wire_errors[category] = self.wire_errors.get(category, 0) + 1
        self._limiter(
            logging.WARNING,
            f"wire-{category}",
            f"autopilot link {self.endpoint}: corrupt MAVLink input ({category}: {detail[:80]}); "
            "check the baud rate, that only MAVLink is written to this port, and the signing key",
        )

    def _dispatch(self, m: Any, now: float) -> None:
        kind = m.get_type()
        self.messages_rx += 1
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src == (self.cfg.link.source_system, self.cfg.link.source_component):
            return  # our own traffic echoed by a router
        if kind == "HEARTBEAT":
            self._on_heartbeat(m, src, now)
            return
        if self._target is None or src != self._target:
            self._ignore(src)
            return
        self.rates.tick(kind, now)
        if kind == "TIMESYNC":
            self._on_timesync(m, now)
            return
        if kind == "COMMAND_ACK":
            self._on_command_ack(m)
            return
        if kind == "STATUSTEXT":
            self._limiter(logging.INFO, f"ap-text-{m.text}", f"autopilot says: {m.text}")
            return
        boot_ms = getattr(m, "time_boot_ms", None)
        if boot_ms:
            verdict = self.timesync.check_remote_time(boot_ms * 1e-3, now)
            self._check_reboot(now)
            if verdict in ("behind", "ahead"):
                # One stamp off the autopilot's clock is a stray or corrupt message, not a reboot (that
                # takes several consistent ones): it must not move the time base or reach the state.
                self.time_rejections[verdict] = self.time_rejections.get(verdict, 0) + 1
                self._limiter(logging.WARNING, f"time-{verdict}",
                              f"autopilot link: {kind} stamped {boot_ms} ms dropped: {verdict} the autopilot's clock (one stray stamp is not a reboot)")
                return
        if kind == "SYSTEM_TIME" and m.time_boot_ms:
            self.timesync.add_one_way(m.time_boot_ms * 1e-3, now)
            self._check_reboot(now)
        if kind in HANDLED_MESSAGES:
            nav = self.assembler.update(m, now)
            if self.assembler.estimator_resets != self._seen_estimator_resets:
                self._seen_estimator_resets = self.assembler.estimator_resets
                self.nav_buffer.clear()  # the estimate jumped: never interpolate across a reset
            if self.assembler.time_basis_changes != self._seen_basis_changes:
                self._seen_basis_changes = self.assembler.time_basis_changes
                self.nav_buffer.clear()  # arrival-stamped and synchronised states are not mixed
            if nav is not None and not self.nav_buffer.push(nav):
                self._limiter(logging.WARNING, "nav-buffer", f"autopilot link: navigation state not buffered ({self.nav_buffer.rejected})")

    def _ignore(self, src: tuple[int, int]) -> None:
        """A message from a system/component that is not our autopilot (GCS, gimbal, another vehicle)."""
        self.ignored_messages += 1
        key = f"{src[0]}/{src[1]}"
        if key in self.ignored_sources or len(self.ignored_sources) < IGNORED_SOURCES_KEPT:
            self.ignored_sources[key] = self.ignored_sources.get(key, 0) + 1
        else:
            self.ignored_sources["others"] = self.ignored_sources.get("others", 0) + 1

    def _check_reboot(self, now: float) -> None:
        """React to a change of the autopilot's time base: a reboot, or a confirmed jump of its clock."""
        if self.timesync.resets != self._seen_time_resets and self.timesync.reboots == self.reboots:
            self._seen_time_resets = self.timesync.resets
            log.warning("autopilot link: the autopilot's time mapping changed (its clock jumped); navigation history cleared")
            self.assembler.forget_state()
            self.nav_buffer.clear()  # stamps before and after the jump are not comparable
            return
        self._seen_time_resets = self.timesync.resets
        if self.timesync.reboots != self.reboots:
            self.reboots = self.timesync.reboots
            log.warning("autopilot link: the autopilot rebooted (its clock went backwards); resetting navigation and streams")
            self.assembler.reset()
            self.nav_buffer.clear()
            self._need_stream_request = True
            self._want_oneshots_again(now)
            self.send_statustext("WARNING", "companion: autopilot reboot detected")

    def _want_oneshots_again(self, now: float) -> None:
        """A new or rebooted autopilot: its origin and home must be asked for again."""
        for o in self._oneshots.values():
            o.wanted_since = now
            o.next_check = 0.0
            o.backoff_s = 0.0

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
            self._target[0], self._target[1], detected, _mav_type_name(self._heartbeat.type), self.mode, self.endpoint,
        )  # fmt: skip
        if self._lost_since is not None:
            gap = now - self._lost_since
            self._lost_since = None
            self.send_statustext("NOTICE", f"companion: autopilot link back after {gap:.1f} s")
        while self._statustext_queue:
            level, text = self._statustext_queue.popleft()
            self._send_statustext_now(level, statustext_chunks(text))

    def _on_timesync(self, m: Any, now: float) -> None:
        if m.tc1 == 0:  # the autopilot asks for our time (PX4 does, ArduPilot may): answer
            self._send(self._mav.timesync_encode(int(now * 1e9) + 1, m.ts1))
            return
        t_sent = self._timesync_sent.pop(m.ts1, None)
        if t_sent is None:
            return  # an answer to somebody else's request (replies are broadcast)
        if not self.timesync.add_roundtrip(t_sent, m.tc1 * 1e-9, now):
            self.time_rejections["round trip"] = self.time_rejections.get("round trip", 0) + 1
            self._limiter(logging.WARNING, "time-round-trip", "autopilot link: a TIMESYNC answer was unusable (too slow, or off the autopilot's clock)")
        self._check_reboot(now)

    def _on_command_ack(self, m: Any) -> None:
        p = self._pending
        if p is None or m.command != p.command or p.future.done():
            return
        target_system = getattr(m, "target_system", 0)
        if target_system not in (0, self.cfg.link.source_system):
            return  # an ACK meant for another component
        if m.result == MAV_RESULT_IN_PROGRESS:
            return
        p.future.set_result(_result_name(m.result))

    # ------------------------------------------------------------------------------------------
    # Status
    # ------------------------------------------------------------------------------------------

    def setpoint_rate_hz(self, now: float | None = None) -> float:
        now = self.clock.now() if now is None else now
        recent = [t for t in self._setpoint_times if now - t <= 2.0]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)

    def status(self) -> dict[str, Any]:
        """Everything an operator needs to judge the link, as plain JSON-serialisable data."""
        now = self.clock.now()
        hb = self._heartbeat
        ts = self.timesync.status()
        latest = self.nav_buffer.latest()
        ok, reason = self.can_command()
        rejected = {f"nav: {k}": v for k, v in self.assembler.rejections.counts.items()}
        rejected.update({f"wire: {k}": v for k, v in self.wire_errors.items()})
        rejected.update({f"nav buffer: {k}": v for k, v in self.nav_buffer.rejected.items()})
        rejected.update({f"handler: {k}": v for k, v in self.handler_errors.items()})
        rejected.update({f"time: {k}": v for k, v in self.time_rejections.items()})
        sp = self.last_setpoint
        return {
            "link": {
                "state": self._state,
                "endpoint": str(self.endpoint),
                "local_address": None if self.local_address is None else list(self.local_address[:2]),
                "autopilot": None
                if hb is None
                else {
                    "system": self._target[0] if self._target else None,
                    "component": self._target[1] if self._target else None,
                    "flavour": self.flavour,
                    "type": _mav_type_name(hb.type),
                    "mode": self.mode,
                    "armed": self.armed,
                    "system_status": hb.system_status,
                },
                "heartbeat_age_s": None if self._last_heartbeat is None else round(now - self._last_heartbeat, 3),
                "connects": self.connects,
                "reconnects": self.reconnects,
                "link_losses": self.link_losses,
                "autopilot_reboots": self.reboots,
                "bytes_rx": self.bytes_rx,
                "messages_rx": self.messages_rx,
                "messages_tx": self.messages_tx,
                "ignored_messages": self.ignored_messages,
                "ignored_sources": dict(self.ignored_sources),
                "dropped_writes": 0 if self._transport is None else self._transport.dropped_writes,
                "last_error": self.last_error,
                "telemetry_log": None if self._tlog is None else {"path": str(self._tlog_path), "records": self.tlog_records},
            },
            "streams": {
                s.name: {
                    "requested_hz": s.rate_hz,
                    "result": s.result,
                    "requests": s.requests,
                    "rate_hz": round(self.rates.rate(s.name, now), 2),
                    "arriving": self.rates.last(s.name) is not None and now - self.rates.last(s.name) < self.cfg.link.stream_check_s,
                }
                for s in self._streams.values()
            },
            "rates_hz": self.rates.rates(now),
            "nav": {
                "covariance_source": None if latest is None else latest.covariance_source,
                "age_s": None if latest is None else round(now - latest.t_s, 3),
                "samples": len(self.nav_buffer),
                **self.assembler.status(now),
            },
            "time": {
                "source": ts.source,
                "offset_s": ts.offset_s,
                "jitter_s": ts.jitter_s,
                "rtt_s": ts.rtt_s,
                "samples": ts.samples,
                "resets": ts.resets,
            },
            "rejected": rejected,
            "commanding": {
                "enabled": self.cfg.control.commanding_enabled,
                "active": ok,
                "reason": reason,
                "setpoints_sent": self.setpoints_sent,
                "setpoints_not_sent": self.setpoints_refused,
                "setpoint_rate_hz": round(self.setpoint_rate_hz(now), 2),
                "last_setpoint": None
                if sp is None
                else {
                    "age_s": round(now - sp.t_s, 3),
                    "velocity_ned_mps": list(sp.velocity_ned_mps),
                    "yaw_rad": sp.yaw_rad,
                    "commanded": sp.commanded,
                    "reason": sp.reason,
                    "type_mask": sp.type_mask,
                },
            },
            "truth": None if not self.cfg.link.request_sim_state else _truth_status(self.truth_pose(), now),
            "signing": None if self.signing is None else {
                "required": self.signing.required,
                "accepted_signed": self.signing.accepted_signed,
                "accepted_unsigned": self.signing.accepted_unsigned,
                "streams": len(self.signing.streams),
            },
        }


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def statustext_chunks(text: str) -> list[bytes]:
    """Split UTF-8 text into STATUSTEXT payloads (<= 50 bytes, on character boundaries, <= 5 chunks)."""
    data = text.encode("utf-8")
    limit = STATUSTEXT_CHUNK * STATUSTEXT_MAX_CHUNKS
    if len(data) > limit:
        cut = limit - 4  # 249 bytes with the ellipsis: the last chunk is not full, so no terminator chunk
        while cut > 0 and (data[cut] & 0xC0) == 0x80:
            cut -= 1
        data = data[:cut] + b"..."
    if len(data) <= STATUSTEXT_CHUNK:
        return [data]
    chunks = []
    while data:
        cut = min(STATUSTEXT_CHUNK, len(data))
        while cut < len(data) and cut > 0 and (data[cut] & 0xC0) == 0x80:  # do not split a character
            cut -= 1
        chunks.append(data[:cut])
        data = data[cut:]
    if len(chunks[-1]) == STATUSTEXT_CHUNK:
        chunks.append(b"")  # a NUL-terminated (empty) chunk marks the end
    return chunks


def _mav_type_name(mav_type: int) -> str:
    entry = mavlink2.enums["MAV_TYPE"].get(int(mav_type))
    return entry.name.removeprefix("MAV_TYPE_") if entry is not None else f"TYPE_{mav_type}"


def _ardupilot_mode_table(mav_type: int) -> dict[int, str]:
    if mav_type in MULTIROTOR_TYPES:
        return ARDUCOPTER_MODES
    from pymavlink import mavutil  # other vehicle types: pymavlink's tables (imported only when needed)

    return mavutil.mode_mapping_bynumber(mav_type) or {}


def _ardupilot_mode_name(mav_type: int, custom_mode: int) -> str:
    return _ardupilot_mode_table(mav_type).get(custom_mode, f"MODE_{custom_mode}")


def _px4_mode_name(custom_mode: int) -> str:
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    name = PX4_MAIN_MODES.get(main, f"MAIN_{main}")
    if main == 4:
        return f"AUTO.{PX4_AUTO_SUB_MODES.get(sub, sub)}"
    return name


def _truth_status(truth: TruthPose | None, now: float) -> dict[str, Any] | None:
    if truth is None:
        return None
    return {
        "age_s": round(now - truth.t_s, 3),
        "position_ned_m": [round(x, 3) for x in truth.position_ned_m.tolist()],
        "origin_source": truth.origin_source,
    }
