"""Connection strings as MAVProxy, mavlink-router and MAVSDK users write them, parsed to an :class:`Endpoint`."""

from __future__ import annotations

import re
from dataclasses import dataclass

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
