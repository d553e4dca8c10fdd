"""The frame stream camera (drivers/cameras/stream.py) and the simulator's camera server
(drivers/sim/camera_server.py): the wire format, a reader against a real TCP server on 127.0.0.1
that misbehaves, and ``companion sim --camera-listen`` rendering the true pose at the exposure."""

from __future__ import annotations

import asyncio
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import CameraConfig
from drivers.cameras.base import CameraError
from drivers.cameras.stream import HEADER, FrameStreamError, StreamCamera, decode_header, encode_frame, parse_address


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**63 - 1), st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(1, 40))
def test_a_frame_record_round_trips(t_us, seq, w, h):
    img = np.random.default_rng(seq % 1000).integers(0, 256, (h, w), dtype=np.uint8)
    rec = encode_frame(t_us, seq, img)
    assert len(rec) == HEADER.size + w * h
    assert decode_header(rec[:HEADER.size]) == (t_us, seq, w, h, w * h)
    assert np.array_equal(np.frombuffer(rec[HEADER.size:], np.uint8).reshape(h, w), img)


def test_bad_records_and_addresses_are_named():
    good = encode_frame(5, 1, np.zeros((4, 6), np.uint8))[:HEADER.size]
    with pytest.raises(FrameStreamError, match="magic"):
        decode_header(b"XXXX" + good[4:])
    with pytest.raises(FrameStreamError, match="version"):
        decode_header(good[:4] + struct.pack("<H", 9) + good[6:])
    with pytest.raises(FrameStreamError, match="payload"):
        decode_header(good[:-4] + struct.pack("<I", 7))
    with pytest.raises(ValueError, match="uint8"):
        encode_frame(0, 0, np.zeros((4, 4), np.float32))
    for bad in ("localhost", ":5600", "host:port", "127.0.0.1:0", "127.0.0.1:70000"):
        with pytest.raises(ValueError, match="stream_address"):
            parse_address(bad)
    assert parse_address("127.0.0.1:5600") == ("127.0.0.1", 5600)


def _image(k: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 256, (48, 64), dtype=np.uint8)


def _config(port: int, **kw) -> CameraConfig:
    return CameraConfig(source="stream", stream_address=f"127.0.0.1:{port}", width=64, height=48, rate_hz=1.0, **kw)


def test_the_reader_maps_times_skips_unsynced_frames_and_survives_a_bad_server():
    """A real TCP server on 127.0.0.1 sends: a frame before time sync (dropped), two good frames, a
    corrupt record (connection dropped, CameraError), then, on the reconnection, a frame of the
    wrong size, a blank one, one going back in time (each refused and counted by the frame checks)
    and a good one. The reader says what went wrong and goes on."""
    async def scenario():
        connections = []

        async def serve(reader, writer):
            connections.append(writer)
            if len(connections) == 1:
                for k in (1, 2, 3):
                    writer.write(encode_frame(1_000_000 * k, k, _image(k)))
                writer.write(b"CMFR" + b"\x00" * (HEADER.size - 4))  # version 0: not a frame
            else:
                writer.write(encode_frame(7_000_000, 7, _image(7)[:10, :10].copy()))  # wrong size
                writer.write(encode_frame(8_000_000, 8, np.zeros((48, 64), np.uint8)))  # blank
                writer.write(encode_frame(2_500_000, 9, _image(9)))  # before the last delivered frame
                writer.write(encode_frame(10_000_000, 10, _image(10)))
            await writer.drain()
            await reader.read()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        # autopilot time -> companion time: not synced before 1.5 s, then an offset of +100 s
        cam = StreamCamera(_config(port), lambda t: None if t < 1.5 else t + 100.0)
        got = [await asyncio.wait_for(cam.read(), 5) for _ in range(2)]
        errors = []
        for _ in range(3):
            try:
                got.append(await asyncio.wait_for(cam.read(), 5))
                break
            except CameraError as exc:
                errors.append(str(exc))
        await cam.close()
        server.close()
        return got, errors, cam

    got, errors, cam = asyncio.run(scenario())
    assert [f.t_s for f in got] == [102.0, 103.0, 110.0]
    assert [f.sequence for f in got] == [2, 3, 10] and np.array_equal(got[2].image, _image(10))
    assert len(errors) == 1 and "version 0" in errors[0]
    assert (cam.unsynced_frames, cam.bad_records, cam.connections) == (1, 1, 2)
    st = cam.stats
    assert (st.delivered, st.rejected_size, st.rejected_blank, st.rejected_time) == (3, 1, 1, 1)


def test_a_quiet_server_a_stalled_record_and_a_close_during_a_read():
    """Over a real socket: a server quiet for longer than the read timeout is a CameraError that
    keeps the connection (the next frame then arrives on it); a record that stops half-way drops
    the connection (the reader reconnects); close() ends a read blocked in its thread at once."""
    async def scenario():
        connections = []
        release, quiet_seen = asyncio.Event(), asyncio.Event()

        async def serve(reader, writer):
            connections.append(writer)
            if len(connections) == 1:
                await quiet_seen.wait()  # quiet until the reader has given up once (0.3 s read timeout)
                writer.write(encode_frame(2_000_000, 2, _image(2)))
                writer.write(encode_frame(3_000_000, 3, _image(3))[:HEADER.size + 100])  # stops half-way
                await writer.drain()
            elif len(connections) == 2:
                writer.write(encode_frame(4_000_000, 4, _image(4)))
                await writer.drain()
            await release.wait()  # then silent until the test ends
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        cam = StreamCamera(_config(port), lambda t: t, read_timeout_s=0.3)
        outcomes = []
        for _ in range(4):
            try:
                outcomes.append(await asyncio.wait_for(cam.read(), 5))
            except CameraError as exc:
                outcomes.append(str(exc))
                quiet_seen.set()
        blocked = asyncio.ensure_future(cam.read())  # nothing more comes: blocked in recv
        await asyncio.sleep(0.1)
        t0 = time.monotonic()
        await cam.close()
        try:
            await asyncio.wait_for(blocked, 2)
        except CameraError as exc:
            outcomes.append(str(exc))
        closed_in_s = time.monotonic() - t0
        release.set()
        server.close()
        return outcomes, closed_in_s, cam

    outcomes, closed_in_s, cam = asyncio.run(scenario())
    assert "no frame for 0.3 s" in outcomes[0]
    assert outcomes[1].sequence == 2 and outcomes[1].t_s == 2.0
    assert "connection ended" in outcomes[2]
    assert outcomes[3].sequence == 4 and np.array_equal(outcomes[3].image, _image(4))
    assert cam.connections == 2 and len(outcomes) == 5 and closed_in_s < 0.5


def test_an_absent_server_is_a_camera_error_not_a_hang():
    from tests.processes import free_port

    cam = StreamCamera(_config(free_port()), lambda t: t, connect_timeout_s=1.0)
    with pytest.raises(CameraError, match="cannot connect"):
        asyncio.run(asyncio.wait_for(cam.read(), 5))


def test_the_simulator_streams_frames_at_the_camera_rate_on_its_boot_clock():
    """``companion sim --camera-listen``: frames at the camera rate, stamped on the autopilot's clock
    (time since boot, on the physics grid), numbered without gaps."""
    from drivers.sim.harness import SimVehicleProcess

    sim = SimVehicleProcess(["--scenario", "default", "--tcp-listen", "127.0.0.1:0", "--speedup", "2",
                             "--camera-listen", "127.0.0.1:0", "--camera-rate", "10"]).start()
    try:
        port = sim.endpoints["camera"]

        async def read_frames(n):
            # blank check off: on the ground the camera sees a featureless patch of ground
            cam = StreamCamera(CameraConfig(source="stream", stream_address=f"127.0.0.1:{port}", rate_hz=10.0,
                                            blank_std_max=0.0), lambda t: t)
            frames = [await asyncio.wait_for(cam.read(), 10) for _ in range(n)]
            await cam.close()
            return frames

        frames = asyncio.run(read_frames(5))
    finally:
        assert sim.stop() == 0
    t = np.array([f.t_s for f in frames])
    np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-6)  # 10 Hz in simulated time
    assert np.all(np.diff([f.sequence for f in frames]) == 1) and frames[0].image.shape == (480, 640)


def test_the_camera_server_renders_the_pose_of_the_exposure():
    """The server renders the pose it is handed at the tick (the physics step's truth) and stamps
    the frame with that step's time: a frame from 15 m up over the default world equals the local
    render of the same pose, pixel for pixel, and a textured one (not a blank that would match
    anything)."""
    from companion.config import CompanionConfig, replace
    from companion.method.geometry import euler_to_matrix
    from drivers.sim.camera_server import camera_server_from_config

    cfg = replace(CompanionConfig(), **{"sim.image_noise_sigma": 0.0, "camera.rate_hz": 10.0})
    poses = {0.0: (np.array([20.0, 0.0, -15.0]), np.eye(3)),
             0.1: (np.array([20.6, 0.0, -15.0]), euler_to_matrix(0.02, -0.05, 0.1))}
    asked = []

    async def scenario():
        server = camera_server_from_config(cfg, "127.0.0.1", 0)
        await server.start()
        port = int(server.describe().rsplit(":", 1)[1])
        cam = StreamCamera(CameraConfig(source="stream", stream_address=f"127.0.0.1:{port}", rate_hz=10.0),
                           lambda t: t)
        reading = asyncio.create_task(asyncio.wait_for(cam.read(), 10))
        for _ in range(100):  # until the client is connected (ticks without a client are not rendered)
            await asyncio.sleep(0.01)
            if server._clients:
                break
        frames = []
        for t_s in (0.0, 0.05, 0.1):  # 0.05 is between ticks: nothing
            server.tick(t_s, lambda t_s=t_s: asked.append(t_s) or poses[t_s])
            if t_s == 0.05:
                continue
            frames.append(await reading)
            if t_s < 0.1:
                reading = asyncio.create_task(asyncio.wait_for(cam.read(), 10))
        await cam.close()
        local = camera_server_from_config(cfg, "127.0.0.1", 0)
        expected = [local._renderer.render(*local._mount.camera_pose(*poses[t])) for t in (0.0, 0.1)]
        server.close()
        local.close()
        await asyncio.sleep(0.1)  # let the connection handler see the end
        return frames, expected

    frames, expected = asyncio.run(scenario())
    assert asked == [0.0, 0.1]
    assert [f.t_s for f in frames] == pytest.approx([0.0, 0.1], abs=1e-6)  # microseconds on the wire
    for frame, exp in zip(frames, expected):
        assert exp.std() > 10  # textured ground
        assert np.array_equal(frame.image, exp)
    assert not np.array_equal(frames[0].image, frames[1].image)
