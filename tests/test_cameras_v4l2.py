"""V4L2 source: configuration errors, what is asked of the driver, capture timestamps, and loss and
reconnection with capped exponential backoff (a scripted fake device stands in for the hardware;
one test opens a real cv2.VideoCapture on a path that does not exist)."""

from __future__ import annotations

import asyncio
import logging
import time

import cv2
import numpy as np
import pytest

from companion.config import CameraConfig, ConfigError, replace
from drivers.cameras.base import CameraError
from drivers.cameras.factory import build_camera
from drivers.cameras.v4l2 import (
    EXPOSURE_UNIT_US,
    V4L2_EXPOSURE_APERTURE_PRIORITY,
    V4L2_EXPOSURE_MANUAL,
    V4L2Source,
    fourcc_code,
    fourcc_text,
    parse_device,
    parse_pixel_format,
)
from drivers.clock import Clock

W, H = 64, 48


def textured(seed: int, shape=(H, W)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


class FakeDevice:
    """The hardware behind the fake captures: plugged or not, what it grants, what it streams.

    ``script`` is a list of per-read outcomes: an ndarray (a frame), or False (read fails).
    When it runs out the device streams textured frames.
    """

    def __init__(self, *, present=True, grant=None, script=(), pos_msec=None):
        self.present = present
        self.grant = dict(grant or {})
        self.script = list(script)
        self.pos_msec = pos_msec  # callable -> POS_MSEC after a read, or None for "0"
        self.open_times: list[float] = []
        self.captures: list[FakeCapture] = []
        self.reads = 0

    def factory(self, device):
        self.open_times.append(time.monotonic())
        cap = FakeCapture(self, device)
        self.captures.append(cap)
        return cap


class FakeCapture:
    def __init__(self, dev: FakeDevice, device):
        self.dev = dev
        self.device = device
        self.opened = dev.present
        self.props: dict[int, float] = {cv2.CAP_PROP_FPS: 30.0, cv2.CAP_PROP_BUFFERSIZE: 4}
        self.sets: list[tuple[int, float]] = []
        self.released = False

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.sets.append((prop, value))
        self.props[prop] = value
        return True

    def get(self, prop):
        if prop in self.dev.grant:
            return self.dev.grant[prop]
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.dev.pos_msec() if self.dev.pos_msec else 0.0
        return self.props.get(prop, 0.0)

    def read(self):
        if not self.dev.present or not self.opened:
            return False, None
        self.dev.reads += 1
        item = self.dev.script.pop(0) if self.dev.script else textured(self.dev.reads)
        if item is False:
            return False, None
        if self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1) == 0 and fourcc_text(self.get(cv2.CAP_PROP_FOURCC)) == "YUYV":
            packed = np.zeros(item.shape[:2] + (2,), np.uint8)  # Y in channel 0, chroma in 1
            packed[:, :, 0] = item
            packed[:, :, 1] = 128
            return True, packed
        if item.ndim == 2 and self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1) != 0:
            item = cv2.cvtColor(item, cv2.COLOR_GRAY2BGR)  # what OpenCV gives with conversion on
        return True, item

    def release(self):
        self.released = True
        self.opened = False


def cam(**changes) -> CameraConfig:
    base = CameraConfig(source="v4l2", device="/dev/video7", width=W, height=H, rate_hz=50.0, pixel_format="GREY")
    return replace(base, **changes) if changes else base


def run(coro):
    return asyncio.run(coro)


# ---- configuration ------------------------------------------------------------------------


def test_device_and_pixel_format_parsing():
    assert parse_device("0") == 0 and parse_device(" 3 ") == 3
    assert parse_device("/dev/v4l/by-id/usb-cam-video-index0") == "/dev/v4l/by-id/usb-cam-video-index0"
    with pytest.raises(ConfigError, match="camera.device"):
        parse_device("  ")
    assert parse_pixel_format("grey") == "GREY"
    assert parse_pixel_format("Y16") == "Y16 "
    for bad in ("XYZW", "TOOLONG", "", "é"):
        with pytest.raises(ConfigError, match="camera.pixel_format"):
            parse_pixel_format(bad)
    assert fourcc_text(fourcc_code("MJPG")) == "MJPG" and fourcc_text(0) == ""


def test_construction_rejects_bad_config_without_touching_the_device():
    dev = FakeDevice()
    with pytest.raises(ConfigError, match="camera.pixel_format"):
        V4L2Source(cam(pixel_format="H264"), Clock(), capture_factory=dev.factory)
    with pytest.raises(ConfigError, match="camera.device"):
        V4L2Source(cam(device=""), Clock(), capture_factory=dev.factory)
    assert dev.open_times == []  # construction does not open: an absent device is not a config error
    src = build_camera(cam(), Clock(), capture_factory=dev.factory)
    assert isinstance(src, V4L2Source) and src.name == "v4l2:/dev/video7" and not src.connected


def test_open_asks_for_format_size_rate_and_manual_exposure_and_reports_the_grant():
    dev = FakeDevice()
    src = V4L2Source(cam(exposure_us=2500.0, pixel_format="YUYV"), Clock(), capture_factory=dev.factory)
    frame = run(src.read())
    sets = dict(dev.captures[0].sets)
    order = [p for p, _ in dev.captures[0].sets]
    assert order.index(cv2.CAP_PROP_FOURCC) < order.index(cv2.CAP_PROP_FRAME_WIDTH)  # format first
    assert fourcc_text(sets[cv2.CAP_PROP_FOURCC]) == "YUYV"
    assert (sets[cv2.CAP_PROP_FRAME_WIDTH], sets[cv2.CAP_PROP_FRAME_HEIGHT], sets[cv2.CAP_PROP_FPS]) == (W, H, 50.0)
    assert sets[cv2.CAP_PROP_AUTO_EXPOSURE] == V4L2_EXPOSURE_MANUAL
    assert sets[cv2.CAP_PROP_EXPOSURE] == pytest.approx(2500.0 / EXPOSURE_UNIT_US)
    g = src.granted
    assert (g.width, g.height, g.fourcc, g.exposure_us) == (W, H, "YUYV", pytest.approx(2500.0))
    # YUYV is read raw and its luma taken directly: exactly the streamed grey values
    assert sets[cv2.CAP_PROP_CONVERT_RGB] == 0
    assert frame.image.shape == (H, W) and frame.image.dtype == np.uint8
    assert np.array_equal(frame.image, textured(1))


def test_automatic_exposure_when_exposure_is_zero():
    dev = FakeDevice()
    src = V4L2Source(cam(exposure_us=0.0), Clock(), capture_factory=dev.factory)
    run(src.read())
    sets = dict(dev.captures[0].sets)
    assert sets[cv2.CAP_PROP_AUTO_EXPOSURE] == V4L2_EXPOSURE_APERTURE_PRIORITY
    assert cv2.CAP_PROP_EXPOSURE not in sets


def test_granted_size_differing_from_config_is_a_clear_camera_error():
    dev = FakeDevice(grant={cv2.CAP_PROP_FRAME_WIDTH: 320, cv2.CAP_PROP_FRAME_HEIGHT: 240})
    src = V4L2Source(cam(), Clock(), capture_factory=dev.factory, backoff_initial_s=0.01)
    with pytest.raises(CameraError) as e:
        run(src.read())
    msg = str(e.value)
    assert "320x240" in msg and f"{W}x{H}" in msg and "camera.width" in msg
    assert dev.captures[0].released


@pytest.mark.parametrize("backend", ["cv2.VideoCapture", "default"])
def test_real_opencv_on_a_missing_device_gives_a_clear_error_once_then_keeps_trying(backend):
    path = "/dev/video-companion-test-absent"
    kwargs = {"capture_factory": lambda d: cv2.VideoCapture(d, cv2.CAP_V4L2)} if backend != "default" else {}
    src = V4L2Source(cam(device=path), Clock(), backoff_initial_s=0.01, **kwargs)

    async def scenario():
        with pytest.raises(CameraError) as e:
            await src.read()
        assert path in str(e.value) and "no such device" in str(e.value)
        # The next read waits for the device instead of raising again; it stays cancellable.
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(src.read(), 0.2)
        await src.close()

    run(scenario())
    assert not src.connected


# ---- timestamps ---------------------------------------------------------------------------


def test_buffer_timestamp_stamps_the_capture_instant_on_the_companion_clock():
    age = 0.040  # the driver dequeued a frame captured 40 ms before the read returned
    dev = FakeDevice(pos_msec=lambda: (time.monotonic() - age) * 1000.0)
    clock = Clock(speedup=2.0)
    src = V4L2Source(cam(), clock, capture_factory=dev.factory)

    async def scenario():
        frame = await src.read()
        return frame, clock.now()

    frame, after = run(scenario())
    # age is wall time; on a 2x clock it is 80 ms of clock time
    assert after - frame.t_s == pytest.approx(age * clock.speedup, abs=0.015)
    assert src.stats.timestamps_fallback == 0


def test_without_buffer_timestamps_frames_are_stamped_half_a_period_before_the_read_returned():
    dev = FakeDevice(pos_msec=None)
    clock = Clock()
    src = V4L2Source(cam(rate_hz=10.0), clock, capture_factory=dev.factory)

    async def scenario():
        frames = [await src.read() for _ in range(3)]
        return frames, clock.now()

    frames, after = run(scenario())
    assert 0.05 <= after - frames[-1].t_s < 0.05 + 0.02
    assert src.stats.timestamps_fallback == 3
    assert all(b.t_s > a.t_s for a, b in zip(frames, frames[1:]))


# ---- frame checks on live frames ----------------------------------------------------------


def test_wrong_size_and_blank_frames_are_rejected_counted_and_skipped():
    good = textured(99)
    dev = FakeDevice(script=[textured(5, (H + 2, W)), np.zeros((H, W), np.uint8), np.full((H, W), 255, np.uint8), good])
    src = V4L2Source(cam(), Clock(), capture_factory=dev.factory)
    frame = run(src.read())
    assert np.array_equal(frame.image, good)
    assert frame.sequence == 4  # the device's 4th frame; the gap in sequence shows the rejections
    assert (src.stats.rejected_size, src.stats.rejected_blank, src.stats.delivered) == (1, 2, 1)


def test_a_device_that_only_sends_rejects_raises_after_a_bounded_number():
    dev = FakeDevice(script=[np.zeros((H, W), np.uint8)] * 30)
    src = V4L2Source(cam(), Clock(), capture_factory=dev.factory, max_consecutive_rejects=12)
    with pytest.raises(CameraError, match="12 consecutive frames rejected"):
        run(src.read())
    assert dev.reads == 12 and src.stats.rejected_blank == 12


# ---- loss and reconnection ----------------------------------------------------------------


def test_unplug_raises_once_then_reconnects_with_capped_exponential_backoff(caplog):
    dev = FakeDevice()
    src = V4L2Source(cam(reconnect_backoff_max_s=0.08), Clock(), capture_factory=dev.factory, backoff_initial_s=0.02)
    caplog.set_level(logging.INFO, logger="drivers.cameras.v4l2")

    async def scenario():
        before = [await src.read() for _ in range(3)]
        dev.present = False  # unplugged: reads fail, opens fail
        with pytest.raises(CameraError, match="camera lost"):
            await src.read()
        assert not src.connected
        task = asyncio.create_task(src.read())  # keeps trying without raising again
        while len(dev.open_times) < 7:  # initial open, the immediate reopen, then 5 after growing waits
            await asyncio.sleep(0.005)
        assert not task.done()
        dev.present = True  # plugged back in
        after = await asyncio.wait_for(task, 2.0)
        return before, after

    before, after = run(scenario())
    assert after.t_s > before[-1].t_s
    assert src.stats.read_errors == 1 and src.stats.reconnects == 1
    # waits between reopen attempts after the loss: 0.02, 0.04, 0.08, then capped at 0.08
    # (uncapped they would be 0.16, 0.32)
    gaps = np.diff(dev.open_times[1:7])
    expected = [0.02, 0.04, 0.08, 0.08, 0.08]
    assert len(gaps) == len(expected)
    for g, e in zip(gaps, expected):
        assert e * 0.9 <= g < e + 0.07, (gaps, expected)
    text = caplog.text
    assert text.count("camera lost") == 1 and "camera back" in text
    print(f"\nreconnect waits (s): {np.round(gaps, 3).tolist()}")


def test_absent_at_start_raises_once_and_returns_frames_when_the_device_appears():
    dev = FakeDevice(present=False)
    src = V4L2Source(cam(), Clock(), capture_factory=dev.factory, backoff_initial_s=0.01)

    async def scenario():
        with pytest.raises(CameraError, match="camera not available"):
            await src.read()
        task = asyncio.create_task(src.read())
        await asyncio.sleep(0.05)
        assert not task.done()
        dev.present = True
        return await asyncio.wait_for(task, 2.0)

    frame = run(scenario())
    assert frame.image.shape == (H, W)
    assert src.stats.reconnects == 1 and all(c.released for c in dev.captures[:-1])


def test_a_single_failed_read_reopens_at_once():
    dev = FakeDevice(script=[textured(1), False, textured(3)])
    src = V4L2Source(cam(), Clock(), capture_factory=dev.factory, backoff_initial_s=5.0)

    async def scenario():
        await src.read()
        with pytest.raises(CameraError, match="read failed"):
            await src.read()
        t0 = time.monotonic()
        frame = await asyncio.wait_for(src.read(), 1.0)
        return frame, time.monotonic() - t0

    frame, waited = run(scenario())
    assert np.array_equal(frame.image, textured(3)) and waited < 0.5  # no 5 s backoff before the first retry
    assert len(dev.captures) == 2 and dev.captures[0].released
