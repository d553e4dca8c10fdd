"""Synthetic recordings for the replay tests: one simulated flight rendered with the project's
renderer over the ``flat`` scenario, written in each layout ``companion replay`` reads.

The flight: 15 m above the ground, north at 6 m/s, camera on the default mount (45 deg down), a
gentle roll/pitch/lateral wobble so attitude and position both vary. Frames at 10 Hz.
"""

from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.config import CompanionConfig, replace
from companion.desk.recordings.recording import WorldFrame, camera_pose_to_opencv
from companion.method.geometry import PinholeCamera, camera_from_config, euler_to_matrix, matrix_to_quat
from companion.method.messages import Frame
from drivers.clock import Clock
from drivers.sim.renderer import Renderer, RenderOptions
from drivers.sim.world import World

RATE_HZ = 10.0
N_FRAMES = 60
SPEED_MPS = 6.0
ALTITUDE_M = 15.0
START_NORTH_M = 10.0
DISTORTION = (-0.12, 0.05, 0.001, -0.0005, 0.0)


def body_pose(t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True body position (3,) and R_nb (3, 3) at flight time t (s)."""
    t = float(t)
    p = np.array([START_NORTH_M + SPEED_MPS * t, 0.3 * math.sin(0.7 * t), -ALTITUDE_M + 0.2 * math.sin(0.5 * t)])
    R = euler_to_matrix(math.radians(2.0) * math.sin(1.3 * t), math.radians(1.5) * math.sin(0.9 * t), math.radians(3.0) * math.sin(0.4 * t))
    return p, R


@dataclass(frozen=True)
class Flight:
    """Frames and true poses: t (N,) flight time; p (N, 3), R_nb (N, 3, 3) body; p_c, R_nc camera."""

    t: np.ndarray
    p: np.ndarray
    R_nb: np.ndarray
    p_c: np.ndarray
    R_nc: np.ndarray
    images: tuple[np.ndarray, ...]
    camera: PinholeCamera
    cfg: CompanionConfig

    @property
    def mount(self):
        return camera_from_config(self.cfg.camera)[1]


@functools.lru_cache(maxsize=2)
def world() -> World:
    return World.load("flat")


def flight(distorted: bool = False, n_frames: int = N_FRAMES) -> Flight:
    """The first ``n_frames`` of the flight (rendered once per process and lens: the renderer
    build costs about a second)."""
    full = _full_flight(distorted)
    if n_frames >= len(full.t):
        return full
    k = slice(0, n_frames)
    return Flight(full.t[k], full.p[k], full.R_nb[k], full.p_c[k], full.R_nc[k], full.images[k], full.camera, full.cfg)


@functools.lru_cache(maxsize=2)
def _full_flight(distorted: bool) -> Flight:
    n_frames = N_FRAMES
    # The recording's configuration (meta.yaml of a --record folder): navigation floors that
    # match the simulated autopilot's accuracy, as an operator would set them.
    cfg = replace(CompanionConfig(), **{"nav.position_sigma_floor_m": 0.05, "nav.attitude_sigma_floor_deg": 0.2})
    if distorted:
        cfg = replace(cfg, **{"camera.distortion": DISTORTION})
    camera, mount = camera_from_config(cfg.camera)
    renderer = Renderer(world(), camera, RenderOptions(noise_sigma=2.0, seed=5))
    t = np.arange(n_frames) / RATE_HZ
    poses = [body_pose(tk) for tk in t]
    p = np.array([q[0] for q in poses])
    R = np.array([q[1] for q in poses])
    cam = [mount.camera_pose(pk, Rk) for pk, Rk in zip(p, R)]
    p_c = np.array([c[0] for c in cam])
    R_nc = np.array([c[1] for c in cam])
    images = tuple(renderer.render(pc, Rc) for pc, Rc in zip(p_c, R_nc))
    return Flight(t, p, R, p_c, R_nc, images, camera, cfg)


def camera_yaml(camera: PinholeCamera) -> dict:
    return {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "distortion": [float(d) for d in camera.distortion]}


# --------------------------------------------------------------------------------------------
# TUM folder
# --------------------------------------------------------------------------------------------


def write_tum(folder: Path, f: Flight, frame: WorldFrame, *, t0: float = 1000.0, image_ext: str = ".png",
              sigmas: str | None = None, meta_extra: dict | None = None) -> Path:
    """Images + poses.txt (camera-to-world, OpenCV axes, in ``frame``) + camera.yaml + meta.yaml.
    ``sigmas`` = "iso" or "axes" also writes pose_sigmas.txt in that form."""
    (folder / "images").mkdir(parents=True)
    img_lines, pose_lines, sigma_lines = [], [], []
    for k, (tk, pc, Rc, image) in enumerate(zip(f.t, f.p_c, f.R_nc, f.images)):
        name = f"images/{k:04d}{image_ext}"
        cv2.imwrite(str(folder / name), image)
        t_w, R_w_cv = camera_pose_to_opencv(pc, Rc, frame)
        q = matrix_to_quat(R_w_cv)
        ts = repr(t0 + float(tk))
        img_lines.append(f"{ts} {name}")
        pose_lines.append(" ".join([ts, *map(repr, map(float, t_w)), *map(repr, map(float, (q[1], q[2], q[3], q[0])))]))
        if sigmas == "iso":
            sigma_lines.append(f"{ts} 0.05 0.3")
        elif sigmas == "axes":
            sigma_lines.append(f"{ts} 0.01 0.02 0.03 0.1 0.2 0.3")
    (folder / "images.txt").write_text("# timestamp filename\n" + "\n".join(img_lines) + "\n")
    (folder / "poses.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(pose_lines) + "\n")
    if sigma_lines:
        (folder / "pose_sigmas.txt").write_text("\n".join(sigma_lines) + "\n")
    (folder / "camera.yaml").write_text(yaml.safe_dump(camera_yaml(f.camera)))
    def axis(a):
        return list(a) if isinstance(a, tuple) else a

    meta = {"world_up": axis(frame.up), "world_north": axis(frame.north), "scale_m_per_unit": frame.scale_m_per_unit,
            "pose_sigma_m": 0.05, "pose_sigma_deg": 0.2, **(meta_extra or {})}
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    return folder


# --------------------------------------------------------------------------------------------
# COLMAP text model
# --------------------------------------------------------------------------------------------


def write_colmap(folder: Path, f: Flight, frame: WorldFrame, *, model_dir: str = "sparse/0", interval_s: float | None = None,
                 points_xyz: np.ndarray | None = None, meta_extra: dict | None = None) -> Path:
    """A COLMAP text model as ``colmap model_converter --output_type TXT`` writes one, independently
    of the reader: world-to-camera poses (``QW QX QY QZ TX TY TZ``), a PINHOLE camera (or OPENCV with
    distortion) with its principal point on COLMAP's pixel centres (+0.5), two lines per image (the
    2D points line left empty), ``points3D.txt`` holding ``points_xyz`` (world units), and the
    meta.yaml the reader needs; times from ``interval_s`` (meta.yaml) or a timestamps.txt."""
    model = folder / model_dir
    model.mkdir(parents=True)
    (folder / "images").mkdir()
    c = f.camera
    dist = [float(d) for d in np.asarray(c.distortion).ravel()]
    if any(dist):
        camera = f"1 OPENCV {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx + 0.5!r} {c.cy + 0.5!r} " + " ".join(map(repr, dist[:4]))
    else:
        camera = f"1 PINHOLE {c.width} {c.height} {c.fx!r} {c.fy!r} {c.cx + 0.5!r} {c.cy + 0.5!r}"
    (model / "cameras.txt").write_text("# Camera list with one line of data per camera:\n" + camera + "\n")
    lines, times = ["# Image list with two lines of data per image:"], []
    for k, (tk, pc, Rc, image) in enumerate(zip(f.t, f.p_c, f.R_nc, f.images)):
        name = f"DJI_{k + 1:04d}.png"
        cv2.imwrite(str(folder / "images" / name), image)
        centre, R_w_cv = camera_pose_to_opencv(pc, Rc, frame)
        R_cw = R_w_cv.T
        q = matrix_to_quat(R_cw)  # w, x, y, z
        t = -R_cw @ centre
        lines += [" ".join([str(k + 1), *map(repr, map(float, q)), *map(repr, map(float, t)), "1", name]), ""]
        times.append(f"{100.0 + float(tk)!r} {name}")
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    pts = np.zeros((0, 3)) if points_xyz is None else np.asarray(points_xyz, float)
    (model / "points3D.txt").write_text("# 3D point list with one line of data per point:\n" + "".join(
        f"{k + 1} {x!r} {y!r} {z!r} 128 128 128 0.5 1 0 2 0\n" for k, (x, y, z) in enumerate(pts.tolist())))
    if interval_s is None:
        (folder / "timestamps.txt").write_text("\n".join(times) + "\n")

    def axis(a):
        return list(a) if isinstance(a, tuple) else a

    meta = {"world_up": axis(frame.up), "world_north": axis(frame.north), "scale_m_per_unit": frame.scale_m_per_unit,
            "pose_sigma_m": 0.05, "pose_sigma_deg": 0.2, **({"frame_interval_s": interval_s} if interval_s else {}),
            **(meta_extra or {})}
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    return folder


# --------------------------------------------------------------------------------------------
# EuRoC MAV
# --------------------------------------------------------------------------------------------

EUROC_R_SC = euler_to_matrix(math.radians(1.0), math.radians(-2.0), math.radians(90.0))  # camera -> IMU body
EUROC_T_SC = np.array([0.05, -0.02, 0.01])
EUROC_NS0 = 1_403_636_579_763_555_584  # a EuRoC-like epoch (ns)


def write_euroc(root: Path, f: Flight, *, gt_rate_hz: float = 40.0, gt_offset_s: float = 0.0123) -> Path:
    """mav0/cam0 (data.csv, data/*.png, sensor.yaml with T_BS) and the ground-truth body poses at
    ``gt_rate_hz``, sampled between the frame times (so replay must interpolate)."""
    world_frame = WorldFrame("z", "x", 1.0)
    cam_dir = root / "mav0" / "cam0" / "data"
    cam_dir.mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for tk, image in zip(f.t, f.images):
        ns = EUROC_NS0 + int(round(tk * 1e9))
        cv2.imwrite(str(cam_dir / f"{ns}.png"), image)
        lines.append(f"{ns},{ns}.png")
    (root / "mav0" / "cam0" / "data.csv").write_text("\n".join(lines) + "\n")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = EUROC_R_SC, EUROC_T_SC
    c = f.camera
    sensor = (
        "%YAML:1.0\n"  # as OpenCV writes it; not valid YAML, the reader must cope
        "sensor_type: camera\ncomment: synthetic cam0\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{', '.join(repr(float(v)) for v in T.ravel())}]\n"
        f"rate_hz: {RATE_HZ}\nresolution: [{c.width}, {c.height}]\ncamera_model: pinhole\n"
        f"intrinsics: [{c.fx}, {c.fy}, {c.cx}, {c.cy}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(repr(float(d)) for d in np.asarray(c.distortion)[:4])}]\n"
    )
    (root / "mav0" / "cam0" / "sensor.yaml").write_text(sensor)
    mount = f.mount
    gt = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
          "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
          "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    t_gt = np.arange(-0.2 + gt_offset_s, f.t[-1] + 0.2, 1.0 / gt_rate_hz)
    for tk in t_gt:
        p, R = body_pose(tk)
        p_c, R_nc = mount.camera_pose(p, R)
        p_w, R_w_cv = camera_pose_to_opencv(p_c, R_nc, world_frame)  # camera in EuRoC's world
        R_rs = R_w_cv @ EUROC_R_SC.T
        p_rs = p_w - R_rs @ EUROC_T_SC
        q = matrix_to_quat(R_rs)
        ns = EUROC_NS0 + int(round(tk * 1e9))
        gt.append(",".join([str(ns), *map(repr, map(float, p_rs)), *map(repr, map(float, q)), *["0.0"] * 9]))
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    (gt_dir / "data.csv").write_text("\n".join(gt) + "\n")
    return root


# --------------------------------------------------------------------------------------------
# The service's own recording: FrameRecorder + a tlog written with pymavlink
# --------------------------------------------------------------------------------------------

BOOT_AT_START_S = 50.0  # autopilot uptime when the recording starts
NAV_RATE_HZ = 50.0
LINK_DELAY_S = 0.002  # one way


def write_companion(folder: Path, f: Flight, *, frames_after_s: float = 1.0, telemetry_until_s: float | None = None) -> Path:
    """A ``--record`` folder: frames through :class:`FrameRecorder` (times = recording start +
    ``frames_after_s`` + flight time), and ``telemetry.tlog`` with what an ArduPilot link delivers:
    HEARTBEAT and SYSTEM_TIME at 1 Hz, TIMESYNC answers to our (companion-clock) requests, and
    LOCAL_POSITION_NED + ATTITUDE_QUATERNION at 50 Hz from the true body trajectory, received
    2 ms after they were sent. ``telemetry_until_s``: flight time at which the log stops."""
    from drivers.cameras.recorder import FrameRecorder

    recorder = FrameRecorder.from_config(folder, f.cfg, clock=Clock())
    recorder.start()
    clock = recorder.meta["clock"]
    t_s0, unix0 = float(clock["t_s"]), float(clock["unix_time_s"])
    t_fly0 = t_s0 + frames_after_s  # companion time of flight time 0
    for k, (tk, image) in enumerate(zip(f.t, f.images)):
        recorder.submit(Frame(t_fly0 + float(tk), image, k, "synthetic"))
    recorder.close()

    offset = t_s0 - BOOT_AT_START_S  # companion - autopilot boot clock
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    records: list[tuple[float, bytes]] = []

    def log(t_rx: float, msg) -> None:
        records.append((t_rx, msg.pack(mav)))

    end = f.t[-1] + 0.5 if telemetry_until_s is None else telemetry_until_s
    n = int(math.floor((frames_after_s + end) * NAV_RATE_HZ)) + 1
    for i in range(n):
        t_c = t_s0 + i / NAV_RATE_HZ  # companion time the autopilot's sample is valid
        boot_ms = int(round((t_c - offset) * 1000.0))
        if i % int(NAV_RATE_HZ) == 0:
            log(t_c + LINK_DELAY_S, mav.heartbeat_encode(2, 3, 0, 4, 4))
            log(t_c + LINK_DELAY_S, mav.system_time_encode(int((unix0 + t_c - t_s0) * 1e6), boot_ms))
            sent = t_c - 0.01  # our TIMESYNC request; the answer arrives 2 x 2 ms later
            tc1 = int(round((sent + LINK_DELAY_S - offset) * 1e9))
            log(sent + 2 * LINK_DELAY_S, mav.timesync_encode(tc1, int(sent * 1e9) + 1))
        p, R = body_pose(t_c - t_fly0)
        v = np.array([SPEED_MPS, 0.0, 0.0])
        q = matrix_to_quat(R)
        log(t_c + LINK_DELAY_S, mav.local_position_ned_encode(boot_ms, *map(float, p), *map(float, v)))
        log(t_c + LINK_DELAY_S, mav.attitude_quaternion_encode(boot_ms, *map(float, q), 0.0, 0.0, 0.0))
    records.sort(key=lambda r: r[0])
    with open(folder / "telemetry.tlog", "wb") as out:
        for t_rx, packet in records:
            out.write(struct.pack(">Q", int(round((unix0 + (t_rx - t_s0)) * 1e6))) + packet)
    return folder


# --------------------------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------------------------


def truth_csv(path: Path, north: tuple[float, float], east: tuple[float, float], cell_m: float = 1.0, shift_m: float = 0.0) -> Path:
    """The true surface as a DSM grid CSV (x north, y east, z altitude up) at cell centres."""
    h = world().true_height_grid(north[0], east[0], north[1], east[1], cell_m) + shift_m
    xs = north[0] + (np.arange(h.shape[0]) + 0.5) * cell_m
    ys = east[0] + (np.arange(h.shape[1]) + 0.5) * cell_m
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    rows = np.column_stack([X.ravel(), Y.ravel(), h.ravel()])
    path.write_text("x,y,z\n" + "\n".join(f"{x!r},{y!r},{z!r}" for x, y, z in rows.tolist()) + "\n")
    return path
