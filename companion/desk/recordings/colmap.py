"""The COLMAP text model, read as a recording (:func:`open_colmap`) and written
(:func:`export_colmap`) (docs/replay.md, "COLMAP model").

A COLMAP sparse model (``cameras.txt``, ``images.txt``, ``points3D.txt``; the output of
``colmap model_converter --output_type TXT`` and of most drone photogrammetry pipelines) holds
the camera intrinsics and one pose per registered image, world-to-camera: ``x_cam = R(q) X + t``
with the quaternion written ``QW QX QY QZ`` and the camera centre ``C = -R^T t``. Camera axes are
OpenCV's (x right, y down, z optical). COLMAP puts the centre of the top-left pixel at (0.5, 0.5),
OpenCV at (0, 0): ``cx_opencv = cx_colmap - 0.5`` (and the same for cy).

What a COLMAP model does not say is given beside it: ``meta.yaml`` (the world's up direction and
metric scale, as for the TUM layout: an SfM world has neither) and the images' times, either
``timestamps.txt`` (``timestamp name`` per line) or ``frame_interval_s`` in ``meta.yaml`` (images
in the order of their names). ``pose_sigmas.txt`` gives per-frame uncertainty as in the TUM layout.
``points3D.txt`` serves as a reference surface (:func:`read_points3d`).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import yaml

from companion.config import NavConfig
from companion.desk.recordings.poses import PoseRecording
from companion.desk.recordings.recording import (
    IDENTITY_MOUNT,
    Overrides,
    Recording,
    RecordingError,
    RecordingStats,
    finite_float,
    sorted_frames,
    table_rows,
)
from companion.desk.recordings.tum import (TUM_SIGMAS, exported_frames, exported_meta, meta_float, pose_recording,
                                           read_pose_meta)
from companion.method.geometry import CameraMount, PinholeCamera, matrix_to_quat, quat_to_matrix

COLMAP_MODEL_DIRS = (".", "sparse/0", "sparse")  # where the model's files are looked for, in order
COLMAP_CAMERAS = "cameras.txt"
COLMAP_IMAGES = "images.txt"
COLMAP_POINTS = "points3D.txt"
COLMAP_META = "meta.yaml"
COLMAP_TIMES = "timestamps.txt"
COLMAP_META_KEYS = ("world_up", "world_north", "scale_m_per_unit", "origin", "pose_sigma_m", "pose_sigma_deg",
                    "ground_alt_m", "association_s", "frame_interval_s", "images_dir", "source")

# Camera models whose distortion OpenCV's pinhole model holds: name -> (parameter count, a function
# of the parameters giving fx, fy, cx, cy (COLMAP pixel centres) and OpenCV's distortion vector).
_MODELS = {
    "SIMPLE_PINHOLE": (3, lambda p: (p[0], p[0], p[1], p[2], [0.0, 0.0, 0.0, 0.0])),
    "PINHOLE": (4, lambda p: (p[0], p[1], p[2], p[3], [0.0, 0.0, 0.0, 0.0])),
    "SIMPLE_RADIAL": (4, lambda p: (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0])),
    "RADIAL": (5, lambda p: (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0])),
    "OPENCV": (8, lambda p: (p[0], p[1], p[2], p[3], list(p[4:8]))),
    "FULL_OPENCV": (12, lambda p: (p[0], p[1], p[2], p[3], list(p[4:12]))),
}
PIXEL_CENTRE = 0.5  # COLMAP's pixel (0, 0) spans [0, 1]; OpenCV's is centred on 0


def colmap_model_dir(folder: Path) -> Path | None:
    """The folder holding ``cameras.txt`` and ``images.txt``: ``folder`` itself, ``sparse/0`` or
    ``sparse`` under it (COLMAP's own layout); None when there is none."""
    for sub in COLMAP_MODEL_DIRS:
        d = folder / sub
        if (d / COLMAP_CAMERAS).is_file() and (d / COLMAP_IMAGES).is_file():
            return d
    return None


def camera_from_colmap(fields: list[str]) -> PinholeCamera:
    """One ``cameras.txt`` line, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``, as the pinhole camera
    with OpenCV distortion it describes (principal point moved to OpenCV's pixel centres).
    ValueError saying what is wrong with the line."""
    if len(fields) < 4:
        raise ValueError(f"{len(fields)} fields, expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'")
    model = fields[1].upper()
    if model not in _MODELS:
        raise ValueError(f"camera model {fields[1]} is not a pinhole model with OpenCV distortion ({', '.join(_MODELS)}); "
                         "undistort the images first (colmap image_undistorter writes PINHOLE cameras)")
    count, convert = _MODELS[model]
    params = [finite_float(v, "camera parameter") for v in fields[4:]]
    if len(params) != count:
        raise ValueError(f"{model} has {count} parameters, the line has {len(params)}")
    width, height = int(fields[2]), int(fields[3])
    fx, fy, cx, cy, dist = convert(params)
    if width < 16 or height < 16 or fx <= 0 or fy <= 0:
        raise ValueError(f"implausible camera (size {width}x{height}, fx {fx}, fy {fy})")
    return PinholeCamera(fx, fy, cx - PIXEL_CENTRE, cy - PIXEL_CENTRE, width, height, np.asarray(dist, float))


def read_cameras(path: Path, stats: RecordingStats) -> dict[int, PinholeCamera]:
    """``cameras.txt`` by camera id; a line that is not a usable camera is counted and skipped, and
    when none is usable the first line's reason is the error."""
    cameras: dict[int, PinholeCamera] = {}
    reasons = []
    for line_no, fields in table_rows(path, stats):
        try:
            cameras[int(fields[0])] = camera_from_colmap(fields)
        except ValueError as exc:
            stats.bad_line(path, line_no, str(exc))
            reasons.append(f"line {line_no}: {exc}")
    if not cameras:
        raise RecordingError(f"{path}: " + (reasons[0] if reasons else "no camera (expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]' lines)"))
    return cameras


def read_images(path: Path, stats: RecordingStats) -> list[tuple[int, str, int, np.ndarray, np.ndarray]]:
    """``images.txt``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then its
    2D points (which may be an empty line, and are not read). Returns (line, name, camera id, camera
    centre C (3,), camera-to-world rotation (3, 3)) per usable image."""
    out = []
    points_line_next = False
    with open(path, "rb") as f:
        for line_no, raw in enumerate(f, start=1):
            try:
                text = raw.decode("utf-8").rstrip("\r\n")
            except UnicodeDecodeError:
                stats.bad_line(path, line_no, "not UTF-8 text")
                points_line_next = not points_line_next
                continue
            if text.startswith("#"):
                continue
            if points_line_next:  # the 2D points of the image above, blank or not
                points_line_next = False
                continue
            if not text.strip():
                continue
            points_line_next = True
            fields = text.split()
            try:
                if len(fields) < 10:
                    raise ValueError(f"{len(fields)} fields, expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
                q_wxyz = np.array([finite_float(v, "quaternion") for v in fields[1:5]])
                t = np.array([finite_float(v, "translation") for v in fields[5:8]])
                norm = float(np.linalg.norm(q_wxyz))
                if abs(norm - 1.0) > 1e-3:
                    raise ValueError(f"quaternion norm {norm:.6f} (unit quaternion expected)")
                camera_id = int(fields[8])
            except ValueError as exc:
                stats.bad_line(path, line_no, str(exc))
                continue
            R_cw = quat_to_matrix(q_wxyz / norm)
            out.append((line_no, " ".join(fields[9:]), camera_id, -R_cw.T @ t, R_cw.T))
    return out


def read_times(path: Path, stats: RecordingStats) -> dict[str, float]:
    """``timestamps.txt``: ``timestamp name`` per line (the name as in images.txt)."""
    times: dict[str, float] = {}
    for line_no, fields in table_rows(path, stats):
        try:
            if len(fields) < 2:
                raise ValueError(f"{len(fields)} fields, expected 'timestamp name'")
            times[" ".join(fields[1:])] = finite_float(fields[0], "timestamp")
        except ValueError as exc:
            stats.bad_line(path, line_no, str(exc))
    return times


def open_colmap(folder: Path, nav: NavConfig, overrides: Overrides = Overrides(),
                mount: CameraMount = IDENTITY_MOUNT) -> PoseRecording:
    """A COLMAP text model with ``meta.yaml`` and the images' times beside it (module docstring)."""
    stats = RecordingStats()
    model = colmap_model_dir(folder)
    if model is None:
        raise RecordingError(f"{folder}: no COLMAP text model ({COLMAP_CAMERAS} and {COLMAP_IMAGES} in it, "
                             "sparse/0 or sparse; convert a binary model with colmap model_converter --output_type TXT)")
    meta_path = folder / COLMAP_META
    pm, meta = read_pose_meta(meta_path, COLMAP_META_KEYS, overrides, "a COLMAP world has no up direction, scale or times: "
                              "it declares world_up, scale_m_per_unit and frame_interval_s or a timestamps.txt")
    images_dir = folder / str(meta.get("images_dir", "images"))
    if not images_dir.is_dir():
        raise RecordingError(f"{images_dir}: missing (the images, named as in {model / COLMAP_IMAGES}; "
                             f"meta.yaml images_dir names another folder)")

    cameras_path, images_path = model / COLMAP_CAMERAS, model / COLMAP_IMAGES
    cameras = read_cameras(cameras_path, stats)
    images = read_images(images_path, stats)
    if not images:
        raise RecordingError(f"{images_path}: no usable registered image")
    # One camera per recording: the one most images use; images of another are left out (counted).
    used = Counter(camera_id for _, _, camera_id, _, _ in images)
    camera_id = used.most_common(1)[0][0]
    if camera_id not in cameras:
        raise RecordingError(f"{images_path}: camera {camera_id} is not in {cameras_path}")
    camera = cameras[camera_id]
    kept = []
    for row in images:
        if row[2] == camera_id or (row[2] in cameras and cameras[row[2]] == camera):
            kept.append(row)
        else:
            stats.bad_line(images_path, row[0], f"{row[1]}: camera {row[2]}, the recording's camera is {camera_id} "
                                                "(one camera per recording)")

    times_path = folder / COLMAP_TIMES
    if times_path.is_file():
        times = read_times(times_path, stats)
    elif "frame_interval_s" in meta:
        interval = meta_float(meta, "frame_interval_s", 1.0, 1e-9, meta_path)
        times = {name: k * interval for k, name in enumerate(sorted(row[1] for row in kept))}
    else:
        raise RecordingError(f"{meta_path}: a COLMAP model has no times: give 'frame_interval_s' (images in the "
                             f"order of their names) or a {times_path.name} beside it ('timestamp name' per line)")
    entries, rows = [], []
    for line_no, name, _, centre, R_w_cv in kept:
        if name not in times:
            stats.bad_line(images_path, line_no, f"{name}: no time in {times_path.name}")
            continue
        entries.append((line_no, images_dir / name, times[name], len(entries)))
        rows.append((times[name], centre, R_w_cv))
    if not rows:
        raise RecordingError(f"{times_path}: no time for any registered image of {images_path}")
    frames = sorted_frames(entries, images_path, stats)
    recording = pose_recording(folder, camera, mount, frames, stats, pm, rows, images_path, nav, overrides, "colmap")
    points_path = model / COLMAP_POINTS
    if "ground_alt_m" not in meta and overrides.ground_alt_m is None and points_path.is_file():
        # The ground new features are started on: the model's own sparse points say where it is
        # (their median altitude), where a default of 0 would be the first camera's height with
        # origin: auto, or the geoid's with a geo-referenced one.
        xyz, _, _ = read_points3d(points_path)
        if len(xyz):
            recording.ground_alt_m = float(np.median(-recording.world.position_to_ned(xyz)[:, 2]))
            stats.note(f"{points_path}: ground altitude {recording.ground_alt_m:.2f} m, the median of its {len(xyz)} "
                       "points (meta.yaml ground_alt_m sets another)")
    return recording


def read_points3d(path: str | Path) -> tuple[np.ndarray, int, str]:
    """``points3D.txt`` (``POINT3D_ID X Y Z R G B ERROR TRACK[]``) -> xyz (N, 3) in the model's
    world, the count of malformed lines and the first of them."""
    path = Path(path)
    stats = RecordingStats()
    rows = []
    for line_no, fields in table_rows(path, stats):
        try:
            if len(fields) < 4:
                raise ValueError(f"{len(fields)} fields, expected 'POINT3D_ID X Y Z R G B ERROR TRACK[]'")
            rows.append([finite_float(v, "coordinate") for v in fields[1:4]])
        except ValueError as exc:
            stats.bad_line(path, line_no, str(exc))
    bad = sum(stats.bad_lines.values())
    return np.asarray(rows, float).reshape(-1, 3), bad, (stats.problems[0] if stats.problems else "")


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------


def export_colmap(recording: Recording, out: str | Path, limit: int | None = None) -> dict[str, int]:
    """Write ``recording`` as a COLMAP text model (module docstring) in the NED world (``world_up:
    -z``, north x, scale 1): ``images/`` copied byte for byte, ``sparse/0/{cameras,images,points3D}.txt``
    (one camera, ``OPENCV`` or ``FULL_OPENCV``; no 2D or 3D points), ``timestamps.txt``,
    ``pose_sigmas.txt`` (square roots of each frame's pose-covariance diagonal) and ``meta.yaml``.
    Frames without navigation are left out (counted). Refuses a folder that already holds a model."""
    out = Path(out)
    model = out / "sparse" / "0"
    if (model / COLMAP_IMAGES).exists() or (out / COLMAP_META).exists():
        raise FileExistsError(f"{out} already holds a COLMAP export; choose a new folder")
    c = recording.camera
    dist = np.asarray(c.distortion, float).ravel()
    if dist.size > 8 and np.any(dist[8:]):
        raise ValueError(f"the camera's distortion has {dist.size} coefficients; a COLMAP camera holds at most 8")
    dist = np.r_[dist, np.zeros(8)][:8]
    model_name, params = (("OPENCV", dist[:4]) if not np.any(dist[4:]) else ("FULL_OPENCV", dist))
    (out / "images").mkdir(parents=True, exist_ok=True)
    model.mkdir(parents=True, exist_ok=True)
    counts = {"written": 0, "without_nav": 0, "missing_image": 0}
    with (open(model / COLMAP_IMAGES, "w") as f_img, open(out / COLMAP_TIMES, "w") as f_time,
          open(out / TUM_SIGMAS, "w") as f_sig):
        f_img.write("# Image list with two lines of data per image:\n"
                    "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f_time.write("# timestamp name\n")
        f_sig.write("# timestamp sigma_north_m sigma_east_m sigma_down_m sigma_rot_north_deg sigma_rot_east_deg sigma_rot_down_deg\n")
        for name, ts, centre, R_w_cv, sigmas in exported_frames(recording, out / "images", limit, counts):
            R_cw = R_w_cv.T
            q = matrix_to_quat(R_cw)
            t = -R_cw @ centre
            f_img.write(" ".join([str(counts["written"]), *(repr(float(v)) for v in q), *(repr(float(v)) for v in t),
                                  "1", name]) + "\n\n")
            f_time.write(f"{ts} {name}\n")
            f_sig.write(f"{ts} {sigmas}\n")
    camera_line = [1, model_name, c.width, c.height, c.fx, c.fy, c.cx + PIXEL_CENTRE, c.cy + PIXEL_CENTRE, *params]
    (model / COLMAP_CAMERAS).write_text("# Camera list with one line of data per camera:\n"
                                        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                                        + " ".join(repr(float(v)) if isinstance(v, (float, np.floating)) else str(v)
                                                   for v in camera_line) + "\n")
    (model / COLMAP_POINTS).write_text("# 3D point list with one line of data per point:\n"
                                       "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
    (out / COLMAP_META).write_text(yaml.safe_dump(exported_meta(recording), sort_keys=False))
    return counts
