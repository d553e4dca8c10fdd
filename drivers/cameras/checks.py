"""Frame admission shared by the real camera sources: counted rejections, never silent repairs.

Every frame a V4L2 device or a recording yields passes :class:`FrameChecker.admit` before it
becomes a :class:`companion.method.messages.Frame`. The checks, in order:

1. pixel format: uint8 with 1, 3 or 4 channels (colour is converted to grey here, once);
2. size: exactly the configured width x height; the image is never resized, because the
   intrinsics (fx, fy, cx, cy) belong to one size and a silent resize would corrupt every ray;
3. blank: a frame whose pixel standard deviation is at most ``blank_std_max`` (lens cap, sensor
   starting, all white after an exposure jump) carries no features;
4. time: a timestamp that is not finite, goes backwards or repeats the previous one is dropped,
   because the navigation buffer is interpolated at frame times and the mapper assumes order;
5. gaps: an interval longer than ``gap_factor`` frame periods is counted (the frame is kept).

Each rejection increments a counter in :class:`CameraStats` and is logged at counts 1, 10, 100,
... so a stuck camera cannot flood the log.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

log = logging.getLogger(__name__)


class FrameFormatError(ValueError):
    """An image whose dtype or channel count is not a camera image we understand."""


@dataclass(slots=True)
class CameraStats:
    """Counters a source keeps; the daemon publishes them in its status."""

    delivered: int = 0
    rejected_format: int = 0
    rejected_size: int = 0
    rejected_blank: int = 0
    rejected_time: int = 0  # not finite, backwards or repeated
    gaps: int = 0  # intervals longer than gap_factor frame periods (frames kept)
    skipped_missing: int = 0  # recorded folder: image file listed but absent
    skipped_corrupt: int = 0  # recorded folder: image file present but undecodable
    read_errors: int = 0  # V4L2: failed reads (each one starts a reconnect)
    reconnects: int = 0  # V4L2: successful reopenings after a loss
    timestamps_fallback: int = 0  # V4L2: frames stamped at read return (no usable buffer timestamp)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @property
    def rejected(self) -> int:
        return self.rejected_format + self.rejected_size + self.rejected_blank + self.rejected_time


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 from (H, W), (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4) uint8.

    Raises :class:`FrameFormatError` for anything else (16-bit, float, 2-channel packed YUV).
    """
    if not isinstance(image, np.ndarray):
        raise FrameFormatError(f"image is a {type(image).__name__}, not a numpy array")
    if image.dtype != np.uint8:
        raise FrameFormatError(f"image dtype is {image.dtype}, expected uint8")
    if image.ndim == 2:
        return image
    if image.ndim == 3:
        channels = image.shape[2]
        if channels == 1:
            return image[:, :, 0]
        if channels == 3:
            return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if channels == 4:
            return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise FrameFormatError(f"image shape {image.shape} is not (H, W) or (H, W, 1|3|4)")


def _log_count(count: int, message: str, *args) -> None:
    """Log at counts 1, 10, 100, ...: visible, never a flood."""
    if count > 0 and 10 ** int(math.log10(count)) == count:
        log.warning(message + " (%d so far)", *args, count)


class FrameChecker:
    """Admits or rejects frames for one source; keeps the last admitted time.

    width, height: the configured image size (px). nominal_period_s: the expected frame period,
    for gap counting. blank_std_max: grey levels; 0 disables the blank check.
    """

    def __init__(
        self,
        width: int,
        height: int,
        stats: CameraStats,
        *,
        name: str,
        nominal_period_s: float,
        blank_std_max: float = 1.0,
        gap_factor: float = 3.0,
    ) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"{name}: image size must be positive, got {width}x{height}")
        if not nominal_period_s > 0:
            raise ValueError(f"{name}: nominal frame period must be positive, got {nominal_period_s}")
        self.width = int(width)
        self.height = int(height)
        self.stats = stats
        self.name = name
        self.nominal_period_s = float(nominal_period_s)
        self.blank_std_max = float(blank_std_max)
        self.gap_factor = float(gap_factor)
        self.last_t_s: float | None = None

    def admit(self, image: np.ndarray, t_s: float) -> np.ndarray | None:
        """The grey (H, W) uint8 image if the frame passes every check, else None (counted)."""
        s = self.stats
        try:
            gray = to_gray(image)
        except FrameFormatError as exc:
            s.rejected_format += 1
            _log_count(s.rejected_format, "%s: frame rejected: %s", self.name, exc)
            return None
        h, w = gray.shape
        if (w, h) != (self.width, self.height):
            s.rejected_size += 1
            _log_count(
                s.rejected_size, "%s: frame rejected: size %dx%d, configured camera.width x height is %dx%d",
                self.name, w, h, self.width, self.height,
            )
            return None
        if self.blank_std_max > 0 and self.is_blank(gray):
            s.rejected_blank += 1
            _log_count(s.rejected_blank, "%s: frame rejected: blank (mean %.0f, no texture)", self.name, float(gray.mean()))
            return None
        if not math.isfinite(t_s) or (self.last_t_s is not None and t_s <= self.last_t_s):
            s.rejected_time += 1
            _log_count(
                s.rejected_time, "%s: frame rejected: timestamp %.6f s does not follow the previous %.6f s",
                self.name, t_s, self.last_t_s if self.last_t_s is not None else float("nan"),
            )
            return None
        if self.last_t_s is not None and t_s - self.last_t_s > self.gap_factor * self.nominal_period_s:
            s.gaps += 1
            _log_count(s.gaps, "%s: gap of %.3f s between frames (nominal %.3f s)", self.name, t_s - self.last_t_s, self.nominal_period_s)
        self.last_t_s = t_s
        s.delivered += 1
        return gray

    def is_blank(self, gray: np.ndarray) -> bool:
        """True when the (4x subsampled) image has no more texture than ``blank_std_max``."""
        return float(gray[::4, ::4].std()) <= self.blank_std_max
