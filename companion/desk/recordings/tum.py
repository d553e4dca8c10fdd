"""The TUM folder layout, read (:func:`open_tum`) and written (:func:`export_tum`) (docs/replay.md):
images with camera poses in TUM trajectory format (``timestamp tx ty tz qx qy qz qw``,
camera-to-world, OpenCV camera axes) plus ``camera.yaml`` (intrinsics, OpenCV distortion, size) and
``meta.yaml`` (the world's up axis, metric scale, pose uncertainty); ``pose_sigmas.txt`` gives
per-frame uncertainty when present.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from companion.config import NavConfig
from companion.desk.recordings.poses import PoseRecording, PoseTable, camera_from_mapping, sorted_poses
from companion.desk.recordings.recording import (
    IDENTITY_MOUNT,
    Overrides,
    Recording,
    RecordingError,
    RecordingStats,
    WorldFrame,
    camera_pose_from_opencv,
    camera_pose_to_opencv,
    check_keys,
    finite_float,
    first_existing,
    pose_covariance,
    read_yaml,
    sorted_frames,
    table_rows,
)
from companion.method.geometry import CameraMount, PinholeCamera, matrix_to_quat, quat_to_matrix

# TUM folder file names (the first that exists is used).
TUM_IMAGES = ("images.txt", "rgb.txt")
TUM_POSES = ("poses.txt", "groundtruth.txt")
TUM_CAMERA = "camera.yaml"
TUM_META = "meta.yaml"
TUM_SIGMAS = "pose_sigmas.txt"

TUM_META_KEYS = ("world_up", "world_north", "scale_m_per_unit", "origin", "pose_sigma_m", "pose_sigma_deg",
                 "ground_alt_m", "association_s", "source")


def meta_origin(meta: dict, where: Path) -> tuple[float, float, float] | None:
    """meta.yaml ``origin``: three numbers (world units), ``auto`` (None: the first pose's position) or
    absent (zero)."""
    value = meta.get("origin", [0.0, 0.0, 0.0])
    if isinstance(value, str) and value.strip().lower() == "auto":
        return None
    try:
        origin = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        origin = ()
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise RecordingError(f"{where}: 'origin' must be three numbers in world units, or 'auto' (the first pose), got {value!r}")
    return origin


def _sigmas(text: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """``sp sa`` (isotropic) or ``spx spy spz sax say saz`` -> (3,) m, (3,) rad; attitude in degrees."""
    values = [finite_float(v, "sigma") for v in text]
    if any(v < 0 for v in values):
        raise ValueError("sigmas must be >= 0")
    if len(values) == 2:
        return np.full(3, values[0]), np.full(3, math.radians(values[1]))
    if len(values) == 6:
        return np.asarray(values[:3]), np.radians(values[3:])
    raise ValueError(f"{len(values)} sigma values (2 or 6 expected)")


def read_sigmas(path: Path, world: WorldFrame, stats: RecordingStats) -> dict[float, np.ndarray]:
    """``pose_sigmas.txt``: per-frame pose covariance (9, 9) by timestamp; sigmas about the world's
    axes (:func:`_sigmas`), rotated into NED by the world frame."""
    frame_cov: dict[float, np.ndarray] = {}
    for line_no, fields in table_rows(path, stats):
        try:
            ts = finite_float(fields[0], "timestamp")
            sp, sa = _sigmas(fields[1:])
        except (ValueError, IndexError) as exc:
            stats.bad_line(path, line_no, str(exc))
            continue
        frame_cov[ts] = pose_covariance(sp, sa, world.A)
    return frame_cov


def meta_float(meta: dict, key: str, default: float, lo: float, where: Path) -> float:
    value = meta.get(key, default)
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: '{key}' must be a number, got {value!r}") from exc
    if not math.isfinite(value) or value < lo:
        raise RecordingError(f"{where}: '{key}' = {value} must be finite and >= {lo}")
    return value


@dataclass(frozen=True, slots=True)
class PoseMeta:
    """What a pose-given layout's ``meta.yaml`` declares (docs/replay.md): the world frame (its
    origin still to be set when ``origin_auto``), the pose sigmas, the ground altitude and the
    association window of per-frame sigmas; command-line overrides already applied."""

    world: WorldFrame
    origin_auto: bool
    sigma_m: float
    sigma_deg: float
    ground_alt_m: float
    association_s: float


def read_pose_meta(meta_path: Path, known_keys: tuple[str, ...], overrides: Overrides, missing_hint: str) -> tuple[PoseMeta, dict]:
    """Read and check a ``meta.yaml`` with the keys of the TUM layout (and a layout's own, in
    ``known_keys``); returns what it declares and the mapping itself. RecordingError naming the
    file when it is missing (with ``missing_hint``), has an unknown key or a bad value."""
    if not meta_path.is_file():
        raise RecordingError(f"{meta_path}: missing ({missing_hint}; see docs/replay.md)")
    meta = read_yaml(meta_path)
    check_keys(meta, known_keys, meta_path)
    if "world_up" not in meta or "scale_m_per_unit" not in meta:
        raise RecordingError(f"{meta_path}: must declare 'world_up' (x, -x, y, -y, z, -z or a direction [x, y, z]) and 'scale_m_per_unit'")
    origin = meta_origin(meta, meta_path)
    try:
        world = WorldFrame.from_up(meta["world_up"], meta.get("world_north"), meta_float(meta, "scale_m_per_unit", 1.0, 1e-12, meta_path),
                                   origin if origin is not None else (0.0, 0.0, 0.0))
    except RecordingError as exc:
        text = str(exc)
        raise RecordingError(text if text.startswith(str(meta_path)) else f"{meta_path}: {text}") from None
    sigma_m = overrides.pose_sigma_m if overrides.pose_sigma_m is not None else meta_float(meta, "pose_sigma_m", 0.02, 0.0, meta_path)
    sigma_deg = overrides.pose_sigma_deg if overrides.pose_sigma_deg is not None else meta_float(meta, "pose_sigma_deg", 0.2, 0.0, meta_path)
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else meta_float(meta, "ground_alt_m", 0.0, -1e6, meta_path)
    association_s = meta_float(meta, "association_s", 0.02, 0.0, meta_path)
    return PoseMeta(world, origin is None, sigma_m, sigma_deg, ground, association_s), meta


def pose_recording(folder: Path, camera: PinholeCamera, mount: CameraMount, frames: list, stats: RecordingStats,
                   pm: PoseMeta, rows: list[tuple[float, np.ndarray, np.ndarray]], poses_path: Path, nav: NavConfig,
                   overrides: Overrides, source: str) -> PoseRecording:
    """A pose-given recording from its camera poses ``rows`` = (t, camera centre in world units (3,),
    camera-to-world rotation with OpenCV axes (3, 3)) read from ``poses_path``: the world's origin
    set to the earliest pose when ``origin: auto``, the poses converted to NED and the paper camera
    frame, and the per-frame sigmas of ``pose_sigmas.txt`` unless the command line gave sigmas."""
    world = pm.world
    if pm.origin_auto and rows:  # origin: auto, the earliest pose's position
        world = replace(world, origin=tuple(float(v) for v in min(rows, key=lambda r: r[0])[1]))
    t, p, R = [], [], []
    for t_k, xyz, R_w_cv in rows:
        p_c, R_nc = camera_pose_from_opencv(xyz, R_w_cv, world)
        t.append(t_k)
        p.append(p_c)
        R.append(R_nc)
    tt, pp, qq = sorted_poses(t, p, R, poses_path, stats)
    covariance = pose_covariance(np.full(3, pm.sigma_m), np.full(3, math.radians(pm.sigma_deg)))
    table = PoseTable(tt, pp, qq, covariance, mount, nav.buffer_max_gap_s, nav.buffer_extrapolate_s, source)
    sigmas_path = folder / TUM_SIGMAS
    frame_cov = (read_sigmas(sigmas_path, world, stats)
                 if sigmas_path.is_file() and overrides.pose_sigma_m is None and overrides.pose_sigma_deg is None else {})
    return PoseRecording(folder, camera, mount, frames, stats, world=world, ground_alt_m=pm.ground_alt_m, poses=table,
                         frame_covariances=frame_cov, association_s=pm.association_s)


def open_tum(folder: Path, nav: NavConfig, overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> PoseRecording:
    """A TUM-style folder: ``meta.yaml``, ``camera.yaml``, ``images.txt`` (or ``rgb.txt``),
    ``poses.txt`` (or ``groundtruth.txt``) and optionally ``pose_sigmas.txt`` (docs/replay.md)."""
    stats = RecordingStats()
    pm, _ = read_pose_meta(folder / TUM_META, TUM_META_KEYS, overrides, "it declares world_up and scale_m_per_unit")
    camera_path = folder / TUM_CAMERA
    if not camera_path.is_file():
        raise RecordingError(f"{camera_path}: missing (width, height, fx, fy, cx, cy, distortion)")
    camera = camera_from_mapping(read_yaml(camera_path), camera_path)

    images = first_existing(folder, TUM_IMAGES)
    entries: list[tuple[int, Path, float, int]] = []
    if images is not None:
        for line_no, fields in table_rows(images, stats):
            try:
                if len(fields) < 2:
                    raise ValueError(f"{len(fields)} fields, expected 'timestamp filename'")
                entries.append((line_no, folder / fields[1], finite_float(fields[0], "timestamp"), len(entries)))
            except ValueError as exc:
                stats.bad_line(images, line_no, str(exc))
        source = images
    else:  # TUM RGB-D style: images/<timestamp>.png
        source = folder / "images"
        if not source.is_dir():
            raise RecordingError(f"{folder}: neither {' nor '.join(TUM_IMAGES)} nor an images/ folder of <timestamp>.<ext> files")
        for k, path in enumerate(sorted(p for p in source.iterdir() if p.is_file())):
            try:
                entries.append((k + 1, path, finite_float(path.stem, "timestamp"), k))
            except ValueError:
                stats.bad_line(source, k + 1, f"{path.name}: file name is not a timestamp")
    frames = sorted_frames(entries, source, stats)

    poses_path = first_existing(folder, TUM_POSES)
    if poses_path is None:
        raise RecordingError(f"{folder}: no pose file ({' or '.join(TUM_POSES)})")
    rows = []
    for line_no, fields in table_rows(poses_path, stats):
        try:
            if len(fields) != 8:
                raise ValueError(f"{len(fields)} fields, expected 'timestamp tx ty tz qx qy qz qw'")
            values = [finite_float(v, "value") for v in fields]
            q_xyzw = np.asarray(values[4:8])
            norm = float(np.linalg.norm(q_xyzw))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"quaternion norm {norm:.6f} (unit quaternion expected)")
        except ValueError as exc:
            stats.bad_line(poses_path, line_no, str(exc))
            continue
        rows.append((values[0], np.asarray(values[1:4]), quat_to_matrix(np.r_[q_xyzw[3], q_xyzw[:3]])))
    return pose_recording(folder, camera, mount, frames, stats, pm, rows, poses_path, nav, overrides, "tum")


# --------------------------------------------------------------------------------------------
# Export to the TUM folder form
# --------------------------------------------------------------------------------------------


def exported_frames(recording: Recording, images_dir: Path, limit: int | None, counts: dict[str, int]):
    """The frames an export writes, each image copied byte for byte to ``images_dir/NNNNNN.<ext>``:
    yields (file name, time as text, camera centre (3,) and camera-to-world rotation with OpenCV
    axes (3, 3) in the NED world, the pose sigmas as text: the square roots of the covariance
    diagonal, north east down in metres then about north east down in degrees). Frames without
    navigation or image are counted in ``counts`` and left out."""
    world = WorldFrame()
    for s in recording.samples(load_images=False, limit=limit):
        if s.nav is None:
            counts["without_nav"] += 1
            continue
        if not s.image_path.is_file():
            counts["missing_image"] += 1
            continue
        name = f"{counts['written']:06d}{s.image_path.suffix.lower()}"
        shutil.copyfile(s.image_path, images_dir / name)
        p_c, R_nc = recording.mount.camera_pose(s.nav.position_ned_m, s.nav.R_nb)
        t_w, R_w_cv = camera_pose_to_opencv(p_c, R_nc, world)
        sig = np.sqrt(np.clip(np.diag(s.nav.pose_covariance), 0.0, None))
        sigmas = " ".join([*(repr(float(v)) for v in sig[:3]), *(repr(float(math.degrees(v))) for v in sig[3:])])
        counts["written"] += 1
        yield name, repr(float(s.t_s)), t_w, R_w_cv, sigmas


def export_tum(recording: Recording, out: str | Path, limit: int | None = None) -> dict[str, int]:
    """Write ``recording`` as a TUM folder (docs/replay.md): the images copied byte for byte, the
    camera poses (camera-to-world, OpenCV axes) in the NED world (``world_up: -z``, north x, scale
    1), per-frame sigmas from the diagonal of each frame's pose covariance, ``camera.yaml`` and
    ``meta.yaml``. Frames without navigation are left out (counted). Refuses a folder that already
    holds poses. Returns counts."""
    out = Path(out)
    if (out / TUM_POSES[0]).exists() or (out / TUM_META).exists():
        raise FileExistsError(f"{out} already holds a TUM export; choose a new folder")
    (out / "images").mkdir(parents=True, exist_ok=True)
    counts = {"written": 0, "without_nav": 0, "missing_image": 0}
    with open(out / TUM_IMAGES[0], "w") as f_img, open(out / TUM_POSES[0], "w") as f_pose, open(out / TUM_SIGMAS, "w") as f_sig:
        f_img.write("# timestamp filename\n")
        f_pose.write("# timestamp tx ty tz qx qy qz qw (camera-to-world, OpenCV camera axes, NED world)\n")
        f_sig.write("# timestamp sigma_north_m sigma_east_m sigma_down_m sigma_rot_north_deg sigma_rot_east_deg sigma_rot_down_deg\n")
        for name, t, t_w, R_w_cv, sigmas in exported_frames(recording, out / "images", limit, counts):
            q = matrix_to_quat(R_w_cv)
            f_img.write(f"{t} images/{name}\n")
            f_pose.write(" ".join([t, *(repr(float(v)) for v in t_w), *(repr(float(v)) for v in (q[1], q[2], q[3], q[0]))]) + "\n")
            f_sig.write(f"{t} {sigmas}\n")
    c = recording.camera
    camera = {"width": c.width, "height": c.height, "fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy),
              "distortion": [float(d) for d in np.asarray(c.distortion).ravel()]}
    (out / TUM_CAMERA).write_text(yaml.safe_dump(camera, sort_keys=False))
    (out / TUM_META).write_text(yaml.safe_dump(exported_meta(recording), sort_keys=False))
    return counts


def exported_meta(recording: Recording) -> dict:
    """The ``meta.yaml`` of an export: the NED world (``world_up: -z``, north x, scale 1), the
    recording's ground altitude, default sigmas (each frame's own are in ``pose_sigmas.txt``) and
    where it came from."""
    return {
        "world_up": "-z", "world_north": "x", "scale_m_per_unit": 1.0,
        "ground_alt_m": recording.ground_alt_m,
        "pose_sigma_m": 0.02, "pose_sigma_deg": 0.2,
        "source": {"kind": recording.kind, "path": str(recording.path)},
    }  # fmt: skip
