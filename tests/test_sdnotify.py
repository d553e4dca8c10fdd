"""sd_notify over a real unix datagram socket, as systemd provides it."""

import socket

from companion.service.sdnotify import SystemdNotifier


def test_ready_watchdog_status_reach_the_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(2.0)
    try:
        n = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert n.enabled and n.watchdog_interval_s == 1.0
        assert n.ready("mapping")
        assert server.recv(256) == b"READY=1\nSTATUS=mapping"
        assert n.watchdog()
        assert server.recv(256) == b"WATCHDOG=1"
        assert n.stopping()
        assert server.recv(256) == b"STOPPING=1"
        n.close()
    finally:
        server.close()


def test_without_systemd_it_is_a_no_op():
    n = SystemdNotifier({})
    assert not n.enabled and n.watchdog_interval_s is None
    assert not n.ready()


def test_vanished_socket_is_counted_not_raised(tmp_path):
    n = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    assert not n.watchdog()
    assert n.errors == 1
