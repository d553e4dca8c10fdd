"""The daemon's mapper in a child process, so that the control loop never waits for a GIL the mapper holds
(``Daemon(cfg, mapper_process=True)``; the daemon's default is the mapper thread).

In one process the mapper thread and the event loop share Python's GIL: when the control loop's
timer fires while the mapper is between two NumPy calls, the loop waits until the mapper lets go,
up to the GIL's switch interval (5 ms). In a bare experiment (the mapper at 30 frames/s and a
20 Hz loop sharing one core, docs/performance.md) the mapper in its own process cut the ticks
later than 3 ms by 40-70 % and the median lateness from 1.5-4.2 ms to about 1 ms. In the daemon
flying the simulated circuit it measured no better than the thread (the other work of the
daemon's process and of the shared machine dominate the tail) and costs about 1.5 ms a frame
(the hand-over between the processes), so it stays an option. Lowering the mapper thread's
priority (nice, ``SCHED_IDLE``) made things worse: preempted while holding the GIL, it held up
the loop longer (priority inversion).

:class:`MapperProcess` offers the mapper's ``step(nav, image) -> MapperStep``. The child is a
plain ``python -m companion.service.mapper_process`` (not multiprocessing's spawn, which would import the
caller's main module again) connected by a Unix socket pair. Each step copies the image into a
shared memory buffer (an anonymous file whose descriptor is passed over the socket) and sends the
navigation state; one frame is in flight at a time. The child keeps its own copy of the terrain
map for the depth prior of new features (eq. 16): it starts from the daemon's map and inserts
each step's converged points as the daemon inserts them into its own, so both hold the same map.
If the child dies, the next step starts a new one from the daemon's current map (the stored
features are lost, as after a mapper reset).
"""

from __future__ import annotations

import mmap
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.reduction import recv_handle, send_handle
from typing import Any

import numpy as np

from companion.config import CompanionConfig
from companion.method.messages import NavState

START_TIMEOUT_S = 60.0  # a new interpreter imports NumPy, OpenCV and the mapper (seconds on a small board)


class MapperProcessError(RuntimeError):
    """The child process could not start, died, or its step raised (the message says which)."""


def _anonymous_file(size: int) -> int:
    """A descriptor of an unnamed shared-memory file of ``size`` bytes (memfd on Linux)."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("companion-frame", os.MFD_CLOEXEC)
    else:  # pragma: no cover - not Linux
        f = tempfile.TemporaryFile()
        fd = os.dup(f.fileno())
        f.close()
    os.ftruncate(fd, size)
    return fd


class _FrameBuffer:
    """An image-sized shared buffer: the descriptor (to send), the mapping and its capacity."""

    def __init__(self, size: int):
        self.fd = _anonymous_file(max(size, 1))
        self.size = max(size, 1)
        self.map = mmap.mmap(self.fd, self.size)

    def view(self, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        return np.ndarray(shape, dtype=dtype, buffer=self.map)

    def close(self) -> None:
        self.map.close()
        os.close(self.fd)


# ------------------------------------------------------------------------------------------------
# The child
# ------------------------------------------------------------------------------------------------


def serve(conn: Connection) -> None:
    """The child's loop: ``("init", cfg, grid)``, then ``("step", nav, shape, dtype, new_buffer)``
    requests (a new buffer's descriptor follows its request) answered ``("ok", MapperStep)`` or
    ``("error", text)``, until ``None`` or the end of the connection."""
    from companion.method.geometry import camera_from_config
    from companion.method.mapper import Mapper

    _, cfg, grid = conn.recv()
    camera, mount = camera_from_config(cfg.camera)
    max_range = cfg.mapper.prior_max_range_m

    def depth_prior(origin_ned: np.ndarray, rays_ned: np.ndarray) -> np.ndarray:
        return grid.ray_range(origin_ned, rays_ned, max_range)

    mapper = Mapper(cfg.mapper, camera, mount, depth_prior=depth_prior,
                    default_ground_alt_m=cfg.terrain.default_ground_alt_m, border_px=cfg.camera.border_px)
    buffer: mmap.mmap | None = None
    conn.send(("ready", None))
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return  # the daemon is gone
        if request is None:
            return
        _, nav, shape, dtype, new_buffer = request
        try:
            if new_buffer:
                fd = recv_handle(conn)
                if buffer is not None:
                    buffer.close()
                buffer = mmap.mmap(fd, 0)
                os.close(fd)
            image = np.ndarray(shape, dtype=np.dtype(dtype), buffer=buffer)
            step = mapper.step(nav, image)
            grid.add_evidence(step.points, step.free_space, step.floors)  # the daemon's map takes the same
            reply = ("ok", step)
        except Exception as exc:  # noqa: BLE001 - reported to the daemon, which counts and logs it
            reply = ("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        image = step = None  # no view of the buffer outlives the step (a new buffer closes the old one)
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return


def main(argv: list[str] | None = None) -> int:
    """``python -m companion.service.mapper_process FD``: serve the daemon on the socket descriptor FD."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the daemon, which stops the child
    fd = int((sys.argv[1:] if argv is None else argv)[0])
    serve(Connection(fd))
    return 0


# ------------------------------------------------------------------------------------------------
# The daemon's side
# ------------------------------------------------------------------------------------------------


class MapperProcess:
    """``Mapper.step`` run in a child process.

    cfg: the daemon's configuration (its mapper, camera and terrain sections). with_map(use): calls
    ``use(grid)`` with the daemon's terrain map while holding the daemon's map lock (the child is
    started from that map). One caller of :meth:`step` at a time (the daemon's mapper thread);
    :meth:`close` may come from another thread.
    """

    def __init__(self, cfg: CompanionConfig, with_map: Callable[[Callable[[Any], None]], None]):
        self.cfg = cfg
        self._with_map = with_map
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._buffer: _FrameBuffer | None = None  # shared with the current child (None: none sent yet)
        self._lock = threading.Lock()
        self.starts = 0

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> None:
        """Start the child from the daemon's current map and wait until it is ready (raises
        :class:`MapperProcessError` if it is not within ``START_TIMEOUT_S``)."""
        with self._lock:
            self._stop_child()
            ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                proc = subprocess.Popen([sys.executable, "-m", "companion.service.mapper_process", str(theirs.fileno())],
                                        pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
            except OSError as exc:
                ours.close()
                raise MapperProcessError(f"mapper process not started: {exc}") from exc
            finally:
                theirs.close()
            conn = Connection(ours.detach())
            self._proc, self._conn = proc, conn
            self.starts += 1
            try:
                self._with_map(lambda grid: conn.send(("init", self.cfg, grid)))  # the map as it is now
                ready = conn.poll(START_TIMEOUT_S)
                kind = conn.recv()[0] if ready else "no answer"
            except (EOFError, OSError) as exc:
                kind = repr(exc)
            if kind != "ready":
                self._stop_child()
                raise MapperProcessError(f"mapper process failed to start ({kind})")

    def step(self, nav: NavState, image: np.ndarray):
        """``Mapper.step(nav, image)`` in the child -> :class:`companion.method.mapper.MapperStep`. Starts
        the child first if it is not running. Raises :class:`MapperProcessError` when the step
        raised in the child or the child died (the next call starts a new one)."""
        image = np.asarray(image)
        if not self.alive:
            self.start()
        with self._lock:
            new_buffer = self._buffer is None or self._buffer.size < image.nbytes
            try:
                if new_buffer:
                    if self._buffer is not None:
                        self._buffer.close()
                    self._buffer = _FrameBuffer(image.nbytes)
                np.copyto(self._buffer.view(image.shape, image.dtype), image)
                self._conn.send(("step", nav, image.shape, image.dtype.str, new_buffer))
                if new_buffer:
                    send_handle(self._conn, self._buffer.fd, self._proc.pid)
                kind, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self._stop_child()
                raise MapperProcessError(f"mapper process died: {exc!r}") from exc
        if kind != "ok":
            raise MapperProcessError(f"mapper step failed in the mapper process: {value}")
        return value

    def close(self, timeout_s: float = 1.0) -> None:
        """Ask the child to finish, then terminate it if it has not within ``timeout_s``. A step
        that does not come back within ``timeout_s`` is ended by terminating the child."""
        if self._lock.acquire(timeout=timeout_s):
            try:
                self._stop_child(timeout_s)
            finally:
                self._lock.release()
            return
        proc = self._proc
        if proc is not None:
            proc.terminate()  # the step waiting on it gets EOF and returns
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()

    def _stop_child(self, timeout_s: float = 1.0) -> None:
        proc, conn, buffer = self._proc, self._conn, self._buffer
        self._proc = self._conn = self._buffer = None
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        if proc is not None:
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout_s)
        if conn is not None:
            conn.close()
        if buffer is not None:
            buffer.close()


if __name__ == "__main__":
    sys.exit(main())
