"""Reading recordings for replay (companion/desk/recordings/): frame conventions, the three layouts,
damage counting, export to the TUM form, and black borders in the images they deliver."""

from __future__ import annotations

import math
import shutil

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

import replay_synthetic as rs
from companion.config import CompanionConfig
from companion.desk.recordings.layouts import detect_kind, open_recording
from companion.desk.recordings.poses import PoseTable
from companion.desk.recordings.recording import (
    IDENTITY_MOUNT,
    Overrides,
    RecordingError,
    WorldFrame,
    body_pose_from_camera,
    camera_pose_from_opencv,
    camera_pose_to_opencv,
    pose_covariance,
    read_gray,
)
from companion.desk.recordings.tum import export_tum
from companion.desk.replay import JPEG_BLACK_LEVEL, black_level_for, build_mapper, clamp_black
from companion.method.geometry import CameraMount, PinholeCamera, euler_to_matrix
from companion.method.terrain.grid import TerrainGrid

AXES = ["x", "-x", "y", "-y", "z", "-z"]


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def camera_of(sample, recording):
    return recording.mount.camera_pose(sample.nav.position_ned_m, sample.nav.R_nb)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------


@settings(deadline=None, max_examples=60)
@given(st.sampled_from(AXES), st.sampled_from(AXES), st.floats(0.01, 100.0))
def test_world_frame_is_a_proper_rotation_that_puts_up_up_and_north_north(up, north, scale):
    if up.lstrip("-") == north.lstrip("-"):
        with pytest.raises(RecordingError, match="perpendicular"):
            WorldFrame(up, north, scale)
        return
    w = WorldFrame(up, north, scale)
    A = w.A
    assert np.allclose(A @ A.T, np.eye(3)) and np.isclose(np.linalg.det(A), 1.0)
    up_w = np.array(rs_axis(up))
    assert np.allclose(A @ up_w, [0.0, 0.0, -1.0])  # world up is NED up (-down)
    assert np.allclose(A @ np.array(rs_axis(north)), [1.0, 0.0, 0.0])
    p = np.array([1.5, -2.0, 3.25])
    assert np.allclose(w.position_to_ned(p), scale * A @ p)
    assert np.allclose(w.position_from_ned(w.position_to_ned(p)), p)


def rs_axis(name: str) -> tuple[float, float, float]:
    v = [0.0, 0.0, 0.0]
    v["xyz".index(name[-1])] = -1.0 if name.startswith("-") else 1.0
    return tuple(v)


@settings(deadline=None, max_examples=60)
@given(st.lists(st.floats(-1.0, 1.0).map(lambda v: round(v, 3)), min_size=3, max_size=3),
       st.lists(st.floats(-1.0, 1.0).map(lambda v: round(v, 3)), min_size=3, max_size=3), st.floats(0.01, 100.0))
def test_an_up_direction_given_as_numbers_is_up_and_north_is_its_level_part(up, north, scale):
    """An SfM model's up is wherever the reconstruction put it: ``world_up: [ux, uy, uz]`` (any
    length). North is the given direction projected onto the level plane; A stays a proper
    rotation that sends up to NED up."""
    u, n = np.asarray(up), np.asarray(north)
    if not np.any(u) or not np.any(n):
        with pytest.raises(RecordingError, match="not a direction"):
            WorldFrame(tuple(up), tuple(north), scale)
        return
    u_hat, n_hat = u / np.linalg.norm(u), n / np.linalg.norm(n)
    if abs(u_hat @ n_hat) > 0.5:
        with pytest.raises(RecordingError, match="perpendicular"):
            WorldFrame(tuple(up), tuple(north), scale)
        return
    A = WorldFrame(tuple(up), tuple(north), scale).A
    assert np.allclose(A @ A.T, np.eye(3)) and np.isclose(np.linalg.det(A), 1.0)
    assert np.allclose(A @ u_hat, [0.0, 0.0, -1.0])
    level = n_hat - (n_hat @ u_hat) * u_hat
    assert np.allclose(A @ (level / np.linalg.norm(level)), [1.0, 0.0, 0.0])


def test_an_up_direction_without_north_takes_the_world_axis_farthest_from_it():
    w = WorldFrame.from_up([0.1, -0.2, 0.97])
    assert w.up == (0.1, -0.2, 0.97) and w.north == "x"
    assert WorldFrame.from_up([0.9, 0.1, 0.3]).north == "y"
    assert np.allclose(WorldFrame.from_up([0.0, 0.0, 2.0]).A, WorldFrame("z", "x").A)
    with pytest.raises(RecordingError, match=r"world_up: \['a', 1.0, 2.0\] is not a direction"):
        WorldFrame.from_up(["a", 1.0, 2.0])


def test_world_frame_rejects_unknown_axes_and_bad_scale():
    with pytest.raises(RecordingError, match="world_up"):
        WorldFrame("up", "x")
    with pytest.raises(RecordingError, match="scale"):
        WorldFrame("z", "x", 0.0)
    assert WorldFrame.from_up("x").north == "y" and WorldFrame.from_up("-y").north == "x"


def test_tum_camera_pose_in_a_z_up_world_becomes_the_paper_frame_in_ned():
    # Camera at world (1, 2, 3) looking along world x (OpenCV z), image right = world -y, image
    # down = world -z. In NED (north = x, east = -y, down = -z): looking north, right = east,
    # image down = down: the paper camera frame coincides with NED, R_nc = I.
    R_w_cv = np.column_stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]]).astype(float)
    p_c, R_nc = camera_pose_from_opencv(np.array([1.0, 2.0, 3.0]), R_w_cv, WorldFrame("z", "x", 2.0))
    assert np.allclose(R_nc, np.eye(3))
    assert np.allclose(p_c, [2.0, -4.0, -6.0])  # scaled by 2 m per unit, altitude 6 m
    back = camera_pose_to_opencv(p_c, R_nc, WorldFrame("z", "x", 2.0))
    assert np.allclose(back[0], [1, 2, 3]) and np.allclose(back[1], R_w_cv)


@settings(deadline=None, max_examples=50)
@given(st.tuples(*[st.floats(-170, 170)] * 3), st.tuples(*[st.floats(-2, 2)] * 3), st.tuples(*[st.floats(-1, 1)] * 3),
       st.tuples(*[st.floats(-3, 3)] * 3))
def test_body_pose_from_camera_is_what_the_mount_maps_back(euler_deg, offset, body_euler, p_c):
    mount = CameraMount.from_euler_deg(euler_deg[0], max(-89.0, min(89.0, euler_deg[1])), euler_deg[2], offset)
    R_nc = euler_to_matrix(*body_euler)
    p, R_nb = body_pose_from_camera(np.array(p_c), R_nc, mount)
    p_c2, R_nc2 = mount.camera_pose(p, R_nb)
    assert np.allclose(p_c2, p_c, atol=1e-12) and np.allclose(R_nc2, R_nc, atol=1e-12)
    assert np.allclose(R_nb @ R_nb.T, np.eye(3), atol=1e-12)


def test_pose_covariance_rotates_world_axis_sigmas_into_ned():
    A = WorldFrame("-y", "x").A  # north = x, east = -z, down = y
    P = pose_covariance([0.01, 0.02, 0.03], np.radians([0.1, 0.2, 0.3]), A)
    assert np.allclose(np.sqrt(np.diag(P[0:3, 0:3])), [0.01, 0.03, 0.02])
    assert np.allclose(np.degrees(np.sqrt(np.diag(P[6:9, 6:9]))), [0.1, 0.3, 0.2])


def test_pose_table_interpolates_inside_and_refuses_gaps_and_outside():
    t = np.array([0.0, 0.1, 0.2, 1.0])
    p_c = np.array([[0, 0, -10], [1, 0, -10], [2, 0, -10], [3, 0, -10]], float)
    q = np.array([[1, 0, 0, 0], [math.cos(0.05), 0, 0, math.sin(0.05)], [math.cos(0.1), 0, 0, math.sin(0.1)], [1, 0, 0, 0]])
    table = PoseTable(t, p_c, q, np.eye(9) * 1e-4, IDENTITY_MOUNT, max_gap_s=0.5, extrapolate_s=0.05, source="test")
    mid = table.lookup(0.15).nav
    assert np.allclose(mid.position_ned_m, [1.5, 0, -10])
    assert np.isclose(rotation_angle_deg(np.eye(3), mid.R_nb), math.degrees(0.15))  # slerp: yaw 0.15 rad
    assert np.allclose(mid.velocity_ned_mps, [10.0, 0, 0])
    assert table.lookup(0.1).nav.t_s == 0.1
    assert "gap" in table.lookup(0.6).reason
    assert "before the first pose" in table.lookup(-0.1).reason
    assert table.lookup(1.04).nav is not None and "after the last pose" in table.lookup(1.2).reason


# --------------------------------------------------------------------------------------------
# TUM folder
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tum_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tum") / "flight"
    return rs.write_tum(folder, rs.flight(), WorldFrame.from_up("-y", scale_m_per_unit=0.5), sigmas="axes")


def test_tum_folder_gives_the_true_camera_poses_with_per_frame_sigmas(tum_dir):
    f = rs.flight()
    rec = open_recording(tum_dir, CompanionConfig())
    assert rec.kind == "tum" == detect_kind(tum_dir) and len(rec) == len(f.t)
    samples = list(rec.samples())
    for s in samples:
        p_c, R_nc = camera_of(s, rec)
        assert np.allclose(p_c, f.p_c[s.index], atol=1e-9) and np.allclose(R_nc, f.R_nc[s.index], atol=1e-9)
        assert s.frame is not None and np.array_equal(s.frame.image, f.images[s.index])
        # pose_sigmas.txt, axes form, about world x, y, z -> NED north = x, east = -z, down = y
        assert np.allclose(np.sqrt(np.diag(s.nav.pose_covariance)), [0.01, 0.03, 0.02, *np.radians([0.1, 0.3, 0.2])])
    # the command line's sigma overrides the metadata and the per-frame file
    rec2 = open_recording(tum_dir, CompanionConfig(), overrides=Overrides(pose_sigma_m=0.5, pose_sigma_deg=1.0))
    nav = next(rec2.samples(load_images=False)).nav
    assert np.allclose(np.sqrt(np.diag(nav.pose_covariance)), [0.5] * 3 + [math.radians(1.0)] * 3)


def test_tum_isotropic_sigmas_and_frames_without_a_sigma_row_use_the_metadata(tmp_path):
    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=4), WorldFrame("z", "x"), sigmas="iso")
    lines = (folder / "pose_sigmas.txt").read_text().splitlines()
    (folder / "pose_sigmas.txt").write_text("\n".join(lines[:2]) + "\n")  # rows for frames 0 and 1 only
    sig = [np.sqrt(np.diag(s.nav.pose_covariance)) for s in open_recording(folder).samples(load_images=False)]
    assert np.allclose(sig[0], [0.05] * 3 + [math.radians(0.3)] * 3)
    assert np.allclose(sig[3], [0.05] * 3 + [math.radians(0.2)] * 3)  # meta.yaml: 0.05 m, 0.2 deg


def test_tum_damage_is_counted_and_reading_continues(tmp_path):
    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=12), WorldFrame("z", "x"))
    poses = (folder / "poses.txt").read_text().splitlines()
    poses.insert(3, "1000.25 1.0 2.0 oops 0 0 0 1")  # not a number
    poses.insert(5, "1000.26 1 2 3 0 0 0 2")  # not a unit quaternion
    (folder / "poses.txt").write_text("\n".join(poses) + "\n")
    images = (folder / "images.txt").read_text().splitlines()
    images.insert(2, "garbage-without-a-filename")
    images.append("1001.5 images/0002.png")  # a frame after the last pose
    (folder / "images.txt").write_text("\n".join(images) + "\n")
    (folder / "images" / "0004.png").unlink()
    (folder / "images" / "0006.png").write_bytes(b"\x89PNG not really")
    rec = open_recording(folder)
    assert rec.stats.bad_lines == {"poses.txt": 2, "images.txt": 1}
    samples = list(rec.samples())
    assert len(samples) == 13  # 12 good lines and the extra one
    assert "missing" in samples[4].image_problem and samples[4].frame is None
    assert "cannot be decoded" in samples[6].image_problem
    assert samples[-1].nav is None and "after the last pose" in samples[-1].nav_problem
    assert sum(s.frame is not None for s in samples) == 10


def test_tum_folder_of_timestamp_named_images_without_an_image_list(tmp_path):
    f = rs.flight(n_frames=3)
    folder = rs.write_tum(tmp_path / "t", f, WorldFrame("z", "x"), t0=1305031102.0)
    for line in (folder / "images.txt").read_text().splitlines()[1:]:
        t, name = line.split()
        (folder / name).rename(folder / "images" / f"{t}.png")
    (folder / "images.txt").unlink()
    rec = open_recording(folder)
    samples = list(rec.samples())
    assert [s.t_s for s in samples] == [1305031102.0 + t for t in f.t]
    assert all(s.frame is not None and s.nav is not None for s in samples)


def test_tum_without_metadata_or_camera_file_is_refused_with_the_file_named(tmp_path):
    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=2), WorldFrame("z", "x"))
    (folder / "camera.yaml").unlink()
    with pytest.raises(RecordingError, match="camera.yaml"):
        open_recording(folder)
    (folder / "meta.yaml").write_text("scale_m_per_unit: 1.0\n")
    with pytest.raises(RecordingError, match="world_up"):
        open_recording(folder)
    with pytest.raises(RecordingError, match="not a recording"):
        open_recording(tmp_path)


def test_a_misspelt_key_in_meta_or_camera_yaml_is_an_error_naming_the_file_and_the_key(tmp_path):
    """A misspelt optional key was ignored and its default used without a word."""
    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=2), WorldFrame("z", "x"))
    meta = yaml.safe_load((folder / "meta.yaml").read_text())
    (folder / "meta.yaml").write_text(yaml.safe_dump({**meta, "pose_sigma": 0.1}))
    with pytest.raises(RecordingError) as err:
        open_recording(folder)
    assert str(err.value).startswith(f"{folder / 'meta.yaml'}: unknown key 'pose_sigma' (did you mean 'pose_sigma_m'?)")
    (folder / "meta.yaml").write_text(yaml.safe_dump({**meta, "ground_altitude_m": 2.0}))
    with pytest.raises(RecordingError, match=r"unknown key 'ground_altitude_m' \(did you mean 'ground_alt_m'\?\)"):
        open_recording(folder)
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    camera = yaml.safe_load((folder / "camera.yaml").read_text())
    (folder / "camera.yaml").write_text(yaml.safe_dump({**camera, "k1": 0.1}))
    with pytest.raises(RecordingError, match=r"camera.yaml: unknown key 'k1'; known keys: width, height, fx, fy, cx, cy, distortion"):
        open_recording(folder)
    (folder / "camera.yaml").write_text(yaml.safe_dump(camera))
    assert len(list(open_recording(folder).samples())) == 2  # and the files as written are accepted


# --------------------------------------------------------------------------------------------
# EuRoC MAV
# --------------------------------------------------------------------------------------------


def test_euroc_layout_gives_the_true_camera_poses_through_t_bs_and_interpolation(tmp_path):
    f = rs.flight(distorted=True)
    root = rs.write_euroc(tmp_path / "MH_synthetic", f)
    for path in (root, root / "mav0"):
        rec = open_recording(path)
        assert rec.kind == "euroc" and len(rec) == len(f.t)
    assert rec.camera.has_distortion and np.allclose(rec.camera.distortion[:4], rs.DISTORTION[:4])
    worst_p = worst_deg = 0.0
    for s in rec.samples():
        assert np.isclose(s.t_s, f.t[s.index], atol=1e-9)  # ns from the first frame
        p_c, R_nc = camera_of(s, rec)
        worst_p = max(worst_p, float(np.linalg.norm(p_c - f.p_c[s.index])))
        worst_deg = max(worst_deg, rotation_angle_deg(R_nc, f.R_nc[s.index]))
    # ground truth at 40 Hz between the frames: linear/slerp interpolation of a smooth flight
    assert worst_p < 2e-3 and worst_deg < 0.02, (worst_p, worst_deg)


def test_euroc_damaged_groundtruth_lines_are_counted(tmp_path):
    root = rs.write_euroc(tmp_path / "e", rs.flight(distorted=True))
    gt = root / "mav0/state_groundtruth_estimate0/data.csv"
    lines = gt.read_text().splitlines()
    lines[10] = lines[10][:30]  # cut short
    gt.write_text("\n".join(lines) + "\n")
    rec = open_recording(root)
    assert rec.stats.bad_lines == {"data.csv": 1}
    assert all(s.nav is not None for s in rec.samples(load_images=False))


# --------------------------------------------------------------------------------------------
# The service's own recording
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def companion_dir(tmp_path_factory):
    return rs.write_companion(tmp_path_factory.mktemp("rec") / "flight", rs.flight())


def test_own_recording_navigation_is_rebuilt_from_the_telemetry_log(companion_dir):
    f = rs.flight()
    rec = open_recording(companion_dir)
    assert rec.kind == "companion" and len(rec) == len(f.t)
    # the mount comes from meta.yaml: the navigation is the body's, the camera pose follows
    assert np.allclose(rec.mount.R_bc, f.mount.R_bc)
    worst_p = worst_deg = 0.0
    for s in rec.samples():
        assert s.nav is not None and s.frame is not None, s.nav_problem
        worst_p = max(worst_p, float(np.linalg.norm(s.nav.position_ned_m - f.p[s.index])))
        worst_deg = max(worst_deg, rotation_angle_deg(s.nav.R_nb, f.R_nb[s.index]))
        assert np.array_equal(s.frame.image, f.images[s.index])
    assert worst_p < 1e-3 and worst_deg < 1e-3, (worst_p, worst_deg)
    assert rec.stats.telemetry_bad == 0 and rec.stats.nav_states > 700


def test_frames_outside_the_telemetry_have_no_navigation_and_are_told_why(tmp_path):
    folder = rs.write_companion(tmp_path / "r", rs.flight(n_frames=12), frames_after_s=0.0, telemetry_until_s=0.55)
    samples = list(open_recording(folder).samples(load_images=False))
    with_nav = [s.nav is not None for s in samples]
    assert with_nav[1:6] == [True] * 5 and not any(with_nav[7:])
    assert "after the newest navigation" in samples[-1].nav_problem


def test_corrupt_telemetry_bytes_are_counted_and_navigation_resumes(tmp_path, companion_dir):
    folder = tmp_path / "r"
    shutil.copytree(companion_dir, folder)
    data = bytearray((folder / "telemetry.tlog").read_bytes())
    middle = len(data) // 2
    data[middle:middle + 200] = bytes(200)  # a burst of zeros mid-log
    (folder / "telemetry.tlog").write_bytes(bytes(data))
    rec = open_recording(folder)
    samples = list(rec.samples(load_images=False))
    assert rec.stats.telemetry_bad > 0
    assert sum(s.nav is not None for s in samples) >= len(samples) - 3


def test_missing_clock_mapping_is_a_clear_error(tmp_path, companion_dir):
    import yaml

    folder = tmp_path / "r"
    shutil.copytree(companion_dir, folder)
    meta = yaml.safe_load((folder / "meta.yaml").read_text())
    del meta["clock"]["t_s"]
    (folder / "meta.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(RecordingError, match="clock"):
        open_recording(folder)


def test_export_to_tum_round_trips_poses_sigmas_and_images(tmp_path, companion_dir):
    rec = open_recording(companion_dir)
    counts = export_tum(rec, tmp_path / "tum")
    assert counts == {"written": len(rec), "without_nav": 0, "missing_image": 0}
    with pytest.raises(FileExistsError):
        export_tum(rec, tmp_path / "tum")
    tum = open_recording(tmp_path / "tum")
    assert tum.kind == "tum" and np.allclose(tum.camera.K, rec.camera.K)
    for a, b in zip(rec.samples(), tum.samples(), strict=True):
        pa, Ra = camera_of(a, rec)
        pb, Rb = camera_of(b, tum)
        assert a.t_s == b.t_s
        assert np.allclose(pa, pb, atol=1e-9) and np.allclose(Ra, Rb, atol=1e-9)
        assert np.allclose(np.diag(a.nav.pose_covariance), np.diag(b.nav.pose_covariance), rtol=1e-9)
        assert np.array_equal(a.frame.image, b.frame.image)


# --------------------------------------------------------------------------------------------
# Images: formats and black borders
# --------------------------------------------------------------------------------------------


def test_read_gray_accepts_8_and_16_bit_grey_and_colour_and_refuses_the_wrong_size(tmp_path):
    grey = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    cv2.imwrite(str(tmp_path / "w.png"), grey.astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "c.png"), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    for name in ("g.png", "w.png", "c.png"):
        image, problem = read_gray(tmp_path / name, 64, 48)
        assert problem == "" and np.array_equal(image, grey), name
    image, problem = read_gray(tmp_path / "g.png", 640, 480)
    assert image is None and "64x48" in problem


def black_border(image: np.ndarray) -> np.ndarray:
    """What cv2.undistort of a barrel-distorted lens leaves: black (0) outside the valid area."""
    cam = rs.flight().camera
    return cv2.undistort(image, cam.K, np.array([0.3, 0.1, 0.0, 0.0, 0.0]))


def distance_to_black(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    dist = cv2.distanceTransform((image > 0).astype(np.uint8), cv2.DIST_C, 3)
    px = np.round(uv).astype(int)
    return dist[px[:, 1], px[:, 0]]


@pytest.mark.parametrize("fmt", ["png", "jpg"])
def test_undistorted_frames_with_black_borders_give_no_feature_on_the_border(tmp_path, fmt):
    """Frames read from a TUM folder (lossless PNG, and JPEG whose black border rings a few grey
    levels above 0: without the automatic black level a feature lands 6 px from it) through the
    replay's own detector."""
    f = rs.flight(n_frames=6)
    folder = rs.write_tum(tmp_path / "t", f, WorldFrame("z", "x"), image_ext=f".{fmt}")
    for k, image in enumerate(f.images):
        params = [cv2.IMWRITE_JPEG_QUALITY, 75] if fmt == "jpg" else []
        cv2.imwrite(str(folder / "images" / f"{k:04d}.{fmt}"), black_border(image), params)
    rec = open_recording(folder)
    cfg = CompanionConfig()
    mapper = build_mapper(cfg, rec, TerrainGrid.from_config(cfg.terrain))
    levels = {black_level_for(s.image_path, None) for s in rec.samples(load_images=False)}
    assert levels == ({JPEG_BLACK_LEVEL} if fmt == "jpg" else {0})  # automatic: JPEG borders ring above 0
    level = levels.pop()
    n = 0
    for s in rec.samples():
        truth = black_border(f.images[s.index])  # where the border really is
        assert (truth == 0).mean() > 0.1
        uv, _ = mapper.detector(clamp_black(s.frame.image, level))
        assert len(uv) > 20
        assert distance_to_black(truth, uv).min() >= cfg.camera.border_px
        n += len(uv)
    print(f"\n{fmt}: {n} features in {len(f.images)} bordered frames, none within {cfg.camera.border_px} px of the border")


def test_a_static_mask_keeps_features_out_of_its_region():
    f = rs.flight(n_frames=2)
    cfg = CompanionConfig()
    mask = np.full((f.camera.height, f.camera.width), 255, np.uint8)
    mask[300:, 200:440] = 0  # e.g. landing gear in view
    rec = type("R", (), {"camera": f.camera, "mount": f.mount, "ground_alt_m": 0.0})()
    mapper = build_mapper(cfg, rec, TerrainGrid.from_config(cfg.terrain), mask=mask)
    uv, _ = mapper.detector(f.images[0])
    assert len(uv) > 20
    assert distance_to_black(mask, uv).min() >= cfg.camera.border_px


def test_camera_file_with_wrong_distortion_is_refused(tmp_path):
    import yaml

    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=2), WorldFrame("z", "x"))
    cam = yaml.safe_load((folder / "camera.yaml").read_text())
    cam["distortion"] = [0.1, 0.2, 0.3]
    (folder / "camera.yaml").write_text(yaml.safe_dump(cam))
    with pytest.raises(RecordingError, match="distortion"):
        open_recording(folder)


def test_pinhole_camera_from_tum_matches_the_file(tum_dir):
    rec = open_recording(tum_dir)
    c: PinholeCamera = rec.camera
    f = rs.flight().camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (f.width, f.height, f.fx, f.fy, f.cx, f.cy)
