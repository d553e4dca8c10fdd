"""Recording and replay: the recorder's folder reads back identical frames and times; videos and
image folders replay at real time or as fast as possible; damage delivers the frames before it
and then a CorruptInput naming the file and frame; bad timestamps are dropped and counted."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.config import CameraConfig, CompanionConfig, ConfigError, config_from_dict, replace
from companion.method.messages import Frame
from drivers.cameras import recorder as recorder_module
from drivers.cameras.base import CorruptInput, EndOfStream
from drivers.cameras.factory import build_camera
from drivers.cameras.recorded import ImageFolderSource, VideoFileSource, open_recording, walk_avi
from drivers.cameras.recorder import FrameRecorder, read_recording_meta
from drivers.clock import Clock

W, H = 80, 60


def textured(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 256, (H, W), dtype=np.uint8), (3, 3), 0.8)


def cam(path: Path | str = "", **changes) -> CameraConfig:
    return replace(CameraConfig(source="file", path=str(path), width=W, height=H, rate_hz=10.0, realtime=False), **changes)


async def read_all(src, limit: int = 1000) -> tuple[list[Frame], BaseException]:
    frames = []
    for _ in range(limit):
        try:
            frames.append(await src.read())
        except (EndOfStream, CorruptInput) as exc:
            return frames, exc
    raise AssertionError("source never ended")


def replay(src) -> tuple[list[Frame], BaseException]:
    return asyncio.run(read_all(src))


def record(directory: Path, frames: list[Frame], **kw) -> FrameRecorder:
    config = replace(CompanionConfig(), **{"camera.width": W, "camera.height": H, "camera.fx": 70.0})
    rec = FrameRecorder.from_config(directory, config, Clock())
    for k, v in kw.items():
        setattr(rec, k, v)
    with rec:
        for f in frames:
            assert rec.submit(f)
    return rec


def write_video(path: Path, images: list[np.ndarray], fourcc: str, fps: float = 10.0) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), fps, (W, H), isColor=False)
    assert w.isOpened(), f"cannot write {fourcc} video"
    for im in images:
        w.write(im)
    w.release()


# ---- recorder -> folder -> replay ---------------------------------------------------------


def test_recorder_folder_replays_identical_frames_and_times(tmp_path):
    rng = np.random.default_rng(7)
    times = 100.0 + np.cumsum(rng.uniform(0.04, 0.06, 15))  # irregular, as a real camera's
    frames = [Frame(float(t), textured(i), sequence=10 + i, source="cam") for i, t in enumerate(times)]
    rec = record(tmp_path / "rec", frames)
    assert rec.stats.as_dict() == {"submitted": 15, "written": 15, "dropped": 0, "failed": 0}

    layout = sorted(p.relative_to(tmp_path / "rec").as_posix() for p in (tmp_path / "rec").rglob("*"))
    assert layout[:3] == ["frames", "frames.csv", "frames/000000.png"] and "meta.yaml" in layout
    meta = read_recording_meta(tmp_path / "rec")
    assert meta["camera"]["fx"] == 70.0 and meta["camera"]["width"] == W
    assert meta["files"]["telemetry"] == "telemetry.tlog"
    assert meta["summary"]["written"] == 15 and meta["summary"]["last_t_s"] == times[-1]
    assert config_from_dict(meta["config"]).camera.fx == 70.0  # the snapshot is a loadable config

    # offset_s=0 keeps the recorded times exactly
    src = ImageFolderSource(tmp_path / "rec", Clock(), width=W, height=H, realtime=False, offset_s=0.0)
    out, end = replay(src)
    assert isinstance(end, EndOfStream)
    assert [f.sequence for f in out] == [f.sequence for f in frames]
    assert [f.t_s for f in out] == [f.t_s for f in frames]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(out, frames))

    # by default the first frame is at the clock's now, spacing preserved
    clock = Clock()
    src = build_camera(cam(tmp_path / "rec"), clock)
    t_before = clock.now()
    out, _ = replay(src)
    assert t_before <= out[0].t_s <= clock.now()
    assert np.allclose(np.diff([f.t_s for f in out]), np.diff(times), atol=1e-9)


def test_recorder_never_blocks_the_capture_path_drops_and_counts_when_full(tmp_path, monkeypatch):
    writing, release = threading.Event(), threading.Event()
    real_imwrite = cv2.imwrite

    def slow_imwrite(*args, **kw):
        writing.set()
        release.wait(5.0)
        return real_imwrite(*args, **kw)

    monkeypatch.setattr(recorder_module.cv2, "imwrite", slow_imwrite)
    rec = FrameRecorder(tmp_path / "rec", queue_frames=2).start()
    assert rec.submit(Frame(0.0, textured(0), 0))
    assert writing.wait(2.0)  # the writer holds frame 0 inside imwrite
    waits = []
    results = []
    for i in range(1, 6):
        t0 = time.perf_counter()
        results.append(rec.submit(Frame(i * 0.1, textured(i), i)))
        waits.append(time.perf_counter() - t0)
    release.set()
    stats = rec.close()
    assert results == [True, True, False, False, False]
    assert (stats.written, stats.dropped, stats.submitted) == (3, 3, 6)
    assert max(waits) < 0.01
    lines = (tmp_path / "rec" / "frames.csv").read_text().splitlines()
    assert lines == ["sequence,t_s,filename", "0,0.0,frames/000000.png", "1,0.1,frames/000001.png", "2,0.2,frames/000002.png"]
    print(f"\nsubmit() with the writer stalled: max {max(waits) * 1e6:.0f} us")


def test_recorder_refuses_to_overwrite_a_recording_and_measures_write_rate(tmp_path):
    big = [Frame(i * 0.05, cv2.resize(textured(i), (640, 480)), i) for i in range(20)]
    rec = FrameRecorder(tmp_path / "rec", queue_frames=64).start()
    t0 = time.perf_counter()
    for f in big:
        rec.submit(f)
    stats = rec.close()
    dt = time.perf_counter() - t0
    assert stats.written == 20
    with pytest.raises(FileExistsError, match="already holds a recording"):
        FrameRecorder(tmp_path / "rec").start()
    size = sum(p.stat().st_size for p in (tmp_path / "rec" / "frames").iterdir()) / 20
    print(f"\n640x480 grey PNG: {20 / dt:.0f} frames/s written, {size / 1024:.0f} KiB/frame")


def test_jpeg_recording_replays_within_jpeg_error(tmp_path):
    frames = [Frame(i * 0.1, textured(i), i) for i in range(4)]
    rec = FrameRecorder(tmp_path / "rec", image_format="jpg", jpeg_quality=95)
    with rec:
        for f in frames:
            rec.submit(f)
    out, _ = replay(ImageFolderSource(tmp_path / "rec", Clock(), width=W, height=H, realtime=False))
    assert len(out) == 4 and all(np.abs(a.image.astype(int) - b.image).mean() < 3 for a, b in zip(out, frames))


# ---- pacing -------------------------------------------------------------------------------


def test_realtime_replay_is_paced_by_an_accelerated_clock_and_fast_mode_is_not(tmp_path):
    frames = [Frame(i * 0.1, textured(i), i) for i in range(11)]  # 1.0 s of recording
    record(tmp_path / "rec", frames)
    clock = Clock(speedup=20.0)  # 1.0 s of recording = 50 ms of wall time
    src = ImageFolderSource(tmp_path / "rec", clock, width=W, height=H, realtime=True)

    async def paced():
        late = []
        t0 = time.monotonic()
        for _ in range(11):
            f = await src.read()
            late.append(clock.now() - f.t_s)
        return time.monotonic() - t0, late

    wall, late = asyncio.run(paced())
    assert min(late) >= -1e-3  # no frame is handed out before its time
    assert 0.045 <= wall < 0.6
    fast = ImageFolderSource(tmp_path / "rec", Clock(), width=W, height=H, realtime=False)
    t0 = time.monotonic()
    out, _ = replay(fast)
    fast_wall = time.monotonic() - t0
    assert len(out) == 11 and fast_wall < 0.5  # 1 s of recording on a 1x clock, not waited for
    assert np.allclose(np.diff([f.t_s for f in out]), 0.1)
    print(f"\nrealtime 1.0 s at 20x: {wall * 1e3:.0f} ms wall; fast mode at 1x: {fast_wall * 1e3:.0f} ms")


# ---- image folders: damage, missing files, bad times ----------------------------------------


def test_corrupt_and_missing_images_are_skipped_counted_and_named(tmp_path, caplog):
    frames = [Frame(i * 0.1, textured(i), i) for i in range(6)]
    record(tmp_path / "rec", frames)
    f2 = tmp_path / "rec" / "frames" / "000002.png"
    f2.write_bytes(f2.read_bytes()[:200])  # truncated PNG
    (tmp_path / "rec" / "frames" / "000004.png").unlink()
    caplog.set_level(logging.WARNING)
    src = ImageFolderSource(tmp_path / "rec", Clock(), width=W, height=H, realtime=False)
    out, end = replay(src)
    assert isinstance(end, EndOfStream)
    assert [f.sequence for f in out] == [0, 1, 3, 5]
    assert src.stats.skipped_corrupt == 1 and src.stats.skipped_missing == 1
    assert "000002.png cannot be decoded" in caplog.text and "000004.png is missing" in caplog.text


def test_truncated_index_delivers_the_frames_before_then_corrupt_input_naming_the_line(tmp_path):
    frames = [Frame(i * 0.1, textured(i), i) for i in range(6)]
    record(tmp_path / "rec", frames)
    csv = tmp_path / "rec" / "frames.csv"
    text = csv.read_text()
    csv.write_text(text[: text.index("4,0.4") + 4])  # the crash cut line 6 (frame 4) mid-write
    src = build_camera(cam(tmp_path / "rec"), Clock())
    out, end = replay(src)
    assert [f.sequence for f in out] == [0, 1, 2, 3]
    assert isinstance(end, CorruptInput)
    assert "frames.csv: line 6 (frame 4)" in str(end)
    with pytest.raises(CorruptInput):  # and it stays that way
        asyncio.run(src.read())


def test_timestamps_txt_backwards_and_repeated_times_are_dropped_and_counted(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    times = [0.0, 0.1, 0.2, 0.15, 0.2, 0.3, 0.9, 1.0]  # back at #3, repeat at #4, gap before #6
    for i in range(len(times)):
        cv2.imwrite(str(folder / f"im{i}.png"), cv2.cvtColor(textured(i), cv2.COLOR_GRAY2BGR))  # colour file
    (folder / "timestamps.txt").write_text(
        "# t_s filename\n" + "".join(f"{t} im{i}.png\n" for i, t in enumerate(times)) + "\n"
    )
    src = open_recording(cam(folder), Clock(), offset_s=0.0)
    out, end = replay(src)
    assert isinstance(end, EndOfStream)
    assert [f.t_s for f in out] == [0.0, 0.1, 0.2, 0.3, 0.9, 1.0]
    assert src.stats.rejected_time == 2 and src.stats.gaps == 1
    assert np.array_equal(out[0].image, textured(0))  # colour files become the same grey


def test_blank_and_wrong_size_frames_inside_a_recording_are_rejected(tmp_path):
    frames = [Frame(0.0, textured(0), 0), Frame(0.1, np.zeros((H, W), np.uint8), 1), Frame(0.2, textured(2), 2)]
    record(tmp_path / "rec", frames)
    cv2.imwrite(str(tmp_path / "rec" / "frames" / "000002.png"), np.zeros((H, W + 4), np.uint8) + textured(5)[:, :1])
    src = ImageFolderSource(tmp_path / "rec", Clock(), width=W, height=H, realtime=False)
    out, _ = replay(src)
    assert [f.sequence for f in out] == [0]
    assert src.stats.rejected_blank == 1 and src.stats.rejected_size == 1


# ---- videos -------------------------------------------------------------------------------


def test_lossless_video_replays_exactly_with_times_from_its_frame_rate_or_sidecar(tmp_path):
    images = [textured(i) for i in range(12)]
    video = tmp_path / "flight.avi"
    write_video(video, images, "FFV1", fps=25.0)
    out, end = replay(build_camera(cam(video), Clock()))
    assert isinstance(end, EndOfStream) and len(out) == 12
    assert all(np.array_equal(f.image, im) for f, im in zip(out, images))
    assert np.allclose(np.diff([f.t_s for f in out]), 1 / 25.0)

    sidecar_times = [5.0 + 0.03 * i + 0.01 * (i % 2) for i in range(12)]
    (tmp_path / "flight.csv").write_text("sequence,t_s\n" + "".join(f"{100 + i},{t}\n" for i, t in enumerate(sidecar_times)))
    out, _ = replay(VideoFileSource(video, Clock(), width=W, height=H, realtime=False, offset_s=0.0))
    assert [f.t_s for f in out] == sidecar_times and out[0].sequence == 100


@pytest.mark.parametrize("fourcc", ["MJPG", "FFV1"])
def test_truncated_video_delivers_the_complete_frames_then_corrupt_input(tmp_path, fourcc):
    images = [textured(i) for i in range(20)]
    video = tmp_path / "whole.avi"
    write_video(video, images, fourcc)
    intact, _ = replay(VideoFileSource(video, Clock(), width=W, height=H, realtime=False))
    data = video.read_bytes()
    # cut 80 % into frame 11's chunk, as a recorder killed mid-write leaves it
    at = data.index(b"movi")
    for _ in range(12):
        at = data.index(b"00dc", at + 1)
    size = int.from_bytes(data[at + 4 : at + 8], "little")
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: at + 8 + int(0.8 * size)])
    chunks = walk_avi(cut)
    assert chunks.truncated and chunks.complete_frames == 11

    out, end = replay(VideoFileSource(cut, Clock(), width=W, height=H, realtime=False))
    assert isinstance(end, CorruptInput)
    k = chunks.complete_frames
    assert len(out) == k and f"frame {k} is incomplete" in str(end) and "cut.avi" in str(end)
    # exactly the frames the intact file decodes to: no concealed half-frame slipped through
    assert all(np.array_equal(a.image, b.image) for a, b in zip(out, intact))


def test_video_ending_before_its_sidecar_is_corrupt(tmp_path):
    video = tmp_path / "v.mkv"  # not AVI: the sidecar is the reference count
    write_video(video, [textured(i) for i in range(5)], "FFV1")
    (tmp_path / "v.csv").write_text("t_s\n" + "".join(f"{i * 0.1}\n" for i in range(8)))
    out, end = replay(VideoFileSource(video, Clock(), width=W, height=H, realtime=False))
    assert len(out) == 5 and isinstance(end, CorruptInput) and "lists 8 frames" in str(end)


# ---- open-time errors ---------------------------------------------------------------------


def test_open_time_errors_are_clear(tmp_path):
    clock = Clock()
    with pytest.raises(ConfigError, match="camera.path is empty"):
        build_camera(cam(""), clock)
    with pytest.raises(ConfigError, match="does not exist"):
        build_camera(cam(tmp_path / "nope.avi"), clock)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="neither frames.csv nor timestamps.txt"):
        build_camera(cam(tmp_path / "empty"), clock)
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(CorruptInput, match="garbage.avi"):
        build_camera(cam(garbage), clock)
    video = tmp_path / "small.avi"
    write_video(video, [textured(0)], "MJPG")
    with pytest.raises(ConfigError, match=rf"{W}x{H} but camera.width x camera.height are 64x48"):
        build_camera(cam(video, width=64, height=48), clock)
    record(tmp_path / "rec", [Frame(0.0, textured(0), 0)])
    with pytest.raises(ConfigError, match="camera.width x camera.height are 64x48"):
        build_camera(cam(tmp_path / "rec", width=64, height=48), clock)
    with pytest.raises(ConfigError, match="synthetic.*daemon"):
        build_camera(CameraConfig(source="synthetic"), clock)
    with pytest.raises(ConfigError, match="camera.timestamps_file"):
        build_camera(cam(video, timestamps_file=str(tmp_path / "missing.txt")), clock)


def test_meta_yaml_is_plain_yaml_another_tool_can_read(tmp_path):
    record(tmp_path / "rec", [Frame(1.5, textured(0), 0)])
    data = yaml.safe_load((tmp_path / "rec" / "meta.yaml").read_text())
    assert data["format_version"] == 1 and data["image_format"] == "png"
    assert set(data["clock"]) == {"t_s", "unix_time_s", "speedup"}
    assert data["camera"]["distortion"] == [0.0, 0.0, 0.0, 0.0, 0.0]
