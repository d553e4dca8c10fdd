"""``companion run --record DIR``: frames and their times written beside the telemetry log.

Layout of a recording folder (see docs/cameras.md for the byte-level details)::

    DIR/meta.yaml        format version, clock mapping, camera intrinsics and mount, config snapshot,
                         and at close a summary (frames written / dropped / failed)
    DIR/frames.csv       header "sequence,t_s,filename"; one line per written frame
    DIR/frames/000000.png  the images (grey, lossless PNG; or JPEG when configured)
    DIR/telemetry.tlog   MAVLink telemetry (written by the autopilot link, not by this module):
                         per message an 8-byte big-endian unsigned microsecond Unix timestamp
                         followed by the raw MAVLink packet, as MAVProxy and pymavlink write .tlog

The capture path only calls :meth:`FrameRecorder.submit`, which copies the image into a bounded
queue and returns at once; a writer thread owned by the recorder encodes and writes. When the
queue is full the frame is dropped and counted (a recording with holes is better than a camera
that stalls). Each image is written before its ``frames.csv`` line, so a crash leaves no line
pointing at a missing file. The folder replays with ``camera.source: file`` and
``camera.path: DIR`` (:class:`drivers.cameras.recorded.ImageFolderSource` reads ``frames.csv``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from companion.config import CameraConfig, CompanionConfig
from companion.method.messages import Frame
from drivers.clock import Clock

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
META_YAML = "meta.yaml"
FRAMES_CSV = "frames.csv"
FRAMES_DIR = "frames"
TELEMETRY_TLOG = "telemetry.tlog"


@dataclass(slots=True)
class RecorderStats:
    submitted: int = 0
    written: int = 0
    dropped: int = 0  # queue full: never waited for
    failed: int = 0  # encoding or writing failed (disk full, ...)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


def _plain(value: Any) -> Any:
    """Dataclasses, tuples and NumPy scalars as plain YAML-safe values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def camera_meta(camera: CameraConfig) -> dict[str, Any]:
    """Intrinsics, distortion and mount of the recording camera (the keys of ``camera.*``)."""
    keys = (
        "source", "device", "path", "width", "height", "rate_hz", "pixel_format", "exposure_us",
        "fx", "fy", "cx", "cy", "distortion",
        "mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg", "mount_offset_m",
    )
    return {k: _plain(getattr(camera, k)) for k in keys}


def _write_yaml_atomic(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(yaml.safe_dump(data, sort_keys=False))
    os.replace(tmp, path)


def read_recording_meta(directory: str | os.PathLike) -> dict[str, Any]:
    """The parsed ``meta.yaml`` of a recording folder (ValueError naming the file if unreadable)."""
    path = Path(directory) / META_YAML
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read recording metadata: {exc}") from exc
    if not isinstance(data, dict) or data.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: not a companion recording (format_version {FORMAT_VERSION} expected)")
    return data


class FrameRecorder:
    """Writes frames to a recording folder from a bounded queue on its own writer thread.

    Use :meth:`start` (creates the layout, writes ``meta.yaml``), :meth:`submit` from the capture
    path, and :meth:`close` (or ``async with`` / ``with``) to flush, join and write the summary.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        *,
        image_format: str = "png",
        png_compression: int = -1,
        jpeg_quality: int = 95,
        queue_frames: int = 64,
        meta: dict[str, Any] | None = None,
        clock: Clock | None = None,
    ) -> None:
        if image_format not in ("png", "jpg"):
            raise ValueError(f"image_format must be 'png' or 'jpg', got {image_format!r}")
        if queue_frames < 1:
            raise ValueError(f"queue_frames must be at least 1, got {queue_frames}")
        self.directory = Path(directory)
        self.frames_dir = self.directory / FRAMES_DIR
        self.frames_csv = self.directory / FRAMES_CSV
        self.meta_path = self.directory / META_YAML
        self.telemetry_path = self.directory / TELEMETRY_TLOG
        self.image_format = image_format
        if image_format == "png":
            self._encode_params = [cv2.IMWRITE_PNG_COMPRESSION, png_compression] if png_compression >= 0 else []
        else:
            self._encode_params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        self.meta = dict(meta or {})
        self.clock = clock
        self.stats = RecorderStats()
        self._queue: queue.Queue[tuple[int, float, np.ndarray] | None] = queue.Queue(maxsize=queue_frames)
        self._thread: threading.Thread | None = None
        self._csv = None
        self._t_first: float | None = None
        self._t_last: float | None = None
        self._closed = False

    @classmethod
    def from_config(
        cls, directory: str | os.PathLike, config: CompanionConfig, clock: Clock | None = None
    ) -> "FrameRecorder":
        """A recorder with the ``camera.record_*`` settings and the whole config in ``meta.yaml``."""
        cam = config.camera
        return cls(
            directory,
            image_format=cam.record_format,
            png_compression=cam.record_png_compression,
            jpeg_quality=cam.record_jpeg_quality,
            queue_frames=cam.record_queue_frames,
            meta={"camera": camera_meta(cam), "config": _plain(config)},
            clock=clock,
        )

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> "FrameRecorder":
        """Create the folder layout and the writer thread. Refuses a folder that holds a recording."""
        if self._thread is not None:
            raise RuntimeError(f"{self.directory}: recorder already started")
        if self.frames_csv.exists() or self.meta_path.exists():
            raise FileExistsError(f"{self.directory} already holds a recording; choose a new --record folder")
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        clock_info: dict[str, Any] = {"unix_time_s": time.time()}
        if self.clock is not None:
            # Sampled together: t_s in frames.csv maps to Unix time (the tlog's clock) as
            # unix = unix_time_s + (t_s - t_s0) / speedup.
            clock_info = {"t_s": self.clock.now(), "unix_time_s": time.time(), "speedup": self.clock.speedup}
        self.meta = {
            "format_version": FORMAT_VERSION,
            "created_unix_s": clock_info["unix_time_s"],
            "clock": clock_info,
            "files": {"frames_csv": FRAMES_CSV, "frames_dir": FRAMES_DIR, "telemetry": TELEMETRY_TLOG},
            "image_format": self.image_format,
            **self.meta,
        }
        _write_yaml_atomic(self.meta_path, self.meta)
        self._csv = open(self.frames_csv, "w", newline="", buffering=1)  # line buffered
        self._csv.write("sequence,t_s,filename\n")
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self.directory.name}", daemon=True)
        self._thread.start()
        log.info("recording frames to %s (%s, queue %d)", self.directory, self.image_format, self._queue.maxsize)
        return self

    def submit(self, frame: Frame) -> bool:
        """Queue a frame for writing; False (and counted) if the queue is full. Never blocks."""
        if self._thread is None or self._closed:
            raise RuntimeError(f"{self.directory}: recorder is not running")
        self.stats.submitted += 1
        try:
            self._queue.put_nowait((int(frame.sequence), float(frame.t_s), np.array(frame.image, copy=True)))
        except queue.Full:
            self.stats.dropped += 1
            if self.stats.dropped in (1, 10, 100) or self.stats.dropped % 1000 == 0:
                log.warning("%s: writer behind, frame dropped (%d so far)", self.directory, self.stats.dropped)
            return False
        return True

    def close(self, timeout_s: float = 30.0) -> RecorderStats:
        """Write what is queued, stop the writer and add the summary to ``meta.yaml``."""
        if self._thread is None or self._closed:
            return self.stats
        self._closed = True
        deadline = time.monotonic() + timeout_s
        try:
            self._queue.put(None, timeout=timeout_s)  # the writer drains everything queued before it
        except queue.Full:
            pass
        self._thread.join(max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.error("%s: writer did not finish within %.0f s", self.directory, timeout_s)
        if self._csv is not None:
            self._csv.close()
        self.meta["summary"] = {
            **self.stats.as_dict(),
            "first_t_s": self._t_first,
            "last_t_s": self._t_last,
        }
        _write_yaml_atomic(self.meta_path, self.meta)
        log.info("recording %s closed: %s", self.directory, self.stats.as_dict())
        return self.stats

    async def aclose(self) -> RecorderStats:
        return await asyncio.to_thread(self.close)

    def __enter__(self) -> "FrameRecorder":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    async def __aenter__(self) -> "FrameRecorder":
        return self.start()

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    # -- writer thread ------------------------------------------------------------------------

    def _run(self) -> None:
        index = 0
        while True:
            item = self._queue.get()
            if item is None:
                return
            sequence, t_s, image = item
            name = f"{FRAMES_DIR}/{index:06d}.{self.image_format}"
            try:
                ok = cv2.imwrite(str(self.directory / name), image, self._encode_params)
                if not ok:
                    raise OSError("cv2.imwrite returned False")
                self._csv.write(f"{sequence},{t_s!r},{name}\n")
            except Exception as exc:  # disk full, permissions: count, keep the thread alive
                self.stats.failed += 1
                if self.stats.failed in (1, 10, 100) or self.stats.failed % 1000 == 0:
                    log.error("%s: writing %s failed: %s (%d so far)", self.directory, name, exc, self.stats.failed)
                continue
            index += 1
            self.stats.written += 1
            if self._t_first is None:
                self._t_first = t_s
            self._t_last = t_s
