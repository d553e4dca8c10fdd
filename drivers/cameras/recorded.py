"""Recorded camera sources: a video file or an image folder with a timestamp file.

Time. A recording carries its own times (``t_rec``). The first frame read is stamped at the
clock's ``now()`` and every later one keeps its recorded spacing: ``t_s = t_rec + offset`` with
``offset = clock.now() - t_rec[0]`` (or a caller's ``offset_s``, e.g. 0.0 to keep the recorded
times for aligning a replay with its telemetry log). ``realtime=True`` paces reads with the clock
(an accelerated :class:`Clock` replays faster); ``realtime=False`` returns each frame as soon as
it is decoded, still stamped with its recorded spacing.

Damage. Frames before any damage are delivered; then :class:`CorruptInput` names the file and the
frame index (and is raised again on every later read). In an image folder each image is its own
file, so a missing or undecodable image is counted (``stats.skipped_missing`` /
``stats.skipped_corrupt``), logged and skipped, while a damaged timestamp file ends the replay at
the damaged line. A video is checked for truncation at open: for AVI (RIFF) files the ``movi``
chunks are walked so that a partly written last frame, which the decoder would conceal into a
plausible-looking image, is never delivered; for other containers a decoder stop before the
declared frame count (or before the sidecar's last timestamp) is reported as corruption.

Frame checks (size, blank, timestamps going backwards or repeating, gaps) are those of
:mod:`drivers.cameras.checks`; a recording whose images are not the configured size is refused
at open with :class:`ConfigError`.
"""

from __future__ import annotations

import abc
import asyncio
import csv
import logging
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.config import CameraConfig, ConfigError
from companion.method.messages import Frame
from drivers.cameras.base import CameraSource, CorruptInput, EndOfStream
from drivers.cameras.checks import CameraStats, FrameChecker
from drivers.clock import Clock

log = logging.getLogger(__name__)

FRAMES_CSV = "frames.csv"
TIMESTAMPS_TXT = "timestamps.txt"
CSV_COLUMNS = ("sequence", "t_s", "filename")


# --------------------------------------------------------------------------------------------
# Timestamp files
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TimestampEntry:
    sequence: int
    t_s: float
    filename: str | None


@dataclass(frozen=True, slots=True)
class TimestampFile:
    """Entries parsed up to the first damaged line; ``problem`` describes that line (None = intact)."""

    path: Path
    entries: tuple[TimestampEntry, ...]
    problem: str | None

    @property
    def times(self) -> np.ndarray:
        """(N,) recorded times in seconds."""
        return np.array([e.t_s for e in self.entries], dtype=float)


def _number(text: str, what: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{what} {text!r} is not finite")
    return value


def read_frames_csv(path: Path) -> TimestampFile:
    """A CSV with a header naming ``t_s`` and optionally ``sequence`` and ``filename`` (the recorder's own)."""
    entries: list[TimestampEntry] = []
    with open(path, newline="") as f:
        rows = csv.reader(f)
        header = next(rows, None)
        if header is None:
            return TimestampFile(path, (), f"{path}: empty (no header line)")
        header = [h.strip() for h in header]
        if "t_s" not in header:
            return TimestampFile(path, (), f"{path}: line 1: header {header} has no 't_s' column")
        i_t = header.index("t_s")
        i_seq = header.index("sequence") if "sequence" in header else None
        i_file = header.index("filename") if "filename" in header else None
        width = len(header)
        for line_no, row in enumerate(rows, start=2):
            if not row or (len(row) == 1 and not row[0].strip()):
                continue
            try:
                if len(row) != width:
                    raise ValueError(f"{len(row)} fields, header has {width}")
                t = _number(row[i_t], "time")
                seq = int(row[i_seq]) if i_seq is not None else len(entries)
                name = row[i_file].strip() if i_file is not None else None
                if i_file is not None and not name:
                    raise ValueError("empty filename")
            except ValueError as exc:
                return TimestampFile(path, tuple(entries), f"{path}: line {line_no} (frame {len(entries)}): {exc}")
            entries.append(TimestampEntry(seq, t, name))
    return TimestampFile(path, tuple(entries), None)


def read_timestamps_txt(path: Path) -> TimestampFile:
    """Whitespace separated ``t_s [filename]`` per line; blank lines and ``#`` comments ignored."""
    entries: list[TimestampEntry] = []
    with open(path) as f:
        for line_no, line in enumerate(f, start=1):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            parts = text.split()
            try:
                if len(parts) > 2:
                    raise ValueError(f"{len(parts)} fields, expected 'timestamp [filename]'")
                t = _number(parts[0], "time")
            except ValueError as exc:
                return TimestampFile(path, tuple(entries), f"{path}: line {line_no} (frame {len(entries)}): {exc}")
            entries.append(TimestampEntry(len(entries), t, parts[1] if len(parts) == 2 else None))
    return TimestampFile(path, tuple(entries), None)


def read_timestamp_file(path: Path) -> TimestampFile:
    """``.csv`` files as :func:`read_frames_csv`, anything else as :func:`read_timestamps_txt`."""
    try:
        return read_frames_csv(path) if path.suffix.lower() == ".csv" else read_timestamps_txt(path)
    except UnicodeDecodeError as exc:
        return TimestampFile(path, (), f"{path}: not a text file ({exc.reason})")


def nominal_period(times: np.ndarray, fallback_s: float) -> float:
    """Median positive interval of (N,) times (robust to gaps and reordering), else ``fallback_s``."""
    d = np.diff(times)
    d = d[d > 0]
    return float(np.median(d)) if d.size else fallback_s


# --------------------------------------------------------------------------------------------
# AVI structure (truncation check)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class AviChunks:
    """Video chunks found by walking an AVI file's RIFF structure."""

    complete_frames: int  # video chunks ('##dc' / '##db') lying wholly inside the file
    truncated: bool  # the file ends before a chunk (or the RIFF list) it declares


def walk_avi(path: Path) -> AviChunks | None:
    """Count complete video chunks in an AVI (incl. OpenDML 'AVIX' extensions); None if not AVI.

    Only chunk headers are read (8 bytes per chunk), so this costs one seek per frame.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(12)
        if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"AVI ":
            return None
        frames = 0
        stream: bytes | None = None  # the first video stream's two-digit number

        def walk(start: int, end: int, depth: int) -> bool:
            """Count video chunks in [start, end); True if the data stops inside a chunk."""
            nonlocal frames, stream
            pos = start
            while pos + 8 <= end:
                f.seek(pos)
                hdr = f.read(8)
                if len(hdr) < 8:
                    return True
                cid, csize = hdr[:4], struct.unpack("<I", hdr[4:])[0]
                chunk_end = pos + 8 + csize
                if cid == b"LIST" and depth < 3:
                    # A truncated file cuts its 'movi' list short: walk what is there.
                    cut = f.read(4) in (b"movi", b"rec ") and walk(pos + 12, min(chunk_end, size), depth + 1)
                    if cut or chunk_end > size:
                        return True
                elif chunk_end > size:
                    return True
                elif depth > 0 and cid[2:4] in (b"dc", b"db") and csize > 0:
                    if stream is None:
                        stream = cid[:2]
                    if cid[:2] == stream:
                        frames += 1
                pos = chunk_end + (csize & 1)
            return end - pos > 1  # a partial chunk header at the very end

        truncated = False
        riff_start = 0
        while riff_start + 12 <= size:
            f.seek(riff_start)
            head = f.read(12)
            if head[:4] != b"RIFF" or head[8:12] not in (b"AVI ", b"AVIX"):
                break
            riff_end = riff_start + 8 + struct.unpack("<I", head[4:8])[0]
            if walk(riff_start + 12, min(riff_end, size), 0) or riff_end > size:
                truncated = True
                break
            riff_start = riff_end + (riff_end & 1)
        return AviChunks(frames, truncated)


# --------------------------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------------------------


class RecordedSource(CameraSource):
    """Common replay logic: time mapping, pacing, checks, sticky end/corruption."""

    def __init__(
        self,
        path: str | os.PathLike,
        clock: Clock,
        *,
        width: int,
        height: int,
        realtime: bool = True,
        offset_s: float | None = None,
        blank_std_max: float = 1.0,
        gap_factor: float = 3.0,
        nominal_period_s: float = 0.05,
    ) -> None:
        self.path = Path(path)
        self.clock = clock
        self.width = int(width)
        self.height = int(height)
        self.realtime = bool(realtime)
        self.offset_s = offset_s
        self.stats = CameraStats()
        self.recorded_t0_s: float | None = None
        self._checker = FrameChecker(
            width, height, self.stats, name=self.name, nominal_period_s=nominal_period_s,
            blank_std_max=blank_std_max, gap_factor=gap_factor,
        )
        self._finished: Exception | None = None

    @abc.abstractmethod
    def _next_raw(self) -> tuple[int, float, np.ndarray] | None:
        """(sequence, recorded time, image) of the next frame; None for a skipped one (counted).

        Raises EndOfStream or CorruptInput when there is nothing more to deliver.
        """

    def _release(self) -> None:  # noqa: B027 - sources with an open handle override it
        """Release file handles (blocking)."""

    async def read(self) -> Frame:
        while True:
            if self._finished is not None:
                raise type(self._finished)(*self._finished.args)
            try:
                raw = await asyncio.to_thread(self._next_raw)
            except (EndOfStream, CorruptInput) as exc:
                self._finished = exc
                if isinstance(exc, CorruptInput):
                    log.error("%s: %s (%d frames delivered)", self.name, exc, self.stats.delivered)
                raise
            if raw is None:
                continue
            sequence, t_rec, image = raw
            if self.offset_s is None:
                self.offset_s = self.clock.now() - t_rec
            if self.recorded_t0_s is None:
                self.recorded_t0_s = t_rec
            t_s = t_rec + self.offset_s
            gray = self._checker.admit(image, t_s)
            if gray is None:
                continue
            if self.realtime:
                await self.clock.sleep_until(t_s)
            return Frame(t_s=t_s, image=gray, sequence=sequence, source=self.name)

    async def close(self) -> None:
        await asyncio.to_thread(self._release)


def _check_size(path: Path, w: int, h: int, width: int, height: int) -> None:
    if (w, h) != (width, height):
        raise ConfigError(
            f"{path}: recorded images are {w}x{h} but camera.width x camera.height are {width}x{height}; "
            f"set them (and the intrinsics) to the recording's"
        )


class VideoFileSource(RecordedSource):
    """Frames of a video file (anything OpenCV's FFmpeg backend decodes; AVI is checked structurally).

    Times come from ``timestamps_file`` if given, else ``<video stem>.csv`` beside the video if it
    exists, else frame index / the container's frame rate (``rate_hz`` if it declares none).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        clock: Clock,
        *,
        width: int,
        height: int,
        timestamps_file: str | os.PathLike | None = None,
        rate_hz: float = 20.0,
        realtime: bool = True,
        offset_s: float | None = None,
        blank_std_max: float = 1.0,
        gap_factor: float = 3.0,
    ) -> None:
        path = Path(path)
        self.name = f"video:{path.name}"
        if not path.is_file():
            raise ConfigError(f"camera.path: video file {path} does not exist")
        self.avi = walk_avi(path)
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        if not cap.isOpened():
            cap.release()
            raise CorruptInput(f"{path}: not a video OpenCV can open (corrupt, or truncated before its index)")
        self._cap = cap
        _check_size(path, int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), width, height)
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.fps = fps if 0 < fps < 10_000 else float(rate_hz)
        self.declared_frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        sidecar = Path(timestamps_file) if timestamps_file else path.with_suffix(".csv")
        if timestamps_file and not sidecar.is_file():
            raise ConfigError(f"camera.timestamps_file: {sidecar} does not exist")
        self.timestamps = read_timestamp_file(sidecar) if sidecar.is_file() else None
        if self.timestamps is not None and not self.timestamps.entries and self.timestamps.problem:
            raise CorruptInput(self.timestamps.problem)
        period = nominal_period(self.timestamps.times, 1.0 / self.fps) if self.timestamps else 1.0 / self.fps
        super().__init__(
            path, clock, width=width, height=height, realtime=realtime, offset_s=offset_s,
            blank_std_max=blank_std_max, gap_factor=gap_factor, nominal_period_s=period,
        )
        self._index = 0
        if self.avi is not None and self.avi.truncated:
            log.warning("%s: truncated AVI: %d complete frames", path, self.avi.complete_frames)

    def _end(self, i: int) -> Exception:
        """EndOfStream, or CorruptInput when frame ``i`` should have existed."""
        p = self.path
        if self.avi is not None:
            if i < self.avi.complete_frames:
                return CorruptInput(f"{p}: frame {i} could not be decoded ({self.avi.complete_frames} complete frames in the file)")
            if self.avi.truncated:
                return CorruptInput(f"{p}: truncated: frame {i} is incomplete; frames 0..{i - 1} were delivered")
        elif self.declared_frames > 0 and i < self.declared_frames - 1:
            return CorruptInput(f"{p}: frame {i} could not be decoded; the container declares {self.declared_frames} frames")
        if self.timestamps is not None and i < len(self.timestamps.entries):
            return CorruptInput(f"{p}: video ends at frame {i} but {self.timestamps.path} lists {len(self.timestamps.entries)} frames")
        return EndOfStream(f"{p}: end after {i} frames")

    def _next_raw(self) -> tuple[int, float, np.ndarray] | None:
        i = self._index
        if self.avi is not None and i >= self.avi.complete_frames:
            raise self._end(i)  # never decode a partly written chunk: the decoder would conceal it
        ok, image = self._cap.read()
        if not ok or image is None:
            raise self._end(i)
        self._index += 1
        if self.timestamps is None:
            return i, i / self.fps, image
        if i >= len(self.timestamps.entries):
            raise CorruptInput(
                self.timestamps.problem
                or f"{self.timestamps.path}: has {len(self.timestamps.entries)} timestamps but {self.path} has more frames"
            )
        entry = self.timestamps.entries[i]
        return entry.sequence, entry.t_s, image

    def _release(self) -> None:
        self._cap.release()


class ImageFolderSource(RecordedSource):
    """Images listed in a timestamp file: the recorder's ``frames.csv`` or a ``timestamps.txt``.

    File names are relative to the folder. ``timestamps_file`` overrides the search.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        clock: Clock,
        *,
        width: int,
        height: int,
        timestamps_file: str | os.PathLike | None = None,
        rate_hz: float = 20.0,
        realtime: bool = True,
        offset_s: float | None = None,
        blank_std_max: float = 1.0,
        gap_factor: float = 3.0,
    ) -> None:
        folder = Path(path)
        self.name = f"folder:{folder.name}"
        if not folder.is_dir():
            raise ConfigError(f"camera.path: image folder {folder} does not exist")
        if timestamps_file:
            index = Path(timestamps_file)
            if not index.is_absolute() and not index.is_file():
                index = folder / index
            if not index.is_file():
                raise ConfigError(f"camera.timestamps_file: {timestamps_file} does not exist")
        else:
            candidates = [folder / FRAMES_CSV, folder / TIMESTAMPS_TXT]
            index = next((c for c in candidates if c.is_file()), None)
            if index is None:
                raise ConfigError(
                    f"camera.path: folder {folder} has neither {FRAMES_CSV} nor {TIMESTAMPS_TXT}; "
                    f"set camera.timestamps_file"
                )
        self.timestamps = read_timestamp_file(index)
        missing_names = [e for e in self.timestamps.entries if e.filename is None]
        if missing_names:
            raise ConfigError(f"{index}: lines without a file name cannot index an image folder")
        if not self.timestamps.entries and self.timestamps.problem:
            raise CorruptInput(self.timestamps.problem)
        self.folder = folder
        for entry in self.timestamps.entries[:10]:  # size check on the first readable image
            image = cv2.imread(str(folder / entry.filename), cv2.IMREAD_UNCHANGED)
            if image is not None:
                _check_size(folder / entry.filename, image.shape[1], image.shape[0], width, height)
                break
        super().__init__(
            folder, clock, width=width, height=height, realtime=realtime, offset_s=offset_s,
            blank_std_max=blank_std_max, gap_factor=gap_factor,
            nominal_period_s=nominal_period(self.timestamps.times, 1.0 / rate_hz),
        )
        self._index = 0

    def _next_raw(self) -> tuple[int, float, np.ndarray] | None:
        entries = self.timestamps.entries
        i = self._index
        if i >= len(entries):
            if self.timestamps.problem:
                raise CorruptInput(self.timestamps.problem)
            raise EndOfStream(f"{self.folder}: end after {i} frames")
        self._index += 1
        entry = entries[i]
        file = self.folder / entry.filename
        if not file.is_file():
            self.stats.skipped_missing += 1
            log.warning("%s: frame %d: %s is missing; skipped (%d so far)", self.name, i, file, self.stats.skipped_missing)
            return None
        image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
        if image is None:
            self.stats.skipped_corrupt += 1
            log.warning("%s: frame %d: %s cannot be decoded; skipped (%d so far)", self.name, i, file, self.stats.skipped_corrupt)
            return None
        return entry.sequence, entry.t_s, image


def open_recording(config: CameraConfig, clock: Clock, *, offset_s: float | None = None) -> RecordedSource:
    """The recorded source ``camera.path`` names: a folder -> :class:`ImageFolderSource`, a file -> video."""
    if not config.path:
        raise ConfigError("camera.path is empty: camera.source 'file' needs a video file or an image folder")
    path = Path(config.path).expanduser()
    if not path.exists():
        raise ConfigError(f"camera.path: {path} does not exist")
    cls = ImageFolderSource if path.is_dir() else VideoFileSource
    return cls(
        path, clock, width=config.width, height=config.height, timestamps_file=config.timestamps_file or None,
        rate_hz=config.rate_hz, realtime=config.realtime, offset_s=offset_s,
        blank_std_max=config.blank_std_max, gap_factor=config.gap_factor,
    )
