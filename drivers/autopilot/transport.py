"""Byte pipes to the autopilot, on asyncio: UDP (``udpin`` answers the last sender of an acceptable
frame, ``udpout`` sends to a fixed address), a TCP client, a TCP server that talks to one client at
a time, and a serial tty in raw mode read through ``loop.add_reader`` (no pyserial, no thread).

The link gives a transport two callbacks, bytes received and connection lost (:func:`make_transport`).
A write never blocks: a transport that cannot take the bytes drops them and counts the drop.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import termios
from collections.abc import Callable
from typing import Any

from drivers.autopilot.connection import Endpoint

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
