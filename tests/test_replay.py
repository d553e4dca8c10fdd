"""``companion replay``: the mapper over recordings (companion/desk/replay.py, docs/replay.md).

Every recording here is the same simulated flight (tests/replay_synthetic.py: flat textured
ground, 15 m up, 6 m/s north, camera 45 deg down, 60 frames at 10 Hz) written in one layout.
Run with ``-s`` to print the figures (map error against the true surface, frames/s).
"""

from __future__ import annotations

import json
import math
import re

import cv2
import numpy as np
import pytest
import yaml

import replay_synthetic as rs
from companion import cli
from companion.config import CompanionConfig, MapperConfig
from companion.desk.map_metrics import bin_heights, compare, map_cells, read_reference_csv, reference_metrics
from companion.desk.recordings.layouts import open_recording, recording_config
from companion.desk.recordings.recording import WorldFrame, pose_covariance
from companion.desk.recordings.tum import export_tum
from companion.desk.replay import EXIT_NOTHING_MAPPED, build_mapper, load_reference, plausibility, run_replay
from companion.method.geometry import euler_to_matrix, matrix_to_quat
from companion.method.mapper.flow_depth import FlowRanger
from companion.method.messages import NavState
from companion.method.terrain.grid import TerrainGrid

# Region of the flight's map, and the accuracy the mapper reaches on it today (measured: median
# |error| ~0.02 m, RMSE ~0.07 m, 100 % of cells within 1 m). Since the mapper emits a point only
# when its depth sigma is below the emission limit (docs/mapper.md, "Convergence and emission"),
# this 6 s flight maps ~226 cells, not the 300+ a relative limit alone gives, whose far, imprecise
# ones were metres off: the coverage bound follows.
MIN_CELLS = 100
NORTH, EAST = (-20.0, 140.0), (-60.0, 60.0)
MEDIAN_ABS_MAX_M = 0.3
WITHIN_1M_MIN = 0.8
SAME_MAP_TOL_M = 0.01  # own recording vs its TUM export: same cells, heights within this


def print_figures(name: str, metrics: dict) -> None:
    ref = metrics.get("reference") or {}
    print(f"\n{name}: {metrics['frames_processed']} frames, mapper {metrics['mapper_fps']:.1f} frames/s "
          f"(replay {metrics['replay_fps']:.1f}), {metrics['converged_points']} points, {metrics['cells_mapped']} cells"
          + (f"; vs truth RMSE {ref['rmse_m']:.2f} m, bias {ref['bias_m']:+.3f} m, median |e| {ref['median_abs_m']:.3f} m, "
             f"within 1 m {100 * ref['within_1m']:.1f} %" if ref.get("rmse_m") is not None else ""))


def assert_close_to_truth(metrics: dict) -> None:
    ref = metrics["reference"]
    assert ref["cells_compared"] == metrics["cells_mapped"] > MIN_CELLS
    assert ref["median_abs_m"] < MEDIAN_ABS_MAX_M, ref
    assert ref["within_1m"] > WITHIN_1M_MIN, ref


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("replay")
    truth = rs.truth_csv(root / "truth.csv", NORTH, EAST)
    return {
        "root": root,
        "truth": truth,
        "tum": rs.write_tum(root / "tum", rs.flight(), WorldFrame.from_up("-y", scale_m_per_unit=0.5)),
        "companion": rs.write_companion(root / "own", rs.flight()),
    }


def direct_map(cfg: CompanionConfig, sigma_m: float, sigma_deg: float) -> TerrainGrid:
    """The mapper and the dense-flow stage beside it fed directly with the true body poses and the
    rendered images (no files)."""
    f = rs.flight()
    grid = TerrainGrid.from_config(cfg.terrain)
    rec = type("R", (), {"camera": f.camera, "mount": f.mount, "ground_alt_m": 0.0})()
    mapper = build_mapper(cfg, rec, grid)
    flow = FlowRanger(cfg.mapper, f.camera, f.mount) if cfg.mapper.flow_on else None
    cov = pose_covariance(np.full(3, sigma_m), np.full(3, math.radians(sigma_deg)))
    for t, p, R, image in zip(f.t, f.p, f.R_nb, f.images):
        nav = NavState(float(t), p, np.zeros(3), matrix_to_quat(R), cov)
        step = mapper.step(nav, image)
        grid.add_evidence(step.points, step.free_space, step.floors)
        if flow is not None:
            flowed = flow.step(nav, image)
            grid.add_flow(flowed.surface, flowed.floors)
    return grid


def test_tum_replay_is_the_mapper_on_the_true_poses_and_writes_map_and_metrics(data, tmp_path):
    """A TUM folder in a y-down world at 2 m per unit replays to exactly the map the mapper makes
    from the true NED poses: the conversions lose nothing."""
    cfg = CompanionConfig()
    rec = open_recording(data["tum"], cfg)
    ref = load_reference(data["truth"], rec)
    result = run_replay(rec, cfg, tmp_path / "out", reference=ref)
    m = result.metrics
    print_figures("TUM replay", m)
    assert m["frames_processed"] == 60 and m["frames_without_nav"] == 0 and m["frames_unreadable"] == 0
    direct = map_cells(direct_map(cfg, 0.05, 0.2))  # meta.yaml's pose sigmas
    replayed = map_cells(result.grid)
    assert np.array_equal(replayed.keys, direct.keys)
    assert np.max(np.abs(replayed.height - direct.height)) < 1e-6
    assert_close_to_truth(m)
    # outputs: metrics.json as returned, figures that decode, a snapshot that is the map
    on_disk = json.loads((tmp_path / "out" / "metrics.json").read_text())
    for key in ("frames_processed", "frames_without_nav", "mapper_fps", "converged_points", "cells_mapped", "reference"):
        assert on_disk[key] == m[key]
    assert set(on_disk["reference"]) >= {"rmse_m", "bias_m", "coverage", "cells_compared"}
    for png in ("terrain_map.png", "terrain_error.png"):
        image = cv2.imread(str(tmp_path / "out" / png))
        assert image is not None and image.shape[0] > 100
    again = map_cells(TerrainGrid.load_snapshot(tmp_path / "out" / "terrain.snapshot", cfg.terrain))
    assert np.array_equal(again.keys, replayed.keys) and np.array_equal(again.height, replayed.height)


def test_reference_bias_and_rmse_follow_a_shifted_reference_exactly(data, tmp_path):
    grid = direct_map(CompanionConfig(), 0.05, 0.2)
    pts = read_reference_csv(data["truth"]).xyz
    base = reference_metrics(grid, pts[:, 0], pts[:, 1], pts[:, 2])
    for shift in (+1.0, -2.5):
        m = reference_metrics(grid, pts[:, 0], pts[:, 1], pts[:, 2] + shift)
        assert m["cells_compared"] == base["cells_compared"] > MIN_CELLS
        assert math.isclose(m["bias_m"], base["bias_m"] - shift, abs_tol=1e-9)
        # mean((e - s)^2) = rmse^2 - 2 s bias + s^2
        assert math.isclose(m["rmse_m"] ** 2, base["rmse_m"] ** 2 - 2 * shift * base["bias_m"] + shift**2, rel_tol=1e-9)
    assert math.isclose(base["coverage"], base["cells_compared"] / base["cells_reference"])
    # a point cloud: several points per cell reduce to the cell's mean / max / median
    cells = bin_heights(np.array([0.2, 0.7, 0.9, 5.5]), np.array([0.1, 0.4, 0.3, 5.5]), np.array([1.0, 2.0, 6.0, 3.0]), 1.0, "mean")
    assert cells.height.tolist() == [3.0, 3.0] and cells.count.tolist() == [3, 1]
    assert bin_heights(np.zeros(3), np.zeros(3), np.array([1.0, 2.0, 6.0]), 1.0, "max").height.tolist() == [6.0]
    assert bin_heights(np.zeros(4), np.zeros(4), np.array([1.0, 2.0, 6.0, 9.0]), 1.0, "median").height.tolist() == [4.0]
    no_overlap = compare(map_cells(grid), bin_heights(np.array([1e4]), np.array([1e4]), np.array([0.0]), 1.0))
    assert no_overlap["cells_compared"] == 0 and no_overlap["rmse_m"] is None


def test_euroc_replay_maps_the_true_surface(data, tmp_path):
    root = rs.write_euroc(data["root"] / "euroc", rs.flight(distorted=True))
    cfg = CompanionConfig()
    rec = open_recording(root, cfg)
    # the EuRoC world is z up, x north: a reference in the dataset's frame has y = -east
    pts = read_reference_csv(data["truth"]).xyz
    (tmp_path / "ref_world.csv").write_text("\n".join(f"{x},{-y},{z}" for x, y, z in pts.tolist()))
    ref = load_reference(tmp_path / "ref_world.csv", rec, frame="dataset")
    m = run_replay(rec, cfg, tmp_path / "out", reference=ref).metrics
    print_figures("EuRoC replay (distorted lens)", m)
    assert m["frames_processed"] == 60
    assert_close_to_truth(m)


def test_own_recording_and_its_tum_export_replay_to_the_same_map(data, tmp_path):
    """The documented conversion (``companion replay REC --export-tum OUT``) of a --record folder:
    both replay to the same map within SAME_MAP_TOL_M."""
    cfg = recording_config(data["companion"])  # what the command line uses without --config
    assert cfg is not None and cfg.nav.position_sigma_floor_m == 0.05
    own = open_recording(data["companion"], cfg)
    ref = load_reference(data["truth"], own)
    a = run_replay(own, cfg, tmp_path / "own", reference=ref)
    assert cli.main(["replay", str(data["companion"]), "--export-tum", str(tmp_path / "tum")]) == 0
    b = run_replay(open_recording(tmp_path / "tum", cfg), cfg, tmp_path / "tum_out", reference=ref)
    print_figures("own recording", a.metrics)
    print_figures("its TUM export", b.metrics)
    ca, cb = map_cells(a.grid), map_cells(b.grid)
    assert np.array_equal(ca.keys, cb.keys) and len(ca) > MIN_CELLS
    diff = float(np.max(np.abs(ca.height - cb.height)))
    print(f"own vs export: {len(ca)} cells, max |height difference| {diff:.2e} m")
    assert diff < SAME_MAP_TOL_M
    assert_close_to_truth(a.metrics)


def test_broken_frames_and_pose_lines_are_counted_and_the_replay_continues(tmp_path):
    folder = rs.write_tum(tmp_path / "t", rs.flight(n_frames=30), WorldFrame("z", "x"))
    poses = (folder / "poses.txt").read_text().splitlines()
    poses[8] = poses[8].rsplit(" ", 2)[0]  # a pose line cut short
    (folder / "poses.txt").write_text("\n".join(poses) + "\n")
    images = (folder / "images.txt").read_text().splitlines()
    images.insert(5, "not-a-time images/0003.png")
    (folder / "images.txt").write_text("\n".join(images) + "\n")
    (folder / "images" / "0010.png").write_bytes(b"broken")
    (folder / "images" / "0011.png").unlink()
    cfg = CompanionConfig()
    m = run_replay(open_recording(folder, cfg), cfg, tmp_path / "out").metrics
    assert m["recording"]["bad_lines"] == {"poses.txt": 1, "images.txt": 1}
    assert m["frames_listed"] == 30 and m["frames_unreadable"] == 2 and m["frames_processed"] == 28
    assert sum(m["image_problems"].values()) == 2
    assert m["cells_mapped"] > MIN_CELLS // 3 and m["converged_points"] > 0
    assert any("images.txt: line" in p for p in m["recording"]["problems"])


def test_command_line_replay_with_reference_progress_and_limits(data, tmp_path, capsys):
    out = tmp_path / "cli"
    rc = cli.main(["replay", str(data["tum"]), "--output", str(out), "--max-frames", "20", "--reference",
                   str(data["truth"]), "--parameterisation", "cartesian"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "replay [" in captured.err and "20/20 frames" in captured.err  # the progress bar
    assert "reference: RMSE" in captured.out
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames_listed"] == 20 and m["config"]["parameterisation"] == "cartesian"
    assert m["reference"]["cells_compared"] > 0 and (out / "terrain_map.png").is_file()
    # the filter's consistency: its mean innovation squared over the corner updates, printed too
    nis = m["mapper"]["innovation_nis_mean"]
    assert m["mapper"]["corner_updates"] > 100 and 0.0 < nis < MapperConfig().gate_chi2
    assert f"filter consistency: mean innovation squared {nis:.2f} over {m['mapper']['corner_updates']}" in captured.out
    # bad input: a clear message and exit status 2, nothing written
    assert cli.main(["replay", str(tmp_path / "nothing-here")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert cli.main(["replay", str(data["tum"]), "--max-frames", "0"]) == 2
    assert cli.main(["replay", str(data["tum"]), "-o", str(tmp_path / "x"), "--reference", str(tmp_path / "none.csv")]) == 2
    assert "cannot read reference" in capsys.readouterr().err
    assert not (tmp_path / "x" / "metrics.json").exists()


def test_own_recording_config_is_used_unless_a_config_file_is_given(data, tmp_path, capsys):
    rc = cli.main(["replay", str(data["companion"]), "-o", str(tmp_path / "o"), "--max-frames", "15", "--no-progress"])
    assert rc == 0 and capsys.readouterr().err == ""
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["config"]["source"].endswith("meta.yaml")
    (tmp_path / "c.yaml").write_text("mapper:\n  max_features: 30\nterrain:\n  cell_size_m: 0.5\n")
    rc = cli.main(["replay", str(data["companion"]), "-o", str(tmp_path / "p"), "--max-frames", "15", "--no-progress",
                   "--config", str(tmp_path / "c.yaml")])
    m = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert rc == 0 and m["config"]["max_features"] == 30 and m["map"]["cell_size_m"] == 0.5


def test_a_replay_that_maps_nothing_says_why_on_the_console_and_exits_3(data, tmp_path, capsys):
    """The user's mistakes that used to give an empty map, exit 0 and nothing on the console."""
    def replay(folder, *extra):
        rc = cli.main(["replay", str(folder), "-o", str(tmp_path / f"out{len(extra)}"), "--no-progress", *extra])
        return rc, capsys.readouterr()

    # Too few frames for a feature to converge.
    rc, out = replay(data["companion"], "--max-frames", "3")
    assert rc == EXIT_NOTHING_MAPPED == 3
    assert out.out.startswith("3 of 3 frames mapped (0 without navigation, 0 unreadable, 0 refused)")
    assert out.err == (f"companion replay: {data['companion']}: 3 frames mapped but no feature converged "
                       f"(79 feature updates, 53 features started): too little motion between frames, or too little texture\n")
    # Every frame unreadable: camera.yaml says 752 pixels wide, the images are 640.
    folder = rs.write_tum(tmp_path / "wide", rs.flight(n_frames=6), WorldFrame("z", "x"))
    camera = yaml.safe_load((folder / "camera.yaml").read_text())
    (folder / "camera.yaml").write_text(yaml.safe_dump({**camera, "width": 752}))
    rc, out = replay(folder)
    assert rc == 3
    assert out.err.startswith(f"companion replay: {folder}: no frame mapped: all 6 frames unreadable (6 of them: ")
    assert "752" in out.err and "camera.yaml" in out.err
    # Poses far sparser than the frames: the gap and the setting to change, with their numbers.
    folder = rs.write_tum(tmp_path / "sparse", rs.flight(n_frames=20), WorldFrame("z", "x"))
    lines = (folder / "poses.txt").read_text().splitlines()
    (folder / "poses.txt").write_text("\n".join([lines[0], lines[1], lines[-1]]) + "\n")
    rc, out = replay(folder)
    assert rc == 3
    assert "frames without a pose" in out.err and "gap of " in out.err
    assert "(limit nav.buffer_max_gap_s 0.500 s)" in out.err
    # Geo-referenced (UTM-like) coordinates: every converged point is beyond terrain.max_abs_coordinate_m.
    folder = rs.write_tum(tmp_path / "utm", rs.flight(), WorldFrame("z", "x"))
    _rewrite_poses(folder, lambda t, xyz, q: (t, xyz + UTM_SHIFT, q))
    rc, out = replay(folder)
    assert rc == 3
    assert "converged points rejected as invalid by the map: coordinates beyond terrain.max_abs_coordinate_m" in out.err
    assert "'origin: auto'" in out.err and "meta.yaml" in out.err


def test_export_leaves_out_frames_without_navigation(tmp_path):
    folder = rs.write_companion(tmp_path / "r", rs.flight(n_frames=12), frames_after_s=0.0, telemetry_until_s=0.55)
    counts = export_tum(open_recording(folder), tmp_path / "tum")
    assert counts["written"] + counts["without_nav"] == 12 and counts["without_nav"] >= 5
    assert len((tmp_path / "tum" / "poses.txt").read_text().splitlines()) == 1 + counts["written"]


UTM_SHIFT = np.array([5.0e6, 4.0e5, 0.0])  # a geo-referenced world's offset (world units)


def _rewrite_poses(folder, change):
    """poses.txt with ``change(t, xyz (3,), q_xyzw (4,)) -> (t, xyz, q_xyzw)`` applied to every pose."""
    rows = []
    for line in (folder / "poses.txt").read_text().splitlines():
        if line.startswith("#"):
            rows.append(line)
            continue
        f = [float(x) for x in line.split()]
        t, xyz, q = change(f[0], np.array(f[1:4]), np.array(f[4:8]))
        rows.append(" ".join(map(repr, [float(t), *map(float, xyz), *map(float, q)])))
    (folder / "poses.txt").write_text("\n".join(rows) + "\n")


def _quat_matrix(q_xyzw):
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_a_nadir_survey_camera_is_not_taken_for_a_rolled_one(tmp_path):
    """A survey camera looking straight down (a real DJI survey: 89.9 deg gimbal pitch) has no
    upright: whatever its heading, no frame counts as rolled. The same camera 45 deg down and
    rolled 90 deg on its side is; at 10 deg off nadir a 70 deg roll is."""
    def cameras(depression_deg, roll_deg, n=24):
        # paper camera frame: x optical, y right, z image down; heading, then depression, then roll
        return np.stack([euler_to_matrix(math.radians(roll_deg), -math.radians(depression_deg), yaw)
                         for yaw in np.linspace(-math.pi, math.pi, n, endpoint=False)])

    def warnings(R):
        return plausibility(np.arange(len(R)) * 0.5, np.full(len(R), 40.0), R, 0.0, tmp_path)

    assert warnings(cameras(89.9, 0.0)) == [] and warnings(cameras(90.0, 37.0)) == []
    assert warnings(cameras(45.0, 0.0)) == [] and warnings(cameras(45.0, 50.0)) == []
    rolled = warnings(cameras(45.0, 90.0))
    assert len(rolled) == 1 and "rolled more than 60 deg from upright in 24 of 24 frames" in rolled[0]
    assert len(warnings(cameras(80.0, 70.0))) == 1


def test_implausible_inputs_get_a_warning_naming_the_likely_mistake(tmp_path, capsys):
    """A user's recording with world-to-camera poses, the up axis reversed, quaternions written w
    first, or timestamps in microseconds: the console says which, naming the recording, whatever the
    map became."""
    def replay(folder):
        rc = cli.main(["replay", str(folder), "-o", str(tmp_path / f"out-{folder.name}"), "--no-progress"])
        return rc, capsys.readouterr().err

    good = rs.write_tum(tmp_path / "good", rs.flight(), WorldFrame("z", "x"))
    rc, err = replay(good)
    assert rc == 0 and "warning" not in err

    # World-to-camera poses (the inverse of what the layout expects): the camera is 20 m under the
    # ground, rolled on its side.
    inverted = rs.write_tum(tmp_path / "inverted", rs.flight(), WorldFrame("z", "x"))

    def invert(t, xyz, q):
        R = _quat_matrix(q)
        return t, -R.T @ xyz, np.array([-q[0], -q[1], -q[2], q[3]])

    _rewrite_poses(inverted, invert)
    rc, err = replay(inverted)
    assert re.search(rf"companion replay: warning: {re.escape(str(inverted))}: the camera is below the ground "
                     r"altitude \(0 m\) in (\d+) of 60 frames", err)
    assert f"companion replay: warning: {inverted}: the image is rolled more than 60 deg from upright in 60 of 60 frames" in err
    assert "world-to-camera" in err and "x y z w" in err and "world_up" in err
    # The up axis reversed (meta.yaml world_up "-z" for a recording whose up is z): looking at the sky
    # from below the ground.
    upside = rs.write_tum(tmp_path / "upside", rs.flight(), WorldFrame("z", "x"))
    meta = yaml.safe_load((upside / "meta.yaml").read_text())
    (upside / "meta.yaml").write_text(yaml.safe_dump({**meta, "world_up": "-z"}))
    rc, err = replay(upside)
    assert f"companion replay: warning: {upside}: the camera looks above the horizon in 60 of 60 frames" in err

    # Quaternions written w first: a level camera, which a forward-looking mount can be, so no
    # warning; but the corners are rarely where the poses predict them, and nothing converges.
    wfirst = rs.write_tum(tmp_path / "wfirst", rs.flight(), WorldFrame("z", "x"))
    _rewrite_poses(wfirst, lambda t, xyz, q: (t, xyz, np.r_[q[3], q[:3]]))
    rc, err = replay(wfirst)
    assert rc == EXIT_NOTHING_MAPPED and re.search(
        rf"companion replay: {re.escape(str(wfirst))}: 60 frames mapped but no feature converged \(\d+ feature updates, \d+ "
        r"features started\): the features rarely match from frame to frame \(\d+ of \d+ detections\): poses that do not "
        r"match the images \(world-to-camera where camera-to-world is expected, quaternions in another order than x y z w", err)

    # Timestamps in microseconds, in both files: frames 66,667 s apart.
    micro = rs.write_tum(tmp_path / "micro", rs.flight(), WorldFrame("z", "x"), t0=1.0)
    _rewrite_poses(micro, lambda t, xyz, q: (t * 1e6, xyz, q))
    lines = (micro / "images.txt").read_text().splitlines()
    (micro / "images.txt").write_text("\n".join(
        [lines[0]] + [f"{float(ln.split()[0]) * 1e6!r} {ln.split()[1]}" for ln in lines[1:]]) + "\n")
    rc, err = replay(micro)
    assert f"companion replay: warning: {micro}: the frames are a median of " in err
    assert "microseconds or nanoseconds" in err


def test_reference_percentile_and_minimum_of_points_per_cell():
    """A point cloud's cell: nine points of a roof at 10 m and one noisy point at 30 m. max takes the
    noise; p90 interpolates between the 9th and 10th ranks (10 + 0.1 x 20 = 12 m), p50 is the median;
    a cell with fewer points than the minimum is left out."""
    north = np.r_[np.full(10, 0.5), 5.5]
    east = np.full(11, 0.5)
    height = np.r_[np.full(9, 10.0), 30.0, 4.0]
    def by_cell(stat, min_points=1):
        cells = bin_heights(north, east, height, 1.0, stat, min_points)
        return dict(zip(map(int, cells.ci), cells.height.tolist()))
    assert by_cell("max") == {0: 30.0, 5: 4.0}
    assert by_cell("p90") == pytest.approx({0: 12.0, 5: 4.0})
    assert by_cell("p50") == by_cell("median") == {0: 10.0, 5: 4.0}
    assert by_cell("p100") == by_cell("max") and by_cell("p0") == {0: 10.0, 5: 4.0}
    assert by_cell("p90", min_points=3) == pytest.approx({0: 12.0})
    for bad in ("p101", "px", "top", "p-1"):
        with pytest.raises(ValueError, match="pNN"):
            bin_heights(north, east, height, 1.0, bad)


def test_a_wrong_reference_statistic_is_refused_in_one_line(data, tmp_path, capsys):
    for args, words in ((["--reference-stat", "p120"], "--reference-stat: statistic must be mean, median, max or pNN"),
                        (["--reference-min-points", "0"], "--reference-min-points must be at least 1, got 0")):
        rc = cli.main(["replay", str(data["tum"]), "-o", str(tmp_path / "o"), "--no-progress",
                       "--reference", str(data["truth"]), *args])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and words in err, err


@pytest.mark.parametrize("meta, words", [
    ({"world_up": "q"}, "world_up"),
    ({"world_north": "z"}, "world_north 'z' must be perpendicular to world_up 'z'"),
    ({"scale_m_per_unit": "big"}, "'scale_m_per_unit' must be a number, got 'big'"),
])
def test_a_meta_yaml_error_names_the_file(tmp_path, capsys, meta, words):
    folder = rs.write_tum(tmp_path / "r", rs.flight(n_frames=5), WorldFrame("z", "x"))
    (folder / "meta.yaml").write_text(yaml.safe_dump({**yaml.safe_load((folder / "meta.yaml").read_text()), **meta}))
    rc = cli.main(["replay", str(folder), "-o", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith(f"companion replay: {folder / 'meta.yaml'}: ") and words in err, err


def test_a_geo_referenced_world_maps_about_its_origin(tmp_path, capsys):
    """UTM-like poses 5,000 km from their frame's origin: with the origin's coordinates in meta.yaml
    the recording maps as the local one does; with 'origin: auto' about its first pose; a wrong
    origin is refused in one line naming the file."""
    def utm(name, origin):
        folder = rs.write_tum(tmp_path / name, rs.flight(), WorldFrame("z", "x"))
        _rewrite_poses(folder, lambda t, xyz, q: (t, xyz + UTM_SHIFT, q))
        meta = yaml.safe_load((folder / "meta.yaml").read_text())
        (folder / "meta.yaml").write_text(yaml.safe_dump({**meta, "origin": origin}))
        return folder

    local = run_replay(open_recording(rs.write_tum(tmp_path / "local", rs.flight(), WorldFrame("z", "x"))),
                       CompanionConfig(), tmp_path / "out-local")
    fixed = run_replay(open_recording(utm("fixed", UTM_SHIFT.tolist())), CompanionConfig(), tmp_path / "out-fixed")
    same = compare(map_cells(fixed.grid), map_cells(local.grid))
    assert local.metrics["cells_mapped"] > 100 and same["coverage"] > 0.95 and same["rmse_m"] < 0.01
    folder = utm("auto", "auto")
    first = next(line.split() for line in (folder / "poses.txt").read_text().splitlines() if not line.startswith("#"))
    auto = open_recording(folder)
    assert auto.describe()["world"]["origin"] == pytest.approx([float(v) for v in first[1:4]])
    assert run_replay(auto, CompanionConfig(), tmp_path / "out-auto").metrics["cells_mapped"] > 100
    for name, bad in (("sky", "sky"), ("two", [1.0, 2.0]), ("text", ["x", 1, 2])):
        folder = utm(name, bad)
        rc = cli.main(["replay", str(folder), "-o", str(tmp_path / "o"), "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and f"{folder / 'meta.yaml'}: 'origin' must be three numbers" in err, err


def test_a_world_whose_up_is_any_direction_maps_as_the_level_one(tmp_path, data):
    """An SfM model's world, tilted 23 deg and turned about its up: meta.yaml gives world_up and
    world_north as directions (numbers). The replay maps the same cells as the axis-aligned
    recording, and the truth given in the tilted world's own coordinates (--reference-frame dataset)
    scores as the truth in the map's frame does."""
    tilt = euler_to_matrix(math.radians(17.0), math.radians(-15.0), math.radians(40.0))  # level world -> tilted
    level = WorldFrame("z", "x")
    tilted = WorldFrame(tuple(map(float, tilt[:, 2])), tuple(map(float, tilt[:, 0])))  # world up, world north
    assert math.degrees(math.acos(tilted.A[2] @ np.array([0.0, 0.0, -1.0]))) > 20.0  # far from any axis
    local = run_replay(open_recording(rs.write_tum(tmp_path / "level", rs.flight(), level)), CompanionConfig(),
                       tmp_path / "out-level")
    folder = rs.write_tum(tmp_path / "tilted", rs.flight(), tilted)
    assert yaml.safe_load((folder / "meta.yaml").read_text())["world_up"] == pytest.approx(list(tilted.up))
    recording = open_recording(folder)
    # The truth (flat ground, 0 m) written in the tilted world's coordinates.
    truth = np.loadtxt(data["truth"], delimiter=",", skiprows=1)
    ned = np.column_stack([truth[:, 0], truth[:, 1], -truth[:, 2]])
    np.savetxt(tmp_path / "truth_tilted.csv", tilted.position_from_ned(ned), delimiter=",", fmt="%.9f", header="x,y,z", comments="")
    reference = load_reference(tmp_path / "truth_tilted.csv", recording, frame="dataset")
    out = run_replay(recording, CompanionConfig(), tmp_path / "out-tilted", reference=reference)
    same = compare(map_cells(out.grid), map_cells(local.grid))
    print(f"tilted vs level world: {same['cells_compared']} cells, RMSE {same['rmse_m']:.2e} m, coverage {same['coverage']:.3f}")
    assert local.metrics["cells_mapped"] > MIN_CELLS and same["coverage"] > 0.95 and same["rmse_m"] < 0.01
    assert_close_to_truth(out.metrics)
    assert out.metrics["recording"]["world"]["up"] == pytest.approx(list(tilted.up))


def _write_ply(path, xyz, fmt):
    """A PLY point cloud of ``xyz`` (N, 3) with a colour per vertex, as photogrammetry tools write."""
    header = (f"ply\nformat {fmt} 1.0\ncomment written by the test\nelement vertex {len(xyz)}\n"
              "property double x\nproperty double y\nproperty float z\nproperty uchar red\nend_header\n")
    if fmt == "ascii":
        body = "".join(f"{float(x)!r} {float(y)!r} {float(z)!r} 200\n" for x, y, z in xyz).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        rows = np.zeros(len(xyz), dtype=[("x", order + "f8"), ("y", order + "f8"), ("z", order + "f4"), ("red", "u1")])
        rows["x"], rows["y"], rows["z"], rows["red"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], 200
        body = rows.tobytes()
    path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_a_ply_point_cloud_is_a_reference_like_its_csv(data, tmp_path, fmt, capsys):
    """The truth as a PLY (the photogrammetry tools' point cloud, with a colour property) judges the
    map exactly as the same points in a CSV do; a damaged PLY is refused in one line naming it."""
    rec = open_recording(data["tum"], CompanionConfig())
    csv = load_reference(data["truth"], rec)
    xyz = np.column_stack([csv.north_m, csv.east_m, csv.height_m])
    ply = load_reference(_write_ply(tmp_path / "truth.ply", xyz, fmt), rec)
    assert np.allclose(np.column_stack([ply.north_m, ply.east_m]), xyz[:, :2])
    assert np.allclose(ply.height_m, xyz[:, 2], atol=1e-5)  # float32 z
    grid = direct_map(CompanionConfig(), 0.05, 0.2)
    a = compare(map_cells(grid), bin_heights(csv.north_m, csv.east_m, csv.height_m, 1.0))
    b = compare(map_cells(grid), bin_heights(ply.north_m, ply.east_m, ply.height_m, 1.0))
    assert b["cells_compared"] == a["cells_compared"] and b["rmse_m"] == pytest.approx(a["rmse_m"], abs=1e-5)
    if fmt != "ascii":
        broken = tmp_path / "broken.ply"
        broken.write_bytes((tmp_path / "truth.ply").read_bytes()[:-7])
        rc = cli.main(["replay", str(data["tum"]), "-o", str(tmp_path / "o"), "--no-progress", "--reference", str(broken)])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith(f"companion replay: {broken}: truncated") and len(err.splitlines()) == 1, err


# --------------------------------------------------------------------------------------------
# COLMAP text model
# --------------------------------------------------------------------------------------------

SFM_WORLD = WorldFrame((0.12, -0.31, 0.94), (0.8, 0.55, 0.0), 0.5)  # an SfM model's tilted, half-scale world


def _truth_in(frame: WorldFrame, truth_csv) -> np.ndarray:
    """The true surface's points (the DSM grid) in ``frame``'s world coordinates."""
    truth = np.loadtxt(truth_csv, delimiter=",", skiprows=1)
    return frame.position_from_ned(np.column_stack([truth[:, 0], truth[:, 1], -truth[:, 2]]))


def test_a_colmap_model_replays_as_its_tum_twin_and_scores_against_its_own_points(data, tmp_path, capsys):
    """The flight written as COLMAP writes a model (world-to-camera, w-first quaternions, COLMAP's
    pixel centres, a PINHOLE camera, sparse/0, images named DJI_NNNN) in a tilted half-scale SfM
    world, its points3D the true surface: it is read as a recording without conversion, maps the
    same cells as the same flight in the TUM layout, and its points3D.txt is the reference (in the
    model's world without being told)."""
    colmap = rs.write_colmap(tmp_path / "colmap", rs.flight(), SFM_WORLD, points_xyz=_truth_in(SFM_WORLD, data["truth"]))
    tum = rs.write_tum(tmp_path / "tum", rs.flight(), SFM_WORLD)
    recording = open_recording(colmap)
    assert recording.kind == "colmap" and len(recording) == rs.N_FRAMES
    a = run_replay(recording, CompanionConfig(), tmp_path / "out-colmap")
    b = run_replay(open_recording(tum), CompanionConfig(), tmp_path / "out-tum")
    same = compare(map_cells(a.grid), map_cells(b.grid))
    print(f"COLMAP vs TUM: {same['cells_compared']} cells, RMSE {same['rmse_m']:.2e} m, coverage {same['coverage']:.3f}")
    assert a.metrics["cells_mapped"] > MIN_CELLS and same["coverage"] > 0.99 and same["rmse_m"] < 0.01
    rc = cli.main(["replay", str(colmap), "-o", str(tmp_path / "cli"), "--no-progress",
                   "--reference", str(colmap / "sparse" / "0" / "points3D.txt")])
    out = capsys.readouterr().out
    m = json.loads((tmp_path / "cli" / "metrics.json").read_text())
    print_figures("COLMAP model", m)
    assert rc == 0 and "reference: RMSE" in out and m["reference"]["frame"] == "dataset"
    assert_close_to_truth(m)


def test_an_export_to_colmap_replays_to_the_same_map(data, tmp_path):
    """``companion replay REC --export-colmap OUT`` of a --record folder, read back: the same cells,
    heights within SAME_MAP_TOL_M (its per-frame pose sigmas travel in pose_sigmas.txt)."""
    cfg = recording_config(data["companion"])
    own = run_replay(open_recording(data["companion"], cfg), cfg, tmp_path / "own")
    assert cli.main(["replay", str(data["companion"]), "--export-colmap", str(tmp_path / "colmap")]) == 0
    assert (tmp_path / "colmap" / "sparse" / "0" / "cameras.txt").read_text().splitlines()[-1].split()[1] == "OPENCV"
    back = open_recording(tmp_path / "colmap", cfg)
    assert back.kind == "colmap"
    again = run_replay(back, cfg, tmp_path / "back")
    ca, cb = map_cells(own.grid), map_cells(again.grid)
    diff = float(np.max(np.abs(ca.height - cb.height))) if np.array_equal(ca.keys, cb.keys) else math.inf
    print(f"own vs COLMAP export: {len(ca)} cells, max |height difference| {diff:.2e} m")
    assert len(ca) > MIN_CELLS and diff < SAME_MAP_TOL_M
    assert cli.main(["replay", str(data["companion"]), "--export-colmap", str(tmp_path / "colmap")]) == 2  # never overwrites


def test_colmap_cameras_become_opencv_pinholes_on_opencv_pixel_centres():
    """COLMAP's top-left pixel is centred at (0.5, 0.5), OpenCV's at (0, 0); radial models map onto
    OpenCV's coefficient order; a fisheye model is refused with the way out."""
    from companion.desk.recordings.colmap import camera_from_colmap

    c = camera_from_colmap("1 SIMPLE_RADIAL 640 480 500.0 320.5 240.5 -0.1".split())
    assert (c.fx, c.fy, c.cx, c.cy) == (500.0, 500.0, 320.0, 240.0)
    assert np.allclose(c.distortion, [-0.1, 0.0, 0.0, 0.0])
    c = camera_from_colmap("2 FULL_OPENCV 64 48 50 51 32 24 1 2 3 4 5 6 7 8".split())
    assert (c.fx, c.fy, c.cx, c.cy) == (50.0, 51.0, 31.5, 23.5) and np.allclose(c.distortion, [1, 2, 3, 4, 5, 6, 7, 8])
    with pytest.raises(ValueError, match="OPENCV_FISHEYE is not a pinhole model .*colmap image_undistorter"):
        camera_from_colmap("3 OPENCV_FISHEYE 640 480 500 500 320 240 0 0 0 0".split())
    with pytest.raises(ValueError, match="PINHOLE has 4 parameters, the line has 3"):
        camera_from_colmap("4 PINHOLE 640 480 500 320 240".split())


def test_colmap_mistakes_get_one_line_naming_the_file(data, tmp_path, capsys):
    """What a COLMAP model lacks is asked for by name; times from frame_interval_s serve as well as a
    timestamps.txt; an image of a second camera is left out and counted."""
    def replay(folder):
        rc = cli.main(["replay", str(folder), "-o", str(tmp_path / f"out-{folder.name}"), "--no-progress"])
        return rc, capsys.readouterr().err

    folder = rs.write_colmap(tmp_path / "nometa", rs.flight(n_frames=12), SFM_WORLD)
    (folder / "meta.yaml").unlink()
    rc, err = replay(folder)
    assert rc == 2 and f"{folder / 'meta.yaml'}: missing (a COLMAP world has no up direction, scale or times" in err

    folder = rs.write_colmap(tmp_path / "notimes", rs.flight(n_frames=12), SFM_WORLD)
    (folder / "timestamps.txt").unlink()
    rc, err = replay(folder)
    assert rc == 2 and (f"{folder / 'meta.yaml'}: a COLMAP model has no times: give 'frame_interval_s' (images in the "
                        f"order of their names) or a timestamps.txt beside it") in err

    folder = rs.write_colmap(tmp_path / "fisheye", rs.flight(n_frames=12), SFM_WORLD)
    cameras = folder / "sparse" / "0" / "cameras.txt"
    cameras.write_text("# a fisheye lens\n1 OPENCV_FISHEYE 640 480 500 500 320 240 0.1 0 0 0\n")
    rc, err = replay(folder)
    assert rc == 2 and f"{cameras}: line 2: camera model OPENCV_FISHEYE is not a pinhole model" in err

    folder = rs.write_colmap(tmp_path / "interval", rs.flight(), SFM_WORLD, interval_s=0.1)
    images = folder / "sparse" / "0" / "images.txt"
    lines = images.read_text().splitlines()
    lines[3] = lines[3].rsplit(" ", 2)[0] + " 2 " + lines[3].rsplit(" ", 1)[1]  # the second image on camera 2
    images.write_text("\n".join(lines) + "\n")
    rc, err = replay(folder)
    m = json.loads((tmp_path / "out-interval" / "metrics.json").read_text())
    assert rc == 0 and m["frames_listed"] == rs.N_FRAMES - 1 and m["cells_mapped"] > MIN_CELLS
    assert m["recording"]["bad_lines"] == {"images.txt": 1}
    assert "DJI_0002.png: camera 2, the recording's camera is 1 (one camera per recording)" in m["recording"]["problems"][0]


def test_a_colmap_model_starts_its_features_on_the_ground_its_points_show(data, tmp_path):
    """With 'origin: auto' the map's origin is the first camera, 15 m above the ground: a default
    ground altitude of 0 would start every feature at the camera's own height. Without
    ground_alt_m in meta.yaml the reader takes the median altitude of the model's points3D (said
    in the recording's notes); a ground_alt_m given wins; the map is as good as with the truth's."""
    points = _truth_in(SFM_WORLD, data["truth"])
    auto = open_recording(rs.write_colmap(tmp_path / "auto", rs.flight(), SFM_WORLD, points_xyz=points,
                                          meta_extra={"origin": "auto"}))
    first_camera_alt = -float(rs.flight().p_c[0][2])
    assert auto.ground_alt_m == pytest.approx(-first_camera_alt, abs=0.01)
    assert any("ground altitude" in p and "the median of its" in p for p in auto.stats.problems)
    given = open_recording(rs.write_colmap(tmp_path / "given", rs.flight(), SFM_WORLD, points_xyz=points,
                                           meta_extra={"origin": "auto", "ground_alt_m": -14.0}))
    assert given.ground_alt_m == -14.0
    m = run_replay(auto, CompanionConfig(), tmp_path / "out").metrics
    assert m["cells_mapped"] > MIN_CELLS
