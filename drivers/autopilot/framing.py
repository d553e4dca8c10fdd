"""MAVLink framing that resynchronises after every bad frame, and MAVLink 2 signature checks.

Why not ``MAVLink.parse_buffer`` alone: when a frame fails (bad CRC, impossible header) pymavlink's
robust parser drops the whole span its length byte claimed, up to 280 bytes. A stray start byte in
line noise (0xFD or 0xFE, 2 bytes in 256) therefore swallows the valid frames that follow it:
measured with random bytes interleaved with a 10 Hz HEARTBEAT and 100 Hz navigation, it lost 6 of 8
heartbeats and half the navigation (``tests/test_reliability_link.py`` keeps the figure). The
MAVLink C library behaves the same. :class:`MavlinkFramer` instead treats a failed candidate as one
bad byte and searches again from the byte after its start, so a valid frame is lost only when it
is itself damaged.

How a candidate is judged (``MAVLink.decode`` of pymavlink's generated dialect does the CRC and the
field unpacking):

* a start byte, then the header's length byte gives the frame size (v1: ``len + 8``; v2:
  ``len + 12``, ``+ 13`` with the signed flag); v2 ``incompat_flags`` other than SIGNED are refused;
* too few bytes: wait for more, except at the end of a datagram (UDP carries whole frames, so the
  rest of a datagram after a truncated frame is searched at once);
* CRC over the header and payload with the message's CRC_EXTRA; a frame whose message id this
  dialect does not know cannot be checked, so it is accepted as framed only when a start byte (or
  the datagram end) follows it and no frame that passes its CRC starts inside it, and otherwise
  counted as one bad byte;
* signatures (when a key is configured) by :class:`SignatureCheck`, after the CRC.

Every rejection is reported with a bounded category (:data:`CATEGORIES`) so the link can count it.
"""

from __future__ import annotations

import hashlib
import struct
import time
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

V1_START, V2_START = 0xFE, 0xFD
V1_OVERHEAD = 8  # start, len, seq, sys, comp, msgid, crc x2
V2_OVERHEAD = 12  # start, len, incompat, compat, seq, sys, comp, msgid x3, crc x2
SIGNATURE_LEN = 13  # link id, 48-bit timestamp, 48-bit signature
IFLAG_SIGNED = 0x01
SIGNING_EPOCH_UNIX_S = 1420070400  # MAVLink 2 signing timestamps count 10 us units since 2015-01-01
SIGNING_NEW_STREAM_WINDOW = 60 * 100_000  # a new stream may be at most one minute behind our timestamp

CATEGORIES = (
    "bad start byte",  # bytes before a start byte (one count per run of them)
    "bad CRC",
    "bad length",
    "unsupported incompat_flags",
    "truncated frame",
    "unknown message id",
    "undecodable payload",
    "unsigned message",
    "bad signature",
    "old signature timestamp",
)


@dataclass(frozen=True, slots=True)
class Rejected:
    """A span of input that is not an acceptable message: its category and the bytes it covered."""

    category: str
    detail: str
    nbytes: int


def _category(reason: str) -> str:
    r = reason.lower()
    for needle, category in (("crc", "bad CRC"), ("length", "bad length"), ("unpack", "undecodable payload"),
                             ("incompat", "unsupported incompat_flags")):
        if needle in r:
            return category
    return "undecodable payload"


class SignatureCheck:
    """MAVLink 2 signature verification (https://mavlink.io/en/guide/message_signing.html).

    ``signature = sha256(key + frame up to and including the timestamp)[:6]``; per stream (link id,
    system, component) the timestamp must increase, and a stream not seen before may be at most one
    minute behind our own timestamp. Unlike pymavlink's ``check_signature``, the stream's timestamp
    is recorded only after the signature has verified: a forged frame with a far-future timestamp
    must not make every genuine frame after it look like a replay.

    ``timestamp()`` is our signing timestamp (10 us units since 2015-01-01): the wall clock, never
    going back, and at least the newest verified timestamp received (as the specification asks).
    """

    def __init__(self, key: bytes, required: bool) -> None:
        if len(key) != 32:
            raise ValueError(f"a MAVLink 2 signing key has 32 bytes, got {len(key)}")
        self.key = bytes(key)
        self.required = bool(required)
        self.streams: dict[tuple[int, int, int], int] = {}
        self._timestamp = 0
        self.accepted_signed = 0
        self.accepted_unsigned = 0

    def timestamp(self) -> int:
        now = int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)
        self._timestamp = max(self._timestamp + 1, now)
        return self._timestamp

    def check(self, frame: bytes | bytearray, signed: bool) -> str | None:
        """None when the frame is acceptable, else the rejection category."""
        if not signed:
            if self.required:
                return "unsigned message"
            self.accepted_unsigned += 1
            return None
        sig = hashlib.sha256(self.key + bytes(frame[:-6])).digest()[:6]
        if sig != bytes(frame[-6:]):
            return "bad signature"
        link_id = frame[-13]
        stamp = int.from_bytes(frame[-12:-6], "little")
        key = (link_id, frame[5], frame[6])  # v2 header: sysid at 5, compid at 6
        last = self.streams.get(key)
        if last is not None:
            if stamp <= last:
                return "old signature timestamp"
        elif stamp + SIGNING_NEW_STREAM_WINDOW < max(self._timestamp, int((time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)):
            return "old signature timestamp"
        self.streams[key] = stamp
        self._timestamp = max(self._timestamp, stamp)
        self.accepted_signed += 1
        return None


class MavlinkFramer:
    """Bytes in, pymavlink messages and :class:`Rejected` spans out, resynchronising after bad frames.

    ``feed(data, packet_end)``: ``packet_end`` says the data was one datagram (a frame never spans
    two). The buffer holds at most one incomplete frame (<= 280 bytes) between calls.
    ``signing``: a :class:`SignatureCheck`, or None to accept signed and unsigned frames unchecked
    (what the MAVLink specification asks of a system that does not sign).
    """

    def __init__(self, signing: SignatureCheck | None = None) -> None:
        # A decoder without a key: pymavlink then leaves signatures alone and SignatureCheck judges them.
        self._decoder = mavlink2.MAVLink(None)
        self._decoder.robust_parsing = True
        self.signing = signing
        self._buf = bytearray()

    def reset(self) -> None:
        """Forget a partial frame (a new connection starts clean)."""
        self._buf.clear()

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray, packet_end: bool = False) -> list[Any]:
        buf = self._buf
        buf += data
        out: list[Any] = []
        pos = 0
        n = len(buf)
        while pos < n:
            start = _next_start(buf, pos)
            if start != pos:  # line noise before a start byte (or no start byte at all)
                end = n if start < 0 else start
                out.append(Rejected("bad start byte", f"{end - pos} bytes before a start byte", end - pos))
                pos = end
                continue
            size = _frame_size(buf, pos)
            if size is None or pos + size > n:  # header or frame incomplete
                if not packet_end:
                    break
                item: Any = Rejected("truncated frame", f"{n - pos} bytes left at the end of a datagram", 0)
            elif size < 0:
                item = Rejected("unsupported incompat_flags", f"incompat_flags 0x{buf[pos + 2]:02x}", 0)
            else:
                item = self._decode(buf, pos, size, packet_end)
            if isinstance(item, Rejected) and item.nbytes == 0:
                # Not a frame after all: one bad start byte. Search again from the next byte, and let this
                # rejection cover the bytes up to the next start byte (one count per failed candidate).
                nxt = _next_start(buf, pos + 1)
                end = n if nxt < 0 else nxt
                item = Rejected(item.category, item.detail, end - pos)
            out.append(item)
            pos += item.nbytes if isinstance(item, Rejected) else size
        del buf[:pos]
        return out

    def _decode(self, buf: bytearray, pos: int, size: int, packet_end: bool) -> Any:
        """The message, or a Rejected; ``nbytes == 0`` means "not a frame: resynchronise"."""
        frame = bytes(buf[pos : pos + size])
        try:
            msg = self._decoder.decode(bytearray(frame))
        except Exception as exc:  # MAVError, or anything a hostile frame provokes: not a frame
            reason = str(getattr(exc, "message", exc))
            return Rejected(_category(reason), reason[:120], 0)
        if msg.get_type().startswith("UNKNOWN_"):
            # No CRC_EXTRA, so no CRC check: believe the framing only if another frame starts right after.
            # And never when a frame this dialect can check starts inside it (or may, once more bytes come):
            # random bytes often end on some start byte, and swallowing the valid frame within would lose it.
            after = pos + size
            framed = (after < len(buf) and buf[after] in (V1_START, V2_START)) or (after == len(buf) and packet_end)
            framed = framed and not self._holds_a_checkable_frame(buf, pos + 1, after, packet_end)
            return Rejected("unknown message id", msg.get_type(), size if framed else 0)
        if self.signing is not None:
            signed = frame[0] == V2_START and bool(frame[2] & IFLAG_SIGNED)  # MAVLink 1 cannot be signed
            problem = self.signing.check(frame, signed)
            if problem:  # a genuine frame (its CRC is right) that is not acceptable: skip all of it
                return Rejected(problem, f"{msg.get_type()} from {msg.get_srcSystem()}/{msg.get_srcComponent()}", size)
        return msg


    def _holds_a_checkable_frame(self, buf: bytearray, lo: int, hi: int, packet_end: bool) -> bool:
        """Whether a start byte in ``buf[lo:hi]`` begins a frame that passes its CRC, or one still incomplete."""
        q = _next_start(buf, lo)
        while 0 <= q < hi:
            size = _frame_size(buf, q)
            if size is None or (size > 0 and q + size > len(buf)):
                if not packet_end:
                    return True  # cannot tell yet: do not swallow it
            elif size > 0:
                try:
                    inner = self._decoder.decode(bytearray(buf[q : q + size]))
                except Exception:  # bad CRC or impossible payload: not a frame
                    inner = None
                if inner is not None and not inner.get_type().startswith("UNKNOWN_"):
                    return True
            q = _next_start(buf, q + 1)
        return False


def _next_start(buf: bytearray, pos: int) -> int:
    a = buf.find(V2_START, pos)
    b = buf.find(V1_START, pos)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


def _frame_size(buf: bytearray, pos: int) -> int | None:
    """Bytes of the frame starting at ``pos``; None if the header is incomplete; -1 for bad incompat flags."""
    if pos + 3 > len(buf):
        return None
    length = buf[pos + 1]
    if buf[pos] == V1_START:
        return length + V1_OVERHEAD
    flags = buf[pos + 2]
    if flags & ~IFLAG_SIGNED:
        return -1
    return length + V2_OVERHEAD + (SIGNATURE_LEN if flags & IFLAG_SIGNED else 0)


def signature_timestamp(frame: bytes | bytearray) -> int | None:
    """The signing timestamp (10 us units since 2015-01-01) of a signed MAVLink 2 frame, else None."""
    if len(frame) < V2_OVERHEAD + SIGNATURE_LEN or frame[0] != V2_START or not frame[2] & IFLAG_SIGNED:
        return None
    return struct.unpack("<Q", bytes(frame[-12:-6]) + b"\0\0")[0]


__all__ = ["CATEGORIES", "MavlinkFramer", "Rejected", "SignatureCheck", "signature_timestamp"]
