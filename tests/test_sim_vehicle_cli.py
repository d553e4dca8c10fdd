"""`companion sim` command line: bad input is refused with a clear message; TCP serves one client at a time."""

import os
import signal
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.cli import main
from drivers.sim.harness import MavClient, SimVehicleProcess


@pytest.mark.parametrize("argv, message", [
    (["sim"], "give at least one link"),
    (["sim", "--udp-out", "nonsense"], "--udp-out: expected HOST:PORT"),
    (["sim", "--tcp-listen", "127.0.0.1:99999"], "port must be in 0..65535"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--set", "nav_pos_sigma_h=1"], "'sim.nav_pos_sigma_h'"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--set", "nav_vel_sigma_mps=-1"], "'sim.nav_vel_sigma_mps'"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--speedup", "0"], "'sim.speedup'"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--scenario", "no_such_scenario"], "no_such_scenario"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--home=95,0,0"], "latitude"),
    (["sim", "--tcp-listen", "127.0.0.1:0", "--sysid", "0"], "--sysid"),
])
def test_bad_command_lines_exit_2_naming_the_problem(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_tcp_serves_one_client_at_a_time_and_stream_rates_stick_to_the_port():
    with SimVehicleProcess(["--flavour", "ardupilot", "--tcp-listen", "127.0.0.1:0", "--speedup", "5",
                            "--origin-delay", "0"]) as sim:
        port = sim.endpoints["tcp"]
        first = MavClient(f"tcp:127.0.0.1:{port}")
        first.wait_heartbeat()
        assert first.set_interval(mav.MAVLINK_MSG_ID_ATTITUDE, 10) == mav.MAV_RESULT_ACCEPTED
        # a second client is refused while the first is connected (like an ArduPilot SITL port)
        second = socket.create_connection(("127.0.0.1", port), timeout=2)
        second.settimeout(2)
        assert second.recv(1024) == b""
        second.close()
        # line noise (no frame start bytes) and a corrupted frame are dropped; the link keeps working
        noise = bytes(b for b in os.urandom(400) if b not in (0xFD, 0xFE))
        frame = bytearray(mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(mav.MAVLink(None, 255, 190)))
        frame[-1] ^= 0xFF  # bad CRC
        first.conn.write(noise + bytes(frame))
        ack = first.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert ack is not None and ack.result == mav.MAV_RESULT_ACCEPTED
        version = first.recv("AUTOPILOT_VERSION", 2)
        assert version is not None and version.flight_sw_version >> 24 == 4  # 4.6.x
        assert first.recv("ATTITUDE", 2) is not None
        # TIMESYNC requests are answered with the vehicle's clock (simulated ns since boot)
        first.mav.timesync_send(0, 123456789)
        ts = first.recv("TIMESYNC", 2, lambda m: m.ts1 == 123456789)
        boot = first.recv("ATTITUDE", 2).time_boot_ms
        assert ts is not None and abs(ts.tc1 * 1e-6 - boot) < 500
        first.close()
        time.sleep(0.3)
        # the next client gets the port's streams without asking again
        third = MavClient(f"tcp:127.0.0.1:{port}")
        third.wait_heartbeat()
        assert third.recv("ATTITUDE", 2) is not None
        third.close()
        assert sim.stop() == 0


def test_udp_in_answers_the_peer_that_spoke_and_sigint_ends_the_process_cleanly():
    sim = SimVehicleProcess(["--tcp-listen", "127.0.0.1:0", "--udp-in", "127.0.0.1:0"]).start()
    assert set(sim.endpoints) == {"tcp", "udp"}
    client = MavClient(f"udpout:127.0.0.1:{sim.endpoints['udp']}")
    client.heartbeat()  # udpin semantics: the vehicle answers whoever spoke last
    assert client.wait_heartbeat().autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    client.close()
    sim.proc.send_signal(signal.SIGINT)
    assert sim.proc.wait(10) == 0
    sim.stop()
