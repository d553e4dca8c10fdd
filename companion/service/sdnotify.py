"""systemd notification protocol (sd_notify) without libsystemd.

systemd passes ``NOTIFY_SOCKET`` (a filesystem path or an abstract socket starting with '@')
to a ``Type=notify`` service. The service sends datagrams such as ``READY=1``,
``WATCHDOG=1``, ``STATUS=...`` and ``STOPPING=1``. With ``WatchdogSec=`` set, systemd also
passes ``WATCHDOG_USEC``; if no ``WATCHDOG=1`` arrives within it, systemd kills and restarts the
service. The daemon sends WATCHDOG from the control loop, so a stuck loop gets restarted.
"""

from __future__ import annotations

import os
import socket


class SystemdNotifier:
    """Sends sd_notify datagrams; a no-op when not started by systemd (no NOTIFY_SOCKET)."""

    def __init__(self, environ: dict[str, str] | None = None):
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        self._address = "\0" + address[1:] if address.startswith("@") else address
        usec = env.get("WATCHDOG_USEC", "")
        self.watchdog_interval_s = int(usec) / 1e6 / 2 if usec.isdigit() and int(usec) > 0 else None
        self._sock: socket.socket | None = None
        self.errors = 0
        if self._address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.setblocking(False)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, state: str) -> bool:
        if self._sock is None:
            return False
        try:
            self._sock.sendto(state.encode(), self._address)
            return True
        except OSError:
            self.errors += 1
            return False

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
