"""A camera that sends its frames over a local TCP stream, stamped in the autopilot's time.

What a companion computer sees of a camera that is triggered by (or synchronised with) the
autopilot: each frame carries its exposure time on the autopilot's clock (``time_boot``, as in
MAVLink's CAMERA_TRIGGER), and the service maps it to its own clock through the link's time
synchronisation. The simulator serves such a camera (``companion sim --camera-listen``,
:mod:`drivers.sim.camera_server`): it renders the world from the true pose at the exposure
instant in its own process, as camera hardware would, so the service spends nothing on rendering.

Wire format (docs/cameras.md, "Frame stream"), little-endian, one record per frame::

    magic b"CMFR" | version u16 (1) | reserved u16 | time_boot_us u64 | sequence u32 |
    width u16 | height u16 | payload_bytes u32 | payload (width x height 8-bit grey, row-major)
"""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import Callable

import numpy as np

from companion.config import CameraConfig
from companion.method.messages import Frame
from drivers.addresses import parse_host_port
from drivers.cameras.base import CameraError, CameraSource
from drivers.cameras.checks import CameraStats, FrameChecker

MAGIC = b"CMFR"
VERSION = 1
HEADER = struct.Struct("<4sHHQIHHI")  # 28 bytes
MAX_SIDE_PX = 8192

# autopilot time (s since its boot) -> companion time (s), or None while not synchronised
TimeMap = Callable[[float], "float | None"]


class FrameStreamError(ValueError):
    """A record that is not a frame of this format (bad magic, version or sizes)."""


def encode_frame(time_boot_us: int, sequence: int, image: np.ndarray) -> bytes:
    """One record: header + the (H, W) uint8 image's bytes."""
    img = np.ascontiguousarray(image)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"a stream frame is (H, W) uint8 grey, got {img.dtype} {img.shape}")
    h, w = img.shape
    if not (0 < w <= MAX_SIDE_PX and 0 < h <= MAX_SIDE_PX):
        raise ValueError(f"frame size {w}x{h} outside 1..{MAX_SIDE_PX}")
    return HEADER.pack(MAGIC, VERSION, 0, int(time_boot_us), int(sequence) & 0xFFFFFFFF, w, h, w * h) + img.tobytes()


def decode_header(header: bytes) -> tuple[int, int, int, int, int]:
    """(time_boot_us, sequence, width, height, payload_bytes) of a header; FrameStreamError if it
    is not one (the stream is then out of step: drop the connection)."""
    magic, version, _, t_us, seq, w, h, n = HEADER.unpack(header)
    if magic != MAGIC:
        raise FrameStreamError(f"bad magic {magic!r} (expected {MAGIC!r})")
    if version != VERSION:
        raise FrameStreamError(f"frame stream version {version}, this reader knows {VERSION}")
    if not (0 < w <= MAX_SIDE_PX and 0 < h <= MAX_SIDE_PX) or n != w * h:
        raise FrameStreamError(f"frame {w}x{h} with {n} payload bytes")
    return t_us, seq, w, h, n


def parse_address(address: str) -> tuple[str, int]:
    """``camera.stream_address`` ``HOST:PORT`` -> (host, port); ValueError naming the key."""
    return parse_host_port(address, "camera.stream_address", allow_port_zero=False)


class StreamCamera(CameraSource):
    """Frames from a frame stream server (``camera.source: stream``), each stamped with its
    exposure mapped to companion time by ``time_map``.

    ``read()`` connects when needed and returns the next frame. Raises :class:`CameraError` (the
    daemon waits and tries again) when the server cannot be reached or the connection ends, when a
    record is malformed (the connection is dropped: the stream is out of step; counted in
    ``bad_records``), and while the autopilot's time is not yet synchronised (frames then are
    counted in ``unsynced_frames`` and dropped: without a time they cannot be paired with
    navigation). Every frame then passes the frame checks of all sources (size, blank, time order,
    gaps; docs/cameras.md): a rejected frame is counted in ``stats`` and skipped.
    """

    name = "stream"

    def __init__(self, config: CameraConfig, time_map: TimeMap, connect_timeout_s: float = 2.0,
                 read_timeout_s: float = 2.0):
        self.host, self.port = parse_address(config.stream_address)
        self.name = f"stream:{self.host}:{self.port}"
        self._time_map = time_map
        self.stats = CameraStats()
        self._checker = FrameChecker(config.width, config.height, self.stats, name=self.name,
                                     nominal_period_s=1.0 / config.rate_hz, blank_std_max=config.blank_std_max,
                                     gap_factor=config.gap_factor)
        self._connect_timeout_s = connect_timeout_s
        self._read_timeout_s = read_timeout_s
        self._sock: socket.socket | None = None
        self._pending: asyncio.Future | None = None  # the read of the next frame, started with the last one
        self._closed = False
        self.connections = 0
        self.bad_records = 0
        self.unsynced_frames = 0

    # The socket is read by blocking calls in a worker thread (asyncio.to_thread): a frame is
    # 300 kB, and asyncio's StreamReader takes it in 64 kB pieces on the event loop, holding the
    # GIL for ~0.7 ms a frame in the loop that also runs the control law; recv_into a buffer of the
    # frame's size takes ~0.13 ms of a thread that lets go of the GIL while it waits.

    def _connect_blocking(self) -> socket.socket:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self._connect_timeout_s)
        except OSError as exc:
            raise CameraError(f"frame stream {self.host}:{self.port}: cannot connect ({exc or 'timeout'})") from exc
        sock.settimeout(self._read_timeout_s)
        self.connections += 1
        return sock

    def _read_frame_blocking(self, sock: socket.socket) -> Frame | None:
        """The next record as a checked frame, or None when it was dropped (no time yet, or refused
        by the frame checks; counted). Runs in the reader thread, checks included: NumPy lets go of
        the GIL inside them, and on the event loop the mapper thread would then keep the loop
        waiting for it. Raises FrameStreamError, :class:`_QuietStream` before a record starts (the
        connection is still in step), or OSError / EOFError (the connection is not)."""
        header = _recv_exactly(sock, HEADER.size, first_timeout_ok=True)
        t_us, seq, w, h, n = decode_header(bytes(header))
        payload = _recv_exactly(sock, n)
        t = self._time_map(t_us * 1e-6)
        if t is None:
            self.unsynced_frames += 1
            return None  # no time yet: the next frame may have one
        image = self._checker.admit(np.frombuffer(payload, np.uint8).reshape(h, w), float(t))
        if image is None:
            return None  # counted in stats and logged by the checker
        return Frame(t_s=float(t), image=image, sequence=int(seq), source="stream")

    def _drop_connection(self) -> None:
        # (a pending read of this connection ends with an error, which read() or close() collects)
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    async def read(self) -> Frame:
        while True:
            if self._closed:
                raise CameraError("frame stream camera is closed")
            sock = self._sock
            if sock is None:
                sock = self._sock = await asyncio.to_thread(self._connect_blocking)
            pending, self._pending = self._pending, None
            try:
                frame = await (pending or self._start_read(sock))
            except FrameStreamError as exc:
                self.bad_records += 1
                self._drop_connection()
                raise CameraError(f"frame stream {self.host}:{self.port}: {exc}; reconnecting") from exc
            except _QuietStream as exc:
                raise CameraError(f"frame stream {self.host}:{self.port}: no frame for {self._read_timeout_s:g} s") from exc
            except (EOFError, OSError) as exc:
                self._drop_connection()
                raise CameraError(f"frame stream {self.host}:{self.port}: connection ended") from exc
            if frame is not None:
                # The next frame is read from now on, so that the caller's work with this one (the
                # mapper's queue wakes the mapper thread) does not wait for the read to be set up.
                self._pending = self._start_read(sock)
                return frame

    def _start_read(self, sock: socket.socket) -> asyncio.Future:
        return asyncio.ensure_future(asyncio.to_thread(self._read_frame_blocking, sock))

    async def close(self) -> None:
        self._closed = True
        self._drop_connection()  # a read blocked in its thread ends with an error at once
        pending, self._pending = self._pending, None
        if pending is not None:
            try:
                await asyncio.wait_for(pending, 1.0)
            except Exception:  # noqa: BLE001 - the read ends with the connection: its error is expected
                pass


class _QuietStream(Exception):
    """No byte of a new record within the read timeout: the server is quiet, the stream in step."""


def _recv_exactly(sock: socket.socket, n: int, first_timeout_ok: bool = False) -> bytearray:
    """``n`` bytes from ``sock`` into a new buffer (the frame's own memory). EOFError when the
    connection ends first; a timeout before the first byte is :class:`_QuietStream` when
    ``first_timeout_ok``, a timeout later an OSError (the stream is out of step)."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        try:
            k = sock.recv_into(view[got:])
        except TimeoutError as exc:
            if got == 0 and first_timeout_ok:
                raise _QuietStream() from exc
            raise
        if k == 0:
            raise EOFError(f"connection ended after {got} of {n} bytes")
        got += k
    return buf
