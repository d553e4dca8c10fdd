"""A camera that films the simulated world from the vehicle's true pose.

It behaves like a real camera source: frames come at a fixed rate on the companion clock, each
stamped at capture. The pose comes from a provider (in the daemon: the simulated autopilot's
SIM_STATE truth, mapped to companion time), so the mapper sees exactly what a camera on the
simulated vehicle would see while navigation comes separately, with its own errors, from the
autopilot's estimator.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import numpy as np

from companion.method.geometry import CameraMount, quat_to_matrix
from companion.method.messages import Frame
from drivers.cameras.base import CameraError, CameraSource
from drivers.clock import Clock
from drivers.sim.renderer import Renderer

# () -> (t_s companion time, position NED (3,), quaternion body->NED wxyz (4,)) or None.
PoseProvider = Callable[[], "tuple[float, np.ndarray, np.ndarray] | None"]


class SyntheticCamera(CameraSource):
    """Renders frames at ``rate_hz`` (clock seconds) from the latest true body pose.

    ``read()`` waits for the next frame tick, asks ``pose_at()`` for the pose, renders in a worker
    thread and returns ``Frame(t_s=pose time, image, sequence, "synthetic")``. Ticks missed
    because rendering or the consumer was slow are skipped (counted in ``dropped_ticks``), as a
    free-running camera drops frames. A tick whose pose is not newer than the last frame's is
    skipped too (``stale_ticks``), so frame times strictly increase.

    Raises :class:`CameraError` while no pose is available, when the pose is malformed, or when the
    pose is older than ``max_pose_age_s`` (the vehicle stopped reporting).
    """

    name = "synthetic"

    def __init__(self, renderer: Renderer, mount: CameraMount, rate_hz: float, clock: Clock,
                 pose_at: PoseProvider, max_pose_age_s: float = 1.0):
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        if not max_pose_age_s > 0:
            raise ValueError(f"max_pose_age_s must be positive, got {max_pose_age_s}")
        self._renderer = renderer
        self._mount = mount
        self._period = 1.0 / rate_hz
        self._clock = clock
        self._pose_at = pose_at
        self._max_age = max_pose_age_s
        self._next_tick: float | None = None
        self._last_t = -np.inf
        self._sequence = 0
        self._lock = asyncio.Lock()
        self._closed = False
        self.dropped_ticks = 0
        self.stale_ticks = 0

    @property
    def rate_hz(self) -> float:
        return 1.0 / self._period

    async def _wait_tick(self) -> None:
        now = self._clock.now()
        if self._next_tick is None:
            self._next_tick = now
        elif self._next_tick < now - self._period:
            missed = int((now - self._next_tick) / self._period)
            self.dropped_ticks += missed
            self._next_tick += missed * self._period
        await self._clock.sleep_until(self._next_tick)
        self._next_tick += self._period

    def _pose(self) -> tuple[float, np.ndarray, np.ndarray]:
        pose = self._pose_at()
        if pose is None:
            raise CameraError("synthetic camera: no vehicle pose yet")
        try:
            t, p, q = pose
            t = float(t)
            p = np.asarray(p, float).reshape(3)
            q = np.asarray(q, float).reshape(4)
        except (TypeError, ValueError) as exc:
            raise CameraError(f"synthetic camera: malformed pose {pose!r}: {exc}") from exc
        if not (np.isfinite(t) and np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6):
            raise CameraError("synthetic camera: pose is not finite (or zero quaternion)")
        age = self._clock.now() - t
        if age > self._max_age:
            raise CameraError(f"synthetic camera: pose is {age:.2f} s old (limit {self._max_age:.2f} s)")
        return t, p, q

    async def read(self) -> Frame:
        if self._closed:
            raise CameraError("synthetic camera is closed")
        async with self._lock:
            while True:
                await self._wait_tick()
                t, p, q = self._pose()
                if t > self._last_t:
                    break
                self.stale_ticks += 1  # the pose has not moved on since the last frame
            p_c, R_nc = self._mount.camera_pose(p, quat_to_matrix(q))
            image = await asyncio.to_thread(self._renderer.render, p_c, R_nc)
            self._last_t = t
            self._sequence += 1
            return Frame(t_s=t, image=image, sequence=self._sequence, source="synthetic")

    async def close(self) -> None:
        self._closed = True


def synthetic_camera_from_config(cfg, clock: Clock, pose_at: PoseProvider, world=None) -> SyntheticCamera:
    """Build the world (``cfg.sim.scenario`` unless given), renderer and camera from a
    :class:`companion.config.CompanionConfig`: intrinsics, mount and rate from ``cfg.camera``, sensor
    noise, blur and pose age limit from ``cfg.sim``."""
    from companion.method.geometry import camera_from_config
    from drivers.sim.renderer import RenderOptions
    from drivers.sim.world import World

    world = world if world is not None else World.load(cfg.sim.scenario)
    camera, mount = camera_from_config(cfg.camera)
    options = RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, blur_sigma_px=cfg.sim.image_blur_sigma_px,
                            seed=cfg.sim.seed)
    return SyntheticCamera(Renderer(world, camera, options), mount, cfg.camera.rate_hz, clock, pose_at,
                           max_pose_age_s=cfg.sim.max_pose_age_s)
