"""The EuRoC MAV layout (``mav0/cam0/data.csv``, ``mav0/cam0/sensor.yaml``,
``mav0/state_groundtruth_estimate0/data.csv``; docs/replay.md)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import NavConfig
from companion.desk.recordings.poses import PoseRecording, PoseTable, camera_from_mapping, sorted_poses
from companion.desk.recordings.recording import (
    IDENTITY_MOUNT,
    Overrides,
    RecordingError,
    RecordingStats,
    WorldFrame,
    camera_pose_from_opencv,
    finite_float,
    pose_covariance,
    read_yaml,
    sorted_frames,
    table_rows,
)
from companion.method.geometry import CameraMount, quat_to_matrix

EUROC_CAM_CSV = "mav0/cam0/data.csv"
EUROC_CAM_DIR = "mav0/cam0/data"
EUROC_CAM_YAML = "mav0/cam0/sensor.yaml"
EUROC_GROUNDTRUTH = "mav0/state_groundtruth_estimate0/data.csv"


EUROC_WORLD = WorldFrame("z", "x", 1.0)  # EuRoC's Vicon / Leica frame: z up (gravity aligned)


def euroc_root(path: Path) -> Path:
    """The folder holding ``mav0`` (the argument may be that folder or ``mav0`` itself)."""
    return path.parent if path.name == "mav0" else path


def _matrix_4x4(value: Any, where: Path) -> np.ndarray:
    data = value.get("data") if isinstance(value, dict) else value
    try:
        T = np.asarray(data, dtype=float).reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: T_BS must hold 16 numbers (row-major 4x4): {exc}") from exc
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or np.max(np.abs(R @ R.T - np.eye(3))) > 1e-3 or np.linalg.det(R) < 0:
        raise RecordingError(f"{where}: T_BS rotation is not a rotation matrix")
    return T


def open_euroc(path: Path, nav: NavConfig, overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> PoseRecording:
    """EuRoC MAV: ``cam0`` images and ``state_groundtruth_estimate0`` poses of the body (IMU) frame,
    composed with the camera's ``T_BS`` (camera -> body) into camera poses. Times are nanoseconds;
    they are counted from the first camera timestamp so seconds keep full precision."""
    root = euroc_root(path)
    stats = RecordingStats()
    where = root / EUROC_CAM_YAML
    if not where.is_file():
        raise RecordingError(f"{where}: missing (camera intrinsics, distortion, resolution and T_BS)")
    sensor = read_yaml(where)
    model = str(sensor.get("camera_model", "pinhole"))
    dist_model = str(sensor.get("distortion_model", "radial-tangential"))
    if model != "pinhole" or dist_model not in ("radial-tangential", "radtan", "none"):
        raise RecordingError(f"{where}: camera_model {model!r} / distortion_model {dist_model!r} (pinhole radial-tangential supported)")
    try:
        fu, fv, cu, cv_ = (float(v) for v in sensor["intrinsics"])
        width, height = (int(v) for v in sensor["resolution"])
        dist = [float(v) for v in sensor.get("distortion_coefficients", [0, 0, 0, 0])]
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"{where}: need intrinsics [fu, fv, cu, cv], resolution [w, h], distortion_coefficients: {exc}") from exc
    camera = camera_from_mapping({"width": width, "height": height, "fx": fu, "fy": fv, "cx": cu, "cy": cv_,
                                   "distortion": dist if dist_model != "none" else [0.0] * 4}, where)
    T_bc = _matrix_4x4(sensor.get("T_BS"), where) if "T_BS" in sensor else np.eye(4)

    cam_csv = root / EUROC_CAM_CSV
    if not cam_csv.is_file():
        raise RecordingError(f"{cam_csv}: missing (timestamp [ns], filename per image)")
    raw: list[tuple[int, int, str]] = []
    for line_no, fields in table_rows(cam_csv, stats, sep=","):
        try:
            if len(fields) < 2 or not fields[1]:
                raise ValueError("expected 'timestamp [ns], filename'")
            raw.append((line_no, int(fields[0]), fields[1]))
        except ValueError as exc:
            stats.bad_line(cam_csv, line_no, str(exc))
    if not raw:
        raise RecordingError(f"{cam_csv}: no usable image line")
    ns0 = min(r[1] for r in raw)
    frames = sorted_frames([(ln, root / EUROC_CAM_DIR / name, (ns - ns0) * 1e-9, k) for k, (ln, ns, name) in enumerate(raw)],
                            cam_csv, stats)

    gt_path = root / EUROC_GROUNDTRUTH
    if not gt_path.is_file():
        raise RecordingError(f"{gt_path}: missing (replay needs the ground-truth poses)")
    t, p, R = [], [], []
    R_sc, t_sc = T_bc[:3, :3], T_bc[:3, 3]
    for line_no, fields in table_rows(gt_path, stats, sep=","):
        try:
            if len(fields) < 8:
                raise ValueError(f"{len(fields)} fields, expected timestamp, p_RS_R xyz, q_RS_R wxyz, ...")
            ns = int(fields[0])
            values = [finite_float(v, "value") for v in fields[1:8]]
            q = np.asarray(values[3:7])
            norm = float(np.linalg.norm(q))
            if abs(norm - 1.0) > 1e-3:
                raise ValueError(f"quaternion norm {norm:.6f} (unit quaternion expected)")
            R_rs = quat_to_matrix(q)
            # Camera pose in the world R: T_RC = T_RS T_SC (the body B of cam0's T_BS is the IMU S).
            p_c, R_nc = camera_pose_from_opencv(np.asarray(values[:3]) + R_rs @ t_sc, R_rs @ R_sc, EUROC_WORLD)
        except ValueError as exc:
            stats.bad_line(gt_path, line_no, str(exc))
            continue
        t.append((ns - ns0) * 1e-9)
        p.append(p_c)
        R.append(R_nc)
    tt, pp, qq = sorted_poses(t, p, R, gt_path, stats)
    sigma_m = overrides.pose_sigma_m if overrides.pose_sigma_m is not None else 0.02
    sigma_deg = overrides.pose_sigma_deg if overrides.pose_sigma_deg is not None else 0.2
    covariance = pose_covariance(np.full(3, sigma_m), np.full(3, math.radians(sigma_deg)))
    table = PoseTable(tt, pp, qq, covariance, mount, nav.buffer_max_gap_s, nav.buffer_extrapolate_s, "euroc")
    ground = overrides.ground_alt_m if overrides.ground_alt_m is not None else 0.0
    return PoseRecording(root, camera, mount, frames, stats, world=EUROC_WORLD, ground_alt_m=ground, poses=table)
