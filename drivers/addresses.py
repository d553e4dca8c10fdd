"""``HOST:PORT`` addresses of command-line options and configuration keys."""

from __future__ import annotations


def parse_host_port(text: str, what: str, allow_port_zero: bool = True) -> tuple[str, int]:
    """``'HOST:PORT'`` -> ``(host, port)``; ValueError naming ``what`` (the option or key) on bad
    input. Port 0 (an ephemeral port, for a listener) only when ``allow_port_zero``: a client
    cannot connect to it."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"{what}: expected HOST:PORT, got {text!r}")
    try:
        port_n = int(port)
    except ValueError:
        raise ValueError(f"{what}: port must be an integer, got {port!r}") from None
    lowest = 0 if allow_port_zero else 1
    if not lowest <= port_n <= 65535:
        raise ValueError(f"{what}: port must be in {lowest}..65535, got {port_n}")
    return host, port_n
