"""The simulated vehicle's MAVLink links: per-link stream schedules and the UDP / TCP endpoints.

Each endpoint is one *link* in the autopilot's sense (an ArduPilot serial port / SITL TCP port, a
PX4 MAVLink instance): it owns a MAVLink 2 encoder (its own sequence numbers), a parser, and a
:class:`StreamSchedule` of message intervals. Rates set with SET_MESSAGE_INTERVAL or
REQUEST_DATA_STREAM stick to the link, also across TCP reconnections ("they stick to the port").

Endpoints (asyncio, owned by the vehicle's event loop; nothing here starts a thread):

* ``UdpOutEndpoint`` - sends to a fixed address (the way SITL ``--out`` / MAVProxy outputs feed a
  GCS or companion that listens with ``udpin``), and accepts whatever comes back on its socket.
* ``UdpInEndpoint`` - listens; replies go to the last peer heard (``udpin`` semantics).
* ``TcpListenEndpoint`` - a server taking one client at a time, like each ArduPilot SITL TCP port;
  a second client is refused while one is connected.

Incoming bytes are parsed on arrival and queued (bounded, oldest dropped and counted) for the
simulation loop, which hands them to the autopilot between physics steps.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import socket
import struct
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

log = logging.getLogger("companion.sim.link")

MAX_INBOUND = 4096  # parsed messages waiting for the simulation loop, per link


@dataclass(slots=True)
class StreamSchedule:
    """Message intervals of one link, in simulated seconds, on a grid of multiples of the interval.

    Grid alignment means two messages at the same rate go out in the same physics step, so a
    client can pair, say, ODOMETRY with the SIM_STATE truth sent right after it.
    """

    intervals_s: dict[int, float] = field(default_factory=dict)
    next_due_s: dict[int, float] = field(default_factory=dict)
    earliest_due_s: float = math.inf

    def set_interval(self, msg_id: int, interval_s: float | None, now_s: float) -> None:
        """Stream ``msg_id`` every ``interval_s`` (None or <= 0 stops it)."""
        if interval_s is None or not interval_s > 0:
            self.intervals_s.pop(msg_id, None)
            self.next_due_s.pop(msg_id, None)
        else:
            if not math.isfinite(interval_s):
                raise ValueError(f"message interval must be finite, got {interval_s!r}")
            self.intervals_s[msg_id] = interval_s
            self.next_due_s[msg_id] = (math.floor(now_s / interval_s + 1e-9) + 1) * interval_s
        self.earliest_due_s = min(self.next_due_s.values(), default=math.inf)

    def interval(self, msg_id: int) -> float | None:
        return self.intervals_s.get(msg_id)

    def pop_due(self, now_s: float) -> list[int]:
        """Message ids due at ``now_s``; each is rescheduled to its next grid point after now."""
        if now_s < self.earliest_due_s:
            return []
        due = []
        for msg_id, t in self.next_due_s.items():
            if t <= now_s + 1e-9:
                due.append(msg_id)
                iv = self.intervals_s[msg_id]
                self.next_due_s[msg_id] = (math.floor(now_s / iv + 1e-9) + 1) * iv
        self.earliest_due_s = min(self.next_due_s.values(), default=math.inf)
        return due


class Link:
    """One MAVLink link of the vehicle: encoder, parser, schedule and a transport to write to."""

    def __init__(self, name: str, sysid: int, compid: int = 1):
        self.name = name
        self.schedule = StreamSchedule()
        self._encoder = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._parser = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._parser.robust_parsing = True
        self.inbound: collections.deque = collections.deque(maxlen=MAX_INBOUND)
        self.inbound_dropped = 0
        self.parse_errors = 0
        self.sent = 0
        self.send_errors = 0
        self._writer = None  # callable(bytes) or None when nobody is connected

    @property
    def connected(self) -> bool:
        return self._writer is not None

    def attach(self, writer) -> None:
        self._writer = writer

    def detach(self) -> None:
        self._writer = None
        # a new client starts a new byte stream: forget any half-parsed frame
        self._parser = mavlink2.MAVLink(None, srcSystem=self._parser.srcSystem, srcComponent=self._parser.srcComponent)
        self._parser.robust_parsing = True

    def send(self, msg) -> None:
        """Encode with this link's sequence numbers and write (silently nothing if disconnected)."""
        if self._writer is None:
            return
        try:
            data = msg.pack(self._encoder)
            self._encoder.seq = (self._encoder.seq + 1) % 256
            self._writer(data)
            self.sent += 1
        except (OSError, ValueError, TypeError, struct.error) as exc:
            self.send_errors += 1
            log.warning("%s: could not send %s: %s", self.name, msg.get_type(), exc)

    def feed(self, data: bytes) -> None:
        """Parse received bytes; complete messages go to ``inbound`` (bounded, oldest dropped)."""
        try:
            msgs = self._parser.parse_buffer(data) or []
        except mavlink2.MAVError as exc:
            self.parse_errors += 1
            log.debug("%s: parse error: %s", self.name, exc)
            return
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                self.parse_errors += 1
                continue
            if len(self.inbound) == self.inbound.maxlen:
                self.inbound_dropped += 1
            self.inbound.append(m)


class _Datagram(asyncio.DatagramProtocol):
    def __init__(self, endpoint):
        self.endpoint = endpoint

    def datagram_received(self, data, addr):
        self.endpoint.on_datagram(data, addr)

    def error_received(self, exc):
        # ICMP port unreachable while nobody listens at the udp-out address: normal, keep sending
        log.debug("%s: %s", self.endpoint.link.name, exc)


class UdpOutEndpoint:
    """Send to a fixed HOST:PORT from an ephemeral local port; accept replies on that socket."""

    kind = "udp-out"

    def __init__(self, link: Link, remote: tuple[str, int]):
        self.link = link
        self.remote = remote
        self.transport = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        host = self.remote[0]
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.transport, _ = await loop.create_datagram_endpoint(lambda: _Datagram(self), family=family,
                                                                local_addr=("::" if family == socket.AF_INET6 else "0.0.0.0", 0))
        self.link.attach(lambda data: self.transport.sendto(data, self.remote))

    def on_datagram(self, data, addr) -> None:
        self.link.feed(data)

    def describe(self) -> str:
        local = self.transport.get_extra_info("sockname")
        return f"SENDING udp {self.remote[0]}:{self.remote[1]} from port {local[1]}"

    def close(self) -> None:
        self.link.detach()
        if self.transport is not None:
            self.transport.close()


class UdpInEndpoint:
    """Listen on HOST:PORT (0 = ephemeral); replies go to the last sender."""

    kind = "udp-in"

    def __init__(self, link: Link, local: tuple[str, int]):
        self.link = link
        self.local = local
        self.transport = None
        self.peer = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        self.transport, _ = await loop.create_datagram_endpoint(lambda: _Datagram(self), local_addr=self.local)

    def on_datagram(self, data, addr) -> None:
        if addr != self.peer:
            self.peer = addr
            self.link.attach(lambda d, a=addr: self.transport.sendto(d, a))
            log.info("%s: peer %s:%s", self.link.name, addr[0], addr[1])
        self.link.feed(data)

    @property
    def port(self) -> int:
        return self.transport.get_extra_info("sockname")[1]

    def describe(self) -> str:
        return f"LISTENING udp {self.local[0]}:{self.port}"

    def close(self) -> None:
        self.link.detach()
        if self.transport is not None:
            self.transport.close()


class TcpListenEndpoint:
    """TCP server on HOST:PORT (0 = ephemeral), one client at a time (like an ArduPilot SITL port)."""

    kind = "tcp"

    def __init__(self, link: Link, local: tuple[str, int], max_write_buffer: int = 1 << 20):
        self.link = link
        self.local = local
        self.server = None
        self.client_writer = None
        self.max_write_buffer = max_write_buffer
        self.dropped_writes = 0

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._client, self.local[0], self.local[1])

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if self.client_writer is not None:
            log.info("%s: refusing %s, a client is connected", self.link.name, peer)
            writer.close()
            return
        log.info("%s: client %s connected", self.link.name, peer)
        self.client_writer = writer
        self.link.attach(self._write)
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                self.link.feed(data)
        except (ConnectionError, OSError) as exc:
            log.info("%s: client %s: %s", self.link.name, peer, exc)
        finally:
            self.link.detach()
            self.client_writer = None
            writer.close()
            log.info("%s: client %s disconnected", self.link.name, peer)

    def _write(self, data: bytes) -> None:
        w = self.client_writer
        if w is None or w.is_closing():
            return
        # a client that does not read must not make the simulator hoard memory: drop, count
        if w.transport.get_write_buffer_size() > self.max_write_buffer:
            self.dropped_writes += 1
            return
        w.write(data)

    @property
    def port(self) -> int:
        return self.server.sockets[0].getsockname()[1]

    def describe(self) -> str:
        return f"LISTENING tcp {self.local[0]}:{self.port}"

    def close(self) -> None:
        self.link.detach()
        if self.client_writer is not None:
            self.client_writer.close()
        if self.server is not None:
            self.server.close()
