"""The frame stream camera (drivers/cameras/stream.py) and the simulator's camera server
(drivers/sim/camera_server.py): the wire format, a reader against a real TCP server on 127.0.0.1
that misbehaves, and ``companion sim --camera-listen`` rendering the true pose at the exposure."""

from __future__ import annotations

import asyncio
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.clock import Clock
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
    return np.full((48, 64), k % 256, np.uint8)


def test_the_reader_maps_times_skips_unsynced_frames_and_survives_a_bad_server():
    """A real TCP server on 127.0.0.1 sends: a frame before time sync (dropped), two good frames, a
    corrupt record (connection dropped, CameraError), then, on the reconnection, a frame of the
    wrong size (refused) and a good one. The reader says what went wrong and goes on."""
    async def scenario():
        connections = []

        async def serve(reader, writer):
            connections.append(writer)
            if len(connections) == 1:
                for k in (1, 2, 3):
                    writer.write(encode_frame(1_000_000 * k, k, _image(k)))
                writer.write(b"CMFR" + b"\x00" * (HEADER.size - 4))  # version 0: not a frame
            else:
                writer.write(encode_frame(9_000_000, 9, np.zeros((10, 10), np.uint8)))
                writer.write(encode_frame(10_000_000, 10, _image(10)))
            await writer.drain()
            await reader.read()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        # autopilot time -> companion time: not synced before 1.5 s, then an offset of +100 s
        cam = StreamCamera(f"127.0.0.1:{port}", Clock(1.0), lambda t: None if t < 1.5 else t + 100.0, 64, 48)
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
    assert [f.sequence for f in got] == [2, 3, 10] and got[2].image.shape == (48, 64) and got[2].image[0, 0] == 10
    assert "version 0" in errors[0] and "10x10" in errors[1]
    assert (cam.unsynced_frames, cam.bad_records, cam.wrong_size, cam.connections) == (1, 1, 1, 2)


def test_an_absent_server_is_a_camera_error_not_a_hang():
    from tests.processes import free_port

    cam = StreamCamera(f"127.0.0.1:{free_port()}", Clock(1.0), lambda t: t, 64, 48, connect_timeout_s=1.0)
    with pytest.raises(CameraError, match="cannot connect"):
        asyncio.run(asyncio.wait_for(cam.read(), 5))


def test_the_simulator_serves_the_true_pose_at_each_exposure():
    """``companion sim --camera-listen``: frames at the camera rate, stamped on the autopilot's clock
    (time since boot), each one exactly the render of the vehicle's true pose at that instant
    (on the ground before take-off: home, level, heading north)."""
    from companion.config import CompanionConfig, replace
    from drivers.sim.camera_server import camera_server_from_config
    from drivers.sim.harness import SimVehicleProcess

    sim = SimVehicleProcess(["--scenario", "default", "--tcp-listen", "127.0.0.1:0", "--speedup", "2",
                             "--camera-listen", "127.0.0.1:0", "--camera-rate", "10",
                             "--set", "image_noise_sigma=0"]).start()
    try:
        port = sim.endpoints["camera"]

        async def read_frames(n):
            cam = StreamCamera(f"127.0.0.1:{port}", Clock(1.0), lambda t: t, 640, 480)
            frames = [await asyncio.wait_for(cam.read(), 10) for _ in range(n)]
            await cam.close()
            return frames

        frames = asyncio.run(read_frames(5))
    finally:
        assert sim.stop() == 0
    t = np.array([f.t_s for f in frames])
    np.testing.assert_allclose(np.diff(t), 0.1, atol=1e-6)  # 10 Hz in simulated time, on the physics grid
    assert np.all(np.diff([f.sequence for f in frames]) == 1)
    # The same render, made here from the pose the vehicle has on the ground.
    cfg = replace(CompanionConfig(), **{"sim.image_noise_sigma": 0.0})
    local = camera_server_from_config(cfg, "127.0.0.1", 0)
    from drivers.sim.vehicle import home_from_scenario

    p_body = np.array([0.0, 0.0, home_from_scenario("default").start_down_m])
    p_c, R_nc = local._mount.camera_pose(p_body, np.eye(3))
    expected = local._renderer.render(p_c, R_nc)
    diff = np.abs(frames[-1].image.astype(int) - expected.astype(int))
    print(f"\nsim camera stream: {len(frames)} frames at {t[0]:.2f}..{t[-1]:.2f} s since boot; "
          f"pixels differing from the local render of the true pose: {np.count_nonzero(diff)} (max {diff.max()})")
    assert diff.mean() < 0.5 and np.count_nonzero(diff > 2) < 0.001 * diff.size
    local.close()
