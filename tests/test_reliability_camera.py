"""Reliability of the camera path: bad frames are counted rejections that the service's status
shows while mapping goes on with the good ones; a camera that vanishes comes back (V4L2 device node that
disappears, synthetic camera without a pose, recording whose files vanish).

The service runs in this process (``companion.service.daemon.Daemon``) so its parts can be inspected; navigation is
pushed into its buffer directly (a hovering vehicle), the autopilot link waits on a port nobody uses.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.config import CompanionConfig, replace
from companion.method.geometry import CameraMount, PinholeCamera
from companion.method.messages import NavState
from drivers.cameras.base import CameraError, EndOfStream
from drivers.cameras.recorded import ImageFolderSource
from drivers.cameras.v4l2 import V4L2Source, opencv_v4l2_backend
from drivers.clock import Clock

W, H = 320, 240
RATE_HZ = 20.0


def textured(seed: int, shape=(H, W)) -> np.ndarray:
    """A grey image with structure at several scales (corners for the mapper, never blank)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    image = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return cv2.add(image, rng.integers(0, 20, shape, dtype=np.uint8))


def camera_section(**changes) -> dict:
    base = {"camera.width": W, "camera.height": H, "camera.fx": 312.65, "camera.fy": 312.65, "camera.cx": 159.5,
            "camera.cy": 119.5, "camera.rate_hz": RATE_HZ}
    base.update(changes)
    return base


def service_config(tmp_path: Path, **changes) -> CompanionConfig:
    base = {
        "link.connection": "udpin:127.0.0.1:0",  # nobody talks: navigation is pushed by the test
        "zenoh.enabled": False,
        "persistence.directory": str(tmp_path / "map"), "persistence.snapshot_interval_s": 600.0,
        **camera_section(),
    }
    base.update(changes)
    return replace(CompanionConfig(), **base)


def hover(t: float) -> NavState:
    """A vehicle hovering 20 m up, camera pitched 45 deg down as configured."""
    P = np.diag([0.3**2] * 3 + [0.1**2] * 3 + [math.radians(0.5) ** 2] * 3)
    return NavState(t, np.array([0.0, 0.0, -20.0]), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), P, "floors")


@contextlib.asynccontextmanager
async def service(cfg: CompanionConfig, build_camera=None):
    """The daemon in this process, with navigation pushed at 50 Hz; ended as SIGTERM would end it."""
    from companion.service.daemon import Daemon

    d = Daemon(cfg)
    if build_camera is not None:
        d._build_camera = lambda: build_camera(d)

    async def navigation():
        while True:
            d.link.nav_buffer.push(hover(d.clock.now()))
            await asyncio.sleep(0.02)

    nav = asyncio.create_task(navigation())
    task = asyncio.create_task(d.run())
    try:
        yield d
    finally:
        d.request_stop()
        await asyncio.wait_for(task, 15)
        nav.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await nav


async def wait_for(pred, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out ({timeout_s} s) waiting for {what}")
        await asyncio.sleep(0.02)


# --------------------------------------------------------------------------------------------
# Bad frames: counted, shown in the status, mapping goes on
# --------------------------------------------------------------------------------------------


def write_folder(folder: Path, entries: list[tuple[float, np.ndarray]]) -> None:
    folder.mkdir()
    lines = []
    for i, (t, image) in enumerate(entries):
        name = f"{i:04d}.png"
        cv2.imwrite(str(folder / name), image)
        lines.append(f"{t:.6f} {name}")
    (folder / "timestamps.txt").write_text("\n".join(lines) + "\n")


def test_bad_frames_are_counted_in_the_status_and_mapping_goes_on_with_the_good_ones(tmp_path):
    """A recording with every kind of bad frame among good ones, replayed through the running service."""
    period = 1.0 / RATE_HZ
    good, entries, t = 0, [], 0.0

    def add(image, dt=period):
        nonlocal t
        t += dt
        entries.append((t, image))

    for i in range(6):
        add(textured(i))
    bad = [
        np.zeros((H, W), np.uint8),  # lens cap: all black
        np.full((H, W), 255, np.uint8),  # all white
        textured(50, (H // 2, W)),  # wrong size
        (textured(51).astype(np.uint16) * 257),  # 16-bit: a pixel format the camera path does not take
    ]
    for i, image in enumerate(bad):
        add(image)
        add(textured(100 + i))
    bad_times = [len(entries), len(entries) + 1]
    entries.append((t, textured(200)))  # repeats the previous time
    entries.append((t - 0.2, textured(201)))  # goes back in time
    add(textured(202))
    add(textured(203), dt=1.0)  # a long gap (20 frame periods): counted, the frame kept
    for i in range(6):
        add(textured(300 + i))
    good = sum(1 for _, im in entries if im.dtype == np.uint8 and im.shape == (H, W) and im.std() > 1.0) - 2  # minus the two bad times
    folder = tmp_path / "recording"
    write_folder(folder, entries)
    cfg = service_config(tmp_path, **{"camera.source": "file", "camera.path": str(folder), "camera.realtime": True})
    mapped: list[int] = []  # sequence numbers (recording index) of the frames the mapper took

    async def main():
        async with service(cfg) as d:
            map_frame = d._map_frame
            d._map_frame = lambda frame: (mapped.append(frame.sequence), map_frame(frame))
            await wait_for(lambda: d.camera_state == "ended", 15, "the end of the recording")
            await wait_for(lambda: d.frames_mapped + d.frames.dropped + sum(d.frames_no_nav.values()) >= d.frames_in, 5,
                           "the mapper to take the last frame")
            return d.status()

    st = asyncio.run(asyncio.wait_for(main(), 30))
    cam = st["camera"]
    print(f"\n{len(entries)} recorded frames, {good} good: camera {cam}; mapper {st['mapper']['frames_mapped']} mapped, "
          f"without nav {st['mapper']['frames_without_nav']}; problems {st['problems']}")
    s = cam["stats"]
    assert (s["rejected_blank"], s["rejected_size"], s["rejected_format"], s["rejected_time"], s["gaps"]) == (2, 1, 1, 2, 1)
    assert s["delivered"] == cam["frames"] == good
    assert st["mapper"]["frames_mapped"] + cam["queue_dropped"] == good and st["mapper"]["errors"] == 0
    # Mapping went on after every bad frame (the queue drops the oldest frame when the mapper is slow, as on
    # a loaded machine, never the newest), and no bad frame reached the mapper.
    bad_index = [i for i, (_, im) in enumerate(entries) if not (im.dtype == np.uint8 and im.shape == (H, W) and im.std() > 1.0)]
    bad_index += bad_times  # the repeated and the backward timestamps
    assert all(any(m > i for m in mapped) for i in bad_index) and not set(mapped) & set(bad_index)
    assert len(mapped) >= good // 2 and mapped[-1] == len(entries) - 1
    assert cam["state"] == "ended" and any("camera ended" in p for p in st["problems"])


# --------------------------------------------------------------------------------------------
# The camera vanishes and returns
# --------------------------------------------------------------------------------------------


class FakeV4L2:
    """A capture device behind a device node: present while the node exists, its reads fail once it is gone."""

    def __init__(self, node: Path):
        self.node = node
        self.reads = 0
        self.opens = 0

    def factory(self, device):
        if not os.path.exists(device):
            return opencv_v4l2_backend(device)  # the real path check: "no such device", without asking OpenCV
        self.opens += 1
        return FakeCapture(self)


class FakeCapture:
    def __init__(self, dev: FakeV4L2):
        self.dev = dev
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H, cv2.CAP_PROP_FPS: RATE_HZ}

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop not in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            self.props[prop] = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_POS_MSEC:
            return time.monotonic() * 1000.0 - 5.0  # captured 5 ms before the read returns (CLOCK_MONOTONIC)
        return self.props.get(prop, 0.0)

    def read(self):
        time.sleep(1.0 / RATE_HZ)  # the sensor's frame period
        if not self.dev.node.exists():
            return False, None  # unplugged: the dequeue fails
        self.dev.reads += 1
        return True, textured(self.dev.reads)

    def release(self):
        pass


def test_v4l2_device_node_vanishes_and_returns_the_service_reports_it_and_maps_again(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    node = tmp_path / "video-usb-cam"
    node.write_bytes(b"")
    dev = FakeV4L2(node)
    cfg = service_config(tmp_path, **{"camera.source": "v4l2", "camera.device": str(node), "camera.reconnect_backoff_max_s": 0.2})

    async def main():
        async with service(cfg, build_camera=lambda d: V4L2Source(cfg.camera, d.clock, capture_factory=dev.factory,
                                                                   backoff_initial_s=0.05)) as d:
            await wait_for(lambda: d.frames_mapped >= 5, 15, "mapping")
            node.unlink()  # unplugged
            await wait_for(lambda: d.camera_state == "lost", 5, "camera lost")
            mapped, frames = d.frames_mapped, d.frames_in
            await asyncio.sleep(0.6)
            during = (d.frames_in - frames, d.status())
            node.write_bytes(b"")  # plugged back in
            await wait_for(lambda: d.camera_state == "ok" and d.frames_mapped >= mapped + 5, 10, "mapping again")
            return during, d.status(), d.link._statustext_queue

    (new_frames, lost), back, queued = asyncio.run(asyncio.wait_for(main(), 40))
    stats = back["camera"]["stats"]
    print(f"\nV4L2 unplugged: state {lost['camera']['state']} ({lost['camera']['error']}); back: {back['camera']}")
    assert new_frames == 0 and lost["health"] == "degraded"
    assert any(p.startswith(f"camera lost: camera lost: v4l2:{node}") for p in lost["problems"])
    assert "read failed" in lost["camera"]["error"]
    assert stats["read_errors"] == 1 and stats["reconnects"] == 1 and dev.opens == 2
    assert back["camera"]["state"] == "ok" and "camera lost" not in " ".join(back["problems"])
    assert [text for _, text in queued] == ["companion: camera lost", "companion: camera back"]  # for the GCS, once linked
    assert "camera back" in caplog.text


def test_synthetic_camera_without_a_pose_raises_and_resumes_with_increasing_times():
    """The synthetic camera films the simulator's true pose; when the pose stops (link down) it says so, and frames
    resume, in time order, when the pose is back."""
    from drivers.cameras.synthetic import SyntheticCamera
    from drivers.sim.renderer import Renderer
    from drivers.sim.world import World

    clock = Clock()
    camera = PinholeCamera(312.65, 312.65, 159.5, 119.5, W, H)
    mount = CameraMount.from_euler_deg(0.0, -45.0, 0.0)
    pose = {"on": True}

    def pose_at():
        if not pose["on"]:
            return None
        return clock.now(), np.array([0.0, 0.0, -20.0]), np.array([1.0, 0.0, 0.0, 0.0])

    cam = SyntheticCamera(Renderer(World.load("default"), camera), mount, 20.0, clock, pose_at)

    async def main():
        before = [await cam.read() for _ in range(3)]
        pose["on"] = False
        errors = 0
        for _ in range(3):
            with pytest.raises(CameraError, match="no vehicle pose"):
                await cam.read()
            errors += 1
        pose["on"] = True
        after = [await cam.read() for _ in range(3)]
        return before, errors, after

    before, errors, after = asyncio.run(asyncio.wait_for(main(), 10))
    times = [f.t_s for f in before + after]
    assert errors == 3 and all(b > a for a, b in zip(times, times[1:]))
    assert [f.sequence for f in before + after] == [1, 2, 3, 4, 5, 6]
    assert all(f.image.shape == (H, W) and f.image.std() > 1.0 for f in after)


def test_recording_whose_files_vanish_and_return_skips_what_is_missing_and_goes_on(tmp_path):
    folder = tmp_path / "rec"
    write_folder(folder, [(0.05 * i, textured(i)) for i in range(12)])
    src = ImageFolderSource(folder, Clock(), width=W, height=H, realtime=False)
    moved = tmp_path / "moved"
    moved.mkdir()

    async def main():
        got = [await src.read() for _ in range(3)]
        for i in range(3, 7):  # the medium loses these files while the replay runs...
            (folder / f"{i:04d}.png").rename(moved / f"{i:04d}.png")
        got.append(await src.read())
        for p in moved.iterdir():  # ...and they are back before the replay reaches the next ones
            p.rename(folder / p.name)
        while True:
            try:
                got.append(await src.read())
            except EndOfStream:
                return got

    frames = asyncio.run(asyncio.wait_for(main(), 10))
    assert [f.sequence for f in frames] == [0, 1, 2, 7, 8, 9, 10, 11]
    assert src.stats.skipped_missing == 4 and src.stats.delivered == 8
    for f in frames:
        assert np.array_equal(f.image, textured(f.sequence))
