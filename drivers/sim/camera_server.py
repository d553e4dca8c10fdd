"""The simulated vehicle's camera, served as a frame stream (``companion sim --camera-listen``).

At each camera tick of simulated time the vehicle process takes the TRUE body pose of that physics
step, renders the world from it in a worker thread (the physics goes on meanwhile), stamps the
frame with the tick's ``time_boot`` (the exposure, on the autopilot's clock) and sends it to every
connected client in the format of :mod:`drivers.cameras.stream`. The service reads it with
``camera.source: stream``: a camera in its own hardware, as on a vehicle, so the service's
figures do not include a renderer sharing its process.

A tick that comes while the previous frame is still rendering is skipped (``skipped_ticks``), as
a camera that cannot keep up drops frames; a client whose socket is still full of older frames
misses this one (``dropped_sends``) rather than slowing the simulation.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging

import numpy as np

from companion.method.geometry import CameraMount
from drivers.cameras.stream import encode_frame
from drivers.sim.renderer import Renderer

log = logging.getLogger("companion.sim.camera")

MAX_QUEUED_BYTES = 2 * 640 * 480  # a client this far behind misses frames


class CameraServer:
    """TCP server of the frame stream; ``start`` binds, ``tick`` is called after each physics step."""

    def __init__(self, renderer: Renderer, mount: CameraMount, rate_hz: float, host: str, port: int):
        if not rate_hz > 0:
            raise ValueError(f"camera rate must be positive, got {rate_hz}")
        self._renderer = renderer
        self._mount = mount
        self._period = 1.0 / rate_hz
        self._host, self._port = host, port
        self._server: asyncio.base_events.Server | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="sim-camera")
        self._busy = False
        self._next_tick_s: float | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.sequence = 0
        self.frames_sent = 0
        self.skipped_ticks = 0
        self.dropped_sends = 0
        self.render_errors = 0

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._server = await asyncio.start_server(self._on_client, self._host, self._port)

    def describe(self) -> str:
        host, port = self._server.sockets[0].getsockname()[:2]
        return f"LISTENING camera {host}:{port}"

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._clients.add(writer)
        log.info("camera client %s connected", writer.get_extra_info("peername"))
        try:
            await reader.read()  # a client sends nothing: returns when it goes away
        except OSError:
            pass
        finally:
            self._clients.discard(writer)
            writer.close()

    def tick(self, t_s: float, true_pose) -> None:
        """After a physics step at simulated time ``t_s``: expose if a tick is due. ``true_pose()``
        -> (body position NED (3,), R body->NED (3, 3)) is asked only then."""
        if self._next_tick_s is None:
            self._next_tick_s = t_s
        if t_s + 1e-9 < self._next_tick_s:
            return
        while self._next_tick_s <= t_s + 1e-9:
            self._next_tick_s += self._period
        if not self._clients:
            return
        if self._busy:
            self.skipped_ticks += 1
            return
        self._busy = True
        p_body_ned, R_body_to_ned = true_pose()
        p_c, R_nc = self._mount.camera_pose(np.array(p_body_ned, float), np.array(R_body_to_ned, float))
        self._pool.submit(self._render, int(round(t_s * 1e6)), p_c, R_nc)

    def _render(self, t_us: int, p_c: np.ndarray, R_nc: np.ndarray) -> None:
        try:
            image = self._renderer.render(p_c, R_nc)
            self.sequence += 1
            record = encode_frame(t_us, self.sequence, image)
        except Exception:  # noqa: BLE001 - one bad render must not stop the camera
            self.render_errors += 1
            log.exception("camera: render failed")
            self._busy = False
            return
        self._loop.call_soon_threadsafe(self._send, record)

    def _send(self, record: bytes) -> None:
        self._busy = False
        for writer in list(self._clients):
            if writer.is_closing():
                self._clients.discard(writer)
                continue
            if writer.transport.get_write_buffer_size() > MAX_QUEUED_BYTES:
                self.dropped_sends += 1
                continue
            writer.write(record)
        self.frames_sent += 1

    def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for writer in list(self._clients):
            writer.close()
        self._clients.clear()
        self._pool.shutdown(wait=False, cancel_futures=True)


def camera_server_from_config(cfg, host: str, port: int, rate_hz: float | None = None, world=None) -> CameraServer:
    """The server for a :class:`companion.config.CompanionConfig`: intrinsics, mount and rate from
    ``cfg.camera`` (``rate_hz`` overrides), scenario, image noise and blur from ``cfg.sim``."""
    from companion.method.geometry import camera_from_config
    from drivers.sim.renderer import RenderOptions
    from drivers.sim.world import World

    world = world if world is not None else World.load(cfg.sim.scenario)
    camera, mount = camera_from_config(cfg.camera)
    options = RenderOptions(noise_sigma=cfg.sim.image_noise_sigma, blur_sigma_px=cfg.sim.image_blur_sigma_px,
                            seed=cfg.sim.seed)
    return CameraServer(Renderer(world, camera, options), mount, rate_hz or cfg.camera.rate_hz, host, port)
