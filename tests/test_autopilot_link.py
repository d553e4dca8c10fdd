"""The autopilot link against a scripted autopilot over real loopback UDP, TCP and a pty.

The peer below is written here, from pymavlink's MAVLink 2 dialect, and does just what ArduPilot
Copter / PX4 do that the link depends on: HEARTBEAT, SET_MESSAGE_INTERVAL (with DENIED for the
messages ArduPilot does not have), streams at the requested intervals, TIMESYNC answers, modes,
arming, REQUEST_MESSAGE, and it records what the companion sends.
"""

import asyncio
import contextlib
import json
import math
import os
import random

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.config import CompanionConfig, replace
from companion.method.geometry import euler_to_quat
from companion.method.navigation.covariance import quat_to_euler
from drivers.autopilot.link import AutopilotLink
from drivers.autopilot.protocol import TYPEMASK_VELOCITY_ONLY
from drivers.clock import Clock

AP_AHEAD_S = 876.543  # the autopilot booted this long before the companion clock started
TRUE_OFFSET = -AP_AHEAD_S  # companion - autopilot
SPEED = np.array([2.0, 1.0, 0.0])
YAW_RATE = 0.2
ARDUPILOT_DENIED = {
    mavlink2.MAVLINK_MSG_ID_ODOMETRY,
    mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV,
    mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION_COV,
    mavlink2.MAVLINK_MSG_ID_ESTIMATOR_STATUS,
}
PX4_UNSUPPORTED = {mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT}
COPTER_GUIDED, COPTER_LOITER = 4, 5
ORIGIN = (47.0, 8.0, 400.0)


def px4_mode(main, sub=0):
    return (main << 16) | (sub << 24)


class Peer:
    """A scripted autopilot (system 1, component 1)."""

    def __init__(self, clock, flavour="ardupilot", denied=None, hb_rate=10.0, ap_ahead_s=AP_AHEAD_S):
        self.clock = clock
        self.flavour = flavour
        self.ap_ahead_s = ap_ahead_s
        self.denied = set(ARDUPILOT_DENIED if flavour == "ardupilot" else PX4_UNSUPPORTED) if denied is None else set(denied)
        self.hb_rate = hb_rate
        self.mav = mavlink2.MAVLink(None, 1, 1)
        self.mav.robust_parsing = True
        self.intervals: dict[int, float] = {}
        self.next_due: dict[int, float] = {}
        self.received: list = []
        self.heartbeats_on = True
        self.nav_on = True
        self.custom_mode = COPTER_LOITER if flavour == "ardupilot" else px4_mode(3)
        self.armed = False
        self.garbage = False
        self.sent = 0
        self._write = None
        self._udp = None
        self._udp_addr = None
        self._server = None
        self._client = None
        self._task = None
        self.ekf_flags = 1 | 2 | 4 | 8 | 16 | 32

    # --- time and motion ---------------------------------------------------------------------
    def ap_time(self):
        return self.clock.now() + self.ap_ahead_s

    def t_motion(self):
        return self.clock.now()  # motion is a function of companion time so tests can check it

    # --- transports ----------------------------------------------------------------------------
    async def serve_udp(self):
        loop = asyncio.get_running_loop()
        peer = self

        class P(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                peer._udp_addr = addr
                peer._on_bytes(data)

        self._udp, _ = await loop.create_datagram_endpoint(P, local_addr=("127.0.0.1", 0))
        self._write = lambda b: self._udp_addr and self._udp.sendto(b, self._udp_addr)
        return self._udp.get_extra_info("sockname")[1]

    async def send_udp_to(self, addr):
        loop = asyncio.get_running_loop()
        peer = self

        class P(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                peer._on_bytes(data)

        self._udp, _ = await loop.create_datagram_endpoint(P, remote_addr=addr)
        self._write = lambda b: self._udp.sendto(b)

    async def serve_tcp(self, port=0):
        loop = asyncio.get_running_loop()
        peer = self

        class P(asyncio.Protocol):
            def connection_made(self, transport):
                if peer._client is not None:
                    transport.close()  # SITL: one client per port
                    return
                peer._client = transport

            def data_received(self, data):
                peer._on_bytes(data)

            def connection_lost(self, exc):
                if peer._client is not None and peer._client.is_closing():
                    peer._client = None

        self._server = await loop.create_server(P, "127.0.0.1", port)
        self._write = lambda b: self._client is not None and not self._client.is_closing() and self._client.write(b)
        return self._server.sockets[0].getsockname()[1]

    async def stop_tcp(self):
        if self._client is not None:
            self._client.close()
            self._client = None
        self._server.close()
        await self._server.wait_closed()

    def start(self):
        self._task = asyncio.create_task(self._run())

    async def stop(self):
        if self._task:
            await cancel_and_wait(self._task)
        if self._udp:
            self._udp.close()
        if self._server:
            self._server.close()

    # --- sending ---------------------------------------------------------------------------------
    def send(self, msg, mav=None):
        mav = mav or self.mav
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        if self._write and self._write(buf) is not False:
            self.sent += 1

    def heartbeat(self):
        autopilot = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA if self.flavour == "ardupilot" else mavlink2.MAV_AUTOPILOT_PX4
        base = 1 | (128 if self.armed else 0)
        return self.mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, autopilot, base, self.custom_mode, mavlink2.MAV_STATE_STANDBY)

    def make(self, msg_id):
        t_ap = self.ap_time()
        t = self.t_motion()
        ms = int(t_ap * 1000)
        p = SPEED * t + np.array([0.0, 0.0, -10.0])
        v = SPEED
        q = euler_to_quat(0.0, 0.0, YAW_RATE * t)
        m = self.mav
        if msg_id == mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return m.local_position_ned_encode(ms, *p, *v)
        if msg_id == mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            return m.attitude_quaternion_encode(ms, *q, 0.0, 0.0, YAW_RATE)
        if msg_id == mavlink2.MAVLINK_MSG_ID_ODOMETRY:
            pose = [float("nan")] * 21
            for i, var in zip((0, 6, 11, 15, 18, 20), (0.04, 0.04, 0.09, 1e-4, 1e-4, 4e-4)):
                pose[i] = var
            twist = [float("nan")] * 21
            for i, var in zip((0, 6, 11), (0.01, 0.01, 0.02)):
                twist[i] = var
            return m.odometry_encode(int(t_ap * 1e6), 1, 1, *p, list(q), *v, 0.0, 0.0, YAW_RATE, pose, twist, 0, 1)
        if msg_id == mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT:
            return m.ekf_status_report_encode(self.ekf_flags, 0.1, 0.2, 0.1, 0.1, 0.0)
        if msg_id == mavlink2.MAVLINK_MSG_ID_ESTIMATOR_STATUS:
            return m.estimator_status_encode(int(t_ap * 1e6), 63, 0.1, 0.1, 0.1, 0.1, 0, 0, 0.5, 0.8)
        if msg_id == mavlink2.MAVLINK_MSG_ID_GPS_RAW_INT:
            return m.gps_raw_int_encode(int(t_ap * 1e6), 3, 470000000, 80000000, 400000, 80, 120, 0, 0, 12, 0, 900, 1500, 250)
        if msg_id == mavlink2.MAVLINK_MSG_ID_SYSTEM_TIME:
            return m.system_time_encode(1_700_000_000_000_000 + int(t_ap * 1e6), ms)
        if msg_id == mavlink2.MAVLINK_MSG_ID_SIM_STATE:
            k = 6378100.0 * math.pi / 180
            lat = ORIGIN[0] + p[0] / k
            lon = ORIGIN[1] + p[1] / (k * math.cos(math.radians(0.5 * (lat + ORIGIN[0]))))
            r, pi, y = quat_to_euler(q)
            return m.sim_state_encode(*q, r, pi, y, 0, 0, 0, 0, 0, 0, lat, lon, ORIGIN[2] - p[2], 0, 0, *v, int(round(lat * 1e7)), int(round(lon * 1e7)))
        if msg_id == mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            return m.gps_global_origin_encode(int(ORIGIN[0] * 1e7), int(ORIGIN[1] * 1e7), int(ORIGIN[2] * 1000), int(t_ap * 1e6))
        return None

    async def _run(self):
        next_hb = 0.0
        while True:
            now = self.clock.now()
            if self.heartbeats_on and now >= next_hb:
                self.send(self.heartbeat())
                next_hb = now + 1.0 / self.hb_rate
            if self.nav_on:
                for msg_id, interval in list(self.intervals.items()):
                    if interval > 0 and now >= self.next_due.get(msg_id, 0.0):
                        msg = self.make(msg_id)
                        if msg is not None:
                            self.send(msg)
                        self.next_due[msg_id] = max(self.next_due.get(msg_id, now) + interval, now - interval)
            if self.garbage:
                self._write(bytes(random.getrandbits(8) for _ in range(random.randint(1, 40))))
            await asyncio.sleep(0.002)

    # --- receiving -------------------------------------------------------------------------------
    def _on_bytes(self, data):
        for m in self.mav.parse_buffer(data) or []:
            self.received.append(m)
            kind = m.get_type()
            if kind == "COMMAND_LONG":
                self._on_command(m)
            elif kind == "TIMESYNC" and m.tc1 == 0:
                self.send(self.mav.timesync_encode(int(self.ap_time() * 1e9), m.ts1))

    def _ack(self, m, result):
        self.send(self.mav.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))

    def _on_command(self, m):
        if m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id = int(m.param1)
            if msg_id in self.denied:
                return self._ack(m, mavlink2.MAV_RESULT_DENIED)
            self.intervals[msg_id] = m.param2 / 1e6
            return self._ack(m, mavlink2.MAV_RESULT_ACCEPTED)
        if m.command == mavlink2.MAV_CMD_REQUEST_MESSAGE:
            msg = self.make(int(m.param1))
            if msg is None:
                return self._ack(m, mavlink2.MAV_RESULT_FAILED)
            self._ack(m, mavlink2.MAV_RESULT_ACCEPTED)
            return self.send(msg)
        if m.command == mavlink2.MAV_CMD_DO_SET_MODE:
            self.custom_mode = int(m.param2) if self.flavour == "ardupilot" else px4_mode(int(m.param2), int(m.param3))
            return self._ack(m, mavlink2.MAV_RESULT_ACCEPTED)
        if m.command == mavlink2.MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = m.param1 == 1
            return self._ack(m, mavlink2.MAV_RESULT_ACCEPTED)
        return self._ack(m, mavlink2.MAV_RESULT_UNSUPPORTED)

    def of_type(self, kind):
        return [m for m in self.received if m.get_type() == kind]


# --------------------------------------------------------------------------------------------
# Harness
# --------------------------------------------------------------------------------------------


def make_cfg(connection, **changes):
    base = {
        "link.connection": connection,
        "link.heartbeat_timeout_s": 0.6,
        "link.reconnect_backoff_max_s": 0.2,
        "link.timesync_rate_hz": 10.0,
        "link.stream_check_s": 0.5,
        "link.command_timeout_s": 0.2,
        "link.nav_stream_rate_hz": 50.0,
        "link.aux_stream_rate_hz": 5.0,
    }
    base.update(changes)
    return replace(CompanionConfig(), **base)


async def until(pred, timeout=3.0, what="condition"):
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():
        if loop.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def running(link):
    task = asyncio.create_task(link.run())
    try:
        yield link
    finally:
        await cancel_and_wait(task)
    assert link.state == "stopped"


@contextlib.asynccontextmanager
async def connected(flavour: str = "ardupilot", transport: str = "udp", **settings):
    """A simulated autopilot peer serving on loopback (UDP or TCP) and a link connected to it:
    yields ``(peer, link)``; the link is stopped and the peer closed afterwards."""
    clock = Clock()
    peer = Peer(clock, flavour)
    if transport == "udp":
        address = f"udpout:127.0.0.1:{await peer.serve_udp()}"
    else:
        address = f"tcp:127.0.0.1:{await peer.serve_tcp()}"
    peer.start()
    link = AutopilotLink(make_cfg(address, **settings), clock)
    try:
        async with running(link):
            assert await link.wait_connected(3.0)
            yield peer, link
    finally:
        await peer.stop()


async def cancel_and_wait(task):
    """Cancel a task and wait for it, without swallowing a cancellation of the caller itself."""
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        if asyncio.current_task().cancelling():
            raise


def run(coro, timeout=15.0):
    asyncio.run(asyncio.wait_for(coro, timeout))


# --------------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------------


def test_ardupilot_over_udp_heartbeat_streams_nav_time_and_covariance_source():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_udp()
        # A GCS (system 255) and a gimbal (autopilot INVALID) talk first: neither is the autopilot.
        gcs = mavlink2.MAVLink(None, 255, 190)
        gimbal = mavlink2.MAVLink(None, 1, 154)
        link = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}"), clock)
        async with running(link):
            await until(lambda: peer._udp_addr is not None, what="the companion's first datagram")
            for _ in range(3):
                peer.send(gcs.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4), gcs)
                peer.send(gimbal.heartbeat_encode(mavlink2.MAV_TYPE_GIMBAL, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4), gimbal)
                await asyncio.sleep(0.02)
            assert link.target is None and link.state == "waiting_heartbeat"
            peer.start()
            assert await link.wait_connected(3.0)
            assert link.target == (1, 1) and link.flavour == "ardupilot" and link.mode == "LOITER"

            # Our heartbeat: onboard controller, no autopilot, component 191, MAVLink 2.
            hb = peer.of_type("HEARTBEAT")[0]
            assert (hb.type, hb.autopilot, hb.get_srcComponent()) == (mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 191)
            assert hb.get_header().mlen is not None and hb._header.incompat_flags is not None  # v2 header parsed

            await until(lambda: link.status()["streams"]["GPS_RAW_INT"]["result"] == "ACCEPTED", what="stream requests")
            requested = {int(m.param1): m.param2 for m in peer.of_type("COMMAND_LONG") if m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
            assert requested[mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED] == pytest.approx(20000)  # 50 Hz in us
            assert requested[mavlink2.MAVLINK_MSG_ID_EKF_STATUS_REPORT] == pytest.approx(200000)
            streams = link.status()["streams"]
            assert streams["ODOMETRY"]["result"] == "DENIED" and streams["LOCAL_POSITION_NED"]["result"] == "ACCEPTED"

            await until(lambda: link.timesync.status().samples >= 8 and link.nav_buffer.latest() is not None, what="timesync and nav")
            await asyncio.sleep(1.2)  # rates over a full window, more round trips
            st = link.status()
            offset_err = st["time"]["offset_s"] - TRUE_OFFSET
            print(
                f"\nUDP loopback: offset error {offset_err * 1e3:+.3f} ms, jitter {st['time']['jitter_s'] * 1e3:.3f} ms, "
                f"rtt {st['time']['rtt_s'] * 1e3:.3f} ms; rates {st['rates_hz']}"
            )
            assert st["time"]["source"] == "TIMESYNC"
            assert abs(offset_err) < 0.003
            assert 40 <= st["rates_hz"]["LOCAL_POSITION_NED"] <= 60
            assert 3 <= st["rates_hz"]["EKF_STATUS_REPORT"] <= 7
            assert st["nav"]["covariance_source"] == "EKF_STATUS_REPORT+GPS_RAW_INT+floors"
            assert st["nav"]["covariance_blocks"]["attitude"] == "EKF_STATUS_REPORT+floors"
            assert st["link"]["state"] == "connected" and st["link"]["autopilot"]["mode"] == "LOITER"
            json.loads(json.dumps(st))  # plain data, publishable as it is

            # The nav buffer interpolates the truth at companion times (time mapping included).
            now = clock.now()
            errs = []
            for dt in (0.05, 0.1, 0.2, 0.3):
                t = now - dt
                nav = link.nav_buffer.at(t)
                assert nav is not None
                errs.append(np.abs(nav.position_ned_m - (SPEED * t + [0, 0, -10])).max())
                assert abs(quat_to_euler(nav.quaternion_wxyz)[2] - YAW_RATE * t) < 0.005
            print(f"interpolated position error vs truth: max {max(errs) * 1e3:.2f} mm (2.2 m/s)")
            assert max(errs) < 0.02
        await peer.stop()

    run(main())


def test_px4_over_tcp_uses_odometry_and_answers_timesync_requests():
    async def main():
        clock = Clock()
        peer = Peer(clock, "px4")
        port = await peer.serve_tcp()
        peer.start()
        link = AutopilotLink(make_cfg(f"tcp:127.0.0.1:{port}"), clock)
        async with running(link):
            assert await link.wait_connected(3.0)
            assert link.flavour == "px4" and link.mode == "POSCTL"
            await until(lambda: (link.nav_buffer.latest() or 0) and link.nav_buffer.latest().covariance_source == "ODOMETRY", what="ODOMETRY covariance")
            nav = link.nav_buffer.latest()
            np.testing.assert_allclose(np.diag(nav.covariance)[:3], [0.09, 0.09, 0.09])  # floors (0.3 m)^2 over 0.04
            # Streams are requested one at a time in a fixed order: ODOMETRY can flow before EKF_STATUS_REPORT
            # (later in the order) has its answer, more so on a loaded machine.
            await until(lambda: link.status()["streams"]["EKF_STATUS_REPORT"]["result"] != "not requested", what="EKF_STATUS_REPORT answer")
            st = link.status()
            assert st["streams"]["EKF_STATUS_REPORT"]["result"] == "DENIED"
            assert st["streams"]["ODOMETRY"]["result"] == "ACCEPTED"
            # PX4 asks for our time too: the link answers with tc1 = its clock, ts1 echoed.
            peer.send(peer.mav.timesync_encode(0, 4242))
            await until(lambda: any(m.ts1 == 4242 and m.tc1 > 0 for m in peer.of_type("TIMESYNC")), what="TIMESYNC answer")
            answer = next(m for m in peer.of_type("TIMESYNC") if m.ts1 == 4242)
            assert abs(answer.tc1 * 1e-9 - clock.now()) < 0.1
        await peer.stop()

    run(main())


def test_setpoints_only_in_guided_with_commanding_enabled_else_advisory():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_udp()
        link = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}", **{"control.commanding_enabled": True}), clock)
        advisory = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}"), clock)
        async with running(link):
            peer.start()
            assert await link.wait_connected(3.0)
            await until(lambda: link.nav_buffer.latest() is not None, what="nav")
            # LOITER: not accepted, nothing on the wire.
            assert link.send_setpoint([1.0, 0.0, -0.5]) is False
            ok, why = link.can_command()
            assert not ok and "LOITER" in why and "GUIDED" in why
            assert link.status()["commanding"]["last_setpoint"]["commanded"] is False
            peer.custom_mode = COPTER_GUIDED
            await until(lambda: link.mode == "GUIDED", what="GUIDED")
            for _ in range(10):
                assert link.send_setpoint([1.0, 0.0, -0.5])
                await asyncio.sleep(0.05)
            assert link.send_setpoint([0.5, 0.5, 0.0], yaw_rad=1.0)
            await until(lambda: len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) >= 11, what="setpoints")
            sp = peer.of_type("SET_POSITION_TARGET_LOCAL_NED")
            assert (sp[0].type_mask, sp[0].coordinate_frame, sp[0].target_system, sp[0].target_component) == (3527, mavlink2.MAV_FRAME_LOCAL_NED, 1, 1)
            assert TYPEMASK_VELOCITY_ONLY == 3527
            assert (sp[0].vx, sp[0].vy, sp[0].vz) == (1.0, 0.0, -0.5)
            assert sp[-1].type_mask == 3527 - 1024 and sp[-1].yaw == pytest.approx(1.0)
            st = link.status()["commanding"]
            assert st["active"] and st["setpoints_sent"] == 11 and 10 <= st["setpoint_rate_hz"] <= 30
            with pytest.raises(ValueError, match="velocity"):
                link.send_setpoint([float("nan"), 0, 0])
        # Same vehicle in GUIDED, commanding disabled: advisory, nothing sent.
        n_before = len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        async with running(advisory):
            assert await advisory.wait_connected(3.0)
            await until(lambda: advisory.nav_buffer.latest() is not None, what="nav")
            assert advisory.mode == "GUIDED"
            assert advisory.send_setpoint([1.0, 0.0, 0.0]) is False
            rec = advisory.status()["commanding"]["last_setpoint"]
            assert rec["velocity_ned_mps"] == [1.0, 0.0, 0.0] and "advisory" in rec["reason"]
            await asyncio.sleep(0.1)
        assert len(peer.of_type("SET_POSITION_TARGET_LOCAL_NED")) == n_before
        await peer.stop()

    run(main())


def test_stale_navigation_refuses_commands_and_says_why():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        peer.custom_mode = COPTER_GUIDED
        port = await peer.serve_udp()
        cfg = make_cfg(f"udpout:127.0.0.1:{port}", **{"control.commanding_enabled": True, "nav.stale_after_s": 0.2})
        link = AutopilotLink(cfg, clock)
        async with running(link):
            peer.start()
            await until(lambda: link.can_command()[0], what="commanding possible")
            peer.nav_on = False  # heartbeats continue, navigation stops
            await asyncio.sleep(0.35)
            ok, why = link.can_command()
            assert not ok and "navigation stale" in why
            assert link.send_setpoint([1.0, 0, 0]) is False
            assert "navigation stale" in link.status()["commanding"]["reason"]
            peer.nav_on = True
            await until(lambda: link.can_command()[0], what="fresh again")
            peer.ekf_flags = 1 | 2 | 4 | 32 | 128  # EKF in constant-position mode
            await until(lambda: not link.can_command()[0], what="estimator unhealthy")
            assert "CONST_POS_MODE" in link.can_command()[1]
        await peer.stop()

    run(main())


def test_tcp_peer_goes_away_link_lost_then_reconnects_and_rerequests_streams():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_tcp()
        peer.start()
        link = AutopilotLink(make_cfg(f"tcp:127.0.0.1:{port}"), clock)
        async with running(link):
            assert await link.wait_connected(3.0)
            await until(lambda: len(peer.intervals) >= 5, what="streams")
            n_requests = len(peer.of_type("COMMAND_LONG"))
            await peer.stop_tcp()
            peer.intervals.clear()
            await until(lambda: link.state in ("lost", "reconnecting", "connecting"), what="link lost")
            assert link.status()["link"]["link_losses"] == 1
            assert "closed" in link.status()["link"]["last_error"] or "refused" in link.status()["link"]["last_error"]
            assert link.send_setpoint([0, 0, 0]) is False
            link.send_statustext("WARNING", "companion: queued while the link is down")
            await asyncio.sleep(0.3)  # a few refused reconnect attempts
            await peer.serve_tcp(port)
            assert await link.wait_connected(3.0)
            st = link.status()["link"]
            assert st["reconnects"] == 1 and st["connects"] == 2
            await until(lambda: len(peer.intervals) >= 5, what="streams requested again")
            assert len(peer.of_type("COMMAND_LONG")) > n_requests
            await until(lambda: any(b"queued while the link is down" in bytes(m.text, "utf-8") if isinstance(m.text, str) else False for m in peer.of_type("STATUSTEXT")), what="queued STATUSTEXT")
            assert any("link back" in m.text for m in peer.of_type("STATUSTEXT"))
        await peer.stop()

    run(main())


def test_udp_heartbeat_silence_is_link_lost_and_resumption_reconnects():
    async def main():
        async with connected("ardupilot", "udp") as (peer, link):
            peer.heartbeats_on = False
            await until(lambda: link.state == "lost", timeout=2.0, what="heartbeat timeout")
            assert "heartbeat timeout" in link.status()["link"]["last_error"]
            peer.heartbeats_on = True
            assert await link.wait_connected(2.0)
            assert link.reconnects == 1 and link.link_losses == 1

    run(main())


def test_udpin_listens_and_answers_the_sender():
    async def main():
        clock = Clock()
        link = AutopilotLink(make_cfg("udpin:127.0.0.1:0"), clock)
        async with running(link):
            await until(lambda: link.local_address is not None, what="bound")
            peer = Peer(clock, "px4")
            await peer.send_udp_to(("127.0.0.1", link.local_address[1]))
            peer.start()
            assert await link.wait_connected(3.0)
            await until(lambda: peer.of_type("HEARTBEAT"), what="our heartbeat back to the sender")
            await peer.stop()

    run(main())


def test_garbage_bytes_are_counted_and_nothing_stops():
    async def main():
        clock = Clock()
        random.seed(11)
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_tcp()
        peer.start()
        link = AutopilotLink(make_cfg(f"tcp:127.0.0.1:{port}"), clock)
        async with running(link):
            assert await link.wait_connected(3.0)
            await until(lambda: link.nav_buffer.latest() is not None, what="nav")
            peer.garbage = True
            await asyncio.sleep(0.8)
            n_nav = len(link.nav_buffer)
            st = link.status()
            wire = {k: v for k, v in st["rejected"].items() if k.startswith("wire:")}
            print(f"\ngarbage: {wire}; rates {st['rates_hz'].get('LOCAL_POSITION_NED')} Hz")
            assert sum(wire.values()) > 10
            # Line noise used to swallow the heartbeats around it and sometimes cost the link (pymavlink's robust
            # parser drops whatever a stray start byte's length claims); the framer loses none, deterministically
            # shown by tests/test_reliability_link.py::test_line_noise_costs_no_valid_frame_and_every_byte_is_accounted_for.
            assert link.state == "connected"
            peer.garbage = False
            t_before = link.nav_buffer.latest().t_s
            await until(lambda: link.nav_buffer.latest().t_s > t_before + 0.2, what="nav continues")
            assert n_nav > 0
        await peer.stop()

    run(main())


def test_mode_change_and_arming_only_when_configured():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_udp()
        peer.start()
        locked = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}"), clock)
        async with running(locked):
            assert await locked.wait_connected(3.0)
            with pytest.raises(PermissionError, match="allow_mode_change"):
                await locked.set_mode("GUIDED")
            with pytest.raises(PermissionError, match="allow_arm"):
                await locked.arm()
        assert not any(m.get_type() == "COMMAND_LONG" and m.command in (176, 400) for m in peer.received)
        free = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}", **{"control.allow_mode_change": True, "control.allow_arm": True}), clock)
        async with running(free):
            assert await free.wait_connected(3.0)
            assert await free.set_mode("GUIDED") == "ACCEPTED"
            await until(lambda: free.mode == "GUIDED", what="mode reported")
            assert await free.arm() == "ACCEPTED"
            await until(lambda: free.armed, what="armed reported")
            with pytest.raises(ValueError, match="unknown mode"):
                await free.set_mode("WARP")
        await peer.stop()

    run(main())


def test_autopilot_reboot_is_detected_and_time_relearnt():
    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_udp()
        peer.start()
        link = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}"), clock)
        async with running(link):
            assert await link.wait_connected(3.0)
            await until(lambda: link.timesync.synced and link.timesync.source == "TIMESYNC", what="sync")
            await until(lambda: link.assembler.origin is not None, what="origin")
            requests = len(peer.of_type("COMMAND_LONG"))
            peer.ap_ahead_s = 1.0 - clock.now()  # reboot: the autopilot clock restarts at 1 s
            peer.intervals.clear()  # and it forgot the streams
            await until(lambda: link.reboots == 1, what="reboot detected")
            await until(lambda: len(peer.intervals) >= 5, what="streams requested again")
            assert len(peer.of_type("COMMAND_LONG")) > requests
            await until(lambda: link.timesync.synced and abs(link.timesync.offset_s + peer.ap_ahead_s) < 0.003, what="new offset")
            assert any("reboot" in m.text for m in peer.of_type("STATUSTEXT"))
            # The origin is asked for again after the reboot (it may differ) and becomes known again.
            await until(lambda: link.assembler.origin is not None, what="origin known again")
            origin_requests = [m for m in peer.of_type("COMMAND_LONG") if m.command == mavlink2.MAV_CMD_REQUEST_MESSAGE and int(m.param1) == mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN]
            assert len(origin_requests) >= 2
        await peer.stop()

    run(main())


def test_sim_state_truth_pose_in_the_ekf_frame():
    async def main():
        async with connected("ardupilot", "udp", **{"link.request_sim_state": True}) as (peer, link):
            await until(lambda: link.truth_pose() is not None, what="truth")
            truth = link.truth_pose()
            expected = SPEED * truth.t_s + [0, 0, -10]
            assert np.abs(truth.position_ned_m - expected).max() < 0.05  # arrival-stamped, degE7-quantised
            assert truth.origin_source == "GPS_GLOBAL_ORIGIN"
            assert link.status()["streams"]["SIM_STATE"]["result"] == "ACCEPTED"

    run(main())


def test_long_statustext_goes_out_in_chunks():
    async def main():
        async with connected("ardupilot", "udp") as (peer, link):
            text = "companion: terrain avoidance engaged, climbing at 2.5 m/s over a 12 m structure ahead"
            assert link.send_statustext("WARNING", text) == 2
            assert link.send_statustext(6, "camera back") == 1
            await until(lambda: len(peer.of_type("STATUSTEXT")) >= 3, what="STATUSTEXT")
            chunks = [m for m in peer.of_type("STATUSTEXT") if m.id != 0]
            assert [m.chunk_seq for m in chunks] == [0, 1] and len({m.id for m in chunks}) == 1
            assert "".join(m.text for m in chunks) == text
            assert chunks[0].severity == mavlink2.MAV_SEVERITY_WARNING
            with pytest.raises(ValueError, match="severity"):
                link.send_statustext("LOUD", "x")

    run(main())


def test_serial_port_over_a_pty():
    async def main():
        master, slave = os.openpty()
        device = os.ttyname(slave)
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        os.set_blocking(master, False)
        loop = asyncio.get_running_loop()

        def readable():
            with contextlib.suppress(BlockingIOError, OSError):
                peer._on_bytes(os.read(master, 4096))

        loop.add_reader(master, readable)
        peer._write = lambda b: os.write(master, b)
        peer.start()
        link = AutopilotLink(make_cfg(f"{device},115200"), clock)
        try:
            async with running(link):
                assert await link.wait_connected(3.0)
                await until(lambda: link.nav_buffer.latest() is not None, what="nav over serial")
                assert peer.of_type("HEARTBEAT")
        finally:
            loop.remove_reader(master)
            await peer.stop()
            os.close(master)
            os.close(slave)

    run(main())


def test_unreachable_tcp_reports_the_error_and_retries_with_backoff():
    async def main():
        clock = Clock()
        peer = Peer(clock)
        port = await peer.serve_tcp()
        await peer.stop_tcp()  # a port nobody listens on
        link = AutopilotLink(make_cfg(f"tcp:127.0.0.1:{port}"), clock)
        async with running(link):
            await asyncio.sleep(0.8)
            st = link.status()["link"]
            assert st["state"] in ("reconnecting", "connecting")
            assert f"cannot open tcp:127.0.0.1:{port}" in st["last_error"]

    run(main())


def test_cancellation_always_stops_the_link_promptly():
    """Cancelling run() at any moment (mid command, mid reconnect) ends it: no swallowed cancellation."""

    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_tcp()
        peer.start()
        rng = random.Random(3)
        for i in range(12):
            peer._client = None  # each new link is the port's single client
            link = AutopilotLink(make_cfg(f"tcp:127.0.0.1:{port}"), clock)
            task = asyncio.create_task(link.run())
            await asyncio.sleep(rng.uniform(0.0, 0.15))
            async with asyncio.timeout(1.0):
                await cancel_and_wait(task)
            assert link.state == "stopped"
        await peer.stop()

    run(main())


def test_signed_link_rejects_unsigned_traffic_when_signing_is_required(tmp_path):
    key = bytes(range(32))
    key_file = tmp_path / "mavlink.key"
    key_file.write_text(key.hex() + "\n")
    key_file.chmod(0o600)  # a key others may read is refused (tests/test_reliability_link.py)

    def sign(mav):
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = int((__import__("time").time() - 1420070400) * 100_000)

    async def main():
        clock = Clock()
        unsigned = Peer(clock, "ardupilot")
        port = await unsigned.serve_udp()
        unsigned.start()
        cfg = make_cfg(f"udpout:127.0.0.1:{port}", **{"link.signing_key_file": str(key_file), "link.signing_required": True})
        link = AutopilotLink(cfg, clock)
        async with running(link):
            await asyncio.sleep(0.5)
            assert not link.connected
            assert link.status()["rejected"].get("wire: unsigned message", 0) > 0
        await unsigned.stop()

        signed = Peer(clock, "ardupilot")
        sign(signed.mav)
        signed.mav.signing.allow_unsigned_callback = lambda mav, msg_id: False
        port = await signed.serve_udp()
        signed.start()
        link = AutopilotLink(replace(cfg, **{"link.connection": f"udpout:127.0.0.1:{port}"}), clock)
        async with running(link):
            assert await link.wait_connected(3.0)
            await until(lambda: signed.of_type("COMMAND_LONG"), what="signed commands accepted by the peer")
            assert signed.mav.signing.goodsig_count > 0 and signed.mav.signing.reject_count == 0
        await signed.stop()

    run(main())


def test_bad_signing_key_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "short.key"
    bad.write_text("abcd")
    bad.chmod(0o600)
    with pytest.raises(ValueError, match="link.signing_key_file.*64 hex"):
        AutopilotLink(make_cfg("udpin:127.0.0.1:0", **{"link.signing_key_file": str(bad)}), Clock())
    with pytest.raises(ValueError, match="cannot read"):
        AutopilotLink(make_cfg("udpin:127.0.0.1:0", **{"link.signing_key_file": str(tmp_path / "none")}), Clock())
    with pytest.raises(ValueError, match="not understood"):
        AutopilotLink(make_cfg("com7"), Clock())


def test_a_cancelled_command_stays_cancelled_even_when_its_ack_arrives_at_the_same_moment():
    """Regression: asyncio.wait_for (3.11) returns the result instead of raising when the answer and
    the cancellation coincide, which left a link task running through shutdown."""

    class NullTransport:
        stream = False
        dropped_writes = 0

        def write(self, data):
            return True

    async def main():
        link = AutopilotLink(make_cfg("udpin:127.0.0.1:0"), Clock())
        link._command_lock = asyncio.Lock()
        link._target = (1, 1)
        link._transport = NullTransport()
        task = asyncio.create_task(link._command(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (32, 20000, 0, 0, 0, 0, 0)))
        await until(lambda: link._pending is not None, what="command sent")
        link._pending.future.set_result("ACCEPTED")
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    run(main())


def test_telemetry_log_is_a_tlog_pymavlink_reads_with_reception_times(tmp_path):
    from pymavlink import mavutil

    path = tmp_path / "telemetry.tlog"

    async def main():
        clock = Clock()
        peer = Peer(clock, "ardupilot")
        port = await peer.serve_udp()
        peer.start()
        link = AutopilotLink(make_cfg(f"udpout:127.0.0.1:{port}"), clock)
        async with running(link):
            import time as _time

            unix_start, t_start = _time.time(), clock.now()
            link.record_telemetry(path)
            assert await link.wait_connected(3.0)
            await until(lambda: link.nav_buffer.latest() is not None, what="nav")
            await asyncio.sleep(0.3)
            assert link.status()["link"]["telemetry_log"]["records"] > 20
        await peer.stop()
        return unix_start, t_start, clock.now()

    unix_start, t_start, t_end = asyncio.run(asyncio.wait_for(main(), 15))
    log = mavutil.mavlogfile(str(path), robust_parsing=True)
    kinds, stamps = {}, []
    while (m := log.recv_msg()) is not None:
        assert m.get_type() != "BAD_DATA"
        kinds.setdefault((m.get_type(), m.get_srcComponent()), 0)
        kinds[(m.get_type(), m.get_srcComponent())] += 1
        stamps.append(m._timestamp)
    assert kinds[("LOCAL_POSITION_NED", 1)] > 5 and kinds[("HEARTBEAT", 1)] > 0
    assert kinds[("HEARTBEAT", 191)] > 0 and kinds[("COMMAND_LONG", 191)] > 0  # what we sent is logged too
    assert all(b >= a for a, b in zip(stamps, stamps[1:]))
    assert unix_start - 0.01 <= stamps[0] and stamps[-1] <= unix_start + (t_end - t_start) + 0.01
