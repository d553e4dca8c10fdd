"""A V4L2 camera through OpenCV's CAP_V4L2 backend, with capture timestamps and reconnection.

Opening asks the driver for the configured pixel format, size, rate and exposure, then reads
back what it granted (drivers round to the modes they have). A granted size different from
``camera.width`` x ``camera.height`` is refused: the intrinsics belong to one size and frames are
never resized.

Timestamps. OpenCV's V4L2 backend reports the dequeued buffer's ``timestamp`` (a ``timeval``) as
``CAP_PROP_POS_MSEC``. For UVC and most capture drivers that is CLOCK_MONOTONIC at the end of
the frame's capture (V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC), the clock ``time.monotonic()`` reads.
So each frame's age is ``time.monotonic() - pos_msec / 1000`` when the read returns; if that age
is plausible (between -5 ms and 1 s) the frame is stamped ``clock.now() - age * clock.speedup``,
which also stays right when frames queued in the driver's buffers are read late. Otherwise
(a driver with realtime or no timestamps) the frame is stamped at the read's return minus half a
frame period, and ``stats.timestamps_fallback`` counts it.

Loss and recovery. A failed open or read raises :class:`CameraError` once and logs
"camera lost"; the following ``read()`` calls wait and reopen the device with exponential backoff
(``backoff_initial_s`` doubling up to ``camera.reconnect_backoff_max_s``) until it answers, then log
"camera back". They do not raise again during the same outage, so a caller simply keeps reading.
A stuck device that never returns from a read blocks for OpenCV's own 10 s select timeout.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from companion.config import CameraConfig, ConfigError
from companion.method.messages import Frame
from drivers.cameras.base import CameraError, CameraSource
from drivers.cameras.checks import CameraStats, FrameChecker
from drivers.clock import Clock

log = logging.getLogger(__name__)

# FOURCCs OpenCV's V4L2 backend can turn into an image; 2-character-short codes are space padded.
KNOWN_FOURCCS = ("GREY", "Y16 ", "Y10 ", "YUYV", "UYVY", "MJPG", "JPEG", "NV12", "NV21", "YU12", "YV12", "RGB3", "BGR3")
# Formats whose luma we take straight from the raw buffer (no colour conversion round trip).
RAW_LUMA_CHANNEL = {"GREY": None, "YUYV": 0, "UYVY": 1}

V4L2_EXPOSURE_AUTO = 0  # V4L2_CID_EXPOSURE_AUTO menu values (OpenCV passes them through)
V4L2_EXPOSURE_MANUAL = 1
V4L2_EXPOSURE_APERTURE_PRIORITY = 3  # the "auto" most UVC cameras actually implement
EXPOSURE_UNIT_US = 100.0  # V4L2_CID_EXPOSURE_ABSOLUTE counts 100 us steps
DRIVER_BUFFERS = 2  # few queued buffers: lower latency, and buffer timestamps cover the rest
MAX_BUFFER_AGE_S = 1.0


class CaptureBackend(Protocol):
    """What the source needs of ``cv2.VideoCapture`` (a scripted fake implements it in tests)."""

    def read(self) -> tuple[bool, np.ndarray | None]: ...
    def set(self, prop: int, value: float) -> bool: ...
    def get(self, prop: int) -> float: ...
    def isOpened(self) -> bool: ...
    def release(self) -> None: ...


def _device_path(device: str | int) -> str:
    return f"/dev/video{device}" if isinstance(device, int) else device


def explain_open_failure(device: str | int) -> str:
    """Why a device did not open, as far as the file system can tell."""
    path = _device_path(device)
    if not os.path.exists(path):
        return f"{path}: no such device (unplugged, or a different /dev/video number)"
    if not os.access(path, os.R_OK | os.W_OK):
        return f"{path}: permission denied (add the service user to the 'video' group)"
    return f"{path}: exists but OpenCV's V4L2 backend could not open it (busy, or not a capture device)"


def opencv_v4l2_backend(device: str | int) -> CaptureBackend:
    """The real backend: ``cv2.VideoCapture(device, cv2.CAP_V4L2)``.

    A device node that does not exist is reported without asking OpenCV, which would print a
    warning on every reconnect attempt of a long outage.
    """
    if not os.path.exists(_device_path(device)):
        raise CameraError(explain_open_failure(device))
    return cv2.VideoCapture(device, cv2.CAP_V4L2)


def fourcc_code(text: str) -> int:
    """The integer FOURCC of a 4-character code."""
    return cv2.VideoWriter.fourcc(*text)


def fourcc_text(code: float) -> str:
    """The 4 characters of an integer FOURCC as ``CAP_PROP_FOURCC`` returns it ("" if none)."""
    c = int(code)
    if c <= 0:
        return ""
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


def parse_device(device: str) -> str | int:
    """``camera.device`` as OpenCV wants it: an index for "0", "1", ...; otherwise the path."""
    text = device.strip()
    if not text:
        raise ConfigError("camera.device is empty: give a V4L2 device path (/dev/video0) or an index (0)")
    if text.isdigit():
        return int(text)
    return text


def parse_pixel_format(pixel_format: str) -> str:
    """``camera.pixel_format`` as a 4-character FOURCC (upper case, space padded)."""
    text = pixel_format.strip().upper()
    if not 1 <= len(text) <= 4 or not text.isascii():
        raise ConfigError(f"camera.pixel_format must be a FOURCC of up to 4 ASCII characters, got {pixel_format!r}")
    text = text.ljust(4)
    if text not in KNOWN_FOURCCS:
        raise ConfigError(
            f"camera.pixel_format {pixel_format!r} is not one OpenCV's V4L2 backend decodes "
            f"(known: {', '.join(f.strip() for f in KNOWN_FOURCCS)})"
        )
    return text


@dataclass(frozen=True, slots=True)
class GrantedMode:
    """What the driver granted on the last open (as read back through OpenCV)."""

    width: int
    height: int
    fourcc: str
    rate_hz: float
    auto_exposure: float
    exposure_us: float
    buffers: int


class V4L2Source(CameraSource):
    """Grey frames from a V4L2 device, stamped at capture on the companion clock.

    ``capture_factory(device)`` builds the backend (default: ``cv2.VideoCapture(device, CAP_V4L2)``).
    ``stats`` counts rejections, read errors and reconnects; ``granted`` is the mode of the last open.
    """

    def __init__(
        self,
        config: CameraConfig,
        clock: Clock,
        *,
        capture_factory: Callable[[str | int], CaptureBackend] = opencv_v4l2_backend,
        backoff_initial_s: float = 0.25,
        max_consecutive_rejects: int | None = None,
    ) -> None:
        self.device = parse_device(config.device)
        self.fourcc = parse_pixel_format(config.pixel_format)
        if not backoff_initial_s > 0:
            raise ValueError(f"backoff_initial_s must be positive, got {backoff_initial_s}")
        self.config = config
        self.clock = clock
        self.name = f"v4l2:{_device_path(self.device)}"
        self._factory = capture_factory
        self.stats = CameraStats()
        self._checker = FrameChecker(
            config.width, config.height, self.stats, name=self.name, nominal_period_s=1.0 / config.rate_hz,
            blank_std_max=config.blank_std_max, gap_factor=config.gap_factor,
        )
        self.backoff_initial_s = float(backoff_initial_s)
        self.backoff_max_s = max(float(config.reconnect_backoff_max_s), self.backoff_initial_s)
        self.max_consecutive_rejects = max_consecutive_rejects or max(10, int(2 * config.rate_hz))
        self.granted: GrantedMode | None = None
        self._cap: CaptureBackend | None = None
        self._luma_channel: int | None = None
        self._raw_luma = False
        self._sequence = 0
        self._lost_since: float | None = None  # wall time the outage began (None = not lost)
        self._outage_reported = False
        self._attempts = 0
        self._backoff_s = self.backoff_initial_s
        self._next_attempt = 0.0  # time.monotonic() of the next reopen attempt
        self._consecutive_rejects = 0
        self._fallback_logged = False
        # A read runs in a worker thread; close() must not release the device under it.
        self._io_lock = threading.Lock()

    @classmethod
    def from_config(cls, config: CameraConfig, clock: Clock, **kwargs: Any) -> "V4L2Source":
        return cls(config, clock, **kwargs)

    @property
    def connected(self) -> bool:
        return self._cap is not None

    # -- opening ------------------------------------------------------------------------------

    def _open_blocking(self) -> tuple[CaptureBackend, GrantedMode]:
        """Open and configure the device; raises CameraError (with the reason) if it is unusable."""
        cfg = self.config
        try:
            cap = self._factory(self.device)
        except CameraError as exc:
            raise CameraError(f"camera not available: {exc}") from exc
        except Exception as exc:  # a backend that raises instead of returning a closed capture
            raise CameraError(f"camera not available: {self.name}: open failed: {exc}") from exc
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"camera not available: {explain_open_failure(self.device)}")
        try:
            # Order matters for V4L2: the format first (it resets the stream), then the size, the
            # rate, then the controls.
            cap.set(cv2.CAP_PROP_FOURCC, fourcc_code(self.fourcc))
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)
            cap.set(cv2.CAP_PROP_FPS, cfg.rate_hz)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, DRIVER_BUFFERS)
            if cfg.exposure_us > 0:
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL)
                cap.set(cv2.CAP_PROP_EXPOSURE, cfg.exposure_us / EXPOSURE_UNIT_US)
            elif not cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_APERTURE_PRIORITY):
                cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_AUTO)
            granted = GrantedMode(
                width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                fourcc=fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
                rate_hz=float(cap.get(cv2.CAP_PROP_FPS)),
                auto_exposure=float(cap.get(cv2.CAP_PROP_AUTO_EXPOSURE)),
                exposure_us=float(cap.get(cv2.CAP_PROP_EXPOSURE)) * EXPOSURE_UNIT_US,
                buffers=int(cap.get(cv2.CAP_PROP_BUFFERSIZE)),
            )
            if (granted.width, granted.height) != (cfg.width, cfg.height):
                raise CameraError(
                    f"{self.name}: the driver granted {granted.width}x{granted.height}, but camera.width x "
                    f"camera.height ask {cfg.width}x{cfg.height}; set them to a mode the camera has "
                    f"(v4l2-ctl --list-formats-ext) and calibrate at that size"
                )
            # GREY and packed YUV: ask for the raw buffer and take the luma bytes, instead of a
            # grey -> BGR -> grey or YUV -> BGR -> grey round trip.
            self._raw_luma = granted.fourcc in RAW_LUMA_CHANNEL and bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0))
            self._luma_channel = RAW_LUMA_CHANNEL.get(granted.fourcc)
        except CameraError:
            cap.release()
            raise
        except Exception as exc:
            cap.release()
            raise CameraError(f"{self.name}: configuring the device failed: {exc}") from exc
        return cap, granted

    def _report_granted(self, granted: GrantedMode) -> None:
        cfg = self.config
        log.info(
            "%s: granted %dx%d %s at %.2f Hz, auto_exposure=%g exposure=%.0f us, %d buffers",
            self.name, granted.width, granted.height, granted.fourcc or "?", granted.rate_hz,
            granted.auto_exposure, granted.exposure_us, granted.buffers,
        )
        if granted.fourcc and granted.fourcc != self.fourcc:
            log.warning("%s: asked for pixel format %s, driver granted %s (frames are converted to grey)", self.name, self.fourcc, granted.fourcc)
        if granted.rate_hz > 0 and abs(granted.rate_hz - cfg.rate_hz) > 0.01 * cfg.rate_hz:
            log.warning("%s: asked for %.2f Hz, driver granted %.2f Hz", self.name, cfg.rate_hz, granted.rate_hz)
            self._checker.nominal_period_s = 1.0 / granted.rate_hz
        if cfg.exposure_us > 0 and abs(granted.exposure_us - cfg.exposure_us) > max(EXPOSURE_UNIT_US, 0.05 * cfg.exposure_us):
            log.warning("%s: asked for exposure %.0f us, driver reports %.0f us", self.name, cfg.exposure_us, granted.exposure_us)

    async def _connect(self) -> None:
        """Open the device, waiting out the backoff; raise CameraError only once per outage."""
        while self._cap is None:
            delay = self._next_attempt - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            self._attempts += 1
            try:
                cap, granted = await asyncio.to_thread(self._open_blocking)
            except CameraError as exc:
                self._next_attempt = time.monotonic() + self._backoff_s
                self._backoff_s = min(2.0 * self._backoff_s, self.backoff_max_s)
                if self._lost_since is None:
                    self._lost_since = time.monotonic()
                if not self._outage_reported:
                    self._outage_reported = True
                    log.warning("camera lost: %s; retrying with backoff up to %.1f s", exc, self.backoff_max_s)
                    raise
                log.debug("%s: reopen attempt %d failed: %s", self.name, self._attempts, exc)
                continue
            self._cap, self.granted = cap, granted
            self._report_granted(granted)
            if self._lost_since is not None:
                self.stats.reconnects += 1
                log.warning(
                    "camera back: %s after %.1f s and %d attempts", self.name, time.monotonic() - self._lost_since, self._attempts
                )
            self._lost_since = None
            self._outage_reported = False
            self._attempts = 0
            self._backoff_s = self.backoff_initial_s
            self._next_attempt = 0.0

    def _lose(self, reason: str) -> CameraError:
        """Drop the device after a failed read; the next read() reopens it."""
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            except Exception:  # a vanished device may fail to release; it is gone either way
                log.debug("%s: release after loss failed", self.name, exc_info=True)
        self.stats.read_errors += 1
        self._lost_since = time.monotonic()
        self._outage_reported = True
        self._next_attempt = 0.0  # first reopen at once: most losses are a replug
        self._backoff_s = self.backoff_initial_s
        log.warning("camera lost: %s: %s; reconnecting", self.name, reason)
        return CameraError(f"camera lost: {self.name}: {reason}")

    # -- reading ------------------------------------------------------------------------------

    def _read_blocking(self, cap: CaptureBackend) -> tuple[bool, np.ndarray | None, float]:
        """(ok, image, t_s): one read, stamped on the companion clock (see the module docstring)."""
        with self._io_lock:
            ok, image = cap.read()
            now_mono = time.monotonic()
            now_clock = self.clock.now()
            if not ok or image is None:
                return False, None, now_clock
            try:
                pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
            except Exception:  # a backend without buffer timestamps
                pos_ms = 0.0
        age = now_mono - pos_ms / 1000.0
        if pos_ms > 0 and -0.005 <= age <= MAX_BUFFER_AGE_S:
            return True, image, now_clock - max(age, 0.0) * self.clock.speedup
        self.stats.timestamps_fallback += 1
        if not self._fallback_logged:
            self._fallback_logged = True
            log.warning(
                "%s: no usable buffer timestamp (POS_MSEC=%.1f ms, monotonic now %.1f ms): stamping at read minus half a period",
                self.name, pos_ms, now_mono * 1000.0,
            )
        return True, image, now_clock - 0.5 * self._checker.nominal_period_s

    def _luma(self, image: np.ndarray) -> np.ndarray:
        """The grey image of a raw GREY/YUYV/UYVY buffer; other images go to the checker as they are."""
        if self._raw_luma and image.ndim == 3 and image.shape[2] == 2 and self._luma_channel is not None:
            return image[:, :, self._luma_channel]
        return image

    async def read(self) -> Frame:
        while True:
            if self._cap is None:
                await self._connect()
            cap = self._cap
            assert cap is not None
            try:
                ok, image, t_s = await asyncio.to_thread(self._read_blocking, cap)
            except Exception as exc:
                raise self._lose(f"read raised {exc}") from exc
            if not ok:
                raise self._lose("read failed (device unplugged or stream stopped)")
            self._sequence += 1
            gray = self._checker.admit(self._luma(image), t_s)
            if gray is None:
                self._consecutive_rejects += 1
                if self._consecutive_rejects >= self.max_consecutive_rejects:
                    self._consecutive_rejects = 0
                    raise CameraError(
                        f"{self.name}: {self.max_consecutive_rejects} consecutive frames rejected "
                        f"({self.stats.as_dict()}); still reading"
                    )
                continue
            self._consecutive_rejects = 0
            return Frame(t_s=t_s, image=gray, sequence=self._sequence, source=self.name)

    async def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            await asyncio.to_thread(self._release_blocking, cap)

    def _release_blocking(self, cap: CaptureBackend) -> None:
        with self._io_lock:
            cap.release()
