"""The synthetic camera behaves like a real camera source: a steady frame rate on the companion
clock, capture timestamps that increase, images rendered from the vehicle's true pose."""

import asyncio
import time

import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.method.geometry import CameraMount, PinholeCamera, euler_to_quat, quat_to_matrix
from drivers.cameras.base import CameraError
from drivers.cameras.synthetic import SyntheticCamera, synthetic_camera_from_config
from drivers.clock import Clock
from drivers.sim.renderer import Renderer
from drivers.sim.world import World

SMALL = PinholeCamera(156.3, 156.3, 79.5, 59.5, 160, 120)
MOUNT = CameraMount.from_euler_deg(0.0, -45.0, 0.0)
LEVEL_NORTH = euler_to_quat(0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def world():
    return World.from_dict({"name": "cam_test", "seed": 2, "ground": {"tile_px": 512},
                            "boxes": [{"name": "b", "center_ne_m": [30.0, 0.0], "size_m": [10.0, 10.0], "height_m": 8.0}]})


@pytest.fixture(scope="module")
def renderer(world):
    return Renderer(world, SMALL)


class Flight:
    """Pose provider: flies north at 6 m/s, 15 m up, and remembers what it handed out."""

    def __init__(self, clock: Clock, delay_s: float = 0.0, speed_mps: float = 6.0):
        self.clock = clock
        self.speed = speed_mps
        self.delay_s = delay_s
        self.given: list[tuple[float, np.ndarray, np.ndarray]] = []

    def __call__(self):
        t = self.clock.now() - self.delay_s
        pose = (t, np.array([self.speed * t, 0.0, -15.0]), LEVEL_NORTH)
        self.given.append(pose)
        return pose


def read_n(cam: SyntheticCamera, n: int, between_s: float = 0.0):
    async def go():
        frames = []
        async with cam:
            for _ in range(n):
                frames.append(await cam.read())
                if between_s:
                    await asyncio.sleep(between_s)
        return frames

    return asyncio.run(go())


def test_frames_come_at_the_rate_with_increasing_capture_times(renderer):
    clock = Clock(speedup=10.0)
    flight = Flight(clock, delay_s=0.02)
    cam = SyntheticCamera(renderer, MOUNT, 20.0, clock, flight)
    wall0 = time.monotonic()
    frames = read_n(cam, 20)
    wall = time.monotonic() - wall0
    t = np.array([f.t_s for f in frames])
    assert np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(0.05, rel=0.2)  # 20 Hz in clock seconds
    assert t[-1] - t[0] == pytest.approx(19 * 0.05, rel=0.15)
    assert wall < 19 * 0.05 / 10.0 * 3 + 0.5  # the speed-up applies
    assert [f.sequence for f in frames] == list(range(1, 21))
    assert all(f.source == "synthetic" and f.image.shape == (120, 160) and f.image.dtype == np.uint8 for f in frames)
    # Each frame is stamped with its pose's time and shows the world from that pose.
    last = frames[-1]
    pose = next(p for p in flight.given if p[0] == last.t_s)
    p_c, R_nc = MOUNT.camera_pose(pose[1], quat_to_matrix(pose[2]))
    assert np.array_equal(last.image, renderer.render(p_c, R_nc))
    assert not np.array_equal(frames[0].image, last.image)  # the vehicle moved


def test_no_pose_is_a_camera_error_until_one_arrives(renderer):
    clock = Clock(speedup=20.0)
    state = {"pose": None}
    cam = SyntheticCamera(renderer, MOUNT, 20.0, clock, lambda: state["pose"])

    async def go():
        with pytest.raises(CameraError, match="no vehicle pose"):
            await cam.read()
        state["pose"] = (clock.now(), np.array([0.0, 0.0, -15.0]), LEVEL_NORTH)
        return await cam.read()

    frame = asyncio.run(go())
    assert frame.sequence == 1


@pytest.mark.parametrize("pose", [
    (0.0, np.array([1.0, 2.0]), LEVEL_NORTH),
    (0.0, np.array([np.nan, 0.0, 0.0]), LEVEL_NORTH),
    (0.0, np.zeros(3), np.zeros(4)),
    "garbage",
])
def test_malformed_poses_are_camera_errors(renderer, pose):
    clock = Clock(speedup=20.0)
    fixed = pose if isinstance(pose, str) else (clock.now(), *pose[1:])
    cam = SyntheticCamera(renderer, MOUNT, 20.0, clock, lambda: fixed)
    with pytest.raises(CameraError):
        asyncio.run(cam.read())


def test_old_or_frozen_poses_are_refused(renderer):
    clock = Clock(speedup=20.0)
    old = SyntheticCamera(renderer, MOUNT, 20.0, clock, lambda: (clock.now() - 5.0, np.zeros(3), LEVEL_NORTH),
                          max_pose_age_s=1.0)
    with pytest.raises(CameraError, match="old"):
        asyncio.run(old.read())
    # A pose that stops moving on: the first frame is fine, then ticks are skipped (no duplicate
    # timestamps) until the pose is too old.
    t_frozen = clock.now()
    frozen = SyntheticCamera(renderer, MOUNT, 20.0, clock, lambda: (t_frozen, np.array([0.0, 0.0, -15.0]), LEVEL_NORTH),
                             max_pose_age_s=0.5)

    async def go():
        first = await frozen.read()
        with pytest.raises(CameraError, match="old"):
            await frozen.read()
        return first

    assert asyncio.run(go()).t_s == t_frozen
    assert frozen.stale_ticks >= 5


def test_a_slow_consumer_drops_ticks_like_a_free_running_camera(renderer):
    clock = Clock(speedup=10.0)
    cam = SyntheticCamera(renderer, MOUNT, 20.0, clock, Flight(clock))
    frames = read_n(cam, 5, between_s=0.02)  # 0.2 clock seconds between reads = 4 periods
    gaps = np.diff([f.t_s for f in frames])
    assert np.all(gaps > 0.1)
    assert cam.dropped_ticks >= 6


def test_closed_camera_and_bad_arguments(renderer):
    clock = Clock(speedup=10.0)
    cam = SyntheticCamera(renderer, MOUNT, 20.0, clock, Flight(clock))
    asyncio.run(cam.close())
    with pytest.raises(CameraError, match="closed"):
        asyncio.run(cam.read())
    with pytest.raises(ValueError):
        SyntheticCamera(renderer, MOUNT, 0.0, clock, Flight(clock))


def test_built_from_the_configuration(world):
    clock = Clock(speedup=10.0)
    cfg = CompanionConfig()
    cam = synthetic_camera_from_config(cfg, clock, Flight(clock, speed_mps=0.0), world=world)
    assert cam.rate_hz == cfg.camera.rate_hz
    frames = read_n(cam, 2)
    assert frames[0].image.shape == (cfg.camera.height, cfg.camera.width)
    # Hovering: the view is the same, only the configured sensor noise differs between frames.
    diff = frames[0].image.astype(float) - frames[1].image.astype(float)
    assert diff.std() == pytest.approx(np.sqrt(2) * cfg.sim.image_noise_sigma, rel=0.25)
